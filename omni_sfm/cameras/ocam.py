"""Scaramuzza's OCamCalib polynomial model (``calib_results.txt``), exact in both directions."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from omni_sfm.cameras.base import (
    MASK_TOL,
    CameraModel,
    MonotoneInverse,
    first_nonincreasing,
    polyval_asc,
    radius_ok,
    unit_input_rays,
    unit_rows,
)
from omni_sfm.geometry import FloatArray

# Newton steps after the table's start point (error ~1e-7 -> ~1e-14 -> rounding)
NEWTON_STEPS = 2


@dataclass(frozen=True, kw_only=True)
class OCamCamera(CameraModel):
    """OCamCalib (Scaramuzza 2006) omnidirectional camera. Camera frame: OpenCV's (x right =
    image ``u``, y down = image ``v``, z forward along the optical axis).

    OCamCalib works in (row, column) order: its "x" is the row and "y" the column, and its
    camera frame (x down, y right, z backwards) looks along -z. In our fields and pixels:
    ``cx`` is the column and ``cy`` the row of the distortion centre (OpenCV pixels; the loader
    converts calib_results.txt, see docs/cameras.md), and for a pixel ``(u, v)``:

        [v - cy, u - cx] = [[c, d], [e, 1]] @ [xp, yp],  r = |(xp, yp)|,  zp = pol(r)
        ray ~ (yp, xp, -zp)        (OCamCalib's cam2world ray (xp, yp, zp), reordered)

    with ``pol(r) = pol[0] + pol[1] r + ...`` (``ss`` in OCamCalib, ``pol[0] < 0``).
    Ray -> pixel solves ``pol`` exactly (table start + Newton on the ray's angle) instead of
    OCamCalib's approximate ``invpol`` fit; ``invpol`` is kept only to write the file back.
    Valid: ``r`` up to the image corners and within the monotone part of the angle
    ``atan2(r, -pol(r))``, and the optional radius mask (px around ``(cx, cy)``).
    """

    model = "ocam"
    cx: float
    cy: float
    c: float = 1.0
    d: float = 0.0
    e: float = 0.0
    pol: tuple[float, ...]
    invpol: tuple[float, ...] = ()
    inner_radius: float | None = None
    outer_radius: float | None = None

    def _check(self) -> None:
        if not isinstance(self.pol, tuple) or len(self.pol) < 2:
            raise ValueError(f"key 'pol' must list at least 2 coefficients, got {self.pol!r}")
        if not self.pol[0] < 0:
            raise ValueError(
                f"key 'pol' must start with a negative coefficient (OCamCalib's convention, "
                f"the optical axis is -z), got pol[0] = {self.pol[0]!r}"
            )
        if self.c - self.d * self.e == 0:
            raise ValueError("keys 'c', 'd', 'e': the affine matrix [[c, d], [e, 1]] is singular")

    def _metric(self, u: FloatArray, v: FloatArray) -> tuple[FloatArray, FloatArray]:
        inv = 1.0 / (self.c - self.d * self.e)
        du = u - self.cx
        dv = v - self.cy
        xp = (dv - self.d * du) * inv
        yp = (self.c * du - self.e * dv) * inv
        return xp, yp

    def _angle(self, r: FloatArray) -> FloatArray:
        return np.arctan2(r, -polyval_asc(self.pol, r))

    def _dangle(self, r: FloatArray) -> FloatArray:
        p = polyval_asc(self.pol, r)
        dp = polyval_asc(tuple(i * a for i, a in enumerate(self.pol))[1:] or (0.0,), r)
        return (r * dp - p) / (r * r + p * p)

    @cached_property
    def r_max(self) -> float:
        """Largest valid metric radius: the image corners, or where the angle stops growing."""
        w, h = self.width - 1.0, self.height - 1.0
        xp, yp = self._metric(np.array([0.0, w, 0.0, w]), np.array([0.0, 0.0, h, h]))
        r_img = float(np.hypot(xp, yp).max())
        return first_nonincreasing(self._dangle, r_img)

    @cached_property
    def theta_max(self) -> float:
        """Largest angle of a valid ray from the optical axis (rad)."""
        return float(self._angle(np.array([self.r_max]))[0])

    @cached_property
    def _inverse(self) -> MonotoneInverse:
        # start points only: _pixels_block polishes with Newton on a trig-free equation
        return MonotoneInverse(self._angle, self._dangle, self.r_max, newton_steps=0)

    @cached_property
    def _dpol(self) -> tuple[float, ...]:
        return tuple(i * a for i, a in enumerate(self.pol))[1:]

    def _rays_block(self, uv: FloatArray) -> FloatArray:
        u, v = uv[:, 0], uv[:, 1]
        xp, yp = self._metric(u, v)
        r = np.hypot(xp, yp)
        zp = polyval_asc(self.pol, r)
        rays = unit_rows(yp, xp, -zp)
        with np.errstate(invalid="ignore"):
            ok = r <= self.r_max
        ok &= radius_ok(u, v, self.cx, self.cy, self.inner_radius, self.outer_radius)
        rays[~ok] = np.nan
        return rays

    def _pixels_block(self, rays: FloatArray) -> FloatArray:
        x, y, z = unit_input_rays(rays)
        with np.errstate(invalid="ignore", divide="ignore"):
            n = np.sqrt(x * x + y * y)
            r = self._inverse(np.arctan2(n, z))
            # the ray's pixel radius solves h(r) = n pol(r) + z r = 0, h' > 0 in the domain
            for _ in range(NEWTON_STEPS):
                h = polyval_asc(self.pol, r)
                h *= n
                h += z * r
                dh = polyval_asc(self._dpol, r)
                dh *= n
                dh += z
                r -= h / dh
            r[r > self.r_max] = np.nan
            s = r / n
            s[n == 0] = 0.0
            xp = y * s
            yp = x * s
            uv = np.empty((len(rays), 2))
            uv[:, 0] = self.e * xp + yp + self.cx
            uv[:, 1] = self.c * xp + self.d * yp + self.cy
        ok = np.isfinite(r)
        ok &= radius_ok(uv[:, 0], uv[:, 1], self.cx, self.cy, self.inner_radius, self.outer_radius,
                        MASK_TOL)
        uv[~ok] = np.nan
        return uv
