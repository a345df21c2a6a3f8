"""``omni-sfm init --lines --images`` end to end on rendered sequences with exact ground truth.

Sized for CI; the full-size figures (800x600 and 1600x800, 200 frames) are produced by
``scripts/eval/init.py`` and quoted in docs/results.md.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import EQUIRECT_CORRIDOR, assert_one_line_error

from omni_sfm.cli import main
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.lines.tracks import read_tracks
from omni_sfm.lines3d import read_lines3d
from omni_sfm.poses import read_tum
from omni_sfm.synth.render import RenderOptions


def _init(seq: Path, out: Path, *extra: str) -> int:
    return main(["init", "--lines", "--images", str(seq / "images"), "--camera",
                 str(seq / "camera.yaml"), "--output", str(out), "--quiet", *extra])


def test_corridor_hyperboloid_every_frame_within_thresholds(corridor, tmp_path):
    out = tmp_path / "init"
    assert _init(corridor, out) == 0
    est, gt = read_tum(out / "trajectory.tum"), read_tum(corridor / "groundtruth.tum")
    assert len(est) == len(gt)
    err = trajectory_errors(est, gt)
    assert err.rot_max_deg <= 0.5
    assert err.ate_rel <= 0.01
    for name in ("tracks.json", "report.json", "trajectory.png", "camera.yaml", "sparse",
                 "images_colmap", "debug"):
        assert (out / name).exists(), name
    report = json.loads((out / "report.json").read_text())
    assert report["reflection"].startswith("resolved")
    assert report["num_frames_estimated"] == len(gt)
    assert len(list((out / "debug").glob("*.png"))) == len(gt)
    # the estimated 3D segments lie on the scene's true lines (after the trajectory's alignment)
    est_lines, true_lines = read_lines3d(out / "lines3d.json"), read_lines3d(corridor /
                                                                             "lines3d.json")
    assert len(est_lines) >= 15 and (est_lines.groups == 0).sum() >= 3
    mids = err.alignment.apply_points((est_lines.starts + est_lines.ends) / 2)
    dirs = est_lines.directions @ err.alignment.rotation.T
    dist = []
    for m, d in zip(mids, dirs, strict=True):
        v = m - true_lines.starts
        perp = v - np.sum(v * true_lines.directions, axis=1)[:, None] * true_lines.directions
        similar = np.abs(true_lines.directions @ d) > np.cos(np.radians(3.0))
        dist.append(np.linalg.norm(perp, axis=1)[similar].min() if similar.any() else np.inf)
    assert np.median(dist) < 0.03  # metres; the path is 1.5 m
    # the tracks artifact re-runs the estimator alone, to the same poses to the bit (the
    # estimator took the tracks as the file holds them)
    assert main(["init", "--tracks", str(out / "tracks.json"), "-o", str(tmp_path / "again")]) \
        == 0
    assert (tmp_path / "again" / "trajectory.tum").read_bytes() == \
        (out / "trajectory.tum").read_bytes()


@pytest.mark.parametrize("opts", [
    # the 360 camera
    EQUIRECT_CORRIDOR,
    # surface texture beside every edge: the paper's strict corner test would leave about 14
    # lines per frame; the default front end keeps about 26 and the weighted adjustment uses
    # them (full size, 100 frames: docs/results.md); measured 24/24, max 0.08 deg, ATE 0.04 %;
    # its render and init take 14 s (slow: its file starts first)
    pytest.param(RenderOptions(scene="room", textured=True, frames=24, seed=0),
                 marks=pytest.mark.slow(seconds=14)),
], ids=["equirectangular-corridor", "textured-room"])
def test_every_frame_within_thresholds(opts, rendered, tmp_path):
    seq = rendered(opts).output
    out = tmp_path / "init"
    assert _init(seq, out, "--no-colmap", "--debug-view", "none") == 0
    err = trajectory_errors(read_tum(out / "trajectory.tum"), read_tum(seq / "groundtruth.tum"))
    assert err.num_common == opts.frames
    assert err.rot_max_deg <= 0.5
    assert err.ate_rel <= 0.01


def test_video_gives_the_same_result_as_its_image_folder(corridor, tmp_path):
    frames = sorted((corridor / "images").glob("*.png"))[:12]
    folder = tmp_path / "frames"
    folder.mkdir()
    video = tmp_path / "seq.avi"
    first = cv2.imread(str(frames[0]))
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"FFV1"), 10.0,
                             (first.shape[1], first.shape[0]))
    assert writer.isOpened()
    for f in frames:
        img = cv2.imread(str(f))
        writer.write(img)
        cv2.imwrite(str(folder / f.name), img)
    writer.release()
    common = ["--camera", str(corridor / "camera.yaml"), "--no-colmap", "--debug-view", "none",
              "--quiet"]
    assert main(["init", "--images", str(folder), "-o", str(tmp_path / "a"), *common]) == 0
    assert main(["init", "--images", str(video), "-o", str(tmp_path / "b"), *common]) == 0
    a, b = read_tum(tmp_path / "a" / "trajectory.tum"), read_tum(tmp_path / "b" / "trajectory.tum")
    np.testing.assert_allclose(b.timestamps, a.timestamps / 10.0)  # video: seconds
    np.testing.assert_allclose(b.positions, a.positions, atol=1e-12)
    np.testing.assert_allclose(b.rotations, a.rotations, atol=1e-12)
    ta, tb = read_tracks(tmp_path / "a" / "tracks.json"), read_tracks(tmp_path / "b" /
                                                                       "tracks.json")
    np.testing.assert_array_equal(ta.obs_frame, tb.obs_frame)


def _one_line_error(capsys, argv: list[str], *needles: str) -> None:
    assert main(argv) == 2
    assert_one_line_error(capsys, *needles)


def test_bad_image_input(corridor, tmp_path, capsys):
    cam = str(corridor / "camera.yaml")
    _one_line_error(capsys, ["init", "--images", str(tmp_path / "missing"), "--camera", cam,
                             "-o", str(tmp_path / "o1")], "missing")
    small = tmp_path / "small"
    small.mkdir()
    for k in range(4):
        cv2.imwrite(str(small / f"{k:03d}.png"), np.zeros((100, 120), np.uint8))
    _one_line_error(capsys, ["init", "--images", str(small), "--camera", cam,
                             "-o", str(tmp_path / "o2")], "120x100")
    blank = tmp_path / "blank"
    blank.mkdir()
    for k in range(5):
        cv2.imwrite(str(blank / f"{k:03d}.png"), np.full((600, 800), 128, np.uint8))
    _one_line_error(capsys, ["init", "--images", str(blank), "--camera", cam, "--quiet",
                             "-o", str(tmp_path / "o3")])
    bad_cam = tmp_path / "cam.yaml"
    bad_cam.write_text("model: hyperboloid\nwidth: 800\n")
    _one_line_error(capsys, ["init", "--images", str(corridor / "images"), "--camera",
                             str(bad_cam), "-o", str(tmp_path / "o4")], str(bad_cam))
    _one_line_error(capsys, ["init", "--images", str(corridor / "images"),
                             "-o", str(tmp_path / "o5")], "--camera")
    for k in range(1, 6):
        assert not (tmp_path / f"o{k}").exists()
