"""360 equirectangular images, exactly as pycolmap's EQUIRECTANGULAR camera."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from omni_sfm.cameras.base import CameraModel, as_points
from omni_sfm.geometry import FloatArray


@dataclass(frozen=True, kw_only=True)
class EquirectangularCamera(CameraModel):
    """Longitude along ``u``, latitude along ``v``; COLMAP's axes and pixel convention.

    With COLMAP pixel coordinates ``(uc, vc) = (u + 0.5, v + 0.5)`` (omni-sfm pixels are
    OpenCV's, centre of the top-left pixel at 0): ``lon = 2 pi uc / W - pi``,
    ``lat = pi vc / H - pi / 2``, ray ``= (cos lat sin lon, sin lat, cos lat cos lon)``.
    So +Z is the image centre, +Y is down (the bottom row), +X is at ``u = 3W/4``.
    """

    model = "equirectangular"

    def rays_from_pixels(self, uv: ArrayLike) -> FloatArray:
        p = as_points(uv, 2, "uv")
        lon = 2.0 * np.pi * (p[:, 0] + 0.5) / self.width - np.pi
        lat = np.pi * (p[:, 1] + 0.5) / self.height - np.pi / 2.0
        c = np.cos(lat)
        return np.stack([c * np.sin(lon), np.sin(lat), c * np.cos(lon)], axis=1)

    def pixels_from_rays(self, rays: ArrayLike) -> FloatArray:
        d = as_points(rays, 3, "rays")
        with np.errstate(invalid="ignore", divide="ignore"):
            n = np.linalg.norm(d, axis=1)
            lon = np.arctan2(d[:, 0], d[:, 2])
            lat = np.arcsin(np.clip(d[:, 1] / n, -1.0, 1.0))
        uv = np.stack(
            [(lon + np.pi) * self.width / (2.0 * np.pi) - 0.5,
             (lat + np.pi / 2.0) * self.height / np.pi - 0.5],
            axis=1,
        )
        uv[~(n > 0)] = np.nan
        return uv

    def valid_mask(self) -> np.ndarray:
        return np.ones((self.height, self.width), dtype=bool)

    def to_pycolmap(self) -> Any:
        import pycolmap

        return pycolmap.Camera(
            model="EQUIRECTANGULAR", width=self.width, height=self.height,
            params=[float(self.width), float(self.height)],
        )
