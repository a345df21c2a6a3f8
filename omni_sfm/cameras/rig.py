"""A rig of central lenses recorded in one frame: raw dual-fisheye footage (two ~200 deg
fisheyes side by side or stacked, as Ricoh Theta and Insta360 cameras record it) and two-camera
rigs from a Kalibr camchain (``T_cn_cnm1``), their images put side by side.

Rig frame: each lens ``k`` sits at ``rig_from_lens[k]`` (a rotation and the lens centre, metres).
A pixel belongs to the lens whose part of the frame holds it (side by side: lens 0 leftmost;
stacked: lens 0 on top); its ray is the lens's ray turned into the rig frame. A direction is
imaged by exactly one lens, the one whose optical axis is nearest to it, so that every ray knows
its lens (:meth:`RigCamera.lens_of_rays`) and its centre (:meth:`RigCamera.ray_origins`): where
two lenses' fields overlap, each keeps its own side of the plane between their axes.

As a :class:`~omni_sfm.cameras.base.CameraModel` the rig is the map pixel <-> ray direction; the
few centimetres between the lens centres are the observation offsets the line estimation
handles (``LineTracks.obs_offset``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from omni_sfm.cameras.base import CameraModel, as_points
from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray

LAYOUTS = ("side_by_side", "stacked")


def rigid_transform(path: Path | str, key: str, value: Any) -> FloatArray:
    """A ``(4, 4)`` rigid transform from a 4x4 (or 3x4) nested list, checked."""
    try:
        T = np.array(value, dtype=np.float64)  # a copy: the rotation is made exact below
    except (TypeError, ValueError):
        raise OmniSfmError(f"{path}: key {key!r} must be a 4x4 matrix of numbers") from None
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise OmniSfmError(f"{path}: key {key!r} must be a finite 4x4 matrix, got shape "
                           f"{T.shape}")
    R = T[:3, :3]
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9) or \
            not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise OmniSfmError(f"{path}: key {key!r} must be a rigid transform (rotation, "
                           "translation, last row 0 0 0 1)")
    # the nearest rotation, so that the camera's rays stay unit vectors to round-off
    u, _, vt = np.linalg.svd(R)
    T[:3, :3] = u @ vt
    return T


def frame_size(lenses: Sequence[CameraModel], layout: str) -> tuple[int, int]:
    """``(width, height)`` of the frame that holds ``lenses`` in ``layout``: side by side, the
    widths summed and the largest height; stacked, the largest width and the heights summed."""
    ws, hs = [c.width for c in lenses], [c.height for c in lenses]
    return (sum(ws), max(hs)) if layout == "side_by_side" else (max(ws), sum(hs))


@dataclass(frozen=True, kw_only=True, eq=False)
class RigCamera(CameraModel):
    """Two or more central lenses in one frame (module docstring).

    Attributes:
        lenses: the lenses' own models, each in its own pixel coordinates (its part of the
            frame, the top-left pixel at ``(0, 0)``).
        rig_from_lens: ``(L, 4, 4)`` each lens's rotation and centre (metres) in the rig frame.
        layout: ``side_by_side`` (lens 0 leftmost) or ``stacked`` (lens 0 on top).
    """

    model: ClassVar[str] = "rig"
    lenses: tuple[CameraModel, ...]
    rig_from_lens: FloatArray = field(repr=False)
    layout: str = "side_by_side"
    file: str = field(default="", repr=False)
    """The camera file the rig was read from ('' when built in code), named in messages."""
    camchain: bool = field(default=False, repr=False)
    """Read from a Kalibr camchain: messages call its lenses the camchain's cameras."""

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise ValueError(f"key 'layout' must be one of {', '.join(LAYOUTS)}, "
                             f"got {self.layout!r}")
        if len(self.lenses) < 2 or not all(isinstance(c, CameraModel) and not
                                           isinstance(c, RigCamera) for c in self.lenses):
            raise ValueError("key 'lenses' must list two or more central lens models")
        T = np.asarray(self.rig_from_lens, dtype=np.float64)
        if T.shape != (len(self.lenses), 4, 4):
            raise ValueError(f"rig_from_lens must be ({len(self.lenses)}, 4, 4), got {T.shape}")
        T = np.array([rigid_transform("<rig>", f"lenses[{k}].rig_from_lens", t)
                      for k, t in enumerate(T)])
        T.flags.writeable = False
        object.__setattr__(self, "rig_from_lens", T)
        w, h = frame_size(self.lenses, self.layout)
        if (self.width, self.height) != (w, h):
            raise ValueError(f"a {self.layout} rig of these lenses is {w} x {h} px, got "
                             f"width {self.width}, height {self.height}")
        if np.linalg.norm(self.axes[0] - self.axes[1]) < 1e-6:
            raise ValueError("two lenses of a rig look the same way")

    def __eq__(self, other: object) -> bool:
        """The same lenses, placements and layout (the file read from aside)."""
        if not isinstance(other, RigCamera):
            return NotImplemented
        return (self.width, self.height, self.layout, self.lenses) == \
            (other.width, other.height, other.layout, other.lenses) and \
            np.array_equal(self.rig_from_lens, other.rig_from_lens)

    def __hash__(self) -> int:
        return hash((self.width, self.height, self.layout, self.lenses,
                     self.rig_from_lens.tobytes()))

    @property
    def num_lenses(self) -> int:
        return len(self.lenses)

    @cached_property
    def corners(self) -> np.ndarray:
        """``(L, 2)`` int: the frame pixel of each lens's top-left pixel."""
        out = np.zeros((self.num_lenses, 2), dtype=np.int64)
        axis = 0 if self.layout == "side_by_side" else 1
        sizes = [c.width if axis == 0 else c.height for c in self.lenses]
        out[1:, axis] = np.cumsum(sizes)[:-1]
        return out

    def lens_image(self, frame: np.ndarray, k: int) -> np.ndarray:
        """Lens ``k``'s part of ``frame`` (``H x W[ x C]``, the rig's size): its own image."""
        x0, y0 = (int(v) for v in self.corners[k])
        lens = self.lenses[k]
        return frame[y0:y0 + lens.height, x0:x0 + lens.width]

    def rig_from_lens_in(self, k: int, metres_per_unit: float) -> FloatArray:
        """``(4, 4)`` rig_from_lens of lens ``k`` with its centre in units of
        ``metres_per_unit`` metres (the poses' units; the lens's poses:
        :meth:`omni_sfm.poses.Trajectory.fixed_camera`)."""
        T = self.rig_from_lens[k].copy()
        T[:3, 3] /= metres_per_unit
        return T

    @property
    def rotations(self) -> FloatArray:
        """``(L, 3, 3)`` rig_from_lens rotations."""
        return self.rig_from_lens[:, :3, :3]

    @property
    def centres(self) -> FloatArray:
        """``(L, 3)`` lens centres in the rig frame, metres."""
        return self.rig_from_lens[:, :3, 3]

    @cached_property
    def axes(self) -> FloatArray:
        """``(L, 3)`` optical axes (each lens's +z) in the rig frame."""
        return np.ascontiguousarray(self.rig_from_lens[:, :3, 2])

    def lens_of_rays(self, rays: FloatArray) -> np.ndarray:
        """``(N,)`` int: the lens that images each ray direction (rig frame): the one whose
        optical axis is nearest."""
        r = as_points(rays, 3, "rays")
        return np.asarray(np.argmax(r @ self.axes.T, axis=1), dtype=np.int64)

    def ray_origins(self, rays: FloatArray) -> FloatArray:
        """``(N, 3)`` the centre (rig frame, metres) of the lens imaging each ray."""
        return self.centres[self.lens_of_rays(rays)]

    def lens_of_pixels(self, uv: FloatArray) -> np.ndarray:
        """``(N,)`` int: the lens whose part of the frame holds each pixel (-1: none)."""
        p = as_points(uv, 2, "uv")
        out = np.full(len(p), -1, dtype=np.int64)
        for k, cam in enumerate(self.lenses):
            x0, y0 = self.corners[k]
            with np.errstate(invalid="ignore"):
                inside = ((p[:, 0] >= x0 - 0.5) & (p[:, 0] < x0 + cam.width - 0.5)
                          & (p[:, 1] >= y0 - 0.5) & (p[:, 1] < y0 + cam.height - 0.5))
            out[inside & (out < 0)] = k
        return out

    def _rays_block(self, uv: FloatArray) -> FloatArray:
        out = np.full((len(uv), 3), np.nan)
        lens = self.lens_of_pixels(uv)
        for k, cam in enumerate(self.lenses):
            idx = np.flatnonzero(lens == k)
            if idx.size == 0:
                continue
            r = cam.rays_from_pixels(uv[idx] - self.corners[k]) @ self.rotations[k].T
            with np.errstate(invalid="ignore"):
                own = self.lens_of_rays(np.nan_to_num(r)) == k
            r[~own] = np.nan
            out[idx] = r
        return out

    def _pixels_block(self, rays: FloatArray) -> FloatArray:
        out = np.full((len(rays), 2), np.nan)
        with np.errstate(invalid="ignore"):
            lens = self.lens_of_rays(np.nan_to_num(rays))
        for k, cam in enumerate(self.lenses):
            idx = np.flatnonzero(lens == k)
            if idx.size:
                out[idx] = cam.pixels_from_rays(rays[idx] @ self.rotations[k]) + self.corners[k]
        return out

    def frame_size_mismatch(self, width: int, height: int) -> str:
        """Frames of another size than the rig's: how to make them, or use one lens alone."""
        whose, one, many = ("the camchain's", "camera", "cameras") if self.camchain else \
            ("the rig's", "lens", "lenses")
        where = "side by side" if self.layout == "side_by_side" else "one above the other"
        return (f"frames are {width} x {height} but {whose} {self.num_lenses} {many} {where} "
                f"are {self.width} x {self.height}: put the {many}' images {where}, or convert "
                f"one {one} with 'omni-sfm camera convert {self.file or 'CAMERA_FILE'} "
                "--lens 0'")

    def params(self) -> dict[str, Any]:
        lenses = []
        for cam, T in zip(self.lenses, self.rig_from_lens, strict=True):
            p = cam.params()
            p["rig_from_lens"] = [[float(x) for x in row] for row in T]
            lenses.append(p)
        return {"model": self.model, "width": self.width, "height": self.height,
                "layout": self.layout, "lenses": lenses}

    @classmethod
    def from_params(cls, data: dict[str, Any], path: Path | str) -> RigCamera:
        """The rig of a camera file's keys (``model: rig``; see docs/cameras.md)."""
        from omni_sfm.cameras.io import camera_from_dict

        unknown = set(data) - {"model", "width", "height", "layout", "lenses"}
        if unknown:
            raise OmniSfmError(f"{path}: unknown key {sorted(unknown)[0]!r} for model 'rig' "
                               "(known: width, height, layout, lenses)")
        lens_data = data.get("lenses")
        if not isinstance(lens_data, list) or len(lens_data) < 2:
            raise OmniSfmError(f"{path}: key 'lenses' must list two or more lenses")
        lenses, T = [], []
        for k, lens in enumerate(lens_data):
            if not isinstance(lens, dict):
                raise OmniSfmError(f"{path}: key 'lenses[{k}]' must be a mapping")
            lens = dict(lens)
            if "rig_from_lens" not in lens:
                raise OmniSfmError(f"{path}: missing key 'lenses[{k}].rig_from_lens'")
            T.append(rigid_transform(path, f"lenses[{k}].rig_from_lens", lens.pop("rig_from_lens")))
            if lens.get("model") == cls.model:
                raise OmniSfmError(f"{path}: key 'lenses[{k}]' must be a central lens model")
            lenses.append(camera_from_dict(lens, f"{path} lenses[{k}]"))
        layout = data.get("layout", "side_by_side")
        w, h = frame_size(lenses, layout if layout in LAYOUTS else LAYOUTS[0])
        width, height = data.get("width", w), data.get("height", h)
        try:
            return cls(width=width, height=height, lenses=tuple(lenses),
                       rig_from_lens=np.array(T), layout=layout)
        except (TypeError, ValueError) as exc:
            raise OmniSfmError(f"{path}: invalid 'rig' camera: {exc}") from None

    def summary(self) -> str:
        lines = [f"model: rig of {self.num_lenses} lenses, {self.layout}",
                 f"size: {self.width} x {self.height} px"]
        for k, cam in enumerate(self.lenses):
            c = self.centres[k]
            ang = math.degrees(math.acos(float(np.clip(self.axes[k] @ self.axes[0], -1, 1))))
            lines.append(f"lens {k}: {cam.model} {cam.width} x {cam.height} px at pixel "
                         f"{tuple(int(x) for x in self.corners[k])}, centre "
                         f"({c[0]:.4f}, {c[1]:.4f}, {c[2]:.4f}) m, axis {ang:.1f} deg from "
                         "lens 0's")
        lines.append(f"valid pixels: {100 * float(self.valid_mask().mean()):.1f} %")
        lines.append("COLMAP: one camera per lens in a rig (export colmap)")
        return "\n".join(lines)


def dual_fisheye(lens: CameraModel, *, baseline: float = 0.04,
                 layout: str = "side_by_side") -> RigCamera:
    """Two copies of ``lens`` back to back (lens 1 turned 180 deg about the rig's y axis),
    their centres ``baseline`` metres apart along lens 0's axis, the rig's origin between."""
    T0, T1 = np.eye(4), np.eye(4)
    T0[2, 3] = baseline / 2
    T1[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    T1[2, 3] = -baseline / 2
    w, h = (2 * lens.width, lens.height) if layout == "side_by_side" else \
        (lens.width, 2 * lens.height)
    return RigCamera(width=w, height=h, lenses=(lens, lens), rig_from_lens=np.array([T0, T1]),
                     layout=layout)
