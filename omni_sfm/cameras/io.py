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


def camera_dict_from_file(path: Path | str, lens: int | None = None) -> dict[str, Any]:
    """The omni-sfm camera keys of any supported camera file, format detected from content:
    OpenCV FileStorage (``%YAML:1.0`` or ``<opencv_storage>``), OCamCalib
    ``calib_results.txt``, COLMAP ``cameras.txt``, Kalibr camchain YAML, omni-sfm YAML.

    ``lens``: only that camera of a Kalibr camchain (``cam<lens>``) or lens of a ``rig``
    camera file (counted from 0); of a file with one camera, 0 is that camera."""
    return _camera_dict(Path(path), lens)[0]


def _camera_dict(path: Path, lens: int | None) -> tuple[dict[str, Any], str]:
    """:func:`camera_dict_from_file`'s keys and the format read (``kalibr`` or ``other``)."""
    if lens is not None and (isinstance(lens, bool) or not isinstance(lens, int) or lens < 0):
        raise OmniSfmError(f"lens must be an integer >= 0, got {lens!r}")
    text = _read_text(path)
    head = text.lstrip()[:200]
    data: Any = None
    if head.startswith("%YAML:1") or "<opencv_storage>" in head or "!!opencv-matrix" in text:
        out = formats.read_opencv_storage(path)
    elif formats.OCAM_MARKER in text.lower():
        out = formats.read_ocamcalib(path, text)
    elif formats.looks_like_colmap(text):
        out = formats.read_colmap_cameras_txt(path, text)
    else:
        data = _parse_yaml(path, text)
    if data is None:
        return _one_lens(path, out, lens), "other"
    if isinstance(data, dict) and "model" in data:
        return _one_lens(path, data, lens), "other"
    if isinstance(data, dict) and ("K" in data or "camera_matrix" in data):
        return _one_lens(path, formats.read_opencv_storage(path), lens), "other"
    if isinstance(data, dict) and (
        "camera_model" in data
        or any(isinstance(v, dict) and "camera_model" in v for v in data.values())
    ):
        return formats.read_kalibr(path, data, lens), "kalibr"
    raise OmniSfmError(
        f"{path}: unrecognised camera file: expected an omni-sfm camera YAML (key 'model'), an "
        "OpenCV FileStorage file, a Kalibr camchain, OCamCalib calib_results.txt or COLMAP "
        "cameras.txt"
    )


def _one_lens(path: Path, data: dict[str, Any], lens: int | None) -> dict[str, Any]:
    """``data``, or with ``lens`` its lens ``lens`` (a ``rig``'s, without its placement)."""
    if lens is None:
        return data
    lenses = data.get("lenses") if data.get("model") == "rig" else None
    if not isinstance(lenses, list):
        if lens == 0:
            return data
        raise OmniSfmError(f"{path}: no lens {lens}: the file holds one camera (model "
                           f"{data.get('model')!r}); a lens is one camera of a Kalibr camchain "
                           "or one of a 'rig' camera's lenses")
    if lens >= len(lenses):
        raise OmniSfmError(f"{path}: no lens {lens} (counted from 0): the rig has "
                           f"{len(lenses)} lenses")
    one = lenses[lens]
    if not isinstance(one, dict):
        raise OmniSfmError(f"{path}: key 'lenses[{lens}]' must be a mapping")
    return {k: v for k, v in one.items() if k != "rig_from_lens"}


def write_camera_yaml(path: Path, camera: CameraModel) -> None:
    """Write ``camera`` as an omni-sfm camera YAML file (atomically)."""

    def nested_mask(p: dict[str, Any]) -> dict[str, Any]:
        mask = {k: p.pop(k) for k in ("inner_radius", "outer_radius") if k in p}
        mask = {k: v for k, v in mask.items() if v is not None}
        if mask:
            p["mask"] = mask
        return p

    p = nested_mask(camera.params())
    if isinstance(p.get("lenses"), list):  # a rig: each lens's mask as its own
        p["lenses"] = [nested_mask(lens) for lens in p["lenses"]]
    atomic_write_text(Path(path), yaml.safe_dump(p, sort_keys=False))


def load_camera(path: Path | str, lens: int | None = None) -> CameraModel:
    """Load any camera file omni-sfm reads, unchanged as the tools write it (format detected
    from the content, see :func:`camera_dict_from_file` and docs/cameras.md). A Kalibr
    camchain of several cameras is a ``rig``; ``lens``: only that camera of it (or lens of a
    ``rig`` camera file).

    Raises OmniSfmError (one line naming the file and key) for unreadable or invalid files."""
    from omni_sfm.cameras.rig import RigCamera

    path = Path(path)
    data, kind = _camera_dict(path, lens)
    cam = camera_from_dict(data, path)
    if isinstance(cam, RigCamera):  # its messages name the file (and the camchain's cameras)
        object.__setattr__(cam, "file", str(path))
        object.__setattr__(cam, "camchain", kind == "kalibr")
    return cam
