"""Rotations of a camera that turns but does not move (docs/method.md §13, docs/estimator.md).

When the camera only rotates, the plane through the (fixed) viewpoint and a 3D line is the same
plane in every frame: the line's normal vector (NV) ``n_j`` is constant in the world, and each
observation is that plane's normal seen from the turned camera, ``m_ij = +-R_i^T n_j``. The
rotations follow from the NVs alone, without any translation (the paper's searches need
parallax and fail here: "the camera barely moved"):

1. **Incremental**: the first frame is the world; each next frame's rotation is the weighted
   Procrustes (Kabsch) rotation that maps its NVs onto the world NVs of the lines already seen
   (signs chosen by the previous frame's rotation, robust Cauchy weights); the NVs of lines
   seen for the first time are added from it.
2. **Joint**: alternate, until the cost settles, the world NVs (the signed mean of each line's
   rotated observations) and every frame's Procrustes rotation: least squares over all
   observations (a block-coordinate descent on ``sum w ||R_i m_ij - s_ij n_j||^2``).
3. Tracks whose RMS angle stays far above the rest are outliers (wrong correspondences); the
   fit is repeated without them.

Translation, and so scale and 3D lines, are undetermined: the result says so instead of
inventing them. The fit's residual tells whether the data really is rotation-only: translation
changes the NVs of lines (the parallax the paper's method uses), which a pure rotation cannot
explain.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray
from omni_sfm.lines.tracks import LineTracks


@dataclass(frozen=True, kw_only=True)
class RotationOnlyOptions:
    """Options of :func:`estimate_rotation_only`."""

    min_lines: int = 2
    """A frame is estimated when at least this many lines with known world NVs, not all in one
    plane's pencil (their NVs not all parallel), are seen in it."""
    min_spread_deg: float = 5.0
    """... and the NVs of those lines span at least this angle (else the rotation about their
    common normal is undetermined)."""
    iterations: int = 30
    """Maximum rounds of the joint fit."""
    robust_scale_deg: float = 0.5
    """Scale of the Cauchy weights ``1 / (1 + (r / scale)^2)`` on each observation's angle."""
    outlier_factor: float = 5.0
    """A track is an outlier when its RMS angle exceeds this times the robust scale of all
    tracks' RMS angles (1.4826 x their median), and at least 0.2 deg."""


@dataclass(frozen=True)
class RotationOnlyResult:
    """Rotations of a turning camera.

    Attributes:
        rotations: ``(F, 3, 3)`` world_from_cam (world = the first estimated frame's camera);
            identity where not estimated.
        estimated: ``(F,)`` bool.
        world_normals: ``(M, 3)`` each line's plane normal in the world (NaN if unused).
        used_tracks: ``(M,)`` bool, tracks in the final fit.
        outliers: ``(M,)`` bool, tracks rejected as outliers.
        track_rms_deg: ``(M,)`` RMS angle of each track's observations at the solution.
        rms_initial_deg: RMS angle over the used observations after the incremental pass.
        rms_final_deg: the same after the joint fit.
        median_deg: median observation angle at the solution.
        reasons: frame index -> why it was not estimated.
    """

    rotations: FloatArray
    estimated: np.ndarray
    world_normals: FloatArray
    used_tracks: np.ndarray
    outliers: np.ndarray
    track_rms_deg: FloatArray
    rms_initial_deg: float
    rms_final_deg: float
    median_deg: float
    reasons: dict[int, str]


def procrustes(a: FloatArray, b: FloatArray, w: FloatArray) -> FloatArray:
    """The rotation ``R`` minimising ``sum w_k ||R a_k - b_k||^2`` (Kabsch; ``a, b (K, 3)``)."""
    return _procrustes_batch(a * w[:, None], b, np.zeros(len(a), dtype=np.int64), 1)[0]


def _procrustes_batch(a: FloatArray, b: FloatArray, group: np.ndarray, num: int) -> FloatArray:
    """``(num, 3, 3)``: for each group ``g`` the rotation minimising
    ``sum ||R a_k - b_k||^2`` over the rows ``k`` with ``group[k] == g`` (weights folded into
    ``a``); identity for empty groups."""
    H = np.zeros((num, 3, 3))
    np.add.at(H, group, a[:, :, None] * b[:, None, :])
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
    sign = np.sign(np.linalg.det(V @ Ut))
    sign[sign == 0] = 1.0
    D = np.zeros((num, 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = sign
    return np.asarray(V @ D @ Ut)


def _spread_ok(n: FloatArray, min_spread: float) -> bool:
    """The unsigned unit vectors ``n (K, 3)`` are not all (nearly) parallel."""
    if len(n) < 2:
        return False
    s = np.linalg.svd(n, compute_uv=False)
    # second singular value of K unit vectors: sqrt(K) sin(spread) for two bundles
    return bool(s[1] >= np.sin(min_spread) * np.sqrt(len(n)) / 2)


def _weights(r: FloatArray, scale: float) -> FloatArray:
    return np.asarray(1.0 / (1.0 + (r / scale) ** 2))


def _incremental(tracks: LineTracks, use: np.ndarray, o: RotationOnlyOptions
                 ) -> tuple[FloatArray, np.ndarray, FloatArray, dict[int, str]]:
    """Frame by frame: each rotation from the lines seen before, then its new lines."""
    F, M = tracks.num_frames, tracks.num_tracks
    R = np.tile(np.eye(3), (F, 1, 1))
    done = np.zeros(F, bool)
    acc = np.zeros((M, 3))  # signed sums of the rotated observations of each line
    reasons: dict[int, str] = {}
    by_frame = np.argsort(tracks.obs_frame, kind="stable")
    bounds = np.searchsorted(tracks.obs_frame[by_frame], np.arange(F + 1))
    prev = np.eye(3)
    min_spread = np.radians(o.min_spread_deg)
    scale = np.radians(o.robust_scale_deg)
    started = False
    for f in range(F):
        k = by_frame[bounds[f]:bounds[f + 1]]
        k = k[use[tracks.obs_track[k]]]
        t = tracks.obs_track[k]
        m = tracks.obs_normal[k]
        if not started:
            if not _spread_ok(m, min_spread) or len(k) < o.min_lines:
                reasons[f] = f"sees {len(k)} lines, too few to start from"
                continue
            started, R[f], done[f] = True, np.eye(3), True
            acc[t] += m
            continue
        known = np.linalg.norm(acc[t], axis=1) > 0
        n = acc[t[known]] / np.linalg.norm(acc[t[known]], axis=1, keepdims=True)
        mk = m[known]
        if known.sum() < o.min_lines or not _spread_ok(n, min_spread):
            reasons[f] = (f"sees {int(known.sum())} lines already placed, too few (or all in "
                          "one pencil) to fix the rotation")
            continue
        Rf = prev
        for _ in range(5):
            s = np.sign(np.sum((mk @ Rf.T) * n, axis=1))
            s[s == 0] = 1.0
            r = np.arccos(np.clip(np.sum((mk @ Rf.T) * (s[:, None] * n), axis=1), -1, 1))
            Rf = procrustes(mk * s[:, None], n, _weights(r, scale))
        R[f], done[f], prev = Rf, True, Rf
        rot = m @ Rf.T
        s = np.ones(len(t))
        s[known] = np.sign(np.sum(rot[known] * n, axis=1))
        s[s == 0] = 1.0
        acc[t] += rot * s[:, None]
    normals = np.full((M, 3), np.nan)
    ok = np.linalg.norm(acc, axis=1) > 0
    normals[ok] = acc[ok] / np.linalg.norm(acc[ok], axis=1, keepdims=True)
    return R, done, normals, reasons


def _residuals(tracks: LineTracks, R: FloatArray, n: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Angle (rad) of every observation to its line's world NV, and the aligned sign."""
    rot = np.einsum("kij,kj->ki", R[tracks.obs_frame], tracks.obs_normal)
    dot = np.sum(rot * n[tracks.obs_track], axis=1)
    s = np.where(dot < 0, -1.0, 1.0)
    return np.arccos(np.clip(np.abs(dot), 0.0, 1.0)), s


def _joint(tracks: LineTracks, R: FloatArray, n: FloatArray, sel: np.ndarray,
           o: RotationOnlyOptions) -> tuple[FloatArray, FloatArray]:
    """Alternate world NVs and per-frame rotations over the observations ``sel`` (bool, K)."""
    F, M = tracks.num_frames, tracks.num_tracks
    scale = np.radians(o.robust_scale_deg)
    f_all, t_all, m_all = tracks.obs_frame[sel], tracks.obs_track[sel], tracks.obs_normal[sel]
    frames = np.unique(f_all)
    last = np.inf
    for _ in range(o.iterations):
        rot = np.einsum("kij,kj->ki", R[f_all], m_all)
        dot = np.sum(rot * n[t_all], axis=1)
        s = np.where(dot < 0, -1.0, 1.0)
        r = np.arccos(np.clip(np.abs(dot), 0.0, 1.0))
        w = _weights(r, scale)
        acc = np.zeros((M, 3))
        np.add.at(acc, t_all, (w * s)[:, None] * rot)
        ok = np.linalg.norm(acc, axis=1) > 0
        n = n.copy()
        n[ok] = acc[ok] / np.linalg.norm(acc[ok], axis=1, keepdims=True)
        R[frames] = _procrustes_batch(m_all * (w * s)[:, None], n[t_all], f_all, F)[frames]
        cost = float(np.sum(w * r ** 2))
        if last - cost <= 1e-12 * max(last, 1e-30):
            break
        last = cost
    return R, n


def estimate_rotation_only(tracks: LineTracks,
                           options: RotationOnlyOptions | None = None) -> RotationOnlyResult:
    """Rotations of every frame of a camera that turns in place (see the module docstring).

    Raises:
        OmniSfmError: no frame sees enough lines to start from.
    """
    o = options or RotationOnlyOptions()
    M = tracks.num_tracks
    use = np.ones(M, bool)
    outliers = np.zeros(M, bool)
    for _ in range(3):
        R, done, n, reasons = _incremental(tracks, use, o)
        if not done.any():
            raise OmniSfmError("no frame sees 2 or more lines in different directions: "
                               "nothing to fix a rotation with")
        sel = use[tracks.obs_track] & done[tracks.obs_frame] & \
            np.isfinite(n[tracks.obs_track]).all(axis=1)
        ang0, _ = _residuals(tracks, R, np.nan_to_num(n))
        rms0 = float(np.degrees(np.sqrt(np.mean(ang0[sel] ** 2)))) if sel.any() else np.nan
        R, n = _joint(tracks, R, np.nan_to_num(n), sel, o)
        ang, _ = _residuals(tracks, R, n)
        sq = np.bincount(tracks.obs_track[sel], ang[sel] ** 2, minlength=M)
        cnt = np.bincount(tracks.obs_track[sel], minlength=M)
        track_rms = np.full(M, np.nan)
        track_rms[cnt > 0] = np.sqrt(sq[cnt > 0] / cnt[cnt > 0])
        good = cnt > 0
        robust = 1.4826 * float(np.median(track_rms[good]))
        bad = good & (track_rms > max(o.outlier_factor * robust, np.radians(0.2)))
        if not bad.any():
            break
        outliers |= bad
        use &= ~bad
    first = int(np.flatnonzero(done)[0])
    R_first = R[first].copy()
    R = np.einsum("ji,fjk->fik", R_first, R)  # world = the first estimated camera
    R[~done] = np.eye(3)
    used = use & (cnt > 0)
    world_n = np.full((M, 3), np.nan)
    world_n[used] = n[used] @ R_first
    return RotationOnlyResult(
        rotations=R, estimated=done, world_normals=world_n, used_tracks=used,
        outliers=outliers, track_rms_deg=np.degrees(track_rms),
        rms_initial_deg=rms0,
        rms_final_deg=float(np.degrees(np.sqrt(np.mean(ang[sel] ** 2)))),
        median_deg=float(np.degrees(np.median(ang[sel]))), reasons=reasons)
