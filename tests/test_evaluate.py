"""Relative pose error as the TUM RGB-D benchmark / evo define it: hand-computed values, no
alignment (invariant to a rigid or similarity transform of the estimate), delta > 1, and a heading
drift that the RPE sees per step while the older aligned step error mixes it with global shape."""

from __future__ import annotations

import numpy as np
import pytest

from omni_sfm.evaluate import relative_pose_errors, trajectory_errors, umeyama
from omni_sfm.geometry import FloatArray
from omni_sfm.poses import Trajectory


def rz(deg: float) -> FloatArray:
    """Rotation about z by ``deg`` degrees."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rx(deg: float) -> FloatArray:
    """Rotation about x by ``deg`` degrees."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def chain(steps: list[tuple[FloatArray, FloatArray]]) -> Trajectory:
    """World_from_cam poses ``P_0 = I``, ``P_{k+1} = P_k A_k`` with ``A_k = (R, t)`` (camera
    frame ``k`` to ``k+1``): ``R_{k+1} = R_k R``, ``p_{k+1} = p_k + R_k t``."""
    rots, pos = [np.eye(3)], [np.zeros(3)]
    for r, t in steps:
        pos.append(pos[-1] + rots[-1] @ t)
        rots.append(rots[-1] @ r)
    return Trajectory(np.arange(len(rots), dtype=float), np.array(rots), np.array(pos))


def transformed(tr: Trajectory, rot: FloatArray, trans: FloatArray, scale: float) -> Trajectory:
    """``tr`` in another world: ``P -> S P`` with ``S = (scale, rot, trans)``."""
    return Trajectory(tr.timestamps.copy(), rot @ tr.rotations,
                      scale * tr.positions @ rot.T + trans)


# Ground truth: three steps, each one unit forward along the camera's x then a quarter turn
# about z. Centres (0,0,0), (1,0,0), (1,1,0), (0,1,0); every step has length 1, the motions over
# two frames |p2 - p0| = |p3 - p1| = sqrt(2).
FORWARD_TURN = (rz(90.0), np.array([1.0, 0.0, 0.0]))
GT = chain([FORWARD_TURN] * 3)


def test_extra_translation_in_one_step() -> None:
    # estimate: step 1 moves by t + d with d = (0, 0.3, 0.4) (camera frame 1), |d| = 0.5.
    # E_1 = A_1^-1 B_1 = (I, R_A^T d): |trans| = 0.5; E_0 = E_2 = I since those steps are exact.
    d = np.array([0.0, 0.3, 0.4])
    est = chain([FORWARD_TURN, (rz(90.0), np.array([1.0, 0.0, 0.0]) + d), FORWARD_TURN])
    r = relative_pose_errors(est, GT, scale=1.0)
    # trans = [0, 0.5, 0]: RMSE = sqrt(0.25 / 3) = 0.5 / sqrt(3), mean = 0.5 / 3
    np.testing.assert_allclose(r.trans, [0.0, 0.5, 0.0], atol=1e-12)
    assert r.trans_rmse == pytest.approx(0.5 / np.sqrt(3.0), abs=1e-12)
    assert r.trans_mean == pytest.approx(1.0 / 6.0, abs=1e-12)
    # mean true step 1: relative figure = RMSE
    assert r.mean_gt_motion == pytest.approx(1.0, abs=1e-12)
    assert r.trans_rel == pytest.approx(0.5 / np.sqrt(3.0), abs=1e-12)
    np.testing.assert_allclose(r.rot_deg, 0.0, atol=1e-12)
    assert r.rot_mean_deg == pytest.approx(0.0, abs=1e-12)

    # delta = 2: E(0,2) = A_1^-1 B_1 = (I, R_1^T d), E(1,3) = A_2^-1 (I, R_1^T d) A_2 =
    # (I, R_2^T R_1^T d): both |trans| = 0.5, so RMSE = mean = 0.5; mean true motion sqrt(2).
    r2 = relative_pose_errors(est, GT, delta=2, scale=1.0)
    np.testing.assert_allclose(r2.trans, [0.5, 0.5], atol=1e-12)
    assert r2.trans_rmse == pytest.approx(0.5, abs=1e-12)
    assert r2.trans_mean == pytest.approx(0.5, abs=1e-12)
    assert r2.mean_gt_motion == pytest.approx(np.sqrt(2.0), abs=1e-12)
    assert r2.trans_rel == pytest.approx(0.5 / np.sqrt(2.0), abs=1e-12)
    assert r2.rot_mean_deg == pytest.approx(0.0, abs=1e-12)


def test_extra_rotation_in_one_step() -> None:
    # estimate: step 1 ends with an extra 60 deg turn about z, B_1 = A_1 (Rz(60), 0); the other
    # relative motions are exact, so the later centres move (heading changed) but:
    # delta 1: E_0 = E_2 = I, E_1 = (Rz(60), 0): rot = [0, 60, 0] deg, mean 20; trans all 0.
    est = chain([FORWARD_TURN, (rz(90.0) @ rz(60.0), np.array([1.0, 0.0, 0.0])), FORWARD_TURN])
    r = relative_pose_errors(est, GT, scale=1.0)
    np.testing.assert_allclose(r.rot_deg, [0.0, 60.0, 0.0], atol=1e-12)
    assert r.rot_mean_deg == pytest.approx(20.0, abs=1e-12)
    assert r.trans_rmse == pytest.approx(0.0, abs=1e-12)
    # delta 2: E(0,2) = (Rz(60), 0); E(1,3) = A_2^-1 (Rz(60), 0) A_2 = (Rz(60), Rz(-90)(Rz(60) t
    # - t)) with t = (1,0,0): |Rz(60) t - t| = 2 sin(30 deg) = 1. rot = [60, 60] deg,
    # trans = [0, 1]: RMSE = sqrt(1/2), mean = 0.5.
    r2 = relative_pose_errors(est, GT, delta=2, scale=1.0)
    np.testing.assert_allclose(r2.rot_deg, [60.0, 60.0], atol=1e-12)
    np.testing.assert_allclose(r2.trans, [0.0, 1.0], atol=1e-12)
    assert r2.trans_rmse == pytest.approx(np.sqrt(0.5), abs=1e-12)
    assert r2.trans_mean == pytest.approx(0.5, abs=1e-12)
    assert r2.rot_mean_deg == pytest.approx(60.0, abs=1e-12)


def test_alignment_free() -> None:
    rot = rx(35.0) @ rz(-120.0)
    shift = np.array([4.0, -2.0, 7.5])
    # an exact estimate in another world and at another scale: RPE 0, the default scale (summed
    # true over summed estimated motions) is exactly 1 / 2.5
    est = transformed(GT, rot, shift, 2.5)
    for delta in (1, 2, 3):
        r = relative_pose_errors(est, GT, delta=delta)
        assert r.scale == pytest.approx(0.4, abs=1e-12)
        np.testing.assert_allclose(r.trans, 0.0, atol=1e-12)
        np.testing.assert_allclose(r.rot_deg, 0.0, atol=1e-9)
    # a perturbed estimate: a rigid transform changes nothing, a similarity only the scale
    d = np.array([0.0, 0.3, 0.4])
    pert = chain([FORWARD_TURN, (rz(90.0) @ rz(60.0), np.array([1.0, 0.0, 0.0]) + d),
                  FORWARD_TURN])
    for delta in (1, 2):
        ref = relative_pose_errors(pert, GT, delta=delta)
        moved = relative_pose_errors(transformed(pert, rot, shift, 1.0), GT, delta=delta)
        scaled = relative_pose_errors(transformed(pert, rot, shift, 3.0), GT, delta=delta)
        for r in (moved, scaled):
            np.testing.assert_allclose(r.trans, ref.trans, atol=1e-12)
            np.testing.assert_allclose(r.rot_deg, ref.rot_deg, atol=1e-9)
        assert scaled.scale == pytest.approx(ref.scale / 3.0, rel=1e-12)
        assert ref.trans_rmse > 0.1
    # the rotational part never depends on the scale
    np.testing.assert_array_equal(relative_pose_errors(pert, GT, scale=1.0).rot_deg,
                                  relative_pose_errors(pert, GT, scale=7.0).rot_deg)


def test_constant_heading_drift_is_per_step() -> None:
    # A straight corridor walk (20 unit steps along x, no turning); the estimate turns by an
    # extra 2 deg per step but has every step length right. RPE sees 2 deg per step and no
    # translational error (the relative translations are exact in each camera's frame), while the
    # error relative to the first frame grows to 38 deg and the estimated path curves, so the
    # step error after one global similarity alignment is not 0: it mixes in the global drift.
    n = 20
    straight = (np.eye(3), np.array([1.0, 0.0, 0.0]))
    gt = chain([straight] * n)
    est = chain([(rz(2.0), np.array([1.0, 0.0, 0.0]))] * n)
    r = relative_pose_errors(est, gt)
    assert r.scale == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(r.rot_deg, 2.0, atol=1e-12)
    np.testing.assert_allclose(r.trans, 0.0, atol=1e-12)

    e = trajectory_errors(est, gt)
    assert e.rot_max_deg == pytest.approx(2.0 * n, abs=1e-9)
    assert e.rpe.rot_mean_deg == pytest.approx(2.0, abs=1e-12)
    assert e.rpe.trans_rel == pytest.approx(0.0, abs=1e-12)
    assert e.step_error_after_alignment > 0.01
    d = e.as_dict()
    assert d["rpe"] == e.rpe.trans_rel and d["rpe_rot_deg"] == e.rpe.rot_mean_deg
    assert d["step_error_after_alignment"] == e.step_error_after_alignment
    # the evo --correct_scale variant: Umeyama's scale of the curved path is not 1, so its
    # translational RPE is |1 - s| per unit step
    s = umeyama(est.positions, gt.positions).scale
    r_evo = relative_pose_errors(est, gt, scale=s)
    assert abs(s - 1.0) > 1e-3
    np.testing.assert_allclose(r_evo.trans, abs(1.0 - s), atol=1e-12)


def test_bad_arguments() -> None:
    with pytest.raises(ValueError):
        relative_pose_errors(GT, GT, delta=0)
    with pytest.raises(ValueError):
        relative_pose_errors(GT, GT, delta=4)
    with pytest.raises(ValueError):
        relative_pose_errors(GT.subset(np.arange(3)), GT)


def _square_loop(laps: float = 1.25, n: int = 400) -> Trajectory:
    """A camera walking around a 4 m square (16 m a lap), heading along its path."""
    s = np.linspace(0.0, 16.0 * laps, n)
    side, u = np.floor(s / 4.0) % 4, s % 4.0
    corners = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]])
    dirs = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    xy = corners[side.astype(int)] + u[:, None] * dirs[side.astype(int)]
    rots = np.array([rz(90.0 * k) for k in side])
    return Trajectory(np.arange(n, dtype=float), rots, np.column_stack([xy, np.zeros(n)]))


def test_revisits_see_a_loop_that_does_not_close() -> None:
    from omni_sfm.evaluate import revisit_errors

    gt = _square_loop()
    est = transformed(gt, rx(20.0) @ rz(30.0), np.array([1.0, 2.0, 3.0]), 0.5)
    rev = revisit_errors(est, gt)
    # the last quarter lap passes the first (and the lap's end nears the start): each frame of
    # it with its nearest earlier one, within the radius
    assert 80 <= len(rev.pairs) <= 110
    gap = np.linalg.norm(np.diff(np.take(gt.positions, rev.pairs, axis=0), axis=1)[:, 0], axis=1)
    assert gap.max() <= 0.5 and np.median(gap) < 0.05
    assert rev.pos_rel.max() < 1e-9 and rev.rot_deg.max() < 1e-6   # a closed loop
    # drift: the heading turns 1 deg and the walk stretches 2 % over the lap (the estimate no
    # longer comes back to its start)
    k = np.arange(len(gt)) / (len(gt) - 1)
    drift = Trajectory(gt.timestamps, np.array([rz(1.0 * t) for t in k]) @ gt.rotations,
                       (gt.positions - gt.positions[0]) * (1 + 0.02 * k[:, None]))
    rev = revisit_errors(drift, gt)
    assert 0.7 < rev.rot_deg.max() < 1.0
    assert rev.pos_rel.max() > 0.001
    with pytest.raises(Exception, match="zero length"):
        still = Trajectory(gt.timestamps, gt.rotations, np.zeros_like(gt.positions))
        revisit_errors(still, still)
