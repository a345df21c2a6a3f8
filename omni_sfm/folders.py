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
every file of a folder is named in one place. An init folder is read back by
:meth:`InitFolder.load`. docs/formats.md describes the files.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import read_json, resolve_stored

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


TRAJECTORY_FILE = StageFolder.TRAJECTORY
REPORT_FILE = StageFolder.REPORT
"""The estimator's names for :class:`StageFolder`'s ``TRAJECTORY`` and ``REPORT``."""

CARRIED_FILES = (StageFolder.CAMERA, StageFolder.MASK, StageFolder.LINES3D)
"""Files a stage copies from its input folder when it does not write its own."""


def recorded_images(folder: Path | str) -> Path | None:
    """The image folder or video that ``folder`` (an init, refine or dense output) was made
    from, as recorded in its ``report.json``, or None when it records none."""
    folder = Path(folder)
    report = folder / StageFolder.REPORT
    if not report.is_file():
        return None
    doc = read_json(report, "report")
    inp = doc.get("input") if isinstance(doc, dict) else None
    images = inp.get("images") if isinstance(inp, dict) else None
    return resolve_stored(images, folder) if isinstance(images, str) and images else None


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


def pose_frame_names(folder: Path | str, traj: Trajectory, frames: FrameStore) -> list[str]:
    """The name in ``frames`` of the frame of every pose of ``traj`` (``folder``'s poses), in
    trajectory order; a one-line OmniSfmError when they cannot be matched or some are missing.

    Frames are found by the folder's ``colmap.json`` image names when present, else (video) by
    the timestamps in seconds ``init`` gives video frames, else by names equal to the integer
    timestamps (``000012.png`` for timestamp 12), else in order when the source holds exactly
    one frame per pose."""
    names = list(frames.names)
    manifest = Path(folder) / InitFolder.MANIFEST
    chosen: list[str] | None = None
    if manifest.is_file():
        m = read_json(manifest, "colmap manifest")
        listed = m.get("image_names") if isinstance(m, dict) else None
        if isinstance(listed, list) and len(listed) == len(traj):
            chosen = [str(n) for n in listed]
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
        mask = self / self.MASK
        return InitArtifacts(self, camera, trajectory, self.read_lines3d(),
                             recorded_images(self.path), mask if mask.is_file() else None)


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


@dataclass(frozen=True)
class RefineFolder(StageFolder):
    """``omni-sfm refine`` output (docs/colmap.md)."""

    DATABASE: ClassVar[str] = "database.db"
    SPARSE: ClassVar[str] = InitFolder.SPARSE
    COLMAP_IMAGES: ClassVar[str] = InitFolder.COLMAP_IMAGES
    COLMAP_MASK: ClassVar[str] = InitFolder.COLMAP_MASK


@dataclass(frozen=True)
class DenseFolder(StageFolder):
    """``omni-sfm dense`` output, and ``omni-sfm view``'s files beside it (docs/dense.md)."""

    POINTS: ClassVar[str] = "dense.ply"
    MESH: ClassVar[str] = "mesh.ply"
    VIEW_PNG: ClassVar[str] = "view.png"


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
