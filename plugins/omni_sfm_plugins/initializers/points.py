"""Point features for the point-based initializers: tracks from images (SIFT or KLT), rays, and
a monocular chain of relative poses whose scale is carried by triangulated points.

The chain (:func:`chain_relative_poses`) is what a monocular SfM start does: the first pair
``(0, s)`` (``s`` = stride) fixes the scale (unit baseline) and the first points; every further
frame ``k`` gets its relative pose to the reference ``r = max(0, k - s)`` from a two-view solver
on rays, and the length of its baseline from the depths (in frame ``r``) of the points that the
already posed frames triangulate, against the depths the new pair triangulates at unit
baseline (median ratio). The chain stops at the first frame it cannot pose; the trajectory is
the frames posed before it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from omni_sfm.cameras.base import CameraModel
from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray, skew
from omni_sfm.plugin_contract import PointObservations, SequenceInput
from omni_sfm.poses import Trajectory

RelPose = tuple[FloatArray, FloatArray, np.ndarray]
"""``(R, t, inliers)``: cam2_from_cam1 rotation ``(3, 3)``, unit translation ``(3,)`` (x2 = R x1
+ t), ``(N,)`` bool inlier mask."""


def angular_resolution_rad(camera: CameraModel) -> float:
    """Median angle between the rays of horizontally adjacent valid pixels (radians)."""
    rays = camera.pixel_grid_rays()
    a, b = rays[::4, :-1:4], rays[::4, 1::4]
    dots = np.sum(a * b, axis=-1)
    ok = np.isfinite(dots)
    if not ok.any():
        raise OmniSfmError("the camera has no valid pixels")
    return float(np.median(np.arccos(np.clip(dots[ok], -1.0, 1.0))))


def _mask(camera: CameraModel) -> np.ndarray:
    return (camera.valid_mask() * 255).astype(np.uint8)


def sift_tracks(seq: SequenceInput, max_features: int = 4000, ratio: float = 0.8
                ) -> PointObservations:
    """SIFT keypoints of every frame (inside the camera's valid mask), matched between
    consecutive frames (Lowe's ratio test, mutual best), chained into tracks."""
    import cv2 as cv2_typed

    cv2: Any = cv2_typed  # OpenCV's stubs lack some overloads used here
    sift = cv2.SIFT_create(nfeatures=max_features)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    mask = _mask(seq.camera)
    tr: list[np.ndarray] = []
    fr: list[np.ndarray] = []
    uv: list[np.ndarray] = []
    prev_desc: np.ndarray | None = None
    prev_ids = np.zeros(0, np.int64)
    next_id = 0
    for k in range(seq.num_frames):
        kps, desc = sift.detectAndCompute(seq.read_gray(k), mask)
        pts = np.array([kp.pt for kp in kps], np.float64).reshape(-1, 2)
        ids = np.arange(next_id, next_id + len(pts))
        if prev_desc is not None and desc is not None and len(prev_desc) >= 2 and len(desc) >= 2:
            fwd = matcher.knnMatch(desc, prev_desc, k=2)
            back = {m[0].queryIdx: m[0].trainIdx for m in matcher.knnMatch(prev_desc, desc, k=1)
                    if m}
            for m in fwd:
                if len(m) == 2 and m[0].distance < ratio * m[1].distance and \
                        back.get(m[0].trainIdx) == m[0].queryIdx:
                    ids[m[0].queryIdx] = prev_ids[m[0].trainIdx]
        fresh = ids >= next_id
        ids[fresh] = next_id + np.arange(int(fresh.sum()))
        next_id += int(fresh.sum())
        tr.append(ids)
        fr.append(np.full(len(ids), k))
        uv.append(pts)
        prev_desc, prev_ids = desc, ids
    return _observations(seq.camera, tr, fr, uv)


def klt_tracks(seq: SequenceInput, max_corners: int = 2000, min_distance: float = 7.0,
               fb_max_px: float = 1.0) -> PointObservations:
    """Shi-Tomasi corners tracked by pyramidal KLT with a forward-backward check; new corners
    are added away from the tracked ones whenever fewer than 70 % of ``max_corners`` remain
    (the library's tracker, :func:`omni_sfm.corners.track_corners`)."""
    from omni_sfm.corners import CornerTrackOptions, track_corners

    opts = CornerTrackOptions(max_corners=max_corners, min_distance_px=min_distance,
                              fb_max_px=fb_max_px)
    t = track_corners((seq.read_gray(k) for k in range(seq.num_frames)), _mask(seq.camera),
                      opts)
    return _observations(seq.camera, [t.track], [t.frame], [t.uv])


def _observations(camera: CameraModel, tr: list[np.ndarray], fr: list[np.ndarray],
                  uv: list[np.ndarray]) -> PointObservations:
    t = np.concatenate(tr).astype(np.int64) if tr else np.zeros(0, np.int64)
    f = np.concatenate(fr).astype(np.int64) if fr else np.zeros(0, np.int64)
    u = np.concatenate(uv).reshape(-1, 2) if uv else np.zeros((0, 2))
    rays = camera.rays_from_pixels(u) if len(u) else np.zeros((0, 3))
    ok = np.isfinite(rays).all(1)
    return PointObservations(t[ok], f[ok], u[ok], rays[ok])


def point_tracks(seq: SequenceInput, options: Mapping[str, Any]) -> tuple[PointObservations, str]:
    """The sequence's precomputed points, else features of its images (``options["features"]``:
    ``"sift"`` (default) or ``"klt"``). Returns the observations and where they came from."""
    if seq.points is not None and seq.images is None:
        return seq.points, "given"
    features = str(options.get("features", "sift"))
    if features == "sift":
        return sift_tracks(seq, int(options.get("max_features", 4000))), "sift"
    if features == "klt":
        return klt_tracks(seq, int(options.get("max_features", 2000))), "klt"
    raise OmniSfmError(f"unknown features {features!r} (known: sift, klt)")


class FrameIndex:
    """Per-frame access to point observations: sorted track ids and rays."""

    def __init__(self, pts: PointObservations, num_frames: int) -> None:
        order = np.lexsort((pts.obs_track, pts.obs_frame))
        self.track = pts.obs_track[order]
        self.frame = pts.obs_frame[order]
        self.ray = pts.obs_ray[order]
        self.bounds = np.searchsorted(self.frame, np.arange(num_frames + 1))

    def frame_obs(self, f: int) -> tuple[np.ndarray, FloatArray]:
        a, b = self.bounds[f], self.bounds[f + 1]
        ids, first = np.unique(self.track[a:b], return_index=True)
        return ids, self.ray[a:b][first]

    def common(self, f1: int, f2: int) -> tuple[np.ndarray, FloatArray, FloatArray]:
        i1, r1 = self.frame_obs(f1)
        i2, r2 = self.frame_obs(f2)
        ids, a, b = np.intersect1d(i1, i2, assume_unique=True, return_indices=True)
        return ids, r1[a], r2[b]


def triangulate_midpoint(index: FrameIndex, R: FloatArray, c: FloatArray, posed: np.ndarray,
                         min_angle_deg: float) -> tuple[np.ndarray, FloatArray]:
    """Least-squares intersection of the world rays of every track over the posed frames.

    Returns the track ids and points ``(T, 3)`` of the tracks seen in at least two posed frames
    whose rays span at least ``min_angle_deg`` (from the first ray).
    """
    sel = posed[index.frame]
    if not sel.any():
        return np.zeros(0, np.int64), np.zeros((0, 3))
    tid, f = index.track[sel], index.frame[sel]
    w = np.einsum("kij,kj->ki", R[f], index.ray[sel])
    ids, inv = np.unique(tid, return_inverse=True)
    P = np.eye(3)[None] - w[:, :, None] * w[:, None, :]
    A = np.zeros((len(ids), 3, 3))
    b = np.zeros((len(ids), 3))
    np.add.at(A, inv, P)
    np.add.at(b, inv, np.einsum("kij,kj->ki", P, c[f]))
    count = np.bincount(inv, minlength=len(ids))
    first = np.zeros((len(ids), 3))
    first[inv[::-1]] = w[::-1]
    cosmin = np.full(len(ids), 1.0)
    np.minimum.at(cosmin, inv, np.sum(w * first[inv], 1))
    ok = (count >= 2) & (cosmin < np.cos(np.radians(min_angle_deg)))
    ok &= np.linalg.det(A) > 1e-12
    X = np.full((len(ids), 3), np.nan)
    X[ok] = np.linalg.solve(A[ok], b[ok][:, :, None])[:, :, 0]
    return ids[ok], X[ok]


def pair_depths(x1: FloatArray, x2: FloatArray, R: FloatArray, t: FloatArray
                ) -> tuple[FloatArray, FloatArray]:
    """Depths along ``x1`` (frame 1) of the midpoints of the ray pairs, for cam2_from_cam1
    ``(R, t)``; and the angle between the two rays in frame 1 (radians)."""
    c2 = -R.T @ t
    b = x2 @ R
    ab = np.sum(x1 * b, 1)
    den = 1.0 - ab**2
    ac, bc = x1 @ c2, b @ c2
    with np.errstate(divide="ignore", invalid="ignore"):
        s1 = (ac - ab * bc) / den
    ang = np.arccos(np.clip(ab, -1.0, 1.0))
    return s1, ang


@dataclass(frozen=True, kw_only=True)
class ChainOptions:
    """Options of :func:`chain_relative_poses`."""

    stride: int = 3
    """Frames between a frame and its reference frame."""
    min_matches: int = 15
    """Correspondences a pair needs."""
    min_inliers: int = 12
    """Inliers the relative pose needs."""
    min_scale_points: int = 6
    """Points that must carry the scale to a new frame."""
    min_angle_deg: float = 0.5
    """Smallest triangulation angle of a point used for the scale."""


def chain_relative_poses(seq: SequenceInput, pts: PointObservations,
                         relpose: Callable[[int, int, FloatArray, FloatArray], RelPose | None],
                         opts: ChainOptions) -> tuple[Trajectory, str, dict[str, Any]]:
    """Monocular chain of relative poses (module docstring).

    ``relpose(r, k, x_r, x_k)`` returns cam_k_from_cam_r with a unit translation and its
    inliers, or None, or raises OmniSfmError saying why the pair cannot be solved. Returns the
    trajectory of the frames posed before the first failure (world = frame 0, scale = first
    pair's baseline), the reason of that failure ("" when every frame was posed) and counts.
    """
    F = seq.num_frames
    index = FrameIndex(pts, F)
    R = np.broadcast_to(np.eye(3), (F, 3, 3)).copy()
    c = np.zeros((F, 3))
    posed = np.zeros(F, bool)
    posed[0] = True
    s = max(1, min(opts.stride, F - 1))
    order = [s, *range(1, s), *range(s + 1, F)]
    inliers: list[int] = []
    reason = ""
    for k in order:
        r = 0 if k <= s else k - s
        ids, xr, xk = index.common(r, k)
        if len(ids) < opts.min_matches:
            reason = f"frame {k}: {len(ids)} point correspondences with frame {r}; need " \
                     f"{opts.min_matches}"
            break
        try:
            rel = relpose(r, k, xr, xk)
        except OmniSfmError as exc:
            reason = f"frame {k}: {exc}"
            break
        if rel is None or int(rel[2].sum()) < opts.min_inliers:
            n = 0 if rel is None else int(rel[2].sum())
            reason = f"frame {k}: no relative pose to frame {r} ({n} inliers of {len(ids)})"
            break
        Rkr, t, inl = rel
        inliers.append(int(inl.sum()))
        if k == s:
            scale = 1.0
        else:
            d_pair, ang = pair_depths(xr[inl], xk[inl], Rkr, t)
            mids, X = triangulate_midpoint(index, R, c, posed, opts.min_angle_deg)
            common, ia, ib = np.intersect1d(ids[inl], mids, return_indices=True)
            d_map = np.einsum("ij,kj->ki", R[r].T, X[ib] - c[r])
            d_map = np.sum(d_map * xr[inl][ia], 1)
            ok = (d_pair[ia] > 0) & (d_map > 0) & (ang[ia] > np.radians(opts.min_angle_deg)) & \
                np.isfinite(d_pair[ia])
            if ok.sum() < opts.min_scale_points:
                reason = f"frame {k}: {int(ok.sum())} triangulated points carry the scale " \
                         f"from frame {r}; need {opts.min_scale_points}"
                break
            scale = float(np.median(d_map[ok] / d_pair[ia][ok]))
        R[k] = R[r] @ Rkr.T
        c[k] = c[r] - scale * R[r] @ (Rkr.T @ t)
        posed[k] = True
    # the frames posed contiguously from frame 0
    n = int(np.argmin(posed)) if not posed.all() else F
    idx = np.arange(n)
    traj = Trajectory(seq.timestamps[idx].copy(), R[idx], c[idx])
    info = {"observations": pts.num_observations,
            "tracks": int(len(np.unique(pts.obs_track))),
            "median_inliers_per_pair": float(np.median(inliers)) if inliers else 0.0,
            "stride": s}
    if reason and n < F:
        reason = f"chain stopped at {reason}"
    return traj, reason, info


def upright_basis(v: FloatArray) -> FloatArray:
    """A rotation ``A`` with ``A @ v = (0, 1, 0)`` (``v`` unit), turning ``v`` onto +y."""
    y = np.array([0.0, 1.0, 0.0])
    axis = np.cross(v, y)
    s = float(np.linalg.norm(axis))
    cth = float(v @ y)
    if s < 1e-12:
        return np.eye(3) if cth > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    K = skew(k)
    return np.eye(3) + s * K + (1 - cth) * K @ K
