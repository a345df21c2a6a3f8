"""Partial tracks and long sequences: overlapping windows solved by the paper's method, chained.

The paper's method (:func:`omni_sfm.estimate.paper.estimate_paper`) needs every line in every
frame. Real videos lose and gain lines, and in a long sequence no line is seen throughout. We cut
the sequence into overlapping windows of consecutive frames in each of which enough tracks of the
parallel family and enough other tracks are seen in *every* frame, solve each window by the
paper's method on those tracks (with the family's per-frame VPVs), and chain the windows: the
frames two neighbouring windows share give the similarity (rotation, translation, scale) between
their solutions. The chained poses are the initial values of the joint bundle adjustment over all
observations (:mod:`omni_sfm.estimate.bundle`).

Frames that no window covers, and windows that cannot be chained to the longest chain, are not
estimated; they are reported, never filled with guesses.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray, rotation_angle
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.transforms import similarity_from_poses
from omni_sfm.vanishing import ParallelFamily


@dataclass(frozen=True, kw_only=True)
class WindowOptions:
    min_parallel: int = 3
    """Fewest family tracks seen in every frame of a window (the method needs 3)."""
    min_other: int = 3
    """Fewest other tracks seen in every frame of a window (the method needs 3)."""
    preferred_lines: int = 5
    """Windows keep at least this many tracks of each kind where they can (the paper's
    method is fragile with only 3 + 3 lines); fewer, down to the minimum, only where no window
    with this many continues the chain."""
    max_length: int = 60
    """Longest window, frames (longer windows give the paper's method more baseline)."""
    max_rotation_step_deg: float = 45.0
    """A window's solution that turns by more than this between two consecutive frames is
    taken for a per-frame flip of the rotation search (video frames turn little): the window is
    solved again without the rotation polish (:attr:`PaperOptions.polish_rotation`), and that
    solution is kept if its steps stay below this."""
    max_disagreement_deg: float | None = None
    """A window whose rotations, after the best rotation onto the chain, differ from the chained
    ones on a shared frame by more than this (deg) and whose unpolished solution does too is not
    chained (its frames are left to the next windows, or not estimated). None: no check (off by
    default: on the 40-frame textured room 5-45 deg drop a window and 8 frames that the
    bundle adjustment recovers when the window is kept)."""


@dataclass(frozen=True)
class Window:
    """Frames ``start..stop-1`` and the tracks (indices into the full tracks) seen in all."""

    start: int
    stop: int
    tracks: np.ndarray

    @property
    def frames(self) -> np.ndarray:
        return np.arange(self.start, self.stop)


def full_visibility_counts(vis: np.ndarray, members: np.ndarray, start: int,
                           stop_max: int) -> tuple[np.ndarray, np.ndarray]:
    """For windows ``start..e`` (e < stop_max): family / other tracks seen in all their frames.

    Returns two ``(stop_max - start,)`` int arrays indexed by ``e - start``.
    """
    run = np.logical_and.accumulate(vis[:, start:stop_max], axis=1)  # (M, L)
    return run[members].sum(0), run[~members].sum(0)


def _longest_stops(vis: np.ndarray, members: np.ndarray, starts: np.ndarray,
                   options: WindowOptions, min_parallel: int, min_other: int) -> np.ndarray:
    """For each start frame: the stop of the longest valid window from it (start if none).

    Valid: at least 3 frames, at most ``max_length``, and ``min_parallel`` family and
    ``min_other`` other tracks seen in every frame.
    """
    F = vis.shape[1]
    stops = np.array(starts, copy=True)
    for k, s in enumerate(starts):
        stop_max = min(F, int(s) + options.max_length)
        n_par, n_oth = full_visibility_counts(vis, members, int(s), stop_max)
        ok = (n_par >= min_parallel) & (n_oth >= min_other)
        ok[:2] = False
        if ok.any():
            # counts only fall as the window grows: the last valid end is the longest window
            stops[k] = int(s) + int(np.flatnonzero(ok)[-1]) + 1
    return stops


def plan_windows(tracks: LineTracks, members: np.ndarray, frame_ok: np.ndarray,
                 options: WindowOptions = WindowOptions()) -> list[Window]:
    """Overlapping windows covering as many frames as possible (see the module docstring).

    Greedy: the first window is the longest valid one from the first usable frame; each next
    window starts inside the previous one (sharing at least 3 and at most ``overlap`` frames
    where it can) at the start whose longest valid window reaches furthest. Where no window
    can continue the chain, the next one starts at the first frame that has a valid window
    (the gap and the break are left to the chaining, which keeps the longest chain).

    Args:
        tracks: all observations.
        members: ``(M,)`` bool, tracks of the parallel family.
        frame_ok: ``(F,)`` bool, frames usable at all (e.g. where the family's VPV is defined).

    Returns the windows in order of their start frames.
    """
    vis = tracks.visibility() & np.asarray(frame_ok, bool)[None, :]
    F = tracks.num_frames
    members = np.asarray(members, bool)
    windows: list[Window] = []

    def add(s: int, stop: int) -> None:
        run = np.logical_and.reduce(vis[:, s:stop], axis=1)
        windows.append(Window(s, stop, np.flatnonzero(run)))

    levels = [(max(options.preferred_lines, options.min_parallel),
               max(options.preferred_lines, options.min_other)),
              (options.min_parallel, options.min_other)]

    def first_valid(from_frame: int) -> tuple[int, int] | None:
        for s in range(max(from_frame, 0), F - 2):
            for mp, mo in levels:
                stop = int(_longest_stops(vis, members, np.array([s]), options, mp, mo)[0])
                if stop > s:
                    return s, stop
        return None

    nxt = first_valid(0)
    while nxt is not None:
        add(*nxt)
        prev = windows[-1]
        if prev.stop >= F:
            break
        cands = np.arange(prev.start + 1, prev.stop - 2)
        nxt = None
        for mp, mo in levels:
            stops = _longest_stops(vis, members, cands, options, mp, mo)
            good = stops > prev.stop
            if good.any():
                # reach furthest; among those, start earliest (longest window, most overlap)
                best = int(stops[good].max())
                nxt = (int(cands[good & (stops == best)].min()), best)
                break
        if nxt is None:
            nxt = first_valid(prev.stop - 2)
    return windows


def window_tracks(tracks: LineTracks, window: Window) -> LineTracks:
    """The window's tracks restricted to its frames, frames renumbered from 0."""
    sub = tracks.select_tracks(window.tracks)
    sel = (sub.obs_frame >= window.start) & (sub.obs_frame < window.stop)
    return LineTracks(window.stop - window.start, sub.track_ids, sub.obs_track[sel],
                      sub.obs_frame[sel] - window.start, sub.obs_normal[sel],
                      tracks.timestamps[window.start:window.stop])


def window_family(family: ParallelFamily, window: Window) -> ParallelFamily:
    """The family restricted to a window's tracks and frames."""
    return family.select(tracks=window.tracks, frames=window.frames)


def max_rotation_step_deg(rotations: FloatArray) -> float:
    """Largest rotation angle (deg) between consecutive frames of ``rotations`` ``(n,3,3)``."""
    if rotations.shape[0] < 2:
        return 0.0
    rel = np.einsum("kji,kjl->kil", rotations[:-1], rotations[1:])
    return float(np.degrees(rotation_angle(rel)).max())


def similarity_from_overlap(rot_a: FloatArray, pos_a: FloatArray, rot_b: FloatArray,
                            pos_b: FloatArray) -> tuple[FloatArray, float, FloatArray]:
    """Similarity ``x_a = s R x_b + t`` taking solution b onto solution a on shared frames.

    ``rot_*`` are ``(n, 3, 3)`` world_from_cam and ``pos_*`` ``(n, 3)`` camera centres of the
    same ``n >= 2`` frames in the two solutions. The rotation is the chordal mean of
    ``R_a R_b^T`` over the frames (rotations are well determined), the scale the least-squares
    ratio of the centres about their means, the translation maps the means
    (:func:`omni_sfm.transforms.similarity_from_poses` with ``allow_reflection``).

    The scale may come out negative: NVs have no sign, so a window's solution is determined only
    up to the point reflection of its positions (and lines) through its first camera; a negative
    scale means b is the reflected solution, and applying it reflects b onto a's branch.
    """
    if rot_a.shape[0] < 2:
        raise OmniSfmError("chaining windows needs at least 2 shared frames")
    try:
        sim = similarity_from_poses(rot_a, pos_a, rot_b, pos_b, allow_reflection=True)
    except OmniSfmError as e:
        raise OmniSfmError("chaining windows: the shared frames do not move; scale "
                           "undefined") from e
    return sim.rotation, sim.scale, sim.translation


def _fit_overlap(rot_a: FloatArray, pos_a: FloatArray, rot_b: FloatArray, pos_b: FloatArray,
                 max_disagreement_deg: float | None
                 ) -> tuple[FloatArray, float, FloatArray, bool]:
    """:func:`similarity_from_overlap` and whether the rotations agree within the limit."""
    Rs, s, t = similarity_from_overlap(rot_a, pos_a, rot_b, pos_b)
    if max_disagreement_deg is None:
        return Rs, s, t, True
    diff = np.einsum("kji,kjl->kil", rot_a, Rs @ rot_b)
    return Rs, s, t, float(np.degrees(rotation_angle(diff)).max()) <= max_disagreement_deg


RefineFn = Callable[[FloatArray, FloatArray, np.ndarray, np.ndarray],
                    tuple[FloatArray, FloatArray, np.ndarray]]


class Chain(NamedTuple):
    """Windows chained into one trajectory (:func:`chain_windows`)."""

    rotations: FloatArray
    """``(F, 3, 3)`` world_from_cam, NaN for frames not chained."""
    positions: FloatArray
    """``(F, 3)`` camera centres, NaN for frames not chained."""
    estimated: np.ndarray
    """``(F,)`` bool."""
    chained: list[int]
    """Indices of the chained windows."""
    skipped: dict[int, str]
    """Solved windows left out of the chain, and why."""


def _linked_runs(windows: list[Window],
                 solutions: list[tuple[FloatArray, FloatArray] | None]) -> list[list[int]]:
    """The runs of solved windows in which each shares at least 3 frames with the one before."""
    runs: list[list[int]] = []
    for w, sol in enumerate(solutions):
        if sol is None:
            continue
        if runs and windows[runs[-1][-1]].stop - windows[w].start >= 3:
            runs[-1].append(w)
        else:
            runs.append([w])
    return runs


def _longest_run(windows: list[Window], solutions: list[tuple[FloatArray, FloatArray] | None]
                 ) -> tuple[list[int], dict[int, str]]:
    """The longest run of :func:`_linked_runs` (empty where no window is solved) and the
    windows of the others, each with why it is not chained."""
    runs = _linked_runs(windows, solutions)
    if not runs:
        return [], {}
    best = max(runs, key=lambda r: windows[r[-1]].stop - windows[r[0]].start)
    return best, {w: "not in the longest run of windows linked by 3 shared frames (a gap)"
                  for r in runs if r is not best for w in r}


def _refined_locally(refine: RefineFn, R: FloatArray, c: FloatArray, done: np.ndarray,
                     new: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """:func:`chain_windows`' local refinement of frames ``lo:hi`` (those chained and the
    ``new`` ones), in place in ``R``, ``c`` and ``done`` (frames it could not estimate are
    dropped); returns the new frames it kept."""
    local = np.zeros(len(done), bool)
    local[lo:hi] = True
    local &= done | np.isin(np.arange(len(done)), new)
    R2, c2, ok = refine(R, c, local, done & local)
    R[local], c[local] = R2[local], c2[local]
    lost = local & ~ok
    R[lost], c[lost] = np.nan, np.nan
    done &= ~lost
    return np.asarray(new[ok[new]])


def _fit_or_resolve(R: FloatArray, c: FloatArray, sol: tuple[FloatArray, FloatArray],
                    idx: np.ndarray, max_disagreement_deg: float | None,
                    other: Callable[[], tuple[FloatArray, FloatArray] | None] | None
                    ) -> tuple[FloatArray, float, FloatArray, bool,
                               tuple[FloatArray, FloatArray]]:
    """:func:`_fit_overlap` of a window's solution ``sol`` (its rows ``idx`` on the chain's
    shared poses ``R``, ``c``); where they disagree, of ``other()``'s solution instead, if it
    agrees. Returns the fit, whether it agrees, and the solution it is of."""
    Rs, s, t, agree = _fit_overlap(R, c, sol[0][idx], sol[1][idx], max_disagreement_deg)
    if not agree and other is not None:
        alt = other()
        if alt is not None:
            fit = _fit_overlap(R, c, alt[0][idx], alt[1][idx], max_disagreement_deg)
            if fit[3]:
                return (*fit, alt)
    return Rs, s, t, agree, sol


def _add_window(R: FloatArray, c: FloatArray, done: np.ndarray, window: Window,
                solution: tuple[FloatArray, FloatArray], prev_start: int,
                refine: RefineFn | None, max_disagreement_deg: float | None,
                other: Callable[[], tuple[FloatArray, FloatArray] | None] | None
                ) -> str | None:
    """:func:`chain_windows`' step: ``window``'s ``solution`` turned and scaled onto the chain
    by its shared frames and its new frames added to ``R``, ``c``, ``done`` (in place; the
    first window as it is), then refined locally; None, or why the window is skipped."""
    rot_w, pos_w = solution
    fr = window.frames
    if not done.any():
        R[fr], c[fr] = rot_w, pos_w
        done[fr] = True
        return None
    shared = fr[done[fr]]
    if len(shared) < 3:
        return f"shares {len(shared)} frames with the chain (a window before it was " \
               f"skipped); need 3"
    Rs, s, t, agree, (rot_w, pos_w) = _fit_or_resolve(
        R[shared], c[shared], (rot_w, pos_w), shared - window.start, max_disagreement_deg,
        other)
    if not agree:
        return (f"its rotations disagree with the chain's on the shared frames by more than "
                f"{max_disagreement_deg} deg")
    new = fr[~done[fr]]
    jdx = new - window.start
    R[new] = Rs @ rot_w[jdx]
    c[new] = s * pos_w[jdx] @ Rs.T + t
    if refine is not None:
        new = _refined_locally(refine, R, c, done, new, prev_start, window.stop)
    done[new] = True
    return None


def chain_windows(num_frames: int, windows: list[Window],
                  solutions: list[tuple[FloatArray, FloatArray] | None],
                  refine: RefineFn | None = None,
                  max_disagreement_deg: float | None = None,
                  resolve: Callable[[int], tuple[FloatArray, FloatArray] | None] | None = None
                  ) -> Chain:
    """Chain per-window poses into one trajectory (world = the first chained window's frame 0).

    Args:
        num_frames: ``F``.
        windows: the windows, in order.
        solutions: per window ``(rotations (n,3,3), positions (n,3))`` world_from_cam in the
            window's own frame and scale, or None where the window could not be solved.
        refine: optional local refinement after each window is added:
            ``refine(rotations, positions, frames, old_frames) -> (rotations, positions,
            frames)`` adjusts the poses of ``frames`` (bool, the previous and the new window)
            keeping the gauge of ``old_frames`` (the frames chained before); it returns the
            frames it could estimate. Without it, errors of the windows accumulate.
        max_disagreement_deg: a window whose rotations, mapped onto the chain by the overlap's
            rotation, differ from the chained rotations by more than this (deg) on a shared
            frame is skipped (e.g. one frame of it flipped by 180 deg), as is a window left
            with fewer than 3 shared frames by a skipped one. None: no check.
        resolve: optional ``resolve(w)`` giving another solution of window ``w`` (or None),
            tried before a disagreeing window is skipped.

    Returns the :class:`Chain`. Only the longest run of windows linked by >= 3 shared frames is
    kept; the other frames are NaN and not estimated. Where windows overlap, the earlier
    window's poses stand.
    """
    R = np.full((num_frames, 3, 3), np.nan)
    c = np.full((num_frames, 3), np.nan)
    done = np.zeros(num_frames, bool)
    best, skipped = _longest_run(windows, solutions)
    if not best:
        return Chain(R, c, done, [], {})
    prev_start = windows[best[0]].start
    chained: list[int] = []
    for w in best:
        sol = solutions[w]
        assert sol is not None  # the runs hold solved windows only
        why = _add_window(R, c, done, windows[w], sol, prev_start, refine, max_disagreement_deg,
                          None if resolve is None else partial(resolve, w))
        if why is not None:
            skipped[w] = why
            continue
        prev_start = windows[w].start
        chained.append(w)
    return Chain(R, c, done, chained, skipped)
