"""The line adjustment's compiled loops (omni_sfm/estimate/_lines.c) against the same formulas
written in numpy (bundle.py's before they were compiled): the values agree to round-off."""

from __future__ import annotations

import numpy as np
import pytest

from omni_sfm.estimate import kernels
from omni_sfm.estimate.bundle import (
    _LINE_PARTS,
    LineProblem,
    _normal_derivative,
    _pose_jacobian,
    _tangent_basis,
    triangulate_lines,
)
from omni_sfm.geometry import cross3, normalize, predicted_normals, rotvec_to_matrix
from omni_sfm.solver import RobustLoss, damped, loss_weights
from omni_sfm.synth.simulate import SimulationOptions, simulate


def _problem(loss: RobustLoss = RobustLoss.LINEAR, held_directions: bool = False):
    sim = simulate(SimulationOptions(num_views=40, num_parallel=6, num_other=8, noise_deg=0.2,
                                     visible_frames=25, seed=5))
    g, tr = sim.groundtruth, sim.tracks
    F, M = tr.num_frames, tr.num_tracks
    rng = np.random.default_rng(1)
    R = g.rotations @ rotvec_to_matrix(rng.normal(size=(F, 3)) * 0.002)
    c = g.positions + rng.normal(size=(F, 3)) * 0.01
    d, p, ok = triangulate_lines(tr, R, c)
    d = normalize(d + rng.normal(size=d.shape) * 0.02)
    p = p + rng.normal(size=p.shape) * 0.05
    p = p - np.sum(p * d, 1, keepdims=True) * d
    held = (np.arange(M) % 3 == 0) if held_directions else None
    prob = LineProblem(tr, np.ones(F, bool), ok, 0, F - 1, 0, held_directions=held,
                       line_iterations=2, loss=loss, loss_scale=0.003)
    return prob, (R, c, d, p)


def _residuals(prob, R, c, d, p):
    f, t = prob.f, prob.t
    u = predicted_normals(R[f], c[f], p[t], d[t])
    return np.einsum("kai,ki->ka", prob.B, u / np.linalg.norm(u, axis=1, keepdims=True)), u


def _line_jacobian(prob, R, c, d, p, A):
    f, t = prob.f, prob.t
    b1, b2 = _tangent_basis(d)
    pc = p[t] - c[f]
    V = np.stack([cross3(pc, b1[t]), cross3(pc, b2[t]), cross3(b1, d)[t], cross3(b2, d)[t]], 1)
    W = np.einsum("kji,kaj->kia", R[f], V)
    return A @ W * prob.line_free[t][:, None, :]


def _by(index, values, n):
    out = np.zeros((n, *values.shape[1:]))
    np.add.at(out, index, values)
    return out


def _refit(prob, R, c, d, p):
    """The lines' own iterations as bundle.py wrote them in numpy."""
    M, t, lf = prob.M, prob.t, prob.line_free
    e, u = _residuals(prob, R, c, d, p)

    def costs(e):
        rho, w = loss_weights(np.sum(e * e, 1), prob.loss, prob.loss_scale)
        return np.bincount(t, weights=rho, minlength=M), w

    cost, w = costs(e)
    mu = np.full(M, 1e-6)
    for _ in range(prob.line_iterations):
        J = _line_jacobian(prob, R, c, d, p, _normal_derivative(u, prob.B))
        wJ = J * w[:, None, None]
        H = _by(t, np.swapaxes(wJ, 1, 2) @ J, M)
        g = _by(t, np.einsum("kai,ka->ki", wJ, e), M)
        step = -np.linalg.solve(damped(H, mu, lf, _LINE_PARTS), g[:, :, None])[:, :, 0] * lf
        d3, p3 = prob._moved_lines(d, p, step)
        e3, u3 = _residuals(prob, R, c, d3, p3)
        cost3, w3 = costs(e3)
        ok = np.isfinite(cost3) & (cost3 < cost)
        d, p = np.where(ok[:, None], d3, d), np.where(ok[:, None], p3, p)
        k = ok[t]
        e, u, w = np.where(k[:, None], e3, e), np.where(k[:, None], u3, u), np.where(k, w3, w)
        cost = np.where(ok, cost3, cost)
        mu = np.where(ok, mu / 10.0, mu * 10.0)
    return d, p, e, u


def test_residuals_and_jacobians_are_numpys_formulas() -> None:
    prob, (R, c, d, p) = _problem(held_directions=True)
    e, u = prob.residuals(R, c, d, p)
    e0, u0 = _residuals(prob, R, c, d, p)
    np.testing.assert_array_equal(u, u0)
    np.testing.assert_allclose(e, e0, rtol=0, atol=1e-15)
    Jp, Jl = prob.jacobian(R, c, d, p, u)
    f = prob.f
    A, J_rot, J_c = _pose_jacobian(R[f], d[prob.t], u, prob.B)
    Jp0 = np.concatenate([J_rot, J_c], axis=2) * prob.pose_free[f][:, None, :]
    np.testing.assert_allclose(Jp, Jp0, rtol=0, atol=1e-13 * np.abs(Jp0).max())
    Jl0 = _line_jacobian(prob, R, c, d, p, A)
    np.testing.assert_allclose(Jl, Jl0, rtol=0, atol=1e-13 * np.abs(Jl0).max())
    assert (Jl[prob.line_free[prob.t][:, None, :].repeat(2, 1) == 0] == 0).all()
    w = np.random.default_rng(0).uniform(0.5, 1.0, len(f))
    got = prob.normal_equations(Jp, Jl, e, w)
    wJp, wJl = Jp * w[:, None, None], Jl * w[:, None, None]
    want = (_by(f, np.swapaxes(wJp, 1, 2) @ Jp, prob.F), _by(prob.t, np.swapaxes(wJl, 1, 2) @ Jl,
                                                            prob.M),
            np.swapaxes(wJp, 1, 2) @ Jl, _by(f, np.einsum("kai,ka->ki", wJp, e), prob.F),
            _by(prob.t, np.einsum("kai,ka->ki", wJl, e), prob.M))
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(np.abs(b).max(), 1e-300))


@pytest.mark.parametrize("loss", list(RobustLoss))
@pytest.mark.parametrize("held", [False, True])
def test_lines_own_iterations_are_numpys(loss: RobustLoss, held: bool) -> None:
    prob, (R, c, d, p) = _problem(loss, held)
    d1, p1, e1, u1 = prob._refit_lines(R, c, d, p)
    d0, p0, e0, u0 = _refit(prob, R, c, d, p)
    act = prob.line_free.any(1)
    assert not np.allclose(d1[act], d[act])  # they moved
    for a, b in ((d1, d0), (p1, p0), (e1, e0), (u1, u0)):
        np.testing.assert_allclose(a[np.isfinite(b).all(1)], b[np.isfinite(b).all(1)],
                                   rtol=0, atol=1e-10)
    # held directions stay (normalised again: to round-off)
    if held:
        h = (np.arange(prob.M) % 3 == 0) & act
        np.testing.assert_allclose(d1[h], d[h], rtol=0, atol=1e-15)


def test_bad_arrays_are_refused_not_read_out_of_bounds() -> None:
    prob, (R, c, d, p) = _problem()
    with pytest.raises(ValueError, match="expected"):
        kernels.residuals(R, c[:-1], d, p, prob.f, prob.t, prob.B)
    with pytest.raises(IndexError, match="out of range"):
        kernels.residuals(R[:-1], c[:-1], d, p, prob.f, prob.t, prob.B)
    bad = prob.t.copy()
    bad[0] = prob.M
    with pytest.raises(IndexError, match="out of range"):
        kernels.refit_lines(R, c, d, p, prob.f, bad, prob.B, prob.line_free, "linear", 1.0, 2)


def test_sparse_reduced_system_keeps_the_block_of_a_line_without_observations() -> None:
    """A long walk's sparse system where one active line has no observation in the frames:
    its diagonal block is its damped ``Hll`` alone (the structure holds every line's diagonal
    block, which the compiled sums then find), and the rest is the Schur complement."""
    from omni_sfm.estimate.bundle import _ReducedSystem

    rng = np.random.default_rng(3)
    F, M, seen = 1200, 300, 40
    first = rng.integers(0, F - seen, M)
    f = np.concatenate([np.arange(first[m], first[m] + seen) for m in range(M) if m != 7])
    tc = np.concatenate([np.full(seen, m) for m in range(M) if m != 7])
    G = rng.normal(size=(len(f), 6, 4))
    A = rng.normal(size=(M, 4, 4))
    Hll = A @ np.swapaxes(A, 1, 2) + 50.0 * np.eye(4)
    gpt, gl = rng.normal(size=(F, 6)), rng.normal(size=(M, 4))
    system = _ReducedSystem(f, tc, F, M)
    dense, blocks, rhs = system.assemble(Hll, G, gpt, gl)
    assert dense is None and blocks is not None
    sparse = system.csc(blocks)
    Gd = np.zeros((F, 6, M, 4))
    Gd[f, :, tc, :] = G
    Gm = Gd.reshape(6 * F, 4 * M)
    want = -Gm.T @ Gm
    for m in range(M):
        want[4 * m:4 * m + 4, 4 * m:4 * m + 4] += Hll[m]
    got = sparse.toarray()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())
    np.testing.assert_array_equal(got[28:32, 28:32], Hll[7])
    np.testing.assert_allclose(rhs, -gl.ravel() + Gm.T @ gpt.ravel(), rtol=0, atol=1e-9)


def test_a_grouping_that_does_not_fit_is_refused() -> None:
    f, tc = np.array([0, 0, 1, 2, 2]), np.array([0, 1, 1, 0, 2])
    index = kernels.PairIndex(f, tc, 3, 3)
    pattern = kernels.block_pattern(index)
    assert pattern[1].tolist() == [0, 1, 2, 0, 1, 0, 2]  # per line: the lines seen with it
    index.frame_start = index.frame_start.copy()
    index.frame_start[-1] = 9  # past the observations
    with pytest.raises(ValueError, match="grouping does not fit"):
        kernels.reduce_lines(index, np.zeros((5, 6, 4)), np.zeros((3, 4, 4)), np.zeros((3, 6)),
                             np.zeros((3, 4)), pattern)


@pytest.mark.parametrize(("F", "M", "seen"), [(1200, 300, 40), (300, 60, 300), (50, 5, 10)])
def test_block_cholesky_solves_the_reduced_system(F: int, M: int, seen: int) -> None:
    """The block Cholesky factorisation in the structure worked out once
    (``kernels.BlockCholesky``) solves the sparse reduced system as a dense solve does, in
    any order of the lines and at a second step of the same structure, and reports a
    system that is not positive definite."""
    rng = np.random.default_rng(F + M)
    first = rng.integers(0, max(1, F - seen), M)
    f = np.concatenate([np.arange(first[m], min(F, first[m] + seen)) for m in range(M)])
    tc = np.concatenate([np.full(min(F, first[m] + seen) - first[m], m) for m in range(M)])
    index = kernels.PairIndex(f, tc, F, M)
    pattern = kernels.block_pattern(index)
    ptr, rows = pattern
    for step in range(2):
        # S = diag(Hll) - G^T G positive definite: G_f^T G_f <= n diag(G_k^T G_k) for the n
        # observations of a frame, so Hll = n_max sum_k G_k^T G_k + I will do
        G = rng.normal(size=(len(f), 6, 4))
        Hll = np.zeros((M, 4, 4))
        np.add.at(Hll, tc, np.swapaxes(G, 1, 2) @ G)
        Hll = np.bincount(f).max() * Hll + (1.0 + step) * np.eye(4)
        gpt, gl = rng.normal(size=(F, 6)), rng.normal(size=(M, 4))
        S, rhs = kernels.reduce_lines(index, G, Hll, gpt, gl, pattern)
        dense = np.zeros((4 * M, 4 * M))  # block column j: its block rows' 4 rows, 4 columns
        for j in range(M):
            nb = ptr[j + 1] - ptr[j]
            strip = S[16 * ptr[j]:16 * ptr[j + 1]].reshape(4, 4 * nb).T
            for m, i in enumerate(rows[ptr[j]:ptr[j + 1]]):
                dense[4 * i:4 * i + 4, 4 * j:4 * j + 4] = strip[4 * m:4 * m + 4]
        np.testing.assert_array_equal(dense, dense.T)
        want = np.linalg.solve(dense, rhs)
        for order in (np.arange(M), rng.permutation(M)):
            chol = kernels.BlockCholesky(pattern, order)
            assert chol.factor(S)
            np.testing.assert_allclose(chol.solve(rhs), want, rtol=0,
                                       atol=1e-10 * np.abs(want).max())
    assert not chol.factor(-S)
    with pytest.raises(ValueError, match="permutation"):
        kernels.BlockCholesky(pattern, np.zeros(M, np.int64))
