"""Benchmark the joint adjustment of lines and points alone, on a work folder of
``bench_refine.py`` (its ``init_lines``, ``database_sift.db`` and ``render/groundtruth.tum``):
COLMAP's triangulation on the init's poses (as ``refine`` does it), then one Levenberg-Marquardt
step with the cameras' system formed and factored against conjugate gradients (time, agreement),
then the whole adjustment (time, iterations, errors against the ground truth).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/bench_joint.py --work W_300
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="a bench_refine.py work folder")
    ap.add_argument("--iterative-above", type=int, nargs="+", default=[50],
                    help="whole adjustments to run, one per value of "
                         "JointOptions.iterative_above (default: 50, the default)")
    ap.add_argument("--no-whole", action="store_true", help="only the one step")
    args = ap.parse_args()

    from omni_sfm.estimate.bundle import LineProblem, gauge
    from omni_sfm.evaluate import trajectory_errors
    from omni_sfm.export.colmap import read_init_model, seed_for_database
    from omni_sfm.libs import library_logging
    from omni_sfm.poses import Trajectory, read_tum
    from omni_sfm.refine.joint import JointOptions, PointObservations, _JointProblem, joint_adjust
    from omni_sfm.refine.joint_model import model_points, read_line_evidence
    from omni_sfm.refine.triangulation import triangulate_seeded

    W = args.work
    init = read_init_model(W / "init_lines")
    lines = read_line_evidence(W / "init_lines", init.trajectory)
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

    # one step, factored and by conjugate gradients, from the input
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
    print(f"the steps differ by {np.abs(steps[1] - steps[0]).max() / np.abs(steps[0]).max():.1e}"
          " of the largest entry")
    if args.no_whole:
        return
    for above in args.iterative_above:
        t = time.perf_counter()
        out = joint_adjust(lines.tracks, R, c, lines.directions, lines.points, points, X,
                           options=JointOptions(iterative_above=above))
        took = time.perf_counter() - t
        e = trajectory_errors(Trajectory(init.trajectory.timestamps, out.rotations[k],
                                         out.positions[k]), gt)
        print(f"whole adjustment, iterative above {above} frames: {took:.1f} s "
              f"({1000 * took / len(k):.0f} ms a frame), {out.iterations} iterations; "
              f"rotation mean / max {e.rot_mean_deg:.4f} / {e.rot_max_deg:.4f} deg, "
              f"ATE {100 * e.ate_rel:.4f} %")


if __name__ == "__main__":
    main()
