"""The initializer contract: what a plugin of the ``omni_sfm.initializers`` group gets and
returns (docs/plugins.md).

An initializer is a callable ``(sequence: SequenceInput, options: Mapping[str, Any]) ->
InitializerResult`` (:class:`Initializer`), registered as an entry point
(:mod:`omni_sfm.registry`) and run by ``omni-sfm compare`` (:mod:`omni_sfm.compare`). It reports
a failure by returning :func:`failed` (or raising :class:`~omni_sfm.errors.OmniSfmError`);
:func:`check_result` turns anything else it returns into a recorded failure.
"""

from __future__ import annotations

import time
import traceback
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from omni_sfm import registry
from omni_sfm.cameras.base import CameraModel
from omni_sfm.errors import OmniSfmError
from omni_sfm.frames import FrameStore
from omni_sfm.geometry import FloatArray
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.poses import Trajectory

STATUSES = ("ok", "failed")
"""The values of :attr:`InitializerResult.status`."""


@dataclass(frozen=True)
class PointObservations:
    """Point feature tracks of a sequence, as pixels and unit rays.

    Attributes:
        obs_track: ``(K,)`` int track id of each observation.
        obs_frame: ``(K,)`` int frame index (0..F-1) of each observation.
        obs_uv: ``(K, 2)`` pixel of each observation (OpenCV convention), in the image of
            :attr:`SequenceInput.camera`.
        obs_ray: ``(K, 3)`` unit ray of each observation in the camera frame.
    """

    obs_track: np.ndarray
    obs_frame: np.ndarray
    obs_uv: FloatArray
    obs_ray: FloatArray

    def __post_init__(self) -> None:
        k = self.obs_track.shape[0]
        if self.obs_frame.shape != (k,) or self.obs_uv.shape != (k, 2) or \
                self.obs_ray.shape != (k, 3):
            raise ValueError(f"inconsistent point observations: {self.obs_track.shape=} "
                             f"{self.obs_frame.shape=} {self.obs_uv.shape=} "
                             f"{self.obs_ray.shape=}")

    @property
    def num_observations(self) -> int:
        return int(self.obs_track.shape[0])


@dataclass(frozen=True)
class SequenceInput:
    """What an initializer gets: the frames of one sequence and its camera.

    Either ``images`` (real or rendered frames: every initializer extracts its own features)
    or precomputed observations (a simulation: ``line_tracks`` and/or ``points``), or both.

    Attributes:
        timestamps: ``(F,)`` timestamp of each frame (frame index for an image folder), the
            timestamps the trajectories are written with.
        camera: the calibrated camera model of every frame.
        images: the ``F`` frames (an image folder or a video, in frame order), or None.
        line_tracks: line observations (unit normals) of the ``F`` frames, or None.
        points: point observations (pixels and rays) of the ``F`` frames, or None.
        name: a label for reports.
    """

    timestamps: FloatArray
    camera: CameraModel
    images: FrameStore | None = None
    line_tracks: LineTracks | None = None
    points: PointObservations | None = None
    name: str = "sequence"

    def __post_init__(self) -> None:
        f = self.timestamps.shape[0]
        if self.timestamps.shape != (f,) or f < 3:
            raise OmniSfmError(f"a sequence needs at least 3 frames, got {self.timestamps.shape}")
        if self.images is not None and len(self.images) != f:
            raise ValueError(f"{len(self.images)} images for {f} timestamps")
        if self.line_tracks is not None and self.line_tracks.num_frames != f:
            raise ValueError(f"line tracks have {self.line_tracks.num_frames} frames, not {f}")
        if self.images is None and self.line_tracks is None and self.points is None:
            raise ValueError("a sequence needs images or precomputed observations")

    @property
    def num_frames(self) -> int:
        return int(self.timestamps.shape[0])

    def read_image(self, k: int, *, gray: bool = False) -> np.ndarray:
        """Frame ``k`` as OpenCV reads it (BGR uint8, or ``(H, W)`` uint8 grey with ``gray``,
        converted as the front end does), checked against the camera size."""
        if self.images is None:
            raise OmniSfmError(f"{self.name}: this sequence has no images")
        name = self.images.names[k]
        img = self.images.read(name, gray=gray)
        if img.shape[:2] != (self.camera.height, self.camera.width):
            said = self.camera.frame_size_mismatch(img.shape[1], img.shape[0])
            raise OmniSfmError(f"{self.images.where(name)}: " + (
                said or f"image is {img.shape[1]}x{img.shape[0]} px, the camera is "
                f"{self.camera.width}x{self.camera.height} px"))
        return img

    def read_gray(self, k: int) -> np.ndarray:
        """Frame ``k`` as an ``(H, W)`` uint8 grey image, as ``init``'s front end reads it."""
        return self.read_image(k, gray=True)


@dataclass(frozen=True)
class InitializerResult:
    """What an initializer returns.

    Attributes:
        trajectory: world_from_cam of the frames it registered (timestamps of the sequence),
            any world and scale; None when it failed before registering anything.
        status: ``"ok"`` or ``"failed"``.
        reason: why it failed (one line), or a note; empty when there is nothing to say.
        reflection_ambiguous: True when the data determine the positions only up to the point
            reflection through the first camera (line normals alone, docs/method.md §6); the
            comparison then evaluates the branch nearer the ground truth and says so.
        info: JSON-ready details (counts, options used).
    """

    trajectory: Trajectory | None
    status: str = "ok"
    reason: str = ""
    reflection_ambiguous: bool = False
    info: dict[str, Any] = field(default_factory=dict)


def failed(reason: str, **info: Any) -> InitializerResult:
    """An :class:`InitializerResult` for a failure."""
    return InitializerResult(None, "failed", reason, info=dict(info))


class Initializer(Protocol):
    """The plugin interface of the ``omni_sfm.initializers`` entry-point group."""

    def __call__(self, sequence: SequenceInput,
                 options: Mapping[str, Any]) -> InitializerResult: ...


def result_problem(res: object) -> str | None:
    """Why ``res`` breaks the contract of :class:`InitializerResult` (one line), or None."""
    if not isinstance(res, InitializerResult):
        return f"returned {type(res).__module__}.{type(res).__qualname__}, not an " \
               "InitializerResult"
    if res.trajectory is not None and not isinstance(res.trajectory, Trajectory):
        return f"returned a trajectory of type {type(res.trajectory).__qualname__}, not a " \
               "Trajectory or None"
    if res.status not in STATUSES:
        return f"returned status {res.status!r}, not one of {', '.join(map(repr, STATUSES))}"
    if not isinstance(res.reason, str):
        return f"returned a reason of type {type(res.reason).__qualname__}, not a str"
    if not isinstance(res.info, dict):
        return f"returned info of type {type(res.info).__qualname__}, not a dict"
    return None


def check_result(res: object) -> InitializerResult:
    """``res`` when it keeps the contract, else a failed result that says what is wrong."""
    problem = result_problem(res)
    if problem is not None:
        return failed(f"broken plugin: {problem}")
    assert isinstance(res, InitializerResult)
    return res


def sequence_from_frames(images: Path, camera: CameraModel) -> SequenceInput:
    """Every frame of an image folder (sorted by name; timestamp = index) or a video
    (timestamps in seconds), named and stamped as ``init`` names them. One-line OmniSfmError
    when there are fewer than 3 frames or the first does not have the camera's size."""
    frames = FrameStore(images)
    if len(frames) < 3:
        raise OmniSfmError(f"{images}: {len(frames)} frames; need at least 3")
    path = Path(images)
    name = path.resolve().parent.name if path.name == "images" else path.stem
    seq = SequenceInput(frames.timestamps.copy(), camera, images=frames, name=name)
    seq.read_image(0)  # a camera for other images fails here, before any initializer runs
    return seq


def run_initializer(name: str, sequence: SequenceInput,
                    options: Mapping[str, Any] | None = None) -> tuple[InitializerResult, float]:
    """Run one initializer; any exception becomes a failed result with its one-line reason,
    and so does a plugin that cannot be loaded or returns what breaks the contract
    (:func:`omni_sfm.plugin_contract.check_result`).

    Returns the result and the wall time in seconds.

    Raises:
        OmniSfmError: no initializer ``name`` is installed.
    """
    try:
        fn: Initializer = registry.load(registry.INITIALIZERS, name)
    except registry.PluginError as exc:
        return failed(str(exc)), 0.0
    t0 = time.perf_counter()
    try:
        res = check_result(fn(sequence, dict(options or {})))
    except OmniSfmError as exc:
        res = failed(str(exc))
    except Exception as exc:  # a crash of one initializer must not lose the others' results
        tb = traceback.extract_tb(exc.__traceback__)
        where = f" ({Path(tb[-1].filename).name}:{tb[-1].lineno})" if tb else ""
        res = failed(f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
                     f"{where}")
    return res, time.perf_counter() - t0
