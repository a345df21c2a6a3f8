"""A rig camera's frames (:class:`~omni_sfm.cameras.rig.RigCamera`: raw dual-fisheye footage)
as a COLMAP 4.2 rig (docs/colmap.md, "A rig camera in COLMAP").

One ``pycolmap.Camera`` per lens, camera ``k + 1`` for lens ``k`` (its exact model,
:meth:`~omni_sfm.cameras.base.CameraModel.colmap_export`); one rig (``rigs.bin``) whose reference
sensor is lens 0, so that COLMAP's rig frame is lens 0's COLMAP camera frame, and lens ``k`` at
``sensor_from_rig`` = lens ``k``'s COLMAP frame from lens 0's, its translation included; one
frame per pose (``frames.bin``) at ``rig_from_world`` = lens 0's COLMAP ``cam_from_world``; one
image per lens and frame, ``lens{k}/<frame name>`` (COLMAP's rig convention: the same file name
in one folder per sensor), lens ``k``'s part of the frame as COLMAP must see it (mirrored where
its export says so).

Units: the poses (``trajectory.tum``) are in the trajectory's arbitrary units, the lens centres
(``rig_from_lens``) in metres; the lens offsets go to COLMAP in the model's units,
``centre_metres / metres_per_unit``, the scale :func:`rig_metres_per_unit` reads.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras.base import ColmapExport
from omni_sfm.cameras.rig import RigCamera
from omni_sfm.errors import OmniSfmError
from omni_sfm.export.colmap import sensor_from_world, write_colmap_mask
from omni_sfm.export.colmap_rig import sensor_rig_reconstruction
from omni_sfm.geometry import FloatArray
from omni_sfm.poses import Trajectory


def lens_image_name(lens: int, frame_name: str) -> str:
    """The COLMAP image of lens ``lens`` in the frame named ``frame_name``."""
    return f"lens{lens}/{frame_name}"


def lens_mask_name(lens: int) -> str:
    """The file (beside ``sparse/``) of lens ``lens``'s COLMAP camera mask."""
    return f"camera_mask_lens{lens}.png"


def rig_metres_per_unit(folder: Path | str, *, shown_as: Path | str | None = None) -> float:
    """The metres of one unit of the folder's poses, for the rig's lens offsets.

    Contract: the line estimator (``omni-sfm init``) finds the metric scale of its trajectory
    from the lens baseline (the lens centres of ``camera.yaml``, metres, are observed in the
    lines) and records it in the init folder's ``report.json`` as
    ``"rig": {"metres_per_unit": <float>}`` (:class:`~omni_sfm.reports.RigScaleRecord`).
    A dense folder records it in its own unit (docs/dense.md). Nothing else guesses it: without
    it (an initializer plugin's folder, lines too far for the baseline to fix it) this is a
    one-line OmniSfmError, naming the folder ``shown_as`` (the output a temporary folder
    becomes) when given."""
    from omni_sfm.folders import StageFolder

    stage = StageFolder(Path(folder))
    path = Path(shown_as if shown_as is not None else folder) / stage.REPORT
    report = stage.read_stage_report()
    if report is None:
        raise OmniSfmError(f"{path}: report not found")
    value = None if report.rig is None else report.rig.metres_per_unit
    if value is None:
        raise OmniSfmError(f"{path}: no metric scale for the rig's lens offsets (key "
                           "rig.metres_per_unit)")
    if not math.isfinite(value) or value <= 0:
        raise OmniSfmError(f"{path}: rig.metres_per_unit must be a positive number, got "
                           f"{value!r}")
    return float(value)


@dataclass(frozen=True)
class LensExports:
    """How each lens of a rig goes to COLMAP.

    Attributes:
        camera: the rig.
        exports: each lens's :class:`~omni_sfm.cameras.base.ColmapExport`.
    """

    camera: RigCamera
    exports: tuple[ColmapExport, ...]

    @classmethod
    def of(cls, camera: RigCamera) -> LensExports:
        """The exports of the rig's lenses; OmniSfmError naming the lens that has no exact
        COLMAP model."""
        exports = []
        for k, lens in enumerate(camera.lenses):
            try:
                exports.append(lens.colmap_export())
            except OmniSfmError as exc:
                raise OmniSfmError(f"rig lens {k}: {exc}") from None
        return cls(camera, tuple(exports))

    @property
    def num_lenses(self) -> int:
        return len(self.exports)

    def image_names(self, frame_name: str) -> list[str]:
        """The frame's COLMAP images, lens by lens (:func:`lens_image_name`)."""
        return [lens_image_name(k, frame_name) for k in range(self.num_lenses)]

    def images(self, frame: np.ndarray) -> list[np.ndarray]:
        """Each lens's part of ``frame`` (``H x W[ x C]``, the rig's size) as COLMAP must see
        it (mirrored where the lens's export says so)."""
        img = np.asarray(frame)
        cam = self.camera
        if img.ndim not in (2, 3) or img.shape[:2] != (cam.height, cam.width):
            raise ValueError(f"frame must be ({cam.height}, {cam.width}[, C]), got {img.shape=}")
        return [export.image_to_colmap(cam.lens_image(img, k))
                for k, export in enumerate(self.exports)]

    def colmap_lens_from_rig(self, metres_per_unit: float) -> FloatArray:
        """``(L, 4, 4)`` each lens's COLMAP camera frame from our rig frame, the translation in
        the trajectory's units (metres / ``metres_per_unit``)."""
        out = np.zeros((self.num_lenses, 4, 4))
        for k, (T, export) in enumerate(zip(self.camera.rig_from_lens, self.exports,
                                             strict=True)):
            R = export.colmap_cam_from_cam @ T[:3, :3].T
            out[k, :3, :3] = R
            out[k, :3, 3] = -R @ (T[:3, 3] / metres_per_unit)
            out[k, 3, 3] = 1.0
        return out

    def manifest(self) -> list[dict[str, Any]]:
        """Each lens's entry of ``colmap.json``: its images, COLMAP model, frame map, flip."""
        return [{"images": f"{lens_image_name(k, '')}", "camera_model": e.camera.model_name,
                 "colmap_cam_from_cam": e.colmap_cam_from_cam, "flip_u": e.flip_u,
                 "camera_mask": lens_mask_name(k)} for k, e in enumerate(self.exports)]


@dataclass(frozen=True)
class LensRigSeed:
    """A rig camera's COLMAP model built from omni-sfm poses (:func:`build_lens_rig`).

    Attributes:
        reconstruction: the ``pycolmap.Reconstruction``: camera ``k + 1`` is lens ``k``, rig 1,
            frame ``k + 1`` is pose ``k``, image ``k * L + l + 1`` is lens ``l`` of pose ``k``.
        lenses: how each lens goes to COLMAP.
        metres_per_unit: the scale of the lens offsets (:func:`rig_metres_per_unit`).
        image_names: ``(N,)`` the frame names (each lens's image is
            :func:`lens_image_name`).
    """

    reconstruction: Any
    lenses: LensExports
    metres_per_unit: float
    image_names: tuple[str, ...]


def build_lens_rig(camera: RigCamera, traj: Trajectory, frame_names: Sequence[str],
                   metres_per_unit: float) -> LensRigSeed:
    """The COLMAP rig (module docstring) of ``camera`` posed at ``traj`` (world_from_rig), one
    frame per pose named ``frame_names``."""
    if len(frame_names) != len(traj):
        raise ValueError(f"{len(frame_names)=} differs from the {len(traj)} poses")
    if len(set(frame_names)) != len(frame_names):
        raise OmniSfmError("image names must be unique for a COLMAP model")
    lenses = LensExports.of(camera)
    lens_from_rig = lenses.colmap_lens_from_rig(metres_per_unit)
    # COLMAP's rig frame is lens 0's COLMAP frame
    sensor_from_rig = lens_from_rig @ np.linalg.inv(lens_from_rig[0])[None]
    sensor_from_rig[0] = np.eye(4)
    rec = sensor_rig_reconstruction(
        [e.camera for e in lenses.exports], sensor_from_rig,
        sensor_from_world(lens_from_rig[0], traj),
        [lenses.image_names(str(n)) for n in frame_names])
    return LensRigSeed(rec, lenses, float(metres_per_unit), tuple(str(n) for n in frame_names))


def rig_manifest(seed: LensRigSeed, traj: Trajectory, note: str | None = None
                 ) -> dict[str, Any]:
    """``colmap.json`` of a lens rig's model posed at ``traj``: the frame names and timestamps,
    the lenses (:meth:`LensExports.manifest`) and the scale of their offsets; ``note`` how the
    model's ids follow the trajectory (default: as :func:`build_lens_rig` numbers them)."""
    return {
        "image_names": list(seed.image_names),
        "timestamps": traj.timestamps,
        "camera_model": seed.lenses.camera.model,
        "lenses": seed.lenses.manifest(),
        "metres_per_unit": seed.metres_per_unit,
        "note": note or ("frame k+1 in sparse/ is row k of trajectory.tum, its image of lens "
                         "L images_colmap/lensL/<name> (image id k*lenses+L+1)"),
    }


RIG_CONFIG_FILE = "rig_config.json"
"""COLMAP's rig configuration of the lens rig (``colmap rig_configurator --rig_config_path``)."""


def rig_config(reconstruction: Any) -> list[dict[str, Any]]:
    """COLMAP's rig configuration (``rig_config.json``) of a lens rig's model: each lens's
    image prefix, exact camera (model and parameters) and ``cam_from_rig`` (rotation
    ``[w, x, y, z]``, translation in the model's units), lens 0 the reference sensor."""
    rig = next(iter(reconstruction.rigs.values()))
    cameras = []
    for s in sorted(rig.sensor_ids(), key=lambda sensor: sensor.id):
        cam = reconstruction.cameras[s.id]
        entry: dict[str, Any] = {"image_prefix": lens_image_name(s.id - 1, ""),
                                 "camera_model_name": cam.model_name,
                                 "camera_params": [float(x) for x in cam.params]}
        if rig.is_ref_sensor(s):
            entry["ref_sensor"] = True
        else:
            T = rig.sensor_from_rig(s)
            x, y, z, w = (float(v) for v in T.rotation.quat)
            entry["cam_from_rig_rotation"] = [w, x, y, z]
            entry["cam_from_rig_translation"] = [float(v) for v in T.translation]
        cameras.append(entry)
    return [{"cameras": cameras}]


def write_rig_config(directory: Path, reconstruction: Any) -> None:
    """``directory/rig_config.json``: :func:`rig_config` of the model."""
    from omni_sfm.fileio import atomic_write_text, dumps_json

    atomic_write_text(Path(directory) / RIG_CONFIG_FILE, dumps_json(rig_config(reconstruction)))


def write_lens_masks(directory: Path, lenses: LensExports) -> None:
    """Each lens's COLMAP camera mask (:func:`~omni_sfm.export.colmap.write_colmap_mask` of
    the lens) in ``directory`` (:func:`lens_mask_name`)."""
    for k, lens in enumerate(lenses.camera.lenses):
        write_colmap_mask(Path(directory) / lens_mask_name(k), lens)
