"""The camera contract: pixels <-> unit rays, vectorised, for every central camera model."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike

from omni_sfm.geometry import FloatArray


def as_points(a: ArrayLike, dim: int, name: str) -> FloatArray:
    """``a`` as a float64 ``(N, dim)`` array, or a ValueError naming its shape."""
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}), got {arr.shape=}")
    return arr


@dataclass(frozen=True, kw_only=True)
class CameraModel(ABC):
    """A calibrated central camera.

    Pixel convention (all models): OpenCV's, the centre of the top-left pixel is ``(0, 0)``,
    ``u`` right, ``v`` down. Rays are unit vectors in the model's camera frame.
    Subclasses are frozen dataclasses whose fields are the model parameters; ``model`` names
    the model in camera files.
    """

    model: ClassVar[str]
    width: int
    height: int

    @abstractmethod
    def rays_from_pixels(self, uv: ArrayLike) -> FloatArray:
        """``(N, 2)`` pixels -> ``(N, 3)`` unit rays; NaN rows where a pixel sees nothing."""

    @abstractmethod
    def pixels_from_rays(self, rays: ArrayLike) -> FloatArray:
        """``(N, 3)`` rays (any length > 0) -> ``(N, 2)`` pixels; NaN rows where not imaged."""

    def valid_mask(self) -> np.ndarray:
        """``(height, width)`` bool: the pixels whose ray sees the scene."""
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
        ok = np.isfinite(self.rays_from_pixels(uv)).all(axis=1)
        return ok.reshape(self.height, self.width)

    def pixel_grid_rays(self) -> FloatArray:
        """``(height, width, 3)`` rays of every pixel centre (NaN outside the valid region)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
        return self.rays_from_pixels(uv).reshape(self.height, self.width, 3)

    def to_pycolmap(self) -> Any:
        """A ``pycolmap.Camera`` of the exact COLMAP model, or OmniSfmError if none exists."""
        from omni_sfm.errors import OmniSfmError

        raise OmniSfmError(f"camera model {self.model!r} has no exact COLMAP model")

    def params(self) -> dict[str, Any]:
        """The model's parameters (the camera file's keys) as plain Python values."""
        out: dict[str, Any] = {"model": self.model}
        for f in fields(self):
            val = getattr(self, f.name)
            if isinstance(val, np.ndarray):
                val = val.tolist()
            elif isinstance(val, tuple):
                val = [v.tolist() if isinstance(v, np.ndarray) else v for v in val]
            out[f.name] = val
        return out

    def field_of_view_deg(self) -> tuple[float, float]:
        """(min, max) elevation in degrees of valid pixels above the camera's x-y plane.

        Sampled on a coarse pixel grid; for an upward-looking mirror camera this is the vertical
        field of view around the horizon.
        """
        step = max(1, min(self.width, self.height) // 200)
        v, u = np.mgrid[0 : self.height : step, 0 : self.width : step]
        r = self.rays_from_pixels(np.stack([u.ravel(), v.ravel()], 1).astype(np.float64))
        r = r[np.isfinite(r).all(axis=1)]
        if r.size == 0:
            return (float("nan"), float("nan"))
        el = np.degrees(np.arcsin(np.clip(r[:, 2], -1, 1)))
        return (float(el.min()), float(el.max()))

    def summary(self) -> str:
        """Readable several-line description: model, size, parameters, field of view."""
        p = self.params()
        lines = [f"model: {p.pop('model')}", f"size: {p.pop('width')} x {p.pop('height')} px"]
        for k, v in p.items():
            lines.append(f"{k}: {v}")
        lo, hi = self.field_of_view_deg()
        frac = float(self.valid_mask().mean())
        lines.append(f"elevation of valid rays: {lo:.1f} .. {hi:.1f} deg (camera z up)")
        lines.append(f"valid pixels: {100 * frac:.1f} %")
        return "\n".join(lines)
