"""How well the data fix each frame's pose: the covariance of the line adjustment's solution.

At the solution, the adjustment's information ``J^T J`` over the used lines' observations (each
weighted as the adjustment weighs it, robust loss aside), every line free (4 parameters; 2
where the adjustment held its direction), with the lines eliminated (Schur complement),
leaves the cameras' ``6n x 6n`` information ``S``
(each frame's camera-frame rotation increment, then its centre, as
:class:`~omni_sfm.estimate.bundle.LineProblem` moves them). Lines fix the poses only up to a
similarity of the world (its rotation, translation and scale: 7 degrees of freedom, ``S``'s
null space), so the covariance ``sigma^2 S^+`` is taken with the whole aligned to the truth as
the trajectory's error is measured (:func:`omni_sfm.evaluate.flag_honesty`): the centres (of
the frames given as aligned) by the similarity that fits them best, each rotation counted
from the first aligned frame's. A window's rotations are counted from its frame whose own
error the windows before it fix best, and that error is added (the windows from the one that
holds the first aligned frame on to the end, then back to the start): the drift of the turn
that only the lines shared from frame to frame fix builds up along a walk. A frame with a
large spread
is one whose pose the data do not fix, whatever its own lines say (a stretch whose lines leave
the walk's speed or bend free ties it weakly to the rest).

Long videos are taken in overlapping windows of ``window`` posed frames (each with its own
similarity gauge; laid out the same in either frame order): each frame's figures come from the
window in which it lies farthest from the ends (the larger figures of two such windows). Where
the data leave a direction free that moves a few of a window's frames, their spread is
infinite; free directions that move most of them (two parts whose relative pose nothing fixes)
are left out, except from the frames they move by much (each frame's own parameters free:
lines along the walk in most frames), whose spread is infinite too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np
import scipy.linalg
import scipy.sparse.linalg

from omni_sfm.estimate.bundle import LineProblem
from omni_sfm.estimate.windows import window_starts
from omni_sfm.geometry import FloatArray, skew
from omni_sfm.lines.tracks import LineTracks


@dataclass(frozen=True)
class PoseSpread:
    """Each frame's pose spread: the RMS error to expect of its rotation (the angle) and of its
    centre (the distance), after the whole is aligned to the truth: the centres by the
    similarity that fits them best, each rotation counted from the first aligned frame's.

    Attributes:
        rotation_deg: ``(F,)`` degrees (NaN: frame not posed; inf: the data leave it free).
        position: ``(F,)`` in the world's units (NaN, inf as ``rotation_deg``).
    """

    rotation_deg: FloatArray
    position: FloatArray


def _similarity_motions(R: FloatArray, c: FloatArray) -> FloatArray:
    """``(6n, 7)`` the poses' change under an infinitesimal similarity of the world (rotation
    ``w``, translation ``t``, scale ``s``): the camera-frame rotation increment ``R^T w`` and
    the centre's ``w x c + t + s c``."""
    n = len(R)
    G = np.zeros((n, 6, 7))
    G[:, :3, :3] = np.transpose(R, (0, 2, 1))
    G[:, 3:, :3] = -skew(c)
    G[:, 3:, 3:6] = np.eye(3)
    G[:, 3:, 6] = c
    return G.reshape(6 * n, 7)


def _camera_information(tracks: LineTracks, R: FloatArray, c: FloatArray, d: FloatArray,
                        p: FloatArray, frames: np.ndarray, used: np.ndarray,
                        held: np.ndarray | None = None) -> tuple[np.ndarray, FloatArray]:
    """``(idx, S)``: the posed frames of ``frames`` and their ``6n x 6n`` information with the
    ``used`` lines (those seen twice or more among ``frames``) eliminated: their positions,
    and their directions but where ``held`` (the adjustment held them: a world direction)."""
    F = tracks.num_frames
    idx = np.flatnonzero(frames)
    seen = np.bincount(tracks.obs_track[frames[tracks.obs_frame]], minlength=tracks.num_tracks)
    active = used & (seen >= 2)
    prob = LineProblem(tracks, frames, active, fixed_frame=int(idx[0]),
                       scale_frame=int(idx[-1]), scale_axis=0, held_directions=held)
    prob.pose_free[:] = False
    prob.pose_free[frames] = True  # every pose free: the gauge is handled by the caller
    e, u = prob.residuals(R, c, d, p)
    Jp, Jl = prob.jacobian(R, c, d, p, u)
    Hpp, Hll, Hpl, _, _ = prob.normal_equations(Jp, Jl, e, np.ones(len(prob.f)))
    n = len(idx)
    at = np.full(F, -1)
    at[idx] = np.arange(n)
    S = np.zeros((n, 6, n, 6))
    S[np.arange(n), :, np.arange(n), :] = Hpp[idx]
    order = np.argsort(prob.t, kind="stable")
    bounds = np.searchsorted(prob.t[order], np.arange(tracks.num_tracks + 1))
    for line in np.flatnonzero(active):
        ks = order[bounds[line]:bounds[line + 1]]
        A = Hpl[ks]                                              # (m, 6, 4)
        H = Hll[line] + 1e-12 * float(np.trace(Hll[line])) * np.eye(4)
        Af = A.reshape(-1, 4)                                    # (6m, 4)
        block = (Af @ np.linalg.solve(H, Af.T)).reshape(len(ks), 6, len(ks), 6)
        fi = at[prob.f[ks]]
        S[fi[:, None], :, fi[None, :], :] -= np.transpose(block, (0, 2, 1, 3))
    return idx, S.reshape(6 * n, 6 * n)


_FREE_TRACE = 0.5
"""A frame whose block of the free directions' projector has at least this trace is left free
(one parameter of its own free gives 1; a split that leaves a part of 14 frames or more free as
a whole gives less)."""


_WEAK_SPREAD = 0.1
"""A direction of the poses whose RMS error would exceed this (radians; the path's length) and
that moves a few frames (:data:`_LOCAL_FRAMES`) leaves those frames free (:func:`_inverse`):
the data do not fix them. Counted in the covariance, its spread would reach every frame of the
window through the alignment's similarity (a camera that sees only vertical lines through a
few frames, its height nearly free, would give every frame of its window a spread of the
path's length)."""

_LOCAL_FRAMES = 0.25
"""A weak direction moves a few frames where its participation (the number of frames it moves,
``1 / sum m_k^2`` of its frames' shares ``m_k``) is at most this fraction of the window's."""


def _inverse(A: FloatArray, floor: float = 0.0) -> tuple[FloatArray, np.ndarray | None]:
    """``(C, moves)``: the inverse of the symmetric ``A`` (Cholesky), or, where ``A`` has
    eigenvalues at round-off (a direction the data leave free) or at most ``floor`` in a
    direction that moves a few frames (:data:`_WEAK_SPREAD`), its inverse on the other
    directions and ``(n,)`` how much the free directions move each frame (the trace of its
    block of their projector: about 1 for each of its parameters that they leave free, about
    ``7 / m`` where a split leaves a part of ``m`` frames free as a whole; None: no free
    direction). The free directions are taken as they are, orthogonal to the similarities
    (which ``A`` lifts): each moves the frames it frees and next to nothing elsewhere (the
    alignment's similarity would spread them over every frame, and where the aligned frames
    lie on a straight line, whose turn about it only their rotations' small weight fixes, by
    many times their size).

    Only the eigenvalues at most ``floor`` are computed, with their vectors (the free ones
    among them then lifted to the matrix's mean eigenvalue and taken out of its inverse):
    half the time of the whole decomposition."""
    try:
        L = scipy.linalg.cholesky(A, lower=True, check_finite=False)
        inv, info = scipy.linalg.lapack.dpotri(L, lower=1)
        # no eigenvalue of the inverse exceeds its trace: below 1 / floor, none is weak
        if info == 0 and float(np.trace(inv)) * floor < 1.0:
            return np.tril(inv) + np.tril(inv, -1).T, None
    except np.linalg.LinAlgError:
        pass
    scale = max(float(np.trace(A)) / len(A), 1e-300)  # at least the largest eigenvalue / n
    # the largest eigenvalue (Lanczos, from a start vector the same in any frame order)
    top = scipy.sparse.linalg.eigsh(A, k=1, which="LA", v0=np.ones(len(A)),
                                    return_eigenvectors=False)
    w, V = scipy.linalg.eigh(A, subset_by_value=(-np.inf, max(floor, 1e-13 * float(top[0]))),
                             driver="evr", check_finite=False)
    n = len(A) // 6
    share = np.square(V).reshape(n, 6, -1).sum(axis=1)
    frames_moved = 1.0 / np.maximum(np.square(share).sum(axis=0), 1e-300)
    free = (w <= 1e-13 * float(top[0])) | ((w <= floor) & (frames_moved <= _LOCAL_FRAMES * n))
    Vf = V[:, free]
    # the free directions' eigenvalues lifted to ``scale`` (a definite matrix), their part
    # of its inverse taken out again: the inverse on the other directions
    L = scipy.linalg.cholesky(A + (Vf * (scale - w[free])) @ Vf.T, lower=True,
                              check_finite=False)
    inv, _ = scipy.linalg.lapack.dpotri(L, lower=1)
    C = np.tril(inv) + np.tril(inv, -1).T - (Vf / scale) @ Vf.T
    return C, (share[:, free].sum(axis=1) if free.any() else None)


@dataclass(frozen=True)
class _WindowInverse:
    """A window's posed frames ``idx``, their similarity motions ``G`` and the inverse ``C``
    of their information (the similarities lifted), with how much the free directions move
    each frame (``moves``; None: none); ``C`` None where the information is not finite."""

    idx: np.ndarray
    G: FloatArray
    C: FloatArray | None
    moves: FloatArray | None


def _window_inverse(tracks: LineTracks, R: FloatArray, c: FloatArray, d: FloatArray,
                    p: FloatArray, frames: np.ndarray, used: np.ndarray, sigma: float,
                    held: np.ndarray | None) -> _WindowInverse:
    """The part of a window's spread that does not depend on which frames are aligned."""
    idx, S = _camera_information(tracks, R, c, d, p, frames, used, held)
    G = _similarity_motions(R[idx], c[idx])
    if not np.isfinite(S).all() or np.trace(S) <= 0.0:
        return _WindowInverse(idx, G, None, None)
    Q, _ = np.linalg.qr(G)
    scale = max(float(np.trace(S)) / len(S), 1e-300)
    # the similarities' directions have eigenvalue ~scale after this, and no part in the
    # covariance once the alignment removes them
    C, moves = _inverse(S + scale * (Q @ Q.T), (sigma / _WEAK_SPREAD) ** 2)
    return _WindowInverse(idx, G, C, moves)


def _window_free(inv: _WindowInverse) -> np.ndarray:
    """``(n,)`` the window's frames that its free directions leave free: a free direction that
    moves a few frames leaves those free; one that moves most of them is a split of the window
    into parts whose relative pose nothing fixes, which the spread cannot attribute to a part
    (the caller's ties between parts judge it), unless it moves frames by much: then the
    frames' own parameters are free (lines along the walk that leave the motion along them free
    in most frames), whatever their number."""
    n = len(inv.idx)
    free = np.zeros(n, bool)
    if inv.moves is not None:
        moved = inv.moves > 1e-12
        free = (moved if moved.sum() <= n // 2 else False) | (inv.moves >= _FREE_TRACE)
    return free


def _window_aligned(idx: np.ndarray, aligned: np.ndarray) -> np.ndarray:
    """``(n,)`` the window's frames aligned to the truth: the ``aligned`` ones (``(F,)``), all
    where fewer than 3 of them are posed in it."""
    on = aligned[idx]
    return on if on.sum() >= 3 else np.ones(len(idx), bool)


def _reference(idx: np.ndarray, free: np.ndarray, on: np.ndarray, carried: FloatArray,
               origin: bool) -> int | None:
    """The window's frame its rotations' errors are counted from: of those whose own error
    from the gauge (``carried``) the windows before it give, the least known; in the
    ``origin`` window, where none is, its first aligned frame (``on``) not ``free``; None
    where there is no such frame."""
    known = np.flatnonzero(np.isfinite(carried[idx]) & ~free)
    if origin and len(known) == 0:
        # the first aligned frame's pose is free: the errors are counted from the next one
        known = np.flatnonzero(on & ~free)[:1]
    if len(known) == 0:
        return None
    return int(known[np.argmin(np.nan_to_num(carried[idx][known]))])


def _window_variances(R: FloatArray, inv: _WindowInverse, sigma: float, on: np.ndarray,
                      ref: int | None) -> tuple[FloatArray, FloatArray]:
    """``(rotation (n,) rad^2, position (n,))`` the variances to expect of each posed frame of
    a window (``inv``: :func:`_window_inverse`; its covariance block's trace), the ``on``
    frames aligned as the trajectory's error is measured (module docstring), the rotations
    counted from the frame ``ref`` (its own error from the gauge not added; inf where None)."""
    idx, G, C = inv.idx, inv.G, inv.C
    n = len(idx)
    if C is None:
        return np.full(n, np.inf), np.full(n, np.inf)
    # the alignment: the similarity that best fits the aligned frames' centres (their
    # rotations, weighted 1e-6, only settle the turn about a straight walk)
    weight = (on[:, None] * np.r_[np.full(3, 1e-6), np.ones(3)]).ravel()
    GW = G.T * weight
    Amap = np.linalg.lstsq(GW @ G, GW, rcond=None)[0]  # (7, 6n); a stop: rank < 7
    CA = C @ Amap.T
    Y = (C - G @ CA.T - CA @ G.T + G @ (Amap @ CA) @ G.T).reshape(n, 6, n, 6)
    pos = sigma**2 * np.einsum("kiki->k", Y[:, 3:, :, 3:])
    if ref is None:
        return np.full(n, np.inf), pos
    # the rotations' errors in the world counted from those of the reference frame: the
    # traces of the world-frame blocks R_k Y_kj R_j^T
    Yr = Y[:, :3, ref, :3]
    tr = np.einsum("kab,kbc,ac->k", R[idx], Yr, R[idx[ref]])
    diag = np.einsum("kab,kbc,kac->k", R[idx], Y[np.arange(n), :3, np.arange(n), :3], R[idx])
    return sigma**2 * (diag - 2.0 * tr + diag[ref]), pos


def observation_noise(residual_sigma: float, tracks: LineTracks, frames: np.ndarray,
                      used: np.ndarray, held: np.ndarray | None) -> float:
    """The observations' noise (radians, per axis) from the noise ``residual_sigma`` that the
    adjustment's residuals show: ``sqrt(n / (n - p))`` times it, the residuals' ``n``
    components left by ``p`` fitted parameters (6 per posed frame of ``frames`` less the
    similarity's 7, 4 per ``used`` line or 2 where its direction is ``held``; on a walk of few
    lines a frame, each seen in few frames, the residuals are about a quarter below the
    noise), at most ``sqrt(2)`` times it (parameters as many as half the components or more:
    a count that says little)."""
    n = 2 * int(np.count_nonzero(frames[tracks.obs_frame] & used[tracks.obs_track]))
    lines = 4 * int(np.count_nonzero(used))
    if held is not None:
        lines -= 2 * int(np.count_nonzero(used & held))
    p = 6 * int(np.count_nonzero(frames)) - 7 + lines
    return residual_sigma * (float(np.sqrt(n / (n - p))) if n > 2 * p else float(np.sqrt(2.0)))


def _path_unit(c: FloatArray) -> float:
    """The length of the path through the centres ``c`` ``(n, 3)``, steps of more than 10
    times the median (a frame posed far off) counted as 10: the spread is computed in units of
    it (the rotations' and the centres' information then have comparable sizes, and a
    direction left free stands out against both)."""
    steps = np.linalg.norm(np.diff(c, axis=0), axis=1)
    unit = float(np.sum(np.minimum(steps, 10.0 * np.median(steps))))
    return unit if np.isfinite(unit) and unit > 0.0 else 1.0


_INVERSE_CACHE_BYTES = 256 * 2**20
"""The windows' inverse information kept between the flags' rounds at most (a window of 300
frames holds 26 MB: every window of a 20,000-frame walk would hold 3.5 GB)."""


@dataclass(frozen=True)
class _KeptWindow:
    """A window's figures kept between the flags' rounds (:func:`_window_figures`): its frames
    and those its free directions leave free (which depend on the solution alone), the
    variances for the aligned frames and reference in ``key``, and its inverse information
    where the memory allows (:class:`SpreadCache`)."""

    idx: np.ndarray
    free: np.ndarray
    key: tuple[bytes, int | None]
    variances: tuple[FloatArray, FloatArray]
    inv: _WindowInverse | None


@dataclass
class SpreadCache:
    """Each window's figures kept between calls of :func:`pose_spread` with the same solution
    and noise (the flags' rounds), and the inverse information of the windows used most
    recently, within :data:`_INVERSE_CACHE_BYTES` (which windows keep theirs changes the time a
    round takes, not its result)."""

    windows: dict[int, _KeptWindow] = field(default_factory=dict)
    recent: list[int] = field(default_factory=list)
    """The windows holding their inverse, the least recently used first."""
    size: int = 0
    """Their inverses' bytes."""

    def keep(self, a: int, kept: _KeptWindow) -> None:
        """Keep the window at ``a``'s figures, and its inverse (``kept.inv``) as the most
        recently used, those used least recently given up for it where the memory needs."""
        inv = kept.inv
        if a in self.recent:
            self.recent.remove(a)
            self.size -= _inverse_bytes(self.windows[a].inv)
        nbytes = _inverse_bytes(inv)
        while self.recent and self.size + nbytes > _INVERSE_CACHE_BYTES:
            old = self.recent.pop(0)
            self.size -= _inverse_bytes(self.windows[old].inv)
            self.windows[old] = replace(self.windows[old], inv=None)
        if inv is not None and self.size + nbytes <= _INVERSE_CACHE_BYTES:
            self.recent.append(a)
            self.size += nbytes
        else:
            kept = replace(kept, inv=None)
        self.windows[a] = kept


def _inverse_bytes(inv: _WindowInverse | None) -> int:
    return 0 if inv is None or inv.C is None else int(inv.C.nbytes)


def _window_figures(R: FloatArray, cache: SpreadCache | None, a: int,
                    inverse: Callable[[], _WindowInverse], sigma: float, aligned: np.ndarray,
                    carried: FloatArray, origin: bool
                    ) -> tuple[np.ndarray, FloatArray, FloatArray]:
    """``(idx, rotation (n,) rad, position (n,))`` the RMS error to expect of each posed frame
    of the window at ``a`` (its ``inverse``: :func:`_window_inverse`), the ``aligned`` frames
    aligned (:func:`_window_aligned`), its rotations counted from its reference frame
    (:func:`_reference`) plus that frame's own error from the gauge (``carried``; the variances
    before it are kept in ``cache`` from an earlier round where its aligned frames and its
    reference are the same: a change of the errors carried from the windows before it adds a
    constant; its inverse, which depends on neither, is kept where the memory allows:
    :class:`SpreadCache`)."""
    kept = cache.windows.get(a) if cache is not None else None
    inv = kept.inv if kept is not None else None
    if kept is None:
        inv = inverse()
        idx, free = inv.idx, _window_free(inv)
    else:
        idx, free = kept.idx, kept.free
    on = _window_aligned(idx, aligned)
    ref = _reference(idx, free, on, carried, origin)
    key = (on.tobytes(), ref)
    if kept is not None and kept.key == key:
        rot, pos = kept.variances
    else:
        inv = inv if inv is not None else inverse()
        rot, pos = _window_variances(R, inv, sigma, on, ref)
        if cache is not None:
            cache.keep(a, _KeptWindow(idx, free, key, (rot, pos), inv))
    if ref is not None:
        rot = rot + np.nan_to_num(carried[idx[ref]])
    rot, pos = rot.copy(), pos.copy()
    rot[free], pos[free] = np.inf, np.inf
    return idx, np.sqrt(np.maximum(rot, 0.0)), np.sqrt(np.maximum(pos, 0.0))


def pose_spread(tracks: LineTracks, rotations: FloatArray, positions: FloatArray,
                line_directions: FloatArray, line_points: FloatArray, frames: np.ndarray,
                used_tracks: np.ndarray, sigma_rad: float, window: int = 300,
                aligned: np.ndarray | None = None,
                held_directions: np.ndarray | None = None,
                cache: SpreadCache | None = None) -> PoseSpread:
    """Each posed frame's pose spread (module docstring) at the adjustment's solution
    (``rotations``, ``positions`` world_from_cam; the lines; ``frames`` posed; the
    ``used_tracks``), the observations' noise ``sigma_rad`` (radians, per axis), with the
    ``aligned`` frames (default: every posed frame) aligned to the truth: the others' poses
    still tie the lines together, but their errors do not count in the alignment. The lines
    of ``held_directions`` keep their direction, as the adjustment held it. ``cache`` keeps
    each window's figures between calls with the same solution and noise (the flags'
    rounds): a window whose aligned frames and reference frame have not changed is not
    computed again (the errors carried from the windows before it add a constant), and a
    window's inverse information, which does not depend on them, is computed once where the
    memory allows (:class:`SpreadCache`)."""
    F = tracks.num_frames
    rot, pos = np.full(F, np.nan), np.full(F, np.nan)
    posed = np.flatnonzero(frames)
    if len(posed) < 3:
        return PoseSpread(rot, pos)
    unit = _path_unit(positions[posed])
    positions, line_points = positions / unit, line_points / unit
    aligned = frames if aligned is None else aligned & frames
    centrality = np.full(F, -1.0)
    # each rotation's variance counted from the first aligned frame's (the frame the errors
    # are counted from), known so far: the windows from the one that holds it on to the end,
    # then back to the start
    first = int(np.flatnonzero(aligned)[0]) if aligned.any() else int(posed[0])
    carried = np.where(np.arange(F) == first, 0.0, np.nan)
    starts = window_starts(len(posed), max(window, 2))
    at = next(i for i, a in enumerate(starts) if first in posed[a:a + window])
    for a in starts[at:] + starts[:at][::-1]:
        members = posed[a:a + window]
        sel = np.zeros(F, bool)
        sel[members] = True
        idx, r, q = _window_figures(
            rotations, cache, a, partial(_window_inverse, tracks, rotations, positions,
                                         line_directions, line_points, sel, used_tracks,
                                         sigma_rad, held_directions),
            sigma_rad, aligned, carried, a == starts[at])
        new = np.isnan(carried[idx])
        carried[idx[new]] = np.square(r[new])
        k = np.arange(len(idx))
        # a window at the video's end is as good as a central one there
        left = k if a > 0 else np.full(len(k), len(k))
        right = len(k) - 1 - k if a + window < len(posed) else np.full(len(k), len(k))
        central = np.minimum(left, right).astype(float)
        # as central in two windows (the same layout in either frame order): the larger
        better = central > centrality[idx]
        tie = central == centrality[idx]
        rot[idx[tie]] = np.maximum(rot[idx[tie]], r[tie])
        pos[idx[tie]] = np.maximum(pos[idx[tie]], q[tie])
        rot[idx[better]], pos[idx[better]] = r[better], q[better]
        centrality[idx[better]] = central[better]
    return PoseSpread(np.degrees(rot), pos * unit)
