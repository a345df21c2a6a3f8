"""A COLMAP 4.2 rig of perspective views rendered from the omni frames (``colmap-rig``).

One rig (``rigs.bin``): one sensor per view of the layout (:mod:`omni_sfm.export.perspective`),
camera ``k + 1`` for view ``k`` (all PINHOLE with the same intrinsics), the first view the
reference sensor and every other one at ``sensor_from_rig = view_k_from_view_0`` (a rotation:
the views share the omni camera's centre). One frame per pose (``frames.bin``) with
``rig_from_world = view_0_from_world``, holding the frame's images, ``VIEW/NAME.png``
(``images.bin``). COLMAP's rig documentation: https://colmap.github.io/rigs.html.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from omni_sfm.export.perspective import ViewLayout
from omni_sfm.poses import Trajectory


def view_image_name(view: str, frame_name: str) -> str:
    """The rig image of ``view`` for the frame named ``frame_name`` (always PNG)."""
    from pathlib import PurePosixPath

    return f"{view}/{PurePosixPath(frame_name).with_suffix('.png').as_posix()}"


def build_rig_reconstruction(layout: ViewLayout, traj: Trajectory,
                             frame_names: Sequence[str]) -> Any:
    """The ``pycolmap.Reconstruction`` of the rig: cameras, rig, frames and posed images (image
    id ``k * V + v + 1`` is view ``v`` of pose ``k``), no points."""
    import pycolmap

    views = len(layout.names)
    rec = pycolmap.Reconstruction()
    rig = pycolmap.Rig(rig_id=1)
    sensors = [pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=v + 1) for v in range(views)]
    view0_from_cam = layout.cam_from_views[0].T
    for v in range(views):
        rec.add_camera(layout.pycolmap_camera(v + 1))
        if v == 0:
            rig.add_ref_sensor(sensors[0])
        else:
            R = layout.cam_from_views[v].T @ layout.cam_from_views[0]   # view_v_from_view_0
            rig.add_sensor(sensors[v], pycolmap.Rigid3d(pycolmap.Rotation3d(R), np.zeros(3)))
    rec.add_rig(rig)
    for k, name in enumerate(frame_names):
        R_vw = view0_from_cam @ traj.rotations[k].T
        t_vw = -R_vw @ traj.positions[k]
        frame = pycolmap.Frame(frame_id=k + 1, rig_id=1)
        frame.rig_from_world = pycolmap.Rigid3d(np.hstack([R_vw, t_vw[:, None]]))
        for v in range(views):
            frame.add_data_id(pycolmap.data_t(sensor_id=sensors[v], id=k * views + v + 1))
        rec.add_frame(frame)
        for v in range(views):
            image = pycolmap.Image(name=view_image_name(layout.names[v], name), camera_id=v + 1,
                                   image_id=k * views + v + 1)
            image.frame_id = k + 1
            rec.add_image(image)
    return rec
