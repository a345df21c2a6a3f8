#!/usr/bin/env python
"""The same walk in other variants of its input: does the estimator come through it right
whatever the frame order, the first frame and the last bits of the normals?

Runs `estimate_poses` (the defaults, one worker) on a `tracks.json` as it is, in reversed frame
order (timestamps kept), without its first 10, 25, 50 or 100 frames, with 1e-9 noise on its
normals (seeds 1-3), reversed without its first 50 frames, and without its first 25 frames with
1e-9 noise, and prints for each the frames posed and trusted, the largest rotation error and
the ATE against the ground truth (of the trusted frames and of every posed frame), how far its
poses are from those of the tracks as they are (the largest rotation difference and the RMS
position difference on the frames both pose, after a similarity alignment), and the wall time.
Writes the record ``docs/benchmarks/eval_variants.json``. On the 2,000-frame office walk of
`scripts.bench.init` (its `lines_2000` and `render_2000_*` folders):

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.eval.variants \\
        --tracks W/lines_2000/tracks.json --groundtruth W/render_2000_22.99m/groundtruth.tum
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from omni_sfm.estimate.pipeline import EstimationOptions, estimate_poses, trusted  # noqa: E402
from omni_sfm.estimate.segments import frame_range  # noqa: E402
from omni_sfm.evaluate import match_reflection, trajectory_errors  # noqa: E402
from omni_sfm.geometry import normalize  # noqa: E402
from omni_sfm.lines.tracks import LineTracks, read_tracks, reversed_frames  # noqa: E402
from omni_sfm.poses import Trajectory, read_tum  # noqa: E402
from scripts.benchlib import add_log_arguments, write_log  # noqa: E402


def perturbed(tracks: LineTracks, seed: int, size: float = 1e-9) -> LineTracks:
    """``tracks`` with ``size`` (normal draws of generator ``seed``) added to every normal."""
    rng = np.random.default_rng(seed)
    n = tracks.obs_normal + size * rng.normal(size=tracks.obs_normal.shape)
    return replace(tracks, obs_normal=normalize(n))


def reversed_order(tracks: LineTracks) -> LineTracks:
    """``tracks`` in reversed frame order, each frame keeping its timestamp."""
    return replace(reversed_frames(tracks), timestamps=tracks.timestamps[::-1].copy())


def _without(tracks: LineTracks, first: int) -> LineTracks:
    return frame_range(tracks, first, tracks.num_frames)[0]


def variants(tracks: LineTracks) -> list[tuple[str, LineTracks]]:
    """The variants of the module docstring, by name."""
    out = [("as they are", tracks), ("reversed", reversed_order(tracks))]
    out += [(f"first {k} dropped", _without(tracks, k)) for k in (10, 25, 50, 100)]
    out += [(f"1e-9 noise, seed {s}", perturbed(tracks, s)) for s in (1, 2, 3)]
    out.append(("reversed, first 50 dropped", reversed_order(_without(tracks, 50))))
    out.append(("first 25 dropped, 1e-9 noise", perturbed(_without(tracks, 25), 4)))
    return out


def _apart(a: Trajectory, b: Trajectory) -> tuple[float, float]:
    """Largest rotation difference (deg) and RMS position difference (% of the path) of ``b``
    from ``a`` on the frames both pose (by timestamp), after the similarity alignment."""
    common = np.intersect1d(a.timestamps, b.timestamps)
    a = a.subset(np.isin(a.timestamps, common))
    b = b.subset(np.isin(b.timestamps, common))
    e = trajectory_errors(match_reflection(b, a), a)
    return e.rot_max_deg, 100 * e.ate_rel


COLUMNS: list[str | dict] = [
    "variant", "posed", "trusted", {"label": "trusted: rotation max (deg)", "format": ".3f"},
    {"label": "trusted: ATE (%)", "format": ".3f"},
    {"label": "all posed: rotation max (deg)", "format": ".3f"},
    {"label": "all posed: ATE (%)", "format": ".3f"},
    {"label": "from the tracks as they are: rotation (deg)", "format": ".4f"},
    {"label": "from the tracks as they are: position (%)", "format": ".4f"},
    {"label": "time (s)", "format": ".0f"}]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tracks", type=Path, required=True, help="tracks.json of init --lines")
    p.add_argument("--groundtruth", type=Path, required=True, help="groundtruth.tum")
    add_log_arguments(p)
    args = p.parse_args()
    gt = read_tum(args.groundtruth)
    print("| " + " | ".join(c if isinstance(c, str) else c["label"] for c in COLUMNS) + " |")
    print("|" + "---|" * len(COLUMNS))
    rows: list[list[object]] = []
    first: Trajectory | None = None
    for name, tracks in variants(read_tracks(args.tracks)):
        t0 = time.perf_counter()
        res = estimate_poses(tracks, EstimationOptions(workers=1))
        wall = time.perf_counter() - t0
        keep = trusted(res)
        every = trajectory_errors(res.trajectory, gt)
        kept = trajectory_errors(res.trajectory.subset(keep), gt)
        first = res.trajectory if first is None else first
        rot, pos = _apart(first, res.trajectory)
        rows.append([name, f"{int(res.estimated.sum())}/{tracks.num_frames}", int(keep.sum()),
                     kept.rot_max_deg, 100 * kept.ate_rel, every.rot_max_deg,
                     100 * every.ate_rel, rot, pos, wall])
        print(f"| {name} | {rows[-1][1]} | {rows[-1][2]} | {kept.rot_max_deg:.3f} "
              f"| {100 * kept.ate_rel:.3f} | {every.rot_max_deg:.3f} | {100 * every.ate_rel:.3f} "
              f"| {rot:.4f} | {pos:.4f} | {wall:.0f} |", flush=True)
    worst = max(float(r[5]) for r in rows)  # type: ignore[arg-type]
    write_log(args, "eval_variants", "The 2,000-frame office walk in ten variants of its input",
              COLUMNS, rows, headline=f"the tracks as they are and {len(rows) - 1} variants: "
              f"every posed frame within {worst:.2f} deg of the truth")


if __name__ == "__main__":
    main()
