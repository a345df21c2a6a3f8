"""Line tracking over short synthetic sequences with known motion and true line identities."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from linetest_utils import (
    EQUIRECT_WORLD_FROM_CAM,
    Room,
    equirect_camera,
    hyperboloid_camera,
    label_lines,
    render,
)

from omni_sfm.geometry import rotation_about_axis
from omni_sfm.lines.extract import ExtractionOptions, LineExtractor
from omni_sfm.lines.track import LineTracker, TrackingOptions


def _poses(n, base=None):
    """A smooth path: 3 cm per frame forward, some sideways and up, 1.5 deg/frame turning."""
    base = np.eye(3) if base is None else base
    out = []
    for k in range(n):
        pos = np.array([0.3 + 0.03 * k, 0.2 - 0.01 * k, 0.1 + 0.005 * k])
        R = rotation_about_axis([0.1, 0.2, 1.0], np.radians(1.5 * k)) @ base
        out.append((R, pos))
    return out


def _run(cam, poses, room=None, ext=None, trk=None, paint=None):
    room = room or Room()
    extractor = LineExtractor(cam, ext)
    tracker = LineTracker(trk)
    labels = []
    for k, (R, pos) in enumerate(poses):
        img = render(cam, room, R, pos)
        if paint is not None:
            img = paint(k, img)
        lines = extractor.extract(img)
        tracker.add_frame(img, lines)
        labels.append(label_lines(lines, room.segments(), room.line_ids(), R, pos)[0])
    obs = tracker.finish()
    truth = np.array([labels[f][i] for f, i in zip(obs.frame, obs.line_index, strict=True)])
    return obs, truth


def _purity(obs, truth):
    """Share of observations that carry their track's majority true line."""
    agree = 0
    for m in range(obs.num_tracks):
        lab = truth[obs.track == m]
        agree += np.unique(lab, return_counts=True)[1].max()
    return agree / len(truth)


@pytest.fixture(scope="module")
def hyper_run(built_once):
    """The hyperboloid's 8 frames tracked, once per test run (``built_once``)."""
    return built_once("lines-track-hyperboloid", lambda _: _run(hyperboloid_camera(),
                                                                  _poses(8)))[1]


def test_tracks_keep_identity_hyperboloid(hyper_run):
    obs, truth = hyper_run
    # measured: purity 1.0, 30+ tracks over all 8 frames
    assert _purity(obs, truth) > 0.95
    lengths = np.bincount(obs.track)
    assert (lengths == 8).sum() >= 25
    # one observation per (track, frame), sorted
    key = obs.track * 100 + obs.frame
    assert np.all(np.diff(key) > 0)
    assert obs.matched[1:].min() >= 25


def test_tracks_keep_identity_equirectangular():
    obs, truth = _run(equirect_camera(), _poses(4, EQUIRECT_WORLD_FROM_CAM))
    assert _purity(obs, truth) > 0.95
    assert (np.bincount(obs.track) == 4).sum() >= 25


def _blank_frame_2(k, img):
    return np.full_like(img, 128) if k == 2 else img


def test_lines_that_vanish_end_and_new_lines_start():
    """A blank frame in the middle, revival off: every track ends there, new ones start."""
    obs, _ = _run(hyperboloid_camera(), _poses(5), paint=_blank_frame_2,
                  trk=TrackingOptions(min_track_frames=1, max_gap_frames=0))
    assert obs.started[2] == 0 and obs.started[3] >= 25 and obs.matched[3] == 0
    for m in range(obs.num_tracks):
        fr = obs.frame[obs.track == m]
        assert not (fr.min() < 2 < fr.max()), fr


def test_lost_tracks_are_revived_after_a_gap():
    """The same blank frame with revival on: the tracks of frame 1 go on in frame 3."""
    obs, truth = _run(hyperboloid_camera(), _poses(5), paint=_blank_frame_2)
    assert obs.revived[3] >= 25 and obs.started[3] <= 3
    assert _purity(obs, truth) > 0.95
    spans = [np.unique(obs.frame[obs.track == m]).tolist() for m in range(obs.num_tracks)]
    assert sum(s == [0, 1, 3, 4] for s in spans) >= 25


def test_occlusion_split_stays_one_track():
    """Frames 2-4 hide the middle of the longest line (its pieces are not merged in the frame):
    the tracker keeps the pieces and the whole line in one track."""
    cam = hyperboloid_camera()
    poses = _poses(7)
    room = Room()
    first = LineExtractor(cam).extract(render(cam, room, *poses[0]))
    k = int(np.argmax(first.num_support))
    true_id = label_lines(first, room.segments(), room.line_ids(), *poses[0])[0][k]
    target = room.segments()[room.line_ids() == true_id][0]

    def paint(f, img):
        if 2 <= f <= 4:
            R, pos = poses[f]
            mid = cam.pixels_from_rays([(target.mean(axis=0) - pos) @ R])[0]
            cv2.circle(img, (int(mid[0]), int(mid[1])), 10, 128, -1, cv2.LINE_AA)
        return img

    obs, truth = _run(cam, poses, room, ext=ExtractionOptions(merge_angle_deg=0.0), paint=paint)
    tracks_of_line = np.unique(obs.track[truth == true_id])
    assert len(tracks_of_line) == 1
    assert len(np.unique(obs.frame[obs.track == tracks_of_line[0]])) == 7


def test_tracker_keeps_no_edge_points_of_past_frames():
    # a long video's memory must not grow by each frame's edge points (0.65 MB a 1920x960
    # frame): once a frame is older than the revival's history, only its lines' per-line
    # arrays (what the tracks keep) may stay referenced
    import weakref

    cam = hyperboloid_camera()
    extractor = LineExtractor(cam)
    opts = TrackingOptions()
    tracker = LineTracker(opts)
    refs = []
    poses = _poses(opts.max_gap_frames + 4)
    for R, pos in poses:
        img = render(cam, Room(), R, pos)
        lines = extractor.extract(img)
        assert lines.num_lines > 0
        refs.append((weakref.ref(lines.points_uv), weakref.ref(lines.point_rays)))
        tracker.add_frame(img, lines)
        del lines
    old = refs[: len(poses) - opts.max_gap_frames - 1]
    assert old and all(a() is None and b() is None for a, b in old)
    assert len(tracker.finish().track) > 0
