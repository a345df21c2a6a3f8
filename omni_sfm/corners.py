"""Corner tracks through a video: Shi-Tomasi corners followed frame to frame by pyramidal KLT,
each step checked forward-backward, new corners added where the tracks thin out.

Shared by the point-based initializers (``omni_sfm_plugins.initializers.points``) and
``omni-sfm refine --features klt`` (:mod:`omni_sfm.refine.database`), so both track alike.
Pixels are OpenCV's (centre of the top-left pixel at (0, 0)).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from omni_sfm.geometry import FloatArray


@dataclass(frozen=True, kw_only=True)
class CornerTrackOptions:
    max_corners: int = 2000
    """Corners tracked at most; new ones are detected when fewer than ``redetect_fraction`` of
    this remain."""
    min_distance_px: float = 7.0
    """New corners keep at least this distance from each other and from the tracked ones."""
    quality: float = 0.01
    """``cv2.goodFeaturesToTrack``'s quality level (fraction of the strongest corner's score)."""
    redetect_fraction: float = 0.7
    """Detect new corners when fewer than this fraction of ``max_corners`` are tracked."""
    fb_max_px: float = 1.0
    """A step is kept only if tracking the new position back lands within this distance of
    where it started (inf: no check)."""
    anchor_max_px: float = np.inf
    """Drift control (inf: off): after each step every tracked corner is tracked again from its
    first frame's image straight into the new one, starting at the frame-to-frame position; it
    takes that position when the two agree within this distance, otherwise its track ends."""
    window_px: int = 15
    """KLT window side."""
    levels: int = 3
    """KLT pyramid levels above the image."""


@dataclass(frozen=True)
class CornerTracks:
    """Observations of tracked corners, in frame order.

    Attributes:
        track: ``(M,)`` track id of each observation (unique within a frame).
        frame: ``(M,)`` frame index (0-based position in the frames given), non-decreasing.
        uv: ``(M, 2)`` pixel (OpenCV convention).
    """

    track: np.ndarray
    frame: np.ndarray
    uv: FloatArray

    def in_frame(self, k: int) -> tuple[np.ndarray, FloatArray]:
        """Track ids and pixels of frame ``k``'s observations."""
        a, b = np.searchsorted(self.frame, [k, k + 1])
        return self.track[a:b], self.uv[a:b]


def _lk_params(o: CornerTrackOptions) -> dict[str, Any]:
    import cv2

    return {"winSize": (o.window_px, o.window_px), "maxLevel": o.levels,
            "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}


def klt_step(prev: np.ndarray, img: np.ndarray, pts: np.ndarray, mask: np.ndarray,
             options: CornerTrackOptions | None = None) -> tuple[FloatArray, np.ndarray]:
    """Track ``pts`` ``(N, 2)`` from ``prev`` to ``img`` (grey uint8 images): the new positions
    ``(N, 2)`` and ``(N,)`` bool, kept (KLT found it both ways, it came back within
    ``fb_max_px``, and it lies inside the image on a non-zero pixel of ``mask``)."""
    import cv2 as cv2_typed

    cv2: Any = cv2_typed  # OpenCV's stubs lack the overloads used here
    o = options or CornerTrackOptions()
    if len(pts) == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    lk = _lk_params(o)
    p0 = np.asarray(pts, np.float32).reshape(-1, 1, 2)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, img, p0, None, **lk)
    pb, st2, _ = cv2.calcOpticalFlowPyrLK(img, prev, p1, None, **lk)
    good = (st.ravel() == 1) & (st2.ravel() == 1)
    if np.isfinite(o.fb_max_px):
        good &= np.linalg.norm(pb.reshape(-1, 2) - p0.reshape(-1, 2), axis=1) < o.fb_max_px
    p1 = p1.reshape(-1, 2)
    good &= (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= img.shape[1] - 1) & \
        (p1[:, 1] <= img.shape[0] - 1)
    good[good] &= mask[p1[good, 1].round().astype(int), p1[good, 0].round().astype(int)] > 0
    return p1.astype(np.float64), good


def _anchor(anchors: dict[int, np.ndarray], img: np.ndarray, pts: np.ndarray,
            born: np.ndarray, start: np.ndarray, o: CornerTrackOptions) -> np.ndarray:
    """Track each corner from its first frame (``anchors[born]``, position ``start``) into
    ``img`` starting at ``pts``; where that lands within ``anchor_max_px`` of ``pts`` the corner
    moves there (in place), elsewhere it is dropped. Returns ``(N,)`` bool, kept."""
    import cv2 as cv2_typed

    cv2: Any = cv2_typed
    keep = np.zeros(len(pts), bool)
    lk = _lk_params(o)
    for f in np.unique(born):
        sel = np.flatnonzero(born == f)
        guess = pts[sel].reshape(-1, 1, 2).copy()
        q, st, _ = cv2.calcOpticalFlowPyrLK(anchors[int(f)], img,
                                            start[sel].reshape(-1, 1, 2), guess,
                                            flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        q = q.reshape(-1, 2)
        ok = (st.ravel() == 1) & (np.linalg.norm(q - pts[sel], axis=1) < o.anchor_max_px)
        pts[sel[ok]] = q[ok]
        keep[sel[ok]] = True
    return keep


def track_corners(frames: Iterable[np.ndarray], mask: np.ndarray,
                  options: CornerTrackOptions | None = None) -> CornerTracks:
    """Corner tracks through ``frames`` (grey uint8 images of one size, in order) inside
    ``mask`` (non-zero: usable): each frame's corners are tracked into the next
    (:func:`klt_step`); a lost corner ends its track; when fewer than ``redetect_fraction`` of
    ``max_corners`` remain, new corners are detected at least ``min_distance_px`` away from the
    tracked ones and start new tracks."""
    import cv2 as cv2_typed

    cv2: Any = cv2_typed
    o = options or CornerTrackOptions()
    mask = (np.asarray(mask) > 0).astype(np.uint8) * 255
    tr: list[np.ndarray] = []
    fr: list[np.ndarray] = []
    uv: list[np.ndarray] = []
    prev: np.ndarray | None = None
    pts = np.zeros((0, 2), np.float32)
    ids = np.zeros(0, np.int64)
    born = np.zeros(0, np.int64)  # frame of each live track's first observation
    start = np.zeros((0, 2), np.float32)  # and its position there
    anchors: dict[int, np.ndarray] = {}
    anchored = np.isfinite(o.anchor_max_px)
    next_id = 0
    for k, img in enumerate(frames):
        if prev is not None and len(pts):
            p1, good = klt_step(prev, img, pts, mask, o)
            pts, ids, born, start = p1[good].astype(np.float32), ids[good], born[good], \
                start[good]
            if anchored:
                keep = _anchor(anchors, img, pts, born, start, o)
                pts, ids, born, start = pts[keep], ids[keep], born[keep], start[keep]
        if len(pts) < o.redetect_fraction * o.max_corners:
            m = mask.copy()
            r = int(o.min_distance_px)
            for p in pts:
                cv2.circle(m, (int(round(p[0])), int(round(p[1]))), r, 0, -1)
            new = cv2.goodFeaturesToTrack(img, o.max_corners - len(pts), o.quality,
                                          o.min_distance_px, mask=m)
            if new is not None:
                new = new.reshape(-1, 2).astype(np.float32)
                pts = np.concatenate([pts, new])
                ids = np.concatenate([ids, next_id + np.arange(len(new))])
                born = np.concatenate([born, np.full(len(new), k)])
                start = np.concatenate([start, new])
                next_id += len(new)
        if anchored:
            anchors = {f: anchors.get(f, img) for f in np.unique(born).tolist()}
        tr.append(ids.copy())
        fr.append(np.full(len(ids), k, np.int64))
        uv.append(pts.astype(np.float64))
        prev = img
    if not tr:
        return CornerTracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
    return CornerTracks(np.concatenate(tr).astype(np.int64), np.concatenate(fr),
                        np.concatenate(uv).reshape(-1, 2))
