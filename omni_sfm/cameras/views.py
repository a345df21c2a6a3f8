"""Virtual pinhole views of a central camera's frames: the pixels of a pinhole view come from
the camera's image through its ``pixels_from_rays`` and ``cv2.remap``.

Used by ``dense`` (rectified stereo views) and ``export`` (perspective views and COLMAP rigs for
pinhole-only tools). Frames: ``world_from_view`` maps view rays (OpenCV pinhole frame: ``x``
right, ``y`` down, ``z`` forward) to the world; pixels are OpenCV's (centre of the top-left
pixel at (0, 0)).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from omni_sfm.cameras.base import CameraModel
from omni_sfm.geometry import FloatArray


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


def camera_angular_step(camera: CameraModel) -> float:
    """Median angle (radians) between the rays of horizontally adjacent valid pixels."""
    g = camera.pixel_grid_rays()
    a, b = g[:, :-1].reshape(-1, 3), g[:, 1:].reshape(-1, 3)
    ok = np.isfinite(a[:, 0]) & np.isfinite(b[:, 0])
    cos = np.clip(np.einsum("ij,ij->i", a[ok], b[ok]), -1.0, 1.0)
    if not cos.size:
        raise ValueError(f"camera {camera.model} has no two adjacent valid pixels")
    return float(np.median(np.arccos(cos)))


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
                 erode_px: int = 2, *, wrap: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Views of ``image`` ``(H0, W0[, 3])`` uint8 through ``tables`` ``(V, H, W, 2)``: the
    ``(V, H, W[, 3])`` images (bilinear) and ``(V, H, W)`` bool validity (the camera's
    ``valid`` mask eroded by ``erode_px``, so the rim's black border gives no matches).
    ``wrap``: the image wraps around left-right (a 360 panorama, whose every ray is valid)."""
    import cv2

    border = cv2.BORDER_WRAP if wrap else cv2.BORDER_CONSTANT

    mask: np.ndarray = valid.astype(np.uint8)
    if erode_px > 0:
        mask = cv2.erode(mask, np.ones((2 * erode_px + 1, 2 * erode_px + 1), np.uint8))
    imgs, oks = [], []
    for t in tables:
        imgs.append(cv2.remap(image, t[..., 0], t[..., 1], cv2.INTER_LINEAR,
                              borderMode=border, borderValue=0))
        oks.append(cv2.remap(mask, t[..., 0], t[..., 1], cv2.INTER_NEAREST,
                             borderMode=border, borderValue=0) > 0)
    return np.stack(imgs), np.stack(oks)
