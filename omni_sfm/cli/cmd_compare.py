"""``omni-sfm compare``: line-based against point-based initializers on one sequence
(docs/comparison.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "compare",
        help="run line- and point-based initializers on the same frames against ground truth",
        description=(
            "Runs each initializer (plugins of the omni_sfm.initializers entry-point group: "
            "lines, five-point, colmap, upright-3pt) on the frames of PATH and writes "
            "OUTPUT/results.json (status, registered fraction, rotation error, ATE, RPE, time), "
            "OUTPUT/trajectories/NAME.tum, OUTPUT/report.md and plots (see docs/comparison.md). "
            "A failing initializer is recorded with its reason."
        ),
    )
    p.add_argument("--images", type=Path, required=True,
                   help="image folder (sorted by name; timestamp = index) or video file "
                        "(timestamps in seconds), as for init")
    p.add_argument("--camera", type=Path, default=None,
                   help="camera file (docs/cameras.md) or 'equirectangular' (built from the "
                        "frame size); without it, an MP4's spherical-video metadata, as for init")
    p.add_argument("--groundtruth", type=Path, required=True,
                   help="ground-truth trajectory, TUM (timestamps = frame indices)")
    p.add_argument("--output", "-o", type=Path, required=True, help="output folder")
    p.add_argument("--initializers", default=None,
                   help="comma-separated names (default: lines,five-point,colmap,upright-3pt)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUTPUT")
    p.add_argument("--no-plots", action="store_true", help="do not draw the PNG plots")
    p.add_argument("--verbose", action="store_true", help="show COLMAP's log on stderr")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from omni_sfm.compare import compare, parse_initializer_names, sequence_from_frames
    from omni_sfm.fileio import check_output_dir
    from omni_sfm.folders import CompareFolder
    from omni_sfm.lines.source_camera import camera_for_frames
    from omni_sfm.poses import read_tum

    names = parse_initializer_names(args.initializers)
    camera = camera_for_frames(
        args.camera, args.images,
        note=lambda text: print(f"omni-sfm: note: {text}", file=sys.stderr, flush=True))
    gt = read_tum(args.groundtruth)
    inputs = (args.images, args.groundtruth)
    check_output_dir(args.output, overwrite=args.overwrite, inputs=inputs)
    seq = sequence_from_frames(args.images, camera)
    options = {n: {"verbose": True} for n in names} if args.verbose else None
    res = compare(seq, gt, args.output, names, options=options, overwrite=args.overwrite,
                  plots=not args.no_plots, progress=sys.stderr.isatty(), inputs=inputs)
    for name, e in res.results.initializers.items():
        if e.status == "ok":
            print(f"{name}: ok, {100 * e.registered:.0f} % of frames, rotation max "
                  f"{e.rot_max_deg:.3f} deg, ATE {100 * (e.ate_rel or 0.0):.2f} % of the path, "
                  f"{e.time_s:.1f} s")
        else:
            print(f"{name}: failed: {e.reason or ''}")
    print(f"wrote {res.output / CompareFolder.RESULTS} and {CompareFolder.REPORT_MD}")
    return 0
