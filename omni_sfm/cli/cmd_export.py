"""``omni-sfm export``: a poses folder in another tool's format (docs/formats.md, "Exports")."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from omni_sfm.export.pipeline import FORMATS


def add_parser(sub: Any) -> None:
    on = ", ".join(f for f, up in FORMATS.items() if up)
    p = sub.add_parser(
        "export",
        help="export an init, refine or dense folder for other tools (COLMAP, nerfstudio, "
             "LIMAP, TUM, KITTI)",
        description=(
            "Write the poses (and frames, 3D lines) of an init, refine or dense folder in the "
            "format another tool reads: tum, kitti (trajectories), colmap (COLMAP model and its "
            "images), nerfstudio (transforms.json: equirectangular or fisheye frames as they "
            "are, perspective views otherwise), limap (LIMAP line tracks beside the COLMAP "
            "model), colmap-rig (a COLMAP 4.2 rig of perspective views). --up turns the world "
            f"so that the vertical line family points +z, origin at the first camera (default "
            f"for {on}). See docs/formats.md, \"Exports\"."),
    )
    p.add_argument("--input", "-i", type=Path, required=True,
                   help="init, refine or dense output folder")
    p.add_argument("--format", "-f", required=True, choices=list(FORMATS), dest="fmt",
                   help="what to write")
    p.add_argument("--output", "-o", type=Path, required=True, help="output folder")
    up = p.add_mutually_exclusive_group()
    up.add_argument("--up", dest="up", action="store_true", default=None,
                    help=f"turn the world gravity-up (default for {on})")
    up.add_argument("--no-up", dest="up", action="store_false",
                    help="keep the folder's world (the first camera's frame)")
    p.add_argument("--up-axis", default=None, metavar="AXIS",
                   help="the camera axis that points up (x, -x, y, -y, z, -z; default: the "
                        "camera model's mount: +z hyperboloid, -y equirectangular and fisheye)")
    p.add_argument("--views", choices=["overlapping", "cubemap"], default="overlapping",
                   help="perspective views for colmap-rig and nerfstudio (default: overlapping, "
                        "pycolmap.panorama's layout)")
    p.add_argument("--images", type=Path, default=None,
                   help="image folder or video of the frames (default: the one INPUT records)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUTPUT")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from omni_sfm.export.pipeline import ExportOptions, run_export

    opts = ExportOptions(fmt=args.fmt, up=args.up, up_axis=args.up_axis, views=args.views)
    rep = run_export(args.input, args.output, opts, images=args.images,
                     overwrite=args.overwrite, progress=sys.stderr.isatty())
    world = "gravity-up (+z)" if rep.turned else "the first camera's frame"
    extra = f", {rep.num_images} images" if rep.num_images is not None else ""
    print(f"export: {rep.num_poses} poses as {args.fmt} into {args.output} ({world}"
          f"{extra}) in {rep.seconds:.1f} s")
    return 0
