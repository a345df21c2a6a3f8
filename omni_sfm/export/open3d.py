"""Open3D geometry of omni-sfm results: 3D lines and camera poses as ``LineSet`` PLY files.

``lines3d.ply``: one segment per 3D line, coloured by its parallel group (:func:`group_colors`).
``cameras.ply``: the camera path (grey polyline through the centres) and, for every pose drawn,
its three axes (x red, y green, z blue; length ``axis_length``). Both are PLY line sets that
``open3d.io.read_line_set`` reads.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray
from omni_sfm.libs import open3d_module
from omni_sfm.poses import Trajectory

# Tableau-like palette: distinct hues for the first parallel groups, then it repeats
PALETTE = np.array([
    [0.12, 0.47, 0.71], [1.00, 0.50, 0.05], [0.17, 0.63, 0.17], [0.84, 0.15, 0.16],
    [0.58, 0.40, 0.74], [0.55, 0.34, 0.29], [0.89, 0.47, 0.76], [0.74, 0.74, 0.13],
    [0.09, 0.75, 0.81], [0.50, 0.50, 0.50],
])
PATH_COLOR = np.array([0.35, 0.35, 0.35])
AXIS_COLORS = np.eye(3)


def group_colors(groups: np.ndarray) -> FloatArray:
    """``(L, 3)`` RGB in [0, 1] for parallel-group ids ``(L,)`` (negative: grey, ungrouped)."""
    g = np.asarray(groups, dtype=np.int64)
    out = PALETTE[np.mod(g, len(PALETTE))].copy()
    out[g < 0] = PALETTE[-1]
    return out


def line_set(starts: FloatArray, ends: FloatArray, colors: FloatArray) -> Any:
    """A legacy ``open3d.geometry.LineSet`` of segments ``starts/ends (L, 3)`` with per-segment
    ``colors (L, 3)`` in [0, 1]."""
    o3d = open3d_module()
    s, e = np.asarray(starts, float).reshape(-1, 3), np.asarray(ends, float).reshape(-1, 3)
    if s.shape != e.shape or np.asarray(colors).shape != s.shape:
        raise ValueError(f"need matching (L, 3) arrays, got {s.shape=} {e.shape=} "
                         f"{np.asarray(colors).shape=}")
    ls = o3d.geometry.LineSet()
    ls.points = o3d.utility.Vector3dVector(np.concatenate([s, e]) if len(s) else np.zeros((0, 3)))
    idx = np.stack([np.arange(len(s)), np.arange(len(s)) + len(s)], axis=1)
    ls.lines = o3d.utility.Vector2iVector(idx.astype(np.int32))
    ls.colors = o3d.utility.Vector3dVector(np.asarray(colors, float).reshape(-1, 3))
    return ls


def lines3d_line_set(starts: FloatArray, ends: FloatArray, groups: np.ndarray) -> Any:
    """3D lines coloured by parallel group."""
    return line_set(starts, ends, group_colors(groups))


def camera_segments(traj: Trajectory, axis_length: float, every: int = 1
                    ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Segments ``(starts, ends, colors)`` of the camera path and of the axes of every
    ``every``-th pose (and the last)."""
    c = traj.positions
    path_s, path_e = c[:-1], c[1:]
    idx = np.unique(np.r_[np.arange(0, len(traj), max(1, every)), len(traj) - 1])
    axes = traj.rotations[idx] * axis_length                    # columns: axes in the world
    ax_s = np.repeat(c[idx], 3, axis=0)
    ax_e = ax_s + np.swapaxes(axes, 1, 2).reshape(-1, 3)
    colors = np.concatenate([np.tile(PATH_COLOR, (len(path_s), 1)),
                             np.tile(AXIS_COLORS, (len(idx), 1))])
    return np.concatenate([path_s, ax_s]), np.concatenate([path_e, ax_e]), colors


def cameras_line_set(traj: Trajectory, axis_length: float, every: int = 1) -> Any:
    """The camera path and the poses' axes as one line set (see the module docstring)."""
    return line_set(*camera_segments(traj, axis_length, every))


def write_line_set(path: Path, ls: Any) -> None:
    """Write a line set as PLY; OmniSfmError if Open3D cannot."""
    o3d = open3d_module()
    if not o3d.io.write_line_set(str(path), ls):
        raise OmniSfmError(f"{path}: Open3D could not write this line set")
