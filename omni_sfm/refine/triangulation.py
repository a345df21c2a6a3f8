"""Points for the posed frames of a COLMAP model from its database's verified matches, the poses
held: tracks are the connected components of the match graph, each triangulated by least
squares over its rays, observations that disagree dropped, then COLMAP's own filter (pixel
reprojection error, triangulation angle).

COLMAP's incremental triangulator (``IncrementalMapper.triangulate_image`` over every image,
then track completion and merging) does the same job one image and one correspondence at a
time; on video, where matches run along tracks, its time per frame grew with the sequence
(158 / 253 / 311 ms a frame on 100 / 300 / 1,000 frames of the office walk with SIFT) and it
took 255 ms a frame on KLT matches. Here every step is one pass over the observations.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras.base import CameraModel
from omni_sfm.export.colmap import ColmapExport
from omni_sfm.geometry import FloatArray, angle_between


def angular_resolution_rad(camera: CameraModel) -> float:
    """Median angle between the rays of horizontally adjacent valid pixels."""
    rays = camera.pixel_grid_rays()
    dots = np.sum(rays[::4, :-1:4] * rays[::4, 1::4], axis=-1)
    return float(np.median(np.arccos(np.clip(dots[np.isfinite(dots)], -1.0, 1.0))))


def tracks_from_matches(pairs: list[tuple[int, int, np.ndarray]], num_keypoints: dict[int, int]
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tracks of the match graph: ``pairs`` (image id 1, image id 2, ``(n, 2)`` keypoint index
    pairs) among the images of ``num_keypoints`` (image id -> keypoint count). Returns
    ``(image_id, keypoint, track)``, one row per keypoint on a track of two or more, track ids
    consecutive from 0, sorted by track."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ids = np.array(sorted(num_keypoints), np.int64)
    sizes = np.array([num_keypoints[i] for i in ids.tolist()], np.int64)
    first = np.cumsum(sizes) - sizes  # each image's first node
    offset = dict(zip(ids.tolist(), first.tolist(), strict=True))
    n = int(sizes.sum())
    a = [offset[i] + m[:, 0] for i, j, m in pairs if len(m)]
    b = [offset[j] + m[:, 1] for i, j, m in pairs if len(m)]
    if not a:
        z = np.zeros(0, np.int64)
        return z, z, z
    src, dst = np.concatenate(a), np.concatenate(b)
    graph = coo_matrix((np.ones(len(src), np.int8), (src, dst)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    size = np.bincount(label)
    node = np.flatnonzero(size[label] >= 2)
    node = node[np.argsort(label[node], kind="stable")]
    _, track = np.unique(label[node], return_inverse=True)
    which = np.searchsorted(first, node, side="right") - 1
    return ids[which], node - first[which], track.astype(np.int64)


def triangulate_rays(track: np.ndarray, rays: FloatArray, centres: FloatArray,
                     max_error_rad: float, rounds: int = 5
                     ) -> tuple[FloatArray, np.ndarray]:
    """Each track's point from its observations' world rays ``(K, 3)`` (unit) from
    ``centres`` ``(K, 3)``: least squares over the rays' perpendicular distances; then, in up
    to ``rounds`` rounds, the observations behind their camera and those off by more than
    ``max_error_rad`` and by at least half their track's largest error (one gross outlier
    pulls the point, and with it the good observations, off) are dropped and the point solved
    again. Returns the points ``(T, 3)`` (NaN: fewer than two observations left, or no
    intersection) and the ``(K,)`` kept observations, each within ``max_error_rad``."""
    T = int(track.max()) + 1 if len(track) else 0
    on = np.ones(len(track), bool)
    X = np.full((T, 3), np.nan)
    for round_ in range(rounds + 1):
        w, c, t = rays[on], centres[on], track[on]
        # sum over a track of (I - w w^T) and of (I - w w^T) c, without the (K, 3, 3) terms
        count = np.bincount(t, minlength=T).astype(float)
        ww = {(i, j): np.bincount(t, w[:, i] * w[:, j], T) for i in range(3) for j in range(i, 3)}
        A = np.empty((T, 3, 3))
        for (i, j), v in ww.items():
            A[:, i, j] = A[:, j, i] = (count if i == j else 0.0) - v
        wc = np.einsum("ki,ki->k", w, c)
        rhs = np.stack([np.bincount(t, c[:, i] - w[:, i] * wc, T) for i in range(3)], 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            ev = np.linalg.eigvalsh(A)  # ascending; A is symmetric positive semi-definite
            ok = (count >= 2) & (ev[:, 0] > 1e-8 * ev[:, 2])
        X[:] = np.nan
        X[ok] = np.linalg.solve(A[ok], rhs[ok][:, :, None])[:, :, 0]
        err = angle_between(X[track] - centres, rays)
        bad = ~(err <= max_error_rad)
        if round_ == rounds or not (bad & on).any():
            break
        worst = np.zeros(T)
        np.maximum.at(worst, track[on], np.nan_to_num(err[on], nan=np.pi))
        on &= ~(bad & ~(err < 0.5 * worst[track]))
    return X, on & ~bad


def _repose_outliers(rec: Any, rows: dict[int, np.ndarray], keypoints: dict[int, FloatArray],
                     kp: np.ndarray, track: np.ndarray, X: FloatArray, on: np.ndarray,
                     min_observations: int = 15) -> list[int]:
    """Images of ``rec`` whose pose disagrees with the points the others triangulated (at
    least ``min_observations`` of their keypoints on a track with a point, fewer than half of
    them kept): each is posed again from those 2D-3D pairs by COLMAP's absolute pose
    (LO-RANSAC and refinement) in place, where that finds ``min_observations`` inliers. A
    blunder of the input (one frame 8 deg off) then still gets its observations, and the
    adjustment corrects it as far as they back it. Returns the ids of the images posed
    again."""
    import pycolmap

    moved = []
    for i, r in rows.items():
        has = np.isfinite(X[track[r]]).all(1)
        if has.sum() < min_observations or on[r][has].sum() >= 0.5 * has.sum():
            continue
        im = rec.images[i]
        est = pycolmap.estimate_and_refine_absolute_pose(
            keypoints[i][kp[r[has]]], X[track[r[has]]], rec.cameras[im.camera_id])
        if est is None or int(np.sum(est["inlier_mask"])) < min_observations:
            continue
        rec.frame(im.frame_id).rig_from_world = est["cam_from_world"]
        moved.append(i)
    return moved


def _one_per_image(track: np.ndarray, image: np.ndarray, error: FloatArray) -> np.ndarray:
    """``(K,)`` bool: the observation with the smallest error of each (track, image)."""
    order = np.lexsort((error, image, track))
    first = np.ones(len(order), bool)
    first[1:] = (np.diff(track[order]) != 0) | (np.diff(image[order]) != 0)
    keep = np.zeros(len(track), bool)
    keep[order[first]] = True
    return keep


def triangulate_seeded(rec: Any, db_path: Path, image_dir: Path, camera: CameraModel,
                       export: ColmapExport, *, max_error_px: float = 4.0,
                       min_angle_deg: float = 1.5) -> tuple[Any, list[str]]:
    """COLMAP's points for the posed images of ``rec`` (poses held, in place) from the
    database's verified matches among them; colours read from ``image_dir``. An observation
    whose ray misses its point by more than ``max_error_px`` (twice that, in angle at the
    camera's median resolution, while the points are solved; then COLMAP's exact pixel error)
    or lies behind the camera is dropped, a track keeps one observation per image, and a
    point seen under less than ``min_angle_deg`` is removed. A seeded image whose pose
    disagrees with the others' points is posed again from them (:func:`_repose_outliers`).
    Returns the model and the names of the images posed again."""
    import pycolmap

    with pycolmap.Database.open(str(db_path)) as db:
        pair_ids, geoms = db.read_two_view_geometries()
        posed = sorted(i for i in rec.images if rec.images[i].has_pose)
        keypoints = {i: np.asarray(db.read_keypoints(i), float)[:, :2] for i in posed}
    for i in posed:  # the seeded images' keypoints, as COLMAP's mapper would load them
        if rec.images[i].num_points2D() == 0:
            rec.images[i].points2D = pycolmap.Image(keypoints=keypoints[i]).points2D
    inside = set(posed)
    pairs = []
    for pair_id, g in zip(pair_ids, geoms, strict=True):
        i, j = pycolmap.pair_id_to_image_pair(pair_id)
        if i in inside and j in inside:
            pairs.append((int(i), int(j), np.asarray(g.inlier_matches, np.int64).reshape(-1, 2)))
    image, kp, track = tracks_from_matches(pairs, {i: len(keypoints[i]) for i in posed})
    if len(track) == 0:
        return rec, []
    rays = np.full((len(kp), 3), np.nan)
    centres = np.zeros((len(kp), 3))
    by_image = np.argsort(image, kind="stable")
    bounds = np.searchsorted(image[by_image], [*posed, max(posed) + 1])
    rows = {i: by_image[a:b] for i, a, b in zip(posed, bounds[:-1], bounds[1:], strict=True)}

    def place(i: int) -> None:  # image i's observations as world rays from its centre
        im = rec.images[i]
        world_from_cam = np.asarray(im.cam_from_world().rotation.matrix()).T @ \
            export.colmap_cam_from_cam
        r = camera.rays_from_pixels(export.pixels_from_colmap(keypoints[i][kp[rows[i]]]))
        rays[rows[i]] = r @ world_from_cam.T
        centres[rows[i]] = np.asarray(im.projection_center())

    for i in posed:
        place(i)
    loose = 2.0 * max_error_px * angular_resolution_rad(camera)
    X, on = triangulate_rays(track, rays, centres, loose)
    reposed = _repose_outliers(rec, rows, keypoints, kp, track, X, on)
    for i in reposed:
        place(i)
    err = angle_between(X[track] - centres, rays)
    on = (err <= loose) & _one_per_image(track, image, np.where(err <= loose, err, np.inf))
    X, on2 = triangulate_rays(track[on], rays[on], centres[on], loose)
    keep = np.flatnonzero(on)[on2]
    image, kp, track = image[keep], kp[keep], track[keep]
    starts = np.flatnonzero(np.r_[True, np.diff(track) != 0, True])
    for a, b in zip(starts[:-1], starts[1:], strict=True):
        if b - a < 2:
            continue
        rec.add_point3D(X[track[a]], pycolmap.Track([pycolmap.TrackElement(int(i), int(k))
                                                     for i, k in zip(image[a:b], kp[a:b],
                                                                     strict=True)]))
    pycolmap.ObservationManager(rec).filter_all_points3D(max_error_px, min_angle_deg)
    rec.extract_colors_for_all_images(str(image_dir))
    return rec, [rec.images[i].name for i in reposed]
