"""Camera models: exact round trips, honest valid regions, the cached pixel grid."""

from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import pytest

from omni_sfm.cameras import (
    MODELS,
    CameraModel,
    DoubleSphereCamera,
    EquirectangularCamera,
    EUCMCamera,
    HyperboloidCamera,
    OCamCamera,
    OpenCVFisheyeCamera,
    UnifiedCamera,
    load_camera,
)

EXAMPLES = Path(__file__).resolve().parents[1] / "docs" / "examples" / "cameras"

# small images keep the grid tests fast; parameters scaled to give wide fields of view
CAMERAS: dict[str, CameraModel] = {
    "hyperboloid": HyperboloidCamera(
        width=320, height=240, cx=160.3, cy=119.6, px=0.025, py=0.025, f=8.0, alpha=14.0,
        beta=19.4,
    ),
    "hyperboloid_mask": HyperboloidCamera(
        width=320, height=240, cx=160.0, cy=120.0, px=0.025, py=0.025, f=8.0, alpha=14.0,
        beta=19.4, inner_radius=20.0, outer_radius=115.0,
    ),
    "unified_radtan_xi_gt_1": UnifiedCamera(
        width=320, height=240, fx=260.0, fy=255.0, cx=161.0, cy=118.0, xi=1.6, skew=0.7,
        k1=-0.21, k2=0.06, p1=0.0012, p2=-0.0007,
    ),
    "unified_xi_lt_1": UnifiedCamera(
        width=320, height=240, fx=150.0, fy=148.0, cx=160.0, cy=121.0, xi=0.8,
    ),
    "pinhole_radtan": UnifiedCamera(
        width=320, height=240, fx=200.0, fy=201.0, cx=159.0, cy=120.5, xi=0.0,
        k1=-0.28, k2=0.09, p1=0.001, p2=0.0005,
    ),
    "eucm_wide": EUCMCamera(
        width=320, height=240, fx=95.0, fy=94.0, cx=160.0, cy=120.0, alpha=0.62, beta=1.15,
    ),
    "eucm_narrow": EUCMCamera(
        width=320, height=240, fx=140.0, fy=140.0, cx=160.0, cy=120.0, alpha=0.4, beta=0.9,
    ),
    "double_sphere": DoubleSphereCamera(
        width=320, height=240, fx=80.0, fy=80.0, cx=160.0, cy=120.0, xi=-0.19, alpha=0.59,
    ),
    "equirectangular": EquirectangularCamera(width=320, height=160),
    "ocam": OCamCamera(
        width=320, height=240, cx=158.7, cy=121.4, c=1.0004, d=0.0003, e=-0.0002,
        pol=(-82.0, 0.0, 4.6e-3, -1.1e-5, 4.0e-8),
    ),
    "opencv_fisheye": OpenCVFisheyeCamera(
        width=320, height=240, fx=80.0, fy=80.5, cx=160.5, cy=119.5,
        k1=0.03, k2=-0.012, k3=0.002, k4=-0.0002, outer_radius=150.0,
    ),
}


def grid_and_random_pixels(cam: CameraModel, n: int = 4000, seed: int = 0) -> np.ndarray:
    v, u = np.mgrid[0 : cam.height : 3, 0 : cam.width : 3]
    rng = np.random.default_rng(seed)
    rnd = rng.uniform([-0.5, -0.5], [cam.width - 0.5, cam.height - 0.5], size=(n, 2))
    return np.concatenate([np.stack([u.ravel(), v.ravel()], 1).astype(float), rnd])


def random_rays(n: int, seed: int = 1) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad) between unit rows, accurate for tiny angles."""
    return 2.0 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=1) / 2.0, 0, 1))


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_pixel_ray_pixel_round_trip(name: str) -> None:
    cam = CAMERAS[name]
    uv = grid_and_random_pixels(cam)
    rays = cam.rays_from_pixels(uv)
    ok = np.isfinite(rays).all(axis=1)
    assert ok.mean() > 0.3, f"{name}: only {ok.mean():.0%} of the image is valid"
    assert np.allclose(np.linalg.norm(rays[ok], axis=1), 1.0, atol=1e-12)
    back = cam.pixels_from_rays(rays[ok])
    assert np.isfinite(back).all(), f"{name}: valid pixels whose ray does not project back"
    err = np.linalg.norm(back - uv[ok], axis=1)
    assert err.max() < 1e-6, f"{name}: pixel -> ray -> pixel error {err.max():.2e} px"


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_ray_pixel_ray_round_trip(name: str) -> None:
    cam = CAMERAS[name]
    rays = random_rays(20000)
    # rays of any length project like their unit vector
    uv = cam.pixels_from_rays(rays * np.random.default_rng(2).uniform(0.1, 50, (len(rays), 1)))
    ok = np.isfinite(uv).all(axis=1)
    assert ok.mean() > 0.15, f"{name}: only {ok.mean():.0%} of all directions are imaged"
    back = cam.rays_from_pixels(uv[ok])
    assert np.isfinite(back).all(), f"{name}: projected rays whose pixel has no ray"
    err = angle(back, rays[ok])
    assert err.max() < 1e-9, f"{name}: ray -> pixel -> ray error {err.max():.2e} rad"


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_grid_rays_cached_and_consistent_with_valid_mask(name: str) -> None:
    cam = CAMERAS[name]
    grid = cam.pixel_grid_rays()
    assert grid.shape == (cam.height, cam.width, 3)
    assert cam.pixel_grid_rays() is grid  # cached: the renderer calls it every frame
    assert not grid.flags.writeable
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(float)
    direct = cam.rays_from_pixels(uv).reshape(grid.shape)
    np.testing.assert_array_equal(np.isnan(direct), np.isnan(grid))
    np.testing.assert_allclose(direct[np.isfinite(direct)], grid[np.isfinite(grid)], atol=1e-15)
    mask = cam.valid_mask()
    assert mask.dtype == bool and mask.shape == (cam.height, cam.width)
    np.testing.assert_array_equal(mask, np.isfinite(grid).all(axis=2))
    mask[:] = False  # a copy: the camera's cache is unaffected
    assert cam.valid_mask().any()


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_nan_and_inf_inputs_give_nan_rows(name: str) -> None:
    cam = CAMERAS[name]
    uv = np.array([[np.nan, 10.0], [10.0, np.inf], [cam.width / 2, cam.height / 2 + 0.3]])
    rays = cam.rays_from_pixels(uv)
    assert np.isnan(rays[:2]).all()
    d = np.array([[np.nan, 0.0, 1.0], [0.0, np.inf, 1.0], [0.0, 0.0, 0.0]])
    assert np.isnan(cam.pixels_from_rays(d)).all()


def test_in_image_frame() -> None:
    cam = CAMERAS["equirectangular"]
    uv = np.array([[-0.5, 0.0], [-0.51, 0.0], [319.49, 159.49], [319.5, 0.0], [np.nan, 0.0]])
    np.testing.assert_array_equal(cam.in_image(uv), [True, False, True, False, False])


def test_pickling_drops_the_caches() -> None:
    cam = CAMERAS["opencv_fisheye"]
    cam.pixel_grid_rays()
    data = pickle.dumps(cam)
    assert len(data) < 2000
    again = pickle.loads(data)
    assert again == cam
    np.testing.assert_array_equal(again.pixel_grid_rays(), cam.pixel_grid_rays())


def test_shapes_are_checked() -> None:
    cam = CAMERAS["eucm_wide"]
    with pytest.raises(ValueError, match="shape"):
        cam.rays_from_pixels(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="shape"):
        cam.pixels_from_rays(np.zeros(3))
    assert cam.rays_from_pixels(np.zeros((0, 2))).shape == (0, 3)
    assert np.isnan(cam.pixels_from_rays(np.zeros((1, 3)))).all()  # a zero ray has no pixel


def test_large_inputs_are_processed_blockwise_identically() -> None:
    cam = CAMERAS["unified_radtan_xi_gt_1"]
    rng = np.random.default_rng(3)
    uv = rng.uniform(-10, 330, size=(150_000, 2))
    whole = cam.rays_from_pixels(uv)
    part = np.concatenate([cam.rays_from_pixels(uv[i : i + 997]) for i in range(0, len(uv), 997)])
    np.testing.assert_array_equal(np.isnan(whole), np.isnan(part))
    np.testing.assert_allclose(whole[np.isfinite(whole)], part[np.isfinite(part)], atol=1e-14)


# ---------------------------------------------------------------- honest valid regions


def test_unified_domain_ends_where_projection_folds() -> None:
    cam = UnifiedCamera(width=400, height=400, fx=100, fy=100, cx=200, cy=200, xi=2.0)
    w = 1 / cam.xi  # rays with z <= -1/xi are not imaged
    z = np.array([-w + 1e-3, -w - 1e-3])
    rays = np.stack([np.sqrt(1 - z**2), np.zeros(2), z], 1)
    uv = cam.pixels_from_rays(rays)
    assert np.isfinite(uv[0]).all() and np.isnan(uv[1]).all()
    # pixels beyond the image of that circle (radius fx / sqrt(xi^2 - 1)) see nothing
    r_lim = 100 / math.sqrt(cam.xi**2 - 1)
    r = cam.rays_from_pixels(np.array([[200 + r_lim - 0.01, 200], [200 + r_lim + 0.01, 200]]))
    assert np.isfinite(r[0]).all() and np.isnan(r[1]).all()


def test_radial_distortion_beyond_its_monotone_part_is_invalid() -> None:
    cam = UnifiedCamera(width=400, height=400, fx=100, fy=100, cx=200, cy=200, xi=0.0, k1=-0.3)
    r_fold = math.sqrt(1 / (3 * 0.3))  # d/dr r (1 + k1 r^2) = 0
    assert cam.r_max == pytest.approx(r_fold, rel=1e-6)
    rays = np.array([[r_fold * 0.99, 0, 1], [r_fold * 1.01, 0, 1]])
    uv = cam.pixels_from_rays(rays)
    assert np.isfinite(uv[0]).all() and np.isnan(uv[1]).all()
    # the distorted image of the fold is the image's edge: pixels beyond it see nothing
    rd = r_fold * (1 - 0.3 * r_fold**2) * 100
    r = cam.rays_from_pixels(np.array([[200 + rd - 0.05, 200], [200 + rd + 0.05, 200]]))
    assert np.isfinite(r[0]).all() and np.isnan(r[1]).all()


def test_fisheye_beyond_max_angle_is_invalid() -> None:
    cam = OpenCVFisheyeCamera(width=400, height=400, fx=60, fy=60, cx=200, cy=200, k1=-0.09)
    t = cam.theta_max
    assert t == pytest.approx(math.sqrt(1 / (3 * 0.09)), rel=1e-6)
    rays = np.array([[math.sin(t - 1e-3), 0, math.cos(t - 1e-3)],
                     [math.sin(t + 1e-3), 0, math.cos(t + 1e-3)]])
    uv = cam.pixels_from_rays(rays)
    assert np.isfinite(uv[0]).all() and np.isnan(uv[1]).all()
    # past 90 deg from the axis (cv2 / COLMAP stop at 90): still exact here
    wide = OpenCVFisheyeCamera(width=400, height=400, fx=60, fy=60, cx=200, cy=200)
    ray = np.array([[math.sin(2.0), 0.0, math.cos(2.0)]])
    assert wide.pixels_from_rays(ray)[0] == pytest.approx([200 + 60 * 2.0, 200.0])


def test_ocam_valid_only_inside_polynomial_validity() -> None:
    cam = CAMERAS["ocam"]
    corners = np.array([[0.0, 0.0], [319.0, 239.0]])
    assert np.isfinite(cam.rays_from_pixels(corners)).all()
    # beyond the image corners the polynomial is extrapolated: not valid
    assert np.isnan(cam.rays_from_pixels(np.array([[-40.0, -40.0]]))).all()
    t = cam.theta_max
    rays = np.array([[math.sin(t - 1e-4), 0, math.cos(t - 1e-4)],
                     [math.sin(t + 1e-3), 0, math.cos(t + 1e-3)]])
    uv = cam.pixels_from_rays(rays)
    assert np.isfinite(uv[0]).all() and np.isnan(uv[1]).all()


def test_hyperboloid_geometry_and_mask() -> None:
    cam = CAMERAS["hyperboloid_mask"]
    centre = cam.rays_from_pixels(np.array([[cam.cx, cam.cy]]))
    assert np.isnan(centre).all()  # inside inner_radius: the camera's own reflection
    plain = CAMERAS["hyperboloid"]
    c = plain.rays_from_pixels(np.array([[plain.cx, plain.cy]]))[0]
    np.testing.assert_allclose(c, [0, 0, -1], atol=1e-12)
    # elevation grows with the radius
    r = plain.rays_from_pixels(np.stack([plain.cx + np.arange(5, 110, 10.0),
                                         np.full(11, plain.cy)], 1))
    assert np.all(np.diff(r[:, 2]) > 0)
    # nothing below the mirror's asymptote is imaged: rho < f alpha / beta
    rho_max = plain.f * plain.alpha / plain.beta / plain.px
    r = plain.rays_from_pixels(np.array([[plain.cx + rho_max * 0.999, plain.cy],
                                         [plain.cx + rho_max * 1.001, plain.cy]]))
    assert np.isfinite(r[0]).all() and np.isnan(r[1]).all()
    # rays above the mirror's asymptotic cone (d_z >= beta / gamma) never hit the mirror
    z = np.array([-1e-3, 1e-3]) + plain.beta / plain.gamma
    uv = plain.pixels_from_rays(np.stack([np.sqrt(1 - z**2), np.zeros(2), z], 1))
    assert np.isfinite(uv[0]).all() and np.isnan(uv[1]).all()


# ---------------------------------------------------------------- parameters and examples


@pytest.mark.parametrize("model", sorted(MODELS))
def test_every_model_has_a_documented_example(model: str) -> None:
    cam = load_camera(EXAMPLES / f"{model}.yaml")
    assert cam.model == model
    assert cam.valid_mask().mean() > 0.3
    text = cam.summary()
    assert f"model: {model}" in text and "valid pixels" in text


@pytest.mark.parametrize(
    ("cls", "kwargs", "key"),
    [
        (EUCMCamera, {"fx": 1, "fy": 1, "cx": 0, "cy": 0, "alpha": 1.5, "beta": 1}, "alpha"),
        (EUCMCamera, {"fx": -1, "fy": 1, "cx": 0, "cy": 0, "alpha": 0.5, "beta": 1}, "fx"),
        (UnifiedCamera, {"fx": 1, "fy": 1, "cx": 0, "cy": 0, "xi": float("nan")}, "xi"),
        (HyperboloidCamera, {"cx": 0, "cy": 0, "px": 0, "py": 1, "f": 1, "alpha": 1,
                             "beta": 1}, "px"),
        (OCamCamera, {"cx": 0, "cy": 0, "pol": (5.0, 0.0, 1e-3)}, "pol"),
        (DoubleSphereCamera, {"fx": 1, "fy": 1, "cx": 0, "cy": 0, "xi": -2, "alpha": 0.5},
         "xi"),
    ],
)
def test_constructor_rejects_bad_parameters(cls: type, kwargs: dict, key: str) -> None:
    with pytest.raises(ValueError, match=f"'{key}'"):
        cls(width=10, height=10, **kwargs)
    with pytest.raises(ValueError, match="'width'"):
        EquirectangularCamera(width=0, height=10)
    with pytest.raises(ValueError, match="'fx' must be a number"):
        EUCMCamera(width=10, height=10, fx=[1.0, 2.0], fy=1, cx=0, cy=0, alpha=0.5, beta=1)


def test_numpy_parameters_become_plain_numbers() -> None:
    cam = OCamCamera(width=np.int64(20), height=10, cx=np.float32(5.5), cy=5.0,
                     pol=np.array([-8.0, 0.0, 0.01]))
    assert type(cam.width) is int and type(cam.cx) is float
    assert cam.pol == (-8.0, 0.0, 0.01)
