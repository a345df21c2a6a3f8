"""The frames the init missed, registered through COLMAP's global machinery (``refine --mapper
global``): rotation averaging and global positioning, seeded by the line-based poses.

1. **Pose graph**: every verified pair of the database with a missed frame gets its relative pose
   from its inlier matches (``pycolmap.estimate_relative_pose``: LO-RANSAC on the rays of the
   exact camera model, so any omnidirectional camera; COLMAP's own verification stores no
   relative pose for these cameras, docs/colmap.md); a pair of two seeded frames gets the
   relative pose of their line-based poses.
2. **Rotations**: each missed frame starts from a seeded neighbour's rotation composed with
   their relative rotation (the best-matched chain), then ``pycolmap.run_rotation_averaging``
   (no initialisation of its own: the seed is the start) averages the graph. Its result is put
   back onto the seed (the rotation taking the averaged seeded frames onto their line-based
   rotations, a chordal mean), and the seeded frames keep their line-based rotations.
3. **Observations**: a missed frame's keypoint matched to a keypoint that already carries a point
   of the triangulated model observes that point (one observation per point and frame).
4. **Positions**: ``pycolmap.run_global_positioning`` with the rotations held, the points held
   (they were triangulated on the seeded poses: they fix the gauge) and the positions started at
   the nearest seeded neighbour's centre; then the seeded frames are put back at their seed and
   observations with a large reprojection error are dropped. A missed frame left with fewer
   than ``min_observations`` observations is not registered.

The joint adjustment of refine then adjusts these frames with the rest."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras.base import CameraModel
from omni_sfm.export.colmap import ColmapExport
from omni_sfm.geometry import FloatArray, nearest_rotation
from omni_sfm.refine.triangulation import angular_resolution_rad
from omni_sfm.reports import MapperReport


@dataclass(frozen=True)
class GlobalRegistration:
    """What :func:`register_global` did (``report.json``: ``mapper``)."""

    registered: list[str]
    not_registered: list[str]
    pairs: int
    """Verified pairs with a missed frame whose relative pose was estimated."""
    rotation_averaging: bool
    global_positioning: bool
    observations: int
    """Observations of the registered frames on the model's points."""

    def report(self) -> MapperReport:
        return MapperReport(mapper="global", registered=self.registered,
                            not_registered=self.not_registered, relative_poses=self.pairs,
                            rotation_averaging_converged=self.rotation_averaging,
                            global_positioning_converged=self.global_positioning,
                            observations_of_registered_frames=self.observations)


def _rigid(R: FloatArray, t: FloatArray) -> Any:
    import pycolmap

    return pycolmap.Rigid3d(np.hstack([R, np.asarray(t, float).reshape(3, 1)]))


def _pose(rec: Any, image_id: int) -> tuple[FloatArray, FloatArray]:
    """``(R, t)`` cam_from_world of a posed image of ``rec``."""
    T = np.asarray(rec.images[image_id].cam_from_world().matrix())
    return T[:, :3], T[:, 3]


def _chordal_mean(Rs: list[FloatArray]) -> FloatArray:
    return nearest_rotation(np.sum(Rs, axis=0))


@dataclass
class _Graph:
    """The database's verified pairs with a missed frame, and their relative poses."""

    pairs: list[tuple[int, int, np.ndarray]]
    """(image id 1, image id 2, ``(n, 2)`` inlier keypoint pairs)."""
    keypoints: dict[int, FloatArray]
    relative: dict[tuple[int, int], tuple[FloatArray, FloatArray, int]]
    """(i, j) -> cam_j_from_cam_i rotation, translation and inlier count."""


def _read_pairs(db_path: Path, new: set[int], posed: set[int], min_inliers: int
                ) -> tuple[list[tuple[int, int, np.ndarray]], dict[int, FloatArray]]:
    import pycolmap

    with pycolmap.Database.open(str(db_path)) as db:
        pair_ids, geoms = db.read_two_view_geometries()
        pairs = []
        for pair_id, g in zip(pair_ids, geoms, strict=True):
            i, j = (int(v) for v in pycolmap.pair_id_to_image_pair(pair_id))
            m = np.asarray(g.inlier_matches, np.int64).reshape(-1, 2)
            if len(m) >= min_inliers and (i in new or j in new) and {i, j} <= new | posed:
                pairs.append((i, j, m))
        keypoints = {i: np.asarray(db.read_keypoints(i), float)[:, :2]
                     for i in {k for p in pairs for k in p[:2]}}
    return pairs, keypoints


def _relative_poses(camera: CameraModel, export: ColmapExport,
                    pairs: list[tuple[int, int, np.ndarray]], keypoints: dict[int, FloatArray],
                    max_error_px: float, min_inliers: int
                    ) -> dict[tuple[int, int], tuple[FloatArray, FloatArray, int]]:
    """Each pair's relative pose (COLMAP's camera frames) by COLMAP's LO-RANSAC on the rays of
    the exact camera model. Given pixels and a COLMAP camera, the estimator works on the
    camera's normalised image plane, which holds only the rays in front of the camera: through
    the mirror it kept a third of the verified matches and took five times as long."""
    import pycolmap

    ransac = pycolmap.RANSACOptions()
    ransac.max_error = 0.5 * max_error_px * angular_resolution_rad(camera)
    ransac.min_num_trials = 100  # COLMAP's two-view verification's bounds
    ransac.max_num_trials = 10000
    ransac.confidence = 0.999
    ransac.random_seed = 0
    C = np.asarray(export.colmap_cam_from_cam)
    rays = {i: camera.rays_from_pixels(export.pixels_from_colmap(kp)) @ C.T
            for i, kp in keypoints.items()}
    rel = {}
    for i, j, m in pairs:
        est = pycolmap.estimate_relative_pose(rays[i][m[:, 0]], rays[j][m[:, 1]], ransac)
        if est is None:
            continue
        n_in = int(np.sum(est["inlier_mask"]))
        if n_in >= min_inliers:
            T = np.asarray(est["cam2_from_cam1"].matrix())
            rel[(i, j)] = (T[:, :3], T[:, 3], n_in)
    return rel


def _start_poses(rel: dict[tuple[int, int], tuple[FloatArray, FloatArray, int]],
                 start: dict[int, FloatArray], centre: dict[int, FloatArray]) -> None:
    """Rotations (and centres: the neighbour's) of the frames reachable from ``start`` along
    the best-matched edges, in place."""
    todo = sorted(rel.items(), key=lambda kv: -kv[1][2])
    grew = True
    while grew:
        grew = False
        for (i, j), (R, _, _) in todo:
            if i in start and j not in start:
                start[j], centre[j] = R @ start[i], centre[i]
                grew = True
            elif j in start and i not in start:
                start[i], centre[i] = R.T @ start[j], centre[j]
                grew = True


def _observe(rec: Any, pairs: list[tuple[int, int, np.ndarray]], ids: set[int]) -> None:
    """The frames ``ids`` observe the model's points their keypoints are matched to (one
    observation per point and frame), in place."""
    import pycolmap

    seen: dict[int, set[int]] = defaultdict(set)
    for i, j, m in pairs:
        if (i in ids) == (j in ids):
            continue
        new_id, old_id, cols = (i, j, [0, 1]) if i in ids else (j, i, [1, 0])
        old, new = rec.images[old_id], rec.images[new_id]
        for k_new, k_old in m[:, cols].tolist():
            p = old.points2D[k_old]
            if not p.has_point3D() or p.point3D_id in seen[new_id] or \
                    new.points2D[k_new].has_point3D():
                continue
            rec.add_observation(p.point3D_id, pycolmap.TrackElement(new_id, k_new))
            seen[new_id].add(p.point3D_id)


def _add_images(rec: Any, db_path: Path, want: list[Any], keypoints: dict[int, FloatArray],
                start: dict[int, FloatArray], centre: dict[int, FloatArray]) -> set[int]:
    """The database's frames and images ``want`` that have a start pose, added to ``rec``
    posed there; their image ids."""
    import pycolmap

    with pycolmap.Database.open(str(db_path)) as db:
        frames = {f.frame_id: f for f in db.read_all_frames()}
        rigs = {r.rig_id: r for r in db.read_all_rigs()}
    ids = set()
    for im in want:
        if im.image_id not in start:
            continue
        frame = frames[im.frame_id]
        R = start[im.image_id]
        frame.rig_from_world = _rigid(R, -R @ centre[im.image_id])
        if not rec.exists_rig(frame.rig_id):
            rec.add_rig(rigs[frame.rig_id])
        rec.add_frame(frame)
        image = pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id,
                               keypoints=keypoints.get(im.image_id, np.zeros((0, 2))))
        image.frame_id = im.frame_id
        rec.add_image(image)
        ids.add(im.image_id)
    return ids


def register_global(rec: Any, db_path: Path, missed: list[str], camera: CameraModel,
                    export: ColmapExport, *, min_inliers: int = 15,
                    max_error_px: float = 4.0, min_angle_deg: float = 1.5,
                    min_observations: int = 15) -> GlobalRegistration:
    """Register the frames ``missed`` (names of database images without a pose) into ``rec``
    (in place; its posed images keep their poses) by COLMAP's rotation averaging and global
    positioning, seeded by the posed images (the module's docstring)."""
    import pycolmap

    with pycolmap.Database.open(str(db_path)) as db:
        db_images = {im.name: im for im in db.read_all_images()}
    want = [db_images[n] for n in missed if n in db_images]
    posed = {i for i in rec.images if rec.images[i].has_pose}
    pairs, keypoints = _read_pairs(db_path, {im.image_id for im in want}, posed, min_inliers)
    rel = _relative_poses(camera, export, pairs, keypoints, max_error_px, min_inliers)
    if not rel:
        return GlobalRegistration([], [im.name for im in want], 0, False, False, 0)
    graph = pycolmap.PoseGraph()
    for (i, j), (R, t, n_in) in rel.items():
        graph.add_edge(i, j, pycolmap.PoseGraphEdge(cam2_from_cam1=_rigid(R, t), num_matches=n_in))
    seed = {i: _pose(rec, i) for i in posed}
    seeded = sorted(posed)
    for a, b in zip(seeded[:-1], seeded[1:], strict=True):  # the seed's own relative poses
        (Ra, ta), (Rb, tb) = seed[a], seed[b]
        graph.add_edge(a, b, pycolmap.PoseGraphEdge(
            cam2_from_cam1=_rigid(Rb @ Ra.T, tb - Rb @ Ra.T @ ta), num_matches=1000))
    start = {i: seed[i][0] for i in posed}
    centre = {i: np.asarray(rec.images[i].projection_center()) for i in posed}
    _start_poses(rel, start, centre)
    ids = _add_images(rec, db_path, want, keypoints, start, centre)
    ra = pycolmap.RotationEstimatorOptions()
    ra.skip_initialization = True
    ok_ra = bool(pycolmap.run_rotation_averaging(ra, graph, rec, []))
    if ok_ra:  # back onto the seed: the rotation taking the averaged seeded frames onto theirs
        fix = _chordal_mean([_pose(rec, i)[0].T @ seed[i][0] for i in posed
                             if rec.images[i].has_pose])
        for i in ids:
            if rec.images[i].has_pose:
                start[i] = _pose(rec, i)[0] @ fix
    for i in posed:
        rec.frame(rec.images[i].frame_id).rig_from_world = _rigid(*seed[i])
    for i in ids:
        rec.frame(rec.images[i].frame_id).rig_from_world = _rigid(start[i],
                                                                  -start[i] @ centre[i])
    _observe(rec, pairs, ids)
    gp = pycolmap.GlobalPositionerOptions()  # positions only: rotations and points held
    gp.generate_random_positions = False
    gp.generate_random_points = False
    gp.optimize_points = False
    gp.use_gpu = False
    ok_gp = bool(pycolmap.run_global_positioning(gp, graph, rec))
    for i in posed:
        rec.frame(rec.images[i].frame_id).rig_from_world = _rigid(*seed[i])
    pycolmap.ObservationManager(rec).filter_all_points3D(max_error_px, min_angle_deg)
    registered, count = [], 0
    for im in want:
        i = im.image_id
        n = rec.images[i].num_points3D if i in ids and rec.images[i].has_pose else 0
        if i in ids and n < min_observations:
            rec.deregister_frame(rec.images[i].frame_id)
        elif i in ids:
            registered.append(im.name)
            count += n
    return GlobalRegistration(registered, [im.name for im in want if im.name not in registered],
                              len(rel), ok_ra, ok_gp, count)
