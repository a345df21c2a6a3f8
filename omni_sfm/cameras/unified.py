"""Mei's unified (sphere) model with radial-tangential distortion, exactly as ``cv2.omnidir``."""

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
    unit_rows,
)
from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray

# Newton on the 2-D radtan distortion: stop when every residual of a block is below this
# (normalised image units, ~1e-12 px at f = 1000), give up after NEWTON_MAX steps.
NEWTON_TOL = 1e-14
NEWTON_MAX = 10
# a pixel is valid only if its undistorted point reproduces it to this (normalised units)
RESIDUAL_OK = 1e-10


@dataclass(frozen=True, kw_only=True)
class UnifiedCamera(CameraModel):
    """Unified (sphere) model of Geyer / Mei, identical to ``cv2.omnidir`` and Kalibr's ``omni``
    camera with ``radtan`` distortion. Camera frame: OpenCV's (x right, y down, z forward).

    Ray -> pixel: unit ray ``(x, y, z)``; ``m = (x, y) / (z + xi)``; radtan distortion with
    ``r^2 = |m|^2``: ``m_d = m (1 + k1 r^2 + k2 r^4) + (2 p1 m_x m_y + p2 (r^2 + 2 m_x^2),
    p1 (r^2 + 2 m_y^2) + 2 p2 m_x m_y)``; ``u = fx m_dx + skew m_dy + cx``, ``v = fy m_dy + cy``
    (``K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]``). Pixel -> ray inverts the distortion by
    Newton's method and lifts ``m`` onto the unit sphere.

    Valid: rays with ``z > -w`` (``w = xi`` for ``xi <= 1``, ``1/xi`` otherwise; beyond it the
    projection folds over), undistorted radius inside the monotone part of the radial
    polynomial, and the optional radius mask (px around ``(cx, cy)``). ``xi = 0`` is the
    ordinary pinhole camera with OpenCV's ``k1 k2 p1 p2`` distortion.
    """

    model = "unified"
    fx: float
    fy: float
    cx: float
    cy: float
    xi: float
    skew: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    inner_radius: float | None = None
    outer_radius: float | None = None

    def _check(self) -> None:
        self._positive("fx", "fy")
        if self.xi < 0:
            raise ValueError(f"key 'xi' must be >= 0, got {self.xi!r}")

    @property
    def has_distortion(self) -> bool:
        return any(c != 0.0 for c in (self.k1, self.k2, self.p1, self.p2))

    @property
    def _w(self) -> float:
        return self.xi if self.xi <= 1.0 else 1.0 / self.xi

    def _radial(self, r: FloatArray) -> FloatArray:
        r2 = r * r
        return r * (1.0 + r2 * (self.k1 + r2 * self.k2))

    def _dradial(self, r: FloatArray) -> FloatArray:
        r2 = r * r
        return 1.0 + r2 * (3.0 * self.k1 + r2 * 5.0 * self.k2)

    @cached_property
    def r_max(self) -> float:
        """Largest undistorted radius of the model's domain (``inf`` if unbounded):
        ``1/sqrt(xi^2 - 1)`` for ``xi > 1``; with distortion also the end of the radial
        polynomial's monotone part and the radius whose distorted image lies 4x as far from the
        principal point as the farthest image corner (the distortion is inverted up to there)."""
        lim = math.inf if self.xi <= 1.0 else 1.0 / math.sqrt(self.xi**2 - 1.0)
        if not self.has_distortion:
            return lim
        hi = min(lim, 1e3)
        mono = first_nonincreasing(self._dradial, hi) if self.k1 or self.k2 else hi
        corners = np.array([[0, 0], [self.width - 1, 0], [0, self.height - 1],
                            [self.width - 1, self.height - 1]], dtype=np.float64)
        yd = (corners[:, 1] - self.cy) / self.fy
        xd = (corners[:, 0] - self.cx - self.skew * yd) / self.fx
        need = 4.0 * float(np.hypot(xd, yd).max()) + 1.0
        r = 1.0 / 16.0
        while r < mono and self._radial(np.array([r]))[0] < need:
            r *= 2.0
        return min(r, mono)

    @cached_property
    def _radial_inverse(self) -> MonotoneInverse:
        # with tangential terms the 2-D Newton refines the table's start point anyway
        steps = 2 if self.p1 == 0.0 and self.p2 == 0.0 else 0
        return MonotoneInverse(self._radial, self._dradial, self.r_max, newton_steps=steps)

    def _distort(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        r2 = x * x + y * y
        rad = 1.0 + r2 * (self.k1 + r2 * self.k2)
        xy2 = 2.0 * x * y
        xd = x * rad + self.p1 * xy2 + self.p2 * (r2 + 2.0 * x * x)
        yd = y * rad + self.p1 * (r2 + 2.0 * y * y) + self.p2 * xy2
        return xd, yd

    def _undistort(self, xd: FloatArray, yd: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Newton's method on the radtan map, started from the exact radial-only inverse;
        NaN where it does not reproduce ``(xd, yd)`` or leaves the monotone domain."""
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        with np.errstate(divide="ignore", invalid="ignore"):
            rd = np.sqrt(xd * xd + yd * yd)
            s = self._radial_inverse(rd, clamp=True) / rd
            s[rd == 0] = 1.0
            x, y = xd * s, yd * s
            for _ in range(NEWTON_MAX):
                r2 = x * x + y * y
                rad = 1.0 + r2 * (k1 + r2 * k2)
                xy = x * y
                ex = x * rad + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x) - xd
                ey = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy - yd
                err = np.abs(ex) + np.abs(ey)
                if not np.nanmax(err, initial=0.0) > NEWTON_TOL:
                    break
                q2 = 2.0 * (k1 + 2.0 * k2 * r2)
                jxx = rad + q2 * x * x + 2.0 * p1 * y + 6.0 * p2 * x
                jyy = rad + q2 * y * y + 6.0 * p1 * y + 2.0 * p2 * x
                jxy = q2 * xy + 2.0 * p1 * x + 2.0 * p2 * y
                det = jxx * jyy - jxy * jxy
                x -= (jyy * ex - jxy * ey) / det
                y -= (jxx * ey - jxy * ex) / det
            else:
                ex, ey = self._distort(x, y)
                err = np.abs(ex - xd) + np.abs(ey - yd)
                r2 = x * x + y * y
            ok = (err < RESIDUAL_OK) & (r2 < self.r_max**2)
        x[~ok] = np.nan
        y[~ok] = np.nan
        return x, y

    def _rays_block(self, uv: FloatArray) -> FloatArray:
        u, v = uv[:, 0], uv[:, 1]
        my = v - self.cy
        my /= self.fy
        mx = u - self.cx
        if self.skew != 0.0:
            mx -= self.skew * my
        mx /= self.fx
        if self.has_distortion:
            mx, my = self._undistort(mx, my)
        r2 = mx * mx + my * my
        with np.errstate(invalid="ignore"):
            disc = r2 * (1.0 - self.xi**2)
            disc += 1.0
            ok = disc >= 0
            if self.xi > 1.0:
                ok &= r2 < 1.0 / (self.xi**2 - 1.0)
            k = np.sqrt(disc)
            k += self.xi
            k /= r2 + 1.0
            z = k - self.xi
            rays = unit_rows(k * mx, k * my, z)
        ok &= radius_ok(u, v, self.cx, self.cy, self.inner_radius, self.outer_radius)
        rays[~ok] = np.nan
        return rays

    def _pixels_block(self, rays: FloatArray) -> FloatArray:
        x, y, z = unit_input_rays(rays)
        with np.errstate(divide="ignore", invalid="ignore"):
            ok = z > -self._w
            den = z + self.xi
            mx = x / den
            my = y / den
            if self.has_distortion:
                ok &= mx * mx + my * my < self.r_max**2
                mx, my = self._distort(mx, my)
            uv = np.empty((len(rays), 2))
            np.multiply(mx, self.fx, out=uv[:, 0])
            if self.skew != 0.0:
                uv[:, 0] += self.skew * my
            uv[:, 0] += self.cx
            np.multiply(my, self.fy, out=uv[:, 1])
            uv[:, 1] += self.cy
        ok &= radius_ok(uv[:, 0], uv[:, 1], self.cx, self.cy, self.inner_radius, self.outer_radius,
                        MASK_TOL)
        uv[~ok] = np.nan
        return uv

    def colmap_export(self) -> ColmapExport:
        """No distortion: ``EUCM`` with ``alpha = xi / (1 + xi)``, ``beta = 1``, focal lengths
        divided by ``1 + xi`` (``PINHOLE`` if ``xi = 0``); ``xi = 0`` with distortion:
        ``OPENCV``. Same camera frame, pixels shifted by 0.5. Otherwise OmniSfmError."""
        import pycolmap

        if self.skew != 0.0:
            raise OmniSfmError(
                f"no exact COLMAP model for a unified camera with skew = {self.skew}"
            )
        c = [self.cx + 0.5, self.cy + 0.5]
        if not self.has_distortion and self.xi == 0.0:
            model, params = "PINHOLE", [self.fx, self.fy, *c]
        elif not self.has_distortion:
            s = 1.0 / (1.0 + self.xi)
            model, params = "EUCM", [self.fx * s, self.fy * s, *c, self.xi * s, 1.0]
        elif self.xi == 0.0:
            model = "OPENCV"
            params = [self.fx, self.fy, *c, self.k1, self.k2, self.p1, self.p2]
        else:
            raise OmniSfmError(
                "no exact COLMAP model for a unified camera with xi != 0 and radtan distortion "
                f"(xi = {self.xi}, k1 k2 p1 p2 = {self.k1} {self.k2} {self.p1} {self.p2})"
            )
        cam = pycolmap.Camera(model=model, width=self.width, height=self.height, params=params)
        return colmap_export_plain(cam, self.width, self.height)
