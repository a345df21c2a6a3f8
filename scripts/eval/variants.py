#!/usr/bin/env python
"""The same walk in other variants of its input: does the estimator come through it right
whatever the frame order, the first frame and the last bits of the normals?

Runs `estimate_poses` (the defaults, one worker) on a `tracks.json` as it is, in reversed frame
order (timestamps kept), without its first 10, 25, 50 or 100 frames, with 1e-9 noise on its
normals (seeds 1-3), reversed without its first 50 frames, and without its first 25 frames with
1e-9 noise, and prints for each the frames posed and trusted, the largest rotation error and
the ATE against the ground truth (of the trusted frames and of every posed frame), and the
wall time. On the 2,000-frame office walk of `scripts.bench.init` (its `lines_2000` and
`render_2000_*` folders):

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
from omni_sfm.evaluate import trajectory_errors  # noqa: E402
from omni_sfm.geometry import normalize  # noqa: E402
from omni_sfm.lines.tracks import LineTracks, read_tracks, reversed_frames  # noqa: E402
from omni_sfm.poses import read_tum  # noqa: E402


def _perturbed(tracks: LineTracks, seed: int, size: float = 1e-9) -> LineTracks:
    rng = np.random.default_rng(seed)
    n = tracks.obs_normal + size * rng.normal(size=tracks.obs_normal.shape)
    return replace(tracks, obs_normal=normalize(n))


def _reversed(tracks: LineTracks) -> LineTracks:
    return replace(reversed_frames(tracks), timestamps=tracks.timestamps[::-1].copy())


def _without(tracks: LineTracks, first: int) -> LineTracks:
    return frame_range(tracks, first, tracks.num_frames)[0]


def variants(tracks: LineTracks) -> list[tuple[str, LineTracks]]:
    """The variants of the module docstring, by name."""
    out = [("as they are", tracks), ("reversed", _reversed(tracks))]
    out += [(f"first {k} dropped", _without(tracks, k)) for k in (10, 25, 50, 100)]
    out += [(f"1e-9 noise, seed {s}", _perturbed(tracks, s)) for s in (1, 2, 3)]
    out.append(("reversed, first 50 dropped", _reversed(_without(tracks, 50))))
    out.append(("first 25 dropped, 1e-9 noise", _perturbed(_without(tracks, 25), 4)))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tracks", type=Path, required=True, help="tracks.json of init --lines")
    p.add_argument("--groundtruth", type=Path, required=True, help="groundtruth.tum")
    args = p.parse_args()
    gt = read_tum(args.groundtruth)
    print("| variant | posed | trusted | trusted: rotation max (deg), ATE (%) "
          "| all posed: rotation max (deg), ATE (%) | time (s) |")
    print("|---|---|---|---|---|---|")
    for name, tracks in variants(read_tracks(args.tracks)):
        t0 = time.perf_counter()
        res = estimate_poses(tracks, EstimationOptions(workers=1))
        wall = time.perf_counter() - t0
        keep = trusted(res)
        every = trajectory_errors(res.trajectory, gt)
        kept = trajectory_errors(res.trajectory.subset(keep), gt)
        print(f"| {name} | {int(res.estimated.sum())}/{tracks.num_frames} | {int(keep.sum())} "
              f"| {kept.rot_max_deg:.3f}, {100 * kept.ate_rel:.3f} "
              f"| {every.rot_max_deg:.3f}, {100 * every.ate_rel:.3f} | {wall:.0f} |", flush=True)


if __name__ == "__main__":
    main()
