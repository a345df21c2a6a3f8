"""Revisits: a line seen again after the camera left it is joined to its first track.

The front end tracks a line while it stays in view; when the camera comes back (a loop around a
block, a return along a corridor) the same line starts a new track, and without a tie between
the two visits the walk's small drift stays in the result. After a global solution, each pair
of tracks that do not share a frame is a candidate when

- their 3D lines point the same way (within ``max_angle_deg``),
- they lie on each other: their perpendicular offset (across their mean direction) is within
  ``max_offset_deg`` seen from the cameras of the track farther from its line plus
  ``max_drift`` of the path walked between the two visits (the drift a solution gathers
  grows with it),
- their seen parts overlap along the line (the extents the observations' rays mark on it,
  within a tenth of that distance),
- neither has a second candidate nearly as close (``ambiguity``) on another line (tracks of
  the best candidate's line do not count): of two parallel edges a few centimetres apart (a
  door frame's), neither is joined where drift makes them indistinguishable, and
- each is the other's best candidate (the later track's among the tracks before it, the
  earlier's among those after it).

Every measure is the same for the pair whichever track comes first; the solution it is
measured on differs in its last digits between frame orders, so a pair near a threshold can be
joined one way and not the other (the 2,000-frame office walk: 8 tracks forward, 11 reversed),
which ``min_joins`` keeps from a second solve.

The joins are made only where the later track begins at least ``min_gap_frames`` after the
earlier one ends (a revisit, not the front end losing a line for a moment), and never between
two tracks that saw one frame; the estimator solves again only where at least ``min_joins``
tracks are joined (a place seen again, not a line found again: :func:`revisit_groups`).
:func:`join_revisits` merges the tracks of each group into one and gives the merged track of
each original one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omni_sfm.geometry import FloatArray, normalize
from omni_sfm.lines.tracks import LineTracks


@dataclass(frozen=True, kw_only=True)
class RevisitOptions:
    """When two tracks are one line seen on two visits (module docstring)."""

    enabled: bool = True
    """Join revisited lines and solve again (where at least ``min_joins`` are joined: the
    problem is then solved twice; docs/estimator.md, step 5)."""
    min_joins: int = 16
    """A revisit is a place seen again, many of its lines at once: with fewer tracks joined
    (a line lost for a while and found again) the first solution stands, and its second solve
    is not paid for. The loops around a block join 24-86; the 2,000-frame office walk, which
    never comes back, 8 forward and 11 reversed (solving those again costs 46 s and puts the
    two orders 0.32 deg apart)."""
    min_gap_frames: int = 30
    """The later track begins at least this many frames after the earlier one ends."""
    max_angle_deg: float = 1.0
    """Largest angle between the two lines' directions."""
    max_offset_deg: float = 0.5
    """Largest perpendicular offset between the two lines: this angle at the median distance
    of the later track's cameras from its line ..."""
    max_drift: float = 0.005
    """... plus this share of the path walked between the two visits (the drift the solution
    may have gathered in between)."""
    ambiguity: float = 3.0
    """A second candidate for the same later track must be this many times farther off."""

    def __post_init__(self) -> None:
        if self.min_gap_frames < 1:
            raise ValueError(f"min_gap_frames must be >= 1, got {self.min_gap_frames!r}")
        if self.min_joins < 1:
            raise ValueError(f"min_joins must be >= 1, got {self.min_joins!r}")
        for name in ("max_angle_deg", "max_offset_deg", "max_drift"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if not self.ambiguity >= 1:
            raise ValueError(f"ambiguity must be >= 1, got {self.ambiguity!r}")


def line_extents(tracks: LineTracks, R: FloatArray, c: FloatArray, d: FloatArray,
                 p: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per track: ``(lo, hi, depth)``, the interval ``p + t d`` (``lo <= t <= hi``) that the
    observations' rays meet (their closest points on the line) and the median distance of the
    observing cameras from the line; NaN for a track without a line, a posed observation or
    rays."""
    m = tracks.num_tracks
    lo, hi, depth = np.full(m, np.nan), np.full(m, np.nan), np.full(m, np.nan)
    if tracks.obs_ray is None:
        return lo, hi, depth
    t, f = tracks.obs_track, tracks.obs_frame
    ok = np.isfinite(d[t]).all(axis=1) & np.isfinite(c[f]).all(axis=1)
    t, f = t[ok], f[ok]
    w = np.einsum("kij,kj->ki", R[f], tracks.obs_ray[ok])
    dt, r = d[t], p[t] - c[f]
    b = np.einsum("ki,ki->k", dt, w)
    denom = 1.0 - b**2
    seen = denom > 1e-6  # a ray along the line marks no point of it
    u = (b * np.einsum("ki,ki->k", w, r) - np.einsum("ki,ki->k", dt, r)) / np.where(seen, denom,
                                                                                     1.0)
    off = r - np.einsum("ki,ki->k", r, dt)[:, None] * dt
    dist = np.linalg.norm(off, axis=1)
    order = np.argsort(t, kind="stable")
    t, u, dist, seen = t[order], u[order], dist[order], seen[order]
    starts = np.flatnonzero(np.r_[True, np.diff(t) != 0])
    for a, z in zip(starts, np.r_[starts[1:], len(t)], strict=True):
        k = t[a]
        depth[k] = float(np.median(dist[a:z]))
        if seen[a:z].any():
            lo[k], hi[k] = float(u[a:z][seen[a:z]].min()), float(u[a:z][seen[a:z]].max())
    return lo, hi, depth


def revisit_pairs(tracks: LineTracks, R: FloatArray, c: FloatArray, d: FloatArray,
                  p: FloatArray, used: np.ndarray, options: RevisitOptions
                  ) -> list[tuple[int, int]]:
    """``(earlier, later)`` track pairs that are one line seen on two visits (module
    docstring), in the order of the later track: each the other's best match, the later
    track's among the tracks before it and the earlier's among those after it (:meth:`_Lines.best`),
    and every measure symmetric in the two tracks, so that the same pairs are found whichever
    way the frames run."""
    lo, hi, depth = line_extents(tracks, R, c, d, p)
    first, last = tracks.frame_spans()
    step = np.linalg.norm(np.diff(c, axis=0), axis=1)
    walked = np.r_[0.0, np.cumsum(np.where(np.isfinite(step), step, 0.0))]
    good = used & np.isfinite(lo) & np.isfinite(depth)
    idx = np.flatnonzero(good)
    lines = _Lines(d, p, lo, hi, depth, walked, first, last, options)
    pairs = []
    for b in idx[np.argsort(first[idx], kind="stable")]:
        a = lines.best(int(b), idx[last[idx] + options.min_gap_frames <= first[b]])
        if a is not None and \
                lines.best(a, idx[first[idx] >= last[a] + options.min_gap_frames]) == b:
            pairs.append((a, int(b)))
    return pairs


@dataclass(frozen=True)
class _Lines:
    """The solution's lines (``d, p``), their seen parts (``lo, hi``) and depths, the path
    walked to each frame and each track's frame span: what :meth:`best` measures pairs on."""

    d: FloatArray
    p: FloatArray
    lo: FloatArray
    hi: FloatArray
    depth: FloatArray
    walked: FloatArray
    first: np.ndarray
    last: np.ndarray
    options: RevisitOptions

    def best(self, b: int, cand: np.ndarray) -> int | None:
        """The track of ``cand`` that is ``b``'s line seen on another visit, or None: the
        candidate within the angle whose seen part overlaps ``b``'s with the least offset,
        within the reach (the angle at the deeper track's depth plus the drift over the path
        walked between the visits), and no other line within ``ambiguity`` times that offset.
        Offsets are measured across the two lines' mean direction, parts and margins along
        it: the same for the pair whichever track is ``b``."""
        o = self.options
        d, p = self.d, self.p
        cos = d[cand] @ d[b]
        keep = np.abs(cos) >= np.cos(np.radians(o.max_angle_deg))
        cand, sign = cand[keep], np.sign(cos[keep])
        if len(cand) == 0:
            return None
        mean = normalize(d[cand] * sign[:, None] + d[b])  # the pair's direction, b's way
        gap = p[cand] - p[b]
        along = np.einsum("ki,ki->k", gap, mean)
        offset = np.linalg.norm(gap - along[:, None] * mean, axis=1)
        deep = np.maximum(self.depth[cand], self.depth[b])
        tan_off = np.tan(np.radians(o.max_offset_deg))
        # the seen parts along the pair's direction (from b's point; each line's own parameter
        # scaled by its direction's share of it)
        da, db = np.einsum("ki,ki->k", d[cand], mean), mean @ d[b]
        c0, c1 = along + self.lo[cand] * da, along + self.hi[cand] * da
        b0, b1 = self.lo[b] * db, self.hi[b] * db
        margin = 0.1 * deep
        overlap = np.flatnonzero((np.maximum(c0, c1) >= np.minimum(b0, b1) - margin)
                                 & (np.minimum(c0, c1) <= np.maximum(b0, b1) + margin))
        if len(overlap) == 0:
            return None
        best = overlap[np.argmin(offset[overlap])]
        a = int(cand[best])
        earlier, later = (a, b) if self.first[a] < self.first[b] else (b, a)
        between = abs(self.walked[self.first[later]] - self.walked[self.last[earlier]])
        reach = tan_off * deep[best] + o.max_drift * between
        # the other lines there (not the best's line again, as a track of its own)
        gap = p[cand[overlap]] - p[a]
        apart = np.linalg.norm(gap - np.outer(gap @ mean[best], mean[best]), axis=1) > \
            tan_off * deep[best]
        rest = offset[overlap[apart]]
        if offset[best] > reach or (len(rest) and rest.min() < o.ambiguity * offset[best]):
            return None
        return a


def groups_of(tracks: LineTracks, pairs: list[tuple[int, int]]) -> np.ndarray:
    """``(M,)`` each track's group (the index of its group's first track) after joining
    ``pairs`` in order, a join skipped where the two groups would see one frame twice."""
    group = np.arange(tracks.num_tracks)
    frames = {k: set(tracks.obs_frame[tracks.obs_track == k].tolist()) for pair in pairs
              for k in pair}

    def root(k: int) -> int:
        while group[k] != k:
            k = int(group[k])
        return k

    members: dict[int, set[int]] = {}
    for a, b in pairs:
        ra, rb = root(a), root(b)
        if ra == rb:
            continue
        seen_a = set().union(*(frames[k] for k in members.get(ra, {ra}) if k in frames))
        seen_b = set().union(*(frames[k] for k in members.get(rb, {rb}) if k in frames))
        if seen_a & seen_b:
            continue
        keep, drop = min(ra, rb), max(ra, rb)
        group[drop] = keep
        members[keep] = members.get(keep, {keep}) | members.pop(drop, {drop})
    return np.array([root(k) for k in range(tracks.num_tracks)], np.int64)


def join_revisits(tracks: LineTracks, group: np.ndarray) -> tuple[LineTracks, np.ndarray]:
    """The tracks with each group merged into one (the id of its first track), and ``(M,)``
    the merged track of each original one."""
    roots, merged_of = np.unique(group, return_inverse=True)
    t = merged_of[tracks.obs_track]
    order = np.lexsort((tracks.obs_frame, t))
    joined = LineTracks(
        num_frames=tracks.num_frames, track_ids=tracks.track_ids[roots].copy(),
        obs_track=t[order], obs_frame=tracks.obs_frame[order],
        obs_normal=tracks.obs_normal[order], timestamps=tracks.timestamps,
        obs_ray=None if tracks.obs_ray is None else tracks.obs_ray[order],
        obs_sigma=None if tracks.obs_sigma is None else tracks.obs_sigma[order],
        obs_offset=None if tracks.obs_offset is None else tracks.obs_offset[order])
    return joined, merged_of



def revisit_groups(tracks: LineTracks, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
                   used: np.ndarray, options: RevisitOptions) -> np.ndarray | None:
    """:func:`groups_of` the :func:`revisit_pairs` of a solution, or None where fewer than
    ``options.min_joins`` tracks would be joined (no place seen again: a line found again
    after a while is not worth solving the problem twice)."""
    group = groups_of(tracks, revisit_pairs(tracks, R, c, d, p, used, options))
    joins = tracks.num_tracks - len(np.unique(group))
    return group if joins >= options.min_joins else None
