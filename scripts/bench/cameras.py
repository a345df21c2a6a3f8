"""Speed of the camera models on a 1600 x 800 image (1.28 million pixels).

Run ``OPENBLAS_NUM_THREADS=1 python -m scripts.bench.cameras [--repeats N] [--models NAME ...]``;
prints the median wall time and, in brackets, the median CPU time of this process
(``time.process_time``) of ``rays_from_pixels`` on every pixel centre, ``pixels_from_rays`` on the
valid rays, the first (computing) and a later (cached) ``pixel_grid_rays``, and the wall time of
``valid_mask``. On a loaded machine the CPU time is the figure to compare. Writes the record
``docs/benchmarks/bench_cameras.json`` (docs/cameras.md renders it).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Callable
from functools import partial

import numpy as np

from omni_sfm.cameras import (
    CameraModel,
    DoubleSphereCamera,
    EquirectangularCamera,
    EUCMCamera,
    HyperboloidCamera,
    OCamCamera,
    OpenCVFisheyeCamera,
    UnifiedCamera,
)
from scripts.benchlib import add_log_arguments, write_log

W, H = 1600, 800


def bench_cameras() -> dict[str, CameraModel]:
    """One camera per model (two for unified: with and without radtan distortion)."""
    c: dict[str, int] = {"width": W, "height": H}
    return {
        "hyperboloid": HyperboloidCamera(**c, cx=800, cy=400, px=0.0075, py=0.0075, f=8.0,
                                         alpha=14.0, beta=19.4, inner_radius=64,
                                         outer_radius=390),
        "unified": UnifiedCamera(**c, fx=700, fy=700, cx=800, cy=400, xi=0.9),
        "unified+radtan": UnifiedCamera(**c, fx=900, fy=898, cx=800, cy=400, xi=1.3,
                                        k1=-0.17, k2=0.035, p1=0.0013, p2=-0.0009),
        "eucm": EUCMCamera(**c, fx=380, fy=380, cx=800, cy=400, alpha=0.62, beta=1.1),
        "double_sphere": DoubleSphereCamera(**c, fx=350, fy=350, cx=800, cy=400, xi=-0.19,
                                            alpha=0.59),
        "equirectangular": EquirectangularCamera(**c),
        "ocam": OCamCamera(width=W, height=H, cx=800, cy=400, c=1.0003, d=0.0003, e=-0.0002,
                           pol=(-330.0, 0.0, 1.2e-3, -1e-7, 2e-10)),
        "opencv_fisheye": OpenCVFisheyeCamera(**c, fx=300, fy=300, cx=800, cy=400, k1=0.03,
                                              k2=-0.012, k3=0.002, k4=-0.0002),
    }


def timed(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """Median wall time and median CPU time of this process, in ms, over ``repeats`` calls.

    On a machine shared with other jobs the wall time grows with their load; the CPU time
    approximates the wall time on an idle machine (numpy runs these kernels on one thread)."""
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return 1e3 * float(np.median(wall)), 1e3 * float(np.median(cpu))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=7)
    cams = bench_cameras()
    ap.add_argument("--models", nargs="+", choices=sorted(cams), default=list(cams),
                    help="time only these (default: all)")
    add_log_arguments(ap)
    args = ap.parse_args(argv)
    rows: list[list[object]] = []
    v, u = np.mgrid[0:H, 0:W]
    uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    print(f"{W} x {H} = {len(uv)} pixels; median of {args.repeats} runs: wall ms [CPU ms]")
    print(f"{'model':16s} {'rays_from_pixels':>18s} {'pixels_from_rays':>18s} "
          f"{'grid 1st':>16s} {'grid cached':>12s} {'valid_mask':>11s}")
    for name in args.models:
        cam = cams[name]
        rays = cam.rays_from_pixels(uv)
        ok = rays[np.isfinite(rays).all(axis=1)]
        r2p = timed(partial(cam.rays_from_pixels, uv), args.repeats)
        p2r = timed(partial(cam.pixels_from_rays, ok), args.repeats)
        # a fresh copy per call: the first pixel_grid_rays() computes, later ones are cached
        fresh = iter([dataclasses.replace(cam) for _ in range(args.repeats)])
        first = timed(lambda: next(fresh).pixel_grid_rays(), args.repeats)  # noqa: B023
        cached = timed(cam.pixel_grid_rays, args.repeats)
        mask = timed(cam.valid_mask, args.repeats)
        print(f"{name:16s} {r2p[0]:8.1f} [{r2p[1]:6.1f}] {p2r[0]:8.1f} [{p2r[1]:6.1f}] "
              f"{first[0]:7.1f} [{first[1]:6.1f}] {cached[0]:12.4f} {mask[0]:11.2f}")
        rows.append([name, r2p[0], r2p[1], p2r[0], p2r[1], first[0], first[1], cached[0],
                     mask[0]])
    ms = {"format": ".1f"}
    write_log(args, "bench_cameras", f"Camera models on {W} x {H} pixels", [
        "model", {"label": "rays_from_pixels wall ms", **ms}, {"label": "CPU ms", **ms},
        {"label": "pixels_from_rays wall ms", **ms}, {"label": "CPU ms", **ms},
        {"label": "grid, first call (ms)", **ms}, {"label": "CPU ms", **ms},
        {"label": "grid, cached (ms)", "format": ".4f"},
        {"label": "valid_mask (ms)", "format": ".2f"}], rows,
        headline=", ".join(f"{{rows[{k}][0]}} {{rows[{k}][1]}} ms" for k in range(len(rows))),
        notes=f"Median of {args.repeats} runs: wall time and the process's CPU time "
              "(`time.process_time`), which is about what the wall time comes to on an idle "
              "core (numpy runs these kernels on one thread).")


if __name__ == "__main__":
    main()
