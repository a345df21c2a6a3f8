#!/usr/bin/env python
"""Speed of the estimator on the paper's real case: 200 views, 10 parallel + 5 other lines.

The paper (Core i7 975, 3.33 GHz) reports 35 ms for parallel-line detection, 2 ms for the
rotation and 16 ms for the translation of all views. This prints our medians per stage over
seeded simulations (0.1 deg noise on the normals), plus the line bundle adjustment the paper
does not have, and the accuracy against the oracle as a sanity check.

    .venv/bin/python -m scripts.bench.backend [--trials 9] [--noise-deg 0.1]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys

import numpy as np

from omni_sfm.estimate.pipeline import estimate_poses
from omni_sfm.evaluate import match_reflection, trajectory_errors
from omni_sfm.synth.simulate import SimulationOptions, simulate
from scripts.benchlib import add_log_arguments, write_log

PAPER_MS = {"parallel_lines": 35.0, "rotation": 2.0, "translation": 16.0}
STAGES = ("parallel_lines", "rotation", "translation", "refinement", "total")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=9)
    ap.add_argument("--noise-deg", type=float, default=0.1)
    add_log_arguments(ap)
    args = ap.parse_args()
    # warm-up (imports, caches) not counted
    estimate_poses(simulate(SimulationOptions(num_views=200, num_parallel=10, num_other=5,
                                              noise_deg=args.noise_deg, seed=999)).tracks)
    times: dict[str, list[float]] = {s: [] for s in STAGES}
    errs = []
    for seed in range(args.trials):
        sim = simulate(SimulationOptions(num_views=200, num_parallel=10, num_other=5,
                                         noise_deg=args.noise_deg, seed=seed))
        res = estimate_poses(sim.tracks)
        for s in STAGES:
            times[s].append(float(res.timings_ms.get(s, 0.0)))
        e = trajectory_errors(match_reflection(res.trajectory, sim.groundtruth), sim.groundtruth)
        errs.append((e.rot_mean_deg, float(e.paper_trans.mean())))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"# 200 views, 10 parallel + 5 other lines, noise {args.noise_deg} deg, "
          f"{args.trials} trials; {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, load average {load:.1f}")
    print(f"{'stage':<16}{'median ms':>12}{'min ms':>10}{'paper ms':>10}")
    rows = []
    for s in STAGES:
        a = np.asarray(times[s])
        paper = f"{PAPER_MS[s]:.0f}" if s in PAPER_MS else "-"
        print(f"{s:<16}{np.median(a):>12.1f}{a.min():>10.1f}{paper:>10}")
        rows.append([s, float(np.median(a)), float(a.min()), PAPER_MS.get(s)])
    r = np.asarray(errs)
    print(f"refined mean errors: rotation {r[:, 0].mean():.4f} deg, translation (paper's "
          f"definition) {r[:, 1].mean():.5f}")
    write_log(args, "bench_backend", "Estimator stages on the paper's case (200 views)",
              ["stage", {"label": "median ms", "format": ".1f"},
               {"label": "min ms", "format": ".1f"}, {"label": "paper ms", "format": ".0f"}],
              rows,
              headline="parallel lines {rows[0][1]} ms (paper: 35), rotation {rows[1][1]} ms "
                       "(paper: 2), translation {rows[2][1]} ms (paper: 16)",
              notes=f"{args.trials} seeded trials, {args.noise_deg} deg noise on the normals; "
                    f"refined mean errors {r[:, 0].mean():.4f} deg rotation, "
                    f"{r[:, 1].mean():.5f} translation (paper's definition).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
