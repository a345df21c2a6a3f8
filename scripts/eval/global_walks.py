#!/usr/bin/env python
"""The global estimator on simulated walks, and its answer on the same tracks in reversed frame
order.

For each seed it simulates a 600-frame walk (``--world manhattan``: a corridor route with three
world directions; ``random``: the paper's random world, one parallel family, each line seen in
about 60 frames) with 0.1 deg noise, runs ``estimate_poses`` with ``estimator="global"``, and
prints frames posed, mean / max rotation error, ATE (% of the path), time, and the largest
difference between its forward and reversed-order poses.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.eval.global_walks --world manhattan \
        --seeds 20 21 22
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from typing import Any

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.pipeline import EstimationOptions, EstimationResult, estimate_poses
from omni_sfm.evaluate import match_reflection, trajectory_errors
from omni_sfm.lines.tracks import LineTracks, reversed_frames
from omni_sfm.poses import Trajectory
from omni_sfm.synth.simulate import SimulationOptions, simulate
from scripts.benchlib import add_log_arguments, write_log


def _sim(world: str, seed: int, views: int) -> SimulationOptions:
    if world == "manhattan":
        return SimulationOptions(num_views=views, world="manhattan",
                                 path_length=40.0 * views / 600, noise_deg=0.1, seed=seed)
    return SimulationOptions(num_views=views, num_parallel=40, num_other=40, noise_deg=0.1,
                             visible_frames=60, seed=seed)


def _row(name: str, res: EstimationResult, gt: Trajectory, dt: float) -> list[Any]:
    e = trajectory_errors(match_reflection(res.trajectory, gt), gt)
    return [name, f"{int(res.estimated.sum())}/{len(res.estimated)}", e.rot_mean_deg,
            e.rot_max_deg, 100 * e.ate_rel, dt]


def _run(tracks: LineTracks, estimator: str) -> tuple[EstimationResult, float]:
    t0 = time.perf_counter()
    res = estimate_poses(tracks, EstimationOptions(estimator=estimator))
    return res, time.perf_counter() - t0


def _headline(rows: list[list[Any]], world: str) -> str:
    """One line for the README: the global estimator's range over the walks."""
    g = [r for r in rows if r[1] == "global"]
    if not g:
        return ""
    posed = sum(r[2].split("/")[0] == r[2].split("/")[1] for r in g)
    return (f"{world} walks: `--estimator global` poses every frame of {posed} of {len(g)}, "
            f"rotation {min(r[3] for r in g):.3f}-{max(r[3] for r in g):.3f} deg mean, ATE "
            f"{min(r[5] for r in g):.3f}-{max(r[5] for r in g):.3f} %, "
            f"{min(r[6] for r in g):.1f}-{max(r[6] for r in g):.1f} s a walk")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", choices=["manhattan", "random"], default="manhattan")
    ap.add_argument("--seeds", type=int, nargs="+", default=[20, 21, 22])
    ap.add_argument("--views", type=int, default=600)
    add_log_arguments(ap)
    args = ap.parse_args()
    rows: list[list[Any]] = []
    for seed in args.seeds:
        sim = simulate(_sim(args.world, seed, args.views))
        tr, gt = sim.tracks, sim.groundtruth
        for name in ["global"]:
            try:
                res, dt = _run(tr, name)
            except OmniSfmError as exc:
                print(f"{args.world} seed {seed} {name}: error: {exc}")
                continue
            row = [f"{args.world} {seed}", *_row(name, res, gt, dt), ""]
            if name == "global":
                rev = replace(reversed_frames(tr), timestamps=tr.timestamps[::-1].copy())
                back, _ = _run(rev, name)
                d = trajectory_errors(match_reflection(back.trajectory, res.trajectory),
                                      res.trajectory)
                row[-1] = f"{d.rot_max_deg:.5f} deg, {100 * d.ate_rel:.5f} %"
            print(" | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row),
                  flush=True)
            rows.append(row)
    write_log(args, f"eval_global_{args.world}", f"The global estimator, {args.world} "
              f"walks of {args.views} frames", [
                  "walk, seed", "estimator", "posed", {"label": "rotation mean (deg)",
                                                      "format": ".3f"},
                  {"label": "rotation max (deg)", "format": ".3f"},
                  {"label": "ATE (%)", "format": ".4f"}, {"label": "time (s)", "format": ".1f"},
                  "reversed order differs by (rotation max, positions RMS)"], rows,
              headline=_headline(rows, args.world))


if __name__ == "__main__":
    main()
