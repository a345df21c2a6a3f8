"""The paper's catadioptric camera: hyperboloid mirror + perspective camera (docs/method.md §1)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omni_sfm.cameras.base import (
    MASK_TOL,
    CameraModel,
    ColmapExport,
    radius_ok,
    unit_input_rays,
    unit_rows,
)
from omni_sfm.geometry import FloatArray


@dataclass(frozen=True, kw_only=True)
class HyperboloidCamera(CameraModel):
    """Hyperboloid mirror ``(X^2+Y^2)/alpha^2 - (Z+gamma)^2/beta^2 = -1`` seen by a pinhole.

    The mirror's outer focus is the origin (the single viewpoint), the lens centre is at
    ``(0, 0, -2 gamma)`` and the image plane at focal length ``f`` along +Z, so the mirror axis
    is the camera's +Z and the image centre sees -Z (the camera's own reflection). Camera frame:
    ``x`` along image ``u``, ``y`` along image ``v``, ``z`` the mirror axis (up, towards the
    mirror). ``f, alpha, beta`` and the pixel pitch ``px, py`` share one length unit.
    ``inner_radius``/``outer_radius`` (px around ``(cx, cy)``) bound the valid annulus; None
    means no bound beyond the mirror's own geometry (image radius ``< f alpha / beta``).

    Pixel -> ray is eq. (1)-(2); ray -> pixel intersects the ray with the mirror (focal polar
    form ``s = alpha^2 / (beta - gamma d_z)``) and projects through the lens. Equivalent form:
    ``x = F d_x / (xi - d_z)``, ``F = f alpha^2 / (gamma^2 + beta^2)``,
    ``xi = 2 gamma beta / (gamma^2 + beta^2)``: the unified model with ``d_z`` negated.
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

    def _check(self) -> None:
        self._positive("px", "py", "f", "alpha", "beta")

    @property
    def gamma(self) -> float:
        return math.sqrt(self.alpha**2 + self.beta**2)

    @property
    def unified_xi(self) -> float:
        """``xi`` of the equivalent unified (sphere) model: ``2e/(1+e^2)``, ``e = gamma/beta``."""
        e = self.gamma / self.beta
        return 2 * e / (1 + e * e)

    @property
    def unified_focal(self) -> float:
        """``F = f alpha^2 / (gamma^2 + beta^2)`` of the equivalent unified model (length unit)."""
        return self.f * self.alpha**2 / (self.gamma**2 + self.beta**2)

    def _rays_block(self, uv: FloatArray) -> FloatArray:
        """Eq. (1)-(2) of the paper, normalised; NaN outside the mask or beyond the mirror."""
        u, v = uv[:, 0], uv[:, 1]
        x = u - self.cx
        x *= self.px
        y = v - self.cy
        y *= self.py
        rho2 = x * x
        rho2 += y * y
        a2, b2, g, f = self.alpha**2, self.beta**2, self.gamma, self.f
        den = rho2 * (-b2)
        den += a2 * f * f
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = rho2 + f * f
            np.sqrt(lam, out=lam)
            lam *= self.beta
            lam += f * g
            lam *= a2
            lam /= den
            z = lam * f
            z -= 2.0 * g
            x *= lam
            y *= lam
            r = unit_rows(x, y, z)
        ok = (den > 0) & radius_ok(u, v, self.cx, self.cy, self.inner_radius, self.outer_radius)
        r[~ok] = np.nan
        return r

    def _pixels_block(self, rays: FloatArray) -> FloatArray:
        """Mirror point ``s d`` with ``s = alpha^2 / (beta - gamma d_z)`` (focal polar form of
        the mirror's sheet around the origin), then the pinhole through ``(0, 0, -2 gamma)``."""
        dx, dy, dz = unit_input_rays(rays)
        g = self.gamma
        with np.errstate(divide="ignore", invalid="ignore"):
            den = self.beta - g * dz
            s = self.alpha**2 / den
            zc = s * dz
            zc += 2.0 * g
            k = self.f * s / zc
            uv = np.empty((len(rays), 2))
            np.multiply(dx, k / self.px, out=uv[:, 0])
            uv[:, 0] += self.cx
            np.multiply(dy, k / self.py, out=uv[:, 1])
            uv[:, 1] += self.cy
            # beyond the mirror's own image (eq. 2's denominator) nothing is imaged
            rho2 = (k * dx) ** 2 + (k * dy) ** 2
            ok = (den > 0) & (zc > 0) & (self.alpha**2 * self.f**2 - self.beta**2 * rho2 > 0)
        ok &= radius_ok(uv[:, 0], uv[:, 1], self.cx, self.cy, self.inner_radius, self.outer_radius,
                        MASK_TOL)
        uv[~ok] = np.nan
        return uv

    def colmap_export(self) -> ColmapExport:
        """COLMAP ``EUCM`` with ``beta = 1`` (exact), in a frame rotated 180 deg about ``y`` and
        with the image mirrored left-right (the mirror makes our map a reflection)."""
        import pycolmap

        xi = self.unified_xi
        fx = self.unified_focal / self.px / (1.0 + xi)
        fy = self.unified_focal / self.py / (1.0 + xi)
        cam = pycolmap.Camera(
            model="EUCM", width=self.width, height=self.height,
            params=[fx, fy, (self.width - 1 - self.cx) + 0.5, self.cy + 0.5, xi / (1.0 + xi), 1.0],
        )
        return ColmapExport(
            camera=cam, colmap_cam_from_cam=np.diag([-1.0, 1.0, -1.0]), flip_u=True,
            width=self.width, height=self.height,
        )
