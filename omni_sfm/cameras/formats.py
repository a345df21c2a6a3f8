"""Readers for the camera files other tools write, turned into omni-sfm camera dicts.

Each reader returns the keys of an omni-sfm camera file (docs/cameras.md); ``load_camera`` then
builds and checks the camera with ``camera_from_dict``. Pixel conventions are converted here:
omni-sfm pixels are OpenCV's (centre of the top-left pixel at 0), COLMAP's at 0.5.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.errors import OmniSfmError


def _num(path: Path, key: str, value: Any) -> float:
    """``value`` as a finite float, or OmniSfmError naming the file and key."""
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise OmniSfmError(f"{path}: key {key!r} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(out):
        raise OmniSfmError(f"{path}: key {key!r} must be a finite number, got {value!r}")
    return out


def _int(path: Path, key: str, value: Any) -> int:
    out = _num(path, key, value)
    if out != int(out):
        raise OmniSfmError(f"{path}: key {key!r} must be an integer, got {value!r}")
    return int(out)


def _numbers(path: Path, key: str, values: Any, count: int | None = None) -> list[float]:
    if not isinstance(values, list | tuple):
        raise OmniSfmError(f"{path}: key {key!r} must be a list of numbers, got {values!r}")
    if count is not None and len(values) != count:
        raise OmniSfmError(
            f"{path}: key {key!r} must have {count} numbers, got {len(values)}: {values!r}"
        )
    return [_num(path, f"{key}[{i}]", v) for i, v in enumerate(values)]


# ---------------------------------------------------------------- OpenCV FileStorage (omnidir)

def _fs_matrix(path: Path, fs: Any, key: str) -> list[float] | None:
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        return None
    if node.isReal() or node.isInt():
        return [_num(path, key, node.real())]
    if node.isSeq():
        return [_num(path, f"{key}[{i}]", node.at(i).real()) for i in range(node.size())]
    mat = node.mat()
    if mat is None:
        raise OmniSfmError(f"{path}: key {key!r} must be a number or a matrix")
    return [_num(path, f"{key}[{i}]", v) for i, v in enumerate(mat.ravel().tolist())]


def _fs_first(path: Path, fs: Any, keys: tuple[str, ...]) -> list[float] | None:
    for key in keys:
        val = _fs_matrix(path, fs, key)
        if val is not None:
            return val
    return None


def read_opencv_storage(path: Path) -> dict[str, Any]:
    """An OpenCV FileStorage file (YAML ``%YAML:1.0`` or XML) with ``cv2.omnidir.calibrate``'s
    results: ``K`` (3x3; alias ``camera_matrix``), ``D`` (k1 k2 p1 p2; alias
    ``distortion_coefficients``), ``xi``, and the image size as ``width``/``height``,
    ``image_width``/``image_height`` or ``image_size`` ([w, h]). Becomes a ``unified`` camera.
    """
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:
        # cv2 reports parse errors as cv2.error (or SystemError wrapping it): keep one line
        lines = [ln for ln in str(exc).splitlines() if "error:" in ln] or ["parse error"]
        msg = lines[-1].split("error:", 1)[-1].strip()
        raise OmniSfmError(f"{path}: not a readable OpenCV FileStorage file: {msg}") from None
    try:
        if not fs.isOpened():
            raise OmniSfmError(f"{path}: not a readable OpenCV FileStorage file")
        k = _fs_first(path, fs, ("K", "camera_matrix"))
        d = _fs_first(path, fs, ("D", "distortion_coefficients"))
        xi = _fs_matrix(path, fs, "xi")
        size = _fs_first(path, fs, ("image_size", "size"))
        w = _fs_first(path, fs, ("width", "image_width"))
        h = _fs_first(path, fs, ("height", "image_height"))
    finally:
        fs.release()
    if k is None:
        raise OmniSfmError(f"{path}: missing key 'K' (the 3x3 camera matrix)")
    if len(k) != 9:
        raise OmniSfmError(f"{path}: key 'K' must be a 3x3 matrix, got {len(k)} numbers")
    if xi is None:
        raise OmniSfmError(f"{path}: missing key 'xi' (cv2.omnidir's mirror parameter)")
    if len(xi) != 1:
        raise OmniSfmError(f"{path}: key 'xi' must be one number, got {xi!r}")
    if d is None:
        d = [0.0, 0.0, 0.0, 0.0]
    if len(d) != 4:
        raise OmniSfmError(f"{path}: key 'D' must hold 4 numbers (k1 k2 p1 p2), got {d!r}")
    if size is not None and w is None and h is None:
        if len(size) != 2:
            raise OmniSfmError(f"{path}: key 'image_size' must be [width, height], got {size!r}")
        w, h = [size[0]], [size[1]]
    if w is None:
        raise OmniSfmError(f"{path}: missing key 'width' (or 'image_width' / 'image_size')")
    if h is None:
        raise OmniSfmError(f"{path}: missing key 'height' (or 'image_height' / 'image_size')")
    if k[3] != 0 or k[6] != 0 or k[7] != 0 or k[8] != 1:
        raise OmniSfmError(f"{path}: key 'K' must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
    return {
        "model": "unified",
        "width": _int(path, "width", w[0]), "height": _int(path, "height", h[0]),
        "fx": k[0], "fy": k[4], "cx": k[2], "cy": k[5], "skew": k[1], "xi": xi[0],
        "k1": d[0], "k2": d[1], "p1": d[2], "p2": d[3],
    }


# ---------------------------------------------------------------- Kalibr camchain

def _kalibr_cameras(path: Path, data: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """``(key prefix, camera mapping)`` of each camera of a camchain, ``cam0`` first (a single
    camera mapping: one, with no prefix)."""
    if "camera_model" in data:
        return [("", data)]
    cams = sorted(
        (k for k, v in data.items() if isinstance(v, dict) and "camera_model" in v),
        key=lambda k: (int(m.group(1)) if (m := re.search(r"(\d+)$", str(k))) else 1 << 30, k),
    )
    if not cams:
        raise OmniSfmError(f"{path}: no camera with key 'camera_model' (Kalibr camchain)")
    return [(f"{k}.", data[k]) for k in cams]


def read_kalibr(path: Path, data: dict[str, Any], lens: int | None = None) -> dict[str, Any]:
    """A Kalibr camchain (``cam0: {camera_model, intrinsics, distortion_model,
    distortion_coeffs, resolution}``, ``cam1: {..., T_cn_cnm1}``, ...) or a single camera
    mapping with those keys. One camera becomes that camera; several become a ``rig`` (see
    :func:`kalibr_rig`); ``lens``: only camera ``lens`` of the chain (``cam<lens>``)."""
    cams = _kalibr_cameras(path, data)
    if lens is not None:
        if not 0 <= lens < len(cams):
            names = ", ".join(pre[:-1] or "one camera mapping" for pre, _ in cams)
            raise OmniSfmError(f"{path}: no camera {lens} (counted from 0): the file holds "
                               f"{len(cams)} ({names})")
        return kalibr_camera(path, *cams[lens])
    if len(cams) == 1:
        return kalibr_camera(path, *cams[0])
    return kalibr_rig(path, cams)


def kalibr_rig(path: Path, cams: list[tuple[str, dict[str, Any]]]) -> dict[str, Any]:
    """The ``rig`` camera keys of a camchain's cameras chained by ``T_cn_cnm1`` (camera n-1's
    points into camera n's frame, metres): rig frame = cam0's, ``rig_from_lens[0] = I``,
    ``rig_from_lens[n] = rig_from_lens[n-1] @ inv(T_cn_cnm1)``; their images side by side,
    cam0 leftmost."""
    from omni_sfm.cameras.rig import rigid_transform

    lenses: list[dict[str, Any]] = []
    rig_from_lens = np.eye(4)
    for n, (pre, cam) in enumerate(cams):
        lens = kalibr_camera(path, pre, cam)
        if n > 0:
            key = pre + "T_cn_cnm1"
            if "T_cn_cnm1" not in cam:
                raise OmniSfmError(
                    f"{path}: missing key {key!r} ({cams[n - 1][0][:-1]}'s frame into "
                    f"{pre[:-1]}'s, which makes the camchain's cameras one rig; for one camera: "
                    f"'omni-sfm camera convert {path} --lens 0')")
            T = rigid_transform(path, key, cam["T_cn_cnm1"])
            rig_from_lens = rig_from_lens @ np.linalg.inv(T)
            axes = [np.asarray(p["rig_from_lens"])[:3, 2] for p in lenses]
            for k, axis in enumerate(axes):
                if np.linalg.norm(axis - rig_from_lens[:3, 2]) < 1e-6:
                    raise OmniSfmError(
                        f"{path}: {cams[k][0][:-1]} and {pre[:-1]} look the same way (a stereo "
                        "pair?): a camchain is read as one rig of cameras that each image their "
                        f"own directions; for one camera: 'omni-sfm camera convert {path} "
                        f"--lens {k}'")
        lens["rig_from_lens"] = [[float(x) for x in row] for row in rig_from_lens]
        lenses.append(lens)
    return {
        "model": "rig",
        "width": sum(p["width"] for p in lenses),
        "height": max(p["height"] for p in lenses),
        "layout": "side_by_side",
        "lenses": lenses,
    }


def kalibr_camera(path: Path, pre: str, cam: dict[str, Any]) -> dict[str, Any]:
    """One Kalibr camera mapping (its keys named ``pre + key`` in messages). Models: ``omni``
    (+ ``radtan``/``none``) -> ``unified``, ``eucm``, ``ds`` -> ``double_sphere``, ``pinhole``
    + ``equidistant`` -> ``opencv_fisheye``, ``pinhole`` + ``radtan``/``none`` -> ``unified``
    with ``xi = 0``. Kalibr's pixels are OpenCV's (no shift)."""

    def get(key: str) -> Any:
        if key not in cam:
            raise OmniSfmError(f"{path}: missing key {pre + key!r}")
        return cam[key]

    model = get("camera_model")
    dist = cam.get("distortion_model", "none")
    dist = "none" if dist is None else str(dist)
    res = _numbers(path, pre + "resolution", get("resolution"), 2)
    out: dict[str, Any] = {
        "width": _int(path, pre + "resolution[0]", res[0]),
        "height": _int(path, pre + "resolution[1]", res[1]),
    }
    coeffs_raw = cam.get("distortion_coeffs") or []
    coeffs = _numbers(path, pre + "distortion_coeffs", coeffs_raw)
    if dist == "none" and any(coeffs):
        raise OmniSfmError(f"{path}: key {pre + 'distortion_coeffs'!r} given but "
                           "distortion_model is none")

    def radtan() -> dict[str, float]:
        if dist == "none":
            return {}
        if len(coeffs) != 4:
            raise OmniSfmError(f"{path}: key {pre + 'distortion_coeffs'!r} must have 4 numbers "
                               f"(k1 k2 r1 r2) for radtan, got {coeffs!r}")
        return dict(zip(("k1", "k2", "p1", "p2"), coeffs, strict=True))

    supported = {
        ("omni", "radtan"), ("omni", "none"), ("eucm", "none"), ("ds", "none"),
        ("pinhole", "equidistant"), ("pinhole", "radtan"), ("pinhole", "none"),
    }
    if (model, dist) not in supported:
        raise OmniSfmError(
            f"{path}: unsupported Kalibr camera {pre + 'camera_model'!r} = {model!r} with "
            f"distortion_model {dist!r} (supported: omni/pinhole + radtan or none, eucm, ds, "
            "pinhole + equidistant)"
        )
    n = {"omni": 5, "eucm": 6, "ds": 6, "pinhole": 4}[model]
    it = _numbers(path, pre + "intrinsics", get("intrinsics"), n)
    if model == "omni":
        out.update(model="unified", xi=it[0], fx=it[1], fy=it[2], cx=it[3], cy=it[4])
        out.update(radtan())
    elif model == "eucm":
        out.update(model="eucm", alpha=it[0], beta=it[1], fx=it[2], fy=it[3], cx=it[4], cy=it[5])
    elif model == "ds":
        out.update(model="double_sphere", xi=it[0], alpha=it[1],
                   fx=it[2], fy=it[3], cx=it[4], cy=it[5])
    elif dist == "equidistant":
        if len(coeffs) != 4:
            raise OmniSfmError(f"{path}: key {pre + 'distortion_coeffs'!r} must have 4 numbers "
                               f"(k1 k2 k3 k4) for equidistant, got {coeffs!r}")
        out.update(model="opencv_fisheye", fx=it[0], fy=it[1], cx=it[2], cy=it[3])
        out.update(zip(("k1", "k2", "k3", "k4"), coeffs, strict=True))
    else:
        out.update(model="unified", xi=0.0, fx=it[0], fy=it[1], cx=it[2], cy=it[3])
        out.update(radtan())
    return out


# ---------------------------------------------------------------- OCamCalib calib_results.txt

OCAM_MARKER = "polynomial coefficients for the direct mapping"


def read_ocamcalib(path: Path, text: str) -> dict[str, Any]:
    """OCamCalib's ``calib_results.txt`` (as written by the toolbox's ``export_data``): after the
    ``#`` comment lines, five lines ``N a0 .. a(N-1)`` (pol, cam2world), ``M b0 .. b(M-1)``
    (invpol, world2cam), ``xc yc`` (the distortion centre's row and column, 0-based "C
    convention"), ``c d e`` (affine), ``height width``. Becomes an ``ocam`` camera with
    ``cx = yc`` (column), ``cy = xc`` (row)."""
    rows = [ln.split() for ln in text.splitlines()
            if ln.strip() and not ln.lstrip().startswith("#")]
    names = ("pol", "invpol", "center", "affine", "image size")
    if len(rows) < 5:
        raise OmniSfmError(
            f"{path}: OCamCalib file needs 5 data lines (pol, invpol, center, affine, image size),"
            f" found {len(rows)}: missing {names[len(rows)]!r}"
        )
    vals = [[_num(path, names[i], v) for v in row] for i, row in enumerate(rows[:5])]

    def poly(i: int) -> list[float]:
        n = _int(path, f"{names[i]} count", vals[i][0])
        if n < 1 or len(vals[i]) != n + 1:
            raise OmniSfmError(
                f"{path}: key {names[i]!r}: the line announces {n} coefficients but holds "
                f"{len(vals[i]) - 1}"
            )
        return vals[i][1:]

    pol, invpol = poly(0), poly(1)
    for i, count in ((2, 2), (3, 3), (4, 2)):
        if len(vals[i]) != count:
            raise OmniSfmError(
                f"{path}: key {names[i]!r} must have {count} numbers, got {len(vals[i])}"
            )
    return {
        "model": "ocam",
        "height": _int(path, "height", vals[4][0]), "width": _int(path, "width", vals[4][1]),
        "cx": vals[2][1], "cy": vals[2][0],
        "c": vals[3][0], "d": vals[3][1], "e": vals[3][2],
        "pol": pol, "invpol": invpol,
    }


# ---------------------------------------------------------------- COLMAP cameras.txt

def colmap_model_names() -> set[str]:
    import pycolmap

    return set(pycolmap.CameraModelId.__members__) - {"INVALID"}


def read_colmap_cameras_txt(path: Path, text: str) -> dict[str, Any]:
    """COLMAP's ``cameras.txt`` (``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``; the first camera is
    read). COLMAP pixels are shifted by -0.5 into ours. Models: ``EUCM`` -> ``eucm``,
    ``OPENCV_FISHEYE`` -> ``opencv_fisheye``, ``EQUIRECTANGULAR`` -> ``equirectangular``,
    ``SIMPLE_PINHOLE``, ``PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV`` -> ``unified``
    with ``xi = 0`` (the same pinhole + radtan equations)."""
    lines = [ln.split() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
    if not lines:
        raise OmniSfmError(f"{path}: COLMAP cameras.txt holds no camera line")
    tok = lines[0]
    if len(tok) < 4:
        raise OmniSfmError(f"{path}: COLMAP camera line needs CAMERA_ID MODEL WIDTH HEIGHT PARAMS")
    model = tok[1]
    w, h = _int(path, "WIDTH", tok[2]), _int(path, "HEIGHT", tok[3])
    p = [_num(path, f"PARAMS[{i}]", v) for i, v in enumerate(tok[4:])]
    counts = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8,
              "OPENCV_FISHEYE": 8, "EUCM": 6, "EQUIRECTANGULAR": 2}
    if model not in counts:
        raise OmniSfmError(
            f"{path}: COLMAP camera MODEL {model!r} has no exact omni-sfm model "
            f"(supported: {', '.join(sorted(counts))})"
        )
    if len(p) != counts[model]:
        raise OmniSfmError(
            f"{path}: COLMAP {model} needs {counts[model]} PARAMS, got {len(p)}"
        )
    out: dict[str, Any] = {"width": w, "height": h}
    if model == "EQUIRECTANGULAR":
        if p != [float(w), float(h)]:
            raise OmniSfmError(
                f"{path}: COLMAP EQUIRECTANGULAR PARAMS must equal WIDTH HEIGHT, got {p!r}"
            )
        out["model"] = "equirectangular"
        return out
    if model.startswith("SIMPLE_"):
        p = [p[0], *p]  # f -> fx, fy
    fx, fy, cx, cy, *rest = p
    out.update(fx=fx, fy=fy, cx=cx - 0.5, cy=cy - 0.5)
    if model == "EUCM":
        out.update(model="eucm", alpha=rest[0], beta=rest[1])
    elif model == "OPENCV_FISHEYE":
        out.update(model="opencv_fisheye", k1=rest[0], k2=rest[1], k3=rest[2], k4=rest[3])
    else:
        out.update(model="unified", xi=0.0)
        out.update(zip(("k1", "k2", "p1", "p2"), rest, strict=False))
    return out


def looks_like_colmap(text: str) -> bool:
    """The first data line reads ``<int> <COLMAP MODEL NAME> <int> <int> ...``."""
    for ln in text.splitlines():
        if not ln.strip() or ln.startswith("#"):
            continue
        tok = ln.split()
        return len(tok) >= 4 and tok[0].isdigit() and tok[1] in colmap_model_names()
    return False
