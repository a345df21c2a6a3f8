"""``omni-sfm refine``: COLMAP refinement seeded by the line-based poses, never worse than them.

Stages (pycolmap's features, matching, mapper and bundle adjustment; the triangulation and the
joint adjustment are omni-sfm's own; docs/colmap.md) for one camera; a rig camera's folder is
refined as a COLMAP rig (:mod:`omni_sfm.refine.rig_pipeline`):

1. images: the frames as COLMAP must see them (``images_colmap/``, mirrored where the camera
   export says so) and the camera's valid mask as COLMAP's camera mask;
2. features: one shared camera with the exact COLMAP model, and either KLT corner tracks through
   the ordered frames (``features="klt"``) or SIFT (``"sift"``); images that already have
   features in the database are not extracted again;
3. matching: the pairs of COLMAP's sequential matching, pairs matched before skipped. SIFT:
   pairs of two posed frames matched along the epipolar geometry of their input poses
   (:mod:`omni_sfm.refine.guided`; ``guided_matching``), the other pairs (and posed pairs
   with too few such matches) by COLMAP's matcher and geometric verification; KLT: the
   corners on a common track, written as the pairs' inlier matches (COLMAP's verification
   with ``klt_verify``);
4. triangulation: the verified matches' tracks (connected components) triangulated on the
   line-based poses (held fixed) by least squares over their rays, observations that miss
   dropped, then COLMAP's filter (:mod:`omni_sfm.refine.triangulation`; one pass over the
   observations, where COLMAP's incremental triangulator took 255 ms a frame and grew with
   the sequence);
5. mapper (only when the folder holds frames the line stage did not pose): COLMAP's
   registration of the next image, with triangulation and local adjustment around it, from
   the triangulated model, the seeded frames held fixed (no global refinement: the
   adjustment that follows is global); or, with ``mapper="global"``, COLMAP's rotation
   averaging and global positioning seeded by the line-based poses
   (:mod:`omni_sfm.refine.global_register`);
6. adjustment: by default the joint adjustment of cameras, the init's 3D lines and the points
   (:mod:`omni_sfm.refine.joint`; the cameras' system by conjugate gradients on long
   sequences); with
   ``adjustment="colmap"`` COLMAP's: poses and points free, intrinsics fixed, the gauge fixed
   by weak position priors at the input's camera centres (COLMAP's pose-prior adjuster),
   robust loss, in rounds with outlier filtering; frames with too few observations stay
   fixed;
7. acceptance: the adjusted model is mapped back onto the input's frame and scale (a similarity
   fitted to the trusted frames), and each frame keeps its line-based pose unless it has enough
   observations and a plausible change; if the whole model is too weak, every input pose is
   kept. The output model is made consistent with ``trajectory.tum``.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras import write_camera_yaml
from omni_sfm.corners import CornerTrackOptions
from omni_sfm.errors import OmniSfmError
from omni_sfm.export.colmap import (
    InitModel,
    read_init_model,
    seed_for_database,
    set_colmap_poses,
    trajectory_from_reconstruction,
    write_colmap_mask,
)
from omni_sfm.fileio import (
    atomic_output_dir,
    check_output_dir,
    stored_path,
)
from omni_sfm.folders import (
    InitArtifacts,
    InitFolder,
    RefineFolder,
    carry_forward,
    images_for,
)
from omni_sfm.frames import FrameStore, read_mask
from omni_sfm.geometry import FloatArray, rotation_angle
from omni_sfm.libs import library_logging
from omni_sfm.lines3d import write_lines3d
from omni_sfm.poses import Trajectory, write_tum
from omni_sfm.refine.database import (
    FEATURE_SOURCES,
    check_image_names,
    extract_features,
    match_guided,
    match_sequential,
    match_tracks,
    track_features,
    write_colmap_images,
)
from omni_sfm.refine.global_register import register_global
from omni_sfm.refine.joint import JointResult
from omni_sfm.refine.joint_model import (
    LineEvidence,
    adjust_model,
    adjusted_segments,
    read_line_evidence,
)
from omni_sfm.refine.synthetic import write_init_without
from omni_sfm.refine.triangulation import triangulate_seeded
from omni_sfm.reports import (
    AdjustmentRound,
    AlignmentReport,
    BundleAdjustmentReport,
    FeaturesReport,
    FrameChange,
    GuidedMatchingReport,
    JointAdjustmentNote,
    JointReport,
    MapperReport,
    ModelStatistics,
    PoseChanges,
    RefineCamera,
    RefineInput,
    RefineReport,
    RefineSettings,
    TriangulationReport,
)
from omni_sfm.transforms import Similarity, similarity_from_poses

MAPPERS = ("incremental", "global")
"""How refine registers the frames the init did not pose (``RefineOptions.mapper``)."""


def klt_tracking(max_corners: int) -> CornerTrackOptions:
    """How refine tracks corners (``features="klt"``). Against the rendered room's ground truth
    (docs/colmap.md) the drift of frame-to-frame KLT dominated: a small window (7 px; the
    hyperboloid bends larger patches), each step re-tracked from the corner's first frame
    (``anchor_max_px``), and new corners in every frame wherever there is room."""
    return CornerTrackOptions(max_corners=max_corners, min_distance_px=5.0, window_px=7,
                              anchor_max_px=0.5, redetect_fraction=1.0)


@dataclass(frozen=True, kw_only=True)
class RefineOptions:
    features: str = "sift"
    """Point evidence: ``sift`` (SIFT features matched on the pairs of COLMAP's sequential
    matching, also for images that are not in order; see ``guided_matching``) or ``klt``
    (corners tracked through the frames in name order: a video or an ordered image folder;
    3-4x faster than SIFT but less accurate along a walk:
    on the 1,000-frame office walk of docs/colmap.md 0.088 deg mean rotation error against
    SIFT's 0.008, hence not the default)."""
    max_features: int = 8192
    """SIFT features per image at most."""
    guided_matching: bool = True
    """SIFT: match each pair of frames the input poses along its epipolar geometry (omni-sfm's
    guided matcher, no RANSAC; 2.5-3x faster than COLMAP's matching and verification on the
    120-frame room of docs/colmap.md, with 8 % more matches and the same refined result);
    off, or for pairs with a frame the input does not pose or with too few guided matches,
    COLMAP's matcher."""
    max_corners: int = 5000
    """KLT: corners tracked at most (new ones are added in every frame up to this)."""
    klt_verify: bool = False
    """KLT: run COLMAP's geometric verification on the track matches; off, they are written as
    the pairs' inlier matches (docs/colmap.md: why, and what verification costs)."""
    overlap: int = 8
    """COLMAP's sequential ``overlap`` with its quadratic overlap on: each frame is matched with
    the frames 1, 2, 4, ..., ``2**(overlap - 1)`` ahead (SIFT: by COLMAP's matcher; KLT: the
    corners on a common track): with 8, up to 128 frames ahead, at most 8 pairs a frame
    however long the video. COLMAP's own default (10) adds pairs 256 and 512 frames apart: on
    the 1,000-frame office walk 1,232 of its 8,977 pairs, whose removal left the joint result
    as it was (docs/colmap.md)."""
    mask_erosion_px: int = 3
    """The valid mask is shrunk by this many pixels so the rim of the mirror gives no features."""
    num_threads: int = -1
    """Threads for pycolmap's extraction, matching and bundle adjustment (-1: all cores)."""
    register_missing: bool = True
    """Run COLMAP's mapper to register frames of the image folder that the init did not pose."""
    mapper: str = "incremental"
    """How those frames are registered: ``incremental`` (COLMAP's incremental mapper's
    next-image loop from the triangulated model) or ``global`` (COLMAP's rotation averaging
    and global positioning seeded by the line-based poses,
    :mod:`omni_sfm.refine.global_register`); docs/colmap.md compares them."""
    ba_rounds: int = 2
    """Bundle adjustment rounds (each followed by filtering points with large errors)."""
    ba_max_iterations: int = 100
    """Ceres iterations per round at most."""
    prior_position_sigma: float = 0.02
    """Standard deviation of the position priors (the input's camera centres) that fix the
    adjustment's gauge, as a fraction of the input path length; weak next to the images."""
    loss_scale_px: float = 1.0
    """Scale of the robust (soft L1) loss on reprojection errors, pixels."""
    max_reprojection_error_px: float = 4.0
    """Observations with a larger error are removed after each round."""
    min_triangulation_angle_deg: float = 1.5
    """Points seen under a smaller angle are removed after each round."""
    min_points: int = 100
    """Fewer 3D points than this: the images cannot be trusted, every input pose is kept."""
    min_points_per_frame: float = 10.0
    """Fewer 3D points than this many per posed frame: likewise. A few points spread over a
    long sequence pin each pose worse than the lines did (seen on the texture-poor corridor:
    147 points for 100 frames moved 25 frames off a line-based start 10x more accurate)."""
    min_observations: int = 40
    """A frame with fewer triangulated observations keeps its input pose (and is held fixed in
    the adjustment)."""
    max_rotation_change_deg: float = 5.0
    """A frame whose adjusted rotation differs more from its input keeps its input pose unless
    its observations back the change strongly (``max_frame_error_px``)."""
    max_position_change: float = 0.05
    """Same for a centre that moves more than this fraction of the input path length."""
    max_frame_error_px: float = 1.0
    """A frame may change by more than the bounds above only if its own observations (at least
    ``min_observations``) have a mean reprojection error at most this (px)."""
    max_mean_reprojection_error_px: float = 2.0
    """An adjusted model with a larger mean reprojection error is not trusted at all."""
    adjustment: str = "joint"
    """``joint``: cameras, the init's 3D lines and the triangulated points adjusted together
    (:mod:`omni_sfm.refine.joint`; COLMAP's adjustment where the init folder has no line
    tracks); ``colmap``: COLMAP's point bundle adjustment alone."""
    text: bool = False
    """Also write the output model as COLMAP text files."""


@dataclass(frozen=True)
class RefineResult:
    """What :func:`refine` wrote and decided.

    Attributes:
        output: the output directory.
        trajectory: ``(N,)`` poses world_from_cam of our ray frame (``trajectory.tum``).
        input_trajectory: the init's poses.
        refined: ``(N,)`` bool, the frame's pose comes from the adjustment (else kept from input).
        report: ``report.json``.
    """

    output: Path
    trajectory: Trajectory
    input_trajectory: Trajectory
    refined: np.ndarray
    report: RefineReport


class Stages:
    """Per-stage wall time and a stage-level progress bar (pycolmap's calls report nothing)."""

    def __init__(self, names: list[str], progress: bool) -> None:
        from tqdm import tqdm

        self.times: dict[str, float] = {}
        self.bar = tqdm(total=len(names), desc="refine", unit="stage",
                        disable=None if progress else True, leave=False, file=sys.stderr)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        self.bar.set_description(f"refine: {name}")
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.times[name] = round(time.perf_counter() - t0, 3)
            self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


def model_statistics(rec: Any) -> ModelStatistics:
    """``colmap model_analyzer``'s numbers for a pycolmap Reconstruction."""
    return ModelStatistics(
        cameras=int(rec.num_cameras()),
        images=int(rec.num_images()),
        registered_images=int(rec.num_reg_images()),
        points=int(rec.num_points3D()),
        observations=int(rec.compute_num_observations()),
        mean_track_length=float(rec.compute_mean_track_length()),
        mean_observations_per_image=float(rec.compute_mean_observations_per_reg_image()),
        mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
    )


def observation_counts(rec: Any, image_ids: list[int]) -> np.ndarray:
    """``(N,)`` each image's observations of triangulated points (0 for an image not posed)."""
    return np.asarray([rec.images[i].num_points3D if i in rec.images and
                       rec.images[i].has_pose else 0 for i in image_ids], dtype=np.int64)


def _position_priors(rec: Any, image_ids: list[int], inp: Trajectory,
                     sigma: float) -> list[Any]:
    """COLMAP position priors (camera centres, isotropic ``sigma``) from the input poses."""
    import pycolmap

    priors = []
    for k, image_id in enumerate(image_ids):
        prior = pycolmap.PosePrior()
        prior.corr_data_id = rec.images[image_id].data_id
        prior.position = inp.positions[k]
        prior.position_covariance = np.eye(3) * sigma**2
        prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
        priors.append(prior)
    return priors


def colmap_bundle_adjust(rec: Any, fixed_frames: set[int], priors: list[Any] | None,
                         opts: RefineOptions) -> list[AdjustmentRound]:
    """Rounds of BA (poses and points free, intrinsics and ``fixed_frames`` fixed) each followed
    by removing observations with large errors or small triangulation angles (the reported
    error after a round is after that filtering).

    The gauge (position, rotation, scale) is fixed by the input's camera centres as position
    priors (COLMAP's pose-prior bundle adjuster); COLMAP's ``TWO_CAMS_FROM_WORLD`` gauge fixes
    one coordinate of the second image's centre, which for neighbouring video frames leaves the
    scale nearly free (it collapsed on the 100-frame room). ``priors`` None: no priors (a rig,
    whose lens offsets fix the scale, with a frame of ``fixed_frames`` held for the rest)."""
    import pycolmap

    rounds = []
    for _ in range(opts.ba_rounds):
        config = pycolmap.BundleAdjustmentConfig()
        for image_id in rec.reg_image_ids():
            config.add_image(image_id)
        for cam_id in rec.cameras:
            config.set_constant_cam_intrinsics(cam_id)
        for frame_id in fixed_frames:
            if rec.exists_frame(frame_id) and rec.frame(frame_id).has_pose:
                config.set_constant_rig_from_world_pose(frame_id)
        ba = pycolmap.BundleAdjustmentOptions()
        ba.refine_focal_length = False
        ba.refine_principal_point = False
        ba.refine_extra_params = False
        ba.refine_sensor_from_rig = False
        ba.print_summary = False
        ba.ceres.loss_function_type = pycolmap.LossFunctionType.SOFT_L1
        ba.ceres.loss_function_scale = opts.loss_scale_px
        ba.ceres.solver_options.max_num_iterations = opts.ba_max_iterations
        ba.ceres.solver_options.num_threads = opts.num_threads
        rec.update_point_3d_errors()
        before = float(rec.compute_mean_reprojection_error())
        adjuster = pycolmap.create_default_bundle_adjuster(ba, config, rec) if priors is None \
            else pycolmap.create_pose_prior_bundle_adjuster(
                ba, pycolmap.PosePriorBundleAdjustmentOptions(), config, priors, rec)
        summary = adjuster.solve()
        rec.update_point_3d_errors()
        # a few points end up where the camera model does not image them (error ~1e150):
        # the mean is taken after they are filtered
        removed = pycolmap.ObservationManager(rec).filter_all_points3D(
            opts.max_reprojection_error_px, opts.min_triangulation_angle_deg)
        rounds.append(AdjustmentRound(
            mean_reprojection_error_before_px=before,
            mean_reprojection_error_after_px=float(rec.compute_mean_reprojection_error()),
            termination=str(summary.termination_type).rsplit(".", 1)[-1],
            usable=bool(summary.is_solution_usable()),
            removed_observations=int(removed),
            points=int(rec.num_points3D()),
        ))
    return rounds


def _align_to_input(ref: Trajectory, inp: Trajectory) -> tuple[FloatArray, FloatArray, float]:
    """Similarity ``x_in = s R x_ref + t`` mapping the adjusted frames onto the input's.

    ``R`` is the chordal mean of the per-frame rotation differences (well defined even for a
    straight path, where centres alone leave a rotation free), then ``s`` and ``t`` by least
    squares on the centres; ``s`` is 1 where that is not positive or the adjusted centres do
    not spread (:func:`omni_sfm.transforms.similarity_from_poses`)."""
    sim = similarity_from_poses(inp.rotations, inp.positions, ref.rotations, ref.positions,
                                allow_reflection=False)
    return sim.rotation, sim.translation, sim.scale


def frame_timestamps(all_names: Sequence[str], image_names: Sequence[str],
                     timestamps: FloatArray) -> tuple[FloatArray | None, str]:
    """Timestamps for every image of the folder (``all_names``, sorted), when the input's
    ``timestamps`` (of its frames ``image_names``) are an affine function of the image's
    position in the folder (frame index or constant frame rate); otherwise None and the
    reason."""
    index = {n: k for k, n in enumerate(all_names)}
    x = np.asarray([index[n] for n in image_names], dtype=np.float64)
    y = np.asarray(timestamps, dtype=np.float64)
    if len(x) < 2:
        return None, "fewer than two input poses"
    A = np.stack([x, np.ones_like(x)], 1)
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    if np.abs(A @ coef - y).max() > 1e-6 * max(1.0, float(np.abs(y).max())):
        return None, "input timestamps are not an affine function of the frame index"
    ts = coef[0] * np.arange(len(all_names)) + coef[1]
    if np.array_equal(y, np.round(y)) and np.allclose(coef, np.round(coef), atol=1e-9):
        ts = np.round(ts)  # frame indices stay integers
    return ts, "affine in the frame index"


def _is_rig(init_dir: Path) -> bool:
    """The init folder's camera is a rig of lenses (refined by :mod:`.rig_pipeline`)."""
    from omni_sfm.cameras import RigCamera, load_camera

    path = init_dir / InitFolder.CAMERA
    return path.is_file() and isinstance(load_camera(path), RigCamera)


def refine(init_dir: Path, images: Path | None, output: Path,
           options: RefineOptions | None = None, *, database: Path | None = None,
           overwrite: bool = False, progress: bool = True, verbose: bool = False
           ) -> RefineResult:
    """Refine the poses of ``init_dir`` with COLMAP on its frames.

    Args:
        init_dir: an init directory (:func:`omni_sfm.export.colmap.write_init_model`).
        images: the image folder or video (as recorded, not mirrored), frame names as in the
            init model; frames the init did not pose may be there too (the mapper stage tries
            to register them). None: the frames ``init_dir`` records
            (:func:`omni_sfm.folders.images_for`).
        output: the output directory (complete or absent): ``sparse/``, ``trajectory.tum``,
            ``report.json``, ``images_colmap/``, ``camera_mask.png`` and ``database.db``
            (unless ``database`` is given), and, carried from ``init_dir`` for the later
            stages, ``camera.yaml``, ``lines3d.json`` and ``mask.png`` (docs/colmap.md).
        verbose: let COLMAP log to stderr (off: warnings and errors only).
        database: a COLMAP database to use and keep (created if missing); features and matches
            it holds are reused.

    Poses of ``init_dir``'s ``trajectory.tum`` that its report flags as not fixed by the data
    (``frames_uncertain``) do not seed COLMAP: their frames are left to the mapper.

    Raises OmniSfmError (one line) for a bad init directory or image folder, or where the data
    fix fewer than 3 of the init's poses.
    """
    o = options or RefineOptions()
    if o.mapper not in MAPPERS:
        raise OmniSfmError(f"unknown mapper {o.mapper!r} (known: {', '.join(MAPPERS)})")
    if o.features not in FEATURE_SOURCES:
        raise OmniSfmError(f"unknown feature source {o.features!r} (known: "
                           f"{', '.join(FEATURE_SOURCES)})")
    init_dir, output = Path(init_dir), Path(output)
    check_output_dir(output, overwrite=overwrite, inputs=(init_dir, images, database))
    images_dir = images_for(init_dir, images)
    check_output_dir(output, overwrite=overwrite, inputs=(images_dir,))
    if _is_rig(init_dir):
        from omni_sfm.refine.rig_pipeline import refine_rig

        return refine_rig(init_dir, images_dir, output, o, database=database,
                          overwrite=overwrite, progress=progress, verbose=verbose)
    init = read_init_model(init_dir)
    frames = FrameStore(images_dir)
    all_names = list(frames.names)
    check_image_names(images_dir, all_names, init.image_names, init_dir / InitFolder.SPARSE)
    with tempfile.TemporaryDirectory(prefix="omni_sfm_refine_") as scratch:
        init, uncertain = _seed_without_uncertain(init, init_dir, Path(scratch))
        return _refine(o, init, init_dir, images_dir, output, frames, all_names, uncertain,
                       database, overwrite=overwrite, progress=progress, verbose=verbose)


def flagged_seed_poses(artifacts: InitArtifacts, init_dir: Path) -> np.ndarray:
    """``(N,)`` bool over the init's poses: those its report flags as not fixed by the data
    (:meth:`~omni_sfm.folders.InitArtifacts.uncertain_rows`), which do not seed COLMAP; a
    one-line OmniSfmError when fewer than 3 poses are left to seed it with."""
    flagged = artifacts.uncertain_rows()
    if (~flagged).sum() < 3:
        raise OmniSfmError(
            f"{init_dir}: the data fix {int((~flagged).sum())} of the {len(flagged)} poses in "
            f"{InitFolder.TRAJECTORY} (report.json frames_uncertain); refine needs 3 to seed "
            "COLMAP with (omni-sfm init --initializer colmap starts from the images alone)")
    return flagged


def _seed_without_uncertain(init: InitModel, init_dir: Path, scratch: Path
                            ) -> tuple[InitModel, int]:
    """The init model without the poses its report lists as not fixed by the data (they are
    left to the mapper, as frames the init did not pose) and how many those are; a one-line
    OmniSfmError when fewer than 3 poses are left to seed COLMAP with."""
    flagged = flagged_seed_poses(init.artifacts, init_dir)
    if not flagged.any():
        return init, 0
    drop = [n for n, f in zip(init.image_names, flagged, strict=True) if f]
    return read_init_model(write_init_without(init_dir, scratch / "init", drop)), len(drop)


def _refine(o: RefineOptions, init: InitModel, init_dir: Path, images_dir: Path, output: Path,
            frames: FrameStore, all_names: list[str], uncertain: int, database: Path | None, *,
            overwrite: bool, progress: bool, verbose: bool) -> RefineResult:
    """:func:`refine` once its inputs are read and checked (``uncertain``: the input poses left
    to the mapper because the init's report flags them)."""
    posed = set(init.image_names)
    unposed = [n for n in all_names if n not in posed]
    stages = Stages(["images", "features", "matching", "triangulation", "mapper",
                     "bundle adjustment", "acceptance and output"], progress)
    export = init.camera.colmap_export()
    parts = Sections(
        input=RefineInput(init=stored_path(init_dir, output),
                          images=stored_path(images_dir, output),
                          database=stored_path(database, output) if database
                          else RefineFolder.DATABASE),
        camera=RefineCamera(model=init.camera.model, colmap_model=export.camera.model_name,
                            image_mirrored_for_colmap=export.flip_u),
        frames={"input_poses": len(init.trajectory), "images_in_folder": len(all_names),
                "unposed_in_folder": len(unposed), "input_poses_uncertain": uncertain},
        options=RefineSettings(**asdict(o)))
    try:
        with library_logging(verbose), atomic_output_dir(output, overwrite=overwrite,
                               inputs=(init_dir, images_dir, database)) as tmp:
            run = _Run(o, init, init_dir, frames, all_names, unposed, tmp,
                       Path(database) if database else tmp / RefineFolder.DATABASE, stages, parts,
                       progress)
            rec, seed, image_ids = run.colmap_model()
            obs0, trusted = run.bundle_adjustment(rec, image_ids)
            with stages.stage("acceptance and output"):
                traj, refined = run.accept_and_write(rec, seed, image_ids, obs0, trusted)
            report = parts.report(dict(stages.times))
            report.write(tmp / RefineFolder.REPORT)
    finally:
        stages.close()
    return RefineResult(output, traj, init.trajectory, refined, report)


@dataclass
class Sections:
    """The sections of refine's :class:`~omni_sfm.reports.RefineReport`, as the steps of
    :class:`_Run` add them."""

    input: RefineInput
    camera: RefineCamera
    frames: dict[str, int]
    options: RefineSettings
    features: FeaturesReport | None = None
    matching_guided: GuidedMatchingReport | None = None
    matching: dict[str, int] | None = None
    triangulation: TriangulationReport | None = None
    mapper: MapperReport | None = None
    joint_adjustment: JointAdjustmentNote | None = None
    bundle_adjustment: BundleAdjustmentReport | None = None
    acceptance: Acceptance | None = None
    model: ModelStatistics | None = None
    summary: str = ""
    lines3d: str | None = None
    carried_from_input: list[str] = field(default_factory=list)
    trajectory_frames: int = 0

    def report(self, timings_s: dict[str, float]) -> RefineReport:
        """The report, once every step has added its section."""
        assert self.features is not None and self.matching is not None
        assert self.triangulation is not None and self.mapper is not None
        assert self.bundle_adjustment is not None and self.acceptance is not None
        assert self.model is not None
        acc = self.acceptance
        return RefineReport(
            input=self.input, camera=self.camera, frames=self.frames, options=self.options,
            features=self.features, matching_guided=self.matching_guided,
            matching=self.matching, triangulation=self.triangulation, mapper=self.mapper,
            joint_adjustment=self.joint_adjustment, bundle_adjustment=self.bundle_adjustment,
            kept_input_for_all=acc.kept_input_for_all, refined_frames=int(acc.refined.sum()),
            kept_frames=acc.kept_frames, alignment_to_input=acc.alignment_report(),
            pose_changes=acc.pose_changes, model=self.model, summary=self.summary,
            lines3d=self.lines3d, carried_from_input=self.carried_from_input,
            trajectory_frames=self.trajectory_frames, timings_s=timings_s)


@dataclass
class _Run:
    """One refinement's state, its steps in the order :func:`refine` calls them."""

    o: RefineOptions
    init: InitModel
    init_dir: Path
    frames: FrameStore
    all_names: list[str]
    unposed: list[str]
    tmp: Path
    db_path: Path
    stages: Stages
    report: Sections
    progress: bool
    joint: bool = False
    """The model was adjusted with the lines (:meth:`_joint`)."""
    lines: tuple[LineEvidence, JointResult] | None = None
    """The init's lines and the joint adjustment's result (:meth:`_joint`)."""
    reposed: list[str] = field(default_factory=list)
    """Seeded frames the triangulation posed again (their input disagreed with the points)."""

    @property
    def register(self) -> bool:
        return self.o.register_missing and bool(self.unposed)

    def colmap_model(self) -> tuple[Any, Any, list[int]]:
        """Images and mask for COLMAP, features, matches, triangulation on the fixed input
        poses, the mapper for unposed frames: the model, the seed and the seeded image ids."""
        o, init, tmp, report = self.o, self.init, self.tmp, self.report
        camera, db = init.camera, self.db_path
        export = camera.colmap_export()
        names = list(self.all_names) if self.register else list(init.image_names)
        mask_path = init.artifacts.user_mask
        user_mask = None if mask_path is None else \
            read_mask(mask_path, (camera.width, camera.height))
        work = tmp / ".work"
        work.mkdir()
        images, colmap_mask = tmp / RefineFolder.COLMAP_IMAGES, tmp / RefineFolder.COLMAP_MASK
        with self.stages.stage("images"):
            write_colmap_images(self.frames, images, names, export, progress=self.progress)
            self.frames.close()
            write_colmap_mask(colmap_mask, camera, o.mask_erosion_px, user_mask)
        klt = o.features == "klt"
        if klt:  # tracks run through the frames in the folder's order
            wanted = set(names)
            names = [n for n in self.all_names if n in wanted]
        with self.stages.stage("features"):
            if klt:
                feats = track_features(db, images, colmap_mask, names, export,
                                       klt_tracking(o.max_corners))
            else:
                feats = extract_features(db, images, colmap_mask, names, export,
                                         max_features=o.max_features,
                                         num_threads=o.num_threads)
        report.features = FeaturesReport(
            source=o.features, extracted_images=len(feats.extracted),
            reused_images=len(feats.reused), keypoints=feats.num_keypoints,
            tracks=None if feats.tracks is None else int(len(np.unique(feats.tracks.track))))
        with self.stages.stage("matching"):
            if klt:
                matches = match_tracks(db, names, feats.tracks, work, overlap=o.overlap,
                                       verify=o.klt_verify)
            else:
                if o.guided_matching:
                    guided = match_guided(db, names, init.trajectory, init.image_names,
                                          camera, export, overlap=o.overlap,
                                          progress=self.progress)
                    report.matching_guided = GuidedMatchingReport(**asdict(guided))
                matches = match_sequential(db, overlap=o.overlap, num_threads=o.num_threads)
        report.matching = {"verified_pairs": matches.verified_pairs,
                           "inlier_matches": matches.inlier_matches}
        seed = seed_for_database(camera, init.trajectory, init.image_names, db)
        image_ids = [seed.reconstruction.find_image_with_name(n).image_id
                     for n in init.image_names]
        with self.stages.stage("triangulation"):
            rec, self.reposed = triangulate_seeded(
                seed.reconstruction, db, images, camera, export,
                max_error_px=o.max_reprojection_error_px,
                min_angle_deg=o.min_triangulation_angle_deg)
        report.triangulation = TriangulationReport(**asdict(model_statistics(rec)),
                                                   frames_posed_again=list(self.reposed))
        with self.stages.stage("mapper"):
            if self.register and o.mapper == "global":
                got = register_global(rec, db, self.unposed, camera, export,
                                      max_error_px=o.max_reprojection_error_px,
                                      min_angle_deg=o.min_triangulation_angle_deg)
                for name in got.registered:
                    rec.extract_colors_for_image(rec.find_image_with_name(name).image_id,
                                                 str(images))
                report.mapper = got.report()
            else:
                rec, report.mapper = register_unposed(rec, self.register, self.unposed, db,
                                                      images, o)
        shutil.rmtree(work, ignore_errors=True)
        return rec, seed, image_ids

    def bundle_adjustment(self, rec: Any, image_ids: list[int]) -> tuple[np.ndarray, bool]:
        """Adjust when the model is strong enough; the seeded frames' observation counts
        before it and whether the model is trusted."""
        o, inp = self.o, self.init.trajectory
        obs0 = observation_counts(rec, image_ids)
        weak = obs0 < o.min_observations
        fixed = {rec.images[i].frame_id for i, w in zip(image_ids, weak, strict=True) if w}
        need_points = max(o.min_points, int(np.ceil(o.min_points_per_frame * len(image_ids))))
        trusted = rec.num_points3D() >= need_points and (~weak).sum() >= 3
        with self.stages.stage("bundle adjustment"):
            # too few points: they add nothing the init's own line adjustment lacked
            joint = self._joint(rec, image_ids) if o.adjustment == "joint" and trusted \
                else None
            if joint is not None:
                self.joint = True
                self.report.bundle_adjustment = BundleAdjustmentReport(joint=joint)
            elif trusted:
                priors = _position_priors(rec, image_ids, inp,
                                          o.prior_position_sigma * max(inp.path_length(), 1e-9))
                rounds = colmap_bundle_adjust(rec, fixed, priors, o)
                self.report.bundle_adjustment = BundleAdjustmentReport(
                    rounds=rounds, held_fixed_frames=int(len(fixed)),
                    after=model_statistics(rec))
            else:
                self.report.bundle_adjustment = BundleAdjustmentReport(
                    skipped=f"too few points ({rec.num_points3D()} < {need_points}) "
                            f"or well-observed frames ({int((~weak).sum())} < 3)")
        return obs0, bool(trusted)

    def _joint(self, rec: Any, image_ids: list[int]) -> JointReport | None:
        """The joint adjustment of lines and points on ``rec`` (its report), or None where the
        init folder has no line evidence or the adjustment fails (the reason reported)."""
        lines = read_line_evidence(self.init.artifacts)
        if isinstance(lines, str):
            self.report.joint_adjustment = JointAdjustmentNote(skipped=lines)
            return None
        # the mapper's frames go in too: held at their mapper poses they would stay in the
        # model's frame before the adjustment (0.9 m off on the 1,000-frame office walk)
        added, ts = self.registered(rec)
        try:
            res, rep = adjust_model(rec, image_ids, self._start(rec), lines,
                                    self.init.camera, registered=added,
                                    registered_timestamps=ts)
            self.lines = (lines, res)
        except OmniSfmError as exc:
            self.report.joint_adjustment = JointAdjustmentNote(failed=str(exc))
            return None
        # as after COLMAP's adjustment: points that the camera model does not image where
        # they are seen (a few end up behind a mirror, errors of 1e150 px) go
        import pycolmap

        removed = int(pycolmap.ObservationManager(rec).filter_all_points3D(
            self.o.max_reprojection_error_px, self.o.min_triangulation_angle_deg))
        return replace(rep, removed_observations=removed, after=model_statistics(rec))

    def _start(self, rec: Any) -> Trajectory:
        """The adjustment's start: the input poses, those the triangulation posed again
        from the model."""
        inp = self.init.trajectory
        if not self.reposed:
            return inp
        export = self.init.camera.colmap_export()
        again, ok = trajectory_from_reconstruction(rec, export, self.reposed,
                                                   np.zeros(len(self.reposed)))
        R, c = inp.rotations.copy(), inp.positions.copy()
        row = {n: k for k, n in enumerate(self.init.image_names)}
        for j, name in enumerate(np.asarray(self.reposed)[ok].tolist()):
            R[row[name]], c[row[name]] = again.rotations[j], again.positions[j]
        return Trajectory(inp.timestamps, R, c)

    def registered(self, rec: Any) -> tuple[list[str], FloatArray | None]:
        """The frames without an input pose that the mapper posed, and their timestamps
        (none where the folder's frames have no timestamps: they cannot be placed)."""
        ts_all, _ = frame_timestamps(self.all_names, self.init.image_names,
                                     self.init.trajectory.timestamps)
        added = [n for n in self.unposed if (im := rec.find_image_with_name(n)) is not None
                 and im.has_pose]
        if ts_all is None or not added:
            return [], None
        idx = {n: k for k, n in enumerate(self.all_names)}
        return added, ts_all[[idx[n] for n in added]]

    def accept_and_write(self, rec: Any, seed: Any, image_ids: list[int], obs0: np.ndarray,
                         trusted: bool) -> tuple[Trajectory, np.ndarray]:
        """Accept per frame, place the mapper's frames, write the model, trajectory and the
        files carried forward; the trajectory and which frames were refined."""
        o, init, tmp, report = self.o, self.init, self.tmp, self.report
        acc = _accept(rec, seed.export, init, image_ids, obs0, trusted, o,
                      init.trajectory.path_length(), lines_too=self.joint)
        report.acceptance = acc
        traj, refined = acc.trajectory, acc.refined
        _, ts_why = frame_timestamps(self.all_names, init.image_names,
                                    init.trajectory.timestamps)
        added, ts = self.registered(rec)
        if acc.alignment is None or ts is None:
            added = []  # without the alignment or timestamps they cannot be placed
        else:
            new, _ = trajectory_from_reconstruction(rec, seed.export, added, ts)
            traj, refined = merge_poses(traj, refined, acc.alignment.apply(new))
        if self.register and report.mapper is not None:
            report.mapper = replace(
                report.mapper, added_to_trajectory=added,
                timestamps=ts_why if acc.alignment is not None else (
                    "not placed: the adjusted model was not trusted"))
        final = _final_model(rec, seed.export, acc.alignment, image_ids, init, traj, added)
        report.model = model_statistics(final)
        report.summary = final.summary()
        (tmp / RefineFolder.SPARSE).mkdir()
        final.write_binary(str(tmp / RefineFolder.SPARSE))
        if o.text:
            final.write_text(str(tmp / RefineFolder.SPARSE))
        write_tum(tmp / RefineFolder.TRAJECTORY, traj)
        write_camera_yaml(tmp / RefineFolder.CAMERA, init.camera)
        if self.lines is not None and acc.alignment is not None:
            # the adjusted lines, in the output's world (carry_forward then skips the init's)
            write_lines3d(tmp / RefineFolder.LINES3D, adjusted_segments(*self.lines, acc.alignment))
            report.lines3d = "adjusted with the points (joint adjustment)"
        report.carried_from_input = carry_forward(self.init_dir, tmp)
        report.trajectory_frames = len(image_ids) + len(added)
        return traj, refined


def register_unposed(rec: Any, register: bool, unposed: list[str], db_path: Path,
                     image_dir: Path, o: RefineOptions) -> tuple[Any, MapperReport]:
    """COLMAP's registration of the frames ``unposed`` into ``rec`` (in place), the seeded
    frames held: the incremental mapper's next-image loop (absolute pose, triangulation of the
    new frame's observations, local adjustments around it) without its global refinements,
    which on a long video took most of the stage (260 s for 61 frames of a 1,000-frame walk)
    and which the global adjustment after this stage does anyway."""
    import pycolmap

    if not register:
        return rec, MapperReport(skipped="every frame of the folder has an input pose"
                                 if not unposed else "disabled")
    opts = pycolmap.IncrementalPipelineOptions()
    opts.fix_existing_frames = True
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.num_threads = o.num_threads
    mapper_opts, tri = opts.get_mapper(), opts.get_triangulation()
    local_ba = opts.get_local_bundle_adjustment()
    with pycolmap.Database.open(str(db_path)) as db:
        cache = pycolmap.DatabaseCache.create(db, pycolmap.DatabaseCacheOptions())
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    wanted = {im.image_id for im in rec.images.values() if im.name in set(unposed)}
    while True:  # the best-connected candidate first, as the mapper chooses
        got = next((i for i in mapper.find_next_images(mapper_opts, False)
                    if i in wanted and mapper.register_next_image(mapper_opts, i)), None)
        if got is None:
            break
        mapper.triangulate_image(tri, got)
        mapper.iterative_local_refinement(opts.ba_local_max_refinements,
                                          opts.ba_local_max_refinement_change, mapper_opts,
                                          local_ba, tri, got)
    mapper.end_reconstruction(False)
    for image_id in wanted:  # (the mapper's end removes the frames it did not register)
        if rec.exists_image(image_id) and rec.images[image_id].has_pose:
            rec.extract_colors_for_image(image_id, str(image_dir))
    names = {im.name for im in rec.images.values() if im.has_pose}
    return rec, MapperReport(registered=[n for n in unposed if n in names],
                             not_registered=[n for n in unposed if n not in names])


def merge_poses(traj: Trajectory, refined: np.ndarray, new: Trajectory
                ) -> tuple[Trajectory, np.ndarray]:
    """``traj`` and the poses ``new`` in one trajectory in timestamp order, and which of them
    the images refined (``refined``, then every one of ``new``)."""
    ts = np.concatenate([traj.timestamps, new.timestamps])
    order = np.argsort(ts, kind="stable")
    merged = Trajectory(ts[order], np.concatenate([traj.rotations, new.rotations])[order],
                        np.concatenate([traj.positions, new.positions])[order])
    return merged, np.concatenate([refined, np.ones(len(new), dtype=bool)])[order]


def frame_errors(rec: Any, image_ids: list[int]) -> np.ndarray:
    """``(N,)`` mean reprojection error (px) of each image's triangulated observations
    (inf for an image without any)."""
    out = np.full(len(image_ids), np.inf)
    for k, image_id in enumerate(image_ids):
        if image_id not in rec.images or not rec.images[image_id].has_pose:
            continue
        im = rec.images[image_id]
        obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
        if not obs:
            continue
        uv = np.asarray([o[0] for o in obs])
        xyz = np.asarray([o[1] for o in obs])
        T = np.asarray(im.cam_from_world().matrix())
        proj = np.asarray(rec.cameras[im.camera_id].img_from_cam(xyz @ T[:, :3].T + T[:, 3]))
        out[k] = float(np.nanmean(np.linalg.norm(proj - uv, axis=1)))
    return out


@dataclass(frozen=True)
class Acceptance:
    """What the acceptance step decided (``report.json``: :meth:`report`).

    Attributes:
        trajectory: ``(N,)`` per input frame, the adjusted pose (mapped onto the input's frame)
            or the input pose.
        refined: ``(N,)`` bool, the frame's pose comes from the adjustment.
        alignment: the similarity taking the adjusted model onto the input's frame and scale,
            or None when the adjustment was not trusted at all.
        kept_input_for_all: why every input pose was kept, or None.
        kept_frames: frame name -> why its input pose was kept.
        pose_changes: how far the accepted poses moved, or None.
    """

    trajectory: Trajectory
    refined: np.ndarray
    alignment: Similarity | None = None
    kept_input_for_all: str | None = None
    kept_frames: dict[str, str] = field(default_factory=dict)
    pose_changes: PoseChanges | None = None

    def alignment_report(self) -> AlignmentReport | None:
        """``alignment_to_input`` of the report."""
        a = self.alignment
        return None if a is None else AlignmentReport(
            rotation=a.rotation, translation=a.translation, scale=a.scale,
            rotation_deg=float(np.degrees(rotation_angle(a.rotation))))


def _accept(rec: Any, export: Any, init: InitModel, image_ids: list[int], obs0: np.ndarray,
            trusted_model: bool, o: RefineOptions, path_length: float, *,
            lines_too: bool = False) -> Acceptance:
    """Per frame: the adjusted pose (mapped onto the input's frame) or the input pose, and why.
    ``lines_too``: the adjustment used the lines, which fix every frame, so a frame with few
    point observations is not held to its input pose for that."""
    inp = init.trajectory
    why = untrusted_model(rec, trusted_model, o)
    if why is not None:
        return Acceptance(inp, np.zeros(len(inp), dtype=bool), kept_input_for_all=why)
    ref, ok = trajectory_from_reconstruction(rec, export, init.image_names, inp.timestamps)
    return accept_poses(inp, init.image_names, ref, ok, obs0, observation_counts(rec, image_ids),
                        frame_errors(rec, image_ids), o, path_length, lines_too=lines_too)


def untrusted_model(rec: Any, trusted_model: bool, o: RefineOptions) -> str | None:
    """Why the adjusted model is not trusted at all (every input pose kept), or None."""
    ba_mean = float(rec.compute_mean_reprojection_error())
    if not trusted_model:
        return "too few points or well-observed frames for a trustworthy adjustment"
    if ba_mean > o.max_mean_reprojection_error_px:
        return f"mean reprojection error {ba_mean:.2f} px > {o.max_mean_reprojection_error_px}"
    return None


def accept_poses(inp: Trajectory, names: Sequence[str], ref: Trajectory, ok: np.ndarray,
                 obs0: np.ndarray, obs: np.ndarray, err: np.ndarray, o: RefineOptions,
                 path_length: float, *, lines_too: bool = False) -> Acceptance:
    """:func:`_accept` once the model is trusted, for any camera: ``ref`` the adjusted poses of
    the frames ``ok`` (``(N,)`` over the input frames ``names``), ``obs0`` / ``obs`` each
    frame's point observations before and after the adjustment, ``err`` its mean reprojection
    error (px)."""
    n = len(inp)
    reasons: dict[str, str] = {}
    full_R, full_c = inp.rotations.copy(), inp.positions.copy()
    full_R[ok], full_c[ok] = ref.rotations, ref.positions
    adjusted = Trajectory(inp.timestamps.copy(), full_R, full_c)
    cand = ok if lines_too else ok & (obs0 >= o.min_observations) & (obs >= o.min_observations)
    # a change beyond the plausible bounds stands only where the frame's own observations
    # (at least min_observations of them) fit it to a small error: 6 pose parameters against
    # dozens of sub-pixel observations; otherwise the adjustment is not trusted there
    strong = cand & (err <= o.max_frame_error_px)
    scale_len = path_length if path_length > 0 else 1.0
    rot_change = pos_change = np.zeros(n)
    small = cand.copy()
    R = np.eye(3)
    t = np.zeros(3)
    s = 1.0
    for _ in range(3):  # fit on the frames that changed little, re-check, fit again
        if small.sum() < 3:
            break
        R, t, s = _align_to_input(adjusted.subset(small), inp.subset(small))
        aligned = Similarity(R, t, s).apply(adjusted)
        rot_change = np.degrees(rotation_angle(np.swapaxes(inp.rotations, 1, 2)
                                               @ aligned.rotations))
        pos_change = np.linalg.norm(aligned.positions - inp.positions, axis=1) / scale_len
        new_small = cand & (rot_change <= o.max_rotation_change_deg) & (
            pos_change <= o.max_position_change)
        if np.array_equal(new_small, small):
            break
        small = new_small
    if small.sum() < 3 or small.sum() < 0.5 * cand.sum():
        return Acceptance(inp, np.zeros(n, dtype=bool), kept_input_for_all=(
            "the adjustment moved most frames implausibly far (or fewer than three frames "
            "changed plausibly)"))
    use = small | (cand & strong)
    aligned = Similarity(R, t, s).apply(adjusted)
    for k, name in enumerate(names):
        if use[k]:
            continue
        if not ok[k]:
            reasons[name] = "not registered in the COLMAP model"
        elif obs0[k] < o.min_observations or obs[k] < o.min_observations:
            reasons[name] = (f"{int(min(obs0[k], obs[k]))} observations < "
                             f"{o.min_observations}")
        else:
            what = (f"rotation changed {rot_change[k]:.2f} deg"
                    if rot_change[k] > o.max_rotation_change_deg else
                    f"centre moved {100 * pos_change[k]:.2f}% of the path")
            reasons[name] = (f"{what} with weak support ({int(obs[k])} observations, "
                             f"{err[k]:.2f} px): implausible")
    large = use & ~small
    rot = np.where(use[:, None, None], aligned.rotations, inp.rotations)
    pos = np.where(use[:, None], aligned.positions, inp.positions)
    traj = Trajectory(inp.timestamps.copy(), rot, pos)
    changes = PoseChanges(
        large_changes_backed_by_images={
            names[int(k)]: FrameChange(rotation_deg=float(rot_change[k]),
                                       position_fraction_of_path=float(pos_change[k]),
                                       observations=int(obs[k]),
                                       mean_reprojection_error_px=float(err[k]))
            for k in np.flatnonzero(large)},
        rotation_deg_median=float(np.median(rot_change[use])),
        rotation_deg_max=float(rot_change[use].max()),
        position_fraction_of_path_median=float(np.median(pos_change[use])),
        position_fraction_of_path_max=float(pos_change[use].max()),
    )
    return Acceptance(traj, use, Similarity(R, t, s), kept_frames=reasons, pose_changes=changes)


def _final_model(rec: Any, export: Any, alignment: Similarity | None, image_ids: list[int],
                 init: InitModel, traj: Trajectory, added: list[str]) -> Any:
    """The adjusted model mapped onto the input's frame, with every seeded frame at its
    ``trajectory.tum`` pose (kept frames back at their input pose) and point errors updated.
    Frames registered by the mapper stay when they are in the trajectory, otherwise they are
    deregistered."""
    import pycolmap

    if alignment is not None:
        rec.transform(pycolmap.Sim3d(float(alignment.scale),
                                     pycolmap.Rotation3d(np.asarray(alignment.rotation)),
                                     np.asarray(alignment.translation)))
    by_ts = {float(ts): k for k, ts in enumerate(traj.timestamps)}
    idx = [by_ts[float(ts)] for ts in init.trajectory.timestamps]
    set_colmap_poses(rec, export, image_ids, traj.subset(np.asarray(idx, dtype=np.intp)))
    keep = {rec.find_image_with_name(n).image_id for n in added}
    for image_id in list(rec.reg_image_ids()):
        if image_id not in image_ids and image_id not in keep:
            rec.deregister_frame(rec.images[image_id].frame_id)
    rec.update_point_3d_errors()
    return rec
