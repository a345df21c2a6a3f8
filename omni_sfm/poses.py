"""Camera trajectories (``world_from_cam`` per frame) and the TUM trajectory format.

TUM format, one line per pose: ``timestamp tx ty tz qx qy qz qw``; lines starting with ``#``
are comments. ``t`` is the camera centre in the world and ``q`` the rotation world_from_cam of
the frame in which the camera model's rays are expressed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import atomic_write_text
from omni_sfm.geometry import FloatArray, matrix_from_quat_xyzw, quat_xyzw_from_matrix


@dataclass(frozen=True)
class Trajectory:
    """Poses of a sequence of frames.

    Attributes:
        timestamps: ``(N,)`` frame index or seconds, increasing.
        rotations: ``(N, 3, 3)`` rotation of world_from_cam.
        positions: ``(N, 3)`` translation of world_from_cam (the camera centre in the world).
    """

    timestamps: FloatArray
    rotations: FloatArray
    positions: FloatArray

    def __post_init__(self) -> None:
        n = self.timestamps.shape[0]
        if self.timestamps.shape != (n,) or self.rotations.shape != (n, 3, 3) or \
                self.positions.shape != (n, 3):
            raise ValueError(
                f"inconsistent trajectory: {self.timestamps.shape=} {self.rotations.shape=} "
                f"{self.positions.shape=}"
            )

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def cam_from_world_rotations(self) -> FloatArray:
        """``(N, 3, 3)`` rotation of cam_from_world (the transpose)."""
        return np.swapaxes(self.rotations, -1, -2)

    def path_length(self) -> float:
        """Sum of distances between consecutive camera centres."""
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())

    def fixed_camera(self, body_from_cam: FloatArray) -> Trajectory:
        """The poses world_from_cam of a camera fixed to the body these poses are of, at
        ``body_from_cam`` (``(4, 4)``, its centre in these poses' units): a lens of a rig."""
        T = np.asarray(body_from_cam, dtype=np.float64)
        return Trajectory(self.timestamps.copy(), self.rotations @ T[:3, :3],
                          self.positions + self.rotations @ T[:3, 3])

    def subset(self, index: np.ndarray) -> Trajectory:
        """The poses at ``index`` (integer array or boolean mask)."""
        return Trajectory(self.timestamps[index], self.rotations[index], self.positions[index])

    def to_tum(self) -> str:
        """TUM text, one pose per line (full float precision)."""
        return TUM_HEADER + self.tum_rows()

    def tum_rows(self) -> str:
        """The poses as TUM lines, without the header."""
        q = quat_xyzw_from_matrix(self.rotations) if len(self) else np.zeros((0, 4))
        rows = [
            " ".join(f"{x:.17g}" for x in (t, *p, *qq))
            for t, p, qq in zip(self.timestamps, self.positions, q, strict=True)
        ]
        return "".join(r + "\n" for r in rows)


TUM_HEADER = "# timestamp tx ty tz qx qy qz qw (world_from_cam)\n"
"""The comment line that starts every TUM file omni-sfm writes."""


def write_tum(path: Path, traj: Trajectory) -> None:
    """Write ``traj`` to ``path`` in TUM format (atomically)."""
    atomic_write_text(Path(path), traj.to_tum())


def read_tum(path: Path) -> Trajectory:
    """Read a TUM trajectory; every defect becomes a one-line :class:`OmniSfmError`."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise OmniSfmError(f"{path}: trajectory file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise OmniSfmError(f"{path}: cannot read trajectory: {exc}") from None
    rows = []
    for k, line in enumerate(lines, 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise OmniSfmError(f"{path}:{k}: expected 8 numbers (t tx ty tz qx qy qz qw), "
                               f"got {len(parts)}")
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            raise OmniSfmError(f"{path}:{k}: not a number in {s!r}") from None
        if not np.all(np.isfinite(vals)):
            raise OmniSfmError(f"{path}:{k}: non-finite value in {s!r}")
        if np.linalg.norm(vals[4:]) < 1e-9:
            raise OmniSfmError(f"{path}:{k}: zero quaternion")
        rows.append(vals)
    if not rows:
        raise OmniSfmError(f"{path}: no poses in trajectory file")
    a = np.asarray(rows)
    return Trajectory(a[:, 0].copy(), matrix_from_quat_xyzw(a[:, 4:]), a[:, 1:4].copy())
