"""Rotations of all frames at once (docs/estimator.md, "Global estimator", step 1).

A line's plane through a camera contains the line: its world normal ``m = R_k n`` is
perpendicular to the line's direction ``d`` whatever the camera's position (eq. 11 of the
paper, for every frame and line at once). So the rotations ``R_k`` (world_from_cam) and the
lines' directions follow from one least-squares problem over all observations,

    min  sum_obs  rho( ((R_k n_ik) . d_i / s_ik)^2 )

independent of the translations. Lines of one parallel family share one direction (a world
direction: the vertical, a corridor's axis), so a frame's rotation is tied to the same few world
directions as every other frame's, and rotation error does not accumulate along the video. The
gauge is the rotation of the frame whose lines fix it best (:func:`gauge_frame`), whose camera is
the solution's world. A frame whose lines all have one direction keeps one degree of freedom
free (the turn about that direction): its information says so
(:attr:`GlobalRotations.frame_information`). A line of a direction of its own enters only where
a frame needs it (:func:`_needed_groups`).

The start comes from consecutive frames: the normals a line shows in two neighbouring frames
differ by the rotation between them and a small parallax, so a weighted Procrustes alignment of
the shared normals gives each step; the joint problem then removes the parallax's bias and the
drift of that chain. The start follows the frame order; the joint problem's minimum does not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.rotation_only import procrustes
from omni_sfm.geometry import (
    FloatArray,
    cross3,
    orthonormal_completion,
    rotvec_to_matrix,
    smallest_eigenvector,
)
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.solver import isotropic_diagonal


@dataclass(frozen=True, kw_only=True)
class GlobalRotationOptions:
    max_iterations: int = 300
    """Gauss-Newton (Levenberg-Marquardt) iterations of the joint problem at most."""
    tolerance: float = 1e-9
    """Stop when the relative decrease of the cost falls below this. The re-weighted solve
    converges linearly (its cost's decrease halves every few iterations, each a full sparse
    factorisation): going on from 1e-9 to 1e-12 costs 40-200 iterations on a 5,000-frame walk
    and moves no frame that the data fix by more than 0.00001 deg."""
    loss_scale: float = 3.0
    """Cauchy loss scale, in units of the robust noise estimate of the residuals."""
    every_line: bool = False
    """Every line of a direction of its own in the problem, not only those a frame needs
    (:func:`_needed_groups`): a start solved from scratch (a window of the windows' start)
    has to come through turns that the shared directions cannot tell apart (180 deg about one
    of them fits them as well), and those lines carry the frames' continuity through them."""


@dataclass(frozen=True)
class GlobalRotations:
    """The rotations of all frames and the directions of all lines.

    Attributes:
        rotations: ``(F, 3, 3)`` world_from_cam, the world the gauge frame's camera
            (:func:`gauge_frame`: its rotation the identity); NaN for frames without a rotation.
        directions: ``(M, 3)`` unit line directions in the world (one per group), NaN for
            lines not used.
        frames: ``(F,)`` bool, frames with a rotation.
        frame_information: ``(F,)`` the smallest eigenvalue of each frame's 3x3 information
            block (the lines' directions held): 0 where a rotation is free.
        free_axis: ``(F, 3)`` the world axis of each frame's least determined turn (the
            eigenvector of ``frame_information``).
        sigma: robust noise estimate of the residuals ``(R n) . d`` (radians).
        iterations: iterations of the joint problem.
    """

    rotations: FloatArray
    directions: FloatArray
    frames: np.ndarray
    frame_information: FloatArray
    free_axis: FloatArray
    sigma: float
    iterations: int


def _sign_aligned(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a`` with each row's sign flipped to agree with ``b``'s row."""
    s = np.sign(np.einsum("ij,ij->i", a, b))
    s[s == 0] = 1.0
    return a * s[:, None]


def chained_start(tracks: LineTracks, frames: np.ndarray) -> FloatArray:
    """Start rotations ``(F, 3, 3)``: each frame turned from the previous posed one by the
    Procrustes rotation of the normals the two share (identity where they share fewer than 2
    non-parallel ones)."""
    F, M = tracks.num_frames, tracks.num_tracks
    slot = np.full((M, F), -1)
    slot[tracks.obs_track, tracks.obs_frame] = np.arange(tracks.num_observations)
    R = np.tile(np.eye(3), (F, 1, 1))
    idx = np.flatnonzero(frames)
    for a, b in zip(idx[:-1], idx[1:], strict=True):
        both = (slot[:, a] >= 0) & (slot[:, b] >= 0)
        na = tracks.obs_normal[slot[both, a]]
        nb = _sign_aligned(tracks.obs_normal[slot[both, b]], na)
        step = np.eye(3)
        if len(na) >= 2 and np.linalg.svd(na, compute_uv=False)[1] > 1e-3:
            # rotation cam_a_from_cam_b: maps b's normals onto a's
            step = procrustes(nb, na, np.ones(len(na)))
        R[b] = R[a] @ step
    return R


def world_normals(tracks: LineTracks, R: FloatArray, ok: np.ndarray) -> FloatArray:
    """``(K', 3)`` the world normals ``R_k n`` of the observations ``ok`` ``(K,)`` bool."""
    return np.asarray(np.einsum("kij,kj->ki", R[tracks.obs_frame[ok]], tracks.obs_normal[ok]))


def group_directions(tracks: LineTracks, R: FloatArray, frames: np.ndarray,
                     group: np.ndarray) -> FloatArray:
    """``(G, 3)`` each group's direction: the unit vector most nearly perpendicular to the
    world normals of its tracks in the posed ``frames`` (smallest eigenvector of their
    scatter)."""
    ok = frames[tracks.obs_frame] & (group[tracks.obs_track] >= 0)
    m = world_normals(tracks, R, ok)
    S = np.zeros((int(group.max()) + 1, 3, 3))
    np.add.at(S, group[tracks.obs_track[ok]], m[:, :, None] * m[:, None, :])
    return smallest_eigenvector(S)


def _robust_sigma(r: FloatArray) -> float:
    return float(1.4826 * np.median(np.abs(r))) if len(r) else 0.0


def gauge_frame(tracks: LineTracks, frames: np.ndarray, lines: np.ndarray) -> int:
    """The frame to hold as a joint problem's gauge: of the ``frames`` ``(F,)``, the one whose
    normals of the ``lines`` ``(M,)`` fix its rotation best (the largest smallest eigenvalue of
    their scatter), which does not depend on the frames' order (the first frame would: from a
    start far from the minimum, which minimum the solver reaches can follow the gauge)."""
    obs = frames[tracks.obs_frame] & lines[tracks.obs_track]
    n, f = tracks.obs_normal[obs], tracks.obs_frame[obs]
    S = np.zeros((tracks.num_frames, 3, 3))
    np.add.at(S, f, n[:, :, None] * n[:, None, :])
    posed = np.flatnonzero(frames)
    low = np.linalg.eigvalsh(S[posed])[:, 0]
    return int(posed[int(np.argmax(low))])


class _RotationProblem:
    """The joint problem's residuals, Jacobian and normal equations (sparse). The unknowns are
    the posed frames' rotations but the gauge frame's (:func:`gauge_frame`) and one direction
    per group of lines (``group`` ``(M,)``: the direction variable of each track, -1 for tracks
    left out)."""

    def __init__(self, tracks: LineTracks, frames: np.ndarray, group: np.ndarray) -> None:
        obs = frames[tracks.obs_frame] & (group[tracks.obs_track] >= 0)
        self.n = tracks.obs_normal[obs]
        self.f = tracks.obs_frame[obs]
        self.t = group[tracks.obs_track[obs]]
        self.F = tracks.num_frames
        pose_idx = np.full(self.F, -1)
        posed = np.flatnonzero(frames)
        self.gauge = gauge_frame(tracks, frames, group >= 0)
        free = posed[posed != self.gauge]
        pose_idx[free] = np.arange(len(free))
        self.pose_idx = pose_idx
        self.num_pose, self.num_line = len(posed) - 1, int(group.max()) + 1
        # the directions' columns after the rotations', the shared ones (a world direction's
        # many lines) last: eliminated in this order the rotations (independent 3x3 blocks given
        # the directions) leave fill only among directions seen by one frame, and a shared
        # direction fills nothing before it (:func:`_factor`)
        size = np.bincount(self.t, minlength=self.num_line)
        first = np.full(self.num_line, self.F)
        np.minimum.at(first, self.t, self.f)
        self.line_idx = np.empty(self.num_line, int)
        self.line_idx[np.lexsort((first, size > 1 + 3 * np.median(size)))] = \
            np.arange(self.num_line)

    def residuals(self, R: FloatArray, d: FloatArray) -> FloatArray:
        m = np.einsum("kij,kj->ki", R[self.f], self.n)
        return np.asarray(np.einsum("ki,ki->k", m, d[self.t]))

    def normal_equations(self, R: FloatArray, d: FloatArray, w: FloatArray
                         ) -> tuple[sp.csc_matrix, FloatArray, FloatArray, FloatArray]:
        m = np.einsum("kij,kj->ki", R[self.f], self.n)
        dt = d[self.t]
        r = np.einsum("ki,ki->k", m, dt)
        # d/d(delta) of (R exp([delta]) n) . d = delta . (n x R^T d)
        Jp = cross3(self.n, np.einsum("kji,kj->ki", R[self.f], dt))
        e1, e2 = orthonormal_completion(d)
        Jl = np.stack([np.einsum("ki,ki->k", m, e1[self.t]),
                       np.einsum("ki,ki->k", m, e2[self.t])], axis=1)
        P = self.num_pose * 3
        pc = self.pose_idx[self.f]
        lc = P + 2 * self.line_idx[self.t]
        has_pose = pc >= 0
        cols = np.concatenate([np.where(has_pose[:, None], 3 * pc[:, None] + np.arange(3), -1),
                               lc[:, None] + np.arange(2)], axis=1)
        J = np.concatenate([Jp, Jl], axis=1)
        keep = cols >= 0
        rows = np.broadcast_to(np.arange(len(r))[:, None], cols.shape)
        N = P + 2 * self.num_line
        Jm = sp.csr_matrix((J[keep], (rows[keep], cols[keep])), shape=(len(r), N))
        Wm = sp.diags(w)
        H = (Jm.T @ Wm @ Jm).tocsc()
        g = Jm.T @ (w * r)
        return H, np.asarray(g), r, self._isotropic(np.asarray(H.diagonal()))

    def _isotropic(self, diag: FloatArray) -> FloatArray:
        """The diagonal with each rotation's 3 entries and each direction's 2 their mean
        (:func:`~omni_sfm.solver.isotropic_diagonal`): the damping then does not depend on the
        directions' tangent bases, and so on the world's orientation."""
        P = self.num_pose * 3
        return np.concatenate([isotropic_diagonal(diag[:P].reshape(-1, 3), (3,)).ravel(),
                               isotropic_diagonal(diag[P:].reshape(-1, 2), (2,)).ravel()])

    def retract(self, R: FloatArray, d: FloatArray, step: FloatArray) -> tuple[FloatArray,
                                                                              FloatArray]:
        P = self.num_pose * 3
        R2 = R.copy()
        posed = np.flatnonzero(self.pose_idx >= 0)
        dp = step[:P].reshape(-1, 3)
        R2[posed] = R[posed] @ rotvec_to_matrix(dp[self.pose_idx[posed]])
        d2 = d.copy()
        used = np.flatnonzero(self.line_idx >= 0)
        e1, e2 = orthonormal_completion(d[used])
        dl = step[P:].reshape(-1, 2)[self.line_idx[used]]
        nd = d[used] + dl[:, :1] * e1 + dl[:, 1:] * e2
        d2[used] = nd / np.linalg.norm(nd, axis=1, keepdims=True)
        return R2, d2


def _factor(A: sp.spmatrix) -> spla.SuperLU:
    """The LU factorisation of the damped normal equations ``A`` (symmetric positive definite)
    in the order of their columns (:class:`_RotationProblem`: the rotations first, then the
    directions, the shared ones last): the Schur complement on the directions, with no pivoting
    (the diagonal is the pivot of a positive definite matrix). A fill-reducing reordering finds
    nothing better, at three to ten times the cost on a 600-frame walk."""
    return spla.splu(sp.csc_matrix(A), permc_spec="NATURAL", diag_pivot_thresh=0.0,
                     options={"SymmetricMode": True})


def _cauchy_weights(r: FloatArray, scale: float) -> FloatArray:
    return np.asarray(1.0 / (1.0 + (r / scale) ** 2))


def _cost(r: FloatArray, scale: float) -> float:
    return float(0.5 * scale**2 * np.sum(np.log1p((r / scale) ** 2)))


_HELD_LINES = 2
"""A frame is held by the shared directions when it sees this many lines of each of two of
them (:func:`_needed_groups`)."""


def _needed_groups(tracks: LineTracks, frames: np.ndarray, group: np.ndarray) -> np.ndarray:
    """``group`` ``(M,)`` without the lines of a direction of their own (groups of one track)
    that no frame needs: a frame that sees :data:`_HELD_LINES` lines of each of two shared
    directions (groups of several tracks) is held by them; a line of its own direction is
    kept where it is seen in a frame that is not. Such a line adds little where the frame is
    held, and its direction, weakly fixed where its planes barely turn, makes the robust solve
    crawl (docs/estimator.md, step 1). The choice counts lines; it does not depend on the
    start. Returned renumbered from 0 (-1: left out)."""
    M, F = tracks.num_tracks, tracks.num_frames
    size = np.bincount(group[group >= 0], minlength=int(group.max()) + 1)
    shared = (group >= 0) & (size[np.maximum(group, 0)] > 1)
    obs = frames[tracks.obs_frame] & shared[tracks.obs_track]
    key = tracks.obs_frame[obs].astype(np.int64) * len(size) + group[tracks.obs_track[obs]]
    pair, count = np.unique(key, return_counts=True)
    held = np.bincount(pair[count >= _HELD_LINES] // len(size), minlength=F) >= 2
    needed = np.zeros(M, bool)
    needed[tracks.obs_track[(frames & ~held)[tracks.obs_frame]]] = True
    kept = np.where(shared | needed, group, -1)
    out = np.full(M, -1)
    out[kept >= 0] = np.unique(kept[kept >= 0], return_inverse=True)[1]
    return out


def solve_rotations(tracks: LineTracks, frames: np.ndarray, R0: FloatArray,
                    group: np.ndarray,
                    options: GlobalRotationOptions = GlobalRotationOptions()) -> GlobalRotations:
    """The joint rotation problem (module docstring) from the start ``R0`` ``(F, 3, 3)`` on
    the frames ``frames`` ``(F,)`` bool, the tracks of one ``group`` ``(M,)`` sharing one
    direction (-1: left out), by Levenberg-Marquardt with a Cauchy loss whose scale follows the
    residuals' robust spread (iteratively reweighted). The lines of a direction of their own
    enter where a frame needs them (:func:`_needed_groups`); the others get their direction
    from the solved rotations."""
    if frames.sum() < 2 or group.max() < 1:
        raise OmniSfmError("too few frames or lines for the rotations")
    solved = group if options.every_line else _needed_groups(tracks, frames, group)
    if solved.max() < 1:
        solved = group
    prob = _RotationProblem(tracks, frames, solved)
    # solved and returned in the world of the gauge frame's camera: the directions' parameters
    # (and so the solver's path) depend on the world's orientation, and the same start in
    # another world (another frame first) could reach another minimum; starts that differ
    # at the gauge frame and reach one minimum give one solution
    R = np.einsum("ji,fjk->fik", R0[prob.gauge], R0)
    d = group_directions(tracks, R, frames, solved)
    r = prob.residuals(R, d)
    sigma = max(_robust_sigma(r), 1e-9)
    scale = options.loss_scale * sigma
    cost = _cost(r, scale)
    lam = 1e-4
    it = 0
    for it in range(1, options.max_iterations + 1):  # noqa: B007
        w = _cauchy_weights(r, scale)
        H, g, _, diag = prob.normal_equations(R, d, w)
        improved = False
        while lam < 1e12:
            A = H + sp.diags(lam * np.maximum(diag, 1e-12))
            step = -_factor(A).solve(g)
            R2, d2 = prob.retract(R, d, step)
            r2 = prob.residuals(R2, d2)
            cost2 = _cost(r2, scale)
            if cost2 < cost:
                rel = (cost - cost2) / max(cost, 1e-300)
                R, d, r, cost = R2, d2, r2, cost2
                lam = max(lam / 10, 1e-12)
                improved = True
                break
            lam *= 10
        # the loss follows the residuals' spread: a new scale, a new cost to compare against
        sigma_new = max(_robust_sigma(r), 1e-12)
        if improved and abs(sigma_new - sigma) > 1e-6 * sigma:
            sigma, scale = sigma_new, options.loss_scale * sigma_new
            cost = _cost(r, scale)
            continue
        if not improved or rel < options.tolerance:
            break
    H, _, _, _ = prob.normal_equations(R, d, _cauchy_weights(r, scale))
    info, axis = _frame_information(H, prob, tracks.num_frames)
    Rout = np.where(frames[:, None, None], R, np.nan)
    d_tracks = _track_directions(tracks, R, frames, d, solved, group)
    free_axis = np.einsum("fij,fj->fi", Rout, axis)
    return GlobalRotations(rotations=Rout, directions=d_tracks, frames=frames.copy(),
                           frame_information=info, free_axis=free_axis, sigma=sigma,
                           iterations=it)


def _track_directions(tracks: LineTracks, R: FloatArray, frames: np.ndarray, d: FloatArray,
                      solved: np.ndarray, group: np.ndarray) -> FloatArray:
    """``(M, 3)`` each track's direction: its solved group's (``solved``), and for a track of
    ``group`` left out of the solve (:func:`_needed_groups`) the one its planes give at the
    rotations ``R``; NaN for the tracks of no group."""
    out = np.where((solved >= 0)[:, None], d[np.maximum(solved, 0)], np.nan)
    rest = (group >= 0) & (solved < 0)
    if rest.any():
        own = np.full(tracks.num_tracks, -1)
        own[rest] = np.arange(int(rest.sum()))
        out[rest] = group_directions(tracks, R, frames, own)
    return np.asarray(out)


def _frame_information(H: sp.csc_matrix, prob: _RotationProblem, F: int
                       ) -> tuple[FloatArray, FloatArray]:
    """The smallest eigenvalue of each posed frame's 3x3 diagonal block of ``H`` (the gauge
    frame: infinity) and its eigenvector (camera frame; NaN for the gauge frame)."""
    info = np.full(F, np.inf)
    P = prob.num_pose
    if P == 0:
        return info, np.full((F, 3), np.nan)
    Hd = H[: 3 * P, : 3 * P].tocsr()
    blocks = np.zeros((P, 3, 3))
    for a in range(3):
        for b in range(3):
            blocks[:, a, b] = np.asarray(Hd[np.arange(P) * 3 + a, np.arange(P) * 3 + b]).ravel()
    ev, vec = np.linalg.eigh(blocks)
    posed = np.flatnonzero(prob.pose_idx >= 0)
    info[posed] = ev[prob.pose_idx[posed], 0]
    axis = np.full((F, 3), np.nan)
    axis[posed] = vec[prob.pose_idx[posed], :, 0]
    return info, axis
