"""``upright-3pt``: PoseLib's upright three-point solver on point rays, the vertical taken from
omni-sfm's vanishing direction.

omni-sfm's parallel-line detection (:func:`omni_sfm.vanishing.detect_parallel_family`) gives
the family's vanishing direction (VPV) in every frame, with a sign consistent over time: the
same world direction seen from each camera. Rays of frame ``k`` are turned by ``A_k`` with
``A_k v_k = +y`` (PoseLib's upright axis: ``poselib.relpose_upright_3pt`` solves ``x2 = R_y x1 +
t`` with ``R_y`` a rotation about ``y``), so the relative rotation has one unknown angle; back
in the camera frames ``R = A_k^T R_y A_r``, ``t = A_k^T t``. Around the minimal solver: RANSAC
(symmetric angular epipolar error), cheirality by the sign of the triangulated depths, and a
least-squares refinement of the angle and the translation direction on the inliers (still
upright). The chain and its scale are the five-point initializer's
(:func:`.points.chain_relative_poses`). The family need not be vertical:
any direction fixed in the world works.

Options: as ``five-point`` (``features``, ``max_features``, ``stride``, ``max_error_px``,
``seed``) plus ``iterations`` (RANSAC samples, 500).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray, skew
from omni_sfm.plugin_contract import InitializerResult, SequenceInput, failed

from .five_point import chain_options, ransac_threshold
from .points import RelPose, chain_relative_poses, pair_depths, point_tracks, upright_basis


def _ry(theta: float) -> FloatArray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def epipolar_errors(x1: FloatArray, x2: FloatArray, R: FloatArray, t: FloatArray) -> FloatArray:
    """``(N,)`` larger of the two angles (sines) between a ray and its epipolar plane."""
    E = skew(t) @ R
    n2 = x1 @ E.T
    n1 = x2 @ E
    with np.errstate(invalid="ignore", divide="ignore"):
        e2 = np.abs(np.sum(x2 * n2, 1)) / np.linalg.norm(n2, axis=1)
        e1 = np.abs(np.sum(x1 * n1, 1)) / np.linalg.norm(n1, axis=1)
    return np.nan_to_num(np.maximum(e1, e2), nan=np.inf)


def upright_ransac(y1: FloatArray, y2: FloatArray, thr: float, iterations: int,
                   rng: np.random.Generator) -> tuple[FloatArray, FloatArray, np.ndarray] | None:
    """Best upright pose (``R_y``, unit ``t``, inliers) for rays already turned upright."""
    import poselib
    from scipy.optimize import least_squares

    n = len(y1)
    if n < 3:
        return None
    best: tuple[FloatArray, FloatArray, np.ndarray] | None = None
    best_n = 0
    for _ in range(iterations):
        s = rng.choice(n, 3, replace=False)
        for p in poselib.relpose_upright_3pt(y1[s], y2[s]):
            t = np.asarray(p.t, float)
            if not np.linalg.norm(t) > 0:
                continue
            R = np.asarray(p.R, float)
            inl = epipolar_errors(y1, y2, R, t) < thr
            k = int(inl.sum())
            if k > best_n:
                best, best_n = (R, t / np.linalg.norm(t), inl), k
    if best is None:
        return None
    R, t, inl = best
    theta0 = float(np.arctan2(R[0, 2], R[0, 0]))
    a, b = y1[inl], y2[inl]

    def tvec(q: FloatArray) -> FloatArray:
        return np.array([np.cos(q[1]) * np.cos(q[2]), np.sin(q[1]), np.cos(q[1]) * np.sin(q[2])])

    def resid(q: FloatArray) -> FloatArray:
        e = epipolar_errors(a, b, _ry(q[0]), tvec(q))
        return np.minimum(e, 10 * thr)  # bounded, robust to a wrong inlier

    q0 = np.array([theta0, np.arcsin(np.clip(t[1], -1, 1)), np.arctan2(t[2], t[0])])
    q = least_squares(resid, q0, method="lm" if len(a) >= 3 else "trf").x
    R, t = _ry(q[0]), tvec(q)
    inl = epipolar_errors(y1, y2, R, t) < thr
    d, _ = pair_depths(y1[inl], y2[inl], R, t)
    if np.sum(d < 0) > np.sum(d > 0):
        t = -t
    return R, t, inl


def upright_3pt(sequence: SequenceInput, options: Mapping[str, Any]) -> InitializerResult:
    """The ``upright-3pt`` initializer (module docstring)."""
    from omni_sfm.vanishing import detect_parallel_family

    if sequence.line_tracks is not None and sequence.images is None:
        tracks = sequence.line_tracks
    else:
        from omni_sfm.lines.frontend import FrontEndOptions, track_lines

        frames = ((k, float(sequence.timestamps[k]), sequence.read_gray(k))
                  for k in range(sequence.num_frames))
        tracks = track_lines(frames, sequence.camera, FrontEndOptions(progress=False)).tracks
    try:
        family = detect_parallel_family(tracks)
    except OmniSfmError as exc:
        return failed(f"no vanishing direction: {exc}")
    vpv = np.asarray(family.vpv)
    pts, source = point_tracks(sequence, options)
    thr = ransac_threshold(sequence, options)
    seed = int(options.get("seed", 0))
    iterations = int(options.get("iterations", 500))

    def relpose(r: int, k: int, x1: FloatArray, x2: FloatArray) -> RelPose | None:
        for f in (r, k):
            if not np.isfinite(vpv[f]).all():
                raise OmniSfmError(f"no vanishing direction in frame {f} (fewer than 2 tracks "
                                   f"of the parallel family seen there)")
        A1, A2 = upright_basis(vpv[r]), upright_basis(vpv[k])
        rng = np.random.default_rng(seed + 1000 * k + r)
        res = upright_ransac(x1 @ A1.T, x2 @ A2.T, thr, iterations, rng)
        if res is None:
            return None
        Ry, t, inl = res
        return A2.T @ Ry @ A1, A2.T @ t, inl

    traj, reason, info = chain_relative_poses(sequence, pts, relpose, chain_options(options))
    info.update({"features": source, "ransac_max_error_rad": thr,
                 "family_tracks": int(family.size),
                 "frames_without_vpv": int((~np.isfinite(vpv).all(1)).sum())})
    if len(traj) < 3:
        return InitializerResult(None if len(traj) < 2 else traj, "failed",
                                 reason or "fewer than 3 frames posed", info=info)
    return InitializerResult(traj, "ok", reason, info=info)
