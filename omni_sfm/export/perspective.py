"""Perspective views of omnidirectional frames for pinhole-only tools (COLMAP's MVS, most
Gaussian-splat trainers): the ``colmap-rig`` export and ``nerfstudio`` for cameras it has no
model of.

The views are laid out as :mod:`pycolmap.panorama` lays them out for equirectangular
panoramas (:func:`pycolmap.panorama.get_virtual_rotations`): ``overlapping``: 90 x 90 deg views
at four yaws 90 deg apart and pitches -35, 0 and +35 deg (the tilted rows turned by 45 deg);
``cubemap``: the four horizontal cube faces. The yaw and pitch are about the *level frame*
of the camera (OpenCV axes: ``y`` down along the vertical, ``z`` the camera's forward axis
laid horizontal), so that the rows of views follow the horizon however the camera is mounted;
the layout is fixed to the camera (a rig), from the vertical averaged over the frames. Views
that the camera covers less than half of (the hole and the rim of a mirror camera) are left
out. A view's pixel subtends the camera's own median angle (pycolmap's size for
equirectangular panoramas: a 90 deg view of a 1600 x 800 panorama is 400 x 400 px); its
pixels come from the frame through the camera model (:mod:`omni_sfm.cameras.views`), bilinear.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from omni_sfm.cameras import CameraModel
from omni_sfm.cameras.views import ViewGeometry, camera_angular_step, remap_tables, sample_views
from omni_sfm.geometry import FloatArray, normalize

LAYOUTS = {
    # name: (yaw steps, pitches in degrees), pycolmap.panorama.PANO_RENDER_OPTIONS
    "overlapping": (4, (-35.0, 0.0, 35.0)),
    "cubemap": (4, (0.0,)),
}
VIEW_FOV_DEG = 90.0
MIN_COVERAGE = 0.5


@dataclass(frozen=True)
class ViewLayout:
    """Pinhole views fixed to the camera.

    Attributes:
        geometry: intrinsics shared by every view (OpenCV pixels).
        cam_from_views: ``(V, 3, 3)`` rotation of each view (OpenCV axes) in the camera frame.
        coverage: ``(V,)`` share of each view's pixels the camera sees.
        names: ``V`` folder names of the views (``view00`` ...), in the layout's order.
        tables: ``(V, H, W, 2)`` float32 source pixels of the frame for ``cv2.remap``.
        valid: ``(V, H, W)`` bool, the view pixels that the camera sees.
        wrap: the frames wrap around left-right (equirectangular).
    """

    geometry: ViewGeometry
    cam_from_views: FloatArray
    coverage: FloatArray
    names: tuple[str, ...]
    tables: np.ndarray
    valid: np.ndarray
    wrap: bool = False

    def render(self, image: np.ndarray, camera_valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(V, H, W[, C])`` views of ``image`` and ``(V, H, W)`` bool validity (the camera's
        valid region)."""
        return sample_views(image, self.tables, camera_valid, erode_px=0, wrap=self.wrap)

    def pycolmap_camera(self, camera_id: int) -> Any:
        """The views' ``pycolmap.Camera`` (PINHOLE, COLMAP's pixel convention)."""
        import pycolmap

        g = self.geometry
        return pycolmap.Camera(model="PINHOLE", width=g.width, height=g.height,
                               params=[g.focal, g.focal, g.cx + 0.5, g.cy + 0.5],
                               camera_id=camera_id)

    def to_json(self) -> dict[str, Any]:
        g = self.geometry
        return {"width": g.width, "height": g.height, "focal_px": g.focal,
                "cx": g.cx, "cy": g.cy, "pixel_convention": "OpenCV (top-left pixel centre 0)",
                "views": [{"name": n, "cam_from_view": r.tolist(), "coverage": float(c)}
                          for n, r, c in zip(self.names, self.cam_from_views, self.coverage,
                                             strict=True)]}


def level_frame(up_in_cam: FloatArray) -> FloatArray:
    """``(3, 3)`` cam_from_level: level ``y`` = down, ``z`` = the camera's ``z`` (or ``x`` where
    ``z`` is nearly vertical) laid horizontal, ``x = y x z``."""
    down = -normalize(np.asarray(up_in_cam, float))
    fwd = np.array([0.0, 0.0, 1.0]) if abs(down[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    z = normalize(fwd - (fwd @ down) * down)
    x = np.cross(down, z)
    return np.stack([x, down, z], axis=1)


def view_layout(camera: CameraModel, up_in_cam: FloatArray, layout: str = "overlapping",
                fov_deg: float = VIEW_FOV_DEG) -> ViewLayout:
    """The views of ``layout`` (see the module docstring) that the camera covers."""
    from pycolmap.panorama import get_virtual_rotations

    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {sorted(LAYOUTS)}, got {layout!r}")
    steps, pitches = LAYOUTS[layout]
    step = camera_angular_step(camera)
    size = max(16, int(round(math.radians(fov_deg) / step)))
    focal = size / (2.0 * math.tan(math.radians(fov_deg) / 2.0))
    geom = ViewGeometry(focal=focal, width=size, height=size)
    cam_from_level = level_frame(up_in_cam)
    views_from_level = np.asarray(get_virtual_rotations(steps, pitches))
    cam_from_views = cam_from_level[None] @ np.swapaxes(views_from_level, 1, 2)
    tables = remap_tables(camera, geom, cam_from_views, np.eye(3))
    ok = tables[..., 0] >= 0
    valid_cam = camera.valid_mask()
    u = np.clip(np.rint(tables[..., 0]).astype(int), 0, camera.width - 1)
    v = np.clip(np.rint(tables[..., 1]).astype(int), 0, camera.height - 1)
    ok &= valid_cam[v, u]
    coverage = ok.reshape(len(ok), -1).mean(axis=1)
    keep = coverage >= MIN_COVERAGE
    if not keep.any():
        from omni_sfm.errors import OmniSfmError

        raise OmniSfmError(f"no {fov_deg:.0f} deg view of the {layout} layout is covered to "
                           f"{100 * MIN_COVERAGE:.0f} % by camera model {camera.model!r}")
    idx = np.flatnonzero(keep)
    return ViewLayout(geom, cam_from_views[idx], coverage[idx],
                      tuple(f"view{i:02d}" for i in idx), tables[idx], ok[idx],
                      wrap=camera.model == "equirectangular")
