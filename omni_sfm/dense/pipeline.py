"""Dense mapping from known poses: rectified virtual views, SGBM depth, 3-view check, TSDF.

Input: a poses folder (``init`` or ``refine`` output: ``trajectory.tum``, ``camera.yaml``) and
the frames. For every keyframe ``k`` two stereo pairs are formed with the frame before and the
frame after it whose baseline is closest to the stereo baseline ``B``; each pair is seen
through a rig of four rectified pinhole views (:mod:`omni_sfm.dense.views`), matched with
``cv2.StereoSGBM`` (:mod:`omni_sfm.dense.stereo`); a depth is kept only where the other pair
(a third view) confirms it; the kept depths are fused in a TSDF (:mod:`omni_sfm.dense.fusion`)
whose zero level set gives ``dense.ply`` and ``mesh.ply``.

Scale. Line-based poses have an arbitrary scale, so nothing here assumes metres: ``B`` is a
parallax angle times the scene's median depth, and that depth is measured first by stereo on
the middle frame with growing frame offsets (disparity is ``f b / z``, so the offset whose
median disparity reaches the target parallax gives both). The voxel size is the pixel
footprint at the median depth. The outputs are in the poses' unit, or in metres when a known
distance (first-to-last camera distance, or camera height above the floor) fixes the scale.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras import CameraModel, RigCamera, write_camera_yaml
from omni_sfm.dense.fusion import TsdfFusion
from omni_sfm.dense.relpose import (
    Features,
    PairPose,
    PairPoseOptions,
    frame_features,
    pair_pose,
)
from omni_sfm.dense.stereo import StereoOptions, consistent, depth_along, rig_depth
from omni_sfm.dense.views import (
    StereoRig,
    ViewGeometry,
    remap_tables,
    sample_views,
    stereo_rig,
    view_geometry,
)
from omni_sfm.errors import OmniSfmError
from omni_sfm.export.colmap_lenses import rig_metres_per_unit
from omni_sfm.fileio import (
    atomic_output_dir,
    check_output_dir,
    stored_path,
)
from omni_sfm.folders import (
    DenseFolder,
    StageFolder,
    carry_forward,
    images_for,
    pose_frame_names,
)
from omni_sfm.frames import FrameStore
from omni_sfm.geometry import FloatArray, normalize
from omni_sfm.libs import open3d_module
from omni_sfm.lines.source_camera import camera_for_frames
from omni_sfm.lines3d import LineSegments3D, write_lines3d
from omni_sfm.poses import Trajectory, write_tum
from omni_sfm.reports import (
    BackendReport,
    CalibrationReport,
    CalibrationTrial,
    DenseFrame,
    DenseInputRecord,
    DenseReport,
    PairPoseCheck,
    PairPoseSummary,
    RigScaleRecord,
    ScaleReport,
    ViewsReport,
)


@dataclass(frozen=True, kw_only=True)
class DenseOptions:
    """Options of :func:`dense_map`; lengths are relative to the scene, never absolute."""

    keyframe_step: int | None = None
    """Frames between keyframes; None: half the frame offset of the stereo baseline."""
    known_distance: float | None = None
    """Distance between the first and last camera centres (e.g. metres): makes the map metric."""
    camera_height: float | None = None
    """Camera height above the floor (e.g. metres): makes the map metric (floor found in the
    dense points)."""
    up_in_camera: tuple[float, float, float] | None = None
    """The camera's up axis in its ray frame (for ``camera_height``); None: ``+z`` for the
    hyperboloid (robot mount, mirror axis up), ``-y`` otherwise (OpenCV's hand-held convention)."""
    parallax: float = 0.2
    """Stereo baseline as a fraction of the scene's median depth (the parallax angle, rad)."""
    near_ratio: float = 0.25
    """Closest depth measured, as a fraction of the median depth (sets SGBM's disparity range)."""
    resolution_scale: float = 1.0
    """Virtual view pixels per camera pixel (angle); < 1 is faster and coarser."""
    fov_along_deg: float = 130.0
    """Field of view of each virtual view along the baseline, deg (90 across it)."""
    voxel_pixels: float = 2.0
    """TSDF voxel size in pixel footprints at the median depth."""
    min_weight: float = 3.0
    """TSDF weight (number of depth observations) a surface point needs to be output."""
    min_points: int = 1000
    """Fewer fused surface points than this is an error (nothing usable was seen)."""
    max_depth_ratio: float = 8.0
    """Depths beyond this many median depths are not fused."""
    stereo: StereoOptions = field(default_factory=StereoOptions)
    """Matching and filtering."""
    pair_pose: PairPoseOptions = field(default_factory=PairPoseOptions)
    """Re-estimating each stereo pair's relative pose from SIFT matches."""


@dataclass(frozen=True)
class DenseInput:
    """Poses, camera and the frame of every pose.

    Attributes:
        trajectory: the poses (world_from_cam, pose units).
        camera: the camera model the poses refer to.
        frames: the image folder or video.
        image_names: the name of each pose's frame in ``frames``, in trajectory order.
        lines: the 3D lines of the poses folder (``lines3d.json``), or None.
        metres_per_unit: for a rig camera, the metres in one pose unit (the poses folder's
            ``report.json`` ``rig.metres_per_unit``): where each lens's centre lies in the
            poses' units; None for a central camera.
        metric: the lenses' baseline fixes ``metres_per_unit`` (``rig.fixed``), so it makes
            the map metric; else it only places the lenses (a rough scale).
    """

    trajectory: Trajectory
    camera: CameraModel
    frames: FrameStore
    image_names: tuple[str, ...]
    lines: LineSegments3D | None
    metres_per_unit: float | None = None
    metric: bool = False


@dataclass(frozen=True)
class KeyframeStats:
    """What one keyframe gave.

    Attributes:
        frame: keyframe index; ``sources``: the two frames matched; ``baselines``: their
            distances (pose units).
        depth_share: share of the frame's valid pixels whose ray has a checked depth in one of
            the two rigs (nearest view pixel); what the frame contributes to the map.
        view_pixels, depth_pixels: virtual-view pixels inside the camera's valid region, and
            those with a checked depth (both rigs).
        seconds_depth, seconds_fusion: time of depth estimation (views, SGBM, check) and of
            TSDF integration.
        pair_poses: the source pose used by each of the two pairs (image-based or given).
    """

    frame: int
    sources: tuple[int, ...]
    baselines: tuple[float, ...]
    depth_share: float
    view_pixels: int
    depth_pixels: int
    seconds_depth: float
    seconds_fusion: float
    pair_poses: tuple[PairPose, ...] = ()

    @property
    def view_share(self) -> float:
        return self.depth_pixels / self.view_pixels if self.view_pixels else 0.0


@dataclass(frozen=True)
class DenseResult:
    """The fused map, in output units (see ``scale``).

    Attributes:
        points: ``(N, 3)`` dense surface points (world).
        colors: ``(N, 3)`` RGB in [0, 1].
        mesh: legacy ``open3d.geometry.TriangleMesh``.
        trajectory: the poses in output units.
        scale: output units per pose unit.
        median_depth: the scene's median depth, output units.
        voxel_size: TSDF voxel, output units.
        keyframes: per keyframe statistics.
        report: ``report.json`` (without ``input``, which :func:`write_dense` adds).
    """

    points: FloatArray
    colors: FloatArray
    mesh: Any
    trajectory: Trajectory
    scale: float
    median_depth: float
    voxel_size: float
    keyframes: tuple[KeyframeStats, ...]
    report: DenseReport


def read_dense_input(poses_dir: Path, images: Path | None = None,
                     camera_file: Path | None = None) -> DenseInput:
    """Poses folder + frames -> :class:`DenseInput`; every defect is a one-line OmniSfmError.

    ``images``: the image folder or video; None: the frames the poses folder records
    (:func:`omni_sfm.folders.images_for`). Frames are found by the poses folder's
    ``colmap.json`` image names when present, else (video) by the timestamps in seconds ``init``
    gives video frames, else by names equal to the integer timestamps (``000012.png`` for
    timestamp 12), else in order when the source holds exactly one frame per pose."""
    poses_dir = Path(poses_dir)
    if not poses_dir.is_dir():
        raise OmniSfmError(f"{poses_dir}: poses folder not found")
    tum = poses_dir / StageFolder.TRAJECTORY
    if not tum.is_file():
        raise OmniSfmError(f"{tum}: no trajectory (need the output folder of init or refine)")
    art = StageFolder(poses_dir).load_stage(camera=camera_file is None)
    traj = art.trajectory
    if len(traj) < 3:
        raise OmniSfmError(f"{tum}: {len(traj)} poses, dense mapping needs at least 3")
    source = images_for(poses_dir, images)
    if camera_file is not None:  # a file, or equirectangular from the frame size
        camera = camera_for_frames(camera_file, source)
    elif art.camera is None:
        raise OmniSfmError(f"{art.folder / art.folder.CAMERA}: camera file not found (give "
                           "--camera FILE)")
    else:
        camera = art.camera
    # a rig's lenses sit at their offsets (metres) from the rig's centre: the scale says where
    scale, metric = None, False
    if isinstance(camera, RigCamera):
        scale = rig_metres_per_unit(poses_dir)  # one line when the report lacks it
        metric = art.report is not None and art.report.rig is not None and \
            art.report.rig.fixed is True
    frames = FrameStore(source)
    chosen = pose_frame_names(poses_dir, traj, frames)
    return DenseInput(traj, camera, frames, tuple(chosen), art.lines3d, scale, metric)


@dataclass(frozen=True)
class _Lens:
    """One lens of the frames: its model, its poses (world_from_lens, pose units) and the
    frame pixel of its top-left pixel (a central camera: the whole frame, the poses as given)."""

    camera: CameraModel
    trajectory: Trajectory
    corner: tuple[int, int]


def _lenses(inp: DenseInput) -> list[_Lens]:
    """The lenses of ``inp``'s camera: each lens of a rig at its place in the rig (its centre
    ``rig_from_lens`` metres from the rig's, ``inp.metres_per_unit`` to pose units); a central
    camera is one lens."""
    cam, traj = inp.camera, inp.trajectory
    if not isinstance(cam, RigCamera):
        return [_Lens(cam, traj, (0, 0))]
    if inp.metres_per_unit is None or not inp.metres_per_unit > 0:
        raise OmniSfmError("a rig camera needs the poses' scale (report.json rig.metres_per_unit)"
                           " to place its lenses")
    out = []
    for k, lens in enumerate(cam.lenses):
        x, y = (int(v) for v in cam.corners[k])
        out.append(_Lens(lens, traj.fixed_camera(cam.rig_from_lens_in(k, inp.metres_per_unit)),
                         (x, y)))
    return out


class _Frames:
    """Images of one lens by pose index, read on demand (RGB uint8, the lens's part of the
    frame), a few kept."""

    def __init__(self, inp: DenseInput, lens: _Lens) -> None:
        self.inp = inp
        self.camera = inp.camera
        self.lens = lens
        self._cache: dict[int, np.ndarray] = {}

    def __call__(self, k: int) -> np.ndarray:
        if k not in self._cache:
            name = self.inp.image_names[k]
            img = self.inp.frames.read(name)
            if img.shape[:2] != (self.camera.height, self.camera.width):
                said = self.camera.frame_size_mismatch(img.shape[1], img.shape[0])
                raise OmniSfmError(f"{self.inp.frames.where(name)}: " + (
                    said or f"image is {img.shape[1]}x{img.shape[0]} px, the camera is "
                    f"{self.camera.width}x{self.camera.height}"))
            if len(self._cache) > 24:
                self._cache.pop(next(iter(self._cache)))
            (x, y), lc = self.lens.corner, self.lens.camera
            self._cache[k] = np.ascontiguousarray(img[y:y + lc.height, x:x + lc.width, ::-1])
        return self._cache[k]


@dataclass
class _PairDepth:
    rig: StereoRig
    depth: FloatArray          # (V, H, W) view z, NaN where none
    colors: np.ndarray         # (V, H, W, 3) uint8 reference views
    valid: np.ndarray          # (V, H, W) reference views inside the camera's valid region
    pose: PairPose             # the source pose used


class _Matcher:
    """Stereo of frame pairs of one lens through rectified rigs."""

    def __init__(self, inp: DenseInput, lens: _Lens, geometry: ViewGeometry,
                 num_disparities: int, opts: StereoOptions, pose_opts: PairPoseOptions) -> None:
        import cv2

        self.inp = inp
        self.lens = lens
        self.geometry = geometry
        self.num_disparities = num_disparities
        self.opts = opts
        self.pose_opts = pose_opts
        self.frames = _Frames(inp, lens)
        self.valid = lens.camera.valid_mask()
        self._sift_mask = cv2.erode(self.valid.astype(np.uint8) * 255, np.ones((7, 7), np.uint8))
        self._features: dict[int, Features] = {}
        self._cv2 = cv2

    def features(self, k: int) -> Features:
        if k not in self._features:
            if len(self._features) > 24:
                self._features.pop(next(iter(self._features)))
            self._features[k] = frame_features(self.frames(k), self.lens.camera,
                                               self._sift_mask, self.pose_opts)
        return self._features[k]

    def pair(self, ref: int, src: int) -> _PairDepth:
        traj, cam, cv2 = self.lens.trajectory, self.lens.camera, self._cv2
        if self.pose_opts.enabled:
            pose = pair_pose(self.features(ref), self.features(src), traj.rotations[ref],
                             traj.positions[ref], traj.rotations[src], traj.positions[src],
                             self.pose_opts)
        else:
            pose = PairPose(traj.rotations[src], traj.positions[src], False, 0, float("nan"),
                            float("nan"))
        rig = stereo_rig(self.geometry, traj.positions[ref], pose.centre_src,
                         traj.rotations[ref])
        views = []
        for k, rot in ((ref, traj.rotations[ref]), (src, pose.world_from_src)):
            tables = remap_tables(cam, self.geometry, rig.world_from_views, rot)
            views.append(sample_views(self.frames(k), tables, self.valid))
        (ref_rgb, ref_ok), (src_rgb, src_ok) = views
        grey = [np.stack([cv2.cvtColor(v, cv2.COLOR_RGB2GRAY) for v in rgb])
                for rgb in (ref_rgb, src_rgb)]
        depth = rig_depth(rig, grey[0], ref_ok, grey[1], src_ok, self.num_disparities,
                          self.opts)
        return _PairDepth(rig, depth, ref_rgb, ref_ok, pose)


def _num_disparities(geometry: ViewGeometry, opts: DenseOptions) -> int:
    """SGBM's disparity range: the median depth at ``parallax`` has disparity ``f parallax``,
    the nearest measured depth (``near_ratio`` of it) ``f parallax / near_ratio``."""
    d = geometry.focal * opts.parallax / opts.near_ratio
    return int(16 * max(2, math.ceil(d / 16.0)))


@dataclass(frozen=True)
class BaselineCalibration:
    """The scene's depth scale in pose units, measured by stereo on one frame.

    Attributes:
        frame: the frame measured.
        median_depth: median view depth of its stereo points, pose units.
        baseline: the stereo baseline ``parallax * median_depth``, pose units.
        frame_offset: typical frame offset that gives ``baseline``.
        trials: ``(offset, baseline, median disparity px, depth share)`` per trial.
    """

    frame: int
    median_depth: float
    baseline: float
    frame_offset: int
    trials: tuple[tuple[int, float, float, float], ...]


def calibrate_baseline(matcher: _Matcher, opts: DenseOptions) -> BaselineCalibration:
    """Stereo on the middle frame with frame offsets 1, 2, 4, ... until the median disparity
    reaches the target parallax; OmniSfmError when no offset gives depth (no baseline)."""
    traj = matcher.lens.trajectory
    n = len(traj)
    m = n // 2
    f = matcher.geometry.focal
    target = opts.parallax * f
    trials: list[tuple[int, float, float, float]] = []
    best: tuple[float, float, float] | None = None     # median depth, baseline, disparity
    o = 1
    while o <= n - 1:
        src = m + o if m + o < n else m - o
        if src < 0:
            break
        b = float(np.linalg.norm(traj.positions[src] - traj.positions[m]))
        if b > 0:
            pd = matcher.pair(m, src)
            z = pd.depth[np.isfinite(pd.depth)]
            share = z.size / max(int(pd.valid.sum()), 1)
            if z.size >= 200:
                med_z = float(np.median(z))
                disp = f * b / med_z
                trials.append((o, b, disp, share))
                best = (med_z, b, disp)
                if disp >= target:
                    break
            else:
                trials.append((o, b, 0.0, share))
        o *= 2
    if best is None:
        raise OmniSfmError(
            "no stereo depth on the middle frame at any frame offset: the camera barely moves "
            "(not enough baseline for stereo) or the images have no texture")
    med_z = best[0]
    if best[2] < 2.0:
        raise OmniSfmError(
            f"not enough baseline for stereo: at the largest frame offset with depth the median "
            f"disparity is {best[2]:.2f} px (need the camera to move a few percent of the scene "
            "depth)")
    baseline = opts.parallax * med_z
    steps = np.linalg.norm(np.diff(traj.positions, axis=0), axis=1)
    per_frame = float(np.median(steps)) if steps.size else 0.0
    offset = max(1, round(baseline / per_frame)) if per_frame > 0 else 1
    return BaselineCalibration(m, med_z, baseline, int(offset), tuple(trials))


def _sources(traj: Trajectory, k: int, baseline: float) -> list[tuple[int, float]]:
    """Two source frames for keyframe ``k``: before and after it, baseline closest to
    ``baseline`` (at least half of it); one side missing: two from the other (B and 2B)."""
    dist = np.linalg.norm(traj.positions - traj.positions[k], axis=1)
    idx = np.arange(len(traj))
    picks: list[tuple[int, float]] = []
    for side in (idx < k, idx > k):
        cand = np.flatnonzero(side & (dist >= 0.5 * baseline))
        if cand.size:
            j = int(cand[np.argmin(np.abs(dist[cand] - baseline))])
            picks.append((j, float(dist[j])))
    if len(picks) == 1:
        j0 = picks[0][0]
        cand = np.flatnonzero((np.sign(idx - k) == np.sign(j0 - k)) & (idx != j0)
                              & (dist >= 0.5 * baseline))
        if cand.size:
            j = int(cand[np.argmin(np.abs(dist[cand] - 2 * baseline))])
            picks.append((j, float(dist[j])))
    return picks


def _floor_scale(points: FloatArray, traj: Trajectory, up_in_camera: FloatArray, height: float,
                 tolerance: float) -> ScaleReport:
    """Scale (``factor``) from the camera height: the floor is the largest plane (RANSAC,
    inliers within ``tolerance``) among the dense points below the cameras whose normal is
    within 20 deg of the cameras' mean up axis; a least-squares fit to its inliers gives the
    camera height."""
    o3d = open3d_module()
    up = normalize((traj.rotations @ up_in_camera).mean(axis=0))
    h = (points - traj.positions.mean(axis=0)) @ up
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[h < -2 * tolerance]))
    o3d.utility.random.seed(0)
    floor = None
    for _ in range(8):
        if len(pcd.points) < 100:
            break
        plane, inliers = pcd.segment_plane(distance_threshold=tolerance, ransac_n=3,
                                           num_iterations=1000)
        if abs(np.asarray(plane[:3]) @ up) > math.cos(math.radians(20.0)):
            floor = np.asarray(pcd.points)[inliers]
            break
        pcd = pcd.select_by_index(inliers, invert=True)
    if floor is None or len(floor) < 100:
        raise OmniSfmError("--camera-height: no floor (a horizontal plane below the cameras) "
                           "in the dense points")
    centre = floor.mean(axis=0)
    normal = np.linalg.svd(floor - centre, full_matrices=False)[2][2]
    if normal @ up < 0:
        normal = -normal
    tilt = float(np.degrees(np.arccos(np.clip(normal @ up, -1, 1))))
    h_cam = float(np.median((traj.positions - centre) @ normal))
    if not h_cam > 0:
        raise OmniSfmError("--camera-height: the floor found is not below the cameras")
    return ScaleReport(source="camera_height", unit="unit of --camera-height",
                       camera_height=height, floor_points=int(len(floor)), floor_tilt_deg=tilt,
                       camera_height_pose_units=h_cam, factor=height / h_cam)


def check_options(opts: DenseOptions) -> None:
    """OmniSfmError naming the option when ``opts`` cannot be honoured."""
    if opts.known_distance is not None and opts.camera_height is not None:
        raise OmniSfmError("give either known_distance or camera_height, not both")
    for name in ("known_distance", "camera_height"):
        val = getattr(opts, name)
        if val is not None and not val > 0:
            raise OmniSfmError(f"{name} must be > 0, got {val}")
    if opts.keyframe_step is not None and opts.keyframe_step < 1:
        raise OmniSfmError(f"keyframe_step must be >= 1, got {opts.keyframe_step}")
    if not opts.resolution_scale > 0:
        raise OmniSfmError(f"resolution_scale must be > 0, got {opts.resolution_scale}")


def _keyframe_depth(matchers: list[_Matcher], traj: Trajectory, k: int, baseline: float,
                    fusion: TsdfFusion, frame_rays: list[FloatArray], opts: DenseOptions
                    ) -> KeyframeStats | None:
    """Checked depth of keyframe ``k`` from its two stereo pairs in each lens (``matchers``,
    ``frame_rays`` each lens's), fused; None when fewer than two frames lie at the stereo
    baseline (``traj``: the poses, whose frames the lenses share)."""
    srcs = _sources(traj, k, baseline)
    if len(srcs) < 2:
        return None
    seconds = [0.0, 0.0]
    view_px = depth_px = 0
    has, poses = [], []
    for matcher, rays_cam in zip(matchers, frame_rays, strict=True):
        lens = matcher.lens.trajectory
        t1 = time.perf_counter()
        pa, pb = (matcher.pair(k, j) for j, _ in srcs)
        ok_a = consistent(pa.rig, pa.depth, pb.rig, pb.depth, opts.stereo)
        ok_b = consistent(pb.rig, pb.depth, pa.rig, pa.depth, opts.stereo)
        da = np.where(ok_a, pa.depth, np.nan)
        db = np.where(ok_b, pb.depth, np.nan)
        t2 = time.perf_counter()
        for pd, d in ((pa, da), (pb, db)):
            fusion.integrate_rig(pd.rig, d, pd.colors, lens.positions[k])
        seconds[0] += t2 - t1
        seconds[1] += time.perf_counter() - t2
        view_px += int(pa.valid.sum() + pb.valid.sum())
        depth_px += int(ok_a.sum() + ok_b.sum())
        rays = (lens.rotations[k] @ rays_cam.T).T
        has.append(np.isfinite(depth_along(pa.rig, da, rays)[0]) |
                   np.isfinite(depth_along(pb.rig, db, rays)[0]))
        poses += [pa.pose, pb.pose]
    return KeyframeStats(frame=k, sources=tuple(j for j, _ in srcs),
                         baselines=tuple(b for _, b in srcs),
                         depth_share=float(np.concatenate(has).mean()),
                         view_pixels=view_px, depth_pixels=depth_px,
                         seconds_depth=seconds[0], seconds_fusion=seconds[1],
                         pair_poses=tuple(poses))


def _output_scale(points: FloatArray, traj: Trajectory, cam: CameraModel, voxel: float,
                  opts: DenseOptions, metres_per_unit: float | None = None) -> ScaleReport:
    """Output units per pose unit (``factor``) and where they come from (``report.json``
    ``scale``): a known distance or the camera's height when given, else a rig's lens offsets
    (``metres_per_unit``), else the poses' own unit."""
    if opts.known_distance is not None:
        first_last = float(np.linalg.norm(traj.positions[-1] - traj.positions[0]))
        if not first_last > 0:
            raise OmniSfmError("known_distance: the first and last cameras coincide")
        return ScaleReport(source="known_distance", unit="unit of --known-distance",
                           first_last_pose_units=first_last, known_distance=opts.known_distance,
                           factor=opts.known_distance / first_last)
    if opts.camera_height is not None:
        up_cam = np.asarray(opts.up_in_camera if opts.up_in_camera is not None else
                            ((0.0, 0.0, 1.0) if cam.model == "hyperboloid" else (0.0, -1.0, 0.0)),
                            dtype=np.float64)
        return _floor_scale(points, traj, normalize(up_cam), opts.camera_height, voxel)
    if metres_per_unit is not None:
        return ScaleReport(source="rig", unit="metres (from the rig's lens offsets)",
                           factor=metres_per_unit)
    return ScaleReport(source="poses", unit="pose units (arbitrary scale of the input poses)",
                       factor=1.0)


def dense_map(inp: DenseInput, opts: DenseOptions | None = None, *,
              progress: bool = False) -> DenseResult:
    """Dense map of ``inp`` (see the module docstring); OmniSfmError for impossible input."""
    from tqdm import tqdm

    opts = opts or DenseOptions()
    check_options(opts)
    traj, cam = inp.trajectory, inp.camera
    lenses = _lenses(inp)
    # one view geometry for every lens: the finest lens's pixels
    geometry = max((view_geometry(lens.camera, resolution_scale=opts.resolution_scale,
                                  fov_along_deg=opts.fov_along_deg) for lens in lenses),
                   key=lambda g: g.focal)
    matchers = [_Matcher(inp, lens, geometry, _num_disparities(geometry, opts), opts.stereo,
                         opts.pair_pose) for lens in lenses]
    matcher = matchers[0]
    t0 = time.perf_counter()
    calib = calibrate_baseline(matcher, opts)
    t_calib = time.perf_counter() - t0
    step = opts.keyframe_step or max(1, calib.frame_offset // 2)
    voxel = opts.voxel_pixels * calib.median_depth / geometry.focal
    fusion = TsdfFusion(voxel, max_depth=opts.max_depth_ratio * calib.median_depth)
    stats: list[KeyframeStats] = []
    warnings: list[str] = []
    if inp.metres_per_unit is not None and not inp.metric:
        warnings.append("the rig's metric scale is a rough one (the lenses' baseline did not fix "
                        "it): the map is in the poses' unit")
    frame_rays = []
    for lens in lenses:  # every 4th pixel: enough for a share
        grid = lens.camera.pixel_grid_rays()[::2, ::2].reshape(-1, 3)
        frame_rays.append(grid[np.isfinite(grid[:, 0])])
    for k in tqdm(range(0, len(traj), step), desc="dense", unit="keyframe",
                  disable=None if progress else True, leave=False):
        st = _keyframe_depth(matchers, traj, k, calib.baseline, fusion, frame_rays, opts)
        if st is None:
            warnings.append(f"frame {k}: fewer than two frames with enough baseline, skipped")
        else:
            stats.append(st)
    if not stats:
        raise OmniSfmError("no keyframe had two frames with enough baseline for stereo")
    t4 = time.perf_counter()
    points, colors = fusion.point_cloud(opts.min_weight)
    mesh = fusion.mesh(opts.min_weight)
    t_extract = time.perf_counter() - t4
    if points.shape[0] < opts.min_points:
        raise OmniSfmError(f"stereo gave {points.shape[0]} surface points confirmed by enough "
                           "views: too little texture or baseline for stereo, or poses that do "
                           "not fit the images")
    scale_info = _output_scale(points, traj, cam, voxel, opts,
                               inp.metres_per_unit if inp.metric else None)
    scale = scale_info.factor
    points = points * scale
    mesh.scale(scale, center=np.zeros(3))
    out_traj = Trajectory(traj.timestamps.copy(), traj.rotations.copy(), traj.positions * scale)
    poor = [s.frame for s in stats if s.depth_share < 0.05]
    if poor:
        warnings.append(f"{len(poor)} keyframes got depth on under 5% of their valid pixels "
                        f"(texture-poor or little parallax): {poor[:10]}")
    report = _dense_report(inp, stats, calib, geometry, matcher, opts, scale, scale_info, voxel,
                           step, points, mesh, warnings, {"calibration": t_calib,
                                                          "extraction": t_extract})
    if inp.metres_per_unit is not None:  # the lens offsets in the output's unit
        report = replace(report, rig=RigScaleRecord(
            metres_per_unit=inp.metres_per_unit / scale,
            note="the input poses folder's, in this folder's unit", fixed=inp.metric))
    return DenseResult(points=points, colors=colors, mesh=mesh, trajectory=out_traj, scale=scale,
                       median_depth=calib.median_depth * scale, voxel_size=voxel * scale,
                       keyframes=tuple(stats), report=report)


def _dense_report(inp: DenseInput, stats: list[KeyframeStats], calib: BaselineCalibration,
                  geometry: ViewGeometry, matcher: _Matcher, opts: DenseOptions, scale: float,
                  scale_info: ScaleReport, voxel: float, step: int, points: FloatArray,
                  mesh: Any, warnings: list[str], seconds: dict[str, float]) -> DenseReport:
    """The ``report.json`` of a dense map (docs/dense.md), without ``input``."""
    traj = inp.trajectory
    shares = np.array([s.depth_share for s in stats])
    pposes = [p for s in stats for p in s.pair_poses]
    changes = [p.rotation_change_deg for p in pposes if p.corrected]
    return DenseReport(
        scale=scale_info,
        median_depth=calib.median_depth * scale,
        stereo_baseline=calib.baseline * scale,
        voxel_size=voxel * scale,
        calibration=CalibrationReport(
            frame=calib.frame, frame_offset=calib.frame_offset,
            trials=[CalibrationTrial(offset=o, baseline=b * scale, median_disparity_px=d,
                                     depth_share=s) for o, b, d, s in calib.trials]),
        views=ViewsReport(focal_px=geometry.focal, width=geometry.width, height=geometry.height,
                          per_pair=4, num_disparities=matcher.num_disparities),
        keyframe_step=step,
        pair_pose=PairPoseSummary(
            enabled=opts.pair_pose.enabled, pairs=len(pposes), corrected=len(changes),
            median_rotation_change_deg=float(np.median(changes)) if changes else None),
        num_keyframes=len(stats),
        num_points=int(points.shape[0]),
        num_triangles=int(len(mesh.triangles)),
        depth_share={"median": float(np.median(shares)), "min": float(shares.min()),
                     "max": float(shares.max())},
        seconds={"calibration": seconds["calibration"],
                 "depth_per_keyframe": float(np.median([s.seconds_depth for s in stats])),
                 "fusion_per_keyframe": float(np.median([s.seconds_fusion for s in stats])),
                 "depth_total": float(sum(s.seconds_depth for s in stats)),
                 "fusion_total": float(sum(s.seconds_fusion for s in stats)),
                 "extraction": seconds["extraction"]},
        frames=[DenseFrame(frame=s.frame, timestamp=float(traj.timestamps[s.frame]),
                           image=inp.image_names[s.frame], sources=list(s.sources),
                           baselines=[b * scale for b in s.baselines],
                           depth_share=s.depth_share, view_share=s.view_share,
                           view_pixels=s.view_pixels, depth_pixels=s.depth_pixels,
                           seconds_depth=s.seconds_depth, seconds_fusion=s.seconds_fusion,
                           pair_pose=[PairPoseCheck(corrected=p.corrected, inliers=p.inliers,
                                                    rotation_change_deg=p.rotation_change_deg,
                                                    direction_change_deg=p.direction_change_deg)
                                      for p in s.pair_poses]) for s in stats],
        warnings=warnings,
        backend=BackendReport(stereo="cv2.StereoSGBM (CPU)",
                              fusion="open3d VoxelBlockGrid (CPU)",
                              pycolmap_cuda=_pycolmap_has_cuda(),
                              note="pycolmap's patch_match_stereo needs CUDA; not used"),
        note="depth_share: share of the keyframe's valid pixels (camera mask) whose ray got "
             "a depth that passed SGBM, the texture test and the 3-view check; view_share: "
             "the same over the virtual views' pixels. Directions within (180 - "
             "fov_along) / 2 deg of the motion are not covered by the views",
    )


def _pycolmap_has_cuda() -> bool:
    try:
        import pycolmap
    except ImportError:
        return False
    return bool(getattr(pycolmap, "has_cuda", False))


def write_dense(output: Path, inp: DenseInput, res: DenseResult, *, overwrite: bool = False,
                poses_dir: Path | None = None) -> None:
    """Write ``dense.ply``, ``mesh.ply``, ``trajectory.tum`` (output units), ``camera.yaml``,
    ``lines3d.json`` (when the input had one), ``mask.png`` (carried from ``poses_dir``) and
    ``report.json`` with where the poses and frames came from (complete or not at all)."""
    o3d = open3d_module()
    output = Path(output)
    inputs = (poses_dir, inp.frames.path)
    report = replace(res.report, input=DenseInputRecord(
        poses=None if poses_dir is None else stored_path(poses_dir, output),
        images=stored_path(inp.frames.path, output)))
    with atomic_output_dir(output, overwrite=overwrite, inputs=inputs) as tmp:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(res.points))
        pcd.colors = o3d.utility.Vector3dVector(res.colors)
        if not o3d.io.write_point_cloud(str(tmp / DenseFolder.POINTS), pcd):
            raise OmniSfmError(f"{output}: Open3D could not write dense.ply")
        if not o3d.io.write_triangle_mesh(str(tmp / DenseFolder.MESH), res.mesh):
            raise OmniSfmError(f"{output}: Open3D could not write mesh.ply")
        write_tum(tmp / StageFolder.TRAJECTORY, res.trajectory)
        write_camera_yaml(tmp / DenseFolder.CAMERA, inp.camera)
        if inp.lines is not None:
            write_lines3d(tmp / DenseFolder.LINES3D, inp.lines.scaled(res.scale))
        if poses_dir is not None:
            carry_forward(poses_dir, tmp, (DenseFolder.MASK,))
        report.write(tmp / DenseFolder.REPORT)


def run_dense(poses_dir: Path, images: Path | None, output: Path,
              opts: DenseOptions | None = None, *, camera_file: Path | None = None,
              overwrite: bool = False, progress: bool = False) -> DenseResult:
    """Read, map and write (the ``omni-sfm dense`` command); ``images`` None: the frames the
    poses folder records."""
    check_output_dir(Path(output), overwrite=overwrite, inputs=(Path(poses_dir), images))
    inp = read_dense_input(poses_dir, images, camera_file)
    check_output_dir(Path(output), overwrite=overwrite, inputs=(inp.frames.path,))
    res = dense_map(inp, opts, progress=progress)
    write_dense(output, inp, res, overwrite=overwrite, poses_dir=Path(poses_dir))
    return res
