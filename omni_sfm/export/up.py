"""A gravity-up world for exports: the vertical line family points +z, the origin at the first
camera (docs/formats.md, "Exports").

omni-sfm's world is the first camera's frame, whichever way it pointed. The vertical is among
the directions of the parallel line families (``lines3d.json``'s groups, in the folder's own
world; ``report.json``'s ``parallel_family.direction`` where a folder has no 3D lines). Which
family is vertical, and which way is up, is decided by how the camera is mounted:

- the *mount axis*: the camera-frame axis that points up when the camera is used as intended:
  ``+z`` for the hyperboloid mirror camera (its mirror axis, mirror above the lens),
  ``-y`` for equirectangular and OpenCV fisheye cameras (the top of the image is up); other
  models have none unless given (``--up-axis``). The mount axis of every frame, put in the
  world, is averaged over the frames: the vertical is the family direction nearest to that
  mean, signed to agree with it (a camera held upright). This holds however large the family
  is and whatever the camera tilts by, as long as the tilt stays under 45 deg.
- without a mount axis: the family direction most nearly perpendicular to the camera's motion
  (the principal direction of the camera centres, when they spread), ties broken by family
  size; its sign is the one that points along the first camera's nearest axis (give
  ``--up-axis`` to choose).

The family's direction is then fitted to the observed normals of its line tracks
(``tracks.json`` of the folder, or of the init folder a refine or dense folder was made from)
with the folder's rotations. The family directions a folder records are the means of its lines'
directions, each adjusted on its own: 0.49 and 0.19 deg from the true vertical on the two
renders of tests/test_export_formats.py, the fit 0.009 and 0.004 deg.

The up frame: ``z`` = the vertical; ``x`` = the first camera's forward axis (its ``z``, or its
``x`` where ``z`` is nearly vertical) laid into the horizontal plane; ``y = z x x``; origin = the
first camera's centre. Poses become ``world_up_from_cam = up_from_world @ world_from_cam``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from omni_sfm.cameras import CameraModel
from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray, normalize
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.lines3d import LineSegments3D
from omni_sfm.poses import Trajectory
from omni_sfm.reports import ExportWorld, StageReport

MOUNT_UP_AXIS: dict[str, tuple[float, float, float]] = {
    "hyperboloid": (0.0, 0.0, 1.0),
    "equirectangular": (0.0, -1.0, 0.0),
    "opencv_fisheye": (0.0, -1.0, 0.0),
    "rig": (0.0, -1.0, 0.0),
}
"""The camera-frame axis that points up when the camera is mounted as intended, per model (a
rig: its frame's -y, docs/cameras.md)."""

AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
MIN_FAMILY_SEGMENTS = 3
MAX_MOUNT_TILT_DEG = 45.0


def parse_axis(text: str) -> FloatArray:
    """``"x"``, ``"-y"``, ``"+z"`` ... -> the unit camera-frame axis; OmniSfmError otherwise."""
    t = text.strip().lower()
    sign = -1.0 if t.startswith("-") else 1.0
    key = t.lstrip("+-")
    if key not in AXES or len(t) - len(key) > 1:
        raise OmniSfmError(f"--up-axis must be one of x, -x, y, -y, z, -z; got {text!r}")
    return sign * np.asarray(AXES[key])


@dataclass(frozen=True)
class UpFrame:
    """The export's world: ``x_export = up_from_world @ (x_world - origin)``.

    Attributes:
        up_from_world: ``(3, 3)`` rotation from the folder's world to the export's.
        origin: ``(3,)`` the export's origin in the folder's world (the first camera centre).
        vertical: ``(3,)`` the up direction in the folder's world, or None (``--no-up``).
        how: how the vertical was chosen, in words.
        family: index of the chosen family among the candidates, or None.
    """

    up_from_world: FloatArray
    origin: FloatArray
    vertical: FloatArray | None
    how: str
    family: int | None = None

    @classmethod
    def identity(cls) -> UpFrame:
        """The folder's own world (``--no-up``)."""
        return cls(np.eye(3), np.zeros(3), None, "not turned (--no-up): the folder's world")

    def trajectory(self, traj: Trajectory) -> Trajectory:
        """The poses in the export's world."""
        R = self.up_from_world
        return Trajectory(traj.timestamps.copy(), R[None] @ traj.rotations,
                          (traj.positions - self.origin) @ R.T)

    def lines(self, lines: LineSegments3D) -> LineSegments3D:
        """The 3D lines in the export's world (``up`` set when the world is turned)."""
        R = self.up_from_world
        out = lines.transformed(R, -R @ self.origin)
        if self.vertical is not None:
            from dataclasses import replace

            out = replace(out, up=np.array([0.0, 0.0, 1.0]), frame="export world: +z up, "
                          "origin at the first camera, the folder's units")
        return out

    def points(self, x: FloatArray) -> FloatArray:
        """``(N, 3)`` world points in the export's world."""
        return np.asarray((np.asarray(x) - self.origin) @ self.up_from_world.T)

    def matrix(self) -> FloatArray:
        """``(4, 4)`` homogeneous ``export_from_world``."""
        m = np.eye(4)
        m[:3, :3] = self.up_from_world
        m[:3, 3] = -self.up_from_world @ self.origin
        return m

    def report(self) -> ExportWorld:
        """An export report's ``world``."""
        return ExportWorld(
            turned=self.vertical is not None,
            export_from_world=self.matrix().tolist(),
            vertical_in_world=None if self.vertical is None else self.vertical.tolist(),
            how=self.how,
            convention="x_export = R (x_world - origin); +z up, origin at the first camera"
            if self.vertical is not None else "the folder's world (first camera's frame)")


def family_candidates(lines: LineSegments3D | None, report: StageReport | None
                      ) -> tuple[FloatArray, np.ndarray, list[list[int]]]:
    """``(F, 3)`` unit directions of the line families a vertical may be chosen from, their
    ``(F,)`` sizes and each one's line track ids: the groups of ``lines`` with at least
    MIN_FAMILY_SEGMENTS segments, else the report's parallel family."""
    if lines is not None and len(lines) and len(lines.group_directions):
        counts = np.bincount(lines.groups, minlength=len(lines.group_directions))
        keep = np.flatnonzero(counts >= MIN_FAMILY_SEGMENTS)
        if len(keep):
            tids = [[] if lines.track_ids is None else
                    lines.track_ids[lines.groups == g].tolist() for g in keep]
            return normalize(lines.group_directions[keep]), counts[keep], tids
    d = None if report is None else report.family_direction
    if report is not None and d is not None and np.all(np.isfinite(d)) and \
            np.linalg.norm(d) > 0:
        ids = report.family_track_ids
        return normalize(np.asarray(d, float))[None], np.array([len(ids)]), [ids]
    raise OmniSfmError("the folder has no line family to find the vertical from (no "
                       "lines3d.json groups, no parallel_family in report.json); give --no-up "
                       "to keep the first camera's frame")


def fit_direction(d0: FloatArray, track_ids: list[int], tracks: LineTracks, traj: Trajectory,
                  max_change_deg: float = 5.0) -> tuple[FloatArray | None, int]:
    """The common direction of the lines ``track_ids`` fitted to their observed normals, put
    in the world by the poses (frames matched by timestamp): the direction most nearly
    perpendicular to all of them (least squares, normals more than three median residuals off
    dropped twice), signed like ``d0``. ``(None, 0)`` with fewer than 10 normals or a result
    more than ``max_change_deg`` from ``d0``."""
    t = tracks.timestamps[tracks.obs_frame]
    ts = traj.timestamps
    row = np.clip(np.searchsorted(ts, t), 1, max(1, len(ts) - 1)) if len(ts) > 1 else \
        np.zeros(len(t), int)
    if len(ts) > 1:
        row -= (t - ts[row - 1]) < (ts[row] - t)         # the nearest pose
    tol = 1e-6 * max(1.0, float(np.abs(traj.timestamps).max()))
    sel = np.isin(tracks.track_ids[tracks.obs_track], track_ids) & \
        (np.abs(traj.timestamps[row] - t) <= tol)
    if sel.sum() < 10:
        return None, 0
    n = np.einsum("kij,kj->ki", traj.rotations[row[sel]], tracks.obs_normal[sel])
    d = normalize(np.asarray(d0, float))
    keep = np.ones(len(n), bool)
    for _ in range(3):
        w, v = np.linalg.eigh(n[keep].T @ n[keep])
        d = v[:, 0] * (1.0 if v[:, 0] @ d0 >= 0 else -1.0)
        r = np.abs(n @ d)
        keep = r <= max(3.0 * float(np.median(r)), 1e-9)
        if keep.sum() < 10:
            return None, 0
    if np.degrees(np.arccos(min(1.0, float(d @ normalize(d0))))) > max_change_deg:
        return None, 0
    return d, int(keep.sum())


def find_up(traj: Trajectory, camera: CameraModel, lines: LineSegments3D | None,
            report: StageReport | None, up_axis: FloatArray | None = None,
            tracks: LineTracks | None = None) -> UpFrame:
    """The gravity-up world of a folder's poses (the rule: see the module docstring); with the
    line ``tracks`` the folder was estimated from, the chosen family's direction is fitted to
    their normals (:func:`fit_direction`)."""
    dirs, sizes, track_ids = family_candidates(lines, report)
    axis = up_axis if up_axis is not None else MOUNT_UP_AXIS.get(camera.model)
    if axis is not None:
        mount = normalize(np.einsum("nij,j->ni", traj.rotations, np.asarray(axis, float))
                          .mean(axis=0))
        cos = dirs @ mount
        k = int(np.argmax(np.abs(cos)))
        tilt = float(np.degrees(np.arccos(min(1.0, abs(cos[k])))))
        if tilt > MAX_MOUNT_TILT_DEG:
            raise OmniSfmError(
                f"no line family lies within {MAX_MOUNT_TILT_DEG:.0f} deg of the camera's mount "
                f"axis {_axis_name(axis)} (nearest: {tilt:.1f} deg); give --up-axis for a "
                "camera mounted otherwise, or --no-up")
        vertical = dirs[k] * np.sign(cos[k])
        how = (f"family {k} of {len(dirs)} ({int(sizes[k])} segments), {tilt:.2f} deg from the "
               f"camera's mount axis {_axis_name(axis)} averaged over the frames; up = along "
               "the mount axis")
    else:
        centred = traj.positions - traj.positions.mean(axis=0)
        spread = np.linalg.svd(centred, full_matrices=False)[1] if len(traj) > 1 else np.zeros(1)
        if len(traj) > 1 and spread[0] > 1e-9 * max(1.0, float(np.abs(traj.positions).max())):
            motion = np.linalg.svd(centred, full_matrices=False)[2][0]
            along = np.abs(dirs @ motion)
        else:
            along = np.zeros(len(dirs))
        # most perpendicular to the motion (to 0.1 in |cos|), then the largest
        k = int(np.lexsort((-sizes, np.round(along, 1)))[0])
        first_axes = traj.rotations[0].T            # rows: the first camera's axes
        a = int(np.argmax(np.abs(first_axes @ dirs[k])))
        vertical = dirs[k] * np.sign(first_axes[a] @ dirs[k])
        how = (f"family {k} of {len(dirs)} ({int(sizes[k])} segments), the most nearly "
               f"perpendicular to the camera's motion (|cos| {along[k]:.2f}); up = along the "
               f"first camera's +{'xyz'[a]} (no mount axis known for camera model "
               f"{camera.model!r}: --up-axis sets one)")
    if tracks is not None and track_ids[k]:
        fitted, used = fit_direction(vertical, track_ids[k], tracks, traj)
        if fitted is not None:
            how += (f"; direction fitted to {used} line normals of the family's tracks "
                    f"({np.degrees(np.arccos(min(1.0, float(fitted @ vertical)))):.3f} deg from "
                    "the family's)")
            vertical = fitted
    R0 = traj.rotations[0]
    fwd = R0[:, 2] if abs(R0[:, 2] @ vertical) < 0.9 else R0[:, 0]
    ex = normalize(fwd - (fwd @ vertical) * vertical)
    ey = np.cross(vertical, ex)
    up_from_world = np.stack([ex, ey, vertical])
    return UpFrame(up_from_world, traj.positions[0].copy(), vertical, how, k)


def _axis_name(axis: Any) -> str:
    a = np.asarray(axis, float)
    i = int(np.argmax(np.abs(a)))
    return f"{'-' if a[i] < 0 else '+'}{'xyz'[i]}"
