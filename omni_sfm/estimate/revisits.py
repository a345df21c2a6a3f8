"""Revisits: a line seen again after the camera left it is joined to its first track.

The front end tracks a line while it stays in view; when the camera comes back (a loop around a
block, a return along a corridor) the same line starts a new track, and without a tie between
the two visits the walk's small drift stays in the result. After a global solution, each pair
of tracks that do not share a frame is a candidate when

- their 3D lines point the same way (within ``max_angle_deg``),
- they lie on each other: their perpendicular offset is within ``max_offset_deg`` seen from
  the later track's cameras plus ``max_drift`` of the path walked between the two visits (the
  drift a solution gathers grows with it),
- their seen parts overlap along the line (the extents the observations' rays mark on it,
  within a tenth of the later track's distance), and
- the later track has no second candidate nearly as close (``ambiguity``) on another line
  (tracks of the best candidate's line do not count): of two parallel edges a few centimetres
  apart (a door frame's), neither is joined where drift makes them indistinguishable.

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

from omni_sfm.geometry import FloatArray
from omni_sfm.lines.tracks import LineTracks


@dataclass(frozen=True, kw_only=True)
class RevisitOptions:
    """When two tracks are one line seen on two visits (module docstring)."""

    enabled: bool = True
    """Join revisited lines and solve again (where at least ``min_joins`` are joined: the
    problem is then solved twice; docs/estimator.md, step 5)."""
    min_joins: int = 8
    """A revisit is a place seen again, many of its lines at once: with fewer tracks joined
    (a line lost for a while and found again) the first solution stands, and its second solve
    is not paid for."""
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
    docstring), each later track at most once, in the order of the later track."""
    lo, hi, depth = line_extents(tracks, R, c, d, p)
    first, last = tracks.frame_spans()
    step = np.linalg.norm(np.diff(c, axis=0), axis=1)
    walked = np.r_[0.0, np.cumsum(np.where(np.isfinite(step), step, 0.0))]
    good = used & np.isfinite(lo) & np.isfinite(depth)
    idx = np.flatnonzero(good)
    cos_max = np.cos(np.radians(options.max_angle_deg))
    tan_off = np.tan(np.radians(options.max_offset_deg))
    pairs = []
    for b in idx[np.argsort(first[idx], kind="stable")]:
        cand = idx[last[idx] + options.min_gap_frames <= first[b]]
        if len(cand) == 0:
            continue
        cos = d[cand] @ d[b]
        cand, cos = cand[np.abs(cos) >= cos_max], cos[np.abs(cos) >= cos_max]
        if len(cand) == 0:
            continue
        da = d[cand] * np.sign(cos)[:, None]  # each earlier line's direction, turned to b's
        gap = p[b] - p[cand]
        offset = np.linalg.norm(gap - np.einsum("ki,ki->k", gap, da)[:, None] * da, axis=1)
        # b's seen part, on each earlier line (its parameter along d[cand])
        t0 = np.einsum("ki,ki->k", p[b] + lo[b] * d[b] - p[cand], d[cand])
        t1 = np.einsum("ki,ki->k", p[b] + hi[b] * d[b] - p[cand], d[cand])
        margin = 0.1 * depth[b]
        overlap = np.flatnonzero((np.maximum(t0, t1) >= lo[cand] - margin)
                                 & (np.minimum(t0, t1) <= hi[cand] + margin))
        if len(overlap) == 0:
            continue
        best = overlap[np.argmin(offset[overlap])]
        reach = tan_off * depth[b] + options.max_drift * (walked[first[b]]
                                                          - walked[last[cand[best]]])
        # the other lines there (not the best's line again, as a track of its own: within the
        # angle, the earlier tracks being solved together)
        gap = p[cand[overlap]] - p[cand[best]]
        apart = np.linalg.norm(gap - np.outer(gap @ da[best], da[best]), axis=1) > \
            tan_off * depth[b]
        rest = offset[overlap[apart]]
        if offset[best] > reach or (len(rest) and rest.min() < options.ambiguity * offset[best]):
            continue
        pairs.append((int(cand[best]), int(b)))
    return pairs


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
