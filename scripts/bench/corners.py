"""How well corner tracks (``omni_sfm.corners``) follow the scene: on a rendered sequence, each
track is triangulated with the ground-truth poses (least-squares ray intersection) and the
angle between each observation's ray and the ray to that point is its residual, in pixels of
the camera's angular resolution. Drift shows as residuals that grow with a track's age.

    .venv/bin/python -m scripts.bench.corners --render W/render --frames 60 \\
        '{}' '{"anchor_max_px": 0.5}' '{"anchor_max_px": 0.5, "window_px": 7}'

Each argument is a JSON object of ``CornerTrackOptions`` fields (one tracking run each);
``refine`` names the settings ``omni-sfm refine --features klt`` uses. Frames are the render's
images (not mirrored), the mask the camera's valid region shrunk by 3 px.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from omni_sfm.cameras import load_camera
from omni_sfm.corners import CornerTrackOptions, track_corners
from omni_sfm.poses import read_tum
from omni_sfm.refine import RefineOptions
from omni_sfm.refine.pipeline import klt_tracking
from omni_sfm.refine.triangulation import angular_resolution_rad
from scripts.benchlib import add_log_arguments, write_log


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--render", type=Path, required=True, help="omni-sfm render output folder")
    p.add_argument("--frames", type=int, default=60, help="first N frames")
    p.add_argument("options", nargs="+", help="CornerTrackOptions as JSON, or 'refine'")
    add_log_arguments(p)
    args = p.parse_args()
    rows: list[list[object]] = []
    cam = load_camera(args.render / "camera.yaml")
    gt = read_tum(args.render / "groundtruth.tum")
    names = sorted(q.name for q in (args.render / "images").iterdir())[:args.frames]
    mask = cv2.erode((cam.valid_mask() * 255).astype(np.uint8), np.ones((7, 7), np.uint8))
    imgs = []
    for n in names:
        img = cv2.imread(str(args.render / "images" / n), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise SystemExit(f"{args.render / 'images' / n}: cannot read")
        imgs.append(img)
    res = angular_resolution_rad(cam)
    for text in args.options:
        o = klt_tracking(RefineOptions().max_corners) if text == "refine" else \
            CornerTrackOptions(**json.loads(text))
        t0 = time.perf_counter()
        t = track_corners(imgs, mask, o)
        dt = time.perf_counter() - t0
        w = np.einsum("kij,kj->ki", gt.rotations[t.frame], cam.rays_from_pixels(t.uv))
        c = gt.positions[t.frame]
        ids, inv = np.unique(t.track, return_inverse=True)
        P = np.eye(3)[None] - w[:, :, None] * w[:, None, :]
        A = np.zeros((len(ids), 3, 3))
        b = np.zeros((len(ids), 3))
        np.add.at(A, inv, P)
        np.add.at(b, inv, np.einsum("kij,kj->ki", P, c))
        ok = (np.bincount(inv) >= 3) & (np.linalg.cond(A) < 1e6)
        X = np.full((len(ids), 3), np.nan)
        X[ok] = np.linalg.solve(A[ok], b[ok][:, :, None])[:, :, 0]
        v = X[inv] - c
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        r = np.arccos(np.clip(np.sum(v * w, 1), -1.0, 1.0)) / res
        good = ok[inv] & np.isfinite(r)
        first = np.full(len(ids), len(imgs))
        np.minimum.at(first, inv, t.frame)
        age = t.frame - first[inv]
        print(f"{text}: {dt:.1f} s, {len(t.track)} observations, {len(ids)} tracks; residual "
              f"px: median {np.median(r[good]):.3f}, 90th percentile "
              f"{np.percentile(r[good], 90):.3f}, above 2 px {np.mean(r[good] > 2):.3f}")
        rows.append([text, dt, len(t.track), len(ids), np.median(r[good]),
                     np.percentile(r[good], 90), 100 * np.mean(r[good] > 2)])
        if text == "refine":
            print(f"  refine's settings: {asdict(o)}")
        for lo, hi in [(0, 15), (15, 30), (30, 60), (60, 10**9)]:
            s = good & (age >= lo) & (age < hi)
            if s.any():
                print(f"  age {lo}-{hi if hi < 10**9 else ''} frames: {int(s.sum())} "
                      f"observations, median {np.median(r[s]):.3f} px")
    write_log(args, "bench_corners", "Corner tracks against the true poses", [
        "options", {"label": "time (s)", "format": ".1f"}, "observations", "tracks",
        {"label": "residual median (px)", "format": ".3f"},
        {"label": "90th percentile (px)", "format": ".3f"},
        {"label": "above 2 px (%)", "format": ".1f"}], rows,
        headline="{rows[0][0]}: residual median {rows[0][4]} px",
        notes=f"The first {len(imgs)} frames of {args.render.name}; each track triangulated "
              "on the true poses.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
