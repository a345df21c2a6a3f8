"""Trajectory errors against ground truth: similarity alignment, rotation error, ATE, RPE.

Definitions (used by tests, docs and ``omni-sfm compare`` alike):

- rotation error of frame k: the angle of ``(R_gt0^T R_gtk)^T (R_est0^T R_estk)``, i.e. the
  error of the rotation relative to the first frame, in degrees; independent of the world frame.
- ATE: RMSE of camera centres after the similarity (Umeyama) alignment of the estimate onto the
  ground truth, divided by the ground-truth path length (``ate_rel``).
- translation error as in the paper (Sec. VII): distance between estimated and true positions
  after bringing both to the first frame and scaling so that the first-to-last distance is 1.
- RPE: mean rotation-free relative translation error between consecutive frames after the
  similarity alignment, divided by the mean true step length.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray, rotation_angle
from omni_sfm.poses import Trajectory


@dataclass(frozen=True)
class Similarity:
    """``x_b = scale * R @ x_a + t``."""

    rotation: FloatArray
    translation: FloatArray
    scale: float

    def apply_points(self, x: FloatArray) -> FloatArray:
        return self.scale * x @ self.rotation.T + self.translation

    def apply(self, traj: Trajectory) -> Trajectory:
        return Trajectory(
            traj.timestamps.copy(),
            self.rotation @ traj.rotations,
            self.apply_points(traj.positions),
        )


def umeyama(src: FloatArray, dst: FloatArray, *, with_scale: bool = True) -> Similarity:
    """Least-squares similarity taking points ``src (N,3)`` onto ``dst (N,3)`` (Umeyama 1991)."""
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 3:
        raise ValueError(f"need matching (N>=3, 3) arrays, got {src.shape=} {dst.shape=}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / src.shape[0]
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = float((xs**2).sum() / src.shape[0])
    scale = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > 0 else 1.0
    return Similarity(R, mu_d - scale * R @ mu_s, scale)


def associate(
    est: Trajectory, gt: Trajectory, *, tol: float = 1e-6
) -> tuple[Trajectory, Trajectory]:
    """The frames present in both trajectories (timestamps equal within ``tol``), in order."""
    idx = np.searchsorted(gt.timestamps, est.timestamps)
    idx = np.clip(idx, 0, len(gt) - 1)
    prev = np.clip(idx - 1, 0, len(gt) - 1)
    pick = np.where(np.abs(gt.timestamps[prev] - est.timestamps) <
                    np.abs(gt.timestamps[idx] - est.timestamps), prev, idx)
    ok = np.abs(gt.timestamps[pick] - est.timestamps) <= tol
    if not ok.any():
        raise OmniSfmError("no timestamp of the estimate matches the ground truth")
    return est.subset(np.flatnonzero(ok)), gt.subset(pick[ok])


def relative_rotation_errors_deg(est: Trajectory, gt: Trajectory) -> FloatArray:
    """Per-frame rotation error (deg) of the rotation relative to the first frame."""
    rel_e = np.swapaxes(est.rotations[:1], -1, -2) @ est.rotations
    rel_g = np.swapaxes(gt.rotations[:1], -1, -2) @ gt.rotations
    return np.degrees(rotation_angle(np.swapaxes(rel_g, -1, -2) @ rel_e))


def paper_translation_errors(est: Trajectory, gt: Trajectory) -> FloatArray:
    """Per-frame position error as the paper defines it (first-to-last distance scaled to 1).

    Both trajectories are expressed in their first frame's camera, then scaled so that the
    first-to-last camera distance is 1.
    """
    def normalised(tr: Trajectory) -> FloatArray:
        p = (tr.positions - tr.positions[0]) @ tr.rotations[0]
        d = np.linalg.norm(p[-1])
        if d <= 0:
            raise OmniSfmError("first and last camera coincide: the paper's scale is undefined")
        return p / d

    return np.linalg.norm(normalised(est) - normalised(gt), axis=1)


@dataclass(frozen=True)
class TrajectoryErrors:
    """Errors of an estimate against ground truth on their common frames."""

    num_common: int
    rot_deg: FloatArray
    ate_rel: float
    rpe_rel: float
    paper_trans: FloatArray
    alignment: Similarity

    @property
    def rot_max_deg(self) -> float:
        return float(self.rot_deg.max())

    @property
    def rot_mean_deg(self) -> float:
        return float(self.rot_deg.mean())

    def as_dict(self) -> dict[str, float]:
        return {
            "frames_compared": self.num_common,
            "rot_max_deg": self.rot_max_deg,
            "rot_mean_deg": self.rot_mean_deg,
            "ate_rel": self.ate_rel,
            "rpe": self.rpe_rel,
            "paper_trans_mean": float(self.paper_trans.mean()),
            "paper_trans_max": float(self.paper_trans.max()),
        }


def trajectory_errors(est: Trajectory, gt: Trajectory) -> TrajectoryErrors:
    """All errors of ``est`` against ``gt`` on the frames they share (at least 3)."""
    e, g = associate(est, gt)
    if len(e) < 3:
        raise OmniSfmError(f"only {len(e)} frames in common with the ground truth; need 3")
    sim = umeyama(e.positions, g.positions)
    ea = sim.apply(e)
    resid = np.linalg.norm(ea.positions - g.positions, axis=1)
    length = g.path_length()
    if length <= 0:
        raise OmniSfmError("ground-truth path has zero length")
    ate = float(np.sqrt(np.mean(resid**2)) / length)
    step_e = np.diff(ea.positions, axis=0)
    step_g = np.diff(g.positions, axis=0)
    mean_step = float(np.linalg.norm(step_g, axis=1).mean())
    rpe = float(np.linalg.norm(step_e - step_g, axis=1).mean() / mean_step) if mean_step > 0 \
        else float("nan")
    return TrajectoryErrors(len(e), relative_rotation_errors_deg(e, g), ate, rpe,
                            paper_translation_errors(e, g), sim)
