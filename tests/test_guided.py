"""Guided matching (omni_sfm.refine.guided): SIFT-like matches of two posed frames along their
epipolar geometry, on simulated keypoints whose true correspondences are known."""

from __future__ import annotations

import numpy as np
import pytest

from omni_sfm.geometry import rotvec_to_matrix
from omni_sfm.refine.guided import FrameKeypoints, GuidedMatchOptions, match_pair

PIXEL = np.radians(0.3)  # angular size of a pixel, as on an 800 x 600 mirror camera


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _jitter(rays: np.ndarray, rng: np.random.Generator, sigma: float) -> np.ndarray:
    return _unit(rays + rng.normal(0.0, sigma, rays.shape))


def _scene(seed: int = 0, *, n: int = 800, extra: int = 300, repeated: int = 100,
           baseline=(0.06, 0.015, 0.004)):
    """Points 1-6 m around two cameras; frame b is turned 12 deg and moved by ``baseline``.
    Keypoint k < n of either frame sees point k (shuffled in b); ``extra`` unmatched keypoints
    each; the last ``repeated`` points share their descriptors in pairs (repeated texture).
    Returns the frames, the truth ``(M, 2)``, ``world_from_b`` and ``b``'s centre."""
    rng = np.random.default_rng(seed)
    X = _unit(rng.normal(size=(n, 3))) * rng.uniform(1.0, 6.0, (n, 1))
    world_from_b = rotvec_to_matrix(np.radians([2.0, -3.0, 12.0]))
    centre_b = np.asarray(baseline, float)
    rays_a = _jitter(_unit(X), rng, 0.4 * PIXEL)
    rays_b = _jitter(_unit((X - centre_b) @ world_from_b), rng, 0.4 * PIXEL)
    desc = rng.uniform(0, 1, (n, 128)) ** 3
    half = repeated // 2
    desc[n - half:] = desc[n - repeated:n - half]
    desc_a = desc + rng.normal(0, 0.01, desc.shape)
    desc_b = desc + rng.normal(0, 0.01, desc.shape)
    rays_a = np.concatenate([rays_a, _unit(rng.normal(size=(extra, 3)))])
    rays_b = np.concatenate([rays_b, _unit(rng.normal(size=(extra, 3)))])
    desc_a = np.concatenate([desc_a, rng.uniform(0, 1, (extra, 128)) ** 3])
    desc_b = np.concatenate([desc_b, rng.uniform(0, 1, (extra, 128)) ** 3])
    perm = rng.permutation(n + extra)  # b's keypoint perm[k] is keypoint k of the list above
    rays_b_out, desc_b_out = np.empty_like(rays_b), np.empty_like(desc_b)
    rays_b_out[perm], desc_b_out[perm] = rays_b, desc_b
    a = FrameKeypoints.build(rays_a, np.full(n + extra, PIXEL), desc_a)
    b = FrameKeypoints.build(rays_b_out, np.full(n + extra, PIXEL), desc_b_out)
    truth = np.stack([np.arange(n), perm[:n]], 1)
    return a, b, truth, world_from_b, centre_b


def _match(a, b, world_from_b, centre_b, options=None):
    return match_pair(a, b, world_from_b.T, centre_b, options)  # a's frame is the world


def _score(matches: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    right = {tuple(m) for m in truth.tolist()}
    hits = sum(tuple(m) in right for m in matches.tolist())
    return hits / max(len(matches), 1), hits / len(truth)


def _brute_force(a: FrameKeypoints, b: FrameKeypoints, o: GuidedMatchOptions) -> np.ndarray:
    """COLMAP's tests among all keypoints, no geometry."""
    sim = a.descriptors @ b.descriptors.T
    return _tests(sim, a, b, o)


def _tests(sim: np.ndarray, a: FrameKeypoints, b: FrameKeypoints, o: GuidedMatchOptions
           ) -> np.ndarray:
    def one_way(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        order = np.argsort(-s, axis=1)
        best = s[np.arange(len(s)), order[:, 0]]
        second = s[np.arange(len(s)), order[:, 1]] if s.shape[1] > 1 else np.full(len(s), -2.0)
        d1 = np.arccos(np.clip(best, -1, 1))
        d2 = np.arccos(np.clip(np.where(second > -2.0, second, 0.0), -1, 1))
        ok = (best > -2.0) & (d1 <= o.max_distance) & (d1 < o.max_ratio * d2)
        return order[:, 0], ok

    j, ok_a = one_way(sim)
    i, ok_b = one_way(sim.T.copy())
    keep = np.flatnonzero(ok_a & ok_b[j] & (i[j] == np.arange(len(j))))
    return np.stack([a.index[keep], b.index[j[keep]]], 1)


def test_guided_matches_are_right_and_complete_and_beat_repeated_texture():
    a, b, truth, world_from_b, centre_b = _scene()
    m = _match(a, b, world_from_b, centre_b)
    precision, recall = _score(m, truth)
    assert precision > 0.99 and recall > 0.97, (precision, recall)
    # the repeated texture: ambiguous to descriptors alone, told apart by the geometry
    repeated = truth[-100:]
    assert _score(m, repeated)[1] > 0.9
    assert _score(_brute_force(a, b, GuidedMatchOptions()), repeated)[1] < 0.1


def test_a_pose_outside_the_tolerance_finds_almost_nothing():
    """The band follows the given poses: turned 6 deg away, the true matches fall outside it
    (but for rays near the turn's axis)."""
    a, b, truth, world_from_b, centre_b = _scene(1)
    wrong = world_from_b @ rotvec_to_matrix(np.radians([6.0, 0.0, 0.0]))
    assert _score(_match(a, b, wrong, centre_b), truth)[1] < 0.15
    slightly = world_from_b @ rotvec_to_matrix(np.radians([0.0, 0.25, 0.0]))
    assert _score(_match(a, b, slightly, centre_b), truth)[1] > 0.95


def test_the_baseline_length_does_not_matter_and_a_camera_at_rest_matches_along_its_rays():
    a, b, truth, world_from_b, centre_b = _scene(2)
    m = _match(a, b, world_from_b, centre_b)
    np.testing.assert_array_equal(m, _match(a, b, world_from_b, 1e3 * centre_b))
    a, b, truth, world_from_b, centre_b = _scene(3, baseline=(0.0, 0.0, 0.0))
    precision, recall = _score(_match(a, b, world_from_b, centre_b), truth)
    assert precision > 0.99 and recall > 0.97, (precision, recall)


@pytest.mark.parametrize("seed", [4, 5])
def test_the_blocks_find_exactly_the_matches_of_the_whole_band(seed):
    """The azimuth windows and blocks against a dense evaluation of the same band on all
    keypoint pairs (wrap-around at +-180 deg, keypoints near both poles, short blocks)."""
    rng = np.random.default_rng(seed)
    a, b, _, world_from_b, centre_b = _scene(seed, n=500, extra=200)
    baseline = _unit(centre_b)
    # match_pair's azimuth 0 (the baseline is mostly along x)
    u = _unit(np.cross(baseline, [0.0, 1.0, 0.0]))
    v = np.cross(baseline, u)
    # points at azimuth +-180 deg (their rays straddle the cut), and rays of b near both poles
    e = rng.uniform(-1.2, 1.2, (40, 1))
    X = (-np.cos(e) * u + np.sin(e) * baseline + rng.normal(0, 2e-3, (40, 1)) * v) * \
        rng.uniform(1.0, 4.0, (40, 1))
    cut_a = _jitter(_unit(X), rng, 0.4 * PIXEL)
    cut_b = _jitter(_unit((X - centre_b) @ world_from_b), rng, 0.4 * PIXEL)
    near = _unit(baseline + rng.normal(0, 0.05, (40, 3))) * rng.choice([-1.0, 1.0], (40, 1))
    desc = rng.uniform(0, 1, (80, 128)) ** 3
    a = FrameKeypoints.build(np.concatenate([a.rays_in_cam, cut_a]), np.full(740, PIXEL),
                             np.concatenate([a.descriptors, desc[:40]]))
    b = FrameKeypoints.build(np.concatenate([b.rays_in_cam, cut_b, near @ world_from_b]),
                             np.full(780, PIXEL),
                             np.concatenate([b.descriptors, desc[:40], desc[40:]]))
    side = np.sign(cut_b @ world_from_b.T @ v)
    assert np.sum(side > 0) > 5 and np.sum(side < 0) > 5
    o = GuidedMatchOptions(block=37)
    got = _match(a, b, world_from_b, centre_b, o)
    # the band of match_pair's docstring, evaluated for every pair
    basis = np.stack([u, v, baseline])
    pa, pb = a.rays_in_cam @ basis.T, (b.rays_in_cam @ world_from_b.T) @ basis.T
    phi_a, phi_b = np.arctan2(pa[:, 1], pa[:, 0]), np.arctan2(pb[:, 1], pb[:, 0])
    rho_b = np.hypot(pb[:, 0], pb[:, 1])
    delta_a = 0.5 * o.band_px * a.pixel_rad + np.radians(o.pose_tolerance_deg)
    delta_b = 0.5 * o.band_px * b.pixel_rad
    rho_eff = np.where(rho_b < delta_a.max() + delta_b.max(), 0.0, rho_b)
    dphi = np.abs((phi_b[None] - phi_a[:, None] + np.pi) % (2 * np.pi) - np.pi)
    inside = (dphi * rho_eff[None] <= delta_a[:, None] + delta_b[None] + 1e-6) & \
        (pb[None, :, 2] - delta_b[None] <= pa[:, None, 2] + delta_a[:, None])
    sim = np.where(inside, a.descriptors @ b.descriptors.T, -2.0)
    want = _tests(sim, a, b, o)
    assert len(want) > 300 and np.sum(want[:, 0] >= 700) > 30
    assert {tuple(m) for m in got.tolist()} == {tuple(m) for m in want.tolist()}


def test_keypoints_without_a_ray_are_left_out_and_bad_input_is_refused():
    a, b, truth, world_from_b, centre_b = _scene(6, n=200, extra=0)
    rays = a.rays_in_cam.copy()
    rays[:10] = np.nan
    a2 = FrameKeypoints.build(rays, a.pixel_rad, a.descriptors)
    assert len(a2.index) == 190 and a2.index[0] == 10
    m = _match(a2, b, world_from_b, centre_b)
    assert len(m) and m[:, 0].min() >= 10
    with pytest.raises(ValueError, match="shape"):
        FrameKeypoints.build(rays[:, :2], a.pixel_rad, a.descriptors)
    with pytest.raises(ValueError, match="not finite"):
        match_pair(a, b, np.eye(3), np.array([np.nan, 0.0, 0.0]))
    for bad in ({"band_px": 0.0}, {"max_ratio": -1.0}, {"pose_tolerance_deg": -0.1},
                {"block": 0}):
        with pytest.raises(ValueError):
            GuidedMatchOptions(**bad)
