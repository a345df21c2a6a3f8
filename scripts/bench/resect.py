"""Time :func:`omni_sfm.estimate.bundle.resect_pose` (one camera's pose from known 3D lines, the
per-frame step of ``omni-sfm init --lines``) on a fixed, seeded set of typical problems.

Each problem: a random camera, 20 lines 1-6 m away in random directions, their NVs with
0.1 deg noise per axis, the start 1 deg and 5 cm off. Every problem is solved with the Huber
loss (scale 0.4 deg: half the incremental estimator's inlier threshold of 8 noise levels, as
its first call) and with plain least squares
(its second call); the median wall time per call is printed for each, with the core count.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.bench.resect [--problems 200] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from omni_sfm.estimate.bundle import resect_pose
from omni_sfm.geometry import line_plane_normals, normalize, rotvec_to_matrix
from scripts.benchlib import add_log_arguments, write_log

Problem = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def problems(count: int, lines: int = 20, noise_deg: float = 0.1, start_deg: float = 1.0,
             start_m: float = 0.05, seed: int = 0) -> list[Problem]:
    """``count`` problems ``(normals, directions, points, R0, c0)``, seeded."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        R = rotvec_to_matrix(rng.normal(size=3))
        c = rng.normal(size=3) * 3.0
        d = normalize(rng.normal(size=(lines, 3)))
        off = normalize(np.cross(d, rng.normal(size=(lines, 3)))) * rng.uniform(1, 6, (lines, 1))
        p = c + off + d * rng.normal(size=(lines, 1))
        p = p - np.sum(p * d, 1, keepdims=True) * d  # the point closest to the origin
        n = normalize(line_plane_normals(c, p, d) @ R)
        n = np.einsum("kij,kj->ki", rotvec_to_matrix(
            np.radians(noise_deg) * rng.normal(size=(lines, 3))), n)
        R0 = R @ rotvec_to_matrix(np.radians(start_deg) * normalize(rng.normal(size=3)))
        c0 = c + start_m * normalize(rng.normal(size=3))
        out.append((n, d, p, R0, c0))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--problems", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=5)
    add_log_arguments(ap)
    args = ap.parse_args()
    probs = problems(args.problems)
    rows: list[list[object]] = []
    for name, scale in (("huber", float(np.radians(0.4))), ("least squares", np.inf)):
        times = []
        for n, d, p, R0, c0 in probs:
            resect_pose(n, d, p, R0, c0, scale=scale)  # warm
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                resect_pose(n, d, p, R0, c0, scale=scale)
                times.append(time.perf_counter() - t0)
        print(f"resect_pose ({name}): median {np.median(times) * 1e6:.1f} us per call "
              f"({len(probs)} problems x {args.repeats}; cores: {os.cpu_count()})")
        rows.append([name, np.median(times) * 1e6])
    write_log(args, "bench_resect", "Resection of one pose from known lines", [
        "loss", {"label": "median us a call", "format": ".0f"}], rows,
        headline="{rows[0][1]} us a call (Huber), {rows[1][1]} us (least squares)",
        notes=f"{len(probs)} seeded problems of 20 lines, {args.repeats} calls each.")


if __name__ == "__main__":
    main()
