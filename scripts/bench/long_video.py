#!/usr/bin/env python
"""A long 360 video through the whole ``omni-sfm init --lines``: time, memory over the run,
accuracy (the speed issue's "a 1920x960 video of 3,000 frames, H.264, through ``init --step
1`` in bounded memory").

Renders (once, reused from ``--work``) the L-shaped office walk (23 m, a 90 deg turn, plain
walls) through an equirectangular camera as an H.264 video (``--frames`` frames of
``--width`` x ``--height``, CRF ``--crf``, ``--fps`` frames a second, ``--supersample`` rays a
pixel side), then runs ``omni-sfm init --lines --images video.mp4 --step 1`` on it as a user
would (a fresh process, all default outputs) and prints: wall time, the resident memory of
the process and its worker processes (summed, sampled every 0.5 s) at each tenth of the run
and its peak, the front end's and the estimation's wall time from ``report.json``, frames
posed (main trajectory, segments) and the rotation error and ATE of the main trajectory
against the ground truth.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.bench.long_video --work /tmp/long_video

Rendering costs about 1.3 s a 1920x960 frame on one core (``--supersample 1``), so the
default 3,000 frames take about an hour; the render is kept for later runs.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from omni_sfm.evaluate import trajectory_errors
from omni_sfm.poses import read_tum
from omni_sfm.synth.effects import VideoCodec
from omni_sfm.synth.paths import Route
from omni_sfm.synth.render import RenderOptions, render_sequence
from omni_sfm.synth.scenes import SceneName
from scripts.benchlib import add_log_arguments, at_tenths, run_sampled, write_log


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", type=Path, required=True, help="working folder (render reused)")
    p.add_argument("--frames", type=int, default=3000)
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=960)
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--crf", type=int, default=23, help="H.264 constant rate factor")
    p.add_argument("--supersample", type=int, default=1)
    p.add_argument("--render", type=Path, default=None,
                   help="use this rendered folder (video.mp4, camera.yaml, groundtruth.tum) "
                        "instead of rendering into WORK")
    add_log_arguments(p)
    args = p.parse_args()
    render = args.render or args.work / f"render_{args.frames}_{args.width}x{args.height}"
    if not (render / "groundtruth.tum").is_file():
        t0 = time.perf_counter()
        render_sequence(render, RenderOptions(
            scene=SceneName.OFFICE, route=Route.OFFICE, camera="equirectangular",
            frames=args.frames, width=args.width, height=args.height, video=True,
            video_codec=VideoCodec.H264, video_crf=args.crf, fps=args.fps,
            supersample=args.supersample), progress=sys.stderr.isatty())
        print(f"render {args.frames} frames: {time.perf_counter() - t0:.1f} s", flush=True)
    out = args.work / "init_lines"
    cmd = [sys.executable, "-m", "omni_sfm", "init", "--lines", "--images",
           str(render / "video.mp4"), "--camera", str(render / "camera.yaml"), "--step", "1",
           "--overwrite", "--quiet", "--output", str(out)]
    print(f"# bench_long_video: {os.cpu_count()} CPUs, OPENBLAS_NUM_THREADS="
          f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}; {' '.join(cmd[1:])}", flush=True)
    wall, samples, rc, said = run_sampled(cmd)
    if rc != 0:
        print(f"init exited {rc}: {said[-2000:]}")
        return 1
    peak = max((m for _, m in samples), default=0.0)
    print(f"init --lines, {args.frames} frames: {wall:.1f} s wall, {1000 * wall / args.frames:.1f} "
          f"ms a frame, peak {peak:.0f} MB")
    print("resident MB at each tenth of the run: " + at_tenths(samples, wall))
    report = json.loads((out / "report.json").read_text())
    ws = report.get("wall_time_s", {})
    print(f"front end {ws.get('front_end', float('nan')):.1f} s, estimation "
          f"{ws.get('estimation', float('nan')):.1f} s; tracks {report.get('num_tracks')}, "
          f"observations {report.get('num_observations')}")
    est, gt = read_tum(out / "trajectory.tum"), read_tum(render / "groundtruth.tum")
    e = trajectory_errors(est, gt)
    in_segments = sum(s.get("num_frames_estimated", 0) for s in report.get("segments", []))
    print(f"main trajectory {len(est)}/{len(gt)} frames, {in_segments} more in "
          f"{len(report.get('segments', []))} segments; rotation mean / max "
          f"{e.rot_mean_deg:.3f} / {e.rot_max_deg:.3f} deg, ATE {100 * e.ate_rel:.3f} %")
    print(said.splitlines()[-1] if said else "")
    row = [f"{args.width}x{args.height} H.264, {args.frames:,} frames", wall,
           ws.get("front_end"), ws.get("estimation"), peak, f"{len(est):,}/{len(gt):,}",
           f"{e.rot_mean_deg:.3f} / {e.rot_max_deg:.3f}", 100 * e.ate_rel]
    write_log(args, "bench_long_video", "A long 360 video through the whole init", [
        "video", {"label": "wall (s)", "format": ".0f"},
        {"label": "front end (s)", "format": ".0f"}, {"label": "estimation (s)", "format": ".0f"},
        {"label": "peak memory (MB)", "format": ".0f"},
        "main trajectory", "rotation mean / max (deg)", {"label": "ATE (%)", "format": ".3f"}],
        [row], headline="{rows[0][5]} frames in one trajectory in {rows[0][1]} s, "
        "{rows[0][6]} deg, {rows[0][7]} % ATE, peak {rows[0][4]} MB",
        notes="Resident MB at each tenth of the run: " + at_tenths(samples, wall) + ".")
    return 0


if __name__ == "__main__":
    sys.exit(main())
