"""Virtual pinhole views of omnidirectional frames, rectified for two-view stereo.

A *stereo rig* of a pair of frames ``(ref, src)`` is four pinhole views that share one
orientation for both frames: their image ``x`` axis is the baseline direction
``(c_src - c_ref) / |c_src - c_ref|`` and they look in four directions 90 deg apart around it,
so the pair of views of one direction is already rectified (a pure translation along ``x``,
horizontal epipolar lines, disparity ``d = f b / z > 0`` from ``ref`` to ``src``). The pixels of
each view come from the omnidirectional image through the camera model's ``pixels_from_rays``
and ``cv2.remap``. The directions within ``fov_along_deg / 2`` of the baseline (the epipoles,
where stereo has no parallax) are not covered.

Frames: ``world_from_view`` maps view rays (OpenCV pinhole frame: ``x`` right, ``y`` down,
``z`` forward) to the world; pixels are OpenCV's (centre of the top-left pixel at (0, 0)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from omni_sfm.cameras import CameraModel
from omni_sfm.geometry import FloatArray, normalize

# the four viewing directions around the baseline, in the rig frame (x = baseline)
_RIG_ANGLES = np.deg2rad([0.0, 90.0, 180.0, 270.0])


@dataclass(frozen=True, kw_only=True)
class ViewGeometry:
    """Intrinsics shared by the views of a rig (square pixels, principal point at the centre).

    Attributes:
        focal: focal length, px.
        width, height: view size, px.
    """

    focal: float
    width: int
    height: int

    @property
    def cx(self) -> float:
        return (self.width - 1) / 2.0

    @property
    def cy(self) -> float:
        return (self.height - 1) / 2.0

    def intrinsic(self) -> FloatArray:
        """``(3, 3)`` pinhole matrix K."""
        return np.array([[self.focal, 0.0, self.cx], [0.0, self.focal, self.cy], [0.0, 0.0, 1.0]])

    @cached_property
    def rays_in_view(self) -> FloatArray:
        """``(H, W, 3)`` un-normalised view rays ``((u - cx)/f, (v - cy)/f, 1)``."""
        u = (np.arange(self.width) - self.cx) / self.focal
        v = (np.arange(self.height) - self.cy) / self.focal
        out = np.ones((self.height, self.width, 3))
        out[:, :, 0] = u[None, :]
        out[:, :, 1] = v[:, None]
        return out


def view_geometry(camera: CameraModel, *, resolution_scale: float = 1.0,
                  fov_along_deg: float = 130.0) -> ViewGeometry:
    """Views whose pixels subtend about the camera's own angle (times ``1/resolution_scale``).

    Each view covers 90 deg across the baseline (four views close the circle) and
    ``fov_along_deg`` along it."""
    if not 0.0 < fov_along_deg < 170.0:
        raise ValueError(f"fov_along_deg must be in (0, 170), got {fov_along_deg}")
    if resolution_scale <= 0:
        raise ValueError(f"resolution_scale must be > 0, got {resolution_scale}")
    focal = resolution_scale / camera_angular_step(camera)
    half_w = focal * math.tan(math.radians(fov_along_deg) / 2.0)
    return ViewGeometry(focal=focal, width=int(2 * math.ceil(half_w)), height=int(2 * round(focal)))


def camera_angular_step(camera: CameraModel) -> float:
    """Median angle (radians) between the rays of horizontally adjacent valid pixels."""
    g = camera.pixel_grid_rays()
    a, b = g[:, :-1].reshape(-1, 3), g[:, 1:].reshape(-1, 3)
    ok = np.isfinite(a[:, 0]) & np.isfinite(b[:, 0])
    cos = np.clip(np.einsum("ij,ij->i", a[ok], b[ok]), -1.0, 1.0)
    if not cos.size:
        raise ValueError(f"camera {camera.model} has no two adjacent valid pixels")
    return float(np.median(np.arccos(cos)))


@dataclass(frozen=True)
class StereoRig:
    """Four rectified views around the baseline of a frame pair (see the module docstring).

    Attributes:
        geometry: intrinsics of every view.
        world_from_rig: ``(3, 3)``; column 0 is the baseline direction in the world.
        world_from_views: ``(4, 3, 3)`` rotation of each view (x = baseline, z = look direction).
        baseline: ``|c_src - c_ref|`` in pose units.
    """

    geometry: ViewGeometry
    world_from_rig: FloatArray
    world_from_views: FloatArray
    baseline: float


def stereo_rig(geometry: ViewGeometry, centre_ref: FloatArray, centre_src: FloatArray,
               world_from_ref: FloatArray) -> StereoRig:
    """The rig of the pair: baseline ``centre_src - centre_ref`` (world), the second rig axis is
    the reference camera's axis most perpendicular to it (so rigs of one frame look alike)."""
    base = np.asarray(centre_src, float) - np.asarray(centre_ref, float)
    b = float(np.linalg.norm(base))
    if not b > 0:
        raise ValueError("the two frames of a stereo pair have the same centre")
    e1 = base / b
    axes = np.asarray(world_from_ref, float).T  # rows: the camera axes in the world
    a = axes[int(np.argmin(np.abs(axes @ e1)))]
    e2 = normalize(a - (a @ e1) * e1)
    e3 = np.cross(e1, e2)
    world_from_rig = np.stack([e1, e2, e3], axis=1)
    c, s = np.cos(_RIG_ANGLES), np.sin(_RIG_ANGLES)
    look = np.stack([np.zeros(4), c, s], axis=1)          # rig frame
    down = np.stack([np.zeros(4), s, -c], axis=1)         # look x baseline
    x = np.tile([1.0, 0.0, 0.0], (4, 1))
    rig_from_views = np.stack([x, down, look], axis=2)    # columns x, y, z of each view
    return StereoRig(geometry, world_from_rig, world_from_rig @ rig_from_views, b)


def remap_tables(camera: CameraModel, geometry: ViewGeometry, world_from_views: FloatArray,
                 world_from_cam: FloatArray) -> FloatArray:
    """``(V, H, W, 2)`` float32 source pixels (u, v) of the omnidirectional image for every view
    pixel (``-1`` where the camera does not image the ray), for ``cv2.remap``."""
    cam_from_views = np.asarray(world_from_cam).T @ world_from_views           # (V, 3, 3)
    rays = np.einsum("vij,hwj->vhwi", cam_from_views, geometry.rays_in_view)
    uv = camera.pixels_from_rays(rays.reshape(-1, 3))
    ok = camera.in_image(uv)
    uv[~ok] = -1.0
    return uv.reshape(*rays.shape[:3], 2).astype(np.float32)


def sample_views(image: np.ndarray, tables: FloatArray, valid: np.ndarray,
                 erode_px: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Views of ``image`` ``(H0, W0[, 3])`` uint8 through ``tables`` ``(V, H, W, 2)``: the
    ``(V, H, W[, 3])`` images (bilinear) and ``(V, H, W)`` bool validity (the camera's
    ``valid`` mask eroded by ``erode_px``, so the rim's black border gives no matches)."""
    import cv2

    mask: np.ndarray = valid.astype(np.uint8)
    if erode_px > 0:
        mask = cv2.erode(mask, np.ones((2 * erode_px + 1, 2 * erode_px + 1), np.uint8))
    imgs, oks = [], []
    for t in tables:
        imgs.append(cv2.remap(image, t[..., 0], t[..., 1], cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0))
        oks.append(cv2.remap(mask, t[..., 0], t[..., 1], cv2.INTER_NEAREST,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0)
    return np.stack(imgs), np.stack(oks)
