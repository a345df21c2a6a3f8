"""Translation (docs/method.md §5): the closed forms against brute-force searches, exactness,
sign."""

from __future__ import annotations

import numpy as np
import pytest

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.translation import (
    estimate_plane,
    estimate_vertical,
    line_directions,
    line_points,
    normal_residuals,
    plane_basis,
    resolve_sign,
)
from omni_sfm.synth.simulate import Simulation, SimulationOptions, simulate


def _world_normals(sim: Simulation) -> np.ndarray:
    """``(F, M, 3)`` observed normals rotated into the world with the true rotations."""
    n = sim.tracks.dense_normals().transpose(1, 0, 2)
    return np.einsum("fij,fmj->fmi", sim.groundtruth.rotations, n)


def _plane_cost_explicit(m: np.ndarray, v: np.ndarray, c: int, psi: float) -> float:
    """E_t1(psi) the paper's way: triangulate from views 0 and c, least squares per view."""
    a, b = plane_basis(v)
    h = np.stack([m @ a, m @ b], -1)
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    u = np.array([np.cos(psi), np.sin(psi)])
    F, P = h.shape[:2]
    pts = np.array([np.linalg.solve(np.stack([h[0, i], h[c, i]]), [0.0, h[c, i] @ u])
                    for i in range(P)])
    total = 0.0
    for k in range(F):
        if k in (0, c):
            continue
        y = np.sum(h[k] * pts, 1)
        t, *_ = np.linalg.lstsq(h[k], y, rcond=None)
        total += float(np.sum((y - h[k] @ t) ** 2))
    return total


def test_plane_closed_form_matches_brute_force_search() -> None:
    sim = simulate(SimulationOptions(num_views=8, num_parallel=6, num_other=3, noise_deg=0.5,
                                     seed=0))
    m = _world_normals(sim)[:, sim.parallel]
    v = sim.parallel_direction
    c = 7
    res = estimate_plane(m, v, np.ones(6), c, irls_iter=0)
    grid = np.linspace(-np.pi, np.pi, 1441)
    costs = np.array([_plane_cost_explicit(m, v, c, p) for p in grid])
    a, b = plane_basis(v)
    u = np.array([res.positions[c] @ a, res.positions[c] @ b])
    psi = float(np.arctan2(u[1], u[0]))
    assert abs(np.linalg.norm(u) - 1.0) < 1e-12
    best = float(costs.min())
    assert _plane_cost_explicit(m, v, c, psi) <= best + 1e-12
    np.testing.assert_allclose(res.cost, _plane_cost_explicit(m, v, c, psi), rtol=1e-8)
    # the minimiser (up to the unobservable psi + pi) sits where the search found it
    g = grid[int(np.argmin(costs))]
    assert abs(np.angle(np.exp(2j * (g - psi)))) / 2 < np.radians(0.5)


def _vertical_cost_explicit(m: np.ndarray, d: np.ndarray, v: np.ndarray, tp: np.ndarray, c: int,
                            omega_c: float) -> float:
    tc = tp[c] + omega_c * v
    F, Q = m.shape[:2]
    pts = np.array([np.linalg.solve(np.stack([m[0, i], m[c, i], d[i]]), [0.0, m[c, i] @ tc, 0.0])
                    for i in range(Q)])
    total = 0.0
    for k in range(F):
        if k in (0, c):
            continue
        r0 = np.sum(m[k] * (pts - tp[k]), 1)
        eta = m[k] @ v
        om = float(eta @ r0 / (eta @ eta))
        total += float(np.sum((r0 - om * eta) ** 2))
    return total


def test_vertical_closed_form_matches_brute_force_search() -> None:
    sim = simulate(SimulationOptions(num_views=8, num_parallel=3, num_other=6, noise_deg=0.3,
                                     seed=1))
    m_all = _world_normals(sim)
    v = sim.parallel_direction
    c = 7
    gt = sim.groundtruth.positions
    tp = gt - np.outer(gt @ v, v)
    m = m_all[:, ~sim.parallel]
    d = line_directions(m)
    res = estimate_vertical(m, d, v, tp, np.ones(6), c, irls_iter=0)
    om_c = float(res.omega[c])
    grid = om_c + np.linspace(-1.0, 1.0, 2001)
    costs = np.array([_vertical_cost_explicit(m, d, v, tp, c, w) for w in grid])
    assert _vertical_cost_explicit(m, d, v, tp, c, om_c) <= costs.min() + 1e-12
    np.testing.assert_allclose(res.cost, _vertical_cost_explicit(m, d, v, tp, c, om_c),
                               rtol=1e-6, atol=1e-15)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noise_free_translation_is_exact(seed: int) -> None:
    sim = simulate(SimulationOptions(num_views=6, num_parallel=3, num_other=3, seed=seed))
    m = _world_normals(sim)
    v = sim.parallel_direction
    gt = sim.groundtruth.positions
    c = 5
    plane = estimate_plane(m[:, sim.parallel], v, np.ones(3), c)
    d = line_directions(m[:, ~sim.parallel])
    vert = estimate_vertical(m[:, ~sim.parallel], d, v, plane.positions, np.ones(3), c)
    pos = plane.positions + vert.omega[:, None] * v
    # same up to scale and the unobservable point reflection
    gt_plane_c = np.linalg.norm(gt[c] - (gt[c] @ v) * v)
    ref = gt / gt_plane_c
    err = min(np.abs(pos - ref).max(), np.abs(pos + ref).max())
    assert err < 1e-9
    assert plane.cost < 1e-12 and vert.cost < 1e-12


def test_lines_residuals_and_sign() -> None:
    sim = simulate(SimulationOptions(num_views=10, num_parallel=4, num_other=6, seed=3))
    m = _world_normals(sim)
    gt = sim.groundtruth.positions
    d = line_directions(m)
    np.testing.assert_allclose(np.abs(np.sum(d * sim.line_directions, 1)), 1.0, atol=1e-12)
    pts = line_points(m, d, gt)
    # the same 3D lines: the true points lie on them
    off = sim.line_points - pts
    off -= np.sum(off * d, 1, keepdims=True) * d
    assert np.abs(off).max() < 1e-9
    assert normal_residuals(m, d, pts, gt).max() < 1e-9
    # the point reflection explains the normals exactly as well ...
    assert normal_residuals(m, d, -pts, -gt).max() < 1e-9
    # ... but rays towards the observed lines tell them apart
    foot = pts[None] + np.sum((gt[:, None] - pts[None]) * d[None], -1, keepdims=True) * d[None]
    rays = foot - gt[:, None]
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    assert resolve_sign(rays, gt, pts, d) == 1.0
    assert resolve_sign(rays, -gt, -pts, d) == -1.0


def test_no_parallax_raises() -> None:
    sim = simulate(SimulationOptions(num_views=5, num_parallel=3, num_other=3, seed=4))
    m = _world_normals(sim)[:, sim.parallel]
    frozen = np.broadcast_to(m[:1], m.shape).copy()        # every view sees what view 0 sees
    with pytest.raises(OmniSfmError, match="parallax"):
        estimate_plane(frozen, sim.parallel_direction, np.ones(3), 4)
