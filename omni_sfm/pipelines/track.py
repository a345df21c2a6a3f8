"""Frames in, poses out, one at a time with no look-ahead: ``omni-sfm track`` (docs/track.md).

:class:`Tracker` takes frames one at a time (:meth:`Tracker.add_frame`) and returns each
frame's :class:`~omni_sfm.estimate.online.TrackedPose` as soon as the frames so far give it;
the pose returned for frame ``k`` depends on frames ``0..k`` only. It wires the stages' own
pieces, nothing new: :class:`~omni_sfm.lines.extract.LineExtractor` on the frame, then
:class:`~omni_sfm.lines.track.LineTracker` (``record=False``: it keeps only the last few
frames) continues the tracks of the frames before, and the frame's lines go to
:class:`~omni_sfm.estimate.online.OnlineEstimator` (start, registration, local adjustment,
lost / rotation-only / relocalised).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from omni_sfm.cameras.base import CameraModel
from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.online import OnlineEstimator, OnlineOptions, TrackedPose
from omni_sfm.frames import to_gray
from omni_sfm.lines.extract import LineExtractor
from omni_sfm.lines.frontend import middle_rays
from omni_sfm.lines.track import LineTracker


class Tracker:
    """Frames in, poses out: the line front end and :class:`OnlineEstimator` (module
    docstring). ``camera``: the calibrated camera (frames are ``camera.width x
    camera.height``); ``mask``: ``(H, W)``, nonzero where pixels may be used."""

    def __init__(self, camera: CameraModel, options: OnlineOptions | None = None,
                 mask: np.ndarray | None = None) -> None:
        self.options = options or OnlineOptions()
        self.camera = camera
        self.extractor = LineExtractor(camera, self.options.extraction, mask)
        self.lines = LineTracker(self.options.tracking, record=False)
        self.estimator = OnlineEstimator(self.options)

    def add_frame(self, image: np.ndarray, timestamp: float | None = None) -> TrackedPose:
        """The pose of the next frame (grey, BGR or BGRA image), from it and the frames before
        only. ``latency_ms``: this call's wall-clock time."""
        t0 = time.perf_counter()
        gray = to_gray(image)
        if (gray.shape[1], gray.shape[0]) != (self.camera.width, self.camera.height):
            raise OmniSfmError(self.camera.frame_size_mismatch(gray.shape[1], gray.shape[0])
                               or f"frame is {gray.shape[1]}x{gray.shape[0]} px but the camera "
                               f"is {self.camera.width}x{self.camera.height} px")
        lines = self.extractor.extract(gray)
        ids = self.lines.add_frame(gray, lines)
        # pieces of one line in one frame (one track): the best supported observation
        order = np.lexsort((-np.asarray(lines.num_support), ids))
        first = np.ones(len(order), bool)
        first[1:] = ids[order][1:] != ids[order][:-1]
        keep = order[first]
        normals = np.asarray(lines.normals, np.float64).reshape(-1, 3)[keep]
        rays = middle_rays(np.asarray(lines.endpoint_rays).reshape(-1, 2, 3)[keep], normals)
        sig = np.asarray(lines.normal_sigma, np.float64).reshape(-1, 2)[keep]
        pose = self.estimator.add(ids[keep], normals, rays, sig, timestamp)
        return replace(pose, lines=int(lines.num_lines),
                       latency_ms=1000.0 * (time.perf_counter() - t0))
