"""Camera models: pixel <-> unit ray for central omnidirectional cameras (docs/method.md §1).

``load_camera(path)`` reads any camera file omni-sfm knows (our YAML, cv2.omnidir FileStorage,
Kalibr camchain, OCamCalib calib_results.txt, COLMAP cameras.txt); every model is a
:class:`CameraModel` with vectorised ``rays_from_pixels`` / ``pixels_from_rays``.
See docs/cameras.md for the equations, file layouts and the COLMAP export.
"""

from omni_sfm.cameras.base import CameraModel, ColmapExport
from omni_sfm.cameras.equirectangular import EquirectangularCamera
from omni_sfm.cameras.eucm import DoubleSphereCamera, EUCMCamera
from omni_sfm.cameras.fisheye import OpenCVFisheyeCamera
from omni_sfm.cameras.hyperboloid import HyperboloidCamera
from omni_sfm.cameras.io import (
    MODELS,
    camera_from_dict,
    load_camera,
    register_model,
    write_camera_yaml,
)
from omni_sfm.cameras.ocam import OCamCamera
from omni_sfm.cameras.rig import RigCamera, dual_fisheye
from omni_sfm.cameras.unified import UnifiedCamera

for _cls in (
    HyperboloidCamera,
    UnifiedCamera,
    EUCMCamera,
    DoubleSphereCamera,
    EquirectangularCamera,
    OCamCamera,
    OpenCVFisheyeCamera,
    RigCamera,
):
    register_model(_cls)

__all__ = [
    "MODELS",
    "CameraModel",
    "ColmapExport",
    "DoubleSphereCamera",
    "EUCMCamera",
    "EquirectangularCamera",
    "HyperboloidCamera",
    "OCamCamera",
    "OpenCVFisheyeCamera",
    "RigCamera",
    "UnifiedCamera",
    "camera_from_dict",
    "dual_fisheye",
    "load_camera",
    "register_model",
    "write_camera_yaml",
]
