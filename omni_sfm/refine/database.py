"""COLMAP's side of refinement before any geometry: the images COLMAP sees, the database, SIFT
features with the camera's valid mask, and sequential matching with geometric verification.

All work is done by pycolmap (its own threads); this module only prepares the inputs and never
re-extracts features or re-matches pairs that the database already holds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omni_sfm.cameras.base import ColmapExport
from omni_sfm.errors import OmniSfmError
from omni_sfm.lines.video import FrameStore


def check_image_names(folder: Path, available: Sequence[str], model_names: Sequence[str],
                      model: Path) -> None:
    """OmniSfmError unless every image of the model is in the folder."""
    have = set(available)
    missing = [n for n in model_names if n not in have]
    if missing:
        raise OmniSfmError(
            f"{folder}: {len(missing)} of the {len(model_names)} images of {model} are missing "
            f"(first: {missing[0]!r}); give the frames the init directory was made from")


def write_colmap_images(frames: FrameStore, dst: Path, names: Sequence[str],
                        export: ColmapExport, *, progress: bool = False) -> None:
    """Write frame ``<name>`` of ``frames`` (an image folder or a video) as COLMAP must see it
    to ``dst/<name>`` (mirrored where the camera export says so), checking every image's size
    against the camera. Images that exist already are rewritten (cheap next to SIFT)."""
    import cv2
    from tqdm import tqdm

    dst.mkdir(parents=True, exist_ok=True)
    for name in tqdm(names, desc="refine: images for COLMAP", unit="img",
                     disable=None if progress else True, leave=False):
        img = frames.read(name)
        if img.shape[:2] != (export.height, export.width):
            raise OmniSfmError(
                f"{frames.where(name)}: image is {img.shape[1]}x{img.shape[0]} px, the camera "
                f"is {export.width}x{export.height} px")
        if not cv2.imwrite(str(dst / name), export.image_to_colmap(img)):
            raise OmniSfmError(f"{dst / name}: OpenCV cannot write this image")


@dataclass(frozen=True)
class Features:
    """What feature extraction did.

    Attributes:
        camera_id: the shared camera of the images.
        extracted: names whose features were extracted in this run.
        reused: names whose features the database held already.
        num_keypoints: keypoints of all images in the database.
    """

    camera_id: int
    extracted: tuple[str, ...]
    reused: tuple[str, ...]
    num_keypoints: int


@dataclass(frozen=True)
class Matches:
    """What the database holds after matching.

    Attributes:
        verified_pairs: image pairs with a verified two-view geometry.
        inlier_matches: matches that passed geometric verification.
    """

    verified_pairs: int
    inlier_matches: int


def _shared_camera_id(db: Any, names: Sequence[str], export: ColmapExport,
                      path: Path) -> int:
    """The camera of the images already in the database, or a new one with the exact model."""
    known = {im.name: im for im in db.read_all_images()}
    ids = {known[n].camera_id for n in names if n in known}
    if len(ids) > 1:
        raise OmniSfmError(f"{path}: the images use {len(ids)} cameras; refine needs one")
    if ids:
        cam_id = ids.pop()
        cam = db.read_camera(cam_id)
        if cam.model_name != export.camera.model_name or (cam.width, cam.height) != (
                export.width, export.height):
            raise OmniSfmError(
                f"{path}: camera {cam_id} is {cam.model_name} {cam.width}x{cam.height}, the init "
                f"model needs {export.camera.model_name} {export.width}x{export.height}")
        # the exact parameters, whatever the database held (features do not depend on them)
        exact = export.camera
        exact.camera_id = cam_id
        db.update_camera(exact)
        return int(cam_id)
    return int(db.write_camera(export.camera))


def extract_features(database: Path, image_dir: Path, mask_path: Path, names: Sequence[str],
                     export: ColmapExport, *, max_features: int, num_threads: int) -> Features:
    """SIFT features of ``names`` (one shared camera with the exact model, the camera mask),
    skipping images whose keypoints and descriptors ``database`` already holds."""
    import pycolmap

    with pycolmap.Database.open(str(database)) as db:
        cam_id = _shared_camera_id(db, names, export, database)
        known = {im.name: im.image_id for im in db.read_all_images()}
        done = {n for n in names if n in known and db.exists_keypoints(known[n])
                and db.exists_descriptors(known[n])}
    todo = [n for n in names if n not in done]
    if todo:
        reader = pycolmap.ImageReaderOptions()
        reader.existing_camera_id = cam_id
        reader.camera_mask_path = str(mask_path)
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = num_threads
        extraction.use_gpu = False
        extraction.sift.max_num_features = max_features
        pycolmap.extract_features(str(database), str(image_dir), image_names=list(todo),
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
    with pycolmap.Database.open(str(database)) as db:
        names_in_db = {im.name for im in db.read_all_images()}
        num_keypoints = int(db.num_keypoints())
    missing = [n for n in names if n not in names_in_db]
    if missing:
        raise OmniSfmError(f"{database}: COLMAP did not import {len(missing)} images "
                           f"(first: {missing[0]!r})")
    return Features(cam_id, tuple(todo), tuple(sorted(done)), num_keypoints)


def match_sequential(database: Path, *, overlap: int, num_threads: int,
                     verification: Any | None = None) -> Matches:
    """Sequential matching (``overlap`` following frames, by name order) with COLMAP's geometric
    verification (``pycolmap.TwoViewGeometryOptions``, COLMAP's defaults when None); pairs
    matched before are skipped by COLMAP's matcher."""
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    matching.use_gpu = False
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = overlap
    pairing.num_threads = num_threads
    extra = {} if verification is None else {"verification_options": verification}
    pycolmap.match_sequential(str(database), matching_options=matching, pairing_options=pairing,
                              device=pycolmap.Device.cpu, **extra)
    with pycolmap.Database.open(str(database)) as db:
        return Matches(int(db.num_verified_image_pairs()), int(db.num_inlier_matches()))
