"""Depth of a keyframe's rectified views: OpenCV semi-global matching, and the 3-view check.

For a rig (:mod:`omni_sfm.dense.views`) the reference view ``ref`` is the left image and the
source view the right one: a point at view depth ``z`` has disparity ``d = f b / z``
(``x_src = x_ref - d``). Depths are view ``z`` in pose units, NaN where not measured.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omni_sfm.dense.views import StereoRig
from omni_sfm.geometry import FloatArray


@dataclass(frozen=True, kw_only=True)
class StereoOptions:
    """Semi-global matching (``cv2.StereoSGBM``) and the filters after it."""

    block_size: int = 5
    """Matching window, px (odd)."""
    uniqueness_ratio: int = 10
    """SGBM's margin (percent) by which the best cost must beat the second best."""
    min_texture: float = 2.0
    """Minimum grey-level standard deviation in the matching window: flat walls give no depth."""
    min_disparity_px: float = 1.0
    """Smaller disparities (far points, the epipoles) give no depth: too little parallax."""
    consistency_px: float = 0.75
    """3-view check: the two pairs' depths must agree to this many pixels of disparity."""
    speckle_window: int = 100
    """SGBM speckle filter: connected regions smaller than this many px are removed."""


def sgbm_disparity(ref: np.ndarray, src: np.ndarray, num_disparities: int,
                   opts: StereoOptions) -> np.ndarray:
    """``(H, W)`` float32 disparity (px, NaN where SGBM found none) of grey uint8 views."""
    import cv2

    bs = opts.block_size
    sgbm = cv2.StereoSGBM.create(
        minDisparity=0, numDisparities=num_disparities, blockSize=bs, P1=8 * bs * bs,
        P2=32 * bs * bs, disp12MaxDiff=1, uniquenessRatio=opts.uniqueness_ratio,
        speckleWindowSize=opts.speckle_window, speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM)
    raw = sgbm.compute(ref, src)
    disp = raw.astype(np.float32) / 16.0
    disp[raw < 0] = np.nan
    return disp


def local_std(grey: np.ndarray, size: int) -> FloatArray:
    """``(H, W)`` standard deviation of ``grey`` over ``size x size`` windows."""
    import cv2

    g = grey.astype(np.float32)
    m = cv2.blur(g, (size, size))
    m2 = cv2.blur(g * g, (size, size))
    return np.sqrt(np.maximum(m2 - m * m, 0.0)).astype(np.float64)


def rig_depth(rig: StereoRig, ref_grey: np.ndarray, ref_ok: np.ndarray, src_grey: np.ndarray,
              src_ok: np.ndarray, num_disparities: int, opts: StereoOptions) -> np.ndarray:
    """``(V, H, W)`` float32 view depth ``z`` (pose units, NaN: none) of the reference frame's
    views ``ref_grey (V, H, W)`` uint8 matched against the source frame's ``src_grey``.

    A depth needs SGBM's match (uniqueness, left-right check, speckle filter), texture in the
    window, a disparity in ``[min_disparity_px, num_disparities - 1)`` and both pixels inside
    the camera's valid region."""
    g = rig.geometry
    out = np.full(ref_grey.shape, np.nan, dtype=np.float32)
    cols = np.arange(g.width, dtype=np.float32)[None, :]
    rows = np.arange(g.height)[:, None]
    for v in range(ref_grey.shape[0]):
        if not ref_ok[v].any():
            continue
        d = sgbm_disparity(ref_grey[v], src_grey[v], num_disparities, opts)
        with np.errstate(invalid="ignore"):
            ok = ref_ok[v] & (d >= opts.min_disparity_px) & (d < num_disparities - 1)
            ok &= local_std(ref_grey[v], opts.block_size) >= opts.min_texture
        xs = np.rint(np.where(ok, cols - np.nan_to_num(d), 0)).astype(np.intp)
        ok &= (xs >= 0) & src_ok[v][rows, np.clip(xs, 0, g.width - 1)]
        out[v][ok] = g.focal * rig.baseline / d[ok]
    return out


def depth_along(rig: StereoRig, depth: FloatArray, points_rel: FloatArray) -> FloatArray:
    """The rig's measured view depth at the pixel where each point lies, and the point's own
    view depth: ``(2, N)`` (NaN where no view sees the point or none was measured).

    ``points_rel`` ``(N, 3)`` are world points minus the reference camera centre."""
    g = rig.geometry
    in_views = np.einsum("vji,nj->vni", rig.world_from_views, points_rel)     # (V, N, 3)
    z = in_views[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = g.focal * in_views[..., 0] / z + g.cx
        v = g.focal * in_views[..., 1] / z + g.cy
    inside = (z > 0) & (u > -0.5) & (u < g.width - 0.5) & (v > -0.5) & (v < g.height - 0.5)
    best = np.where(inside, z, -np.inf).argmax(axis=0)                          # (N,)
    n = np.arange(points_rel.shape[0])
    ok = inside[best, n]
    ui = np.clip(np.rint(np.nan_to_num(u[best, n])), 0, g.width - 1).astype(np.intp)
    vi = np.clip(np.rint(np.nan_to_num(v[best, n])), 0, g.height - 1).astype(np.intp)
    measured = np.where(ok, depth[best, vi, ui], np.nan)
    return np.stack([measured, np.where(ok, z[best, n], np.nan)])


def consistent(rig_a: StereoRig, depth_a: FloatArray, rig_b: StereoRig, depth_b: FloatArray,
               opts: StereoOptions) -> np.ndarray:
    """``(V, H, W)`` bool: the depths of ``rig_a`` that the other pair ``rig_b`` (same reference
    frame, another source frame) confirms to ``consistency_px`` of ``rig_b``'s disparity."""
    ga = rig_a.geometry
    ok = np.isfinite(depth_a)
    vv, yy, xx = np.nonzero(ok)
    rays = ga.rays_in_view[yy, xx]                                               # (n, 3)
    pts = np.einsum("nij,nj->ni", rig_a.world_from_views[vv], rays) * depth_a[ok][:, None]
    measured, own = depth_along(rig_b, depth_b, pts)
    fb = rig_b.geometry.focal * rig_b.baseline
    with np.errstate(invalid="ignore", divide="ignore"):
        agree = np.abs(fb / measured - fb / own) <= opts.consistency_px
    out = np.zeros_like(ok)
    out[vv, yy, xx] = agree
    return out
