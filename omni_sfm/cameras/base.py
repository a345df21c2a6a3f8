"""The camera contract: pixels <-> unit rays, vectorised, for every central camera model."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from functools import cached_property
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray

# Rows per block in rays_from_pixels / pixels_from_rays: the temporaries of one block stay in
# the CPU cache, which makes the element-wise numpy work 2-3x faster than whole-array passes.
BLOCK_ROWS = 1 << 16
# slack (px) of the radius mask when projecting rays, see radius_ok
MASK_TOL = 1e-6


def as_points(a: ArrayLike, dim: int, name: str) -> FloatArray:
    """``a`` as a float64 ``(N, dim)`` array, or a ValueError naming its shape."""
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}), got {arr.shape=}")
    return arr


def blockwise(fn: Callable[[FloatArray], FloatArray], a: FloatArray, dim: int) -> FloatArray:
    """``fn`` applied to row blocks of ``a`` ``(N, k)``, results stacked into ``(N, dim)``."""
    n = len(a)
    if n <= BLOCK_ROWS:
        return fn(a)
    out = np.empty((n, dim), dtype=np.float64)
    for i in range(0, n, BLOCK_ROWS):
        out[i : i + BLOCK_ROWS] = fn(a[i : i + BLOCK_ROWS])
    return out


def unit_rows(x: FloatArray, y: FloatArray, z: FloatArray) -> FloatArray:
    """Stack ``(n,)`` components into ``(n, 3)`` unit vectors (zero-length rows become NaN)."""
    out = np.empty((len(x), 3), dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = x * x
        inv += y * y
        inv += z * z
        np.sqrt(inv, out=inv)
        np.divide(1.0, inv, out=inv)
        np.multiply(x, inv, out=out[:, 0])
        np.multiply(y, inv, out=out[:, 1])
        np.multiply(z, inv, out=out[:, 2])
    return out


def unit_input_rays(d: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Components of the rows of ``d`` ``(n, 3)`` scaled to unit length (NaN for zero rows)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y, z = d[:, 0].copy(), d[:, 1].copy(), d[:, 2].copy()
        inv = x * x
        inv += y * y
        inv += z * z
        np.sqrt(inv, out=inv)
        np.divide(1.0, inv, out=inv)
        inv[~np.isfinite(inv)] = np.nan
        x *= inv
        y *= inv
        z *= inv
    return x, y, z


def polyval_asc(coeffs: tuple[float, ...], x: FloatArray) -> FloatArray:
    """``sum_i coeffs[i] x^i`` by Horner's rule (coefficients in ascending order)."""
    out = np.full_like(x, coeffs[-1])
    for c in coeffs[-2::-1]:
        out *= x
        out += c
    return out


def radius_ok(
    u: FloatArray, v: FloatArray, cx: float, cy: float,
    inner: float | None, outer: float | None, tol: float = 0.0,
) -> np.ndarray:
    """Bool ``(n,)``: pixel radius around ``(cx, cy)`` within ``[inner, outer]`` (None: no bound)
    widened by ``tol`` px (projections use ``MASK_TOL`` so that pixel -> ray -> pixel keeps the
    mask's boundary pixels despite rounding)."""
    ok = np.isfinite(u) & np.isfinite(v)
    if inner is None and outer is None:
        return ok
    with np.errstate(invalid="ignore"):
        r = np.hypot(u - cx, v - cy)
        if inner is not None:
            ok &= r >= inner - tol
        if outer is not None:
            ok &= r <= outer + tol
    return ok


@dataclass(frozen=True, eq=False)
class MonotoneInverse:
    """Exact inverse ``x = g^-1(y)`` of a strictly increasing scalar function on ``[0, x_max]``.

    A uniform table in ``y`` gives a start point good to ~1e-7 relative, then Newton steps on
    ``g(x) - y`` make it exact to rounding. ``y`` outside ``[g(0), g(x_max)]`` gives NaN.
    Used to invert radial distortion polynomials (Kannala-Brandt, radtan, OCamCalib).
    """

    g: Callable[[FloatArray], FloatArray]
    dg: Callable[[FloatArray], FloatArray]
    x_max: float
    size: int = 4096
    newton_steps: int = 3
    table: FloatArray = field(init=False, repr=False)
    y0: float = field(init=False)
    y1: float = field(init=False)

    def __post_init__(self) -> None:
        xs = np.linspace(0.0, self.x_max, 16 * self.size + 1)
        ys = self.g(xs)
        y0, y1 = float(ys[0]), float(ys[-1])
        table = np.interp(np.linspace(y0, y1, self.size + 1), ys, xs)
        object.__setattr__(self, "table", table)
        object.__setattr__(self, "y0", y0)
        object.__setattr__(self, "y1", y1)

    def __call__(self, y: FloatArray, *, clamp: bool = False) -> FloatArray:
        """``x`` with ``g(x) = y``; out-of-range ``y`` gives NaN, or with ``clamp`` the nearest
        end of ``[0, x_max]`` (a start point for a caller's own iteration)."""
        with np.errstate(invalid="ignore"):
            t = (y - self.y0) * (self.size / (self.y1 - self.y0))
            if clamp:
                np.clip(t, 0.0, self.size, out=t)
            bad = ~((t >= 0) & (t <= self.size))
            t[bad] = 0.0
            i = np.minimum(t.astype(np.intp), self.size - 1)
            t -= i
            x = self.table[i]
            x += t * (self.table[i + 1] - x)
            for _ in range(self.newton_steps):
                x -= (self.g(x) - y) / self.dg(x)
            np.clip(x, 0.0, self.x_max, out=x)
        x[bad] = np.nan
        return x


def first_nonincreasing(
    dg: Callable[[FloatArray], FloatArray], x_hi: float, samples: int = 200_001
) -> float:
    """The first ``x`` in ``(0, x_hi]`` where ``dg(x) <= 0`` (found on a fine grid and refined
    by bisection), or ``x_hi`` if ``dg`` stays positive: the end of a function's monotone part."""
    xs = np.linspace(0.0, x_hi, samples)
    bad = np.flatnonzero(dg(xs) <= 0)
    if bad.size == 0:
        return x_hi
    hi = float(xs[bad[0]])
    lo = float(xs[max(bad[0] - 1, 0)])
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if dg(np.array([mid]))[0] > 0:
            lo = mid
        else:
            hi = mid
    # stay strictly inside the monotone part so the inverse is well conditioned
    return lo * (1.0 - 1e-9)


@dataclass(frozen=True, eq=False)
class ColmapExport:
    """How a camera is handed to COLMAP exactly (see docs/cameras.md, "Export to COLMAP").

    ``camera`` is a ``pycolmap.Camera`` whose ``img_from_cam`` / ``cam_ray_from_img`` equal our
    ``pixels_from_rays`` / ``rays_from_pixels`` after these two fixed maps:

    - rays: ``ray_colmap = colmap_cam_from_cam @ ray_ours`` (a proper 3x3 rotation), so a pose
      ``cam_from_world`` of ours becomes ``colmap_cam_from_cam @ cam_from_world`` for COLMAP;
    - pixels: COLMAP's pixel convention (centre of the top-left pixel at (0.5, 0.5)) and, when
      ``flip_u``, the image mirrored left-right: ``u_colmap = (W - 1 - u) + 0.5``,
      ``v_colmap = v + 0.5``. The image files COLMAP reads must then be mirrored the same way
      (:meth:`image_to_colmap`).

    A catadioptric camera (hyperboloid) is a reflection of an ordinary camera; mirroring the image
    is what keeps ``colmap_cam_from_cam`` a rotation (det +1) rather than a reflection.
    """

    camera: Any
    colmap_cam_from_cam: FloatArray
    flip_u: bool
    width: int
    height: int

    def pixels_to_colmap(self, uv: ArrayLike) -> FloatArray:
        """``(N, 2)`` omni-sfm pixels -> the same image points in COLMAP's (flipped) image."""
        p = as_points(uv, 2, "uv").copy()
        if self.flip_u:
            p[:, 0] = (self.width - 1) - p[:, 0]
        p += 0.5
        return p

    def pixels_from_colmap(self, uv_colmap: ArrayLike) -> FloatArray:
        """Inverse of :meth:`pixels_to_colmap`."""
        p = as_points(uv_colmap, 2, "uv_colmap") - 0.5
        if self.flip_u:
            p[:, 0] = (self.width - 1) - p[:, 0]
        return p

    def rays_to_colmap(self, rays: ArrayLike) -> FloatArray:
        """``(N, 3)`` rays in our camera frame -> COLMAP's camera frame."""
        return as_points(rays, 3, "rays") @ self.colmap_cam_from_cam.T

    def image_to_colmap(self, image: np.ndarray) -> np.ndarray:
        """The image array (``H x W`` or ``H x W x C``) COLMAP must see: mirrored left-right when
        ``flip_u``, otherwise returned unchanged. Always a contiguous array."""
        img = np.asarray(image)
        if img.ndim not in (2, 3) or img.shape[:2] != (self.height, self.width):
            raise ValueError(
                f"image must be ({self.height}, {self.width}[, C]), got {img.shape=}"
            )
        return np.ascontiguousarray(img[:, ::-1] if self.flip_u else img)


def colmap_export_plain(camera: Any, width: int, height: int) -> ColmapExport:
    """A :class:`ColmapExport` whose frames and image agree with ours (only the 0.5 px shift)."""
    return ColmapExport(
        camera=camera, colmap_cam_from_cam=np.eye(3), flip_u=False, width=width, height=height
    )


@dataclass(frozen=True, kw_only=True)
class CameraModel(ABC):
    """A calibrated central camera.

    Pixel convention (all models): OpenCV's, the centre of the top-left pixel is ``(0, 0)``,
    ``u`` right, ``v`` down. Rays are unit vectors in the model's camera frame (each model's
    docstring says which frame). Subclasses are frozen dataclasses whose fields are the model
    parameters (the camera file's keys); ``model`` names the model in camera files.
    Subclasses implement ``_rays_block`` / ``_pixels_block`` on ``(n, 2)`` / ``(n, 3)`` blocks;
    the public methods check shapes and process large inputs block by block.
    """

    model: ClassVar[str]
    width: int
    height: int

    def __post_init__(self) -> None:
        for f in fields(self):
            val = getattr(self, f.name)
            # numpy scalars and sequences become plain Python numbers and tuples
            if isinstance(val, np.generic):
                val = val.item()
            elif isinstance(val, list | np.ndarray):
                val = tuple(np.asarray(val).ravel().tolist())
            elif isinstance(val, tuple):
                val = tuple(v.item() if isinstance(v, np.generic) else v for v in val)
            object.__setattr__(self, f.name, val)
            if isinstance(val, tuple) and "tuple" not in str(f.type):
                raise ValueError(f"key {f.name!r} must be a number, got {val!r}")
            vals = val if isinstance(val, tuple) else (val,)
            for x in vals:
                if isinstance(x, bool) or not isinstance(x, int | float | type(None)):
                    raise ValueError(f"key {f.name!r} must be a number, got {x!r}")
                if x is not None and not math.isfinite(x):
                    raise ValueError(f"key {f.name!r} must be finite, got {x!r}")
        for key in ("width", "height"):
            val = getattr(self, key)
            if not isinstance(val, int) or val <= 0:
                raise ValueError(f"key {key!r} must be a positive integer, got {val!r}")
        self._check()

    def __getstate__(self) -> dict[str, Any]:
        # pickle the parameters only, not the cached pixel grid (30 MB at 1600 x 800) and tables
        names = {f.name for f in fields(self)}
        return {k: v for k, v in self.__dict__.items() if k in names}

    def _check(self) -> None:  # noqa: B027 (optional hook, most models override it)
        """Raise ValueError naming the key if a parameter is out of its domain."""

    def _positive(self, *keys: str) -> None:
        for key in keys:
            if not getattr(self, key) > 0:
                raise ValueError(f"key {key!r} must be positive, got {getattr(self, key)!r}")

    @abstractmethod
    def _rays_block(self, uv: FloatArray) -> FloatArray:
        """``(n, 2)`` pixels -> ``(n, 3)`` unit rays, NaN rows where invalid."""

    @abstractmethod
    def _pixels_block(self, rays: FloatArray) -> FloatArray:
        """``(n, 3)`` rays (any length) -> ``(n, 2)`` pixels, NaN rows where invalid."""

    def rays_from_pixels(self, uv: ArrayLike) -> FloatArray:
        """``(N, 2)`` pixels -> ``(N, 3)`` unit rays; NaN rows where a pixel sees nothing."""
        return blockwise(self._rays_block, as_points(uv, 2, "uv"), 3)

    def pixels_from_rays(self, rays: ArrayLike) -> FloatArray:
        """``(N, 3)`` rays (any length > 0) -> ``(N, 2)`` pixels; NaN rows where the model does
        not image the ray (outside its domain or mask). Pixels beyond the image frame are
        returned as computed; use :meth:`in_image` to test the frame."""
        return blockwise(self._pixels_block, as_points(rays, 3, "rays"), 2)

    def in_image(self, uv: ArrayLike) -> np.ndarray:
        """``(N,)`` bool: finite pixels inside the frame ``-0.5 <= u < W - 0.5`` (same for v)."""
        p = as_points(uv, 2, "uv")
        with np.errstate(invalid="ignore"):
            return (
                (p[:, 0] >= -0.5) & (p[:, 0] < self.width - 0.5)
                & (p[:, 1] >= -0.5) & (p[:, 1] < self.height - 0.5)
            )

    @cached_property
    def _grid_rays(self) -> FloatArray:
        # block by image rows: the pixel coordinates of one block are built in the cache too
        h, w = self.height, self.width
        rows = max(1, BLOCK_ROWS // w)
        out = np.empty((h, w, 3), dtype=np.float64)
        uv = np.empty((rows * w, 2), dtype=np.float64)
        uv[:, 0] = np.tile(np.arange(w, dtype=np.float64), rows)
        row_of = np.repeat(np.arange(rows, dtype=np.float64), w)
        for v0 in range(0, h, rows):
            n = min(rows, h - v0)
            np.add(row_of[: n * w], v0, out=uv[: n * w, 1])
            out[v0 : v0 + n] = self._rays_block(uv[: n * w]).reshape(n, w, 3)
        out.flags.writeable = False
        return out

    @cached_property
    def _valid(self) -> np.ndarray:
        ok = np.isfinite(self._grid_rays[..., 0])
        ok.flags.writeable = False
        return ok

    def valid_mask(self) -> np.ndarray:
        """``(height, width)`` bool: the pixels whose ray sees the scene (a fresh copy)."""
        return self._valid.copy()

    def pixel_grid_rays(self) -> FloatArray:
        """``(height, width, 3)`` rays of every pixel centre, NaN outside the valid region.

        Computed once per camera and cached: the array is read-only (copy it to modify)."""
        return self._grid_rays

    def colmap_export(self) -> ColmapExport:
        """The exact COLMAP camera with the frame and pixel maps to use it (see ColmapExport);
        OmniSfmError if COLMAP has no exact model for this camera."""
        raise OmniSfmError(f"no exact COLMAP model for camera model {self.model!r}")

    def to_pycolmap(self) -> Any:
        """A ``pycolmap.Camera`` of the exact COLMAP model, or OmniSfmError if none exists.

        Use :meth:`colmap_export` for the frame rotation and image flip that go with it."""
        return self.colmap_export().camera

    def params(self) -> dict[str, Any]:
        """The model's parameters (the camera file's keys) as plain Python values."""
        out: dict[str, Any] = {"model": self.model}
        for f in fields(self):
            val = getattr(self, f.name)
            if isinstance(val, np.ndarray | np.generic):
                val = val.tolist()
            elif isinstance(val, tuple):
                val = [v.tolist() if isinstance(v, np.ndarray | np.generic) else v for v in val]
            out[f.name] = val
        return out

    def frame_size_mismatch(self, width: int, height: int) -> str | None:
        """This camera's own one-line account of frames of ``width x height`` px that do not
        have its size, or None: the message of whoever checks the frames names both sizes."""
        return None

    def _coarse_rays(self) -> FloatArray:
        step = max(1, min(self.width, self.height) // 200)
        v, u = np.mgrid[0 : self.height : step, 0 : self.width : step]
        r = self.rays_from_pixels(np.stack([u.ravel(), v.ravel()], 1).astype(np.float64))
        return r[np.isfinite(r).all(axis=1)]

    def summary(self) -> str:
        """Readable several-line description: model, size, parameters, field of view."""
        p = self.params()
        lines = [f"model: {p.pop('model')}", f"size: {p.pop('width')} x {p.pop('height')} px"]
        lines.extend(f"{k}: {v}" for k, v in p.items() if v is not None)
        r = self._coarse_rays()
        if r.size:
            ang = np.degrees(np.arccos(np.clip(r[:, 2], -1, 1)))
            lines.append(
                f"angle of valid rays from the camera +z axis: {ang.min():.1f} .. "
                f"{ang.max():.1f} deg"
            )
            el = 90.0 - ang
            lines.append(
                f"elevation of valid rays above the x-y plane: {el.min():.1f} .. "
                f"{el.max():.1f} deg"
            )
        frac = float(self.valid_mask().mean())
        lines.append(f"valid pixels: {100 * frac:.1f} %")
        try:
            cam = self.colmap_export()
            lines.append(
                f"COLMAP: {cam.camera.model_name}"
                + (" (image mirrored left-right, see docs/cameras.md)" if cam.flip_u else "")
            )
        except OmniSfmError:
            lines.append("COLMAP: no exact model")
        return "\n".join(lines)
