"""The shared corner tracker (omni_sfm.corners): KLT steps checked forward-backward, tracks."""

from __future__ import annotations

import cv2
import numpy as np

from omni_sfm.corners import CornerTrackOptions, klt_step, track_corners


def _texture(seed: int, shape: tuple[int, int] = (240, 320)) -> np.ndarray:
    """Smooth random texture stretched to 0..255 (float)."""
    r = np.random.default_rng(seed).uniform(0, 255, shape).astype(np.float32)
    r = cv2.GaussianBlur(r, (0, 0), 2.0)
    return (r - r.min()) / (r.max() - r.min()) * 255


def test_forward_backward_check_rejects_tracks_into_an_occluded_patch():
    """The second image is the first shifted by (2, 1) px, except a patch that shows another
    texture (an occluder). KLT alone follows every corner of the patch somewhere wrong; the
    forward-backward check drops them all and keeps the corners that moved with the image."""
    a = _texture(0)
    b = np.roll(a, (1, 2), axis=(0, 1))
    b[80:160, 120:200] = _texture(1)[80:160, 120:200]
    a8, b8 = a.astype(np.uint8), b.astype(np.uint8)
    mask = np.full(a8.shape, 255, np.uint8)
    pts = cv2.goodFeaturesToTrack(a8, 500, 0.01, 7).reshape(-1, 2).astype(np.float64)
    x, y = pts[:, 0], pts[:, 1]
    occluded = (x > 128) & (x < 192) & (y > 88) & (y < 152)
    free = ((x < 100) | (x > 220) | (y < 60) | (y > 180)) & (x > 20) & (y > 20) & \
        (x < 300) & (y < 220)
    assert occluded.sum() >= 10 and free.sum() >= 100
    truth = pts + [2.0, 1.0]

    p1, ok = klt_step(a8, b8, pts, mask, CornerTrackOptions(fb_max_px=np.inf))
    wrong = np.linalg.norm(p1 - truth, axis=1) > 2.0
    assert (ok & occluded & wrong).sum() >= 0.8 * occluded.sum()  # KLT alone accepts them

    p1, ok = klt_step(a8, b8, pts, mask, CornerTrackOptions(fb_max_px=1.0))
    assert not (ok & occluded).any()
    assert (ok & free).sum() >= 0.95 * free.sum()
    np.testing.assert_allclose(p1[ok & free], truth[ok & free], atol=0.05)


def test_klt_step_drops_points_leaving_the_mask():
    a = _texture(2)
    b = np.roll(a, (0, 3), axis=(0, 1))
    a8, b8 = a.astype(np.uint8), b.astype(np.uint8)
    mask = np.full(a8.shape, 255, np.uint8)
    mask[:, 160:] = 0
    pts = np.array([[100.0, 120.0], [158.5, 120.0]])
    p1, ok = klt_step(a8, b8, pts, mask)
    np.testing.assert_allclose(p1, pts + [3.0, 0.0], atol=0.05)
    assert ok.tolist() == [True, False]


def test_track_corners_follows_a_panning_image_and_refills():
    """Frames pan 5 px per frame to the right: tracks keep their ids with exact positions, and
    corners entering on the left start new tracks once too few remain."""
    big = _texture(3, (240, 450)).astype(np.uint8)
    frames = [big[:, 125 - 5 * k: 445 - 5 * k].copy() for k in range(25)]
    mask = np.full(frames[0].shape, 255, np.uint8)
    mask[:12], mask[-12:], mask[:, :12], mask[:, -12:] = 0, 0, 0, 0
    opts = CornerTrackOptions(max_corners=300, min_distance_px=8.0)
    t = track_corners(frames, mask, opts)
    assert np.all(np.diff(t.frame) >= 0) and set(t.frame.tolist()) == set(range(25))
    ids0, uv0 = t.in_frame(0)
    assert 200 <= len(ids0) <= 300
    ids5, uv5 = t.in_frame(5)
    common, i0, i5 = np.intersect1d(ids0, ids5, return_indices=True)
    assert len(common) >= 0.6 * len(ids0)
    np.testing.assert_allclose(uv5[i5] - uv0[i0], np.tile([25.0, 0.0], (len(common), 1)),
                               atol=0.1)
    for k in range(25):
        ids, _ = t.in_frame(k)
        assert len(np.unique(ids)) == len(ids)
    # tracks leave on the right; the refill adds new ids
    ids_last, _ = t.in_frame(24)
    assert (ids_last > ids0.max()).any() and len(ids_last) >= opts.redetect_fraction * 300 * 0.8


def test_anchoring_stops_drift_under_noise():
    """A texture moving 1 px per frame under strong independent noise (sigma 16 grey levels):
    frame-to-frame KLT passes every step's forward-backward check yet its errors add up over 39
    steps; anchored to the first frame, the surviving tracks stay where the texture is."""
    big = _texture(7, (240, 440))
    rng = np.random.default_rng(8)
    frames = [np.clip(big[:, 40 - k: 440 - k] + rng.normal(0, 16, (240, 400)), 0, 255)
              .astype(np.uint8) for k in range(40)]
    mask = np.zeros((240, 400), np.uint8)
    mask[20:220, 60:380] = 255

    def last_frame_errors(anchor: float) -> np.ndarray:
        t = track_corners(frames, mask, CornerTrackOptions(max_corners=300, window_px=7,
                                                          anchor_max_px=anchor))
        ids0, uv0 = t.in_frame(0)
        ids, uv = t.in_frame(39)
        _, a, b = np.intersect1d(ids0, ids, return_indices=True)
        return np.linalg.norm(uv[b] - (uv0[a] + [39.0, 0.0]), axis=1)

    free = last_frame_errors(np.inf)
    assert len(free) >= 100 and np.median(free) > 0.5 and free.max() > 2.0
    anchored = last_frame_errors(0.5)
    assert len(anchored) >= 50
    assert np.median(anchored) < 0.4 and anchored.max() < 1.0
