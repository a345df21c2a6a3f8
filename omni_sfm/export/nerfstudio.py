"""``transforms.json`` in nerfstudio's data conventions
(https://docs.nerf.studio/quickstart/data_conventions.html), which gsplat's and
LichtFeld-Studio's loaders read too.

- Camera frame: OpenGL's (``x`` right, ``y`` up, ``z`` back; the camera looks along ``-z``);
  ``transform_matrix`` is the ``4 x 4`` camera-to-world matrix of that frame, so
  ``transform_matrix[:3, :3] = world_from_cam_opencv @ diag(1, -1, -1)``.
- World: +z up (nerfstudio's world space) when the export turns the world
  (:mod:`omni_sfm.export.up`); ``applied_transform`` is the ``3 x 4`` map from the folder's world
  to this one (nerfstudio's key for the same thing), units are the folder's.
- Pixels: nerfstudio shoots pixel ``(i, j)`` through its centre ``(i + 0.5, j + 0.5)``, COLMAP's
  convention: ``cx = cx_opencv + 0.5``.

Per camera model: ``EQUIRECTANGULAR`` for equirectangular frames (nerfstudio's equirectangular
rays: ``fl_x = w / 2``, ``fl_y = h``, ``cx = w / 2``, ``cy = h / 2``; the image centre looks
along the camera's ``-z``, the top row up, as omni-sfm's equirectangular camera in OpenCV axes),
``OPENCV_FISHEYE`` with ``k1..k4`` for Kannala-Brandt fisheye frames, and for every other model
perspective views rendered from the frames (:mod:`omni_sfm.export.perspective`), camera model
``OPENCV`` with zero distortion, with a mask for every view image (nerfstudio takes masks for all
images or none) where the camera does not cover every view whole.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras import CameraModel
from omni_sfm.folders import ExportFolder
from omni_sfm.geometry import FloatArray
from omni_sfm.poses import Trajectory

TRANSFORMS_FILE = ExportFolder.TRANSFORMS
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])


def camera_intrinsics(camera: CameraModel) -> dict[str, Any] | None:
    """The nerfstudio intrinsics of ``camera``'s own frames, or None when nerfstudio has no
    model of it (perspective views are exported instead)."""
    w, h = camera.width, camera.height
    if camera.model == "equirectangular":
        return {"camera_model": "EQUIRECTANGULAR", "w": w, "h": h, "fl_x": w / 2.0,
                "fl_y": float(h), "cx": w / 2.0, "cy": h / 2.0}
    if camera.model == "opencv_fisheye":
        p = camera.params()
        return {"camera_model": "OPENCV_FISHEYE", "w": w, "h": h,
                "fl_x": float(p["fx"]), "fl_y": float(p["fy"]),
                "cx": float(p["cx"]) + 0.5, "cy": float(p["cy"]) + 0.5,
                **{f"k{i}": float(p[f"k{i}"]) for i in range(1, 5)}}
    return None


def view_intrinsics(width: int, height: int, focal: float, cx: float, cy: float
                    ) -> dict[str, Any]:
    """nerfstudio intrinsics of a pinhole view (OpenCV pixel centre ``cx, cy``)."""
    return {"camera_model": "OPENCV", "w": int(width), "h": int(height), "fl_x": float(focal),
            "fl_y": float(focal), "cx": float(cx) + 0.5, "cy": float(cy) + 0.5,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}


def transform_matrices(rotations: FloatArray, positions: FloatArray) -> FloatArray:
    """``(N, 4, 4)`` nerfstudio camera-to-world of OpenCV-axis cameras ``world_from_cam``."""
    m = np.zeros((len(rotations), 4, 4))
    m[:, :3, :3] = rotations @ OPENGL_FROM_OPENCV
    m[:, :3, 3] = positions
    m[:, 3, 3] = 1.0
    return m


def transforms_document(intrinsics: dict[str, Any], frames: list[dict[str, Any]],
                        applied_transform: FloatArray | None) -> dict[str, Any]:
    """The ``transforms.json`` document: shared intrinsics at the top, one entry per image."""
    doc: dict[str, Any] = dict(intrinsics)
    doc["frames"] = frames
    if applied_transform is not None:
        doc["applied_transform"] = np.asarray(applied_transform)[:3].tolist()
    return doc


def frame_entry(file_path: str, c2w: FloatArray, *, mask_path: str | None = None,
                **extra: Any) -> dict[str, Any]:
    """One ``frames`` entry: the image (relative path), its camera-to-world, its mask."""
    out: dict[str, Any] = {"file_path": file_path, "transform_matrix": np.asarray(c2w).tolist()}
    if mask_path is not None:
        out["mask_path"] = mask_path
    out.update(extra)
    return out


def read_transforms(path: Path) -> tuple[dict[str, Any], list[tuple[str, FloatArray]]]:
    """Read ``transforms.json`` as nerfstudio's schema describes it: the intrinsics (top level,
    overridden per frame) and, per frame, the image path (relative to the file's folder) and the
    camera-to-world matrix. For tests and scripts; raises ValueError on a schema violation."""
    import json

    doc = json.loads(Path(path).read_text(encoding="utf-8"))
    keys = ("camera_model", "w", "h", "fl_x", "fl_y", "cx", "cy")
    frames = []
    for f in doc["frames"]:
        intr = {k: f.get(k, doc.get(k)) for k in keys}
        if any(v is None for v in intr.values()):
            raise ValueError(f"frame {f.get('file_path')!r} lacks intrinsics {intr}")
        m = np.asarray(f["transform_matrix"], dtype=np.float64)
        if m.shape not in ((4, 4), (3, 4)):
            raise ValueError(f"transform_matrix of {f['file_path']!r} is {m.shape}")
        if not (Path(path).parent / f["file_path"]).is_file():
            raise ValueError(f"{f['file_path']}: no such image")
        frames.append((str(f["file_path"]), m))
    return doc, frames


def opencv_poses(matrices: FloatArray) -> Trajectory:
    """The OpenCV-axis ``world_from_cam`` poses of nerfstudio camera-to-world matrices."""
    m = np.asarray(matrices)
    return Trajectory(np.arange(len(m), dtype=float), m[:, :3, :3] @ OPENGL_FROM_OPENCV,
                      m[:, :3, 3].copy())
