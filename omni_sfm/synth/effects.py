"""Real-footage effects of the renderer (docs/rendering.md, "Effects (real footage)").

What a real omnidirectional camera adds to a clean rendering, each one an option of
:class:`Effects` and all off by default:

- motion blur from the camera's motion within the exposure (per-pixel flow of the scene point
  each pixel sees, between the shutter-open and shutter-close poses; a box filter along it);
- auto-exposure drift (slow) and flicker (frame to frame) of the gain, on linear radiance;
- vignetting (radial fall-off of the gain), on linear radiance;
- shot noise (grows with the square root of the signal), beside the renderer's read noise;
- JPEG frames or H.264 video (:func:`open_video_writer`);
- a camera-fixed body (operator, tripod, robot) occupying a fixed image region, or wobbling
  a little about the camera centre from frame to frame (a hand that holds the camera);
- a stitching seam of a dual-fisheye 360 camera (equirectangular only);
- a person-like occluder walking past the camera in the scene.

The body and the occluder are made of capped cylinders and spheres intersected analytically
(:class:`Shapes`); the renderer composites them with the scene by depth.
Frames here are the renderer's: the scene frame (metres, +Z up), ``world_from_cam`` rotations
of the camera model's ray frame.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from enum import StrEnum
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray
from omni_sfm.poses import Trajectory
from omni_sfm.synth.paths import BODY_FROM_CAM, Mount


class Body(StrEnum):
    """Camera-fixed geometry in view (see :data:`BODY_PARTS`)."""

    NONE = "none"
    OPERATOR = "operator"
    """A person behind and below the camera, holding it on a short pole."""
    TRIPOD = "tripod"
    """A tripod under the camera: a centre column and three legs down to the floor."""
    ROBOT = "robot"
    """A mobile robot under the camera: base, laser scanner, two upright handle posts."""


class VideoCodec(StrEnum):
    H264 = "h264"
    """H.264 (libx264 through PyAV), yuv420p, quality set by the CRF."""
    MP4V = "mp4v"
    """MPEG-4 Part 2 through OpenCV's writer."""


@dataclass(frozen=True, kw_only=True)
class Effects:
    """Real-footage effects; the defaults (all off) give the clean rendering."""

    motion_blur: float = 0.0
    """Exposure time as a fraction of the frame interval (0..1; 0: no motion blur)."""
    exposure_drift: float = 0.0
    """Peak amplitude of the slow auto-exposure gain drift, stops (0..4)."""
    flicker: float = 0.0
    """Peak relative amplitude of the frame-to-frame gain flicker (0..0.5)."""
    shot_noise: float = 0.0
    """Photon (shot) noise std-dev at full white, 8-bit grey levels; scales with the square
    root of the linear signal (the read noise is ``noise_sigma``)."""
    jpeg_quality: int | None = None
    """Write ``images/NNNNNN.jpg`` with this JPEG quality (1..100); None: PNG."""
    vignetting: float = 0.0
    """Fraction of light lost at the image rim (0..1): gain ``1 - v rho^2``."""
    body: Body = Body.NONE
    """Camera-fixed body in view (none, operator, tripod, robot)."""
    body_wobble_deg: float = 0.0
    """Peak rotation of the body about the camera centre per axis, degrees (0..10; 0: rigidly
    fixed): a smooth seeded wobble from frame to frame (:func:`body_wobble`)."""
    seam_deg: float = 0.0
    """Stitching-seam misalignment, degrees (equirectangular only; |seam| <= 10)."""
    occluder: bool = False
    """A person (0.5 m wide, 1.75 m tall) walks past the camera."""

    def is_off(self) -> bool:
        return self == Effects()


def footage_effects(mount: Mount, *, video: bool) -> Effects:
    """The ``--footage`` set: a realistic default for the camera's mount."""
    return Effects(
        motion_blur=0.5, exposure_drift=0.3, flicker=0.02, shot_noise=2.0,
        jpeg_quality=None if video else 85, vignetting=0.3,
        body=Body.ROBOT if Mount(mount) == Mount.ROBOT else Body.OPERATOR,
    )


def _check_range(name: str, value: Any, lo: float, hi: float, unit: str = "") -> None:
    ok = (not isinstance(value, bool) and isinstance(value, int | float | np.floating)
          and np.isfinite(value) and lo <= value <= hi)
    if not ok:
        raise OmniSfmError(f"{name} must be in [{lo:g}, {hi:g}]{unit}, got {value!r}")


def check_effects(effects: Effects, camera_model: str) -> None:
    """Raise OmniSfmError (one line) for an effect value out of range or not possible with
    this camera model."""
    e = effects
    _check_range("motion blur", e.motion_blur, 0.0, 1.0, " (fraction of the frame interval)")
    _check_range("exposure drift", e.exposure_drift, 0.0, 4.0, " stops")
    _check_range("flicker", e.flicker, 0.0, 0.5)
    _check_range("shot noise", e.shot_noise, 0.0, 100.0, " grey levels")
    _check_range("vignetting", e.vignetting, 0.0, 1.0)
    _check_range("seam", e.seam_deg, -10.0, 10.0, " deg")
    _check_range("body wobble", e.body_wobble_deg, 0.0, 10.0, " deg")
    q = e.jpeg_quality
    if q is not None and (isinstance(q, bool) or not isinstance(q, int | np.integer)
                          or not 1 <= q <= 100):
        raise OmniSfmError(f"JPEG quality must be an integer 1..100, got {q!r}")
    try:
        Body(e.body)
    except ValueError:
        raise OmniSfmError(
            f"unknown body {e.body!r} (known: {', '.join(b.value for b in Body)})") from None
    if e.seam_deg != 0 and camera_model != "equirectangular":
        raise OmniSfmError(f"a stitching seam needs an equirectangular camera, not {camera_model}")
    if not isinstance(e.occluder, bool):
        raise OmniSfmError(f"occluder must be true or false, got {e.occluder!r}")


def effects_json(effects: Effects) -> dict[str, Any]:
    """The effects as JSON values (enums as their names)."""
    out: dict[str, Any] = {}
    for f in fields(effects):
        v = getattr(effects, f.name)
        out[f.name] = v.value if isinstance(v, StrEnum) else v
    return out


# ---------------------------------------------------------------- gain, vignetting, noise

def frame_gain(effects: Effects, seed: int, frame_index: int) -> float:
    """Gain of frame ``frame_index`` on linear radiance from drift and flicker (1 when off).

    Drift: ``2 ** (A w(k))`` stops with ``w`` two seeded sines (periods 60..120 and 15..30
    frames, i.e. 4..8 s and 1..2 s at 15 fps) normalised to peak 1. Flicker: ``1 + F u_k``
    with ``u_k`` uniform in [-1, 1], seeded per frame.
    """
    g = 1.0
    k = float(frame_index)
    if effects.exposure_drift > 0:
        rng = np.random.default_rng([seed, 3301])
        p1, p2 = rng.uniform(60.0, 120.0), rng.uniform(15.0, 30.0)
        f1, f2 = rng.uniform(0.0, 2 * np.pi, size=2)
        w = (np.sin(2 * np.pi * k / p1 + f1) + 0.5 * np.sin(2 * np.pi * k / p2 + f2)) / 1.5
        g *= float(2.0 ** (effects.exposure_drift * w))
    if effects.flicker > 0:
        u = np.random.default_rng([seed, 3302, int(frame_index)]).uniform(-1.0, 1.0)
        g *= 1.0 + effects.flicker * float(u)
    return g


def vignetting_gain(camera: Any, uv: FloatArray, rays: FloatArray, strength: float
                    ) -> FloatArray:
    """``(P,)`` float32 gain ``1 - strength rho^2`` of pixels ``uv (P, 2)`` with centre rays
    ``rays (P, 3)``. ``rho``: for the equirectangular camera, the angle from the nearer lens
    axis (+-Z, a dual-fisheye 360 camera) over 90 deg; otherwise the distance from the
    principal point ``(cx, cy)`` (image centre without one) over the mirror's outer radius
    (or the farthest valid pixel)."""
    if camera.model == "equirectangular":
        rho = np.arccos(np.clip(np.abs(rays[:, 2]), 0.0, 1.0)) / (np.pi / 2)
    else:
        cx = getattr(camera, "cx", (camera.width - 1) / 2.0)
        cy = getattr(camera, "cy", (camera.height - 1) / 2.0)
        r = np.hypot(uv[:, 0] - cx, uv[:, 1] - cy)
        outer = getattr(camera, "outer_radius", None) or float(r.max(initial=1.0))
        rho = r / max(outer, 1e-9)
    return np.clip(1.0 - strength * rho**2, 0.0, 1.0).astype(np.float32)


# ------------------------------------------------------------------- shutter and blur

@dataclass(frozen=True)
class Shutter:
    """Camera poses (scene frame) when the shutter opens and closes; the frame's ground-truth
    pose is the one at mid-exposure."""

    open_rotation: FloatArray
    open_position: FloatArray
    close_rotation: FloatArray
    close_position: FloatArray


def pose_at(traj: Trajectory, t: float) -> tuple[FloatArray, FloatArray]:
    """``(world_from_cam (3, 3), centre (3,))`` at fractional frame index ``t``: slerp and lerp
    between the neighbouring poses, extrapolated from the first or last interval outside."""
    from scipy.spatial.transform import Rotation

    n = len(traj)
    if n == 1:
        return traj.rotations[0], traj.positions[0]
    i = int(np.clip(np.floor(t), 0, n - 2))
    s = t - i
    Ra, Rb = traj.rotations[i], traj.rotations[i + 1]
    step = Rotation.from_matrix(Ra.T @ Rb).as_rotvec()
    R = Ra @ Rotation.from_rotvec(s * step).as_matrix()
    c = traj.positions[i] + s * (traj.positions[i + 1] - traj.positions[i])
    return R, c


def shutter_poses(traj: Trajectory, frame_index: int, exposure: float) -> Shutter:
    """The shutter of frame ``frame_index`` open for ``exposure`` frame intervals, centred on
    the frame's pose."""
    R0, c0 = pose_at(traj, frame_index - exposure / 2)
    R1, c1 = pose_at(traj, frame_index + exposure / 2)
    return Shutter(R0, c0, R1, c1)


_MAX_TAPS = 9


def blur_along_flow(image: np.ndarray, weight: np.ndarray, flow: np.ndarray, *,
                    wrap_u: bool) -> np.ndarray:
    """Box-filter ``image (H, W, 3)`` along ``flow (H, W, 2)`` (pixels moved during the
    exposure): the mean of ``n`` bilinear taps at ``p + s flow(p)``, ``s`` evenly spread over
    ``[-1/2, 1/2]``, ``n`` = the 99th percentile of the flow length in px + 1 (2..9).
    ``weight (H, W)`` (1 on valid pixels, 0 elsewhere) keeps invalid pixels out of the mean.
    ``wrap_u``: the image is periodic in ``u`` (equirectangular; rows are clamped)."""
    import cv2

    length = np.sqrt((flow**2).sum(axis=2))
    moving = length[length > 1e-3]
    if len(moving) == 0:
        return image
    taps = int(np.clip(np.ceil(np.percentile(moving, 99)) + 1, 2, _MAX_TAPS))
    H, W = weight.shape
    # a periodic image with every pixel valid needs no weight channel
    plain = wrap_u and bool(weight.min() > 0)
    if plain:
        src = np.ascontiguousarray(image, dtype=np.float32)
    else:
        src = np.empty((H, W, 4), dtype=np.float32)
        src[..., :3] = image * weight[..., None]
        src[..., 3] = weight
    u = np.arange(W, dtype=np.float32)[None, :]
    v = np.arange(H, dtype=np.float32)[:, None]
    border = cv2.BORDER_WRAP if wrap_u else cv2.BORDER_CONSTANT
    acc = np.zeros_like(src)
    for j in range(taps):
        s = np.float32((j + 0.5) / taps - 0.5)
        map_v = v + s * flow[..., 1]
        if wrap_u:  # BORDER_WRAP would wrap the rows too
            np.clip(map_v, 0, H - 1, out=map_v)
        acc += cv2.remap(src, u + s * flow[..., 0], map_v, cv2.INTER_LINEAR,
                         borderMode=border, borderValue=0)
    if plain:
        return np.asarray(acc / np.float32(taps))
    w = acc[..., 3:]
    ok = w[..., 0] > 1e-6
    out = image.copy()
    out[ok] = acc[..., :3][ok] / w[ok]
    return out


def body_wobble(effects: Effects, seed: int, frame_index: int) -> FloatArray:
    """``(3, 3)`` rotation (camera frame, about the camera centre) of the body in frame
    ``frame_index``: the identity without ``body_wobble_deg``, else the rotation vector
    ``A w(k)`` with each of its three components ``w`` two seeded sines (periods 6..12 and
    20..40 frames, the hand's tremor and the walk's sway at 15 fps) normalised to peak 1."""
    from scipy.spatial.transform import Rotation

    if effects.body_wobble_deg <= 0:
        return np.eye(3)
    rng = np.random.default_rng([seed, 3304])
    p1, p2 = rng.uniform(6.0, 12.0, size=3), rng.uniform(20.0, 40.0, size=3)
    f1, f2 = rng.uniform(0.0, 2 * np.pi, size=(2, 3))
    k = float(frame_index)
    w = (np.sin(2 * np.pi * k / p1 + f1) + np.sin(2 * np.pi * k / p2 + f2)) / 2.0
    return np.asarray(Rotation.from_rotvec(np.radians(effects.body_wobble_deg) * w).as_matrix())


# ------------------------------------------------------------------ analytic shapes

@dataclass(frozen=True)
class Part:
    """A capped cylinder from ``a`` to ``b`` (a sphere at ``a`` when ``b`` is None), radius
    ``radius`` (metres), linear RGB albedo ``albedo``."""

    a: tuple[float, float, float]
    b: tuple[float, float, float] | None
    radius: float
    albedo: tuple[float, float, float]


@dataclass(frozen=True)
class ShapeHits:
    """Nearest hits of ``M`` rays: ``t (M,)`` distance along the unit ray (inf: none),
    ``part (M,)`` index (-1: none), ``radiance (M, 3)`` linear (0 where none)."""

    t: FloatArray
    part: np.ndarray
    radiance: np.ndarray


_SHAPE_AMBIENT = 0.22
_SHAPE_DIFFUSE = 0.55


class Shapes:
    """Parts intersected analytically and shaded by a fixed light from ``light`` (in the
    parts' frame): ``albedo (ambient + diffuse max(n . light, 0))``."""

    def __init__(self, parts: tuple[Part, ...], light: FloatArray) -> None:
        self.parts = parts
        self.light = np.asarray(light, dtype=np.float64) / np.linalg.norm(light)
        self.albedo = np.array([p.albedo for p in parts], dtype=np.float32)
        a = np.array([p.a for p in parts], dtype=np.float64)
        ends = np.array([p.b if p.b is not None else p.a for p in parts], dtype=np.float64)
        radius = np.array([p.radius for p in parts])
        # bounding sphere, to cull rays
        lo, hi = (a - radius[:, None]).min(0), (a + radius[:, None]).max(0)
        lo = np.minimum(lo, (ends - radius[:, None]).min(0))
        hi = np.maximum(hi, (ends + radius[:, None]).max(0))
        self.centre = (lo + hi) / 2
        self.bound = float(np.linalg.norm(hi - lo) / 2)

    def candidates(self, origin: FloatArray, dirs: np.ndarray, offset: FloatArray
                   ) -> np.ndarray:
        """Indices of the unit rays ``dirs (M, 3)`` from ``origin`` that may hit the parts
        moved by ``offset (3,)``."""
        to_c = self.centre + offset - origin
        dist = float(np.linalg.norm(to_c))
        if dist <= self.bound * 1.01:
            return np.arange(len(dirs))
        cos_max = np.sqrt(max(0.0, 1.0 - (self.bound * 1.01 / dist) ** 2))
        return np.flatnonzero(dirs @ (to_c / dist).astype(dirs.dtype) >= cos_max - 1e-6)

    def hit(self, origin: FloatArray, dirs: np.ndarray,
            offset: FloatArray | None = None) -> ShapeHits:
        """Nearest hits of the unit rays ``dirs (M, 3)`` from ``origin (3,)`` on the parts
        moved by ``offset (3,)`` (all in the parts' frame)."""
        d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        o = np.asarray(origin, dtype=np.float64) - (0.0 if offset is None else offset)
        m = len(d)
        t = np.full(m, np.inf)
        part = np.full(m, -1, dtype=np.int64)
        normal = np.zeros((m, 3))
        for k, p in enumerate(self.parts):
            if p.b is None:
                tk, nk = _sphere_hit(o, d, np.array(p.a), p.radius)
            else:
                tk, nk = _cylinder_hit(o, d, np.array(p.a), np.array(p.b), p.radius)
            near = tk < t
            t[near], part[near], normal[near] = tk[near], k, nk[near]
        ok = part >= 0
        shade = _SHAPE_AMBIENT + _SHAPE_DIFFUSE * np.maximum(normal @ self.light, 0.0)
        rad = np.zeros((m, 3), dtype=np.float32)
        rad[ok] = self.albedo[part[ok]] * shade[ok, None].astype(np.float32)
        return ShapeHits(t, part, rad)


def _sphere_hit(o: FloatArray, d: FloatArray, c: FloatArray, r: float
                ) -> tuple[FloatArray, FloatArray]:
    """Distance (inf: no hit in front) and outward normal of unit rays on a sphere."""
    oc = o - c
    b = d @ oc
    h = b * b - (oc @ oc - r * r)
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(h)
    t = np.where((h >= 0) & (t > 0), t, np.inf)
    n = (o + np.where(np.isfinite(t), t, 0)[:, None] * d - c) / r
    return t, n


def _cylinder_hit(o: FloatArray, d: FloatArray, a: FloatArray, b: FloatArray, r: float
                  ) -> tuple[FloatArray, FloatArray]:
    """Distance (inf: no hit in front) and outward normal of unit rays on a capped cylinder
    (axis ``a`` -> ``b``, radius ``r``), from outside it."""
    ba, oc = b - a, o - a
    baba, baoc = ba @ ba, ba @ oc
    bard, ocrd = d @ ba, d @ oc
    k2 = baba - bard * bard
    k1 = baba * ocrd - baoc * bard
    k0 = baba * (oc @ oc) - baoc * baoc - r * r * baba
    h = k1 * k1 - k2 * k0
    hit = h >= 0
    with np.errstate(invalid="ignore", divide="ignore"):
        hs = np.sqrt(np.where(hit, h, 0.0))
        t_side = (-k1 - hs) / k2
        y = baoc + t_side * bard
        side = hit & (y > 0) & (y < baba) & (t_side > 0)
        t_cap = (np.where(y < 0, 0.0, baba) - baoc) / bard
        cap = hit & ~side & (np.abs(k1 + k2 * t_cap) < hs) & (t_cap > 0)
    t = np.where(side, t_side, np.where(cap, t_cap, np.inf))
    tt = np.where(np.isfinite(t), t, 0.0)
    n_side = (oc + tt[:, None] * d - np.outer(np.where(side, y, 0.0) / baba, ba)) / r
    n_cap = np.outer(np.sign(y), ba / np.sqrt(baba))
    return t, np.where(side[:, None], n_side, n_cap)


# -------------------------------------------------------------------- body and occluder

def _p3(x: Any) -> tuple[float, float, float]:
    a, b, c = (float(v) for v in x)
    return (a, b, c)


def _legs(top: tuple[float, float, float], foot_radius: float, foot_z: float,
          azimuths_deg: tuple[float, ...]) -> tuple[Part, ...]:
    """Tripod legs: a dark upper tube, a black lock collar and a light lower tube each."""
    out: list[Part] = []
    for az in np.radians(azimuths_deg):
        start = np.array(top)
        foot = np.array([foot_radius * np.cos(az), foot_radius * np.sin(az), foot_z])
        knee = start + 0.45 * (foot - start)
        lock = start + 0.5 * (foot - start)
        out += [Part(_p3(start), _p3(knee), 0.018, (0.05, 0.05, 0.05)),
                Part(_p3(knee), _p3(lock), 0.024, (0.02, 0.02, 0.02)),
                Part(_p3(lock), _p3(foot), 0.013, (0.45, 0.45, 0.47))]
    return tuple(out)


_SKIN = (0.55, 0.38, 0.28)
_SHIRT = (0.12, 0.22, 0.45)
_TROUSERS = (0.08, 0.08, 0.1)

BODY_PARTS: dict[Body, tuple[Part, ...]] = {
    Body.NONE: (),
    # body frame: x forward, y left, z up, metres, origin at the camera centre
    Body.OPERATOR: (
        Part((0.0, 0.0, -0.04), (-0.1, -0.08, -0.55), 0.014, (0.04, 0.04, 0.04)),  # pole
        Part((-0.45, 0.0, -0.25), None, 0.11, _SKIN),  # head
        Part((-0.47, 0.0, -0.33), (-0.47, 0.0, -0.44), 0.05, _SKIN),  # neck
        Part((-0.48, 0.2, -0.47), (-0.48, -0.2, -0.47), 0.07, _SHIRT),  # shoulders
        Part((-0.48, 0.0, -0.47), (-0.48, 0.0, -1.1), 0.18, _SHIRT),  # torso
        Part((-0.48, -0.2, -0.47), (-0.3, -0.2, -0.68), 0.05, _SHIRT),  # upper arm
        Part((-0.3, -0.2, -0.68), (-0.1, -0.08, -0.55), 0.04, _SKIN),  # forearm to hand
        Part((-0.48, 0.1, -1.1), (-0.48, 0.1, -1.9), 0.075, _TROUSERS),  # legs
        Part((-0.48, -0.1, -1.1), (-0.48, -0.1, -1.9), 0.075, _TROUSERS),
    ),
    Body.TRIPOD: (
        Part((0.0, 0.0, -0.05), (0.0, 0.0, -0.25), 0.012, (0.06, 0.06, 0.06)),  # column
        Part((0.0, 0.0, -0.25), (0.0, 0.0, -0.32), 0.03, (0.12, 0.12, 0.13)),  # head
        *_legs((0.0, 0.0, -0.3), 1.0, -1.9, (60.0, 180.0, 300.0)),
    ),
    Body.ROBOT: (
        Part((0.0, 0.0, -0.05), (0.0, 0.0, -0.45), 0.025, (0.4, 0.4, 0.42)),  # mast
        Part((-0.05, 0.0, -0.45), (-0.05, 0.0, -0.8), 0.38, (0.1, 0.1, 0.11)),  # base
        Part((0.3, 0.0, -0.45), (0.3, 0.0, -0.36), 0.05, (0.03, 0.03, 0.03)),  # scanner
        Part((-0.3, 0.18, -0.45), (-0.3, 0.18, 0.25), 0.012, (0.55, 0.55, 0.5)),  # posts
        Part((-0.3, -0.18, -0.45), (-0.3, -0.18, 0.25), 0.012, (0.55, 0.55, 0.5)),
        Part((-0.3, 0.18, 0.25), (-0.3, -0.18, 0.25), 0.012, (0.55, 0.55, 0.5)),
    ),
}
"""Camera-fixed parts of each body, in the body frame (x forward, y left, z up, metres, origin
at the camera centre; see ``omni_sfm.synth.paths.BODY_FROM_CAM``). Legs reach below any floor
(the floor hides their ends)."""

_BODY_LIGHT = np.array([0.3, 0.2, 1.0])


def body_shapes(body: Body, mount: Mount) -> Shapes | None:
    """The body's parts in the camera's ray frame (None for no body)."""
    parts = BODY_PARTS[Body(body)]
    if not parts:
        return None
    cam_from_body = BODY_FROM_CAM[Mount(mount)].T
    cam_parts = tuple(
        Part(_p3(cam_from_body @ p.a), None if p.b is None else _p3(cam_from_body @ p.b),
             p.radius, p.albedo)
        for p in parts)
    return Shapes(cam_parts, cam_from_body @ _BODY_LIGHT)


OCCLUDER_PARTS: tuple[Part, ...] = (
    Part((0.0, 0.0, 0.0), (0.0, 0.0, 0.85), 0.2, _TROUSERS),  # legs
    Part((0.0, 0.0, 0.85), (0.0, 0.0, 1.47), 0.25, (0.45, 0.08, 0.06)),  # red coat
    Part((0.0, 0.0, 1.62), None, 0.13, _SKIN),  # head: top at 1.75 m
)
"""The walking person, feet at the origin (scene frame: metres, +Z up): 0.5 m wide, 1.75 m
tall."""

OCCLUDER_SPEED = 1.3
"""Walking speed of the occluder, m/s."""
OCCLUDER_OFFSET = 0.75
"""Lateral distance of the occluder's line of walk from the camera's mid-sequence position, m."""


def occluder_shapes() -> Shapes:
    return Shapes(OCCLUDER_PARTS, np.array([0.3, 0.2, 1.0]))


def occluder_path(traj: Trajectory, mount: Mount, fps: float, seed: int) -> FloatArray:
    """``(N, 3)`` feet positions (scene frame, on the floor ``z = 0``) of a person walking at
    :data:`OCCLUDER_SPEED` along a straight line :data:`OCCLUDER_OFFSET` to one side (seeded)
    of the camera's mid-sequence position, against the camera's direction of travel (its
    heading when it barely moves), passing the camera at the middle frame."""
    n = len(traj)
    mid = (n - 1) / 2.0
    travel = traj.positions[-1, :2] - traj.positions[0, :2]
    if np.linalg.norm(travel) > 0.2:
        fwd = travel
    else:
        R, _ = pose_at(traj, mid)
        fwd = (R @ BODY_FROM_CAM[Mount(mount)].T)[:2, 0]
    fwd = fwd / max(float(np.linalg.norm(fwd)), 1e-12)
    side = np.array([-fwd[1], fwd[0]])
    if np.random.default_rng([seed, 3303]).random() < 0.5:
        side = -side
    _, centre = pose_at(traj, mid)
    k = np.arange(n, dtype=np.float64)
    xy = (centre[:2] + OCCLUDER_OFFSET * side)[None, :] \
        + ((mid - k) * OCCLUDER_SPEED / float(fps))[:, None] * fwd
    return np.column_stack([xy, np.zeros(n)])


# ------------------------------------------------------------------------------- seam

def seam_rotation(seam_deg: float) -> FloatArray:
    """Rotation (camera frame) of the back lens's rays: ``seam_deg`` about +Z, the lenses'
    axis. Rays with ``z < 0`` (longitude beyond +-90 deg, the image's outer quarters) are
    rendered through it, so the content slides by ``seam_deg`` along the two seam meridians
    (``u = W/4`` and ``3W/4``), in opposite directions."""
    a = np.radians(seam_deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# -------------------------------------------------------------------------- compression

class VideoWriter:
    """Writes RGB frames into an H.264 (PyAV/libx264, yuv420p) or mp4v (OpenCV) video; frame
    ``k`` is stamped ``k / fps``."""

    def __init__(self, path: Path, codec: VideoCodec, fps: float, width: int, height: int,
                 crf: int) -> None:
        self.path = Path(path)
        self.codec = VideoCodec(codec)
        self._cv: Any = None
        self._av: Any = None
        self._stream: Any = None
        if self.codec == VideoCodec.MP4V:
            import cv2

            self._cv = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), float(fps),
                                       (width, height))
            if not self._cv.isOpened():
                raise OmniSfmError(f"{path}: OpenCV cannot write an mp4v video here")
            return
        if width % 2 or height % 2:
            raise OmniSfmError(
                f"H.264 (yuv420p) needs an even image size, got {width}x{height}: use "
                "--video-codec mp4v or an even size")
        import av

        self._av = av.open(str(path), mode="w")
        rate = Fraction(float(fps)).limit_denominator(1001)
        stream = self._av.add_stream("libx264", rate=rate)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.time_base = 1 / rate
        stream.options = {"crf": str(int(crf))}
        self._stream = stream
        self._k = 0

    def write(self, rgb: np.ndarray) -> None:
        """Append one ``(H, W, 3)`` uint8 RGB frame."""
        if self._cv is not None:
            self._cv.write(np.ascontiguousarray(rgb[:, :, ::-1]))
            return
        import av

        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        frame.pts = self._k
        self._k += 1
        for packet in self._stream.encode(frame):
            self._av.mux(packet)

    def close(self) -> None:
        if self._cv is not None:
            self._cv.release()
            self._cv = None
        if self._av is not None:
            for packet in self._stream.encode():
                self._av.mux(packet)
            self._av.close()
            self._av = None


def jpeg_roundtrip(rgb: np.ndarray, quality: int) -> np.ndarray:
    """``rgb`` as it reads back from a JPEG file of this quality (OpenCV's encoder)."""
    import cv2

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]),
                           [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise OmniSfmError("OpenCV could not encode a JPEG frame")
    return np.asarray(cv2.imdecode(buf, cv2.IMREAD_COLOR))[:, :, ::-1]
