"""Camera files: our YAML, files written by cv2.omnidir.calibrate, hand-written Kalibr, OCamCalib
and COLMAP files, bad input, and the ``omni-sfm camera`` command."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import assert_one_line_error

from omni_sfm.cameras import (
    DoubleSphereCamera,
    EUCMCamera,
    OCamCamera,
    OpenCVFisheyeCamera,
    UnifiedCamera,
    load_camera,
    write_camera_yaml,
)
from omni_sfm.cli import main
from omni_sfm.errors import OmniSfmError

DATA = Path(__file__).resolve().parent / "data" / "cameras"
EXAMPLES = Path(__file__).resolve().parents[1] / "docs" / "examples" / "cameras"


@pytest.mark.parametrize("example", sorted(EXAMPLES.glob("*.yaml")), ids=lambda p: p.stem)
def test_yaml_write_read_round_trip(example: Path, tmp_path: Path) -> None:
    cam = load_camera(example)
    out = tmp_path / "camera.yaml"
    write_camera_yaml(out, cam)
    again = load_camera(out)
    assert again == cam
    assert again.params() == cam.params()


# ---------------------------------------------------------------- cv2.omnidir.calibrate


def synthetic_omnidir_calibration() -> tuple[dict, tuple]:
    """Run cv2.omnidir.calibrate on a checkerboard projected with known K, D, xi."""
    k = np.array([[560.0, 0.3, 322.0], [0.0, 556.0, 241.5], [0.0, 0.0, 1.0]])
    d = np.array([[-0.12, 0.03, 0.0008, -0.0005]])
    xi = 1.15
    w, h = 640, 480
    gx, gy = np.meshgrid(np.arange(9), np.arange(6))
    board = np.column_stack([gx.ravel() * 0.04, gy.ravel() * 0.04, np.zeros(gx.size)])
    rng = np.random.default_rng(0)
    objs, imgs = [], []
    while len(objs) < 10:
        rvec = rng.normal(scale=0.35, size=3)
        tvec = np.array([rng.uniform(-0.25, 0.05), rng.uniform(-0.2, 0.05),
                         rng.uniform(0.25, 0.5)])
        ip, _ = cv2.omnidir.projectPoints(board.reshape(-1, 1, 3), rvec, tvec, k, xi, d)
        ip = ip.reshape(-1, 2)
        pc = board @ cv2.Rodrigues(rvec)[0].T + tvec
        if (pc[:, 2] < 0.05).any() or (ip < 5).any() or (ip > [w - 5, h - 5]).any():
            continue
        objs.append(board.reshape(-1, 1, 3).copy())
        imgs.append(ip.reshape(-1, 1, 2))
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 300, 1e-12)
    rms, k2, xi2, d2, _, _, _ = cv2.omnidir.calibrate(objs, imgs, (w, h), None, None, None, 0,
                                                       crit)
    assert rms < 0.05
    return {"K": k2, "D": d2, "xi": xi2, "width": w, "height": h}, (k, d, xi, objs, imgs)


@pytest.fixture(scope="module")
def omnidir_calibration() -> tuple[dict, tuple]:
    return synthetic_omnidir_calibration()


@pytest.mark.parametrize("suffix", [".yaml", ".xml"])
def test_loads_cv2_omnidir_calibrate_results(
    omnidir_calibration: tuple[dict, tuple], tmp_path: Path, suffix: str
) -> None:
    res, (k_true, d_true, xi_true, _, _) = omnidir_calibration
    path = tmp_path / f"omnidir{suffix}"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", res["width"])
    fs.write("image_height", res["height"])
    fs.write("K", res["K"])
    fs.write("D", res["D"])
    fs.write("xi", res["xi"])
    fs.release()
    cam = load_camera(path)
    assert isinstance(cam, UnifiedCamera)
    k, d = res["K"], res["D"].ravel()
    assert (cam.width, cam.height) == (640, 480)
    np.testing.assert_allclose([cam.fx, cam.skew, cam.cx, cam.fy, cam.cy],
                               [k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2]], rtol=1e-14)
    np.testing.assert_allclose([cam.k1, cam.k2, cam.p1, cam.p2], d, rtol=1e-14)
    assert cam.xi == pytest.approx(float(res["xi"].ravel()[0]), rel=1e-14)
    # the loaded camera reproduces cv2's projection with the calibrated values exactly, and the
    # ground-truth camera where the board was seen (calibration leaves xi / f / k1 ambiguous)
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-0.4, 0.4, 500), rng.uniform(-0.3, 0.3, 500),
                           np.full(500, 0.5)])
    ref, _ = cv2.omnidir.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                       res["K"], float(res["xi"].ravel()[0]), res["D"])
    ours = cam.pixels_from_rays(pts)
    assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-6
    true, _ = cv2.omnidir.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                        k_true, xi_true, d_true)
    assert np.abs(ours - true.reshape(-1, 2)).max() < 0.1


def test_opencv_storage_without_xi_or_size_names_the_key(tmp_path: Path) -> None:
    path = tmp_path / "calib.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("K", np.eye(3))
    fs.write("D", np.zeros((1, 4)))
    fs.release()
    with pytest.raises(OmniSfmError, match=r"calib\.yaml: missing key 'xi'"):
        load_camera(path)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("K", np.eye(3))
    fs.write("xi", 1.0)
    fs.release()
    with pytest.raises(OmniSfmError, match="missing key 'width'"):
        load_camera(path)


# ---------------------------------------------------------------- Kalibr, OCamCalib, COLMAP


def test_kalibr_stereo_camchain_reads_one_camera_by_lens() -> None:
    # two cameras looking the same way are no rig: the error says how to read one of them
    with pytest.raises(OmniSfmError, match=r"cam0 and cam1 look the same way .*--lens 0'$"):
        load_camera(DATA / "kalibr_camchain_omni.yaml")
    cam = load_camera(DATA / "kalibr_camchain_omni.yaml", lens=0)
    assert cam == UnifiedCamera(width=1280, height=1024, xi=1.0385, fx=742.31, fy=741.86,
                                cx=639.42, cy=511.07, k1=-0.0412, k2=0.0071, p1=0.00042,
                                p2=-0.00031)


def test_kalibr_eucm_ds_and_pinhole_equidistant() -> None:
    assert load_camera(DATA / "kalibr_eucm.yaml") == EUCMCamera(
        width=1024, height=768, alpha=0.6152, beta=1.0871, fx=381.27, fy=380.94, cx=511.63,
        cy=383.08)
    assert load_camera(DATA / "kalibr_ds.yaml") == DoubleSphereCamera(
        width=1024, height=768, xi=-0.1823, alpha=0.5917, fx=261.84, fy=261.63, cx=511.92,
        cy=384.41)
    assert load_camera(DATA / "kalibr_pinhole_equi.yaml") == OpenCVFisheyeCamera(
        width=1280, height=960, fx=402.61, fy=402.19, cx=639.37, cy=480.83, k1=0.0214,
        k2=-0.0079, k3=0.0012, k4=-0.00021)


def test_ocamcalib_calib_results_conventions() -> None:
    cam = load_camera(DATA / "ocam_calib_results.txt")
    assert isinstance(cam, OCamCamera)
    assert (cam.width, cam.height) == (1024, 768)  # the file lists "height width"
    assert (cam.cx, cam.cy) == (509.35, 384.14)  # the file lists "row column"
    assert (cam.c, cam.d, cam.e) == (0.999822, 0.000294, -0.000286)
    assert cam.pol == (-210.4, 0.0, 1.96e-3, -2.4e-6, 9.1e-9)
    assert len(cam.invpol) == 12
    # the file's own world2cam polynomial agrees with our exact inverse of pol to its fit
    # accuracy (about 0.03 px), which checks the row/column order of centre and affine terms
    uv = np.array([[100.0, 700.0], [900.5, 120.25], [512.0, 300.0], [300.0, 384.0]])
    rays = cam.rays_from_pixels(uv)
    oc = np.column_stack([rays[:, 1], rays[:, 0], -rays[:, 2]])  # OCamCalib's frame
    n = np.hypot(oc[:, 0], oc[:, 1])
    rho = np.polynomial.polynomial.polyval(np.arctan(oc[:, 2] / n), cam.invpol)
    x, y = oc[:, 0] / n * rho, oc[:, 1] / n * rho
    row, col = x * cam.c + y * cam.d + 384.14, x * cam.e + y + 509.35
    assert np.abs(np.column_stack([col, row]) - uv).max() < 0.05


def test_colmap_cameras_txt_shifts_half_a_pixel() -> None:
    cam = load_camera(DATA / "colmap_cameras.txt")
    assert cam == EUCMCamera(width=1024, height=768, fx=381.27, fy=380.94, cx=511.63,
                             cy=383.08, alpha=0.6152, beta=1.0871)
    assert cam.to_pycolmap().params.tolist() == pytest.approx(
        [381.27, 380.94, 512.13, 383.58, 0.6152, 1.0871])
    fish = load_camera(DATA / "colmap_cameras_fisheye.txt")  # the first camera of two
    assert isinstance(fish, OpenCVFisheyeCamera)
    assert (fish.cx, fish.cy, fish.k4) == (pytest.approx(639.37), pytest.approx(480.83), -0.00021)


def test_colmap_pinhole_family_becomes_unified_with_xi_zero(tmp_path: Path) -> None:
    path = tmp_path / "cameras.txt"
    path.write_text("1 SIMPLE_RADIAL 640 480 500 320.5 240.5 -0.05\n")
    cam = load_camera(path)
    assert cam == UnifiedCamera(width=640, height=480, fx=500, fy=500, cx=320, cy=240, xi=0.0,
                                k1=-0.05)
    assert cam.to_pycolmap().model_name == "OPENCV"


# ---------------------------------------------------------------- bad input


def write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


BAD_FILES = {
    "unknown_model": ("model: pinhole_magic\nwidth: 10\nheight: 10\n", "unknown camera model"),
    "missing_key": ("model: eucm\nwidth: 10\nheight: 10\nfx: 1\nfy: 1\ncx: 5\ncy: 5\nalpha: 0.5\n",
                    "missing key 'beta'"),
    "non_numeric": ("model: equirectangular\nwidth: ten\nheight: 10\n", "key 'width'"),
    "negative_size": ("model: equirectangular\nwidth: 10\nheight: -4\n", "key 'height'"),
    "nan_param": ("model: unified\nwidth: 10\nheight: 10\nfx: .nan\nfy: 1\ncx: 5\ncy: 5\n"
                  "xi: 1\n", "key 'fx'"),
    "bad_domain": ("model: eucm\nwidth: 10\nheight: 10\nfx: 1\nfy: 1\ncx: 5\ncy: 5\nalpha: 2\n"
                   "beta: 1\n", "key 'alpha'"),
    "typo_key": ("model: equirectangular\nwidth: 10\nheight: 10\nwidht: 3\n", "key 'widht'"),
    "bad_list": ("model: ocam\nwidth: 10\nheight: 10\ncx: 5\ncy: 5\npol: [-3, zero]\n",
                 "key 'pol[1]'"),
    "bad_mask": ("model: hyperboloid\nwidth: 10\nheight: 10\ncx: 5\ncy: 5\npx: 1\npy: 1\n"
                 "f: 1\nalpha: 1\nbeta: 1\nmask: {inner: 3}\n", "key 'mask.inner'"),
    "model_list": ("model: [eucm]\nwidth: 10\nheight: 10\n", "unknown camera model"),
    "not_yaml": ("model: [unclosed\n", "not valid YAML"),
    "unrecognised": ("just some words\n", "unrecognised camera file"),
    "kalibr_fov": ("cam0:\n  camera_model: pinhole\n  distortion_model: fov\n"
                   "  distortion_coeffs: [0.9]\n  intrinsics: [1, 1, 1, 1]\n"
                   "  resolution: [10, 10]\n", "distortion_model 'fov'"),
    "kalibr_short": ("cam0:\n  camera_model: omni\n  distortion_model: none\n"
                     "  intrinsics: [1, 1, 1, 1]\n  resolution: [10, 10]\n",
                     "key 'cam0.intrinsics' must have 5 numbers"),
    "ocam_short": ("#polynomial coefficients for the DIRECT mapping function\n\n3 -1 0 0.1\n"
                   "\n2 1 2\n", "missing 'center'"),
    "ocam_count": ("#polynomial coefficients for the DIRECT mapping function\n\n4 -1 0 0.1\n"
                   "2 1 2\n5 5\n1 0 0\n10 10\n", "key 'pol'"),
    "colmap_model": ("1 FOV 640 480 500 500 320 240 0.9\n", "MODEL 'FOV'"),
    "colmap_params": ("1 EUCM 640 480 500 500 320 240 0.5\n", "needs 6 PARAMS"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_input_is_one_line_naming_file_and_key(case: str, tmp_path: Path) -> None:
    text, expect = BAD_FILES[case]
    path = write(tmp_path, f"{case}.txt", text)
    with pytest.raises(OmniSfmError) as info:
        load_camera(path)
    msg = str(info.value)
    assert "\n" not in msg
    assert str(path) in msg and expect in msg, msg


def test_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(OmniSfmError, match="camera file not found"):
        load_camera(tmp_path / "missing.yaml")
    with pytest.raises(OmniSfmError, match="is a directory"):
        load_camera(tmp_path)
    (tmp_path / "binary.yaml").write_bytes(b"\xff\xfe\x00\x81garbage")
    with pytest.raises(OmniSfmError, match="not UTF-8"):
        load_camera(tmp_path / "binary.yaml")
    (tmp_path / "broken.yaml").write_text("%YAML:1.0\nK: !!opencv-matrix\n  rows: [\n")
    with pytest.raises(OmniSfmError, match="broken.yaml"):
        load_camera(tmp_path / "broken.yaml")


# ---------------------------------------------------------------- the command


def test_cli_show_and_convert(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = DATA / "kalibr_camchain_omni.yaml"
    assert main(["camera", "show", str(src), "--lens", "0"]) == 0
    out = capsys.readouterr().out
    assert "model: unified" in out and "xi: 1.0385" in out and "valid pixels" in out
    dst = tmp_path / "camera.yaml"
    assert main(["camera", "convert", str(src), "--lens", "0", "-o", str(dst)]) == 0
    assert load_camera(dst) == load_camera(src, lens=0)
    # no silent overwrite
    assert main(["camera", "convert", str(src), "--lens", "0", "-o", str(dst)]) == 2
    assert_one_line_error(capsys, "--overwrite")
    assert main(["camera", "convert", str(src), "--lens", "0", "-o", str(dst),
                 "--overwrite"]) == 0


@pytest.mark.parametrize("case", ["unknown_model", "nan_param", "colmap_model"])
def test_cli_bad_input_exits_2_with_one_line(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(tmp_path, "cam.yaml", BAD_FILES[case][0])
    assert main(["camera", "show", str(path)]) == 2
    assert_one_line_error(capsys, str(path))
    assert main(["camera", "convert", str(path), "-o", str(tmp_path / "o.yaml")]) == 2
    assert_one_line_error(capsys, str(path))
    assert not (tmp_path / "o.yaml").exists()
    assert main(["camera", "show", str(tmp_path / "nope.yaml")]) == 2
    assert_one_line_error(capsys, "nope.yaml")


def test_numpy_scalars_write_as_plain_yaml(tmp_path: Path) -> None:
    cam = EUCMCamera(width=64, height=48, fx=np.float64(30.5), fy=np.float32(30.0), cx=32.0,
                     cy=24.0, alpha=np.float64(0.6), beta=1.0)
    write_camera_yaml(tmp_path / "c.yaml", cam)
    assert "numpy" not in (tmp_path / "c.yaml").read_text()
    assert load_camera(tmp_path / "c.yaml").params() == cam.params()


def test_hyperboloid_xi_matches_issue_formula() -> None:
    cam = load_camera(EXAMPLES / "hyperboloid.yaml")
    e = math.sqrt(14.0**2 + 19.4**2) / 19.4
    assert cam.unified_xi == pytest.approx(2 * e / (1 + e * e))  # type: ignore[attr-defined]
