"""Pieces of a sequence estimated apart, and joining them (docs/estimator.md, stage 8).

Where the registration from known lines stops (a frame sees too few known lines for 10 frames
in a row), the estimator starts again on the frames after it: a new piece, in its own world and
scale. Two pieces that reconstructed some of the same lines (tracks seen on both sides of the
break) are joined by the similarity that maps one piece's lines onto the other's
(:func:`similarity_from_lines`); pieces that share too few lines stay separate segments.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omni_sfm.estimate.rotation_only import procrustes
from omni_sfm.geometry import FloatArray, rotation_angle
from omni_sfm.lines.tracks import LineTracks


def frame_range(tracks: LineTracks, start: int, stop: int) -> tuple[LineTracks, np.ndarray]:
    """The observations of frames ``start..stop-1``, renumbered from 0 (timestamps kept), and
    for each of its tracks the index of the track in ``tracks``."""
    keep = np.flatnonzero((tracks.obs_frame >= start) & (tracks.obs_frame < stop))
    used = np.unique(tracks.obs_track[keep])
    return tracks.subset(keep, used, np.arange(start, stop)), used


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[(start, stop)]`` of the runs of True in ``mask``."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


@dataclass(frozen=True)
class LineSimilarity:
    """``x_a = scale * rotation @ x_b + translation`` and how well it maps the lines.

    Attributes:
        lines: number of common lines that agree (the inliers).
        angle_deg: median angle between mapped and target directions of the inliers.
        distance: median distance of the mapped line points from the target lines, in units of
            the target world.
    """

    rotation: FloatArray
    scale: float
    translation: FloatArray
    lines: int
    angle_deg: float
    distance: float


def _triad(a: FloatArray, b: FloatArray) -> FloatArray:
    """Rotation taking the orthonormal frame built on ``b[0], b[1]`` to the one on ``a``."""
    def frame(u: FloatArray, v: FloatArray) -> FloatArray:
        e1 = u / np.linalg.norm(u)
        e3 = np.cross(u, v)
        e3 /= np.linalg.norm(e3)
        return np.stack([e1, np.cross(e3, e1), e3], axis=1)
    return np.asarray(frame(a[0], a[1]) @ frame(b[0], b[1]).T)


def similarity_from_lines(d_a: FloatArray, p_a: FloatArray, d_b: FloatArray, p_b: FloatArray,
                          *, max_angle_deg: float = 2.0, min_spread_deg: float = 20.0,
                          near: FloatArray | None = None,
                          near_deg: float = 180.0) -> LineSimilarity | None:
    """The similarity mapping lines ``b`` onto lines ``a`` (``(K, 3)`` unit directions of
    arbitrary sign and points, the same K lines in two worlds), or None when they do not fix
    it (fewer than 3 lines that agree, or all of one direction).

    Each pair of lines 20 deg or more apart (both signs) proposes a rotation; it is refined on
    the lines whose directions then agree within ``max_angle_deg``, and scale and translation
    put each mapped line point on its target line (least squares). The proposal with most such
    lines, then the smallest median distance, wins: in a Manhattan world several rotations map
    the directions onto each other and only the positions tell them apart. The scale may come
    out negative: each piece is determined only up to a point reflection. With ``near``, only
    rotations within ``near_deg`` of it are considered (the turn between two frames next to each
    other on both sides of a break: Manhattan scenes are symmetric enough for a wrong turn to
    fit the lines almost as well).
    """
    K = len(d_a)
    if K < 3:
        return None
    cos_tol = np.cos(np.radians(max_angle_deg))
    cos_spread = np.cos(np.radians(min_spread_deg))
    pairs = [(i, j) for i in range(K) for j in range(i + 1, K)
             if abs(float(d_b[i] @ d_b[j])) < cos_spread
             and abs(float(d_a[i] @ d_a[j])) < cos_spread]
    best: LineSimilarity | None = None
    tried: list[FloatArray] = []
    for i, j in pairs[:60]:
        for si, sj in ((1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)):
            R = _triad(np.stack([si * d_a[i], sj * d_a[j]]), d_b[[i, j]])
            if any(np.linalg.norm(R - T) < 1e-3 for T in tried):
                continue
            tried.append(R)
            if near is not None and np.degrees(rotation_angle(R.T @ near)) > near_deg + 5.0:
                continue
            # in a Manhattan world several rotations map the directions onto each other: the
            # lines' positions decide
            cand = _fit(d_a, p_a, d_b, p_b, R, cos_tol, min_spread_deg)
            if cand is not None and (best is None or (cand.lines, -cand.distance) >
                                     (best.lines, -best.distance)):
                best = cand
    return best


def _fit(d_a: FloatArray, p_a: FloatArray, d_b: FloatArray, p_b: FloatArray, R: FloatArray,
         cos_tol: float, min_spread_deg: float) -> LineSimilarity | None:
    """The similarity with rotation near ``R``: refined on the lines whose directions agree
    under it, then scale and translation; the lines that agree in position too count."""
    cosines = np.sum(d_a * (d_b @ R.T), axis=1)
    inl = np.abs(cosines) > cos_tol
    if inl.sum() < 3:
        return None
    R = procrustes(d_b[inl], d_a[inl] * np.sign(cosines[inl])[:, None], np.ones(int(inl.sum())))
    da, pa, pb = d_a[inl], p_a[inl], p_b[inl] @ R.T
    if np.linalg.svd(da, compute_uv=False)[1] < np.sin(np.radians(min_spread_deg)) * 0.5:
        return None  # one direction: the translation along it is free
    P = np.eye(3)[None] - da[:, :, None] * da[:, None, :]  # (k, 3, 3) projectors
    A = np.concatenate([np.einsum("kij,kj->ki", P, pb)[:, :, None], P], axis=2).reshape(-1, 4)
    rhs = np.einsum("kij,kj->ki", P, pa).reshape(-1)
    x = np.linalg.lstsq(A, rhs, rcond=None)[0]
    s, t = float(x[0]), x[1:]
    if abs(s) < 1e-12:
        return None
    resid = np.linalg.norm(np.einsum("kij,kj->ki", P, s * pb + t - pa), axis=1)
    ang = np.degrees(np.arccos(np.clip(np.abs(np.sum(da * (d_b[inl] @ R.T), axis=1)), 0, 1)))
    return LineSimilarity(R, s, t, int(inl.sum()), float(np.median(ang)),
                          float(np.median(resid)))
