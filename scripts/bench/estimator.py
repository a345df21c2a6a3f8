#!/usr/bin/env python
"""The estimator alone on a real video's tracks: ``omni-sfm init --lines --tracks`` on the first
N frames of a ``tracks.json``, each N in a fresh process, as a user would run it.

``init --images`` writes ``OUTPUT/tracks.json``; this script cuts it to the first ``--frames``
frames (the observations of those frames, the tracks renumbered as ``init`` would see them),
runs ``init --lines --tracks`` on each cut and prints: wall time, ms a frame, peak resident
memory, frames posed, residual, the bundle adjustment's time (``report.json``'s ``timings_ms``:
the global estimator's ``bundle_adjustment``, the paper's ``refinement``), and,
with ``--groundtruth`` (the render's ``groundtruth.tum``), the rotation error and ATE of the
main trajectory. The tracks of a rendered video come from ``scripts/bench/long_video.py``
(its ``--work``/``init_lines/tracks.json``) or from ``init --images`` on any video.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.bench.estimator --tracks T.json \\
        --groundtruth groundtruth.tum --frames 300 600 1000 --work /tmp/bench_estimator
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from omni_sfm.estimate.segments import frame_range
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.folders import InitFolder
from omni_sfm.lines.tracks import read_tracks, write_tracks
from omni_sfm.poses import read_tum
from scripts.benchlib import add_log_arguments, run_sampled, write_log


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tracks", type=Path, required=True, help="tracks.json of a video")
    p.add_argument("--frames", type=int, nargs="+", required=True,
                   help="run on the first N frames, each N in a fresh process")
    p.add_argument("--groundtruth", type=Path, default=None, help="TUM ground truth")
    p.add_argument("--work", type=Path, required=True, help="working folder")
    add_log_arguments(p)
    args = p.parse_args()
    tracks = read_tracks(args.tracks)
    gt = read_tum(args.groundtruth) if args.groundtruth is not None else None
    args.work.mkdir(parents=True, exist_ok=True)
    print(f"# bench_estimator: {os.cpu_count()} CPUs, OPENBLAS_NUM_THREADS="
          f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}; {args.tracks}: "
          f"{tracks.num_frames} frames, {tracks.num_tracks} tracks", flush=True)
    print("| frames | tracks | observations | wall (s) | ms per frame | peak memory (MB) "
          "| posed | residual (deg) | adjustment (s) | rot. err. mean / max (deg) "
          "| ATE (%) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    rows: list[list[object]] = []
    for n in args.frames:
        if n > tracks.num_frames:
            print(f"skipped {n}: the tracks have {tracks.num_frames} frames")
            continue
        cut, _ = frame_range(tracks, 0, n)
        path = args.work / f"tracks_{n}.json"
        write_tracks(path, cut)
        out = args.work / f"init_{n}"
        cmd = [sys.executable, "-m", "omni_sfm", "init", "--lines", "--tracks", str(path),
               "--overwrite", "--quiet", "--output", str(out)]
        wall, samples, rc, said = run_sampled(cmd)
        if rc != 0:
            print(f"{n} frames: init exited {rc}: {said[-500:]}")
            continue
        peak = max((m for _, m in samples), default=0.0)
        report = InitFolder(out).read_report()
        posed = f"{report.num_frames_estimated}/{n}"
        rms = report.rms_final_deg
        times = report.timings_ms or {}
        refine_s = times.get("bundle_adjustment", times.get("refinement", float("nan"))) / 1e3
        rot: str | None = None
        ate: float | None = None
        if gt is not None:
            e = trajectory_errors(read_tum(out / "trajectory.tum"), gt)
            rot, ate = f"{e.rot_mean_deg:.3f} / {e.rot_max_deg:.3f}", 100 * e.ate_rel
        rows.append([n, cut.num_tracks, cut.num_observations, wall, 1000 * wall / n, peak, posed,
                     rms, refine_s, rot, ate])
        print(f"| {n} | {cut.num_tracks} | {cut.num_observations} | {wall:.1f} | "
              f"{1000 * wall / n:.1f} | {peak:.0f} | {posed} | {rms:.4f} | {refine_s:.1f} | "
              f"{rot or '-'} | {'-' if ate is None else f'{ate:.3f}'} |", flush=True)
    write_log(args, "bench_estimator", "The estimator alone on a video's tracks", [
        "frames", "tracks", "observations", {"label": "wall (s)", "format": ".1f"},
        {"label": "ms per frame", "format": ".1f"}, {"label": "peak memory (MB)", "format": ".0f"},
        "posed", {"label": "residual (deg)", "format": ".4f"},
        {"label": "adjustment (s)", "format": ".1f"},
        "rot. err. mean / max (deg)", {"label": "ATE (%)", "format": ".3f"}], rows,
        headline=", ".join(f"{{rows[{k}][0]}} frames {{rows[{k}][3]}} s"
                           for k in range(len(rows))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
