"""Rotation (docs/method.md §4): exact per-view solution, global 1-DOF search, noise-free
exactness."""

from __future__ import annotations

import numpy as np
import pytest

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.rotation import (
    RotationProblem,
    estimate_rotations,
    polish_angles,
    rotation_aligning,
    trig2_eval,
    trig2_minimize,
)
from omni_sfm.estimate.search import global_minimize_1d
from omni_sfm.geometry import rotation_angle
from omni_sfm.synth.simulate import Simulation, SimulationOptions, simulate


def _brute_min(coef: np.ndarray, num: int = 20001) -> np.ndarray:
    """Minimum of the trigonometric polynomials on a fine grid."""
    g = np.linspace(-np.pi, np.pi, num)
    vals = trig2_eval(coef[:, None, :], g[None, :])
    return vals.min(axis=1)


def test_trig2_minimize_is_the_global_minimum() -> None:
    rng = np.random.default_rng(0)
    coef = rng.normal(size=(1000, 4))
    coef[:100, 1] = 0.0                       # q may vanish: the "hard case"
    coef[100:200, 2:] = 0.0                   # degree 1 only
    coef[200:300, :2] *= 1e-9                 # almost pure degree 2: two equal minima
    coef[300:400, 0] = 0.0
    coef[400:500] *= 1e6                      # scale does not matter
    phi = trig2_minimize(coef)
    got = trig2_eval(coef, phi)
    ref = _brute_min(coef)
    scale = np.abs(coef).sum(1)
    # never worse than a fine grid (up to round-off), and the grid is within its resolution
    assert np.all(got <= ref + 1e-12 * scale)
    assert np.all(ref - got < 1e-6 * scale)
    # a stationary point: zero derivative
    deriv = (-coef[:, 0] * np.sin(phi) + coef[:, 1] * np.cos(phi)
             - 2 * coef[:, 2] * np.sin(2 * phi) + 2 * coef[:, 3] * np.cos(2 * phi))
    assert np.all(np.abs(deriv) < 1e-9 * scale)


def test_trig2_minimize_degenerate_inputs() -> None:
    phi = trig2_minimize(np.zeros((2, 4)))
    assert np.all(np.isfinite(phi))
    # f = cos 2phi: minima at +-pi/2
    phi = trig2_minimize(np.array([[0.0, 0.0, 1.0, 0.0]]))
    assert abs(abs(phi[0]) - np.pi / 2) < 1e-12


def test_rotation_aligning() -> None:
    rng = np.random.default_rng(1)
    a = rng.normal(size=(100, 3))
    b = rng.normal(size=(100, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    b[0] = -a[0]                              # antiparallel
    b[1] = a[1]                               # identical
    R = rotation_aligning(a, b)
    np.testing.assert_allclose(np.einsum("kij,kj->ki", R, a), b, atol=1e-12)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


@pytest.mark.parametrize("periodic", [True, False])
def test_global_search_matches_brute_force(periodic: bool) -> None:
    rng = np.random.default_rng(2)
    for _ in range(15):
        k = rng.integers(1, 6, size=4)
        amp = rng.normal(size=4)
        ph = rng.uniform(0, 2 * np.pi, size=4)

        def cost(x: np.ndarray, k: np.ndarray = k, amp: np.ndarray = amp,
                 ph: np.ndarray = ph) -> np.ndarray:
            return np.sum(amp * np.cos(k * np.asarray(x)[:, None] + ph), axis=1)

        lo, hi = (-np.pi, np.pi) if periodic else (-1.0, 2.5)
        res = global_minimize_1d(cost, lo, hi, periodic=periodic, num_grid=64)
        grid = np.linspace(lo, hi, 100001)
        ref = cost(grid).min()
        assert res.fx <= ref + 1e-12
        assert lo <= res.x <= hi
        assert res.num_evals < 64 + 3 * 60


def _true_angles(prob: RotationProblem, sim: Simulation) -> np.ndarray:
    """``phi_k`` with ``R_true_k = R_v(phi_k) A_k``."""
    v = prob.v
    x = np.cross(v, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    Rv = sim.groundtruth.rotations @ np.swapaxes(prob.align, 1, 2)
    y = Rv @ x
    return np.arctan2(np.cross(x, y) @ v, y @ x)


def _gt_inputs(sim: Simulation) -> tuple[np.ndarray, np.ndarray]:
    normals = sim.tracks.dense_normals().transpose(1, 0, 2)
    vpv = np.einsum("fji,j->fi", sim.groundtruth.rotations, sim.parallel_direction)
    return normals[:, ~sim.parallel], vpv


@pytest.mark.parametrize("kw,c", [
    (dict(num_views=20, num_parallel=3, num_other=20, seed=0), 19),
    (dict(num_views=20, num_parallel=3, num_other=20, seed=0), 4),
    (dict(num_views=3, num_parallel=3, num_other=3, seed=1), 2),
    (dict(num_views=3, num_parallel=3, num_other=3, seed=2), 1),
    (dict(num_views=10, num_parallel=3, num_other=3, seed=3), 9),
])
@pytest.mark.parametrize("polish", [False, True])
def test_noise_free_rotation_is_exact(kw: dict, c: int, polish: bool) -> None:
    sim = simulate(SimulationOptions(**kw))
    normals, vpv = _gt_inputs(sim)
    res = estimate_rotations(normals, vpv, np.ones(normals.shape[1]), c, polish=polish)
    err = np.degrees(rotation_angle(np.swapaxes(sim.groundtruth.rotations, 1, 2)
                                    @ res.rotations))
    assert err.max() < 1e-7
    assert res.cost < 1e-18
    np.testing.assert_array_equal(res.rotations[0], np.eye(3))


def test_cost_vanishes_at_the_true_angle_only() -> None:
    sim = simulate(SimulationOptions(num_views=8, num_parallel=3, num_other=6, seed=4))
    normals, vpv = _gt_inputs(sim)
    prob = RotationProblem.build(normals, vpv, np.ones(6), 7)
    phi_true = _true_angles(prob, sim)
    assert prob.cost(np.array([phi_true[7]]))[0] < 1e-25
    grid = phi_true[7] + np.linspace(0.05, 2 * np.pi - 0.05, 200)
    assert prob.cost(grid).min() > 1e-8
    # the per-view fit at the true phi_c recovers every true angle
    phi, e = prob.view_fit(np.array([phi_true[7]]))
    d = np.angle(np.exp(1j * (phi[0, 1:] - phi_true[1:])))
    assert np.abs(d).max() < 1e-10


def test_sign_of_normals_does_not_matter() -> None:
    sim = simulate(SimulationOptions(num_views=6, num_parallel=3, num_other=5, seed=5))
    normals, vpv = _gt_inputs(sim)
    flipped = normals * np.random.default_rng(0).choice([-1.0, 1.0], size=normals.shape[:2] + (1,))
    a = estimate_rotations(normals, vpv, np.ones(5), 5, polish=False)
    b = estimate_rotations(flipped, vpv, np.ones(5), 5, polish=False)
    np.testing.assert_allclose(a.rotations, b.rotations, atol=1e-9)


def test_polish_reduces_the_all_view_cost_with_noise() -> None:
    sim = simulate(SimulationOptions(num_views=20, num_parallel=20, num_other=20,
                                     noise_deg=0.2, seed=1))
    normals, vpv = _gt_inputs(sim)
    prob = RotationProblem.build(normals, vpv, np.ones(20), 19)
    res = estimate_rotations(normals, vpv, np.ones(20), 19, polish=False)
    _, d0, cost0 = polish_angles(prob, res.phi.copy(), max_iter=0)
    phi, _, cost = polish_angles(prob, res.phi.copy())
    assert cost < cost0
    gt = sim.groundtruth.rotations
    err_search = np.degrees(rotation_angle(np.swapaxes(gt, 1, 2) @ res.rotations)).mean()
    err_polish = np.degrees(rotation_angle(np.swapaxes(gt, 1, 2) @ prob.rotations(phi))).mean()
    assert err_polish < err_search


def test_bad_inputs() -> None:
    sim = simulate(SimulationOptions(num_views=5, num_parallel=3, num_other=3, seed=6))
    normals, vpv = _gt_inputs(sim)
    with pytest.raises(OmniSfmError, match="second view"):
        estimate_rotations(normals, vpv, np.ones(3), 5)
    with pytest.raises(OmniSfmError, match="at least 3 non-parallel"):
        estimate_rotations(normals, vpv, np.array([1.0, 0.0, 1.0]), 2)
    with pytest.raises(OmniSfmError, match="at least 3 views"):
        estimate_rotations(normals[:2], vpv[:2], np.ones(3), 1)


@pytest.mark.parametrize("seed", [0, 1])
def test_search_finds_the_global_minimum_of_e_rot(seed: int) -> None:
    """With noise E_rot(phi_c) has several local minima; the coarse grid + Brent search must
    return the lowest one, as a dense brute-force scan of the same cost does."""
    sim = simulate(SimulationOptions(num_views=12, num_parallel=4, num_other=6, noise_deg=1.0,
                                     seed=seed))
    normals, vpv = _gt_inputs(sim)
    res = estimate_rotations(normals, vpv, np.ones(6), 11, polish=False, xtol=1e-10)
    prob = RotationProblem.build(normals, vpv, np.ones(6), 11)
    grid = np.linspace(-np.pi, np.pi, 20001)
    brute = prob.cost(grid)
    found = prob.cost(np.array([res.phi[11]]))[0]
    assert found <= brute.min() + 1e-12
    assert res.num_evals < 64 + 2 * 3 * 40


def _manhattan(seed: int, noise_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A corridor-like scene: parallel lines along ``v`` and every other line perpendicular to
    it (two directions), so ``R_v(phi)`` and ``R_v(phi + pi)`` explain the other lines equally
    well. Returns the other lines' normals ``(F, Q, 3)``, the VPVs and the true rotations."""
    from omni_sfm.geometry import normalize
    from omni_sfm.synth.simulate import smooth_path

    rng = np.random.default_rng(seed)
    gt = smooth_path(40, 1.0, 20.0, rng)
    v = normalize(rng.normal(size=3))
    u = normalize(np.cross(v, rng.normal(size=3)))
    dirs = np.array([u, np.cross(v, u)] * 6)
    pts = rng.normal(size=(12, 3)) * 2.0
    n_w = normalize(np.cross(pts[None] - gt.positions[:, None], dirs[None]))  # (F, Q, 3)
    n = np.einsum("fji,fqj->fqi", gt.rotations, n_w)
    if noise_deg:
        axis = normalize(np.cross(n, rng.normal(size=n.shape)))
        ang = np.radians(noise_deg) * rng.normal(size=n.shape[:2] + (1,))
        n = n * np.cos(ang) + np.cross(axis, n) * np.sin(ang)
    vpv = np.einsum("fji,j->fi", gt.rotations, v)
    return n, vpv, gt.rotations


@pytest.mark.parametrize("seed", [2, 3, 5])
def test_half_turn_ambiguity_is_resolved_by_continuity(seed: int) -> None:
    """Lines perpendicular to v cannot tell a view's angle from its half turn; consecutive
    video frames can. Without the continuity rule these noise-free sequences come out with
    many views turned by 180 deg; with it, exact (and within noise when noisy)."""
    n, vpv, R_true = _manhattan(seed, 0.0)

    def err(res):
        return np.degrees(rotation_angle(np.swapaxes(R_true, 1, 2) @ res.rotations))

    plain = estimate_rotations(n, vpv, np.ones(n.shape[1]), 39, continuity=False)
    assert np.count_nonzero(err(plain) > 170) > 5
    assert err(estimate_rotations(n, vpv, np.ones(n.shape[1]), 39)).max() < 1e-6
    n, vpv, R_true = _manhattan(seed, 0.05)
    assert err(estimate_rotations(n, vpv, np.ones(n.shape[1]), 39)).max() < 0.2


def test_continuity_keeps_a_half_turn_the_data_ask_for() -> None:
    """With lines oblique to v the half turn costs much more and is not taken back: a view
    that really is turned by 180 deg about v from its neighbours keeps its angle."""
    from dataclasses import replace

    from omni_sfm.estimate.rotation import keep_continuity
    from omni_sfm.geometry import rotation_about_axis

    sim = simulate(SimulationOptions(num_views=8, num_parallel=3, num_other=6, seed=4))
    normals, vpv = _gt_inputs(sim)
    k = 3
    R = sim.groundtruth.rotations.copy()
    turned = rotation_about_axis(sim.parallel_direction, np.pi) @ R[k]
    # the same camera centre, turned by pi about v: its normals in the camera frame change,
    # its VPV does not
    normals[k] = normals[k] @ (R[k].T @ turned)
    R[k] = turned
    sim = replace(sim, groundtruth=replace(sim.groundtruth, rotations=R))
    prob = RotationProblem.build(normals, vpv, np.ones(6), 7)
    phi_true = _true_angles(prob, sim)
    assert abs(np.angle(np.exp(1j * (phi_true[k] - phi_true[k - 1])))) > np.pi / 2

    phi, e = keep_continuity(prob, float(phi_true[7]), phi_true)
    np.testing.assert_allclose(phi, phi_true)
    assert e.max() < 1e-20
