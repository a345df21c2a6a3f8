"""``omni-sfm render``: rendered omnidirectional video with exact ground truth."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any


def add_parser(sub: Any) -> None:
    from omni_sfm.synth.paths import Mount
    from omni_sfm.synth.render import CameraKind, Preset, RenderOptions
    from omni_sfm.synth.scenes import SceneName

    d = RenderOptions()
    p = sub.add_parser(
        "render",
        help="render an omnidirectional video of a man-made scene with exact ground truth",
        description=(
            "Render a corridor or room through an omnidirectional camera model along a smooth "
            "3D path. Writes images/ (or video.mp4), camera.yaml, groundtruth.tum, scene.ply, "
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
    p.add_argument("--video", action="store_true", help="write video.mp4 instead of PNG frames")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUTPUT")
    p.add_argument("--supersample", type=int, default=d.supersample,
                   help="S x S rays per pixel for anti-aliasing (default: %(default)s)")
    p.add_argument("--noise", type=float, default=d.noise_sigma,
                   help="sensor noise std-dev in grey levels (default: %(default)s)")
    p.add_argument("--path-length", type=float, default=d.path_length,
                   help="camera path length in metres (default: %(default)s)")
    p.add_argument("--mount", choices=[m.value for m in Mount], default=None,
                   help="robot (camera +Z up) or handheld (-Y up); default: robot for the "
                        "hyperboloid camera, handheld otherwise")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from omni_sfm.synth.render import RenderOptions, render_sequence

    opts = RenderOptions(
        scene=args.scene, camera=args.camera, preset=args.preset, frames=args.frames,
        width=args.width, height=args.height, textured=args.textured, seed=args.seed,
        video=args.video, supersample=args.supersample, noise_sigma=args.noise,
        path_length=args.path_length, mount=args.mount,
    )
    res = render_sequence(args.output, opts, overwrite=args.overwrite,
                          progress=sys.stderr.isatty())
    cam = res.camera
    print(f"rendered {res.num_frames} frames {cam.width}x{cam.height} ({cam.model}) into "
          f"{res.output} ({res.seconds_per_frame:.2f} s/frame, path "
          f"{res.groundtruth.path_length():.2f} m)")
    return 0
