#!/usr/bin/env python
"""How honest the flags are on walks with stretches the data do not fix.

For each seed it simulates a walk of the Manhattan world (``--views`` frames, 0.05 m a frame,
0.1 deg noise on the normals) whose frames 30-42 % of the way see only the lines along the
motion (pure translation along the only family seen: the motion along it is free) and whose
frames 65-72 % of the way see two lines (:func:`omni_sfm.synth.simulate.weak_stretches`), runs
``estimate_poses`` (the defaults) and counts, as :func:`omni_sfm.evaluate.flag_honesty` does
(the trusted frames aligned on themselves, as a user reads ``trajectory.tum``): the frames
posed, trusted and flagged, the trusted frames more than 1 deg or 2 % of the path off (a wrong
pose reported as fine: should be none), and the flagged frames within 0.2 deg and 0.2 % (good
poses flagged: should be few). Writes the record ``docs/benchmarks/eval_flags.json``; with
``--no-stretches`` the walks as simulated (long walks of few lines a frame, each line seen in
about 60 frames), record ``eval_flags_long.json``.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.eval.flags --seeds 0 1 2 3 4 5 6 7
    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.eval.flags --no-stretches \
        --views 1000 5000 --seeds 0
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from omni_sfm.estimate.pipeline import EstimationOptions, estimate_poses  # noqa: E402
from omni_sfm.evaluate import flag_honesty  # noqa: E402
from omni_sfm.synth.simulate import SimulationOptions, simulate, weak_stretches  # noqa: E402
from scripts.benchlib import add_log_arguments, write_log  # noqa: E402


def _run(seed: int, views: int, stretches: bool) -> list[object]:
    sim = simulate(SimulationOptions(num_views=views, world="manhattan",
                                     path_length=0.05 * (views - 1), noise_deg=0.1, seed=seed))
    along = (int(0.30 * views), int(0.42 * views))
    two = (int(0.65 * views), int(0.72 * views))
    tracks = weak_stretches(sim, along, two) if stretches else sim.tracks
    t0 = time.perf_counter()
    res = estimate_poses(tracks, EstimationOptions())
    wall = time.perf_counter() - t0
    g = sim.groundtruth
    h = flag_honesty(res.trajectory, g,
                     g.timestamps[[int(k) for k in res.report.frames_uncertain or {}]])
    share = 100.0 * h.flagged_fine / h.flagged if h.flagged else 0.0
    print(f"seed {seed}: {int(res.estimated.sum())} of {views} posed, {h.trusted} trusted, "
          f"{h.flagged} flagged; trusted off by > 1 deg or 2 %: {h.trusted_off}; flagged within "
          f"0.2 deg and 0.2 %: {h.flagged_fine} ({share:.1f} %); {wall:.1f} s", flush=True)
    return [views, seed, f"{int(res.estimated.sum())}/{views}", h.trusted, h.flagged, h.trusted_off,
            h.flagged_fine, share, wall]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--views", type=int, nargs="+", default=[400])
    ap.add_argument("--no-stretches", dest="stretches", action="store_false",
                    help="the walks as simulated, without the stretches")
    add_log_arguments(ap)
    args = ap.parse_args()
    rows = [_run(seed, views, args.stretches) for views in args.views for seed in args.seeds]
    off = sum(int(r[5]) for r in rows)  # type: ignore[call-overload]
    flagged = sum(int(r[4]) for r in rows)  # type: ignore[call-overload]
    fine = sum(int(r[6]) for r in rows)  # type: ignore[call-overload]
    what = ("with a stretch of lines along the walk only and one of two lines" if args.stretches
            else "of few lines a frame, each seen in about 60 frames")
    write_log(args, "eval_flags" if args.stretches else "eval_flags_long",
              f"Flags on walks {what}", [
        "frames", "seed", "posed", "trusted", "flagged", "trusted, off by > 1 deg or 2 %",
        "flagged, within 0.2 deg and 0.2 %", {"label": "flagged within: share (%)",
                                              "format": ".1f"},
        {"label": "time (s)", "format": ".1f"}], rows,
        headline=f"{len(rows)} Manhattan walks {what}: {off} trusted frames off by more than "
                 f"1 deg or 2 %; {fine} of {flagged} flagged frames within 0.2 deg and 0.2 %",
        notes="Manhattan walks, 0.05 m a frame, 0.1 deg noise" + (
            "; frames 30-42 % of the way see only the lines along the motion, frames 65-72 % "
            "two lines." if args.stretches else "."))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
