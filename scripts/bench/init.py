#!/usr/bin/env python
"""Benchmark the whole ``omni-sfm init --lines`` (all default outputs) beside COLMAP's
incremental mapper (``omni-sfm init --initializer colmap``) on the same frames, in one run.

Renders (once, reused from ``WORK``) the L-shaped office walk through an 800 x 600 hyperboloid
camera, with texture so that COLMAP has points to match, in ``--frames`` frames for each size
asked (default 200 and 2,000), all at the same speed (``--metres-per-frame``, default 11.5 mm:
the whole 23 m walk, with its 90 deg turn, in 2,000 frames; 200 frames walk its first 2.3 m),
runs ``omni-sfm init --lines`` on each as a user would (a fresh process), and COLMAP on the
first (smallest) size only, and prints per run: wall time, peak memory (the resident memory of
the process and its worker processes, summed, sampled every 0.2 s), frames posed, rotation
error and ATE against the ground truth; then the ratios the speed issue asks about (``init``
against COLMAP on the same frames; the longest ``init`` against the shortest).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.bench.init --work /tmp/bench_init
    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.bench.init --work /tmp/bench_init \\
        --frames 200 --no-colmap
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from omni_sfm.evaluate import trajectory_errors
from omni_sfm.poses import read_tum
from omni_sfm.synth.paths import Route
from omni_sfm.synth.render import RenderOptions, render_sequence
from omni_sfm.synth.scenes import SceneName
from scripts.benchlib import add_log_arguments, run_timed, write_log


def _errors(out: Path, render: Path) -> tuple[str, float, float]:
    """``("posed/all", max rotation error deg, ATE %)`` of the run in ``out``."""
    est = read_tum(out / "trajectory.tum")
    gt = read_tum(render / "groundtruth.tum")
    e = trajectory_errors(est, gt)
    return f"{len(est):,}/{len(gt):,}", e.rot_max_deg, 100 * e.ate_rel


def _said(errors: tuple[str, float, float]) -> str:
    return f"{errors[0]} frames, rotation max {errors[1]:.3f} deg, ATE {errors[2]:.3f} %"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", type=Path, required=True, help="working folder (renders reused)")
    p.add_argument("--frames", type=int, nargs="+", default=[200, 2000])
    p.add_argument("--no-colmap", action="store_true", help="skip COLMAP's mapper")
    p.add_argument("--metres-per-frame", type=float, default=0.0115,
                   help="the camera's speed (default 0.0115: the office walk in 2,000 frames)")
    add_log_arguments(p)
    args = p.parse_args()
    exe = [sys.executable, "-m", "omni_sfm"]
    print(f"# bench_init: {os.cpu_count()} CPUs, OPENBLAS_NUM_THREADS="
          f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}, 800x600 hyperboloid, textured "
          "office walk")
    lines: dict[int, float] = {}
    colmap = None
    rows: list[list[object]] = []
    for n in sorted(args.frames):
        length = args.metres_per_frame * (n - 1)
        render = args.work / f"render_{n}_{length:.2f}m"
        if not (render / "groundtruth.tum").is_file():
            t0 = time.perf_counter()
            render_sequence(render, RenderOptions(scene=SceneName.OFFICE, route=Route.OFFICE,
                                                  camera="hyperboloid", frames=n,
                                                  path_length=length, textured=True),
                            progress=sys.stderr.isatty())
            print(f"render {n} frames, {length:.1f} m: {time.perf_counter() - t0:.1f} s",
                  flush=True)
        common = ["--images", str(render / "images"), "--camera", str(render / "camera.yaml"),
                  "--overwrite", "--quiet"]
        out = args.work / f"lines_{n}"
        wall, peak, code, said = run_timed([*exe, "init", "--lines", *common, "--output", str(out)])
        if code != 0:
            print(f"init --lines, {n} frames: exit {code}: {said}")
            return 1
        lines[n] = wall
        err = _errors(out, render)
        rows.append([f"`init --lines`, {n:,} frames", wall, 1000 * wall / n, peak, *err])
        print(f"init --lines, {n} frames: {wall:.1f} s wall, {1000 * wall / n:.1f} ms a frame, "
              f"peak {peak:.0f} MB; {_said(err)}", flush=True)
        if colmap is None and not args.no_colmap:
            out = args.work / f"colmap_{n}"
            wall, peak, code, said = run_timed([*exe, "init", "--initializer", "colmap", *common,
                                           "--output", str(out)])
            if code != 0:
                print(f"COLMAP, {n} frames: exit {code}: {said}")
            else:
                colmap = (n, wall)
                err = _errors(out, render)
                rows.append([f"COLMAP's mapper, the same {n:,} frames", wall, 1000 * wall / n,
                             peak, *err])
                print(f"COLMAP incremental mapper, {n} frames: {wall:.1f} s wall, peak "
                      f"{peak:.0f} MB; {_said(err)}", flush=True)
    ratios: list[str] = []
    if colmap is not None:
        n, wall = colmap
        ratios.append(f"`init --lines` is {wall / lines[n]:.1f}x faster than COLMAP's mapper "
                      f"on {n:,} frames")
    if len(lines) > 1:
        lo, hi = min(lines), max(lines)
        ratios.append(f"{hi:,} frames take {lines[hi] / lines[lo]:.1f}x the time of {lo:,} "
                      f"({hi / lo:.0f}x the frames)")
    for s in ratios:
        print(s)
    headline = "`init --lines` {rows[0][1]} s, {rows[0][5]} deg / {rows[0][6]} % ATE"
    if colmap is not None:  # rows: init, COLMAP, ...
        headline = (f"{colmap[1] / lines[colmap[0]]:.0f}x faster than COLMAP's mapper: "
                    "{rows[0][1]} s against {rows[1][1]} s on a textured "
                    f"{colmap[0]:,}-frame office walk "
                    "at {rows[0][5]} deg / {rows[0][6]} % ATE")
    write_log(args, "bench_init", "The whole init against COLMAP's incremental mapper", [
        "run", {"label": "wall (s)", "format": ",.1f"}, {"label": "ms a frame", "format": ",.1f"},
        {"label": "peak memory (MB)", "format": ".0f"}, "frames",
        {"label": "rotation max (deg)", "format": ".3f"}, {"label": "ATE (%)", "format": ".3f"}],
        rows, headline=headline, notes="; ".join(ratios) + ("." if ratios else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
