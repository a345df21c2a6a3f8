"""The line adjustment's compiled loops (omni_sfm/estimate/_lines.c) against the same formulas
written in numpy (bundle.py's before they were compiled): the values agree to round-off."""

from __future__ import annotations

import numpy as np
import pytest

from omni_sfm.estimate import kernels
from omni_sfm.estimate.bundle import (
    _LINE_PARTS,
    _POSE_PARTS,
    LineProblem,
    _normal_derivative,
    _pose_jacobian,
    _tangent_basis,
    resect_pose,
    triangulate_lines,
)
from omni_sfm.geometry import (
    FloatArray,
    cross3,
    normalize,
    predicted_normals,
    rotvec_to_matrix,
    skew,
)
from omni_sfm.solver import (
    RobustLoss,
    damped,
    isotropic_diagonal,
    levenberg_marquardt,
    loss_weights,
)
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


class _PoseProblem:
    """:func:`resect_pose`'s problem as bundle.py wrote it in numpy before it was compiled
    (``kernels.resect``): state ``(R, c, d, p)``, one observation of each line with residual
    basis ``B``, and direction-only normals ``m`` of world directions ``D`` (residual
    ``m . R^T D``)."""

    def __init__(self, B: FloatArray, d: FloatArray, dir_normals: FloatArray | None = None,
                 dir_world: FloatArray | None = None) -> None:
        self.B = B
        self.skew_d = skew(d)
        self.m = np.zeros((0, 3)) if dir_normals is None else dir_normals
        self.D = np.zeros((0, 3)) if dir_world is None else dir_world
        self._norms: tuple[FloatArray, FloatArray, FloatArray] | None = None

    def residuals(self, R: FloatArray, c: FloatArray, d: FloatArray,
                  p: FloatArray) -> tuple[FloatArray, FloatArray]:
        u = predicted_normals(R[None], c[None], p, d)
        with np.errstate(invalid="ignore", divide="ignore"):
            nu = np.sqrt(np.add.reduce(u * u, axis=1, keepdims=True))  # np.linalg.norm's sum
            n = u / nu
        self._norms = (u, nu[:, 0], n)
        e = np.einsum("kai,ki->ka", self.B, np.where(nu > 0, n, np.nan))  # normalize(u)
        if len(self.m):
            r = np.sum(self.m * (self.D @ R), axis=1)
            e = np.concatenate([e, np.stack([r, np.zeros_like(r)], axis=1)])
        return e, u

    def jacobian(self, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
                 u: FloatArray) -> tuple[FloatArray, FloatArray]:
        last = self._norms
        norms = (last[1], last[2]) if last is not None and last[0] is u else None
        # R^T broadcast against the K [d]x: numpy multiplies each pair, as with K copies of R
        _, J_rot, J_c = _pose_jacobian(R, d, u, self.B, rt_skew_d=R.T @ self.skew_d,
                                       norms=norms)
        J = np.concatenate([J_rot, J_c], axis=2)
        if len(self.m):
            Jd = np.zeros((len(self.m), 2, 6))
            Jd[:, 0, :3] = cross3(self.m, self.D @ R)  # d (m . R^T D) / d w, R <- R exp([w]x)
            J = np.concatenate([J, Jd])
        return J, np.zeros((len(J), 2, 0))

    def normal_equations(self, J: FloatArray, _J_line: FloatArray, e: FloatArray,
                         w: FloatArray) -> tuple[FloatArray, FloatArray]:
        return np.einsum("kai,k,kaj->ij", J, w, J), np.einsum("kai,k,ka->i", J, w, e)

    def solve(self, blocks: tuple[FloatArray, FloatArray],
              lam: float) -> tuple[FloatArray, FloatArray]:
        H, g = blocks
        dg = isotropic_diagonal(np.diag(H)[None], _POSE_PARTS)[0]
        damped = H + lam * np.diag(np.maximum(dg, 1e-12))
        return np.asarray(-np.linalg.solve(damped, g), np.float64), np.zeros(0)

    def retract(self, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
                step: FloatArray, _dline: FloatArray) -> tuple[FloatArray, ...]:
        return R @ rotvec_to_matrix(step[:3]), c + step[3:], d, p


def test_pose_problem_matches_the_general_formulas_and_finite_differences():
    """:func:`resect_pose`'s problem: its residuals and Jacobian (one rotation, the lines'
    ``[d]x`` formed once, the norms taken from the residuals) the same bit for bit as the
    adjustment's formulas with the rotation broadcast to every line, and the Jacobian (lines
    and direction-only normals) against finite differences through its retraction."""
    rng = np.random.default_rng(7)
    K = 9
    R, c = rotvec_to_matrix(rng.normal(size=3)), rng.normal(size=3)
    d = normalize(rng.normal(size=(K, 3)))
    p = rng.normal(size=(K, 3)) * 3.0
    B = np.stack(_tangent_basis(normalize(rng.normal(size=(K, 3)))), axis=1)
    D = normalize(rng.normal(size=(2, 3)))
    m = np.cross(D @ R, rng.normal(size=(2, 3))) + 0.05 * rng.normal(size=(2, 3))
    prob = _PoseProblem(B, d, m, D)
    st = (R, c, d, p)
    e, u = prob.residuals(*st)
    assert e.shape == (K + 2, 2) and (e[K:, 1] == 0).all()
    np.testing.assert_array_equal(u, predicted_normals(R[None], c[None], p, d))
    np.testing.assert_array_equal(e[:K], np.einsum("kai,ki->ka", B, normalize(u)))
    J, J_line = prob.jacobian(*st, u)
    assert J.shape == (K + 2, 2, 6) and J_line.shape == (K + 2, 2, 0)
    _, J_rot, J_c = _pose_jacobian(np.broadcast_to(R, (K, 3, 3)), d, u, B)
    np.testing.assert_array_equal(J[:K], np.concatenate([J_rot, J_c], axis=2))
    h = 1e-7
    for j in range(6):
        step = np.zeros(6)
        step[j] = h
        e2, _ = prob.residuals(*prob.retract(*st, step, np.zeros(0)))
        np.testing.assert_allclose((e2 - e) / h, J[:, :, j], atol=1e-5)
    # the Jacobian at the point of an earlier residual call: the norms are computed again
    prob.residuals(R @ rotvec_to_matrix(np.array([0.01, 0.0, 0.0])), c, d, p)
    np.testing.assert_array_equal(prob.jacobian(*st, u)[0], J)


def _resection(seed: int):
    """A camera, its lines (some of them outliers) and direction-only normals, a start off."""
    rng = np.random.default_rng(seed)
    K, J = int(rng.integers(4, 30)), int(rng.integers(0, 4))
    R, c = rotvec_to_matrix(rng.normal(size=3)), rng.normal(size=3)
    d = normalize(rng.normal(size=(K, 3)))
    p = rng.normal(size=(K, 3)) * 3.0
    n = normalize(predicted_normals(R[None], c[None], p, d) + rng.normal(size=(K, 3)) * 0.002)
    n[:seed % 3] = normalize(rng.normal(size=(seed % 3, 3)))
    D = normalize(rng.normal(size=(J, 3)))
    m = normalize(np.cross(D @ R, rng.normal(size=(J, 3))) + 0.002 * rng.normal(size=(J, 3)))
    R0 = R @ rotvec_to_matrix(rng.normal(size=3) * 0.02)
    return n, d, p, m, D, R0, c + rng.normal(size=3) * 0.05


@pytest.mark.parametrize("scale", [np.inf, 0.004])
def test_resection_is_numpys_levenberg_marquardt(scale: float) -> None:
    """The compiled resection (``kernels.resect`` through :func:`resect_pose`) against
    :func:`levenberg_marquardt` on the numpy problem: the same pose to the solver's tolerance,
    and the same angles at it."""
    loss = RobustLoss.HUBER if np.isfinite(scale) else RobustLoss.LINEAR
    for seed in range(40):
        n, d, p, m, D, R0, c0 = _resection(seed)
        R, c, ang = resect_pose(n, d, p, R0, c0, scale=scale, direction_normals=m,
                                directions=D)
        prob = _PoseProblem(np.stack(_tangent_basis(n), axis=1), d, m, D)
        (R_np, c_np, _, _), _ = levenberg_marquardt(prob, (R0.copy(), c0.copy(), d, p), loss,
                                                    scale, 10, 1e-10)
        assert np.abs(R - R_np).max() < 1e-8 and np.abs(c - c_np).max() < 1e-8
        e, u = prob.residuals(R, c, d, p)
        assert ang.shape == (len(d) + len(m),)
        np.testing.assert_allclose(ang[:len(d)], np.arctan2(
            np.linalg.norm(np.cross(normalize(u), n), axis=1),
            np.abs(np.sum(normalize(u) * n, axis=1))), atol=1e-12)
