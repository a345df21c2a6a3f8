"""The rotation helpers' fast paths (one vector in Python floats, batches without stacking):
the same matrices, bit for bit, as Rodrigues' formula written with numpy's array operations
(the estimator's discrete decisions depend on the last bit), in every shape the callers use."""

from __future__ import annotations

import numpy as np
import pytest

from omni_sfm.geometry import (
    cross3,
    nearest_rotation,
    normalize,
    rotation_about_axis,
    rotvec_to_matrix,
    skew,
)


def _reference_about_axis(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues with broadcast arrays and np.stack: how the helpers computed it before."""
    k = normalize(axis)
    th = np.asarray(angle, dtype=np.float64)
    shape = np.broadcast_shapes(k.shape[:-1], th.shape)
    k = np.broadcast_to(k, (*shape, 3))
    th = np.broadcast_to(th, shape)[..., None, None]
    z = np.zeros(k.shape[:-1])
    K = np.stack([np.stack([z, -k[..., 2], k[..., 1]], -1),
                  np.stack([k[..., 2], z, -k[..., 0]], -1),
                  np.stack([-k[..., 1], k[..., 0], z], -1)], -2)
    eye = np.broadcast_to(np.eye(3), (*shape, 3, 3))
    return eye + np.sin(th) * K + (1.0 - np.cos(th)) * (K @ K)


def _reference_rotvec(r: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(r, axis=-1)
    safe = np.where(th > 0, th, 1.0)[..., None]
    axis = np.where(th[..., None] > 0, r / safe, np.array([0.0, 0.0, 1.0]))
    return _reference_about_axis(axis, th)


@pytest.mark.parametrize("scale", [1e-12, 1e-6, 0.3, 3.0])
def test_rotvec_single_and_batched_bit_for_bit(scale: float) -> None:
    rng = np.random.default_rng(0)
    r = rng.normal(size=(4, 5, 3)) * scale
    batch = rotvec_to_matrix(r)
    assert batch.shape == (4, 5, 3, 3)
    np.testing.assert_array_equal(batch, _reference_rotvec(r))
    for idx in np.ndindex(4, 5):
        one = rotvec_to_matrix(r[idx])
        assert one.shape == (3, 3)
        np.testing.assert_array_equal(one, _reference_rotvec(r[idx]))
        np.testing.assert_allclose(one, batch[idx], atol=1e-15)
        np.testing.assert_allclose(one @ one.T, np.eye(3), atol=1e-15)


def test_rotvec_zero_and_undefined() -> None:
    np.testing.assert_array_equal(rotvec_to_matrix(np.zeros(3)), np.eye(3))
    np.testing.assert_array_equal(rotvec_to_matrix(np.zeros((2, 3))), np.stack([np.eye(3)] * 2))
    np.testing.assert_array_equal(rotvec_to_matrix(np.zeros((0, 3))), np.zeros((0, 3, 3)))
    assert np.isnan(rotvec_to_matrix(np.array([np.nan, 0.0, 0.0]))).all()
    with np.errstate(invalid="ignore"):
        assert np.isnan(rotvec_to_matrix(np.array([np.inf, 0.0, 0.0]))).all()


def test_rotation_about_axis_shapes_bit_for_bit() -> None:
    rng = np.random.default_rng(1)
    axes, angles = rng.normal(size=(6, 3)), rng.normal(size=6)
    z = [0.0, 0.0, 1.0]  # a list, as the callers pass
    for axis, angle, shape in ((z, 0.3, (3, 3)), (z, angles, (6, 3, 3)),
                               (axes, 0.3, (6, 3, 3)), (axes, angles, (6, 3, 3)),
                               (axes[0], angles[0], (3, 3))):
        R = rotation_about_axis(axis, angle)
        assert R.shape == shape
        np.testing.assert_array_equal(R, _reference_about_axis(np.asarray(axis), angle))


def test_skew_and_cross3() -> None:
    rng = np.random.default_rng(2)
    a = rng.normal(size=(4, 2, 3))
    S = skew(a)
    assert S.shape == (4, 2, 3, 3) and skew(a[0, 0]).shape == (3, 3)
    np.testing.assert_array_equal(S, -np.swapaxes(S, -1, -2))
    b = rng.normal(size=(4, 1, 3))  # broadcast
    np.testing.assert_allclose(S @ b[..., None], np.cross(a, b)[..., None], atol=1e-15)
    np.testing.assert_array_equal(cross3(a, b), np.cross(a, b))
    out = np.zeros((4, 2, 6))
    cross3(a, b, out=out[..., 3:])
    np.testing.assert_array_equal(out[..., 3:], np.cross(a, b))
    assert (out[..., :3] == 0).all()


def test_nearest_rotation_is_the_chordal_mean_and_never_a_reflection() -> None:
    rng = np.random.default_rng(3)
    R = rotvec_to_matrix(rng.normal(size=(4, 3)))
    # a rotation perturbed, a sum of rotations near one, a reflection's polar factor
    assert np.allclose(nearest_rotation(R + 1e-9), R, atol=1e-8)
    near = rotvec_to_matrix(1e-3 * rng.normal(size=(6, 3))) @ R[0]
    assert np.allclose(nearest_rotation(near.sum(axis=0)), R[0], atol=2e-3)
    Q = nearest_rotation(-R)  # det -1 before the sign fix
    assert np.allclose(np.linalg.det(Q), 1.0) and np.allclose(Q @ np.swapaxes(Q, 1, 2),
                                                             np.eye(3), atol=1e-12)
    assert nearest_rotation(R[1]).shape == (3, 3)
