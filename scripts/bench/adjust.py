"""Time one line bundle adjustment (:func:`omni_sfm.estimate.bundle.bundle_adjust`, the step
most of the estimator's time goes to) on a real walk's tracks, and print a digest of its
result, so that two versions of the code can be compared for speed and, bit for bit, for what
they compute.

The problem: the frames ``--frames A B`` of an ``omni-sfm init`` output folder's main
trajectory (``trajectory.tum``, whose timestamps must be frame indices: an image folder's
init), its ``tracks.json``, every line triangulated again from those poses, the poses moved
by a seeded 0.1 deg and 5 mm; the adjustment's default options but ``--iterations``. Prints
the problem's size, the iterations, the final RMS residual, the md5 of the poses and lines
found, the wall time of each run and their median, with the core count.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.bench.adjust --init lines_2000 \\
        --frames 154 882 --repeats 3
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time
from pathlib import Path

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.bundle import BundleOptions, BundleResult, bundle_adjust
from omni_sfm.folders import InitFolder
from omni_sfm.geometry import rotvec_to_matrix
from omni_sfm.lines.tracks import read_tracks
from omni_sfm.poses import read_tum
from scripts.benchlib import add_log_arguments, write_log


def digest(res: BundleResult) -> str:
    h = hashlib.md5()
    for a in (res.rotations, res.positions, res.line_directions, res.line_points):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--init", type=Path, required=True, help="an omni-sfm init output folder")
    ap.add_argument("--frames", type=int, nargs=2, metavar=("A", "B"), required=True,
                    help="adjust the posed frames A..B-1")
    ap.add_argument("--iterations", type=int, default=200, help="LM iterations per solve")
    ap.add_argument("--repeats", type=int, default=3)
    add_log_arguments(ap)
    args = ap.parse_args()
    try:
        tracks = read_tracks(args.init / InitFolder.TRACKS)
        traj = read_tum(args.init / InitFolder.TRAJECTORY)
    except OmniSfmError as exc:
        print(f"bench_adjust: {exc}", file=sys.stderr)
        return 2
    F, M = tracks.num_frames, tracks.num_tracks
    at = np.rint(np.asarray(traj.timestamps)).astype(int)
    if not np.allclose(traj.timestamps, at) or at.min() < 0 or at.max() >= F:
        print("bench_adjust: trajectory.tum's timestamps are not the tracks' frame indices",
              file=sys.stderr)
        return 2
    R, c = np.full((F, 3, 3), np.nan), np.full((F, 3), np.nan)
    R[at], c[at] = traj.rotations, traj.positions
    frames = np.zeros(F, bool)
    frames[args.frames[0]:args.frames[1]] = True
    frames &= np.isfinite(c[:, 0])
    if frames.sum() < 3:
        print("bench_adjust: fewer than 3 posed frames in that range", file=sys.stderr)
        return 2
    rng = np.random.default_rng(0)
    R[frames] = R[frames] @ rotvec_to_matrix(rng.normal(0.0, np.radians(0.1),
                                                        (frames.sum(), 3)))
    c[frames] += rng.normal(0.0, 0.005, (frames.sum(), 3))
    nan = np.full((M, 3), np.nan)
    options = BundleOptions(max_iterations=args.iterations)
    print(f"# bench_adjust: {os.cpu_count()} CPUs, OPENBLAS_NUM_THREADS="
          f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}, {int(frames.sum())} frames, "
          f"{int(np.isin(tracks.obs_frame, np.flatnonzero(frames)).sum())} observations")
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        res = bundle_adjust(tracks, R, c, nan, nan, frames=frames, options=options)
        times.append(time.perf_counter() - t0)
        print(f"{int(res.used_tracks.sum())} lines, {res.iterations} iterations, residual "
              f"{res.rms_final_deg:.6g} deg, md5 {digest(res)}, {times[-1]:.2f} s", flush=True)
    print(f"median {np.median(times):.2f} s")
    write_log(args, "bench_adjust", "One line bundle adjustment of an init's frames", [
        "frames", "lines", "iterations", {"label": "residual (deg)", "format": ".6g"}, "md5",
        {"label": "median (s)", "format": ".2f"}],
        [[f"{args.frames[0]}-{args.frames[1] - 1} ({int(frames.sum())} posed)",
          int(res.used_tracks.sum()), res.iterations, res.rms_final_deg, digest(res),
          np.median(times)]],
        headline="{rows[0][5]} s for {rows[0][0]}, {rows[0][2]} iterations",
        notes=f"{args.repeats} runs from the init's poses perturbed by 0.1 deg and 5 mm "
              f"(seeded); the md5 compares versions bit for bit.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
