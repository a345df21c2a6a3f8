"""An automatic mask of what does not move with the scene (docs/frontend.md, "Automatic mask").

The operator, a tripod's legs, the robot or the mirror's mount and the camera's own reflection
are fixed to the camera: while the camera moves they stay at the same pixels and the scene
slides past them. Their straight edges would otherwise be tracked as lines that never move,
which the estimator reads as lines at infinity in the wrong direction.

:func:`static_mask` takes a sample of frames spread over the sequence:

1. Canny edges of each lightly smoothed frame inside the usable region (the camera's valid
   mask, less a margin at its border, and the user's mask);
2. *persistent* edge pixels: an edge (within 1 px) in at least ``persist_fraction`` of the
   frames; pieces shorter than ``min_component_px`` are dropped;
3. guard: if most edges of the sample persist, the camera barely moved and nothing can be told
   apart, so no mask is made (``applied`` False, with the reason);
4. *wobbling* edges, of a hand that holds the camera and moves a little with it (or a body
   whose outline the scene behind it shifts by a pixel): an edge of about the same
   orientation within a few pixels (``wobble_px`` of the smaller image side) in at least
   ``persist_fraction`` of the frames, away from the persistent edges, kept only where the
   piece parts a still area from a moving one (the scene sliding past) and the still side is
   enclosed by such edges and the border band (the body's plain inside): a scene line that
   barely moves has the scene on both sides, still on both sides in a plain scene, moving on
   both in a textured one, and a plain stretch of the scene beside it goes on past it;
5. the persistent and wobbling edges are closed into regions, the areas they enclose whose grey
   levels do not change over the sample are filled in (the body's plain inside), and the result
   is grown by a margin.

Deterministic (no sampling), about 15 ms per 640x320 frame (7 ms without step 4).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from omni_sfm.cameras.base import CameraModel
from omni_sfm.lines.extract import usable_pixels
from omni_sfm.reports import AutoMaskReport

HAND_HELD_WOBBLE = 0.01
"""``AutoMaskOptions.wobble_px`` for hand-held footage: 1 % of the smaller image side (3 px at
640x320)."""


@dataclass(frozen=True, kw_only=True)
class AutoMaskOptions:
    """Parameters of :func:`static_mask`; pixel units unless stated."""

    blur_sigma: float = 1.0
    """Gaussian smoothing before edge detection (px)."""
    canny_low: float = 20.0
    """Canny hysteresis low threshold (grey levels, L2 Sobel magnitude as in extraction)."""
    canny_high: float = 50.0
    """Canny hysteresis high threshold."""
    persist_fraction: float = 0.9
    """An edge pixel is camera-fixed if an edge lies within 1 px of it in at least this
    fraction of the sampled frames."""
    min_component_px: int = 40
    """Persistent edge pieces with fewer pixels are ignored (chance coincidences)."""
    border_px: int = 6
    """Edges within this distance of the border of the usable region are ignored: the mirror's
    rim and the user's mask border stay put but are masked already."""
    static_edge_limit: float = 0.35
    """If more than this fraction of all edge pixels of the sample persist, the camera barely
    moved: no mask is made."""
    close_px: float = 0.008
    """Radius of the dilation that thickens the persistent edges into walls (bridging their
    gaps), as a fraction of the smaller image side (at least 2 px)."""
    still_grey: float = 3.0
    """An area enclosed by persistent edges is filled if the median over its pixels of the
    grey level's standard deviation across the sample is below this (grey levels)."""
    max_fill_fraction: float = 0.25
    """Largest enclosed area that is filled, as a fraction of the usable region."""
    margin_px: float = 0.005
    """Margin added around the masked regions, as a fraction of the smaller image side."""
    max_masked_fraction: float = 0.5
    """If the mask would cover more than this fraction of the usable region, it is not applied
    (the sample is too still or too uniform to tell the body from the scene)."""
    min_frames: int = 5
    """Fewest frames in the sample."""
    wobble_px: float = 0.0
    """Wobbling edges: how far an edge may move and still count as staying put, as a fraction
    of the smaller image side (at least 2 px); 0 (the default): no wobbling edges are looked
    for. :data:`HAND_HELD_WOBBLE` for hand-held footage (``init --mask-wobbling``): off by
    default, because the far end of a corridor stays within a few pixels while the camera
    walks straight along it (docs/frontend.md, "Automatic mask")."""
    wobble_orientation_bins: int = 8
    """Wobbling edges: an edge counts near a pixel only if its gradient orientation (modulo
    180 deg) is in the same or a neighbouring one of this many bins."""
    wobble_ring_px: float = 0.02
    """Wobbling edges: width of the ring around a piece where its two sides are looked at, as a
    fraction of the smaller image side (at least 4 px)."""
    still_side: float = 0.25
    """Wobbling edges: a piece is kept if at least this fraction of its ring is still (grey
    level std below ``wobble_still_grey``) ..."""
    moving_side: float = 0.25
    """... and at least this fraction of its ring moves (std above ``moving_grey``)."""
    moving_grey: float = 8.0
    """Wobbling edges: grey-level standard deviation over the sample above which a pixel sees
    the scene move (grey levels)."""
    wobble_still_grey: float = 6.0
    """Wobbling edges: grey-level standard deviation below which a pixel is still, and the
    largest median of an area they enclose that is filled (a shaded body that wobbles changes
    its grey levels a little; grey levels)."""


@dataclass(frozen=True)
class AutoMask:
    """The automatic mask and what it did.

    Attributes:
        mask: ``(H, W)`` bool, True where the image may be used: the user's mask (all True if
            none) less the camera-fixed regions when ``applied``, the user's mask otherwise.
        applied: whether camera-fixed regions were masked (False: nothing found, or the guard
            of a camera that barely moves).
        masked_fraction: fraction of the camera's valid pixels (inside the user's mask) that
            the automatic part removed (0 when not applied).
        static_edge_fraction: fraction of the sample's edge pixels that persist.
        reason: one line for the log and ``report.json``.
        wobbling_edge_fraction: fraction of the sample's edge pixels on the wobbling edges
            that were kept and do not persist within 1 px (step 4 of the module docstring).
    """

    mask: np.ndarray
    applied: bool
    masked_fraction: float
    static_edge_fraction: float
    reason: str
    wobbling_edge_fraction: float = 0.0

    def summary(self) -> AutoMaskReport:
        """Its section of ``report.json`` (``auto_mask``)."""
        return AutoMaskReport(applied=self.applied,
                              masked_fraction=round(self.masked_fraction, 4),
                              static_edge_fraction=round(self.static_edge_fraction, 4),
                              wobbling_edge_fraction=round(self.wobbling_edge_fraction, 4),
                              reason=self.reason)


def _usable_region(camera: CameraModel, user_mask: np.ndarray | None,
                   border_px: int) -> tuple[np.ndarray, np.ndarray]:
    """``(base, inner)``: the camera's valid pixels inside the user's mask, and that region
    eroded by ``border_px`` (edges are only looked for there)."""
    base = usable_pixels(camera, user_mask)
    b = max(0, int(border_px))
    if b == 0:
        return base, base.copy()
    pad = cv2.copyMakeBorder(base.astype(np.uint8), b, b, b, b, cv2.BORDER_CONSTANT, value=0)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * b + 1, 2 * b + 1))
    return base, cv2.erode(pad, k)[b:-b, b:-b] > 0


def _wobble_radius(shape: tuple[int, int], o: AutoMaskOptions) -> int:
    """How far (px) a wobbling edge may move: ``wobble_px`` of the smaller side, at least 2
    (0: off)."""
    return 0 if o.wobble_px <= 0 else max(2, int(round(o.wobble_px * min(shape))))


def _edge_statistics(frames: Sequence[np.ndarray], shape: tuple[int, int],
                     o: AutoMaskOptions
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Per pixel over the sample: ``(raw, near, std, wobble)``, the fraction of frames with an
    edge at the pixel, with an edge within 1 px of it, the standard deviation of the smoothed
    grey level (grey levels), and the fraction of frames with an edge of about the same
    orientation within the wobble radius (the most of any orientation; None when off)."""
    h, w = shape
    raw = np.zeros((h, w), np.float32)
    near = np.zeros((h, w), np.float32)
    s1 = np.zeros((h, w), np.float64)
    s2 = np.zeros((h, w), np.float64)
    k3 = np.ones((3, 3), np.uint8)
    ksize = 2 * int(np.ceil(2.0 * o.blur_sigma)) + 1
    r = _wobble_radius(shape, o)
    nb = max(3, int(o.wobble_orientation_bins))
    per_bin = np.zeros((nb, h, w), np.uint16) if r > 0 else None
    kw = _disk(r)
    for f in frames:
        img = np.asarray(f)
        if img.shape != (h, w) or img.dtype != np.uint8:
            raise ValueError(f"frames must be ({h}, {w}) uint8 grey images, got "
                             f"{img.shape=} {img.dtype=}")
        sm = cv2.GaussianBlur(img.astype(np.float32), (ksize, ksize), o.blur_sigma) \
            if o.blur_sigma > 0 else img.astype(np.float32)
        e = cv2.Canny(np.clip(sm + 0.5, 0, 255).astype(np.uint8), o.canny_low, o.canny_high,
                      L2gradient=True) > 0
        raw += e
        near += cv2.dilate(e.astype(np.uint8), k3) > 0
        s1 += sm
        s2 += sm.astype(np.float64) ** 2
        if per_bin is not None:
            per_bin += _oriented_near(sm, e, nb, kw)
    n = float(len(frames))
    var = np.maximum(s2 / n - (s1 / n) ** 2, 0.0)
    wobble = None if per_bin is None else per_bin.max(axis=0).astype(np.float32) / n
    return raw / n, near / n, np.sqrt(var).astype(np.float32), wobble


def _oriented_near(smooth: np.ndarray, edges: np.ndarray, bins: int,
                   kernel: np.ndarray) -> np.ndarray:
    """``(bins, H, W)`` uint8, 1 at pixels within ``kernel`` of an edge pixel whose gradient
    orientation (modulo 180 deg) lies in bin ``b`` or a neighbouring one."""
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1)
    angle = cv2.phase(gx, gy)  # radians in [0, 2 pi)
    b = (angle * np.float32(bins / np.pi)).astype(np.uint8) % bins
    b[~edges] = 255
    out = np.empty((bins, *edges.shape), np.uint8)
    for i in range(bins):
        sel = (b == i) | (b == (i - 1) % bins) | (b == (i + 1) % bins)
        out[i] = cv2.dilate(sel.view(np.uint8), kernel)
    return out


def _persistent_edges(raw: np.ndarray, near: np.ndarray, inner: np.ndarray,
                      o: AutoMaskOptions) -> tuple[np.ndarray, float]:
    """Bool ``(H, W)`` camera-fixed edge pixels and the fraction of all edge detections of the
    sample that fall on them."""
    persistent = (near >= o.persist_fraction) & (raw >= 0.5 * o.persist_fraction) & inner
    n, lab, stats, _ = cv2.connectedComponentsWithStats(persistent.astype(np.uint8),
                                                        connectivity=8)
    big = stats[:, cv2.CC_STAT_AREA] >= max(1, o.min_component_px)
    big[0] = False
    persistent = big[lab]
    total = float(raw[inner].sum())
    static = float(raw[persistent].sum())
    return persistent, static / total if total > 0 else 0.0


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _wobbling_edges(wobble: np.ndarray, persistent: np.ndarray, std: np.ndarray,
                    base: np.ndarray, inner: np.ndarray, o: AutoMaskOptions
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Bool ``(H, W)`` ``(edges, inside)``: the pieces of edges that stay within the wobble
    radius (``wobble``: the fraction of frames, :func:`_edge_statistics`), away from the
    persistent edges, that part a still area they enclose from a moving one (module
    docstring, step 4), and the still areas they enclose."""
    shape = wobble.shape
    r = _wobble_radius(shape, o)
    near_fixed = cv2.dilate(persistent.astype(np.uint8), _disk(r + 1)) > 0
    cand = (wobble >= o.persist_fraction) & inner & ~near_fixed
    n, lab, stats, _ = cv2.connectedComponentsWithStats(cand.astype(np.uint8), connectivity=8)
    out = np.zeros(shape, bool)
    if n <= 1:
        return out, out
    ring_r = max(4, int(round(o.wobble_ring_px * min(shape))))
    still = std < o.wobble_still_grey
    moving = std > o.moving_grey
    boxes: list[tuple[int, int, int, int, np.ndarray]] = []
    for k in np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= max(1, o.min_component_px)):
        if k == 0:
            continue
        x, y, w, h = (int(v) for v in stats[k, :4])
        pad = r + ring_r + 1
        y0, y1 = max(0, y - pad), min(shape[0], y + h + pad)
        x0, x1 = max(0, x - pad), min(shape[1], x + w + pad)
        piece = (lab[y0:y1, x0:x1] == k).astype(np.uint8)
        ring = ((cv2.dilate(piece, _disk(r + ring_r)) > 0)
                & ~(cv2.dilate(piece, _disk(r)) > 0) & base[y0:y1, x0:x1])
        m = int(ring.sum())
        if (m and still[y0:y1, x0:x1][ring].sum() >= o.still_side * m
                and moving[y0:y1, x0:x1][ring].sum() >= o.moving_side * m):
            out[y0:y1, x0:x1] |= piece > 0
            boxes.append((y0, y1, x0, x1, piece))
    if not boxes:
        return out, out
    # the still side must be enclosed by these edges and the border band (a body's plain
    # inside), not a plain stretch of the scene that goes on past them; the persistent edges
    # do not count: with a rigid body's help, slow far lines beside it would enclose scene
    _, filled = _enclosed_still(out, std, base, inner, o, o.wobble_still_grey)
    kt = _disk(_close_radius(shape, o) + 1)
    kept = np.zeros(shape, bool)
    for y0, y1, x0, x1, piece in boxes:
        if (filled[y0:y1, x0:x1] & (cv2.dilate(piece, kt) > 0)).any():
            kept[y0:y1, x0:x1] |= piece > 0
    if not kept.any():
        return kept, kept
    _, inside = _enclosed_still(kept, std, base, inner, o, o.wobble_still_grey)
    return kept, inside


def _still_hulls(thick: np.ndarray, still: np.ndarray, base: np.ndarray,
                 limit: float) -> np.ndarray:
    """The still pixels inside the convex hull of each connected piece of ``thick`` (a body's
    outline with gaps, where the enclosed-area test leaks)."""
    n, lab, stats, _ = cv2.connectedComponentsWithStats(thick.astype(np.uint8), connectivity=8)
    hulls = np.zeros(thick.shape, np.uint8)
    ys, xs = np.nonzero(lab)
    order = np.argsort(lab[ys, xs], kind="stable")
    pts = np.stack([xs[order], ys[order]], 1).astype(np.int32)
    bounds = np.concatenate([[0], np.cumsum(stats[1:, cv2.CC_STAT_AREA])])
    for k in range(n - 1):
        hull = cv2.convexHull(pts[bounds[k]:bounds[k + 1]])
        if cv2.contourArea(hull) <= limit:
            cv2.fillConvexPoly(hulls, hull, 1)
    return (hulls > 0) & still & base


def _close_radius(shape: tuple[int, int], o: AutoMaskOptions) -> int:
    return max(2, int(round(o.close_px * min(shape))))


def _enclosed_still(persistent: np.ndarray, std: np.ndarray, base: np.ndarray,
                    inner: np.ndarray, o: AutoMaskOptions, still_grey: float | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Bool ``(H, W)`` ``(thick, filled)``: the persistent edges thickened into walls, and the
    still areas (median std below ``still_grey``, default ``o.still_grey``) that they and the
    border band enclose."""
    still_grey = o.still_grey if still_grey is None else still_grey
    # dilation, not closing: closing does not bridge the gaps of a one-pixel-thin edge
    kc = _disk(_close_radius(persistent.shape, o))
    thick = cv2.dilate(persistent.astype(np.uint8), kc) > 0
    # areas of the usable region cut off by the walls and the border band (where edges were
    # not looked for: a body that reaches the rim or the image border is enclosed there)
    walls = thick | ~inner
    free = (base & ~walls).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(free, connectivity=4)
    area = stats[:, cv2.CC_STAT_AREA]
    limit = o.max_fill_fraction * max(1, int(base.sum()))
    cand = np.flatnonzero((area > 0) & (area <= limit))
    cand = cand[cand > 0]
    fill = np.zeros(n, bool)
    if len(cand):
        near = cv2.dilate(thick.astype(np.uint8), _disk(1)) > 0
        touching = np.zeros(n, bool)
        touching[np.unique(lab[near & (free > 0)])] = True
        flat = lab.ravel()
        order = np.argsort(flat, kind="stable")
        starts = np.searchsorted(flat[order], cand)
        ends = np.searchsorted(flat[order], cand, side="right")
        flat_std = std.ravel()[order]
        for k, i0, i1 in zip(cand, starts, ends, strict=True):
            if touching[k] and np.median(flat_std[i0:i1]) < still_grey:
                fill[k] = True
    return thick, fill[lab]


def _regions(persistent: np.ndarray, std: np.ndarray, base: np.ndarray, inner: np.ndarray,
             o: AutoMaskOptions, inside: np.ndarray) -> np.ndarray:
    """Bool ``(H, W)``: the persistent edges thickened into walls, the still areas they
    enclose and ``inside`` (what the wobbling edges enclose) filled, grown by the margin."""
    side = min(persistent.shape)
    kc = _disk(_close_radius(persistent.shape, o))
    thick, filled = _enclosed_still(persistent, std, base, inner, o)
    limit = o.max_fill_fraction * max(1, int(base.sum()))
    region = thick | filled | inside | _still_hulls(thick, std < o.still_grey, base, limit)
    # the border band is masked only where it touches a masked region
    region |= ~inner & (cv2.dilate(region.astype(np.uint8), kc) > 0)
    m = int(round(o.margin_px * side))
    if m > 0:
        region = cv2.dilate(region.astype(np.uint8), _disk(m)) > 0
    return region & base


def static_mask(frames: Sequence[np.ndarray], camera: CameraModel,
                user_mask: np.ndarray | None = None,
                options: AutoMaskOptions | None = None) -> AutoMask:
    """The mask of the regions that stay put while the scene moves (module docstring).

    Args:
        frames: a sample of ``(H, W)`` uint8 grey frames spread over the sequence (20-60 is
            plenty; at least ``options.min_frames``).
        camera: the camera; its valid mask bounds the search.
        user_mask: optional ``(H, W)`` array, nonzero where the image may be used.
        options: thresholds (:class:`AutoMaskOptions`).

    Returns:
        :class:`AutoMask`; its ``mask`` already includes ``user_mask``.
    """
    o = options or AutoMaskOptions()
    h, w = camera.height, camera.width
    base, inner = _usable_region(camera, user_mask, o.border_px)
    keep = np.ones((h, w), bool) if user_mask is None else np.asarray(user_mask) > 0
    if len(frames) < o.min_frames:
        return AutoMask(keep, False, 0.0, 0.0,
                        f"not applied: {len(frames)} frames sampled, at least {o.min_frames} "
                        "needed")
    raw, near, std, wobble = _edge_statistics(frames, (h, w), o)
    persistent, static_frac = _persistent_edges(raw, near, inner, o)
    if static_frac > o.static_edge_limit:
        return AutoMask(keep, False, 0.0, static_frac,
                        f"not applied: the camera barely moves ({100 * static_frac:.0f} % of "
                        "the edges stay put)")
    wobbling, inside = (_wobbling_edges(wobble, persistent, std, base, inner, o)
                        if wobble is not None else (np.zeros((h, w), bool),) * 2)
    total = float(raw[inner].sum())
    wobble_frac = float(raw[wobbling & ~persistent].sum()) / total if total > 0 else 0.0
    if not (persistent.any() or wobbling.any()):
        return AutoMask(keep, False, 0.0, static_frac,
                        "nothing masked: no edges stay put while the scene moves")
    region = _regions(persistent | wobbling, std, base, inner, o, inside)
    frac = float(region.sum()) / max(1, int(base.sum()))
    if frac > o.max_masked_fraction:
        return AutoMask(keep, False, 0.0, static_frac,
                        f"not applied: the regions that stay put would cover {100 * frac:.0f} % "
                        "of the image (too much to be the camera's mount or operator)",
                        wobble_frac)
    said = "edges that stay put while the scene moves"
    if wobble_frac > 0:
        said += (f", or within {_wobble_radius((h, w), o)} px ({100 * wobble_frac:.1f} % of the "
                 "edges)")
    return AutoMask(keep & ~region, True, frac, static_frac,
                    f"masked {100 * frac:.1f} % of the image: {said}", wobble_frac)
