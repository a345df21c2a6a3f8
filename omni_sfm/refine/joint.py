"""Joint adjustment of cameras, 3D lines and 3D points: the maximum-likelihood estimate from
both kinds of evidence (docs/colmap.md, "Joint adjustment").

Residuals, each a 2-vector in radians for small errors:

- a line observation exactly as the line bundle adjustment weighs it
  (:class:`omni_sfm.estimate.bundle.LineProblem`: the predicted interpretation-plane normal
  against the observed one, in the observation's own uncertainty directions);
- a point observation: the observed unit ray ``r`` (camera frame) against the predicted bearing
  ``b = R^T (X - c) / |X - c|`` of the point ``X`` from the camera (world_from_cam ``R``,
  centre ``c``): ``e = B_r b`` with ``B_r`` (2x3) an orthonormal basis of the plane
  perpendicular to ``r``, so ``|e|`` is the sine of the angle between them. Angular residuals
  through the exact camera model: any central camera, omnidirectional ones included.

Each kind is divided by its own per-axis noise level, estimated robustly from its residuals
(or given), so the cost is the sum of squared normalised residuals, the maximum-likelihood
cost for Gaussian noise on both; and each landmark's observations weigh as the independent
errors they hold (:func:`_correlation_weights`: errors that drift slowly along a track are
not as many measurements as the track has frames). Robust rounds (Huber at ``loss_scale``
noise levels) find the outliers: line tracks whose RMS residual is far above the noise, point
observations likewise (a point left with fewer than two observations goes); then plain least
squares on the inliers.

Parameters: 6 per camera (``R <- R exp([w]x)``, ``c <- c + dc``), 4 per line (as the line
adjustment), 3 per point. Gauge: the first camera's pose and one coordinate of the centre
farthest from it are held (:func:`omni_sfm.solver.gauge`), so the input's world and
scale are kept. Solver: :func:`omni_sfm.solver.levenberg_marquardt`; each step
eliminates the lines and points (4x4 and 3x3 blocks) and solves the reduced ``6F x 6F``
camera system: formed and factored up to ``iterative_above`` frames (dense Cholesky up to
4,000 unknowns, sparse LU above), by conjugate gradients with a two-level preconditioner
above (:class:`_IterativeSystem`: a long video's points, in view for hundreds of frames, make
the formed system nearly dense).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.bundle import LineProblem, observation_distance_ratio
from omni_sfm.geometry import FloatArray, cross3, normalize, orthonormal_completion
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.solver import RobustLoss, damped, gauge, levenberg_marquardt, robust_sigma

_DENSE_MAX = 4000
_CHUNK = 32768
"""Observations per chunk where per-observation blocks are formed and summed."""
_PENDING_MAX = 20_000_000
"""Triplets of the cameras' sparse system waiting to be summed, at most (about 320 MB)."""


@dataclass(frozen=True)
class PointObservations:
    """Point evidence: observation ``k`` sees point ``point[k]`` in frame ``frame[k]`` along
    the unit ray ``ray[k]`` (camera frame, the camera model's pixel -> ray)."""

    frame: np.ndarray
    point: np.ndarray
    ray: FloatArray
    num_points: int
    pixel_jacobian: FloatArray | None = None
    """``(K, 2, 2)`` the camera model's local map from angles (radians along the two
    directions of :meth:`tangent_basis`) to pixels at each observation, or None (every
    observation alike). With it, the residuals weigh as pixel errors do: a keypoint's error is
    in pixels, and an omnidirectional image spends very different numbers of pixels on a
    degree across it and along different directions."""

    def __post_init__(self) -> None:
        K = len(self.frame)
        if len(self.point) != K or self.ray.shape != (K, 3):
            raise OmniSfmError(f"point observations: {K} frames, {len(self.point)} points and "
                               f"rays of shape {self.ray.shape} do not match")
        J = self.pixel_jacobian
        if J is not None and (J.shape != (K, 2, 2) or not (
                np.abs(np.linalg.det(J)) > 0).all()):
            raise OmniSfmError("point observations: the pixel Jacobians must be (K, 2, 2) and "
                               "invertible")
        if K and (self.point.min() < 0 or self.point.max() >= self.num_points):
            raise OmniSfmError("point observations: a point index is out of range")
        if not np.isfinite(self.ray).all():
            raise OmniSfmError("point observations: a ray is not finite")

    def subset(self, keep: np.ndarray) -> PointObservations:
        """The observations ``keep`` (bool or indices), the points numbered as before."""
        return PointObservations(self.frame[keep], self.point[keep], self.ray[keep],
                                 self.num_points,
                                 None if self.pixel_jacobian is None else
                                 self.pixel_jacobian[keep])

    def tangent_basis(self) -> tuple[FloatArray, FloatArray]:
        """``(K, 3)`` twice: the directions perpendicular to each ray that the residual (and
        :attr:`pixel_jacobian`) is measured along."""
        return orthonormal_completion(self.ray)

    def residual_basis(self) -> FloatArray:
        """``(K, 2, 3)``: rows ``b`` with residual ``e = b . bearing``: the tangent directions,
        mapped by :attr:`pixel_jacobian` to pixels and divided by the median observation's
        pixels per radian (so that residuals stay in radians of a typical observation and
        the noise level an angle)."""
        e1, e2 = self.tangent_basis()
        B = np.stack([e1, e2], axis=1)
        J = self.pixel_jacobian
        if J is None or len(self.frame) == 0:
            return B
        ref = float(np.median(np.sqrt(np.abs(np.linalg.det(J)))))
        return np.asarray(J @ B / ref)


@dataclass(frozen=True)
class JointOptions:
    line_noise_deg: float | None = None
    """Per-axis noise of the line observations (deg); None: estimated from their residuals."""
    point_noise_deg: float | None = None
    """The same for the point observations."""
    loss_scale: float = 3.0
    """Huber scale of the robust rounds, in noise levels."""
    outlier_threshold: float = 3.0
    """A line track (RMS) or a point observation is an outlier above this many times the
    expected RMS of its noise (sqrt(2) sigma)."""
    robust_rounds: int = 3
    """Robust solve / noise estimate / rejection rounds."""
    robust_iterations: int = 30
    max_iterations: int = 100
    """Levenberg-Marquardt iterations of the final least-squares solve."""
    tolerance: float = 1e-10
    """Relative decrease of the cost below which a solve stops."""
    correlated: tuple[str, ...] = ("lines", "points")
    """The kinds whose errors may be correlated along a landmark's frames (a line that is not
    quite straight, an edge fitted off by shading that changes slowly as the camera moves): each
    landmark's observations weigh as many independent ones as their residuals' lag-1
    correlation ``rho`` allows, ``(1 - rho) / (1 + rho)`` each (:func:`_correlation_weights`)."""
    iterative_above: int = 50
    """More frames than this: the cameras' reduced system is solved by preconditioned
    conjugate gradients without forming it (:class:`_IterativeSystem`; the same step to
    :attr:`cg_tolerance`). Formed, its cost grows with the square of how long points stay in
    view, and a point can stay in view of an omnidirectional camera for hundreds of frames:
    on a 1,000-frame walk one iteration took 17 s, 5 of them factoring a nearly dense system.
    Even on short sequences the iterations are cheaper, as their preconditioner serves
    several steps (:attr:`preconditioner_reuse`): the 120-frame room's adjustment took 9.3 s
    instead of 13.0 s formed every step, the same result (docs/colmap.md)."""
    window_frames: int = 100
    """The preconditioner's windows: the reduced system's diagonal blocks over this many
    consecutive frames, each formed and factored exactly."""
    preconditioner_reuse: int = 8
    """The conjugate gradients' preconditioner is built (formed and factored) for one step
    and serves up to this many steps (1: a new one every step). The later steps' systems
    differ by the damping and by how far the cameras moved, which costs a few more conjugate
    gradient iterations and leaves the step as it is: on the 1,000-frame office walk (KLT)
    the solves took 96 s instead of 152 s, the same result."""
    cg_tolerance: float = 1e-8
    """Conjugate gradients stop when the residual is below this fraction of the right-hand
    side (the final least-squares round)."""
    pose_tolerance: float = 1e-6
    """A solve ends when an undamped step turns no camera by more than this (radians) and moves
    none by more than this fraction of the camera centres' extent: on the 1,000-frame walk the
    errors no longer changed after steps of 1e-6 (5.7e-5 deg), while COLMAP's points that the
    data barely fix kept the cost falling by bits for 80 more iterations. 0: off."""
    robust_pose_tolerance: float = 2e-5
    """:attr:`pose_tolerance` of the robust rounds (2e-5 rad: 0.001 deg), which judge the
    observations and need not polish: on the 1,000-frame office walk the first robust round
    ran 27 iterations, 19 of them steps below 0.002 deg that left every error as it was
    (rotation 0.0735 against 0.0739 deg mean after 8). 0: off."""
    step_tolerance: float = 0.2
    """A solve also ends when a step (damped by at most 1e-7) moves the cameras by at most this
    many of their standard deviations (:class:`omni_sfm.solver.StepDistance`:
    ``sqrt(dp^T S dp)`` with ``S`` the cameras' information, every landmark eliminated; no
    camera, nor any combination of cameras, moved by more than that share of its
    uncertainty). The rule of :attr:`pose_tolerance` in the data's own units: a long walk's
    cameras are fixed no worse than a short one's, but the largest of a thousand small steps
    is larger than the largest of a hundred, and its soft modes converge more slowly in
    radians. On the 1,000-frame office walk (SIFT) the final round's 3 iterations after its
    4th step (0.17 deviations), with 3 more steps rejected, changed no error by more than
    3e-5 deg; the rule stops it there (docs/colmap.md). 0: off."""
    robust_step_tolerance: float = 0.5
    """:attr:`step_tolerance` of the robust rounds. 0: off."""
    near_camera_ratio: float = 0.05
    """A line observation whose camera is closer to the line than this fraction of the
    track's median camera distance is left out after the first round (as outliers are): the
    plane through a camera that nearly lies on the line turns fast with either, so its
    residual is far from linear: on the 1,000-frame office walk one such observation (0.01-0.04
    of its line's median distance as the cameras moved) held the final round to steps of
    0.3-0.6 standard deviations for 2 more iterations (docs/colmap.md). 0: off."""
    warm_damping: float = 1e-6
    """The damping that each solve after the first starts with (the first: 1e-4). Each starts
    at the minimum of the one before, which only its new weights and inliers move, so a step
    close to Gauss-Newton's is taken at once; Levenberg-Marquardt raises the damping if it
    is not. On the office walk's triangulated models (SIFT) the adjustment ran 14 iterations
    instead of 18 at 300 frames and 17 instead of 19 at 1,000, with the same result, and the
    conjugate gradients' preconditioner, built at the solve's first step, serves the
    lower-damped steps after it better (22 iterations a final step at 1,000 frames instead of
    28)."""
    robust_cg_tolerance: float = 1e-3
    """The same in the robust rounds, which only need to come near the minimum to judge the
    observations (on the 1,000-frame walk: 4.3 instead of 5.9 s a step, the same result)."""

    def __post_init__(self) -> None:
        for name in ("pose_tolerance", "robust_pose_tolerance", "step_tolerance",
                     "robust_step_tolerance", "near_camera_ratio"):
            if not getattr(self, name) >= 0.0:
                raise OmniSfmError(f"joint adjustment: {name} must be >= 0, not "
                                   f"{getattr(self, name)}")
        if not 0.0 < self.warm_damping <= 1.0:
            raise OmniSfmError("joint adjustment: warm_damping must be in (0, 1], not "
                               f"{self.warm_damping}")
        if self.preconditioner_reuse < 1:
            raise OmniSfmError("joint adjustment: preconditioner_reuse must be >= 1, not "
                               f"{self.preconditioner_reuse}")
        if not 10 <= self.window_frames <= _DENSE_MAX // 6:
            raise OmniSfmError(f"joint adjustment: window_frames must be in [10, "
                               f"{_DENSE_MAX // 6}], not {self.window_frames}")
        for name in ("cg_tolerance", "robust_cg_tolerance"):
            if not 0.0 < getattr(self, name) < 1.0:
                raise OmniSfmError(f"joint adjustment: {name} must be in (0, 1), not "
                                   f"{getattr(self, name)}")


@dataclass(frozen=True)
class JointResult:
    """Poses ``(F, ...)`` (NaN outside ``frames``), lines ``(M, 3)`` and points ``(P, 3)``
    (NaN where not used), the inliers and the noise level of each kind."""

    rotations: FloatArray
    positions: FloatArray
    frames: np.ndarray
    line_directions: FloatArray
    line_points: FloatArray
    lines_used: np.ndarray
    points: FloatArray
    points_used: np.ndarray
    point_inliers: np.ndarray
    """``(K,)`` bool over the point observations."""
    line_sigma_deg: float
    point_sigma_deg: float
    line_rms_deg: float
    point_rms_deg: float
    iterations: int
    line_share: FloatArray
    """``(F, 2)``: the lines' share of the information that fixes each frame's rotation
    (column 0) and centre (column 1), the points' the rest (:func:`_frame_information`; NaN
    where the frame is held or not adjusted)."""

    def evidence(self, lines: LineTracks, points: PointObservations) -> dict[str, np.ndarray]:
        """Per frame ``(F,)``: the line and the point observations that took part."""
        F = len(self.frames)
        lo = self.lines_used[lines.obs_track] & self.frames[lines.obs_frame]
        return {"lines": np.bincount(lines.obs_frame[lo], minlength=F),
                "points": np.bincount(points.frame[self.point_inliers], minlength=F)}


class _JointProblem:
    """Lines (:class:`LineProblem`) and points together; state ``(R, c, d, p, X)``."""

    def __init__(self, lines: LineProblem, points: PointObservations, active: np.ndarray,
                 sigma_line: float, sigma_point: float, line_weight: FloatArray | None = None,
                 point_weight: FloatArray | None = None,
                 options: JointOptions = JointOptions()) -> None:
        self.lines, self.active, self.options = lines, active, options
        self.cg_iterations: list[int] = []
        self.F, self.M, self.P = lines.F, lines.M, points.num_points
        # the observations used, each point's together (by point, then frame): the iterative
        # solver's products need them in that order (:class:`_ProductPlan`)
        idx = np.flatnonzero(active)
        self.obs_index = idx[np.lexsort((points.frame[idx], points.point[idx]))]
        self.f, self.j = points.frame[self.obs_index], points.point[self.obs_index]
        self.Bp = points.residual_basis()[self.obs_index]  # (Kp, 2, 3)
        self.sigma_line, self.sigma_point = sigma_line, sigma_point
        self.Kl = len(lines.f)
        # per observation: 1 / (noise level), times the square root of its landmark's weight
        self.line_scale = np.full(self.Kl, 1.0 / sigma_line)
        if line_weight is not None:
            self.line_scale *= np.sqrt(line_weight[lines.t])
        self.point_scale = np.full(len(self.f), 1.0 / sigma_point)
        if point_weight is not None:
            self.point_scale *= np.sqrt(point_weight[self.j])
        self.point_free = np.zeros(self.P, bool)
        self.point_free[self.j] = True
        # each landmark's damping beyond the step's (Levenberg-Marquardt's lam): raised for the
        # few landmarks a rejected step went wrong in (:meth:`damp_landmarks`)
        self.extra_damping = (np.zeros(self.M), np.zeros(self.P))
        self.plans: dict[int, _ProductPlan] = {}  # the iterative solver's, per kind
        self.preconditioner: _Preconditioner | None = None  # the iterative solver's, reused
        self.cg_tolerance = options.cg_tolerance
        self.last_distance = np.inf  # the last step in the cameras' standard deviations

    def residuals(self, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
                  X: FloatArray) -> tuple[FloatArray, tuple[FloatArray, FloatArray]]:
        el, u = self.lines.residuals(R, c, d, p)
        v = _offsets(R, c, X, self.f, self.j)
        b = v / np.linalg.norm(v, axis=1, keepdims=True)
        ep = np.einsum("kai,ki->ka", self.Bp, b)
        return np.concatenate([el * self.line_scale[:, None],
                               ep * self.point_scale[:, None]]), (u, v)

    def angles(self, e: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The angular size (radians) of each line and point observation's residual, from
        :meth:`residuals`' ``e``."""
        a = np.linalg.norm(e, axis=1)
        return a[:self.Kl] / self.line_scale, a[self.Kl:] / self.point_scale

    def jacobian(self, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
                 X: FloatArray, aux: tuple[FloatArray, FloatArray]) -> tuple[FloatArray, ...]:
        u, v = aux
        self.at = (R, c)  # where the step is taken (the iterative solver's coarse space)
        Jpl, Jl = self.lines.jacobian(R, c, d, p, u)
        K = len(v)
        Jpp, Jx = np.empty((K, 2, 6)), np.empty((K, 2, 3))
        for a in range(0, K, _CHUNK):  # in chunks: the temporaries stay small
            b = min(a + _CHUNK, K)
            vk, Bk, fk = v[a:b], self.Bp[a:b], self.f[a:b]
            rho = np.linalg.norm(vk, axis=1)
            u_ = vk / rho[:, None]
            # d e / d v = B (I - b b^T) / |v|; v = R^T (X - c): dv/dw = [v]x, dv/dc = -R^T
            A = (Bk - np.einsum("kai,ki->ka", Bk, u_)[:, :, None] * u_[:, None, :]) / \
                rho[:, None, None]
            np.matmul(A, np.swapaxes(R[fk], 1, 2), out=Jx[a:b])  # A R^T
            cross3(A, vk[:, None, :], out=Jpp[a:b, :, :3])  # A [v]x: each row a -> a x v
            np.negative(Jx[a:b], out=Jpp[a:b, :, 3:])
            sq = self.point_scale[a:b, None, None]
            Jpp[a:b] *= self.lines.pose_free[fk][:, None, :] * sq
            Jx[a:b] *= sq
        sl = self.line_scale[:, None, None]
        return Jpl * sl, Jl * sl, Jpp, Jx

    def normal_equations(self, Jpl: FloatArray, Jl: FloatArray, Jpp: FloatArray,
                         Jx: FloatArray, e: FloatArray, w: FloatArray) -> tuple[Any, ...]:
        Kl = self.Kl
        wl, wp, el, ep = w[:Kl], w[Kl:], e[:Kl], e[Kl:]
        fl, tl, fp, jp = self.lines.f, self.lines.t, self.f, self.j
        wJpl, wJl = Jpl * wl[:, None, None], Jl * wl[:, None, None]
        Hpp = _sum_by(fl, np.swapaxes(wJpl, 1, 2) @ Jpl, self.F)
        gp = _sum_by(fl, np.einsum("kai,ka->ki", wJpl, el), self.F)
        Hll = _sum_by(tl, np.swapaxes(wJl, 1, 2) @ Jl, self.M)
        gl = _sum_by(tl, np.einsum("kai,ka->ki", wJl, el), self.M)
        # the points' blocks in chunks of observations (the products' temporaries stay small:
        # 2.5 times faster on 1.5 million observations)
        Kp = len(fp)
        Hxx, gx = np.zeros((self.P, 3, 3)), np.zeros((self.P, 3))
        Hpx = np.empty((Kp, 6, 3))
        for a in range(0, Kp, _CHUNK):
            b = min(a + _CHUNK, Kp)
            wJpp, wJx = Jpp[a:b] * wp[a:b, None, None], Jx[a:b] * wp[a:b, None, None]
            _add_by(Hpp, fp[a:b], np.swapaxes(wJpp, 1, 2) @ Jpp[a:b])
            _add_by(gp, fp[a:b], np.einsum("kai,ka->ki", wJpp, ep[a:b]))
            np.matmul(np.swapaxes(wJpp, 1, 2), Jx[a:b], out=Hpx[a:b])
            _add_by(Hxx, jp[a:b], np.swapaxes(wJx, 1, 2) @ Jx[a:b])
            _add_by(gx, jp[a:b], np.einsum("kai,ka->ki", wJx, ep[a:b]))
        return (Hpp, gp, (Hll, np.swapaxes(wJpl, 1, 2) @ Jl, gl, fl, tl, self.lines.line_free),
                (Hxx, Hpx, gx, fp, jp, np.repeat(self.point_free[:, None], 3, axis=1)))

    def solve(self, blocks: tuple[Any, ...], lam: float
              ) -> tuple[FloatArray, tuple[FloatArray, FloatArray]]:
        """Damped step ``(H + lam diag(H)) dx = -g``, the lines and points eliminated."""
        Hpp, gp, *marks = blocks
        F, pf = self.F, self.lines.pose_free
        # the system over the frames with a free parameter only (unposed frames and the
        # gauge's frame have none: their blocks of ``H_pl`` are zero)
        moving: np.ndarray = np.asarray(pf.any(axis=1))
        compact = np.cumsum(moving) - 1
        o = self.options
        Hd, rhs = damped(Hpp[moving], lam, pf[moving]), -gp[moving]
        pre = self.preconditioner
        if pre is not None and pre.uses >= o.preconditioner_reuse:
            pre = None
        S: _ReducedSystem | _IterativeSystem = \
            _IterativeSystem(Hd, rhs, self.at[0][moving], self.at[1][moving], pf[moving],
                             o.window_frames, self.cg_tolerance, pre) \
            if moving.sum() > o.iterative_above else _ReducedSystem(Hd, rhs)
        reduced = []
        for kind, ((H, Hcross, g, f, t, free), extra) in enumerate(
                zip(marks, self.extra_damping, strict=True)):
            Linv = np.linalg.inv(np.linalg.cholesky(damped(H, np.maximum(lam, extra), free)))
            on = np.flatnonzero(moving[f])
            G = np.empty((len(on), 6, H.shape[1]))  # H_pl L^-T, in chunks
            for a in range(0, len(on), _CHUNK):
                k = on[a:a + _CHUNK]
                np.matmul(Hcross[k], np.swapaxes(Linv[t[k]], 1, 2), out=G[a:a + _CHUNK])
            gt = np.einsum("nij,nj->ni", Linv, g)  # L^-1 g
            if isinstance(S, _IterativeSystem):
                if kind not in self.plans:
                    self.plans[kind] = _ProductPlan(compact[f[on]], t[on], G.shape[2], len(g),
                                                    int(moving.sum()))
                S.subtract(G, compact[f[on]], t[on], gt, self.plans[kind])
            else:
                S.subtract(G, compact[f[on]], t[on], gt)
            reduced.append((Linv, Hcross, g, f, t, free))
        dp = np.zeros((F, 6))
        x = S.solve()
        dp[moving] = x.reshape(-1, 6)
        # S x = rhs: the step's squared length in the metric of the cameras' information
        self.last_distance = float(np.sqrt(max(float(x @ S.rhs), 0.0)))
        dp *= pf
        if isinstance(S, _IterativeSystem):
            self.cg_iterations.append(S.iterations)
            self.preconditioner = S.preconditioner
            assert self.preconditioner is not None
            self.preconditioner.uses += 1
        steps = []
        for Linv, Hcross, g, f, t, free in reduced:
            r = -g
            for a in range(0, len(f), _CHUNK):
                b = min(a + _CHUNK, len(f))
                _add_by(r, t[a:b], -np.einsum("kji,kj->ki", Hcross[a:b], dp[f[a:b]]))
            steps.append(np.einsum("nji,nj->ni", Linv, np.einsum("nij,nj->ni", Linv, r)) * free)
        return dp, (steps[0], steps[1])

    def step_distance(self) -> float:
        """The last step (:meth:`solve`) of the cameras in their standard deviations
        (:class:`omni_sfm.solver.StepDistance`; the damped system it solved, so
        that with the little damping the stop asks for, the undamped one)."""
        return self.last_distance

    def damp_landmarks(self, increase: FloatArray) -> bool:
        """A rejected step's cost increase per residual ``(K,)``: if at most
        ``max(10, 0.5 %)`` of the landmarks hold half of it (a point drifting to infinity along
        its rays, one seen from both sides of the path, a line whose observations share one
        plane: their steps are far outside the linear model), their damping is raised to at
        least their Hessian block's diagonal, tenfold each time (:class:`LandmarkDamping`)."""
        per = np.concatenate([np.bincount(self.lines.t, weights=increase[:self.Kl],
                                          minlength=self.M),
                              np.bincount(self.j, weights=increase[self.Kl:], minlength=self.P)])
        total = float(per[per > 0].sum())
        if not total > 0.0:
            return False
        order = np.argsort(-per)
        n = int(np.searchsorted(np.cumsum(per[order]), 0.5 * total)) + 1
        if n > max(10, 0.005 * len(per)):
            return False
        extra = np.concatenate(self.extra_damping)
        extra[order[:n]] = np.maximum(10.0 * extra[order[:n]], 1.0)
        self.extra_damping = (extra[:self.M], extra[self.M:])
        return True

    def relax_landmarks(self) -> None:
        """After an accepted step the extra damping decays (by 3)."""
        self.extra_damping = (self.extra_damping[0] / 3.0, self.extra_damping[1] / 3.0)

    def retract(self, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
                X: FloatArray, dpose: FloatArray, dmarks: tuple[FloatArray, FloatArray]
                ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        R2, c2, d2, p2 = self.lines.retract(R, c, d, p, dpose, dmarks[0])
        return R2, c2, d2, p2, X + dmarks[1]


def _sum_by(index: np.ndarray, values: FloatArray, n: int) -> FloatArray:
    """``(n, ...)``: the rows of ``values`` ``(K, ...)`` summed by ``index`` ``(K,)`` (a sparse
    product: much faster than ``np.add.at``)."""
    K = len(index)
    if K == 0:
        return np.zeros((n, *values.shape[1:]))
    flat = values.reshape(K, -1)
    A = sp.csr_matrix((np.ones(K), (index, np.arange(K))), shape=(n, K))
    return np.asarray(A @ flat).reshape((n, *values.shape[1:]))


def _add_by(out: FloatArray, index: np.ndarray, values: FloatArray) -> None:
    """``out[index[k]] += values[k]`` for every ``k`` (repeated indices summed), touching only
    the rows between the smallest and the largest index: a chunk of observations costs its
    own length and span, not the length of ``out``. Summed into all of ``out`` chunk by chunk,
    the points' blocks cost the number of chunks times the number of points, which grows with
    the square of the sequence's length (on the 1,000-frame office walk the normal equations
    took 0.51 instead of 0.62 ms a frame, side by side)."""
    if len(index) == 0:
        return
    lo, hi = int(index.min()), int(index.max()) + 1
    out[lo:hi] += _sum_by(index - lo, values, hi - lo)


class _ReducedSystem:
    """The cameras' ``6F x 6F`` system ``S dp = rhs`` left after eliminating landmarks:
    ``S = H_pp - sum_j G_j G_j^T`` with ``G_j`` ``(6F, n)`` the landmark's blocks ``H_pj
    L_j^-T``. Each block of landmarks is handled as a dense window over the frames its
    observations touch (matrix products, not element-wise sparse ones); the sum is kept dense
    up to ``_DENSE_MAX`` unknowns; above, as a sparse matrix into which the chunks' triplets are
    summed whenever more than ``_PENDING_MAX`` of them wait (memory bounded by the system's
    own nonzeros, not by the sum of every chunk's window: a 1,000-frame walk whose lines are
    seen for hundreds of frames needed more than 24 GB when every triplet was kept)."""

    def __init__(self, Hpp: FloatArray, rhs: FloatArray) -> None:
        self.F = len(Hpp)
        n6 = 6 * self.F
        self.rhs = rhs.ravel().copy()
        idx = np.arange(n6).reshape(self.F, 6)
        if n6 <= _DENSE_MAX:
            self.dense: FloatArray | None = np.zeros((n6, n6))
            for k in range(self.F):
                self.dense[6 * k:6 * k + 6, 6 * k:6 * k + 6] = Hpp[k]
            self.parts: list[tuple[np.ndarray, np.ndarray, FloatArray]] = []
        else:
            self.dense = None
            self.parts = [(np.repeat(idx, 6, axis=1).ravel().astype(np.int32),
                           np.tile(idx, (1, 6)).ravel().astype(np.int32), Hpp.ravel())]
            self.pending = len(self.parts[0][0])
            self.summed: sp.csr_matrix | None = None

    def subtract(self, G: FloatArray, f: np.ndarray, t: np.ndarray, gt: FloatArray,
                 chunk: int = 20000) -> None:
        """``S -= sum_j G_j G_j^T`` and ``rhs += sum_j G_j gt_j`` for the observations ``k``
        (frame ``f[k]``, landmark ``t[k]``, block ``G[k]`` ``(6, n)``)."""
        if len(t) == 0:
            return
        n = G.shape[2]
        for sel in _landmark_chunks(f, t, chunk):
            fr, inv_f = np.unique(f[sel], return_inverse=True)
            lm, inv_t = np.unique(t[sel], return_inverse=True)
            blocks = np.zeros((len(fr), 6, len(lm), n))
            pf, pt, Gp = _pairs(inv_f, inv_t, len(lm), G[sel])
            blocks[pf, :, pt, :] = Gp
            Gc = blocks.reshape(6 * len(fr), n * len(lm))
            rows = (6 * fr[:, None] + np.arange(6)).ravel()
            self.rhs[rows] += Gc @ gt[lm].ravel()
            Sc = Gc @ Gc.T
            if self.dense is not None:
                self.dense[np.ix_(rows, rows)] -= Sc
            else:
                rows32 = rows.astype(np.int32)
                self.parts.append((np.repeat(rows32, len(rows)), np.tile(rows32, len(rows)),
                                   -Sc.ravel()))
                self.pending += Sc.size
                if self.pending > _PENDING_MAX:
                    self._fold()

    def _fold(self) -> None:
        """The waiting triplets summed into :attr:`summed`."""
        if not self.parts:
            return
        n6 = 6 * self.F
        r, c, v = (np.concatenate(x) for x in zip(*self.parts, strict=True))
        self.parts, self.pending = [], 0
        add = sp.csr_matrix((v, (r, c)), shape=(n6, n6))
        self.summed = add if self.summed is None else self.summed + add

    def solve(self) -> FloatArray:
        if self.dense is not None:
            return np.asarray(scipy.linalg.cho_solve(
                scipy.linalg.cho_factor(self.dense, check_finite=False), self.rhs,
                check_finite=False))
        self._fold()
        assert self.summed is not None
        S = self.summed.tocsc()
        lu = spla.splu(S, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True})
        if np.any(lu.U.diagonal() <= 0):
            raise np.linalg.LinAlgError("reduced system not positive definite")
        return np.asarray(lu.solve(self.rhs))


class _IterativeSystem:
    """The cameras' reduced system of :class:`_ReducedSystem` solved by preconditioned
    conjugate gradients without forming it: ``S x = H_pp x - sum_j G_j (G_j^T x)`` costs one
    pass over the observations, however long each landmark stays in view. Preconditioner:
    ``S``'s diagonal blocks over windows of ``window`` consecutive frames, each formed (only
    the pairs of observations within the window) and factored exactly: what is left to the
    iterations is the coupling between windows, a few modes each (on the 1,000-frame office
    walk, windows of 100 frames: 30-40 iterations to 1e-8)."""

    def __init__(self, Hpp: FloatArray, rhs: FloatArray, R: FloatArray, c: FloatArray,
                 free: np.ndarray, window: int, tolerance: float,
                 reuse: _Preconditioner | None = None) -> None:
        """The system ``Hpp`` ``(F, 6, 6)`` (damped), ``rhs`` ``(F, 6)`` before the
        landmarks are subtracted, at the poses ``R``, ``c`` with ``free`` ``(F, 6)``
        parameters; ``reuse``: an earlier step's preconditioner instead of a new one."""
        self.F = len(Hpp)
        self.Hpp, self.rhs, self.tolerance = Hpp, rhs.ravel().copy(), tolerance
        self.kinds: list[sp.csr_matrix] = []
        self.iterations = 0
        self.preconditioner = reuse
        if reuse is not None:
            return
        self.bounds = np.linspace(0, self.F, max(1, round(self.F / window)) + 1).astype(int)
        self.window_of = np.searchsorted(self.bounds, np.arange(self.F), side="right") - 1
        self.blocks = [_ReducedSystem(Hpp[a:b], np.zeros((b - a, 6)))
                       for a, b in zip(self.bounds[:-1], self.bounds[1:], strict=True)]
        # the coarse space: each window's cameras moved together (:func:`_window_motions`)
        motions = _window_motions(R, c, free, self.window_of)
        nw, m = len(self.blocks), motions.shape[2]
        self.motions = motions  # (F, 6, m)
        C = np.zeros((nw, nw, m, m))
        np.add.at(C, (self.window_of, self.window_of),
                  np.swapaxes(motions, 1, 2) @ Hpp @ motions)
        self.coarse = C

    def subtract(self, G: FloatArray, f: np.ndarray, t: np.ndarray, gt: FloatArray,
                 plan: _ProductPlan) -> None:
        """As :meth:`_ReducedSystem.subtract`, kept for the products (``plan``: the sparse
        structure of these observations, built once: it does not change from step to step).
        No observation (a kind of landmark that is not used): nothing to subtract."""
        if len(t) == 0:
            return
        self.rhs += _sum_by(f, np.einsum("kai,ki->ka", G, gt[t]), self.F).ravel()
        obs, per_landmark = plan.matrices(G)
        self.kinds.append(per_landmark)
        if self.preconditioner is not None:
            return
        w = self.window_of[f]
        for i, block in enumerate(self.blocks):
            s = w == i
            block.subtract(G[s], f[s] - self.bounds[i], t[s], np.zeros_like(gt))
        # the coarse system: A_jw = sum of G_k^T Phi_k over landmark j's observations in
        # window w; C_ww' -= A_jw^T A_jw' for every landmark and pair of its windows
        nw = len(self.blocks)
        pair, inv = np.unique(t * nw + w, return_inverse=True)
        m = self.motions.shape[2]
        GtPhi = plan.per_observation(obs @ self.motions.reshape(6 * self.F, m))  # (K, n, m)
        A = _sum_by(inv, GtPhi, len(pair))  # (pairs, n, m)
        lm, win = pair // nw, pair % nw
        for lag in range(int(np.bincount(lm).max())):
            a = np.flatnonzero(lm[lag:] == lm[:len(lm) - lag])
            AtA = np.swapaxes(A[a], 1, 2) @ A[a + lag]
            np.add.at(self.coarse, (win[a], win[a + lag]), -AtA)
            if lag:
                np.add.at(self.coarse, (win[a + lag], win[a]), -np.swapaxes(AtA, 1, 2))

    def _product(self, x: FloatArray) -> FloatArray:
        y = np.einsum("fij,fj->fi", self.Hpp, x.reshape(self.F, 6)).ravel()
        for per_landmark in self.kinds:
            y -= per_landmark.T @ (per_landmark @ x)
        return np.asarray(y)

    def solve(self) -> FloatArray:
        if self.preconditioner is None:
            self.preconditioner = _Preconditioner(self)
        precondition = self.preconditioner.apply
        b = self.rhs
        x = precondition(b)
        r = b - self._product(x)
        z = precondition(r)
        d, rz = z.copy(), float(r @ z)
        limit = self.tolerance * float(np.linalg.norm(b))
        for it in range(1, 6 * self.F + 1):
            self.iterations = it
            if float(np.linalg.norm(r)) <= limit or rz <= 0.0:
                break
            Ad = self._product(d)
            alpha = rz / float(d @ Ad)
            x += alpha * d
            r -= alpha * Ad
            z = precondition(r)
            rz, rz_old = float(r @ z), rz
            d = z + (rz / rz_old) * d
        return x


class _Preconditioner:
    """:class:`_IterativeSystem`'s preconditioner, factored: the windows' diagonal blocks and
    the coarse system of their joint motions (additive two-level). Built from one step's
    system, it stays a good preconditioner for the next few steps (their systems differ by
    the damping and by how far the cameras moved), so :class:`_JointProblem` reuses it
    (:attr:`JointOptions.preconditioner_reuse`): the step is the same, to the tolerance of
    the conjugate gradients; only their count may change."""

    def __init__(self, S: _IterativeSystem) -> None:
        self.factors = []
        for block in S.blocks:
            assert block.dense is not None  # a window's system is small
            self.factors.append(scipy.linalg.cho_factor(block.dense, check_finite=False))
        self.spans = [(6 * a, 6 * b) for a, b in zip(S.bounds[:-1], S.bounds[1:], strict=True)]
        nw, m = S.coarse.shape[0], S.coarse.shape[2]
        C = S.coarse.transpose(0, 2, 1, 3).reshape(nw * m, nw * m)
        self.coarse = scipy.linalg.cho_factor(C + 1e-12 * np.trace(C) / len(C) * np.eye(len(C)),
                                              check_finite=False)
        self.motions, self.window_of, self.nw, self.m = S.motions, S.window_of, nw, m
        self.uses = 0

    def apply(self, r: FloatArray) -> FloatArray:
        z = np.empty_like(r)
        for (a, b), fac in zip(self.spans, self.factors, strict=True):
            z[a:b] = scipy.linalg.cho_solve(fac, r[a:b], check_finite=False)
        # plus the windows' joint motions
        Phi = self.motions
        rc = _sum_by(self.window_of, np.einsum("fam,fa->fm", Phi, r.reshape(-1, 6)), self.nw)
        yc = scipy.linalg.cho_solve(self.coarse, rc.ravel(), check_finite=False
                                    ).reshape(self.nw, self.m)
        return z + np.einsum("fam,fm->fa", Phi, yc[self.window_of]).ravel()


class _ProductPlan:
    """The sparse structure of :class:`_IterativeSystem`'s products for one kind of landmark
    (observation ``k``: frame ``f[k]`` of ``F``, landmark ``t[k]`` of ``N``, ``n`` parameters),
    built once per problem: the blocks ``G_k`` change from step to step, their places do not.

    ``obs`` ``(n K, 6F)``: row ``i K + q`` holds ``G_k[:, i]`` in frame ``f[k]``'s columns,
    ``k = by[q]`` the observations in landmark order; ``per_landmark`` ``(n N, 6F)`` the same
    entries with the rows of each landmark's observations summed (``sum_k G_k^T x`` over a
    landmark's observations: its ``G_j^T x``; a landmark seen twice in one frame keeps both
    entries, which the product sums), so that ``S x = H_pp x - P^T (P x)``. In landmark order
    a landmark's rows are consecutive: the two matrices share one array of entries, written
    once a step (:class:`_JointProblem` keeps its points in that order)."""

    def __init__(self, f: np.ndarray, t: np.ndarray, n: int, N: int, F: int) -> None:
        K = len(f)
        by = np.argsort(t, kind="stable")
        self.by: np.ndarray | None = None if np.array_equal(by, np.arange(K)) else by
        fs = f if self.by is None else f[by]
        cols = np.broadcast_to(6 * fs.astype(np.int32)[None, :, None]
                               + np.arange(6, dtype=np.int32), (n, K, 6)).ravel()
        data = np.zeros(len(cols))
        self.obs = sp.csr_matrix((data, cols, np.arange(0, 6 * K * n + 1, 6, dtype=np.int64)),
                                 shape=(K * n, 6 * F))
        ends = 6 * (np.arange(n)[:, None] * K + np.cumsum(np.bincount(t, minlength=N))[None])
        self.per_landmark = sp.csr_matrix((data, cols, np.r_[0, ends.ravel()]),
                                          shape=(N * n, 6 * F))
        self.per_landmark.data, self.per_landmark.indices = self.obs.data, self.obs.indices
        self.shape = (K, n)

    def matrices(self, G: FloatArray) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """``obs`` and ``per_landmark`` for the blocks ``G`` ``(K, 6, n)`` (the same two
        matrices each call, their entries overwritten)."""
        K, n = self.shape
        Gs = G if self.by is None else G[self.by]
        np.copyto(self.obs.data.reshape(n, K, 6), np.transpose(Gs, (2, 0, 1)))
        return self.obs, self.per_landmark

    def per_observation(self, Y: FloatArray) -> FloatArray:
        """``obs @ Z`` ``(n K, m)`` as ``(K, n, m)``, observation ``k``'s rows at ``k``."""
        K, n = self.shape
        Z = np.asarray(Y).reshape(n, K, -1).transpose(1, 0, 2)
        if self.by is None:
            return np.ascontiguousarray(Z)
        out = np.empty_like(Z)
        out[self.by] = Z
        return out


def _window_motions(R: FloatArray, c: FloatArray, free: np.ndarray, window_of: np.ndarray
                    ) -> FloatArray:
    """``(F, 6, 7)``: the pose steps (``R <- R exp([w]x)``, ``c <- c + dc``) of a window's
    cameras moved together (frame ``f`` in window ``window_of[f]``), per frame: a rotation of
    the world (3: ``w = R^T theta``, ``dc = theta x (c - m)``, ``m`` the window's mean centre),
    a translation (3) and a scaling about ``m`` (1); zero on held parameters. The modes that
    the windows' own blocks leave to the iterations."""
    nw = int(window_of.max()) + 1
    m = _sum_by(window_of, c, nw) / np.bincount(window_of, minlength=nw)[:, None]
    rel = c - m[window_of]
    Phi = np.zeros((len(R), 6, 7))
    Phi[:, :3, :3] = np.swapaxes(R, 1, 2)
    Phi[:, 3:, :3] = -np.cross(rel[:, :, None], np.eye(3)[None], axis=1)
    Phi[:, 3:, 3:6] = np.eye(3)
    Phi[:, 3:, 6] = rel
    return Phi * free[:, :, None]


def _landmark_chunks(f: np.ndarray, t: np.ndarray, chunk: int) -> list[np.ndarray]:
    """The observations (frame ``f``, landmark ``t``) in chunks of whole landmarks whose
    frames span a short window: each chunk's dense block costs the square of its window, so
    landmarks are grouped by the span of their frames (classes of powers of two), then by
    their first frame (ranges of half the class's span, at least 16 frames), then cut at about
    ``chunk`` observations. A chunk's window is then at most about 2.5 times its landmarks'
    spans; ordered by first frame alone, one point seen across a 1,000-frame walk made its
    chunk's window the whole walk (25 s of an iteration's 32)."""
    order = np.argsort(t, kind="stable")
    ts, fs = t[order], f[order]
    starts = np.flatnonzero(np.r_[True, ts[1:] != ts[:-1]])
    first = np.minimum.reduceat(fs, starts)
    span = np.maximum.reduceat(fs, starts) - first + 1
    count = np.diff(np.r_[starts, len(ts)])
    cls = np.floor(np.log2(span)).astype(np.int64)
    group = first // np.maximum(16, (1 << cls) // 2)
    lo = np.lexsort((first, group, cls))  # the landmarks in chunk order
    key = cls[lo] * (int(group.max()) + 1) + group[lo]
    new_group = np.r_[True, key[1:] != key[:-1]]
    cum = np.cumsum(count[lo])
    before = cum - count[lo]  # observations before each landmark
    group_start = np.maximum.accumulate(np.where(new_group, before, 0))
    part = (before - group_start) // chunk
    cut = new_group | np.r_[True, part[1:] != part[:-1]]
    # the observations in that order, cut where a chunk starts
    idx = np.repeat(starts[lo] - before, count[lo]) + np.arange(len(ts))
    return np.split(order[idx], before[cut][1:])


def _frame_information(prob: _JointProblem, state: tuple[FloatArray, ...]) -> FloatArray:
    """``(2, F, 6, 6)``: the information of each frame's pose from the lines (0) and from the
    points (1) at ``state``, each kind's landmarks eliminated: the diagonal blocks of each
    kind's part of the cameras' reduced system (lines and points touch only the cameras, so the
    system is the sum of the two parts). The other frames held: how firmly each kind alone
    fixes the frame."""
    R, c, d, p, X = state
    e, aux = prob.residuals(R, c, d, p, X)
    Jpl, Jl, Jpp, Jx = prob.jacobian(R, c, d, p, X, aux)
    out = np.empty((2, prob.F, 6, 6))
    for kind in range(2):
        w = ((np.arange(len(e)) >= prob.Kl) == bool(kind)).astype(np.float64)
        Hpp, _, *marks = prob.normal_equations(Jpl, Jl, Jpp, Jx, e, w)
        H, Hcross, _, f, t, free = marks[kind]
        Linv = np.linalg.inv(np.linalg.cholesky(damped(H, 1e-12, free)))
        pf, _, Gp = _pairs(f, t, len(H), Hcross @ np.swapaxes(Linv[t], 1, 2))  # (K, 6, n)
        out[kind] = Hpp - _sum_by(pf, Gp @ np.swapaxes(Gp, 1, 2), prob.F)
    return out


def _pairs(f: np.ndarray, t: np.ndarray, m: int, G: FloatArray
           ) -> tuple[np.ndarray, np.ndarray, FloatArray]:
    """The observations' blocks ``G`` ``(K, ...)`` (frame ``f``, landmark ``t`` of ``m``)
    summed per (frame, landmark) pair: ``(frames, landmarks, blocks)`` of the distinct pairs. A
    landmark seen twice in one frame (two keypoints of one COLMAP point) counts both; keeping
    one left the Schur step inexact (linear convergence)."""
    pair, inv = np.unique(f * m + t, return_inverse=True)
    if len(pair) == len(f):
        return f, t, G
    return pair // m, pair % m, _sum_by(inv, G, len(pair))


def joint_adjust(lines: LineTracks, rotations: FloatArray, positions: FloatArray,
                 line_directions: FloatArray, line_points: FloatArray,
                 points: PointObservations, point_positions: FloatArray,
                 frames: np.ndarray | None = None,
                 options: JointOptions = JointOptions()) -> JointResult:
    """Cameras, lines and points adjusted together from their initial values.

    ``rotations`` ``(F, 3, 3)`` world_from_cam and ``positions`` ``(F, 3)`` camera centres
    (``frames`` ``(F,)`` bool: the ones to adjust, default those with a finite pose); lines
    ``(M, 3)`` direction and point (NaN: not used) for the tracks of ``lines``; points
    ``(P, 3)`` (NaN: not used) for ``points``' observations. Either kind may be empty.

    Raises:
        OmniSfmError: nothing to adjust, or too little evidence for a gauge.
    """
    M, P = lines.num_tracks, points.num_points
    R = np.array(rotations, float)
    c = np.array(positions, float)
    if frames is None:
        frames = np.isfinite(R).all((1, 2)) & np.isfinite(c).all(1)
    frames = np.asarray(frames, bool) & np.isfinite(c).all(1) & np.isfinite(R).all((1, 2))
    if frames.sum() < 2:
        raise OmniSfmError("joint adjustment: fewer than 2 posed frames")
    d = np.array(line_directions, float)
    p = np.array(line_points, float)
    X = np.array(point_positions, float)
    lines_used = np.isfinite(d).all(1) & np.isfinite(p).all(1)
    lines_used &= np.bincount(lines.obs_track[frames[lines.obs_frame]], minlength=M) >= 2
    pin = frames[points.frame] & np.isfinite(X[points.point]).all(1)
    for arr in (R, c, d, p, X):
        arr[~np.isfinite(arr)] = 0.0
    fixed, scale_frame, scale_axis = gauge(c, frames, None)
    extent = float(np.ptp(c[frames], axis=0).max())  # the camera centres' extent
    sl = np.radians(options.line_noise_deg) if options.line_noise_deg else None
    spt = np.radians(options.point_noise_deg) if options.point_noise_deg else None
    state: tuple[FloatArray, ...] = (R, c, d, p, X)
    iterations = 0
    sig_l, sig_p = 1.0, 1.0

    candidate_lines, candidate_points = lines_used.copy(), pin.copy()

    line_weight, point_weight = np.ones(M), np.ones(P)

    line_obs = np.ones(lines.num_observations, bool)  # not left out as near a camera

    def problem(lines_on: np.ndarray, points_on: np.ndarray) -> _JointProblem:
        points_on &= _enough(points.point, points_on, P)
        lp = LineProblem(lines, frames, lines_on, fixed, scale_frame, scale_axis,
                         observations=line_obs)
        return _JointProblem(lp, points, points_on, sig_l, sig_p, line_weight, point_weight,
                             options)

    def angles(prob: _JointProblem) -> tuple[FloatArray, FloatArray]:
        return prob.angles(prob.residuals(*state)[0])

    for round_ in range(options.robust_rounds + 1):
        if round_ > 0:
            # every candidate judged again from the last solve (a good observation pushed
            # off by outliers in an early round comes back)
            every = problem(candidate_lines.copy(), candidate_points.copy())
            al, ap = angles(every)
            sig_l, sig_p = _noise_sigmas(al, ap, sl, spt)
            lines_used, pin = _inliers(every, al, ap, sig_l, sig_p, candidate_lines,
                                       candidate_points, M, options)
            if options.near_camera_ratio > 0:
                line_obs, lines_used = _off_cameras(lines, state, frames, lines_used,
                                                    options.near_camera_ratio)
            line_weight, point_weight = _landmark_weights(every, state, points, M, P, options,
                                                          line_weight, point_weight)
        prob = problem(lines_used, pin)
        if prob.Kl + len(prob.f) == 0:
            raise OmniSfmError("joint adjustment: no line or point observation")
        if round_ == 0:
            al, ap = angles(prob)
            sig_l, sig_p = _noise_sigmas(al, ap, sl, spt)
            prob = problem(lines_used, pin)
        state, it = _solve_round(prob, state, options, round_, extent)
        iterations += it
    al, ap = angles(prob)
    line_share = _line_share(prob, state, frames)
    R, c, d, p, X = state
    points_used = np.bincount(points.point[pin], minlength=P) >= 2
    nan3 = np.full(3, np.nan)
    return JointResult(
        rotations=np.where(frames[:, None, None], R, np.nan),
        positions=np.where(frames[:, None], c, nan3),
        frames=frames,
        line_directions=np.where(lines_used[:, None], d, nan3),
        line_points=np.where(lines_used[:, None], p, nan3),
        lines_used=lines_used.copy(),
        points=np.where(points_used[:, None], X, nan3),
        points_used=points_used,
        point_inliers=pin.copy(),
        line_sigma_deg=float(np.degrees(sig_l)), point_sigma_deg=float(np.degrees(sig_p)),
        line_rms_deg=float(np.degrees(np.sqrt(np.mean(al ** 2)))) if len(al) else np.nan,
        point_rms_deg=float(np.degrees(np.sqrt(np.mean(ap ** 2)))) if len(ap) else np.nan,
        iterations=iterations, line_share=line_share)


def _noise_sigmas(al: FloatArray, ap: FloatArray, sl: float | None,
                  spt: float | None) -> tuple[float, float]:
    """The lines' and points' noise (radians): the options' where given, else robust ones."""
    sig_l = sl or (robust_sigma(al) if len(al) else 1.0)
    sig_p = spt or (robust_sigma(ap) if len(ap) else 1.0)
    return sig_l, sig_p


def _inliers(every: _JointProblem, al: FloatArray, ap: FloatArray, sig_l: float, sig_p: float,
             candidate_lines: np.ndarray, candidate_points: np.ndarray, M: int,
             options: JointOptions) -> tuple[np.ndarray, np.ndarray]:
    """The candidate lines whose RMS angle and the point observations whose angle are within
    the outlier threshold: ``(lines_used (M,), point_inliers)``."""
    lim_l = options.outlier_threshold * np.sqrt(2.0) * sig_l
    lim_p = options.outlier_threshold * np.sqrt(2.0) * sig_p
    t = every.lines.t
    cnt = np.bincount(t, minlength=M)
    ss = np.bincount(t, weights=al ** 2, minlength=M)
    with np.errstate(invalid="ignore", divide="ignore"):
        lines_used = candidate_lines & ~(np.sqrt(ss / np.maximum(cnt, 1)) > lim_l)
    pin = np.zeros_like(candidate_points)
    pin[every.obs_index[ap <= lim_p]] = True
    return lines_used, pin


def _landmark_weights(every: _JointProblem, state: tuple[FloatArray, ...],
                      points: PointObservations, M: int, P: int, options: JointOptions,
                      line_weight: FloatArray, point_weight: FloatArray
                      ) -> tuple[FloatArray, FloatArray]:
    """The lines' and points' weights from their residuals' correlation, for the kinds in
    :attr:`JointOptions.correlated` (the others' weights as given)."""
    e, (_, v) = every.residuals(*state)
    if "lines" in options.correlated:
        line_weight = _correlation_weights(e[:every.Kl] / every.line_scale[:, None],
                                           every.lines.t, every.lines.f, M)
    if "points" in options.correlated:
        Rf = state[0][every.f]
        off = normalize(v) - points.ray[every.obs_index]
        point_weight = _correlation_weights(np.einsum("kij,kj->ki", Rf, off), every.j,
                                            every.f, P)
    return line_weight, point_weight


def _solve_round(prob: _JointProblem, state: tuple[FloatArray, ...], options: JointOptions,
                 round_: int, extent: float) -> tuple[tuple[FloatArray, ...], int]:
    """One round's Levenberg-Marquardt solve (Huber and loose tolerances but in the last):
    the new state and the iterations."""
    final = round_ == options.robust_rounds
    if not final:
        prob.cg_tolerance = options.robust_cg_tolerance
    tol = options.pose_tolerance if final else options.robust_pose_tolerance
    step_tol = options.step_tolerance if final else options.robust_step_tolerance
    return levenberg_marquardt(
        prob, state, RobustLoss.LINEAR if final else RobustLoss.HUBER, options.loss_scale,
        options.max_iterations if final else options.robust_iterations,
        options.tolerance if final else 1e-6, (tol, tol * extent), step_tol or None,
        1e-4 if round_ == 0 else options.warm_damping)


def _line_share(prob: _JointProblem, state: tuple[FloatArray, ...],
                frames: np.ndarray) -> FloatArray:
    """``(F, 2)``: the lines' share of each frame's rotation and position information (NaN
    where a frame is not adjusted or that part of it is held)."""
    info = _frame_information(prob, state)
    tr = np.stack([np.einsum("kfii->kf", info[:, :, :3, :3]),
                   np.einsum("kfii->kf", info[:, :, 3:, 3:])], axis=2)  # (2, F, 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        line_share = tr[0] / (tr[0] + tr[1])
    line_share[~frames] = np.nan
    line_share[~prob.lines.pose_free[:, :3].any(1), 0] = np.nan
    line_share[~prob.lines.pose_free[:, 3:].any(1), 1] = np.nan
    return line_share


def _off_cameras(lines: LineTracks, state: tuple[FloatArray, ...], frames: np.ndarray,
                 used: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """The line observations ``(K,)`` whose camera is not within ``ratio`` of the median
    camera distance of their track's line (:attr:`JointOptions.near_camera_ratio`; at the
    poses and lines of ``state``), and the ``used`` lines ``(M,)`` that keep two or more."""
    R, c, d, p = state[:4]
    near = observation_distance_ratio(lines, R, c, d, p,
                                      frames[lines.obs_frame] & used[lines.obs_track]) < ratio
    keep = np.bincount(lines.obs_track[~near & frames[lines.obs_frame]],
                       minlength=lines.num_tracks) >= 2
    return ~near, used & keep


def _correlation_weights(r: FloatArray, landmark: np.ndarray, frame: np.ndarray, n: int
                         ) -> FloatArray:
    """``(n,)``: each landmark's weight from its residual vectors ``r`` ``(K, d)`` (observation
    ``k`` of landmark ``landmark[k]`` in frame ``frame[k]``): ``(1 - rho) / (1 + rho)``, the
    share of independent errors in a series with lag-1 correlation ``rho`` (that of the
    residuals of consecutive observations, clipped to [0, 0.95]); 1 for a landmark with
    uncorrelated (or anti-correlated: fitting the landmark leaves some) errors."""
    o = np.lexsort((frame, landmark))
    lo, ro = landmark[o], r[o]
    nxt = lo[1:] == lo[:-1]
    num = np.bincount(lo[1:][nxt], weights=np.sum(ro[1:][nxt] * ro[:-1][nxt], axis=1),
                      minlength=n)
    den = np.bincount(lo, weights=np.sum(ro * ro, axis=1), minlength=n)
    rho = np.clip(num / np.maximum(den, 1e-300), 0.0, 0.95)
    return np.asarray((1.0 - rho) / (1.0 + rho))


def _enough(point: np.ndarray, keep: np.ndarray, P: int) -> np.ndarray:
    """``keep`` narrowed to the observations of points that keep two or more."""
    return keep & (np.bincount(point[keep], minlength=P) >= 2)[point]


def points_seen(rotations: FloatArray, positions: FloatArray, points: FloatArray,
                frame: np.ndarray, point: np.ndarray) -> FloatArray:
    """``(K, 3)`` the unit rays (camera frame) along which frames ``frame`` see ``points``
    ``[point]``: the point model's prediction (the simulation of observations, tests)."""
    return normalize(_offsets(rotations, positions, points, frame, point))


def _offsets(R: FloatArray, c: FloatArray, X: FloatArray, frame: np.ndarray,
             point: np.ndarray) -> FloatArray:
    """``(K, 3)``: ``R^T (X - c)``, point ``point[k]`` in the camera of frame ``frame[k]``."""
    return np.einsum("kji,kj->ki", R[frame], X[point] - c[frame])


__all__ = ["JointOptions", "JointResult", "PointObservations", "joint_adjust", "points_seen"]
