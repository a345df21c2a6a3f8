"""``omni-sfm camera``: show a camera file's summary, or convert it to omni-sfm's YAML."""

from __future__ import annotations

import argparse
import sys
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
    _camera_args(show)
    show.set_defaults(func=run_show)
    conv = csub.add_parser("convert", help="write the camera as omni-sfm camera YAML")
    _camera_args(conv)
    conv.add_argument("-o", "--output", type=Path, required=True, help="camera YAML to write")
    conv.add_argument("--overwrite", action="store_true", help="replace an existing OUTPUT")
    conv.set_defaults(func=run_convert)


def _camera_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", type=Path, nargs="?", default=None,
                   help="camera file, or 'equirectangular' (with --images: built from the frame "
                        "size); omitted: the camera --images' spherical-video metadata gives")
    p.add_argument("--images", type=Path, default=None, metavar="PATH",
                   help="the frames (folder or video) the camera is for, as init reads them")
    p.add_argument("--lens", type=int, default=None, metavar="N",
                   help="only camera N (from 0) of a Kalibr camchain of several cameras, or "
                        "lens N of a 'rig' camera file (read whole: one rig camera)")


def _camera(args: argparse.Namespace) -> Any:
    """The camera of ``file`` (and ``--images``), as init would read it."""
    from omni_sfm.cameras import load_camera
    from omni_sfm.errors import OmniSfmError
    from omni_sfm.lines.source_camera import camera_for_frames, is_keyword

    if args.file is None and args.images is None:
        raise OmniSfmError("give a camera file, or --images PATH (with 'equirectangular' or a "
                           "video with spherical-video metadata)")
    camera = args.file
    if args.lens is not None:
        if camera is None or is_keyword(camera):
            raise OmniSfmError("--lens selects one camera of a camera file: give the file")
        camera = load_camera(camera, lens=args.lens)
    return camera_for_frames(
        camera, args.images,
        note=lambda text: print(f"omni-sfm: note: {text}", file=sys.stderr, flush=True))


def run_show(args: argparse.Namespace) -> int:
    summary = _camera(args).summary()
    print(f"file: {args.file if args.file is not None else args.images}")
    print(summary)
    return 0


def run_convert(args: argparse.Namespace) -> int:
    from omni_sfm.cameras import write_camera_yaml
    from omni_sfm.errors import OmniSfmError

    cam = _camera(args)
    out: Path = args.output
    if out.exists() and not args.overwrite:
        raise OmniSfmError(f"{out}: output exists (pass --overwrite to replace it)")
    if out.is_dir():
        raise OmniSfmError(f"{out}: output is a directory")
    write_camera_yaml(out, cam)
    print(f"wrote {out} (model {cam.model}, {cam.width} x {cam.height} px)")
    return 0
