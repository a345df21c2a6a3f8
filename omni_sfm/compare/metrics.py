"""Errors of one trajectory against ground truth, as ``results.json`` holds them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.evaluate import associate, trajectory_errors
from omni_sfm.folders import CompareFolder
from omni_sfm.geometry import FloatArray
from omni_sfm.poses import Trajectory, read_tum

METRIC_KEYS = ("rot_max_deg", "rot_mean_deg", "ate_rel", "rpe", "rpe_rot_deg",
               "step_error_after_alignment")
"""The error figures of every ``results.json`` entry."""


@dataclass(frozen=True)
class Evaluation:
    """Errors of one trajectory against ground truth (see :mod:`omni_sfm.evaluate`).

    Attributes:
        registered: fraction of the sequence's frames in the trajectory that have ground truth.
        metrics: ``rot_max_deg``, ``rot_mean_deg``, ``ate_rel``, ``rpe`` (TUM/evo translational
            RPE over one frame, RMSE over the mean true step), ``rpe_rot_deg``,
            ``step_error_after_alignment``, ``frames_compared``.
        timestamps: ``(N,)`` the compared frames.
        rot_deg: ``(N,)`` rotation error relative to the first compared frame, degrees.
        pos_err_rel: ``(N,)`` camera-centre error after the similarity alignment, divided by
            the ground-truth path length.
        aligned: the estimate after the similarity alignment onto the ground truth.
    """

    registered: float
    metrics: dict[str, float]
    timestamps: FloatArray
    rot_deg: FloatArray
    pos_err_rel: FloatArray
    aligned: Trajectory


def evaluate_trajectory(est: Trajectory, gt: Trajectory, num_frames: int) -> Evaluation:
    """Errors of ``est`` against ``gt``; ``num_frames``: frames of the sequence.

    Raises:
        OmniSfmError: fewer than 3 frames in common with the ground truth.
    """
    e = trajectory_errors(est, gt)
    ea, ga = associate(est, gt)
    aligned = e.alignment.apply(ea)
    pos = np.linalg.norm(aligned.positions - ga.positions, axis=1) / ga.path_length()
    m = {"rot_max_deg": e.rot_max_deg, "rot_mean_deg": e.rot_mean_deg, "ate_rel": e.ate_rel,
         "rpe": e.rpe.trans_rel, "rpe_rot_deg": e.rpe.rot_mean_deg,
         "step_error_after_alignment": e.step_error_after_alignment,
         "frames_compared": e.num_common}
    return Evaluation(e.num_common / num_frames, m, ea.timestamps, e.rot_deg, pos, aligned)


def recompute_results(output: Path, gt: Trajectory, num_frames: int) -> dict[str, dict[str, Any]]:
    """The figures of ``output/results.json`` recomputed from its TUM files (for checks)."""
    res = CompareFolder(Path(output)).read_results()
    out: dict[str, dict[str, Any]] = {}
    for name, e in res.initializers.items():
        if e.trajectory is None or e.rot_max_deg is None:
            continue
        ev = evaluate_trajectory(read_tum(Path(output) / e.trajectory), gt, num_frames)
        out[name] = {"registered": ev.registered, **ev.metrics}
    return out
