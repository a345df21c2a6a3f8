"""COLMAP models seeded by omni-sfm poses, exact for every camera with a COLMAP model.

The camera goes in through :meth:`CameraModel.colmap_export` (docs/cameras.md): COLMAP's
camera frame is ``colmap_cam_from_cam`` times ours (a proper rotation) and, for catadioptric
cameras, COLMAP sees the image mirrored left-right. A pose ``world_from_cam`` of ours becomes
``cam_from_world = colmap_cam_from_cam @ cam_from_world`` for COLMAP, so the projection
centres are unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras.base import CameraModel, ColmapExport
from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray
from omni_sfm.poses import Trajectory


@dataclass(frozen=True)
class ColmapSeed:
    """A pycolmap model built from omni-sfm poses.

    Attributes:
        reconstruction: ``pycolmap.Reconstruction`` with one camera (id 1), one image per
            estimated frame (ids 1..N in trajectory order) registered with its pose, no points.
        export: how the camera and images map to COLMAP's (flip, frame rotation).
        image_names: ``(N,)`` the image names, as COLMAP finds them under its image folder.
    """

    reconstruction: Any
    export: ColmapExport
    image_names: tuple[str, ...]


def colmap_cam_from_world(export: ColmapExport, traj: Trajectory) -> tuple[FloatArray, FloatArray]:
    """COLMAP's ``cam_from_world`` rotation ``(N,3,3)`` and translation ``(N,3)`` of ``traj``."""
    R_cw = export.colmap_cam_from_cam[None] @ traj.cam_from_world_rotations
    t_cw = -np.einsum("nij,nj->ni", R_cw, traj.positions)
    return R_cw, t_cw


def build_reconstruction(camera: CameraModel, traj: Trajectory,
                         image_names: Sequence[str]) -> ColmapSeed:
    """A pycolmap Reconstruction holding ``camera`` and one posed image per trajectory frame."""
    import pycolmap

    if len(image_names) != len(traj):
        raise ValueError(f"{len(image_names)=} differs from the {len(traj)} poses")
    if len(set(image_names)) != len(image_names):
        raise OmniSfmError("image names must be unique for a COLMAP model")
    export = camera.colmap_export()
    rec = pycolmap.Reconstruction()
    cam = export.camera
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    R_cw, t_cw = colmap_cam_from_world(export, traj)
    for k, name in enumerate(image_names):
        image = pycolmap.Image(name=str(name), camera_id=1, image_id=k + 1)
        pose = pycolmap.Rigid3d(np.hstack([R_cw[k], t_cw[k, :, None]]))
        rec.add_image_with_trivial_frame(image, pose)
    return ColmapSeed(rec, export, tuple(str(n) for n in image_names))


def write_reconstruction(seed: ColmapSeed, sparse_dir: Path, *, text: bool = False) -> None:
    """Write the model to ``sparse_dir`` in COLMAP's binary format (and text with ``text``)."""
    sparse_dir = Path(sparse_dir)
    sparse_dir.mkdir(parents=True, exist_ok=True)
    seed.reconstruction.write_binary(str(sparse_dir))
    if text:
        seed.reconstruction.write_text(str(sparse_dir))


def projection_centres(reconstruction: Any) -> dict[str, FloatArray]:
    """Camera centre of every registered image, by image name (world frame)."""
    return {img.name: np.asarray(img.projection_center())
            for img in reconstruction.images.values() if img.has_pose}
