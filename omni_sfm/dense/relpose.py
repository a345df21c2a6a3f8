"""Relative pose of a stereo pair from SIFT matches on rays, to make the pair self-consistent.

Rectified stereo needs the pair's relative rotation to a fraction of a pixel angle (0.1 deg is
0.4 px at the 800 x 600 hyperboloid's resolution); line-based poses drift by more over a stereo
baseline (about 0.2 deg over 19 frames on the rendered room). The pair's relative pose is
therefore re-estimated from the images: SIFT on the frames (inside the camera's valid region),
ratio-test matches turned into rays by the camera model, pycolmap's five-point RANSAC on rays
and its refinement. The reference frame keeps its given pose and the baseline its given length;
only the source frame's rotation and the baseline direction change, and only when the estimate
is trustworthy (enough inliers, close to the given pose) and the change is larger than the
estimate's own noise: otherwise the given poses are used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omni_sfm.cameras import CameraModel
from omni_sfm.geometry import FloatArray, angle_between, rotation_angle
from omni_sfm.transforms import relative_pose_from_rays


@dataclass(frozen=True, kw_only=True)
class PairPoseOptions:
    """When the image-based relative pose replaces the given one."""

    enabled: bool = True
    """Re-estimate each pair's relative pose from SIFT matches (False: trust the poses)."""
    max_features: int = 4000
    """SIFT features per frame."""
    max_error: float = 0.003
    """RANSAC threshold: angle on the unit sphere (rad), about 0.6 px here."""
    min_inliers: int = 60
    """Fewer inliers: keep the given poses."""
    min_rotation_change_deg: float = 0.1
    """A smaller change is within the estimate's own noise (0.03-0.04 deg on the rendered room
    at 400 x 300): keep the given poses."""
    max_rotation_change_deg: float = 3.0
    """A larger change of the relative rotation is not a drift but a wrong estimate: keep."""
    max_direction_change_deg: float = 20.0
    """Likewise for the baseline direction."""


@dataclass(frozen=True)
class Features:
    """SIFT features of one frame: unit rays ``(N, 3)`` (camera frame) and descriptors."""

    rays: FloatArray
    descriptors: np.ndarray


def frame_features(image: np.ndarray, camera: CameraModel, mask: np.ndarray,
                   opts: PairPoseOptions) -> Features:
    """SIFT on ``image`` ``(H, W, 3)`` uint8 RGB within ``mask`` (uint8, 255 = use)."""
    import cv2

    sift = cv2.SIFT.create(nfeatures=opts.max_features)
    kp, desc = sift.detectAndCompute(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), mask)
    if desc is None or not kp:
        return Features(np.zeros((0, 3)), np.zeros((0, 128), np.float32))
    uv = np.array([k.pt for k in kp], dtype=np.float64)
    rays = camera.rays_from_pixels(uv)
    ok = np.isfinite(rays).all(axis=1)
    return Features(rays[ok], desc[ok])


@dataclass(frozen=True)
class PairPose:
    """The source frame's pose for the pair and what was done.

    Attributes:
        world_from_src: ``(3, 3)`` rotation used for the source frame.
        centre_src: ``(3,)`` its centre (world).
        corrected: whether the image-based estimate replaced the given relative pose.
        inliers: RANSAC inliers (0 without an estimate).
        rotation_change_deg, direction_change_deg: estimate minus given (NaN without one).
    """

    world_from_src: FloatArray
    centre_src: FloatArray
    corrected: bool
    inliers: int
    rotation_change_deg: float
    direction_change_deg: float


def pair_pose(ref: Features, src: Features, world_from_ref: FloatArray, centre_ref: FloatArray,
              world_from_src: FloatArray, centre_src: FloatArray, opts: PairPoseOptions
              ) -> PairPose:
    """The source pose that makes the pair agree with its images (see the module docstring)."""
    keep = PairPose(world_from_src, centre_src, False, 0, float("nan"), float("nan"))
    if not opts.enabled or len(ref.rays) < opts.min_inliers or len(src.rays) < opts.min_inliers:
        return keep
    import cv2

    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(ref.descriptors, src.descriptors, k=2)
    good = [p[0] for p in knn if len(p) == 2 and p[0].distance < 0.8 * p[1].distance]
    if len(good) < opts.min_inliers:
        return keep
    r1 = ref.rays[[m.queryIdx for m in good]]
    r2 = src.rays[[m.trainIdx for m in good]]
    est = relative_pose_from_rays(r1, r2, max_error=opts.max_error, seed=0)
    if est is None or int(est[2].sum()) < opts.min_inliers:
        return keep
    R, t, inlier_mask = est                                   # src_from_ref
    R_given = world_from_src.T @ world_from_ref
    t_given = world_from_src.T @ (centre_ref - centre_src)
    d_rot = float(np.degrees(rotation_angle(R_given.T @ R)))
    d_dir = float(np.degrees(angle_between(t, t_given)))
    inliers = int(inlier_mask.sum())
    if d_rot < opts.min_rotation_change_deg or d_rot > opts.max_rotation_change_deg or \
            d_dir > opts.max_direction_change_deg:
        return PairPose(world_from_src, centre_src, False, inliers, d_rot, d_dir)
    new_rot = world_from_ref @ R.T
    baseline = float(np.linalg.norm(centre_src - centre_ref))
    direction = -(new_rot @ t)                                 # ref -> src centre, world
    new_centre = centre_ref + baseline * direction / np.linalg.norm(direction)
    return PairPose(new_rot, new_centre, True, inliers, d_rot, d_dir)
