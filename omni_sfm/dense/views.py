"""Virtual pinhole views of omnidirectional frames, rectified for two-view stereo.

A *stereo rig* of a pair of frames ``(ref, src)`` is four pinhole views that share one
orientation for both frames: their image ``x`` axis is the baseline direction
``(c_src - c_ref) / |c_src - c_ref|`` and they look in four directions 90 deg apart around it,
so the pair of views of one direction is already rectified (a pure translation along ``x``,
horizontal epipolar lines, disparity ``d = f b / z > 0`` from ``ref`` to ``src``). The pixels of
each view come from the omnidirectional image through the camera model's ``pixels_from_rays``
and ``cv2.remap`` (:mod:`omni_sfm.cameras.views`). The directions within
``fov_along_deg / 2`` of the baseline (the epipoles, where stereo has no parallax) are not
covered.

Frames: ``world_from_view`` maps view rays (OpenCV pinhole frame: ``x`` right, ``y`` down,
``z`` forward) to the world; pixels are OpenCV's (centre of the top-left pixel at (0, 0)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omni_sfm.cameras import CameraModel
from omni_sfm.cameras.views import (  # noqa: F401 (dense's names for them)
    ViewGeometry,
    camera_angular_step,
    remap_tables,
    sample_views,
)
from omni_sfm.geometry import FloatArray, normalize

# the four viewing directions around the baseline, in the rig frame (x = baseline)
_RIG_ANGLES = np.deg2rad([0.0, 90.0, 180.0, 270.0])


def view_geometry(camera: CameraModel, *, resolution_scale: float = 1.0,
                  fov_along_deg: float = 130.0) -> ViewGeometry:
    """Views whose pixels subtend about the camera's own angle (times ``1/resolution_scale``).

    Each view covers 90 deg across the baseline (four views close the circle) and
    ``fov_along_deg`` along it."""
    if not 0.0 < fov_along_deg < 170.0:
        raise ValueError(f"fov_along_deg must be in (0, 170), got {fov_along_deg}")
    if resolution_scale <= 0:
        raise ValueError(f"resolution_scale must be > 0, got {resolution_scale}")
    focal = resolution_scale / camera_angular_step(camera)
    half_w = focal * math.tan(math.radians(fov_along_deg) / 2.0)
    return ViewGeometry(focal=focal, width=int(2 * math.ceil(half_w)), height=int(2 * round(focal)))


@dataclass(frozen=True)
class StereoRig:
    """Four rectified views around the baseline of a frame pair (see the module docstring).

    Attributes:
        geometry: intrinsics of every view.
        world_from_rig: ``(3, 3)``; column 0 is the baseline direction in the world.
        world_from_views: ``(4, 3, 3)`` rotation of each view (x = baseline, z = look direction).
        baseline: ``|c_src - c_ref|`` in pose units.
    """

    geometry: ViewGeometry
    world_from_rig: FloatArray
    world_from_views: FloatArray
    baseline: float


def stereo_rig(geometry: ViewGeometry, centre_ref: FloatArray, centre_src: FloatArray,
               world_from_ref: FloatArray) -> StereoRig:
    """The rig of the pair: baseline ``centre_src - centre_ref`` (world), the second rig axis is
    the reference camera's axis most perpendicular to it (so rigs of one frame look alike)."""
    base = np.asarray(centre_src, float) - np.asarray(centre_ref, float)
    b = float(np.linalg.norm(base))
    if not b > 0:
        raise ValueError("the two frames of a stereo pair have the same centre")
    e1 = base / b
    axes = np.asarray(world_from_ref, float).T  # rows: the camera axes in the world
    a = axes[int(np.argmin(np.abs(axes @ e1)))]
    e2 = normalize(a - (a @ e1) * e1)
    e3 = np.cross(e1, e2)
    world_from_rig = np.stack([e1, e2, e3], axis=1)
    c, s = np.cos(_RIG_ANGLES), np.sin(_RIG_ANGLES)
    look = np.stack([np.zeros(4), c, s], axis=1)          # rig frame
    down = np.stack([np.zeros(4), s, -c], axis=1)         # look x baseline
    x = np.tile([1.0, 0.0, 0.0], (4, 1))
    rig_from_views = np.stack([x, down, look], axis=2)    # columns x, y, z of each view
    return StereoRig(geometry, world_from_rig, world_from_rig @ rig_from_views, b)
