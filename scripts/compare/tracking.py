"""Tracking options side by side: which partners they find and what they cost, on rendered
sequences with ground truth.

Extracts the lines of each sequence once, then runs :class:`LineTracker` with the default
:class:`TrackingOptions` and with each ``--variant`` on the same lines, and prints per run: the
median CPU ms a frame of ``add_frame`` (this thread, OpenCV single-threaded), the links (two
observations of one track in consecutive observed frames), how many of them the defaults also
made, and the wrong links: links whose second observation is more than 1 deg from the true NV of
the 3D line the first one is nearest to (first within 0.5 deg of some true line, else the link is
not judged). Wrong links are what a tracker must not add: one track holding two 3D lines.

    .venv/bin/python -m scripts.compare.tracking --input WORK/<sequence> --frames 200 \\
        --variant "klt_window=11,klt_iterations=10,fb_max_px=1,max_samples_per_line=16"

``--input`` takes folders rendered by ``omni-sfm render`` or ``scripts/eval/footage.py``
(``images/``, ``camera.yaml``, ``groundtruth.tum``, ``lines3d.json``); several may be given.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from omni_sfm.cameras import load_camera
from omni_sfm.frames import read_frames
from omni_sfm.lines.extract import ExtractedLines, LineExtractor
from omni_sfm.lines.track import LineTracker, TrackedObservations, TrackingOptions
from omni_sfm.lines3d import read_lines3d
from omni_sfm.poses import read_tum
from scripts.bench.frontend import true_nvs
from scripts.benchlib import add_log_arguments, write_log

KNOWN_DEG = 0.5
WRONG_DEG = 1.0


def parse_variant(text: str) -> dict[str, Any]:
    """``"a=1,b=2.5"`` -> ``{"a": 1, "b": 2.5}`` (numbers as int or float)."""
    out: dict[str, Any] = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, _, val = item.partition("=")
        if not hasattr(TrackingOptions(), key):
            raise SystemExit(f"compare_tracking: TrackingOptions has no option {key!r}")
        out[key] = float(val) if any(c in val for c in ".e") else int(val)
    return out


def true_normals(seq: Path, frames: int) -> list[np.ndarray]:
    """Per frame, the unit NVs (camera frame) of the renderer's 3D lines."""
    gt = read_tum(seq / "groundtruth.tum")
    lines3d = read_lines3d(seq / "lines3d.json")
    return [true_nvs(lines3d.starts, lines3d.ends, gt.rotations[k], gt.positions[k])
            for k in range(frames)]


def links(obs: TrackedObservations) -> set[tuple[int, int, int, int]]:
    t, f, li = obs.track, obs.frame, obs.line_index
    same = np.flatnonzero(t[1:] == t[:-1])
    return {(int(f[a]), int(li[a]), int(f[a + 1]), int(li[a + 1])) for a in same}


def wrong_links(found: set[tuple[int, int, int, int]], lines: list[ExtractedLines],
                truth: list[np.ndarray]) -> tuple[int, int]:
    """(wrong, judged) links, see the module's docstring."""
    wrong = judged = 0
    for f0, l0, f1, l1 in found:
        c = np.abs(truth[f0] @ lines[f0].normals[l0])
        i = int(np.argmax(c))
        if np.degrees(np.arccos(min(1.0, c[i]))) > KNOWN_DEG:
            continue
        judged += 1
        c1 = abs(float(truth[f1][i] @ lines[f1].normals[l1]))
        wrong += int(np.degrees(np.arccos(min(1.0, c1))) > WRONG_DEG)
    return wrong, judged


def run(grey: list[np.ndarray], lines: list[ExtractedLines],
        options: TrackingOptions) -> tuple[TrackedObservations, float]:
    tracker = LineTracker(options)
    ms = []
    for g, ln in zip(grey, lines, strict=True):
        c = time.thread_time()
        tracker.add_frame(g, ln)
        ms.append(1000 * (time.thread_time() - c))
    return tracker.finish(), float(np.median(ms[1:])) if len(ms) > 1 else 0.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--input", type=Path, nargs="+", required=True,
                    help="rendered sequence folders")
    ap.add_argument("--frames", type=int, default=200, help="first frames of each (default 200)")
    ap.add_argument("--variant", action="append", default=[],
                    help='TrackingOptions to compare with the defaults, "key=value,..."')
    add_log_arguments(ap)
    args = ap.parse_args()
    rows: list[list[object]] = []
    cv2.setNumThreads(1)
    variants = [parse_variant(v) for v in args.variant]
    for seq in args.input:
        cam = load_camera(seq / "camera.yaml")
        extractor = LineExtractor(cam)
        grey, lines = [], []
        for i, (_, _, g) in enumerate(read_frames(seq / "images", size=(cam.width, cam.height))):
            if i >= args.frames:
                break
            grey.append(g)
            lines.append(extractor.extract(g))
        truth = true_normals(seq, len(grey))
        print(f"{seq.name} ({len(grey)} frames)")
        ref, ref_ms = run(grey, lines, TrackingOptions())
        ref_links = links(ref)
        for name, opts in [("defaults", {}), *((str(v), v) for v in variants)]:
            obs, ms = (ref, ref_ms) if not opts else run(grey, lines, TrackingOptions(**opts))
            found = links(obs)
            wrong, judged = wrong_links(found, lines, truth)
            print(f"  {name}: {ms:.2f} ms a frame, links {len(found)} (with the defaults' "
                  f"{len(found & ref_links)}, new {len(found - ref_links)}, missing "
                  f"{len(ref_links - found)}), wrong {wrong} of {judged} judged, tracks "
                  f"{obs.num_tracks}, observations {len(obs.track)}")
            rows.append([seq.name, name, ms, len(found), len(found & ref_links), wrong, judged,
                         obs.num_tracks])
    write_log(args, "compare_tracking", "Tracking options side by side", [
        "sequence", "options", {"label": "tracking ms a frame", "format": ".2f"}, "links",
        "with the defaults'", "wrong", "judged", "tracks"], rows,
        headline="{rows[0][1]}: {rows[0][2]} ms a frame, {rows[0][3]} links, {rows[0][5]} wrong",
        notes=f"The first {args.frames} frames of each sequence.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
