"""``five-point``: point rays, pycolmap's five-point LO-RANSAC, chained through the sequence.

Features (SIFT by default, KLT tracks with ``features: klt``) become unit rays through the
camera model; each frame's pose relative to its reference frame comes from
``pycolmap.estimate_relative_pose`` on the rays (LO-RANSAC, essential matrix) refined by
``pycolmap.refine_relative_pose`` on its inliers; the scale is carried by triangulated points
(:func:`.points.chain_relative_poses`). Simulated sequences give their point
rays directly.

Options: ``features`` (``sift`` | ``klt``), ``max_features``, ``stride`` (3), ``max_error_px``
(RANSAC threshold in pixels of the camera's angular resolution, 1.5), ``seed`` (0).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from omni_sfm.geometry import FloatArray
from omni_sfm.plugin_contract import InitializerResult, SequenceInput

from .points import (
    ChainOptions,
    RelPose,
    angular_resolution_rad,
    chain_relative_poses,
    point_tracks,
)


def ransac_threshold(seq: SequenceInput, options: Mapping[str, Any]) -> float:
    """RANSAC threshold in radians: ``max_error_px`` pixels of the camera's angular resolution,
    or ``max_error_rad`` when given."""
    if "max_error_rad" in options:
        return float(options["max_error_rad"])
    return float(options.get("max_error_px", 1.5)) * angular_resolution_rad(seq.camera)


def chain_options(options: Mapping[str, Any]) -> ChainOptions:
    return ChainOptions(stride=int(options.get("stride", 3)))


def five_point(sequence: SequenceInput, options: Mapping[str, Any]) -> InitializerResult:
    """The ``five-point`` initializer (module docstring)."""
    from omni_sfm.transforms import relative_pose_from_rays

    pts, source = point_tracks(sequence, options)
    thr = ransac_threshold(sequence, options)
    seed = int(options.get("seed", 0))

    def relpose(r: int, k: int, x1: FloatArray, x2: FloatArray) -> RelPose | None:
        est = relative_pose_from_rays(x1, x2, max_error=thr, seed=seed + 1000 * k + r)
        if est is None:
            return None
        R, t, inl = est
        n = np.linalg.norm(t)
        if not n > 0:
            return None
        return R, t / n, inl

    traj, reason, info = chain_relative_poses(sequence, pts, relpose, chain_options(options))
    info.update({"features": source, "ransac_max_error_rad": thr})
    if len(traj) < 3:
        return InitializerResult(None if len(traj) < 2 else traj, "failed",
                                 reason or "fewer than 3 frames posed", info=info)
    return InitializerResult(traj, "ok", reason, info=info)
