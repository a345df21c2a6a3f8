"""Similarity transforms between two solutions of the same frames, shared by every stage.

Two fits, on purpose different:

- :func:`umeyama`: least squares on camera centres alone (Umeyama 1991), used to compare an
  estimate with ground truth (:mod:`omni_sfm.evaluate`);
- :func:`similarity_from_poses`: the rotation from the cameras' rotations (their chordal mean,
  well defined even for a straight path, where centres alone leave a rotation free), then the
  scale and translation by least squares on the centres; used to map a refined model back onto
  its input (:mod:`omni_sfm.refine.pipeline`).

Also the frame matching of two trajectories by timestamp (:func:`associate`) and the paper's
normalised frame with the position error in it (:func:`paper_translation_errors`; the other
errors are :mod:`omni_sfm.evaluate`'s). Below the stages: imports nothing of them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray, nearest_rotation
from omni_sfm.poses import Trajectory


@dataclass(frozen=True)
class Similarity:
    """``x_b = scale * R @ x_a + t``: ``rotation`` ``(3, 3)`` b_from_a, ``translation`` ``(3,)``
    in b's units, ``scale`` (b's units per a's; negative: with a point reflection)."""

    rotation: FloatArray
    translation: FloatArray
    scale: float

    def apply_points(self, x: FloatArray) -> FloatArray:
        """Points ``(N, 3)`` in frame a -> frame b."""
        return self.scale * x @ self.rotation.T + self.translation

    def apply(self, traj: Trajectory) -> Trajectory:
        """A trajectory (world_from_cam) in world a -> world b (rotations and centres)."""
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


def similarity_from_poses(rot_dst: FloatArray, pos_dst: FloatArray, rot_src: FloatArray,
                          pos_src: FloatArray, *, allow_reflection: bool) -> Similarity:
    """Similarity ``x_dst = s R x_src + t`` taking poses of one solution onto another's.

    ``rot_*`` ``(n, 3, 3)`` world_from_cam and ``pos_*`` ``(n, 3)`` camera centres of the same
    ``n`` frames in the two solutions (their worlds and scales). ``R`` is the chordal mean of
    ``R_dst R_src^T`` over the frames (the rotation closest to their sum), ``s`` the
    least-squares ratio of the centres about their means after rotating, and ``t`` maps the
    mean centres.

    Args:
        allow_reflection: True (two estimates of one walk): ``s`` may come out negative, a point
            reflection of the source centres (line normals have no sign, so a solution is
            determined only up to it); centres that do not spread in either solution raise
            :class:`OmniSfmError`. False (aligning a refined model onto its input): ``s`` is 1
            where the fit is not positive or the source centres spread by at most ``1e-18``
            (sum of squares); never raises.
    """
    R = nearest_rotation(np.einsum("kij,klj->il", rot_dst, rot_src))
    m_dst, m_src = pos_dst.mean(0), pos_src.mean(0)
    x_dst, x_src = pos_dst - m_dst, (pos_src - m_src) @ R.T
    den = float(np.sum(x_src * x_src))
    if allow_reflection:
        if not den > 0 or not np.sum(x_dst * x_dst) > 0:
            raise OmniSfmError("the camera centres do not spread: the scale is undefined")
        s = float(np.sum(x_dst * x_src) / den)
    else:
        s = float(np.sum(x_dst * x_src) / den) if den > 1e-18 else 1.0
        if not s > 0:
            s = 1.0
    return Similarity(R, m_dst - s * R @ m_src, s)


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


def paper_normalised_positions(traj: Trajectory) -> FloatArray:
    """``(N, 3)`` camera centres in the paper's normalised frame (Sec. VII): expressed in the
    first camera's frame, scaled so that the first-to-last camera distance is 1.

    Raises:
        OmniSfmError: the first and last cameras coincide.
    """
    p = (traj.positions - traj.positions[0]) @ traj.rotations[0]
    d = np.linalg.norm(p[-1])
    if d <= 0:
        raise OmniSfmError("first and last camera coincide: the paper's scale is undefined")
    return p / d


def paper_translation_errors(est: Trajectory, gt: Trajectory) -> FloatArray:
    """Per-frame position error as the paper defines it (first-to-last distance scaled to 1).

    Both trajectories (the same ``N`` frames, corresponding by index) are expressed in their
    first frame's camera, then scaled so that the first-to-last camera distance is 1
    (:func:`paper_normalised_positions`). Returns ``(N,)`` distances in those units.
    """
    return np.linalg.norm(paper_normalised_positions(est) - paper_normalised_positions(gt),
                          axis=1)


def relative_pose_from_rays(rays1: FloatArray, rays2: FloatArray, *, max_error: float,
                            seed: int) -> tuple[FloatArray, FloatArray, np.ndarray] | None:
    """The relative pose of two views from matched unit rays ``(N, 3)`` (row i of each sees
    the same point): pycolmap's LO-RANSAC essential-matrix estimate (``max_error`` in its
    angular units, seeded), refined on its inliers.

    Returns ``cam2_from_cam1``'s rotation ``(3, 3)``, its translation ``(3,)`` (COLMAP's
    arbitrary scale) and the ``(N,)`` bool inlier mask of the RANSAC, or None when RANSAC
    finds no model.
    """
    import pycolmap

    ransac: Any = pycolmap.RANSACOptions()
    ransac.max_error = max_error
    ransac.random_seed = seed
    res = pycolmap.estimate_relative_pose(rays1, rays2, ransac)
    if res is None:
        return None
    inliers = np.asarray(res["inlier_mask"], bool).ravel()
    pose = res["cam2_from_cam1"]
    refined = pycolmap.refine_relative_pose(pose, rays1, rays2, inliers)
    if refined is not None:
        pose = refined["cam2_from_cam1"]
    return (np.asarray(pose.rotation.matrix()), np.asarray(pose.translation, dtype=np.float64),
            inliers)
