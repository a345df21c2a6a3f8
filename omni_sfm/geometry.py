"""Small, vectorised 3D geometry helpers shared by every stage (rotations, unit vectors)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def normalize(v: ArrayLike, axis: int = -1) -> FloatArray:
    """Unit vectors along ``axis``; zero vectors become NaN (never silently zero)."""
    a = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(a, axis=axis, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, a / n, np.nan)


def skew(v: ArrayLike) -> FloatArray:
    """``(..., 3)`` -> ``(..., 3, 3)`` cross-product matrices: ``skew(a) @ b == cross(a, b)``."""
    a = np.asarray(v, dtype=np.float64)
    z = np.zeros(a.shape[:-1])
    return np.stack(
        [
            np.stack([z, -a[..., 2], a[..., 1]], -1),
            np.stack([a[..., 2], z, -a[..., 0]], -1),
            np.stack([-a[..., 1], a[..., 0], z], -1),
        ],
        -2,
    )


def rotation_about_axis(axis: ArrayLike, angle: ArrayLike) -> FloatArray:
    """Rodrigues: rotation matrices ``(..., 3, 3)`` by ``angle`` (radians) about unit ``axis``.

    ``axis`` is ``(3,)`` or ``(..., 3)`` and broadcasts against ``angle`` ``(...)``.
    Positive angles turn counter-clockwise when looking down the axis (right-hand rule).
    """
    k = normalize(axis)
    th = np.asarray(angle, dtype=np.float64)
    shape = np.broadcast_shapes(k.shape[:-1], th.shape)
    k = np.broadcast_to(k, (*shape, 3))
    th = np.broadcast_to(th, shape)[..., None, None]
    K = skew(k)
    eye = np.broadcast_to(np.eye(3), (*shape, 3, 3))
    return eye + np.sin(th) * K + (1.0 - np.cos(th)) * (K @ K)


def rotvec_to_matrix(rotvec: ArrayLike) -> FloatArray:
    """Axis-angle vectors ``(..., 3)`` (radians) -> rotation matrices ``(..., 3, 3)``."""
    r = np.asarray(rotvec, dtype=np.float64)
    th = np.linalg.norm(r, axis=-1)
    safe = np.where(th > 0, th, 1.0)[..., None]
    axis = np.where(th[..., None] > 0, r / safe, np.array([0.0, 0.0, 1.0]))
    return rotation_about_axis(axis, th)


def rotation_angle(R: ArrayLike) -> FloatArray:
    """Rotation angle in radians of ``(..., 3, 3)`` rotation matrices, robust near 0 and pi."""
    m = np.asarray(R, dtype=np.float64)
    c = (np.trace(m, axis1=-2, axis2=-1) - 1.0) / 2.0
    s = np.linalg.norm(
        np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                  m[..., 1, 0] - m[..., 0, 1]], -1), axis=-1) / 2.0
    return np.arctan2(s, c)


def angle_between(a: ArrayLike, b: ArrayLike, *, unsigned_lines: bool = False) -> FloatArray:
    """Angle in radians between vectors ``(..., 3)``.

    With ``unsigned_lines`` the sign of either vector is ignored (angle in ``[0, pi/2]``), as for
    line normals whose sign is arbitrary.
    """
    ua, ub = normalize(a), normalize(b)
    c = np.sum(ua * ub, axis=-1)
    s = np.linalg.norm(np.cross(ua, ub), axis=-1)
    if unsigned_lines:
        c = np.abs(c)
    return np.arctan2(s, c)


def quat_xyzw_from_matrix(R: ArrayLike) -> FloatArray:
    """Rotation matrices ``(N, 3, 3)`` -> quaternions ``(N, 4)``: ``qx qy qz qw``, qw >= 0."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    return np.where(q[..., 3:4] < 0, -q, q)


def matrix_from_quat_xyzw(q: ArrayLike) -> FloatArray:
    """Quaternions ``(N, 4)`` as ``qx qy qz qw`` (normalised here) -> matrices ``(N, 3, 3)``."""
    from scipy.spatial.transform import Rotation

    return np.asarray(Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix())


def ray_line_closest(origins: ArrayLike, rays: ArrayLike, points: ArrayLike,
                     directions: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Closest approach of rays ``o + s r`` to lines ``p + u d`` (all ``(..., 3)``, broadcast;
    ``r`` and ``d`` unit).

    Returns ``(s, u, den)``: the ray's and the line's parameters at the closest points, and
    ``den = 1 - (r . d)^2``, which vanishes for a ray parallel to its line (``s`` and ``u`` are
    then meaningless; they are computed with ``den`` clamped to 1e-12, so callers filter on it).
    """
    r, d = np.asarray(rays, dtype=np.float64), np.asarray(directions, dtype=np.float64)
    b = np.asarray(points, dtype=np.float64) - np.asarray(origins, dtype=np.float64)
    a = np.sum(r * d, axis=-1)
    br, bd = np.sum(b * r, axis=-1), np.sum(b * d, axis=-1)
    den = 1.0 - a * a
    safe = np.maximum(den, 1e-12)
    return (br - bd * a) / safe, (br * a - bd) / safe, den
