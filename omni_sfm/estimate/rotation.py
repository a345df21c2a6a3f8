"""Rotation of every view from the VPVs and the non-parallel lines (docs/method.md §4).

Conventions: ``world_from_cam`` rotations ``R_k`` (a normal ``n`` seen in view ``k`` is
``R_k n`` in the world), world = the camera of view 0, so the paper's ``R_c^T`` is our ``R_c``.

1. ``A_k`` rotates the VPV ``v_k`` of view ``k`` onto ``v = v_0`` (eq. 7-9).
2. ``R_k = R_v(phi_k) A_k`` with ``R_v`` the rotation about ``v`` (eq. 10). For a trial angle
   ``phi_c`` of the second view ``c`` each non-parallel line gets the direction
   ``d_i = n_i0 x R_c n_ic`` (eq. 12); every other view's ``phi_k`` then minimises
   ``e_k(phi) = sum_i w_i ((R_k n_ik) . d_i)^2`` (eq. 13), a trigonometric polynomial of degree 2
   whose global minimum :func:`trig2_minimize` finds exactly, vectorised over views.
3. ``E_rot(phi_c) = sum_k min e_k`` (eq. 14) is minimised globally over the circle by
   :func:`omni_sfm.estimate.search.global_minimize_1d`.

Every formula is invariant to the (arbitrary) sign of each normal: the residuals are squared and
``d_i``'s sign cancels in them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.search import global_minimize_1d
from omni_sfm.geometry import (
    FloatArray,
    cross3,
    normalize,
    orthonormal_completion,
    skew,
    smallest_eigenvector,
)


def rotation_aligning(a: FloatArray, b: FloatArray) -> FloatArray:
    """The smallest rotations ``(..., 3, 3)`` taking unit vectors ``a`` onto ``b`` (``R a = b``).

    Defined for ``a . b > -1`` (the rotation axis is ``a x b``, the angle ``arccos(a . b)``,
    eq. 8-9); exactly antiparallel pairs are rotated by pi about an axis perpendicular to ``a``.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a, b = np.broadcast_arrays(a, b)
    w = np.cross(a, b)
    c = np.sum(a * b, axis=-1)
    K = skew(w)
    eye = np.broadcast_to(np.eye(3), K.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        R = eye + K + (K @ K) / (1.0 + c)[..., None, None]
    anti = c <= -1.0 + 1e-12
    if np.any(anti):
        # rotation by pi about an axis u perpendicular to a: 2 u u^T - I
        u, _ = orthonormal_completion(a[anti])
        R[anti] = 2.0 * u[:, :, None] * u[:, None, :] - np.eye(3)
    return R


def trig2_eval(coef: FloatArray, phi: FloatArray) -> FloatArray:
    """``a1 cos p + b1 sin p + a2 cos 2p + b2 sin 2p`` for ``coef (..., 4) = (a1, b1, a2, b2)``."""
    return (coef[..., 0] * np.cos(phi) + coef[..., 1] * np.sin(phi)
            + coef[..., 2] * np.cos(2 * phi) + coef[..., 3] * np.sin(2 * phi))


def trig2_minimize(coef: FloatArray, *, max_iter: int = 80) -> FloatArray:
    """Global minimiser ``phi`` (radians, ``(...,)``) of the degree-2 trigonometric polynomial.

    ``f(phi) = a1 cos phi + b1 sin phi + a2 cos 2phi + b2 sin 2phi`` with ``coef (..., 4)``.

    Exact method: with ``x = (cos phi, sin phi)``, ``f = x^T A x + 2 b^T x`` where
    ``A = [[a2, b2], [b2, -a2]]`` (eigenvalues ``+-rho``) and ``b = (a1, b1) / 2``. The global
    minimum on the unit circle is the stationary point ``(A - mu I) x = -b`` with the Lagrange
    multiplier ``mu <= -rho`` (the trust-region condition); in A's eigenbasis, with
    ``s = -rho - mu >= 0``, it solves the secular equation
    ``p^2 / (2 rho + s)^2 + q^2 / s^2 = 1`` whose left side falls monotonically, so the root
    is unique and bracketed by ``[max(|q|, |p| - 2 rho), sqrt(p^2 + q^2)]``. It is found by Newton's
    method on ``g(s)^(-1/2) - 1`` (concave, so Newton from the lower bound climbs monotonically),
    all problems at once.
    The "hard case" ``q = 0, |p| <= 2 rho`` has ``s = 0`` and is handled explicitly. This is
    equivalent to the paper's quartic (the secular equation multiplied out is a quartic in ``s``)
    without its spurious roots.
    """
    coef = np.asarray(coef, dtype=np.float64)
    a1, b1, a2, b2 = (coef[..., j] for j in range(4))
    rho = np.hypot(a2, b2)
    half = 0.5 * np.arctan2(b2, a2)
    e1 = np.stack([np.cos(half), np.sin(half)], -1)      # eigenvector of +rho
    e2 = np.stack([-np.sin(half), np.cos(half)], -1)     # eigenvector of -rho
    bb = 0.5 * np.stack([a1, b1], -1)
    p = np.sum(bb * e1, -1)
    q = np.sum(bb * e2, -1)
    ap, aq = np.abs(p), np.abs(q)
    lo = np.maximum(aq, np.maximum(ap - 2.0 * rho, 0.0))
    hi = np.hypot(ap, aq)                     # g(hi) <= (p^2 + q^2) / hi^2 = 1
    hard = (aq <= 1e-300) | (hi <= 0)

    # h(s) = g(s)^(-1/2) - 1 is increasing and concave in s (Moré-Sorensen), and h(lo) <= 0:
    # Newton's iterates from lo climb monotonically to the root, no safeguard needed
    s = np.where(hard, 1.0, np.maximum(lo, 1e-300))
    p2, q2 = p * p, q * q
    for _ in range(max_iter):
        u = 2.0 * rho + s
        g = p2 / (u * u) + q2 / (s * s)
        dg = -2.0 * (p2 / (u * u * u) + q2 / (s * s * s))
        with np.errstate(divide="ignore", invalid="ignore"):
            step = 2.0 * (g - g * np.sqrt(g)) / dg
        step = np.where(hard | ~np.isfinite(step), 0.0, step)
        s = np.minimum(s + step, hi)
        if not np.any(np.abs(step) > 1e-14 * s):
            break
    s = np.where(hard, 0.0, s)

    with np.errstate(divide="ignore", invalid="ignore"):
        y1 = np.where(hard, np.where(rho > 0, -p / (2.0 * rho), 0.0), -p / (2.0 * rho + s))
        y1 = np.clip(y1, -1.0, 1.0)
        y2_hard = np.sqrt(np.maximum(1.0 - y1 * y1, 0.0)) * np.where(q > 0, -1.0, 1.0)
        y2 = np.where(hard, y2_hard, -q / s)
    y = normalize(np.stack([y1, y2], -1))
    x = y[..., :1] * e1 + y[..., 1:] * e2
    phi = np.arctan2(x[..., 1], x[..., 0])
    return np.where(np.isfinite(phi), phi, 0.0)


def _view_costs(a: FloatArray, b: FloatArray, cc: FloatArray, wq: FloatArray,
                phi: FloatArray) -> FloatArray:
    """``e_k(phi_k) = sum_q wq (a cos phi_k + b sin phi_k + cc)^2`` for ``a, b, cc (..., Q)``
    and angles ``phi (...)`` (:meth:`RotationProblem._view_terms`)."""
    r = a * np.cos(phi)[..., None] + b * np.sin(phi)[..., None] + cc
    return np.sum(wq * r * r, -1)


@dataclass(frozen=True)
class RotationProblem:
    """The rotation problem of one window, prepared for fast evaluation of ``E_rot(phi_c)``.

    Attributes:
        v: ``(3,)`` the parallel direction in the world (= view 0's VPV).
        align: ``(F, 3, 3)`` ``A_k`` with ``A_k v_k = v``.
        w_par, w_perp, w_cross: ``(F, Q, 3)`` parts of ``w = A_k n_ik`` of the non-parallel lines:
            ``R_v(phi) w = w_par + cos(phi) w_perp + sin(phi) w_cross``.
        weights: ``(Q,)`` per-line weights.
        second_view: ``c``.
        softening: ``s0``: each line's residuals are weighted by ``s^2 / (s^2 + s0^2)`` with
            ``s = |n_i0 x R_c n_ic|`` the sine of its parallax between views 0 and ``c``: a line
            seen with little parallax has an ill-defined ``d_i`` (eq. 12) whose normalised
            residuals jump with ``phi_c``; softened, they fade smoothly (0: the paper's cost).
    """

    v: FloatArray
    align: FloatArray
    w_par: FloatArray
    w_perp: FloatArray
    w_cross: FloatArray
    weights: FloatArray
    second_view: int
    softening: float = 0.1

    @classmethod
    def build(cls, normals: FloatArray, vpv: FloatArray, weights: FloatArray,
              second_view: int, softening: float = 0.1) -> RotationProblem:
        """``normals (F, Q, 3)`` of the non-parallel lines (camera frames), ``vpv (F, 3)``."""
        v = vpv[0]
        align = rotation_aligning(vpv, np.broadcast_to(v, vpv.shape))
        align[0] = np.eye(3)
        w = np.einsum("fij,fqj->fqi", align, normals)
        w_par = np.einsum("fq,i->fqi", w @ v, v)
        w_perp = w - w_par
        w_cross = np.cross(v, w)
        return cls(v, align, w_par, w_perp, w_cross, np.asarray(weights, dtype=np.float64),
                   int(second_view), float(softening))

    def directions(self, phi_c: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``d_i`` (eq. 12) for trial ``phi_c (G,)``: ``(G, Q, 3)``, weight factors ``(G, Q)``."""
        c = self.second_view
        cs, sn = np.cos(phi_c)[:, None, None], np.sin(phi_c)[:, None, None]
        m_c = self.w_par[c] + cs * self.w_perp[c] + sn * self.w_cross[c]
        n0 = self.w_par[0] + self.w_perp[0]
        d = cross3(n0, m_c)
        norm = np.linalg.norm(d, axis=-1)
        ok = norm > 1e-12
        d = d / np.where(ok, norm, 1.0)[..., None]
        s2 = norm * norm
        return d, ok * (s2 / (s2 + self.softening ** 2))

    def _view_terms(self, phi_c: FloatArray) -> tuple[FloatArray, ...]:
        """``e_k(phi) = sum_q wq (a cos phi + b sin phi + cc)^2``: ``a, b, cc (G, F, Q)``,
        ``wq (G, 1, Q)`` and the trigonometric coefficients ``(G, F, 4)`` of ``e_k``."""
        d, ok = self.directions(phi_c)
        wt = self.weights[None, :] * ok                                   # (G, Q)
        a = np.einsum("fqj,gqj->gfq", self.w_perp, d)
        b = np.einsum("fqj,gqj->gfq", self.w_cross, d)
        cc = np.einsum("fqj,gqj->gfq", self.w_par, d)
        wq = wt[:, None, :]
        coef = np.stack([np.sum(wq * 2 * a * cc, -1), np.sum(wq * 2 * b * cc, -1),
                         np.sum(wq * 0.5 * (a * a - b * b), -1), np.sum(wq * a * b, -1)], -1)
        return a, b, cc, wq, coef

    def view_fit(self, phi_c: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Each view's best ``phi_k`` and cost ``e_k`` for trial ``phi_c (G,)``: two ``(G, F)``."""
        a, b, cc, wq, coef = self._view_terms(phi_c)
        phi = trig2_minimize(coef)
        return phi, _view_costs(a, b, cc, wq, phi)

    def half_turn_alternatives(self, phi_c: float,
                               phi: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Each view's local minimum of ``e_k`` nearest ``phi_k + pi``, for the second view's
        angle ``phi_c``: angles ``(F,)``, their costs and the costs at ``phi`` (both ``(F,)``).

        Lines perpendicular to the parallel direction cannot tell ``R_v(phi)`` from
        ``R_v(phi + pi)`` (the half turn maps their directions onto their opposites, and normals
        carry no sign); only lines oblique to ``v`` and noise separate the two minima.
        """
        a, b, cc, wq, coef = (x[0] for x in self._view_terms(np.array([phi_c])))
        a1, b1, a2, b2 = coef.T
        alt = np.asarray(phi, dtype=np.float64) + np.pi
        for _ in range(30):  # Newton on e_k'(phi) = 0, steps clipped, towards a minimum
            g = -a1 * np.sin(alt) + b1 * np.cos(alt) - 2 * a2 * np.sin(2 * alt) \
                + 2 * b2 * np.cos(2 * alt)
            h = -a1 * np.cos(alt) - b1 * np.sin(alt) - 4 * a2 * np.cos(2 * alt) \
                - 4 * b2 * np.sin(2 * alt)
            scale = np.abs(a1) + np.abs(b1) + 4 * (np.abs(a2) + np.abs(b2)) + 1e-300
            step = np.where(h > 1e-9 * scale, -g / np.where(h > 0, h, 1.0), -g / scale)
            alt = alt + np.clip(step, -0.2, 0.2)
            if np.all(np.abs(step) < 1e-12):
                break
        return (np.angle(np.exp(1j * alt)), _view_costs(a, b, cc, wq, alt),
                _view_costs(a, b, cc, wq, np.asarray(phi, dtype=np.float64)))

    def cost(self, phi_c: FloatArray) -> FloatArray:
        """``E_rot(phi_c)`` (eq. 14) for ``phi_c (G,)``, views 0 and ``c`` excluded (zero)."""
        _, e = self.view_fit(np.atleast_1d(phi_c))
        keep = np.ones(e.shape[1], dtype=bool)
        keep[[0, self.second_view]] = False
        return np.sum(e[:, keep], axis=1)

    def angles_at(self, phi_c: float) -> tuple[FloatArray, FloatArray]:
        """Every view's angle ``(F,)`` (``phi_0 = 0``, ``phi_c``) and cost ``e_k`` ``(F,)``."""
        phi_all, e = self.view_fit(np.array([phi_c]))
        phi = phi_all[0].copy()
        phi[0] = 0.0
        phi[self.second_view] = phi_c
        e = e[0].copy()
        e[[0, self.second_view]] = 0.0
        return phi, e

    def rotations(self, phi: FloatArray) -> FloatArray:
        """``R_k = R_v(phi_k) A_k`` for ``phi (F,)``: ``(F, 3, 3)`` world_from_cam."""
        from omni_sfm.geometry import rotation_about_axis

        return rotation_about_axis(self.v, phi) @ self.align


def keep_continuity(prob: RotationProblem, phi_c: float, phi: FloatArray, *,
                    tolerance: float = 1.0) -> tuple[FloatArray, FloatArray]:
    """Undo half turns about ``v`` that the data do not ask for, in view order.

    Views are consecutive video frames, so a camera does not turn by more than 90 deg about
    ``v`` between one view and the next. Where view ``k``'s angle jumps by more than that from
    the previous view's (view 0: 0) and its half-turn alternative
    (:meth:`RotationProblem.half_turn_alternatives`) costs at most ``tolerance`` times
    ``e_k``'s minimum more, the alternative is taken. A real half turn of the data (lines
    oblique to ``v`` that reject the alternative) is kept. Views 0 and ``c`` keep their angles
    (the search decided ``phi_c``; :func:`estimate_rotations` also tries ``phi_c + pi``).

    Returns the angles and each view's cost ``e_k``, ``(F,)`` both (views 0 and ``c``: 0, as
    in :meth:`RotationProblem.angles_at`).
    """
    out = np.array(phi, dtype=np.float64, copy=True)
    alt, e_alt, e_min = prob.half_turn_alternatives(phi_c, out)
    e = e_min.copy()
    prev = 0.0
    for k in range(1, out.shape[0]):
        if k != prob.second_view:
            jump = abs(np.angle(np.exp(1j * (out[k] - prev))))
            jump_alt = abs(np.angle(np.exp(1j * (alt[k] - prev))))
            if jump > np.pi / 2 and jump_alt < np.pi / 2 and \
                    e_alt[k] - e_min[k] <= tolerance * max(e_min[k], 1e-300):
                out[k], e[k] = alt[k], e_alt[k]
        prev = out[k]
    e[[0, prob.second_view]] = 0.0
    return out, e


def _polish_step(W: FloatArray, m: FloatArray, dm: FloatArray, d: FloatArray, e1: FloatArray,
                 e2: FloatArray, lam: float) -> tuple[FloatArray, FloatArray] | None:
    """One damped Gauss-Newton step of :func:`polish_angles`: ``(step of the angles (F,),
    step of the directions in their tangent bases (Q, 2))``, the angles eliminated by their
    diagonal Schur complement; None where the reduced system is singular."""
    F, Q = m.shape[:2]
    r = np.einsum("fqi,qi->fq", m, d)
    jp = np.einsum("fqi,qi->fq", dm, d)                                # d r / d phi_k
    jd = np.stack([np.einsum("fqi,qi->fq", m, e1), np.einsum("fqi,qi->fq", m, e2)], -1)
    jp[0] = 0.0                                                         # phi_0 is fixed
    hpp = np.sum(W * jp * jp, 1)
    hpd = W[None, :, None] * jp[..., None] * jd                        # (F, Q, 2)
    hdd = np.einsum("q,fqa,fqb->qab", W, jd, jd)
    gp = np.sum(W * jp * r, 1)
    gd = np.einsum("q,fqa,fq->qa", W, jd, r)
    inv_p = np.where(hpp > 0, 1.0 / (hpp * (1 + lam) + 1e-300), 0.0)
    red = -((inv_p[:, None] * hpd.reshape(F, 2 * Q)).T @ hpd.reshape(F, 2 * Q)).reshape(
        Q, 2, Q, 2)
    idx = np.arange(Q)
    red[idx, :, idx, :] += hdd * (1 + lam) + np.eye(2) * 1e-15
    rhs = gd - np.einsum("f,fqa,f->qa", inv_p, hpd, gp)
    try:
        step_d = -np.linalg.solve(red.reshape(2 * Q, 2 * Q), rhs.reshape(2 * Q)).reshape(Q, 2)
    except np.linalg.LinAlgError:
        return None
    return -inv_p * (gp + np.einsum("fqa,qa->f", hpd, step_d)), step_d


def polish_angles(prob: RotationProblem, phi: FloatArray, *, max_iter: int = 30,
                  tol: float = 1e-13) -> tuple[FloatArray, FloatArray, float]:
    """Joint least squares over all views: the angles ``phi_k`` (``phi_0 = 0`` fixed) and every
    non-parallel line's direction ``d_i``, minimising ``sum_ik w_i ((R_k n_ik) . d_i)^2``.

    The paper's ``d_i`` come from views 0 and ``c`` only; with noise, all views determine them
    much better. Levenberg-Marquardt from the paper's solution; ``d_i`` has 2 tangent DOF; the
    per-view angles are eliminated by their (diagonal) Schur complement, leaving a ``2Q x 2Q``
    system. Returns ``phi (F,)``, ``d (Q, 3)`` and the final cost.
    """
    F, Q = prob.w_par.shape[:2]
    W = prob.weights

    def state(ph: FloatArray) -> tuple[FloatArray, FloatArray]:
        cs, sn = np.cos(ph)[:, None, None], np.sin(ph)[:, None, None]
        m = prob.w_par + cs * prob.w_perp + sn * prob.w_cross
        dm = cs * prob.w_cross - sn * prob.w_perp
        return m, dm

    m, dm = state(phi)
    d = smallest_eigenvector(np.einsum("q,fqi,fqj->qij", np.ones(Q), m, m))
    cost = float(np.sum(W * np.einsum("fqi,qi->fq", m, d) ** 2))
    lam = 1e-6
    for _ in range(max_iter):
        e1, e2 = orthonormal_completion(d)
        step = _polish_step(W, m, dm, d, e1, e2, lam)
        if step is None:
            break
        step_p, step_d = step
        phi_new = phi + step_p
        phi_new[0] = 0.0
        d_new = d + step_d[:, :1] * e1 + step_d[:, 1:] * e2
        d_new /= np.linalg.norm(d_new, axis=1, keepdims=True)
        m_new, dm_new = state(phi_new)
        cost_new = float(np.sum(W * np.einsum("fqi,qi->fq", m_new, d_new) ** 2))
        if cost_new <= cost:
            small = np.max(np.abs(step_p)) < tol and np.max(np.abs(step_d)) < tol
            phi, d, m, dm = phi_new, d_new, m_new, dm_new
            improvement = cost - cost_new
            cost = cost_new
            lam = max(lam / 10, 1e-12)
            if small or improvement <= 1e-15 * max(cost, 1e-300):
                break
        else:
            lam *= 10
            if lam > 1e8:
                break
    return phi, d, cost


@dataclass(frozen=True)
class RotationResult:
    """Rotations of a window.

    Attributes:
        rotations: ``(F, 3, 3)`` world_from_cam, ``rotations[0] = I``.
        phi: ``(F,)`` angle about ``v`` of each view (radians), ``phi[0] = 0``.
        second_view: the ``c`` used.
        cost: ``E_rot`` at the solution (sum of squared sines of angles, weighted).
        view_costs: ``(F,)`` each view's ``e_k``.
        num_evals: cost evaluations of the 1-DOF search.
        polished_cost: the joint all-view cost after :func:`polish_angles` (NaN if not run).
        other_minima: ``(F,)`` angles of every view at the search's other local minima of
            ``E_rot`` (higher, unpolished): alternatives when noise makes basins compete.
        other_costs: ``E_rot`` (all views) at each of ``other_minima``.
    """

    rotations: FloatArray
    phi: FloatArray
    second_view: int
    cost: float
    view_costs: FloatArray
    num_evals: int
    polished_cost: float = float("nan")
    other_minima: tuple[FloatArray, ...] = ()
    other_costs: tuple[float, ...] = ()


def _candidates(prob: RotationProblem, xs: list[float], continuity: bool
                ) -> list[tuple[int, float, FloatArray, FloatArray]]:
    """``(half turns, cost, angles, per-view costs)`` of every view's angles solved at each of
    the second view's angles ``xs`` (the search's minima), the best first. With
    ``continuity`` the half turn of each is tried too (wherever the lines perpendicular to
    ``v`` dominate it is a minimum as well, and may be the one whose angles run continuously),
    and where some candidates have no half turn between neighbouring views, only those are
    kept, lowest cost first."""
    if continuity:
        xs = xs + [float(np.angle(np.exp(1j * (x + np.pi)))) for x in xs]
    cands = []
    for x in xs:
        phi_x, e_x = prob.angles_at(x)
        jumps = 0
        if continuity:
            phi_x, e_x = keep_continuity(prob, x, phi_x)
            jumps = count_half_turns(phi_x)
        cands.append((jumps, float(e_x.sum()), phi_x, e_x))
    if continuity and any(j == 0 for j, *_ in cands):
        # consecutive frames do not turn by more than 90 deg about v: among the minima, those
        # without such jumps, lowest cost first
        cands = [c for c in cands if c[0] == 0]
        cands.sort(key=lambda c: c[1])
    return cands


def estimate_rotations(normals: FloatArray, vpv: FloatArray, weights: FloatArray,
                       second_view: int, *, num_grid: int = 64, num_starts: int = 3,
                       xtol: float = 1e-12, softening: float = 0.1,
                       polish: bool = True, search_views: int | None = None,
                       continuity: bool = True) -> RotationResult:
    """Rotations of all views (docs/method.md §4).

    Args:
        normals: ``(F, Q, 3)`` unit normals of the non-parallel lines in each camera frame
            (any sign), every line seen in every view.
        vpv: ``(F, 3)`` unit VPV of each view in its camera frame, signs consistent over views.
        weights: ``(Q,)`` non-negative line weights (0 drops a line).
        second_view: the view ``c`` whose angle is searched (``1 <= c < F``).
        num_grid, num_starts, xtol: the global 1-DOF search (see ``global_minimize_1d``).
        softening: see :class:`RotationProblem` (0: the paper's exact cost).
        polish: finish with :func:`polish_angles` (all views jointly).
        search_views: evaluate ``E_rot`` during the search on at most this many views (evenly
            spread, always with views 0 and ``c``): the cost over hundreds of views is very
            redundant for locating ``phi_c``. ``None``: all views. Every view's angle is then
            solved at the found ``phi_c``.
        continuity: views are consecutive frames: undo half turns about ``v`` between
            neighbouring views that the data leave open (:func:`keep_continuity`).
    """
    F, Q = normals.shape[:2]
    if F < 3:
        raise OmniSfmError(f"rotation needs at least 3 views, got {F}")
    if not 1 <= second_view < F:
        raise OmniSfmError(f"second view must be in [1, {F}), got {second_view}")
    if int(np.count_nonzero(weights > 0)) < 3:
        raise OmniSfmError("rotation needs at least 3 non-parallel lines with positive weight")
    prob = RotationProblem.build(normals, vpv, weights, second_view, softening)
    search = prob
    if search_views is not None and max(search_views, 3) < F:
        idx = np.unique(np.concatenate([np.linspace(0, F - 1, max(search_views, 3)).round(),
                                        [0, second_view]]).astype(np.int64))
        search = RotationProblem.build(normals[idx], vpv[idx], weights,
                                       int(np.searchsorted(idx, second_view)), softening)
    res = global_minimize_1d(search.cost, -np.pi, np.pi, num_grid=num_grid, periodic=True,
                             num_starts=num_starts, xtol=xtol)
    cands = _candidates(prob, [res.x] + [x for x, _ in res.minima[1:]], continuity)
    _, _, phi, e = cands[0]
    polished = float("nan")
    if polish:
        phi, _, polished = polish_angles(prob, phi)
    R = prob.rotations(phi)
    R[0] = np.eye(3)
    others = [(ph, ex) for _, _, ph, ex in cands[1:]]
    return RotationResult(R, phi, second_view, float(e.sum()), e, res.num_evals, polished,
                          tuple(p for p, _ in others), tuple(float(c.sum()) for _, c in others))


def count_half_turns(phi: FloatArray) -> int:
    """Consecutive views whose angles about ``v`` differ by more than 90 deg."""
    step = np.angle(np.exp(1j * np.diff(np.asarray(phi, dtype=np.float64))))
    return int(np.count_nonzero(np.abs(step) > np.pi / 2))
