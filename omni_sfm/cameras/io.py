"""Camera files: omni-sfm's YAML (documented in docs/cameras.md), read and written."""

from __future__ import annotations

import math
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Any

import yaml

from omni_sfm.cameras.base import CameraModel
from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import atomic_write_text

MODELS: dict[str, type[CameraModel]] = {}


def register_model(cls: type[CameraModel]) -> type[CameraModel]:
    """Make ``cls`` loadable from camera files under ``cls.model``."""
    MODELS[cls.model] = cls
    return cls


def _number(path: Path, key: str, value: Any, *, integer: bool = False) -> float | int:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise OmniSfmError(f"{path}: key {key!r} must be a number, got {value!r}")
    if not math.isfinite(float(value)):
        raise OmniSfmError(f"{path}: key {key!r} must be finite, got {value!r}")
    if integer:
        if float(value) != int(value):
            raise OmniSfmError(f"{path}: key {key!r} must be an integer, got {value!r}")
        return int(value)
    return float(value)


def camera_from_dict(data: dict[str, Any], path: Path | str = "<camera>") -> CameraModel:
    """Build a camera from the keys of an omni-sfm camera file (see docs/cameras.md)."""
    path = Path(path)
    if not isinstance(data, dict):
        raise OmniSfmError(f"{path}: camera file must be a YAML mapping")
    name = data.get("model")
    if name is None:
        raise OmniSfmError(f"{path}: missing key 'model' (one of {', '.join(sorted(MODELS))})")
    if name not in MODELS:
        raise OmniSfmError(
            f"{path}: unknown camera model {name!r} (known: {', '.join(sorted(MODELS))})"
        )
    cls = MODELS[name]
    flat = dict(data)
    flat.pop("model")
    mask = flat.pop("mask", None)
    if isinstance(mask, dict):
        for k, v in mask.items():
            flat[k] = v
    elif mask is not None:
        raise OmniSfmError(f"{path}: key 'mask' must be a mapping, got {mask!r}")
    kwargs: dict[str, Any] = {}
    for f in fields(cls):
        required = f.default is MISSING and f.default_factory is MISSING
        if f.name not in flat:
            if required:
                raise OmniSfmError(f"{path}: missing key {f.name!r} for model {name!r}")
            continue
        val = flat.pop(f.name)
        if val is None and not required:
            kwargs[f.name] = None
        elif f.name in ("width", "height"):
            kwargs[f.name] = _number(path, f.name, val, integer=True)
        elif isinstance(val, list):
            kwargs[f.name] = tuple(_number(path, f"{f.name}[{i}]", v) for i, v in enumerate(val))
        else:
            kwargs[f.name] = _number(path, f.name, val)
    for key in ("width", "height"):
        if kwargs.get(key, 1) <= 0:
            raise OmniSfmError(f"{path}: key {key!r} must be positive, got {kwargs[key]}")
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise OmniSfmError(f"{path}: invalid {name!r} camera: {exc}") from None


def read_camera_yaml(path: Path) -> CameraModel:
    """Read an omni-sfm camera YAML file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise OmniSfmError(f"{path}: camera file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise OmniSfmError(f"{path}: cannot read camera file: {exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise OmniSfmError(f"{path}: not valid YAML: {str(exc).splitlines()[0]}") from None
    return camera_from_dict(data, path)


def write_camera_yaml(path: Path, camera: CameraModel) -> None:
    """Write ``camera`` as an omni-sfm camera YAML file (atomically)."""
    p = camera.params()
    mask = {k: p.pop(k) for k in ("inner_radius", "outer_radius") if k in p}
    mask = {k: v for k, v in mask.items() if v is not None}
    if mask:
        p["mask"] = mask
    atomic_write_text(Path(path), yaml.safe_dump(p, sort_keys=False))


def load_camera(path: Path | str) -> CameraModel:
    """Load any camera file omni-sfm reads (see docs/cameras.md)."""
    return read_camera_yaml(Path(path))
