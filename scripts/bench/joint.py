"""Benchmark the joint adjustment of lines and points alone, on work folders of
``scripts/bench/refine.py`` (each its ``init_lines``, ``database_sift.db`` and
``render/groundtruth.tum``): COLMAP's triangulation on the init's poses (as ``refine`` does
it), then one Levenberg-Marquardt step with the cameras' system formed and factored against
conjugate gradients (time, agreement), then the whole adjustment (time, iterations, errors
against the ground truth); with ``--repeat N``, N rounds of the whole adjustments, the folders
alternated within each round, and the median time a posed frame of each (this machine's
run-to-run spread is 10-15 %). Freed memory is kept for reuse as the ``omni-sfm``
command keeps it (:func:`omni_sfm.libs.keep_freed_memory`).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.bench.joint --work W_300
    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.bench.joint --work W_100 W_300 W_1000 \\
        --no-step --repeat 5
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from scripts.benchlib import add_log_arguments, write_log


def _prepare(W: Path, step: bool) -> dict[str, Any]:
    """Triangulate ``W``'s database on its init's poses; the joint adjustment's inputs (and,
    with ``step``, print one step formed and factored against conjugate gradients)."""
    from omni_sfm.estimate.bundle import LineProblem
    from omni_sfm.evaluate import trajectory_errors
    from omni_sfm.export.colmap import read_init_model, seed_for_database
    from omni_sfm.libs import library_logging
    from omni_sfm.poses import read_tum
    from omni_sfm.refine.joint import JointOptions, PointObservations, _JointProblem
    from omni_sfm.refine.joint_model import model_points, read_line_evidence
    from omni_sfm.refine.triangulation import triangulate_seeded
    from omni_sfm.solver import gauge

    init = read_init_model(W / "init_lines")
    lines = read_line_evidence(init.artifacts)
    if isinstance(lines, str):
        raise SystemExit(f"bench_joint: {lines}")
    gt = read_tum(W / "render" / "groundtruth.tum")
    print(f"# {os.cpu_count()} CPUs; {W}")
    t = time.perf_counter()
    seed = seed_for_database(init.camera, init.trajectory, init.image_names,
                             W / "database_sift.db")
    # no images: no colours (COLMAP's warning for each image silenced), nothing else lost
    with tempfile.TemporaryDirectory() as empty, library_logging(verbose=False):
        rec, _ = triangulate_seeded(seed.reconstruction, W / "database_sift.db", Path(empty),
                                 init.camera, init.camera.colmap_export())
    print(f"triangulation: {time.perf_counter() - t:.1f} s, {rec.num_points3D()} points, "
          f"{rec.compute_num_observations()} observations")
    ids = [rec.find_image_with_name(n).image_id for n in init.image_names]
    obs, X, _, _ = model_points(rec, ids, init.camera, init.camera.colmap_export())
    F, k = lines.tracks.num_frames, lines.frame_of_pose
    R = np.full((F, 3, 3), np.nan)
    c = np.full((F, 3), np.nan)
    R[k], c[k] = init.trajectory.rotations, init.trajectory.positions
    points = PointObservations(k[obs.frame], obs.point, obs.ray, obs.num_points,
                               obs.pixel_jacobian)
    e = trajectory_errors(init.trajectory, gt)
    print(f"input: rotation mean / max {e.rot_mean_deg:.4f} / {e.rot_max_deg:.4f} deg, "
          f"ATE {100 * e.ate_rel:.4f} %")
    if step:  # one step, factored and by conjugate gradients, from the input
        frames = np.isfinite(c).all(1)
        d, p, Xs = (np.nan_to_num(a) for a in (lines.directions, lines.points, X))
        Rs, cs = np.nan_to_num(R), np.nan_to_num(c)
        used: np.ndarray = np.asarray(np.isfinite(lines.directions).all(1))
        lp = LineProblem(lines.tracks, frames, used, *gauge(cs, frames, None))
        active = np.isfinite(X[points.point]).all(1)
        steps = []
        for name, above in (("formed and factored", 10 ** 9), ("conjugate gradients", 0)):
            prob = _JointProblem(lp, points, active, np.radians(0.02), np.radians(0.03),
                                 options=JointOptions(iterative_above=above))
            res, aux = prob.residuals(Rs, cs, d, p, Xs)
            Jpl, Jl, Jpp, Jx = prob.jacobian(Rs, cs, d, p, Xs, aux)
            blocks = prob.normal_equations(Jpl, Jl, Jpp, Jx, res, np.ones(len(res)))
            t = time.perf_counter()
            dp, (dl, dx) = prob.solve(blocks, 1e-6)
            took = time.perf_counter() - t
            steps.append(np.r_[dp.ravel(), dl.ravel(), dx.ravel()])
            cg = f", {prob.cg_iterations[0]} iterations" if prob.cg_iterations else ""
            print(f"one step, {name}: {took:.1f} s{cg}")
        print(f"the steps differ by "
              f"{np.abs(steps[1] - steps[0]).max() / np.abs(steps[0]).max():.1e}"
              " of the largest entry")
    return dict(lines=lines, R=R, c=c, points=points, X=X, k=k, gt=gt,
                timestamps=init.trajectory.timestamps)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, nargs="+", required=True,
                    help="scripts/bench/refine.py work folders")
    ap.add_argument("--iterative-above", type=int, nargs="+", default=[50],
                    help="whole adjustments to run, one per value of "
                         "JointOptions.iterative_above (default: 50, the default)")
    ap.add_argument("--no-whole", action="store_true", help="only the one step")
    ap.add_argument("--no-step", action="store_true", help="only the whole adjustments")
    ap.add_argument("--repeat", type=int, default=1,
                    help="rounds of the whole adjustments (the folders alternated)")
    add_log_arguments(ap)
    args = ap.parse_args()

    from omni_sfm.evaluate import trajectory_errors
    from omni_sfm.libs import keep_freed_memory
    from omni_sfm.poses import Trajectory
    from omni_sfm.refine.joint import JointOptions, joint_adjust

    keep_freed_memory()
    inputs = {W: _prepare(W, not args.no_step) for W in args.work}
    if args.no_whole:
        return
    per_frame: dict[tuple[Path, int], list[float]] = {}
    rows: dict[tuple[Path, int], list[object]] = {}
    for r in range(args.repeat):
        for W, a in inputs.items():
            for above in args.iterative_above:
                t = time.perf_counter()
                out = joint_adjust(a["lines"].tracks, a["R"], a["c"], a["lines"].directions,
                                   a["lines"].points, a["points"], a["X"],
                                   options=JointOptions(iterative_above=above))
                took = time.perf_counter() - t
                k = a["k"]
                e = trajectory_errors(Trajectory(a["timestamps"], out.rotations[k],
                                                 out.positions[k]), a["gt"])
                per_frame.setdefault((W, above), []).append(1000 * took / len(k))
                rows[W, above] = [str(W), above, len(k), out.iterations,
                                  f"{e.rot_mean_deg:.4f} / {e.rot_max_deg:.4f}",
                                  100 * e.ate_rel]
                print(f"{W}, round {r + 1}: whole adjustment, iterative above {above} frames: "
                      f"{took:.1f} s ({1000 * took / len(k):.0f} ms a frame), {out.iterations} "
                      f"iterations; rotation mean / max {e.rot_mean_deg:.4f} / "
                      f"{e.rot_max_deg:.4f} deg, ATE {100 * e.ate_rel:.4f} %", flush=True)
    if args.repeat > 1:
        for (W, above), v in per_frame.items():
            print(f"{W}, iterative above {above}: median {np.median(v):.1f} ms a posed frame "
                  f"over {len(v)} rounds ({min(v):.1f}-{max(v):.1f})")
    write_log(args, "bench_joint", "The joint adjustment alone", [
        "work folder", "iterative above", "posed frames", "iterations",
        "rotation mean / max (deg)", {"label": "ATE (%)", "format": ".4f"},
        {"label": "ms a posed frame (median)", "format": ".1f"}],
        [[*row, float(np.median(per_frame[key]))] for key, row in rows.items()],
        headline="{rows[0][6]} ms a posed frame ({rows[0][2]} frames)",
        notes=f"{args.repeat} round(s), the folders alternated.")


if __name__ == "__main__":
    main()
