"""Simulated line observations with exact ground truth (the paper's Sec. VII set-up and more).

A smooth camera path with full 3D rotation and translation, ``P`` parallel 3D lines sharing one
direction and ``Q`` lines in other directions, observed as unit plane normals (NVs) in each
camera frame, with Gaussian angular noise, optional outlier tracks (wrong correspondences from
some frame on) and optional partial visibility (each line seen in a window of frames).
World = the first camera's frame.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import atomic_write_text, dumps_json
from omni_sfm.geometry import FloatArray, line_plane_normals, normalize, rotvec_to_matrix
from omni_sfm.lines.tracks import LineTracks, make_tracks, write_tracks
from omni_sfm.poses import Trajectory, write_tum


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


def simulate(opts: SimulationOptions) -> Simulation:
    """Run the simulation described by ``opts`` (seeded, reproducible)."""
    if opts.num_views < 3:
        raise OmniSfmError(f"need at least 3 views, got {opts.num_views}")
    if opts.num_parallel < 0 or opts.num_other < 0 or opts.num_parallel + opts.num_other < 1:
        raise OmniSfmError("need a positive number of lines")
    if not opts.noise_deg >= 0:
        raise OmniSfmError(f"noise must be >= 0 degrees, got {opts.noise_deg}")
    if not 0 <= opts.outlier_fraction < 1:
        raise OmniSfmError(f"outlier fraction must be in [0, 1), got {opts.outlier_fraction}")
    if opts.visible_frames is not None and not 3 <= opts.visible_frames <= opts.num_views:
        raise OmniSfmError(f"visible frames must be in [3, {opts.num_views}] (the number of "
                           f"views), got {opts.visible_frames}")
    rng = np.random.default_rng(opts.seed)
    gt = smooth_path(opts.num_views, opts.path_length, opts.rotation_deg, rng)
    F, P, Q = opts.num_views, opts.num_parallel, opts.num_other
    M = P + Q
    v = normalize(rng.normal(size=3))
    dirs = np.empty((M, 3))
    dirs[:P] = v
    k = P
    while k < M:
        d = normalize(rng.normal(size=3))
        if abs(d @ v) < np.cos(np.radians(20.0)):
            dirs[k] = d
            k += 1
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

    vis = np.ones((M, F), dtype=bool)
    if opts.visible_frames is not None:
        half = opts.visible_frames / 2.0
        start = np.clip(anchor - half + rng.uniform(-0.2, 0.2, M) * half, 0, None)
        start = np.minimum(start, max(0.0, F - opts.visible_frames))
        fr = np.arange(F)
        vis = (fr[None, :] >= np.floor(start)[:, None]) & \
            (fr[None, :] < np.floor(start)[:, None] + opts.visible_frames)

    outlier = np.zeros(M, dtype=bool)
    n_out = int(round(opts.outlier_fraction * M))
    if n_out:
        outlier[rng.choice(M, size=n_out, replace=False)] = True
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
    tracks = make_tracks(F, np.arange(M), mm, ff, n_cam[mm, ff], source="simulation")
    return Simulation(tracks, gt, pts, dirs, np.arange(M) < P, outlier, v)


def write_simulation(directory: Path, sim: Simulation, opts: SimulationOptions) -> list[Path]:
    """Write ``tracks.json``, ``groundtruth.tum`` and ``lines.json`` into ``directory``.

    ``lines.json`` holds the true 3D lines (world = first camera): per track id its point,
    unit direction, whether it belongs to the parallel family and whether it is an outlier
    track, plus the options of the simulation. Returns the paths written.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    write_tracks(directory / "tracks.json", sim.tracks)
    write_tum(directory / "groundtruth.tum", sim.groundtruth)
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
    atomic_write_text(directory / "lines.json", dumps_json(lines))
    return [directory / n for n in ("tracks.json", "groundtruth.tum", "lines.json")]
