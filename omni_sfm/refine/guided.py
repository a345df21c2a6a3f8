"""SIFT matching of two posed frames along their epipolar geometry (guided matching).

The line-based poses of ``init`` are accurate to a small fraction of a degree, so for two posed
frames ``a`` and ``b`` the match of a keypoint of ``a`` can only lie near one half great circle
of ``b``'s viewing sphere: the rays from ``b``'s centre to the points on ``a``'s ray. With the
baseline ``t = c_b - c_a`` as the pole of spherical coordinates (azimuth ``phi``, ``z = cos``
of the angle from ``t``), a point ``X = c_a + s d_a`` (``s > 0``) is seen from ``b`` along
``s d_a - t``: the same azimuth as ``d_a`` and farther from the pole (``z_b <= z_a``). So only
keypoints of ``b`` whose azimuth is within the band of ``d_a``'s are compared, by blocks of
keypoints sorted by azimuth (dense products of descriptors, a few percent of all pairs), and a
match must pass COLMAP's own tests among those candidates: angular descriptor distance at most
``max_distance``, Lowe's ratio against the second best, mutual best. No RANSAC: the matches are
consistent with the given poses by construction. On the 120-frame textured room (4,732
keypoints a frame) a pair takes about 40 ms against COLMAP's 120 ms, and the matches include
99.98 % of those COLMAP's matcher and geometric verification find (docs/colmap.md).

The band of a candidate ``(i, j)`` is ``band_px`` times the mean angular size of a pixel at the
two keypoints, plus ``pose_tolerance_deg`` for the poses' own error (a direction error of the
baseline moves the band by at most the parallax times that error: small for short baselines,
and wide baselines have accurate directions). The azimuth window of a keypoint of ``b`` is the
band divided by its distance from the pole (``rho``, the sine of its angle from it): keypoints
of ``b`` are compared in octaves of ``rho``, each with its own window, and those within the
band of a pole with every keypoint of ``a``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omni_sfm.geometry import FloatArray

_NONE = -2.0
"""Descriptor similarity of "no candidate" (similarities of unit descriptors are >= -1)."""


@dataclass(frozen=True, kw_only=True)
class GuidedMatchOptions:
    """How guided matching chooses candidates and matches (COLMAP's SIFT matching defaults for
    the descriptor tests)."""

    band_px: float = 4.0
    """Half-width of the epipolar band, in pixels at the two keypoints (their mean)."""
    pose_tolerance_deg: float = 0.3
    """Added to the band for the input poses' error."""
    max_ratio: float = 0.8
    """Lowe's ratio test on angular descriptor distances (COLMAP's ``max_ratio``)."""
    max_distance: float = 0.7
    """Largest angular descriptor distance in radians (COLMAP's ``max_distance``)."""
    block: int = 128
    """Keypoints of the first frame compared in one dense block."""

    def __post_init__(self) -> None:
        for name in ("band_px", "max_ratio", "max_distance"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if not self.pose_tolerance_deg >= 0:
            raise ValueError(f"pose_tolerance_deg must be >= 0, got {self.pose_tolerance_deg!r}")
        if self.block < 1:
            raise ValueError(f"block must be >= 1, got {self.block!r}")


@dataclass(frozen=True)
class FrameKeypoints:
    """One frame's keypoints for guided matching.

    Attributes:
        index: ``(N,)`` the keypoints' indices in the frame's keypoint list (those with a ray).
        rays_in_cam: ``(N, 3)`` unit rays in the camera frame.
        pixel_rad: ``(N,)`` angular size of a pixel at each keypoint (radians).
        descriptors: ``(N, D)`` float32 unit descriptors.
    """

    index: np.ndarray
    rays_in_cam: FloatArray
    pixel_rad: FloatArray
    descriptors: np.ndarray

    @classmethod
    def build(cls, rays_in_cam: FloatArray, pixel_rad: FloatArray,
              descriptors: np.ndarray) -> FrameKeypoints:
        """Keep the keypoints with a finite ray and a non-zero descriptor (made unit, float32:
        COLMAP's SIFT descriptors are stored as uint8)."""
        rays = np.asarray(rays_in_cam, float)
        desc = np.asarray(descriptors).astype(np.float32)
        if rays.ndim != 2 or rays.shape[1] != 3 or desc.ndim != 2 or \
                desc.shape[0] != rays.shape[0] or np.shape(pixel_rad) != (rays.shape[0],):
            raise ValueError(f"{rays.shape=} {desc.shape=} {np.shape(pixel_rad)=}")
        norm = np.linalg.norm(desc, axis=1)
        ok = np.all(np.isfinite(rays), axis=1) & np.isfinite(pixel_rad) & (norm > 0)
        index = np.flatnonzero(ok)
        desc = desc[ok]
        desc /= norm[ok, None]
        return cls(index, rays[ok], np.asarray(pixel_rad, float)[ok], desc)


def _top2(values: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best value, its index and second best value along ``axis`` of a 2-D array (restored)."""
    v = values if axis == 1 else values.T  # a view: rows of v are the lines along ``axis``
    rows = np.arange(v.shape[0])
    arg = np.argmax(v, axis=1)
    best = v[rows, arg].copy()
    v[rows, arg] = _NONE
    second = v.max(axis=1)
    v[rows, arg] = best
    return best, arg, second


class _Top2:
    """Running best and second best similarity (and the best's partner) of each keypoint."""

    def __init__(self, n: int) -> None:
        self.best = np.full(n, _NONE)
        self.arg = np.full(n, -1, np.int64)
        self.second = np.full(n, _NONE)

    def merge(self, at: np.ndarray | slice, best: np.ndarray, arg: np.ndarray,
              second: np.ndarray) -> None:
        b1, a1, b2 = self.best[at], self.arg[at], self.second[at]
        new = best > b1
        self.best[at] = np.where(new, best, b1)
        self.arg[at] = np.where(new, arg, a1)
        self.second[at] = np.where(new, np.maximum(b1, second), np.maximum(b2, best))

    def passes(self, o: GuidedMatchOptions) -> np.ndarray:
        """COLMAP's one-way tests: a candidate, distance, ratio (no second: a right angle)."""
        d1 = np.arccos(np.clip(self.best, -1.0, 1.0))
        d2 = np.arccos(np.clip(np.where(self.second > _NONE, self.second, 0.0), -1.0, 1.0))
        return (self.best > _NONE) & (d1 <= o.max_distance) & (d1 < o.max_ratio * d2)


def _azimuth_bins(rho: np.ndarray, rho_all: float) -> list[np.ndarray]:
    """Keypoints by distance from the pole (``rho``: sine of the angle from it) in octaves
    ``[1/2, 1], [1/4, 1/2), ...`` down to ``rho_all``; the last entry: those nearer the pole."""
    bins, hi = [], np.inf
    lo = 0.5
    while True:
        lo = max(lo, rho_all)
        bins.append(np.flatnonzero((rho >= lo) & (rho < hi)))
        if lo <= rho_all:
            break
        hi, lo = lo, lo / 2
    bins.append(np.flatnonzero(rho < rho_all))
    return bins


def match_pair(a: FrameKeypoints, b: FrameKeypoints, b_from_a_rotation: FloatArray,
               baseline_in_a: FloatArray, options: GuidedMatchOptions | None = None
               ) -> np.ndarray:
    """Matches ``(M, 2)`` (keypoint indices of ``a``, of ``b``) of two posed frames.

    Args:
        a, b: the two frames' keypoints.
        b_from_a_rotation: ``(3, 3)`` rotation taking ``a``'s camera frame to ``b``'s.
        baseline_in_a: ``(3,)`` ``b``'s centre minus ``a``'s, in ``a``'s camera frame (any
            scale; zero: a camera that did not move, matches must lie on the same rays).
    """
    o = options or GuidedMatchOptions()
    R = np.asarray(b_from_a_rotation, float)
    t = np.asarray(baseline_in_a, float)
    if R.shape != (3, 3) or t.shape != (3,) or not (np.all(np.isfinite(R))
                                                     and np.all(np.isfinite(t))):
        raise ValueError(f"{R.shape=} {t.shape=}, or not finite")
    if len(a.index) == 0 or len(b.index) == 0:
        return np.zeros((0, 2), np.int64)
    moved, basis = _pole_basis(t)
    xa, ya, za = basis @ a.rays_in_cam.T
    xb, yb, zb = basis @ (b.rays_in_cam @ R).T  # b's rays in a's frame
    f32 = np.float32
    phi_a = np.arctan2(ya, xa).astype(f32)
    phi_b = np.arctan2(yb, xb)
    rho_b = np.hypot(xb, yb)
    tol = np.deg2rad(o.pose_tolerance_deg)
    # the band of (i, j): |rho_j (phi_j - phi_i)| <= delta_i + delta_j (the sine's argument:
    # slightly narrower than the band where it is wide); keypoints of b within delta_max of a
    # pole lie in every band (rho_eff 0)
    delta_a = (0.5 * o.band_px * a.pixel_rad + tol).astype(f32)
    delta_b = (0.5 * o.band_px * b.pixel_rad).astype(f32)
    delta_max = float(delta_a.max() + delta_b.max())
    bins = _azimuth_bins(rho_b, delta_max)
    near_pole = bins.pop()
    rho_eff = np.where(rho_b < delta_max, 0.0, rho_b).astype(f32)
    # the arc: b's ray no nearer the pole than a's, z_j - delta_j <= z_i + delta_i
    zb_low = (zb - delta_b).astype(f32)
    za_high = (za + delta_a).astype(f32)
    if not moved:  # and no farther: the same ray
        za_low, zb_high = (za - delta_a).astype(f32), (zb + delta_b).astype(f32)
    ext = _azimuth_windows(bins, phi_b, rho_b, delta_max)

    desc_a, desc_b = a.descriptors, b.descriptors
    rows_top, cols_top = _Top2(len(a.index)), _Top2(len(b.index))
    by_phi = np.argsort(phi_a, kind="stable")
    for s in range(0, len(by_phi), o.block):
        rows = by_phi[s:s + o.block]
        p0, p1 = float(phi_a[rows[0]]), float(phi_a[rows[-1]])
        cols, phi_parts = _block_columns(near_pole, phi_b, ext, p0, p1)
        if len(cols) == 0:
            continue
        sim = desc_a[rows] @ desc_b[cols].T
        across = np.abs(phi_parts[0] if len(phi_parts) == 1 else np.concatenate(phi_parts)
                        - phi_a[rows, None])
        across *= rho_eff[cols]
        across -= delta_b[cols]
        bad = across > delta_a[rows, None]
        bad |= zb_low[cols] > za_high[rows, None]
        if not moved:
            bad |= zb_high[cols] < za_low[rows, None]
        np.putmask(sim, bad, _NONE)
        best, arg, second = _top2(sim, 1)
        rows_top.merge(rows, best, cols[arg], second)
        best, arg, second = _top2(sim, 0)
        cols_top.merge(cols, best, rows[arg], second)
    return _mutual_matches(a, b, rows_top, cols_top, o)


def _pole_basis(t: FloatArray) -> tuple[bool, FloatArray]:
    """Whether the camera moved, and the rows x, y, z of a frame whose z is the baseline."""
    length = float(np.linalg.norm(t))
    moved = length > 0
    pole = t / length if moved else np.array([0.0, 0.0, 1.0])
    u = np.cross(pole, [1.0, 0.0, 0.0] if abs(pole[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    basis = np.stack([u, np.cross(pole, u), pole])  # rows: x, y, z axes in a's frame
    return moved, basis


def _azimuth_windows(bins: list[np.ndarray], phi_b: FloatArray, rho_b: FloatArray,
                     delta_max: float) -> list[tuple[np.ndarray, np.ndarray, float, int]]:
    """Per bin of ``b``'s keypoints: azimuths sorted and wrapped thrice, their columns, the
    half-width of the azimuth window, and the bin's size."""
    f32 = np.float32
    ext = []
    for cols in bins:
        if len(cols) == 0:
            continue
        order = cols[np.argsort(phi_b[cols], kind="stable")]
        ph = phi_b[order]
        rho_low = float(rho_b[cols].min())
        ext.append((np.concatenate([ph - 2 * np.pi, ph, ph + 2 * np.pi]).astype(f32),
                    np.tile(order, 3), min(np.pi, delta_max / rho_low), len(order)))
    return ext


def _block_columns(near_pole: np.ndarray, phi_b: FloatArray,
                   ext: list[tuple[np.ndarray, np.ndarray, float, int]], p0: float,
                   p1: float) -> tuple[np.ndarray, list[np.ndarray]]:
    """The columns of ``b`` a block of rows with azimuths ``[p0, p1]`` may match, and the
    parts of their azimuths."""
    col_parts, phi_parts = [near_pole], [phi_b[near_pole].astype(np.float32)]
    for ext_phi, ext_col, width, n in ext:
        lo = int(np.searchsorted(ext_phi, p0 - width, "left"))
        hi = int(np.searchsorted(ext_phi, p1 + width, "right"))
        if hi - lo >= n:  # the whole circle: every keypoint once, azimuths near the rows'
            lo = int(np.searchsorted(ext_phi, 0.5 * (p0 + p1) - np.pi, "left"))
            hi = lo + n
        col_parts.append(ext_col[lo:hi])
        phi_parts.append(ext_phi[lo:hi])
    return np.concatenate(col_parts), phi_parts


def _mutual_matches(a: FrameKeypoints, b: FrameKeypoints, rows_top: _Top2, cols_top: _Top2,
                    o: GuidedMatchOptions) -> np.ndarray:
    """The matches ``(M, 2)`` that pass the ratio tests and are each other's best."""
    ok_a = rows_top.passes(o)
    ok_b = cols_top.passes(o)
    i = np.flatnonzero(ok_a)
    j = rows_top.arg[i]
    mutual = ok_b[j] & (cols_top.arg[j] == i)
    return np.stack([a.index[i[mutual]], b.index[j[mutual]]], 1).astype(np.int64)
