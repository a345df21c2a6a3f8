"""Straight-line extraction in omnidirectional images (docs/method.md §2, paper Sec. III).

Canny edges -> corner rejection by the ratio of the principal gradients in a small window ->
sub-pixel edge positions -> connected edge segments -> unit rays through the camera model ->
a great-circle (plane through the viewpoint) fit per segment by RANSAC -> the paper's test:
a segment is a straight line if more than half of its points satisfy ``(r . n)^2 < l_th``
(eq. 3). The plane's unit normal ``n`` is the line's NV in the camera frame (sign arbitrary).

Everything works on all pixels and segments at once: RANSAC scores all hypotheses of all
segments together and the least-squares refits use batched 3x3 scatter matrices. The per-point
loops are compiled (``_edges.c``, :mod:`omni_sfm.lines.edge_kernels`): the grey-level
histogram, Sobel and the glue around Canny (int16 gradients, the masked edge pixels, the
long-chain test), the corner test, the orientation-linked components, the sub-pixel positions,
the RANSAC hypotheses, scores and inliers, the scatter matrices, the arc parameters, the order
along each line, the gap cuts, merges and end trimming and the final per-line figures, each with
the arithmetic of the OpenCV or numpy code it replaced (the same bits;
``tests/test_edge_kernels.py``). The planes' normals are the smallest eigenvectors of the
scatter matrices by Jacobi rotations in C (as accurate as ``np.linalg.eigh``, not its bits).
Canny, the blur and ``arctan2`` stay OpenCV's and numpy's.

Thresholds that are angles on the sphere are set in *pixels* and converted with the camera's
local angular pixel scale (the angle between the rays of neighbouring pixels), so the same
defaults work for a 800x600 hyperboloid image and a 1600x800 equirectangular one.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from omni_sfm.cameras.base import CameraModel
from omni_sfm.cameras.rig import RigCamera
from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray
from omni_sfm.lines import edge_kernels

IntArray = np.ndarray

LONG_CHAIN_TEST_FRACTION = 0.05
"""Where more than this share of the searched pixels are edge points (surface texture), the
edge points outside 8-connected chains of at least ``min_points`` points are dropped before the
corner test, which then costs less than the labelling of the chains (below it the labelling
costs more than it saves)."""

DENSE_EDGES_FRACTION = 0.05
"""Where the last frame's edge points were more than this share of the searched pixels, the
next frame's Canny runs compiled (``edge_kernels.canny``, the same edges as ``cv2.Canny``):
0.66 against 0.27 ms on the corridor (2.4 % edge points), 1.19 against 2.27 ms on the
textured room (21 %), 800x600."""


@dataclass(frozen=True, kw_only=True)
class ExtractionOptions:
    """Parameters of :class:`LineExtractor`; pixel units unless stated."""

    blur_sigma: float = 1.0
    """Gaussian pre-smoothing before edge detection (px); 0 disables it."""
    gamma: float = 1.0
    """Decode the image's transfer curve before edge detection, ``I_lin = 255 (I/255)^gamma``
    (2.2 for sRGB-encoded video: blur mixes light linearly, so edges are located where they
    are in linear intensity); 1 uses the values as they are."""
    canny_low: float = 20.0
    """Canny hysteresis low threshold on the L2 magnitude of the 3x3 Sobel gradient of the
    smoothed image (grey levels; a sharp step of ``s`` grey levels gives ``4 s`` unsmoothed,
    about ``2.5 s`` after a 1 px blur)."""
    canny_high: float = 50.0
    """Canny hysteresis high threshold (same units as ``canny_low``)."""
    reference_contrast: float = 80.0
    """Contrast normalisation: both Canny thresholds are scaled by ``min(1, c /
    reference_contrast)``, ``c`` the frame's contrast (:meth:`LineExtractor.image_stats`), so a
    dark or low-contrast frame finds the edges a normal one would; frames with at least this
    contrast (most footage; every frame of the rendered scenes) use the thresholds as they
    are. 0 disables the normalisation."""
    min_threshold_scale: float = 0.1
    """Lowest factor of the normalisation: below it the thresholds would pick up the steps of a
    smooth shading quantised to 8 bits (one grey level gives about 2.5 after the blur)."""
    min_contrast: float = 4.0
    """A frame whose contrast (as for ``reference_contrast``) is below this gives no lines: in
    a frame that dark or flat the 8-bit steps are the edges, and the few lines found were
    mostly false (2 % of the demo corridor's brightness, contrast 2: 21 of 40 frames, 10 deg
    off). 0 disables."""
    corner_ratio: float = 2.0
    """Keep an edge point if the ratio of the principal RMS gradients in a small window (the
    square root of the eigenvalue ratio of the second-moment matrix, linear in intensity like
    the Hessian eigenvalues of the paper) is at least this; lower ratios are corners, junctions
    and line ends. The paper's 10 strips every edge beside surface texture (the window sees the
    texture's gradients); with ``link_angle_deg`` and ``trim_ends_px`` doing the splitting at
    junctions, 2 keeps them and still drops true corners (docs/frontend.md)."""
    tensor_sigma: float = 1.0
    """Gaussian window of the second-moment matrix (px)."""
    link_angle_deg: float = 15.0
    """Two 8-neighbouring edge points belong to one segment only if their gradient
    orientations (modulo 180 deg) differ by less than this; 0 links all neighbours. Splits
    chains where a line meets a texture blob or another edge without having to drop the
    points around the junction."""
    min_points: int = 40
    """Fewest edge points of a segment and of an accepted line (about its length in px); short
    lines carry most of the false NVs (docs/frontend.md)."""
    min_arc_px: float = 20.0
    """Fewest pixels a line's arc spans, measured with the larger side of the local pixel
    (``s(p)`` below): near the poles of an equirectangular image many pixels span a tiny
    angle and give a poorly determined NV."""
    line_threshold_px: float = 1.0
    """``l_th`` of eq. (3) as a distance from the great circle in pixels at that point:
    ``(r . n)^2 < (line_threshold_px * s(p))^2`` with ``s(p)`` the local angle per pixel."""
    ransac_hypotheses: int = 16
    """RANSAC hypotheses (pairs of points) per segment and round."""
    refine_iterations: int = 2
    """Least-squares refits on the inliers after RANSAC."""
    peel_rounds: int = 3
    """Rounds of peeling: the outliers of an accepted segment (and, see ``peel_min_points``,
    of a rejected long one) are re-segmented and fitted again, so one edge chain can hold
    several lines."""
    peel_min_points: int = 60
    """A segment that fails the more-than-half test still yields its best line if that line
    has at least this many inliers (long lines joined by a smooth bend); 0 disables."""
    max_gap_px: float = 4.0
    """A line's inliers are split where consecutive points along the circle are further apart
    than this (px); pieces shorter than ``min_points`` are dropped."""
    merge_angle_deg: float = 0.3
    """Merge two lines of one frame whose normals agree within this angle and whose arcs do not
    overlap (a line split by an occluder or by the equirectangular seam)."""
    merge_gap_deg: float = 20.0
    """Largest gap along the great circle between two pieces that are merged (degrees)."""
    trim_ends_px: float = 5.0
    """Drop the points within this distance (px, along the line) of each end of a line before
    its final fit: where a line meets a corner or a texture blob, its last points bend
    towards the other edge and tilt the NV (0: keep them)."""
    edge_noise_px: float = 0.5
    """Standard deviation of an edge point's position across the edge (px), the noise model
    behind each NV's uncertainty (:attr:`ExtractedLines.normal_sigma`). Only the ratios of
    the uncertainties matter to the estimator, which estimates the overall noise level."""
    mask_erode_px: int = 4
    """Erode the valid mask by this much, so the mask border (mirror rim, the camera's own
    reflection, the image border) gives no edges."""
    seed: int = 0
    """Seed of the RANSAC sampler (results are deterministic for a given image)."""


@dataclass(frozen=True)
class ExtractedLines:
    """The straight lines of one image.

    Attributes:
        normals: ``(L, 3)`` unit NVs in the camera frame (sign arbitrary).
        offsets: ``(L + 1,)`` line ``l`` owns points ``offsets[l]:offsets[l + 1]``.
        points_uv: ``(P, 2)`` sub-pixel inlier edge points (OpenCV pixels), ordered along each
            line.
        point_rays: ``(P, 3)`` their unit rays.
        endpoint_rays: ``(L, 2, 3)`` unit rays of the two ends, projected onto the great circle.
        endpoint_uv: ``(L, 2, 2)`` pixels of the two extreme inlier points.
        num_support: ``(L,)`` inlier count.
        residual_px: ``(L,)`` RMS distance of the inliers from the great circle, in pixels.
        arc_deg: ``(L,)`` angle subtended by the line at the viewpoint, degrees.
        normal_sigma: ``(L, 2)`` standard deviations (radians) of the NV's error along the
            middle ray of the line (projected into its plane) and along ``normal x ray``,
            from the least-squares fit with ``edge_noise_px`` of noise per point (times the
            local angle per pixel): ``1 / sqrt(sum_i (r_i . v)^2 / s_i^2)`` for each direction
            ``v``. Across is the larger, by about ``sqrt(12) / arc`` (radians): a short
            line pins its plane's tilt about its own ray poorly.
        num_edge_points: Canny edge points inside the mask.
        num_corner_points: edge points rejected as corner-like (where the frame has many edge
            points, see :data:`LONG_CHAIN_TEST_FRACTION`, among those in chains of at least
            ``min_points`` points only).
        num_segments: connected segments with at least ``min_points`` points (first round).
        num_rejected: segments that failed the straightness test.
        median_grey: median grey level (0-255) of the image inside the mask (NaN: no pixels).
        contrast: spread of its grey levels inside the mask (:meth:`LineExtractor.image_stats`).
        threshold_scale: the factor the Canny thresholds were scaled by for this image
            (``ExtractionOptions.reference_contrast``).
    """

    normals: FloatArray
    offsets: IntArray
    points_uv: FloatArray
    point_rays: FloatArray
    endpoint_rays: FloatArray
    endpoint_uv: FloatArray
    num_support: IntArray
    residual_px: FloatArray
    arc_deg: FloatArray
    normal_sigma: FloatArray
    num_edge_points: int
    num_corner_points: int
    num_segments: int
    num_rejected: int
    median_grey: float = float("nan")
    contrast: float = float("nan")
    threshold_scale: float = 1.0

    @property
    def num_lines(self) -> int:
        return int(self.normals.shape[0])

    def line_of_point(self) -> IntArray:
        """``(P,)`` index of the line owning each point."""
        return np.repeat(np.arange(self.num_lines), np.diff(self.offsets))


def usable_pixels(camera: CameraModel, mask: np.ndarray | None) -> np.ndarray:
    """``(H, W)`` bool: the camera's valid pixels where ``mask`` (if given, nonzero = use the
    pixel, the camera's size) allows them. A mask of another size is an OmniSfmError."""
    valid = np.asarray(camera.valid_mask(), dtype=bool).copy()
    if mask is not None:
        m = np.asarray(mask)
        h, w = camera.height, camera.width
        if m.shape != (h, w):
            raise OmniSfmError(f"mask is {m.shape[1]}x{m.shape[0]} px but the camera is "
                               f"{w}x{h} px")
        valid &= m > 0
    return valid


def angular_pixel_scale(camera: CameraModel) -> np.ndarray:
    """``(H, W)`` float32: angle (rad) between a pixel's ray and its right/lower neighbour's,
    the larger of the two; NaN where the pixel or both neighbours are invalid."""
    r = camera.pixel_grid_rays()
    with np.errstate(invalid="ignore"):
        du = np.full(r.shape[:2], np.nan)
        dv = np.full(r.shape[:2], np.nan)
        du[:, :-1] = np.linalg.norm(r[:, 1:] - r[:, :-1], axis=2)
        dv[:-1, :] = np.linalg.norm(r[1:, :] - r[:-1, :], axis=2)
        du[:, -1] = du[:, -2]
        dv[-1, :] = dv[-2, :]
        s = np.fmax(du, dv)
    return s.astype(np.float32)


def _scatter(rays: FloatArray, weight: np.ndarray | None, seg: IntArray,
             nseg: int) -> FloatArray:
    """``(S, 3, 3)`` sums of ``w r r^T`` per segment (``seg`` need not be sorted; ``weight``
    None: ones), in C with np.bincount's sums."""
    return edge_kernels.scatter(rays, weight, seg, nseg)


@dataclass(frozen=True)
class _EdgePoints:
    """The line-like edge points of one image (:meth:`LineExtractor._edge_points`):
    ``pix`` ``(N, 2)`` integer (x, y) pixels, ``theta`` ``(N,)`` gradient orientation (rad,
    modulo pi), ``grad`` ``(N,)`` complex64 gradient ``dx + i dy`` there, ``dxy`` the
    ``(h, w)`` complex64 gradient image of the region the edges were searched in, whose
    top-left pixel is ``origin`` (x, y), and ``counts`` (Canny edge points, corner-like points
    rejected)."""

    pix: IntArray
    theta: FloatArray
    grad: np.ndarray
    dxy: np.ndarray
    origin: tuple[int, int]
    counts: dict[str, int]

    def subpixel(self, sel: IntArray) -> FloatArray:
        """``(len(sel), 2)`` sub-pixel positions of the points ``sel``: the vertex of the
        parabola through the gradient magnitude across the edge."""
        return edge_kernels.subpixel(self.dxy, self.pix, self.grad, sel, self.origin)


class LineExtractor:
    """Straight-line extractor for one camera (per-camera tables are computed once).

    ``mask``: optional ``(H, W)`` array, nonzero where the image may be used (combined with the
    camera's valid mask).
    """

    _segment_points_only = True
    """Compute sub-pixel positions and rays for the points of the first round's segments only
    (False: for all line-like edge points, the same lines more slowly; for tests)."""

    def __init__(self, camera: CameraModel, options: ExtractionOptions | None = None,
                 mask: np.ndarray | None = None) -> None:
        self.camera = camera
        self.options = options or ExtractionOptions()
        o = self.options
        if o.min_points < 3:
            raise ValueError(f"min_points must be at least 3, got {o.min_points}")
        if not 0 <= o.canny_low <= o.canny_high:
            raise ValueError(f"need 0 <= canny_low <= canny_high, got {o.canny_low} and "
                             f"{o.canny_high}")
        if o.reference_contrast < 0 or not 0 < o.min_threshold_scale <= 1:
            raise ValueError(f"need reference_contrast >= 0 and 0 < min_threshold_scale <= 1, "
                             f"got {o.reference_contrast} and {o.min_threshold_scale}")
        valid = usable_pixels(camera, mask)
        self.scale = angular_pixel_scale(camera)
        valid &= np.isfinite(self.scale)
        e = int(o.mask_erode_px)
        if e > 0:
            padded = cv2.copyMakeBorder(valid.astype(np.uint8), e, e, e, e,
                                        cv2.BORDER_CONSTANT, value=0)
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * e + 1, 2 * e + 1))
            valid = cv2.erode(padded, k)[e:-e, e:-e] > 0
        self.search_mask = valid.astype(np.uint8) * 255
        self._lut = None if o.gamma == 1.0 else \
            (255.0 * (np.arange(256) / 255.0) ** o.gamma).astype(np.float32)
        rad = max(1, int(np.ceil(1.5 * o.tensor_sigma)))
        self._win_yx = np.mgrid[-rad : rad + 1, -rad : rad + 1]
        wy, wx = self._win_yx
        # edge points need a full tensor window and bilinear neighbours inside the image
        b = rad + 2
        self.search_mask[:b] = 0
        self.search_mask[-b:] = 0
        self.search_mask[:, :b] = 0
        self.search_mask[:, -b:] = 0
        # edges are searched in the bounding box of the search mask and a margin (a
        # hyperboloid's mirror: 587x588 of 800x600 pixels); the margin holds every pixel that
        # the blur, the gradients, Canny's suppression, the tensor window and the sub-pixel
        # interpolation read for a pixel in the mask. The one difference from searching the
        # whole image: Canny's hysteresis no longer keeps a weak edge in the mask whose only
        # strong pixels lie beyond the margin, outside the usable area.
        x, y, bw, bh = cv2.boundingRect(self.search_mask)
        m = (2 * int(np.ceil(2.0 * o.blur_sigma)) + 1) // 2 + rad + 4
        self._set_region((slice(max(0, y - m), min(camera.height, y + bh + m)),
                          slice(max(0, x - m), min(camera.width, x + bw + m))))
        g = np.exp(-(wx**2 + wy**2).ravel() / (2.0 * o.tensor_sigma**2))
        self._win_w = (g / g.sum()).astype(np.float32)
        # pixels where edges are searched: the valid area and the user's mask, eroded
        self.valid_pixels = int(np.count_nonzero(self.search_mask))
        # whether the last frame's edges were dense (picks the faster Canny, see _edge_points)
        self._dense_edges = False

    def _set_region(self, roi: tuple[slice, slice]) -> None:
        """Search edges in ``image[roi]`` (two slices with start and stop) only."""
        self._roi = roi
        wy, wx = self._win_yx
        self._win_flat = (wy * (roi[1].stop - roi[1].start) + wx).ravel().astype(np.int64)

    def image_stats(self, gray: np.ndarray) -> tuple[float, float, float]:
        """``(median grey, contrast, threshold scale)`` of an ``(H, W)`` uint8 image inside the
        search mask (see :class:`ExtractedLines`); NaN, NaN, 1 where the mask is empty.

        Contrast: the larger of the spread between the 5th and 95th percentiles of the grey
        levels and half the spread between the 0.5th and 99.5th, so that a flat frame with a few
        strong edges (a white wall with dark lines) counts as contrasted (one 256-bin
        histogram, in C: about 0.1 ms for 800x600)."""
        if self.valid_pixels == 0:
            return float("nan"), float("nan"), 1.0
        hist = edge_kernels.histogram(gray, self.search_mask, self._roi)
        cdf = np.cumsum(hist) / self.valid_pixels
        q = np.searchsorted(cdf, [0.005, 0.05, 0.5, 0.95, 0.995])
        lut = np.arange(256.0) if self._lut is None else self._lut
        contrast = float(max(q[3] - q[1], (q[4] - q[0]) / 2))
        o = self.options
        if o.reference_contrast <= 0:
            return float(q[2]), contrast, 1.0
        lin = float(max(lut[q[3]] - lut[q[1]], (lut[q[4]] - lut[q[0]]) / 2))
        scale = float(np.clip(lin / o.reference_contrast, o.min_threshold_scale, 1.0))
        return float(q[2]), contrast, scale

    # -- public ---------------------------------------------------------------------------
    def extract(self, image: np.ndarray) -> ExtractedLines:
        """Lines of one ``(H, W)`` 8-bit grey image (a colour image is converted)."""
        gray = self._gray(image)
        median, contrast, scale = self.image_stats(gray)
        if contrast < self.options.min_contrast:  # NaN: an empty mask, which finds nothing anyway
            z = np.zeros(0, np.int64)
            lines = self._package(z, z, np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0),
                                  {"edge": 0, "corner": 0}, 0, 0)
        else:
            edges = self._edge_points(gray, scale)
            lines = self._fit_lines(edges)
        return replace(lines, median_grey=median, contrast=contrast, threshold_scale=scale)

    # -- stages ---------------------------------------------------------------------------
    def _gray(self, image: np.ndarray) -> np.ndarray:
        img = np.asarray(image)
        if img.ndim == 3 and img.shape[2] in (3, 4):
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3
                               else cv2.COLOR_BGRA2GRAY)
        if img.ndim != 2:
            raise ValueError(f"image must be (H, W) or (H, W, 3), got {img.shape=}")
        if img.shape != (self.camera.height, self.camera.width):
            raise OmniSfmError(f"image is {img.shape[1]}x{img.shape[0]} px but the camera is "
                               f"{self.camera.width}x{self.camera.height} px")
        if img.dtype != np.uint8:
            img = np.clip(img, 0, 255).astype(np.uint8)
        return img

    def _edge_points(self, gray: np.ndarray, scale: float = 1.0) -> _EdgePoints:
        """Line-like edge points (see :class:`_EdgePoints`; their sub-pixel positions are
        computed later, by :meth:`_EdgePoints.subpixel`, for the points that need them).
        ``scale`` multiplies the Canny thresholds (contrast normalisation)."""
        o = self.options
        gray = gray[self._roi]
        x0, y0 = self._roi[1].start, self._roi[0].start
        # float pipeline: rounding the smoothed image to 8 bits would cost sub-pixel accuracy
        img = self._lut[gray] if self._lut is not None else gray.astype(np.float32)
        if o.blur_sigma > 0:
            k = 2 * int(np.ceil(2.0 * o.blur_sigma)) + 1
            img = cv2.GaussianBlur(img, (k, k), o.blur_sigma)
        # Sobel's derivatives as Canny wants them, 16-bit: scaled by 8 (|Sobel| <= 1020) to keep
        # 1/8 resolution; and dx, dy interleaved as one complex64 image for the corner test and
        # the sub-pixel positions (in C, one pass; cv2.Sobel's bits)
        dx16, dy16, dxy_img = edge_kernels.sobel_gradients(img)
        low, high = 8.0 * scale * o.canny_low, 8.0 * scale * o.canny_high
        # two implementations of one Canny (the same edges, tested): OpenCV's skips quickly
        # over weak gradients, the compiled one is twice as fast where edges are dense
        # (texture); which one runs follows the previous frame's edges, and changes only time
        if self._dense_edges:
            edges = edge_kernels.canny(dx16, dy16, low, high)
        else:
            edges = cv2.Canny(dx16, dy16, low, high, L2gradient=True)
        # the edge pixels inside the search mask (row by row, as cv2.findNonZero) and their
        # flat indices in the region, in C
        pix, flat = edge_kernels.edge_points(edges, self.search_mask, (x0, y0))
        n_edge = len(pix)
        self._dense_edges = n_edge > DENSE_EDGES_FRACTION * self.valid_pixels
        if n_edge > LONG_CHAIN_TEST_FRACTION * self.valid_pixels:
            # a segment is part of one 8-connected chain of edge points: the points of chains
            # shorter than min_points can never be in a line (half the edge points of a
            # textured image), so the corner test and all that follows skip them; the lines
            # are the same either way, only num_corner_points counts fewer points (the chains
            # by a union-find over the points, in C)
            _, pix, flat = edge_kernels.long_chains(pix, flat, edges.shape, o.min_points)
        # second-moment matrix over a Gaussian window, evaluated only at the edge points (the
        # search mask keeps them far enough from the image border for the window), in C
        n_tested = len(pix)
        pix, g = edge_kernels.corner_test(dxy_img, pix, flat, self._win_flat, self._win_w,
                                          o.corner_ratio**2, (x0, y0))
        # numpy's float32 arctan2 (its own vectorised one, not the C library's: the orientations
        # stay the same bits), the remainder by pi in C
        theta = edge_kernels.mod_pi(np.arctan2(g.imag, g.real))
        return _EdgePoints(pix=pix, theta=theta, grad=g, dxy=dxy_img, origin=(x0, y0),
                           counts={"edge": n_edge, "corner": n_tested - len(pix)})

    def _segments(self, pix: IntArray, idx: IntArray,
                  theta: FloatArray) -> tuple[IntArray, IntArray, IntArray]:
        """8-connected segments of the points ``pix[idx]`` with at least ``min_points`` points
        (neighbours linked only where their orientations ``theta`` agree, see
        ``link_angle_deg``).

        Returns the kept indices sorted by segment, their segment (0..S-1) and the counts.
        """
        p = _rows(pix, idx)
        # (the reductions of an (N, 2) array along its first axis are slow; of its columns not)
        x0, y0 = int(p[:, 0].min()) - 1, int(p[:, 1].min()) - 1
        x1, y1 = int(p[:, 0].max()) + 1, int(p[:, 1].max()) + 1
        if self.options.link_angle_deg > 0:
            n, lab = _oriented_components(p - [x0, y0], (y1 - y0 + 1, x1 - x0 + 1),
                                          theta[idx], np.radians(self.options.link_angle_deg))
        else:
            img = np.zeros((y1 - y0 + 1, x1 - x0 + 1), np.uint8)
            img[p[:, 1] - y0, p[:, 0] - x0] = 1
            n, lab_img = cv2.connectedComponents(img, connectivity=8, ltype=cv2.CV_32S)
            lab = lab_img[p[:, 1] - y0, p[:, 0] - x0]
        area = np.bincount(lab, minlength=n)
        sel = area[lab] >= self.options.min_points
        idx, lab = idx[sel], lab[sel]
        order = _stable_order(lab)
        idx, lab = idx[order], lab[order]
        seg, cnt = _dense_sorted(lab)
        return idx, seg, cnt

    def _fit_lines(self, edges: _EdgePoints) -> ExtractedLines:
        o = self.options
        rng = np.random.default_rng(o.seed)
        pix, theta, counts = edges.pix, edges.theta, edges.counts
        # Only the points of the first round's segments are ever fitted (later rounds
        # re-segment subsets of them), so the sub-pixel positions and rays are computed for
        # those alone (a tenth of the edge points on a textured image). Points whose ray is not
        # finite are dropped before segmenting, which can split a segment: if a segment has
        # such a point, everything is computed for all points, as that requires.
        first = self._segments(pix, np.arange(len(pix)), theta) \
            if len(pix) >= o.min_points and self._segment_points_only else None
        if first is not None:
            use = np.zeros(len(pix), bool)
            use[first[0]] = True
            sub = np.flatnonzero(use)
            uv = edges.subpixel(sub)
            rays = self.camera.rays_from_pixels(uv) if len(uv) else np.zeros((0, 3))
            if np.isfinite(rays).all():
                new = np.cumsum(use) - 1  # monotone: the points keep their order
                pix, theta = _rows(pix, sub), theta[sub]
                first = (new[first[0]], first[1], first[2])
            else:
                first = None
        if first is None:
            uv = edges.subpixel(np.arange(len(pix)))
            rays = self.camera.rays_from_pixels(uv) if len(uv) else np.zeros((0, 3))
            ok = np.isfinite(rays).all(axis=1)
            uv, pix, rays, theta = uv[ok], pix[ok], rays[ok], theta[ok]
        # angle (rad) per pixel at each point; l_th of eq. (3) is (line_threshold_px * scale)^2
        scale = np.take(self.scale.ravel(), pix[:, 1].astype(np.int64) * self.camera.width
                        + pix[:, 0]).astype(np.float64)
        tol = o.line_threshold_px * scale
        pool = np.arange(len(uv))
        piece_idx: list[IntArray] = []
        piece_lab: list[IntArray] = []
        piece_n: list[FloatArray] = []
        n_pieces = n_segments = n_rejected = 0
        for rnd in range(max(1, o.peel_rounds)):
            if len(pool) < o.min_points:
                break
            idx, seg, cnt = first if rnd == 0 and first is not None else \
                self._segments(pix, pool, theta)
            if len(idx) == 0:
                break
            nseg = len(cnt)
            normals, inl, n_in = self._ransac(_rows(rays, idx), tol[idx], seg, cnt, rng)
            accept = (2 * n_in > cnt) & (n_in >= o.min_points)
            take = accept | ((n_in >= o.peel_min_points) if o.peel_min_points > 0 else accept)
            if rnd == 0:
                n_segments, n_rejected = nseg, int((~accept).sum())
            # outliers of taken segments go back to the pool for the next round
            out = take[seg] & ~inl
            n_out = np.bincount(seg[out], minlength=nseg)
            pool = idx[out & (n_out[seg] >= o.min_points)]
            sel = take[seg] & inl
            pi, pl, pn = self._split_gaps(idx[sel], seg[sel], normals, rays, scale)
            piece_idx.append(pi)
            piece_lab.append(pl + n_pieces)
            piece_n.append(pn)
            n_pieces += len(pn)
        if not piece_idx:
            return self._package(np.zeros(0, np.int64), np.zeros(0, np.int64), rays, uv, scale,
                                 counts, n_segments, n_rejected)
        idx = np.concatenate(piece_idx)
        lab = np.concatenate(piece_lab)
        lab = self._merge(idx, lab, np.concatenate(piece_n), rays)
        if o.trim_ends_px > 0:
            idx, lab = self._trim_ends(idx, lab, rays, scale)
        return self._package(idx, lab, rays, uv, scale, counts, n_segments, n_rejected)

    def _ransac(self, rays: FloatArray, tol: FloatArray, seg: IntArray, cnt: IntArray,
                rng: np.random.Generator) -> tuple[FloatArray, np.ndarray, FloatArray]:
        """Great circle per segment: MSAC over pair hypotheses, then LS refits on inliers.

        ``rays`` sorted by segment ``seg`` (0..S-1) with counts ``cnt``. Returns ``(S, 3)``
        normals, the ``(N,)`` inlier mask of the final fit and ``(S,)`` the inliers' count
        per segment (float).
        """
        o = self.options
        nseg = len(cnt)
        start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        nh = max(1, o.ransac_hypotheses)
        ia = start[:, None] + (rng.random((nseg, nh)) * cnt[:, None]).astype(np.int64)
        ib = start[:, None] + (rng.random((nseg, nh)) * cnt[:, None]).astype(np.int64)
        # the unit normals r_a x r_b (float32, (3, S, H)) in C
        hyp_k, degenerate = edge_kernels.hypotheses(rays, ia, ib)
        # d = r . hyp[seg] (N, H), summed over x, y, z in that order as einsum does (the same
        # float32 numbers), the truncated quadratic (MSAC) cost and its sum per segment, in C
        r32 = np.ascontiguousarray(rays.T, dtype=np.float32)
        t2 = (tol * tol).astype(np.float32)
        _, seg_cost = edge_kernels.msac_costs(r32, hyp_k, seg, start, t2)
        seg_cost[degenerate] = np.inf
        best = np.argmin(seg_cost, axis=1)
        n = np.ascontiguousarray(hyp_k[:, np.arange(nseg), best].T, dtype=np.float64)
        # |r . n[seg]| < tol and the inliers' count per segment, in C
        inl, n_in = edge_kernels.inliers(rays, n, seg, tol)
        for _ in range(max(1, o.refine_iterations)):
            n_new = edge_kernels.smallest_eigenvector3(
                _scatter(rays, inl.astype(np.float64), seg, nseg))
            n = np.where((n_in >= 3)[:, None], n_new, n)
            inl, n_in = edge_kernels.inliers(rays, n, seg, tol)
        return n, inl, n_in

    def _split_gaps(self, idx: IntArray, seg: IntArray, normals: FloatArray, rays: FloatArray,
                    scale: FloatArray) -> tuple[IntArray, IntArray, FloatArray]:
        """Cut each segment's inliers where consecutive points along the great circle are more
        than ``max_gap_px`` apart; drop pieces under ``min_points``.

        Returns the kept point indices, a piece label per point (0..P-1) and ``(P, 3)`` the
        normal of each piece (its segment's).
        """
        o = self.options
        if len(idx) == 0:
            return idx, seg, np.zeros((0, 3))
        nseg = normals.shape[0]
        t = _arc_parameter(_rows(rays, idx), normals, seg, nseg)
        # the order by segment and t, the cuts and the pieces' sizes in C
        pos, piece, piece_seg = edge_kernels.gap_pieces(seg, t, scale[idx], nseg, o.max_gap_px,
                                                        o.min_points)
        return idx[pos], piece, _rows(normals, piece_seg)

    def _merge(self, idx: IntArray, lab: IntArray, normals: FloatArray,
               rays: FloatArray) -> IntArray:
        """Join pieces of one great circle (normals within ``merge_angle_deg``, arcs disjoint and
        at most ``merge_gap_deg`` apart). Returns the new label per point (0..L-1)."""
        o = self.options
        used, lab = _dense_labels(lab)
        nl = len(used)
        if nl < 2 or o.merge_angle_deg <= 0:
            return lab
        normals = normals[used]
        cosang = np.abs(normals @ normals.T)
        cand = np.argwhere(np.triu(cosang > np.cos(np.radians(o.merge_angle_deg)), 1))
        if isinstance(self.camera, RigCamera) and len(cand):
            # pieces seen by different lenses of a rig are not one observation: each lens sees
            # the line from its own centre
            some = np.zeros(nl, np.int64)
            some[lab] = idx
            lens = self.camera.lens_of_rays(_rows(rays, some))
            cand = cand[lens[cand[:, 0]] == lens[cand[:, 1]]]
        if len(cand) == 0:
            return lab
        # the gap of every candidate pair: the points of both pieces by their angle along the
        # great circle of the first, from the first's mean direction; the joins (union-find in
        # pair order), in C
        return edge_kernels.merge_labels(rays, idx, lab, normals, cand,
                                         np.radians(o.merge_gap_deg))[lab]

    def _trim_ends(self, idx: IntArray, lab: IntArray, rays: FloatArray,
                   scale: FloatArray) -> tuple[IntArray, IntArray]:
        """Drop the points within ``trim_ends_px`` of either end of each line (labels
        0..L-1); lines left with fewer than ``min_points`` points go. Returns new idx, labels."""
        nl = int(lab.max()) + 1 if len(lab) else 0
        if nl == 0:
            return idx, lab
        r = _rows(rays, idx)
        normals = edge_kernels.smallest_eigenvector3(_scatter(r, None, lab, nl))
        t = _arc_parameter(r, normals, lab, nl)
        # the ends (least and largest t), the points near them and the lines left short, in C
        pos, lab = edge_kernels.trim_ends(lab, t, scale[idx], nl, self.options.trim_ends_px,
                                          self.options.min_points)
        return idx[pos], lab

    def _package(self, idx: IntArray, lab: IntArray, rays: FloatArray, uv: FloatArray,
                 scale: FloatArray, counts: dict[str, int], n_segments: int,
                 n_rejected: int) -> ExtractedLines:
        nl = int(lab.max()) + 1 if len(lab) else 0
        if nl == 0:
            z3 = np.zeros((0, 3))
            return ExtractedLines(
                normals=z3, offsets=np.zeros(1, np.int64), points_uv=np.zeros((0, 2)),
                point_rays=z3, endpoint_rays=np.zeros((0, 2, 3)),
                endpoint_uv=np.zeros((0, 2, 2)), num_support=np.zeros(0, np.int64),
                residual_px=np.zeros(0), arc_deg=np.zeros(0), normal_sigma=np.zeros((0, 2)),
                num_edge_points=counts["edge"],
                num_corner_points=counts["corner"], num_segments=n_segments,
                num_rejected=n_rejected)
        # final normals: least squares on all points of each (merged) line
        r = _rows(rays, idx)
        normals = edge_kernels.smallest_eigenvector3(_scatter(r, None, lab, nl))
        t = _arc_parameter(r, normals, lab, nl)
        order = edge_kernels.order_by(lab, t, nl)
        idx, lab, t, r = idx[order], lab[order], t[order], _rows(r, order)
        # per line, in C: the point count, the end rays projected onto the circle, the RMS
        # residual, the arc, the mean pixel angle and the NV uncertainty (information of the
        # fit along the middle ray and across it)
        sizes, ends, resid, arc_rad, mean_scale, sigma = edge_kernels.package(
            r, normals, lab, t, scale[idx], self.options.edge_noise_px)
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        first, last = offsets[:-1], offsets[1:] - 1
        # the arc in units of the local pixel size: far below the point count where pixels are
        # much narrower one way than the other (near the poles of an equirectangular image)
        short = arc_rad / mean_scale < self.options.min_arc_px
        if short.all():
            z = np.zeros(0, np.int64)
            return self._package(z, z, rays, uv, scale, counts, n_segments, n_rejected)
        if short.any():
            # the other lines as they are (fitting them again on the same points, in their
            # new order, changes their numbers by round-off only)
            line = ~short
            keep = line[lab]
            idx = idx[keep]
            r = np.compress(keep, r, axis=0)
            normals, ends, resid, arc_rad = normals[line], ends[line], resid[line], arc_rad[line]
            sizes, sigma = sizes[line], sigma[line]
            offsets = np.concatenate([[0], np.cumsum(sizes)])
            first, last = offsets[:-1], offsets[1:] - 1
        arc = np.degrees(arc_rad)
        return ExtractedLines(
            normals=normals, offsets=offsets, points_uv=_rows(uv, idx), point_rays=r,
            endpoint_rays=ends, endpoint_uv=np.stack([uv[idx[first]], uv[idx[last]]], 1),
            num_support=sizes, residual_px=resid, arc_deg=arc,
            normal_sigma=sigma,
            num_edge_points=counts["edge"], num_corner_points=counts["corner"],
            num_segments=n_segments, num_rejected=n_rejected)


def _rows(a: np.ndarray, index: IntArray) -> np.ndarray:
    """``a[index]`` for integer ``index`` along the first axis of a 2-D (or more) array:
    np.take does it several times faster than fancy indexing (10 against 36 us for 5,000 rows
    of 3 floats)."""
    return np.take(a, index, axis=0)


def _stable_order(key: IntArray) -> IntArray:
    """``np.argsort(key, kind="stable")`` of non-negative integers, on 16-bit keys where they
    fit (numpy's radix sort)."""
    if len(key) and key.min() >= 0 and key.max() < 2**15:
        key = key.astype(np.int16)
    return np.argsort(key, kind="stable")


def _dense_labels(lab: IntArray) -> tuple[IntArray, IntArray]:
    """``np.unique(lab, return_inverse=True)`` of non-negative integers, by counting instead of
    sorting: the labels used and each one's rank among them."""
    present = np.bincount(lab) > 0 if len(lab) else np.zeros(0, bool)
    return np.flatnonzero(present), (np.cumsum(present) - 1)[lab]


def _dense_sorted(lab: IntArray) -> tuple[IntArray, IntArray]:
    """Labels ``0..K-1`` in place of the non-decreasing ``lab``, and each one's count (what
    ``np.unique(lab, return_inverse=True, return_counts=True)`` gives, without its sort)."""
    first = np.ones(len(lab), bool)
    np.not_equal(lab[1:], lab[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    return np.cumsum(first) - 1, np.diff(np.append(starts, len(lab)))


def _arc_parameter(r: FloatArray, n: FloatArray, group: IntArray, ngroup: int) -> FloatArray:
    """Angle of each ray along its great circle (normal ``n[group]``, ``n`` ``(ngroup, 3)``),
    measured from the mean direction of its group, in ``(-pi, pi]`` (the coordinates in C,
    the angle by numpy's arctan2)."""
    return edge_kernels.arc_parameter(r, n, group, ngroup)


def _oriented_components(p: IntArray, shape: tuple[int, int], theta: FloatArray,
                         max_angle: float) -> tuple[int, IntArray]:
    """Connected components of points ``p`` ``(N, 2)`` (x, y, at least 1 px inside ``shape``)
    where 8-neighbours are linked only if their orientations (mod pi) differ by less than
    ``max_angle`` (rad). Returns the number of components and the ``(N,)`` labels."""
    # a union-find in C; labels in the order of each component's first point, as scipy's
    # connected_components numbered them
    return edge_kernels.oriented_components(p, shape, theta, max_angle)


def extract_lines(image: np.ndarray, camera: CameraModel,
                  options: ExtractionOptions | None = None,
                  mask: np.ndarray | None = None) -> ExtractedLines:
    """One-off extraction; build a :class:`LineExtractor` once for a sequence instead."""
    return LineExtractor(camera, options, mask).extract(image)
