"""Benchmark of the online tracker (``omni-sfm track``, :mod:`omni_sfm.pipelines.track`).

Images (the default): renders (or reuses) a corridor with omni_sfm.synth.render, feeds its
frames one at a time to :class:`omni_sfm.pipelines.track.Tracker` and prints the per-frame latency
(median, 95th percentile, max; wall clock of ``add_frame``, lines and pose, the frame already
decoded) with the core count and the load average, and the accuracy of the poses as they were
returned (each from the frames up to it) against the ground truth: the largest rotation error
and the ATE as a share of the path, over every posed frame and over the frames posed one by
one (after the start). Writes the sequence's row (scene, camera and seed from its
``render.json``) of the records ``docs/benchmarks/bench_track.json`` (latency, accuracy) and
``bench_track_drift.json`` (the worst rotation error in the first and the last third); with
``--memory`` the record ``bench_track_memory.json``, with ``--memory-images``
``bench_track_memory_images.json`` (docs/track.md renders them).

``--memory``: the tracker's state over a long run. Rendering 10,000 frames takes hours here, so
the run feeds :class:`omni_sfm.estimate.online.OnlineEstimator` (the tracker below the front
end: the same start, registration, adjustment and window) the line observations of a simulated walk
through office corridors (``simulate_manhattan``: 50 mm per frame, no rays), and prints the
peak of the traced allocations (tracemalloc) and of the process's resident size at 1,000 frames
and at the end. The front end's own state is the last ``max_gap_frames + 1`` frames
(``LineTracker(record=False)``).

    .venv/bin/python -m scripts.bench.track
    .venv/bin/python -m scripts.bench.track --camera equirectangular
    .venv/bin/python -m scripts.bench.track --input path/to/rendered/sequence
    .venv/bin/python -m scripts.bench.track --memory --frames 10000
    .venv/bin/python -m scripts.bench.track --memory-images 10000

``--memory-images N``: the whole tracker, front end included, on N frames of images: the
rendered corridor (``--input`` or the default render) played forth and back (frames 0..199,
198..0, 1.., so that the camera walks the corridor to and fro) until N frames; prints the
process's resident size now and its peak (``ru_maxrss``) at 1,000 frames, 5,000 and N, the
statuses and the latency.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
import tracemalloc
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from omni_sfm.cameras import CameraModel, load_camera
from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.online import OnlineEstimator, Status, poses_trajectory
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.frames import read_frames
from omni_sfm.libs import keep_freed_memory
from omni_sfm.pipelines.track import Tracker
from omni_sfm.poses import read_tum
from scripts.benchlib import add_log_arguments, write_log

TRACKED = (Status.TRACKING, Status.RELOCALISED)


def render(args: argparse.Namespace) -> Path:
    from omni_sfm.synth.render import RenderOptions, render_sequence

    size = f"{args.width}x{args.height}" if args.width else "default"
    out = Path(args.cache) / f"{args.camera}_{args.frames}_{size}_seed{args.seed}"
    if not (out / "groundtruth.tum").is_file():
        print(f"rendering {out} ...", file=sys.stderr, flush=True)
        render_sequence(out, RenderOptions(camera=args.camera, frames=args.frames,
                                           width=args.width, height=args.height,
                                           seed=args.seed), progress=True)
    return out


def _frame_files(seq: Path) -> list[Path]:
    """The image files of ``seq/images`` in order (PNG, or the --footage renders' JPEG)."""
    return list(read_frames(seq / "images").files)


def sequence_label(seq: Path, camera: CameraModel) -> str:
    """``corridor, hyperboloid 800x600, seed 1``: the scene and seed from the render's
    ``render.json`` (``?`` where a folder has none)."""
    meta_file = seq / "render.json"
    meta = json.loads(meta_file.read_text(encoding="utf-8")) if meta_file.is_file() else {}
    return (f"{meta.get('scene', '?')}, {camera.model} {camera.width}x{camera.height}, "
            f"seed {meta.get('seed', '?')}")


def bench_images(args: argparse.Namespace) -> None:
    seq = Path(args.input) if args.input else render(args)
    camera = load_camera(seq / "camera.yaml")
    files = _frame_files(seq)
    tracker = Tracker(camera)
    poses = []
    cpu = []
    load0 = os.getloadavg()
    for k, f in enumerate(files):
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        assert img is not None, f
        c0 = time.process_time()
        poses.append(tracker.add_frame(img, float(k)))
        cpu.append(1000.0 * (time.process_time() - c0))
    load1 = os.getloadavg()
    lat = np.array([p.latency_ms for p in poses])
    start = next(p.frame for p in poses if p.status in TRACKED)
    after = lat[start + 1:]
    print(f"sequence: {seq} ({camera.width}x{camera.height}, {len(files)} frames)")
    print(f"cores: {os.cpu_count()}; load average before/after: {load0[0]:.2f}/{load1[0]:.2f} "
          "(another process's load makes the wall-clock latency longer)")
    print("statuses: " + ", ".join(f"{n} {s}" for s, n in Counter(p.status for p in poses)
                                   .items()))
    print(f"latency per frame (ms, wall clock), all {len(lat)} frames: median "
          f"{np.median(lat):.1f}, 95th percentile {np.percentile(lat, 95):.1f}, max "
          f"{lat.max():.0f} (the start, frame {start}: {lat[start]:.0f})")
    print(f"latency per frame (ms), the {len(after)} frames after the start: median "
          f"{np.median(after):.1f}, 95th percentile {np.percentile(after, 95):.1f}, max "
          f"{after.max():.0f}")
    print(f"CPU time per frame (ms, all threads of the process): median {np.median(cpu):.1f}, "
          f"95th percentile {np.percentile(cpu, 95):.1f}")
    gt = read_tum(seq / "groundtruth.tum")
    errs = {}
    for name, with_start in (("every posed frame", True), ("frames posed one by one", False)):
        err = trajectory_errors(poses_trajectory(poses, 0, with_start=with_start), gt)
        errs[name] = err
        print(f"accuracy, {name} ({err.num_common} of {len(gt)}): rotation max "
              f"{err.rot_max_deg:.3f} deg, mean {err.rot_mean_deg:.3f} deg; ATE "
              f"{100 * err.ate_rel:.3f} % of the path")
    e = errs["every posed frame"]
    third = len(e.rot_deg) // 3
    print(f"rotation error (every posed frame), worst of the first third of the frames "
          f"{e.rot_deg[:third].max():.3f} deg, of the last third {e.rot_deg[-third:].max():.3f} "
          "deg (drift: the second above the first)")
    label = sequence_label(seq, camera)
    write_log(args, "bench_track_drift", "The online tracker's drift", [
        "sequence", "start at frame", {"label": "rotation error, worst (deg)", "format": ".3f"},
        {"label": "worst in the first third (deg)", "format": ".3f"},
        {"label": "worst in the last third (deg)", "format": ".3f"},
        {"label": "ATE (%)", "format": ".3f"}, {"label": "CPU median (ms)", "format": ".1f"}],
        [[label, start, e.rot_max_deg, e.rot_deg[:third].max(), e.rot_deg[-third:].max(),
          100 * e.ate_rel, np.median(cpu)]],
        headline="worst {rows[0][2]} deg, {rows[0][3]} / {rows[0][4]} deg in the first / last "
                 "third ({rows[0][0]})",
        notes="Every posed frame, the start's frames included (their poses come with the frame "
              "where the start succeeds); the rotation error is relative to the first frame of "
              "the compared set. Drift shows as a last third worse than the first.", merge=True)
    write_log(args, "bench_track", "The online tracker, frame by frame", [
        "sequence", "posed", {"label": "latency median (ms)", "format": ".1f"},
        {"label": "latency p95 (ms)", "format": ".1f"},
        {"label": "CPU median (ms)", "format": ".1f"},
        {"label": "rotation max (deg)", "format": ".3f"}, {"label": "ATE (%)", "format": ".3f"}],
        [[label, f"{e.num_common}/{len(gt)}",
          np.median(after), np.percentile(after, 95), np.median(cpu), e.rot_max_deg,
          100 * e.ate_rel]],
        headline="{rows[0][1]} frames posed as they come, {rows[0][2]} ms a frame (median), "
                 "{rows[0][5]} deg, {rows[0][6]} % ATE ({rows[0][0]})",
        notes="Latency: wall clock of `add_frame` (lines and pose, the frame already decoded) "
              "after the start; accuracy of every pose as it was returned.", merge=True)


def _rss_now_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def bench_memory_images(args: argparse.Namespace, N: int) -> None:
    seq = Path(args.input) if args.input else render(args)
    camera = load_camera(seq / "camera.yaml")
    files = _frame_files(seq)
    cycle = list(range(len(files))) + list(range(len(files) - 2, 0, -1))
    tracker = Tracker(camera)
    status: Counter[str] = Counter()
    lat = np.zeros(N)
    checkpoints = sorted({min(1000, N), min(5000, N), N})
    peaks: dict[int, float] = {}
    rows: list[list[object]] = []
    t0 = time.perf_counter()
    for k in range(N):
        img = cv2.imread(str(files[cycle[k % len(cycle)]]), cv2.IMREAD_UNCHANGED)
        assert img is not None
        p = tracker.add_frame(img, float(k))
        status[str(p.status)] += 1
        lat[k] = p.latency_ms
        if k + 1 in checkpoints:
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
            peaks[k + 1] = peak
            rows.append([k + 1, _rss_now_mb(), peak, tracker.estimator.num_frames_held,
                         tracker.estimator.num_lines, time.perf_counter() - t0])
            print(f"{k + 1} frames: resident now {rows[-1][1]:.1f} MiB, peak {peak:.1f} MiB; "
                  f"holding {tracker.estimator.num_frames_held} frames and "
                  f"{tracker.estimator.num_lines} lines; {time.perf_counter() - t0:.0f} s",
                  flush=True)
    print(f"{seq} forth and back: {N} frames; statuses: "
          + ", ".join(f"{n} {s}" for s, n in status.items()))
    print(f"cores: {os.cpu_count()}; latency per frame (ms): median {np.median(lat):.1f}, 95th "
          f"percentile {np.percentile(lat, 95):.1f}")
    if len(checkpoints) > 1:
        a, b = peaks[checkpoints[0]], peaks[checkpoints[-1]]
        print(f"peak resident size at {checkpoints[-1]} frames / at {checkpoints[0]}: "
              f"{b / a:.3f}")
    mib = {"format": ".1f"}
    write_log(args, "bench_track_memory_images", "The whole tracker's memory over a long run", [
        {"label": "after (frames)", "format": ","}, {"label": "resident now (MiB)", **mib},
        {"label": "peak resident, ru_maxrss (MiB)", **mib}, "frames held", "lines held",
        {"label": "wall (s)", "format": ".0f"}], rows,
        headline=f"peak {{rows[0][2]}} MiB at {{rows[0][0]}} frames, {{rows[{len(rows) - 1}][2]}} "
                 f"MiB at {{rows[{len(rows) - 1}][0]}}",
        notes=f"{seq.name} played forth and back; statuses: "
              + ", ".join(f"{n} {s}" for s, n in status.items())
              + f"; latency median {np.median(lat):.1f} ms, 95th percentile "
                f"{np.percentile(lat, 95):.1f} ms ({os.cpu_count()} CPUs).")


def bench_memory(args: argparse.Namespace) -> None:
    from omni_sfm.synth.simulate import SimulationOptions, simulate_manhattan

    F = args.frames
    sim = simulate_manhattan(SimulationOptions(world="manhattan", num_views=F,
                                               path_length=0.05 * (F - 1), noise_deg=0.05,
                                               line_density=6.0, seed=args.seed))
    tr = sim.tracks
    order = np.argsort(tr.obs_frame, kind="stable")
    starts = np.searchsorted(tr.obs_frame[order], np.arange(F + 1))
    est = OnlineEstimator()
    status: Counter[str] = Counter()
    checkpoints = sorted({min(1000, F), min(5000, F), F})
    peaks: dict[int, tuple[float, float]] = {}
    rows: list[list[object]] = []
    tracemalloc.start()
    t0 = time.perf_counter()
    lat = np.zeros(F)  # preallocated: a growing list would be the only thing that grows
    for k in range(F):
        o = order[starts[k]:starts[k + 1]]
        p = est.add(tr.track_ids[tr.obs_track[o]], tr.obs_normal[o], timestamp=float(k))
        status[str(p.status)] += 1
        lat[k] = p.latency_ms
        if k + 1 in checkpoints:
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
            now, peak = (x / 2**20 for x in tracemalloc.get_traced_memory())
            peaks[k + 1] = (peak, rss)
            rows.append([k + 1, now, peak, rss, est.num_frames_held, est.num_lines])
            print(f"{k + 1} frames: traced now {now:.2f} MiB, traced peak {peak:.2f} MiB, "
                  f"process peak RSS {rss:.1f} MiB; holding {est.num_frames_held} frames and "
                  f"{est.num_lines} lines; {time.perf_counter() - t0:.0f} s", flush=True)
    tracemalloc.stop()
    print(f"simulated walk: {F} frames, {0.05 * (F - 1):.0f} m, {tr.num_tracks} lines; "
          "statuses: " + ", ".join(f"{n} {s}" for s, n in status.items()))
    print(f"latency per frame (ms, under tracemalloc): median {np.median(lat):.1f}, 95th "
          f"percentile {np.percentile(lat, 95):.1f}")
    if len(checkpoints) > 1:
        a, b = peaks[checkpoints[0]], peaks[checkpoints[-1]]
        print(f"peak at {checkpoints[-1]} frames / peak at {checkpoints[0]}: traced "
              f"{b[0] / a[0]:.3f}, RSS {b[1] / a[1]:.3f}")
    mib = {"format": ".2f"}
    write_log(args, "bench_track_memory", "The online estimator's memory over a simulated walk", [
        {"label": "after (frames)", "format": ","}, {"label": "traced now (MiB)", **mib},
        {"label": "traced peak (MiB)", **mib},
        {"label": "process peak RSS (MiB)", "format": ".1f"}, "frames held", "lines held"], rows,
        headline=f"traced {{rows[{len(rows) - 1}][1]}} MiB after {{rows[{len(rows) - 1}][0]}} "
                 f"frames (peak {{rows[{len(rows) - 1}][2]}} MiB)",
        notes=f"A simulated walk of {F} frames, {0.05 * (F - 1):.0f} m, {tr.num_tracks} lines "
              "(tracemalloc on); statuses: "
              + ", ".join(f"{n} {s}" for s, n in status.items()) + ".")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--input", help="a rendered sequence (images/, camera.yaml, "
                                    "groundtruth.tum); default: render one")
    ap.add_argument("--camera", default="hyperboloid",
                    choices=["hyperboloid", "equirectangular"])
    ap.add_argument("--frames", type=int, default=None,
                    help="frames to render (default 200) or, with --memory, to simulate "
                         "(default 10000)")
    ap.add_argument("--width", type=int, default=None)
    ap.add_argument("--height", type=int, default=None)
    ap.add_argument("--seed", type=int, default=None,
                    help="default: 1 (hyperboloid), 2 (equirectangular), 0 (--memory)")
    ap.add_argument("--cache", default="/tmp/omni_sfm_bench_track", help="render cache folder")
    ap.add_argument("--memory", action="store_true",
                    help="memory over a long simulated walk instead (see above)")
    ap.add_argument("--memory-images", type=int, default=None, metavar="N",
                    help="memory of the whole tracker on N frames of the rendered corridor "
                         "played forth and back (see above)")
    add_log_arguments(ap)
    args = ap.parse_args()
    keep_freed_memory()  # as the command does
    if args.memory_images:
        args.frames = args.frames or 200
        if args.seed is None:
            args.seed = 1 if args.camera == "hyperboloid" else 2
        bench_memory_images(args, args.memory_images)
        return
    if args.memory:
        args.frames = args.frames or 10000
        args.seed = 0 if args.seed is None else args.seed
        bench_memory(args)
        return
    args.frames = args.frames or 200
    if args.seed is None:
        args.seed = 1 if args.camera == "hyperboloid" else 2
    bench_images(args)


if __name__ == "__main__":
    try:
        main()
    except OmniSfmError as exc:  # a missing folder or camera file: one line, not a traceback
        raise SystemExit(f"bench.track: {exc}") from None
