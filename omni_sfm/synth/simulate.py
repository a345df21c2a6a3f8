"""Simulated line observations with exact ground truth (the paper's Sec. VII set-up and more).

Two worlds (:attr:`SimulationOptions.world`):

- ``random`` (the default): a smooth camera path with full 3D rotation and translation, ``P``
  parallel 3D lines sharing one direction and ``Q`` lines in other directions, observed as unit
  plane normals (NVs) in each camera frame, with Gaussian angular noise, optional outlier tracks
  (wrong correspondences from some frame on) and optional partial visibility (each line seen in
  a window of frames).
- ``manhattan``: a long walk through office corridors (:func:`simulate_manhattan`): lines in
  the three Manhattan directions on the walls, floor and ceiling along a route with 90 deg
  turns, each seen only while the camera is near it. Only the visible observations are
  generated (sparse), so 20,000 frames and thousands of lines take a few seconds and tens of MB.

World = the first camera's frame.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import atomic_write_text, dumps_json
from omni_sfm.folders import SimulationFolder
from omni_sfm.geometry import (
    FloatArray,
    line_plane_normals,
    normalize,
    rotation_about_axis,
    rotvec_to_matrix,
)
from omni_sfm.lines.tracks import LineTracks, make_tracks, write_tracks
from omni_sfm.poses import Trajectory, write_tum

WORLDS = ("random", "manhattan")
"""The simulated worlds (:attr:`SimulationOptions.world`)."""


@dataclass(frozen=True, kw_only=True)
class SimulationOptions:
    num_views: int = 20
    """Number of viewpoints (frames)."""
    num_parallel: int = 20
    """Lines sharing the parallel direction (the family the method detects)."""
    num_other: int = 20
    """Lines in other directions (random, at least 20 deg away from the parallel one)."""
    noise_deg: float = 0.0
    """Std-dev of the angular Gaussian noise on each normal, degrees."""
    outlier_fraction: float = 0.0
    """Share of tracks that switch to a different 3D line from a random frame on."""
    visible_frames: int | None = None
    """If set, each line is seen only in about this many consecutive frames."""
    path_length: float = 1.0
    """Approximate length of the camera path (the scale of the scene)."""
    rotation_deg: float = 30.0
    """Amplitude of the smooth rotation about every axis over the sequence, degrees."""
    line_distance: tuple[float, float] = (0.8, 3.0)
    """Range of distances of lines from the camera path, in path-length units; with
    ``visible_frames`` in units of the stretch of path seen while a line is visible
    (``path_length * visible_frames / num_views``), so lines stay near the part of the path
    that sees them and can be triangulated from it."""
    seed: int = 0
    world: str = "random"
    """``"random"`` (the paper's set-up, the fields above) or ``"manhattan"`` (a corridor walk,
    :func:`simulate_manhattan`; there ``path_length`` is the route length in metres,
    ``visible_frames`` defaults to 60, ``line_density`` sets the number of lines, and
    ``num_parallel``, ``num_other``, ``rotation_deg``, ``line_distance`` and ``sparse`` are not
    used)."""
    sparse: bool = False
    """``random`` world: generate only the visible observations instead of dense ``(M, F)``
    arrays (for long sequences with ``visible_frames``). The same lines, path, visibility and
    outliers as without it, but other noise and normal signs (other random draws)."""
    line_density: float = 3.5
    """``manhattan`` world: 3D lines per metre of route (about 40 % vertical). A frame sees
    about ``line_density * visible_frames * path_length / num_views`` of them."""


@dataclass(frozen=True)
class Simulation:
    """A simulated sequence.

    Attributes:
        tracks: the observations (parallel lines first, then the others, ids 0..M-1).
        groundtruth: world_from_cam of every frame (world = first camera).
        line_points: ``(M, 3)`` a point of each true 3D line (world).
        line_directions: ``(M, 3)`` unit direction of each true line (world).
        parallel: ``(M,)`` bool, member of the parallel family.
        outlier: ``(M,)`` bool, track corrupted by a wrong correspondence.
        parallel_direction: ``(3,)`` unit direction of the family (world).
    """

    tracks: LineTracks
    groundtruth: Trajectory
    line_points: FloatArray
    line_directions: FloatArray
    parallel: np.ndarray
    outlier: np.ndarray
    parallel_direction: FloatArray


def smooth_path(num_views: int, path_length: float, rotation_deg: float,
                rng: np.random.Generator) -> Trajectory:
    """A smooth path with motion along all axes and yaw, pitch and roll; world = first camera."""
    s = np.linspace(0.0, 1.0, num_views)
    main = normalize(rng.normal(size=3))
    pos = s[:, None] * main * path_length
    for _ in range(3):
        amp = rng.uniform(0.05, 0.15) * path_length * normalize(rng.normal(size=3))
        pos = pos + np.sin(np.pi * rng.uniform(0.5, 2.0) * s + rng.uniform(0, 2 * np.pi))[:, None] \
            * amp
    rv = np.zeros((num_views, 3))
    for ax in range(3):
        f, ph = rng.uniform(0.3, 1.5), rng.uniform(0, 2 * np.pi)
        rv[:, ax] = np.radians(rotation_deg) * np.sin(np.pi * f * s + ph)
    R = rotvec_to_matrix(rv)
    R0, p0 = R[0].copy(), pos[0].copy()
    return Trajectory(np.arange(num_views, dtype=np.float64), R0.T @ R, (pos - p0) @ R0)


def _lines_near_path(n: int, centres: FloatArray, dirs: FloatArray, dist: tuple[float, float],
                     rng: np.random.Generator) -> FloatArray:
    """A point on each line, at a random distance from its anchor point on the path."""
    off = rng.normal(size=(n, 3))
    off -= np.sum(off * dirs, axis=1, keepdims=True) * dirs
    off = normalize(off) * rng.uniform(*dist, size=(n, 1))
    return centres + off


def _observe(gt: Trajectory, frames: np.ndarray, points: FloatArray, directions: FloatArray,
             noise_deg: float, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """``(K, 3)`` NVs of the lines through ``points`` along ``directions`` seen from
    ``frames`` (camera frame), with angular noise and a random sign each (sparse), and the
    ``(K, 3)`` ray from the camera to the line's point closest to it (camera frame, unit; as
    the front end's ray to a point of the segment it saw, it tells on which side of the camera
    the line lies)."""
    n_world = normalize(line_plane_normals(gt.positions[frames], points, directions))
    n_cam = np.einsum("kji,kj->ki", gt.rotations[frames], n_world)
    if noise_deg > 0:
        axis = normalize(np.cross(n_cam, rng.normal(size=n_cam.shape)))
        ang = np.radians(noise_deg) * rng.normal(size=(n_cam.shape[0], 1))
        n_cam = n_cam * np.cos(ang) + np.cross(axis, n_cam) * np.sin(ang)
    n_cam *= rng.choice([-1.0, 1.0], size=(n_cam.shape[0], 1))
    return n_cam, _side_rays(gt, frames, points, directions, n_cam)


def _side_rays(gt: Trajectory, frames: np.ndarray, points: FloatArray, directions: FloatArray,
               normals: FloatArray) -> FloatArray:
    """``(K, 3)`` the ray from each camera of ``frames`` to its line's point nearest it (camera
    frame, unit), projected into the plane of its (noisy) normal, as a front end's ray lies in
    the plane it fitted: it tells on which side of the camera the line lies."""
    off = points - gt.positions[frames]
    off -= np.einsum("ki,ki->k", off, directions)[:, None] * directions
    rays = np.einsum("kji,kj->ki", gt.rotations[frames], off)
    return normalize(rays - np.einsum("ki,ki->k", rays, normals)[:, None] * normals)


def _check_options(opts: SimulationOptions) -> None:
    """Refuse options no simulation can follow (one-line :class:`OmniSfmError`)."""
    if opts.world not in WORLDS:
        raise OmniSfmError(f"world must be one of {', '.join(WORLDS)}, got {opts.world!r}")
    if opts.num_views < 3:
        raise OmniSfmError(f"need at least 3 views, got {opts.num_views}")
    if opts.world == "random" and (opts.num_parallel < 0 or opts.num_other < 0
                                   or opts.num_parallel + opts.num_other < 1):
        raise OmniSfmError("need a positive number of lines")
    if not opts.noise_deg >= 0:
        raise OmniSfmError(f"noise must be >= 0 degrees, got {opts.noise_deg}")
    if not 0 <= opts.outlier_fraction < 1:
        raise OmniSfmError(f"outlier fraction must be in [0, 1), got {opts.outlier_fraction}")
    if opts.visible_frames is not None and not 3 <= opts.visible_frames <= opts.num_views:
        raise OmniSfmError(f"visible frames must be in [3, {opts.num_views}] (the number of "
                           f"views), got {opts.visible_frames}")


def simulate(opts: SimulationOptions) -> Simulation:
    """Run the simulation described by ``opts`` (seeded, reproducible)."""
    _check_options(opts)
    if opts.world == "manhattan":
        return simulate_manhattan(opts)
    rng = np.random.default_rng(opts.seed)
    gt = smooth_path(opts.num_views, opts.path_length, opts.rotation_deg, rng)
    F, P, Q = opts.num_views, opts.num_parallel, opts.num_other
    M = P + Q
    v = normalize(rng.normal(size=3))
    dirs = _line_directions(v, P, M, rng)
    # each line is anchored near a frame; with partial visibility it is seen around that frame
    if opts.visible_frames is None:
        anchor = rng.integers(0, F, size=M)
    else:
        # each kind spread evenly along the path, so that every stretch sees both kinds
        anchor = np.concatenate([rng.permutation(np.linspace(0, F - 1, n).round().astype(int))
                                 for n in (P, Q)])
    scale = opts.path_length
    if opts.visible_frames is not None:
        scale *= opts.visible_frames / F
    pts = _lines_near_path(M, gt.positions[anchor], dirs,
                           (opts.line_distance[0] * scale, opts.line_distance[1] * scale), rng)
    pts += dirs * rng.uniform(-0.5, 0.5, size=(M, 1)) * scale
    vis, start = _visibility(opts, anchor, M, F, rng)

    outlier = np.zeros(M, dtype=bool)
    n_out = int(round(opts.outlier_fraction * M))
    if n_out:
        outlier[rng.choice(M, size=n_out, replace=False)] = True
    if opts.sparse:
        tracks = _sparse_tracks(opts, gt, pts, dirs, outlier, start, scale, rng)
    else:
        tracks = _dense_tracks(opts, gt, pts, dirs, outlier, vis, scale, rng)
    return Simulation(tracks, gt, pts, dirs, np.arange(M) < P, outlier, v)


def _line_directions(v: FloatArray, P: int, M: int, rng: np.random.Generator) -> FloatArray:
    """``(M, 3)``: ``P`` lines along ``v``, the others random and over 20 degrees off it."""
    dirs = np.empty((M, 3))
    dirs[:P] = v
    k = P
    while k < M:
        d = normalize(rng.normal(size=3))
        if abs(d @ v) < np.cos(np.radians(20.0)):
            dirs[k] = d
            k += 1
    return dirs


def _visibility(opts: SimulationOptions, anchor: np.ndarray, M: int, F: int,
                rng: np.random.Generator) -> tuple[np.ndarray, FloatArray | None]:
    """``(M, F)`` which frames see each line, and the first frame's (fractional) index of
    each line's run (None when every frame sees every line)."""
    if opts.visible_frames is None:
        return np.ones((M, F), dtype=bool), None
    half = opts.visible_frames / 2.0
    start = np.clip(anchor - half + rng.uniform(-0.2, 0.2, M) * half, 0, None)
    start = np.minimum(start, max(0.0, F - opts.visible_frames))
    fr = np.arange(F)
    vis = (fr[None, :] >= np.floor(start)[:, None]) & \
        (fr[None, :] < np.floor(start)[:, None] + opts.visible_frames)
    return vis, start


def _sparse_tracks(opts: SimulationOptions, gt: Trajectory, pts: FloatArray, dirs: FloatArray,
                   outlier: np.ndarray, start: FloatArray | None, scale: float,
                   rng: np.random.Generator) -> LineTracks:
    """The tracks built observation by observation (no ``(M, F)`` arrays); outlier lines
    switch to another line part-way along their run."""
    F, M = opts.num_views, len(pts)
    first = np.floor(start).astype(np.int64) if start is not None \
        else np.zeros(M, dtype=np.int64)
    count = F if opts.visible_frames is None else opts.visible_frames
    mm = np.repeat(np.arange(M), count)
    ff = first[mm] + np.tile(np.arange(count), M)
    o_pts, o_dirs = pts[mm], dirs[mm]
    for m in np.flatnonzero(outlier):
        seen = np.arange(first[m], first[m] + count)
        switch = seen[rng.integers(len(seen) // 4,
                                   max(len(seen) // 4 + 1, 3 * len(seen) // 4))]
        other = normalize(rng.normal(size=3))
        sel = (mm == m) & (ff >= switch)
        o_dirs[sel] = other
        o_pts[sel] = _lines_near_path(1, gt.positions[[switch]], other[None],
                                      (0.8 * scale, 2.0 * scale), rng)[0]
    n_obs, rays = _observe(gt, ff, o_pts, o_dirs, opts.noise_deg, rng)
    return make_tracks(F, np.arange(M), mm, ff, n_obs, source="simulation", obs_ray=rays)


def _dense_tracks(opts: SimulationOptions, gt: Trajectory, pts: FloatArray, dirs: FloatArray,
                  outlier: np.ndarray, vis: np.ndarray, scale: float,
                  rng: np.random.Generator) -> LineTracks:
    """The tracks built from ``(M, F)`` arrays of every line in every frame; outlier lines
    switch to another line part-way along the frames that see them."""
    F, M = opts.num_views, len(pts)
    obs_pts = np.broadcast_to(pts[:, None, :], (M, F, 3)).copy()
    obs_dirs = np.broadcast_to(dirs[:, None, :], (M, F, 3)).copy()
    for m in np.flatnonzero(outlier):
        seen = np.flatnonzero(vis[m])
        switch = seen[rng.integers(len(seen) // 4, max(len(seen) // 4 + 1, 3 * len(seen) // 4))]
        other = normalize(rng.normal(size=3))
        obs_dirs[m, switch:] = other
        obs_pts[m, switch:] = _lines_near_path(1, gt.positions[[switch]], other[None],
                                               (0.8 * scale, 2.0 * scale), rng)[0]

    # NV in world: normal of the plane through the camera centre and the line
    c = gt.positions[None, :, :]
    n_world = normalize(line_plane_normals(c, obs_pts, obs_dirs))
    n_cam = np.einsum("fji,mfj->mfi", gt.rotations, n_world)
    if opts.noise_deg > 0:
        axis = normalize(np.cross(n_cam, rng.normal(size=n_cam.shape)))
        ang = np.radians(opts.noise_deg) * rng.normal(size=(M, F, 1))
        n_cam = n_cam * np.cos(ang) + np.cross(axis, n_cam) * np.sin(ang)
    n_cam *= rng.choice([-1.0, 1.0], size=(M, F, 1))
    mm, ff = np.nonzero(vis)
    rays = _side_rays(gt, ff, obs_pts[mm, ff], obs_dirs[mm, ff], n_cam[mm, ff])
    return make_tracks(F, np.arange(M), mm, ff, n_cam[mm, ff], source="simulation",
                       obs_ray=rays)


# --- the Manhattan world: a walk through office corridors ---------------------------------------

CORRIDOR_HALF_WIDTH = 1.0
"""Half the corridor width (m): walls 1 m either side of the route's centre line."""
CEILING_HEIGHT = 2.5
"""Ceiling height (m); the floor is at 0."""
EYE_HEIGHT = 1.5
"""Mean camera height (m)."""
LEG_LENGTH = (8.0, 25.0)
"""Range of the length of a straight corridor between two 90 deg turns (m)."""
NEAREST_MAX = 3.0
"""Lines that no camera comes this near (m) are not seen (those beyond the route's ends)."""
MIN_SUBTENSE_DEG = 5.0
"""A segment is seen only where it spans this angle or more (not end-on): a camera near the
extension of a line (a lintel beyond a corner) cannot see it."""
MANHATTAN_STEP = (0.001, 0.5)
"""Allowed distance walked per frame (m): ``path_length / (num_views - 1)``."""

# Elements per metre and the lines each holds. Along each wall, one after the other: a door
# (2 vertical edges and the lintel), a frame (poster, window, notice board: 2 vertical and 2
# horizontal edges) or a pillar (a column or recess: 2 vertical edges); over them, pieces of
# baseboard, rail or wall junction (1 horizontal line along the wall). Overhead: ceiling
# panels (2 edges across the corridor, 2 along it) and joints across the floor or the ceiling.
_WALL_ELEMENTS = (("door", 0.15, 3), ("frame", 0.10, 4), ("pillar", 0.15, 2))
_WALL_WIDTHS = np.array([0.9, 1.0, 0.3])
"""Mean width of each wall element (m)."""
_RATES = {"piece": 0.10, "light": 0.15, "seam": 0.30}
_BASE_DENSITY = 2 * (sum(r * n for _, r, n in _WALL_ELEMENTS) + _RATES["piece"]) \
    + 4 * _RATES["light"] + _RATES["seam"]
"""Lines per metre of corridor at these rates (both walls, floor and ceiling): 3.4."""


@dataclass(frozen=True)
class _Route:
    """A corridor route in the Manhattan world (metres, +Z up): straight legs joined by
    quarter circles of radius :data:`CORRIDOR_HALF_WIDTH` about the inner wall corners."""

    corners: FloatArray      # (L+1, 2) corner points P_k; leg k runs from P_k to P_k+1
    headings: FloatArray     # (L, 2) unit heading of each leg
    turns: np.ndarray        # (L-1,) +1 left, -1 right turn at P_k+1
    straight_s0: FloatArray  # (L,) arc length where each leg's straight part starts
    straight_u0: FloatArray  # (L,) leg coordinate u of that point (0, or the turn radius)
    total: float             # arc length of the whole centre line


def _left(h: FloatArray) -> FloatArray:
    return np.stack([-h[..., 1], h[..., 0]], -1)


def _manhattan_route(length: float, rng: np.random.Generator) -> _Route:
    """A staircase of corridors (turns alternate left and right, so the route never comes back
    on itself) at least ``length`` long."""
    r = CORRIDOR_HALF_WIDTH
    turn = float(rng.choice([-1.0, 1.0]))
    corners: list[FloatArray] = [np.zeros(2)]
    headings: list[FloatArray] = []
    turns: list[float] = []
    s0s: list[float] = []
    u0s: list[float] = []
    h = np.array([1.0, 0.0])
    s = 0.0
    while True:
        k = len(headings)
        leg = rng.uniform(*LEG_LENGTH)
        u0 = r if k else 0.0
        headings.append(h)
        s0s.append(s)
        u0s.append(u0)
        corners.append(corners[-1] + leg * h)
        straight = leg - u0 - r
        if s + straight >= length:
            break
        s += straight + np.pi * r / 2
        turns.append(turn)
        h = turn * _left(h)
        turn = -turn
    return _Route(np.array(corners), np.array(headings), np.array(turns), np.array(s0s),
                  np.array(u0s), float(length))


def _route_centre(route: _Route, s: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Centre-line point ``(N, 2)`` and heading angle ``(N,)`` at arc lengths ``s``."""
    r = CORRIDOR_HALF_WIDTH
    k = np.clip(np.searchsorted(route.straight_s0, s, side="right") - 1, 0, None)
    h = route.headings[k]
    theta = np.arctan2(h[:, 1], h[:, 0])
    du = s - route.straight_s0[k]
    start = route.corners[k] + route.straight_u0[k, None] * h
    pos = start + du[:, None] * h
    leg_len = np.linalg.norm(route.corners[k + 1] - route.corners[k], axis=1)
    straight = leg_len - route.straight_u0[k] - r
    on_arc = (du > straight) & (k < len(route.turns))
    if on_arc.any():
        ka = k[on_arc]
        sg = route.turns[ka]
        ha = h[on_arc]
        p_arc = route.corners[ka + 1] - r * ha          # where the arc starts
        centre = p_arc + sg[:, None] * r * _left(ha)     # the inner wall corner
        th = theta[on_arc] + sg * (du[on_arc] - straight[on_arc]) / r
        n_left = np.stack([-np.sin(th), np.cos(th)], -1)
        pos[on_arc] = centre - sg[:, None] * r * n_left
        theta[on_arc] = th
    return pos, np.unwrap(theta)


def _manhattan_path(route: _Route, s: FloatArray, rng: np.random.Generator) -> Trajectory:
    """Camera poses along ``route`` at arc lengths ``s`` (Manhattan world): constant speed,
    sway, bob, yaw along the route with small pitch, roll and glances. Camera axes: x forward,
    y left, z up (an upright omnidirectional camera)."""
    def wave(amp: float, wavelength: tuple[float, float]) -> FloatArray:
        lam = rng.uniform(*wavelength)
        return amp * np.sin(2 * np.pi * s / lam + rng.uniform(0, 2 * np.pi))

    centre, theta = _route_centre(route, s)
    lateral = wave(0.08, (8.0, 20.0)) + wave(0.04, (3.0, 6.0)) + wave(0.02, (1.3, 1.5))
    height = EYE_HEIGHT + wave(0.03, (5.0, 15.0)) + wave(0.015, (0.65, 0.75))
    n_left = np.stack([-np.sin(theta), np.cos(theta)], -1)
    pos = np.column_stack([centre + lateral[:, None] * n_left, height])
    yaw = theta + np.radians(wave(1.0, (4.0, 10.0)) + wave(0.5, (1.3, 1.5)))
    # glances: a look to the side of 3-8 deg every 8 m or so, for a metre or two
    n_glance = rng.poisson(max(route.total, 1.0) / 8.0)
    for c, w, a in zip(rng.uniform(0, route.total, n_glance), rng.uniform(0.4, 1.2, n_glance),
                       rng.choice([-1.0, 1.0], n_glance) * rng.uniform(3.0, 8.0, n_glance),
                       strict=True):
        lo, hi = np.searchsorted(s, [c - 4 * w, c + 4 * w])
        yaw[lo:hi] += np.radians(a) * np.exp(-0.5 * ((s[lo:hi] - c) / w) ** 2)
    pitch = np.radians(rng.uniform(-2.0, 2.0) + wave(1.5, (5.0, 12.0)) + wave(0.5, (0.65, 0.75)))
    roll = np.radians(rng.uniform(-1.0, 1.0) + wave(1.0, (5.0, 12.0)) + wave(0.7, (1.3, 1.5)))
    R = rotation_about_axis(np.array([0.0, 0.0, 1.0]), yaw) \
        @ rotation_about_axis(np.array([0.0, 1.0, 0.0]), pitch) \
        @ rotation_about_axis(np.array([1.0, 0.0, 0.0]), roll)
    return Trajectory(np.arange(len(s), dtype=np.float64), R, pos)


def _regular(lo: float, hi: float, spacing: float, rng: np.random.Generator) -> FloatArray:
    """Points from ``lo`` to ``hi``, ``spacing`` apart on average (each gap 0.25 to 1.75 times
    it: fairly regular, as lights and joints are)."""
    n = int((hi - lo) / spacing) + 2
    u = lo + np.cumsum(spacing * rng.uniform(0.25, 1.75, n))
    return u[u < hi]


_Segment = tuple[int, tuple[float, float, float], tuple[float, float, float], int]
"""Leg, start and end ``(u, lateral, z)`` in the leg's frame, family (0 vertical, 1 along the
leg, 2 across it)."""


def _wall_lines(k: int, lat: float, u_lo: float, u_hi: float, scale: float,
                rng: np.random.Generator) -> list[_Segment]:
    """The lines of one wall of leg ``k`` (at ``lat`` from the centre line, from ``u_lo`` to
    ``u_hi`` along the leg): elements one after the other, fairly regular (so that vertical
    edges are never far apart), and pieces of baseboard, rail or junction over them."""
    out: list[_Segment] = []
    top = CEILING_HEIGHT
    rates = np.array([e[1] for e in _WALL_ELEMENTS])
    gap = max(1.0 / (rates.sum() * scale) - float(rates @ _WALL_WIDTHS) / rates.sum(), 0.1)
    u = u_lo + gap * rng.uniform(0.25, 1.75)
    while u < u_hi - 0.3:
        kind = _WALL_ELEMENTS[rng.choice(len(rates), p=rates / rates.sum())][0]
        if kind == "door":
            w, z0, z1 = 0.9, 0.0, 2.1
            out.append((k, (u, lat, z1), (u + w, lat, z1), 1))
        elif kind == "frame":
            w, z0 = rng.uniform(0.5, 1.5), rng.uniform(0.8, 1.2)
            z1 = z0 + rng.uniform(0.5, 1.0)
            out += [(k, (u, lat, z0), (u + w, lat, z0), 1), (k, (u, lat, z1), (u + w, lat, z1), 1)]
        else:
            w, z0, z1 = 0.3, 0.0, top
        if u + w > u_hi:
            break
        out += [(k, (u, lat, z0), (u, lat, z1), 0), (k, (u + w, lat, z0), (u + w, lat, z1), 0)]
        u += w + gap * rng.uniform(0.25, 1.75)
    for u in _regular(u_lo, u_hi, 1.0 / (_RATES["piece"] * scale), rng):
        w, z0 = rng.uniform(0.8, 2.0), float(rng.choice([0.0, 0.1, 0.9, top]))
        out.append((k, (u, lat, z0), (min(u + w, u_hi), lat, z0), 1))
    return out


def _overhead_lines(k: int, u_lo: float, u_hi: float, scale: float,
                    rng: np.random.Generator) -> list[_Segment]:
    """Ceiling panels and floor or ceiling joints of leg ``k`` from ``u_lo`` to ``u_hi``."""
    r, top = CORRIDOR_HALF_WIDTH, CEILING_HEIGHT
    out: list[_Segment] = []
    for u in _regular(u_lo, u_hi, 1.0 / (_RATES["light"] * scale), rng):
        w = rng.uniform(0.6, 1.2)
        out += [(k, (u, -0.3, top), (u, 0.3, top), 2),
                (k, (u + w, -0.3, top), (u + w, 0.3, top), 2),
                (k, (u, -0.3, top), (u + w, -0.3, top), 1),
                (k, (u, 0.3, top), (u + w, 0.3, top), 1)]
    seams = _regular(u_lo, u_hi, 1.0 / (_RATES["seam"] * scale), rng)
    for u, z in zip(seams, rng.choice([0.0, top], len(seams)), strict=True):
        out.append((k, (u, -r, z), (u, r, z), 2))
    return out


def _manhattan_lines(route: _Route, density: float, rng: np.random.Generator
                     ) -> tuple[FloatArray, FloatArray, np.ndarray, FloatArray, FloatArray]:
    """Line segments on the walls, floor and ceiling of ``route``'s corridors.

    Returns start and end points ``(M, 3)``, family ``(M,)`` (0 vertical, 1 along the leg,
    2 across it), the arc-length range ``(M, 2)`` of the route beside each segment and its
    extent along the route ``(M,)`` (m).
    """
    r, top = CORRIDOR_HALF_WIDTH, CEILING_HEIGHT
    scale = density / _BASE_DENSITY
    n_legs = len(route.headings)
    segs: list[_Segment] = []
    for k in range(n_legs):
        leg = float(np.linalg.norm(route.corners[k + 1] - route.corners[k]))
        for side in (1.0, -1.0):
            # walls end at the inner corner (inside a turn) or the outer corner (outside it)
            u_lo = -5.0 if k == 0 else (r if side == route.turns[k - 1] else -r)
            u_hi = leg + 5.0 if k == n_legs - 1 else (leg - r if side == route.turns[k] else
                                                      leg + r)
            segs += _wall_lines(k, side * r, u_lo, u_hi, scale, rng)
        # floor and ceiling, over the leg and the squares of its turns
        segs += _overhead_lines(k, -5.0 if k == 0 else -r,
                                leg + 5.0 if k == n_legs - 1 else leg + r, scale, rng)
        if k < n_legs - 1:  # the vertical wall corners of the turn, inner and outer
            side = float(route.turns[k])
            segs += [(k, (leg - r, side * r, 0.0), (leg - r, side * r, top), 0),
                     (k, (leg + r, -side * r, 0.0), (leg + r, -side * r, top), 0)]
    kk = np.array([sg[0] for sg in segs], dtype=np.int64)
    a = np.array([sg[1] for sg in segs], dtype=np.float64).reshape(-1, 3)
    b = np.array([sg[2] for sg in segs], dtype=np.float64).reshape(-1, 3)
    fam = np.array([sg[3] for sg in segs], dtype=np.int64)
    h, p = route.headings[kk], route.corners[kk]
    n = _left(h)

    def world(x: FloatArray) -> FloatArray:
        return np.column_stack([p + x[:, :1] * h + x[:, 1:2] * n, x[:, 2]])

    u_min, u_max = np.minimum(a[:, 0], b[:, 0]), np.maximum(a[:, 0], b[:, 0])
    s_of_u0 = route.straight_s0[kk] - route.straight_u0[kk]   # s ~ s_of_u0 + u along leg k
    s_range = np.column_stack([s_of_u0 + u_min, s_of_u0 + u_max])
    return world(a), world(b), fam, s_range, u_max - u_min


def _segment_distance(c: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distance of points ``c`` from segments ``a``-``b`` (all ``(K, 3)``)."""
    ab = b - a
    t = np.clip(np.sum((c - a) * ab, axis=1) / np.sum(ab * ab, axis=1), 0.0, 1.0)
    return np.linalg.norm(c - a - t[:, None] * ab, axis=1)


def _manhattan_visibility(gt: Trajectory, s: FloatArray, start: FloatArray, end: FloatArray,
                          s_range: FloatArray, along: FloatArray, reach: float,
                          block: int = 200_000) -> tuple[np.ndarray, np.ndarray]:
    """The (line, frame) pairs that see each other, grouped by line: a camera sees a segment
    while it is within ``sqrt(r^2 + d^2)`` of it, ``d`` the segment's least distance from the
    route and ``r`` such that the route beside it, plus ``r`` either side, is ``reach`` long
    (and in every frame between the first and the last of those), where it spans
    :data:`MIN_SUBTENSE_DEG` or more.

    Only the frames beside each segment are tried, about ``block`` (line, frame) pairs at a
    time, so memory stays small for any number of frames."""
    step = s[1] - s[0]
    half = np.maximum(reach - along, reach / 3.0) / 2.0
    margin = half + NEAREST_MAX + 2.0                   # beyond every camera that can see it
    f_lo = np.clip(np.ceil((s_range[:, 0] - margin) / step), 0, len(s) - 1).astype(np.int64)
    f_hi = np.clip(np.floor((s_range[:, 1] + margin) / step), 0, len(s) - 1).astype(np.int64)
    count = np.maximum(f_hi - f_lo + 1, 0)
    ends = np.cumsum(count)
    out_m, out_f = [], []
    lo = 0
    while lo < len(count):
        hi = max(int(np.searchsorted(ends, ends[lo] - count[lo] + block, side="right")), lo + 1)
        cnt = count[lo:hi]
        mm = np.repeat(np.arange(lo, hi), cnt)
        offsets = np.cumsum(cnt) - cnt
        ff = f_lo[mm] + np.arange(len(mm)) - offsets[mm - lo]
        c = gt.positions[ff]
        dist = _segment_distance(c, start[mm], end[mm])
        to_a, to_b = start[mm] - c, end[mm] - c
        wide = np.linalg.norm(np.cross(to_a, to_b), axis=1) > \
            np.sin(np.radians(MIN_SUBTENSE_DEG)) * np.linalg.norm(to_a, axis=1) \
            * np.linalg.norm(to_b, axis=1)
        del to_a, to_b, c
        d_min = np.full(hi - lo, np.inf)
        if len(mm):
            d_min[cnt > 0] = np.minimum.reduceat(dist, offsets[cnt > 0])
        # lines the camera never comes near (beyond the route's ends) are not seen
        near = (dist <= np.sqrt(half[lo:hi] ** 2 + d_min**2)[mm - lo]) & \
            (d_min[mm - lo] <= NEAREST_MAX) & wide
        # one run of frames, from the first to the last near enough (the bob can cross the limit)
        first = np.full(hi - lo, len(s))
        last = np.full(hi - lo, -1)
        np.minimum.at(first, mm[near] - lo, ff[near])
        np.maximum.at(last, mm[near] - lo, ff[near])
        seen = (ff >= first[mm - lo]) & (ff <= last[mm - lo]) & wide
        out_m.append(mm[seen])
        out_f.append(ff[seen])
        lo = hi
    return np.concatenate(out_m), np.concatenate(out_f)


def simulate_manhattan(opts: SimulationOptions) -> Simulation:
    """A walk of ``opts.path_length`` metres through office corridors (``world="manhattan"``).

    The corridors are 2 m wide and 2.5 m high, straight for 8 to 25 m between 90 deg turns
    (left and right in turn, a staircase that never comes back on itself), the corners rounded
    to quarter circles of 1 m radius about the inner wall corner. The camera (axes x forward,
    y left, z up) walks the centre line at constant speed (``path_length / (num_views - 1)``
    metres per frame; 0.05 is a walk at 1.5 m/s filmed at 30 fps) at 1.5 m height, with a
    sway of about 0.15 m, a bob of a few cm, its yaw following the route plus glances of
    3-8 deg every 8 m or so, and pitch and roll of 1-4 deg.

    Lines (segments, on average ``line_density`` per metre of route) lie in the three Manhattan
    directions: vertical door edges, frame edges, pillars and wall corners (the parallel family,
    about half of them); along the corridor door lintels, frame edges, baseboards, rails and the
    junctions of the walls with the floor and the ceiling; across it ceiling panels and floor
    and ceiling joints. A line is seen while the camera is within a distance of it that makes
    the stretch of route seeing it ``visible_frames`` (default 60) frames long (about 1 to 3 m
    at the defaults: the walls and the ceiling are 1 m from the camera, the floor 1.5 m), in
    one run of frames, and only where it spans 5 deg or more (not end-on); lines seen in fewer
    than 3 frames (at the ends of the route) are left out. At the defaults a frame sees about
    10 lines (2 to 20), 5 of them vertical. Outlier tracks switch to another line seen at that
    frame. Only visible observations are generated: 20,000 frames take about 0.5 s.
    """
    _check_options(replace(opts, world="manhattan"))
    F = opts.num_views
    step = opts.path_length / (F - 1)
    if not MANHATTAN_STEP[0] <= step <= MANHATTAN_STEP[1]:
        raise OmniSfmError(
            f"manhattan world: path_length is the route length in metres; {opts.path_length:g} m "
            f"over {F} frames is {1000 * step:.3g} mm per frame, outside "
            f"[{1000 * MANHATTAN_STEP[0]:g}, {1000 * MANHATTAN_STEP[1]:g}] mm (a walk filmed "
            f"at 30 fps: 50 mm per frame, path_length={0.05 * (F - 1):g})")
    if not opts.line_density > 0:
        raise OmniSfmError(f"line density must be > 0, got {opts.line_density}")
    vf = min(60, F) if opts.visible_frames is None else opts.visible_frames
    rng = np.random.default_rng(opts.seed)
    route = _manhattan_route(opts.path_length, rng)
    s = np.arange(F, dtype=np.float64) * step
    gt = _manhattan_path(route, s, rng)
    start, end, fam, s_range, along = _manhattan_lines(route, opts.line_density, rng)
    mm, ff = _manhattan_visibility(gt, s, start, end, s_range, along, vf * step)
    # keep the lines seen in 3 frames or more; vertical ones first, then by place on the route
    count = np.bincount(mm, minlength=len(fam))
    keep = np.flatnonzero(count >= 3)
    keep = keep[np.lexsort((s_range[keep, 0], fam[keep] != 0))]
    if len(keep) == 0:
        raise OmniSfmError("manhattan world: no line is seen in 3 frames; a longer path?")
    remap = np.full(len(fam), -1)
    remap[keep] = np.arange(len(keep))
    sel = remap[mm] >= 0
    mm, ff = remap[mm[sel]], ff[sel]
    start, end, fam = start[keep], end[keep], fam[keep]
    pts, dirs = 0.5 * (start + end), normalize(end - start)
    M = len(keep)

    o_pts, o_dirs = pts[mm], dirs[mm]
    outlier = np.zeros(M, dtype=bool)
    n_out = int(round(opts.outlier_fraction * M))
    if n_out:
        outlier[rng.choice(M, size=n_out, replace=False)] = True
    for m in np.flatnonzero(outlier):
        seen = ff[mm == m]
        switch = seen[rng.integers(len(seen) // 4, max(len(seen) // 4 + 1, 3 * len(seen) // 4))]
        # another line (not a piece of the same 3D line) seen in that frame, else any other
        apart = np.linalg.norm(np.cross(pts - pts[m], dirs[m]), axis=1) + \
            np.linalg.norm(np.cross(dirs, dirs[m]), axis=1) > 1e-6
        there = np.intersect1d(mm[ff == switch], np.flatnonzero(apart))
        if not len(there):
            there = np.flatnonzero(apart)
        if not len(there):
            continue
        other = rng.choice(there)
        sel = (mm == m) & (ff >= switch)
        o_pts[sel], o_dirs[sel] = pts[other], dirs[other]

    # world = the first camera
    R0, p0 = gt.rotations[0].copy(), gt.positions[0].copy()
    gt = Trajectory(gt.timestamps, R0.T @ gt.rotations, (gt.positions - p0) @ R0)
    pts, o_pts = (pts - p0) @ R0, (o_pts - p0) @ R0
    dirs, o_dirs = dirs @ R0, o_dirs @ R0
    n_obs, rays = _observe(gt, ff, o_pts, o_dirs, opts.noise_deg, rng)
    tracks = make_tracks(F, np.arange(M), mm, ff, n_obs, source="simulation", obs_ray=rays)
    return Simulation(tracks, gt, pts, dirs, fam == 0, outlier, R0.T @ np.array([0.0, 0.0, 1.0]))


def weak_stretches(sim: Simulation, along: tuple[int, int], two: tuple[int, int]
                   ) -> LineTracks:
    """``sim``'s tracks with stretches the data do not fix: in frames ``along`` (first, stop)
    only the lines that run along the camera's motion (within 26 deg: pure translation along
    the only family seen, which leaves the motion along it free), in frames ``two`` only the
    two lines seen in most of them."""
    tr, c = sim.tracks, sim.groundtruth.positions
    motion = normalize(np.gradient(c, axis=0))
    f, t = tr.obs_frame, tr.obs_track
    in_along = (f >= along[0]) & (f < along[1])
    keep = ~in_along | (np.abs(np.sum(sim.line_directions[t] * motion[f], axis=1)) > 0.9)
    in_two = (f >= two[0]) & (f < two[1])
    longest = np.argsort(-np.bincount(t[in_two], minlength=tr.num_tracks), kind="stable")[:2]
    return tr.keep_observations(keep & (~in_two | np.isin(t, longest)))


def write_simulation(directory: Path, sim: Simulation, opts: SimulationOptions) -> list[Path]:
    """Write ``tracks.json``, ``groundtruth.tum`` and ``lines.json`` into ``directory``.

    ``lines.json`` holds the true 3D lines (world = first camera): per track id its point,
    unit direction, whether it belongs to the parallel family and whether it is an outlier
    track, plus the options of the simulation. Returns the paths written.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    folder = SimulationFolder(directory)
    write_tracks(folder / folder.TRACKS, sim.tracks)
    write_tum(folder / folder.GROUNDTRUTH, sim.groundtruth)
    lines = {
        "world": "first camera (world_from_cam of frame 0 is the identity)",
        "options": {k: (list(v) if isinstance(v, tuple) else v)
                    for k, v in asdict(opts).items()},
        "parallel_direction": sim.parallel_direction,
        "lines": [{"id": int(i), "point": pt, "direction": dr, "parallel": bool(par),
                   "outlier": bool(out)}
                  for i, pt, dr, par, out in zip(sim.tracks.track_ids, sim.line_points,
                                                  sim.line_directions, sim.parallel,
                                                  sim.outlier, strict=True)],
    }
    atomic_write_text(folder / folder.LINES, dumps_json(lines))
    return [folder / n for n in (folder.TRACKS, folder.GROUNDTRUTH, folder.LINES)]
