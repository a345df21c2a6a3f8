"""Line tracking between consecutive frames (docs/method.md §2, paper Fig. 6), and beyond.

The paper's rule: sample points at constant intervals on each line of frame ``t``, track them
into frame ``t+1`` with KLT, snap each to the nearest edge point there, and take the line of
``t+1`` that receives the most points as the correspondence; if several lines of ``t`` claim the
same line, the one with more points wins. Lines that find no partner end; unclaimed lines of
``t+1`` start new tracks. No point-to-point matching is needed, so the aperture problem of KLT
along an edge does no harm: a point that slides along its edge still lands on the right line.

Added to the paper (docs/frontend.md says why):
- a forward-backward KLT check and a snap radius, so points lost by KLT do not vote;
- a vote quorum (absolute and as a share of the samples) and a limit on the change of the NV
  between consecutive frames, which reject a partner found by a few stray points;
- pieces of one line (split by an occluder, or re-joined after one) are kept in one track: a
  losing claimant whose NV equals the winner's is merged into the winner's track, and a second
  partner with the same NV as the first is added to the same track; where a track has two
  observations in one frame the better-supported one is kept;
- tracks seen in fewer than ``min_track_frames`` frames are dropped.
Every frame is fully re-detected (extraction runs on every frame), so new lines start tracks as
soon as they appear.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree

from omni_sfm.geometry import FloatArray, unsigned_angle
from omni_sfm.lines import edge_kernels
from omni_sfm.lines.extract import ExtractedLines

IntArray = np.ndarray


@dataclass(frozen=True, kw_only=True)
class TrackingOptions:
    """Parameters of :class:`LineTracker`; pixels unless stated."""

    sample_spacing_px: float = 8.0
    """Interval between the points sampled on a line (along its edge points)."""
    max_samples_per_line: int = 8
    """At most this many samples per line (the interval grows on long lines). 8 finds the same
    partners as 16 on the rendered sequences (docs/frontend.md, "The tracker's cost") at half the
    KLT work."""
    klt_scale: float = 0.5
    """KLT runs on the images resized by this factor (0.5: a quarter of the pixels, 4x faster;
    the tracked points only need to land within ``snap_radius_px`` of their line)."""
    klt_window: int = 9
    """KLT window size (square, px of the resized image)."""
    klt_levels: int = 3
    """KLT pyramid levels above the full image."""
    klt_iterations: int = 3
    """KLT iterations per pyramid level. A point on a straight edge never meets KLT's
    convergence test (it slides along the edge), so it used every iteration allowed; across the
    edge, which is all the snapping needs, it settles within two or three."""
    klt_min_eig: float = 1e-5
    """KLT's minimum-eigenvalue threshold (OpenCV ``minEigThreshold``); kept low because points
    on a straight edge are ill-conditioned along it, which the snapping tolerates."""
    fb_max_px: float = 0.0
    """Forward-backward check: tracked forward and back, a point must return within this
    distance of where it started, measured across the edge (along it KLT is free to slide);
    0 (the default) skips the backward pass, which doubled KLT's work and, behind the snap
    radius and the vote quorum, changed no partner on the rendered sequences."""
    flow_neighbours: int = 8
    """Samples KLT cannot track (the window holds a single ideal straight edge) move with the
    median flow of this many nearest tracked samples; 0 drops them."""
    snap_radius_px: float = 3.0
    """A tracked point votes for the line whose edge point is nearest, if within this radius."""
    min_votes: int = 3
    """Fewest votes for a correspondence."""
    min_vote_fraction: float = 0.25
    """Fewest votes as a share of the line's samples."""
    max_normal_step_deg: float = 10.0
    """Largest angle between the NVs of a line in consecutive frames."""
    merge_angle_deg: float = 0.5
    """Two pieces whose NVs agree within this angle are one line (one track)."""
    max_gap_frames: int = 2
    """A track lost for up to this many frames is picked up again by a line that found no
    partner (KLT and votes from the frame where the track was last seen); 0 disables."""
    min_track_frames: int = 3
    """Tracks seen in fewer frames are dropped."""


@dataclass(frozen=True)
class TrackedObservations:
    """All observations of all tracks, flat (the tracker's output before ``LineTracks``).

    Attributes:
        track: ``(K,)`` track index 0..M-1, sorted by (track, frame).
        frame: ``(K,)`` processed-frame index.
        normal: ``(K, 3)`` unit NVs (camera frame of that frame).
        endpoint_rays: ``(K, 2, 3)`` unit rays of the two ends of the observed piece.
        support: ``(K,)`` number of edge points of the observed line.
        arc_deg: ``(K,)`` angle the observed piece subtends at the viewpoint, degrees.
        normal_sigma: ``(K, 2)`` uncertainty of each NV (:attr:`ExtractedLines.normal_sigma`).
        line_index: ``(K,)`` index of the line in that frame's :class:`ExtractedLines`.
        num_frames: number of processed frames.
        matched: ``(F,)`` lines of frame f that continued a track from frame f-1.
        started: ``(F,)`` lines of frame f that started a new track.
        ended: ``(F,)`` tracks of frame f-1 that found no partner in frame f.
        revived: ``(F,)`` lines of frame f that continued a track lost in an earlier frame.
    """

    track: IntArray
    frame: IntArray
    normal: FloatArray
    endpoint_rays: FloatArray
    support: IntArray
    arc_deg: FloatArray
    normal_sigma: FloatArray
    line_index: IntArray
    num_frames: int
    matched: IntArray
    started: IntArray
    ended: IntArray
    revived: IntArray

    @property
    def num_tracks(self) -> int:
        return int(self.track.max()) + 1 if len(self.track) else 0


@dataclass(frozen=True)
class _LineRecord:
    """The per-line arrays of one frame's :class:`ExtractedLines` that the tracks keep."""

    normals: FloatArray
    endpoint_rays: FloatArray
    num_support: np.ndarray
    arc_deg: FloatArray
    normal_sigma: FloatArray

    @staticmethod
    def of(lines: ExtractedLines) -> _LineRecord:
        # copies: a view would keep the arrays it was cut from alive
        return _LineRecord(np.array(lines.normals), np.array(lines.endpoint_rays),
                           np.array(lines.num_support), np.array(lines.arc_deg),
                           np.array(lines.normal_sigma))


class LineTracker:
    """Feed frames in order with :meth:`add_frame`; :meth:`finish` returns the tracks.

    ``record=False`` (online use, :mod:`omni_sfm.pipelines.track`): only what the next frames'
    tracking needs is kept (the last ``max_gap_frames + 1`` frames), so memory does not grow
    with the number of frames; pieces of one line are not joined into one track afterwards (the
    ids :meth:`add_frame` returns are final) and :meth:`finish` is not available.
    """

    def __init__(self, options: TrackingOptions | None = None, *, record: bool = True) -> None:
        self.options = options or TrackingOptions()
        self.record = record
        o = self.options
        self._win = (int(o.klt_window), int(o.klt_window))
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                          int(o.klt_iterations), 0.01)
        self._prev_pyr: np.ndarray | None = None
        self._prev_lines: ExtractedLines | None = None
        self._prev_track: IntArray = np.zeros(0, np.int64)
        self._next_id = 0
        self._parent: dict[int, int] = {}
        self._frame = 0
        # per frame: track ids, frame, and the per-line arrays that finish() needs (not the
        # lines' edge points: kept for every frame of a long video they grew without bound,
        # about 0.65 MB a 1920x960 frame)
        self._obs: list[tuple[IntArray, int, _LineRecord]] = []
        self._matched: list[int] = []
        self._started: list[int] = []
        self._ended: list[int] = []
        self._revived: list[int] = []
        # the current frame's lines of the support points and, where the snapping needs one,
        # their KD-tree (shared by the step and the revival)
        self._tree: tuple[ExtractedLines | None, Any, IntArray] = (None, None, np.zeros(0))
        # (klt image, lines, track ids) of the last max_gap_frames + 1 frames
        self._history: list[tuple[np.ndarray, ExtractedLines, IntArray]] = []

    # -- public ---------------------------------------------------------------------------
    def add_frame(self, image: np.ndarray, lines: ExtractedLines) -> IntArray:
        """Track into this frame (8-bit grey ``image`` and its lines). Returns ``(L,)`` the
        (provisional) track id of each line."""
        sc = self.options.klt_scale
        pyr = np.ascontiguousarray(image) if sc == 1.0 else \
            cv2.resize(image, None, fx=sc, fy=sc, interpolation=cv2.INTER_AREA)
        nl = lines.num_lines
        track = np.full(nl, -1, np.int64)
        if self._prev_lines is not None and self._prev_pyr is not None and nl \
                and self._prev_lines.num_lines:
            track = self._associate(self._prev_pyr, pyr, self._prev_lines, lines)
        n_matched = int((track >= 0).sum())
        # (sets: np.setdiff1d's sorts cost more on a few dozen ids)
        ended = len(set(self._prev_track.tolist()) - set(track.tolist())) if self.record else 0
        revived = 0
        if nl and self.options.max_gap_frames > 0 and len(self._history) > 1:
            revived = self._revive(pyr, lines, track)
        new = track < 0
        track[new] = self._next_id + np.arange(int(new.sum()))
        self._next_id += int(new.sum())
        if self.record:
            self._ended.append(ended)
            self._revived.append(revived)
            self._matched.append(n_matched)
            self._started.append(int(new.sum()))
            self._obs.append((track.copy(), self._frame, _LineRecord.of(lines)))
        self._prev_pyr, self._prev_lines, self._prev_track = pyr, lines, track
        self._history.append((pyr, lines, track))
        del self._history[: -(self.options.max_gap_frames + 1)]
        self._frame += 1
        return track

    def finish(self) -> TrackedObservations:
        """Merge joined tracks, keep one observation per (track, frame), drop short tracks,
        and number tracks 0..M-1 in order of their first frame."""
        if not self.record:
            raise RuntimeError("LineTracker(record=False) keeps no tracks to finish")
        o = self.options
        if not self._obs:
            z = np.zeros(0, np.int64)
            return TrackedObservations(z, z, np.zeros((0, 3)), np.zeros((0, 2, 3)), z,
                                       np.zeros(0), np.zeros((0, 2)), z,
                                       self._frame, np.asarray(self._matched, np.int64),
                                       np.asarray(self._started, np.int64),
                                       np.asarray(self._ended, np.int64),
                                       np.asarray(self._revived, np.int64))
        c: dict[str, np.ndarray] = {
            "tr": np.concatenate([self._root_many(t) for t, _, _ in self._obs]),
            "fr": np.concatenate([np.full(len(t), f) for t, f, _ in self._obs]),
            "li": np.concatenate([np.arange(len(t)) for t, _, _ in self._obs]),
            "nrm": np.concatenate([ln.normals for _, _, ln in self._obs]).reshape(-1, 3),
            "ends": np.concatenate([ln.endpoint_rays for _, _, ln in self._obs]
                                   ).reshape(-1, 2, 3),
            "sup": np.concatenate([ln.num_support for _, _, ln in self._obs]).astype(np.int64),
            "arc": np.concatenate([ln.arc_deg for _, _, ln in self._obs]).astype(np.float64),
            "sig": np.concatenate([ln.normal_sigma for _, _, ln in self._obs]).reshape(-1, 2),
        }

        def take(sel: np.ndarray) -> None:
            for k in c:
                c[k] = c[k][sel]

        # one observation per (track, frame): the best supported
        take(np.lexsort((-c["sup"], c["fr"], c["tr"])))
        tr, fr = c["tr"], c["fr"]
        first = np.ones(len(tr), bool)
        first[1:] = (tr[1:] != tr[:-1]) | (fr[1:] != fr[:-1])
        take(first)
        _, tidx, nfr = np.unique(c["tr"], return_inverse=True, return_counts=True)
        take(nfr[tidx] >= o.min_track_frames)
        # renumber by first frame, then by old id
        uniq, tidx = np.unique(c["tr"], return_inverse=True)
        first_frame = np.full(len(uniq), np.iinfo(np.int64).max)
        np.minimum.at(first_frame, tidx, c["fr"])
        rank = np.empty(len(uniq), np.int64)
        rank[np.lexsort((uniq, first_frame))] = np.arange(len(uniq))
        c["tr"] = rank[tidx]
        take(np.lexsort((c["fr"], c["tr"])))
        return TrackedObservations(
            track=c["tr"], frame=c["fr"], normal=c["nrm"], endpoint_rays=c["ends"],
            support=c["sup"], arc_deg=c["arc"], normal_sigma=c["sig"], line_index=c["li"],
            num_frames=self._frame,
            matched=np.asarray(self._matched, np.int64),
            started=np.asarray(self._started, np.int64), ended=np.asarray(self._ended, np.int64),
            revived=np.asarray(self._revived, np.int64))

    # -- internals ------------------------------------------------------------------------
    def _root(self, t: int) -> int:
        p = self._parent
        while p.get(t, t) != t:
            p[t] = p.get(p[t], p[t])
            t = p[t]
        return t

    def _root_many(self, t: IntArray) -> IntArray:
        return np.array([self._root(int(x)) for x in t], np.int64) if self._parent else t

    def _union(self, a: int, b: int) -> None:
        if not self.record:
            return
        ra, rb = self._root(a), self._root(b)
        if ra != rb:
            self._parent[max(ra, rb)] = min(ra, rb)

    def _samples(self, lines: ExtractedLines) -> tuple[FloatArray, FloatArray, IntArray,
                                                        IntArray]:
        """Points at constant intervals on each line: ``(S, 2)`` pixels, ``(S, 2)`` unit
        tangents of the edge there, ``(S,)`` line index, ``(L,)`` samples per line (in C,
        :func:`edge_kernels.line_samples`)."""
        o = self.options
        return edge_kernels.line_samples(lines.offsets, lines.points_uv, o.sample_spacing_px,
                                         o.max_samples_per_line)

    def _votes(self, img0: np.ndarray, img1: np.ndarray, prev: ExtractedLines,
               cur: ExtractedLines, prev_keep: np.ndarray | None = None,
               max_step_deg: float | None = None) -> tuple[IntArray, IntArray, IntArray]:
        """KLT + snapping votes from lines of ``prev`` (those in ``prev_keep``) to lines of
        ``cur``: the pairs ``(i, j)`` that pass the quorum and the NV-step limit, and their
        votes."""
        o = self.options
        s0, tangent, owner, nsamp = self._samples(prev)
        if prev_keep is not None:
            sel = prev_keep[owner]
            s0, tangent, owner = s0[sel], tangent[sel], owner[sel]
        z = np.zeros(0, np.int64)
        if len(s0) == 0:
            return z, z, z
        # KLT runs on images scaled by klt_scale (pixel centres map as (x + 0.5) s - 0.5)
        sc = o.klt_scale
        p0 = ((s0 + 0.5) * sc - 0.5).astype(np.float32).reshape(-1, 1, 2)
        kw = dict(winSize=self._win, maxLevel=o.klt_levels, criteria=self._criteria,
                  minEigThreshold=o.klt_min_eig)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(img0, img1, p0, None, **kw)  # type: ignore[call-overload]
        ok = st.ravel() > 0
        if o.fb_max_px > 0:
            pb, st2, _ = cv2.calcOpticalFlowPyrLK(img1, img0, p1, None, **kw)  # type: ignore[call-overload]
            ok &= st2.ravel() > 0
            # only the part across the edge counts: sliding along it (aperture) is harmless
            back = (pb - p0).reshape(-1, 2)
            ok &= np.abs(back[:, 0] * tangent[:, 1] - back[:, 1] * tangent[:, 0]) \
                < o.fb_max_px * sc
        p1 = (p1.reshape(-1, 2).astype(np.float64) + 0.5) / sc - 0.5
        # KLT gives up on points whose window holds one ideal straight edge (a singular
        # system); predict them with the median flow of the nearest tracked samples instead
        lost = np.flatnonzero(st.ravel() == 0)
        if o.flow_neighbours > 0 and len(lost) and ok.sum() >= 3:
            good = np.flatnonzero(ok)
            _, nb = cKDTree(s0[good]).query(s0[lost], k=min(o.flow_neighbours, len(good)))
            flow = (p1[good] - s0[good])[nb.reshape(len(lost), -1)]
            p1[lost] = s0[lost] + np.median(flow, axis=1)
            ok[lost] = True
        if self._tree[0] is not cur:
            self._tree = (cur, None, cur.line_of_point())
        _, tree, line_of = self._tree
        # the nearest edge point within the snap radius: a grid search in C (a tenth of the
        # time of building a KD-tree of the frame's edge points and querying it, the same
        # points), the tree where the points are too sparse for a grid
        q = p1[ok]
        nearest = edge_kernels.snap(cur.points_uv, q, o.snap_radius_px)
        if nearest is None:
            if tree is None:
                # sliding-midpoint tree: builds in 60 % of the time, finds the same neighbours
                tree = cKDTree(cur.points_uv, balanced_tree=False, compact_nodes=False)
                self._tree = (cur, tree, line_of)
            dist, nearest = tree.query(q, distance_upper_bound=o.snap_radius_px)
            nearest = np.where(np.isfinite(dist), nearest, -1)
        hit = nearest >= 0
        i = owner[ok][hit]
        j = line_of[nearest[hit]]
        if len(i) == 0:
            return z, z, z
        n_cur = cur.num_lines
        pair, votes = np.unique(i * n_cur + j, return_counts=True)
        pi, pj = pair // n_cur, pair % n_cur
        need = np.maximum(o.min_votes, o.min_vote_fraction * nsamp[pi])
        step = np.degrees(unsigned_angle(prev.normals[pi], cur.normals[pj]))
        lim = o.max_normal_step_deg if max_step_deg is None else max_step_deg
        good = (votes >= need) & (step <= lim)
        return pi[good], pj[good], votes[good]

    @staticmethod
    def _assign(pi: IntArray, pj: IntArray,
                votes: IntArray) -> tuple[IntArray, IntArray, IntArray, IntArray]:
        """The paper's rule: each previous line's best partner (most votes), and each current
        line to the claimant with most votes. Returns winners ``(wi, wj)`` and the losing
        claims ``(li, lj)``."""
        order = np.lexsort((-votes, pi))
        first = np.ones(len(pi), bool)
        first[1:] = pi[order][1:] != pi[order][:-1]
        bi, bj, bv = pi[order][first], pj[order][first], votes[order][first]
        order = np.lexsort((-bv, bj))
        win = np.ones(len(bj), bool)
        win[1:] = bj[order][1:] != bj[order][:-1]
        return bi[order][win], bj[order][win], bi[order][~win], bj[order][~win]

    def _associate(self, img0: np.ndarray, img1: np.ndarray, prev: ExtractedLines,
                   cur: ExtractedLines) -> IntArray:
        """Track ids for the lines of ``cur`` (-1 where a new track starts)."""
        o = self.options
        track = np.full(cur.num_lines, -1, np.int64)
        pi, pj, votes = self._votes(img0, img1, prev, cur)
        if len(pi) == 0:
            return track
        wi, wj, li_, lj_ = self._assign(pi, pj, votes)
        track[wj] = self._prev_track[wi]
        cos_m = np.cos(np.radians(o.merge_angle_deg))
        # losers that are pieces of the winner's line: one track
        winner_of = np.full(cur.num_lines, -1, np.int64)
        winner_of[wj] = wi
        for li, lj in zip(li_, lj_, strict=True):
            w = winner_of[lj]
            if abs(prev.normals[li] @ prev.normals[w]) > cos_m:
                self._union(int(self._prev_track[li]), int(self._prev_track[w]))
        # a second partner of a line with the same NV as the first: another piece, same track
        partner = np.full(prev.num_lines, -1, np.int64)
        partner[wi] = wj
        for li, lj in zip(pi, pj, strict=True):
            if track[lj] < 0 and partner[li] >= 0 and \
                    abs(cur.normals[lj] @ cur.normals[partner[li]]) > cos_m:
                track[lj] = self._prev_track[li]
        return track

    def _revive(self, img: np.ndarray, cur: ExtractedLines, track: IntArray) -> int:
        """Give lines of ``cur`` that found no partner the tracks that were lost in the last
        ``max_gap_frames`` frames (KLT and votes from the frame where each was last seen).
        Returns how many were revived."""
        o = self.options
        revived = 0
        active = set(self._prev_track.tolist()) | set(track[track >= 0].tolist())
        # most recent first: the history holds frames t-2, t-3, ... (t-1 is the previous frame)
        for gap, (img0, lines0, track0) in enumerate(reversed(self._history[:-1]), start=2):
            free = track < 0
            if not free.any():
                break
            dormant = np.array([t not in active for t in track0.tolist()], bool)
            if not dormant.any():
                continue
            pi, pj, votes = self._votes(img0, img, lines0, cur, prev_keep=dormant,
                                        max_step_deg=o.max_normal_step_deg * gap)
            sel = free[pj]
            if not sel.any():
                continue
            wi, wj, _, _ = self._assign(pi[sel], pj[sel], votes[sel])
            track[wj] = track0[wi]
            active |= set(track0[wi].tolist())
            revived += len(wj)
        return revived
