"""Mei's unified (sphere) model with radial-tangential distortion, exactly as ``cv2.omnidir``."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

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
from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray

# Newton on the 2-D radtan distortion: stop when every residual of a block is below this
# (normalised image units, ~1e-12 px at f = 1000), give up after NEWTON_MAX steps.
NEWTON_TOL = 1e-14
NEWTON_MAX = 10
# steps taken on a whole block before the points not yet converged continue on their own
NEWTON_FAST = 3
# entries of the start table of the radtan inverse (see UnifiedCamera._start_table)
START_TABLE = 8192
# nodes along the image's longer side in the start correction (UnifiedCamera._start_correction)
START_GRID = 128

# a pixel is valid only if its undistorted point reproduces it to this (normalised units)
RESIDUAL_OK = 1e-10


def _absmax(a: FloatArray) -> float:
    """``max |a|`` ignoring NaN (0 for an empty or all-NaN array), without a temporary."""
    return max(float(np.fmax.reduce(a, initial=0.0)), -float(np.fmin.reduce(a, initial=0.0)))


class _Correction(NamedTuple):
    """Nearest-node table over the normalised image plane, see UnifiedCamera._start_correction."""

    inv_step: float
    offset_x: float
    offset_y: float
    nx: int
    ny: int
    dxy: np.ndarray


class _Buffers:
    """Work arrays ``(n,)`` of the radtan residual (reused across Newton steps)."""

    __slots__ = ("xx", "yy", "r2", "a", "t", "ex", "ey")

    def __init__(self, n: int) -> None:
        self.xx, self.yy, self.r2, self.a, self.t, self.ex, self.ey = np.empty((7, n))


class _Jacobian:
    """The radtan Jacobian ``[[xx, xy], [xy, yy]]`` and its ``det``, ``(n,)`` each; ``q`` is
    scratch."""

    __slots__ = ("xx", "yy", "xy", "det", "q")

    def __init__(self, n: int) -> None:
        self.xx, self.yy, self.xy, self.det, self.q = np.empty((5, n))


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
        """Exact inverse of the radial part ``r -> r (1 + k1 r^2 + k2 r^4)`` on ``[0, r_max]``."""
        return MonotoneInverse(self._radial, self._dradial, self.r_max, newton_steps=2)

    @cached_property
    def _start_table(self) -> tuple[float, FloatArray, FloatArray]:
        """Start of the radtan inverse with tangential terms: ``(x, y) = s (xd, yd)`` where
        ``s = r / r_d`` is the radial part's exact inverse ratio, tabulated over ``r_d^2`` (no
        square root, no division, ``s = 1`` at the centre) for linear interpolation:
        ``(1 / step, s_i, s_(i+1) - s_i)``; beyond the table ``s`` stays at its last value."""
        inv = self._radial_inverse
        rho = np.linspace(0.0, inv.y1**2, START_TABLE + 1)
        rd = np.sqrt(rho)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = inv(rd) / rd
        s[0] = 1.0  # d/dr of the radial map is 1 at r = 0
        ds = np.append(np.diff(s), 0.0)
        return START_TABLE / float(rho[-1]), s, ds

    def _distort(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        r2 = x * x + y * y
        rad = 1.0 + r2 * (self.k1 + r2 * self.k2)
        xy2 = 2.0 * x * y
        xd = x * rad + self.p1 * xy2 + self.p2 * (r2 + 2.0 * x * x)
        yd = y * rad + self.p1 * (r2 + 2.0 * y * y) + self.p2 * xy2
        return xd, yd

    @cached_property
    def _start_correction(self) -> _Correction:
        """Nearest-node table of ``(x, y) - s (xd, yd)``: what the tangential terms move the
        undistorted point away from the radial start (see :meth:`_start_table`), on a grid of
        ``START_GRID`` nodes along the longer side of the image's normalised (distorted)
        rectangle, with a border of zeros that catches every point off the grid."""
        u = np.array([-0.5, self.width - 0.5, -0.5, self.width - 0.5])
        v = np.array([-0.5, -0.5, self.height - 0.5, self.height - 0.5])
        yc = (v - self.cy) / self.fy
        xc = (u - self.cx - self.skew * yc) / self.fx
        lo = np.array([xc.min(), yc.min()])
        step = float((np.array([xc.max(), yc.max()]) - lo).max()) / START_GRID
        nx, ny = (np.ceil((np.array([xc.max(), yc.max()]) - lo) / step).astype(int) + 1)
        gy, gx = np.mgrid[0:ny, 0:nx]
        xd = (lo[0] + step * gx.ravel()).astype(np.float64)
        yd = (lo[1] + step * gy.ravel()).astype(np.float64)
        x0, y0, _, _ = self._undistort(xd, yd, iterate=False, correct=False)
        x, y, _, ok = self._undistort(xd, yd, correct=False)
        dxy = np.zeros((ny + 2, nx + 2), dtype=np.complex128)  # (dx, dy) as dx + i dy
        dxy[1:-1, 1:-1] = np.where(ok, (x - x0) + 1j * (y - y0), 0.0).reshape(ny, nx)
        # index = floor((xd - lo) / step + 1.5): the nearest node, shifted by the border
        return _Correction(inv_step=1.0 / step, offset_x=1.5 - lo[0] / step,
                           offset_y=1.5 - lo[1] / step, nx=int(nx) + 2, ny=int(ny) + 2,
                           dxy=dxy.ravel())

    def _undistort(
        self, xd: FloatArray, yd: FloatArray, *, iterate: bool = True, correct: bool = True
    ) -> tuple[FloatArray, FloatArray, FloatArray, np.ndarray]:
        """Invert the radtan map: ``(x, y, r^2, ok)`` with ``distort(x, y) = (xd, yd)``.

        Start: the exact inverse of the radial part (``_radial_inverse`` without tangential
        terms, else ``_start_table``) plus, with ``correct``, the tangential terms' shift at the
        nearest node of ``_start_correction`` (start error ~1e-4 instead of ~1e-2). Then Newton
        steps on the 2-D map on the whole block, each followed by the residual, until every
        residual is below ``NEWTON_TOL`` (two steps from the corrected start) or after
        ``NEWTON_FAST`` steps, the last of which reuses the previous Jacobian (converges like
        Newton this close to the root). Points still above it continue with full Newton steps on
        their own, up to ``NEWTON_MAX`` steps. ``ok``: the solution reproduces ``(xd, yd)`` to
        ``RESIDUAL_OK`` and lies inside the domain ``r < r_max``; ``x, y, r^2`` are meaningless
        where it is False. ``iterate=False`` returns the start point (and no r^2 / ok)."""
        n = len(xd)
        b, j = _Buffers(n), _Jacobian(n)
        err = np.empty(n)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = self._start_scale(xd, yd, b)
            x = np.multiply(xd, s)
            y = np.multiply(yd, s, out=s)
            if correct and (self.p1 != 0.0 or self.p2 != 0.0):
                self._correct_start(x, y, xd, yd, b)
            if not iterate:  # the start point only (to build _start_correction)
                return x, y, b.r2, np.ones(n, dtype=bool)
            steps = self._newton_fast(x, y, xd, yd, b, j)
            r2 = self._newton_rest(x, y, xd, yd, b, err, steps)
            ok = err < RESIDUAL_OK
            ok &= r2 < self.r_max**2
        return x, y, r2, ok

    def _start_scale(self, xd: FloatArray, yd: FloatArray, b: _Buffers) -> FloatArray:
        """The start's scale ``s`` with ``(x, y) = s (xd, yd)`` from the radial part's inverse."""
        if self.p1 == 0.0 and self.p2 == 0.0:
            # radial only: the radial inverse is the exact answer
            rd = np.multiply(xd, xd)
            np.multiply(yd, yd, out=b.t)
            rd += b.t
            np.sqrt(rd, out=rd)
            s = self._radial_inverse(rd, clamp=True)
            s /= rd
            s[rd == 0] = 1.0
            return s
        scale, table, dtable = self._start_table
        rho = np.multiply(xd, xd)
        np.multiply(yd, yd, out=b.t)
        rho += b.t
        rho *= scale
        far = np.flatnonzero(rho > START_TABLE)
        np.fmin(rho, START_TABLE, out=rho)  # also NaN -> the table's end
        i = rho.astype(np.intp)
        rho -= i
        s = table[i]
        d = dtable[i]
        d *= rho
        s += d
        if far.size:  # beyond the radial domain's image: start at radius r_max
            s[far] = self.r_max / np.hypot(xd[far], yd[far])
        return s

    def _correct_start(
        self, x: FloatArray, y: FloatArray, xd: FloatArray, yd: FloatArray, b: _Buffers
    ) -> None:
        """Add to ``(x, y)`` the tangential terms' shift at the nearest correction-grid node."""
        # add the tangential terms' effect at the nearest node of a grid over the
        # image: the start is then good to ~1e-4 and two Newton steps finish
        c = self._start_correction
        tx = np.multiply(xd, c.inv_step, out=b.t)
        tx += c.offset_x
        np.clip(tx, 0.0, c.nx - 1, out=tx)
        ty = np.multiply(yd, c.inv_step, out=b.a)
        ty += c.offset_y
        np.clip(ty, 0.0, c.ny - 1, out=ty)
        np.floor(ty, out=ty)
        ty *= c.nx
        ty += tx
        # NaN gives a nonsense index, clipped into the table: x stays NaN anyway
        d = np.take(c.dxy, ty.astype(np.intp), mode="clip")
        x += d.real
        y += d.imag

    def _newton_fast(
        self, x: FloatArray, y: FloatArray, xd: FloatArray, yd: FloatArray, b: _Buffers,
        j: _Jacobian,
    ) -> int:
        """Newton steps on the whole block, in place, up to ``NEWTON_FAST``; the steps taken."""
        steps = 0
        while True:
            self._residual(x, y, xd, yd, b)
            # every |ex| + |ey| <= NEWTON_TOL (a bound from four reductions, NaN ignored)
            if not _absmax(b.ex) + _absmax(b.ey) > NEWTON_TOL or steps == NEWTON_FAST:
                break
            if steps < NEWTON_FAST - 1:
                self._jacobian(x, y, b, j)
            self._step(x, y, b, j)  # the last fast step reuses the previous Jacobian
            steps += 1
        return steps

    def _newton_rest(
        self, x: FloatArray, y: FloatArray, xd: FloatArray, yd: FloatArray, b: _Buffers,
        err: FloatArray, steps: int,
    ) -> FloatArray:
        """Full Newton steps on the points not converged yet; fills ``err``, returns ``r^2``."""
        np.abs(b.ex, out=err)
        np.abs(b.ey, out=b.t)
        err += b.t
        r2 = b.r2
        idx = np.flatnonzero(err > NEWTON_TOL)
        if idx.size:
            # the few points not converged yet (far from the table's start, near the
            # fold): full Newton steps on these alone
            xs, ys, xds, yds = x[idx], y[idx], xd[idx], yd[idx]
            bs, js = _Buffers(len(idx)), _Jacobian(len(idx))
            errs = np.empty(len(idx))
            self._residual(xs, ys, xds, yds, bs)
            for _ in range(steps, NEWTON_MAX):
                self._jacobian(xs, ys, bs, js)
                self._step(xs, ys, bs, js)
                self._residual(xs, ys, xds, yds, bs)
                np.abs(bs.ex, out=errs)
                np.abs(bs.ey, out=bs.t)
                errs += bs.t
                if not np.fmax.reduce(errs, initial=0.0) > NEWTON_TOL:
                    break
            x[idx], y[idx], err[idx], r2[idx] = xs, ys, errs, bs.r2
        return r2

    def _residual(
        self, x: FloatArray, y: FloatArray, xd: FloatArray, yd: FloatArray, b: _Buffers
    ) -> None:
        """Radtan residual ``distort(x, y) - (xd, yd)`` into ``b.ex, b.ey``, in place, keeping
        ``b.xx = x^2, b.yy = y^2, b.r2 = r^2`` and ``b.a = rad + 2 (p1 y + p2 x)`` for the
        Jacobian. With ``L = p1 y + p2 x`` the tangential terms are ``(p2 r^2 + 2 x L,
        p1 r^2 + 2 y L)``, so ``e = m (rad + 2 L) + (p2, p1) r^2 - m_d`` (19 array operations)."""
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        np.multiply(x, x, out=b.xx)
        np.multiply(y, y, out=b.yy)
        np.add(b.xx, b.yy, out=b.r2)
        a, t = b.a, b.t
        np.multiply(b.r2, k2, out=a)
        a += k1
        a *= b.r2
        a += 1.0
        np.multiply(y, 2.0 * p1, out=t)
        np.multiply(x, 2.0 * p2, out=b.ex)
        t += b.ex
        a += t
        np.multiply(x, a, out=b.ex)
        np.multiply(b.r2, p2, out=t)
        b.ex += t
        b.ex -= xd
        np.multiply(y, a, out=b.ey)
        np.multiply(b.r2, p1, out=t)
        b.ey += t
        b.ey -= yd

    def _jacobian(self, x: FloatArray, y: FloatArray, b: _Buffers, j: _Jacobian) -> None:
        """The radtan map's symmetric Jacobian at ``(x, y)`` from :meth:`_residual`'s ``b``:
        ``jxx = a + q x^2 + 4 p2 x``, ``jyy = a + q y^2 + 4 p1 y``,
        ``jxy = q x y + 2 p1 x + 2 p2 y`` with ``q = 2 k1 + 4 k2 r^2``; and its determinant."""
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        q, t = j.q, b.t
        np.multiply(b.r2, 4.0 * k2, out=q)
        q += 2.0 * k1
        np.multiply(b.xx, q, out=j.xx)
        j.xx += b.a
        np.multiply(x, 4.0 * p2, out=t)
        j.xx += t
        np.multiply(b.yy, q, out=j.yy)
        j.yy += b.a
        np.multiply(y, 4.0 * p1, out=t)
        j.yy += t
        np.multiply(x, y, out=j.xy)
        j.xy *= q
        np.multiply(x, 2.0 * p1, out=t)
        j.xy += t
        np.multiply(y, 2.0 * p2, out=t)
        j.xy += t
        np.multiply(j.xx, j.yy, out=j.det)
        np.multiply(j.xy, j.xy, out=t)
        j.det -= t

    @staticmethod
    def _step(x: FloatArray, y: FloatArray, b: _Buffers, j: _Jacobian) -> None:
        """Newton update ``(x, y) -= J^-1 (ex, ey)`` in place (J from ``j``)."""
        t, d = b.t, j.q  # j.q is free once the Jacobian is built
        np.multiply(j.yy, b.ex, out=d)
        np.multiply(j.xy, b.ey, out=t)
        d -= t
        d /= j.det
        x -= d
        np.multiply(j.xx, b.ey, out=d)
        np.multiply(j.xy, b.ex, out=t)
        d -= t
        d /= j.det
        y -= d

    def _rays_block(self, uv: FloatArray) -> FloatArray:
        u, v = uv[:, 0], uv[:, 1]
        my = v - self.cy
        my /= self.fy
        mx = u - self.cx
        if self.skew != 0.0:
            mx -= self.skew * my
        mx /= self.fx
        masked = self.inner_radius is not None or self.outer_radius is not None
        if self.has_distortion:
            # ok is already False for non-finite pixels (their residual is NaN)
            mx, my, r2, ok = self._undistort(mx, my)
            if masked:
                ok &= radius_ok(u, v, self.cx, self.cy, self.inner_radius, self.outer_radius)
        else:
            r2 = mx * mx
            r2 += my * my
            ok = radius_ok(u, v, self.cx, self.cy, self.inner_radius, self.outer_radius)
        with np.errstate(invalid="ignore"):
            # lift onto the unit sphere: s = (xi + sqrt(1 + (1 - xi^2) r^2)) / (r^2 + 1),
            # ray = (s m, s - xi) has unit length exactly (up to rounding); for xi > 1 the
            # square root's argument is >= 0 exactly where r^2 < 1 / (xi^2 - 1)
            if self.xi > 1.0:
                ok &= r2 < 1.0 / (self.xi**2 - 1.0)
            k = r2 * (1.0 - self.xi**2)
            k += 1.0
            np.sqrt(k, out=k)
            k += self.xi
            r2 += 1.0
            k /= r2
            rays = np.empty((len(uv), 3))
            np.multiply(k, mx, out=rays[:, 0])
            np.multiply(k, my, out=rays[:, 1])
            np.subtract(k, self.xi, out=rays[:, 2])
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
