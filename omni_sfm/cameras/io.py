"""Camera files: omni-sfm's YAML (documented in docs/cameras.md), read and written."""

from __future__ import annotations

import math
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Any

import yaml

from omni_sfm.cameras import formats
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


def _model_class(data: Any, path: Path) -> tuple[str, type[CameraModel]]:
    """The model name and registered class a camera mapping names under ``model``."""
    if not isinstance(data, dict):
        raise OmniSfmError(f"{path}: camera file must be a YAML mapping")
    name = data.get("model")
    if name is None:
        raise OmniSfmError(f"{path}: missing key 'model' (one of {', '.join(sorted(MODELS))})")
    if not isinstance(name, str) or name not in MODELS:
        raise OmniSfmError(
            f"{path}: unknown camera model {name!r} (known: {', '.join(sorted(MODELS))})"
        )
    return name, MODELS[name]


def _flat_keys(data: dict[str, Any], path: Path) -> dict[str, Any]:
    """The camera keys without ``model``, with the ``mask`` mapping's keys lifted to the top."""
    flat = dict(data)
    flat.pop("model")
    mask = flat.pop("mask", None)
    if isinstance(mask, dict):
        for k, v in mask.items():
            if k not in ("inner_radius", "outer_radius"):
                raise OmniSfmError(
                    f"{path}: unknown key 'mask.{k}' (mask takes inner_radius, outer_radius)"
                )
            flat[k] = v
    elif mask is not None:
        raise OmniSfmError(f"{path}: key 'mask' must be a mapping, got {mask!r}")
    return flat


def _field_value(path: Path, f: Any, val: Any, required: bool) -> Any:
    """One dataclass field's value checked and converted from its YAML value."""
    if val is None and not required:
        return None
    if f.name in ("width", "height"):
        return _number(path, f.name, val, integer=True)
    if "tuple" in str(f.type):
        if not isinstance(val, list):
            raise OmniSfmError(f"{path}: key {f.name!r} must be a list of numbers, got {val!r}")
        return tuple(_number(path, f"{f.name}[{i}]", v) for i, v in enumerate(val))
    return _number(path, f.name, val)


def _model_kwargs(
    cls: type[CameraModel], name: str, flat: dict[str, Any], path: Path
) -> dict[str, Any]:
    """The constructor arguments of ``cls`` taken (and removed) from ``flat``."""
    kwargs: dict[str, Any] = {}
    for f in fields(cls):
        required = f.default is MISSING and f.default_factory is MISSING
        if f.name not in flat:
            if required:
                raise OmniSfmError(f"{path}: missing key {f.name!r} for model {name!r}")
            continue
        kwargs[f.name] = _field_value(path, f, flat.pop(f.name), required)
    return kwargs


def camera_from_dict(data: dict[str, Any], path: Path | str = "<camera>") -> CameraModel:
    """Build a camera from the keys of an omni-sfm camera file (see docs/cameras.md)."""
    path = Path(path)
    name, cls = _model_class(data, path)
    from_params = getattr(cls, "from_params", None)
    if from_params is not None:  # a composite model (a rig of lenses) reads its own keys
        return from_params(data, path)
    flat = _flat_keys(data, path)
    kwargs = _model_kwargs(cls, name, flat, path)
    if flat:
        known = ", ".join(f.name for f in fields(cls))
        raise OmniSfmError(
            f"{path}: unknown key {next(iter(flat))!r} for model {name!r} (known: {known}, mask)"
        )
    for key in ("width", "height"):
        if kwargs.get(key, 1) <= 0:
            raise OmniSfmError(f"{path}: key {key!r} must be positive, got {kwargs[key]}")
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise OmniSfmError(f"{path}: invalid {name!r} camera: {exc}") from None


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise OmniSfmError(f"{path}: camera file not found") from None
    except IsADirectoryError:
        raise OmniSfmError(f"{path}: camera file is a directory") from None
    except UnicodeDecodeError:
        raise OmniSfmError(f"{path}: camera file is not UTF-8 text") from None
    except OSError as exc:
        raise OmniSfmError(f"{path}: cannot read camera file: {exc.strerror}") from None


def _parse_yaml(path: Path, text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise OmniSfmError(f"{path}: not valid YAML: {str(exc).splitlines()[0]}") from None


def read_camera_yaml(path: Path) -> CameraModel:
    """Read an omni-sfm camera YAML file."""
    path = Path(path)
    return camera_from_dict(_parse_yaml(path, _read_text(path)), path)


def camera_dict_from_file(path: Path | str) -> dict[str, Any]:
    """The omni-sfm camera keys of any supported camera file, format detected from content:
    OpenCV FileStorage (``%YAML:1.0`` or ``<opencv_storage>``), OCamCalib
    ``calib_results.txt``, COLMAP ``cameras.txt``, Kalibr camchain YAML, omni-sfm YAML."""
    path = Path(path)
    text = _read_text(path)
    head = text.lstrip()[:200]
    if head.startswith("%YAML:1") or "<opencv_storage>" in head or "!!opencv-matrix" in text:
        return formats.read_opencv_storage(path)
    if formats.OCAM_MARKER in text.lower():
        return formats.read_ocamcalib(path, text)
    if formats.looks_like_colmap(text):
        return formats.read_colmap_cameras_txt(path, text)
    data = _parse_yaml(path, text)
    if isinstance(data, dict) and "model" in data:
        return data
    if isinstance(data, dict) and ("K" in data or "camera_matrix" in data):
        return formats.read_opencv_storage(path)
    if isinstance(data, dict) and (
        "camera_model" in data
        or any(isinstance(v, dict) and "camera_model" in v for v in data.values())
    ):
        return formats.read_kalibr(path, data)
    raise OmniSfmError(
        f"{path}: unrecognised camera file: expected an omni-sfm camera YAML (key 'model'), an "
        "OpenCV FileStorage file, a Kalibr camchain, OCamCalib calib_results.txt or COLMAP "
        "cameras.txt"
    )


def write_camera_yaml(path: Path, camera: CameraModel) -> None:
    """Write ``camera`` as an omni-sfm camera YAML file (atomically)."""
    p = camera.params()
    mask = {k: p.pop(k) for k in ("inner_radius", "outer_radius") if k in p}
    mask = {k: v for k, v in mask.items() if v is not None}
    if mask:
        p["mask"] = mask
    atomic_write_text(Path(path), yaml.safe_dump(p, sort_keys=False))


def load_camera(path: Path | str) -> CameraModel:
    """Load any camera file omni-sfm reads, unchanged as the tools write it (format detected
    from the content, see :func:`camera_dict_from_file` and docs/cameras.md).

    Raises OmniSfmError (one line naming the file and key) for unreadable or invalid files."""
    path = Path(path)
    return camera_from_dict(camera_dict_from_file(path), path)
