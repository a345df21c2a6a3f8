"""COLMAP models seeded by omni-sfm poses, exact for every camera with a COLMAP model.

The camera goes in through :meth:`CameraModel.colmap_export` (docs/cameras.md): COLMAP's
camera frame is ``colmap_cam_from_cam`` times ours (a proper rotation) and, for catadioptric
cameras, COLMAP sees the image mirrored left-right. A pose ``world_from_cam`` of ours becomes
``cam_from_world = colmap_cam_from_cam @ cam_from_world`` for COLMAP, so the projection
centres are unchanged.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from omni_sfm.cameras.base import CameraModel, ColmapExport
from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import BackgroundWrites
from omni_sfm.folders import InitArtifacts, InitFolder, read_manifest_names
from omni_sfm.geometry import FloatArray
from omni_sfm.poses import Trajectory

if TYPE_CHECKING:
    from omni_sfm.export.colmap_lenses import LensRigSeed


@dataclass(frozen=True)
class ColmapSeed:
    """A pycolmap model built from omni-sfm poses.

    Attributes:
        reconstruction: ``pycolmap.Reconstruction`` with one camera (id 1), one image per
            estimated frame (ids 1..N in trajectory order) registered with its pose, no points.
        export: how the camera and images map to COLMAP's (flip, frame rotation).
        image_names: ``(N,)`` the image names, as COLMAP finds them under its image folder.
    """

    reconstruction: Any
    export: ColmapExport
    image_names: tuple[str, ...]


def sensor_from_world(sensor_from_body: FloatArray, traj: Trajectory
                      ) -> tuple[FloatArray, FloatArray]:
    """``sensor_from_world`` rotation ``(N,3,3)`` and translation ``(N,3)`` of a sensor fixed to
    the body whose poses are ``traj`` (world_from_body): ``sensor_from_body`` is a ``(3, 3)``
    rotation (the sensor at the body's centre) or a ``(4, 4)`` rigid transform whose
    translation is in the trajectory's units."""
    T = np.asarray(sensor_from_body, dtype=np.float64)
    A, a = (T, np.zeros(3)) if T.shape == (3, 3) else (T[:3, :3], T[:3, 3])
    R_sw = A[None] @ traj.cam_from_world_rotations
    t_sw = a[None] - np.einsum("nij,nj->ni", R_sw, traj.positions)
    return R_sw, t_sw


def rigid3d(R: FloatArray, t: FloatArray) -> Any:
    """The ``pycolmap.Rigid3d`` of rotation ``R (3, 3)`` and translation ``t (3,)``."""
    import pycolmap

    return pycolmap.Rigid3d(np.hstack([np.asarray(R, np.float64),
                                       np.asarray(t, np.float64).reshape(3, 1)]))


def colmap_cam_from_world(export: ColmapExport, traj: Trajectory) -> tuple[FloatArray, FloatArray]:
    """COLMAP's ``cam_from_world`` rotation ``(N,3,3)`` and translation ``(N,3)`` of ``traj``."""
    return sensor_from_world(export.colmap_cam_from_cam, traj)


def set_colmap_poses(rec: Any, export: ColmapExport, image_ids: Sequence[int],
                     traj: Trajectory) -> None:
    """Set the COLMAP poses of the images ``image_ids`` of ``rec`` (their frames, trivial
    rigs) to ``traj`` (ours, world_from_cam), the ``k``-th image to the ``k``-th pose."""
    R_cw, t_cw = colmap_cam_from_world(export, traj)
    for k, image_id in enumerate(image_ids):
        frame = rec.frame(rec.images[image_id].frame_id)
        frame.rig_from_world = rigid3d(R_cw[k], t_cw[k])


def build_reconstruction(camera: CameraModel, traj: Trajectory,
                         image_names: Sequence[str]) -> ColmapSeed:
    """A pycolmap Reconstruction holding ``camera`` and one posed image per trajectory frame."""
    import pycolmap

    if len(image_names) != len(traj):
        raise ValueError(f"{len(image_names)=} differs from the {len(traj)} poses")
    if len(set(image_names)) != len(image_names):
        raise OmniSfmError("image names must be unique for a COLMAP model")
    export = camera.colmap_export()
    rec = pycolmap.Reconstruction()
    cam = export.camera
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    R_cw, t_cw = colmap_cam_from_world(export, traj)
    for k, name in enumerate(image_names):
        image = pycolmap.Image(name=str(name), camera_id=1, image_id=k + 1)
        rec.add_image_with_trivial_frame(image, rigid3d(R_cw[k], t_cw[k]))
    return ColmapSeed(rec, export, tuple(str(n) for n in image_names))


def write_reconstruction(seed: ColmapSeed | LensRigSeed, sparse_dir: Path, *,
                         text: bool = False) -> None:
    """Write the model to ``sparse_dir`` in COLMAP's binary format (and text with ``text``)."""
    sparse_dir = Path(sparse_dir)
    sparse_dir.mkdir(parents=True, exist_ok=True)
    seed.reconstruction.write_binary(str(sparse_dir))
    if text:
        seed.reconstruction.write_text(str(sparse_dir))


def projection_centres(reconstruction: Any) -> dict[str, FloatArray]:
    """Camera centre of every registered image, by image name (world frame)."""
    return {img.name: np.asarray(img.projection_center())
            for img in reconstruction.images.values() if img.has_pose}


# --- the init model layout (written by ``omni-sfm init``, read by ``omni-sfm refine``) ---------

MASK_EROSION_PX = 3


def write_colmap_mask(path: Path, camera: CameraModel, erode_px: int = MASK_EROSION_PX,
                      user_mask: np.ndarray | None = None) -> None:
    """COLMAP's camera mask (``ImageReaderOptions.camera_mask_path``; 0 = ignore) of the valid
    pixels (and of ``user_mask``, ``(H, W)`` bool, where given), shrunk by ``erode_px`` so that
    the strong edges at a mirror's rim or a mask's border give no features, and mirrored like
    the images COLMAP sees."""
    import cv2

    export = camera.colmap_export()
    valid = camera.valid_mask() if user_mask is None else camera.valid_mask() & user_mask
    mask: np.ndarray = np.where(valid, 255, 0).astype(np.uint8)
    if erode_px > 0:
        k = 2 * erode_px + 1
        mask = cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)),
                         borderType=cv2.BORDER_CONSTANT, borderValue=0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), export.image_to_colmap(mask)):
        raise OmniSfmError(f"{path}: OpenCV cannot write the mask image")


@dataclass(frozen=True)
class InitModel:
    """An init directory read back (see :func:`write_init_model`).

    Attributes:
        artifacts: the folder's artifacts (:meth:`omni_sfm.folders.InitFolder.load`): the
            camera, the poses, the 3D lines, the recorded frames and mask.
        image_names: ``(N,)`` image name of each pose, in trajectory order.
        reconstruction: the ``pycolmap.Reconstruction`` of ``sparse/``.
    """

    artifacts: InitArtifacts
    image_names: tuple[str, ...]
    reconstruction: Any

    @property
    def camera(self) -> CameraModel:
        """The omni-sfm camera the poses refer to (``camera.yaml``)."""
        return self.artifacts.camera

    @property
    def trajectory(self) -> Trajectory:
        """``(N,)`` poses world_from_cam of our ray frame (``trajectory.tum``)."""
        return self.artifacts.trajectory

    @property
    def directory(self) -> Path:
        """The init directory."""
        return Path(self.artifacts.folder.path)


class ColmapImages:
    """Writes ``DIR/images_colmap/<name>``: each frame as COLMAP must see it (mirrored where the
    camera's export says so; a rig camera's: each lens's part, ``lens{k}/<name>``,
    :mod:`omni_sfm.export.colmap_lenses`), as the front end reads it (a
    :data:`~omni_sfm.lines.frontend.FrameTap` through :meth:`tap`); :meth:`keep` then deletes
    the frames that got no pose, so that the folder holds the model's images.

    With ``background`` the PNGs are encoded and written in a thread beside the caller (at most
    8 waiting): the front end's process decodes and tracks the next frames meanwhile. Then
    :meth:`wait` for them (it raises a write's error) or :meth:`close` (on an error: the
    writes not started are dropped)."""

    def __init__(self, directory: Path, camera: CameraModel,
                 name_of: Callable[[int], str], *, background: bool = False) -> None:
        from omni_sfm.cameras.rig import RigCamera
        from omni_sfm.export.colmap_lenses import LensExports

        self.directory = Path(directory) / InitFolder.COLMAP_IMAGES
        # a rig camera: each lens's part of the frame, images_colmap/lens{k}/<name>
        self.lenses = LensExports.of(camera) if isinstance(camera, RigCamera) else None
        self.export = None if self.lenses is not None else camera.colmap_export()
        self.name_of = name_of
        self.written: list[str] = []
        self._writes = BackgroundWrites(1, pending=8) if background else None

    def _parts(self, name: str, image: np.ndarray | None) -> list[tuple[str, np.ndarray | None]]:
        """The files of frame ``name`` and, given the frame, their images as COLMAP sees them."""
        if self.lenses is None:
            assert self.export is not None
            return [(name, None if image is None else self.export.image_to_colmap(image))]
        names = self.lenses.image_names(name)
        if image is None:
            return [(n, None) for n in names]
        return list(zip(names, self.lenses.images(image), strict=True))

    def write(self, name: str, image: np.ndarray) -> None:
        """One frame ``(H, W[, 3])`` (RGB if 3 channels) under ``name`` (a rig's: each lens's
        part under ``lens{k}/name``)."""

        for rel, out in self._parts(name, image):
            assert out is not None
            if out.ndim == 3 and out.shape[2] == 3:
                out = np.ascontiguousarray(out[:, :, ::-1])
            path = self.directory / rel
            if self._writes is not None:
                self._writes.submit(_write_png, path, out)
            else:
                _write_png(path, out)
        self.written.append(name)

    def tap(self, number: int, _stamp: float, gray: np.ndarray) -> None:
        self.write(self.name_of(number), gray)

    def wait(self) -> None:
        """Wait for the images being written in the background (raises a write's error)."""
        if self._writes is not None:
            self._writes.wait()

    def close(self) -> None:
        """Stop the background writes (those not started are dropped)."""
        if self._writes is not None:
            self._writes.close()

    def keep(self, names: Sequence[str]) -> None:
        """Delete every written image not in ``names``; each of ``names`` must be written."""
        self.wait()
        wanted = set(names)
        missing = wanted - set(self.written)
        if missing:
            raise ValueError(f"{len(missing)} images were never written, e.g. "
                             f"{sorted(missing)[0]}")
        for name in self.written:
            if name not in wanted:
                for rel, _ in self._parts(name, None):
                    (self.directory / rel).unlink(missing_ok=True)
        self.written = [n for n in self.written if n in wanted]


def _write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    # PNG: fast compression (a tenth larger, a third faster than OpenCV's default)
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise OmniSfmError(f"{path}: OpenCV cannot write this image")


def write_init_model(directory: Path, camera: CameraModel, traj: Trajectory,
                     image_names: Sequence[str], images: Iterable[np.ndarray] | None = None,
                     *, text: bool = False, metres_per_unit: float | None = None
                     ) -> ColmapSeed | LensRigSeed:
    """Write the COLMAP side of an init directory (docs/colmap.md, "Init directory").

    Writes ``DIR/sparse/`` (COLMAP binary model; also text with ``text``): the camera in its exact
    COLMAP model, one posed image per trajectory frame (image ids 1..N in trajectory order, named
    ``image_names``); ``DIR/camera.yaml`` (the omni-sfm camera the poses refer to);
    ``DIR/trajectory.tum`` (the poses, world_from_cam of our ray frame) unless the caller has
    written it already; ``DIR/camera_mask.png`` (COLMAP's camera mask of the valid pixels,
    :func:`write_colmap_mask`); ``DIR/colmap.json`` (image name and timestamp of every pose, the
    frame map and the image flip); and, when ``images`` is given,
    ``DIR/images_colmap/<name>``: each image ``(H, W[, 3])`` (RGB if 3 channels) as COLMAP must
    see it, mirrored where the camera export says so. ``images`` yields one array per name, in
    order.

    A rig camera (:class:`~omni_sfm.cameras.rig.RigCamera`) is written as a COLMAP rig
    (:mod:`omni_sfm.export.colmap_lenses`): camera ``k + 1`` per lens, frame ``k + 1`` per pose,
    images ``lens{k}/<name>``, a camera mask per lens (``camera_mask_lens{k}.png``), COLMAP's
    rig configuration (``rig_config.json``) and the lenses in ``colmap.json``. Its lens offsets
    go in the poses' units: ``metres_per_unit``, else the scale the folder's ``report.json``
    records (:func:`~omni_sfm.export.colmap_lenses.rig_metres_per_unit`; written before this).

    Use inside :func:`omni_sfm.fileio.atomic_output_dir` so the directory appears complete or not
    at all. Returns the seeded model.
    """

    from omni_sfm.cameras import write_camera_yaml
    from omni_sfm.cameras.rig import RigCamera
    from omni_sfm.export.colmap_lenses import (
        build_lens_rig,
        rig_manifest,
        rig_metres_per_unit,
        write_lens_masks,
        write_rig_config,
    )
    from omni_sfm.fileio import atomic_write_text, dumps_json
    from omni_sfm.poses import write_tum

    directory = Path(directory)
    names = [str(n) for n in image_names]
    for n in names:
        if not n or Path(n).is_absolute() or ".." in Path(n).parts:
            raise OmniSfmError(f"image name {n!r} must be a relative path inside the folder")
    seed: ColmapSeed | LensRigSeed
    if isinstance(camera, RigCamera):
        scale = rig_metres_per_unit(directory) if metres_per_unit is None else metres_per_unit
        seed = build_lens_rig(camera, traj, names, scale)
        write_lens_masks(directory, seed.lenses)
        write_rig_config(directory, seed.reconstruction)
        manifest: dict[str, Any] = rig_manifest(seed, traj)
    else:
        seed = build_reconstruction(camera, traj, names)
        write_colmap_mask(directory / InitFolder.COLMAP_MASK, camera)
        manifest = {
            "image_names": names,
            "timestamps": traj.timestamps,
            "camera_model": seed.export.camera.model_name,
            "colmap_cam_from_cam": seed.export.colmap_cam_from_cam,
            "flip_u": seed.export.flip_u,
            "note": "image id k+1 in sparse/ is row k of trajectory.tum; COLMAP sees "
                    "images_colmap/",
        }
    write_reconstruction(seed, directory / InitFolder.SPARSE, text=text)
    write_camera_yaml(directory / InitFolder.CAMERA, camera)
    if not (directory / InitFolder.TRAJECTORY).exists():
        write_tum(directory / InitFolder.TRAJECTORY, traj)
    atomic_write_text(directory / InitFolder.MANIFEST, dumps_json(manifest))
    if images is not None:
        writer = ColmapImages(directory, camera, str)
        count = 0
        for name, img in zip(names, images, strict=False):
            writer.write(name, img)
            count += 1
        if count != len(names):
            raise ValueError(f"got {count} images for {len(names)} image names")
    return seed


def read_init_model(directory: Path) -> InitModel:
    """Read and check an init directory written by :func:`write_init_model`.

    OmniSfmError (one line) when the model, camera or trajectory is missing or inconsistent, or
    the camera has no exact COLMAP model."""
    import pycolmap

    directory = Path(directory)
    if not directory.is_dir():
        raise OmniSfmError(f"{directory}: init directory not found")
    sparse = directory / InitFolder.SPARSE
    if not (sparse / "cameras.bin").is_file() and not (sparse / "cameras.txt").is_file():
        raise OmniSfmError(f"{sparse}: no COLMAP model (cameras.bin / cameras.txt) in the init "
                           "directory")
    art = InitFolder(directory).load()
    camera, traj = art.camera, art.trajectory
    try:
        export = camera.colmap_export()
    except OmniSfmError as exc:
        raise OmniSfmError(f"{directory / InitFolder.CAMERA}: {exc}") from None
    try:
        rec = pycolmap.Reconstruction(str(sparse))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on bad files
        raise OmniSfmError(f"{sparse}: cannot read the COLMAP model: {exc}") from None
    if rec.num_cameras() != 1:
        raise OmniSfmError(f"{sparse}: expected one camera, found {rec.num_cameras()}")
    cam = next(iter(rec.cameras.values()))
    if cam.model_name != export.camera.model_name or (cam.width, cam.height) != (
            export.width, export.height):
        raise OmniSfmError(
            f"{sparse}: camera {cam.model_name} {cam.width}x{cam.height} differs from "
            f"{directory / InitFolder.CAMERA} ({export.camera.model_name} "
            f"{export.width}x{export.height})")
    ids = sorted(rec.images)
    if ids != list(range(1, len(traj) + 1)):
        raise OmniSfmError(f"{sparse}: image ids must be 1..{len(traj)} (one per pose of "
                           f"{directory / InitFolder.TRAJECTORY}), got {len(ids)} images")
    names = tuple(rec.images[i].name for i in ids)
    listed = read_manifest_names(directory)
    if listed is not None and listed != list(names):
        raise OmniSfmError(f"{directory / InitFolder.MANIFEST}: image_names differ from the "
                           "model's images")
    centres = np.asarray([rec.images[i].projection_center() for i in ids])
    if not np.allclose(centres, traj.positions, atol=1e-6 * max(1.0, traj.path_length())):
        raise OmniSfmError(f"{sparse}: projection centres differ from the camera centres in "
                           f"{directory / InitFolder.TRAJECTORY}")
    return InitModel(art, names, rec)


def seed_for_database(camera: CameraModel, traj: Trajectory, image_names: Sequence[str],
                      database_path: Path) -> ColmapSeed:
    """The seeded model with the camera, rig, frame and image ids of an existing database.

    Every name must be an image of the database, all of one camera whose model and size equal
    ``camera``'s exact COLMAP model (its parameters are set to the exact ones). The images are
    posed from ``traj`` (row k is ``image_names[k]``); rigs and frames are the database's, so
    ``pycolmap.triangulate_points`` and the mapper accept the model. OmniSfmError otherwise."""
    import pycolmap

    database_path = Path(database_path)
    if not database_path.is_file():
        raise OmniSfmError(f"{database_path}: COLMAP database not found")
    names = [str(n) for n in image_names]
    if len(names) != len(traj):
        raise ValueError(f"{len(names)=} differs from the {len(traj)} poses")
    export = camera.colmap_export()
    with pycolmap.Database.open(str(database_path)) as db:
        db_images = {im.name: im for im in db.read_all_images()}
        cams = {c.camera_id: c for c in db.read_all_cameras()}
        rigs = {r.rig_id: r for r in db.read_all_rigs()}
        frames = {f.frame_id: f for f in db.read_all_frames()}
    missing = [n for n in names if n not in db_images]
    if missing:
        raise OmniSfmError(f"{database_path}: {len(missing)} posed images are not in the "
                           f"database (first: {missing[0]!r})")
    cam_ids = {db_images[n].camera_id for n in names}
    if len(cam_ids) != 1:
        raise OmniSfmError(f"{database_path}: the posed images use {len(cam_ids)} cameras; "
                           "omni-sfm seeds one shared camera")
    cam_id = cam_ids.pop()
    db_cam = cams[cam_id]
    if db_cam.model_name != export.camera.model_name or (db_cam.width, db_cam.height) != (
            export.width, export.height):
        raise OmniSfmError(
            f"{database_path}: camera {cam_id} is {db_cam.model_name} {db_cam.width}x"
            f"{db_cam.height}, the seed needs {export.camera.model_name} "
            f"{export.width}x{export.height}")
    rec = pycolmap.Reconstruction()
    cam = export.camera
    cam.camera_id = cam_id
    rec.add_camera(cam)
    R_cw, t_cw = colmap_cam_from_world(export, traj)
    used_rigs: set[int] = set()
    for k, name in enumerate(names):
        db_im = db_images[name]
        frame = frames.get(db_im.frame_id)
        if frame is None or len(frame.data_ids) != 1:
            raise OmniSfmError(f"{database_path}: image {name!r} is not alone in a frame of its "
                               "own (multi-camera rigs are not seeded)")
        if frame.rig_id not in used_rigs:
            rec.add_rig(rigs[frame.rig_id])
            used_rigs.add(frame.rig_id)
        frame.rig_from_world = rigid3d(R_cw[k], t_cw[k])
        rec.add_frame(frame)
        image = pycolmap.Image(name=name, camera_id=cam_id, image_id=db_im.image_id)
        image.frame_id = db_im.frame_id
        rec.add_image(image)
    return ColmapSeed(rec, export, tuple(names))


def trajectory_from_reconstruction(reconstruction: Any, export: ColmapExport,
                                   image_names: Sequence[str],
                                   timestamps: FloatArray) -> tuple[Trajectory, np.ndarray]:
    """Our poses (world_from_cam of our ray frame) of the named images of a COLMAP model.

    Returns the trajectory of the registered images among ``image_names`` (with their
    ``timestamps``) and the ``(len(image_names),)`` bool mask of which were registered."""
    by_name = {im.name: im for im in reconstruction.images.values()}
    ok = np.zeros(len(image_names), dtype=bool)
    R_wc, c_w = [], []
    for k, name in enumerate(image_names):
        im = by_name.get(name)
        if im is None or not im.has_pose:
            continue
        ok[k] = True
        R_colmap_cw = np.asarray(im.cam_from_world().rotation.matrix())
        # ours: cam_from_world = colmap_cam_from_cam^T @ colmap's cam_from_world
        R_wc.append((export.colmap_cam_from_cam.T @ R_colmap_cw).T)
        c_w.append(np.asarray(im.projection_center()))
    ts = np.asarray(timestamps, dtype=np.float64)[ok]
    if not ok.any():
        return Trajectory(ts, np.zeros((0, 3, 3)), np.zeros((0, 3))), ok
    return Trajectory(ts, np.asarray(R_wc), np.asarray(c_w)), ok
