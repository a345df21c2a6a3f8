"""Sparse index of the observations of a :class:`LineTracks` (docs/method.md §3).

Parallel-family detection only ever needs the observations of some tracks, the observations in
some frames, or one track's observation in one frame. This index answers the three from the flat
observation arrays, so nothing of size ``tracks x frames`` is built: memory and time are linear
in the number of observations (plus the number of frames).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix

from omni_sfm.geometry import FloatArray
from omni_sfm.lines.tracks import LineTracks

IntArray = np.ndarray


def concat_ranges(starts: IntArray, lengths: IntArray) -> IntArray:
    """The concatenation of ``arange(s, s + n)`` for every ``(s, n)`` of ``starts, lengths``."""
    starts = np.asarray(starts, dtype=np.int64)
    lengths = np.asarray(lengths, dtype=np.int64)
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    offsets = np.cumsum(lengths) - lengths
    return np.repeat(starts - offsets, lengths) + np.arange(total, dtype=np.int64)


@dataclass(frozen=True)
class ObsIndex:
    """The observations of ``M`` tracks in ``F`` frames, sorted by (track, frame) and indexed
    both ways.

    Attributes:
        num_tracks, num_frames: ``M`` and ``F``.
        track, frame: ``(K,)`` track and frame of each observation.
        normal: ``(K, 3)`` its unit normal.
        track_start: ``(M + 1,)`` the observations of track ``m`` are
            ``track_start[m]:track_start[m + 1]`` (in frame order).
        frame_obs: ``(K,)`` observation indices sorted by (frame, track); those of frame ``f``
            are ``frame_obs[frame_start[f]:frame_start[f + 1]]``.
        frame_start: ``(F + 1,)``.
        key: ``(K,)`` increasing ``track * F + frame`` (for look-ups).
    """

    num_tracks: int
    num_frames: int
    track: IntArray
    frame: IntArray
    normal: FloatArray
    track_start: IntArray
    frame_obs: IntArray
    frame_start: IntArray
    key: IntArray

    @classmethod
    def from_tracks(cls, tracks: LineTracks) -> ObsIndex:
        M, F = tracks.num_tracks, tracks.num_frames
        track = np.asarray(tracks.obs_track, dtype=np.int64)
        frame = np.asarray(tracks.obs_frame, dtype=np.int64)
        normal = np.asarray(tracks.obs_normal, dtype=np.float64)
        key = track * F + frame
        if key.size > 1 and np.any(np.diff(key) < 0):        # not sorted as documented
            order = np.argsort(key, kind="stable")
            track, frame, normal, key = track[order], frame[order], normal[order], key[order]
        track_start = np.searchsorted(track, np.arange(M + 1), side="left")
        frame_obs = np.lexsort((track, frame))
        frame_start = np.searchsorted(frame[frame_obs], np.arange(F + 1), side="left")
        return cls(M, F, track, frame, normal, track_start, frame_obs, frame_start, key)

    @property
    def lengths(self) -> IntArray:
        """``(M,)`` observations per track."""
        return np.diff(self.track_start)

    def of_tracks(self, tracks: IntArray) -> tuple[IntArray, IntArray]:
        """Observation indices of ``tracks`` (in the given order, each in frame order) and, for
        each, the position of its track in ``tracks``."""
        tracks = np.asarray(tracks, dtype=np.int64)
        n = self.track_start[tracks + 1] - self.track_start[tracks]
        return concat_ranges(self.track_start[tracks], n), \
            np.repeat(np.arange(len(tracks)), n)

    def in_frames(self, frames: IntArray) -> tuple[IntArray, IntArray]:
        """Observation indices in ``frames`` (in the given order, each in track order) and, for
        each, the position of its frame in ``frames``."""
        frames = np.asarray(frames, dtype=np.int64)
        n = self.frame_start[frames + 1] - self.frame_start[frames]
        return self.frame_obs[concat_ranges(self.frame_start[frames], n)], \
            np.repeat(np.arange(len(frames)), n)

    def lookup(self, tracks: IntArray, frames: IntArray) -> IntArray:
        """The observation of track ``tracks[i]`` in frame ``frames[i]``, or -1 if none."""
        want = np.asarray(tracks, dtype=np.int64) * self.num_frames + np.asarray(frames)
        if self.key.size == 0:
            return np.full(want.shape, -1, dtype=np.int64)
        pos = np.minimum(np.searchsorted(self.key, want), self.key.size - 1)
        return np.where(self.key[pos] == want, pos, -1)

    def visibility_matrix(self) -> csr_matrix:
        """Sparse ``(M, F)`` int32 matrix, 1 where a track is observed."""
        ones = np.ones(self.track.size, dtype=np.int32)
        vis = csr_matrix((ones, (self.track, self.frame)),
                         shape=(self.num_tracks, self.num_frames))
        vis.data = np.minimum(vis.data, 1)          # a frame listed twice is still one frame
        return vis
