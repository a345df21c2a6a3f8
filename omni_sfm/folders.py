"""The output folders of the stages, one owner class each, so the stages chain: ``init`` ->
``refine`` -> ``dense`` -> ``view``, and ``compare`` beside them.

Each folder holds the poses (``trajectory.tum``) and carries forward what a later stage needs
without being told again: the camera (``camera.yaml``), the user's mask (``mask.png``, when one
was given), the estimated 3D lines (``lines3d.json``) and where the frames are (the image folder
or video, recorded in ``report.json`` under ``input.images``). Paths are recorded so that the
folder can be moved (:func:`omni_sfm.fileio.stored_path`): relative to the folder when inside
it, absolute otherwise. A stage reads its input folder with :func:`recorded_images` and copies
the carried files with :func:`carry_forward`.

Each folder kind has one class that knows its file names (:class:`StageFolder` the files every
stage folder has; :class:`InitFolder`, :class:`RefineFolder`, :class:`DenseFolder`,
:class:`CompareFolder`, :class:`RenderFolder`); the stages write and read through them, so
every file of a folder is named in one place. A folder is read back by its loader
(:meth:`InitFolder.load`, :meth:`RefineFolder.load`, :meth:`DenseFolder.load`), its
``report.json`` by ``read_report`` as the typed report of :mod:`omni_sfm.reports` (any stage
folder's, for where its frames are: :meth:`StageFolder.read_stage_report`). docs/formats.md
describes the files.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import read_json
from omni_sfm.reports import (
    CompareResults,
    DenseReport,
    ExportReport,
    InitReport,
    RefineReport,
    StageReport,
    TrackFrame,
    read_track_frames,
)

if TYPE_CHECKING:
    from omni_sfm.cameras import CameraModel
    from omni_sfm.frames import FrameStore
    from omni_sfm.lines.tracks import LineTracks
    from omni_sfm.lines3d import LineSegments3D
    from omni_sfm.poses import Trajectory


@dataclass(frozen=True)
class StageFolder:
    """What every stage folder holds: poses, camera, report, and what is carried forward."""

    path: Path
    TRAJECTORY: ClassVar[str] = "trajectory.tum"
    CAMERA: ClassVar[str] = "camera.yaml"
    LINES3D: ClassVar[str] = "lines3d.json"
    MASK: ClassVar[str] = "mask.png"
    REPORT: ClassVar[str] = "report.json"

    def __truediv__(self, name: str) -> Path:
        return Path(self.path) / name

    def read_trajectory(self) -> Trajectory:
        """``trajectory.tum``: world_from_cam of every posed frame (one-line error if absent)."""
        from omni_sfm.poses import read_tum

        return read_tum(self / self.TRAJECTORY)

    def read_camera(self) -> CameraModel:
        """``camera.yaml``: the camera the poses refer to."""
        from omni_sfm.cameras import load_camera

        return load_camera(self / self.CAMERA)

    def read_lines3d(self) -> LineSegments3D | None:
        """``lines3d.json``, or None when the folder has none."""
        from omni_sfm.lines3d import read_lines3d

        return read_lines3d(self / self.LINES3D) if (self / self.LINES3D).is_file() else None

    def read_stage_report(self) -> StageReport | None:
        """``report.json`` read for what any stage's records (where the frames and the input
        folder are, the parallel family), or None when the folder has none."""
        path = self / self.REPORT
        return StageReport.read(path) if path.is_file() else None

    def user_mask(self) -> Path | None:
        """``mask.png``: the user's mask, or None when none was given."""
        mask = self / self.MASK
        return mask if mask.is_file() else None

    def load_stage(self, camera: bool = True) -> StageArtifacts:
        """Any stage folder (init, refine or dense) read for what they all hold: the poses (a
        one-line error if missing or malformed), and where the folder has them the camera
        (unless ``camera`` is False: the caller has its own), the 3D lines, the recorded
        frames, the user's mask and the report. The readers that take any stage folder
        (dense, view, export) go through here; a folder of one kind is read by its
        ``load``."""
        trajectory = self.read_trajectory()
        has_camera = camera and (self / self.CAMERA).is_file()
        report = self.read_stage_report()
        return StageArtifacts(self, trajectory, self.read_camera() if has_camera else None,
                              self.read_lines3d(),
                              None if report is None else report.images(self.path),
                              self.user_mask(), report)


@dataclass(frozen=True)
class StageArtifacts:
    """Any stage folder read back (:meth:`StageFolder.load_stage`)."""

    folder: StageFolder
    trajectory: Trajectory
    """``trajectory.tum``: world_from_cam of every posed frame."""
    camera: CameraModel | None
    """``camera.yaml``, or None when the folder has none (or it was not asked for)."""
    lines3d: LineSegments3D | None
    """``lines3d.json``, or None when the folder has none."""
    images: Path | None
    """The image folder or video recorded in ``report.json`` (``input.images``), or None."""
    user_mask: Path | None
    """``mask.png``, or None."""
    report: StageReport | None
    """``report.json`` read for what every stage's records, or None when absent."""


TRAJECTORY_FILE = StageFolder.TRAJECTORY
REPORT_FILE = StageFolder.REPORT
"""The estimator's names for :class:`StageFolder`'s ``TRAJECTORY`` and ``REPORT``."""

CARRIED_FILES = (StageFolder.CAMERA, StageFolder.MASK, StageFolder.LINES3D)
"""Files a stage copies from its input folder when it does not write its own."""


def recorded_images(folder: Path | str) -> Path | None:
    """The image folder or video that ``folder`` (an init, refine or dense output) was made
    from, as recorded in its ``report.json``, or None when it records none."""
    report = StageFolder(Path(folder)).read_stage_report()
    return None if report is None else report.images(folder)


def images_for(folder: Path | str, images: Path | str | None) -> Path:
    """``images`` if given, else the frames ``folder`` records (one-line error if neither)."""
    if images is not None:
        return Path(images)
    found = recorded_images(folder)
    if found is None:
        raise OmniSfmError(f"{folder}: the folder does not record its frames (give --images "
                           "PATH, the image folder or video it was made from)")
    if not found.exists():
        raise OmniSfmError(f"{found}: the frames recorded in "
                           f"{Path(folder) / StageFolder.REPORT} are gone (give --images PATH)")
    return found


def carry_forward(src: Path | str, dst: Path | str, names: tuple[str, ...] = CARRIED_FILES
                  ) -> list[str]:
    """Copy those of ``names`` that ``src`` has and ``dst`` does not into ``dst``; returns the
    names copied."""
    src, dst = Path(src), Path(dst)
    copied = []
    for name in names:
        if (src / name).is_file() and not (dst / name).exists():
            shutil.copyfile(src / name, dst / name)
            copied.append(name)
    return copied


def _by_video_time(frames: FrameStore, ts: np.ndarray) -> list[str] | None:
    """The video frames whose times (seconds, as ``init`` stamps video frames) are nearest to
    the pose timestamps ``ts``, if each lies within a quarter of a frame interval; else None."""
    t = frames.timestamps
    if len(t) < 2:
        return None
    k = np.clip(np.searchsorted(t, ts), 1, len(t) - 1)
    k -= (ts - t[k - 1]) < (t[k] - ts)
    if not np.all(np.abs(t[k] - ts) < 0.25 * float(np.diff(t).min())):
        return None
    return [frames.names[int(i)] for i in k]


def read_manifest_names(folder: Path | str) -> list[str] | None:
    """``image_names`` of ``folder``'s ``colmap.json`` (the COLMAP model's manifest: the image
    of every pose, in trajectory order), or None when the folder has none."""
    manifest = Path(folder) / InitFolder.MANIFEST
    if not manifest.is_file():
        return None
    m = read_json(manifest, "colmap manifest")
    listed = m.get("image_names") if isinstance(m, dict) else None
    return [str(n) for n in listed] if isinstance(listed, list) else []


def manifest_names(folder: Path | str, num_poses: int) -> list[str] | None:
    """:func:`read_manifest_names` when it names ``num_poses`` images, else None."""
    listed = read_manifest_names(folder)
    return listed if listed is not None and len(listed) == num_poses else None


def pose_frame_names(folder: Path | str, traj: Trajectory, frames: FrameStore) -> list[str]:
    """The name in ``frames`` of the frame of every pose of ``traj`` (``folder``'s poses), in
    trajectory order; a one-line OmniSfmError when they cannot be matched or some are missing.

    Frames are found by the folder's ``colmap.json`` image names when present, else (video) by
    the timestamps in seconds ``init`` gives video frames, else by names equal to the integer
    timestamps (``000012.png`` for timestamp 12), else in order when the source holds exactly
    one frame per pose."""
    names = list(frames.names)
    chosen = manifest_names(folder, len(traj))
    if chosen is None:
        by_stem: dict[int, str] = {}
        for n in names:
            stem = Path(n).stem
            if stem.isdigit():
                by_stem.setdefault(int(stem), n)
        ts = traj.timestamps
        chosen = _by_video_time(frames, ts) if frames.is_video else None
        if chosen is None and np.all(ts == np.round(ts)) and all(int(t) in by_stem for t in ts):
            chosen = [by_stem[int(t)] for t in ts]
        if chosen is None and len(names) == len(traj):
            chosen = names
        if chosen is None:
            raise OmniSfmError(
                f"{frames.path}: cannot match {len(names)} frames to the {len(traj)} poses of "
                f"{Path(folder) / TRAJECTORY_FILE} (need frame names equal to the timestamps, "
                "colmap.json names, or one frame per pose)")
    have = set(names)
    missing = [n for n in chosen if n not in have]
    if missing:
        raise OmniSfmError(f"{frames.path}: {len(missing)} of {len(chosen)} frames are missing "
                           f"(first: {missing[0]!r})")
    return chosen


@dataclass(frozen=True)
class InitFolder(StageFolder):
    """``omni-sfm init`` output (docs/formats.md, docs/colmap.md)."""

    TRACKS: ClassVar[str] = "tracks.json"
    UNCERTAIN_TRAJECTORY: ClassVar[str] = "trajectory_uncertain.tum"
    """The poses of the frames the data do not fix (``report.json`` ``frames_uncertain``),
    kept out of ``trajectory.tum`` unless ``init --keep-uncertain``."""
    TRAJECTORY_PLOT: ClassVar[str] = "trajectory.png"
    DEBUG_FRAMES: ClassVar[str] = "debug"
    DEBUG_VIDEO: ClassVar[str] = "debug.mp4"
    SPARSE: ClassVar[str] = "sparse"
    COLMAP_IMAGES: ClassVar[str] = "images_colmap"
    COLMAP_MASK: ClassVar[str] = "camera_mask.png"
    MANIFEST: ClassVar[str] = "colmap.json"

    def load(self) -> InitArtifacts:
        """The folder's artifacts, typed: the camera and the poses (a one-line error if either
        is missing or malformed), the 3D lines, the recorded frames and the user's mask where
        the folder has them; the line tracks on demand (:meth:`InitArtifacts.read_tracks`).
        Every reader of an init folder goes through here."""
        camera = self.read_camera()
        trajectory = self.read_trajectory()
        return InitArtifacts(self, camera, trajectory, self.read_lines3d(),
                             recorded_images(self.path), self.user_mask())

    def read_report(self) -> InitReport:
        """``report.json``, typed (a one-line error if missing or malformed)."""
        return InitReport.read(self / self.REPORT)



UNCERTAIN_FILE = InitFolder.UNCERTAIN_TRAJECTORY
"""The estimator's name for :class:`InitFolder`'s ``UNCERTAIN_TRAJECTORY``."""


@dataclass(frozen=True)
class InitArtifacts:
    """An init folder read back (:meth:`InitFolder.load`)."""

    folder: InitFolder
    camera: CameraModel
    """``camera.yaml``: the camera the poses refer to."""
    trajectory: Trajectory
    """``trajectory.tum``: world_from_cam of every posed frame."""
    lines3d: LineSegments3D | None
    """``lines3d.json``: the estimated 3D line segments, or None when the folder has none."""
    images: Path | None
    """The image folder or video the folder was made from (``report.json`` ``input.images``),
    or None when it records none."""
    user_mask: Path | None
    """``mask.png``: the user's mask, or None when none was given."""

    def read_tracks(self) -> LineTracks | None:
        """``tracks.json``: the line tracks with a ray per observation, or None when the
        folder has none (read on demand: a long video's tracks are large)."""
        from omni_sfm.lines.tracks import read_tracks

        path = self.folder / self.folder.TRACKS
        return read_tracks(path) if path.is_file() else None

    def read_report(self) -> InitReport | None:
        """``report.json``, typed, or None when the folder has none."""
        path = self.folder / self.folder.REPORT
        return InitReport.read(path) if path.is_file() else None

    def uncertain_rows(self) -> np.ndarray:
        """``(N,)`` bool over ``trajectory.tum``'s poses: those of frames ``report.json`` lists
        as not fixed by the data (``frames_uncertain``) and that ``trajectory.tum`` holds all
        the same (``init`` writes them there where the data fix fewer than 3 frames, or with
        ``--keep-uncertain``). All False without such a report (a plugin's folder has none).
        The poses are those of the frames not in ``frames_not_estimated``, in frame order; a
        one-line OmniSfmError when the report does not fit ``trajectory.tum``."""
        n = len(self.trajectory)
        report = self.read_report()
        if report is None or not report.frames_uncertain or report.uncertain_poses:
            return np.zeros(n, bool)
        missing = set(report.frames_not_estimated or ())
        posed = [k for k in range(report.num_frames) if k not in missing]
        if len(posed) != n:
            raise OmniSfmError(f"{self.folder / self.folder.REPORT}: {len(posed)} frames "
                               f"estimated but {self.folder / self.folder.TRAJECTORY} holds "
                               f"{n} poses")
        return np.isin(posed, [int(k) for k in report.frames_uncertain])


@dataclass(frozen=True)
class RefineFolder(StageFolder):
    """``omni-sfm refine`` output (docs/colmap.md)."""

    DATABASE: ClassVar[str] = "database.db"
    SPARSE: ClassVar[str] = InitFolder.SPARSE
    COLMAP_IMAGES: ClassVar[str] = InitFolder.COLMAP_IMAGES
    COLMAP_MASK: ClassVar[str] = InitFolder.COLMAP_MASK

    def read_report(self) -> RefineReport:
        """``report.json``, typed (a one-line error if missing or malformed)."""
        return RefineReport.read(self / self.REPORT)

    def load(self) -> RefineArtifacts:
        """The folder's artifacts, typed: the camera, the poses and the report (a one-line
        error if any is missing or malformed), the 3D lines, the recorded frames and the
        user's mask where the folder has them. Every reader of a refine folder as such goes
        through here."""
        camera = self.read_camera()
        trajectory = self.read_trajectory()
        report = self.read_report()
        return RefineArtifacts(self, camera, trajectory, self.read_lines3d(),
                               report.images(self.path), self.user_mask(), report)


@dataclass(frozen=True)
class RefineArtifacts:
    """A refine folder read back (:meth:`RefineFolder.load`)."""

    folder: RefineFolder
    camera: CameraModel
    """``camera.yaml`` (carried from the init folder)."""
    trajectory: Trajectory
    """``trajectory.tum``: the refined poses, in the init's world and scale."""
    lines3d: LineSegments3D | None
    """``lines3d.json``: adjusted with the points, or carried from the init; None if absent."""
    images: Path | None
    """The frames the folder was made from (``report.json`` ``input.images``)."""
    user_mask: Path | None
    """``mask.png`` (carried from the init), or None."""
    report: RefineReport
    """``report.json``."""

    @property
    def sparse(self) -> Path:
        """``sparse/``: the COLMAP model."""
        return self.folder / self.folder.SPARSE


@dataclass(frozen=True)
class DenseFolder(StageFolder):
    """``omni-sfm dense`` output, and ``omni-sfm view``'s files beside it (docs/dense.md)."""

    POINTS: ClassVar[str] = "dense.ply"
    MESH: ClassVar[str] = "mesh.ply"
    VIEW_PNG: ClassVar[str] = "view.png"

    def read_report(self) -> DenseReport:
        """``report.json``, typed (a one-line error if missing or malformed)."""
        return DenseReport.read(self / self.REPORT)

    def load(self) -> DenseArtifacts:
        """The folder's artifacts, typed: the camera, the poses (output units) and the report
        (a one-line error if any is missing or malformed), the 3D lines, the recorded frames,
        the user's mask and the point cloud and mesh files where the folder has them. Every
        reader of a dense folder as such goes through here."""
        camera = self.read_camera()
        trajectory = self.read_trajectory()
        report = self.read_report()
        points, mesh = self / self.POINTS, self / self.MESH
        return DenseArtifacts(self, camera, trajectory, self.read_lines3d(),
                              report.images(self.path), self.user_mask(), report,
                              points if points.is_file() else None,
                              mesh if mesh.is_file() else None)


@dataclass(frozen=True)
class DenseArtifacts:
    """A dense folder read back (:meth:`DenseFolder.load`)."""

    folder: DenseFolder
    camera: CameraModel
    """``camera.yaml``."""
    trajectory: Trajectory
    """``trajectory.tum``: the poses in the output unit (``report.scale``)."""
    lines3d: LineSegments3D | None
    """``lines3d.json`` in the output unit, or None when the input had none."""
    images: Path | None
    """The frames the map was made from (``report.json`` ``input.images``)."""
    user_mask: Path | None
    """``mask.png`` (carried), or None."""
    report: DenseReport
    """``report.json``."""
    points: Path | None
    """``dense.ply`` (``open3d.io.read_point_cloud``), or None when absent."""
    mesh: Path | None
    """``mesh.ply`` (``open3d.io.read_triangle_mesh``), or None when absent."""


@dataclass(frozen=True)
class TrackFolder:
    """``omni-sfm track`` output, written as the poses come (docs/track.md): the first start's
    poses in ``trajectory.tum``, each restart's in its own segment file, a line per frame in
    ``frames.jsonl``."""

    path: Path
    TRAJECTORY: ClassVar[str] = StageFolder.TRAJECTORY
    FRAMES: ClassVar[str] = "frames.jsonl"

    def __truediv__(self, name: str) -> Path:
        return Path(self.path) / name

    def read_frames(self) -> list[TrackFrame]:
        """``frames.jsonl``, a typed record per frame (one-line error if malformed)."""
        return read_track_frames(self / self.FRAMES)


@dataclass(frozen=True)
class ExportFolder:
    """``omni-sfm export`` output (docs/formats.md, "Exports"); which files a format writes:
    :mod:`omni_sfm.export.pipeline`."""

    path: Path
    REPORT: ClassVar[str] = StageFolder.REPORT
    TRAJECTORY: ClassVar[str] = StageFolder.TRAJECTORY
    CAMERA: ClassVar[str] = StageFolder.CAMERA
    SPARSE: ClassVar[str] = InitFolder.SPARSE
    COLMAP_MASK: ClassVar[str] = InitFolder.COLMAP_MASK
    IMAGES: ClassVar[str] = "images"
    MASKS: ClassVar[str] = "masks"
    POINTS: ClassVar[str] = "sparse_pc.ply"
    KITTI_POSES: ClassVar[str] = "poses.txt"
    KITTI_TIMES: ClassVar[str] = "times.txt"
    TRANSFORMS: ClassVar[str] = "transforms.json"
    LIMAP_TRACKS: ClassVar[str] = "finaltracks"
    LIMAP_ALLTRACKS: ClassVar[str] = "alltracks.txt"
    LIMAP_FAMILIES: ClassVar[str] = "line_families.json"

    def __truediv__(self, name: str) -> Path:
        return Path(self.path) / name

    def read_report(self) -> ExportReport:
        """``report.json``, typed (a one-line error if missing or malformed)."""
        return ExportReport.read(self / self.REPORT)


@dataclass(frozen=True)
class CompareFolder:
    """``omni-sfm compare`` output (docs/comparison.md)."""

    path: Path
    RESULTS: ClassVar[str] = "results.json"
    REPORT_MD: ClassVar[str] = "report.md"
    TRAJECTORIES: ClassVar[str] = "trajectories"
    TRAJECTORIES_PLOT: ClassVar[str] = "trajectories.png"
    ERRORS_PLOT: ClassVar[str] = "errors.png"

    def __truediv__(self, name: str) -> Path:
        return Path(self.path) / name

    def read_results(self) -> CompareResults:
        """``results.json``, typed (a one-line error if missing or malformed)."""
        return CompareResults.read(self / self.RESULTS)

    @classmethod
    def trajectory(cls, initializer: str) -> str:
        """Where an initializer's poses go, relative to the folder."""
        return f"{cls.TRAJECTORIES}/{initializer}.tum"


@dataclass(frozen=True)
class RenderFolder:
    """``omni-sfm render`` output: a sequence with exact ground truth (docs/rendering.md)."""

    path: Path
    IMAGES: ClassVar[str] = "images"
    VIDEO: ClassVar[str] = "video.mp4"
    CAMERA: ClassVar[str] = StageFolder.CAMERA
    GROUNDTRUTH: ClassVar[str] = "groundtruth.tum"
    SCENE: ClassVar[str] = "scene.ply"
    LINES3D: ClassVar[str] = StageFolder.LINES3D
    META: ClassVar[str] = "render.json"

    def __truediv__(self, name: str) -> Path:
        return Path(self.path) / name


@dataclass(frozen=True)
class SimulationFolder:
    """``omni-sfm simulate`` output: simulated line tracks with ground truth (docs/formats.md)."""

    path: Path
    TRACKS: ClassVar[str] = InitFolder.TRACKS
    GROUNDTRUTH: ClassVar[str] = RenderFolder.GROUNDTRUTH
    LINES: ClassVar[str] = "lines.json"

    def __truediv__(self, name: str) -> Path:
        return Path(self.path) / name
