"""``omni-sfm track``: online poses, frame by frame, no look-ahead (docs/track.md).

Reads frames from an image folder, a video file, a camera device (an integer, ``0``) or a
stream URL (anything with ``://``), all through :mod:`omni_sfm.frames`, and feeds them to
:class:`omni_sfm.pipelines.track.Tracker`; each pose is appended to ``OUTPUT/trajectory.tum``
as soon as it is known (:class:`omni_sfm.pipelines.track_output.TrackOutput`). Ctrl-C ends it
with everything so far written (exit code 130).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "track",
        help="online camera poses, frame by frame (for robots)",
        description="Estimate each frame's pose as soon as the frames so far give it (no "
                    "look-ahead): lines, a start from the first frames, then registration "
                    "from the lines already in 3D with local adjustments over a sliding "
                    "window (docs/track.md). Appends each pose to OUTPUT/trajectory.tum "
                    "(flushed per frame) and each frame's status to OUTPUT/frames.jsonl; after "
                    "a loss and a new start, to OUTPUT/trajectory_segment_<k>.tum (a new "
                    "world and scale). Ctrl-C ends it with everything so far written.")
    p.add_argument("--images", required=True, metavar="PATH",
                   help="image folder, video file, camera device index (0) or stream URL "
                        "(rtsp://..., file:///...)")
    p.add_argument("--camera", type=Path, default=None,
                   help="camera file (any format omni-sfm reads; docs/cameras.md), or "
                        "'equirectangular' (built from the frame size); without it, an MP4 "
                        "with spherical-video metadata and a 2:1 frame is read as "
                        "equirectangular")
    p.add_argument("--output", "-o", type=Path, required=True, help="output folder")
    p.add_argument("--mask", type=Path, help="mask image: nonzero where pixels may be used")
    p.add_argument("--stream", action="store_true",
                   help="also write one JSON line per frame on stdout (frame, timestamp, "
                        "status, world, position, quaternion_xyzw, lines, latency_ms, reason); "
                        "the summary then goes to stderr")
    p.add_argument("--frames", type=int, default=None, metavar="N",
                   help="stop after N frames (default: until the input ends)")
    p.add_argument("--offline", action="store_true",
                   help="at the end (the input's end, --frames or Ctrl-C), also run the "
                        "offline `init --lines` on the same frames into OUTPUT/offline/ (every "
                        "frame with the whole run's evidence; what `omni-sfm init` gives on "
                        "them); a device or stream's frames are kept in OUTPUT/frames/ for it")
    p.add_argument("--overwrite", action="store_true", help="write into a non-empty OUTPUT")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from omni_sfm.errors import OmniSfmError
    from omni_sfm.estimate.online import Status
    from omni_sfm.fileio import check_output_dir
    from omni_sfm.frames import is_stream, read_frames, read_mask, read_stream
    from omni_sfm.lines.source_camera import camera_for_frames
    from omni_sfm.pipelines.track import Tracker
    from omni_sfm.pipelines.track_output import TrackOutput

    if args.frames is not None and args.frames < 1:
        raise OmniSfmError(f"--frames must be at least 1, got {args.frames}")
    spec = str(args.images)
    stream = is_stream(spec)
    camera = camera_for_frames(
        args.camera, spec,
        note=lambda text: print(f"omni-sfm: note: {text}", file=sys.stderr, flush=True))
    size = (camera.width, camera.height)
    mask = read_mask(args.mask, size) if args.mask is not None else None
    check_output_dir(args.output, overwrite=args.overwrite,
                     inputs=() if stream else (Path(spec),))
    said = camera.frame_size_mismatch
    source = read_stream(spec, size, said) if stream else \
        read_frames(Path(spec), size=size, size_error=said)
    tracker = Tracker(camera, mask=mask)
    counts = {s: 0 for s in Status}
    latency: list[float] = []
    interrupted = False
    kept = args.output / "frames" if args.offline and stream else None
    with TrackOutput(args.output) as out:
        if kept is not None:
            kept.mkdir(exist_ok=True)
        try:
            for frame in source:
                pose = tracker.add_frame(frame.image, frame.timestamp)
                if kept is not None:
                    cv2.imwrite(str(kept / f"{len(latency):06d}.png"), frame.image)
                out.write(pose)
                counts[pose.status] += 1
                latency.append(pose.latency_ms)
                if args.stream:
                    print(json.dumps(pose.to_json()), flush=True)
                if args.frames is not None and len(latency) >= args.frames:
                    break
        except KeyboardInterrupt:
            interrupted = True
    if not latency:
        raise OmniSfmError(f"{spec}: no frame could be read")
    lat = np.asarray(latency)
    text = (f"track: {len(lat)} frames{' (interrupted)' if interrupted else ''}: "
            + ", ".join(f"{n} {s}" for s, n in counts.items() if n)
            + f"; {out.poses} poses -> {out.path(0)}"
            + (" and trajectory_segment_*.tum" if counts[Status.RELOCALISED] else "")
            + f"; latency median {np.median(lat):.1f} ms, 95th percentile "
              f"{np.percentile(lat, 95):.1f} ms")
    print(text, file=sys.stderr if args.stream else sys.stdout, flush=True)
    if args.offline:
        _offline(args, kept or Path(spec), len(lat), camera)
    return 130 if interrupted else 0


def _offline(args: argparse.Namespace, images: Path, frames: int, camera: Any) -> None:
    """``init --lines`` on the first ``frames`` frames of ``images`` into OUTPUT/offline."""
    from omni_sfm.folders import InitFolder
    from omni_sfm.pipelines.init import InitOptions, init_from_images

    where = args.output / "offline"
    res = init_from_images(images, camera, where, InitOptions(end=frames, progress=False),
                           mask=args.mask, overwrite=True,
                           warn=lambda w: print(f"offline: warning: {w}", file=sys.stderr))
    print(f"offline: {len(res.image_names)} of {frames} frames -> {where / InitFolder.TRAJECTORY}",
          file=sys.stderr if args.stream else sys.stdout, flush=True)
