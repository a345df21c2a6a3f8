"""Trajectory files for evaluation tools: TUM and KITTI odometry (docs/formats.md, "Exports").

Both hold ``world_from_cam`` of the camera frame in which the camera model's rays are expressed
(docs/cameras.md), in the export's world (:mod:`omni_sfm.export.up`).

- TUM (``trajectory.tum``): ``timestamp tx ty tz qx qy qz qw`` per pose, as
  :func:`omni_sfm.poses.write_tum` writes it (evo's ``tum`` reader).
- KITTI (``poses.txt`` and ``times.txt``): one pose per line, the 12 numbers of the ``3 x 4``
  matrix ``[R | t]`` row by row (``world_from_cam``: a camera point to the world); the
  timestamps one per line in ``times.txt`` (evo's ``kitti`` reader takes ``poses.txt``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import atomic_write_text
from omni_sfm.folders import ExportFolder
from omni_sfm.poses import Trajectory, write_tum

TUM_FILE = ExportFolder.TRAJECTORY
KITTI_POSES = ExportFolder.KITTI_POSES
KITTI_TIMES = ExportFolder.KITTI_TIMES


def kitti_text(traj: Trajectory) -> str:
    """The poses as KITTI lines (full float precision)."""
    m = np.concatenate([traj.rotations, traj.positions[:, :, None]], axis=2).reshape(-1, 12)
    return "".join(" ".join(f"{x:.17g}" for x in row) + "\n" for row in m)


def write_kitti(directory: Path, traj: Trajectory) -> None:
    """``poses.txt`` and ``times.txt`` of ``traj`` in ``directory``."""
    atomic_write_text(Path(directory) / KITTI_POSES, kitti_text(traj))
    atomic_write_text(Path(directory) / KITTI_TIMES,
                      "".join(f"{t:.17g}\n" for t in traj.timestamps))


def read_kitti(directory: Path) -> Trajectory:
    """Read ``poses.txt`` (and ``times.txt`` when present; else the line index)."""
    directory = Path(directory)
    try:
        rows = np.loadtxt(directory / KITTI_POSES, ndmin=2)
        times = np.loadtxt(directory / KITTI_TIMES, ndmin=1) if (
            directory / KITTI_TIMES).is_file() else np.arange(len(rows), dtype=float)
    except (OSError, ValueError) as exc:
        raise OmniSfmError(f"{directory}: cannot read the KITTI poses: {exc}") from None
    if rows.shape[1] != 12 or len(times) != len(rows):
        raise OmniSfmError(f"{directory / KITTI_POSES}: need 12 numbers a line and one time "
                           "per pose")
    m = rows.reshape(-1, 3, 4)
    return Trajectory(np.asarray(times, float), m[:, :, :3].copy(), m[:, :, 3].copy())


def write_trajectory_export(directory: Path, traj: Trajectory, fmt: str) -> list[str]:
    """Write ``traj`` as ``fmt`` (``tum`` or ``kitti``) in ``directory``; the files written."""
    if fmt == "tum":
        write_tum(Path(directory) / TUM_FILE, traj)
        return [TUM_FILE]
    if fmt == "kitti":
        write_kitti(Path(directory), traj)
        return [KITTI_POSES, KITTI_TIMES]
    raise ValueError(f"not a trajectory format: {fmt!r}")
