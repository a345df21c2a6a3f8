"""Positions of all frames and lines at once, the rotations given (docs/estimator.md, "Global
estimator", step 2).

With the rotations known, an observation of line ``i`` (a point ``p_i``, direction ``d_i``) in
frame ``k`` (centre ``c_k``) says that the line lies in the plane through ``c_k`` with world
normal ``m = R_k n``: ``m . (p_i - c_k) = 0``, with ``m`` made perpendicular to ``d_i`` so that
the residual is the same for every point of the line. That is linear in the centres and in the
lines' offsets ``p_i = a_i e1_i + b_i e2_i`` (``e1, e2`` perpendicular to ``d_i``), and
homogeneous: it fixes the solution up to its scale. The centre of the frame whose lines fix
its rotation best (:func:`~omni_sfm.estimate.global_rotations.gauge_frame`, whatever the
frames' order) is the origin. Each row is weighted by the inverse distance between camera and
line (its residual is then the observation's angle) and by a Cauchy loss, re-weighted as the
solution moves.

The observation's ray (``LineTracks.obs_ray``) says on which side of the camera the line lies:
its depth ``u . (p_i - c_k)`` along ``u``, the unit vector in the plane across the line towards
the ray, is positive. A squared hinge on the depths (solved by its active sets) keeps every
stretch of the walk from shrinking to a point and every line on its side: first every depth at
1 or more (the scale the nearest line's distance), then, once the weights have settled on
the lines that agree, the mean depth at 1 and every depth at a tenth of it or more
(:func:`_with_depths`). Without rays the scale is set by ``sum |c_k|^2 = 1`` and the centres
are the generalised eigenvector of the smallest eigenvalue of the normal equations (lines
included), found by inverse iteration; on long walks of few lines it is several times further
off than the depths (docs/estimator.md).

A second-difference prior on the centres (in frame order) makes every frame's position
defined: a frame that its lines do not fix (a stop with the lines along the motion, a stretch
with two lines) takes its position from its neighbours instead of a free direction, and its
information (:attr:`GlobalPositions.frame_information`) says that the data did not fix it. The
prior is the same read forwards or backwards. Either way the centres are returned scaled to
``sum |c_k|^2 = 1``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.global_rotations import gauge_frame
from omni_sfm.geometry import FloatArray, normalize, orthonormal_completion
from omni_sfm.lines.tracks import LineTracks


@dataclass(frozen=True, kw_only=True)
class GlobalPositionOptions:
    smoothness: float = 0.1
    """Weight of the second-difference prior on the centres, relative to the median weight of a
    frame's own observations (per frame). Under the scale condition ``sum |c|^2 = 1`` a frame
    whose short tracks barely fix it could carry the whole norm alone at almost no cost; the
    prior makes that cost what moving it off its neighbours' line costs, while a smooth walk's
    own second differences cost next to nothing; the adjustment then drops the prior
    (docs/estimator.md, the hand-held 360 walks)."""
    reweight_rounds: int = 4
    """Solves with the rows re-weighted by the current distances and residuals."""
    loss_scale: float = 3.0
    """Cauchy loss scale in units of the residuals' robust spread (angles)."""
    inverse_iterations: int = 30
    """Inverse iterations of each solve at most (tracks without rays)."""
    depth_floor: float = 0.1
    """The depth every observation's line is held at or beyond (a squared hinge) in the last
    re-weightings, in units of the mean depth (:func:`_with_depths`): far below it, so that it
    holds only where a stretch would shrink to a point or turn its lines behind the cameras,
    and the scale is the mean depth's, which does not shrink the other depths with the
    nearest line's."""
    depth_iterations: int = 60
    """Newton steps at most of each re-weighting's problem (tracks with rays;
    :func:`_hinge_minimum`): each solves with the depths below the floor held and stops when
    those are the same after a full step."""


@dataclass(frozen=True)
class GlobalPositions:
    """Centres of all frames and a point of every line.

    Attributes:
        positions: ``(F, 3)`` camera centres (world; the gauge frame at the origin;
            ``sum |c|^2 = 1``); NaN where not posed.
        points: ``(M, 3)`` the point of each line closest to the origin; NaN for lines not used.
        frame_information: ``(F,)`` smallest eigenvalue of each frame's 3x3 information block
            from its observations alone (the lines' positions held), relative to the median
            frame's largest: near 0 where the frame's lines leave its position free.
        free_direction: ``(F, 3)`` the direction of that smallest eigenvalue (world, unit):
            the direction of motion the frame's lines fix least.
        residual_sigma: robust spread of the final residuals (radians).
    """

    positions: FloatArray
    points: FloatArray
    frame_information: FloatArray
    free_direction: FloatArray
    residual_sigma: float


def _second_differences(frames: np.ndarray, pose_idx: np.ndarray) -> sp.csr_matrix:
    """``D`` with ``(D c)_j`` the second difference of the centres at each posed frame but the
    first and the last, per frame squared: ``c_{j-1} - 2 c_j + c_{j+1}`` between consecutive
    frames, ``2 / (a + b) (c_{j-1} / a - (1 / a + 1 / b) c_j + c_{j+1} / b)`` where its posed
    neighbours are ``a`` and ``b`` frames away (a stretch of frames not posed between them is
    not a step of one frame). The gauge frame's centre, fixed at 0, has no column."""
    posed = np.flatnonzero(frames)
    j = np.arange(1, len(posed) - 1)
    # one row per (second difference, neighbour, axis); the gauge frame's entries dropped
    f = np.stack([posed[j - 1], posed[j], posed[j + 1]], axis=1)  # (J, 3)
    a = (f[:, 1] - f[:, 0]).astype(np.float64)
    b = (f[:, 2] - f[:, 1]).astype(np.float64)
    v = (2.0 / (a + b))[:, None] * np.stack([1.0 / a, -(1.0 / a + 1.0 / b), 1.0 / b], axis=1)
    rows = 3 * (j - 1)[:, None, None] + np.arange(3)  # (J, 1, 3)
    cols = 3 * pose_idx[f][:, :, None] + np.arange(3)  # (J, 3, 3)
    rows = np.broadcast_to(rows, cols.shape)
    vals = np.broadcast_to(v[:, :, None], cols.shape)
    keep = np.broadcast_to((pose_idx[f] >= 0)[:, :, None], cols.shape)
    rows, cols, vals = rows[keep], cols[keep], vals[keep]
    n = 3 * max(len(posed) - 2, 0)
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, 3 * (len(posed) - 1)))


def solve_positions(tracks: LineTracks, rotations: FloatArray, directions: FloatArray,
                    frames: np.ndarray, lines: np.ndarray,
                    options: GlobalPositionOptions = GlobalPositionOptions()) -> GlobalPositions:
    """The linear problem of the module docstring on the posed ``frames`` ``(F,)`` and the
    ``lines`` ``(M,)`` with a direction."""
    F, M = tracks.num_frames, tracks.num_tracks
    obs = frames[tracks.obs_frame] & lines[tracks.obs_track]
    f, t = tracks.obs_frame[obs], tracks.obs_track[obs]
    # the world normals made perpendicular to their line's direction: the residual
    # m . (p - c) is then the same for every point p of the line, so the solution does not
    # depend on where the gauge puts the origin (the first frame: which one follows the order)
    m = np.einsum("kij,kj->ki", rotations[f], tracks.obs_normal[obs])
    dl = directions[t]
    m = normalize(m - np.einsum("ki,ki->k", m, dl)[:, None] * dl)
    posed = np.flatnonzero(frames)
    if len(posed) < 3:
        raise OmniSfmError("fewer than 3 frames with a rotation; positions need 3")
    pose_idx = np.full(F, -1)
    # the origin: a frame chosen whatever the frames' order (the ridge that keeps the normal
    # equations definite pulls directions the data barely fix towards it)
    free = posed[posed != gauge_frame(tracks, frames, lines)]
    pose_idx[free] = np.arange(len(free))
    used = np.flatnonzero(lines)
    line_idx = np.full(M, -1)
    line_idx[used] = np.arange(len(used))
    e1, e2 = orthonormal_completion(directions[used])
    P, L = 3 * (len(posed) - 1), 2 * len(used)
    # rows: m . (a e1 + b e2) - m . c = 0
    pc = pose_idx[f]
    li = line_idx[t]
    A = _rows(m, e1, e2, pc, li, P, L)
    D = _second_differences(frames, pose_idx)
    geometry = _Geometry(A, D, e1, e2, directions[used], pc, li, P, L, m,
                         np.searchsorted(posed, f))
    sides = _sides(tracks, rotations, directions, obs, m)
    if sides is None:
        x, w, sigma = _homogeneous(geometry, posed, pose_idx, options)
    else:
        x, w, sigma = _with_depths(geometry, sides, options)
    x = x / max(float(np.linalg.norm(x[:P])), 1e-300)
    c_all = np.full((F, 3), np.nan)
    c_all[posed] = 0.0
    c_all[free] = x[:P].reshape(-1, 3)
    q = x[P:].reshape(-1, 2)
    pts = np.full((M, 3), np.nan)
    pts[used] = q[:, :1] * e1 + q[:, 1:] * e2
    info, free = _frame_information(m, w, f, F, frames)
    return GlobalPositions(positions=c_all, points=pts, frame_information=info,
                           free_direction=free,
                           residual_sigma=sigma)


@dataclass(frozen=True)
class _Geometry:
    """The linear problem: ``A`` (one row ``m . (p - c)`` per observation), ``D`` (second
    differences of the centres), the lines' bases and directions, and each observation's
    centre (``pc``, -1: the gauge frame) and line (``li``) columns."""

    A: sp.csr_matrix
    D: sp.csr_matrix
    e1: FloatArray
    e2: FloatArray
    d: FloatArray
    pc: np.ndarray
    li: np.ndarray
    P: int
    L: int
    m: FloatArray
    frame: np.ndarray
    """Each observation's world plane normal and its frame among the posed ones (the gauge
    frame included)."""

    def depths(self, x: FloatArray) -> FloatArray:
        return _depths(x[:self.P].reshape(-1, 3), x[self.P:].reshape(-1, 2), self.e1, self.e2,
                       self.d, self.pc, self.li)

    def prior(self, H: sp.csc_matrix, smoothness: float, w: FloatArray) -> sp.csc_matrix:
        """``H`` plus the second-difference prior, weighted by ``smoothness`` times the median
        over the posed frames (the gauge frame included, so that the weight does not depend on
        which frame is first) of the mean diagonal entry of a frame's information (a third of
        its plane rows' weights ``w``: unit normals, whatever the world's orientation), and a
        ridge of 1e-12 of the largest diagonal entry."""
        info = np.bincount(self.frame, weights=w, minlength=int(self.frame.max(initial=-1)) + 1)
        lam = smoothness * (float(np.median(info)) / 3.0 if info.size else 1.0)
        K = H
        if self.D.shape[0]:
            DD = (self.D.T @ self.D).tocoo()
            K = H + lam * sp.csc_matrix((DD.data, (DD.row, DD.col)), shape=H.shape)
        eps = 1e-12 * max(float(np.max(H.diagonal())), 1e-300)
        return (K + sp.diags(np.full(H.shape[0], eps))).tocsc()


def _rows(v: FloatArray, e1: FloatArray, e2: FloatArray, pc: np.ndarray, li: np.ndarray, P: int,
          L: int) -> sp.csr_matrix:
    """One row ``v . (a e1 + b e2) - v . c`` per observation (``v`` ``(K, 3)`` world vectors;
    columns: the centres, then each line's ``(a, b)``; the gauge frame's centre has none)."""
    vals = np.concatenate([-v, np.stack([np.einsum("ki,ki->k", v, e1[li]),
                                         np.einsum("ki,ki->k", v, e2[li])], axis=1)], axis=1)
    cols = np.concatenate([np.where(pc[:, None] >= 0, 3 * pc[:, None] + np.arange(3), -1),
                           P + 2 * li[:, None] + np.arange(2)], axis=1)
    keep = cols >= 0
    rows = np.broadcast_to(np.arange(len(v))[:, None], cols.shape)
    return sp.csr_matrix((vals[keep], (rows[keep], cols[keep])), shape=(len(v), P + L))


def _sides(tracks: LineTracks, rotations: FloatArray, directions: FloatArray, obs: np.ndarray,
           m: FloatArray) -> FloatArray | None:
    """``(K, 3)``: for each observation the unit direction, perpendicular to its line and in
    its plane, from the camera towards the line, as its ray says (zero where the ray runs
    within 5 deg of the line: it says nothing); None when the tracks carry no rays."""
    if tracks.obs_ray is None:
        return None
    d = directions[tracks.obs_track[obs]]
    ray = np.einsum("kij,kj->ki", rotations[tracks.obs_frame[obs]], tracks.obs_ray[obs])
    u = np.cross(d, m)
    size = np.linalg.norm(u, axis=1)
    u /= np.maximum(size, 1e-300)[:, None]
    along = np.einsum("ki,ki->k", u, ray)
    ok = (np.abs(along) > np.sin(np.radians(5.0))) & (size > 0.5)
    return np.where(ok[:, None], u * np.sign(along)[:, None], 0.0)


def _with_depths(g: _Geometry, sides: FloatArray, options: GlobalPositionOptions
                 ) -> tuple[FloatArray, FloatArray, float]:
    """``(x, w, sigma)``: the least squares of the plane rows (weighted by the inverse depth and
    a Cauchy loss) with each observation's depth along its side ``U x`` held at a floor or
    more (a squared hinge). Each line then lies on the side of the camera its rays see it on,
    and no part of the walk can shrink to a point.

    ``options.reweight_rounds`` rounds, each with the weights of the last (every row's 1 in the
    first): for given weights the problem is convex and its minimum unique
    (:func:`_hinge_minimum`), a continuous function of the input. Re-weighting and active set
    in one loop cycle through thousands of active sets on a sparse walk, and where they stop
    follows the last bits of the input. The first half of the rounds hold every depth at 1 or
    more (the scale the nearest line's distance): every line then holds the walk's shape,
    and lines that move with the camera (a walker beside it) find no shape to pull it into
    before their weights fall. The second half hold the mean depth at 1 and every depth at
    ``options.depth_floor`` or more: held at the nearest line's distance, the scale would
    shrink every other depth with it and bend a sparse walk's shape (docs/estimator.md,
    step 2)."""
    K = g.A.shape[0]
    U = _rows(sides, g.e1, g.e2, g.pc, g.li, g.P, g.L)
    x = np.zeros(g.P + g.L)
    w = np.ones(K)
    sigma = np.inf
    rounds = max(1, options.reweight_rounds)
    factors = _Factors()
    for r in range(rounds):
        x = _hinge_minimum(g, U, w, x, options, on_mean=2 * r >= rounds, factors=factors)
        w, sigma = _reweighted(g, x, options)
    return x, w, sigma


def _hinge_minimum(g: _Geometry, U: sp.csr_matrix, w: FloatArray, x: FloatArray,
                   options: GlobalPositionOptions, on_mean: bool, factors: _Factors
                   ) -> FloatArray:
    """The minimum of ``1/2 |A x|_w^2 + prior + 1/2 sum w max(0, f - U x)^2`` for the weights
    ``w`` (:func:`_with_depths`), ``on_mean``: on the plane ``s . x = S`` (the depths'
    weighted sum ``sum w U x`` equal to the weights' sum: a mean depth of one) with ``f`` =
    ``options.depth_floor``, else with ``f`` = 1 (the scale the nearest line's distance), by
    Newton's method on the hinge's active sets from ``x`` (every depth held where ``x`` is 0),
    each step shortened until the cost falls: without that the active sets cycle. Each step
    factorises a matrix of one pattern (``factors``: its fill-reducing order found once)."""
    K = g.A.shape[0]
    # the quadratic part: the plane rows, the prior (weighted against the plane rows' own
    # information) and the ridge
    quad = g.prior((g.A.T @ sp.diags(w) @ g.A).tocsc(), options.smoothness, w)
    sides = np.asarray(abs(U).sum(axis=1)).ravel() > 0
    s_vec = np.asarray(U.T @ (w * sides))
    total = float(np.sum(w * sides)) if on_mean else 0.0
    floor = options.depth_floor if on_mean else 1.0

    def solve(held: np.ndarray) -> FloatArray:
        # the minimum on the plane: x = M^-1 (b + lam s), lam from s . x = total
        lu = factors.of((quad + U.T @ sp.diags(w * held) @ U).tocsc())
        xb, xs = lu(np.asarray(U.T @ (w * held * floor))), lu(s_vec)
        across = float(s_vec @ xs)
        if total <= 0.0 or across <= 0.0:  # the scale from the floor alone
            return np.asarray(xb)
        return np.asarray(xb + (total - float(s_vec @ xb)) / across * xs)

    def cost(y: FloatArray) -> float:
        gap = np.maximum(floor - U @ y, 0.0)
        return 0.5 * float(y @ (quad @ y)) + 0.5 * float(np.sum(w * gap**2))

    if on_mean and x.any() and float(s_vec @ x) > 0.0:
        x = x * (total / float(s_vec @ x))  # on the plane: the line search stays on it
    held = np.ones(K, bool) & sides if not x.any() else (U @ x < floor) & sides
    now_cost = cost(x) if x.any() else np.inf
    for _ in range(max(1, options.depth_iterations)):
        y = solve(held)
        step, new_cost = 1.0, cost(y)
        while np.isfinite(now_cost) and new_cost > now_cost and step > 1e-6:
            step *= 0.5
            new_cost = cost(x + step * (y - x))
        x = x + step * (y - x) if step < 1.0 else y
        now = (U @ x < floor) & sides
        done = np.array_equal(now, held) and step == 1.0
        held, now_cost = now, new_cost
        if done:
            break
    return x


def _factor(M: sp.csc_matrix, order: str = "MMD_AT_PLUS_A") -> spla.SuperLU:
    """The factorisation of the symmetric positive definite normal equations ``M`` (a ridge
    keeps them so): a minimum-degree order of ``M``'s own pattern (``order="NATURAL"``: ``M``
    already in a good order) and no pivoting, twice as fast as SuperLU's default on a
    600-frame walk, with the same solution to round-off."""
    return spla.splu(M, permc_spec=order, diag_pivot_thresh=0.0,
                     options={"SymmetricMode": True})


class _Factors:
    """Factorisations of symmetric positive definite matrices of one pattern (the Newton steps
    of :func:`_hinge_minimum`, through all the re-weightings): the minimum-degree order of the
    first (:func:`_factor`) is kept for the others, which are factorised in it without
    ordering again (on the positions of a 3,000-frame video, 0.1 s a factorisation against
    0.35 s)."""

    def __init__(self) -> None:
        self.order: np.ndarray | None = None
        self.back: np.ndarray | None = None

    def of(self, M: sp.csc_matrix) -> Callable[[FloatArray], FloatArray]:
        """A solver ``b -> M^-1 b`` for ``M``."""
        if self.order is None or self.back is None:
            lu = _factor(M)
            self.order, self.back = np.argsort(lu.perm_c), np.asarray(lu.perm_c)
            return lu.solve
        o, back = self.order, self.back
        lu = _factor(M[o][:, o].tocsc(), order="NATURAL")
        return lambda b: np.asarray(lu.solve(b[o])[back])


def _homogeneous(g: _Geometry, posed: np.ndarray, pose_idx: np.ndarray,
                 options: GlobalPositionOptions) -> tuple[FloatArray, FloatArray, float]:
    """``(x, w, sigma)`` without rays: the smallest generalised eigenvector of the plane rows
    (:func:`_smallest`), re-weighted by the inverse depth and a Cauchy loss."""
    w = np.ones(g.A.shape[0])
    x = _initial_vector(g.P, g.L, posed, pose_idx)
    sigma = np.inf
    for _ in range(max(1, options.reweight_rounds)):
        x = _smallest(g, w, options, x)
        w, sigma = _reweighted(g, x, options)
    return x, w, sigma


def _reweighted(g: _Geometry, x: FloatArray, options: GlobalPositionOptions
                ) -> tuple[FloatArray, float]:
    """``(w, sigma)``: each plane row's weight at the solution ``x`` (the inverse squared depth,
    so that its residual is the observation's angle, times a Cauchy loss at
    ``options.loss_scale`` times the angles' robust spread) and that spread (radians)."""
    depth = g.depths(x)
    ang = (g.A @ x) / depth
    if ang.size == 0:  # no plane row (a camera that only turned): nothing to weigh
        return np.ones(0), 1e-12
    sigma = max(float(1.4826 * np.median(np.abs(ang))), 1e-12)
    return 1.0 / depth**2 / (1.0 + (ang / (options.loss_scale * sigma)) ** 2), sigma


def _initial_vector(P: int, L: int, posed: np.ndarray, pose_idx: np.ndarray) -> FloatArray:
    """A start for the inverse iteration with a component along any smooth motion."""
    x = np.zeros(P + L)
    s = np.linspace(0.0, 1.0, len(posed))[1:]
    x[:P] = np.stack([s, s**2, np.sqrt(s)], axis=1).ravel()
    return x


def _depths(c: FloatArray, q: FloatArray, e1: FloatArray, e2: FloatArray, d: FloatArray,
            pc: np.ndarray, li: np.ndarray) -> FloatArray:
    """Distance between each observation's camera and its line (floored at a small fraction
    of the median, so that a camera on a line does not take all the weight)."""
    cc = np.where(pc[:, None] >= 0, c[np.maximum(pc, 0)], 0.0)
    p = q[li, :1] * e1[li] + q[li, 1:] * e2[li]
    off = p - cc
    off -= np.einsum("ki,ki->k", off, d[li])[:, None] * d[li]
    dist = np.linalg.norm(off, axis=1)
    med = float(np.median(dist)) if len(dist) else 1.0
    return np.maximum(dist, 0.05 * med)


def _smallest(g: _Geometry, w: FloatArray, options: GlobalPositionOptions, x0: FloatArray
              ) -> FloatArray:
    """The generalised eigenvector of the smallest eigenvalue of ``(A^T W A + lam D^T D) x =
    mu N x`` with ``N`` the identity on the centres and 0 on the lines, normalised so that
    ``|x_c| = 1``, by inverse iteration."""
    P, L = g.P, g.L
    lu = _factor(g.prior((g.A.T @ sp.diags(w) @ g.A).tocsc(), options.smoothness, w))
    x = x0 / np.linalg.norm(x0[:P])
    for _ in range(options.inverse_iterations):
        rhs = np.zeros(P + L)
        rhs[:P] = x[:P]
        y = lu.solve(rhs)
        size = float(np.linalg.norm(y[:P]))
        if not np.isfinite(size) or size == 0.0:
            raise OmniSfmError("the lines leave every camera centre at one point: no "
                               "translation to estimate (a camera that only turns?)")
        y /= size
        if y[:P] @ x[:P] < 0:
            y = -y
        done = np.linalg.norm(y[:P] - x[:P]) < 1e-13
        x = y
        if done:
            break
    return x


def _frame_information(m: FloatArray, w: FloatArray, f: np.ndarray, F: int,
                       frames: np.ndarray) -> tuple[FloatArray, FloatArray]:
    """Each posed frame's smallest eigenvalue of ``sum w m m^T`` over its observations, over
    the median frame's largest, and its eigenvector (NaN: not posed)."""
    S = np.zeros((F, 3, 3))
    np.add.at(S, f, w[:, None, None] * m[:, :, None] * m[:, None, :])
    ev, vec = np.linalg.eigh(S)
    ref = float(np.median(ev[frames, 2])) if frames.any() else 1.0
    out = np.full(F, np.nan)
    out[frames] = ev[frames, 0] / max(ref, 1e-300)
    direction = np.full((F, 3), np.nan)
    direction[frames] = vec[frames, :, 0]
    return out, direction
