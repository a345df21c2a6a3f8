"""The metric scale of a rig's start: its lens offsets in the linear positions' unit.

A rig of lenses (:class:`~omni_sfm.cameras.RigCamera`, raw dual-fisheye frames) takes each
observation from its lens's centre, ``c_f + R_f o`` with ``o`` in metres
(``LineTracks.obs_offset``). The linear positions have a length unit of their own (``sum |c|^2
= 1``); against them the offsets enter as ``lam o``, ``lam`` the units per metre.
:func:`offset_scale` finds ``lam`` at given poses as the minimum of the robust cost over
``lam`` (every line triangulated again from the lens centres), on a log grid then by golden
section; the global estimator divides the linear positions by it, and its adjustment goes on
in metres with the scale free (docs/estimator.md, "Rigs").

Lines much farther than the baseline hardly see it: the cost is then flat in ``lam``
(:attr:`OffsetScale.fixed` False), the offsets too small to matter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omni_sfm.estimate.bundle import (
    side_votes,
    triangulate_lines,
    truncated_cost,
)
from omni_sfm.geometry import FloatArray, predicted_normals
from omni_sfm.lines.tracks import LineTracks

# the grid of lam * baseline / (median camera-line distance), log-spaced
GRID_LOW, GRID_HIGH, GRID_POINTS = 1e-4, 1.0, 33
GOLDEN_STEPS = 30
# lam counts as fixed when its relative standard deviation is at most this
FIXED_REL_SD = 0.25


@dataclass(frozen=True)
class OffsetScale:
    """``scale``: units per metre (``lam``); ``rel_sd``: its relative standard deviation from
    the cost's curvature at the poses held (inf where the cost is flat); ``fixed``: whether
    the lines fix it (``rel_sd <= FIXED_REL_SD``)."""

    scale: float
    rel_sd: float

    @property
    def fixed(self) -> bool:
        return self.rel_sd <= FIXED_REL_SD


def baseline_m(tracks: LineTracks) -> float:
    """The largest distance (metres) of a lens centre from their mean: 0 for a central camera."""
    if tracks.obs_offset is None or tracks.num_observations == 0:
        return 0.0
    lenses = np.unique(np.round(tracks.obs_offset, 9), axis=0)
    return float(np.max(np.linalg.norm(lenses - lenses.mean(0), axis=1)))


def _cost(tracks: LineTracks, R: FloatArray, c: FloatArray, frames: np.ndarray, lam: float,
          limit: float) -> float:
    return truncated_cost(tracks.with_offset_scale(lam), R, c, frames, limit)


def offset_scale(tracks: LineTracks, R: FloatArray, c: FloatArray, frames: np.ndarray,
                 limit: float) -> OffsetScale:
    """``lam`` minimising :func:`~omni_sfm.estimate.bundle.truncated_cost` (angles capped at
    ``limit`` radians) of the tracks with offsets ``lam o`` at the poses ``R, c`` of
    ``frames`` (module docstring)."""
    b = baseline_m(tracks)
    d, p, ok = triangulate_lines(tracks.with_offset_scale(0.0), R, c, frames)
    sel = np.flatnonzero(frames[tracks.obs_frame] & ok[tracks.obs_track])
    if b <= 0 or sel.size == 0:
        return OffsetScale(0.0, math.inf)
    f, t = tracks.obs_frame[sel], tracks.obs_track[sel]
    dist = np.linalg.norm(predicted_normals(R[f], c[f], p[t], d[t]), axis=1)
    unit = float(np.median(dist)) / b  # lam at which the baseline spans the median distance
    logs = np.linspace(math.log(GRID_LOW), math.log(GRID_HIGH), GRID_POINTS)
    costs = [_cost(tracks, R, c, frames, unit * math.exp(x), limit) for x in logs]
    i = int(np.argmin(costs))
    lo, hi = logs[max(i - 1, 0)], logs[min(i + 1, GRID_POINTS - 1)]
    g = (math.sqrt(5.0) - 1.0) / 2.0
    x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
    f1, f2 = (_cost(tracks, R, c, frames, unit * math.exp(x), limit) for x in (x1, x2))
    for _ in range(GOLDEN_STEPS):
        if f1 <= f2:
            hi, x2, f2 = x2, x1, f1
            x1 = hi - g * (hi - lo)
            f1 = _cost(tracks, R, c, frames, unit * math.exp(x1), limit)
        else:
            lo, x1, f1 = x1, x2, f2
            x2 = lo + g * (hi - lo)
            f2 = _cost(tracks, R, c, frames, unit * math.exp(x2), limit)
    x = x1 if f1 <= f2 else x2
    return scale_spread(tracks, R, c, frames, limit, unit * math.exp(x))


def scale_spread(tracks: LineTracks, R: FloatArray, c: FloatArray, frames: np.ndarray,
                 limit: float, scale: float) -> OffsetScale:
    """``scale`` with its relative standard deviation at the poses ``R, c`` held: from the
    curvature in ``log scale`` of the negative log-likelihood ``N cost / cost`` (``N``
    observations, :func:`~omni_sfm.estimate.bundle.truncated_cost` capped at ``limit``)."""
    h = 0.05
    best, up, down = (_cost(tracks, R, c, frames, scale * math.exp(s), limit)
                      for s in (0.0, h, -h))
    curv = (up + down - 2.0 * best) / (h * h)
    n = int(frames[tracks.obs_frame].sum())
    rel_sd = math.sqrt(best / (n * curv)) if curv > 0 and best > 0 else math.inf
    return OffsetScale(scale, rel_sd)


def facing_lines(tracks: LineTracks, R: FloatArray, c: FloatArray, frames: np.ndarray,
                 points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The positions ``c`` and line ``points`` reflected through the first posed frame's centre
    where the observations' rays see more of the lines behind than in front of their cameras
    (the reflection that normals alone leave open: the lens offsets are not symmetric under
    it, so it is settled before their scale)."""
    d, p, ok = triangulate_lines(tracks.with_offset_scale(0.0), R, c, frames)
    front, behind = side_votes(tracks.with_offset_scale(0.0), R, c, d, p, frames, ok)
    if behind <= front:
        return c, points
    o = c[np.flatnonzero(frames)[0]].copy()
    return 2.0 * o - c, 2.0 * o - points


__all__ = ["OffsetScale", "baseline_m", "facing_lines", "offset_scale", "scale_spread"]
