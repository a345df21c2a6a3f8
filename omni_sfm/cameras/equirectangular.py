"""360 equirectangular images, exactly as pycolmap's EQUIRECTANGULAR camera."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omni_sfm.cameras.base import CameraModel, ColmapExport, colmap_export_plain
from omni_sfm.geometry import FloatArray


def _sin_cos(a: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``(sin a, cos a)`` for ``|a| <= pi`` via ``t = tan(a/2)`` (``a = +-pi`` gives ``t ~ 1e16``,
    still exact to rounding)."""
    t = np.tan(0.5 * a)
    t2 = t * t
    inv = 1.0 / (1.0 + t2)
    return 2.0 * t * inv, (1.0 - t2) * inv


@dataclass(frozen=True, kw_only=True)
class EquirectangularCamera(CameraModel):
    """Longitude along ``u``, latitude along ``v``; COLMAP's axes and pixel convention.

    With COLMAP pixel coordinates ``(uc, vc) = (u + 0.5, v + 0.5)`` (omni-sfm pixels are
    OpenCV's, centre of the top-left pixel at 0): ``lon = 2 pi uc / W - pi``,
    ``lat = pi vc / H - pi / 2``, ray ``= (cos lat sin lon, sin lat, cos lat cos lon)``.
    So +Z is the image centre, +Y is down (the bottom row), +X is at ``u = 3W/4``.

    The width always spans 360 deg and the height 180 deg, whatever the frame's aspect: a 2:1
    frame has equal angular pixel pitches (``360 / W = 180 / H`` deg), a frame squeezed to
    16:9 (1920x1080, as some exporters write 360 video) has ``0.1875`` deg per pixel across
    and ``0.1667`` down. The camera is fully given by the frame size (``--camera
    equirectangular``, docs/cameras.md).
    """

    model = "equirectangular"

    def _rays_block(self, uv: FloatArray) -> FloatArray:
        lon = uv[:, 0] + 0.5
        lon *= 2.0 * np.pi / self.width
        lon -= np.pi
        lat = uv[:, 1] + 0.5
        lat *= np.pi / self.height
        lat -= np.pi / 2.0
        # sin and cos from tan(angle/2): numpy's float64 tan is vectorised, sin/cos are not
        with np.errstate(invalid="ignore"):
            sin_lon, cos_lon = _sin_cos(lon)
            sin_lat, cos_lat = _sin_cos(lat)
        out = np.empty((len(uv), 3))
        np.multiply(cos_lat, sin_lon, out=out[:, 0])
        out[:, 1] = sin_lat
        np.multiply(cos_lat, cos_lon, out=out[:, 2])
        out[~(np.isfinite(uv[:, 0]) & np.isfinite(uv[:, 1]))] = np.nan
        return out

    def _pixels_block(self, rays: FloatArray) -> FloatArray:
        d = rays
        with np.errstate(invalid="ignore", divide="ignore"):
            n = np.linalg.norm(d, axis=1)
            lon = np.arctan2(d[:, 0], d[:, 2])
            lat = np.arcsin(np.clip(d[:, 1] / n, -1.0, 1.0))
        uv = np.stack(
            [(lon + np.pi) * self.width / (2.0 * np.pi) - 0.5,
             (lat + np.pi / 2.0) * self.height / np.pi - 0.5],
            axis=1,
        )
        uv[~((n > 0) & np.isfinite(n))] = np.nan
        return uv

    def summary(self) -> str:
        pitch = (f"pixel pitch: {360.0 / self.width:.4g} deg across, "
                 f"{180.0 / self.height:.4g} deg down")
        if self.width != 2 * self.height:
            pitch += " (squeezed: not 2:1)"
        head, _, rest = super().summary().partition("\n")
        return f"{head}\n{rest.splitlines()[0]}\n{pitch}\n" + "\n".join(rest.splitlines()[1:])

    def valid_mask(self) -> np.ndarray:
        return np.ones((self.height, self.width), dtype=bool)

    def colmap_export(self) -> ColmapExport:
        import pycolmap

        cam = pycolmap.Camera(
            model="EQUIRECTANGULAR", width=self.width, height=self.height,
            params=[float(self.width), float(self.height)],
        )
        return colmap_export_plain(cam, self.width, self.height)
