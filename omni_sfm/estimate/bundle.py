"""Line bundle adjustment: all poses and lines refined jointly from the observed NVs.

Model. A 3D line with unit direction ``d`` through point ``p`` (world) and a camera with
world_from_cam rotation ``R`` and centre ``c`` span a plane whose normal, in the camera frame, is
``u = R^T ((p - c) x d)`` (normalised: ``n = u / |u|``). An observation is a unit normal
``n_obs`` of arbitrary sign. Its residual is the 2-vector ``e = B^T n`` where ``B`` (3x2) is an
orthonormal basis of the plane perpendicular to ``n_obs``: ``|e| = sin(angle(n, +-n_obs))``, so
the squared residual does not depend on either sign, and for small errors ``e`` is the angular
error (radians) in two tangent directions, the quantity the NV noise perturbs. When the tracks
carry each normal's uncertainty (``LineTracks.obs_sigma``: along and across the observation's
ray), ``B``'s columns are those two directions, each divided by its standard deviation (times the
median observation's): the maximum-likelihood weighting, under which a short segment's poorly
fixed tilt counts little (on the rendered textured room it took the maximum rotation error from
1.06 to 0.45 deg with the paper's extraction settings, docs/results.md).

Parameters (minimal, updated on the manifold at each step):
- pose ``k``: rotation increment ``w`` with ``R <- R exp([w]x)`` (camera-frame perturbation) and
  centre increment ``dc`` (6 DOF);
- line: direction moves in the plane perpendicular to ``d`` (2 DOF, ``d <- normalise(d + a e1 +
  b e2)``) and the point moves in that plane too (2 DOF), 4 DOF in all, as Plücker lines have.

Gauge (7 DOF: rotation, translation, scale): the first estimated frame's pose is held fixed,
and the scale by holding one coordinate of the camera centre farthest from it (the one with the
largest magnitude). The cost is gauge invariant, so the estimate is the same up to a similarity
whatever coordinate is held; callers rescale to their convention afterwards. Lines whose
directions are held (``held_directions``: parallel families with fixed world directions) in two
directions or more fix the rotation themselves: the first frame's rotation is then free (held
too, it would disagree with them by its own error, and every rotation measured from it would
carry that error), only its centre is held.

Solver: Levenberg-Marquardt (:func:`omni_sfm.solver.levenberg_marquardt`) with an analytic
Jacobian (one 2x6 pose block and one 2x4 line block per observation), the normal equations
solved by the Schur complement in the lines (dense Cholesky, or a block-sparse Cholesky whose
structure is worked out once per adjustment: :class:`_ReducedSystem`); robust loss by
iteratively reweighted least squares (Huber or Cauchy on the residual norm) with the scale set
from the noise level, estimated robustly (median of residual norms) unless given. After
convergence, tracks whose RMS residual is far above the noise are flagged as outliers, removed,
and the problem solved again.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate import kernels
from omni_sfm.geometry import (
    FloatArray,
    completion_towards,
    normalize,
    orthonormal_completion,
    predicted_normals,
    ray_line_closest,
    rotvec_to_matrix,
    skew,
    unsigned_angle,
)
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.solver import (
    RobustLoss,
    damped,
    gauge,
    levenberg_marquardt,
    robust_sigma,
)

_POSE_PARTS = (3, 3)
_LINE_PARTS = (2, 2)
"""A pose's parameters (rotation, centre) and a line's (direction, point in its tangent basis)
as vectors: each damped by its mean diagonal (:func:`~omni_sfm.solver.isotropic_diagonal`)."""

# held line directions this far apart fix the rotation gauge (bundle_adjust(held_directions=))
_MIN_GAUGE_ANGLE_DEG = 10.0


@dataclass(frozen=True, kw_only=True)
class BundleOptions:
    loss: RobustLoss = RobustLoss.HUBER
    """Robust loss applied to each observation's residual norm."""
    loss_scale: float = 3.0
    """Loss scale in units of the per-axis noise std-dev (quadratic below, robust above)."""
    noise_deg: float | None = None
    """Known per-axis angular noise of the NVs in degrees; None: estimated from the residuals."""
    max_iterations: int = 100
    """Levenberg-Marquardt iterations per solve (long chains converge slowly along their
    drift modes)."""
    tolerance: float = 1e-10
    """Stop the final solve when the relative decrease of the cost falls below this."""
    robust_tolerance: float = 1e-4
    """The same for the robust rounds (reweighting converges slowly; they only need to find
    the outliers and the basin)."""
    settled_decrease: float = 1e-3
    """Stop a solve when a step lowers the cost (half the sum of squared residuals, radians)
    by less than this many times the noise variance: the parameters then move by a few
    hundredths of their standard deviations a step, and what is left is the crawl of lines and
    drift modes that the data barely fix (0: only the relative decrease stops it; 1e-2 stops
    sooner, but two frame orders' solves then stop up to 0.005 deg apart on the simulated
    random walks, 0.0007 deg with this)."""
    robust_iterations: int = 30
    """LM iterations per robust round at most."""
    final_loss: RobustLoss | None = RobustLoss.LINEAR
    """Loss of a last solve on the inlier tracks (None: none). Plain least squares is the
    maximum-likelihood estimate for Gaussian NV noise once the outlier tracks are gone."""
    reject_outliers: bool = True
    """Flag tracks whose residuals are far above the noise, drop them and solve again."""
    outlier_threshold: float = 3.0
    """A track is an outlier if its RMS residual norm exceeds this many times the expected
    RMS for its noise (sqrt(2) sigma) ..."""
    outlier_min_deg: float = 0.05
    """... and this many degrees (a floor for precise data, whose robust noise estimate can be
    far below what the line fits' small systematic errors give good tracks)."""
    max_rounds: int = 6
    """Solve / re-estimate the noise / reject (or take back) outlier tracks rounds at most."""
    min_spread_sigmas: float = 0.0
    """Tracks whose plane normals turn by less than this many noise levels (RMS) are left
    out after the first round: nearly degenerate lines add little information and slow the
    convergence of long chains. 0 (default) keeps all: at high noise a threshold of a few
    noise levels throws away useful lines."""
    min_distance_ratio: float = 0.0
    """Tracks whose line passes this close to a camera that sees it, relative to the track's
    median camera-line distance, are left out of the final polish (0, the default: keep all).
    The camera then (nearly) lies on the line: the line's plane through it is undefined there
    and the residuals are so far from linear that the adjustment of a long chain crawls. Off
    by default: it costs a Fig. 12 trial from a wrong start lines it needs."""
    min_observations: int = 3
    """Tracks with fewer observations in the estimated frames take no part."""
    line_iterations: int = 2
    """Gauss-Newton iterations of each line alone after every step of the adjustment
    (:class:`LineProblem`; 0: none)."""


@dataclass(frozen=True)
class BundleResult:
    """Refined poses and lines.

    Attributes:
        rotations: ``(F, 3, 3)`` world_from_cam (NaN for frames not estimated).
        positions: ``(F, 3)`` camera centres in the world (NaN for frames not estimated); the
            world and the scale are those of the initial values (first estimated frame fixed;
            only its centre when held directions fix the rotation, module docstring).
        line_directions: ``(M, 3)`` unit directions (world; NaN for tracks not used).
        line_points: ``(M, 3)`` the point of each line closest to the world origin.
        frames: ``(F,)`` bool, frames estimated.
        used_tracks: ``(M,)`` bool, tracks in the final solve (not outliers, enough views).
        outlier_tracks: ``(M,)`` bool, tracks rejected as outliers.
        sigma_deg: robust estimate of the per-axis NV noise after the solve, degrees (of the
            median observation when the tracks carry uncertainties).
        track_rms_deg: ``(M,)`` RMS residual of each track at the solution as the adjustment
            weighs it (:func:`weighted_residuals`; all tracks, outliers included; NaN where the
            track has no line), degrees.
        rms_initial_deg: RMS (weighted, as ``track_rms_deg``) residual over the final inlier
            observations at the start.
        rms_final_deg: the same at the solution.
        iterations: LM iterations in all rounds.
        time_ms: wall time of the whole adjustment.
    """

    rotations: FloatArray
    positions: FloatArray
    line_directions: FloatArray
    line_points: FloatArray
    frames: np.ndarray
    used_tracks: np.ndarray
    outlier_tracks: np.ndarray
    sigma_deg: float
    track_rms_deg: FloatArray
    rms_initial_deg: float
    rms_final_deg: float
    iterations: int
    time_ms: float
    history: list[dict[str, float]] = field(default_factory=list)


def _tangent_basis(n: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors ``(..., 3)`` completing unit ``n`` to an orthonormal basis (the
    adjustment's residual and line-update axes: the helper axis switches at ``|n_x| = 0.6``)."""
    return orthonormal_completion(n, switch=0.6)


def _residual_basis(tracks: LineTracks) -> FloatArray:
    """``(K, 2, 3)``: rows ``b`` with residual ``e = b . n`` for each observation.

    Without sigmas: an orthonormal basis of the plane perpendicular to the observed normal
    (``|e|`` = sine of the angle between predicted and observed normal). With
    ``tracks.obs_sigma``: the directions along the observation's ray and across it, each divided
    by its standard deviation and multiplied by the median observation's (the geometric mean of
    its two), so that residuals stay in radians of a typical observation while each one counts
    by its own precision (the maximum-likelihood weighting).
    """
    n = tracks.obs_normal
    if tracks.obs_sigma is None or tracks.obs_ray is None:
        return np.stack(_tangent_basis(n), axis=1)
    m, t = completion_towards(n, tracks.obs_ray)
    sig = tracks.obs_sigma
    ref = float(np.median(np.sqrt(sig[:, 0] * sig[:, 1])))
    return np.stack([m * (ref / sig[:, :1]), t * (ref / sig[:, 1:])], axis=1)


def observation_centres(tracks: LineTracks, rotations: FloatArray, positions: FloatArray,
                        obs: np.ndarray | slice = slice(None)) -> FloatArray:
    """``(K, 3)`` the centre (world) that took each observation ``obs`` (indices or a mask
    over the tracks' observations): its frame's centre ``c_f``, or with lens offsets
    (``tracks.obs_offset``, in the units of ``positions``) ``c_f + R_f o``."""
    f = tracks.obs_frame[obs]
    c = positions[f]
    if tracks.obs_offset is None:
        return np.asarray(c)
    return np.asarray(c + np.einsum("kij,kj->ki", rotations[f], tracks.obs_offset[obs]))


def metric_offsets(tracks: LineTracks) -> bool:
    """Whether the tracks carry lens offsets that differ (a rig of lenses, in metres): the
    adjustment then holds no coordinate for the scale, which the baseline between the lenses
    fixes, and works in metres."""
    off = tracks.obs_offset
    return off is not None and len(off) > 0 and bool(np.any(off != off[0]))


def weighted_residuals(tracks: LineTracks, rotations: FloatArray, positions: FloatArray,
                       line_directions: FloatArray, line_points: FloatArray) -> FloatArray:
    """``(K,)`` residual norm of each observation as the adjustment weighs it (radians).

    Equal to :func:`observation_residuals` (for small errors) when the tracks carry no sigmas;
    otherwise the error in units of the median observation's standard deviation (times it).
    NaN where the frame's pose or the track's line is undefined.
    """
    f, t = tracks.obs_frame, tracks.obs_track
    u = predicted_normals(rotations[f], observation_centres(tracks, rotations, positions),
                          line_points[t], line_directions[t])
    e = np.einsum("kai,ki->ka", _residual_basis(tracks), normalize(u))
    return np.linalg.norm(e, axis=1)


def triangulate_lines(tracks: LineTracks, rotations: FloatArray, positions: FloatArray,
                      frames: np.ndarray | None = None,
                      min_observations: int = 2) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Lines from known poses: the 3D line lying closest to all the planes of its observations.

    Each observation in a frame ``k`` with pose ``(R_k, c_k)`` gives the world plane through
    ``c_k`` with normal ``R_k n``. The direction is the unit vector most orthogonal to all the
    normals (smallest eigenvector of ``sum n n^T``); the point solves ``n . x = n . c_k`` in least
    squares, with ``d . x = 0``.

    Returns ``(directions (M,3), points (M,3), ok (M,))``; not ok (NaN) where a track has fewer
    than ``min_observations`` observations in ``frames`` or its planes do not fix a line.
    """
    F, M = tracks.num_frames, tracks.num_tracks
    use = np.ones(F, bool) if frames is None else np.asarray(frames, bool)
    use = use & np.isfinite(positions).all(1) & np.isfinite(rotations).all((1, 2))
    sel = use[tracks.obs_frame]
    t, f = tracks.obs_track[sel], tracks.obs_frame[sel]
    n_w = np.einsum("kij,kj->ki", rotations[f], tracks.obs_normal[sel])
    cnt = np.bincount(t, minlength=M)
    A = np.zeros((M, 3, 3))
    np.add.at(A, t, n_w[:, :, None] * n_w[:, None, :])
    evals, evecs = np.linalg.eigh(A + np.eye(3) * 1e-300)
    d = evecs[:, :, 0]
    ok = (cnt >= max(2, min_observations)) & (evals[:, 1] > 1e-12 * np.maximum(evals[:, 2], 1e-300))
    # point: minimise sum (n.x - n.c)^2 subject to d.x = 0 via the normal equations + d d^T
    b = np.zeros((M, 3))
    centres = observation_centres(tracks, rotations, positions, sel)
    np.add.at(b, t, n_w * np.sum(n_w * centres, axis=1, keepdims=True))
    N = A + d[:, :, None] * d[:, None, :] * np.maximum(evals[:, 2:3, None], 1.0)
    with np.errstate(all="ignore"):
        p = np.linalg.solve(N[ok], b[ok][..., None])[..., 0] if ok.any() else np.zeros((0, 3))
    dirs = np.full((M, 3), np.nan)
    pts = np.full((M, 3), np.nan)
    dirs[ok], pts[ok] = d[ok], p - np.sum(p * d[ok], 1, keepdims=True) * d[ok]
    return dirs, pts, ok


def observation_residuals(tracks: LineTracks, rotations: FloatArray, positions: FloatArray,
                          line_directions: FloatArray, line_points: FloatArray) -> FloatArray:
    """``(K,)`` angle (radians, in [0, pi/2]) between each observed NV and the predicted one.

    NaN where the frame's pose or the track's line is undefined.
    """
    f, t = tracks.obs_frame, tracks.obs_track
    u = predicted_normals(rotations[f], observation_centres(tracks, rotations, positions),
                          line_points[t], line_directions[t])
    return unsigned_angle(normalize(u), tracks.obs_normal)


def truncated_cost(tracks: LineTracks, rotations: FloatArray, positions: FloatArray,
                   frames: np.ndarray, limit: float, *, everywhere: bool = False) -> float:
    """The mean over the observations in ``frames`` of ``min(angle, limit)^2`` (radians^2),
    every track's line triangulated from the poses (at least 3 observations): a score of a
    solution that does not depend on which tracks it rejected (a wrong solution rejects the
    tracks that disagree with it and fits the rest as well as the right one fits all).

    ``everywhere``: the mean over every observation of the sequence, those of the frames
    without a pose (not in ``frames``) at ``limit``: a score of solutions that pose different
    frames (a frame left out costs as much as a frame that fits none of its lines)."""
    cost = truncated_costs(tracks, rotations, positions, frames, limit)
    if not everywhere:
        cost = cost[frames[tracks.obs_frame]]
    return float(np.mean(cost))


def truncated_costs(tracks: LineTracks, rotations: FloatArray, positions: FloatArray,
                    frames: np.ndarray, limit: float) -> FloatArray:
    """``(K,)`` each observation's ``min(angle, limit)^2`` (:func:`truncated_cost`), those of
    the frames not in ``frames`` and of the tracks without a line at ``limit^2``."""
    d, p, ok = triangulate_lines(tracks, rotations, positions, frames, min_observations=3)
    ang = observation_residuals(tracks, rotations, positions, d, p)
    ang = np.where(ok[tracks.obs_track] & frames[tracks.obs_frame], ang, limit)
    return np.asarray(np.minimum(np.nan_to_num(ang, nan=limit), limit) ** 2)


_State = tuple[FloatArray, FloatArray, FloatArray, FloatArray]


def _pose_jacobian(R: FloatArray, d: FloatArray, u: FloatArray, B: FloatArray, *,
                   rt_skew_d: FloatArray | None = None,
                   norms: tuple[FloatArray, FloatArray] | None = None
                   ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per observation ``(A, J_rot, J_c)``: ``A = d e / d u`` ``(K, 2, 3)`` and the residual's
    derivatives ``(K, 2, 3)`` by the camera-frame rotation increment and by the centre.

    ``R`` ``(K, 3, 3)`` world_from_cam of each observation's frame, ``d`` ``(K, 3)`` its line's
    direction, ``u`` ``(K, 3)`` the unnormalised predicted normal, ``B`` ``(K, 2, 3)`` the
    residual basis: ``e = B normalise(u)``, ``u = R^T ((p - c) x d)``. Already formed, they
    need not be again (the same values as here): ``rt_skew_d``, ``R^T [d]x`` ``(K, 3, 3)``
    (``R`` is then not used); ``norms``, ``|u|`` ``(K,)`` and ``u / |u|`` ``(K, 3)``.
    """
    A = _normal_derivative(u, B, norms)
    if rt_skew_d is None:
        rt_skew_d = np.swapaxes(R, 1, 2) @ skew(d)
    return A, A @ skew(u), A @ rt_skew_d


def _normal_derivative(u: FloatArray, B: FloatArray,
                       norms: tuple[FloatArray, FloatArray] | None = None) -> FloatArray:
    """``A = d e / d u`` ``(K, 2, 3)`` of the residuals ``e = B normalise(u)`` (``norms``:
    ``|u|`` and ``u / |u|`` where already formed)."""
    if norms is None:
        nu = np.linalg.norm(u, axis=1)
        n = u / nu[:, None]
    else:
        nu, n = norms
    # d e / d u = B^T (I - n n^T) / |u|
    return (B - np.add.reduce(B * n[:, None, :], axis=2, keepdims=True) * n[:, None, :]) / \
        nu[:, None, None]


_Blocks = tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]


class _ReducedSystem:
    """The lines' reduced system ``S x = rhs`` once the poses are eliminated: ``S = diag(Hll) -
    G^T G``, ``rhs = -gl + G^T gpt`` (``Hll``, ``gl``: the ``Ma`` active lines' blocks; ``G``:
    one ``6x4`` block per observation, of frame ``f`` and active line ``tc``; ``gpt``: ``(F,
    6)``). :meth:`assemble` returns ``(S, None, rhs)`` with ``S`` dense where the lines are few
    or most pairs of them are seen together, else ``(None, S, rhs)`` with ``S`` the data of
    the block-sparse matrix (:meth:`csc` makes it a scipy matrix); :meth:`solve` solves it.

    Where at most 150 lines are seen in most frames (the paper's views), ``G`` is one dense
    matrix and ``G^T G`` one product (BLAS). Elsewhere each frame adds ``-G_a^T G_b`` for each
    pair of the observations it holds, in one compiled loop
    (:func:`omni_sfm.estimate.kernels.reduce_lines`): the work of the pairs that share a frame
    and no more. The sparse matrix's structure (the pairs of lines seen in a frame together,
    :func:`omni_sfm.estimate.kernels.block_pattern`) is worked out once here, for all the steps
    of an adjustment. The pairs are taken frame by frame, not a dense block per run of frames,
    which would also multiply the zeros of the pairs of lines seen in the run but not in one
    frame (docs/estimator.md, "Solver")."""

    def __init__(self, f: np.ndarray, tc: np.ndarray, F: int, Ma: int) -> None:
        self.f, self.tc, self.F, self.Ma = f, tc, F, Ma
        i4 = np.arange(4)
        ar = np.repeat(np.arange(Ma), 16)  # the block diagonal diag(Hll): rows, columns
        self.bd_flat = (4 * ar + np.tile(np.repeat(i4, 4), Ma)) * (4 * Ma) + \
            4 * ar + np.tile(i4, 4 * Ma)  # in the dense S, raveled
        small = 4 * Ma <= 600
        self.dense_g = small and len(f) > 0.3 * F * Ma  # most lines seen in most frames
        if self.dense_g:
            return
        self.index = kernels.PairIndex(f, tc, F, Ma)
        self.pattern: tuple[np.ndarray, np.ndarray] | None = None
        self.offsets: np.ndarray | None = None
        ptr, rows = kernels.block_pattern(self.index)
        # dense where the lines are few or most pairs of them are seen in a frame together
        self.dense = small or (Ma <= 3000 and len(rows) > 0.3 * Ma * Ma)
        if not self.dense:
            self.pattern = ptr, rows
            self.offsets = kernels.pair_offsets(self.index, self.pattern)
            # the factor's structure, once: a minimum-degree order of the lines (SuperLU's, on
            # the pattern of the lines' blocks; its perm_c lists, for each line, its place)
            P = sp.csc_matrix((np.ones(len(rows)), rows, ptr), shape=(Ma, Ma)) + \
                float(Ma) * sp.identity(Ma, format="csc")
            place = spla.splu(P, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                              options={"SymmetricMode": True}).perm_c
            self.cholesky = kernels.BlockCholesky(self.pattern, np.argsort(place))

    def assemble(self, Hll: FloatArray, G: FloatArray, gpt: FloatArray, gl: FloatArray
                 ) -> tuple[FloatArray | None, FloatArray | None, FloatArray]:
        f, tc, F, Ma = self.f, self.tc, self.F, self.Ma
        if self.dense_g:
            Gd = np.zeros((F, 6, Ma, 4))
            Gd[f, :, tc, :] = G
            Gm = Gd.reshape(6 * F, 4 * Ma)
            S_full = -(Gm.T @ Gm)
            S_full.reshape(-1)[self.bd_flat] += Hll.ravel()
            return S_full, None, -gl.ravel() + Gm.T @ gpt.ravel()
        S, rhs = kernels.reduce_lines(self.index, G, Hll, gpt, gl, self.pattern, self.offsets)
        if self.pattern is None:
            return S, None, rhs
        return None, S, rhs

    def solve(self, S: FloatArray | None, S_blocks: FloatArray | None, rhs: FloatArray
              ) -> FloatArray:
        """``S^-1 rhs`` for :meth:`assemble`'s output: dense Cholesky (LAPACK), or the block
        Cholesky factorisation in the structure worked out once (``kernels.BlockCholesky``).
        Raises ``numpy.linalg.LinAlgError`` where ``S`` is not positive definite."""
        if S is not None:
            c_f = scipy.linalg.cho_factor(S, check_finite=False)
            return np.asarray(scipy.linalg.cho_solve(c_f, rhs, check_finite=False))
        assert S_blocks is not None
        if not self.cholesky.factor(S_blocks):
            raise np.linalg.LinAlgError("reduced system not positive definite")
        return self.cholesky.solve(rhs)

    def csc(self, S_blocks: FloatArray) -> sp.csc_matrix:
        """The sparse :meth:`assemble`'s ``S`` as a scipy CSC matrix (for checks)."""
        assert self.pattern is not None
        ptr, rows = self.pattern
        Ma, i4 = self.Ma, np.arange(4)
        # block column j's column 4 j + c holds its block rows' 4 rows each: the rows
        # 4 rows[ptr[j]:ptr[j + 1]] + (0..3), once for each of its 4 columns
        length = np.repeat(4 * np.diff(ptr), 4)  # entries of each column
        indptr = np.zeros(4 * Ma + 1, np.int64)
        indptr[1:] = np.cumsum(length)
        source = np.arange(indptr[-1]) - np.repeat(indptr[:-1] - np.repeat(4 * ptr[:-1], 4),
                                                     length)
        indices = (4 * rows[:, None] + i4).ravel()[source]
        return sp.csc_matrix((S_blocks, indices, indptr), shape=(4 * Ma, 4 * Ma))


class LineProblem:
    """The LM problem on the active frames and tracks (everything else stays as given).

    Free parameters: 6 per estimated frame except the fixed one (whose 6 are held; its centre
    only when ``hold_rotation`` is False; its centre and its turn about the world direction
    ``turn_axis`` when that is given), minus the one held coordinate of the scale frame; 4
    per active track (2 for a line whose direction is held). Held parameters keep zero
    Jacobian columns and an identity block in the normal equations.

    With ``line_iterations`` > 0, every step tried (:meth:`retract`) is followed by that many
    Gauss-Newton iterations of each line alone, the poses as the step left them, under
    ``loss`` at ``loss_scale`` (the cost the LM measures): each line keeps an iteration only
    where its own cost falls, so the step's cost can only fall by them. These are the
    "embedded point iterations" of Jeong et al. (CVPR 2010), for lines: a line that the chain's
    poses left far from where they now put it (triangulated from drifted poses, swung through a
    camera) does not hold every step back. On the sparse simulation's adjustments they reach
    the LM's minima in a fraction of its iterations (docs/estimator.md, "Line bundle
    adjustment").
    """

    def __init__(self, tracks: LineTracks, frames: np.ndarray, active: np.ndarray,
                 fixed_frame: int, scale_frame: int, scale_axis: int,
                 held: np.ndarray | None = None,
                 held_directions: np.ndarray | None = None, hold_rotation: bool = True,
                 observations: np.ndarray | None = None, *, line_iterations: int = 0,
                 loss: RobustLoss = RobustLoss.LINEAR, loss_scale: float = 1.0,
                 held_rotations: np.ndarray | None = None, hold_scale: bool = True,
                 turn_axis: FloatArray | None = None) -> None:
        self.line_iterations, self.loss, self.loss_scale = line_iterations, loss, loss_scale
        self.fixed_frame = fixed_frame
        self.turn_axis = None if turn_axis is None or hold_rotation else \
            normalize(np.asarray(turn_axis, np.float64))
        """The world direction about which the fixed frame's turn is held (lines of one held
        direction fix the world's rotation but for the turn about it: holding the fixed
        frame's whole rotation as well would tie that direction to the frame, which frame
        is first then deciding the result)."""
        self._turn_basis: FloatArray | None = None
        """The fixed frame's rotation parameters' axes (camera frame, columns; the third along
        ``turn_axis``, held) at the last Jacobian."""
        self._basis: tuple[FloatArray, FloatArray, FloatArray] | None = None
        self._reduced: tuple[np.ndarray, _ReducedSystem] | None = None
        """The active lines and the reduced system's structure (:meth:`solve`)."""
        self._refit: tuple[_State, FloatArray, FloatArray] | None = None
        """The last state :meth:`retract` returned from the lines' own iterations, with its
        residuals and predicted normals (which :meth:`residuals` then need not compute
        again: the same values)."""
        F, M = tracks.num_frames, tracks.num_tracks
        sel = frames[tracks.obs_frame] & active[tracks.obs_track]
        if observations is not None:  # (K,) bool over the tracks' observations: those used
            sel &= observations
        self.F, self.M = F, M
        self.f = tracks.obs_frame[sel]
        self.t = tracks.obs_track[sel]
        self.B = _residual_basis(tracks)[sel]  # (K, 2, 3)
        self.offset = None if tracks.obs_offset is None else tracks.obs_offset[sel]
        """``(K, 3)`` lens offsets (camera frame, the problem's units) or None: with them each
        observation is taken as a camera of its own, at its frame's rotation and at
        :func:`observation_centres`, and the pose Jacobian follows by the chain rule."""
        pose_free = np.zeros((F, 6), bool)
        pose_free[frames] = True
        pose_free[fixed_frame, 3:] = False
        if hold_rotation:
            pose_free[fixed_frame, :3] = False
        elif self.turn_axis is not None:
            pose_free[fixed_frame, 2] = False  # in the axes of _turn_basis
        if hold_scale:  # (a rig's lens offsets in metres fix it otherwise)
            pose_free[scale_frame, 3 + scale_axis] = False
        if held is not None:
            pose_free[held] = False
        if held_rotations is not None:
            pose_free[held_rotations, :3] = False
        self.pose_free = pose_free
        self.line_free = np.repeat(np.asarray(active, bool)[:, None], 4, axis=1)
        if held_directions is not None:
            self.line_free[held_directions, :2] = False
        self._moved_frames, self._moved_tracks = pose_free.any(1), self.line_free.any(1)

    def residuals(self, R: FloatArray, c: FloatArray, d: FloatArray,
                  p: FloatArray) -> tuple[FloatArray, FloatArray]:
        if self._refit is not None:
            (R0, c0, d0, p0), e0, u0 = self._refit
            if R is R0 and c is c0 and d is d0 and p is p0:
                return e0, u0
        Rk, ck, fk = self._cameras(R, c)
        return kernels.residuals(Rk, ck, d, p, fk, self.t, self.B)

    def _cameras(self, R: FloatArray, c: FloatArray) -> tuple[FloatArray, FloatArray, np.ndarray]:
        """The kernels' cameras: the frames ``(R, c, f)``, or with lens offsets one camera per
        observation ``(R_f, c_f + R_f o, 0..K-1)``."""
        if self.offset is None:
            return R, c, self.f
        Rk = R[self.f]
        return Rk, c[self.f] + np.einsum("kij,kj->ki", Rk, self.offset), \
            np.arange(len(self.f))

    def jacobian(self, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
                 u: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Per observation: ``(K, 2, 6)`` d e / d pose and ``(K, 2, 4)`` d e / d line
        (:func:`_pose_jacobian`'s formulas, and the line moved along its tangent basis:
        :func:`omni_sfm.estimate.kernels.jacobians`)."""
        b1, b2 = self._basis_of(d)
        free = self.pose_free
        if self.turn_axis is not None:
            # the fixed frame's rotation moves along the axes of a basis whose third is the
            # held turn about the world direction (camera frame), by the columns' chain rule
            k = self.fixed_frame
            n = normalize(R[k].T @ self.turn_axis)
            self._turn_basis = np.stack([*orthonormal_completion(n), n], axis=1)
            free = free.copy()
            free[k, :3] = True
        if self.offset is None:
            Jp, Jl = kernels.jacobians(R, c, d, p, self.f, self.t, self.B, u, free,
                                       self.line_free, b1, b2)
        else:
            Jp, Jl = self._offset_jacobians(R, c, d, p, u, b1, b2)
        if self._turn_basis is not None:
            at = self.f == self.fixed_frame
            Jp[at, :, :3] = Jp[at, :, :3] @ self._turn_basis
        if self.offset is not None or self._turn_basis is not None:
            Jp *= self.pose_free[self.f][:, None, :]
        return Jp, Jl

    def _offset_jacobians(self, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
                          u: FloatArray, b1: FloatArray, b2: FloatArray
                          ) -> tuple[FloatArray, FloatArray]:
        """:meth:`jacobian` with lens offsets, every pose column kept."""
        # each observation's camera c_f + R_f o moves with the rotation increment w (R_f
        # exp(w)) by R_f (w x o) = -R_f [o]x w: its centre columns carry that into the
        # rotation's; held columns are zeroed after the chain rule
        assert self.offset is not None
        Rk, ck, fk = self._cameras(R, c)
        Jp, Jl = kernels.jacobians(Rk, ck, d, p, fk, self.t, self.B, u,
                                   np.ones((len(fk), 6), bool), self.line_free, b1, b2)
        Jp[:, :, :3] -= np.einsum("kac,kcd->kad", Jp[:, :, 3:], Rk @ skew(self.offset))
        return Jp, Jl

    def normal_equations(self, J_pose: FloatArray, J_line: FloatArray, e: FloatArray,
                         w: FloatArray) -> _Blocks:
        """Blocks of ``J^T W J`` and ``J^T W e``: (F,6,6), (M,4,4), (K,6,4), (F,6), (M,4)."""
        return kernels.normal_blocks(J_pose, J_line, e, w, self.f, self.t, self.F, self.M)

    def solve(self, blocks: _Blocks, lam: float) -> tuple[FloatArray, FloatArray]:
        """Damped step ``(H + lam diag(H)) dx = -g`` from :meth:`normal_equations`' blocks:
        poses eliminated (Schur complement).

        The pose blocks are 6x6 and independent; eliminating them leaves a ``4M x 4M`` system
        in the lines whose update ``G^T G`` (``G = L_f^-1 H_fl``, one 6x4 block per
        observation) is formed and solved by :class:`_ReducedSystem` (dense Cholesky, or
        the block Cholesky factorisation of ``kernels.BlockCholesky``).
        """
        Hpp, Hll, Hpl, gp, gl = blocks
        F, M, f, t = self.F, self.M, self.f, self.t
        pf, lf = self.pose_free, self.line_free
        # held parameters: identity rows/columns, so they stay at zero
        Hpp, Hll = damped(Hpp, lam, pf, _POSE_PARTS), damped(Hll, lam, lf, _LINE_PARTS)
        # Hpp = L L^T per frame; G = L_f^-1 Hpl (K, 6, 4), gpt = L^-1 g_p
        Linv, G, gpt = kernels.eliminate_poses(Hpp, Hpl, gp, f)
        # only the lines with observations enter the reduced system
        if self._reduced is None:
            act = np.flatnonzero(lf.any(1))
            self._reduced = act, _ReducedSystem(f, np.searchsorted(act, t), F, len(act))
        act, reduced = self._reduced
        Ma = len(act)
        x = reduced.solve(*reduced.assemble(Hll[act], G, gpt, gl[act]))
        dl = np.zeros((M, 4))
        dl[act] = x.reshape(Ma, 4)
        # back substitution: Hpp dp = -gp - Hpl dl
        dp = kernels.back_substitute(Linv, Hpl, gp, dl, f, t)
        return dp * pf, dl * lf

    def retract(self, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
                dpose: FloatArray, dline: FloatArray) -> _State:
        R2, c2, d2, p2 = self._moved(R, c, d, p, dpose, dline)
        if self.line_iterations > 0:
            d2, p2, e, u = self._refit_lines(R2, c2, d2, p2)
            self._refit = ((R2, c2, d2, p2), e, u)
        return R2, c2, d2, p2

    def _moved(self, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
               dpose: FloatArray, dline: FloatArray) -> _State:
        """The state moved by the step ``dpose`` ``(F, 6)``, ``dline`` ``(M, 4)``."""
        R2 = R.copy()
        moved = self._moved_frames
        if self._turn_basis is not None:
            dpose = dpose.copy()
            dpose[self.fixed_frame, :3] = self._turn_basis @ dpose[self.fixed_frame, :3]
        R2[moved] = R[moved] @ rotvec_to_matrix(dpose[moved, :3])
        c2 = c + dpose[:, 3:]
        d2, p2 = self._moved_lines(d, p, dline)
        return R2, c2, d2, p2

    def _moved_lines(self, d: FloatArray, p: FloatArray, dline: FloatArray
                     ) -> tuple[FloatArray, FloatArray]:
        """The lines ``d, p`` moved by ``dline`` ``(M, 4)``."""
        act = self._moved_tracks
        dl = dline[act]
        b1, b2 = self._basis_of(d)
        e1, e2 = b1[act], b2[act]
        d2, p2 = d.copy(), p.copy()
        d2[act] = normalize(d[act] + dl[:, :1] * e1 + dl[:, 1:2] * e2)
        q = p[act] + dl[:, 2:3] * e1 + dl[:, 3:4] * e2
        p2[act] = q - np.sum(q * d2[act], 1, keepdims=True) * d2[act]
        return d2, p2

    def _basis_of(self, d: FloatArray) -> tuple[FloatArray, FloatArray]:
        """:func:`_tangent_basis` of the lines' directions ``d`` ``(M, 3)``, kept for the last
        ``d`` (a step's Jacobian and its move start from the same lines)."""
        if self._basis is None or self._basis[0] is not d:
            self._basis = (d, *_tangent_basis(d))
        return self._basis[1], self._basis[2]

    def _refit_lines(self, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray
                     ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """``line_iterations`` Gauss-Newton iterations of each line alone at the poses ``R``,
        ``c`` (class docstring): each line's cost under the problem's loss, its step from
        ``H + mu diag(H)`` of its own observations (:func:`damped`, ``mu`` from 1e-6); an
        iteration that does not lower a line's cost is undone and that line damped tenfold
        more for the next; a singular system stops them all. Returns the lines ``d, p`` and
        the residuals and predicted normals there (:meth:`residuals`). One compiled loop over
        the observations (:func:`omni_sfm.estimate.kernels.refit_lines`)."""
        Rk, ck, fk = self._cameras(R, c)
        return kernels.refit_lines(Rk, ck, d, p, fk, self.t, self.B, self.line_free,
                                   str(self.loss), self.loss_scale, self.line_iterations)


def _initial_state(tracks: LineTracks, rotations: FloatArray, positions: FloatArray,
                   line_directions: FloatArray, line_points: FloatArray,
                   frames: np.ndarray | None) -> tuple[_State, np.ndarray]:
    """The starting point of the adjustment: float64 copies of the initial values, checked.

    Returns ``((R, c, d, p), frames)``: ``R`` ``(F, 3, 3)`` world_from_cam, ``c`` ``(F, 3)``
    camera centres, ``d`` ``(M, 3)`` unit line directions and ``p`` ``(M, 3)`` each line's point
    closest to the world origin (world units of the input); ``frames`` ``(F,)`` bool, the frames
    with a finite pose (among ``frames`` if given). Lines given as NaN are triangulated from the
    initial poses of those frames (NaN where that fails).

    Raises:
        ValueError: arrays of the wrong shape.
    """
    F, M = tracks.num_frames, tracks.num_tracks
    R = np.array(rotations, dtype=np.float64)
    c = np.array(positions, dtype=np.float64)
    if R.shape != (F, 3, 3) or c.shape != (F, 3):
        raise ValueError(f"poses must be ({F},3,3) and ({F},3); got {R.shape=} {c.shape=}")
    d = np.array(line_directions, dtype=np.float64)
    p = np.array(line_points, dtype=np.float64)
    if d.shape != (M, 3) or p.shape != (M, 3):
        raise ValueError(f"lines must be ({M},3); got {d.shape=} {p.shape=}")
    fr: np.ndarray = np.asarray(np.isfinite(c).all(1) & np.isfinite(R).all((1, 2)))
    if frames is not None:
        fr &= np.asarray(frames, bool)
    missing = ~(np.isfinite(d).all(1) & np.isfinite(p).all(1))
    if missing.any():
        d2, p2, ok = triangulate_lines(tracks, R, c, fr)
        d[missing], p[missing] = d2[missing], p2[missing]
    d = normalize(d)
    p = p - np.sum(p * d, 1, keepdims=True) * d
    return (R, c, d, p), fr


def outlier_limit(sigma: float, options: BundleOptions) -> float:
    """The RMS residual (radians) above which a track is an outlier, for per-axis noise
    ``sigma`` (radians)."""
    return max(options.outlier_threshold * np.sqrt(2.0) * sigma,
               float(np.radians(options.outlier_min_deg)))


def _directions_fix_rotation(d: FloatArray, held_directions: np.ndarray | None,
                             active: np.ndarray) -> bool:
    """Whether the active ``(M,)`` lines whose directions ``d`` ``(M, 3)`` are held
    (``held_directions`` ``(M,)`` bool) fix the world's rotation: two of them at least
    ``_MIN_GAUGE_ANGLE_DEG`` apart (one direction leaves the turn about it free)."""
    if held_directions is None:
        return False
    h = d[np.asarray(held_directions, bool) & active]
    if len(h) < 2:
        return False
    sines = np.linalg.norm(np.cross(h, h[0]), axis=1)
    return bool(sines.max() >= np.sin(np.radians(_MIN_GAUGE_ANGLE_DEG)))


def _held_axis(d: FloatArray, held_directions: np.ndarray | None, active: np.ndarray
               ) -> FloatArray | None:
    """The direction of the first active ``(M,)`` line whose direction ``d`` ``(M, 3)`` is held
    (``held_directions`` ``(M,)`` bool), or None: held in one direction only, they fix the
    world's rotation but for the turn about it (:class:`LineProblem`'s ``turn_axis``)."""
    if held_directions is None:
        return None
    h = np.flatnonzero(np.asarray(held_directions, bool) & active)
    return d[h[0]] if len(h) else None


def _new_outliers(active: np.ndarray, rms: FloatArray, sigma: float,
                  options: BundleOptions) -> np.ndarray:
    """``(M,)`` bool: the active tracks to reject in this round (none unless
    ``options.reject_outliers``).

    ``rms`` ``(M,)`` is each track's RMS weighted residual and ``sigma`` the per-axis noise
    (both radians). Of the tracks above ``outlier_threshold`` times the expected RMS
    (``sqrt(2) sigma``), only the gross ones (at least half the worst's RMS) are taken, as they
    bias the others' residuals; at most half the active tracks (the worst).
    """
    M = len(active)
    new_out = np.zeros(M, bool)
    if options.reject_outliers:
        cand = active & (rms > outlier_limit(sigma, options))
        if cand.any():
            worst = float(np.max(rms[cand]))
            new_out = cand & (rms >= 0.5 * worst)
            if new_out.sum() > 0.5 * active.sum():
                keep = np.argsort(-np.where(new_out, rms, -np.inf))[: int(0.5 * active.sum())]
                new_out = np.zeros(M, bool)
                new_out[keep] = True
    return new_out


class _Adjustment:
    """One bundle adjustment's state through its rounds.

    Attributes:
        R, c, d, p: current poses and lines: ``(F, 3, 3)`` world_from_cam, ``(F, 3)`` camera
            centres, ``(M, 3)`` unit line directions and ``(M, 3)`` line points (world units of
            the initial values).
        frames: ``(F,)`` bool, the estimated frames (each sees at least 3 active tracks).
        line_ok: ``(M,)`` bool, tracks with a (finite) line.
        outlier: ``(M,)`` bool, tracks currently rejected as outliers.
        weak: ``(M,)`` bool, tracks left out for their small plane spread or for passing
            through a camera (:class:`BundleOptions`).
        fixed, scale_frame, scale_axis: the gauge (:func:`gauge`).
        obs_in: ``(K,)`` bool, observations in the estimated frames.
        ang0: ``(K,)`` weighted residual norms (radians) at the start, NaN outside ``frames``.
        sigma: current per-axis NV noise, radians.
        iterations: LM iterations so far; history: one entry per solve.
    """

    def __init__(self, tracks: LineTracks, state: _State, frames: np.ndarray,
                 scale_frames: np.ndarray | None, options: BundleOptions,
                 held_frames: np.ndarray | None = None,
                 held_directions: np.ndarray | None = None,
                 held_rotations: np.ndarray | None = None) -> None:
        """Set up from :func:`_initial_state`'s output.

        Raises:
            OmniSfmError: fewer than 3 frames seeing 3 active tracks or more, or no scale.
        """
        self.tracks, self.options = tracks, options
        self.R, self.c, self.d, self.p = state
        self.frames = frames
        M = tracks.num_tracks
        self.line_ok = np.asarray(np.isfinite(self.d).all(1) & np.isfinite(self.p).all(1))
        self.outlier = np.zeros(M, bool)
        self.weak = np.zeros(M, bool)
        # frames need observations of active tracks to be determined
        act = self.active_tracks()
        per_frame = np.bincount(tracks.obs_frame[act[tracks.obs_track]],
                                minlength=tracks.num_frames)
        self.frames &= per_frame >= 3
        if self.frames.sum() < 3:
            raise OmniSfmError(f"bundle adjustment needs at least 3 frames that see 3 lines or "
                               f"more; got {int(self.frames.sum())}")
        self.held = None if held_frames is None else np.asarray(held_frames, bool) & self.frames
        self.held_directions = None if held_directions is None else \
            np.asarray(held_directions, bool)
        self.held_rotations = None if held_rotations is None else \
            np.asarray(held_rotations, bool)
        first_held = None if self.held is None or not self.held.any() else \
            int(np.flatnonzero(self.held)[0])
        self.fixed, self.scale_frame, self.scale_axis = gauge(self.c, self.frames, scale_frames,
                                                               first_held)
        self.metric = metric_offsets(tracks)
        """The tracks' lens offsets (metres) fix the scale: no coordinate is held for it."""
        self.obs_in = self.frames[tracks.obs_frame]
        self.ang0 = self.angles()
        self.sigma = np.radians(options.noise_deg) if options.noise_deg else \
            robust_sigma(self.ang0[act[tracks.obs_track] & self.obs_in])
        self.iterations = 0
        self.history: list[dict[str, float]] = []

    def active_tracks(self) -> np.ndarray:
        """``(M,)`` bool: tracks with a line, not rejected, with enough observations."""
        tracks = self.tracks
        cnt = np.bincount(tracks.obs_track[self.frames[tracks.obs_frame]],
                          minlength=tracks.num_tracks)
        return self.line_ok & ~self.outlier & ~self.weak & (cnt >= self.options.min_observations)

    def angles(self) -> FloatArray:
        """``(K,)`` weighted residual norms (radians) now; NaN outside the estimated frames."""
        a = np.full(self.tracks.num_observations, np.nan)
        a[self.obs_in] = weighted_residuals(self.tracks, self.R, self.c, self.d,
                                            self.p)[self.obs_in]
        return a

    def solve(self, active: np.ndarray, loss: RobustLoss, max_iterations: int,
              tolerance: float) -> int:
        """Run LM on the ``active`` ``(M,)`` tracks with the loss scaled to the current noise;
        returns the iterations it took."""
        scale = self.options.loss_scale * self.sigma
        fixes = _directions_fix_rotation(self.d, self.held_directions, active)
        axis = None if fixes else _held_axis(self.d, self.held_directions, active)
        prob = LineProblem(self.tracks, self.frames, active, self.fixed, self.scale_frame,
                           self.scale_axis, self.held, self.held_directions,
                           not fixes and axis is None,
                           line_iterations=self.options.line_iterations, loss=loss,
                           loss_scale=scale, held_rotations=self.held_rotations,
                           hold_scale=not self.metric, turn_axis=axis)
        (self.R, self.c, self.d, self.p), it = levenberg_marquardt(
            prob, (self.R, self.c, self.d, self.p), loss, scale, max_iterations, tolerance,
            decrease_tolerance=self.options.settled_decrease * self.sigma ** 2)
        self.iterations += it
        return it

    def readmit(self) -> np.ndarray:
        """``(M,)`` bool: rejected tracks that fit the current poses after all.

        Tracks rejected while the solution was still off may be fine: their lines are refitted
        to the current poses, and those whose RMS is now within the threshold get the refitted
        line back (``d``, ``p`` and ``line_ok`` updated in place).
        """
        tracks, o = self.tracks, self.options
        d2, p2, ok2 = triangulate_lines(tracks, self.R, self.c, self.frames, o.min_observations)
        ang2 = weighted_residuals(tracks, self.R, self.c, d2, p2)
        ang2[~self.obs_in] = np.nan
        rms2 = _track_rms(tracks, ang2, tracks.num_tracks)
        readmit = self.outlier & ok2 & (rms2 <= outlier_limit(self.sigma, o))
        if self.held_directions is not None:  # refitted freely: it would leave its direction
            readmit &= ~self.held_directions
        self.d[readmit], self.p[readmit] = d2[readmit], p2[readmit]
        self.line_ok[readmit] = True
        return readmit

    def robust_round(self, round_: int) -> bool:
        """One robust round: solve, re-estimate the noise, reject (or take back) outlier tracks.

        Returns True when it changed nothing (no track rejected or taken back, the noise
        estimate within 10 %): the rounds have converged.
        """
        tracks, o, M = self.tracks, self.options, self.tracks.num_tracks
        act = self.active_tracks()
        if not act.any():
            raise OmniSfmError("bundle adjustment: no track with enough observations remains")
        it = self.solve(act, o.loss, min(o.max_iterations, o.robust_iterations),
                        max(o.tolerance, o.robust_tolerance))
        ang = self.angles()
        old_sigma = self.sigma
        if not o.noise_deg:
            self.sigma = robust_sigma(ang[act[tracks.obs_track]])
        new_out = _new_outliers(act, _track_rms(tracks, ang, M), self.sigma, o)
        readmit = np.zeros(M, bool)
        if o.reject_outliers and self.outlier.any() and not new_out.any():
            readmit = self.readmit()
        self.history.append({"round": float(round_), "sigma_deg": float(np.degrees(self.sigma)),
                             "iterations": float(it), "new_outliers": float(new_out.sum()),
                             "readmitted": float(readmit.sum())})
        self.outlier = (self.outlier | new_out) & ~readmit
        if round_ == 0 and o.min_spread_sigmas > 0:
            # lines whose planes barely turn (seen along their own direction) fix almost
            # nothing but make the problem ill-conditioned: leave them out
            self.weak = act & (_plane_spread(tracks, self.R, self.frames, M)
                               < o.min_spread_sigmas * np.sqrt(2.0) * self.sigma)
        return bool(not new_out.any() and not readmit.any()
                    and abs(self.sigma - old_sigma) <= 0.1 * old_sigma)

    def polish(self, loss: RobustLoss) -> None:
        """The maximum-likelihood polish on the inliers (converges fast: no reweighting), the
        lines that pass through a camera left out (:class:`BundleOptions`)."""
        o, act = self.options, self.active_tracks()
        if o.min_distance_ratio > 0:
            ratio = camera_distance_ratio(self.tracks, self.R, self.c, self.d, self.p,
                                          self.obs_in, self.tracks.num_tracks)
            self.weak |= act & (ratio < o.min_distance_ratio)
        it = self.solve(self.active_tracks(), loss, o.max_iterations, o.tolerance)
        self.history.append({"round": -1.0, "sigma_deg": float(np.degrees(self.sigma)),
                             "iterations": float(it), "new_outliers": 0.0})

    def result(self, t0: float) -> BundleResult:
        """The :class:`BundleResult` now (``t0``: ``time.perf_counter()`` at the start)."""
        tracks = self.tracks
        act = self.active_tracks()
        ang = self.angles()
        used_obs = act[tracks.obs_track] & self.obs_in
        # a frame left with fewer than 3 active tracks (its others rejected) has no pose of
        # its own: its parameters only followed the damping
        seen = np.bincount(tracks.obs_frame[used_obs], minlength=tracks.num_frames)
        fr = self.frames & ((seen >= 3) if self.held is None else ((seen >= 3) | self.held))
        rms_final = float(np.degrees(np.sqrt(np.mean(ang[used_obs] ** 2))))
        rms_initial = float(np.degrees(np.sqrt(np.nanmean(self.ang0[used_obs] ** 2))))
        # the noise at the solution (the last robust round's estimate is of its own state,
        # which the rounds' stopping leaves wherever their path put it)
        sigma = self.sigma if self.options.noise_deg or not act.any() else \
            robust_sigma(ang[act[tracks.obs_track]])
        R_out = np.where(fr[:, None, None], self.R, np.nan)
        c_out = np.where(fr[:, None], self.c, np.nan)
        return BundleResult(R_out, c_out, np.where(act[:, None], self.d, np.nan),
                            np.where(act[:, None], self.p, np.nan), fr, act, self.outlier,
                            float(np.degrees(sigma)),
                            np.degrees(_track_rms(tracks, ang, tracks.num_tracks)),
                            rms_initial, rms_final, self.iterations,
                            (time.perf_counter() - t0) * 1e3, self.history)


def bundle_adjust(tracks: LineTracks, rotations: FloatArray, positions: FloatArray,
                  line_directions: FloatArray, line_points: FloatArray, *,
                  frames: np.ndarray | None = None,
                  scale_frames: np.ndarray | None = None,
                  held_frames: np.ndarray | None = None,
                  held_directions: np.ndarray | None = None,
                  held_rotations: np.ndarray | None = None,
                  options: BundleOptions = BundleOptions()) -> BundleResult:
    """Refine poses and lines jointly from all observations (partial tracks allowed).

    Robust rounds (:meth:`_Adjustment.robust_round`) until nothing changes or
    ``options.max_rounds``, then the polish with ``options.final_loss`` on the inliers.

    Args:
        tracks: the observations; only (track, frame) pairs present give residuals.
        rotations: ``(F, 3, 3)`` initial world_from_cam.
        positions: ``(F, 3)`` initial camera centres.
        line_directions: ``(M, 3)`` initial unit line directions (world); NaN rows: tracks that
            take no part (they are triangulated from the initial poses if possible).
        line_points: ``(M, 3)`` a point of each initial line (world).
        frames: ``(F,)`` bool, the frames to estimate (default: all with finite poses).
        scale_frames: ``(F,)`` bool, frames among which the one that holds the scale is chosen
            (default: all); e.g. the already refined part of a growing chain.
        held_frames: ``(F,)`` bool, estimated frames whose poses are held as given (anchors of
            a local adjustment: their observations fix the lines they share with the others).
        held_directions: ``(M,)`` bool, lines whose directions are held as given (members of a
            parallel family whose world direction is fixed: only their positions move). Held in
            two directions or more, they fix the rotation gauge: the first frame's rotation is
            then estimated too.
        held_rotations: ``(F,)`` bool, frames whose rotations are held as given (referred to
            fixed world directions elsewhere: the online tracker's); their positions move.
        options: see :class:`BundleOptions`.

    Raises:
        OmniSfmError: fewer than 3 estimable frames or no usable track.
    """
    t0 = time.perf_counter()
    state, fr = _initial_state(tracks, rotations, positions, line_directions, line_points, frames)
    F, M = tracks.num_frames, tracks.num_tracks
    obs = np.flatnonzero(fr[tracks.obs_frame])
    lines = np.unique(tracks.obs_track[obs])
    keep = np.flatnonzero(fr)
    if 2 * len(keep) < F or 2 * len(lines) < M:
        # a few frames of a long sequence (a new start, a join): the problem on those frames
        # and the tracks they see alone, so that its cost does not grow with the sequence
        sub = bundle_adjust(tracks.subset(obs, lines, keep), *_state_rows(state, keep, lines),
                            scale_frames=_rows(scale_frames, keep),
                            held_frames=_rows(held_frames, keep),
                            held_directions=_rows(held_directions, lines),
                            held_rotations=_rows(held_rotations, keep), options=options)
        return replace(scattered(sub, keep, lines, F, M),
                       time_ms=(time.perf_counter() - t0) * 1e3)
    adj = _Adjustment(tracks, state, fr, scale_frames, options, held_frames, held_directions,
                      held_rotations)
    for round_ in range(max(1, options.max_rounds)):
        if adj.robust_round(round_):
            break
    if options.final_loss is not None:
        adj.polish(options.final_loss)
    return adj.result(t0)


def polished(tracks: LineTracks, res: BundleResult, *,
             held_directions: np.ndarray | None = None,
             options: BundleOptions = BundleOptions()) -> BundleResult:
    """``res``, an adjustment run without a polish (``final_loss=None``: its robust rounds'
    result), polished with ``options.final_loss`` on the tracks it used (the others, its
    outliers among them, take no part; their lines are triangulated from its poses for their
    residuals). An adjustment started several ways (:func:`~omni_sfm.estimate.
    global_estimator._adjusted`) runs each start's robust rounds, which find the basin and the
    outliers, and polishes one start per set of tracks kept. No subset of the sequence is
    taken (its cost follows the whole of ``tracks``)."""
    if options.final_loss is None:
        return res
    t0 = time.perf_counter()
    used = res.used_tracks
    d2, p2, _ = triangulate_lines(tracks, res.rotations, res.positions, res.frames)
    d = np.where(used[:, None], res.line_directions, d2)
    p = np.where(used[:, None], res.line_points, p2)
    adj = _Adjustment(tracks, (res.rotations.copy(), res.positions.copy(), d, p),
                      res.frames.copy(), None, options, held_directions=held_directions)
    adj.outlier = res.outlier_tracks.copy()
    adj.weak = ~used & ~res.outlier_tracks
    adj.polish(options.final_loss)
    out = adj.result(t0)
    return replace(out, rms_initial_deg=res.rms_initial_deg,
                   iterations=res.iterations + out.iterations,
                   time_ms=res.time_ms + out.time_ms, history=[*res.history, *out.history])


def _state_rows(state: _State, frames: np.ndarray, lines: np.ndarray
                ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The poses of ``frames`` and the lines ``lines`` of ``state``."""
    R, c, d, p = state
    return R[frames], c[frames], d[lines], p[lines]


def _rows(a: np.ndarray | None, idx: np.ndarray) -> np.ndarray | None:
    return None if a is None else np.asarray(a, bool)[idx]


def scatter_rows(a: np.ndarray, at: np.ndarray | slice, size: int, fill: Any) -> np.ndarray:
    """``a`` placed at rows ``at`` of an array of ``size`` rows filled with ``fill``."""
    out = np.full((size, *a.shape[1:]), fill, dtype=a.dtype)
    out[at] = a
    return out


def scattered(res: BundleResult, frames: np.ndarray | None, lines: np.ndarray, F: int,
              M: int) -> BundleResult:
    """``res``, an adjustment of the frames ``frames`` (None: all ``F``) and the tracks
    ``lines`` alone, in the indices of the whole sequence (``F`` frames, ``M`` tracks; NaN or
    False elsewhere)."""
    def rows(a: np.ndarray, fill: Any) -> np.ndarray:
        return a if frames is None else scatter_rows(a, frames, F, fill)

    def tracks(a: np.ndarray, fill: Any) -> np.ndarray:
        return scatter_rows(a, lines, M, fill)

    return replace(res, rotations=rows(res.rotations, np.nan),
                   positions=rows(res.positions, np.nan), frames=rows(res.frames, False),
                   line_directions=tracks(res.line_directions, np.nan),
                   line_points=tracks(res.line_points, np.nan),
                   used_tracks=tracks(res.used_tracks, False),
                   outlier_tracks=tracks(res.outlier_tracks, False),
                   track_rms_deg=tracks(res.track_rms_deg, np.nan))


def _plane_spread(tracks: LineTracks, R: FloatArray, frames: np.ndarray, M: int) -> FloatArray:
    """``(M,)`` RMS angle (rad) by which each track's world plane normals turn about its line."""
    sel = frames[tracks.obs_frame]
    t = tracks.obs_track[sel]
    n_w = np.einsum("kij,kj->ki", R[tracks.obs_frame[sel]], tracks.obs_normal[sel])
    A = np.zeros((M, 3, 3))
    np.add.at(A, t, n_w[:, :, None] * n_w[:, None, :])
    cnt = np.maximum(np.bincount(t, minlength=M), 1)
    ev = np.linalg.eigvalsh(A)
    return np.arcsin(np.sqrt(np.clip(ev[:, 1] / cnt, 0.0, 1.0)))


def observation_distance_ratio(tracks: LineTracks, R: FloatArray, c: FloatArray,
                               d: FloatArray, p: FloatArray, obs: np.ndarray) -> FloatArray:
    """``(K,)`` for each observation of ``obs`` ``(K,)`` bool over all of ``tracks``'
    observations (NaN elsewhere): the distance between its line and its camera over the
    median one of the track's observations in ``obs``. Near 0: the camera nearly lies on the
    line, where the plane through them turns fast with either (far from the linear model)."""
    out = np.full(tracks.num_observations, np.nan)
    k = np.flatnonzero(obs)
    f, t = tracks.obs_frame[k], tracks.obs_track[k]
    dist = np.linalg.norm(predicted_normals(R[f], observation_centres(tracks, R, c, k), p[t],
                                            d[t]), axis=1)
    ok = np.isfinite(dist)
    if not ok.any():
        return out
    k, t, dist = k[ok], t[ok], dist[ok]
    order = np.lexsort((dist, t))
    k, t, dist = k[order], t[order], dist[order]
    starts = np.flatnonzero(np.r_[True, t[1:] != t[:-1]])
    counts = np.diff(np.r_[starts, len(t)])
    med = 0.5 * (dist[starts + (counts - 1) // 2] + dist[starts + counts // 2])
    with np.errstate(invalid="ignore", divide="ignore"):
        out[k] = dist / np.repeat(med, counts)
    return out


def camera_distance_ratio(tracks: LineTracks, R: FloatArray, c: FloatArray, d: FloatArray,
                          p: FloatArray, obs: np.ndarray, M: int) -> FloatArray:
    """``(M,)`` the smallest distance between a track's line and the cameras that see it
    (observations ``obs``) over the median one; NaN for tracks without observations."""
    ratio = observation_distance_ratio(tracks, R, c, d, p, obs)
    ok = np.isfinite(ratio)
    out = np.full(M, np.inf)
    np.minimum.at(out, tracks.obs_track[ok], ratio[ok])
    out[np.isinf(out)] = np.nan
    return out


def _track_rms(tracks: LineTracks, ang: FloatArray, M: int) -> FloatArray:
    ok = np.isfinite(ang)
    cnt = np.bincount(tracks.obs_track[ok], minlength=M)
    ss = np.bincount(tracks.obs_track[ok], weights=ang[ok] ** 2, minlength=M)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, np.sqrt(ss / np.maximum(cnt, 1)), np.nan)


def oracle(tracks: LineTracks, rotations: FloatArray, positions: FloatArray,
           line_directions: FloatArray, line_points: FloatArray, *,
           options: BundleOptions = BundleOptions(reject_outliers=False)) -> BundleResult:
    """The maximum-likelihood floor: the same least squares started from the ground truth.

    Pass the true poses (world_from_cam) and the true lines (world) of the clean tracks; the
    result is the best estimate the data allows with this cost, the reference the estimator's
    errors are compared against.
    """
    return bundle_adjust(tracks, rotations, positions, line_directions, line_points,
                         options=options)


def resect_pose(normals: FloatArray, line_directions: FloatArray, line_points: FloatArray,
                rotation: FloatArray, position: FloatArray, *, scale: float,
                iterations: int = 10, direction_normals: FloatArray | None = None,
                directions: FloatArray | None = None
                ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The pose of one camera from lines known in 3D (absolute pose from lines).

    Minimises the adjustment's residual (module docstring) over the 6 pose parameters with the
    lines held, from ``rotation`` (world_from_cam) and ``position``, by Levenberg-Marquardt with
    a Huber loss of ``scale`` (radians; ``inf``: plain least squares), as
    :func:`~omni_sfm.solver.levenberg_marquardt` runs it (compiled: :func:`~omni_sfm.estimate.
    kernels.resect`). ``normals`` ``(K, 3)``
    are the camera's observed NVs of the lines ``line_directions``, ``line_points`` ``(K, 3)``
    (world). ``direction_normals`` ``(J, 3)``: observed NVs of lines of which only the world
    direction ``directions`` ``(J, 3)`` is known (a parallel family's): they constrain the
    rotation only.

    Returns ``(R, c, angles)``: the pose and the ``(K,)`` angles (radians) between observed and
    predicted normals at it, followed by the ``(J,)`` angles of the direction-only normals out
    of the planes orthogonal to their directions.
    """
    n_obs = normalize(np.asarray(normals, np.float64))
    d, p = np.asarray(line_directions, np.float64), np.asarray(line_points, np.float64)
    m = np.zeros((0, 3)) if direction_normals is None else \
        normalize(np.asarray(direction_normals, np.float64))
    D = np.zeros((0, 3)) if directions is None else np.asarray(directions, np.float64)
    loss = RobustLoss.HUBER if np.isfinite(scale) else RobustLoss.LINEAR
    # one compiled loop (kernels.resect): in numpy, the per-call overhead on a few dozen lines
    # was most of the online tracker's time a frame
    R, c, e, u = kernels.resect(np.stack(_tangent_basis(n_obs), axis=1), d, p, m, D,
                                rotation, position, str(loss), scale, iterations, 1e-10)
    ang = unsigned_angle(normalize(u), n_obs)
    if len(m):
        ang = np.concatenate([ang, np.arcsin(np.clip(np.abs(e[len(d):, 0]), 0.0, 1.0))])
    return R, c, ang


def side_votes(tracks: LineTracks, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
               frames: np.ndarray, used: np.ndarray) -> tuple[int, int]:
    """How many observations see their 3D line in front of / behind the camera.

    For each observation with a ray (``tracks.obs_ray``, from its lens's centre: see
    :func:`observation_centres`) of an estimated frame and a used line: the sign of the depth
    along the ray of its closest approach to the line. ``(0, 0)`` when the tracks carry no
    rays. ``R (F,3,3)`` world_from_cam, ``c (F,3)`` centres, ``d, p (M,3)``
    line directions and points (world).
    """
    if tracks.obs_ray is None:
        return 0, 0
    t, f = tracks.obs_track, tracks.obs_frame
    ok = frames[f] & used[t]
    if not ok.any():
        return 0, 0
    t, f = t[ok], f[ok]
    w = np.einsum("kij,kj->ki", R[f], tracks.obs_ray[ok])
    depth, _, den = ray_line_closest(observation_centres(tracks, R, c, np.flatnonzero(ok)), w,
                                     p[t], d[t])
    depth = depth[den > 1e-6]  # a ray along its own line says nothing
    return int(np.sum(depth > 0)), int(np.sum(depth < 0))
