"""Camera models: pixel <-> unit ray for central omnidirectional cameras (METHOD.md §1).

``load_camera(path)`` reads any camera file omni-sfm knows; every model is a
:class:`CameraModel` with vectorised ``rays_from_pixels`` / ``pixels_from_rays``.
"""

from omni_sfm.cameras.base import CameraModel
from omni_sfm.cameras.equirectangular import EquirectangularCamera
from omni_sfm.cameras.hyperboloid import HyperboloidCamera
from omni_sfm.cameras.io import (
    MODELS,
    camera_from_dict,
    load_camera,
    register_model,
    write_camera_yaml,
)

register_model(HyperboloidCamera)
register_model(EquirectangularCamera)

__all__ = [
    "MODELS",
    "CameraModel",
    "EquirectangularCamera",
    "HyperboloidCamera",
    "camera_from_dict",
    "load_camera",
    "register_model",
    "write_camera_yaml",
]
