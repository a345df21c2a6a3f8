"""Frames beyond the chained windows, registered from the lines already reconstructed
(docs/method.md §14, docs/estimator.md stage 5b).

The paper's method needs a window of frames in which 3 parallel and 3 other lines are seen
throughout; where tracks are short (a turn, a doorway) no window forms and the chain of windows
ends, although each frame there sees lines that neighbouring frames have already fixed in 3D.
:func:`extend_frames` grows the chain frame by frame, forwards then backwards: the next frame's
pose is predicted from its two neighbours (constant velocity and turn rate), then a local line
bundle adjustment over the last ``window`` estimated frames and the new one refines it (lines
the new frame shares with them are triangulated from their poses, the window's first pose and
its scale are held). The frame is kept if it sees enough lines fixed by the window and its
observations fit them as well as the window's own; the growth stops at the first frame that
does not (the caller reports it as not estimated).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.bundle import BundleOptions, bundle_adjust, observation_residuals
from omni_sfm.geometry import FloatArray
from omni_sfm.lines.tracks import LineTracks


@dataclass(frozen=True, kw_only=True)
class ExtendOptions:
    """Options of :func:`extend_frames`."""

    window: int = 12
    """Estimated frames next to the new one that take part in its local adjustment."""
    min_lines: int = 4
    """Lines a new frame must share with the window (fixed in 3D by it)."""
    max_residual_factor: float = 2.0
    """The new frame's median observation angle may be at most this times the window's."""
    min_residual_deg: float = 0.05
    """Floor of that limit (noise-free data), degrees."""
    iterations: int = 10
    """Levenberg-Marquardt iterations of each local adjustment."""


def _prediction(R: FloatArray, c: FloatArray, a: int, b: int) -> tuple[FloatArray, FloatArray]:
    """The pose one step beyond frame ``a`` away from ``b`` (constant velocity and turn)."""
    step = R[b].T @ R[a]
    return R[a] @ step, c[a] + (c[a] - c[b])


def _try_frame(tracks: LineTracks, R: FloatArray, c: FloatArray, frames: np.ndarray, f: int,
               near: np.ndarray, o: ExtendOptions, bundle: BundleOptions
               ) -> tuple[FloatArray, FloatArray] | None:
    """Poses of the window ``near`` and frame ``f`` after their local adjustment, or None when
    ``f`` is not fixed well by the lines of the window."""
    F, M = tracks.num_frames, tracks.num_tracks
    local = np.zeros(F, bool)
    local[near] = True
    local[f] = True
    shared = np.zeros(M, bool)
    seen_f = tracks.obs_track[tracks.obs_frame == f]
    in_window = np.bincount(tracks.obs_track[np.isin(tracks.obs_frame, near)], minlength=M)
    shared[seen_f] = in_window[seen_f] >= 2
    if shared.sum() < o.min_lines:
        return None
    try:
        res = bundle_adjust(tracks, R, c, np.full((M, 3), np.nan), np.full((M, 3), np.nan),
                            frames=local, scale_frames=local & frames, options=bundle)
    except OmniSfmError:
        return None
    if not res.frames[f]:
        return None
    ang = observation_residuals(tracks, res.rotations, res.positions, res.line_directions,
                                res.line_points)
    usable = res.used_tracks[tracks.obs_track] & np.isfinite(ang)
    mine = usable & (tracks.obs_frame == f)
    theirs = usable & np.isin(tracks.obs_frame, near)
    if mine.sum() < o.min_lines or not theirs.any():
        return None
    limit = max(o.max_residual_factor * float(np.median(ang[theirs])),
                np.radians(o.min_residual_deg))
    if float(np.median(ang[mine])) > limit:
        return None
    return res.rotations, res.positions


def extend_frames(tracks: LineTracks, rotations: FloatArray, positions: FloatArray,
                  frames: np.ndarray, bundle: BundleOptions,
                  options: ExtendOptions | None = None
                  ) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Grow the estimated frames ``frames`` (``(F,)`` bool, a contiguous chain) forwards and
    backwards by registering each next frame from the lines of its estimated neighbours.

    Returns the poses (``(F, 3, 3)``, ``(F, 3)``; those of the window frames adjusted along)
    and the new ``frames``.
    """
    o = options or ExtendOptions()
    local_opts = replace(bundle, max_rounds=2, max_iterations=o.iterations, final_loss=None)
    R, c = np.array(rotations, dtype=np.float64), np.array(positions, dtype=np.float64)
    frames = np.array(frames, bool)
    F = tracks.num_frames
    for forward in (True, False):
        while True:
            est = np.flatnonzero(frames)
            if len(est) < 3:
                return R, c, frames
            f = int(est[-1] + 1) if forward else int(est[0] - 1)
            if not 0 <= f < F:
                break
            near = est[-o.window:] if forward else est[:o.window]
            a, b = (int(est[-1]), int(est[-2])) if forward else (int(est[0]), int(est[1]))
            R_try, c_try = R.copy(), c.copy()
            R_try[f], c_try[f] = _prediction(R, c, a, b)
            got = _try_frame(tracks, R_try, c_try, frames, f, near, o, local_opts)
            if got is None:
                break
            R_new, c_new = got
            moved = np.concatenate([near, [f]])
            R[moved], c[moved] = R_new[moved], c_new[moved]
            frames[f] = True
    return R, c, frames
