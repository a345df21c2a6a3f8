"""The joint adjustment (:mod:`omni_sfm.refine.joint`) on a COLMAP model: the init's line
tracks and 3D lines with the model's triangulated points, the poses and points written back.

COLMAP's keypoints become unit rays through the exact camera model (its pixels mapped back
to ours by :class:`omni_sfm.cameras.base.ColmapExport`, mirrored images included); COLMAP's
world is ours, so the points need no change of frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from omni_sfm.cameras.base import CameraModel, ColmapExport
from omni_sfm.errors import OmniSfmError
from omni_sfm.export.colmap import set_colmap_poses, trajectory_from_reconstruction
from omni_sfm.folders import InitArtifacts
from omni_sfm.geometry import FloatArray, rotation_angle
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.lines3d import LineSegments3D
from omni_sfm.poses import Trajectory
from omni_sfm.refine.joint import JointOptions, JointResult, PointObservations, joint_adjust
from omni_sfm.reports import FrameEvidence, JointReport, RegisteredFrames
from omni_sfm.transforms import Similarity


@dataclass(frozen=True)
class LineEvidence:
    """The init's lines on its frames: tracks, each used track's 3D line (NaN: none), and for
    each input pose the tracks' frame index."""

    tracks: LineTracks
    directions: FloatArray
    points: FloatArray
    frame_of_pose: np.ndarray
    segments: LineSegments3D
    """The init's ``lines3d.json``."""


def read_line_evidence(init: InitArtifacts) -> LineEvidence | str:
    """The line evidence an init folder holds for its poses, or why there is none (the folder
    lacks ``tracks.json`` or ``lines3d.json``, or they do not fit)."""
    folder, traj = init.folder, init.trajectory
    if not (folder / folder.TRACKS).is_file():
        return f"the init folder has no {folder.TRACKS}"
    lines = init.lines3d
    if lines is None or lines.track_ids is None or len(lines) == 0:
        return f"the init folder has no estimated 3D lines ({folder.LINES3D})"
    tracks = init.read_tracks()
    assert tracks is not None
    ts = tracks.timestamps
    k = np.searchsorted(ts, traj.timestamps)
    k = np.clip(k, 0, len(ts) - 1)
    if len(ts) == 0 or not np.allclose(ts[k], traj.timestamps, rtol=0, atol=1e-6):
        return f"the frames of {folder.TRACKS} are not those of the trajectory"
    M = tracks.num_tracks
    d, p = np.full((M, 3), np.nan), np.full((M, 3), np.nan)
    m = _track_index(tracks.track_ids, lines.track_ids)
    d[m[m >= 0]], p[m[m >= 0]] = lines.directions[m >= 0], lines.starts[m >= 0]
    if not np.isfinite(d).all(1).any():
        return f"no line of {folder.LINES3D} belongs to a track of {folder.TRACKS}"
    return LineEvidence(tracks, d, p, k, lines)


def _track_index(track_ids: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """For each of the ``wanted`` track ids, its index in ``track_ids`` (-1: not there)."""
    order = np.argsort(track_ids, kind="stable")
    pos = np.clip(np.searchsorted(track_ids, wanted, sorter=order), 0, max(len(order) - 1, 0))
    if len(order) == 0:
        return np.full(len(wanted), -1)
    found = track_ids[order[pos]] == wanted
    return np.where(found, order[pos], -1)


def adjusted_segments(lines: LineEvidence, res: JointResult,
                      world_from_adjusted: Similarity | None) -> LineSegments3D:
    """The init's 3D segments on the adjusted lines (each endpoint moved to the nearest point
    of its track's adjusted line), mapped by ``world_from_adjusted`` (the refinement's
    alignment onto the input's world); segments whose track the adjustment rejected keep
    their place, mapped likewise."""
    seg = lines.segments
    assert seg.track_ids is not None
    m = _track_index(lines.tracks.track_ids, seg.track_ids)
    on = m >= 0
    on[on] = res.lines_used[m[on]]
    d, p = res.line_directions[m[on]], res.line_points[m[on]]
    starts, ends = seg.starts.copy(), seg.ends.copy()
    for x in (starts, ends):  # each endpoint to the nearest point of its adjusted line
        x[on] = p + np.sum((x[on] - p) * d, axis=1, keepdims=True) * d
    if world_from_adjusted is not None:
        starts, ends = (world_from_adjusted.apply_points(x) for x in (starts, ends))
    dirs = ends - starts
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    group_dirs = seg.group_directions.copy()
    for g in range(len(group_dirs)):
        member = dirs[seg.groups == g]
        if len(member):  # the group's direction: the principal axis of its members'
            group_dirs[g] = np.linalg.svd(member, full_matrices=False)[2][0]
    return LineSegments3D(starts, ends, seg.groups.copy(), group_dirs, seg.kinds,
                          seg.track_ids.copy(), seg.frame, seg.up)


def model_points(rec: Any, image_ids: list[int], camera: CameraModel, export: ColmapExport
                 ) -> tuple[PointObservations, FloatArray, list[tuple[int, int]], list[int]]:
    """The triangulated observations of the images ``image_ids`` (pose ``k`` for the ``k``-th)
    as rays of our camera, the points ``(P, 3)``, each observation's ``(image_id, point2D
    index)`` and the COLMAP id of each point."""
    frame, pid, xy, where = [], [], [], []
    for k, image_id in enumerate(image_ids):
        im = rec.images[image_id]
        if not im.has_pose:
            continue
        for idx in im.get_observation_point2D_idxs():
            p2 = im.point2D(idx)
            frame.append(k)
            pid.append(int(p2.point3D_id))
            xy.append(np.asarray(p2.xy, float))
            where.append((image_id, int(idx)))
    ids = sorted(set(pid))
    col = {q: j for j, q in enumerate(ids)}
    X = np.array([rec.points3D[q].xyz for q in ids], float).reshape(-1, 3)
    if xy:
        rays = camera.rays_from_pixels(export.pixels_from_colmap(np.array(xy)))
    else:
        rays = np.zeros((0, 3))
    ok: np.ndarray = np.asarray(np.isfinite(rays).all(1))
    obs = PointObservations(np.array(frame, np.int64)[ok],
                            np.array([col[q] for q in pid], np.int64)[ok], rays[ok], len(ids))
    J = pixel_jacobians(camera, obs)
    with np.errstate(invalid="ignore"):
        good = np.isfinite(J).all((1, 2)) & (np.abs(np.linalg.det(J)) > 0)
    ok[np.flatnonzero(ok)[~good]] = False
    obs = PointObservations(obs.frame[good], obs.point[good], obs.ray[good], obs.num_points,
                            J[good])
    kept = [where[i] for i in np.flatnonzero(ok)]
    return obs, X, kept, ids


def pixel_jacobians(camera: CameraModel, obs: PointObservations, step: float = 1e-4
                    ) -> FloatArray:
    """``(K, 2, 2)`` the local map of ``camera`` from angles at each observation's ray (radians
    along the two directions of :meth:`PointObservations.tangent_basis`, the columns) to pixels
    (central differences of the exact projection over ``step`` radians; NaN where the
    projection is undefined)."""
    out = np.empty((len(obs.ray), 2, 2))
    for i, e in enumerate(obs.tangent_basis()):
        a = camera.pixels_from_rays(obs.ray + step * e)
        b = camera.pixels_from_rays(obs.ray - step * e)
        out[:, :, i] = (a - b) / (2 * step)
    return out


def adjust_model(rec: Any, image_ids: list[int], traj: Trajectory, lines: LineEvidence,
                 camera: CameraModel, options: JointOptions | None = None, *,
                 registered: Sequence[str] = (), registered_timestamps: FloatArray | None = None
                 ) -> tuple[JointResult, JointReport]:
    """The joint adjustment of the model's seeded images (``image_ids``, poses ``traj``), the
    init's lines and the model's points from their current positions; the model's poses and
    points set to its result, its rejected observations deleted. Returns the result (frames
    in the tracks' numbering, then one for each registered frame the tracks lack) and a
    report.

    ``registered``: names of images the mapper posed that have no input pose, with their
    ``registered_timestamps``; they are adjusted with the rest from the model's poses (their
    lines where the tracks have their frame), so that the whole model stays in one frame.

    Raises:
        OmniSfmError: the adjustment fails.
    """
    import pycolmap

    export = camera.colmap_export()
    extra, extra_ids = _registered_frames(rec, export, registered, registered_timestamps)
    tracks, k_extra = _with_frames(lines.tracks, extra.timestamps)
    k = lines.frame_of_pose
    obs, X, where, ids = model_points(rec, list(image_ids) + extra_ids, camera, export)
    F = tracks.num_frames
    R = np.full((F, 3, 3), np.nan)
    c = np.full((F, 3), np.nan)
    R[k], c[k] = traj.rotations, traj.positions
    R[k_extra], c[k_extra] = extra.rotations, extra.positions
    k_all = np.concatenate([k, k_extra])
    pobs = PointObservations(k_all[obs.frame], obs.point, obs.ray, obs.num_points,
                             obs.pixel_jacobian)
    res = joint_adjust(tracks, R, c, lines.directions, lines.points, pobs, X,
                       options=options or JointOptions())
    if not res.frames[k].all():
        raise OmniSfmError("joint adjustment: an input pose was lost")
    set_colmap_poses(rec, export, list(image_ids) + extra_ids,
                     Trajectory(np.concatenate([traj.timestamps, extra.timestamps]),
                                res.rotations[k_all], res.positions[k_all]))
    manager = pycolmap.ObservationManager(rec)
    for (image_id, idx), keep in zip(where, res.point_inliers.tolist(), strict=True):
        if not keep and rec.images[image_id].point2D(idx).has_point3D():
            manager.delete_observation(image_id, idx)
    for j, q in enumerate(ids):
        if res.points_used[j] and rec.exists_point3D(q):
            rec.points3D[q].xyz = res.points[j]
    rec.update_point_3d_errors()
    ev = res.evidence(tracks, pobs)
    report = JointReport(
        line_observations=int(ev["lines"].sum()),
        point_observations=int(res.point_inliers.sum()),
        point_observations_rejected=int((~res.point_inliers).sum()),
        lines_used=int(res.lines_used.sum()),
        points_used=int(res.points_used.sum()),
        line_noise_deg=res.line_sigma_deg, point_noise_deg=res.point_sigma_deg,
        line_rms_deg=res.line_rms_deg, point_rms_deg=res.point_rms_deg,
        iterations=res.iterations,
        evidence_per_frame=_evidence(ev, res, k, traj),
        registered_frames=RegisteredFrames(
            names=[rec.images[i].name for i in extra_ids],
            evidence_per_frame=_evidence(ev, res, k_extra, extra)) if len(extra_ids) else None)
    return res, report


def _evidence(ev: dict[str, np.ndarray], res: JointResult, k: np.ndarray, before: Trajectory
              ) -> FrameEvidence:
    """Per frame ``k``: its line and point observations, the lines' share of its rotation and
    position information, and how far the adjustment moved it from ``before``."""
    return FrameEvidence(
        lines=ev["lines"][k].tolist(),
        points=ev["points"][k].tolist(),
        line_share_rotation=_rounded(res.line_share[k, 0]),
        line_share_position=_rounded(res.line_share[k, 1]),
        rotation_change_deg=_rounded(np.degrees(rotation_angle(
            np.swapaxes(before.rotations, 1, 2) @ res.rotations[k]))),
        position_change=_rounded(np.linalg.norm(res.positions[k] - before.positions, axis=1)),
    )


def _registered_frames(rec: Any, export: ColmapExport, names: Sequence[str],
                       timestamps: FloatArray | None) -> tuple[Trajectory, list[int]]:
    """The poses and image ids of the posed images among ``names``."""
    if not len(names):
        return Trajectory(np.zeros(0), np.zeros((0, 3, 3)), np.zeros((0, 3))), []
    if timestamps is None or len(timestamps) != len(names):
        raise OmniSfmError("joint adjustment: registered frames need one timestamp each")
    traj, ok = trajectory_from_reconstruction(rec, export, list(names), timestamps)
    ids = [rec.find_image_with_name(n).image_id for n, o in zip(names, ok, strict=True) if o]
    return traj, ids


def _with_frames(tracks: LineTracks, timestamps: FloatArray) -> tuple[LineTracks, np.ndarray]:
    """``tracks`` with a frame for each of ``timestamps`` that it lacks (without
    observations), and the frame index of each."""
    ts = tracks.timestamps
    k = np.clip(np.searchsorted(ts, timestamps), 0, max(len(ts) - 1, 0))
    found = np.zeros(len(timestamps), bool) if len(ts) == 0 else \
        np.isclose(ts[k], timestamps, rtol=0, atol=1e-6)
    if found.all():
        return tracks, k
    k = k.copy()
    k[~found] = tracks.num_frames + np.arange(int((~found).sum()))
    return replace(tracks, num_frames=tracks.num_frames + int((~found).sum()),
                   timestamps=np.concatenate([ts, np.asarray(timestamps)[~found]])), k


def _rounded(values: FloatArray, digits: int = 6) -> list[float | None]:
    """JSON-ready: rounded, None for NaN."""
    return [None if not np.isfinite(v) else round(float(v), digits) for v in values]
