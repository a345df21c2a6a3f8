"""Camera models against independent implementations: cv2.omnidir, cv2.fisheye, pycolmap,
a direct transcription of the paper's eq. (1)-(2) and of OCamCalib's C functions."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from omni_sfm.cameras import (
    CameraModel,
    DoubleSphereCamera,
    EquirectangularCamera,
    EUCMCamera,
    HyperboloidCamera,
    OCamCamera,
    OpenCVFisheyeCamera,
    UnifiedCamera,
)
from omni_sfm.errors import OmniSfmError


def random_valid_pixels(cam: CameraModel, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Random sub-pixel positions inside the image and the valid region, with their rays."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([-0.5, -0.5], [cam.width - 0.5, cam.height - 0.5], size=(4 * n, 2))
    rays = cam.rays_from_pixels(uv)
    ok = np.isfinite(rays).all(axis=1)
    assert ok.sum() >= n
    return uv[ok][:n], rays[ok][:n]


def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return 2.0 * np.arcsin(np.clip(np.linalg.norm(a - b, axis=1) / 2.0, 0, 1))


# ---------------------------------------------------------------- OpenCV


UNIFIED = UnifiedCamera(
    width=640, height=480, fx=420.0, fy=415.0, cx=322.0, cy=238.5, xi=1.3, skew=0.8,
    k1=-0.17, k2=0.035, p1=0.0013, p2=-0.0009,
)


def test_unified_matches_cv2_omnidir_project_points() -> None:
    rng = np.random.default_rng(4)
    _, rays = random_valid_pixels(UNIFIED, 3000)
    pts = rays * rng.uniform(0.5, 20.0, size=(len(rays), 1))  # 3D points at random depths
    k = np.array([[UNIFIED.fx, UNIFIED.skew, UNIFIED.cx], [0, UNIFIED.fy, UNIFIED.cy], [0, 0, 1]])
    d = np.array([[UNIFIED.k1, UNIFIED.k2, UNIFIED.p1, UNIFIED.p2]])
    xi = UNIFIED.xi
    ref, _ = cv2.omnidir.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), k, xi, d)
    ours = UNIFIED.pixels_from_rays(pts)
    err = np.linalg.norm(ours - ref.reshape(-1, 2), axis=1)
    assert err.max() < 1e-6, err.max()
    # and our exact inverse of cv2's projection returns the rays
    back = UNIFIED.rays_from_pixels(ref.reshape(-1, 2))
    assert angle(back, pts).max() < 1e-9


def test_unified_matches_cv2_omnidir_undistort_points() -> None:
    uv, rays = random_valid_pixels(UNIFIED, 3000, seed=5)
    front = rays[:, 2] > 0.2  # cv2 returns the perspective image x/z, y/z
    uv, rays = uv[front], rays[front]
    k = np.array([[UNIFIED.fx, UNIFIED.skew, UNIFIED.cx], [0, UNIFIED.fy, UNIFIED.cy], [0, 0, 1]])
    d = np.array([[UNIFIED.k1, UNIFIED.k2, UNIFIED.p1, UNIFIED.p2]])
    ref = cv2.omnidir.undistortPoints(uv.reshape(-1, 1, 2), k, d, np.array([UNIFIED.xi]),
                                      np.eye(3)).reshape(-1, 2)
    ref_rays = np.column_stack([ref, np.ones(len(ref))])
    # cv2 undistorts with a fixed number of fixed-point steps: agreement to its accuracy
    assert np.median(angle(rays, ref_rays)) < 1e-7
    assert angle(rays, ref_rays).max() < 1e-5


FISHEYE = OpenCVFisheyeCamera(
    width=800, height=600, fx=250.0, fy=249.0, cx=401.5, cy=298.0,
    k1=0.031, k2=-0.0123, k3=0.0021, k4=-0.00019,
)


def test_fisheye_matches_cv2_fisheye() -> None:
    rng = np.random.default_rng(6)
    _, rays = random_valid_pixels(FISHEYE, 3000)
    rays = rays[rays[:, 2] > 0.05]  # cv2.fisheye handles the front hemisphere only
    pts = rays * rng.uniform(0.5, 20.0, size=(len(rays), 1))
    k = np.array([[FISHEYE.fx, 0, FISHEYE.cx], [0, FISHEYE.fy, FISHEYE.cy], [0, 0, 1]])
    d = np.array([FISHEYE.k1, FISHEYE.k2, FISHEYE.k3, FISHEYE.k4])
    ref, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), k, d)
    ours = FISHEYE.pixels_from_rays(pts)
    assert np.linalg.norm(ours - ref.reshape(-1, 2), axis=1).max() < 1e-6
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    und = cv2.fisheye.undistortPoints(ours.reshape(-1, 1, 2), k, d, criteria=crit).reshape(-1, 2)
    assert angle(np.column_stack([und, np.ones(len(und))]), rays).max() < 1e-8


# ---------------------------------------------------------------- pycolmap, through colmap_export

EXPORTABLE: dict[str, CameraModel] = {
    "hyperboloid": HyperboloidCamera(
        width=640, height=480, cx=318.4, cy=242.2, px=0.0125, py=0.0124, f=8.0, alpha=14.0,
        beta=19.4, inner_radius=30.0, outer_radius=235.0,
    ),
    "unified": UnifiedCamera(width=640, height=480, fx=300.0, fy=298.0, cx=320.5, cy=241.0,
                             xi=0.9),
    "pinhole_radtan": UnifiedCamera(width=640, height=480, fx=500.0, fy=498.0, cx=320.5,
                                    cy=241.0, xi=0.0, k1=-0.2, k2=0.05, p1=1e-3, p2=-2e-4),
    "eucm": EUCMCamera(width=640, height=480, fx=190.0, fy=189.0, cx=321.0, cy=239.0,
                       alpha=0.63, beta=1.2),
    "equirectangular": EquirectangularCamera(width=640, height=320),
    "opencv_fisheye": FISHEYE,
}
EXPECTED_MODEL = {"hyperboloid": "EUCM", "unified": "EUCM", "pinhole_radtan": "OPENCV",
                  "eucm": "EUCM", "equirectangular": "EQUIRECTANGULAR",
                  "opencv_fisheye": "OPENCV_FISHEYE"}


@pytest.mark.parametrize("name", sorted(EXPORTABLE))
def test_colmap_export_agrees_with_pycolmap(name: str) -> None:
    cam = EXPORTABLE[name]
    exp = cam.colmap_export()
    assert exp.camera.model_name == EXPECTED_MODEL[name]
    assert cam.to_pycolmap().params.tolist() == exp.camera.params.tolist()
    r = exp.colmap_cam_from_cam
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(r) == pytest.approx(1.0)  # a proper rotation, never a reflection
    uv, rays = random_valid_pixels(cam, 3000, seed=7)
    if name in ("opencv_fisheye", "pinhole_radtan"):
        keep = rays[:, 2] > 0.05  # COLMAP's perspective models: front hemisphere only
        uv, rays = uv[keep], rays[keep]
    # 3D points both ways: ours projected, and COLMAP's projection in COLMAP's frame
    pts = rays * np.random.default_rng(8).uniform(0.3, 30.0, size=(len(rays), 1))
    ours = exp.pixels_to_colmap(cam.pixels_from_rays(pts))
    theirs = exp.camera.img_from_cam(exp.rays_to_colmap(pts), check_cheirality=False)
    err = np.linalg.norm(ours - theirs, axis=1)
    assert err.max() < 1e-6, f"{name}: {err.max():.2e} px"
    # and pixels back to rays. pycolmap 4.2.1 unprojects EUCM pixels through the perspective
    # plane, so it returns NaN for rays with z <= 0 in COLMAP's frame: compare the others
    rays_c = exp.rays_to_colmap(rays)
    if exp.camera.model_name == "EUCM":
        front = rays_c[:, 2] > 1e-6
        assert front.mean() > 0.2
        uv, rays_c = uv[front], rays_c[front]
    theirs_rays = exp.camera.cam_ray_from_img(exp.pixels_to_colmap(uv))
    assert angle(theirs_rays, rays_c).max() < 1e-9
    np.testing.assert_allclose(exp.pixels_from_colmap(exp.pixels_to_colmap(uv)), uv, atol=1e-12)


def test_hyperboloid_export_flips_the_image_left_right() -> None:
    cam = EXPORTABLE["hyperboloid"]
    exp = cam.colmap_export()
    assert exp.flip_u
    np.testing.assert_array_equal(exp.colmap_cam_from_cam, np.diag([-1.0, 1.0, -1.0]))
    img = np.arange(cam.height * cam.width * 3).reshape(cam.height, cam.width, 3)
    flipped = exp.image_to_colmap(img)
    assert flipped.shape == img.shape and flipped.flags.c_contiguous
    rng = np.random.default_rng(9)
    uv = np.column_stack([rng.integers(0, cam.width, 50), rng.integers(0, cam.height, 50)])
    uc = exp.pixels_to_colmap(uv.astype(float)) - 0.5  # COLMAP pixel -> array index
    ui, vi = np.rint(uc).astype(int).T
    np.testing.assert_array_equal(flipped[vi, ui], img[uv[:, 1], uv[:, 0]])
    np.testing.assert_array_equal(exp.image_to_colmap(img[..., 0]), img[:, ::-1, 0])
    with pytest.raises(ValueError, match="image must be"):
        exp.image_to_colmap(img[:10])


def test_no_exact_colmap_model_is_a_clear_error() -> None:
    ds = DoubleSphereCamera(width=10, height=10, fx=5, fy=5, cx=5, cy=5, xi=-0.2, alpha=0.6)
    with pytest.raises(OmniSfmError, match="no exact COLMAP model for camera model 'double"):
        ds.to_pycolmap()
    with pytest.raises(OmniSfmError, match="no exact COLMAP model"):
        UNIFIED.to_pycolmap()  # xi != 0 with distortion
    oc = OCamCamera(width=10, height=10, cx=5, cy=5, pol=(-5.0, 0.0, 0.01))
    with pytest.raises(OmniSfmError, match="'ocam'"):
        oc.colmap_export()


# ---------------------------------------------------------------- the paper's camera


def paper_eq_1_2(cam: HyperboloidCamera, u: float, v: float) -> np.ndarray:
    """Eq. (1)-(2) transcribed literally, one pixel at a time."""
    a, b, f = cam.alpha, cam.beta, cam.f
    g = math.sqrt(a * a + b * b)
    x, y = (u - cam.cx) * cam.px, (v - cam.cy) * cam.py
    lam = a * a * (f * g + b * math.sqrt(x * x + y * y + f * f)) / (a * a * f * f
                                                                 - b * b * (x * x + y * y))
    r = np.array([lam * x, lam * y, lam * f - 2 * g])
    return r / np.linalg.norm(r)


def mirror_projection(cam: HyperboloidCamera, d: np.ndarray) -> np.ndarray:
    """Ray -> pixel by solving the mirror's quadric for the ray point ``s d`` directly."""
    a, b = cam.alpha, cam.beta
    g = math.sqrt(a * a + b * b)
    d = d / np.linalg.norm(d)
    # (s^2 (dx^2 + dy^2)) / a^2 - (s dz + g)^2 / b^2 = -1  ->  A s^2 + B s + C = 0
    qa = (d[0] ** 2 + d[1] ** 2) / a**2 - d[2] ** 2 / b**2
    qb = -2 * g * d[2] / b**2
    qc = -(g**2) / b**2 + 1
    roots = np.roots([qa, qb, qc]) if abs(qa) > 1e-15 else np.array([-qc / qb])
    roots = roots[np.isreal(roots)].real
    s = min(r for r in roots if r > 0 and r * d[2] > -g)  # the sheet around the focus
    p = s * d
    x = cam.f * p[0] / (p[2] + 2 * g)
    y = cam.f * p[1] / (p[2] + 2 * g)
    return np.array([x / cam.px + cam.cx, y / cam.py + cam.cy])


def test_hyperboloid_matches_paper_equations_and_mirror_geometry() -> None:
    cam = EXPORTABLE["hyperboloid"]
    uv, rays = random_valid_pixels(cam, 200, seed=10)
    ref = np.array([paper_eq_1_2(cam, u, v) for u, v in uv])
    assert angle(rays, ref).max() < 1e-12
    # the ray meets the mirror at a point whose image through the lens is the pixel
    px = np.array([mirror_projection(cam, d) for d in rays])
    assert np.abs(px - uv).max() < 1e-8
    assert np.abs(cam.pixels_from_rays(rays) - px).max() < 1e-8


def test_hyperboloid_is_the_unified_model_reflected() -> None:
    cam = HyperboloidCamera(width=640, height=480, cx=318.4, cy=242.2, px=0.0125, py=0.0124,
                            f=8.0, alpha=14.0, beta=19.4)
    e = cam.gamma / cam.beta
    assert cam.unified_xi == pytest.approx(2 * e / (1 + e * e))
    uni = UnifiedCamera(width=640, height=480, fx=cam.unified_focal / cam.px,
                        fy=cam.unified_focal / cam.py, cx=cam.cx, cy=cam.cy, xi=cam.unified_xi)
    uv, rays = random_valid_pixels(cam, 2000, seed=11)
    flip_z = np.array([1.0, 1.0, -1.0])
    np.testing.assert_allclose(uni.pixels_from_rays(rays * flip_z), uv, atol=1e-8)
    assert angle(uni.rays_from_pixels(uv) * flip_z, rays).max() < 1e-11
    # the same numbers as EUCM with beta = 1 (COLMAP's model): alpha = xi / (1 + xi)
    s = 1 / (1 + cam.unified_xi)
    eucm = EUCMCamera(width=640, height=480, fx=uni.fx * s, fy=uni.fy * s, cx=cam.cx,
                      cy=cam.cy, alpha=cam.unified_xi * s, beta=1.0)
    np.testing.assert_allclose(eucm.pixels_from_rays(rays * flip_z), uv, atol=1e-8)


def test_double_sphere_with_xi_zero_is_eucm_with_beta_one() -> None:
    ds = DoubleSphereCamera(width=400, height=300, fx=120, fy=119, cx=200, cy=150, xi=0.0,
                            alpha=0.57)
    eu = EUCMCamera(width=400, height=300, fx=120, fy=119, cx=200, cy=150, alpha=0.57, beta=1.0)
    uv, rays = random_valid_pixels(ds, 2000, seed=12)
    assert angle(eu.rays_from_pixels(uv), rays).max() < 1e-12
    np.testing.assert_allclose(eu.pixels_from_rays(rays), uv, atol=1e-9)


# ---------------------------------------------------------------- OCamCalib's C code


def ocam_cam2world(cam: OCamCamera, row: float, col: float) -> np.ndarray:
    """ocam_functions.c cam2world, transcribed: point2D = (row, column), C convention."""
    invdet = 1 / (cam.c - cam.d * cam.e)
    xc, yc = cam.cy, cam.cx  # OCamCalib's xc is the row of the centre
    xp = invdet * ((row - xc) - cam.d * (col - yc))
    yp = invdet * (-cam.e * (row - xc) + cam.c * (col - yc))
    r = math.hypot(xp, yp)
    zp = sum(a * r**i for i, a in enumerate(cam.pol))
    p = np.array([xp, yp, zp])
    return p / np.linalg.norm(p)


def ocam_world2cam(cam: OCamCamera, p: np.ndarray, invpol: np.ndarray) -> tuple[float, float]:
    """ocam_functions.c world2cam, transcribed: returns (row, column)."""
    norm = math.hypot(p[0], p[1])
    theta = math.atan(p[2] / norm)
    rho = sum(a * theta**i for i, a in enumerate(invpol))
    x, y = p[0] / norm * rho, p[1] / norm * rho
    return x * cam.c + y * cam.d + cam.cy, x * cam.e + y + cam.cx


def test_ocam_matches_ocamcalib_c_functions() -> None:
    cam = OCamCamera(width=640, height=480, cx=318.7, cy=241.4, c=1.0004, d=0.0003, e=-0.0002,
                     pol=(-165.0, 0.0, 2.3e-3, -2.7e-6, 5.0e-9))
    uv, rays = random_valid_pixels(cam, 300, seed=13)
    # OCamCalib frame (x = row direction, y = column direction, z backwards) -> ours
    ref = np.array([ocam_cam2world(cam, v, u) for u, v in uv])
    ref_ours = np.column_stack([ref[:, 1], ref[:, 0], -ref[:, 2]])
    assert angle(rays, ref_ours).max() < 1e-12
    # world2cam uses OCamCalib's fitted inverse polynomial; fit one as the toolbox does
    # (rho as a polynomial in theta = atan(z / norm)) and compare to its accuracy
    r = np.linspace(0, cam.r_max, 2000)
    theta = np.arctan(np.polynomial.polynomial.polyval(r, cam.pol) / r.clip(1e-9))
    invpol = np.polynomial.polynomial.polyfit(theta, r, 14)
    fit_err = np.abs(np.polynomial.polynomial.polyval(theta, invpol) - r).max()
    ours = cam.pixels_from_rays(rays)
    ref_px = np.array([ocam_world2cam(cam, p, invpol) for p in ref])  # (row, col)
    err = np.linalg.norm(ours - ref_px[:, ::-1], axis=1)
    assert err.max() < 3 * fit_err + 1e-6, (err.max(), fit_err)
    assert fit_err < 0.05
