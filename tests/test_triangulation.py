"""Tracks from matches and their triangulation on fixed poses (omni_sfm.refine.triangulation);
the whole stage on rendered frames runs in tests/test_refine.py and tests/test_refine_klt.py."""

from __future__ import annotations

import numpy as np

from omni_sfm.geometry import normalize
from omni_sfm.refine.triangulation import tracks_from_matches, triangulate_rays


def test_tracks_are_the_connected_keypoints_of_the_match_graph() -> None:
    # image 1 keypoint 0 - image 2 keypoint 3 - image 5 keypoint 1: one track (the chain
    # closes through a pair that skips image 2); image 1 keypoint 2 - image 2 keypoint 0: a
    # second; unmatched keypoints belong to none
    pairs = [(1, 2, np.array([[0, 3], [2, 0]])), (2, 5, np.array([[3, 1]])),
             (1, 5, np.array([[0, 1]]))]
    image, kp, track = tracks_from_matches(pairs, {1: 4, 2: 5, 3: 0, 5: 2})  # 3: no keypoints
    got = {(int(i), int(k), int(t)) for i, k, t in zip(image, kp, track, strict=True)}
    assert len(got) == 5 and np.all(np.diff(track) >= 0)
    first = {(i, k) for i, k, t in got if t == track[image.tolist().index(5)]}
    assert first == {(1, 0), (2, 3), (5, 1)}
    assert {(i, k) for i, k, t in got} - first == {(1, 2), (2, 0)}
    z = tracks_from_matches([], {1: 3})
    assert all(len(a) == 0 for a in z)


def test_rays_meet_at_their_point_and_the_ones_that_miss_are_dropped() -> None:
    rng = np.random.default_rng(0)
    X = rng.uniform(-3, 3, (50, 3)) + [0, 0, 5]
    centres = rng.uniform(-0.5, 0.5, (8, 3))
    track = np.repeat(np.arange(50), 8)
    c = np.tile(centres, (50, 1))
    rays = normalize(X[track] - c)
    # observation 3 of point 7 points 5 deg away; observation 0 of point 9 points backwards
    bad = 7 * 8 + 3
    rays[bad] = normalize(rays[bad] + [0.0, np.tan(np.radians(5.0)), 0.0])
    rays[9 * 8] = -rays[9 * 8]
    Xs, on = triangulate_rays(track, rays, c, np.radians(0.5))
    assert not on[bad] and not on[9 * 8] and on.sum() == len(track) - 2
    assert np.abs(Xs - X).max() < 1e-9
    # a point seen from one place (or by one ray) has none
    one = np.array([0, 0, 1])
    Xs, on = triangulate_rays(one, normalize(np.array([[0, 0, 1.0], [0, 0, 1], [1, 0, 1]])),
                              np.zeros((3, 3)), np.radians(0.5))
    assert np.isnan(Xs).all() and not on.any()
