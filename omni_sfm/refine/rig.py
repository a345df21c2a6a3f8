"""COLMAP's rig from a rig camera's frames (raw dual-fisheye footage, a camchain), for
``omni-sfm refine`` and the ``colmap`` initializer (docs/colmap.md, "A rig camera").

- :func:`rig_database`: each lens's part of every frame (``lensK/NAME``, mirrored where COLMAP's
  model of the lens wants it) and each lens's mask, SIFT in every lens image with the lens's
  exact camera (one COLMAP camera per lens), the rig applied to the database as COLMAP's
  ``rig_configurator`` does (lens 0 the reference sensor, the others at their offsets in
  metres: the lens images of one frame are one COLMAP frame), then COLMAP's sequential
  matching with its geometric verification.
- :func:`seed_rig_for_database`: the rig's frames posed (world_from_rig in metres) with the
  database's camera, rig, frame and image ids, so that ``pycolmap.triangulate_points`` and
  COLMAP's adjustment take them.
- :func:`rig_trajectory`: the frames' poses back from a COLMAP model (world_from_rig).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from omni_sfm.cameras import RigCamera
from omni_sfm.errors import OmniSfmError
from omni_sfm.export.colmap_lenses import (
    RIG_CONFIG_FILE,
    LensExports,
    build_lens_rig,
    lens_image_name,
    lens_mask_name,
    write_lens_masks,
    write_rig_config,
)
from omni_sfm.poses import Trajectory
from omni_sfm.refine.database import extract_features, match_sequential


@dataclass(frozen=True)
class RigDatabase:
    """What :func:`rig_database` put in the database.

    Attributes:
        lenses: how each lens goes to COLMAP.
        extracted_images: lens images whose features were extracted.
        reused_images: lens images whose features the database already held.
        keypoints: keypoints in the database.
        verified_pairs: verified image pairs after matching.
        inlier_matches: their inlier matches.
    """

    lenses: LensExports
    extracted_images: int
    reused_images: int
    keypoints: int
    verified_pairs: int
    inlier_matches: int


def write_lens_images(image_dir: Path, lenses: LensExports,
                      frames: Iterable[tuple[str, np.ndarray]]) -> None:
    """Each lens's part of every ``(name, frame)`` as ``image_dir/lensK/name``
    (:meth:`LensExports.images`)."""
    for name, frame in frames:
        for lens, img in enumerate(lenses.images(frame)):
            path = Path(image_dir) / lens_image_name(lens, name)
            path.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(path), img):
                raise OmniSfmError(f"{path}: cannot write the lens image")


def rig_database(db_path: Path, work: Path, image_dir: Path, camera: RigCamera,
                 names: Sequence[str], *, max_features: int, num_threads: int, overlap: int,
                 extractor: str = "opencv", verification: Any | None = None) -> RigDatabase:
    """Features, the rig and the matches of the lens images ``image_dir/lensK/NAME`` of the
    frames ``names`` (:func:`write_lens_images`) in the COLMAP database ``db_path`` (module
    docstring); ``work`` receives each lens's mask and ``rig_config.json``. ``extractor`` and
    ``verification`` as :func:`~omni_sfm.refine.database.extract_features` and
    :func:`~omni_sfm.refine.database.match_sequential` take them."""
    import pycolmap

    lenses = LensExports.of(camera)
    write_lens_masks(work, lenses)
    extracted = reused = 0
    for lens in range(lenses.num_lenses):
        f = extract_features(db_path, image_dir, work / lens_mask_name(lens),
                             [lens_image_name(lens, n) for n in names], lenses.exports[lens],
                             max_features=max_features, num_threads=num_threads,
                             extractor=extractor)
        extracted, reused = extracted + len(f.extracted), reused + len(f.reused)
        keypoints = f.num_keypoints
    one = Trajectory(np.zeros(1), np.eye(3)[None], np.zeros((1, 3)))
    write_rig_config(work, build_lens_rig(camera, one, ["rig.png"], 1.0).reconstruction)
    with pycolmap.Database.open(str(db_path)) as db:
        # a database given again holds the rig already
        if not any(r.num_sensors() == lenses.num_lenses for r in db.read_all_rigs()):
            pycolmap.apply_rig_config(pycolmap.read_rig_config(str(work / RIG_CONFIG_FILE)),
                                      db)
    m = match_sequential(db_path, overlap=overlap, num_threads=num_threads,
                         verification=verification)
    return RigDatabase(lenses, extracted, reused, keypoints, m.verified_pairs, m.inlier_matches)


def seed_rig_for_database(camera: RigCamera, traj: Trajectory, frame_names: Sequence[str],
                          database_path: Path) -> tuple[Any, list[list[int]]]:
    """The rig's frames posed at ``traj`` (world_from_rig, metres; row k is the frame named
    ``frame_names[k]``) with the ids of the database :func:`rig_database` made, and each
    frame's image ids, lens by lens. OmniSfmError when a lens image is not in the database."""
    import pycolmap

    built = build_lens_rig(camera, traj, frame_names, 1.0).reconstruction
    with pycolmap.Database.open(str(database_path)) as db:
        db_images = {im.name: im for im in db.read_all_images()}
        cams = {c.camera_id: c for c in db.read_all_cameras()}
        rigs = {r.rig_id: r for r in db.read_all_rigs()}
        frames = {f.frame_id: f for f in db.read_all_frames()}
    by_name = {im.name: im for im in built.images.values()}
    lenses = LensExports.of(camera)
    rows = [lenses.image_names(str(n)) for n in frame_names]
    missing = [n for row in rows for n in row if n not in db_images]
    if missing:
        raise OmniSfmError(f"{database_path}: lens image {missing[0]!r} is not in the database")
    rec = pycolmap.Reconstruction()
    for lens in range(lenses.num_lenses):  # cameras before the rig that holds them
        cam_id = db_images[rows[0][lens]].camera_id
        cam = lenses.exports[lens].camera
        db_cam = cams[cam_id]
        if (db_cam.model_name, db_cam.width, db_cam.height) != (cam.model_name, cam.width,
                                                                cam.height):
            raise OmniSfmError(f"{database_path}: camera {cam_id} is not lens {lens}'s "
                               f"({cam.model_name} {cam.width}x{cam.height})")
        cam.camera_id = cam_id
        rec.add_camera(cam)
    ids: list[list[int]] = []
    for row in rows:
        frame = frames[db_images[row[0]].frame_id]
        if {int(d.id) for d in frame.data_ids} != {db_images[n].image_id for n in row}:
            raise OmniSfmError(f"{database_path}: the lens images {row} are not one frame of "
                               "the rig (rig_config.json not applied)")
        if not rec.exists_rig(frame.rig_id):
            rec.add_rig(rigs[frame.rig_id])
        frame.rig_from_world = by_name[row[0]].cam_from_world()
        rec.add_frame(frame)
        for n in row:
            db_im = db_images[n]
            image = pycolmap.Image(name=n, camera_id=db_im.camera_id, image_id=db_im.image_id)
            image.frame_id = frame.frame_id
            rec.add_image(image)
        ids.append([int(db_images[n].image_id) for n in row])
    return rec, ids


def rig_trajectory(rec: Any, camera: RigCamera, frame_names: Sequence[str],
                   timestamps: np.ndarray) -> tuple[Trajectory, np.ndarray]:
    """The poses world_from_rig (the model's units) of the frames ``frame_names`` whose lens 0
    image ``rec`` poses, with their ``timestamps``, and the ``(N,)`` mask of those posed."""
    L0 = LensExports.of(camera).colmap_lens_from_rig(1.0)[0]
    by_name = {im.name: im for im in rec.images.values()}
    ok = np.zeros(len(frame_names), bool)
    Rs, cs = [], []
    for k, name in enumerate(frame_names):
        im = by_name.get(lens_image_name(0, str(name)))
        if im is None or not im.has_pose:
            continue
        T = np.eye(4)
        T[:3] = np.asarray(im.cam_from_world().matrix())
        world_from_rig = np.linalg.inv(np.linalg.inv(L0) @ T)
        ok[k] = True
        Rs.append(world_from_rig[:3, :3])
        cs.append(world_from_rig[:3, 3])
    return Trajectory(np.asarray(timestamps, float)[ok].copy(),
                      np.asarray(Rs).reshape(-1, 3, 3), np.asarray(cs).reshape(-1, 3)), ok
