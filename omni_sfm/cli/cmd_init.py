"""``omni-sfm init``: initial camera poses of a sequence (docs/estimator.md, docs/formats.md).

Input modes form a mutually exclusive group; ``--tracks FILE`` (tracked line normals,
``tracks.json``) is the one implemented here. An image mode (``--images PATH --camera FILE``)
can be added to the group: it extracts and tracks lines into a :class:`LineTracks` and then
shares everything below it (:func:`omni_sfm.estimate.pipeline.estimate_poses` and
:func:`omni_sfm.estimate.pipeline.write_init_outputs`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "init",
        help="estimate initial camera poses from tracked lines",
        description="Estimate the pose of every frame from tracked straight lines (the "
                    "parallel-line method of Kawanishi et al. 2012, refined by a line bundle "
                    "adjustment). Writes OUTPUT/trajectory.tum (world_from_cam, world = first "
                    "estimated frame's camera, first-to-last distance = 1) and "
                    "OUTPUT/report.json, complete or not at all.",
    )
    method = p.add_mutually_exclusive_group()
    method.add_argument("--lines", action="store_true", default=True,
                        help="line-based initializer (the default and, in the core, the only "
                             "one)")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--tracks", type=Path,
                        help="tracked line normals, tracks.json (docs/formats.md)")
    p.add_argument("--output", "-o", type=Path, required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUTPUT")
    p.add_argument("--no-refine", action="store_true",
                   help="skip the bundle adjustment (the paper's method alone)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from omni_sfm.estimate.pipeline import EstimationOptions, estimate_poses, write_init_outputs
    from omni_sfm.fileio import atomic_output_dir, check_output_dir
    from omni_sfm.lines.tracks import read_tracks

    check_output_dir(args.output, overwrite=args.overwrite)
    tracks = read_tracks(args.tracks)
    result = estimate_poses(tracks, EstimationOptions(refine=not args.no_refine))
    with atomic_output_dir(args.output, overwrite=args.overwrite) as tmp:
        write_init_outputs(tmp, result, extra={"input": {"tracks": str(args.tracks)}})
    rep = result.report
    print(f"omni-sfm init: {rep['num_frames_estimated']}/{rep['num_frames']} frames, "
          f"{len(rep['parallel_family']['track_ids'])} parallel lines, "
          f"{len(rep['rejected_tracks'])} outlier tracks, residual "
          f"{rep['residuals']['rms_final_deg']:.3g} deg RMS -> {args.output}", file=sys.stderr)
    return 0
