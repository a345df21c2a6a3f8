"""Extended unified (EUCM) and double sphere cameras, as Kalibr / basalt and COLMAP define them."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omni_sfm.cameras.base import (
    MASK_TOL,
    CameraModel,
    ColmapExport,
    colmap_export_plain,
    radius_ok,
    unit_input_rays,
    unit_rows,
)
from omni_sfm.geometry import FloatArray


def _finish_pixels(
    cam: EUCMCamera | DoubleSphereCamera, mx: FloatArray, my: FloatArray, ok: np.ndarray
) -> FloatArray:
    uv = np.empty((len(mx), 2))
    np.multiply(mx, cam.fx, out=uv[:, 0])
    uv[:, 0] += cam.cx
    np.multiply(my, cam.fy, out=uv[:, 1])
    uv[:, 1] += cam.cy
    ok &= radius_ok(
        uv[:, 0], uv[:, 1], cam.cx, cam.cy, cam.inner_radius, cam.outer_radius, MASK_TOL
    )
    uv[~ok] = np.nan
    return uv


@dataclass(frozen=True, kw_only=True)
class EUCMCamera(CameraModel):
    """Enhanced unified camera model (Khomutenko et al. 2016), Kalibr ``eucm`` / basalt / COLMAP
    ``EUCM`` (params ``fx, fy, cx, cy, alpha, beta``). Camera frame: OpenCV's.

    Ray -> pixel: ``d = sqrt(beta (x^2 + y^2) + z^2)``, ``den = alpha d + (1 - alpha) z``,
    ``u = fx x / den + cx``, ``v = fy y / den + cy``; valid where ``z > -w d`` with
    ``w = (1 - alpha)/alpha`` if ``alpha > 1/2`` else ``alpha/(1 - alpha)``.
    Pixel -> ray (closed form): ``m = ((u - cx)/fx, (v - cy)/fy)``, ``r^2 = |m|^2``,
    ``mz = (1 - beta alpha^2 r^2) / (alpha sqrt(1 - (2 alpha - 1) beta r^2) + 1 - alpha)``,
    ray ``~ (m_x, m_y, mz)``; valid for ``r^2 < 1 / (beta (2 alpha - 1))`` when ``alpha > 1/2``.
    With ``beta = 1`` this is the unified model with ``xi = alpha / (1 - alpha)``.
    """

    model = "eucm"
    fx: float
    fy: float
    cx: float
    cy: float
    alpha: float
    beta: float
    inner_radius: float | None = None
    outer_radius: float | None = None

    def _check(self) -> None:
        self._positive("fx", "fy", "beta")
        if not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"key 'alpha' must be in [0, 1], got {self.alpha!r}")

    @property
    def _w(self) -> float:
        a = self.alpha
        return (1.0 - a) / a if a > 0.5 else a / (1.0 - a)

    def _rays_block(self, uv: FloatArray) -> FloatArray:
        u, v = uv[:, 0], uv[:, 1]
        a, b = self.alpha, self.beta
        mx = (u - self.cx) / self.fx
        my = (v - self.cy) / self.fy
        r2 = mx * mx + my * my
        with np.errstate(invalid="ignore", divide="ignore"):
            disc = 1.0 - (2.0 * a - 1.0) * b * r2
            mz = (1.0 - b * a * a * r2) / (a * np.sqrt(disc) + (1.0 - a))
            rays = unit_rows(mx, my, mz)
            ok = disc > 0 if a > 0.5 else np.isfinite(mz)
            # the lifted ray must lie in the projection's domain (it does, up to rounding)
            ok &= rays[:, 2] > -self._w * np.sqrt(1.0 + (b - 1.0) * (1.0 - rays[:, 2] ** 2))
        ok &= radius_ok(u, v, self.cx, self.cy, self.inner_radius, self.outer_radius)
        rays[~ok] = np.nan
        return rays

    def _pixels_block(self, rays: FloatArray) -> FloatArray:
        x, y, z = unit_input_rays(rays)
        a = self.alpha
        with np.errstate(invalid="ignore", divide="ignore"):
            d = np.sqrt(self.beta * (x * x + y * y) + z * z)
            den = a * d + (1.0 - a) * z
            ok = (z > -self._w * d) & (den > 0)
            return _finish_pixels(self, x / den, y / den, ok)

    def colmap_export(self) -> ColmapExport:
        """COLMAP ``EUCM``: same parameters, principal point shifted by 0.5 px."""
        import pycolmap

        cam = pycolmap.Camera(
            model="EUCM", width=self.width, height=self.height,
            params=[self.fx, self.fy, self.cx + 0.5, self.cy + 0.5, self.alpha, self.beta],
        )
        return colmap_export_plain(cam, self.width, self.height)


@dataclass(frozen=True, kw_only=True)
class DoubleSphereCamera(CameraModel):
    """Double sphere model (Usenko et al. 2018), Kalibr ``ds`` / basalt ``ds``
    (``fx, fy, cx, cy, xi, alpha``). Camera frame: OpenCV's. COLMAP has no such model.

    Ray -> pixel: ``d1 = |(x, y, z)|``, ``k = xi d1 + z``, ``d2 = |(x, y, k)|``,
    ``den = alpha d2 + (1 - alpha) k``, ``u = fx x / den + cx``, ``v = fy y / den + cy``;
    valid where ``z > -w2 d1``, ``w1 = (1 - alpha)/alpha`` if ``alpha > 1/2`` else
    ``alpha/(1 - alpha)``, ``w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2 + 1)``.
    Pixel -> ray (closed form): ``r^2 = |m|^2``,
    ``mz = (1 - alpha^2 r^2) / (alpha sqrt(1 - (2 alpha - 1) r^2) + 1 - alpha)``,
    ``s = (mz xi + sqrt(mz^2 + (1 - xi^2) r^2)) / (mz^2 + r^2)``, ray ``= (s m_x, s m_y,
    s mz - xi)``; valid for ``r^2 <= 1/(2 alpha - 1)`` when ``alpha > 1/2``.
    """

    model = "double_sphere"
    fx: float
    fy: float
    cx: float
    cy: float
    xi: float
    alpha: float
    inner_radius: float | None = None
    outer_radius: float | None = None

    def _check(self) -> None:
        self._positive("fx", "fy")
        if not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"key 'alpha' must be in [0, 1], got {self.alpha!r}")
        if self.xi <= -1.0:
            raise ValueError(f"key 'xi' must be > -1, got {self.xi!r}")

    @property
    def _w2(self) -> float:
        a, xi = self.alpha, self.xi
        w1 = (1.0 - a) / a if a > 0.5 else a / (1.0 - a)
        return (w1 + xi) / math.sqrt(2.0 * w1 * xi + xi * xi + 1.0)

    def _rays_block(self, uv: FloatArray) -> FloatArray:
        u, v = uv[:, 0], uv[:, 1]
        a, xi = self.alpha, self.xi
        mx = (u - self.cx) / self.fx
        my = (v - self.cy) / self.fy
        r2 = mx * mx + my * my
        with np.errstate(invalid="ignore", divide="ignore"):
            disc = 1.0 - (2.0 * a - 1.0) * r2
            mz = (1.0 - a * a * r2) / (a * np.sqrt(disc) + (1.0 - a))
            mz2 = mz * mz
            disc2 = mz2 + (1.0 - xi * xi) * r2
            s = (mz * xi + np.sqrt(disc2)) / (mz2 + r2)
            rays = unit_rows(s * mx, s * my, s * mz - xi)
            ok = (disc >= 0) & (disc2 >= 0) & np.isfinite(rays[:, 0])
            ok &= rays[:, 2] > -self._w2
        ok &= radius_ok(u, v, self.cx, self.cy, self.inner_radius, self.outer_radius)
        rays[~ok] = np.nan
        return rays

    def _pixels_block(self, rays: FloatArray) -> FloatArray:
        x, y, z = unit_input_rays(rays)
        a, xi = self.alpha, self.xi
        with np.errstate(invalid="ignore", divide="ignore"):
            k = xi + z  # d1 = 1 for unit rays
            d2 = np.sqrt(x * x + y * y + k * k)
            den = a * d2 + (1.0 - a) * k
            ok = (z > -self._w2) & (den > 0)
            return _finish_pixels(self, x / den, y / den, ok)
