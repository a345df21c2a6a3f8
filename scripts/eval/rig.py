"""Raw dual-fisheye footage: ``init --lines`` on rendered walks of a rig of two lenses (issue
"Real 360 footage", item 5; docs/estimator.md, "Rigs").

Renders (or reuses, under ``--work``) the office walk (route ``walk``, 10 m, a 90 deg turn)
through ``--camera dual-fisheye`` (two equidistant 200 deg lenses back to back, 4 cm apart,
their images side by side, ``--width`` x ``--width / 2``) for each seed, runs ``omni-sfm init
--lines`` on the frames as the command line does, and reports: frames posed and trusted
(not flagged; those of them off by more than 1 deg or 2 % of the path),
rotation error (relative to the first frame, mean and largest) and ATE after similarity
alignment over every posed frame (trusted or flagged), the metric scale ``report.json``
records against the truth, and the init's wall time; then the estimator alone on the same
tracks with their lens offsets left out (one centre for both lenses), for the difference the
offsets make. Prints JSON lines and writes the record ``docs/benchmarks/eval_rig.json``.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.eval.rig --work /tmp/rig --seeds 1 4 5 7
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from omni_sfm.cli import main as cli  # noqa: E402
from omni_sfm.estimate.pipeline import EstimationOptions, estimate_poses  # noqa: E402
from omni_sfm.evaluate import trajectory_errors  # noqa: E402
from omni_sfm.folders import InitFolder  # noqa: E402
from omni_sfm.lines.tracks import read_tracks  # noqa: E402
from omni_sfm.poses import Trajectory, read_tum  # noqa: E402
from scripts.benchlib import add_log_arguments, write_log  # noqa: E402

COLUMNS: list[str | dict[str, str]] = [
    "walk", "frames trusted", "trusted, off by > 1 deg or 2 %",
    {"label": "rotation mean (deg)", "format": ".3f"},
    {"label": "rotation max (deg)", "format": ".3f"}, {"label": "ATE (%)", "format": ".3f"},
    {"label": "metres per unit", "format": ".3f"},
    {"label": "true first-to-last (m)", "format": ".3f"}, {"label": "init (s)", "format": ".0f"},
    {"label": "one centre: rotation max (deg)", "format": ".3f"},
    {"label": "one centre: ATE (%)", "format": ".3f"}]


def _posed(init: Path) -> Trajectory:
    """Every posed frame of an init folder: the trusted and the flagged ones, in time order."""
    est = read_tum(init / InitFolder.TRAJECTORY)
    flagged = init / InitFolder.UNCERTAIN_TRAJECTORY
    if not flagged.is_file():
        return est
    unc = read_tum(flagged)
    ts = np.concatenate([est.timestamps, unc.timestamps])
    order = np.argsort(ts)
    return Trajectory(ts[order], np.concatenate([est.rotations, unc.rotations])[order],
                      np.concatenate([est.positions, unc.positions])[order])


def run(work: Path, seed: int, frames: int, width: int) -> dict[str, Any]:
    """One walk: render (unless there), init, the errors, and the tracks from one centre."""
    render = work / f"dual-fisheye-{width}-walk-{frames}-seed{seed}"
    if not (render / "groundtruth.tum").is_file():
        cli(["render", "-o", str(render), "--scene", "office", "--camera", "dual-fisheye",
             "--width", str(width), "--height", str(width // 2), "--frames", str(frames),
             "--route", "walk", "--seed", str(seed), "--overwrite"])
    init = work / f"{render.name}-init"
    t0 = time.perf_counter()
    cli(["init", "--lines", "--images", str(render / "images"), "--camera",
         str(render / "camera.yaml"), "-o", str(init), "--overwrite", "--no-colmap", "--quiet"])
    wall = time.perf_counter() - t0
    gt = read_tum(render / "groundtruth.tum")
    e = trajectory_errors(_posed(init), gt)
    report = InitFolder(init).read_report()
    tracks = read_tracks(init / InitFolder.TRACKS)
    one = estimate_poses(replace(tracks, obs_offset=None), EstimationOptions(progress=False))
    e1 = trajectory_errors(one.trajectory, gt)
    # the frames not flagged (where every frame is, trajectory.tum keeps them all), and those
    # of them off by more than 1 deg or 2 % of the path (a wrong pose reported as fine)
    posed = _posed(init)
    flagged = read_tum(init / InitFolder.UNCERTAIN_TRAJECTORY).timestamps \
        if (init / InitFolder.UNCERTAIN_TRAJECTORY).is_file() else \
        (posed.timestamps if report.frames_uncertain else np.zeros(0))
    kept = ~np.isin(posed.timestamps, flagged)
    trusted = int(kept.sum())
    off = 0
    if trusted >= 3:  # aligned on the trusted frames, as their expected errors are
        et = trajectory_errors(posed.subset(np.flatnonzero(kept)), gt)
        off = int(np.sum((et.rot_deg > 1.0) | (100 * et.pos_rel > 2.0)))
    return {"walk": f"seed {seed}, {frames} frames", "frames": frames, "trusted": trusted,
            "trusted_off": off,
            "rot_mean_deg": float(e.rot_deg.mean()), "rot_max_deg": float(e.rot_deg.max()),
            "ate_pct": 100 * e.ate_rel,
            "metres_per_unit": None if report.rig is None else report.rig.metres_per_unit,
            "true_m": float(np.linalg.norm(gt.positions[-1] - gt.positions[0])),
            "wall_s": wall, "one_centre_rot_max_deg": float(e1.rot_deg.max()),
            "one_centre_ate_pct": 100 * e1.ate_rel}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for renders and results")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 4, 5, 7])
    ap.add_argument("--frames", type=int, default=150, help="frames of each walk (150)")
    ap.add_argument("--width", type=int, default=1920, help="frame width, px (1920: lenses "
                                                            "of 960 x 960)")
    add_log_arguments(ap)
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in args.seeds:
        r = run(args.work, seed, args.frames, args.width)
        print(json.dumps(r), flush=True)
        rows.append([r["walk"], f"{r['trusted']}/{r['frames']}", r["trusted_off"],
                     r["rot_mean_deg"],
                     r["rot_max_deg"], r["ate_pct"], r["metres_per_unit"], r["true_m"],
                     r["wall_s"], r["one_centre_rot_max_deg"], r["one_centre_ate_pct"]])
    write_log(args, "eval_rig", "Raw dual-fisheye walks (a rig of two lenses)", COLUMNS, rows,
              headline="{rows[0][1]} frames trusted, {rows[0][4]} deg, {rows[0][5]} % ATE")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
