"""The automatic mask of camera-fixed regions and the camera-model check (docs/frontend.md)."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from omni_sfm.cameras import load_camera
from omni_sfm.lines.automask import static_mask
from omni_sfm.lines.camfit import check_camera_fit
from omni_sfm.synth.render import RenderOptions

HYP = RenderOptions(camera="hyperboloid", width=400, height=300, frames=12)
EQUI = RenderOptions(camera="equirectangular", width=400, height=200, frames=12)
TEXTURED = RenderOptions(scene="room", camera="hyperboloid", width=400, height=300, frames=12,
                         textured=True)


def _load(rendered, options):
    res = rendered(options)
    files = sorted((Path(res.output) / "images").glob("*.png"))
    return [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files], res.camera


def _body(shape, equirectangular):
    """A dark torso and two legs fixed to the camera, at the nadir."""
    h, w = shape
    m = np.zeros(shape, np.uint8)
    if equirectangular:
        polys = [np.array([[0.40 * w, h], [0.43 * w, 0.8 * h], [0.57 * w, 0.8 * h],
                           [0.60 * w, h]])]
    else:
        c, s = np.array([w / 2, h / 2]), min(w / 800, h / 600)

        def at(r, a):
            return c + r * s * np.array([np.cos(np.radians(a)), np.sin(np.radians(a))])
        polys = [np.array([at(45, a0), at(r, a0 + d), at(r, a1 - d), at(45, a1)])
                 for a0, a1, r, d in ((60, 120, 150, 10), (200, 215, 200, 5),
                                      (320, 335, 200, 5))]
    for p in polys:
        cv2.fillPoly(m, [np.rint(p).astype(np.int32)], 1)
    return m > 0


def _paint(frames, body):
    rng = np.random.default_rng(0)
    out = []
    for f in frames:
        g = f.astype(np.float64)
        g[body] = 40 + rng.normal(0, 1.0, int(body.sum()))
        out.append(np.clip(np.rint(g), 0, 255).astype(np.uint8))
    return out


@pytest.mark.parametrize("options", [HYP, EQUI, TEXTURED], ids=["hyp", "equi", "textured"])
def test_nothing_masked_on_clean_sequences(rendered, options):
    frames, cam = _load(rendered, options)
    auto = static_mask(frames, cam)
    assert auto.masked_fraction < 0.01, auto.reason
    assert auto.mask.all()


@pytest.mark.parametrize("options", [HYP, EQUI], ids=["hyp", "equi"])
def test_camera_fixed_body_is_masked(rendered, options):
    frames, cam = _load(rendered, options)
    valid = cam.valid_mask()
    body = _body(frames[0].shape, options is EQUI) & valid
    auto = static_mask(_paint(frames, body), cam)
    assert auto.applied, auto.reason
    assert auto.reason.startswith("masked ")
    covered = (~auto.mask & body).sum() / body.sum()
    extra = (~auto.mask & ~body & valid).sum() / valid.sum()
    assert covered > 0.85, (covered, auto.reason)
    assert extra < 0.06, (extra, auto.reason)


def test_user_mask_is_kept_and_still_camera_not_applied(rendered):
    frames, cam = _load(rendered, HYP)
    rng = np.random.default_rng(1)
    still = [np.clip(frames[0] + rng.normal(0, 1.0, frames[0].shape), 0, 255).astype(np.uint8)
             for _ in range(10)]
    user = np.ones(frames[0].shape, bool)
    user[:20] = False
    auto = static_mask(still, cam, user)
    assert not auto.applied
    assert "barely moves" in auto.reason
    assert (auto.mask == user).all()


def test_pinhole_on_mirror_frames_warns(rendered, tmp_path):
    frames, _ = _load(rendered, HYP)
    f = tmp_path / "cameras.txt"
    f.write_text("1 PINHOLE 400 300 150 150 200 150\n")
    fit = check_camera_fit(frames[::3], load_camera(f))
    assert not fit.ok
    assert "\n" not in fit.message
    assert fit.message.startswith("the camera model does not fit the images: ")
    assert "%" in fit.message and "expected <" in fit.message
    assert fit.figures["empty_valid"] > 0.3


@pytest.mark.parametrize("options", [HYP, EQUI, TEXTURED], ids=["hyp", "equi", "textured"])
def test_right_camera_does_not_warn(rendered, options):
    frames, cam = _load(rendered, options)
    rng = np.random.default_rng(2)
    noisy = [np.clip(f + rng.normal(0, 3.0, f.shape), 0, 255).astype(np.uint8)
             for f in frames[::3]]
    for sample in (frames[::3], noisy):
        fit = check_camera_fit(sample, cam)
        assert fit.ok, fit.message


def test_mirror_camera_on_panorama_warns(rendered):
    from omni_sfm.synth.render import hyperboloid_camera

    frames, _ = _load(rendered, EQUI)
    fit = check_camera_fit(frames[::3], hyperboloid_camera(400, 200))
    assert not fit.ok, fit.figures


@pytest.mark.parametrize(("camera", "size", "body"),
                         [("hyperboloid", (400, 300), "operator"),
                          ("equirectangular", (400, 200), "robot")])
def test_rendered_body_is_masked(rendered, camera, size, body):
    from omni_sfm.synth.effects import Effects
    from omni_sfm.synth.render import prepare

    options = RenderOptions(camera=camera, width=size[0], height=size[1], frames=12,
                            effects=Effects(body=body))
    frames, cam = _load(rendered, options)
    valid = cam.valid_mask()
    truth = prepare(options).renderer.body_mask() & valid
    auto = static_mask(frames, cam)
    assert auto.applied, auto.reason
    assert (~auto.mask & truth).sum() / truth.sum() > 0.65
    assert (~auto.mask & ~truth & valid).sum() / valid.sum() < 0.08
