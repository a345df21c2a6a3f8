#!/usr/bin/env python
"""The every-frame issue's sparse case: long simulated sequences whose lines are each seen in
about 60 frames, with only a handful of lines per frame, against the maximum-likelihood oracle.

For each seed it simulates 600 frames (``--views``) of the paper's random world with
``--parallel`` + ``--other`` lines (40 + 40: 4 to 13 lines per frame, median 8), each seen in
about ``--visible`` consecutive frames, 0.1 deg noise on the normals, and runs
``estimate_poses`` on the tracks. It prints the lines per frame, the frames estimated (main
trajectory and segments), the main trajectory's errors (mean / max rotation error relative to
the first frame, the paper's translation error, ATE in per cent of the path), and the oracle's
on the same frames (:func:`omni_sfm.estimate.bundle.oracle`: the same least squares started from
the ground truth), and their ratio (the issue asks for at most 2), and how honest the flags
are: the frames flagged, those of them within 0.2 deg and 0.2 % of the path, and the frames
off by more than 1 deg or 2 % that are not flagged.

``--polish N`` also runs the line bundle adjustment again from the estimate, for N
Levenberg-Marquardt iterations without outlier rejection, and prints its RMS residual and
errors: it separates a wrong basin (the cost stays above the oracle's) from slow convergence
(the cost and the errors reach the oracle's with enough iterations).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.eval.sparse [--seeds 0 1 2] [--polish 1000]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.bundle import BundleOptions, bundle_adjust, oracle
from omni_sfm.estimate.pipeline import EstimationOptions, EstimationResult, estimate_poses
from omni_sfm.evaluate import flag_honesty, match_reflection, trajectory_errors
from omni_sfm.poses import Trajectory
from omni_sfm.synth.simulate import Simulation, SimulationOptions, simulate
from scripts.benchlib import add_log_arguments, write_log


def _errors(traj: Trajectory, sim: Simulation) -> tuple[float, float, float, float]:
    """(mean rotation error, max rotation error, mean paper translation error, ATE %)."""
    g = sim.groundtruth
    e = trajectory_errors(match_reflection(traj, g), g)
    return e.rot_mean_deg, e.rot_max_deg, float(e.paper_trans.mean()), 100 * e.ate_rel


def _flag_counts(res: EstimationResult, sim: Simulation) -> tuple[int, int, int]:
    """(frames flagged, of them within 0.2 deg and 0.2 % of the path, frames off by more than
    1 deg or 2 % not flagged), as :func:`omni_sfm.evaluate.flag_honesty` counts them: the
    frames not flagged aligned on themselves as a user reads ``trajectory.tum``."""
    g = sim.groundtruth
    flagged = [g.timestamps[int(k)] for k in res.report.frames_uncertain or {}]
    h = flag_honesty(res.trajectory, g, flagged)
    return h.flagged, h.flagged_fine, h.trusted_off


def _fmt(e: tuple[float, float, float, float]) -> str:
    return f"rotation {e[0]:.3f} / {e[1]:.3f} deg, translation {e[2]:.4f}, ATE {e[3]:.3f} %"


def _run(seed: int, args: argparse.Namespace) -> tuple[list[object], float, bool] | None:
    """Print the seed's figures; its row of the record, its larger ratio to the oracle and
    whether every frame is in the main trajectory (None when the estimator raised)."""
    sim = simulate(SimulationOptions(num_views=args.views, num_parallel=args.parallel,
                                     num_other=args.other, noise_deg=args.noise_deg,
                                     visible_frames=args.visible, seed=seed))
    tr, g = sim.tracks, sim.groundtruth
    per = tr.visibility().sum(0)
    print(f"seed {seed}: {tr.num_tracks} lines, {per.min()}-{per.max()} per frame (median "
          f"{np.median(per):.0f}), {(per >= 4).sum()} frames see 4 or more")
    t0 = time.perf_counter()
    try:
        res = estimate_poses(tr, EstimationOptions(estimator=args.estimator))
    except OmniSfmError as exc:
        print(f"  error: {exc}")
        return None
    wall = time.perf_counter() - t0
    in_segs = sum(int(s.frames.sum()) for s in res.segments)
    est = res.estimated
    print(f"  estimated: {int(est.sum())} in the main trajectory, {in_segs} in "
          f"{len(res.segments)} segments ({100 * (est.sum() + in_segs) / tr.num_frames:.0f} %), "
          f"{wall:.1f} s")
    e = _errors(res.trajectory, sim)
    flagged, flagged_good, unflagged_off = _flag_counts(res, sim)
    print(f"  flags: {flagged} frames flagged, {flagged_good} of them within 0.2 deg and "
          f"0.2 % of the path; {unflagged_off} frames off by more than 1 deg or 2 % unflagged")
    o = oracle(tr, g.rotations, g.positions, sim.line_directions, sim.line_points)
    on = o.frames & est
    eo = _errors(Trajectory(g.timestamps[on], o.rotations[on], o.positions[on]), sim)
    print(f"  main:   {_fmt(e)}, RMS residual {res.residual_rms_final_deg:.4f} deg")
    print(f"  oracle: {_fmt(eo)}, RMS residual {o.rms_final_deg:.4f} deg (same frames)")
    print(f"  ratio:  rotation {e[0] / eo[0]:.1f}x, translation {e[2] / eo[2]:.1f}x")
    row: list[object] = [
        seed, f"{int(est.sum())}" + (f" + {in_segs} in segments" if in_segs else ""),
        f"{e[0]:.3f} / {e[1]:.3f}", f"{eo[0]:.3f} / {eo[1]:.3f}",
        f"{e[0] / eo[0]:.1f}x, {e[2] / eo[2]:.1f}x",
        f"{res.residual_rms_final_deg:.4f} / {o.rms_final_deg:.4f}", flagged, flagged_good,
        unflagged_off, wall]
    ratio = max(e[0] / eo[0], e[2] / eo[2])
    if args.polish:
        F = tr.num_frames
        R = np.full((F, 3, 3), np.nan)
        c = np.full((F, 3), np.nan)
        R[est], c[est] = res.trajectory.rotations, res.trajectory.positions
        t0 = time.perf_counter()
        b = bundle_adjust(tr, R, c, res.line_directions, res.line_points,
                          options=BundleOptions(reject_outliers=False,
                                                max_iterations=args.polish, tolerance=1e-14))
        ep = _errors(Trajectory(g.timestamps[b.frames], b.rotations[b.frames],
                                b.positions[b.frames]), sim)
        print(f"  polished ({args.polish} iterations, {time.perf_counter() - t0:.1f} s): "
              f"{_fmt(ep)}, RMS residual {b.rms_final_deg:.4f} deg")
    return row, ratio, bool(est.all())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--views", type=int, default=600)
    ap.add_argument("--parallel", type=int, default=40)
    ap.add_argument("--other", type=int, default=40)
    ap.add_argument("--visible", type=int, default=60)
    ap.add_argument("--noise-deg", type=float, default=0.1)
    ap.add_argument("--estimator", choices=["auto", "paper", "global"], default="global",
                    help="EstimationOptions.estimator (default global: no window covers these "
                         "tracks)")
    ap.add_argument("--polish", type=int, default=0,
                    help="also adjust again from the estimate for this many LM iterations")
    add_log_arguments(ap)
    args = ap.parse_args()
    print(f"# sparse tracks against the oracle; {os.cpu_count()} CPUs, "
          f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}")
    runs = [r for r in (_run(seed, args) for seed in args.seeds) if r is not None]
    within = sum(r[1] <= 2 for r in runs)
    worst = max((r[1] for r in runs), default=float("nan"))
    every = sum(r[2] for r in runs)
    name = f"eval_sparse_{args.estimator}"
    write_log(args, name, f"Sparse tracks against the oracle ({args.estimator} estimator)", [
        "seed", "frames in the main trajectory", "main: rotation mean / max (deg)",
        "oracle, same frames (deg)", "ratio: rotation, translation",
        "RMS residual: main / oracle (deg)", "flagged", "flagged, within 0.2 deg and 0.2 %",
        "off by > 1 deg or 2 %, not flagged", {"label": "time (s)", "format": ".1f"}],
        [r[0] for r in runs],
        headline=f"{args.views} simulated frames, 4-13 lines a frame: {every} of "
                 f"{len(args.seeds)} seeds pose every frame in one trajectory, {within} within "
                 f"2x of the oracle's errors (worst {worst:.1f}x)",
        notes=f"{args.views} frames, {args.parallel} + {args.other} lines each seen in about "
              f"{args.visible} frames, {args.noise_deg} deg noise on the normals.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
