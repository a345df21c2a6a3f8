"""Windows of frames: the paper's, and the layout of overlapping ones along a video.

The paper's method (:func:`omni_sfm.estimate.paper.estimate_paper`) needs every line in every
frame: its window is the stretch of frames and the tracks seen throughout it. The estimator
(:mod:`omni_sfm.estimate.pipeline`) runs it where one window covers the whole sequence.
:func:`window_starts` lays overlapping windows along a long video the same way in either
direction (the global estimator's windows start, the pose spread's windows).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omni_sfm.geometry import FloatArray, rotation_angle
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.vanishing import ParallelFamily


@dataclass(frozen=True)
class Window:
    """Frames ``start..stop-1`` and the tracks (indices into the full tracks) seen in all."""

    start: int
    stop: int
    tracks: np.ndarray

    @property
    def frames(self) -> np.ndarray:
        return np.arange(self.start, self.stop)


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


def window_starts(count: int, window: int, step: int | None = None) -> list[int]:
    """The first positions of windows of ``window`` among ``count`` items, each at most
    ``step`` after the one before (default ``window // 2``: overlapping by about half), spread
    evenly from 0 to ``count - window``; the layout of ``count`` items in reverse order is its
    mirror image (the same windows)."""
    if count <= window:
        return [0]
    span = count - window
    n = -(-span // max(1, window // 2 if step is None else step)) + 1
    return [(i * span) // (n - 1) if 2 * i <= n - 1 else span - ((n - 1 - i) * span) // (n - 1)
            for i in range(n)]
