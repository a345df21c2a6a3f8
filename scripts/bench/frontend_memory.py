#!/usr/bin/env python
"""Memory of the line front end against video length: does it stay bounded?

Runs the front end alone (``omni_sfm.lines.frontend.track_lines``: decoding, extraction in the
worker processes, tracking; the memory settings of the ``omni-sfm`` command) on the first N
frames of a video for each N in ``--frames``, each in a fresh process, and prints its wall
time, the tracks and observations it made, and the resident memory of the process and its
workers (summed, sampled every 0.5 s): the peak and the value at each tenth of the run. The
speed issue asks for memory that does not grow with the video's length, tracks and
observations aside (these grow by a few hundred bytes an observation).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.bench.frontend_memory \\
        --video LONG/video.mp4 --camera LONG/camera.yaml --frames 300 1000 3000

(``LONG``: e.g. the 3,000-frame 1920x960 render of ``scripts/bench/long_video.py``.)
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from scripts.benchlib import add_log_arguments, at_tenths, run_sampled, write_log


def _child(video: str, camera: str, n: int) -> None:
    from omni_sfm.cameras.io import load_camera
    from omni_sfm.frames import read_frames
    from omni_sfm.libs import keep_freed_memory
    from omni_sfm.lines.frontend import FrontEndOptions, track_lines

    keep_freed_memory()
    t0 = time.perf_counter()
    fe = track_lines(read_frames(video, end=n), load_camera(camera),
                     FrontEndOptions(progress=False))
    print(f"{time.perf_counter() - t0:.1f} {fe.tracks.num_tracks} {fe.tracks.num_observations}",
          flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--video", required=True)
    ap.add_argument("--camera", required=True)
    ap.add_argument("--frames", type=int, nargs="+", default=[300, 1000, 3000])
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    add_log_arguments(ap)
    args = ap.parse_args()
    if args.child is not None:
        _child(args.video, args.camera, args.child)
        return 0
    print(f"# front end memory; {os.cpu_count()} CPUs, OPENBLAS_NUM_THREADS="
          f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}; {args.video}")
    print(f"{'frames':>7} {'wall s':>7} {'tracks':>7} {'obs':>8} {'peak MB':>8}  MB at each tenth")
    rows: list[list[object]] = []
    for n in args.frames:
        wall, samples, rc, said = run_sampled([sys.executable, "-m",
                                               "scripts.bench.frontend_memory", "--video",
                                               args.video, "--camera", args.camera,
                                               "--child", str(n)])
        out = said.splitlines()[-1].split() if said else []
        if rc != 0 or len(out) != 3 or not samples:
            print(f"{n:>7} failed (exit {rc}): {said[-500:]}")
            continue
        peak = max(m for _, m in samples)
        print(f"{n:>7} {float(out[0]):>7.1f} {out[1]:>7} {out[2]:>8} {peak:>8.0f}  "
              f"{at_tenths(samples, wall)}", flush=True)
        rows.append([n, int(out[1]), int(out[2]), float(out[0]), peak])
    write_log(args, "bench_frontend_memory", "The front end's memory against the video's length",
              ["frames", "tracks", "observations", {"label": "wall (s)", "format": ".1f"},
               {"label": "peak MB", "format": ",.0f"}], rows,
              headline="peak {rows[0][4]} MB at {rows[0][0]} frames, {rows[-1][4]} MB at "
                       "{rows[-1][0]}",
              notes="The resident memory of the process and its workers together.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
