"""Joint adjustment of cameras, lines and points (omni_sfm.refine.joint)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.bundle import BundleOptions, bundle_adjust
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.geometry import rotvec_to_matrix
from omni_sfm.poses import Trajectory
from omni_sfm.refine.joint import JointOptions, PointObservations, joint_adjust, points_seen
from omni_sfm.synth.simulate import Simulation, SimulationOptions, simulate

EXAMPLES = Path(__file__).resolve().parents[1] / "docs" / "examples" / "cameras"


def _scene(seed: int, line_noise: float, point_noise: float, num_points: int = 60
           ) -> tuple[Simulation, PointObservations, np.ndarray]:
    sim = simulate(SimulationOptions(num_views=30, num_parallel=6, num_other=6,
                                     noise_deg=line_noise, seed=seed))
    g = sim.groundtruth
    rng = np.random.default_rng(seed)
    X = rng.uniform(-3.0, 3.0, (num_points, 3))
    F = len(g)
    f = np.repeat(np.arange(F), num_points)
    j = np.tile(np.arange(num_points), F)
    keep = rng.random(len(f)) < 0.5  # each frame sees about half of the points
    f, j = f[keep], j[keep]
    ray = points_seen(g.rotations, g.positions, X, f, j)
    if point_noise > 0:
        ray = ray + rng.normal(0.0, np.radians(point_noise), ray.shape)
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    return sim, PointObservations(f, j, ray, num_points), X


def _perturbed(sim: Simulation, X: np.ndarray, seed: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed + 100)
    g = sim.groundtruth
    F = len(g)
    R = g.rotations @ rotvec_to_matrix(rng.normal(0, np.radians(1.0), (F, 3)))
    c = g.positions + rng.normal(0, 0.01, (F, 3))
    R[0], c[0] = g.rotations[0], g.positions[0]
    d = sim.line_directions + rng.normal(0, 0.01, sim.line_directions.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    p = sim.line_points + rng.normal(0, 0.01, sim.line_points.shape)
    return R, c, d, p, X + rng.normal(0, 0.02, X.shape)


def _rot_err(res_R: np.ndarray, res_c: np.ndarray, sim: Simulation) -> float:
    g = sim.groundtruth
    e = trajectory_errors(Trajectory(g.timestamps, res_R, res_c), g)
    return float(e.rot_mean_deg)


def test_noise_free_lines_and_points_are_recovered_exactly() -> None:
    sim, obs, X = _scene(1, 0.0, 0.0)
    R, c, d, p, X0 = _perturbed(sim, X, 1)
    res = joint_adjust(sim.tracks, R, c, d, p, obs, X0,
                       options=JointOptions(line_noise_deg=0.01, point_noise_deg=0.01))
    assert res.frames.all() and res.point_inliers.all() and res.lines_used.all()
    assert _rot_err(res.rotations, res.positions, sim) < 1e-6
    g = sim.groundtruth
    assert trajectory_errors(Trajectory(g.timestamps, res.rotations, res.positions),
                             g).ate_rel < 1e-6
    # the gauge: the first camera and the input's scale (one coordinate of the farthest centre)
    assert np.allclose(res.positions[0], c[0]) and np.allclose(res.rotations[0], R[0])
    s = np.linalg.norm(res.positions - res.positions[0], axis=1).max() / \
        np.linalg.norm(g.positions - g.positions[0], axis=1).max()
    c0 = g.positions[0]
    assert np.abs(res.points - (c0 + s * (X - c0))).max() < 1e-6
    assert np.abs(res.positions - (c0 + s * (g.positions - c0))).max() < 1e-6


@pytest.mark.parametrize("seed", [2, 3])
def test_lines_and_points_together_beat_each_alone(seed: int) -> None:
    # 0.2 deg on the lines, 0.2 deg on the points: each kind alone fixes the poses, together
    # they do better than either (the maximum-likelihood estimate uses all the evidence)
    sim, obs, X = _scene(seed, 0.2, 0.2)
    R, c, d, p, X0 = _perturbed(sim, X, seed)
    nan = np.full_like(d, np.nan)
    joint = joint_adjust(sim.tracks, R, c, d, p, obs, X0)
    points_only = joint_adjust(sim.tracks, R, c, nan, nan, obs, X0)
    lines_only = bundle_adjust(sim.tracks, R, c, d, p, options=BundleOptions())
    e_joint = _rot_err(joint.rotations, joint.positions, sim)
    e_points = _rot_err(points_only.rotations, points_only.positions, sim)
    e_lines = _rot_err(lines_only.rotations, lines_only.positions, sim)
    assert e_joint < min(e_points, e_lines), (e_joint, e_points, e_lines)
    # each kind's noise is found from its own residuals (per axis: 0.14 deg on the lines,
    # whose 4 parameters each take up more of their few residuals; 0.2 on the points)
    assert 0.07 < joint.line_sigma_deg < 0.16 and 0.15 < joint.point_sigma_deg < 0.25


def test_wrong_point_observations_are_rejected() -> None:
    sim, obs, X = _scene(4, 0.1, 0.1)
    rng = np.random.default_rng(4)
    bad = rng.choice(len(obs.frame), 20, replace=False)
    ray = obs.ray.copy()
    ray[bad] = rng.normal(size=(20, 3))
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    obs_bad = PointObservations(obs.frame, obs.point, ray, obs.num_points)
    R, c, d, p, X0 = _perturbed(sim, X, 4)
    clean = joint_adjust(sim.tracks, R, c, d, p, obs, X0)
    res = joint_adjust(sim.tracks, R, c, d, p, obs_bad, X0)
    assert not res.point_inliers[bad].any()
    assert res.point_inliers.sum() >= len(obs.frame) - 40
    assert _rot_err(res.rotations, res.positions, sim) < \
        1.2 * _rot_err(clean.rotations, clean.positions, sim)


def test_bad_point_observations_get_a_clear_error() -> None:
    with pytest.raises(OmniSfmError, match="do not match"):
        PointObservations(np.zeros(3, int), np.zeros(2, int), np.zeros((3, 3)), 1)
    with pytest.raises(OmniSfmError, match="out of range"):
        PointObservations(np.zeros(1, int), np.array([5]), np.ones((1, 3)), 2)
    with pytest.raises(OmniSfmError, match="not finite"):
        PointObservations(np.zeros(1, int), np.zeros(1, int), np.full((1, 3), np.nan), 1)


@pytest.mark.parametrize("pending", [20_000_000, 5000])
def test_the_sparse_solve_of_long_sequences_gives_the_dense_one(monkeypatch: pytest.MonkeyPatch,
                                                                pending: int) -> None:
    # 5000: the waiting triplets summed into the sparse system after every few chunks (what
    # bounds the memory of long sequences)
    import omni_sfm.refine.joint as joint

    sim, obs, X = _scene(5, 0.1, 0.1)
    R, c, d, p, X0 = _perturbed(sim, X, 5)
    dense = joint_adjust(sim.tracks, R, c, d, p, obs, X0)
    monkeypatch.setattr(joint, "_DENSE_MAX", 0)
    monkeypatch.setattr(joint, "_PENDING_MAX", pending)
    monkeypatch.setattr(joint._ReducedSystem.subtract, "__defaults__", (300,))
    sparse = joint_adjust(sim.tracks, R, c, d, p, obs, X0)
    assert np.abs(sparse.positions - dense.positions).max() < 1e-9
    assert np.abs(sparse.rotations - dense.rotations).max() < 1e-9


def test_pixel_jacobians_follow_the_equirectangular_image() -> None:
    # an equirectangular image spends W / (2 pi) pixels on a radian of latitude everywhere,
    # and W / (2 pi cos lat) on a radian along the parallel
    from omni_sfm.cameras import load_camera
    from omni_sfm.refine.joint_model import pixel_jacobians

    cam = load_camera(EXAMPLES / "equirectangular.yaml")
    lat = np.radians([0.0, 30.0, 60.0])
    lon = np.radians([10.0, -50.0, 120.0])
    ray = np.stack([np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)], 1)
    obs = PointObservations(np.zeros(3, int), np.arange(3), ray, 3)
    s = np.linalg.svd(pixel_jacobians(cam, obs), compute_uv=False)[:, ::-1]
    unit = cam.width / (2 * np.pi)
    np.testing.assert_allclose(s[:, 0], unit, rtol=1e-4)
    np.testing.assert_allclose(s[:, 1], unit / np.cos(lat), rtol=1e-4)


def test_observations_weighed_by_pixels_follow_the_pixel_noise() -> None:
    # rays with an error of 0.2 deg where the image is coarse and 0.02 deg where it is fine
    # (the same pixel error): weighed by their pixel scales, the estimate is better than with
    # every ray alike
    sim, obs, X = _scene(6, 0.1, 0.0)
    rng = np.random.default_rng(6)
    fine = rng.random(len(obs.frame)) < 0.5
    sigma = np.where(fine, 0.02, 0.2)
    ray = obs.ray + rng.normal(size=obs.ray.shape) * np.radians(sigma)[:, None]
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    plain = PointObservations(obs.frame, obs.point, ray, obs.num_points)
    scaled = PointObservations(obs.frame, obs.point, ray, obs.num_points,
                               np.eye(2) / sigma[:, None, None])
    R, c, d, p, X0 = _perturbed(sim, X, 6)
    nan = np.full_like(d, np.nan)
    e_plain = _rot_err(*_poses(joint_adjust(sim.tracks, R, c, nan, nan, plain, X0)), sim)
    e_scaled = _rot_err(*_poses(joint_adjust(sim.tracks, R, c, nan, nan, scaled, X0)), sim)
    assert e_scaled < 0.7 * e_plain, (e_scaled, e_plain)


def _poses(res: object) -> tuple[np.ndarray, np.ndarray]:
    return res.rotations, res.positions  # type: ignore[attr-defined]


def test_landmarks_cut_into_chunks_give_the_same_step() -> None:
    # the cameras' system is built from chunks of landmarks (20,000 observations each by
    # default); cut into chunks of 37 observations, the lines (360) and points (about 900) give
    # the same adjustment (the cut after the last landmark start once indexed past the end)
    import omni_sfm.refine.joint as joint

    sim, obs, X = _scene(7, 0.1, 0.1)
    R, c, d, p, X0 = _perturbed(sim, X, 7)
    whole = joint_adjust(sim.tracks, R, c, d, p, obs, X0)
    old = joint._ReducedSystem.subtract.__defaults__
    joint._ReducedSystem.subtract.__defaults__ = (37,)
    try:
        cut = joint_adjust(sim.tracks, R, c, d, p, obs, X0)
    finally:
        joint._ReducedSystem.subtract.__defaults__ = old
    assert np.abs(cut.positions - whole.positions).max() < 1e-9
    assert np.abs(cut.rotations - whole.rotations).max() < 1e-9


def test_segments_find_their_tracks_among_unsorted_ids() -> None:
    from omni_sfm.refine.joint_model import _track_index

    np.testing.assert_array_equal(_track_index(np.array([5, 2, 9]), np.array([9, 3, 5, 2, 10])),
                                  [2, -1, 0, 1, -1])
    np.testing.assert_array_equal(_track_index(np.zeros(0, int), np.array([1])), [-1])


def test_a_point_seen_twice_in_one_frame_gives_the_exact_step() -> None:
    # COLMAP's tracks can hold two keypoints of one image: both observations enter the
    # cameras' reduced system (an assignment kept one of them: an inexact step, LM crawling
    # for a hundred iterations); the Schur step equals the solve of the whole system
    from omni_sfm.estimate.bundle import LineProblem
    from omni_sfm.refine.joint import _JointProblem

    sim, obs, X = _scene(8, 0.1, 0.1, num_points=20)
    twice = np.flatnonzero(np.random.default_rng(8).random(len(obs.frame)) < 0.3)
    obs = PointObservations(np.r_[obs.frame, obs.frame[twice]], np.r_[obs.point, obs.point[twice]],
                            np.r_[obs.ray, obs.ray[twice][:, [1, 2, 0]] * 0.1 + obs.ray[twice]],
                            obs.num_points)
    R, c, d, p, X0 = _perturbed(sim, X, 8)
    F, M, P = len(R), sim.tracks.num_tracks, len(X0)
    lp = LineProblem(sim.tracks, np.ones(F, bool), np.ones(M, bool), 0, F - 1, 0)
    prob = _JointProblem(lp, obs, np.ones(len(obs.frame), bool), 0.01, 0.02)
    e, aux = prob.residuals(R, c, d, p, X0)
    Jpl, Jl, Jpp, Jx = prob.jacobian(R, c, d, p, X0, aux)
    dp, (_, dx) = prob.solve(prob.normal_equations(Jpl, Jl, Jpp, Jx, e, np.ones(len(e))), 1e-12)
    # the whole Jacobian, dense
    n = 6 * F + 4 * M + 3 * P
    J = np.zeros((len(e), 2, n))
    k = np.arange(prob.Kl)
    for i in range(6):
        J[k, :, 6 * lp.f + i] = Jpl[:, :, i]
    for i in range(4):
        J[k, :, 6 * F + 4 * lp.t + i] = Jl[:, :, i]
    k = prob.Kl + np.arange(len(prob.f))
    for i in range(6):
        J[k, :, 6 * prob.f + i] = Jpp[:, :, i]
    for i in range(3):
        J[k, :, 6 * F + 4 * M + 3 * prob.j + i] = Jx[:, :, i]
    J = J.reshape(-1, n)
    free = np.r_[lp.pose_free.ravel(), lp.line_free.ravel(), np.ones(3 * P, bool)]
    H = J.T @ J
    x = np.zeros(n)
    x[free] = np.linalg.solve((H + 1e-12 * np.diag(np.diag(H)))[np.ix_(free, free)],
                              -(J.T @ e.ravel())[free])
    np.testing.assert_allclose(dp.ravel(), x[:6 * F], atol=1e-9 * np.abs(x[:6 * F]).max())
    np.testing.assert_allclose(dx.ravel(), x[6 * F + 4 * M:], atol=1e-9 * np.abs(x).max())


def test_the_share_of_each_kind_in_fixing_a_frame() -> None:
    # frames 5 and 6 see no point: the lines alone fix them (share 1); trusting the points
    # more (a smaller noise level given) gives the points a larger share everywhere else
    sim, obs, X = _scene(9, 0.1, 0.1)
    keep = (obs.frame != 5) & (obs.frame != 6)
    obs = obs.subset(keep)
    R, c, d, p, X0 = _perturbed(sim, X, 9)
    a = joint_adjust(sim.tracks, R, c, d, p, obs, X0,
                     options=JointOptions(line_noise_deg=0.1, point_noise_deg=0.1))
    b = joint_adjust(sim.tracks, R, c, d, p, obs, X0,
                     options=JointOptions(line_noise_deg=0.1, point_noise_deg=0.02))
    np.testing.assert_allclose(a.line_share[[5, 6]], 1.0)
    assert np.isnan(a.line_share[0]).all()  # the gauge's frame is held
    others = np.setdiff1d(np.arange(2, len(R) - 1), [5, 6])
    assert ((a.line_share[others] > 0.0) & (a.line_share[others] < 1.0)).all()
    assert (b.line_share[others] < a.line_share[others]).all()


def test_landmarks_with_slowly_varying_errors_weigh_as_fewer_observations() -> None:
    # a landmark's residuals along its frames: white noise counts fully; an AR(1) series with
    # correlation 0.9 (an edge fitted off by shading that changes slowly) as (1-0.9)/(1+0.9)
    from omni_sfm.refine.joint import _correlation_weights

    rng = np.random.default_rng(0)
    K = 4000
    white = rng.normal(size=(K, 2))
    slow = np.zeros((K, 2))
    for k in range(1, K):
        slow[k] = 0.9 * slow[k - 1] + rng.normal(size=2)
    frame = np.r_[np.arange(K), np.arange(K)]
    order = rng.permutation(2 * K)  # any order of the observations
    w = _correlation_weights(np.r_[white, slow][order], np.repeat([0, 1], K)[order],
                             frame[order], 3)
    assert w[0] > 0.95
    assert abs(w[1] - 0.1 / 1.9) < 0.02
    assert w[2] == 1.0  # no observation: untouched


def _long_scene(seed: int, noise: float, num_views: int = 75, num_points: int = 80
                ) -> tuple[Simulation, PointObservations, np.ndarray]:
    sim = simulate(SimulationOptions(num_views=num_views, num_parallel=6, num_other=6,
                                     noise_deg=noise, seed=seed))
    g = sim.groundtruth
    rng = np.random.default_rng(seed)
    X = rng.uniform(-3.0, 3.0, (num_points, 3))
    # each point in view for 20 consecutive frames somewhere along the walk
    start = rng.integers(0, num_views - 20, num_points)
    f = (start[:, None] + np.arange(20)).ravel()
    j = np.repeat(np.arange(num_points), 20)
    ray = points_seen(g.rotations, g.positions, X, f, j)
    if noise > 0:
        ray = ray + rng.normal(0.0, np.radians(noise), ray.shape)
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    return sim, PointObservations(f, j, ray, num_points), X


@pytest.mark.parametrize("kinds", ["lines and points", "points only", "lines only"])
def test_the_iterative_solver_gives_the_same_adjustment(kinds: str) -> None:
    # 75 frames, points in view for 20 frames each: the cameras' system solved by conjugate
    # gradients (windows of 10 frames as the preconditioner) gives the adjustment of the
    # factored system, in as many iterations; also with one kind of landmark only (either kind
    # may be empty: with no line observed the iterative solver once failed on a reshape). Points
    # alone on the 30-frame scene whose every frame sees half of 60 points (the walk's points
    # leave its last frames unseen and link its held first frame to the rest by one point:
    # there the two solves end apart along the modes the data leave free)
    sim, obs, X = _scene(11, 0.1, 0.1) if kinds == "points only" else _long_scene(11, 0.1)
    R, c, d, p, X0 = _perturbed(sim, X, 11)
    if kinds == "points only":
        d, p = np.full_like(d, np.nan), np.full_like(p, np.nan)
    elif kinds == "lines only":
        none = np.zeros(0, int)
        obs, X0 = PointObservations(none, none, np.zeros((0, 3)), 0), np.zeros((0, 3))
    factored = joint_adjust(sim.tracks, R, c, d, p, obs, X0,
                            options=JointOptions(iterative_above=10**9))
    iterative = joint_adjust(sim.tracks, R, c, d, p, obs, X0,
                             options=JointOptions(iterative_above=20, window_frames=10))
    assert abs(iterative.iterations - factored.iterations) <= 2
    assert np.abs(iterative.positions - factored.positions).max() < 1e-6
    assert np.abs(iterative.rotations - factored.rotations).max() < 1e-6
    assert np.array_equal(iterative.point_inliers, factored.point_inliers)


def test_window_options_are_checked() -> None:
    with pytest.raises(OmniSfmError, match="window_frames"):
        JointOptions(window_frames=5)
    with pytest.raises(OmniSfmError, match="preconditioner_reuse"):
        JointOptions(preconditioner_reuse=0)
    with pytest.raises(OmniSfmError, match="cg_tolerance"):
        JointOptions(cg_tolerance=0.0)
    with pytest.raises(OmniSfmError, match="robust_cg_tolerance"):
        JointOptions(robust_cg_tolerance=1.0)
    with pytest.raises(OmniSfmError, match="pose_tolerance"):
        JointOptions(pose_tolerance=-1.0)
    with pytest.raises(OmniSfmError, match="robust_pose_tolerance"):
        JointOptions(robust_pose_tolerance=float("nan"))


def _degenerate_scene() -> tuple[Simulation, tuple[Any, ...]]:
    """A simulated scene with barely fixed points, and joint_adjust's arguments for it."""
    sim, obs, X = _scene(3, 0.1, 0.1)
    R, c, d, p, X0 = _perturbed(sim, X, 3)
    obs, X0 = _with_degenerate_points(sim, obs, X0, 3)
    return sim, (sim.tracks, R, c, d, p, obs, X0)


def _fewer_iterations_same_cameras(sim: Simulation, args: tuple[Any, ...],
                                   without: JointOptions, rel: float) -> None:
    """The default adjustment against one ``without`` a rule: at least 3 fewer iterations,
    the same cameras."""
    res = joint_adjust(*args)
    full = joint_adjust(*args, options=without)
    assert res.iterations <= full.iterations - 3
    assert np.abs(res.positions - full.positions).max() < 1e-5
    assert _rot_err(res.rotations, res.positions, sim) == pytest.approx(
        _rot_err(full.rotations, full.positions, sim), rel=rel)


def test_the_robust_rounds_stop_when_the_cameras_stand_still() -> None:
    # the robust rounds only judge the observations: once the cameras no longer move they
    # stop (here while a few barely fixed points still creep), and the final round ends where
    # it would have
    sim, args = _degenerate_scene()
    _fewer_iterations_same_cameras(sim, args, JointOptions(robust_pose_tolerance=0.0,
                                                           robust_step_tolerance=0.0), 0.02)


def test_a_solve_stops_when_its_step_is_small_against_the_cameras_uncertainty() -> None:
    # a step that moves the cameras by a fifth of their standard deviation ends the solve
    # (half of it in the robust rounds): fewer iterations, the same cameras
    sim, args = _degenerate_scene()
    _fewer_iterations_same_cameras(
        sim, args, JointOptions(step_tolerance=0.0, robust_step_tolerance=0.0), 0.02)
    with pytest.raises(OmniSfmError, match="robust_step_tolerance"):
        JointOptions(robust_step_tolerance=-0.5)


@pytest.mark.parametrize("seed", [2, 5])
def test_solves_after_the_first_start_with_little_damping(seed: int) -> None:
    # each solve after the first starts at the minimum of the one before: Gauss-Newton's step
    # at once instead of climbing down from the first solve's damping; the same cameras
    sim, obs, X = _long_scene(seed, 0.1)
    R, c, d, p, X0 = _perturbed(sim, X, seed)
    _fewer_iterations_same_cameras(sim, (sim.tracks, R, c, d, p, obs, X0),
                                   JointOptions(warm_damping=1e-4), 0.01)
    with pytest.raises(OmniSfmError, match="warm_damping"):
        JointOptions(warm_damping=0.0)


@pytest.mark.parametrize("iterative", [False, True])
def test_the_step_distance_is_the_cameras_step_in_their_information(iterative: bool) -> None:
    # sqrt(dp^T S dp), S the cameras' information with the landmarks eliminated: the length
    # of the residuals' change when the cameras take the step and every landmark follows as
    # best it can (least squares on the whole Jacobian, formed densely here)
    from omni_sfm.estimate.bundle import LineProblem
    from omni_sfm.refine.joint import _JointProblem

    sim, obs, X = _long_scene(14, 0.1, num_views=30, num_points=40)
    R, c, d, p, X0 = _perturbed(sim, X, 14)
    F, M, P = len(R), sim.tracks.num_tracks, obs.num_points
    lp = LineProblem(sim.tracks, np.ones(F, bool), np.ones(M, bool), 0, F - 1, 0)
    opts = JointOptions(iterative_above=20, window_frames=10, cg_tolerance=1e-12) \
        if iterative else JointOptions(iterative_above=10**9)
    prob = _JointProblem(lp, obs, np.ones(len(obs.frame), bool), 0.002, 0.002, options=opts)
    e, aux = prob.residuals(R, c, d, p, X0)
    Jpl, Jl, Jpp, Jx = prob.jacobian(R, c, d, p, X0, aux)
    dp, _ = prob.solve(prob.normal_equations(Jpl, Jl, Jpp, Jx, e, np.ones(len(e))), 1e-12)
    Kl, Kp = len(Jpl), len(Jpp)
    Ap = np.zeros((2 * (Kl + Kp), 6 * F))
    Al = np.zeros((2 * (Kl + Kp), 4 * M + 3 * P))
    for k in range(Kl):
        f, t = prob.lines.f[k], prob.lines.t[k]
        Ap[2 * k:2 * k + 2, 6 * f:6 * f + 6] = Jpl[k]
        Al[2 * k:2 * k + 2, 4 * t:4 * t + 4] = Jl[k] * prob.lines.line_free[t]
    for k in range(Kp):
        r, f, j = 2 * (Kl + k), prob.f[k], prob.j[k]
        Ap[r:r + 2, 6 * f:6 * f + 6] = Jpp[k]
        Al[r:r + 2, 4 * M + 3 * j:4 * M + 3 * j + 3] = Jx[k]
    change = Ap @ dp.ravel()
    follow = np.linalg.lstsq(Al, -change, rcond=None)[0]
    assert prob.step_distance() == pytest.approx(np.linalg.norm(change + Al @ follow), rel=1e-4)
    assert prob.step_distance() > 0.0


def test_the_iterative_step_is_the_factored_step() -> None:
    from omni_sfm.estimate.bundle import LineProblem
    from omni_sfm.refine.joint import _JointProblem

    sim, obs, X = _long_scene(14, 0.1)
    R, c, d, p, X0 = _perturbed(sim, X, 14)
    F, M = len(R), sim.tracks.num_tracks
    lp = LineProblem(sim.tracks, np.ones(F, bool), np.ones(M, bool), 0, F - 1, 0)
    steps = []
    for opts in (JointOptions(iterative_above=10**9),
                 JointOptions(iterative_above=20, window_frames=10)):
        prob = _JointProblem(lp, obs, np.ones(len(obs.frame), bool), 0.002, 0.002,
                             options=opts)
        e, aux = prob.residuals(R, c, d, p, X0)
        blocks = prob.normal_equations(*prob.jacobian(R, c, d, p, X0, aux), e, np.ones(len(e)))
        dp, (dl, dx) = prob.solve(blocks, 1e-6)
        steps.append(np.r_[dp.ravel(), dl.ravel(), dx.ravel()])
    assert prob.cg_iterations and 1 < prob.cg_iterations[0] < 6 * F
    np.testing.assert_allclose(steps[1], steps[0], rtol=0, atol=1e-5 * np.abs(steps[0]).max())


def _with_degenerate_points(sim: Simulation, obs: PointObservations, X0: np.ndarray,
                            seed: int) -> tuple[PointObservations, np.ndarray]:
    """``obs`` and the initial points ``X0`` with six points added that the data barely fix:
    three a kilometre away (every frame sees them along nearly parallel rays; started 50 m
    off) and three a few millimetres from the camera path (seen from both sides of it)."""
    g = sim.groundtruth
    F, P = len(g), obs.num_points
    rng = np.random.default_rng(seed)
    own = np.array([5, 12, 20])
    Xd = np.concatenate([g.positions.mean(0) + 1e3 * rng.normal(size=(3, 3)),
                         g.positions[own] + 0.005 * rng.normal(size=(3, 3))])
    f = np.tile(np.arange(F), len(Xd))
    j = np.repeat(np.arange(len(Xd)), F)
    keep = (j < 3) | (f != own[np.clip(j - 3, 0, 2)])
    f, j = f[keep], j[keep]
    ray = points_seen(g.rotations, g.positions, Xd, f, j)
    ray = ray + rng.normal(0.0, np.radians(0.1), ray.shape)
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    start = Xd + rng.normal(0.0, 0.05, Xd.shape) * np.array([1e3, 1e3, 1e3, 1, 1, 1])[:, None]
    return (PointObservations(np.r_[obs.frame, f], np.r_[obs.point, P + j],
                              np.r_[obs.ray, ray], P + len(Xd)),
            np.concatenate([X0, start]))


@pytest.mark.parametrize(("seed", "safeguard"), [(2, "landmark damping"), (7, "camera stops")])
def test_a_few_degenerate_points_do_not_stall_the_adjustment(
        monkeypatch: pytest.MonkeyPatch, seed: int, safeguard: str) -> None:
    # Points the data barely fix take steps far outside the linear model (seed 2: rejected
    # steps, tried again with those points damped rather than the whole step) or creep towards
    # infinity along their rays while the cameras stand still (seed 7: the adjustment stops
    # when the cameras no longer move). On COLMAP's points of a 1,000-frame walk both stalled
    # the adjustment (docs/colmap.md)
    sim, obs, X = _scene(seed, 0.1, 0.1)
    R, c, d, p, X0 = _perturbed(sim, X, seed)
    clean = joint_adjust(sim.tracks, R, c, d, p, obs, X0)
    obs_d, X0_d = _with_degenerate_points(sim, obs, X0, seed)
    res = joint_adjust(sim.tracks, R, c, d, p, obs_d, X0_d)
    assert res.iterations <= 2 * clean.iterations + 2
    assert np.abs(res.positions - clean.positions).max() < 0.005
    assert _rot_err(res.rotations, res.positions, sim) < \
        1.2 * _rot_err(clean.rotations, clean.positions, sim)
    # without that safeguard the adjustment crawls
    options = JointOptions()
    if safeguard == "landmark damping":
        monkeypatch.setattr("omni_sfm.refine.joint._JointProblem.damp_landmarks",
                            lambda self, increase: False)
    else:
        options = JointOptions(pose_tolerance=0.0, robust_pose_tolerance=0.0,
                               step_tolerance=0.0, robust_step_tolerance=0.0)
    crawl = joint_adjust(sim.tracks, R, c, d, p, obs_d, X0_d, options=options)
    assert crawl.iterations > 1.5 * res.iterations


@pytest.mark.parametrize("in_landmark_order", [True, False])
def test_the_iterative_products_are_the_reduced_system(in_landmark_order: bool) -> None:
    # S x = H_pp x - sum_j G_j G_j^T x from the shared entries of the product plan, with the
    # observations in landmark order (the points) or not (then gathered into it), a landmark
    # seen twice in one frame included; and the per-observation products back in their order
    from omni_sfm.refine.joint import _ProductPlan

    rng = np.random.default_rng(3)
    F, N, K, n = 9, 7, 40, 3
    t = np.sort(rng.integers(0, N, K)) if in_landmark_order else rng.integers(0, N, K)
    f = rng.integers(0, F, K)
    f[1], t[1] = f[0], t[0]
    G = rng.normal(size=(K, 6, n))
    plan = _ProductPlan(f, t, n, N, F)
    assert (plan.by is None) == in_landmark_order
    obs, per_landmark = plan.matrices(G)
    Gj = np.zeros((N, 6 * F, n))
    for k in range(K):
        Gj[t[k], 6 * f[k]:6 * f[k] + 6] += G[k]
    x = rng.normal(size=6 * F)
    expected = sum(Gj[j] @ (Gj[j].T @ x) for j in range(N))
    np.testing.assert_allclose(per_landmark.T @ (per_landmark @ x), expected, atol=1e-12)
    Z = rng.normal(size=(6 * F, 2))
    per_obs = plan.per_observation(obs @ Z)
    for k in range(K):
        np.testing.assert_allclose(per_obs[k], G[k].T @ Z[6 * f[k]:6 * f[k] + 6], atol=1e-12)


def test_rows_summed_into_the_span_of_their_indices() -> None:
    # the normal equations' chunks add into the rows their observations touch only; repeated
    # indices summed, the rows outside the span untouched
    from omni_sfm.refine.joint import _add_by

    rng = np.random.default_rng(3)
    out = rng.normal(size=(50, 3, 3))
    idx = rng.integers(20, 31, size=200)
    vals = rng.normal(size=(200, 3, 3))
    want = out.copy()
    np.add.at(want, idx, vals)
    _add_by(out, idx, vals)
    np.testing.assert_allclose(out, want, rtol=0, atol=1e-12)
    _add_by(out, idx[:0], vals[:0])  # no observation: nothing changes
    np.testing.assert_allclose(out, want, rtol=0, atol=1e-12)


def test_line_observations_from_a_camera_on_the_line_are_left_out() -> None:
    # a line moved through the camera of frame 20 of a simulated walk: its observations from
    # cameras within 5 % of its median camera distance (frame 20 and its neighbours) are
    # left out, no other; the line keeps the rest. The per-track minimum of the ratio is the
    # one the estimator's "lines off the cameras" uses
    from omni_sfm.estimate.bundle import camera_distance_ratio, observation_distance_ratio
    from omni_sfm.refine.joint import _off_cameras

    sim, _, _ = _long_scene(12, 0.0)
    g, tr, M = sim.groundtruth, sim.tracks, sim.tracks.num_tracks
    d, p = sim.line_directions.copy(), sim.line_points.copy()
    k = int(tr.obs_track[tr.obs_frame == 20][0])
    p[k] = g.positions[20] - (g.positions[20] @ d[k]) * d[k]
    F = len(g)
    state = (g.rotations, g.positions, d, p)
    every = np.ones(tr.num_observations, bool)
    ratio = observation_distance_ratio(tr, *state, every)
    on_k20 = (tr.obs_track == k) & (tr.obs_frame == 20)
    assert ratio[on_k20][0] < 1e-9
    np.testing.assert_array_equal(camera_distance_ratio(tr, *state, every, M),
                                  [ratio[tr.obs_track == m].min() for m in range(M)])
    keep, used = _off_cameras(tr, state, np.ones(F, bool), np.ones(M, bool), 0.05)
    assert not keep[on_k20].any() and (~keep).sum() <= 5
    assert set(tr.obs_track[~keep]) == {k} and used.all()
    with pytest.raises(OmniSfmError, match="near_camera_ratio"):
        JointOptions(near_camera_ratio=-1.0)
