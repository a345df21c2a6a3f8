"""``omni-sfm refine``: COLMAP refinement of the line-based poses (docs/colmap.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any


def add_parser(sub: Any) -> None:
    from omni_sfm.refine import RefineOptions
    from omni_sfm.refine.database import FEATURE_SOURCES

    d = RefineOptions()
    p = sub.add_parser(
        "refine",
        help="refine the line-based poses with COLMAP (pycolmap), never worse than its input",
        description=(
            "Point evidence from SIFT features and sequential matching (default) or KLT corner "
            "tracks through the ordered frames, inside the camera's valid mask; COLMAP's "
            "geometric verification (SIFT), triangulation with the line-based poses fixed, "
            "COLMAP's mapper for frames the init missed, bundle adjustment with the gauge "
            "fixed; frames it cannot improve keep their input pose. "
            "Writes sparse/, trajectory.tum, report.json, images_colmap/, camera_mask.png and "
            "database.db into OUTPUT, and carries camera.yaml, lines3d.json and mask.png over "
            "from INPUT for dense and view (see docs/colmap.md)."
        ),
    )
    p.add_argument("--input", "-i", type=Path, required=True,
                   help="init directory (sparse/, camera.yaml, trajectory.tum)")
    p.add_argument("--images", type=Path, default=None,
                   help="image folder or video the init was made from (default: the one INPUT "
                        "records)")
    p.add_argument("--output", "-o", type=Path, required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUTPUT")
    p.add_argument("--database", type=Path, default=None,
                   help="COLMAP database to use and keep (features and matches in it are "
                        "reused); default: a new OUTPUT/database.db")
    p.add_argument("--text", action="store_true", help="also write sparse/ as COLMAP text")
    p.add_argument("--features", choices=list(FEATURE_SOURCES), default=d.features,
                   help="point evidence: sift (SIFT and sequential matching, also for "
                        "unordered images) or klt (corners tracked through the frames in name "
                        "order: a video or an ordered folder; 3-4x faster than sift but less "
                        "accurate along a walk) (default: %(default)s)")
    p.add_argument("--overlap", type=int, default=d.overlap,
                   help="COLMAP's sequential overlap (quadratic): each frame is matched "
                        "with the frames 1, 2, 4, ... 2^(OVERLAP-1) ahead (default: "
                        "%(default)s)")
    p.add_argument("--max-features", type=int, default=d.max_features,
                   help="SIFT features per image (default: %(default)s)")
    p.add_argument("--no-guided-matching", action="store_true",
                   help="sift: match every pair with COLMAP's matcher and geometric "
                        "verification instead of along the input poses' epipolar geometry")
    p.add_argument("--max-corners", type=int, default=d.max_corners,
                   help="KLT corners tracked at most (default: %(default)s)")
    p.add_argument("--no-mapper", action="store_true",
                   help="do not try to register frames without an input pose (those the init "
                        "did not pose or flags as not fixed by the data)")
    p.add_argument("--mapper", choices=["incremental", "global"], default=d.mapper,
                   help="how the frames the init missed are registered: COLMAP's incremental "
                        "mapper from the triangulated model, or COLMAP's rotation averaging "
                        "and global positioning seeded by the line-based poses "
                        "(default: %(default)s)")
    p.add_argument("--adjustment", choices=["joint", "colmap"], default=d.adjustment,
                   help="joint: cameras, the init's 3D lines and the points adjusted together "
                        "(COLMAP's adjustment where the init has no line tracks); colmap: "
                        "COLMAP's point bundle adjustment alone (default: %(default)s)")
    p.add_argument("--threads", type=int, default=d.num_threads,
                   help="pycolmap threads, -1 = all cores (default: %(default)s)")
    p.add_argument("--verbose", action="store_true", help="show COLMAP's log on stderr")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from omni_sfm.errors import OmniSfmError
    from omni_sfm.refine import RefineOptions, refine

    for key in ("overlap", "max_features", "max_corners"):
        if getattr(args, key) <= 0:
            raise OmniSfmError(f"--{key.replace('_', '-')} must be positive, got "
                               f"{getattr(args, key)}")
    opts = RefineOptions(features=args.features, overlap=args.overlap,
                         max_features=args.max_features, max_corners=args.max_corners,
                         guided_matching=not args.no_guided_matching,
                         register_missing=not args.no_mapper, mapper=args.mapper,
                         num_threads=args.threads,
                         text=args.text, adjustment=args.adjustment)
    res = refine(args.input, args.images, args.output, opts, database=args.database,
                 overwrite=args.overwrite, progress=sys.stderr.isatty(), verbose=args.verbose)
    r = res.report
    n = len(res.input_trajectory)
    rounds = r.adjustment_rounds
    err = (f", mean reprojection error {rounds[0].mean_reprojection_error_before_px:.3f} -> "
           f"{rounds[-1].mean_reprojection_error_after_px:.3f} px" if rounds else "")
    if r.joint is not None:
        err = (f", adjusted with {r.joint.line_observations} line and "
               f"{r.joint.point_observations} point observations")
    print(f"refine: refined {r.refined_frames} of {n} input poses "
          f"({r.model.points} points, {r.model.observations} observations{err}) "
          f"into {res.output}")
    if r.mapper_added:
        flagged = r.frames.get("input_poses_uncertain", 0)
        print(f"COLMAP's mapper registered {len(r.mapper_added)} frames without an input pose"
              + (f" (the init flagged {flagged} as not fixed by the data)" if flagged else ""))
    if r.kept_input_for_all:
        print(f"kept every input pose: {r.kept_input_for_all}")
    elif r.kept_frames:
        print(f"kept the input pose of {len(r.kept_frames)} frames (see report.json)")
    times = ", ".join(f"{k} {v:.1f} s" for k, v in r.timings_s.items())
    print(f"time: {times}")
    return 0
