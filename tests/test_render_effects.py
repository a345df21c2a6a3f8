"""The renderer's real-footage effects each change the image the way they model, and only
when asked for.

- Off by default: a render with every effect explicitly off is the clean render, bit for bit.
- Motion blur: none for a still camera; a yaw during the exposure of an equirectangular
  camera (a uniform horizontal flow) gives the sharp image box-filtered along ``u``.
- Drift and flicker scale the linear radiance by the frame's gain; vignetting darkens the rim;
  shot noise grows with the signal.
- JPEG frames and H.264 video are written and read back (OpenCV) close to the renders.
- The body occupies a fixed image region, the same in every frame, or, with a wobble, a region
  turned by a few pixels from frame to frame (seeded, smooth); the seam shifts the content
  along the seam meridian by the set angle; the occluder is composited by depth.
- Bad values: one-line errors, exit code 2.
"""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest
from helpers import assert_one_line_error

from omni_sfm.cli import main as cli_main
from omni_sfm.errors import OmniSfmError
from omni_sfm.frames import FrameStore
from omni_sfm.geometry import rotation_about_axis
from omni_sfm.lines3d import read_lines3d
from omni_sfm.poses import read_tum
from omni_sfm.synth.effects import (
    Body,
    Effects,
    Shutter,
    VideoCodec,
    frame_gain,
    occluder_shapes,
    pose_at,
    shutter_poses,
)
from omni_sfm.synth.render import Preset, RenderOptions, footage_options, prepare, render_frames

HYP = dict(camera="hyperboloid", preset=Preset.SMALL, width=200, height=150)
EQ = dict(camera="equirectangular", preset=Preset.SMALL, width=320, height=160)


def _lin(img: np.ndarray) -> np.ndarray:
    """8-bit gamma-encoded values back to linear radiance."""
    return (img.astype(np.float64) / 255.0) ** 2.2


def test_defaults_are_the_clean_render():
    assert RenderOptions().effects == Effects() and Effects().is_off()
    opts = RenderOptions(**HYP, frames=2, seed=3)
    off = Effects(motion_blur=0.0, exposure_drift=0.0, flicker=0.0, shot_noise=0.0,
                  jpeg_quality=None, vignetting=0.0, body=Body.NONE, body_wobble_deg=0.0,
                  seam_deg=0.0, occluder=False)
    setup, a = render_frames(opts)
    _, b = render_frames(replace(opts, effects=off))
    assert np.array_equal(a, b)
    # the renderer's plain call (no shutter, no occluder) is the sequence's frame
    gt = setup.groundtruth
    assert np.array_equal(a[1], setup.renderer.render(gt.rotations[1], gt.positions[1], 1))
    # a still shutter blurs nothing
    still = Shutter(gt.rotations[1], gt.positions[1], gt.rotations[1], gt.positions[1])
    blur = prepare(replace(opts, effects=Effects(motion_blur=1.0)))
    assert np.array_equal(a[1], blur.renderer.render(gt.rotations[1], gt.positions[1], 1,
                                                     shutter=still))


def test_shutter_poses_bracket_the_frame_pose():
    setup = prepare(RenderOptions(**HYP, frames=5, seed=1))
    gt = setup.groundtruth
    R, c = pose_at(gt, 2.0)
    np.testing.assert_allclose(R, gt.rotations[2], atol=1e-12)
    np.testing.assert_allclose(c, gt.positions[2], atol=1e-12)
    sh = shutter_poses(gt, 2, 0.5)
    np.testing.assert_allclose(sh.open_position, (3 * gt.positions[2] + gt.positions[1]) / 4,
                               atol=1e-12)
    np.testing.assert_allclose(sh.close_position, (3 * gt.positions[2] + gt.positions[3]) / 4,
                               atol=1e-12)
    # extrapolated from the first interval before the first frame
    sh0 = shutter_poses(gt, 0, 1.0)
    np.testing.assert_allclose(sh0.open_position - gt.positions[0],
                               -(gt.positions[1] - gt.positions[0]) / 2, atol=1e-12)


def test_yaw_within_the_exposure_blurs_along_u():
    """An equirectangular camera turning about its vertical axis (-Y up) during the exposure
    sees every point move by the same number of pixels along u: the blurred frame is the sharp
    frame box-filtered along u (in linear radiance)."""
    setup = prepare(RenderOptions(**EQ, scene="room", frames=1, textured=True,
                                  noise_sigma=0.0, effects=Effects(motion_blur=1.0)))
    r = setup.renderer
    R, c = setup.groundtruth.rotations[0], setup.groundtruth.positions[0]
    sharp = r.render(R, c)
    angle = np.radians(4.0)
    y = np.array([0.0, 1.0, 0.0])
    shutter = Shutter(R @ rotation_about_axis(y, -angle / 2), c,
                      R @ rotation_about_axis(y, angle / 2), c)
    blurred = r.render(R, c, shutter=shutter)
    W = blurred.shape[1]
    shift = angle * W / (2 * np.pi)  # px
    lin = _lin(sharp)
    u = np.arange(W, dtype=np.float64)
    expect = np.zeros_like(lin)
    taps = np.linspace(-0.5, 0.5, 41)
    for s in taps:
        x = (u + s * shift) % W
        i0 = np.floor(x).astype(int)
        f = (x - i0)[None, :, None]
        expect += (1 - f) * lin[:, i0] + f * lin[:, (i0 + 1) % W]
    expect = 255.0 * (expect / len(taps)) ** (1 / 2.2)
    err = np.abs(blurred.astype(float) - expect)
    change = np.abs(blurred.astype(float) - sharp.astype(float))
    assert change.mean() > 3.0  # the blur is substantial
    assert err.mean() < 0.25 * change.mean() and err.mean() < 1.5
    # edges across the motion spread, edges along it stay
    g = cv2.cvtColor(blurred, cv2.COLOR_RGB2GRAY).astype(float)
    g0 = cv2.cvtColor(sharp, cv2.COLOR_RGB2GRAY).astype(float)
    assert np.abs(np.diff(g, axis=1)).mean() < 0.7 * np.abs(np.diff(g0, axis=1)).mean()
    assert np.abs(np.diff(g, axis=0)).mean() > 0.8 * np.abs(np.diff(g0, axis=0)).mean()


def test_motion_blur_in_a_sequence_softens_moving_frames():
    opts = RenderOptions(**EQ, frames=3, noise_sigma=0.0, seed=2)
    _, sharp = render_frames(opts)
    _, blurred = render_frames(replace(opts, effects=Effects(motion_blur=1.0)))
    for k in range(3):
        g = cv2.cvtColor(blurred[k], cv2.COLOR_RGB2GRAY).astype(float)
        g0 = cv2.cvtColor(sharp[k], cv2.COLOR_RGB2GRAY).astype(float)
        grad = np.hypot(*np.gradient(g)).mean()
        grad0 = np.hypot(*np.gradient(g0)).mean()
        assert grad < 0.95 * grad0


def test_drift_and_flicker_scale_the_radiance_by_the_frame_gain():
    eff = Effects(exposure_drift=1.0, flicker=0.05)
    gains = np.array([frame_gain(eff, 4, k) for k in range(200)])
    stops = np.log2(gains)
    assert np.ptp(stops) > 0.8 and np.abs(stops).max() < 1.0 + np.log2(1.05) + 1e-9
    assert frame_gain(Effects(), 4, 7) == 1.0
    flick = np.array([frame_gain(Effects(flicker=0.05), 4, k) for k in range(50)])
    assert np.abs(flick - 1).max() <= 0.05 and np.std(np.diff(flick)) > 0.01
    opts = RenderOptions(**HYP, frames=4, noise_sigma=0.0, seed=4)
    setup, clean = render_frames(opts)
    _, drift = render_frames(replace(opts, effects=eff))
    mask = setup.camera.valid_mask()
    ratios = []
    for k in range(4):
        a, b = clean[k][mask].astype(float), drift[k][mask].astype(float)
        ok = (a > 20) & (a < 180) & (b > 20) & (b < 250)
        ratio = np.median(_lin(b[ok]) / _lin(a[ok]))
        assert ratio == pytest.approx(gains[k], rel=0.03)
        ratios.append(ratio)
    assert np.ptp(ratios) > 0.01  # the brightness varies across frames


def test_vignetting_darkens_the_rim():
    opts = RenderOptions(**HYP, frames=1, noise_sigma=0.0, seed=1)
    setup, clean = render_frames(opts)
    _, vig = render_frames(replace(opts, effects=Effects(vignetting=0.5)))
    cam = setup.camera
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    rho = np.hypot(u - cam.cx, v - cam.cy) / cam.outer_radius
    a, b = clean[0].astype(float), vig[0].astype(float)
    ok = cam.valid_mask()[..., None] & (a > 15) & (a < 250)
    ratio = np.where(ok, _lin(b) / np.maximum(_lin(a), 1e-9), np.nan)
    rim = np.nanmedian(ratio[rho > 0.9])
    inner = np.nanmedian(ratio[rho < 0.3])
    assert rim == pytest.approx(1 - 0.5 * 0.95**2, abs=0.06)
    assert inner > 0.95
    # equirectangular: darkest at the sides, 90 deg from both lenses (the seams)
    eq = RenderOptions(**EQ, frames=1, noise_sigma=0.0)
    _, c2 = render_frames(eq)
    _, v2 = render_frames(replace(eq, effects=Effects(vignetting=0.5)))
    H, W = c2.shape[1:3]
    band = slice(H // 2 - 10, H // 2 + 10)  # near the equator
    r2 = _lin(v2[0][band]).sum(axis=(0, 2)) / _lin(c2[0][band]).sum(axis=(0, 2))
    assert r2[W // 2] > 0.95 and r2[0] > 0.95 and r2[W // 4] < 0.6 and r2[3 * W // 4] < 0.6


def test_shot_noise_grows_with_the_signal():
    opts = RenderOptions(**EQ, frames=1, noise_sigma=0.0)
    _, clean = render_frames(opts)
    _, noisy = render_frames(replace(opts, effects=Effects(shot_noise=6.0)))
    a, d = clean[0].astype(float), noisy[0].astype(float) - clean[0].astype(float)
    bright, dark = (a > 200) & (a < 230), (a > 30) & (a < 60)
    assert bright.sum() > 500 and dark.sum() > 500
    # expected std-dev: 6 sqrt(linear signal), plus the two roundings to 8 bits (var ~1/6)
    z = d / np.sqrt(36.0 * _lin(a) + 1 / 6)
    assert z[bright].std() == pytest.approx(1.0, rel=0.1)
    assert z[dark].std() == pytest.approx(1.0, rel=0.15)
    assert d[bright].std() > 2.5 * d[dark].std()


def test_jpeg_frames_are_written_and_close_to_the_render(rendered):
    opts = RenderOptions(**HYP, frames=3, seed=2, effects=Effects(jpeg_quality=85))
    res = rendered(opts)
    files = sorted((res.output / "images").iterdir())
    assert [p.name for p in files] == ["000000.jpg", "000001.jpg", "000002.jpg"]
    _, imgs = render_frames(opts)
    for k, p in enumerate(files):
        img = cv2.imread(str(p))[:, :, ::-1]
        assert img.shape == imgs[k].shape
        mse = np.mean((img.astype(float) - imgs[k].astype(float)) ** 2)
        assert mse > 0 and 10 * np.log10(255**2 / mse) > 30  # lossy but close: PSNR > 30 dB
    meta = json.loads((res.output / "render.json").read_text())
    assert meta["effects"]["jpeg_quality"] == 85 and "seconds_per_frame" in meta


def test_h264_video_reads_back_with_opencv(rendered):
    opts = RenderOptions(**EQ, frames=5, seed=1, video=True, video_codec=VideoCodec.H264,
                         effects=Effects(exposure_drift=0.5, vignetting=0.2))
    res = rendered(opts)
    path = res.output / "video.mp4"
    cap = cv2.VideoCapture(str(path))
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(15.0)
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f[:, :, ::-1])
    cap.release()
    assert len(frames) == 5 and frames[0].shape == (160, 320, 3)
    with open(path, "rb") as fh:
        assert b"avc1" in fh.read(4096)  # H.264, not mp4v
    _, imgs = render_frames(opts)
    for k in range(5):
        assert np.abs(frames[k].astype(float) - imgs[k].astype(float)).mean() < 3.0
    # stamped index / fps, as omni-sfm reads the video
    gt = read_tum(res.output / "groundtruth.tum")
    np.testing.assert_allclose(gt.timestamps, np.arange(5) / 15.0)
    np.testing.assert_allclose(FrameStore(path).timestamps, gt.timestamps)
    meta = json.loads((res.output / "render.json").read_text())
    assert meta["video_codec"] == "h264" and meta["effects"]["vignetting"] == 0.2


def test_video_codec_defaults_mp4v_and_h264_with_footage(tmp_path):
    out = tmp_path / "v"
    assert cli_main(["render", "-o", str(out), "--camera", "equirectangular", "--width", "160",
                     "--preset", "small", "--frames", "2", "--video"]) == 0
    cap = cv2.VideoCapture(str(out / "video.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 2
    assert json.loads((out / "render.json").read_text())["video_codec"] == VideoCodec.MP4V
    out = tmp_path / "f"
    assert cli_main(["render", "-o", str(out), "--camera", "equirectangular", "--width", "160",
                     "--preset", "small", "--frames", "2", "--video", "--footage"]) == 0
    assert json.loads((out / "render.json").read_text())["video_codec"] == VideoCodec.H264


@pytest.mark.parametrize(("base", "body"), [(HYP, "robot"), (EQ, "operator"), (EQ, "tripod")])
def test_body_is_a_fixed_region_the_same_in_every_frame(base, body):
    opts = RenderOptions(**base, frames=3, noise_sigma=0.0, seed=5,
                         effects=Effects(body=Body(body)))
    setup, imgs = render_frames(opts)
    _, clean = render_frames(replace(opts, effects=Effects()))
    region = setup.renderer.body_mask()
    valid = setup.camera.valid_mask()
    assert 0.003 * valid.sum() < region.sum() < 0.3 * valid.sum()
    assert not (region & ~valid).any()
    inner = cv2.erode(region.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    # the floor may hide a tripod's feet: compare where the body is nearer in every frame
    steady = inner & (imgs[0] == imgs[1]).all(axis=2) & (imgs[1] == imgs[2]).all(axis=2)
    assert steady.sum() > 0.9 * inner.sum()
    assert (imgs[0][steady] != clean[0][steady]).any(axis=1).mean() > 0.9
    # outside the body the moving camera changes the image
    out = valid & ~cv2.dilate(region.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert (imgs[0][out] != imgs[2][out]).any(axis=1).mean() > 0.3


def test_wobbling_body_turns_a_few_pixels_from_frame_to_frame():
    from omni_sfm.synth.effects import body_wobble

    opts = RenderOptions(**EQ, frames=4, noise_sigma=0.0, seed=5,
                         effects=Effects(body=Body.OPERATOR, body_wobble_deg=2.0))
    setup, imgs = render_frames(opts)
    r = setup.renderer
    masks = [r.body_mask(k) for k in range(4)]
    rigid = prepare(replace(opts, effects=Effects(body=Body.OPERATOR))).renderer
    # frame by frame the region the rotation gives: the rigid body's rays turned back
    turn = [body_wobble(opts.effects, opts.seed, k) for k in range(4)]
    angles = [np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) for R in turn]
    assert all(0.05 < a <= 2.0 * np.sqrt(3) for a in angles)
    assert np.array_equal(turn[1], body_wobble(opts.effects, opts.seed, 1))  # seeded
    assert np.array_equal(body_wobble(Effects(body=Body.OPERATOR), 5, 1), np.eye(3))
    for m in masks:
        # the same size as the rigid body's region, moved: at most 2 deg * sqrt(3) = 6.2 px
        assert abs(int(m.sum()) - int(rigid.body_mask().sum())) < 0.1 * rigid.body_mask().sum()
        grown = cv2.dilate(rigid.body_mask().astype(np.uint8), np.ones((15, 15), np.uint8))
        assert not (m & ~grown.astype(bool)).any()
    assert not np.array_equal(masks[0], masks[1])
    # the image shows the body where the mask of its frame says
    for k in (0, 3):
        inner = cv2.erode(masks[k].astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        again = r.render(setup.groundtruth.rotations[k], setup.groundtruth.positions[k], k)
        assert np.array_equal(again, imgs[k])
        _, clean = render_frames(replace(opts, frames=k + 1, effects=Effects()))
        assert (imgs[k][inner] != clean[k][inner]).any(axis=1).mean() > 0.9


def test_body_wobble_flag_is_in_render_json(tmp_path):
    out = tmp_path / "w"
    assert cli_main(["render", "-o", str(out), "--camera", "equirectangular", "--width", "160",
                     "--preset", "small", "--frames", "2", "--footage", "--body-wobble",
                     "1.5"]) == 0
    effects = json.loads((out / "render.json").read_text())["effects"]
    assert effects["body_wobble_deg"] == 1.5 and effects["body"] == "operator"


def test_body_is_not_in_the_true_lines(rendered):
    res = rendered(RenderOptions(**HYP, frames=2, effects=Effects(body=Body.ROBOT)))
    clean = prepare(RenderOptions(**HYP, frames=2))
    lines = read_lines3d(res.output / "lines3d.json")
    assert lines.kinds == clean.scene.lines.kinds
    assert json.loads((res.output / "render.json").read_text())["effects"]["body"] == "robot"


def _best_shift(col: np.ndarray, ref: np.ndarray) -> float:
    """Vertical shift (px) that best maps ``ref`` onto ``col`` (both 1D, grey levels)."""
    rows = np.arange(len(col), dtype=float)
    inner = slice(20, len(col) - 20)
    shifts = np.arange(-6.0, 6.0001, 0.125)
    sse = [np.sum((col[inner] - np.interp(rows - s, rows, ref)[inner]) ** 2) for s in shifts]
    return float(shifts[int(np.argmin(sse))])


def test_seam_shifts_the_back_lens_along_the_seam_meridians():
    opts = RenderOptions(**EQ, scene="room", frames=1, textured=True, noise_sigma=0.0, seed=3)
    _, clean = render_frames(opts)
    seam = 3.0
    _, bad = render_frames(replace(opts, effects=Effects(seam_deg=seam)))
    g0 = cv2.cvtColor(clean[0], cv2.COLOR_RGB2GRAY).astype(float)
    g1 = cv2.cvtColor(bad[0], cv2.COLOR_RGB2GRAY).astype(float)
    H, W = g0.shape
    px = seam * H / 180.0
    # the seam meridians at u = W/4 and 3W/4 (longitude -90 and +90 deg); outside them: back
    # (content from latitude lat -/+ seam: lower at W/4, higher at 3W/4)
    for front, back, sign in ((W // 4 + 2, W // 4 - 3, 1), (3 * W // 4 - 3, 3 * W // 4 + 2, -1)):
        assert abs(_best_shift(g1[:, front], g0[:, front])) < 0.2
        assert abs(_best_shift(g1[:, back], g0[:, back]) - sign * px) < 0.6
        # across the seam, neighbouring columns disagree more than in the clean image
        assert (np.abs(g1[:, back] - g1[:, front]).mean()
                > np.abs(g0[:, back] - g0[:, front]).mean())
    assert np.array_equal(g0[:, W // 4 + 2:3 * W // 4 - 2], g1[:, W // 4 + 2:3 * W // 4 - 2])


def test_occluder_is_composited_by_depth():
    opts = RenderOptions(**EQ, frames=3, noise_sigma=0.0, seed=1)
    setup = prepare(replace(opts, effects=Effects(occluder=True)))
    clean = prepare(opts)
    r, gt = setup.renderer, setup.groundtruth
    R, c = gt.rotations[1], gt.positions[1]
    base = clean.renderer.render(R, c)
    a, b = setup.scene.walkway[0, :2], setup.scene.walkway[1, :2]
    along = (b - a) / np.linalg.norm(b - a)
    side = np.array([-along[1], along[0]])
    # a person 3 m to the side stands behind the corridor's wall: nothing changes
    behind = np.array([*(c[:2] + 3.0 * side), 0.0])
    to_it = np.array([*(3.0 * side), 1.0 - c[2]])
    wall = clean.renderer.depth_along_rays(np.eye(3), c, to_it[None])[0]
    assert wall < np.linalg.norm(to_it) - 0.5
    assert np.array_equal(r.render(R, c, occluder=behind), base)
    # 1.5 m along the corridor (towards its farther end): the pixels that change are those
    # where it is nearer
    room = clean.renderer.depth_along_rays(np.eye(3), c, np.array([[*along, 0.0],
                                                                   [*-along, 0.0]]))
    ahead = np.array([*(c[:2] + 1.5 * (along if room[0] > room[1] else -along)), 0.0])
    img = r.render(R, c, occluder=ahead)
    changed = (img != base).any(axis=2).ravel()
    assert changed.sum() > 200
    rays = setup.camera.rays_from_pixels(np.stack(np.meshgrid(
        np.arange(320.0), np.arange(160.0)), axis=-1).reshape(-1, 2))
    person = occluder_shapes().hit(c, rays @ R.T, ahead).t
    scene_t = clean.renderer.depth_along_rays(R, c, rays)
    in_front = person < scene_t
    # anti-aliased outline pixels may change without their centre hitting it
    outline = cv2.dilate(in_front.reshape(160, 320).astype(np.uint8),
                         np.ones((3, 3), np.uint8)).ravel() > 0
    assert not (changed & ~outline).any()
    assert changed[in_front].mean() > 0.95
    # the sequence's walk passes the camera: every frame changes
    _, frames = render_frames(replace(opts, effects=Effects(occluder=True)))
    _, plain = render_frames(opts)
    for k in range(3):
        assert (frames[k] != plain[k]).any(axis=2).sum() > 100
    path = setup.occluder_path
    assert path is not None and path.shape == (3, 3) and np.allclose(path[:, 2], 0)


def test_footage_flag_sets_the_documented_defaults(tmp_path):
    out = tmp_path / "f"
    assert cli_main(["render", "-o", str(out), "--preset", "small", "--width", "160",
                     "--frames", "2", "--footage", "--vignetting", "0.1"]) == 0
    meta = json.loads((out / "render.json").read_text())
    assert meta["effects"] == {
        "motion_blur": 0.5, "exposure_drift": 0.3, "flicker": 0.02, "shot_noise": 2.0,
        "jpeg_quality": 85, "vignetting": 0.1, "body": "robot", "body_wobble_deg": 0.0,
        "seam_deg": 0.0, "occluder": False}
    assert meta["route"] == "lane" and meta["path_length"] is None
    assert sorted(p.name for p in (out / "images").iterdir()) == ["000000.jpg", "000001.jpg"]
    eq = footage_options(RenderOptions(camera="equirectangular", video=True))
    assert eq.effects.body == Body.OPERATOR and eq.effects.jpeg_quality is None
    assert eq.video_crf == 23


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--motion-blur", "-0.5"], "motion blur must be in [0, 1]"),
        (["--motion-blur", "1.5"], "motion blur must be in [0, 1]"),
        (["--seam", "0.5"], "a stitching seam needs an equirectangular camera"),
        (["--jpeg", "0"], "JPEG quality must be an integer 1..100"),
        (["--jpeg", "101"], "JPEG quality must be an integer 1..100"),
        (["--vignetting", "2"], "vignetting must be in [0, 1]"),
        (["--exposure-drift", "-1"], "exposure drift must be in [0, 4]"),
        (["--video", "--jpeg", "80"], "JPEG quality applies to image frames"),
        (["--video", "--video-crf", "60"], "H.264 CRF must be an integer 0..51"),
        (["--video", "--video-codec", "h264", "--width", "201", "--height", "151"],
         "needs an even image size"),
        (["--fps", "0"], "frame rate must be > 0"),
        (["--body", "operator", "--body-wobble", "12"], "body wobble must be in [0, 10] deg"),
    ],
)
def test_bad_effect_values_are_one_line_and_exit_2(tmp_path, capsys, args, message):
    out = tmp_path / "o"
    rc = cli_main(["render", "--output", str(out), "--preset", "small", "--frames", "1", *args])
    assert rc == 2
    assert_one_line_error(capsys, message)
    assert not out.exists()


def test_bad_effect_values_in_the_library():
    with pytest.raises(OmniSfmError, match="unknown body 'tank'"):
        prepare(RenderOptions(**HYP, frames=1,
                              effects=Effects(body="tank")))  # type: ignore[arg-type]
    with pytest.raises(OmniSfmError, match="flicker must be in"):
        prepare(RenderOptions(**HYP, frames=1, effects=Effects(flicker=float("nan"))))
    with pytest.raises(OmniSfmError, match="unknown video codec"):
        prepare(RenderOptions(**HYP, frames=1, video_codec="h265"))  # type: ignore[arg-type]
    with pytest.raises(OmniSfmError, match="unknown route"):
        prepare(RenderOptions(**HYP, frames=1, route="fly"))  # type: ignore[arg-type]
    assert hash(RenderOptions(effects=Effects(body=Body.TRIPOD)))  # session-cache key
