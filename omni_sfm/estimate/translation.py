"""Translation of every view once the rotations are known (docs/method.md §5).

World normals ``m_ik = R_k n_ik`` (any sign). ``v`` is the parallel direction, ``(a, b, v)`` an
orthonormal basis.

(a) In the plane perpendicular to ``v`` (parallel lines). A parallel line ``i`` seen from view
``k`` lies on the in-plane line through the view's in-plane position ``t_k`` with normal
``h_ik = (m_ik . a, m_ik . b)`` (normalised): ``h_ik . (l_i - t_k) = 0`` (eq. 16, sign-free). The
scale is fixed by ``t_c = u = (cos psi, sin psi)`` (eq. 18). Each ``l_i`` is the intersection of
its lines from view 0 (at the origin) and view ``c`` (eq. 19-20) and is *linear* in ``u``:
``l_i = L_i u``. Each other view's ``t_k`` is the linear least-squares fit of eq. (21), so its
residual is linear in ``u`` too and ``E_t1(psi) = u^T S u`` exactly: a quadratic form on the
circle, whose global minimum over ``psi`` is the eigenvector of the 2x2 ``S`` with the smallest
eigenvalue. This replaces the paper's 1-DOF search by its exact solution (tests compare it with a
brute-force search over ``psi``). ``psi`` and ``psi + pi`` give the same cost: see below.

(b) Along ``v`` (non-parallel lines). ``t_c = t^p_c + omega_c v`` (eq. 24). Each line is
triangulated from views 0 and ``c`` (its direction from all views' normals), which is affine in
``omega_c``; each other view's ``omega_k`` is then the least-squares solution of
``m_ik . (x_i - t^p_k - omega_k v) = 0`` and ``E_t(omega_c)`` is a quadratic in ``omega_c``:
solved exactly.

Both steps weight every residual (a distance) by the inverse squared distance of the line from
the camera and iterate (``irls_iter``), which turns it into the angle of the paper's eq. (25) up
to second order, while keeping each step a closed form.

Sign: NVs with arbitrary sign cannot tell a line from its point reflection through the camera,
so the whole scene reflected through the first camera (``t_k -> -t_k``, lines likewise, rotations
unchanged) explains the normals exactly as well. :func:`resolve_sign` fixes it from rays that
point at the observed segments, when the caller has them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import (
    FloatArray,
    line_plane_normals,
    normalize,
    orthonormal_completion,
    ray_line_closest,
    smallest_eigenvector,
    unsigned_angle,
)


def plane_basis(v: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit ``a, b`` ``(3,)`` with ``(a, b, v)`` a right-handed orthonormal basis (unit ``v``).

    The negated :func:`~omni_sfm.geometry.orthonormal_completion`: the in-plane coordinates
    and the sign convention of :func:`estimate_plane` are defined in this basis."""
    e1, e2 = orthonormal_completion(v)
    return -e1, -e2


def _perp(x: FloatArray) -> FloatArray:
    """Rotate 2D vectors by +90 deg: ``(x, y) -> (-y, x)``."""
    return np.stack([-x[..., 1], x[..., 0]], -1)


def in_plane_parallax(world_normals: FloatArray, v: FloatArray) -> FloatArray:
    """``(F, P)`` angle (rad) between each parallel line's in-plane direction in view 0 and view k.

    ``world_normals (F, P, 3)`` of the parallel lines. Zero for a view that has not moved across
    the lines (relative to view 0).
    """
    a, b = plane_basis(v)
    h = normalize(np.stack([world_normals @ a, world_normals @ b], -1))
    s = np.abs(h[..., 0] * h[:1, :, 1] - h[..., 1] * h[:1, :, 0])
    c = np.abs(np.sum(h * h[:1], -1))
    return np.arctan2(s, c)


def line_parallax(world_normals: FloatArray) -> FloatArray:
    """``(F, Q)`` angle (rad) between each line's plane (its NV) in view 0 and in view k."""
    return unsigned_angle(world_normals, world_normals[:1])


@dataclass(frozen=True)
class PlaneResult:
    """In-plane positions (step a).

    Attributes:
        positions: ``(F, 3)`` in-plane camera positions in the world (``positions[0] = 0``,
            ``|positions[c]| = 1``), orthogonal to ``v``.
        points: ``(P, 3)`` where each parallel line pierces the plane through view 0.
        cost: ``E_t1`` at the solution (weighted sum of squared residuals ~ squared angles).
        ratio: smallest / largest eigenvalue of ``S`` (near 1: the direction is undetermined).
    """

    positions: FloatArray
    points: FloatArray
    cost: float
    ratio: float


def _plane_system(h: FloatArray, w: FloatArray, c: int) -> tuple[FloatArray, FloatArray,
                                                                     FloatArray, FloatArray]:
    """For 2D normals ``h (F, P, 2)`` and weights ``w (F, P)``: ``L (P,2,2)``, per-view ``S_k``,
    and the per-view maps ``t_k = T_k u`` (``(F,2,2)``), plus line validity ``(P,)``."""
    h0, hc = h[0], h[c]
    jh0 = _perp(h0)
    den = np.sum(hc * jh0, -1)                                         # sin of the parallax
    ok = np.abs(den) > 1e-12
    L = jh0[:, :, None] * hc[:, None, :] / np.where(ok, den, 1.0)[:, None, None]
    z = np.einsum("fpi,pij->fpj", h, L)                                # y_kp = z_kp . u
    w = w * ok[None, :]
    wh = (w[..., None] * h).transpose(0, 2, 1)
    H = wh @ h
    Zh = wh @ z                                                         # sum w h z^T
    Zz = (w[..., None] * z).transpose(0, 2, 1) @ z
    det = H[:, 0, 0] * H[:, 1, 1] - H[:, 0, 1] * H[:, 1, 0]
    good = np.abs(det) > 1e-14 * np.maximum(np.trace(H, axis1=1, axis2=2) ** 2, 1e-300)
    Hinv = np.zeros_like(H)
    Hinv[good] = np.linalg.inv(H[good])
    T = Hinv @ Zh                                                       # t_k = T_k u
    S = Zz - np.swapaxes(Zh, 1, 2) @ T
    S[~good] = 0.0
    T[~good] = np.nan
    return L, S, T, ok


def estimate_plane(world_normals: FloatArray, v: FloatArray, weights: FloatArray, c: int, *,
                   irls_iter: int = 2) -> PlaneResult:
    """Step (a): in-plane positions from the parallel lines' world normals ``(F, P, 3)``."""
    F, P = world_normals.shape[:2]
    a, b = plane_basis(v)
    h = normalize(np.stack([world_normals @ a, world_normals @ b], -1))
    w = np.broadcast_to(np.asarray(weights, dtype=np.float64)[None, :], (F, P)).copy()
    keep = np.ones(F, dtype=bool)
    keep[[0, c]] = False
    u = np.array([1.0, 0.0])
    cost, ratio = np.inf, 1.0
    L = T = np.zeros(0)
    for it in range(irls_iter + 1):
        L, S_k, T, ok = _plane_system(h, w, c)
        S = S_k[keep].sum(0)
        evals, evecs = np.linalg.eigh(S)
        if not np.isfinite(evals).all() or evals[1] <= 0:
            raise OmniSfmError("the in-plane translation is undetermined: the parallel lines show "
                               "no parallax between the views")
        u = evecs[:, 0]
        cost = float(max(evals[0], 0.0))
        ratio = float(max(evals[0], 0.0) / evals[1])
        if it == irls_iter:
            break
        # reweight by 1 / (in-plane distance of line from camera)^2 -> residuals become angles
        l2 = L @ u
        t2 = T @ u
        t2[0], t2[c] = 0.0, u
        dist2 = np.sum((l2[None] - t2[:, None]) ** 2, -1)
        scale = np.nanmedian(dist2[:, ok]) if np.any(ok) else 1.0
        w = np.asarray(weights, dtype=np.float64)[None, :] * scale / np.maximum(
            np.nan_to_num(dist2, nan=np.inf), 1e-6 * scale)
    # the sign convention without cheirality: u along +a
    if u[0] < 0 or (u[0] == 0 and u[1] < 0):
        u = -u
    t2 = T @ u
    t2[0], t2[c] = 0.0, u
    l2 = L @ u
    pos = t2[:, :1] * a + t2[:, 1:] * b
    pts = l2[:, :1] * a + l2[:, 1:] * b
    return PlaneResult(pos, pts, cost, ratio)


@dataclass(frozen=True)
class VerticalResult:
    """Positions along ``v`` (step b).

    Attributes:
        omega: ``(F,)`` coordinate of each view along ``v`` (``omega[0] = 0``).
        cost: ``E_t`` at the solution (weighted sum of squared residuals ~ squared angles).
    """

    omega: FloatArray
    cost: float


def line_directions(world_normals: FloatArray, weights: FloatArray | None = None) -> FloatArray:
    """``(Q, 3)`` direction of each line from all its world normals ``(F, Q, 3)`` (eq. 5 again)."""
    w = np.ones(world_normals.shape[0]) if weights is None else weights
    return smallest_eigenvector(np.einsum("f,fqi,fqj->qij", w, world_normals, world_normals))


def estimate_vertical(world_normals: FloatArray, directions: FloatArray, v: FloatArray,
                      plane_positions: FloatArray, weights: FloatArray, c: int, *,
                      irls_iter: int = 2) -> VerticalResult:
    """Step (b): coordinates along ``v`` from the non-parallel lines.

    Args:
        world_normals: ``(F, Q, 3)`` world normals of the non-parallel lines.
        directions: ``(Q, 3)`` their unit directions.
        v: ``(3,)`` the parallel direction.
        plane_positions: ``(F, 3)`` in-plane positions from step (a).
        weights: ``(Q,)`` line weights.
        c: the second view.
    """
    F, Q = world_normals.shape[:2]
    m = world_normals
    B = np.stack([m[0], m[c], directions], 1)                          # (Q, 3, 3)
    det = np.linalg.det(B)
    ok = np.abs(det) > 1e-9
    beta = np.zeros((Q, 3))
    beta[ok] = np.linalg.inv(B[ok])[:, :, 1]                            # x_i = beta_i (m_ic.t_c)
    mb = np.einsum("fqi,qi->fq", m, beta)                               # m_ik . beta_i
    mct = m[c] @ plane_positions[c]
    mcv = m[c] @ v
    alpha = mb * mct[None, :] - np.einsum("fqi,fi->fq", m, plane_positions)
    gamma = mb * mcv[None, :]
    eta = m @ v
    keep = np.ones(F, dtype=bool)
    keep[[0, c]] = False
    base_w = np.asarray(weights, dtype=np.float64) * ok
    w = np.broadcast_to(base_w[None, :], (F, Q)).copy()
    omega_c, cost = 0.0, np.inf
    omega = np.zeros(F)
    for it in range(irls_iter + 1):
        se = np.sum(w * eta * eta, 1)
        good = se > 1e-14 * np.maximum(np.sum(w, 1), 1e-300)
        inv = np.where(good, 1.0 / np.where(good, se, 1.0), 0.0)
        sea, seg = np.sum(w * eta * alpha, 1), np.sum(w * eta * gamma, 1)
        A2 = np.sum(w * gamma * gamma, 1) - seg * seg * inv
        A1 = np.sum(w * alpha * gamma, 1) - sea * seg * inv
        A0 = np.sum(w * alpha * alpha, 1) - sea * sea * inv
        a2, a1 = A2[keep & good].sum(), A1[keep & good].sum()
        if not a2 > 1e-14 * max(np.sum(w[keep] * gamma[keep] ** 2), 1e-300):
            raise OmniSfmError("the translation along the parallel lines is undetermined: the "
                               "non-parallel lines show no parallax along them")
        omega_c = -a1 / a2
        omega = np.where(good, (sea + omega_c * seg) * inv, np.nan)
        omega[0], omega[c] = 0.0, omega_c
        cost = float(np.sum((A0 + 2 * omega_c * A1 + omega_c ** 2 * A2)[keep & good]))
        if it == irls_iter:
            break
        pos = plane_positions + omega[:, None] * v
        x = beta * (m[c] @ pos[c])[:, None]                             # (Q, 3) line points
        rel = x[None] - pos[:, None]
        rel -= np.sum(rel * directions[None], -1, keepdims=True) * directions[None]
        dist2 = np.sum(rel * rel, -1)
        scale = float(np.median(dist2[:, ok])) if np.any(ok) else 1.0
        w = base_w[None, :] * scale / np.maximum(np.nan_to_num(dist2, nan=np.inf), 1e-6 * scale)
    return VerticalResult(omega, max(cost, 0.0))


def _tangent_bases(d: FloatArray) -> FloatArray:
    """``(L, 3, 2)`` orthonormal bases of the planes perpendicular to the unit ``d (L, 3)``."""
    return np.stack(orthonormal_completion(d), -1)


def _weighted_solve(m: FloatArray, y: FloatArray, w: FloatArray
                    ) -> tuple[FloatArray, float, FloatArray]:
    """One weighted solve of :func:`translation_all_views`: ``(z (L, 2), cost, T (F, 3, 2L))``,
    the lines' offsets (the eigenvector of the smallest eigenvalue of the reduced form), that
    eigenvalue, and the map ``t_k = T_k z`` from them to each view's position (``t_0 = 0``).
    ``m`` ``(F, L, 3)`` world normals, ``y`` ``(F, L, 2)`` their products with the lines'
    tangent bases, ``w`` ``(F, L)`` weights."""
    F, L = m.shape[:2]
    H = (w[..., None] * m).transpose(0, 2, 1) @ m
    G = (w[..., None, None] * y[..., :, None]) * m[..., None, :]    # (F, L, 2, 3)
    ridge = 1e-12 * np.trace(H[1:], axis1=1, axis2=2)[:, None, None] * np.eye(3)
    Hinv = np.linalg.inv(H[1:] + ridge)
    GH = (G[1:].reshape(F - 1, 2 * L, 3) @ Hinv).reshape(F - 1, L, 2, 3)
    Z = -(GH.transpose(1, 2, 0, 3).reshape(2 * L, -1)
          @ G[1:].transpose(0, 3, 1, 2).reshape(-1, 2 * L)).reshape(L, 2, L, 2)
    diag = np.einsum("fl,fla,flb->lab", w, y, y)
    idx = np.arange(L)
    Z[idx, :, idx, :] += diag
    vals, vecs = np.linalg.eigh(Z.reshape(2 * L, 2 * L))
    # t_k = H_k^-1 sum_l w m (m . B_l z_l)
    T = np.zeros((F, 3, 2 * L))
    T[1:] = Hinv @ G[1:].reshape(F - 1, 2 * L, 3).transpose(0, 2, 1)
    return vecs[:, 0].reshape(L, 2), float(max(vals[0], 0.0)), T


def translation_all_views(world_normals: FloatArray, directions: FloatArray,
                          weights: FloatArray, *, irls_iter: int = 3,
                          reference: FloatArray | None = None) -> tuple[FloatArray, FloatArray,
                                                                        float]:
    """Positions and line points from all views at once, given rotations and line directions.

    Every observation says the camera lies in the line's plane: ``m_lk . (x_l - t_k) = 0`` with
    ``x_l = B_l z_l`` (``B_l`` spans the plane perpendicular to ``d_l``, ``z_l`` 2 unknowns) and
    ``t_0 = 0``. Homogeneous and linear: each view's ``t_k`` is eliminated by its 3x3 normal
    equations, leaving a ``2L x 2L`` quadratic form in ``z`` whose eigenvector of the smallest
    eigenvalue is the least-squares solution up to scale (and sign: the point reflection).
    Residuals are reweighted by the inverse squared camera-line distance (``irls_iter`` rounds),
    making them angles, as in the paper's costs.

    Args:
        world_normals: ``(F, L, 3)`` world normals of every line in every view.
        directions: ``(L, 3)`` unit line directions.
        weights: ``(L,)`` non-negative weights.
        reference: ``(F, 3)`` positions whose scale and sign to adopt (least-squares scale).

    Returns ``positions (F, 3)``, ``points (L, 3)`` (closest to the origin) and the final
    weighted cost.
    """
    m = world_normals
    F, L = m.shape[:2]
    B = _tangent_bases(directions)
    y = np.einsum("fli,lia->fla", m, B)                                   # m . B_l
    w = np.broadcast_to(np.asarray(weights, dtype=np.float64)[None, :], (F, L)).copy()
    z = np.zeros((L, 2))
    T = np.zeros((F, 3, 2 * L))
    cost = np.inf
    for it in range(irls_iter + 1):
        z, cost, T = _weighted_solve(m, y, w)
        if it == irls_iter:
            break
        pos = T @ z.reshape(-1)
        pts = np.einsum("lia,la->li", B, z)
        rel = pts[None] - pos[:, None]
        rel -= np.sum(rel * directions[None], -1, keepdims=True) * directions[None]
        dist2 = np.sum(rel * rel, -1)
        scale = float(np.median(dist2[:, weights > 0]))
        w = np.asarray(weights, dtype=np.float64)[None, :] * scale / np.maximum(dist2,
                                                                              1e-6 * scale)
    pos = T @ z.reshape(-1)
    pts = np.einsum("lia,la->li", B, z)
    if reference is not None:
        k = float(np.sum(pos * reference) / max(float(np.sum(pos * pos)), 1e-300))
        pos, pts = pos * k, pts * k
        cost *= k * k
    return pos, pts, cost


def line_points(world_normals: FloatArray, directions: FloatArray,
                positions: FloatArray) -> FloatArray:
    """``(L, 3)`` point of each line of known direction closest to the world origin, from the
    normals of all views (every line seen in every view, the paper's setting).

    Minimises ``sum_k (m_ik . (x - t_k))^2`` with ``x . d_i = 0``; ``world_normals (F, L, 3)``,
    ``directions (L, 3)``, ``positions (F, 3)``. (Lines of partial tracks, directions and
    points, from poses: :func:`omni_sfm.estimate.bundle.triangulate_lines`.)
    """
    m = world_normals
    A = np.einsum("fli,flj->lij", m, m) + np.einsum("li,lj->lij", directions, directions)
    rhs = np.einsum("fli,fl->li", m, np.einsum("fli,fi->fl", m, positions))
    return np.linalg.solve(A, rhs[..., None])[..., 0]


def normal_residuals(world_normals: FloatArray, directions: FloatArray, points: FloatArray,
                     positions: FloatArray) -> FloatArray:
    """``(F, L)`` angle (rad) between each observed world normal and the one the model predicts.

    The predicted NV of line ``l`` (``points``, ``directions`` ``(L, 3)``) from the camera at
    ``positions[k]`` is ``(x_l - t_k) x d_l`` normalised; the angle ignores the normals' signs.
    """
    pred = line_plane_normals(positions[:, None], points[None], directions[None])
    pred /= np.maximum(np.linalg.norm(pred, axis=-1, keepdims=True), 1e-300)
    return unsigned_angle(world_normals, pred)


def resolve_sign(rays_in_world: FloatArray, origins: FloatArray, points: FloatArray,
                 directions: FloatArray, mask: np.ndarray | None = None) -> float:
    """+1 or -1: the sign of the reconstruction that puts the lines in front of the rays.

    ``rays_in_world (F, L, 3)`` point from the camera at ``origins (F, 3)`` towards a point of
    line ``l`` (``points``, ``directions`` ``(L, 3)``) as observed; ``mask (F, L)`` selects the
    rays to use. Each ray votes with the sign of the ray parameter of its closest approach to the
    line; the reflected reconstruction reverses every vote.
    """
    lam, _, _ = ray_line_closest(origins[:, None], rays_in_world, points[None],
                                 directions[None])                       # (F, L)
    if mask is not None:
        lam = np.where(mask, lam, 0.0)
    vote = float(np.sum(np.sign(np.nan_to_num(lam))))
    return -1.0 if vote < 0 else 1.0
