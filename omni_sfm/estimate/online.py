"""Online poses from line observations, frame by frame, with no look-ahead: the estimator
under ``omni-sfm track`` (docs/track.md; frames in: :class:`omni_sfm.pipelines.track.Tracker`).

:class:`OnlineEstimator` takes one frame's line observations at a time (track ids, normals,
rays: :meth:`OnlineEstimator.add`) and returns the frame's :class:`TrackedPose` as soon as the
frames so far give it; the pose returned for frame ``k`` depends on frames ``0..k`` only. It
wires the estimator's own pieces, nothing new:

1. **Start.** The first frames are buffered (status ``initialising``, no pose) until the
   offline estimator (:func:`~omni_sfm.estimate.pipeline.estimate_poses`: the paper's method
   where one window covers the buffered frames, else the global estimator) solves the buffered
   frames and poses the newest of them: the first try after ``start_frames`` frames, again
   every ``start_retry`` frames, the oldest frames dropped beyond ``max_start_frames``; a start
   is taken once its lines' planes turn by ``min_start_parallax_deg`` across the buffered
   frames (or the buffer is full): its
   baseline fixes the scale that the tracking carries on. The frame where the start succeeds
   gets its pose (status ``tracking``) and, in :attr:`TrackedPose.start_poses`, the poses of
   the buffered frames that the start solved (computed from the frames up to this one).
   **World directions.** The start's parallel families (vanishing directions) become fixed
   world directions, each from every view of its members (their planes, with the start's
   rotations); the start's rotations are then turned by the correction (a constant and a turn
   growing with the frame index) that best puts each frame's lines of a family on their
   directions, the world turned onto the first frame's, and the start's positions and lines
   adjusted to those rotations, held.
2. **Tracking.** Each later frame is registered from the 3D lines already triangulated that it
   sees (:meth:`omni_sfm.estimate.incremental.Growth.register`: absolute pose, acceptance by
   inliers); its rotation is then replaced by the one its lines of a family give against the
   world directions (where they fit, in two families or more), which the local adjustments
   hold, so that the rotation cannot drift with the lines triangulated from earlier poses;
   a line's family comes from its planes in the window (the one world direction they all
   contain). Its new lines are triangulated once they have parallax
   (:meth:`~omni_sfm.estimate.incremental.Growth.triangulate`), and every ``local_every``
   frames the last ``local_frames`` registered frames and their lines are adjusted with the
   line bundle adjustment, the older frames of the window held
   (:meth:`~omni_sfm.estimate.incremental.Growth.adjust`). The state is a sliding window of
   the last ``window`` frames (observations and poses) and the lines they see; everything
   older is dropped, so memory and time per frame do not grow with the sequence.
3. **Lost.** A frame that cannot be registered (too few known lines: a blank wall, a dark
   corridor) is ``lost`` with the reason; if it still sees lines of at least two of the
   parallel families (vanishing directions) its rotation is kept (``rotation-only``: rotation,
   no position). After ``max_misses`` frames in a row without a pose the estimator starts
   again (step 1) on the frames that follow; the frame where that start succeeds is
   ``relocalised`` and its poses are in a new world and scale (:attr:`TrackedPose.world`
   counts the starts): nothing joins them to the earlier ones.

It serves callers with their own front end and simulated lines as well as the tracker;
:func:`poses_trajectory` gathers the poses it returned into a trajectory.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import Any

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.bundle import BundleOptions, bundle_adjust
from omni_sfm.estimate.families import (
    family_of_lines,
    family_of_planes,
    line_families,
    manhattan,
    plane_directions,
)
from omni_sfm.estimate.incremental import (
    Growth,
    IncrementalOptions,
    plane_parallax_deg,
    rotation_from_directions,
)
from omni_sfm.estimate.pipeline import EstimationOptions, EstimationResult, estimate_poses
from omni_sfm.geometry import (
    FloatArray,
    matrix_to_rotvec,
    quat_xyzw_from_matrix,
    rotation_angle,
    rotvec_to_matrix,
)
from omni_sfm.lines.extract import ExtractionOptions
from omni_sfm.lines.track import TrackingOptions
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.poses import Trajectory
from omni_sfm.reports import TrackFrame, TrackPose
from omni_sfm.vanishing import VanishingOptions, detect_parallel_families

_SAME_DIRECTION_DEG = 15.0
_SAME_DIRECTION = math.cos(math.radians(_SAME_DIRECTION_DEG))
"""Two parallel families whose world directions are within 15 deg are one world direction
(:func:`~omni_sfm.estimate.families.world_families`' ``min_separation_deg``)."""


class Status(StrEnum):
    """What :class:`TrackedPose` says about its frame."""

    INITIALISING = "initialising"
    """Buffered for the start: no pose yet (it may come later in ``start_poses``)."""
    TRACKING = "tracking"
    """Registered: full pose."""
    ROTATION_ONLY = "rotation-only"
    """Not registered, but the parallel families' directions give its rotation."""
    LOST = "lost"
    """No pose (``reason`` says why)."""
    RELOCALISED = "relocalised"
    """Full pose from a new start after a loss: a new world and scale."""


def _default_start() -> EstimationOptions:
    # the buffered frames are few: the paper's method on them where one window covers them,
    # the global estimator where some lines come or go
    return EstimationOptions(progress=False)


@dataclass(frozen=True, kw_only=True)
class OnlineOptions:
    """Options of :class:`~omni_sfm.pipelines.track.Tracker` and :class:`OnlineEstimator`."""

    extraction: ExtractionOptions = field(default_factory=ExtractionOptions)
    """Line extraction (:class:`~omni_sfm.pipelines.track.Tracker` only)."""
    tracking: TrackingOptions = field(default_factory=TrackingOptions)
    """Frame-to-frame line tracking (:class:`~omni_sfm.pipelines.track.Tracker` only)."""
    start: EstimationOptions = field(default_factory=_default_start)
    """The offline estimator run on the buffered frames to start."""
    start_frames: int = 15
    """Frames buffered before the first try of a start."""
    start_retry: int = 5
    """A start that fails is tried again after this many more frames ..."""
    max_start_frames: int = 40
    """... on at most this many of the latest frames."""
    min_start_parallax_deg: float = 2.5
    """A start is taken once the planes of its lines turn by this much across the buffered
    frames (90th percentile over the lines; or once ``max_start_frames`` are buffered): the
    start's lines and baseline fix the scale that the tracking carries on, and a start on too
    short a baseline leaves them out of proportion, which the tracking then relaxes as a scale
    drift (docs/track.md)."""
    registration: IncrementalOptions = field(
        default_factory=lambda: IncrementalOptions(families=False))
    """Registration, triangulation and local adjustment (``local_every``, ``local_frames``,
    ``max_misses``: failures in a row before a new start). ``families`` is off: the lines
    keep their own directions; the world directions enter through the rotations (module
    docstring)."""
    bundle: BundleOptions = field(
        default_factory=lambda: BundleOptions(reject_outliers=False))
    """The local adjustments' line bundle adjustment. Outlier tracks are not rejected there
    (the robust loss still bounds their weight): on the window's few frames the test flagged
    a third of the corridor's good lines at a time, which then had to be triangulated
    again."""
    window: int = 30
    """Frames kept: their observations and poses, and the lines they see; at least
    ``registration.local_frames + 2`` (the adjustment holds the older frames of the window)."""
    hold_anchored: bool = True
    """The local adjustments hold the rotations referred to the world directions."""
    anchor_inlier_deg: float = 0.3
    """A line of a family fits a rotation from the world directions when its plane misses
    its direction by at most this (or the registration's inlier threshold, if larger)."""
    max_anchor_turn_deg: float = 3.0
    """A rotation from the world directions that turns a registered frame by more than this
    is not taken (lines given the wrong family): the frame keeps the registration's."""
    min_rotation_lines: int = 3
    """Lines of known directions a frame must see (and fit) to keep its rotation ..."""
    min_rotation_families: int = 2
    """... in at least this many parallel families."""

    def __post_init__(self) -> None:
        if self.window < self.registration.local_frames + 2:
            raise OmniSfmError(f"window ({self.window}) must be at least local_frames + 2 "
                               f"({self.registration.local_frames + 2})")
        if not 3 <= self.start_frames <= self.max_start_frames:
            raise OmniSfmError(f"need 3 <= start_frames ({self.start_frames}) <= "
                               f"max_start_frames ({self.max_start_frames})")
        if self.start_retry < 1:
            raise OmniSfmError(f"start_retry must be at least 1, got {self.start_retry}")


@dataclass(frozen=True)
class TrackedPose:
    """One frame's result.

    Attributes:
        frame: the frame's number, in the order fed (0, 1, ...).
        timestamp: as given with the frame.
        status: :class:`Status`.
        rotation: ``(3, 3)`` world_from_cam rotation, or None (``initialising``, ``lost``).
        position: ``(3,)`` camera centre in the world, or None (also ``rotation-only``).
        lines: lines observed in the frame.
        lines_known: of those, lines already triangulated (the registration's material).
        latency_ms: wall-clock time spent on this frame (the tracker's: lines and pose).
        reason: why there is no (full) pose, one line; None when there is one.
        world: which start the pose is in (0: the first; each restart after a loss, +1): poses
            of different worlds have different origins and scales.
        start_poses: with the frame where a start succeeded, the poses of the buffered frames
            it solved (status ``initialising``, world of this start), computed from the frames
            up to this one; empty otherwise.
    """

    frame: int
    timestamp: float
    status: Status
    rotation: FloatArray | None
    position: FloatArray | None
    lines: int
    lines_known: int
    latency_ms: float
    reason: str | None = None
    world: int = 0
    start_poses: tuple[TrackedPose, ...] = ()

    @property
    def has_pose(self) -> bool:
        """A full pose (rotation and position)."""
        return self.rotation is not None and self.position is not None

    def _pose(self) -> TrackPose:
        q = None if self.rotation is None else quat_xyzw_from_matrix(self.rotation[None])[0]
        return TrackPose(frame=self.frame, timestamp=self.timestamp,
                         position=None if self.position is None else
                         [float(x) for x in self.position],
                         quaternion_xyzw=None if q is None else [float(x) for x in q])

    def record(self) -> TrackFrame:
        """Its line of ``frames.jsonl`` and of ``--stream`` (docs/track.md); ``start_poses``:
        the start's poses (frame, timestamp, position, quaternion_xyzw)."""
        pose = self._pose()
        return TrackFrame(frame=pose.frame, timestamp=pose.timestamp, position=pose.position,
                          quaternion_xyzw=pose.quaternion_xyzw, status=str(self.status),
                          world=self.world, lines=self.lines, lines_known=self.lines_known,
                          latency_ms=round(self.latency_ms, 3), reason=self.reason,
                          start_poses=[p._pose() for p in self.start_poses])

    def to_json(self) -> dict[str, Any]:
        """:meth:`record`'s JSON document."""
        return self.record().to_json()


@dataclass
class _Frame:
    """A frame of the window: its observations and (once known) pose."""

    frame: int
    timestamp: float
    ids: np.ndarray
    normals: FloatArray
    rays: FloatArray | None
    sigmas: FloatArray | None
    R: FloatArray = field(default_factory=lambda: np.full((3, 3), np.nan))
    c: FloatArray = field(default_factory=lambda: np.full(3, np.nan))
    registered: bool = False
    anchored: bool = False
    """Its rotation is referred to the world directions (held by the adjustments)."""


def _window_tracks(frames: list[_Frame], min_views: int = 1
                   ) -> tuple[LineTracks, np.ndarray]:
    """The observations of ``frames`` as :class:`LineTracks` (frames ``0..len-1``), and the
    track ids of its tracks (sorted); tracks seen in fewer than ``min_views`` frames left
    out."""
    ids = np.concatenate([f.ids for f in frames])
    fr = np.concatenate([np.full(len(f.ids), k) for k, f in enumerate(frames)])
    nrm = np.concatenate([f.normals for f in frames]).reshape(-1, 3)
    with_rays = all(f.rays is not None for f in frames)
    with_sig = with_rays and all(f.sigmas is not None for f in frames)
    rays = np.concatenate([f.rays for f in frames if f.rays is not None]).reshape(-1, 3) \
        if with_rays else None
    sig = np.concatenate([f.sigmas for f in frames if f.sigmas is not None]).reshape(-1, 2) \
        if with_sig else None
    uniq, local, count = np.unique(ids, return_inverse=True, return_counts=True)
    keep = count[local] >= min_views
    if not keep.all():
        uniq, local = np.unique(ids[keep], return_inverse=True)
        fr, nrm = fr[keep], nrm[keep]
        rays = None if rays is None else rays[keep]
        sig = None if sig is None else sig[keep]
    order = np.lexsort((fr, local))
    tracks = LineTracks(len(frames), uniq, local[order], fr[order], nrm[order],
                        np.asarray([f.timestamp for f in frames], np.float64),
                        None if rays is None else rays[order],
                        None if sig is None else sig[order])
    return tracks, uniq


def _start_parallax(tracks: LineTracks, res: EstimationResult) -> float:
    """The 90th percentile over the start's lines of how far their planes turn across the
    posed buffered frames (:func:`~omni_sfm.estimate.incremental.plane_parallax_deg`)."""
    R = np.full((tracks.num_frames, 3, 3), np.nan)
    R[res.estimated] = res.trajectory.rotations
    ok = res.estimated[tracks.obs_frame]
    n_w = np.einsum("kij,kj->ki", R[tracks.obs_frame[ok]], tracks.obs_normal[ok])
    return float(np.percentile(plane_parallax_deg(n_w, tracks.obs_track[ok],
                                                  tracks.num_tracks), 90))


class OnlineEstimator:
    """Steps 1-3 of the module docstring on line observations: feed each frame's tracked lines
    with :meth:`add`, in order."""

    def __init__(self, options: OnlineOptions | None = None) -> None:
        self.options = options or OnlineOptions()
        self._count = 0  # frames fed
        self._world = -1  # no start yet
        self._buffer: deque[_Frame] = deque(maxlen=self.options.max_start_frames)
        self._window: deque[_Frame] = deque(maxlen=self.options.window)
        self._starting = True
        self._lines: dict[int, tuple[FloatArray, FloatArray]] = {}  # id -> (direction, point)
        self._family: dict[int, int] = {}  # id -> parallel family (-1: none)
        self._D: FloatArray = np.zeros((0, 3))
        self._sigma = 0.0
        self._thr = 0.0
        self._last_median = 0.0
        self._refit = False
        self._since_adjust = 0
        self._misses = 0
        self._last_R: FloatArray | None = None  # rotation of the latest frame that had one
        self._lost_since: int | None = None
        self._lost_reason = ""
        self._tried = False  # a start was tried on the current buffer
        self._since_try = 0  # frames buffered since

    # -- public ---------------------------------------------------------------------------
    def add(self, track_ids: np.ndarray, normals: FloatArray, rays: FloatArray | None = None,
            sigmas: FloatArray | None = None, timestamp: float | None = None) -> TrackedPose:
        """The pose of the next frame from its lines: ``track_ids`` ``(L,)`` (the same id for
        the same line in every frame it is seen in; one observation per id), ``normals``
        ``(L, 3)`` unit NVs in the camera frame, optionally ``rays`` ``(L, 3)`` towards each
        segment (settle the reflection, docs/formats.md) and ``sigmas`` ``(L, 2)`` (radians,
        :attr:`LineTracks.obs_sigma`). ``timestamp`` defaults to the frame's number."""
        t0 = time.perf_counter()
        k = self._count
        self._count += 1
        ids = np.asarray(track_ids, np.int64).reshape(-1)
        fr = _Frame(k, float(k if timestamp is None else timestamp), ids,
                    np.asarray(normals, np.float64).reshape(-1, 3),
                    None if rays is None else np.asarray(rays, np.float64).reshape(-1, 3),
                    None if sigmas is None else np.asarray(sigmas, np.float64).reshape(-1, 2))
        if len(np.unique(ids)) != len(ids):
            raise OmniSfmError(f"frame {k}: a track id is given twice")
        pose = self._start(fr) if self._starting else self._track(fr)
        return replace(pose, latency_ms=1000.0 * (time.perf_counter() - t0))

    @property
    def num_lines(self) -> int:
        """3D lines currently held (bounded by the window)."""
        return len(self._lines)

    @property
    def num_frames_held(self) -> int:
        """Frames currently held (the window, or the start's buffer)."""
        return len(self._buffer) if self._starting else len(self._window)

    # -- start ----------------------------------------------------------------------------
    def _pose(self, fr: _Frame, status: Status, reason: str | None = None,
              rotation: FloatArray | None = None, known: int = 0,
              start_poses: tuple[TrackedPose, ...] = ()) -> TrackedPose:
        full = status in (Status.TRACKING, Status.RELOCALISED, Status.INITIALISING) and \
            fr.registered
        return TrackedPose(fr.frame, fr.timestamp, status,
                           fr.R.copy() if full else rotation,
                           fr.c.copy() if full else None, len(fr.ids), known, 0.0, reason,
                           max(self._world, 0), start_poses)

    def _start(self, fr: _Frame) -> TrackedPose:
        o = self.options
        self._buffer.append(fr)
        n = len(self._buffer)
        lost = self._lost_since is not None
        status = Status.LOST if lost else Status.INITIALISING
        head = (f"lost since frame {self._lost_since} ({self._lost_reason}); restarting: "
                if lost else "")
        rot = self._rotation_only(fr) if lost else None
        self._since_try += 1
        if n < o.start_frames or (self._tried and self._since_try < o.start_retry):
            why = f"{head}{n} frames buffered for the start (" + \
                (f"tried again every {o.start_retry} frames)" if self._tried else
                 f"first try at {o.start_frames})")
            return self._rot_or(fr, status, why, rot)
        self._tried, self._since_try = True, 0
        frames = list(self._buffer)
        got = self._start_solution(frames)
        if isinstance(got, str):
            return self._rot_or(fr, status, f"{head}{got}", rot)
        return self._adopt_start(fr, frames, *got, lost)

    def _start_solution(self, frames: list[_Frame]
                        ) -> tuple[LineTracks, np.ndarray, EstimationResult] | str:
        """The offline estimator on the buffered ``frames``: ``(tracks, their ids, result)``,
        or why it gives no start (too few lines, a failure, a camera that only turns, the
        newest frame not posed, too little parallax while the buffer can still grow)."""
        o, n = self.options, len(frames)
        try:
            tracks, uniq = _window_tracks(frames, min_views=3)
            if tracks.num_tracks < 6:
                raise OmniSfmError(f"{tracks.num_tracks} lines seen in 3 or more of the "
                                   f"{n} buffered frames; need 6")
            res = estimate_poses(tracks, o.start)
        except OmniSfmError as exc:
            return f"start on {n} frames failed: {exc}"
        if res.report.rotation_only:
            return (f"start on {n} frames: the camera turns without moving (no position to "
                    "start from)")
        if not res.estimated[-1] or res.estimated.sum() < 3:
            return f"start on {n} frames did not pose the newest frame"
        turn = _start_parallax(tracks, res)
        if turn < o.min_start_parallax_deg and n < o.max_start_frames:
            return (f"start on {n} frames: its lines' planes turn by {turn:.1f} deg (90th "
                    f"percentile); need {o.min_start_parallax_deg:g}")
        return tracks, uniq, res

    def _adopt_start(self, fr: _Frame, frames: list[_Frame], tracks: LineTracks,
                     uniq: np.ndarray, res: EstimationResult, lost: bool) -> TrackedPose:
        """The start's poses and lines taken as the tracker's state: a new world, the lines
        of the window, their parallel families (fixed world directions from now on) and the
        registration's threshold; the newest frame's pose, with the start's other poses."""
        o = self.options
        traj = res.trajectory
        est = np.flatnonzero(res.estimated)
        for k, f in enumerate(frames):
            f.registered = bool(res.estimated[k])
        for j, e in enumerate(est.tolist()):
            frames[e].R, frames[e].c = traj.rotations[j].copy(), traj.positions[j].copy()
        self._world += 1
        self._sigma = float(np.radians(res.sigma_deg))
        known = np.isfinite(res.line_directions).all(1) & np.isfinite(res.line_points).all(1)
        window = frames[-o.window:]
        self._lines, self._family = {}, {}
        for m in np.flatnonzero(known):
            self._lines[int(uniq[m])] = (res.line_directions[m], res.line_points[m])
        # the parallel families of the start's lines (fixed world directions from now on):
        # the registration's (found and imposed by the growth) or, without them, for the
        # rotation-only fallback alone
        wt, wids = _window_tracks(window)
        d, p = self._line_arrays(wids)
        ro = o.registration
        self._D, of_family = self._start_families(tracks, uniq, frames, d, wids)
        # the registration's inlier threshold (:class:`Growth`'s)
        self._thr = max(ro.inlier_sigmas * self._sigma, math.radians(ro.min_inlier_deg))
        if self._D.shape[0]:
            self._anchor_start(tracks, uniq, frames, of_family)
            d, p = self._line_arrays(wids)
        fam = np.array([of_family.get(t, -1) for t in wids.tolist()], np.int64)
        g = Growth(wt, np.stack([f.R for f in window]), np.stack([f.c for f in window]),
                   np.array([f.registered for f in window]), d, p, self._sigma, ro, o.bundle,
                   families=(self._D, fam) if ro.families else None)
        if ro.families:
            g.snap(np.flatnonzero(g.known & (g.fam >= 0)))
        self._family, self._thr = of_family, g.thr
        self._store(g, window, wids)
        self._window = deque(window, maxlen=o.window)
        self._buffer.clear()
        self._starting = False
        self._thr, self._last_median, self._refit = g.thr, 0.0, False
        self._since_adjust, self._misses = 0, 0
        self._last_R = fr.R.copy()
        self._lost_since = None
        starts = tuple(self._pose(f, Status.INITIALISING) for f in frames[:-1] if f.registered)
        return self._pose(fr, Status.RELOCALISED if lost else Status.TRACKING,
                          known=self._known_count(fr), start_poses=starts)

    def _start_families(self, tracks: LineTracks, uniq: np.ndarray, frames: list[_Frame],
                        d: FloatArray, wids: np.ndarray) -> tuple[FloatArray, dict[int, int]]:
        """The world directions from now on, and the family of each line that has one: the
        parallel families of the start's tracks (vanishing directions,
        :func:`~omni_sfm.vanishing.detect_parallel_families`), each family's world direction
        from every view of its members with the start's rotations
        (:func:`~omni_sfm.estimate.families.plane_directions`: a few frames' baseline leaves
        the members' triangulated directions off by degrees, their planes do not), families
        within ``min_separation_deg`` of a larger one merged into it, made Manhattan where
        they nearly are, the third axis of a Manhattan pair taken exactly (and added where no
        family is near it: the corridor round the next corner). Without parallel families,
        the families of the start's lines (``d``, of the window's tracks ``wids``)."""
        ro = self.options.registration
        fams = detect_parallel_families(tracks, VanishingOptions())
        posed = np.array([f.registered for f in frames])
        if not fams:
            D, fam = line_families(d, max_angle_deg=ro.family_angle_deg,
                                   min_lines=ro.min_family_lines)
            return D, {int(t): int(j) for t, j in zip(wids, fam, strict=True) if j >= 0}
        group = np.full(tracks.num_tracks, -1)
        for j in range(len(fams) - 1, -1, -1):
            group[np.asarray(fams[j].members, bool)] = j
        ok = posed[tracks.obs_frame] & (group[tracks.obs_track] >= 0)
        R = np.stack([f.R for f in frames])
        m = np.einsum("kij,kj->ki", R[tracks.obs_frame[ok]], tracks.obs_normal[ok])
        W = plane_directions(m, group[tracks.obs_track[ok]], len(fams))
        index = np.full(len(fams), -1)  # each family's world direction
        kept: list[int] = []
        for j in range(len(fams)):
            if not np.isfinite(W[j]).all():
                continue
            near = [i for i, k in enumerate(kept) if abs(float(W[k] @ W[j])) > _SAME_DIRECTION]
            if near:
                index[j] = near[0]
            else:
                index[j] = len(kept)
                kept.append(j)
        sizes = np.bincount(index[group[group >= 0]][index[group[group >= 0]] >= 0],
                            minlength=len(kept))
        D = manhattan(W[kept], sizes, complete_deg=_SAME_DIRECTION_DEG)
        of_family = {int(uniq[m]): int(index[group[m]]) for m in np.flatnonzero(group >= 0)
                     if index[group[m]] >= 0}
        return D, of_family

    def _anchor_start(self, tracks: LineTracks, uniq: np.ndarray, frames: list[_Frame],
                      of_family: dict[int, int]) -> None:
        """The start's rotations referred to the world directions: each frame's rotation from
        its lines of a family (:meth:`_directions_rotation`), the start's own rotations turned
        by the correction that fits them best as a constant plus a turn growing with the frame
        index (the start's own rotations may turn by a tenth of a degree a frame where lines
        along the way look alike from every frame), the world turned so that it stays the
        first frame's camera, and the start's positions and lines adjusted to those rotations,
        held; ``self._lines`` updated."""
        fam = np.array([of_family.get(int(t), -1) for t in uniq.tolist()], np.int64)
        R = np.stack([f.R for f in frames])
        c = np.stack([f.c for f in frames])
        held = np.zeros(len(frames), bool)
        for k, f in enumerate(frames):
            if not f.registered:
                continue
            obs = np.flatnonzero(tracks.obs_frame == k)
            Rk = self._directions_rotation(tracks.obs_normal[obs], fam[tracks.obs_track[obs]],
                                           f.R, self.options.max_anchor_turn_deg)
            if Rk is not None:
                R[k], held[k] = Rk, True
        if held.sum() < 3:
            return
        # the start's own turns are smooth and right from frame to frame: what the world
        # directions correct is their drift, a turn growing with the frame index (each
        # frame's own correction, held, cost the positions: 0.34 % ATE instead of 0.11 on
        # the bench's mirror-camera corridor)
        R0 = np.stack([f.R for f in frames])
        ks = np.flatnonzero(held)
        w = matrix_to_rotvec(np.swapaxes(R0[ks], 1, 2) @ R[ks])
        A = np.stack([np.ones(len(ks)), ks.astype(float)], axis=1)
        a, b = np.linalg.lstsq(A, w, rcond=None)[0]
        reg = np.flatnonzero([f.registered for f in frames])
        R[reg] = R0[reg] @ rotvec_to_matrix(a + np.outer(reg, b))
        held[reg] = True
        d, p = self._line_arrays(uniq)
        first = int(np.flatnonzero([f.registered for f in frames])[0])
        if held[first]:
            # the world stays the first frame's camera: turned with everything in it onto
            # the first frame's rotation from the world directions
            Q = R[first].T
            R, c, d, p = Q @ R, c @ Q.T, d @ Q.T, p @ Q.T
            self._D = self._D @ Q.T
        try:
            res = bundle_adjust(tracks, R, c, d, p, held_rotations=held,
                                options=replace(self.options.bundle, max_rounds=2,
                                                final_loss=None))
        except OmniSfmError:
            return
        for k, f in enumerate(frames):
            if res.frames[k]:
                f.R, f.c, f.anchored = res.rotations[k].copy(), res.positions[k].copy(), \
                    bool(held[k]) and self.options.hold_anchored
        for m in np.flatnonzero(res.used_tracks):
            self._lines[int(uniq[m])] = (res.line_directions[m], res.line_points[m])

    def _rot_or(self, fr: _Frame, status: Status, why: str,
                rot: FloatArray | None) -> TrackedPose:
        if rot is None:
            return self._pose(fr, status, why)
        return self._pose(fr, Status.ROTATION_ONLY, why, rotation=rot)

    # -- tracking -------------------------------------------------------------------------
    def _line_arrays(self, ids: np.ndarray) -> tuple[FloatArray, FloatArray]:
        d = np.full((len(ids), 3), np.nan)
        p = np.full((len(ids), 3), np.nan)
        for m, t in enumerate(ids.tolist()):
            got = self._lines.get(t)
            if got is not None:
                d[m], p[m] = got
        return d, p

    def _known_count(self, fr: _Frame) -> int:
        return sum(1 for t in fr.ids.tolist() if t in self._lines)

    def _store(self, g: Growth, window: list[_Frame], ids: np.ndarray) -> None:
        """Poses, lines and families back from the growth ``g`` over ``window``; lines no frame
        of the window sees are dropped."""
        for k, f in enumerate(window):
            f.R, f.c, f.registered = g.R[k].copy(), g.c[k].copy(), bool(g.est[k])
            f.anchored = bool(g.anchored[k])
        lines: dict[int, tuple[FloatArray, FloatArray]] = {}
        for m in np.flatnonzero(g.known):
            lines[int(ids[m])] = (g.d[m].copy(), g.p[m].copy())
        self._lines = lines
        if self.options.registration.families:
            self._family = {int(ids[m]): int(g.fam[m]) for m in np.flatnonzero(g.fam >= 0)}
            return
        # each line's family from its planes in the window's registered frames (the one
        # world direction they all contain), else from its direction (a known line), else as
        # before (:meth:`_classify`, the start), while its track is in the window: a few
        # frames' baseline leaves the directions of lines triangulated from them off by
        # degrees, the planes are as good as the rotations
        tr = g.tracks
        ok = g.est[tr.obs_frame]
        n_w = np.einsum("kij,kj->ki", g.R[tr.obs_frame[ok]], tr.obs_normal[ok])
        planes = family_of_planes(n_w, tr.obs_track[ok], tr.num_tracks, self._D,
                                  max_angle_deg=float(np.degrees(self._thr)),
                                  min_views=self.options.registration.min_views)
        fam = family_of_lines(g.d, self._D,
                              max_angle_deg=self.options.registration.family_angle_deg)
        fam = np.where(planes >= 0, planes, np.where(g.known, fam, -1))
        before = self._family
        self._family = {}
        for j, t in enumerate(ids.tolist()):
            got = int(fam[j]) if fam[j] >= 0 else before.get(t, -1)
            if got >= 0:
                self._family[t] = got

    def _track(self, fr: _Frame) -> TrackedPose:
        o, ro = self.options, self.options.registration
        self._window.append(fr)
        window = list(self._window)
        tracks, ids = _window_tracks(window)
        d, p = self._line_arrays(ids)
        fam = np.array([self._family.get(t, -1) for t in ids.tolist()], np.int64)
        g = Growth(tracks, np.stack([f.R for f in window]), np.stack([f.c for f in window]),
                   np.array([f.registered for f in window]), d, p, self._sigma, ro,
                   o.bundle, families=(self._D, fam) if ro.families else None)
        g.last_median, g.refit = self._last_median, self._refit
        g.anchored[:] = [f.anchored for f in window]
        reg = [k for k, f in enumerate(window[:-1]) if f.registered]
        f_new = len(window) - 1
        known = int(g.known[tracks.obs_track[g.frame_obs(f_new)]].sum())
        why = "no registered frame in the window" if not reg else \
            g.register(f_new, reg[-1], reg[-2] if len(reg) > 1 else None)
        if why is None:
            self._anchor(g, f_new, ids)
            g.triangulate(f_new)
            reg.append(f_new)
            self._since_adjust += 1
            if (self._since_adjust >= ro.local_every or g.refit) and len(reg) > ro.local_frames:
                self._since_adjust = 0
                g.adjust(np.asarray(reg[-ro.local_frames:]))
            self._last_median, self._refit = g.last_median, g.refit
        self._store(g, window, ids)
        if why is None:
            self._misses = 0
            self._last_R = fr.R.copy()
            return self._pose(fr, Status.TRACKING, known=known)
        self._misses += 1
        rot = self._rotation_only(fr)
        if self._misses >= ro.max_misses:
            # start again on the frames that follow
            self._lost_since = fr.frame - self._misses + 1
            self._lost_reason = why
            self._starting = True
            self._buffer.clear()
            self._tried, self._since_try = False, 0
            self._lines, self._family = {}, self._family
            why = f"{why}; {self._misses} frames in a row without a pose: restarting"
        if rot is not None:
            return self._pose(fr, Status.ROTATION_ONLY, why, rotation=rot, known=known)
        return self._pose(fr, Status.LOST, why, known=known)

    def _anchor(self, g: Growth, f: int, ids: np.ndarray) -> None:
        """Frame ``f``'s rotation, just registered, from its lines of known world directions
        alone (:meth:`_directions_rotation`), held from then on by the local adjustments
        (``hold_anchored``): the registration's rotation leans on lines triangulated from
        earlier poses and, adjusted with them, drifts with them (docs/track.md); the world
        directions do not move. ``ids``: the track ids of the growth's tracks."""
        obs = g.frame_obs(f)
        t = g.tracks.obs_track[obs]
        fam = g.fam[t] if self.options.registration.families else \
            np.array([self._family.get(int(i), -1) for i in ids[t].tolist()], np.int64)
        R = self._directions_rotation(g.tracks.obs_normal[obs], fam, g.R[f],
                                      self.options.max_anchor_turn_deg)
        if R is not None:
            g.R[f], g.anchored[f] = R, self.options.hold_anchored

    def _directions_rotation(self, normals: FloatArray, fam: np.ndarray, R0: FloatArray,
                             max_turn_deg: float = 180.0) -> FloatArray | None:
        """The world_from_cam rotation that makes the normals ``(L, 3)`` of lines of a family
        (``fam`` ``(L,)``, -1: none) orthogonal to their world directions, from ``R0``: on the
        lines that miss them by at most 4 times the threshold (the registration's inlier
        threshold, at least ``anchor_inlier_deg``) at ``R0``, then again on those within it.
        None when fewer than
        ``min_rotation_lines`` lines in ``min_rotation_families`` families fit, or when it
        turns more than ``max_turn_deg`` from ``R0``."""
        o = self.options
        sel = fam >= 0
        if sel.sum() < o.min_rotation_lines or \
                len(np.unique(fam[sel])) < o.min_rotation_families:
            return None
        n, D = normals[sel], self._D[fam[sel]]
        thr = max(self._thr, math.radians(o.anchor_inlier_deg))
        R = R0
        for times in (4.0, 1.0):
            off = np.abs(np.sum((n @ R.T) * D, axis=1))  # sines of the planes' misfit
            inl = off <= math.sin(times * thr)
            if inl.sum() < o.min_rotation_lines or \
                    len(np.unique(fam[sel][inl])) < o.min_rotation_families:
                return None
            R = rotation_from_directions(n[inl], D[inl], R)
        if np.degrees(rotation_angle(R0.T @ R)) > max_turn_deg:
            return None
        return R

    # -- rotation only --------------------------------------------------------------------
    def _rotation_only(self, fr: _Frame) -> FloatArray | None:
        """The frame's rotation from the lines of known parallel families it sees (their
        world directions fixed), started from the latest rotation; None when it sees too few
        of them, in too few families, or they do not fit. Lines not yet of a family are given
        one from their views in the frames of the window whose rotation is known."""
        if self._last_R is None or len(self._D) == 0 or len(fr.ids) == 0:
            return None
        fam = np.array([self._family.get(t, -1) for t in fr.ids.tolist()], np.int64)
        R = self._directions_rotation(fr.normals, fam, self._last_R)
        if R is None:
            return None
        self._last_R = R
        self._classify(fr, R)
        return R

    def _classify(self, fr: _Frame, R: FloatArray) -> None:
        """Give the frame's lines without a family the one family whose direction lies in
        their plane (:func:`~omni_sfm.estimate.families.family_of_planes`, one view)."""
        free = np.array([t not in self._family for t in fr.ids.tolist()], bool)
        if not free.any():
            return
        n_w = fr.normals[free] @ R.T
        got = family_of_planes(n_w, np.arange(int(free.sum())), int(free.sum()), self._D,
                               max_angle_deg=float(np.degrees(self._thr)), min_views=1)
        for t, f in zip(fr.ids[free].tolist(), got.tolist(), strict=True):
            if f >= 0:
                self._family[t] = f


def poses_trajectory(poses: Iterable[TrackedPose], world: int | None = None, *,
                     with_start: bool = True) -> Trajectory:
    """The full poses among ``poses`` (and, ``with_start``, their ``start_poses``) as a
    :class:`~omni_sfm.poses.Trajectory` in frame order (one pose per frame: the latest given);
    ``world``: only those of that world."""
    got: dict[int, TrackedPose] = {}
    for q in poses:
        for p in (*(q.start_poses if with_start else ()), q):
            if p.rotation is not None and p.position is not None and \
                    (world is None or p.world == world):
                got[p.frame] = p
    ks = sorted(got)
    R = np.array([got[k].rotation for k in ks], np.float64).reshape(-1, 3, 3)
    c = np.array([got[k].position for k in ks], np.float64).reshape(-1, 3)
    return Trajectory(np.array([got[k].timestamp for k in ks], np.float64), R, c)
