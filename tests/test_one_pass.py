"""One pass over the frames: worker processes, the frames taken from the front end's pass
(COLMAP images, debug view), the evenly spread sample, and what a dead worker gives."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_one_line_error

from omni_sfm.cameras import load_camera
from omni_sfm.cli import main
from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.pipeline import estimate_poses
from omni_sfm.frames import FrameSource, read_frames
from omni_sfm.lines.extract import LineExtractor
from omni_sfm.lines.frontend import FrontEndOptions, track_lines, worker_count
from omni_sfm.lines.workers import ExtractionWorkers
from omni_sfm.pipelines.init import DEBUG_FRAMES, SAMPLE_FRAMES, _debug_numbers
from omni_sfm.synth.render import RenderOptions, VideoCodec


@pytest.fixture(scope="module")
def video(rendered) -> Path:
    """The same kind of corridor as an H.264 video, 20 frames (read-only)."""
    return rendered(RenderOptions(camera="hyperboloid", frames=20, seed=2, video=True,
                                  video_codec=VideoCodec.H264)).output


def _front_end(seq: Path, workers: int):
    cam = load_camera(seq / "camera.yaml")
    src = read_frames(seq / "images", size=(cam.width, cam.height))
    return track_lines(src, cam, FrontEndOptions(progress=False, workers=workers))


def test_same_tracks_and_poses_with_one_and_two_workers(corridor):
    one, two = _front_end(corridor, 1), _front_end(corridor, 2)
    a, b = one.tracks, two.tracks
    np.testing.assert_array_equal(a.obs_track, b.obs_track)
    np.testing.assert_array_equal(a.obs_frame, b.obs_frame)
    # OpenCV single-threaded in the workers: the same numbers to round-off
    np.testing.assert_allclose(a.obs_normal, b.obs_normal, atol=1e-9)
    ra, rb = estimate_poses(one.estimator_tracks()), estimate_poses(two.estimator_tracks())
    np.testing.assert_array_equal(ra.estimated, rb.estimated)
    np.testing.assert_allclose(ra.trajectory.rotations, rb.trajectory.rotations, atol=1e-6)
    np.testing.assert_allclose(ra.trajectory.positions, rb.trajectory.positions, atol=1e-6)


def test_worker_count_defaults():
    assert worker_count(FrontEndOptions(workers=3), 10) == 3
    assert worker_count(FrontEndOptions(), 5) == 1  # too few frames to pay for processes
    assert worker_count(FrontEndOptions(), None) >= 1
    with pytest.raises(OmniSfmError, match="workers must be at least 1"):
        worker_count(FrontEndOptions(workers=0), 10)


def test_a_worker_that_dies_is_a_one_line_error(corridor):
    cam = load_camera(corridor / "camera.yaml")
    frame = np.zeros((cam.height, cam.width), np.uint8)
    with ExtractionWorkers(LineExtractor(cam), 1) as pool:
        pool.submit(frame)
        pool.result()
        pool._procs[0].kill()
        with pytest.raises(OmniSfmError, match="a line extraction worker stopped"):
            pool.submit(frame)
            pool.result()


def test_workers_holding_unread_results_end_on_close(corridor):
    # after an error the caller stops reading: closing must end the workers, not kill them
    # after a timeout (each result is larger than a pipe's buffer)
    cam = load_camera(corridor / "camera.yaml")
    frames = [f.image for f in read_frames(corridor / "images")][:2]
    pool = ExtractionWorkers(LineExtractor(cam), 2)
    procs = list(pool._procs)
    for frame in frames:
        pool.submit(frame)
    procs[0].stdout.peek(1)  # a result is on its way
    pool.close()
    assert [p.returncode for p in procs] == [0, 0]


def test_sample_reads_the_frames_it_names(corridor, video):
    for path in (corridor / "images", video / "video.mp4"):
        src = read_frames(path, size=(800, 600))
        every = {f.number: f.image for f in src}
        picks = sorted({int(k) for k in np.linspace(0, len(every) - 1, 7).round()})
        got = src.sample(7)
        assert len(got) == 7
        for k, img in zip(picks, got, strict=True):
            np.testing.assert_array_equal(img, every[k])


def test_debug_frames_of_a_long_run_are_a_spread_sample():
    short = FrameSource(path=Path("."), files=[Path(f"{k}.png") for k in range(50)], step=2)
    assert _debug_numbers(short, "auto") == list(range(0, 50, 2))
    long = FrameSource(path=Path("."), is_video=True, frame_count=10 * DEBUG_FRAMES, start=5)
    nums = _debug_numbers(long, "auto")
    assert len(nums) == DEBUG_FRAMES and nums[0] == 5 and nums[-1] == 10 * DEBUG_FRAMES - 1
    assert _debug_numbers(long, "png") == []  # every frame: read again after the estimate


def test_init_writes_colmap_images_and_debug_view_from_one_pass(video, tmp_path, monkeypatch):
    # count the frames decoded: one pass, plus the sample of the checks
    import omni_sfm.frames as frames_mod

    decoded = []
    real = frames_mod.open_video

    class Counting:
        def __init__(self, cap):
            self.cap = cap

        def grab(self):
            decoded.append(1)
            return self.cap.grab()

        def read(self):
            decoded.append(1)
            return self.cap.read()

        def __getattr__(self, name):
            return getattr(self.cap, name)

    monkeypatch.setattr(frames_mod, "open_video", lambda path: Counting(real(path)))
    out = tmp_path / "init"
    assert main(["init", "--lines", "--images", str(video / "video.mp4"), "--camera",
                 str(video / "camera.yaml"), "--output", str(out), "--quiet"]) == 0
    # every frame once (the debug view and images_colmap/ included), and the checks' sample
    assert len(decoded) <= 20 + SAMPLE_FRAMES, len(decoded)
    report = json.loads((out / "report.json").read_text())
    names = json.loads((out / "colmap.json").read_text())["image_names"]
    assert sorted(p.name for p in (out / "images_colmap").iterdir()) == sorted(names)
    assert len(names) == report["num_frames_estimated"]
    assert len(list((out / "debug").glob("*.png"))) == 20


def test_no_colmap_images_and_no_debug_view_when_asked(corridor, tmp_path):
    out = tmp_path / "init"
    assert main(["init", "--lines", "--images", str(corridor / "images"), "--camera",
                 str(corridor / "camera.yaml"), "--output", str(out), "--quiet",
                 "--no-colmap-images", "--debug-view", "none", "--workers", "1"]) == 0
    assert (out / "sparse").is_dir() and not (out / "images_colmap").exists()
    assert not (out / "debug").exists()


def test_bad_worker_count_is_a_one_line_error(corridor, tmp_path, capsys):
    code = main(["init", "--lines", "--images", str(corridor / "images"), "--camera",
                 str(corridor / "camera.yaml"), "--output", str(tmp_path / "o"), "--quiet",
                 "--workers", "0"])
    assert code == 2
    assert_one_line_error(capsys, "--workers must be at least 1")
    assert not (tmp_path / "o").exists()
