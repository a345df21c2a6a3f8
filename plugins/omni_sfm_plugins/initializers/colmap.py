"""``colmap``: pycolmap's incremental (or global) mapping on the same frames with the exact
camera model.

The camera goes to COLMAP through :meth:`omni_sfm.cameras.base.CameraModel.colmap_export`
(images mirrored left-right where the export says ``flip_u``, e.g. the hyperboloid), COLMAP's
SIFT with the camera's valid mask, sequential matching, geometric verification (seeded,
single-threaded RANSAC, so that runs are reproducible) and
``pycolmap.incremental_mapping`` with the intrinsics held fixed. Poses of the largest model
come back to omni-sfm's ray frame: ``cam_from_world = colmap_cam_from_cam^T @
cam_from_world_colmap``. A simulated sequence gives its point observations as keypoints (pixels
of the sequence's camera) and its tracks as matches. A rig camera (raw dual-fisheye frames)
goes to COLMAP as its rig (:mod:`omni_sfm.export.colmap_lenses`): each lens's images, camera
and mask, the lens offsets held (metres, so the poses come back metric), the poses those of
the rig's frame.

Options: ``max_features`` (4000), ``overlap`` (sequential matching, 10), ``init_min_tri_angle``
(degrees, COLMAP's default 16), ``seed`` (0), ``threads`` (1); ``mapper``: ``incremental``
(default) or ``global`` (``pycolmap.global_mapping``: COLMAP 4.2's global SfM, GLOMAP's rotation
averaging, global positioning and bundle adjustment, from scratch; it decomposes each pair's
stored geometry into the relative pose itself), both with the intrinsics held fixed;
``database``: a COLMAP database path to keep (features and matches it holds are reused, so two
mappers can run on the same database). ``info`` reports the seconds of the database
(``database_s``) and of the mapper (``mapper_s``).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.plugin_contract import InitializerResult, PointObservations, SequenceInput, failed
from omni_sfm.poses import Trajectory


def _frame_name(k: int) -> str:
    return f"{k:06d}.png"


def _verification(options: Mapping[str, Any]) -> Any:
    """COLMAP's two-view geometry options with a seeded, single-threaded RANSAC."""
    import pycolmap

    tvg = pycolmap.TwoViewGeometryOptions()
    tvg.ransac.random_seed = int(options.get("seed", 0))
    tvg.ransac.num_threads = 1
    return tvg


def _incremental_options(options: Mapping[str, Any]) -> Any:
    """COLMAP's incremental mapper, intrinsics held, seeded."""
    import pycolmap

    opts = pycolmap.IncrementalPipelineOptions()
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.ba_refine_sensor_from_rig = False
    opts.random_seed = int(options.get("seed", 0))
    opts.num_threads = int(options.get("threads", 1))
    if "init_min_tri_angle" in options:
        opts.mapper.init_min_tri_angle = float(options["init_min_tri_angle"])
    return opts


def _global_options(options: Mapping[str, Any]) -> Any:
    """COLMAP's global mapper (GLOMAP), intrinsics held, seeded, on the CPU."""
    import pycolmap

    opts = pycolmap.GlobalPipelineOptions()
    opts.random_seed = int(options.get("seed", 0))
    opts.num_threads = int(options.get("threads", 1))
    m = opts.mapper
    m.random_seed = opts.random_seed
    m.num_threads = opts.num_threads
    m.bundle_adjustment.refine_focal_length = False
    m.bundle_adjustment.refine_principal_point = False
    m.bundle_adjustment.refine_extra_params = False
    m.bundle_adjustment.refine_sensor_from_rig = False
    m.bundle_adjustment.ceres.use_gpu = False
    m.global_positioning.use_gpu = False
    return opts


def _write_rig_frames(db: Any, cam_id: int, names: list[str]) -> list[int]:
    """Images ``names`` of camera ``cam_id``, one single-camera rig and one frame per image."""
    import pycolmap

    rig = pycolmap.Rig()
    sensor = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cam_id)
    rig.add_ref_sensor(sensor)
    rig_id = db.write_rig(rig)
    ids = []
    for name in names:
        iid = db.write_image(pycolmap.Image(name=name, camera_id=cam_id))
        frame = pycolmap.Frame()
        frame.rig_id = rig_id
        frame.add_data_id(pycolmap.data_t(sensor, iid))
        db.write_frame(frame)
        ids.append(int(iid))
    return ids


def _database_from_points(db_path: Path, seq: SequenceInput, pts: PointObservations,
                          export: Any, options: Mapping[str, Any]) -> None:
    """Keypoints of the given observations, matches between frames ``overlap`` apart or less
    that share a track, COLMAP's geometric verification (seeded)."""
    import pycolmap

    overlap = int(options.get("overlap", 10))
    with pycolmap.Database.open(str(db_path)) as db:
        cam_id = int(db.write_camera(export.camera))
        ids = _write_rig_frames(db, cam_id, [_frame_name(k) for k in range(seq.num_frames)])
        per_frame: list[np.ndarray] = []
        for k in range(seq.num_frames):
            sel = np.flatnonzero(pts.obs_frame == k)
            db.write_keypoints(ids[k],
                               export.pixels_to_colmap(pts.obs_uv[sel]).astype(np.float32))
            per_frame.append(pts.obs_track[sel])
        for a in range(seq.num_frames):
            for b in range(a + 1, min(seq.num_frames, a + overlap + 1)):
                _, ia, ib = np.intersect1d(per_frame[a], per_frame[b], return_indices=True)
                if len(ia):
                    db.write_matches(ids[a], ids[b], np.stack([ia, ib], 1).astype(np.uint32))
    verifier = pycolmap.GeometricVerifierOptions()
    verifier.num_threads = 1
    pycolmap.geometric_verification(str(db_path), verifier_options=verifier,
                                    two_view_geometry_options=_verification(options))


def _database_from_images(db_path: Path, work: Path, seq: SequenceInput, export: Any,
                          options: Mapping[str, Any]) -> None:
    """COLMAP SIFT of the (mirrored where needed) frames with the camera mask, the exact camera
    shared by all, sequential matching with seeded geometric verification."""
    import cv2

    from omni_sfm.export.colmap import write_colmap_mask
    from omni_sfm.refine.database import extract_features, match_sequential

    img_dir = work / "images"
    img_dir.mkdir()
    names = [_frame_name(k) for k in range(seq.num_frames)]
    for k, name in enumerate(names):
        cv2.imwrite(str(img_dir / name), export.image_to_colmap(seq.read_image(k)))
    write_colmap_mask(work / "mask.png", seq.camera)
    threads = int(options.get("threads", 1))
    # COLMAP's own SIFT (COLMAP as its users run it) and refine's sequential matching, with a
    # seeded verification
    extract_features(db_path, img_dir, work / "mask.png", names, export,
                     max_features=int(options.get("max_features", 4000)), num_threads=threads,
                     extractor="colmap")
    match_sequential(db_path, overlap=int(options.get("overlap", 10)), num_threads=threads,
                     verification=_verification(options))


def _rig_database_from_images(db_path: Path, work: Path, seq: SequenceInput,
                              options: Mapping[str, Any]) -> Any:
    """A rig camera's frames as COLMAP's rig (:func:`omni_sfm.refine.rig.rig_database`): each
    lens's part of every frame (``lensK/NAME``), COLMAP SIFT with the lens's mask and exact
    camera, the rig applied to the database, then sequential matching. Returns the lenses'
    exports."""
    from omni_sfm.cameras import RigCamera
    from omni_sfm.export.colmap_lenses import LensExports
    from omni_sfm.refine.rig import rig_database, write_lens_images

    camera = seq.camera
    assert isinstance(camera, RigCamera)
    names = [_frame_name(k) for k in range(seq.num_frames)]
    write_lens_images(work / "images", LensExports.of(camera),
                      ((n, seq.read_image(k)) for k, n in enumerate(names)))
    return rig_database(db_path, work, work / "images", camera, names,
                        max_features=int(options.get("max_features", 4000)),
                        num_threads=int(options.get("threads", 1)),
                        overlap=int(options.get("overlap", 10)), extractor="colmap",
                        verification=_verification(options)).lenses


def _trajectory(best: Any, export: Any, timestamps: np.ndarray) -> tuple[Trajectory, int]:
    """The poses of the frames the model poses (omni-sfm's ray frame:
    ``colmap_cam_from_cam^T`` after COLMAP's), and their number."""
    C = np.asarray(export.colmap_cam_from_cam)
    frames, Rs, cs = [], [], []
    for im in best.images.values():
        if not im.has_pose:
            continue
        cw = im.cam_from_world()
        R_cw = np.asarray(cw.rotation.matrix())
        frames.append(int(Path(im.name).stem))
        Rs.append(R_cw.T @ C)
        cs.append(-R_cw.T @ np.asarray(cw.translation, float))
    order = np.argsort(frames)
    fr = np.asarray(frames, dtype=np.int64)[order]
    return Trajectory(timestamps[fr].copy(), np.asarray(Rs).reshape(-1, 3, 3)[order],
                      np.asarray(cs).reshape(-1, 3)[order]), len(fr)


def colmap(sequence: SequenceInput, options: Mapping[str, Any]) -> InitializerResult:
    """The ``colmap`` initializer (module docstring)."""
    import pycolmap

    from omni_sfm.cameras import RigCamera

    rig = isinstance(sequence.camera, RigCamera)
    if rig and sequence.images is None:
        return failed("a rig camera needs the frames themselves")
    export = None if rig else sequence.camera.colmap_export()
    prev_level = pycolmap.logging.minloglevel
    # the mapper's own errors ("Failed to create any sparse model") become this result's
    # reason; COLMAP's log is for --verbose
    verbose = bool(options.get("verbose", False))
    pycolmap.logging.minloglevel = 0 if verbose else 3
    try:
        with tempfile.TemporaryDirectory(prefix="omni_sfm_colmap_") as tmp:
            work = Path(tmp)
            db_path = Path(options["database"]) if options.get("database") else \
                work / "database.db"
            t0 = time.perf_counter()
            lenses = None
            if rig:
                lenses = _rig_database_from_images(db_path, work, sequence, options)
                source = "COLMAP SIFT, each lens of the rig"
            elif sequence.images is not None:
                _database_from_images(db_path, work, sequence, export, options)
                source = "COLMAP SIFT"
            elif sequence.points is not None:
                _database_from_points(db_path, sequence, sequence.points, export, options)
                source = "given"
            else:
                return failed("the sequence has neither images nor point observations")
            database_s = time.perf_counter() - t0
            mapper = str(options.get("mapper", "incremental"))
            out = work / "sparse"
            out.mkdir()
            t0 = time.perf_counter()
            try:
                if mapper == "global":
                    models = pycolmap.global_mapping(str(db_path), str(work), str(out),
                                                     _global_options(options))
                elif mapper == "incremental":
                    models = pycolmap.incremental_mapping(str(db_path), str(work), str(out),
                                                          _incremental_options(options))
                else:
                    return failed(f"unknown mapper {mapper!r} (incremental, global)")
            except Exception as exc:  # the mapper raises when it gives up
                return failed(f"COLMAP's mapper failed: {str(exc).splitlines()[0][:200]}")
            mapper_s = time.perf_counter() - t0
            with pycolmap.Database.open(str(db_path)) as db:
                verified = int(db.num_verified_image_pairs())
    finally:
        pycolmap.logging.minloglevel = prev_level
    best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
    info: dict[str, Any] = {"features": source, "verified_pairs": verified,
                            "models": len(models), "mapper": mapper,
                            "database_s": round(database_s, 3), "mapper_s": round(mapper_s, 3)}
    if best is None or best.num_reg_images() == 0:
        return failed(f"COLMAP's mapper built no model ({verified} verified image pairs)",
                      **info)
    if lenses is not None:
        from omni_sfm.refine.rig import rig_trajectory

        traj, posed = rig_trajectory(best, lenses.camera, [_frame_name(k) for k in range(
            sequence.num_frames)], sequence.timestamps)
        n = int(posed.sum())
    else:
        traj, n = _trajectory(best, export, sequence.timestamps)
    info.update({"points3D": int(best.num_points3D()), "registered": n})
    if lenses is not None:
        info["metres_per_unit"] = 1.0
    if n < 3:
        return InitializerResult(traj, "failed", f"COLMAP registered {n} frames", info=info)
    reason = "" if n == sequence.num_frames else \
        f"COLMAP registered {n} of {sequence.num_frames} frames"
    return InitializerResult(traj, "ok", reason, info=info)
