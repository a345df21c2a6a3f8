"""Parallel families as fixed world directions (omni_sfm/estimate/families.py) and the rotation
gauge they fix in the bundle adjustment (bundle_adjust(held_directions=))."""

from __future__ import annotations

import numpy as np

from omni_sfm.estimate.bundle import _directions_fix_rotation, bundle_adjust
from omni_sfm.estimate.families import (
    camera_anchors,
    line_families,
    manhattan,
    point_given_direction,
    snap_to_families,
)
from omni_sfm.geometry import normalize, rotation_angle, rotvec_to_matrix
from omni_sfm.synth.simulate import SimulationOptions, simulate


def _manhattan_lines(rng: np.random.Generator, noise_deg: float) -> tuple[np.ndarray, ...]:
    """Directions of 3 x 20 lines around the axes of a turned Manhattan frame (noisy, random
    signs) and 10 others; the frame's axes and each line's axis (-1: other)."""
    Q = rotvec_to_matrix(np.array([0.3, -0.2, 0.5]))
    axis = np.repeat(np.arange(3), 20)
    d = Q[:, axis].T + np.radians(noise_deg) * rng.normal(size=(60, 3))
    d = normalize(d) * rng.choice([-1.0, 1.0], size=(60, 1))
    other = normalize(rng.normal(size=(10, 3)))
    return np.concatenate([d, other]), Q.T, np.concatenate([axis, np.full(10, -1)])


def test_line_families_are_the_manhattan_axes() -> None:
    d, axes, axis = _manhattan_lines(np.random.default_rng(0), 0.3)
    d[5] = np.nan  # an unknown line
    D, fam = line_families(d)
    assert len(D) == 3
    np.testing.assert_allclose(D @ D.T, np.eye(3), atol=1e-12)  # made exactly orthogonal
    for k in range(3):
        j = int(np.argmax(np.abs(axes @ D[k])))
        assert np.degrees(np.arccos(min(1.0, abs(float(axes[j] @ D[k]))))) < 0.2
        # the family's members are exactly the lines of that axis
        assert set(np.flatnonzero(fam == k)) == set(np.flatnonzero(axis == j)) - {5}
    assert fam[5] == -1


def test_snap_keeps_the_part_of_the_line_the_cameras_see() -> None:
    anchor = np.array([50.0, 2.0, 1.0])
    D = normalize(np.array([[1.0, 0.0, 0.0]]))
    d = normalize(np.array([[1.0, 0.01, -0.01]]))  # 0.8 deg off its family
    p0 = anchor - 0.5 * np.cross(d[0], [0.0, 0.0, 1.0])  # the line passes near the anchor
    p = p0 - float(p0 @ d[0]) * d
    d2, p2 = snap_to_families(-d, p, D, np.array([0]), anchor[None])
    np.testing.assert_allclose(d2[0], -D[0])  # its family's direction, its own sign
    assert abs(float(p2[0] @ d2[0])) < 1e-12  # the point nearest the origin
    # it turns about its point nearest the anchor: that point stays on it
    near = p[0] + float((anchor - p[0]) @ d[0]) * d[0]

    def off(dd: np.ndarray, pp: np.ndarray) -> float:
        return float(np.linalg.norm(np.cross(near - pp, dd)))

    assert off(d2[0], p2[0]) < 1e-9
    # turning about the point nearest the origin would move it by ~0.7 m
    d3, p3 = snap_to_families(d, p, D, np.array([0]), np.full((1, 3), np.nan))
    assert off(d3[0], p3[0]) > 0.5


def test_camera_anchors_are_the_mean_centres() -> None:
    c = np.array([[0.0, 0, 0], [2.0, 0, 0], [np.nan, 0, 0]])
    a = camera_anchors(np.array([0, 1, 2, 2]), np.array([0, 0, 0, 1]), c, 3)
    np.testing.assert_allclose(a[0], [1.0, 0, 0])
    assert np.isnan(a[1:]).all()


def test_point_given_direction_is_exact() -> None:
    D = normalize(np.array([0.2, 1.0, 0.1]))
    p = np.array([1.0, 0.0, 3.0])
    p -= float(p @ D) * D
    c = np.array([[0.0, 0, 0], [1.0, 0.5, 0], [2.0, -0.3, 0.4]])
    n = normalize(np.cross(p - c, D))
    q, spread = point_given_direction(n, c, D)
    np.testing.assert_allclose(q, p, atol=1e-9)
    assert spread > np.radians(5.0)


def test_point_given_direction_fits_noisy_views_far_from_the_origin() -> None:
    # a corridor's cross line 40 m along its direction from the world's origin, seen from
    # cameras 0.6-2.5 m from it with 0.1 deg of noise: the distances from the planes must not
    # take the noise of the normals along the direction times those 40 m (the formula before
    # fitted such a line's views degrees off and the registration of a long walk stopped at it)
    rng = np.random.default_rng(4)
    D = normalize(np.array([1.0, 0.02, -0.01]))
    p = np.array([40.0, 1.1, 0.7])
    p -= float(p @ D) * D
    c = p + 40.0 * D + np.column_stack([rng.uniform(-2, 2, 15), np.linspace(-2.5, -0.6, 15),
                                        rng.uniform(-0.3, 0.3, 15)])
    n = normalize(np.cross(p - c, D))
    noisy = normalize(n + np.radians(0.1) * rng.normal(size=n.shape))
    q, spread = point_given_direction(noisy, c, D)
    assert spread > np.radians(10.0)
    u = normalize(np.cross(q - c, D))
    ang = np.degrees(np.arccos(np.clip(np.abs(np.sum(u * noisy, 1)), 0.0, 1.0)))
    assert np.sqrt(np.mean(ang ** 2)) < 0.2
    assert np.linalg.norm(q - p) < 0.02


def test_held_directions_of_two_families_fix_the_rotation_gauge() -> None:
    # noise-free; frame 0 starts 1 deg off. Its rotation is part of the gauge only while the
    # held directions leave the world's rotation free: with lines of two directions or more
    # held at their true directions, it is estimated (exactly) like every other frame's.
    sim = simulate(SimulationOptions(num_views=12, num_parallel=6, num_other=8, seed=2))
    g, tracks = sim.groundtruth, sim.tracks
    F, M = len(g), tracks.num_tracks
    rng = np.random.default_rng(1)
    R = g.rotations @ rotvec_to_matrix(rng.normal(size=(F, 3)) * 0.005)
    R[0] = g.rotations[0] @ rotvec_to_matrix(np.radians([1.0, 0.0, 0.0]))
    d = sim.line_directions
    p = sim.line_points - np.sum(sim.line_points * d, 1, keepdims=True) * d
    held = sim.parallel.copy()
    held[np.flatnonzero(~sim.parallel)[:3]] = True  # the family and three other lines
    every = np.ones(M, bool)
    assert _directions_fix_rotation(d, held, every)
    assert not _directions_fix_rotation(d, sim.parallel, every)
    assert not _directions_fix_rotation(d, None, every)
    res = bundle_adjust(tracks, R, g.positions, d, p, held_directions=held)
    err = np.degrees(rotation_angle(np.swapaxes(g.rotations, 1, 2) @ res.rotations))
    assert err.max() < 1e-5
    assert res.rms_final_deg < 1e-5
    np.testing.assert_allclose(res.line_directions[held], d[held], atol=1e-12)
    # one family held: the turn about it is free, frame 0's turn about it is the gauge; the
    # rest of its rotation is estimated like every other frame's (holding all of it would tie
    # the family's direction to the first frame, and another first frame would give another
    # result): the whole comes out turned about the family by frame 0's start
    res1 = bundle_adjust(tracks, R, g.positions, d, p, held_directions=sim.parallel)
    turn = res1.rotations @ np.swapaxes(g.rotations, 1, 2)  # world turn of each frame
    np.testing.assert_allclose(turn, np.broadcast_to(turn[0], turn.shape), atol=1e-7)
    family = d[sim.parallel][0]
    np.testing.assert_allclose(turn[0] @ family, family, atol=1e-9)
    assert res1.rms_final_deg < 1e-5


def test_manhattan_pair_fixes_its_third_axis() -> None:
    """Two orthogonal families fix the third axis: a family of a few lines 8 deg off it takes
    it exactly, and where no family is near it, it is added (the corridor round the corner)."""
    ax = np.eye(3)
    tilt = np.array([0.0, np.cos(np.radians(8.0)), np.sin(np.radians(8.0))])
    D = manhattan(np.stack([ax[2], ax[0], -tilt]), np.array([20, 10, 2]), complete_deg=15.0)
    assert D.shape == (3, 3)
    np.testing.assert_allclose(D @ D.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(D[2], -ax[1], atol=1e-12)  # its sign kept
    # without complete_deg the few lines' family stays where they put it
    np.testing.assert_allclose(manhattan(np.stack([ax[2], ax[0], tilt]), np.array([20, 10, 2]))[2],
                               tilt, atol=1e-12)
    D = manhattan(np.stack([ax[2], ax[0]]), np.array([20, 10]), complete_deg=15.0)
    assert D.shape == (3, 3)
    np.testing.assert_allclose(np.abs(D[2]), ax[1], atol=1e-12)
    # an Atlanta direction 45 deg off the axes is neither moved nor taken for the third axis
    diag = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    D = manhattan(np.stack([ax[2], ax[0], diag]), np.array([20, 10, 5]), complete_deg=15.0)
    assert D.shape == (4, 3)
    np.testing.assert_allclose(D[2], diag, atol=1e-12)
