"""``omni-sfm dense``: dense point cloud and mesh from known poses (docs/dense.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from omni_sfm.errors import OmniSfmError


def _known_distance(text: str) -> float:
    """``first-last=D`` -> D."""
    key, sep, value = text.partition("=")
    if not sep or key.strip() != "first-last":
        raise argparse.ArgumentTypeError(f"expected first-last=D, got {text!r}")
    try:
        return float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number after '=', got {value!r}") from None


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "dense",
        help="dense point cloud and mesh from the estimated poses (stereo + TSDF fusion)",
        description=(
            "Depth for keyframes by semi-global matching on rectified virtual pinhole views of "
            "neighbouring frames, checked against a third view, fused with Open3D into "
            "OUTPUT/dense.ply and OUTPUT/mesh.ply (see docs/dense.md). Units: the poses' "
            "(arbitrary for line-based poses) unless --known-distance or --camera-height."),
    )
    p.add_argument("--input", "-i", type=Path, required=True,
                   help="poses folder (output of init or refine: trajectory.tum, camera.yaml)")
    p.add_argument("--images", type=Path, default=None,
                   help="image folder or video of the frames (default: the one INPUT records)")
    p.add_argument("--output", "-o", type=Path, required=True, help="output folder")
    p.add_argument("--camera", type=Path, default=None,
                   help="camera file, or 'equirectangular' (built from the frame size) "
                        "(default: INPUT/camera.yaml)")
    p.add_argument("--keyframe-step", type=int, default=None,
                   help="frames between keyframes (default: half the stereo baseline's offset)")
    scale = p.add_mutually_exclusive_group()
    scale.add_argument("--known-distance", type=_known_distance, default=None,
                       metavar="first-last=D",
                       help="distance between the first and last camera centres (e.g. metres)")
    scale.add_argument("--camera-height", type=float, default=None, metavar="H",
                       help="camera height above the floor (e.g. metres)")
    p.add_argument("--resolution-scale", type=float, default=1.0,
                   help="virtual-view pixels per camera pixel; < 1 is faster (default: 1)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUTPUT")
    p.add_argument("--verbose", action="store_true", help="show Open3D's and COLMAP's log")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from omni_sfm.dense import DenseOptions, run_dense

    for flag in ("resolution_scale", "camera_height", "known_distance"):
        val = getattr(args, flag)
        if val is not None and not val > 0:
            raise OmniSfmError(f"--{flag.replace('_', '-')} must be > 0, got {val}")
    if args.keyframe_step is not None and args.keyframe_step < 1:
        raise OmniSfmError(f"--keyframe-step must be >= 1, got {args.keyframe_step}")
    opts = DenseOptions(keyframe_step=args.keyframe_step, known_distance=args.known_distance,
                        camera_height=args.camera_height, resolution_scale=args.resolution_scale)
    from omni_sfm.libs import library_logging

    with library_logging(args.verbose):
        res = run_dense(args.input, args.images, args.output, opts, camera_file=args.camera,
                        overwrite=args.overwrite, progress=sys.stderr.isatty())
    r = res.report
    sec = r.seconds
    print(f"dense: {r.num_points} points, {r.num_triangles} triangles from "
          f"{r.num_keyframes} keyframes into {args.output} ({r.scale.unit}; median "
          f"depth {r.median_depth:.3g}, voxel {r.voxel_size:.3g}); depth on "
          f"{100 * r.depth_share['median']:.0f}% of a keyframe's view pixels (median); "
          f"{sec['depth_per_keyframe']:.2f} s depth + {sec['fusion_per_keyframe']:.2f} s fusion "
          "per keyframe")
    for w in r.warnings:
        print(f"warning: {w}", file=sys.stderr)
    return 0
