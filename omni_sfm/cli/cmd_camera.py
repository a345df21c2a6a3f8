"""``omni-sfm camera``: show a camera file's summary, or convert it to omni-sfm's YAML."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

FORMATS = (
    "omni-sfm camera YAML, OpenCV FileStorage with cv2.omnidir results (K, D, xi), "
    "Kalibr camchain, OCamCalib calib_results.txt, COLMAP cameras.txt"
)


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "camera",
        help="inspect or convert a camera calibration file",
        description=f"Camera files omni-sfm reads unchanged: {FORMATS} (see docs/cameras.md).",
    )
    csub = p.add_subparsers(dest="camera_command", metavar="ACTION", required=True,
                            parser_class=type(p))
    show = csub.add_parser("show", help="print the model, parameters and field of view")
    show.add_argument("file", type=Path, help="camera file")
    show.set_defaults(func=run_show)
    conv = csub.add_parser("convert", help="write the camera as omni-sfm camera YAML")
    conv.add_argument("file", type=Path, help="camera file")
    conv.add_argument("-o", "--output", type=Path, required=True, help="camera YAML to write")
    conv.add_argument("--overwrite", action="store_true", help="replace an existing OUTPUT")
    conv.set_defaults(func=run_convert)


def run_show(args: argparse.Namespace) -> int:
    from omni_sfm.cameras import load_camera

    summary = load_camera(args.file).summary()
    print(f"file: {args.file}")
    print(summary)
    return 0


def run_convert(args: argparse.Namespace) -> int:
    from omni_sfm.cameras import load_camera, write_camera_yaml
    from omni_sfm.errors import OmniSfmError

    cam = load_camera(args.file)
    out: Path = args.output
    if out.exists() and not args.overwrite:
        raise OmniSfmError(f"{out}: output exists (pass --overwrite to replace it)")
    if out.is_dir():
        raise OmniSfmError(f"{out}: output is a directory")
    write_camera_yaml(out, cam)
    print(f"wrote {out} (model {cam.model}, {cam.width} x {cam.height} px)")
    return 0
