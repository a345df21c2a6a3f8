"""The front end: frames -> straight lines -> line tracks (docs/method.md §2).

``track_lines(frames, camera, options, mask)`` extracts the lines of every frame
(:mod:`omni_sfm.lines.extract`), tracks them from frame to frame (:mod:`omni_sfm.lines.track`)
and returns a :class:`FrontEndResult` whose ``tracks`` (:class:`LineTracks`) the parallel-line
detection and the estimator consume. Frames come from :func:`omni_sfm.frames.read_frames`
or any iterable of ``(index, timestamp, image)``.
"""

from __future__ import annotations

import os
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from tqdm import tqdm

from omni_sfm.cameras.base import CameraModel
from omni_sfm.errors import OmniSfmError
from omni_sfm.frames import to_gray
from omni_sfm.geometry import FloatArray, normalize
from omni_sfm.lines.extract import ExtractedLines, ExtractionOptions, LineExtractor
from omni_sfm.lines.track import LineTracker, TrackingOptions
from omni_sfm.lines.tracks import LineTracks, make_tracks
from omni_sfm.lines.workers import ExtractionWorkers, extract_timed
from omni_sfm.reports import FrontEndSummary, SkippedFrame, TrackLengths

IntArray = np.ndarray

MIN_TRACKS = 6
"""Fewest line tracks the estimator takes (3 parallel lines and 3 others)."""
DARK_GREY = 25
"""Frames whose median grey level is below this are "very dark" in the diagnosis of
:meth:`FrontEndResult.why_too_few_lines`."""
LOW_CONTRAST = 12
"""Frames whose contrast (grey levels spread over fewer levels than this, mostly the 5th to
95th percentile: :meth:`~omni_sfm.lines.extract.LineExtractor.image_stats`) are "low
contrast" there."""


@dataclass(frozen=True, kw_only=True)
class FrontEndOptions:
    """Options of :func:`track_lines`."""

    extraction: ExtractionOptions = field(default_factory=ExtractionOptions)
    """Line extraction (per frame)."""
    tracking: TrackingOptions = field(default_factory=TrackingOptions)
    """Frame-to-frame tracking."""
    progress: bool = True
    """Show a progress bar on stderr."""
    workers: int | None = None
    """Processes that extract the lines of upcoming frames while the calling process decodes
    frames and tracks (a bounded, ordered pipeline: the result is the same whatever the
    number). 1: everything in the calling process; None: one per CPU core (at most
    :data:`MAX_WORKERS`), or 1 for fewer than :data:`MIN_FRAMES_PER_WORKER` frames per
    worker."""


MAX_WORKERS = 8
"""Most extraction processes that ``workers=None`` starts."""
MIN_FRAMES_PER_WORKER = 25
"""With ``workers=None``, a sequence of fewer frames than this per core is done in the calling
process (starting the processes costs more than they save)."""

FrameTap = Callable[[int, float, np.ndarray], None]
"""Called with every frame the front end reads, ``(index, timestamp, grey image)``, in order:
what else needs the frames (the COLMAP images, the debug view) takes them from the same pass."""


@dataclass(frozen=True)
class FrontEndResult:
    """Line tracks of a sequence and what it took to get them.

    Attributes:
        tracks: the observations (``F`` = frames read; timestamps from the source).
        obs_endpoint_rays: ``(K, 2, 3)`` unit rays of the ends of each observation (aligned with
            ``tracks.obs_*``), for drawing.
        obs_support: ``(K,)`` edge points of each observation.
        obs_arc_deg: ``(K,)`` angle each observation subtends at the viewpoint, degrees.
        obs_normal_sigma: ``(K, 2)`` uncertainty of each NV along and across the segment's
            middle ray (radians; :attr:`ExtractedLines.normal_sigma`).
        frame_numbers: ``(F,)`` index of each frame in the source (image or video frame).
        lines_extracted: ``(F,)`` lines found per frame.
        segments_rejected: ``(F,)`` edge segments that failed the straightness test, per frame.
        lines_continued: ``(F,)`` lines that continued a track from the previous frame.
        tracks_started: ``(F,)`` lines that started a new track.
        tracks_revived: ``(F,)`` lines that continued a track lost in an earlier frame.
        timings_ms: per-frame wall-clock milliseconds of each stage: ``read``, ``extract``,
            ``track`` (``(F,)`` each) and ``finish`` (one value); ``extract_cpu`` and
            ``track_cpu``: CPU time of the calling thread (equal to the work done when OpenCV
            runs single-threaded, ``cv2.setNumThreads(1)``, whatever the machine's load).
        frames_skipped: source indices of frames skipped: not decoded, damaged or of another
            size (:class:`~omni_sfm.frames.FrameSource`).
        frames_skipped_reasons: why, one line for each of ``frames_skipped``.
        median_grey: ``(F,)`` median grey level of each frame inside the mask (0-255).
        contrast: ``(F,)`` spread of each frame's grey levels (mostly the 5th to 95th
            percentile: :meth:`~omni_sfm.lines.extract.LineExtractor.image_stats`).
        threshold_scale: ``(F,)`` factor of the edge thresholds after contrast normalisation
            (:attr:`ExtractionOptions.reference_contrast`).
        edge_points: ``(F,)`` Canny edge points inside the mask per frame.
        valid_pixels: pixels where edges are searched (the camera's valid area and the mask,
            eroded).
    """

    tracks: LineTracks
    obs_endpoint_rays: FloatArray
    obs_support: IntArray
    obs_arc_deg: FloatArray
    obs_normal_sigma: FloatArray
    frame_numbers: IntArray
    lines_extracted: IntArray
    segments_rejected: IntArray
    lines_continued: IntArray
    tracks_started: IntArray
    tracks_revived: IntArray
    timings_ms: dict[str, FloatArray]
    frames_skipped: tuple[int, ...]
    frames_skipped_reasons: tuple[str, ...]
    median_grey: FloatArray
    contrast: FloatArray
    threshold_scale: FloatArray
    edge_points: IntArray
    valid_pixels: int

    def camera_fixed_tracks(self) -> np.ndarray:
        """``(M,)`` bool: tracks of structure fixed to the camera (:func:`camera_fixed_tracks`)."""
        return camera_fixed_tracks(self.tracks)

    def without_tracks(self, drop: np.ndarray) -> FrontEndResult:
        """The same result without the tracks ``drop`` (``(M,)`` bool) and their observations;
        the per-frame figures are those of the front end as it ran."""
        keep_obs = ~np.asarray(drop, bool)[self.tracks.obs_track]
        return replace(self, tracks=self.tracks.select_tracks(~np.asarray(drop, bool)),
                       obs_endpoint_rays=self.obs_endpoint_rays[keep_obs],
                       obs_support=self.obs_support[keep_obs],
                       obs_arc_deg=self.obs_arc_deg[keep_obs],
                       obs_normal_sigma=self.obs_normal_sigma[keep_obs])

    def estimator_tracks(self, camera: CameraModel | None = None) -> LineTracks:
        """The tracks as the estimator takes them: every caller of the estimator on images
        (``init``, the ``lines`` initializer of ``compare``) goes through this one conversion.

        Each observation gets a ray towards the middle of its segment (the middle of the arc
        between its end rays, projected into the line's plane), which tells on which side of the
        viewpoint the line lies and so settles the point reflection that normals leave open
        (docs/formats.md), and the uncertainty of its NV along and across that ray, with which
        the bundle adjustment weighs a short segment's poorly fixed tilt less. The numbers are
        those ``tracks.json`` holds (:meth:`LineTracks.as_written`), so that the estimator
        alone on that file (``init --tracks``) finds the same poses to the bit. With a rig of
        lenses (``camera`` a :class:`~omni_sfm.cameras.RigCamera`) each observation also gets
        the centre of the lens that took it (``obs_offset``, metres).
        """
        from omni_sfm.cameras.rig import RigCamera

        tr = self.tracks
        rays = middle_rays(self.obs_endpoint_rays, tr.obs_normal)
        offsets = camera.ray_origins(rays) if isinstance(camera, RigCamera) else None
        return replace(tr, obs_ray=rays, obs_sigma=self.obs_normal_sigma,
                       obs_offset=offsets).as_written()

    def track_lengths(self) -> IntArray:
        """``(M,)`` frames each track is seen in."""
        return np.bincount(self.tracks.obs_track, minlength=self.tracks.num_tracks)

    def per_frame(self) -> dict[str, list[Any]]:
        """Per-frame counts and times as plain lists (for ``report.json``)."""
        return {
            "frame": self.frame_numbers.tolist(),
            "timestamp": self.tracks.timestamps.tolist(),
            "lines_extracted": self.lines_extracted.tolist(),
            "segments_rejected": self.segments_rejected.tolist(),
            "lines_continued": self.lines_continued.tolist(),
            "tracks_started": self.tracks_started.tolist(),
            "tracks_revived": self.tracks_revived.tolist(),
            "edge_points": self.edge_points.tolist(),
            "median_grey": self.median_grey.tolist(),
            "contrast": self.contrast.tolist(),
            "threshold_scale": np.round(self.threshold_scale, 4).tolist(),
            "extract_ms": np.round(self.timings_ms["extract"], 3).tolist(),
            "track_ms": np.round(self.timings_ms["track"], 3).tolist(),
        }

    def summary(self) -> FrontEndSummary:
        """Counts and median timings, as plain numbers (``report.json`` ``front_end``)."""
        lengths = self.track_lengths()
        t = self.timings_ms

        def med(a: np.ndarray) -> float:
            return float(np.median(a)) if len(a) else 0.0

        return FrontEndSummary(
            frames=int(self.tracks.num_frames),
            frames_skipped=list(self.frames_skipped),
            frames_skipped_reasons=[
                SkippedFrame(frame=n, reason=r)
                for n, r in zip(self.frames_skipped, self.frames_skipped_reasons, strict=True)],
            valid_pixels=self.valid_pixels,
            tracks=int(self.tracks.num_tracks),
            observations=int(self.tracks.num_observations),
            track_length_frames=TrackLengths(
                median=med(lengths), min=int(lengths.min()) if len(lengths) else 0,
                max=int(lengths.max()) if len(lengths) else 0),
            lines_per_frame_median=med(self.lines_extracted),
            lines_extracted_total=int(self.lines_extracted.sum()),
            segments_rejected_total=int(self.segments_rejected.sum()),
            lines_continued_per_frame_median=med(self.lines_continued[1:]),
            tracks_started_total=int(self.tracks_started.sum()),
            tracks_revived_total=int(self.tracks_revived.sum()),
            timings_ms_per_frame_median={k: med(v) for k, v in t.items() if k != "finish"},
            timings_ms_total={k: float(np.sum(v)) for k, v in t.items()},
        )

    def image_problem(self) -> str | None:
        """What is wrong with the images as a whole, if anything: the mask leaves no pixels, the
        frames are very dark (median grey below :data:`DARK_GREY`) or low contrast (spread below
        :data:`LOW_CONTRAST`); medians over the frames. Such frames may still give lines (the
        edge thresholds follow the contrast): this says why when they give too few."""
        if self.valid_pixels == 0:
            return ("the mask leaves no pixels (the camera's valid area and the mask, less a "
                    "border, do not overlap)")
        grey = float(np.median(self.median_grey))
        spread = float(np.median(self.contrast))
        if grey < DARK_GREY:
            return f"the frames are very dark (median grey {grey:.0f} of 255)"
        if spread < LOW_CONTRAST:
            return f"the frames are low contrast (grey levels spread over {spread:.0f} of 255)"
        return None

    def why_too_few_lines(self, need: int = MIN_TRACKS) -> str | None:
        """One line that says why the sequence gave fewer than ``need`` line tracks (the
        estimator's minimum), from the per-frame statistics; None if it gave enough.

        In this order: the mask leaves no pixels; the frames are very dark (median grey below
        :data:`DARK_GREY`); low contrast (spread below :data:`LOW_CONTRAST`); edges but no
        straight ones (a wrong camera model bends every line); straight lines in single frames
        that were not followed from frame to frame; too few edges at all.
        """
        n = self.tracks.num_tracks
        if n >= need:
            return None
        head = "no straight edges found"
        problem = self.image_problem()
        if problem:
            return f"{head}: {problem}"
        edges = int(np.median(self.edge_points))
        lines = float(np.median(self.lines_extracted))
        if lines < 1 and edges >= 1000:
            return (f"{head}: edges found ({edges} points per frame) but none straight: is the "
                    "camera file right?")
        if lines >= 1:
            return (f"too few line tracks ({n}; need {need}): {lines:.0f} straight lines per "
                    "frame, but too few followed over 3 or more frames (is the motion between "
                    "frames too large? try a smaller --step)")
        return (f"{head}: only {edges} edge points per frame (a scene without straight edges, "
                "or images out of focus?)")


def middle_rays(endpoint_rays: FloatArray, normals: FloatArray) -> FloatArray:
    """``(K, 3)`` unit rays towards the middle of each segment: the middle of the arc between
    its end rays ``(K, 2, 3)``, projected into its line's plane (normal ``(K, 3)``). The ray the
    estimator takes with each observation (:meth:`FrontEndResult.estimator_tracks`)."""
    mid = endpoint_rays[:, 0] + endpoint_rays[:, 1]
    mid = mid - np.sum(mid * normals, axis=1, keepdims=True) * normals
    return normalize(mid)


def worker_count(options: FrontEndOptions, frames: int | None) -> int:
    """Extraction processes :func:`track_lines` uses for ``frames`` frames (None: unknown)."""
    if options.workers is not None:
        if options.workers < 1:
            raise OmniSfmError(f"workers must be at least 1, got {options.workers}")
        return int(options.workers)
    cores = min(os.cpu_count() or 1, MAX_WORKERS)
    if frames is not None and frames < MIN_FRAMES_PER_WORKER * cores:
        cores = max(1, frames // MIN_FRAMES_PER_WORKER)
    return max(1, cores)


def _extracted(frames: Iterator[tuple[int, float, np.ndarray]], extractor: LineExtractor,
               workers: int, tap: FrameTap | None,
               ) -> Iterator[tuple[int, float, np.ndarray, ExtractedLines, float, float]]:
    """``(index, stamp, grey, lines, extract wall s, extract CPU s)`` in frame order; with
    ``workers`` > 1 the next frames' extraction runs in worker processes
    (:class:`~omni_sfm.lines.workers.ExtractionWorkers`) while the caller tracks."""
    def read() -> tuple[int, float, np.ndarray] | None:
        try:
            number, stamp, image = next(frames)
        except StopIteration:
            return None
        gray = to_gray(image)
        if tap is not None:
            tap(int(number), float(stamp), gray)
        return int(number), float(stamp), gray

    if workers <= 1:
        while (got := read()) is not None:
            lines, wall, cpu = extract_timed(extractor, got[2])
            yield *got, lines, wall, cpu
        return
    with ExtractionWorkers(extractor, workers) as pool:
        queue: deque[tuple[int, float, np.ndarray]] = deque()
        done = False
        while True:
            while not done and pool.in_flight < workers:
                got = read()
                if got is None:
                    done = True
                    break
                pool.submit(got[2])
                queue.append(got)
            if not queue:
                return
            lines, wall, cpu = pool.result()
            yield *queue.popleft(), lines, wall, cpu


def track_lines(frames: Iterable[tuple[int, float, np.ndarray]], camera: CameraModel,
                options: FrontEndOptions | None = None,
                mask: np.ndarray | None = None, *,
                tap: FrameTap | None = None) -> FrontEndResult:
    """Extract and track the straight lines of a frame sequence.

    Args:
        frames: ``(index, timestamp, image)`` in order, e.g. a
            :class:`~omni_sfm.frames.FrameSource`; its ``skipped`` list and
            ``skip_reasons`` (if any) are reported in ``frames_skipped`` and
            ``frames_skipped_reasons``.
        camera: the calibrated camera; images must be ``camera.width x camera.height``.
        options: extraction/tracking options.
        mask: optional ``(H, W)`` array, nonzero where the image may be used.
        tap: called with every frame read, in order (:data:`FrameTap`).

    With ``options.workers`` above 1 (by default on a multi-core machine), worker processes
    extract the lines of the frames ahead while this process decodes and tracks; the tracks
    are the same as with one worker (extraction is a function of the frame alone, and the
    tracker takes the frames in order). ``timings_ms`` ``read`` then includes the time spent
    waiting for a worker, and ``extract_cpu`` is measured in the worker.
    """
    o = options or FrontEndOptions()
    extractor = LineExtractor(camera, o.extraction, mask)
    tracker = LineTracker(o.tracking)
    numbers: list[int] = []
    stamps: list[float] = []
    n_lines: list[int] = []
    n_rej: list[int] = []
    t_read: list[float] = []
    t_ext: list[float] = []
    t_trk: list[float] = []
    c_ext: list[float] = []
    c_trk: list[float] = []
    stats: list[tuple[float, float, float, int]] = []
    total = (len(frames) or None) if hasattr(frames, "__len__") else None  # type: ignore[arg-type]
    workers = worker_count(o, total)
    with tqdm(total=total, desc="lines", unit="frame", disable=None if o.progress else True,
              leave=False) as bar:
        t0 = time.perf_counter()
        for number, stamp, gray, lines, wall, cpu in _extracted(iter(frames), extractor,
                                                                   workers, tap):
            t2, c2 = time.perf_counter(), time.thread_time()
            tracker.add_frame(gray, lines)
            t3, c3 = time.perf_counter(), time.thread_time()
            numbers.append(int(number))
            stamps.append(float(stamp))
            n_lines.append(lines.num_lines)
            n_rej.append(lines.num_rejected)
            # with workers, the wait for this frame's lines counts as reading
            t_ext.append(wall)
            t_read.append(max(0.0, t2 - t0 - (wall if workers <= 1 else 0.0)))
            t_trk.append(t3 - t2)
            c_ext.append(cpu)
            c_trk.append(c3 - c2)
            stats.append((lines.median_grey, lines.contrast, lines.threshold_scale,
                          lines.num_edge_points))
            bar.update(1)
            bar.set_postfix(lines=lines.num_lines, refresh=False)
            t0 = time.perf_counter()
    skipped = tuple(int(s) for s in getattr(frames, "skipped", ()))
    reasons: dict[int, str] = getattr(frames, "skip_reasons", {})
    if not numbers:
        why = f": {len(skipped)} skipped, e.g. frame {skipped[0]}: " \
            f"{reasons.get(skipped[0], 'does not decode')}" if skipped else ""
        raise OmniSfmError(f"no frames could be read (nothing to track){why}")
    t4 = time.perf_counter()
    obs = tracker.finish()
    ids = np.arange(obs.num_tracks)
    tracks = make_tracks(len(numbers), ids, obs.track, obs.frame, obs.normal,
                         np.asarray(stamps), source="front end")
    t5 = time.perf_counter()
    st = np.asarray(stats, dtype=np.float64).reshape(-1, 4)
    ms = 1000.0
    return FrontEndResult(
        tracks=tracks, obs_endpoint_rays=obs.endpoint_rays, obs_support=obs.support,
        obs_arc_deg=obs.arc_deg, obs_normal_sigma=obs.normal_sigma,
        frame_numbers=np.asarray(numbers, np.int64),
        lines_extracted=np.asarray(n_lines, np.int64),
        segments_rejected=np.asarray(n_rej, np.int64), lines_continued=obs.matched,
        tracks_started=obs.started, tracks_revived=obs.revived,
        timings_ms={"read": ms * np.asarray(t_read), "extract": ms * np.asarray(t_ext),
                    "track": ms * np.asarray(t_trk), "finish": np.asarray([ms * (t5 - t4)]),
                    "extract_cpu": ms * np.asarray(c_ext), "track_cpu": ms * np.asarray(c_trk)},
        frames_skipped=skipped,
        frames_skipped_reasons=tuple(reasons.get(k, "does not decode") for k in skipped),
        median_grey=st[:, 0], contrast=st[:, 1], threshold_scale=st[:, 2],
        edge_points=st[:, 3].astype(np.int64), valid_pixels=extractor.valid_pixels)


def camera_fixed_tracks(tracks: LineTracks, *, max_spread_deg: float = 0.1,
                        min_ratio: float = 10.0, min_others_deg: float = 0.5) -> np.ndarray:
    """``(M,)`` bool: tracks of structure fixed to the camera (the operator's outline, a
    tripod leg, the robot's body, the mirror's mount) that the automatic mask left.

    Such a line is seen along the same plane through the viewpoint whatever the camera
    does: its NVs stay put in the camera frame. A track is camera-fixed when its NVs stay
    within ``max_spread_deg`` of their mean while, over the same frames, the other tracks'
    NVs spread by at least ``min_ratio`` times as much (median) and by ``min_others_deg``:
    the camera moved, the line did not move with the scene. When the camera stands still
    every track stays put and none is flagged.
    """
    tr = tracks
    M = tr.num_tracks
    n = tr.obs_normal * np.where(
        np.sum(tr.obs_normal * tr.obs_normal[np.searchsorted(tr.obs_track, tr.obs_track)],
               axis=1) < 0, -1.0, 1.0)[:, None]  # signs aligned with each track's first
    mean = np.zeros((M, 3))
    np.add.at(mean, tr.obs_track, n)
    mean = normalize(mean)
    dev = np.degrees(np.arccos(np.clip(np.abs(np.sum(n * mean[tr.obs_track], axis=1)),
                                       0.0, 1.0)))
    spread = np.zeros(M)
    np.maximum.at(spread, tr.obs_track, dev)
    out = np.zeros(M, dtype=bool)
    for m in np.flatnonzero(spread <= max_spread_deg):
        frames = tr.obs_frame[tr.obs_track == m]
        # the other tracks' spread over the frames this one is seen in
        sel = (tr.obs_frame >= frames[0]) & (tr.obs_frame <= frames[-1]) & \
            (tr.obs_track != m)
        if not sel.any():
            continue
        t, nn = tr.obs_track[sel], n[sel]
        mm = np.zeros((M, 3))
        np.add.at(mm, t, nn)
        cnt = np.bincount(t, minlength=M)
        mm = normalize(mm)
        d = np.degrees(np.arccos(np.clip(np.abs(np.sum(nn * mm[t], axis=1)), 0.0, 1.0)))
        sp = np.zeros(M)
        np.maximum.at(sp, t, d)
        others = sp[(cnt >= max(2, len(frames) // 2)) & (spread > max_spread_deg)]
        if len(others) >= 3:
            level = float(np.median(others))
            out[m] = level >= max(min_ratio * spread[m], min_others_deg)
    return out
