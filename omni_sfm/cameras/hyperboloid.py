"""The paper's catadioptric camera: hyperboloid mirror + perspective camera (METHOD.md §1)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from omni_sfm.cameras.base import CameraModel, as_points
from omni_sfm.geometry import FloatArray


@dataclass(frozen=True, kw_only=True)
class HyperboloidCamera(CameraModel):
    """Hyperboloid mirror ``(X^2+Y^2)/alpha^2 - (Z+gamma)^2/beta^2 = -1`` seen by a pinhole.

    The mirror's outer focus is the origin (the single viewpoint), the lens centre is at
    ``(0, 0, -2 gamma)`` and the image plane at focal length ``f`` along +Z, so the mirror axis
    is the camera's +Z and the image centre sees -Z (the camera's own reflection).
    ``f, alpha, beta`` and the pixel pitch ``px, py`` share one length unit.
    ``inner_radius``/``outer_radius`` (px around ``(cx, cy)``) bound the valid annulus; None
    means no bound beyond the mirror's own geometry.
    """

    model = "hyperboloid"
    cx: float
    cy: float
    px: float
    py: float
    f: float
    alpha: float
    beta: float
    inner_radius: float | None = None
    outer_radius: float | None = None

    @property
    def gamma(self) -> float:
        return math.sqrt(self.alpha**2 + self.beta**2)

    @property
    def unified_xi(self) -> float:
        """``xi`` of the equivalent unified (sphere) model: ``2e/(1+e^2)``, ``e = gamma/beta``."""
        e = self.gamma / self.beta
        return 2 * e / (1 + e * e)

    def _radius_ok(self, uv: FloatArray) -> np.ndarray:
        r = np.hypot(uv[:, 0] - self.cx, uv[:, 1] - self.cy)
        ok = np.ones(len(uv), dtype=bool)
        if self.inner_radius is not None:
            ok &= r >= self.inner_radius
        if self.outer_radius is not None:
            ok &= r <= self.outer_radius
        return ok

    def rays_from_pixels(self, uv: ArrayLike) -> FloatArray:
        """Eq. (1)-(2) of the paper, normalised; NaN outside the mask or beyond the mirror."""
        p = as_points(uv, 2, "uv")
        x = (p[:, 0] - self.cx) * self.px
        y = (p[:, 1] - self.cy) * self.py
        rho2 = x * x + y * y
        a2, b2, g, f = self.alpha**2, self.beta**2, self.gamma, self.f
        den = a2 * f * f - b2 * rho2
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = a2 * (f * g + self.beta * np.sqrt(rho2 + f * f)) / den
            r = np.stack([lam * x, lam * y, lam * f - 2.0 * g], axis=1)
            r /= np.linalg.norm(r, axis=1, keepdims=True)
        ok = (den > 0) & self._radius_ok(p) & np.isfinite(p).all(axis=1)
        r[~ok] = np.nan
        return r

    def pixels_from_rays(self, rays: ArrayLike) -> FloatArray:
        """Mirror point ``s d`` with ``s = alpha^2 / (beta - gamma d_z)`` (focal polar form of
        the mirror's sheet around the origin), then the pinhole through ``(0, 0, -2 gamma)``."""
        d = as_points(rays, 3, "rays")
        with np.errstate(divide="ignore", invalid="ignore"):
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
            den = self.beta - self.gamma * d[:, 2]
            s = self.alpha**2 / den
            zc = s * d[:, 2] + 2.0 * self.gamma
            x = self.f * s * d[:, 0] / zc
            y = self.f * s * d[:, 1] / zc
            uv = np.stack([x / self.px + self.cx, y / self.py + self.cy], axis=1)
        ok = (den > 0) & (zc > 0) & np.isfinite(uv).all(axis=1)
        ok &= self._radius_ok(np.where(ok[:, None], uv, 0.0))
        # beyond the mirror's own image (eq. 2's denominator) nothing is imaged
        rho2 = ((uv[:, 0] - self.cx) * self.px) ** 2 + ((uv[:, 1] - self.cy) * self.py) ** 2
        ok &= self.alpha**2 * self.f**2 - self.beta**2 * np.where(ok, rho2, 0.0) > 0
        uv[~ok] = np.nan
        return uv
