"""COLMAP's side of refinement before any geometry: the images COLMAP sees, the database, and
the point evidence in it, from one of two feature sources:

- ``sift``: SIFT features (OpenCV's, in COLMAP's form: :func:`colmap_sift`) inside the
  camera's valid mask; pairs of posed frames matched along their epipolar geometry
  (:mod:`omni_sfm.refine.guided`, :func:`match_guided`), the other pairs by pycolmap's
  sequential matching;
- ``klt``: corners tracked through the ordered frames (:mod:`omni_sfm.corners`), written as
  keypoints (no descriptors) and, for every pair of COLMAP's sequential matching, the corners
  on a common track as matches, written as the pair's inlier matches too (or verified by
  COLMAP: :func:`match_tracks`).

Images whose features the database already holds are not extracted again and matched pairs
are not matched again; a database holds the features of one source only
(:func:`feature_source`).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras.base import CameraModel, ColmapExport
from omni_sfm.corners import CornerTrackOptions, CornerTracks, track_corners
from omni_sfm.errors import OmniSfmError
from omni_sfm.frames import FrameStore
from omni_sfm.geometry import angle_between
from omni_sfm.poses import Trajectory
from omni_sfm.refine.guided import FrameKeypoints, GuidedMatchOptions, match_pair

FEATURE_SOURCES = ("klt", "sift")
"""Where refine's point evidence comes from (:class:`omni_sfm.refine.RefineOptions`)."""


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
        tracks: KLT only: the tracks found in this run (None: every image's keypoints were
            reused, nothing tracked), their frames indexing ``names`` as given.
    """

    camera_id: int
    extracted: tuple[str, ...]
    reused: tuple[str, ...]
    num_keypoints: int
    tracks: CornerTracks | None = None


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


def feature_source(db: Any) -> str | None:
    """Which source made the features an open database holds: ``sift`` (descriptors),
    ``klt`` (keypoints without any descriptors) or None (no keypoints)."""
    if db.num_descriptors() > 0:
        return "sift"
    return "klt" if db.num_keypoints() > 0 else None


def _check_source(db: Any, wanted: str, path: Path) -> None:
    """OmniSfmError when the database holds features of another source than ``wanted``: the
    two do not mix (KLT keypoints have no descriptors for SIFT matching, and SIFT keypoints are
    not on tracks)."""
    have = feature_source(db)
    if have is not None and have != wanted:
        what = "SIFT features" if have == "sift" else "KLT corners (keypoints, no descriptors)"
        raise OmniSfmError(
            f"{path}: the database holds {what}; refine --features {wanted} needs a database "
            f"without them (a new --database, or --features {have} with this one)")


SIFT_EXTRACTORS = ("opencv", "colmap")
"""Who computes SIFT features: OpenCV (refine's, :func:`colmap_sift`) or pycolmap's CPU SIFT
(COLMAP's own, for the ``colmap`` initializer that stands for COLMAP as its users run it)."""


def extract_features(database: Path, image_dir: Path, mask_path: Path, names: Sequence[str],
                     export: ColmapExport, *, max_features: int, num_threads: int,
                     extractor: str = "opencv") -> Features:
    """SIFT features of ``names`` (one shared camera with the exact model, inside the camera
    mask), skipping images whose keypoints and descriptors ``database`` already holds.

    ``extractor`` (:data:`SIFT_EXTRACTORS`): ``opencv`` runs OpenCV's SIFT, the same detector
    as COLMAP's (Lowe's, on an upsampled first octave; keypoints within 1e-4 px of COLMAP's
    on a rendered frame) in a third of pycolmap's CPU time, one image per thread, written in
    COLMAP's conventions (:func:`colmap_sift`); ``colmap`` runs pycolmap's extraction."""
    import pycolmap

    if extractor not in SIFT_EXTRACTORS:
        raise ValueError(f"extractor {extractor!r}: one of {SIFT_EXTRACTORS}")
    with pycolmap.Database.open(str(database)) as db:
        _check_source(db, "sift", database)
        cam_id = _shared_camera_id(db, names, export, database)
        known = {im.name: im.image_id for im in db.read_all_images()}
        done = {n for n in names if n in known and db.exists_keypoints(known[n])
                and db.exists_descriptors(known[n])}
    todo = [n for n in names if n not in done]
    if todo and extractor == "colmap":
        _colmap_extraction(database, image_dir, mask_path, todo, cam_id,
                           max_features=max_features, num_threads=num_threads)
    elif todo:
        new = [n for n in todo if n not in known]
        if new:
            reader = pycolmap.ImageReaderOptions()
            reader.existing_camera_id = cam_id
            pycolmap.import_images(str(database), str(image_dir), pycolmap.CameraMode.SINGLE,
                                   image_names=new, options=reader)
        _opencv_extraction(database, image_dir, mask_path, todo, max_features=max_features,
                           num_threads=num_threads)
    with pycolmap.Database.open(str(database)) as db:
        names_in_db = {im.name for im in db.read_all_images()}
        num_keypoints = int(db.num_keypoints())
    missing = [n for n in names if n not in names_in_db]
    if missing:
        raise OmniSfmError(f"{database}: COLMAP did not import {len(missing)} images "
                           f"(first: {missing[0]!r})")
    return Features(cam_id, tuple(todo), tuple(sorted(done)), num_keypoints)


def _colmap_extraction(database: Path, image_dir: Path, mask_path: Path, names: Sequence[str],
                       cam_id: int, *, max_features: int, num_threads: int) -> None:
    """pycolmap's CPU SIFT of ``names`` with the camera mask, into ``database``."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.existing_camera_id = cam_id
    reader.camera_mask_path = str(mask_path)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.use_gpu = False
    extraction.sift.max_num_features = max_features
    pycolmap.extract_features(str(database), str(image_dir), image_names=list(names),
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)


def _opencv_extraction(database: Path, image_dir: Path, mask_path: Path, names: Sequence[str],
                       *, max_features: int, num_threads: int) -> None:
    """:func:`colmap_sift` of the images ``names`` (imported in ``database`` already) inside
    the camera mask, written as their keypoints and descriptors (replacing any they had). The
    images are extracted on ``num_threads`` threads (all CPUs when not positive), each image
    on one (OpenCV's own threads held at one: the features do not depend on the thread
    count), a batch at a time so that memory does not grow with the video."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    import cv2
    import pycolmap

    mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        raise OmniSfmError(f"{mask_path}: OpenCV cannot read the camera mask")

    def one(name: str) -> tuple[np.ndarray, np.ndarray]:
        img = cv2.imread(str(image_dir / name), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise OmniSfmError(f"{image_dir / name}: OpenCV cannot read this image")
        if img.shape != mask.shape:
            raise OmniSfmError(f"{image_dir / name}: image is {img.shape[1]}x{img.shape[0]} "
                               f"px, the camera mask {mask.shape[1]}x{mask.shape[0]} px")
        return colmap_sift(img, mask, max_features)

    workers = max(1, num_threads if num_threads > 0 else (os.cpu_count() or 1))
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with pycolmap.Database.open(str(database)) as db, ThreadPoolExecutor(workers) as pool:
            ids = _image_ids(db, names)
            for s in range(0, len(names), 8 * workers):
                batch = list(zip(ids[s:s + 8 * workers],
                                 pool.map(one, names[s:s + 8 * workers]), strict=True))
                with pycolmap.DatabaseTransaction(db):
                    for image_id, (kp, desc) in batch:
                        _write_sift(db, image_id, kp, desc)
    finally:
        cv2.setNumThreads(before)


def _write_sift(db: Any, image_id: int, keypoints: np.ndarray, descriptors: np.ndarray) -> None:
    """An image's SIFT keypoints and descriptors written to an open database (replaced where
    it had them)."""
    import pycolmap

    data = pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, descriptors)
    if db.exists_keypoints(image_id):
        db.update_keypoints(image_id, keypoints)
    else:
        db.write_keypoints(image_id, keypoints)
    if db.exists_descriptors(image_id):
        db.update_descriptors(image_id, data)
    else:
        db.write_descriptors(image_id, data)



def colmap_sift(gray: np.ndarray, mask: np.ndarray | None, max_features: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints and descriptors of a grayscale image as COLMAP stores them: keypoints
    ``(x, y, a11, a12, a21, a22)`` (pixel centres at +0.5, the affine shape from the scale and
    orientation) and descriptors L1-root normalised, as unsigned bytes (``512 x``, rounded,
    capped at 255), at most ``max_features`` of the strongest, in a fixed order."""
    import cv2

    sift = cv2.SIFT.create(nfeatures=max_features, enable_precise_upscale=True)
    kps, desc = sift.detectAndCompute(gray, mask)
    if not kps:
        return np.zeros((0, 6), np.float32), np.zeros((0, 128), np.uint8)
    xy = np.array([k.pt for k in kps], float)
    scale = np.array([k.size for k in kps], float) / 2.0
    theta = np.deg2rad(np.array([k.angle for k in kps], float))  # COLMAP's orientation
    c, s = scale * np.cos(theta), scale * np.sin(theta)
    kp = np.column_stack([xy + 0.5, c, -s, s, c]).astype(np.float32)
    d = np.asarray(desc, float)
    d = np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12))
    d8 = np.minimum(np.round(512.0 * d), 255).astype(np.uint8)
    return kp, d8


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


@dataclass(frozen=True)
class GuidedMatches:
    """What guided matching did.

    Attributes:
        pairs: pairs of posed frames matched (pairs matched before are skipped).
        written: pairs with at least ``min_matches`` matches, written as verified; the others
            are left to COLMAP's matcher.
        matches: matches written.
    """

    pairs: int
    written: int
    matches: int


def _frame_keypoints(db: Any, image_id: int, camera: CameraModel,
                     export: ColmapExport) -> FrameKeypoints:
    """An image's keypoints as rays of ``camera`` with their pixel size, and descriptors."""
    kp = np.asarray(db.read_keypoints(image_id), float)[:, :2]
    desc = np.asarray(db.read_descriptors(image_id).data)
    uv = export.pixels_from_colmap(kp) if len(kp) else np.zeros((0, 2))
    rays = camera.rays_from_pixels(uv)
    pixel = np.maximum(angle_between(rays, camera.rays_from_pixels(uv + [1.0, 0.0])),
                       angle_between(rays, camera.rays_from_pixels(uv + [0.0, 1.0])))
    return FrameKeypoints.build(rays, pixel, desc)


def match_guided(database: Path, names: Sequence[str], trajectory: Trajectory,
                 trajectory_names: Sequence[str], camera: CameraModel, export: ColmapExport,
                 *, overlap: int, options: GuidedMatchOptions | None = None,
                 min_matches: int = 15, progress: bool = False) -> GuidedMatches:
    """SIFT matches of the pairs of COLMAP's sequential matching (``names`` in name order, as
    COLMAP orders them; :func:`sequential_pairs`) whose two frames ``trajectory`` poses (row k
    is ``trajectory_names[k]``), found along the pair's epipolar geometry
    (:func:`omni_sfm.refine.guided.match_pair`). A pair with at least ``min_matches`` matches
    is written with them as its matches and its verified (calibrated) two-view geometry, the
    relative pose the trajectory's; a pair with fewer is not written, so that COLMAP's own
    matcher (:func:`match_sequential`) tries it. Pairs the database has matched already are
    skipped. Frames are read as the pairs need them (at most ``2**(overlap-1)`` frames ahead
    held). One thread (numpy's BLAS may use more): two threads over the pairs were no faster
    on 2 CPUs (docs/colmap.md)."""
    import pycolmap
    from tqdm import tqdm

    order = sorted(names)
    row = {n: k for k, n in enumerate(trajectory_names)}
    colmap_from_cam = export.colmap_cam_from_cam

    def relative(pair: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Rotation b_from_a of the pair's cameras and b's centre in a's camera frame."""
        a, b = (row[order[k]] for k in pair)
        world_from_a, world_from_b = trajectory.rotations[a], trajectory.rotations[b]
        return (world_from_b.T @ world_from_a,
                world_from_a.T @ (trajectory.positions[b] - trajectory.positions[a]))

    with pycolmap.Database.open(str(database)) as db:
        ids = _image_ids(db, order)
        todo = [(i, j) for i, j in sequential_pairs(len(order), overlap)
                if order[i] in row and order[j] in row
                and not db.exists_matches(ids[i], ids[j])]
        held: dict[int, FrameKeypoints] = {}
        written = matches = 0
        with tqdm(total=len(todo), desc="refine: guided matching", unit="pair",
                  disable=None if progress else True, leave=False) as bar:
            step = 32
            for s in range(0, len(todo), step):
                batch = todo[s:s + step]
                for k in sorted({k for pair in batch for k in pair} - set(held)):
                    held[k] = _frame_keypoints(db, ids[k], camera, export)
                with pycolmap.DatabaseTransaction(db):
                    for i, j in batch:
                        b_from_a, baseline = relative((i, j))
                        m = match_pair(held[i], held[j], b_from_a, baseline, options)
                        if len(m) >= min_matches:
                            _write_guided(db, ids[i], ids[j], m.astype(np.uint32),
                                          colmap_from_cam @ b_from_a @ colmap_from_cam.T,
                                          -colmap_from_cam @ b_from_a @ baseline)
                            written += 1
                            matches += len(m)
                        bar.update()
                first = todo[s + step][0] if s + step < len(todo) else len(order)
                for k in [k for k in held if k < first]:
                    del held[k]
    return GuidedMatches(len(todo), written, matches)


def _write_guided(db: Any, id1: int, id2: int, matches: np.ndarray,
                  cam2_from_cam1_rotation: np.ndarray, cam2_from_cam1_translation: np.ndarray
                  ) -> None:
    """Matches of images ``id1``, ``id2`` written as their matches and inlier matches, with
    the calibrated relative pose (COLMAP's camera frames; translation made unit)."""
    import pycolmap

    t = np.asarray(cam2_from_cam1_translation, float)
    norm = float(np.linalg.norm(t))
    db.write_matches(id1, id2, matches)
    db.write_two_view_geometry(id1, id2, pycolmap.TwoViewGeometry(
        config=pycolmap.TwoViewGeometryConfiguration.CALIBRATED, inlier_matches=matches,
        cam2_from_cam1=pycolmap.Rigid3d(pycolmap.Rotation3d(cam2_from_cam1_rotation),
                                        t / norm if norm > 0 else t)))


def _image_ids(db: Any, names: Sequence[str]) -> list[int]:
    known = {im.name: int(im.image_id) for im in db.read_all_images()}
    return [known[n] for n in names]


def track_features(database: Path, image_dir: Path, mask_path: Path, names: Sequence[str],
                   export: ColmapExport, options: CornerTrackOptions) -> Features:
    """KLT corner tracks through ``names`` (in this order, a video's frames) of the images in
    ``image_dir`` (as COLMAP sees them) inside the camera mask, written to ``database`` as
    keypoints (COLMAP's pixels: +0.5 px) of images imported with one shared camera.

    When every image of ``names`` already has keypoints in the database, nothing is tracked
    (the matches written with them are reused). Otherwise all of ``names`` are tracked again
    (tracks run through the whole sequence): their old keypoints are replaced and the matches
    and two-view geometries of pairs that involve them deleted, since keypoint indices change.
    """
    import cv2
    import pycolmap

    with pycolmap.Database.open(str(database)) as db:
        _check_source(db, "klt", database)
        cam_id = _shared_camera_id(db, names, export, database)
        known = {im.name: im.image_id for im in db.read_all_images()}
        done = [n for n in names if n in known and db.exists_keypoints(known[n])]
        if len(done) == len(names):
            return Features(cam_id, (), tuple(sorted(done)), int(db.num_keypoints()))
    new = [n for n in names if n not in known]
    if new:
        reader = pycolmap.ImageReaderOptions()
        reader.existing_camera_id = cam_id
        reader.camera_mask_path = str(mask_path)
        pycolmap.import_images(str(database), str(image_dir), pycolmap.CameraMode.SINGLE,
                               image_names=list(new), options=reader)
    mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        raise OmniSfmError(f"{mask_path}: OpenCV cannot read the camera mask")

    def frames() -> Iterator[np.ndarray]:
        for n in names:
            img = cv2.imread(str(image_dir / n), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise OmniSfmError(f"{image_dir / n}: OpenCV cannot read this image")
            yield img

    tracks = track_corners(frames(), mask, options)
    with pycolmap.Database.open(str(database)) as db:
        missing = [n for n in names if n not in {im.name for im in db.read_all_images()}]
        if missing:
            raise OmniSfmError(f"{database}: COLMAP did not import {len(missing)} images "
                               f"(first: {missing[0]!r})")
        ids = _image_ids(db, names)
        stale = {i for i, n in zip(ids, names, strict=True) if n in set(done)}
        with pycolmap.DatabaseTransaction(db):
            _write_keypoints(db, ids, stale, tracks)
        num_keypoints = int(db.num_keypoints())
    return Features(cam_id, tuple(names), (), num_keypoints, tracks)


def _write_keypoints(db: Any, ids: list[int], stale: set[int], tracks: CornerTracks) -> None:
    """Frame ``k``'s corners as the keypoints of image ``ids[k]``; the keypoints of ``stale``
    images are replaced and every match or two-view geometry involving them deleted."""
    import pycolmap

    if stale:
        for table in (db.read_all_matches()[0], db.read_two_view_geometries()[0]):
            for pair_id in table:
                i1, i2 = pycolmap.pair_id_to_image_pair(pair_id)
                if i1 in stale or i2 in stale:
                    db.delete_matches(i1, i2)
                    db.delete_two_view_geometry(i1, i2)
    for k, image_id in enumerate(ids):
        _, uv = tracks.in_frame(k)
        kp = (uv + 0.5).astype(np.float32)  # COLMAP's pixel centres are at +0.5
        if image_id in stale:
            db.update_keypoints(image_id, kp)
        else:
            db.write_keypoints(image_id, kp)


def sequential_pairs(n: int, overlap: int) -> list[tuple[int, int]]:
    """The pairs COLMAP's sequential matching forms with its quadratic overlap (pycolmap
    4.2.1's ``SequentialPairGenerator``, tested), as indices into ``n`` frames in order: each
    frame with the frames ``2**k`` ahead, ``k < overlap`` (1, 2, 4, ..., so short and wide
    baselines)."""
    steps = [2**k for k in range(min(overlap, 62)) if 2**k < n]
    return [(i, i + d) for i in range(n) for d in steps if i + d < n]


def _write_track_matches(db: Any, ids: list[int], tracks: CornerTracks,
                         pairs: list[tuple[int, int]], verify: bool, min_matches: int) -> None:
    """For each pair ``(i, j)`` of frames not matched yet, the keypoints on a common track as
    the matches of images ``ids[i]``, ``ids[j]`` (and as their inlier matches unless
    ``verify``)."""
    import pycolmap

    per_frame = [tracks.in_frame(k)[0] for k in range(len(ids))]
    for i, j in pairs:
        if db.exists_matches(ids[i], ids[j]):
            continue
        _, a, b = np.intersect1d(per_frame[i], per_frame[j], assume_unique=True,
                                 return_indices=True)
        if len(a) < min_matches:
            continue
        m = np.stack([a, b], 1).astype(np.uint32)
        db.write_matches(ids[i], ids[j], m)
        if not verify:
            db.write_two_view_geometry(ids[i], ids[j], pycolmap.TwoViewGeometry(
                config=pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED, inlier_matches=m))


def match_tracks(database: Path, names: Sequence[str], tracks: CornerTracks | None,
                 work: Path, *, overlap: int, verify: bool = True, min_matches: int = 15,
                 verification: Any | None = None) -> Matches:
    """Matches from ``tracks`` (:func:`track_features`; frames index ``names``): for each pair
    of :func:`sequential_pairs`, the keypoints on a common track (pairs with fewer than
    ``min_matches`` are not written). Then, with ``verify``, COLMAP's geometric verification
    (``pycolmap.verify_matches``, ``verification`` options or COLMAP's defaults) of every such
    pair that has matches but no two-view geometry yet (``work``: a folder for its pairs file);
    without, the matches are written as the pair's inlier matches directly. With ``tracks``
    None (keypoints reused) only the verification of pairs left unverified runs."""
    import pycolmap

    with pycolmap.Database.open(str(database)) as db:
        ids = _image_ids(db, names)
        todo = sequential_pairs(len(names), overlap)
        if tracks is not None:
            with pycolmap.DatabaseTransaction(db):
                _write_track_matches(db, ids, tracks, todo, verify, min_matches)
        pairs = [(names[i], names[j]) for i, j in todo if db.exists_matches(ids[i], ids[j])
                 and not db.exists_two_view_geometry(ids[i], ids[j])]
    if pairs:
        work.mkdir(parents=True, exist_ok=True)
        pairs_file = work / "pairs.txt"
        pairs_file.write_text("".join(f"{a} {b}\n" for a, b in pairs), encoding="utf-8")
        if verification is None:
            pycolmap.verify_matches(str(database), str(pairs_file))
        else:
            pycolmap.verify_matches(str(database), str(pairs_file), verification)
    with pycolmap.Database.open(str(database)) as db:
        return Matches(int(db.num_verified_image_pairs()), int(db.num_inlier_matches()))
