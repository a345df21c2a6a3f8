#!/usr/bin/env python
"""The estimator alone on saved tracks: `estimate_poses` on each `init` folder's `tracks.json`
against the ground truth of the rendered sequence it came from.

Re-running only the estimator separates what it does from the front end (the tracks are fixed),
so a change of the estimator is measured on exactly the same input. For each pair it prints the
frames of the main trajectory and their errors (maximum and mean rotation error relative to the
first frame, ATE as a per cent of the path after similarity alignment), then each segment
(parts with nothing in common, in their own world) the same way, and the wall time.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.eval.tracks \\
        /tmp/f600/hyperboloid-800x600--clean-init:/tmp/f600/hyperboloid-800x600--clean ...

``--frames START STOP`` runs the estimator on those frames only (``STOP`` excluded), e.g. the
turn of a long walk.

``--blocks N`` also prints the mean rotation error of each block of N frames. ``--perturb N``
also runs the estimator N more times on each input with its normals turned by about
``--noise`` (default 1e-9, random, seeds 1..N) and prints how far each run differs from the
first: a result that changes with the last bits of the input is chaotic, and one run of it
says little. ``--reversed``
also runs it on the frames in reversed order (the same observations, timestamps kept) and
prints how far the two trajectories differ: the largest rotation difference and the RMS
position difference in per cent of the path, after a similarity alignment.
``--estimator`` picks the estimator (``EstimationOptions.estimator``: ``auto``, the default,
``paper`` or ``global``).

Each argument is ``INIT_DIR:RENDER_DIR`` (``RENDER_DIR`` holds ``groundtruth.tum``); a bare
``INIT_DIR`` ending in ``-init`` pairs with the folder of the same name without it, as
``scripts/eval/footage.py`` lays them out.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.pipeline import EstimationOptions, estimate_poses
from omni_sfm.estimate.segments import frame_range
from omni_sfm.evaluate import match_reflection, relative_rotation_errors_deg, trajectory_errors
from omni_sfm.geometry import normalize
from omni_sfm.lines.tracks import read_tracks, reversed_frames
from omni_sfm.poses import Trajectory, read_tum
from omni_sfm.reports import InitReport
from omni_sfm.transforms import associate
from scripts.benchlib import add_log_arguments, write_log


def _pair(arg: str) -> tuple[Path, Path]:
    if ":" in arg:
        a, b = arg.split(":", 1)
        return Path(a), Path(b)
    d = Path(arg.rstrip("/"))
    if not d.name.endswith("-init"):
        raise SystemExit(f"eval_tracks: {arg}: give INIT_DIR:RENDER_DIR")
    return d, d.with_name(d.name[: -len("-init")])


def moving_of(report: InitReport) -> bool:
    """The camera moved (not a rotation-only estimate): its positions can be compared."""
    return not report.rotation_only


def _errors(traj: Trajectory, gt: Trajectory, positions: bool) -> str:
    if not positions:
        e, g = associate(traj, gt)
        rot = relative_rotation_errors_deg(e, g)
        return f"{len(e)} frames, rotation {rot.max():.3f} / {rot.mean():.3f} deg, rotation only"
    err = trajectory_errors(match_reflection(traj, gt), gt)
    return (f"{err.num_common} frames, rotation {err.rot_max_deg:.3f} / {err.rot_mean_deg:.3f} "
            f"deg (max / mean), ATE {100 * err.ate_rel:.3f} %")


def _blocks(traj: Trajectory, gt: Trajectory, n: int) -> str:
    """The mean rotation error (relative to the first frame) of each block of ``n`` frames,
    by the blocks' first frame index (timestamps matched to the ground truth's frames)."""
    e, g = associate(traj, gt)
    rot = relative_rotation_errors_deg(e, g)
    frame = np.searchsorted(gt.timestamps, g.timestamps)
    block = frame // n
    return ", ".join(f"{b * n}: {rot[block == b].mean():.2f}" for b in np.unique(block))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("pairs", nargs="+", help="INIT_DIR:RENDER_DIR (or INIT_DIR ending in -init)")
    ap.add_argument("--perturb", type=int, default=0, metavar="N",
                    help="also N runs with the normals perturbed by about --noise (default 0)")
    ap.add_argument("--noise", type=float, default=1e-9,
                    help="the perturbation of --perturb, radians (default 1e-9)")
    ap.add_argument("--frames", type=int, nargs=2, metavar=("START", "STOP"),
                    help="only these frames (STOP excluded)")
    ap.add_argument("--blocks", type=int, default=0, metavar="N",
                    help="also the main trajectory's mean rotation error per block of N frames "
                         "(where the error comes from: drift grows along the blocks, a stretch "
                         "turned against the rest shows as a step)")
    ap.add_argument("--reversed", action="store_true",
                    help="also the frames in reversed order, and how far the two differ")
    ap.add_argument("--estimator", choices=["auto", "paper", "global"], default="auto",
                    help="EstimationOptions.estimator (default auto)")
    add_log_arguments(ap)
    args = ap.parse_args()
    rows: list[list[object]] = []
    options = EstimationOptions(estimator=args.estimator)
    print(f"# estimator alone on saved tracks; {os.cpu_count()} CPUs, "
          f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}")
    for arg in args.pairs:
        init_dir, render_dir = _pair(arg)
        try:
            tracks = read_tracks(init_dir / "tracks.json")
            if args.frames:
                tracks = frame_range(tracks, *args.frames)[0]
            gt = read_tum(render_dir / "groundtruth.tum")
            t0 = time.perf_counter()
            res = estimate_poses(tracks, options)
            wall = time.perf_counter() - t0
        except OmniSfmError as exc:
            print(f"{init_dir.name}: error: {exc}")
            rows.append([init_dir.name, f"error: {exc}", "", "", None])
            continue
        moving = moving_of(res.report)
        in_segs = sum(int(s.frames.sum()) for s in res.segments)
        print(f"{init_dir.name}: {int(res.estimated.sum())}/{tracks.num_frames} in the main "
              f"trajectory, {in_segs} in {len(res.segments)} segments, {wall:.1f} s")
        print(f"  main: {_errors(res.trajectory, gt, moving)} ({res.report.estimator})")
        rows.append([init_dir.name, f"{int(res.estimated.sum())}/{tracks.num_frames}",
                     f"{in_segs} in {len(res.segments)}", _errors(res.trajectory, gt, moving),
                     wall])
        if args.blocks > 0:
            print(f"  per {args.blocks} frames: {_blocks(res.trajectory, gt, args.blocks)}")
        for seg in res.segments:
            first, last = np.flatnonzero(seg.frames)[[0, -1]]
            print(f"  segment {seg.number} (frames {first}-{last}): "
                  f"{_errors(seg.trajectory, gt, True)}")
        if args.reversed:
            back = estimate_poses(replace(reversed_frames(tracks),
                                          timestamps=tracks.timestamps[::-1].copy()), options)
            d = trajectory_errors(match_reflection(back.trajectory, res.trajectory),
                                  res.trajectory)
            print(f"  reversed: {int(back.estimated.sum())} frames; differs from the forward "
                  f"run by {d.rot_max_deg:.4f} deg (largest rotation), "
                  f"{100 * d.ate_rel:.4f} % of the path (RMS position)")
        for seed in range(1, args.perturb + 1):
            rng = np.random.default_rng(seed)
            n = normalize(tracks.obs_normal + args.noise * rng.normal(size=tracks.obs_normal.shape))
            try:
                r = estimate_poses(replace(tracks, obs_normal=n), options)
            except OmniSfmError as exc:
                print(f"  perturbed {seed}: error: {exc}")
                continue
            d = trajectory_errors(match_reflection(r.trajectory, res.trajectory),
                                  res.trajectory)
            print(f"  perturbed {seed}: {int(r.estimated.sum())} frames; main: "
                  f"{_errors(r.trajectory, gt, moving_of(r.report))}; differs from the first "
                  f"run by {d.rot_max_deg:.4f} deg, {100 * d.ate_rel:.4f} % of the path")
            rows.append([f"{init_dir.name}, normals perturbed ({seed})",
                         f"{int(r.estimated.sum())}/{tracks.num_frames}", "",
                         _errors(r.trajectory, gt, moving_of(r.report)), None])
    write_log(args, "eval_tracks", "The estimator alone on saved tracks", [
        "run", "main trajectory", "in segments", "main: errors",
        {"label": "wall (s)", "format": ".1f"}], rows,
        headline="{rows[0][0]}: {rows[0][3]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
