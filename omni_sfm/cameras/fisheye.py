"""Kannala-Brandt fisheye, exactly as ``cv2.fisheye`` and COLMAP's ``OPENCV_FISHEYE``."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from omni_sfm.cameras.base import (
    MASK_TOL,
    CameraModel,
    ColmapExport,
    MonotoneInverse,
    colmap_export_plain,
    first_nonincreasing,
    radius_ok,
    unit_input_rays,
)
from omni_sfm.geometry import FloatArray


@dataclass(frozen=True, kw_only=True)
class OpenCVFisheyeCamera(CameraModel):
    """Kannala-Brandt equidistant fisheye (``cv2.fisheye``, COLMAP ``OPENCV_FISHEYE``, Kalibr
    ``pinhole`` + ``equidistant``). Camera frame: OpenCV's (x right, y down, z forward).

    Ray -> pixel: ``theta = atan2(sqrt(x^2 + y^2), z)`` (angle from the optical axis),
    ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``,
    ``u = fx theta_d x / sqrt(x^2 + y^2) + cx``, ``v = fy theta_d y / sqrt(x^2 + y^2) + cy``.
    Pixel -> ray inverts ``theta_d(theta)`` exactly (table start + Newton).

    Valid: ``theta <= theta_max``, the end of the monotone part of ``theta_d(theta)`` (at most
    pi), and the optional radius mask. OpenCV and COLMAP compute ``theta = atan(r / z)`` and so
    only handle ``z > 0``; for those rays all three agree, this model continues past 90 deg.
    """

    model = "opencv_fisheye"
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    inner_radius: float | None = None
    outer_radius: float | None = None

    def _check(self) -> None:
        self._positive("fx", "fy")

    def _theta_d(self, t: FloatArray) -> FloatArray:
        t2 = t * t
        return t * (1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4))))

    def _dtheta_d(self, t: FloatArray) -> FloatArray:
        t2 = t * t
        return 1.0 + t2 * (
            3.0 * self.k1 + t2 * (5.0 * self.k2 + t2 * (7.0 * self.k3 + t2 * 9.0 * self.k4))
        )

    @cached_property
    def theta_max(self) -> float:
        """Largest angle from the optical axis (rad) the model images one-to-one."""
        return first_nonincreasing(self._dtheta_d, math.pi)

    @cached_property
    def _inverse(self) -> MonotoneInverse:
        return MonotoneInverse(self._theta_d, self._dtheta_d, self.theta_max, newton_steps=2)

    def _rays_block(self, uv: FloatArray) -> FloatArray:
        u, v = uv[:, 0], uv[:, 1]
        mx = (u - self.cx) / self.fx
        my = (v - self.cy) / self.fy
        td = np.sqrt(mx * mx + my * my)
        theta = self._inverse(td)
        out = np.empty((len(uv), 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            # sin and cos from tan(theta/2): numpy's float64 tan is vectorised, sin/cos are not
            t = np.tan(0.5 * theta)
            t2 = t * t
            inv = 1.0 / (1.0 + t2)
            s = 2.0 * t * inv
            s /= td
            s[td == 0] = 1.0
            np.multiply(mx, s, out=out[:, 0])
            np.multiply(my, s, out=out[:, 1])
            np.multiply(1.0 - t2, inv, out=out[:, 2])
        ok = np.isfinite(theta)
        ok &= radius_ok(u, v, self.cx, self.cy, self.inner_radius, self.outer_radius)
        out[~ok] = np.nan
        return out

    def _pixels_block(self, rays: FloatArray) -> FloatArray:
        x, y, z = unit_input_rays(rays)
        with np.errstate(invalid="ignore", divide="ignore"):
            rho = np.hypot(x, y)
            theta = np.arctan2(rho, z)
            s = self._theta_d(theta)
            s /= rho
            s[rho == 0] = 1.0
            ok = theta <= self.theta_max
        uv = np.empty((len(rays), 2))
        np.multiply(x, s * self.fx, out=uv[:, 0])
        uv[:, 0] += self.cx
        np.multiply(y, s * self.fy, out=uv[:, 1])
        uv[:, 1] += self.cy
        ok &= radius_ok(uv[:, 0], uv[:, 1], self.cx, self.cy, self.inner_radius, self.outer_radius,
                        MASK_TOL)
        uv[~ok] = np.nan
        return uv

    def colmap_export(self) -> ColmapExport:
        """COLMAP ``OPENCV_FISHEYE``: same parameters, principal point shifted by 0.5 px."""
        import pycolmap

        cam = pycolmap.Camera(
            model="OPENCV_FISHEYE", width=self.width, height=self.height,
            params=[self.fx, self.fy, self.cx + 0.5, self.cy + 0.5,
                    self.k1, self.k2, self.k3, self.k4],
        )
        return colmap_export_plain(cam, self.width, self.height)
