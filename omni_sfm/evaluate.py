"""Trajectory errors against ground truth: similarity alignment, rotation error, ATE, RPE.

Definitions (used by tests, docs and ``omni-sfm compare`` alike):

- rotation error of frame k: the angle of ``(R_gt0^T R_gtk)^T (R_est0^T R_estk)``, i.e. the
  error of the rotation relative to the first frame, in degrees; independent of the world frame.
- ATE: RMSE of camera centres after the similarity (Umeyama) alignment of the estimate onto the
  ground truth, divided by the ground-truth path length (``ate_rel``).
- translation error as in the paper (Sec. VII): distance between estimated and true positions
  after bringing both to the first frame and scaling so that the first-to-last distance is 1.
- RPE (relative pose error, as the TUM RGB-D benchmark and evo define it): for a frame delta
  ``d``, ``E_i = (Q_i^-1 Q_{i+d})^-1 (P_i^-1 P_{i+d})`` with ``Q`` the ground truth and ``P`` the
  estimate (world_from_cam). No alignment: only the estimate's scale is fixed before the
  translational part, by the ratio of the summed true to the summed estimated motions over ``d``
  frames. ``rpe``: RMSE of ``|trans(E_i)|`` divided by the mean true motion over ``d`` frames;
  ``rpe_rot_deg``: mean angle of ``rot(E_i)``.
- reflection: from NVs alone the estimate is determined only up to a similarity and the point
  reflection of the camera centres through the first camera (:func:`reflect_positions`); the
  comparison is made on the branch nearer the ground truth (:func:`match_reflection`).
- revisit errors (:func:`revisit_errors`): where the true camera comes back to where it was
  (within ``radius``) after having gone at least ``min_gap`` of the path, the relative pose of
  the two visits, estimated against true: position error over the path length (the estimate
  scaled by the similarity alignment's scale) and rotation angle. A loop that does not close
  shows here, whatever the alignment spreads over the rest.
- flag honesty (:func:`flag_honesty`): the frames not flagged (those ``trajectory.tum`` keeps)
  aligned on themselves, as a user reads them, their rotations counted from the first of them;
  the flagged frames measured in the same alignment. A trusted frame more than 1 deg or 2 % of
  the path off is a wrong pose reported as fine; a flagged frame within 0.2 deg and 0.2 % is a
  good pose flagged.
- step error after alignment (``step_error_after_alignment``; called RPE before): mean norm of
  the difference between aligned and true steps of consecutive frames after the similarity
  alignment, divided by the mean true step. Mixes global drift into a per-step figure.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray, rotation_angle
from omni_sfm.poses import Trajectory
from omni_sfm.transforms import Similarity, associate, paper_translation_errors, umeyama

__all__ = [
    "FlagHonesty", "RelativePoseErrors", "RevisitErrors", "Similarity", "TrajectoryErrors",
    "associate", "flag_honesty", "match_reflection", "revisit_errors",
    "paper_translation_errors", "reflect_positions", "relative_pose_errors",
    "relative_rotation_errors_deg", "trajectory_errors", "umeyama",
]


def relative_rotation_errors_deg(est: Trajectory, gt: Trajectory, ref: int = 0) -> FloatArray:
    """Per-frame rotation error (deg) of the rotation relative to frame ``ref`` (the first)."""
    rel_e = np.swapaxes(est.rotations[ref], -1, -2) @ est.rotations
    rel_g = np.swapaxes(gt.rotations[ref], -1, -2) @ gt.rotations
    return np.degrees(rotation_angle(np.swapaxes(rel_g, -1, -2) @ rel_e))


@dataclass(frozen=True)
class RelativePoseErrors:
    """Relative pose errors (TUM RGB-D benchmark / evo) of an estimate over a frame delta.

    Attributes:
        delta: frame delta ``d``, in frames of the compared (common) frames.
        scale: the factor applied to the estimate's positions before the translational part.
        trans: ``(M,)`` ``|trans(E_i)|`` in ground-truth units, ``M = N - delta``.
        rot_deg: ``(M,)`` angle of ``rot(E_i)``, degrees.
        mean_gt_motion: mean true camera displacement over ``delta`` frames (ground-truth units).
    """

    delta: int
    scale: float
    trans: FloatArray
    rot_deg: FloatArray
    mean_gt_motion: float

    @property
    def trans_rmse(self) -> float:
        """RMSE of ``|trans(E_i)|`` (ground-truth units)."""
        return float(np.sqrt(np.mean(self.trans**2)))

    @property
    def trans_mean(self) -> float:
        """Mean of ``|trans(E_i)|`` (ground-truth units)."""
        return float(self.trans.mean())

    @property
    def trans_rel(self) -> float:
        """``trans_rmse`` over the mean true motion over ``delta`` (dimensionless); NaN when the
        ground truth does not move."""
        m = self.mean_gt_motion
        return self.trans_rmse / m if m > 0 else float("nan")

    @property
    def rot_mean_deg(self) -> float:
        """Mean angle of ``rot(E_i)``, degrees."""
        return float(self.rot_deg.mean())


def relative_pose_errors(est: Trajectory, gt: Trajectory, *, delta: int = 1,
                         scale: float | None = None) -> RelativePoseErrors:
    """Relative pose error of ``est`` against ``gt`` (TUM RGB-D benchmark / evo), no alignment.

    ``E_i = (Q_i^-1 Q_{i+d})^-1 (P_i^-1 P_{i+d})`` for ``i = 0 .. N-1-d`` with ``Q_i``, ``P_i``
    the world_from_cam poses of ground truth and estimate; frame ``i`` of ``est`` is frame ``i``
    of ``gt`` (pass :func:`associate`'s output). ``E_i`` does not change under a rigid transform
    of either world, so no alignment is done; the estimate's arbitrary scale is fixed first by
    multiplying its positions by ``scale``. By default that is the ratio of the summed relative
    motions, ``sum_i |q_{i+d} - q_i| / sum_i |p_{i+d} - p_i|`` (camera centres), which like the
    RPE itself depends on relative motions only, so global drift does not leak in through the
    scale. (``evo_rpe --correct_scale`` instead takes the scale of the Umeyama similarity
    alignment: pass ``scale=umeyama(est.positions, gt.positions).scale`` for that.) The
    rotational part needs no scale.

    Args:
        est, gt: ``N`` poses each, corresponding by index.
        delta: frame delta ``d >= 1`` (index steps of the given frames).
        scale: factor for the estimate's positions; ``None``: the ratio of summed relative
            motions above (NaN when the estimate does not move).

    Raises:
        ValueError: trajectories of different lengths, ``delta < 1`` or ``delta >= N``.
    """
    n = len(est)
    if len(gt) != n:
        raise ValueError(f"trajectories differ in length: {n} and {len(gt)}")
    if not 1 <= delta < n:
        raise ValueError(f"need 1 <= delta < {n} frames, got {delta=}")

    def relative(rot: FloatArray, pos: FloatArray) -> tuple[FloatArray, FloatArray]:
        # X_i^-1 X_{i+d}: rotation R_i^T R_{i+d}, translation R_i^T (p_{i+d} - p_i)
        rt = np.swapaxes(rot[:-delta], -1, -2)
        return rt @ rot[delta:], (rt @ (pos[delta:] - pos[:-delta])[..., None])[..., 0]

    rot_g, t_g = relative(gt.rotations, gt.positions)
    rot_e, t_e = relative(est.rotations, est.positions)
    motion_g = np.linalg.norm(t_g, axis=1)
    if scale is None:
        motion_e = float(np.linalg.norm(t_e, axis=1).sum())
        scale = float(motion_g.sum()) / motion_e if motion_e > 0 else float("nan")
    t_e = scale * t_e
    # E = A^-1 B: rotation R_A^T R_B, translation R_A^T (t_B - t_A), |R_A^T x| = |x|
    rot_err = np.swapaxes(rot_g, -1, -2) @ rot_e
    trans = np.linalg.norm(t_e - t_g, axis=1)
    return RelativePoseErrors(delta, float(scale), trans, np.degrees(rotation_angle(rot_err)),
                              float(motion_g.mean()))


@dataclass(frozen=True)
class TrajectoryErrors:
    """Errors of an estimate against ground truth on their common frames."""

    num_common: int
    rot_deg: FloatArray
    ate_rel: float
    rpe: RelativePoseErrors
    step_error_after_alignment: float
    paper_trans: FloatArray
    alignment: Similarity
    timestamps: FloatArray
    """``(N,)`` the common frames' timestamps (the order of ``rot_deg`` and ``pos_rel``)."""
    pos_rel: FloatArray
    """``(N,)`` each common frame's position error after the alignment, over the path length."""

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
            "rpe": self.rpe.trans_rel,
            "rpe_rot_deg": self.rpe.rot_mean_deg,
            "step_error_after_alignment": self.step_error_after_alignment,
            "paper_trans_mean": float(self.paper_trans.mean()),
            "paper_trans_max": float(self.paper_trans.max()),
        }


def trajectory_errors(est: Trajectory, gt: Trajectory) -> TrajectoryErrors:
    """All errors of ``est`` against ``gt`` on the frames they share (at least 3).

    The RPE is over consecutive common frames (``delta = 1``) with its default scale.
    """
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
    step_err = float(np.linalg.norm(step_e - step_g, axis=1).mean() / mean_step) \
        if mean_step > 0 else float("nan")
    return TrajectoryErrors(len(e), relative_rotation_errors_deg(e, g), ate,
                            relative_pose_errors(e, g, delta=1), step_err,
                            paper_translation_errors(e, g), sim, e.timestamps.copy(),
                            resid / length)


def reflect_positions(traj: Trajectory) -> Trajectory:
    """The point reflection of the camera centres through the first camera (rotations kept).

    Line normals have no sign, so reflecting every camera centre and every line through the
    first camera leaves all observations unchanged: from NVs alone, the estimate is determined
    only up to this reflection (and a similarity). Compare with ground truth on the branch that
    matches it (:func:`match_reflection`).
    """
    return Trajectory(traj.timestamps.copy(), traj.rotations.copy(),
                      2.0 * traj.positions[:1] - traj.positions)


def match_reflection(est: Trajectory, gt: Trajectory) -> Trajectory:
    """``est`` or its reflection (:func:`reflect_positions`), whichever is nearer ``gt``.

    Nearer: smaller mean translation error as the paper defines it
    (:func:`omni_sfm.transforms.paper_translation_errors`) on the frames the two share (at least
    3, as :func:`trajectory_errors`). For evaluation only: the data cannot tell the two apart.

    Raises:
        OmniSfmError: fewer than 3 frames in common with ``gt``.
    """
    def mean_error(tr: Trajectory) -> float:
        e, g = associate(tr, gt)
        if len(e) < 3:
            raise OmniSfmError(f"only {len(e)} frames in common with the ground truth; need 3")
        return float(paper_translation_errors(e, g).mean())

    ref = reflect_positions(est)
    e0 = mean_error(est)
    e1 = mean_error(ref)
    return ref if e1 < e0 else est


@dataclass(frozen=True)
class RevisitErrors:
    """Errors of the relative pose between two visits of the same place (:func:`revisit_errors`).

    Attributes:
        pairs: ``(M, 2)`` indices (into the common frames) of the first and the second visit.
        pos_rel: ``(M,)`` position error of the second visit relative to the first, over the
            true path length.
        rot_deg: ``(M,)`` rotation error of the second visit relative to the first (deg).
    """

    pairs: np.ndarray
    pos_rel: FloatArray
    rot_deg: FloatArray

    def as_dict(self) -> dict[str, float]:
        return {"revisit_pairs": int(len(self.pairs)),
                "revisit_pos_rel_max": float(self.pos_rel.max()) if len(self.pairs) else 0.0,
                "revisit_rot_max_deg": float(self.rot_deg.max()) if len(self.pairs) else 0.0}


def revisit_errors(est: Trajectory, gt: Trajectory, *, radius: float = 0.5,
                   min_gap: float = 0.5) -> RevisitErrors:
    """Relative pose errors between visits of the same place, on the frames ``est`` and ``gt``
    share: for each frame of a later visit, the earlier frame nearest to it among those at
    least ``min_gap`` of the path length before it along the true path, where that frame is
    within ``radius`` (ground-truth units) of it. The estimate is brought onto the ground truth
    by the similarity alignment first (its offsets compared in the true world and scale)."""
    e, g = associate(est, gt)
    if len(e) < 3:
        raise OmniSfmError(f"only {len(e)} frames in common with the ground truth; need 3")
    ea = umeyama(e.positions, g.positions).apply(e)
    along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(g.positions, axis=0), axis=1))]
    length = float(along[-1])
    if length <= 0:
        raise OmniSfmError("ground-truth path has zero length")
    pairs = []
    for later in range(len(g)):
        before = np.flatnonzero(along <= along[later] - min_gap * length)
        if len(before) == 0:
            continue
        d = np.linalg.norm(g.positions[before] - g.positions[later], axis=1)
        if d.min() <= radius:
            pairs.append((int(before[np.argmin(d)]), later))
    ij = np.asarray(pairs, np.int64).reshape(-1, 2)
    i, j = ij[:, 0], ij[:, 1]
    pos = np.linalg.norm((ea.positions[j] - ea.positions[i])
                         - (g.positions[j] - g.positions[i]), axis=1) / length
    rel_g = np.swapaxes(g.rotations[i], -1, -2) @ g.rotations[j]
    rel_e = np.swapaxes(e.rotations[i], -1, -2) @ e.rotations[j]
    return RevisitErrors(ij, pos, np.degrees(rotation_angle(np.swapaxes(rel_g, -1, -2) @ rel_e)))


@dataclass(frozen=True)
class FlagHonesty:
    """The flags of an estimate against ground truth (:func:`flag_honesty`).

    Attributes:
        trusted, flagged: the common frames not flagged, and flagged.
        trusted_off: trusted frames more than ``off_deg`` or ``off_path`` of the path off.
        flagged_fine: flagged frames within ``fine_deg`` and ``fine_path``.
        rot_deg, pos_rel: ``(N,)`` each common frame's rotation error (deg, counted from the
            first trusted frame) and position error (over the true path length), the trusted
            frames aligned on themselves.
        is_flagged: ``(N,)`` bool.
    """

    trusted: int
    flagged: int
    trusted_off: int
    flagged_fine: int
    rot_deg: FloatArray
    pos_rel: FloatArray
    is_flagged: np.ndarray

    def as_dict(self) -> dict[str, float]:
        return {"trusted": self.trusted, "flagged": self.flagged,
                "trusted_off": self.trusted_off, "flagged_fine": self.flagged_fine}


def flag_honesty(est: Trajectory, gt: Trajectory, flagged: Sequence[float] | FloatArray, *,
                 off_deg: float = 1.0, off_path: float = 0.02, fine_deg: float = 0.2,
                 fine_path: float = 0.002) -> FlagHonesty:
    """How honest the flags of ``est`` are: ``flagged`` holds the timestamps of its flagged
    frames. The frames not flagged are aligned on themselves (the similarity of their centres,
    the reflection nearer the truth on them; all frames where fewer than 3 are trusted), their
    rotations counted from the first of them; the flagged frames are measured in the same
    alignment (module docstring).

    Raises:
        OmniSfmError: fewer than 3 frames in common with ``gt``.
    """
    e, g = associate(est, gt)  # in the estimate's order
    if len(e) < 3:
        raise OmniSfmError(f"only {len(e)} frames in common with the ground truth; need 3")
    is_flagged = np.isin(e.timestamps, np.asarray(flagged, dtype=np.float64))
    on = ~is_flagged if np.count_nonzero(~is_flagged) >= 3 else np.ones(len(e), bool)
    sub = e.subset(on)
    if match_reflection(sub, gt) is not sub:
        e = reflect_positions(e)
    sim = umeyama(e.positions[on], g.positions[on])
    length = g.path_length()
    if length <= 0:
        raise OmniSfmError("ground-truth path has zero length")
    pos = np.linalg.norm(sim.apply(e).positions - g.positions, axis=1) / length
    rot = relative_rotation_errors_deg(e, g, int(np.flatnonzero(on)[0]))
    trusted = ~is_flagged
    off = (rot > off_deg) | (pos > off_path)
    fine = (rot <= fine_deg) & (pos <= fine_path)
    return FlagHonesty(int(trusted.sum()), int(is_flagged.sum()), int(np.sum(trusted & off)),
                       int(np.sum(is_flagged & fine)), rot, pos, is_flagged)
