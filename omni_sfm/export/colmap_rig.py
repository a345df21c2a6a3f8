"""A COLMAP 4.2 rig of perspective views rendered from the omni frames (``colmap-rig``).

One rig (``rigs.bin``): one sensor per view of the layout (:mod:`omni_sfm.export.perspective`),
camera ``k + 1`` for view ``k`` (PINHOLE), the first view the reference sensor and every other
one at ``sensor_from_rig = view_k_from_view_0`` (a rotation: the views share the omni
camera's centre; for a rig camera, the views of every lens, each lens's at its centre). One
frame per pose (``frames.bin``) with ``rig_from_world = view_0_from_world``, holding the frame's
images, ``VIEW/NAME.png`` (``lensK/VIEW/NAME.png`` for a rig camera; ``images.bin``).
COLMAP's rig documentation: https://colmap.github.io/rigs.html.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from omni_sfm.export.colmap import rigid3d, sensor_from_world
from omni_sfm.export.perspective import ViewLayout
from omni_sfm.geometry import FloatArray
from omni_sfm.poses import Trajectory


def view_image_name(view: str, frame_name: str) -> str:
    """The rig image of ``view`` for the frame named ``frame_name`` (always PNG)."""
    from pathlib import PurePosixPath

    return f"{view}/{PurePosixPath(frame_name).with_suffix('.png').as_posix()}"


def sensor_rig_reconstruction(cameras: Sequence[Any], sensor_from_rig: FloatArray,
                              rig_from_world: tuple[FloatArray, FloatArray],
                              image_names: Sequence[Sequence[str]]) -> Any:
    """A ``pycolmap.Reconstruction`` of one rig (id 1) of ``S`` sensors, one frame per pose:
    cameras, rig, frames and posed images, no points.

    ``cameras``: the ``S`` ``pycolmap.Camera`` (given ids ``1..S``), sensor 0 the reference;
    ``sensor_from_rig``: ``(S, 4, 4)``, ``[0]`` the identity (COLMAP's rig frame is the
    reference sensor's); ``rig_from_world``: rotations ``(N, 3, 3)`` and translations
    ``(N, 3)``, frame ``k + 1`` at row ``k``; ``image_names[k][s]``: the image of sensor ``s``
    in frame ``k + 1``, image id ``k * S + s + 1``."""
    import pycolmap

    T = np.asarray(sensor_from_rig, dtype=np.float64)
    S = len(cameras)
    if T.shape != (S, 4, 4) or not np.allclose(T[0], np.eye(4), atol=1e-12):
        raise ValueError(f"sensor_from_rig must be ({S}, 4, 4) with [0] the identity")
    R_rw, t_rw = rig_from_world
    if len(image_names) != len(R_rw):
        raise ValueError(f"{len(image_names)=} differs from the {len(R_rw)} poses")
    rec = pycolmap.Reconstruction()
    rig = pycolmap.Rig(rig_id=1)
    sensors = [pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=s + 1) for s in range(S)]
    for s, cam in enumerate(cameras):
        cam.camera_id = s + 1
        rec.add_camera(cam)
        if s == 0:
            rig.add_ref_sensor(sensors[0])
        else:
            rig.add_sensor(sensors[s], rigid3d(T[s, :3, :3], T[s, :3, 3]))
    rec.add_rig(rig)
    for k, names in enumerate(image_names):
        if len(names) != S:
            raise ValueError(f"frame {k}: {len(names)} image names for {S} sensors")
        frame = pycolmap.Frame(frame_id=k + 1, rig_id=1)
        frame.rig_from_world = rigid3d(R_rw[k], t_rw[k])
        for s in range(S):
            frame.add_data_id(pycolmap.data_t(sensor_id=sensors[s], id=k * S + s + 1))
        rec.add_frame(frame)
        for s in range(S):
            image = pycolmap.Image(name=str(names[s]), camera_id=s + 1, image_id=k * S + s + 1)
            image.frame_id = k + 1
            rec.add_image(image)
    return rec


def build_rig_reconstruction(layouts: Sequence[ViewLayout], traj: Trajectory,
                             frame_names: Sequence[str],
                             body_from_cams: FloatArray | None = None,
                             prefixes: Sequence[str] | None = None) -> Any:
    """The ``pycolmap.Reconstruction`` of the views' rig (:func:`sensor_rig_reconstruction`):
    the views of each camera ``c`` fixed to the body the poses ``traj`` are of
    (``layouts[c]``, the camera at ``body_from_cams[c]``, ``(C, 4, 4)`` with the centre in the
    poses' units; default: one camera, the body's own), its images named ``prefixes[c]`` +
    view; image id ``k * S + s + 1`` is sensor ``s`` (the cameras' views in order) of pose
    ``k``. The first view of the first camera is the reference sensor."""
    C = len(layouts)
    B = np.repeat(np.eye(4)[None], C, axis=0) if body_from_cams is None else \
        np.asarray(body_from_cams, dtype=np.float64)
    pre = [""] * C if prefixes is None else list(prefixes)
    body_from_views = []
    for layout, T in zip(layouts, B, strict=True):
        for R_cv in layout.cam_from_views:
            V = np.eye(4)
            V[:3, :3] = R_cv
            body_from_views.append(T @ V)
    ref = body_from_views[0]
    inv = [np.linalg.inv(T) for T in body_from_views]
    sensor_from_rig = np.asarray([Ti @ ref for Ti in inv])  # view_s_from_view_0
    sensor_from_rig[0] = np.eye(4)
    names = [[view_image_name(p + view, name) for layout, p in zip(layouts, pre, strict=True)
              for view in layout.names] for name in frame_names]
    cameras = [layout.pycolmap_camera(1) for layout in layouts for _ in layout.names]
    return sensor_rig_reconstruction(cameras, sensor_from_rig, sensor_from_world(inv[0], traj),
                                     names)
