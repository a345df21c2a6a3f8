"""``omni-sfm render``: rendered omnidirectional video with exact ground truth."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any


def add_parser(sub: Any) -> None:
    from omni_sfm.synth.effects import Body, VideoCodec
    from omni_sfm.synth.paths import Mount, Route
    from omni_sfm.synth.render import CameraKind, Preset, RenderOptions
    from omni_sfm.synth.scenes import SceneName

    d = RenderOptions()
    p = sub.add_parser(
        "render",
        help="render an omnidirectional video of a man-made scene with exact ground truth",
        description=(
            "Render a corridor, room, L-shaped office or cell house through an omnidirectional "
            "camera model along a 3D path (--route), clean or with the effects of real footage "
            "(--footage). "
            "Writes images/ (or video.mp4), camera.yaml, groundtruth.tum, scene.ply, "
            "lines3d.json and render.json into OUTPUT (see docs/rendering.md)."
        ),
    )
    p.add_argument("--output", "-o", type=Path, required=True, help="output folder")
    p.add_argument("--scene", default=d.scene.value, metavar="|".join(s.value for s in SceneName),
                   help="scene to render (default: %(default)s)")
    p.add_argument("--camera", default=d.camera,
                   metavar="|".join(k.value for k in CameraKind) + "|CAMERA.yaml",
                   help="camera kind or camera file (default: %(default)s)")
    p.add_argument("--preset", default=d.preset.value, choices=[x.value for x in Preset],
                   help="default size: small = 320x240 (equirect. 320x160), 12 frames; "
                        "paper = 800x600 (equirect. 1600x800), 200 frames (default: %(default)s)")
    p.add_argument("--frames", type=int, default=None, help="number of frames (default: preset)")
    p.add_argument("--width", type=int, default=None, help="image width in px (default: preset)")
    p.add_argument("--height", type=int, default=None,
                   help="image height in px (default: preset)")
    p.add_argument("--textured", action="store_true",
                   help="add surface texture so that point features exist")
    p.add_argument("--seed", type=int, default=d.seed,
                   help="seeds path, texture and noise (default: %(default)s)")
    p.add_argument("--video", action="store_true",
                   help="write video.mp4 instead of image frames")
    p.add_argument("--video-codec", choices=[c.value for c in VideoCodec],
                   default=None,
                   help="codec of video.mp4: mp4v (OpenCV's MPEG-4 Part 2) or h264 "
                        "(PyAV/libx264, yuv420p, as 360 cameras write) (default: "
                        f"{d.video_codec.value}; h264 with --footage)")
    p.add_argument("--video-crf", type=int, default=None,
                   help=f"H.264 constant rate factor 0..51, lower is better (default: "
                        f"{d.video_crf}, 23 with --footage)")
    p.add_argument("--fps", type=float, default=d.fps,
                   help="frame rate of video.mp4 and of the occluder's walk "
                        "(default: %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUTPUT")
    p.add_argument("--supersample", type=int, default=d.supersample,
                   help="S x S rays per pixel for anti-aliasing (default: %(default)s)")
    p.add_argument("--noise", type=float, default=d.noise_sigma,
                   help="read noise std-dev in grey levels (default: %(default)s)")
    p.add_argument("--route", choices=[r.value for r in Route], default=d.route.value,
                   help="how the camera moves (default: %(default)s)")
    p.add_argument("--path-length", type=float, default=None,
                   help="camera path length in metres (default: the route's, 1.5 for lane)")
    p.add_argument("--mount", choices=[m.value for m in Mount], default=None,
                   help="robot (camera +Z up) or handheld (-Y up); default: robot for the "
                        "hyperboloid camera, handheld otherwise")
    _add_effect_arguments(p, [b.value for b in Body])
    p.set_defaults(func=run)


def _add_effect_arguments(p: argparse.ArgumentParser, bodies: list[str]) -> None:
    g = p.add_argument_group(
        "real-footage effects (docs/rendering.md, 'Effects'; all off unless given or "
        "--footage)")
    g.add_argument("--footage", action="store_true",
                   help="realistic defaults: --motion-blur 0.5 --exposure-drift 0.3 "
                        "--flicker 0.02 --shot-noise 2 --vignetting 0.3, --jpeg 85 (H.264 at "
                        "CRF 23 with --video), --body robot (robot mount) or operator "
                        "(hand-held); the flags below override them")
    g.add_argument("--motion-blur", type=float, default=None, metavar="FRACTION",
                   help="exposure as a fraction of the frame interval, 0..1")
    g.add_argument("--exposure-drift", type=float, default=None, metavar="STOPS",
                   help="peak amplitude of the slow auto-exposure drift, stops")
    g.add_argument("--flicker", type=float, default=None, metavar="FRACTION",
                   help="peak relative frame-to-frame gain flicker, 0..0.5")
    g.add_argument("--shot-noise", type=float, default=None, metavar="LEVELS",
                   help="shot-noise std-dev at full white, grey levels (--noise: read noise)")
    g.add_argument("--jpeg", type=int, default=None, metavar="QUALITY",
                   help="write images/NNNNNN.jpg with this JPEG quality, 1..100")
    g.add_argument("--vignetting", type=float, default=None, metavar="FRACTION",
                   help="fraction of light lost at the image rim, 0..1")
    g.add_argument("--body", choices=bodies, default=None,
                   help="camera-fixed body in view")
    g.add_argument("--body-wobble", type=float, default=None, metavar="DEG",
                   help="the body wobbles about the camera centre by up to DEG per axis, "
                        "0..10 (a hand holding the camera)")
    g.add_argument("--seam", type=float, default=None, metavar="DEG",
                   help="stitching-seam misalignment in degrees (equirectangular only)")
    g.add_argument("--occluder", action="store_const", const=True, default=None,
                   help="a person walks past the camera")


_EFFECT_FLAGS = {"motion_blur": "motion_blur", "exposure_drift": "exposure_drift",
                 "flicker": "flicker", "shot_noise": "shot_noise", "jpeg": "jpeg_quality",
                 "vignetting": "vignetting", "body": "body", "body_wobble": "body_wobble_deg",
                 "seam": "seam_deg",
                 "occluder": "occluder"}


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from omni_sfm.synth.render import RenderOptions, footage_options, render_sequence

    opts = RenderOptions(
        scene=args.scene, camera=args.camera, preset=args.preset, frames=args.frames,
        width=args.width, height=args.height, textured=args.textured, seed=args.seed,
        video=args.video, supersample=args.supersample,
        noise_sigma=args.noise, route=args.route, path_length=args.path_length,
        mount=args.mount, fps=args.fps,
    )
    if args.footage:
        opts = footage_options(opts)
    given = {field: getattr(args, flag) for flag, field in _EFFECT_FLAGS.items()
             if getattr(args, flag) is not None}
    opts = replace(opts, effects=replace(opts.effects, **given))
    if args.video_codec is not None:
        opts = replace(opts, video_codec=args.video_codec)
    if args.video_crf is not None:
        opts = replace(opts, video_crf=args.video_crf)
    res = render_sequence(args.output, opts, overwrite=args.overwrite,
                          progress=sys.stderr.isatty())
    cam = res.camera
    print(f"rendered {res.num_frames} frames {cam.width}x{cam.height} ({cam.model}) into "
          f"{res.output} ({res.seconds_per_frame:.2f} s/frame, path "
          f"{res.groundtruth.path_length():.2f} m)")
    return 0
