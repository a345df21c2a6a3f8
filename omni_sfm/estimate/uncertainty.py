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
from dataclasses import dataclass
from functools import partial
from typing import Any

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


def _window_spread(R: FloatArray, inv: _WindowInverse, sigma: float, aligned: np.ndarray,
                   carried: FloatArray, origin: bool
                   ) -> tuple[np.ndarray, FloatArray, FloatArray]:
    """``(idx, rotation (n,) rad, position (n,))`` the RMS error to expect of each posed frame of
    a window (``inv``: :func:`_window_inverse`; the root of its covariance block's trace), the
    ``aligned`` frames (``(F,)``; all where fewer than 3 of them are posed) aligned as the
    trajectory's error is measured (module docstring)."""
    idx, G, C, moves = inv.idx, inv.G, inv.C, inv.moves
    n = len(idx)
    if C is None:
        return idx, np.full(n, np.inf), np.full(n, np.inf)
    on = aligned[idx] if aligned[idx].sum() >= 3 else np.ones(n, bool)
    # the alignment: the similarity that best fits the aligned frames' centres (their
    # rotations, weighted 1e-6, only settle the turn about a straight walk)
    weight = (on[:, None] * np.r_[np.full(3, 1e-6), np.ones(3)]).ravel()
    GW = G.T * weight
    Amap = np.linalg.lstsq(GW @ G, GW, rcond=None)[0]  # (7, 6n); a stop: rank < 7
    CA = C @ Amap.T
    Y = (C - G @ CA.T - CA @ G.T + G @ (Amap @ CA) @ G.T).reshape(n, 6, n, 6)
    pos = sigma**2 * np.einsum("kiki->k", Y[:, 3:, :, 3:])
    # a free direction that moves a few frames leaves those free; one that moves most of
    # them is a split of the window into parts whose relative pose nothing fixes, which the
    # spread cannot attribute to a part (the caller's ties between parts judge it), unless it
    # moves frames by much: then the frames' own parameters are free (lines along the walk
    # that leave the motion along them free in most frames), whatever their number
    free = np.zeros(n, bool)
    if moves is not None:
        moved = moves > 1e-12
        free = (moved if moved.sum() <= n // 2 else False) | (moves >= _FREE_TRACE)
    # the rotations' errors in the world counted from those of the reference frame (the one
    # whose own error from the gauge, ``carried``, is the least known: the traces of the
    # world-frame blocks R_k Y_kj R_j^T), plus the reference's own
    known = np.flatnonzero(np.isfinite(carried[idx]) & ~free)
    if origin and len(known) == 0:
        # the first aligned frame's pose is free: the errors are counted from the next one
        known = np.flatnonzero(on & ~free)[:1]
    if len(known) == 0:
        return idx, np.full(n, np.inf), np.where(free, np.inf, np.sqrt(np.maximum(pos, 0.0)))
    ref = int(known[np.argmin(np.nan_to_num(carried[idx][known]))])
    Yr = Y[:, :3, ref, :3]
    tr = np.einsum("kab,kbc,ac->k", R[idx], Yr, R[idx[ref]])
    diag = np.einsum("kab,kbc,kac->k", R[idx], Y[np.arange(n), :3, np.arange(n), :3], R[idx])
    rot = sigma**2 * (diag - 2.0 * tr + diag[ref]) + np.nan_to_num(carried[idx[ref]])
    rot[free], pos[free] = np.inf, np.inf
    return idx, np.sqrt(np.maximum(rot, 0.0)), np.sqrt(np.maximum(pos, 0.0))


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


def _cached_window(cache: dict[int, object] | None, a: int, key: tuple[Any, ...],
                   inverse: Callable[[], _WindowInverse],
                   spread: Callable[[_WindowInverse], tuple[np.ndarray, FloatArray, FloatArray]]
                   ) -> tuple[np.ndarray, FloatArray, FloatArray]:
    """The window at ``a``'s figures (``spread`` of its ``inverse``): kept in ``cache`` from an
    earlier round where its ``key`` (aligned frames, reference errors) is the same; its
    inverse, which does not depend on them, kept where the memory allows
    (:func:`_kept_inverse`)."""
    kept = cache.get(a) if cache is not None else None
    if isinstance(kept, tuple) and kept[0] == key:
        return kept[1]
    inv = kept[2] if isinstance(kept, tuple) and kept[2] is not None else inverse()
    out = spread(inv)
    if cache is not None:
        cache[a] = (key, out, inv if _kept_inverse(cache, a, inv) else None)
    return out


def _kept_inverse(cache: dict[int, object], a: int, inv: _WindowInverse) -> bool:
    """Whether the window at ``a`` keeps its inverse ``inv`` in ``cache``: one it kept already,
    or a new one while the kept ones stay within :data:`_INVERSE_CACHE_BYTES` (their total
    under key -1). Which windows keep theirs changes the time a round takes, not its result."""
    kept = cache.get(a)
    if isinstance(kept, tuple) and kept[2] is inv:
        return True
    size = 0 if inv.C is None else int(inv.C.nbytes)
    used = cache.get(-1, 0)
    assert isinstance(used, int)
    if used + size > _INVERSE_CACHE_BYTES:
        return False
    cache[-1] = used + size
    return True


def pose_spread(tracks: LineTracks, rotations: FloatArray, positions: FloatArray,
                line_directions: FloatArray, line_points: FloatArray, frames: np.ndarray,
                used_tracks: np.ndarray, sigma_rad: float, window: int = 300,
                aligned: np.ndarray | None = None,
                held_directions: np.ndarray | None = None,
                cache: dict[int, object] | None = None) -> PoseSpread:
    """Each posed frame's pose spread (module docstring) at the adjustment's solution
    (``rotations``, ``positions`` world_from_cam; the lines; ``frames`` posed; the
    ``used_tracks``), the observations' noise ``sigma_rad`` (radians, per axis), with the
    ``aligned`` frames (default: every posed frame) aligned to the truth: the others' poses
    still tie the lines together, but their errors do not count in the alignment. The lines
    of ``held_directions`` keep their direction, as the adjustment held it. ``cache`` keeps
    each window's figures between calls with the same solution and noise (the flags'
    rounds): a window whose aligned frames and reference errors have not changed is not
    computed again, and a window's inverse information, which does not depend on them, is
    computed once where the memory allows (:func:`_kept_inverse`)."""
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
        key = (aligned[members].tobytes(), carried[members].tobytes(), a == starts[at])
        idx, r, q = _cached_window(
            cache, a, key, partial(_window_inverse, tracks, rotations, positions,
                                   line_directions, line_points, sel, used_tracks, sigma_rad,
                                   held_directions),
            partial(_window_spread, rotations, sigma=sigma_rad, aligned=aligned,
                    carried=carried, origin=a == starts[at]))
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
