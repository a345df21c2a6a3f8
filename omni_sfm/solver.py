"""Non-linear least squares on manifolds: the Levenberg-Marquardt loop, robust losses and the
gauge, shared by the line bundle adjustment (:mod:`omni_sfm.estimate.bundle`), the resection of
one camera from known lines, and the joint adjustment of cameras, lines and points
(:mod:`omni_sfm.refine.joint`).

A problem is any object with the methods of :class:`LMProblem`: its residuals ``e`` ``(K, 2)``
at a state, their Jacobian, the blocks of the normal equations weighted by the robust loss's
IRLS weights, the damped step (:func:`damped` adds the Levenberg-Marquardt damping to
per-block systems) and the state moved along it. :func:`levenberg_marquardt` drives it; a
problem may add :class:`LandmarkDamping` (damp a few landmarks instead of the whole step) and
:class:`StepDistance` (stop on the cameras' step in their own standard deviations). The
robust loss (:class:`RobustLoss`, :func:`loss_weights`) acts on the residual norm, its scale
from the noise level estimated by :func:`robust_sigma`. :func:`gauge` picks what an
adjustment of camera poses holds fixed: the first camera's pose and one coordinate of the
farthest camera centre (7 DOF: rotation, translation, scale).
"""

from __future__ import annotations

from enum import StrEnum
from typing import Any, Protocol, TypeVar, runtime_checkable

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray

# median of the norm of a 2D isotropic Gaussian with unit std-dev per axis (Rayleigh median)
_RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))
_SIGMA_FLOOR = 1e-9


class RobustLoss(StrEnum):
    """Robust loss on the residual norm (angle, radians)."""

    LINEAR = "linear"
    HUBER = "huber"
    CAUCHY = "cauchy"


def loss_weights(s: FloatArray, loss: RobustLoss, scale: float) -> tuple[FloatArray, FloatArray]:
    """Robust cost rho(s) and its derivative (the IRLS weight) for squared norms ``s``."""
    f2 = scale * scale
    if loss == RobustLoss.LINEAR:
        return s, np.ones_like(s)
    if loss == RobustLoss.HUBER:
        inl = s <= f2
        if inl.all():  # all in the quadratic part (the same values as below)
            return s, np.ones_like(s)
        r = np.sqrt(s)
        rho = np.where(inl, s, 2.0 * scale * r - f2)
        w = np.where(inl, 1.0, scale / np.maximum(r, 1e-300))
        return rho, w
    return f2 * np.log1p(s / f2), 1.0 / (1.0 + s / f2)


def isotropic_diagonal(dg: FloatArray, parts: tuple[int, ...],
                       free: np.ndarray | None = None) -> FloatArray:
    """``(N, n)`` the diagonals ``dg`` ``(N, n)`` of ``N`` blocks, each of the consecutive
    ``parts`` (sizes summing to ``n``: a 3-vector, a 2-vector in a tangent basis) replaced by
    the mean of its ``free`` entries (``(N, n)`` bool; all where None). Damping by it does not
    depend on the axes a vector is written in (the world's orientation, a line's tangent
    basis), where damping by the diagonal itself does: along a direction the data leave free,
    which coordinate carries it decides how far a step goes."""
    ok = np.ones(dg.shape, bool) if free is None else free
    out = np.empty(dg.shape)
    a = 0
    for size in parts:
        part = slice(a, a + size)
        n = np.maximum(ok[:, part].sum(axis=1, keepdims=True), 1)
        out[:, part] = np.sum(dg[:, part] * ok[:, part], axis=1, keepdims=True) / n
        a += size
    return out


def damped(H: FloatArray, lam: float | FloatArray, free: np.ndarray,
           parts: tuple[int, ...] | None = None) -> FloatArray:
    """``H + lam diag(H)`` per block ``(N, n, n)`` (``lam`` one or ``(N,)``, one per block; a
    floor on tiny diagonals), held parameters' rows and columns (``free`` ``(N, n)`` False)
    replaced by the identity so that they stay at zero. With ``parts``, the diagonal of each
    part is its mean (:func:`isotropic_diagonal`)."""
    i = np.arange(H.shape[1])
    dg = H.diagonal(0, 1, 2)
    if parts is not None:
        dg = isotropic_diagonal(dg, parts, free)
    lam_k = np.asarray(lam, float)
    add = (lam_k[:, None] if lam_k.ndim else lam_k) * \
        np.maximum(dg, 1e-12 * max(float(dg.max(initial=0.0)), 1e-30))
    # the values of (H + add I) * (free free^T) + diag(~free) to the bit, zeros' signs too
    out = H + 0.0
    out[:, i, i] = out.diagonal(0, 1, 2) + add
    out *= free[:, :, None] & free[:, None, :]
    out += 0.0
    out[:, i, i] += ~free
    return out


def robust_sigma(angles: FloatArray) -> float:
    """Per-axis noise std-dev (radians) from residual norms, robust to outliers."""
    a = angles[np.isfinite(angles)]
    if a.size == 0:
        return _SIGMA_FLOOR
    return max(float(np.median(a)) / _RAYLEIGH_MEDIAN, _SIGMA_FLOOR)


class LMProblem(Protocol):
    """What :func:`levenberg_marquardt` asks of a problem: residuals ``e`` ``(K, 2)`` at a state
    (and what the Jacobian needs from them), the Jacobian, the blocks of the normal equations,
    the damped step, and the state moved by it."""

    def residuals(self, *state: Any) -> tuple[FloatArray, Any]: ...

    def jacobian(self, *state_and_aux: Any) -> Any: ...

    def normal_equations(self, *jacobian_e_w: Any) -> Any: ...

    def solve(self, blocks: Any, lam: float) -> tuple[Any, Any]: ...

    def retract(self, *state_and_step: Any) -> Any: ...


@runtime_checkable
class LandmarkDamping(Protocol):
    """What a problem may add so that :func:`levenberg_marquardt` damps a few landmarks instead
    of the whole step: a rejected step whose cost increase sits in a few landmarks (a point
    drifting to infinity along its rays, a line whose observations all lie in one plane) is
    tried again with those landmarks damped more and the rest as before."""

    def damp_landmarks(self, increase: FloatArray) -> bool:
        """``increase`` ``(K,)``: each residual's cost change in the rejected step. Damp the
        landmarks that account for most of it; False if the increase is not theirs."""
        ...

    def relax_landmarks(self) -> None:
        """A step was accepted: the landmarks' extra damping decays."""
        ...


@runtime_checkable
class StepDistance(Protocol):
    """What a problem may add so that :func:`levenberg_marquardt` stops on a step's size in
    the cameras' own uncertainty: the data decide when the cameras no longer move, however
    many there are and however long the walk."""

    def step_distance(self) -> float:
        """The last solved step of the cameras in their standard deviations: ``sqrt(dp^T S
        dp)``, ``S`` the cameras' information with every landmark eliminated (the system that
        the step solved). No camera, nor any combination of cameras, moved by more than this
        many of its standard deviations."""
        ...


S = TypeVar("S", bound=tuple[Any, ...])


def levenberg_marquardt(prob: LMProblem, state: S, loss: RobustLoss, scale: float,
                        max_iterations: int, tolerance: float,
                        pose_tolerance: tuple[float, float] | None = None,
                        step_tolerance: float | None = None,
                        damping: float = 1e-4, decrease_tolerance: float = 0.0
                        ) -> tuple[S, int]:
    """Levenberg-Marquardt on ``prob`` from ``state`` with robust ``loss`` at ``scale``
    (residual units), IRLS weights from the current residuals; stops after ``max_iterations``,
    when the relative decrease of the cost falls below ``tolerance`` or its decrease below
    ``decrease_tolerance`` (the cost's units: a fraction of the noise variance says that the
    parameters moved by a small fraction of their standard deviations), when a step with almost
    no damping (at most 1e-8: soft modes, such as a long walk's drift, are not held back) moves
    no camera by more than ``pose_tolerance`` (radians, units of length: that step is about
    the distance left to the minimum), when a step damped by at most 1e-7 moves the cameras
    of a :class:`StepDistance` problem by no more than ``step_tolerance`` of their standard
    deviations (damping shortens the step most along the modes the data fix least, which
    the distance weighs least), or when no damping finds a lower cost. A problem that is
    also a :class:`LandmarkDamping` gets a rejected step whose cost increase sits in a few
    landmarks tried again with those damped, the damping of the rest unchanged. ``damping``:
    the first step's (a start near the minimum can take a lower one). Returns the state and
    the iterations run."""
    def cost_of(e: FloatArray) -> tuple[float, FloatArray, FloatArray]:
        """The cost of residuals ``e``, their IRLS weights (for the step from there) and each
        residual's cost."""
        rho, w = loss_weights(np.sum(e * e, 1), loss, scale)
        return 0.5 * float(np.sum(rho)), w, rho

    local = prob if isinstance(prob, LandmarkDamping) else None
    e, u = prob.residuals(*state)
    cost, w, rho = cost_of(e)
    lam = damping
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007
        blocks: Any = prob.normal_equations(*prob.jacobian(*state, u), e, w)
        improved = False
        for _ in range(12):
            try:
                dpose, dline = prob.solve(blocks, lam)
            except np.linalg.LinAlgError:  # not positive definite: damp more
                lam *= 10.0
                continue
            new_state = prob.retract(*state, dpose, dline)
            e_new, u_new = prob.residuals(*new_state)
            new_cost, w_new, rho_new = cost_of(e_new)
            if np.isfinite(new_cost) and new_cost <= cost:
                improved = True
                break
            if not (local is not None and np.isfinite(new_cost)
                    and local.damp_landmarks(0.5 * (rho_new - rho))):
                lam *= 10.0
        if not improved:
            break
        drop = cost - new_cost
        rel = drop / max(cost, 1e-300)
        state, e, u, cost, w, rho = new_state, e_new, u_new, new_cost, w_new, rho_new
        step_lam, lam = lam, max(lam / 10.0, 1e-12)
        if local is not None:
            local.relax_landmarks()
        # the cameras no longer move (what is left is a landmark creeping along a direction
        # the data barely fix, such as a point towards infinity along its nearly parallel rays)
        # (the damping is a power of ten to round-off: 1.5 of one is between two)
        still = step_lam <= 1.5e-8 and pose_tolerance is not None and \
            float(np.abs(dpose[:, :3]).max(initial=0.0)) <= pose_tolerance[0] and \
            float(np.abs(dpose[:, 3:]).max(initial=0.0)) <= pose_tolerance[1]
        still |= step_lam <= 1.5e-7 and step_tolerance is not None and \
            isinstance(prob, StepDistance) and prob.step_distance() <= step_tolerance
        if rel < tolerance or drop < decrease_tolerance or cost <= 1e-300 or still:
            break
    return state, it


def gauge(c: FloatArray, frames: np.ndarray, scale_frames: np.ndarray | None,
           fixed: int | None = None) -> tuple[int, int, int]:
    """``(fixed_frame, scale_frame, scale_axis)``: the gauge held during the adjustment.

    ``c`` ``(F, 3)`` initial camera centres, ``frames`` ``(F,)`` bool the estimated frames. The
    first estimated frame's pose (or that of ``fixed``) is held; the scale by the coordinate
    (axis 0-2) of the largest magnitude of the offset from it of the camera centre farthest
    from it (among ``scale_frames`` ``(F,)`` bool, if given).

    Raises:
        OmniSfmError: all candidate centres coincide with the fixed one (no scale).
    """
    if fixed is None:
        fixed = int(np.flatnonzero(frames)[0])
    dist = np.linalg.norm(np.where(frames[:, None], c - c[fixed], 0.0), axis=1)
    if scale_frames is not None:
        dist = np.where(np.asarray(scale_frames, bool), dist, 0.0)
    scale_frame = int(np.argmax(dist))
    scale_axis = int(np.argmax(np.abs(c[scale_frame] - c[fixed])))
    if dist[scale_frame] <= 0:
        raise OmniSfmError("bundle adjustment: all initial camera centres coincide; the scale "
                           "is undefined")
    return fixed, scale_frame, scale_axis
