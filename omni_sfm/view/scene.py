"""What a view shows, read from a results folder: trajectory, 3D lines, dense points."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.folders import DenseFolder
from omni_sfm.geometry import FloatArray, normalize
from omni_sfm.libs import open3d_module
from omni_sfm.lines3d import LineSegments3D
from omni_sfm.poses import Trajectory


@dataclass(frozen=True)
class ViewScene:
    """Everything drawn, in the results' world frame and unit.

    Attributes:
        trajectory: camera poses (world_from_cam).
        line_starts, line_ends: ``(L, 3)`` 3D line segments (L may be 0).
        line_groups: ``(L,)`` parallel group of each segment (-1: none).
        points: ``(N, 3)`` dense points (N may be 0), subsampled to at most ``max_points``.
        colors: ``(N, 3)`` their RGB in [0, 1].
        up: ``(3,)`` unit up direction of the world (for an upright view).
        sources: which file gave what (for the caption).
    """

    trajectory: Trajectory
    line_starts: FloatArray
    line_ends: FloatArray
    line_groups: np.ndarray
    points: FloatArray
    colors: FloatArray
    up: FloatArray
    sources: dict[str, str]

    def extent(self) -> float:
        """Diagonal of the bounding box of the trajectory, the lines and the central 98 % of
        the points (stray points do not count), > 0."""
        parts = [self.trajectory.positions, self.line_starts, self.line_ends]
        if len(self.points):
            parts.append(np.percentile(self.points, [1, 99], axis=0))
        allp = np.concatenate(parts)
        d = float(np.linalg.norm(allp.max(0) - allp.min(0)))
        return d if d > 0 else 1.0


def up_direction(traj: Trajectory, camera_model: str | None) -> FloatArray:
    """The world's up: the cameras' mean up axis (``+z`` of the hyperboloid, robot mount;
    ``-y`` of other models, OpenCV's hand-held convention; world ``-y`` without a camera)."""
    up_cam = np.array([0.0, 0.0, 1.0]) if camera_model == "hyperboloid" else \
        np.array([0.0, -1.0, 0.0])
    if camera_model is None:
        return up_cam
    return normalize((traj.rotations @ up_cam).mean(axis=0))


def load_view_scene(folder: Path, *, max_points: int = 200_000, seed: int = 0) -> ViewScene:
    """Read ``trajectory.tum`` (required), ``dense.ply`` (optional), 3D lines from
    ``lines3d.json`` (optional) and the camera model from ``camera.yaml`` (optional, for the up
    direction), through :class:`omni_sfm.folders.DenseFolder`. One-line OmniSfmError when the
    folder or its trajectory is missing."""

    folder = Path(folder)
    if not folder.is_dir():
        raise OmniSfmError(f"{folder}: folder not found")
    owner = DenseFolder(folder)
    tum = owner / owner.TRAJECTORY
    if not tum.is_file():
        raise OmniSfmError(f"{tum}: no trajectory (give a dense, init or refine output folder)")
    art = owner.load_stage()
    traj = art.trajectory
    if len(traj) == 0:
        raise OmniSfmError(f"{tum}: the trajectory is empty")
    sources = {"trajectory": tum.name}
    lines = art.lines3d
    if lines is not None:
        sources["lines"] = owner.LINES3D
    else:
        lines = LineSegments3D.empty()
    pts, cols = np.zeros((0, 3)), np.zeros((0, 3))
    if (folder / DenseFolder.POINTS).is_file():
        o3d = open3d_module()
        pcd = o3d.io.read_point_cloud(str(folder / DenseFolder.POINTS))
        pts = np.asarray(pcd.points)
        cols = np.asarray(pcd.colors) if pcd.has_colors() else np.full_like(pts, 0.6)
        if len(pts) > max_points:
            keep = np.sort(np.random.default_rng(seed).choice(len(pts), max_points,
                                                              replace=False))
            pts, cols = pts[keep], cols[keep]
        sources["points"] = DenseFolder.POINTS
    model = None if art.camera is None else art.camera.model
    return ViewScene(traj, lines.starts, lines.ends, lines.groups, pts, cols,
                     up_direction(traj, model), sources)


def upright_from_world(up: FloatArray) -> FloatArray:
    """``(3, 3)`` rotation taking the unit ``up`` to ``+z`` (the smallest such rotation)."""
    from omni_sfm.geometry import rotation_about_axis

    u = normalize(np.asarray(up, dtype=np.float64))
    axis = np.cross(u, [0.0, 0.0, 1.0])
    s, c = float(np.linalg.norm(axis)), float(u[2])
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return np.asarray(rotation_about_axis(axis / s, np.arctan2(s, c)))
