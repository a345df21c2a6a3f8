"""Benchmark and accuracy of the line front end (extraction + tracking) on rendered sequences.

Renders (or reuses) a sequence with omni_sfm.synth.render, runs ``track_lines`` and prints:
median milliseconds per frame for reading, extraction and tracking (against the paper's 5 ms
per frame for line tracking on a Core i7 975), the NV error of every extracted line and of every
tracked observation against the renderer's true 3D lines (``lines3d.json`` with
``groundtruth.tum``), the share of false lines (NV further than 0.5 deg from every true NV), and
track statistics. ``--stages`` adds where the CPU time goes: each stage of the extraction and the
KLT calls of the tracking, in one more pass over the frames. Writes its row (one sequence) of
the records ``docs/benchmarks/bench_frontend.json`` (time, accuracy) and
``bench_frontend_tracks.json`` (tracks); docs/frontend.md renders them.

    .venv/bin/python -m scripts.bench.frontend --frames 200
    .venv/bin/python -m scripts.bench.frontend --camera equirectangular --frames 50
    .venv/bin/python -m scripts.bench.frontend --camera equirectangular --size 1920x960
    .venv/bin/python -m scripts.bench.frontend --input path/to/rendered/sequence
    .venv/bin/python -m scripts.bench.frontend --frames 50 --threads 1 --stages
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras import load_camera
from omni_sfm.frames import read_frames
from omni_sfm.libs import keep_freed_memory
from omni_sfm.lines import extract as extract_module
from omni_sfm.lines.extract import LineExtractor
from omni_sfm.lines.frontend import FrontEndOptions, track_lines
from omni_sfm.lines.track import LineTracker, TrackingOptions
from omni_sfm.lines3d import read_lines3d
from omni_sfm.poses import read_tum
from scripts.benchlib import add_log_arguments, write_log

PAPER_MS = 5.0
FALSE_DEG = 0.5


def nv_errors_deg(normals: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Smallest unsigned angle (deg) from each normal to any true NV."""
    if len(normals) == 0:
        return np.zeros(0)
    c = np.abs(normals @ truth.T).max(axis=1)
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


def true_nvs(starts: np.ndarray, ends: np.ndarray, world_from_cam: np.ndarray,
             position: np.ndarray) -> np.ndarray:
    a = (starts - position) @ world_from_cam
    b = (ends - position) @ world_from_cam
    n = np.cross(a, b)
    return np.asarray(n / np.linalg.norm(n, axis=1, keepdims=True))


def describe(name: str, err: np.ndarray) -> str:
    if len(err) == 0:
        return f"{name}: none"
    return (f"{name}: {len(err)}, NV error median {np.median(err):.3f} deg, "
            f"p90 {np.percentile(err, 90):.3f} deg, false (> {FALSE_DEG} deg) "
            f"{100 * np.mean(err > FALSE_DEG):.1f} %")


# (owner, attribute, label) of the timed stages, in the order they run; an indented label is a
# part of the stage above it
EXTRACTION_STAGES: list[tuple[Any, str, str]] = [
    (LineExtractor, "image_stats", "grey-level statistics (histogram)"),
    (LineExtractor, "_edge_points", "edge points: blur, gradients, Canny, corner test"),
    (LineExtractor, "_segments", "segments (orientation-linked components)"),
    (extract_module, "_oriented_components", "  of which the components"),
    (extract_module._EdgePoints, "subpixel", "sub-pixel positions"),
    (LineExtractor, "_ransac", "great circles (MSAC, refits)"),
    (LineExtractor, "_split_gaps", "cuts at gaps"),
    (LineExtractor, "_merge", "merges"),
    (LineExtractor, "_trim_ends", "end trimming"),
    (LineExtractor, "_package", "final fits, ordering, uncertainties"),
]


@contextmanager
def timed(stages: list[tuple[Any, str, str]], acc: dict[str, float]) -> Iterator[None]:
    """Adds the CPU seconds spent in each ``owner.attribute`` to ``acc[label]`` meanwhile."""
    saved = [(owner, name, getattr(owner, name)) for owner, name, _ in stages]

    def wrap(f: Callable[..., Any], label: str) -> Callable[..., Any]:
        @functools.wraps(f)
        def g(*a: Any, **k: Any) -> Any:
            c = time.process_time()
            try:
                return f(*a, **k)
            finally:
                acc[label] = acc.get(label, 0.0) + time.process_time() - c
        return g

    try:
        for (owner, name, f), (_, _, label) in zip(saved, stages, strict=True):
            setattr(owner, name, wrap(f, label))
        yield
    finally:
        for owner, name, f in saved:
            setattr(owner, name, f)


def print_stages(src: Path, cam: Any, options: FrontEndOptions) -> None:
    """CPU ms per frame of each stage (one more pass: extraction, then tracking)."""
    import cv2

    grey = [image for _, _, image in read_frames(src, size=(cam.width, cam.height))]
    extractor = LineExtractor(cam, options.extraction)
    acc: dict[str, float] = {}
    stages = [*EXTRACTION_STAGES, (type(cam), "rays_from_pixels", "rays")]
    with timed(stages, acc):
        c = time.process_time()
        lines = [extractor.extract(g) for g in grey]
        total = time.process_time() - c
    n = len(grey)
    print(f"extraction, CPU ms per frame (mean of {n} frames): {1000 * total / n:.2f}")
    for _, _, label in stages:
        print(f"  {label:52s} {1000 * acc.get(label, 0.0) / n:6.2f}")
    inner = sum(v for k, v in acc.items() if not k.startswith(" "))
    print(f"  {'the rest':52s} {1000 * (total - inner) / n:6.2f}")
    tracker = LineTracker(options.tracking)
    acc.clear()
    with timed([(cv2, "calcOpticalFlowPyrLK", "KLT")], acc):
        c = time.process_time()
        for g, ln in zip(grey, lines, strict=True):
            tracker.add_frame(g, ln)
        total = time.process_time() - c
    print(f"tracking, CPU ms per frame: {1000 * total / n:.2f}, of which KLT (OpenCV) "
          f"{1000 * acc.get('KLT', 0.0) / n:.2f}")


def _parser() -> argparse.ArgumentParser:
    """The command line's arguments."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--input", type=Path, help="a rendered sequence folder (else render one)")
    ap.add_argument("--camera", default="hyperboloid", help="hyperboloid or equirectangular")
    ap.add_argument("--scene", default="corridor", help="corridor or room")
    ap.add_argument("--textured", action="store_true")
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--size", help="image size WxH of the render (default: the camera's "
                    "preset, 800x600 hyperboloid, 1600x800 equirectangular)")
    ap.add_argument("--cache", type=Path, default=Path(".cache/bench_frontend"),
                    help="where rendered sequences are kept between runs")
    ap.add_argument("--no-fb", action="store_true", help="skip the backward KLT pass")
    ap.add_argument("--threads", type=int, default=0, help="OpenCV threads (0: its default)")
    ap.add_argument("--workers", type=int, default=1,
                    help="extraction worker processes (1: all in this process, the per-frame "
                         "CPU figures; 0: the front end's default, one per core)")
    ap.add_argument("--stages", action="store_true",
                    help="also print the CPU time of each stage (one more pass over the frames)")
    add_log_arguments(ap)
    return ap


def _sequence(ap: argparse.ArgumentParser, args: argparse.Namespace) -> Path:
    """The sequence folder: ``--input``, else a render kept in ``--cache``."""
    if args.input is not None:
        return Path(args.input)
    from omni_sfm.synth.render import RenderOptions, render_sequence

    width = height = None
    if args.size:
        try:
            width, height = (int(v) for v in args.size.lower().split("x"))
        except ValueError:
            ap.error(f"--size: WxH, e.g. 1920x960, got {args.size!r}")
    tag = (f"{args.scene}_{args.camera}_{args.frames}{'_tex' if args.textured else ''}"
           f"{f'_{width}x{height}' if args.size else ''}")
    seq = Path(args.cache / tag)
    if not (seq / "lines3d.json").exists():
        print(f"rendering {tag} into {seq} ...", file=sys.stderr)
        render_sequence(seq, RenderOptions(scene=args.scene, camera=args.camera,
                                           frames=args.frames, textured=args.textured,
                                           width=width, height=height),
                        overwrite=True)
    return seq


def main() -> int:
    ap = _parser()
    args = ap.parse_args()
    seq = _sequence(ap, args)
    cam = load_camera(seq / "camera.yaml")
    gt = read_tum(seq / "groundtruth.tum")
    lines3d = read_lines3d(seq / "lines3d.json")
    src = seq / "images" if (seq / "images").is_dir() else seq / "video.mp4"

    opts = FrontEndOptions(progress=False,
                           tracking=TrackingOptions(fb_max_px=0.0) if args.no_fb
                           else TrackingOptions(),
                           workers=args.workers or None)
    keep_freed_memory()  # as the omni-sfm command does
    if args.threads:
        import cv2

        cv2.setNumThreads(args.threads)
    t0, c0 = time.perf_counter(), time.process_time()
    res = track_lines(read_frames(src, size=(cam.width, cam.height)), cam, opts)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    t = res.timings_ms
    ext, trk = np.median(t["extract"]), np.median(t["track"])
    print(f"sequence: {seq} ({cam.model} {cam.width}x{cam.height}, {res.tracks.num_frames} "
          f"frames)")
    print(f"median ms/frame (wall): read {np.median(t['read']):.2f}, extract {ext:.2f}, "
          f"track {trk:.2f}, extract+track {ext + trk:.2f} (paper: {PAPER_MS:.0f} ms, C++)")
    ec, tc = np.median(t["extract_cpu"]), np.median(t["track_cpu"])
    print(f"median ms/frame (CPU of the thread that did it; the work itself with --threads 1 "
          f"or workers): "
          f"extract {ec:.2f}, track {tc:.2f}, extract+track {ec + tc:.2f}")
    nf = res.tracks.num_frames
    print(f"whole front end: {wall:.2f} s wall ({1000 * wall / nf:.1f} ms/frame incl. reading "
          f"PNGs), CPU time {1000 * cpu / nf:.1f} ms/frame (this process's threads; "
          f"{os.cpu_count()} CPUs, workers {args.workers or 'default'})")

    extractor = LineExtractor(cam)
    all_err = []
    obs_err = []
    tr = res.tracks
    for f, (number, _, img) in enumerate(read_frames(src)):
        k = int(res.frame_numbers[f]) if f < len(res.frame_numbers) else number
        truth = true_nvs(lines3d.starts, lines3d.ends, gt.rotations[k], gt.positions[k])
        all_err.append(nv_errors_deg(extractor.extract(img).normals, truth))
        obs_err.append(nv_errors_deg(tr.obs_normal[tr.obs_frame == f], truth))
    lines_err, obs = np.concatenate(all_err), np.concatenate(obs_err)
    print(describe("extracted lines", lines_err))
    print(describe("tracked observations", obs))
    lengths = res.track_lengths()
    print(f"tracks: {tr.num_tracks}, observations {tr.num_observations}, length median "
          f"{np.median(lengths):.0f} frames (max {lengths.max()}), lines per frame median "
          f"{np.median(res.lines_extracted):.0f}, continued per frame median "
          f"{np.median(res.lines_continued[1:]):.0f}")
    if args.stages:
        print_stages(src, cam, opts)
    texture = "textured " if args.textured else ""
    sequence = f"{texture}{args.scene}, {cam.model} {cam.width}x{cam.height}, {nf} frames"
    write_log(args, "bench_frontend_tracks", "The line front end's tracks", [
        "sequence", "lines a frame (median)", "continued a frame (median)", "tracks",
        "track length median (frames)", "longest track (frames)"],
        [[sequence, round(float(np.median(res.lines_extracted))),
          round(float(np.median(res.lines_continued[1:]))),
          tr.num_tracks, round(float(np.median(lengths))), int(lengths.max())]],
        headline="{rows[0][3]} tracks, {rows[0][4]} frames long (median; {rows[0][0]})",
        notes="Lines extracted and lines continued from the frame before, per frame.",
        merge=True)
    write_log(args, "bench_frontend", "The line front end: CPU time and accuracy", [
        "sequence", {"label": "extraction (CPU ms a frame)", "format": ".2f"},
        {"label": "tracking", "format": ".2f"}, {"label": "extraction + tracking", "format": ".2f"},
        "lines", {"label": "NV error median (deg)", "format": ".3f"},
        {"label": "false (%)", "format": ".1f"}, "tracked observations",
        {"label": "tracked: NV error median (deg)", "format": ".3f"},
        {"label": "tracked: false (%)", "format": ".1f"}],
        [[sequence, ec, tc,
          ec + tc, len(lines_err), np.median(lines_err), 100 * np.mean(lines_err > FALSE_DEG),
          len(obs), np.median(obs), 100 * np.mean(obs > FALSE_DEG)]],
        headline="{rows[0][3]} ms CPU a frame (corridor, 800x600; paper: 5 ms, C++); "
                 "NV error median {rows[0][8]} deg, {rows[0][9]} % of lines false",
        notes="Median CPU ms a frame of the thread that did the work (OpenCV single-threaded "
              "with `--threads 1`); a line is false when its NV is more than 0.5 deg from "
              "every true NV.", merge=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
