"""Small, vectorised 3D geometry helpers shared by every stage: rotations, unit vectors, bases,
the normal vectors (NVs) of lines and the angles between them.

Each piece of math has its home here (similarity transforms: :mod:`omni_sfm.transforms`), so
that the stages call one implementation; tests/test_foundation.py tests them.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def _norm(a: FloatArray, axis: int = -1, keepdims: bool = False) -> FloatArray:
    """``np.linalg.norm(a, axis=axis, keepdims=keepdims)`` of a float array (the same
    computation, without its argument handling, which costs more than the sum on small
    arrays)."""
    s: FloatArray = np.add.reduce(a * a, axis=axis, keepdims=keepdims)  # type: ignore[call-overload]
    return np.sqrt(s)


def normalize(v: ArrayLike, axis: int = -1) -> FloatArray:
    """Unit vectors along ``axis``; zero vectors become NaN (never silently zero)."""
    a = np.asarray(v, dtype=np.float64)
    n = _norm(a, axis, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, a / n, np.nan)


# flat indices of a 3x3 matrix's entries that hold +x, +y, +z and -x, -y, -z in skew(x, y, z)
_SKEW_PLUS = np.array([7, 2, 3])
_SKEW_MINUS = np.array([5, 6, 1])


def skew(v: ArrayLike) -> FloatArray:
    """``(..., 3)`` -> ``(..., 3, 3)`` cross-product matrices: ``skew(a) @ b == cross(a, b)``."""
    a = np.asarray(v, dtype=np.float64)
    out = np.zeros((*a.shape[:-1], 3, 3))
    flat = out.reshape(*a.shape[:-1], 9)
    flat[..., _SKEW_PLUS] = a  # (2, 1), (0, 2), (1, 0)
    flat[..., _SKEW_MINUS] = -a  # (1, 2), (2, 0), (0, 1)
    return out


def cross3(a: FloatArray, b: FloatArray, out: FloatArray | None = None) -> FloatArray:
    """``np.cross`` for ``(..., 3)`` arrays with broadcasting, without its axis bookkeeping
    (several times faster, on the small arrays of the per-evaluation loops as on large ones;
    the same values). ``out``: an array of the broadcast shape to write into (a view of a
    larger one, e.g. a Jacobian's columns)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    if out is None:
        shape = a.shape if a.shape == b.shape else np.broadcast_shapes(a.shape, b.shape)
        out = np.empty(shape, np.result_type(a, b))
    np.subtract(a1 * b2, a2 * b1, out=out[..., 0])
    np.subtract(a2 * b0, a0 * b2, out=out[..., 1])
    np.subtract(a0 * b1, a1 * b0, out=out[..., 2])
    return out


_X_AXIS, _Y_AXIS, _Z_AXIS = np.eye(3)
for _axis in (_X_AXIS, _Y_AXIS, _Z_AXIS):
    _axis.setflags(write=False)


def orthonormal_completion(n: FloatArray, *, switch: float = 0.9
                           ) -> tuple[FloatArray, FloatArray]:
    """Unit ``e1, e2`` ``(..., 3)`` with ``(e1, e2, n)`` a right-handed orthonormal basis.

    ``n`` ``(..., 3)`` is unit. ``e1 = normalize(n x h)`` and ``e2 = n x e1`` with the helper
    axis ``h = x`` where ``|n_x| < switch``, else ``y`` (never near ``n`` for ``switch`` well
    below 1). The basis, unlike the plane it spans, depends on ``switch``: each caller keeps the
    one its basis was defined with.
    """
    helper = np.where(np.abs(n[..., :1]) < switch, _X_AXIS, _Y_AXIS)
    e1 = normalize(cross3(n, helper))
    return e1, cross3(n, e1)


def completion_towards(n: FloatArray, hint: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit ``e1, e2`` ``(..., 3)`` with ``(e1, e2, n)`` right-handed orthonormal and ``e1`` the
    direction of ``hint`` ``(..., 3)`` projected onto the plane perpendicular to unit ``n``.

    Undefined where ``hint`` is parallel to ``n`` (NaN where its projection is exactly zero,
    else a direction of round-off)."""
    e1 = normalize(hint - np.sum(hint * n, axis=-1, keepdims=True) * n)
    return e1, cross3(n, e1)


def smallest_eigenvector(S: FloatArray) -> FloatArray:
    """Unit eigenvectors ``(..., n)`` of the smallest eigenvalue of symmetric ``S (..., n, n)``
    (``np.linalg.eigh``; arbitrary sign). For a scatter matrix ``sum w x x^T`` of vectors
    ``x``: the unit ``v`` minimising ``sum w (x . v)^2``."""
    return np.linalg.eigh(S)[1][..., 0]


def smallest_eigenvector_3x3(S: FloatArray) -> FloatArray:
    """:func:`smallest_eigenvector` of many symmetric PSD ``S (K, 3, 3)``: unit eigenvectors
    ``(K, 3)`` of the smallest eigenvalue (arbitrary sign), the same to round-off (1e-14).

    Closed form, five times faster than a batched ``eigh`` on many small matrices (the
    vanishing-point groups' per-frame scatters): the eigenvalue by the trigonometric formula,
    the vector as the largest cross product of two rows of ``S - lambda I``. The line
    extractor's per-segment fits use a compiled version of ``eigh``'s Jacobi rotations
    (:func:`omni_sfm.lines.edge_kernels.smallest_eigenvector3`).
    """
    a, b, c = S[:, 0, 0], S[:, 1, 1], S[:, 2, 2]
    d, e, f = S[:, 0, 1], S[:, 0, 2], S[:, 1, 2]
    tr = (a + b + c) / 3.0
    a0, b0, c0 = a - tr, b - tr, c - tr
    p = np.sqrt(np.maximum((a0 * a0 + b0 * b0 + c0 * c0 + 2.0 * (d * d + e * e + f * f)) / 6.0,
                           1e-200))
    det = a0 * (b0 * c0 - f * f) - d * (d * c0 - f * e) + e * (d * f - b0 * e)
    th = np.arccos(np.clip(det / (2.0 * p ** 3), -1.0, 1.0)) / 3.0
    lam = tr + 2.0 * p * np.cos(th + 2.0 * np.pi / 3.0)
    a1, b1, c1 = a - lam, b - lam, c - lam
    # rows r0 = (a1, d, e), r1 = (d, b1, f), r2 = (e, f, c1) and their cross products
    x01 = np.stack([d * f - e * b1, e * d - a1 * f, a1 * b1 - d * d], 1)
    x02 = np.stack([d * c1 - e * f, e * e - a1 * c1, a1 * f - d * e], 1)
    x12 = np.stack([b1 * c1 - f * f, f * e - d * c1, d * f - b1 * e], 1)
    cand = np.stack([x01, x02, x12], 1)
    norms = np.einsum("kij,kij->ki", cand, cand)
    best = np.argmax(norms, axis=1)
    k = np.arange(S.shape[0])
    return cand[k, best] / np.sqrt(np.maximum(norms[k, best], 1e-300))[:, None]


def unsigned_angle(a: FloatArray, b: FloatArray) -> FloatArray:
    """Angle in radians ``[0, pi/2]`` between unit vectors ``(..., 3)`` ignoring their signs
    (as for line normals): ``atan2(|a x b|, |a . b|)``, accurate near 0 and pi/2.

    The inputs are not normalised here (see :func:`angle_between` for any vectors)."""
    return np.arctan2(_norm(cross3(a, b)), np.abs(np.sum(a * b, axis=-1)))


def line_plane_normals(centres: FloatArray, points: FloatArray,
                       directions: FloatArray) -> FloatArray:
    """``(p - c) x d`` ``(..., 3)``: normals (world frame, not normalised) of the planes through
    camera centres ``c`` and the 3D lines through ``p`` along ``d`` (all ``(..., 3)``, broadcast).

    Normalised and rotated into a camera's frame, this is the line's normal vector (NV) as that
    camera sees it; zero for a camera on the line."""
    return cross3(points - centres, directions)


def predicted_normals(world_from_cam: FloatArray, centres: FloatArray, points: FloatArray,
                      directions: FloatArray) -> FloatArray:
    """``(K, 3)`` NVs predicted in the camera frame (not normalised): ``R^T ((p - c) x d)`` for
    ``K`` pairs of a pose (``world_from_cam (K, 3, 3)``, centre ``(K, 3)``) and a line
    (``points``, ``directions`` ``(K, 3)``)."""
    return np.einsum("kji,kj->ki", world_from_cam,
                     line_plane_normals(centres, points, directions))


def rotation_about_axis(axis: ArrayLike, angle: ArrayLike) -> FloatArray:
    """Rodrigues: rotation matrices ``(..., 3, 3)`` by ``angle`` (radians) about unit ``axis``.

    ``axis`` is ``(3,)`` or ``(..., 3)`` and broadcasts against ``angle`` ``(...)``.
    Positive angles turn counter-clockwise when looking down the axis (right-hand rule).
    """
    k = normalize(axis)
    th = np.asarray(angle, dtype=np.float64)
    if k.shape == (3,) and th.ndim == 0:
        x, y, z = k.tolist()
        return _rodrigues_one(x, y, z, float(th))
    return _rodrigues(k, th)


_EYE3 = np.eye(3)
_EYE3.setflags(write=False)


def _rodrigues_one(x: float, y: float, z: float, th: float) -> FloatArray:
    """``I + sin(th) K + (1 - cos(th)) K^2``, ``K = [k]x``, for one unit axis ``k = (x, y, z)``:
    the operations of :func:`_rodrigues` on one matrix (the same values, bit for bit: ``K^2``
    is numpy's product as there) without its broadcasting and stacking, which cost several
    times the arithmetic on one matrix."""
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return _EYE3 + np.sin(th) * K + (1.0 - np.cos(th)) * (K @ K)


def _rodrigues(k: FloatArray, th: FloatArray) -> FloatArray:
    """``I + sin(th) K + (1 - cos(th)) K^2`` ``(..., 3, 3)``, ``K = [k]x``, for unit axes ``k``
    ``(..., 3)`` broadcast against angles ``th`` ``(...)``."""
    shape = np.broadcast_shapes(k.shape[:-1], th.shape)
    K = skew(np.broadcast_to(k, (*shape, 3)))
    t = np.broadcast_to(th, shape)[..., None, None]
    return _EYE3 + np.sin(t) * K + (1.0 - np.cos(t)) * (K @ K)


def rotvec_to_matrix(rotvec: ArrayLike) -> FloatArray:
    """Axis-angle vectors ``(..., 3)`` (radians) -> rotation matrices ``(..., 3, 3)``.

    A zero vector gives the identity. One vector is computed in Python floats up to the
    matrix (its norms summed in numpy's order), a batch without stacking; both give
    ``rotation_about_axis(r / |r|, |r|)`` bit for bit, the values they always had (the
    estimator's discrete decisions turn on the last bits)."""
    r = np.asarray(rotvec, dtype=np.float64)
    if r.shape == (3,):
        # one vector in Python floats: the sums in numpy's order, (x^2 + y^2) + z^2
        x, y, z = r.tolist()
        t = math.sqrt(x * x + y * y + z * z)
        x, y, z = (x / t, y / t, z / t) if t > 0 else (0.0, 0.0, 1.0)
        n = math.sqrt(x * x + y * y + z * z)
        x, y, z = (x / n, y / n, z / n) if n > 0 else (math.nan, math.nan, math.nan)
        return _rodrigues_one(x, y, z, t)
    th = _norm(r)
    pos = th > 0
    safe = np.where(pos, th, 1.0)[..., None]
    axis = np.where(pos[..., None], r / safe, _Z_AXIS)
    return _rodrigues(normalize(axis), th)


def matrix_to_rotvec(R: ArrayLike) -> FloatArray:
    """Rotation matrices ``(..., 3, 3)`` -> axis-angle vectors ``(..., 3)`` (radians, angle in
    ``[0, pi]``); the inverse of :func:`rotvec_to_matrix`."""
    from scipy.spatial.transform import Rotation

    m = np.asarray(R, dtype=np.float64)
    return np.asarray(Rotation.from_matrix(m.reshape(-1, 3, 3)).as_rotvec()).reshape(
        m.shape[:-1])


def nearest_rotation(M: ArrayLike) -> FloatArray:
    """The rotation nearest each ``(..., 3, 3)`` matrix (Frobenius; the polar factor with its
    determinant made +1): the chordal mean of rotations summed into ``M``, or the Kabsch
    rotation of a correlation matrix ``sum b a^T``."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=np.float64))
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    scale = np.stack([np.ones_like(d), np.ones_like(d), d], axis=-1)
    return np.asarray((U * scale[..., None, :]) @ Vt)


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
    if unsigned_lines:
        return unsigned_angle(ua, ub)
    return np.arctan2(np.linalg.norm(cross3(ua, ub), axis=-1), np.sum(ua * ub, axis=-1))


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
