"""Parts of a sequence: a stretch of frames as tracks of its own, runs of frames.

Parts with nothing in common (no line seen on both sides of a frame: two videos one after the
other) are posed each on its own (:mod:`omni_sfm.estimate.pipeline`), in worlds and scales of
their own.
"""

from __future__ import annotations

import numpy as np

from omni_sfm.lines.tracks import LineTracks


def frame_range(tracks: LineTracks, start: int, stop: int) -> tuple[LineTracks, np.ndarray]:
    """The observations of frames ``start..stop-1``, renumbered from 0 (timestamps kept), and
    for each of its tracks the index of the track in ``tracks``."""
    keep = np.flatnonzero((tracks.obs_frame >= start) & (tracks.obs_frame < stop))
    used = np.unique(tracks.obs_track[keep])
    return tracks.subset(keep, used, np.arange(start, stop)), used


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[(start, stop)]`` of the runs of True in ``mask``."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]
