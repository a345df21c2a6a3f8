"""``omni-sfm init`` on what real footage brings: a camera that only turns, a camera-fixed body
in the image (automatic mask), a camera file that does not fit the frames (camera check)."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import assert_one_line_error

from omni_sfm.cli import main
from omni_sfm.evaluate import relative_rotation_errors_deg
from omni_sfm.folders import InitFolder
from omni_sfm.frames import read_mask
from omni_sfm.poses import read_tum
from omni_sfm.synth.effects import Body, Effects
from omni_sfm.synth.paths import Route
from omni_sfm.synth.render import RenderOptions, prepare
from omni_sfm.transforms import associate

FAST = ["--no-colmap", "--debug-view", "none", "--quiet"]
TURN = RenderOptions(scene="office", route=Route.TURN, camera="equirectangular", width=480,
                     height=240, frames=24)
BODY = RenderOptions(camera="hyperboloid", width=400, height=300, frames=12,
                     effects=Effects(body=Body.OPERATOR))
SMALL = RenderOptions(camera="hyperboloid", width=400, height=300, frames=12)


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no numpy warning reaches the user
def test_turning_in_place_gives_every_rotation(rendered, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    seq = rendered(TURN).output
    out = tmp_path / "init"
    assert main(["init", "--images", str(seq / "images"), "--camera",
                 str(seq / "camera.yaml"), "--output", str(out), *FAST]) == 0
    said = capsys.readouterr().out
    assert "24 of 24 frames estimated" in said
    assert "rotation only: the camera turned without moving" in said
    report = InitFolder(out).read_report()
    assert report.rotation_only and report.motion is not None
    assert report.motion.kind == "rotation only"
    est = read_tum(out / "trajectory.tum")
    assert np.all(est.positions == 0)
    e, g = associate(est, read_tum(seq / "groundtruth.tum"))
    assert len(e) == 24
    assert relative_rotation_errors_deg(e, g).max() < 0.3


def test_camera_fixed_body_is_masked_and_written(rendered, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    seq = rendered(BODY).output
    out = tmp_path / "init"
    assert main(["init", "--images", str(seq / "images"), "--camera",
                 str(seq / "camera.yaml"), "--output", str(out), *FAST]) == 0
    assert "automatic mask: masked" in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert report["auto_mask"]["applied"]
    mask = read_mask(out / "mask.png", (400, 300))
    body = prepare(BODY).renderer.body_mask()
    assert (~mask & body).sum() > 0.65 * body.sum()
    # switched off: no mask written, nothing said
    out2 = tmp_path / "init2"
    assert main(["init", "--images", str(seq / "images"), "--camera",
                 str(seq / "camera.yaml"), "--output", str(out2), "--no-auto-mask",
                 *FAST]) == 0
    assert "automatic mask" not in capsys.readouterr().out
    assert not (out2 / "mask.png").exists()


def test_user_mask_and_automatic_mask_are_combined(rendered, tmp_path: Path) -> None:
    seq = rendered(BODY).output
    user = np.full((300, 400), 255, np.uint8)
    user[:40, :40] = 0
    cv2.imwrite(str(tmp_path / "user.png"), user)
    out = tmp_path / "init"
    assert main(["init", "--images", str(seq / "images"), "--camera",
                 str(seq / "camera.yaml"), "--mask", str(tmp_path / "user.png"),
                 "--output", str(out), *FAST]) == 0
    mask = read_mask(out / "mask.png", (400, 300))
    assert not mask[:40, :40].any()
    assert (~mask).sum() > (user == 0).sum()


def _pinhole(path: Path) -> Path:
    path.write_text("# COLMAP cameras.txt\n1 PINHOLE 400 300 150 150 200 150\n")
    return path


def test_wrong_camera_file_warns_and_strict_refuses(rendered, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    seq = rendered(SMALL).output
    cam = _pinhole(tmp_path / "cameras.txt")
    main(["init", "--images", str(seq / "images"), "--camera", str(cam), "--output",
          str(tmp_path / "init"), *FAST])
    err = capsys.readouterr().err
    warning = [line for line in err.splitlines() if line.startswith("omni-sfm: warning: ")]
    assert len(warning) == 1 and "camera model does not fit the images" in warning[0]
    assert "%" in warning[0]  # with the figure
    assert main(["init", "--images", str(seq / "images"), "--camera", str(cam), "--output",
                 str(tmp_path / "strict"), "--strict", *FAST]) == 2
    assert_one_line_error(capsys, "camera model does not fit the images", "--strict")
    assert not (tmp_path / "strict").exists()


def test_right_camera_does_not_warn(rendered, tmp_path: Path,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    seq = rendered(SMALL).output
    assert main(["init", "--images", str(seq / "images"), "--camera",
                 str(seq / "camera.yaml"), "--output", str(tmp_path / "init"), "--strict",
                 *FAST]) == 0
    assert "warning" not in capsys.readouterr().err
    report = json.loads((tmp_path / "init" / "report.json").read_text())
    assert report["camera_check"]["ok"] and report["warnings"] == []


def _with_fixed_track(tracks, frames: range):
    """``tracks`` plus one track whose NV stays put in the camera frame over ``frames``."""
    from dataclasses import replace as dc_replace

    n = np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93])
    k = len(frames)
    side = np.cross(n, [1.0, 0.0, 0.0])  # a ray in its plane
    return dc_replace(
        tracks, track_ids=np.append(tracks.track_ids, 999),
        obs_track=np.append(tracks.obs_track, np.full(k, tracks.num_tracks)),
        obs_frame=np.append(tracks.obs_frame, np.asarray(frames)),
        obs_normal=np.vstack([tracks.obs_normal, np.tile(n, (k, 1))]),
        obs_ray=None if tracks.obs_ray is None else
        np.vstack([tracks.obs_ray, np.tile(side / np.linalg.norm(side), (k, 1))]),
        obs_sigma=None if tracks.obs_sigma is None else
        np.vstack([tracks.obs_sigma, np.tile(tracks.obs_sigma[0], (k, 1))]))


def test_camera_fixed_tracks_are_found_only_when_the_camera_moves() -> None:
    from omni_sfm.lines.frontend import camera_fixed_tracks
    from omni_sfm.synth.simulate import SimulationOptions, simulate

    moving = simulate(SimulationOptions(num_views=30, noise_deg=0.05, seed=1)).tracks
    assert not camera_fixed_tracks(moving).any()
    flagged = camera_fixed_tracks(_with_fixed_track(moving, range(5, 20)))
    assert flagged[-1] and flagged.sum() == 1
    # a camera standing still: every line stays put, none is taken for the camera's own
    from dataclasses import replace as dc_replace

    rng = np.random.default_rng(2)
    first = moving.obs_normal[np.searchsorted(moving.obs_track, moving.obs_track)]
    noisy = first + np.radians(0.02) * rng.normal(size=first.shape)
    still = dc_replace(moving, obs_normal=noisy / np.linalg.norm(noisy, axis=1, keepdims=True))
    assert not camera_fixed_tracks(_with_fixed_track(still, range(5, 20))).any()
