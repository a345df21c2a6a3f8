"""Rig cameras from files: a Kalibr camchain of several cameras (chained by ``T_cn_cnm1``) read
as one rig, its round trip through omni-sfm's YAML, its errors, one camera of it by ``--lens``,
and the frame-size message of a rig."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from helpers import assert_one_line_error

from omni_sfm.cameras import EUCMCamera, RigCamera, load_camera, write_camera_yaml
from omni_sfm.cli import main
from omni_sfm.errors import OmniSfmError
from omni_sfm.frames import read_frames

# cam1 turned 180 deg about y, its centre 4 cm behind cam0's (along cam0's -z): the transform
# that takes cam0's points into cam1's frame
T_C1_C0 = [[-1.0, 0.0, 0.0, 0.0],
           [0.0, 1.0, 0.0, 0.0],
           [0.0, 0.0, -1.0, -0.04],
           [0.0, 0.0, 0.0, 1.0]]


def _camchain() -> dict[str, Any]:
    cam = {"camera_model": "eucm", "distortion_model": "none", "distortion_coeffs": [],
           "resolution": [640, 480], "rostopic": "/cam0/image_raw"}
    return {
        "cam0": {**cam, "intrinsics": [0.62, 1.05, 190.0, 189.5, 319.5, 239.5]},
        "cam1": {**cam, "intrinsics": [0.60, 1.10, 185.0, 185.5, 321.0, 238.0],
                 "T_cn_cnm1": T_C1_C0, "cam_overlaps": [0], "rostopic": "/cam1/image_raw"},
    }


def _write(tmp_path: Path, data: dict[str, Any], name: str = "camchain.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_two_eucm_back_to_back_are_one_rig(tmp_path: Path) -> None:
    rig = load_camera(_write(tmp_path, _camchain()))
    assert isinstance(rig, RigCamera)
    assert (rig.width, rig.height, rig.layout) == (1280, 480, "side_by_side")
    assert rig.lenses == (
        EUCMCamera(width=640, height=480, alpha=0.62, beta=1.05, fx=190.0, fy=189.5, cx=319.5,
                   cy=239.5),
        EUCMCamera(width=640, height=480, alpha=0.60, beta=1.10, fx=185.0, fy=185.5, cx=321.0,
                   cy=238.0))
    # rig frame = cam0's; cam1 at rig_from_lens[0] @ inv(T_cn_cnm1)
    want1 = np.diag([-1.0, 1.0, -1.0, 1.0])
    want1[2, 3] = -0.04
    assert np.allclose(rig.rig_from_lens[0], np.eye(4), atol=1e-12)
    assert np.allclose(rig.rig_from_lens[1], want1, atol=1e-12)
    assert np.allclose(rig.centres, [[0, 0, 0], [0, 0, -0.04]])
    # straight ahead: cam0's principal point; straight behind: cam1's, right of cam0's image
    uv = rig.pixels_from_rays(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
    assert np.allclose(uv, [[319.5, 239.5], [640 + 321.0, 238.0]])
    assert rig.lens_of_rays(np.array([[0.1, 0.0, -1.0]])).tolist() == [1]
    assert rig.camchain and rig.file.endswith("camchain.yaml")


def test_three_cameras_chain_their_transforms(tmp_path: Path) -> None:
    data = _camchain()
    # cam2 turned 90 deg about cam1's y axis, 3 cm along cam1's x axis
    c, s = 0.0, 1.0
    cam2_from_cam1 = np.linalg.inv(np.array([[c, 0, s, 0.03], [0, 1, 0, 0], [-s, 0, c, 0],
                                             [0, 0, 0, 1.0]]))
    data["cam2"] = {**data["cam1"], "resolution": [320, 400],
                    "intrinsics": [0.6, 1.1, 95.0, 95.0, 159.5, 199.5],
                    "T_cn_cnm1": cam2_from_cam1.tolist()}
    rig = load_camera(_write(tmp_path, data))
    assert isinstance(rig, RigCamera) and rig.num_lenses == 3
    assert (rig.width, rig.height) == (640 + 640 + 320, 480)
    assert np.allclose(rig.rig_from_lens[2],
                       rig.rig_from_lens[1] @ np.linalg.inv(cam2_from_cam1), atol=1e-12)
    assert rig.corners.tolist() == [[0, 0], [640, 0], [1280, 0]]


def test_rig_round_trip_through_camera_yaml(tmp_path: Path) -> None:
    rig = load_camera(_write(tmp_path, _camchain()))
    out = tmp_path / "rig.yaml"
    write_camera_yaml(out, rig)
    back = load_camera(out)
    assert isinstance(back, RigCamera)
    assert back == rig and back.params() == rig.params()
    assert not back.camchain  # an omni-sfm rig file now: its messages call them lenses


@pytest.mark.parametrize(("change", "needle"), [
    (lambda d: d["cam1"].pop("T_cn_cnm1"), r"missing key 'cam1\.T_cn_cnm1'"),
    (lambda d: d["cam1"]["T_cn_cnm1"][0].__setitem__(0, -1.1),
     r"key 'cam1\.T_cn_cnm1' must be a rigid transform"),
    (lambda d: d["cam1"].__setitem__("T_cn_cnm1", [[1, 0, 0], [0, 1, 0]]),
     r"key 'cam1\.T_cn_cnm1' must be a finite 4x4 matrix"),
    (lambda d: d["cam1"].__setitem__("T_cn_cnm1", "identity"),
     r"key 'cam1\.T_cn_cnm1' must be a"),
    (lambda d: d["cam1"]["T_cn_cnm1"][0].__setitem__(0, 1.0),  # a mirror, det -1
     r"key 'cam1\.T_cn_cnm1' must be a rigid transform"),
])
def test_bad_transform_is_a_one_line_error(tmp_path: Path, change: Any, needle: str) -> None:
    data = copy.deepcopy(_camchain())
    change(data)
    with pytest.raises(OmniSfmError, match=needle) as info:
        load_camera(_write(tmp_path, data))
    assert "\n" not in str(info.value) and "camchain.yaml" in str(info.value)


def test_cameras_looking_the_same_way_point_to_lens(tmp_path: Path) -> None:
    data = _camchain()
    data["cam1"]["T_cn_cnm1"] = [[1, 0, 0, -0.11], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    path = _write(tmp_path, data)
    with pytest.raises(OmniSfmError, match="cam0 and cam1 look the same way"):
        load_camera(path)
    assert load_camera(path, lens=1).model == "eucm"


def test_convert_lens_1_writes_that_camera_alone(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    src = _write(tmp_path, _camchain())
    dst = tmp_path / "cam1.yaml"
    assert main(["camera", "convert", str(src), "--lens", "1", "-o", str(dst)]) == 0
    assert "model eucm, 640 x 480 px" in capsys.readouterr().out
    assert load_camera(dst) == EUCMCamera(width=640, height=480, alpha=0.60, beta=1.10,
                                          fx=185.0, fy=185.5, cx=321.0, cy=238.0)
    assert "T_cn_cnm1" not in dst.read_text() and "rig_from_lens" not in dst.read_text()
    # the whole chain converts to a rig camera file, whose lens 1 is the same camera again
    rig_file = tmp_path / "rig.yaml"
    assert main(["camera", "convert", str(src), "-o", str(rig_file)]) == 0
    assert load_camera(rig_file, lens=1) == load_camera(dst)
    # no camera 2
    assert main(["camera", "convert", str(src), "--lens", "2", "-o",
                 str(tmp_path / "x.yaml")]) == 2
    assert_one_line_error(capsys, "no camera 2", "holds 2 (cam0, cam1)")
    assert main(["camera", "show", "equirectangular", "--lens", "0"]) == 2
    assert_one_line_error(capsys, "--lens selects one camera of a camera file")


def test_show_rig_prints_its_lenses(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["camera", "show", str(_write(tmp_path, _camchain()))]) == 0
    out = capsys.readouterr().out
    assert "model: rig of 2 lenses, side_by_side" in out and "size: 1280 x 480 px" in out
    assert "lens 0: eucm 640 x 480 px at pixel (0, 0), centre (0.0000, 0.0000, 0.0000) m" in out
    assert "lens 1: eucm 640 x 480 px at pixel (640, 0), centre (0.0000, 0.0000, -0.0400) m, " \
           "axis 180.0 deg from lens 0's" in out


def test_frames_of_one_camera_for_a_camchain_rig_say_what_to_do(tmp_path: Path) -> None:
    src = _write(tmp_path, _camchain())
    rig = load_camera(src)
    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(1)
    for k in range(2):
        cv2.imwrite(str(folder / f"{k:06d}.png"), rng.integers(0, 255, (480, 640), np.uint8))
    frames = read_frames(folder, size=(rig.width, rig.height),
                         size_error=rig.frame_size_mismatch)
    with pytest.raises(OmniSfmError) as info:
        list(frames)
    msg = str(info.value)
    assert msg == (f"{folder / '000000.png'}: frames are 640 x 480 but the camchain's 2 cameras "
                   "side by side are 1280 x 480: put the cameras' images side by side, or "
                   f"convert one camera with 'omni-sfm camera convert {src} --lens 0'")
    # a rig camera file's message calls them lenses; stacked lenses are one above the other
    stacked = RigCamera(width=640, height=960, lenses=rig.lenses,
                        rig_from_lens=rig.rig_from_lens, layout="stacked")
    assert stacked.frame_size_mismatch(640, 480) == (
        "frames are 640 x 480 but the rig's 2 lenses one above the other are 640 x 960: put "
        "the lenses' images one above the other, or convert one lens with 'omni-sfm camera "
        "convert CAMERA_FILE --lens 0'")
