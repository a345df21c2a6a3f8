"""Rendered omnidirectional video with exact ground truth (Open3D ray casting).

Every pixel is rendered from the rays the camera model gives (``rays_from_pixels``) at its
centre and, where a surface edge crosses it, at ``S x S`` sub-pixel positions (adaptive
supersampling), so any omni-sfm camera model renders exactly and its valid mask is respected
(outside it the image is black). The renderer works in the scene's frame (metres, +Z up); the
files use the first camera's frame (see :class:`RenderSetup`). Shading: Lambert diffuse light
from the scene's point lights with a soft distance falloff, a direction-dependent ambient term
(so that two faces of a box never look the same), emissive light panels and windows, no
shadows; optional procedural texture (value noise and spots fixed to the surfaces, so point
features are trackable); a little seeded Gaussian sensor noise; gamma 1/2.2 and 8-bit output.
Real-footage effects (motion blur, exposure drift and flicker, vignetting, shot noise, JPEG or
H.264, a camera-fixed body, a stitching seam, a walking occluder) come from
:mod:`omni_sfm.synth.effects`, all off by default.

Output of :func:`render_sequence` (documented in docs/rendering.md): ``images/NNNNNN.png``
(``.jpg`` with JPEG compression) or ``video.mp4``, ``camera.yaml``, ``groundtruth.tum``,
``scene.ply``, ``lines3d.json``, ``render.json``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, fields
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras import (
    CameraModel,
    EquirectangularCamera,
    HyperboloidCamera,
    OpenCVFisheyeCamera,
    RigCamera,
    dual_fisheye,
    load_camera,
    write_camera_yaml,
)
from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import atomic_output_dir, atomic_write_text, dumps_json
from omni_sfm.folders import RenderFolder
from omni_sfm.frames import video_frame_name
from omni_sfm.geometry import FloatArray
from omni_sfm.libs import open3d_module
from omni_sfm.lines3d import write_lines3d
from omni_sfm.poses import Trajectory, write_tum
from omni_sfm.synth.effects import (
    Effects,
    Shapes,
    Shutter,
    VideoCodec,
    VideoWriter,
    blur_along_flow,
    body_shapes,
    body_wobble,
    check_effects,
    effects_json,
    frame_gain,
    occluder_path,
    occluder_shapes,
    seam_rotation,
    shutter_poses,
    vignetting_gain,
)
from omni_sfm.synth.paths import Mount, PathOptions, Route, camera_path
from omni_sfm.synth.scenes import (
    MATERIAL_ALBEDO,
    MATERIAL_EMISSION,
    MATERIAL_TEXTURED,
    Scene,
    SceneName,
    make_scene,
)


class CameraKind(StrEnum):
    HYPERBOLOID = "hyperboloid"
    EQUIRECTANGULAR = "equirectangular"
    DUAL_FISHEYE = "dual-fisheye"


class Preset(StrEnum):
    SMALL = "small"
    PAPER = "paper"


@dataclass(frozen=True)
class PresetSize:
    frames: int
    hyperboloid: tuple[int, int]
    equirectangular: tuple[int, int]
    dual_fisheye: tuple[int, int]


PRESETS = {
    Preset.SMALL: PresetSize(12, (320, 240), (320, 160), (320, 160)),
    Preset.PAPER: PresetSize(200, (800, 600), (1600, 800), (1920, 960)),
}
# the rendered dual-fisheye camera: two equidistant 200 deg lenses back to back, 4 cm apart
DUAL_FISHEYE_FOV_DEG = 200.0
DUAL_FISHEYE_BASELINE_M = 0.04


def hyperboloid_camera(width: int = 800, height: int = 600) -> HyperboloidCamera:
    """The paper's camera file (800 x 600, px 0.01, f 8, alpha 14, beta 19.4, mask 48..290 px),
    its pixel pitch, centre and mask scaled to ``width x height``."""
    _check_size(width, height)
    s = min(width / 800.0, height / 600.0)
    return HyperboloidCamera(
        width=width, height=height, cx=width / 2.0, cy=height / 2.0, px=0.01 / s, py=0.01 / s,
        f=8.0, alpha=14.0, beta=19.4, inner_radius=48.0 * s, outer_radius=290.0 * s,
    )


def dual_fisheye_camera(width: int = 1920, height: int = 960) -> RigCamera:
    """Raw dual-fisheye frames ``width x height`` (two square lenses side by side, so
    ``width = 2 height``): equidistant ``DUAL_FISHEYE_FOV_DEG`` lenses whose image circle fills
    98 % of their square, back to back ``DUAL_FISHEYE_BASELINE_M`` apart."""
    _check_size(width, height)
    if width != 2 * height:
        raise OmniSfmError(f"dual-fisheye frames are two square lenses side by side: width must "
                           f"be 2 x height, got {width} x {height}")
    r = 0.49 * height
    f = r / math.radians(DUAL_FISHEYE_FOV_DEG / 2)
    c = (height - 1) / 2.0
    lens = OpenCVFisheyeCamera(width=height, height=height, fx=f, fy=f, cx=c, cy=c,
                               outer_radius=r)
    return dual_fisheye(lens, baseline=DUAL_FISHEYE_BASELINE_M)


def _check_size(width: int, height: int) -> None:
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or v <= 0:
            raise OmniSfmError(f"image {name} must be a positive integer, got {v!r}")


def make_camera(camera: str | Path | CameraModel = CameraKind.HYPERBOLOID, *,
                width: int | None = None, height: int | None = None,
                preset: Preset = Preset.PAPER) -> CameraModel:
    """A camera model from a kind name (``hyperboloid``, ``equirectangular``; size from the
    preset unless given), a camera file path, or a model (returned as is)."""
    if isinstance(camera, CameraModel):
        if width is not None or height is not None:
            raise OmniSfmError("image size cannot be changed for a given camera model")
        return camera
    name = str(camera)
    kinds = [k.value for k in CameraKind]
    if name in kinds:
        kind = CameraKind(name)
        dw, dh = getattr(PRESETS[Preset(preset)], kind.value.replace("-", "_"))
        if width is None and height is None:
            width, height = dw, dh
        elif width is None or height is None:
            # keep the preset's aspect ratio
            if height is not None:
                _check_size(1, height)
                width = max(1, round(height * dw / dh))
            elif width is not None:
                _check_size(width, 1)
                height = max(1, round(width * dh / dw))
        assert width is not None and height is not None
        _check_size(width, height)
        if kind == CameraKind.HYPERBOLOID:
            return hyperboloid_camera(width, height)
        if kind == CameraKind.DUAL_FISHEYE:
            return dual_fisheye_camera(width, height)
        return EquirectangularCamera(width=width, height=height)
    path = Path(name)
    if path.suffix.lower() not in (".yaml", ".yml") and not path.exists():
        raise OmniSfmError(
            f"unknown camera {name!r}: give one of {', '.join(kinds)} or a camera YAML file"
        )
    if width is not None or height is not None:
        raise OmniSfmError(f"{path}: --width/--height cannot be combined with a camera file")
    return load_camera(path)


def default_mount(camera: CameraModel) -> Mount:
    """Robot mount (camera +Z up) for mirror cameras, hand-held (-Y up) for the others."""
    return Mount.ROBOT if camera.model == CameraKind.HYPERBOLOID else Mount.HANDHELD


@dataclass(frozen=True, kw_only=True)
class ShadingOptions:
    supersample: int = 3
    """Sub-pixel rays per edge pixel along each axis (S x S rays, box filter)."""
    textured: bool = False
    """Procedural surface texture, for point features."""
    noise_sigma: float = 1.0
    """Std-dev of the Gaussian sensor noise, 8-bit grey levels."""
    exposure: float = 1.0
    """Linear radiance multiplier before the gamma curve."""
    seed: int = 0
    """Seeds the texture pattern, the sensor noise, the gain drift and flicker."""
    effects: Effects = field(default_factory=Effects)
    """Real-footage effects (:class:`omni_sfm.synth.effects.Effects`); all off by default."""


_AMBIENT = 0.16
_AMBIENT_TILT = 0.07
_AMBIENT_DIR = np.array([0.32, 0.55, 0.77]) / np.linalg.norm([0.32, 0.55, 0.77])
_FALLOFF = 1.0  # m: irradiance = power * cos / (d^2 + _FALLOFF^2)
_TEX_WAVELENGTHS = (0.55, 0.23, 0.1, 0.045)  # m
_TEX_WEIGHTS = (0.45, 0.3, 0.17, 0.08)
_TEX_AMPLITUDE = 0.3
_TEX_SPOTS = ((0.3, 0.1, 0.3), (0.12, 0.12, 0.33))  # cell size (m), radius range (cells)
_TEX_TABLE = 256
_SUBRAY_CACHE_BYTES = 64 * 2**20
# surface ids of the body's and the occluder's parts (scene surfaces are numbered from 0)
_BODY_SID = 1_000_000
_OCCLUDER_SID = 2_000_000


@dataclass(frozen=True)
class _BodyPixels:
    """The camera-fixed body as the valid pixels see it (in every frame; in one frame when the
    body wobbles).

    ``t (P,)`` distance along the centre ray (inf: no body), ``rad (P, 3)``, ``sid (P,)``;
    ``hits``: indices of the pixels whose centre ray hits it. Pixels on the body's outline
    (``sub_row (P,)`` >= 0) keep their ``S x S`` sub-pixel hits: ``sub_t (S*S, E)``,
    ``sub_rad (S*S, E, 3)``, ``sub_sid (S*S, E)``; elsewhere the centre's hit stands for all.
    """

    t: np.ndarray
    rad: np.ndarray
    sid: np.ndarray
    hits: np.ndarray
    sub_row: np.ndarray
    sub_t: np.ndarray
    sub_rad: np.ndarray
    sub_sid: np.ndarray


class Renderer:
    """Renders frames of one scene through one camera model.

    Adaptive supersampling: each frame first casts one ray per valid pixel centre; pixels whose
    8-neighbourhood sees more than one flat surface (the edges) are re-rendered from ``S x S``
    sub-pixel rays and box-filtered, the others keep the centre sample (lighting is smooth
    within a surface, and the texture is pre-filtered to the pixel footprint). All rays come
    from the camera model and are computed once. Images are ``(height, width, 3)`` uint8 RGB.
    """

    def __init__(self, scene: Scene, camera: CameraModel,
                 options: ShadingOptions | None = None, *, mount: Mount | None = None) -> None:
        """``mount``: how the body (``options.effects.body``) is attached; None: the camera's
        default mount."""
        self.o3d = open3d_module()
        self.scene = scene
        self.camera = camera
        self.options = o = options or ShadingOptions()
        if not (isinstance(o.supersample, int) and 1 <= o.supersample <= 8):
            raise OmniSfmError(f"supersample must be an integer 1..8, got {o.supersample!r}")
        if not o.noise_sigma >= 0:
            raise OmniSfmError(f"noise sigma must be >= 0, got {o.noise_sigma}")
        e = o.effects
        check_effects(e, camera.model)
        self.mount = Mount(mount) if mount is not None else default_mount(camera)
        self.raycaster = scene.raycasting_scene()
        self.materials = scene.materials.astype(np.int64)
        self.surfaces = scene.surfaces.astype(np.int32)
        self.mask = camera.valid_mask()
        self.pixel_index = np.flatnonzero(self.mask.ravel())
        self.centre_rays, self.pixel_angle = self._centre_rays()
        self.vignette = (vignetting_gain(camera, np.stack(self._pixel_uv(), axis=1),
                                         self.centre_rays, e.vignetting)
                         if e.vignetting > 0 else None)
        # a stitching seam: the back lens's pixels (z < 0) see through rotated rays
        self.seam = seam_rotation(e.seam_deg).astype(np.float32) if e.seam_deg != 0 else None
        if self.seam is not None:
            back = self.centre_rays[:, 2] < 0
            self.centre_rays[back] = self.centre_rays[back] @ self.seam.T
        # sub-pixel rays are kept when they fit in _SUBRAY_CACHE_BYTES, else made per frame
        S2 = o.supersample**2
        cache = o.supersample > 1 and S2 * len(self.pixel_index) * 12 <= _SUBRAY_CACHE_BYTES
        self.sub_rays = self._subpixel_rays(np.arange(len(self.pixel_index))) if cache else None
        self.wrap_u = camera.model == CameraKind.EQUIRECTANGULAR
        self.light_pos = scene.light_positions.astype(np.float32)
        self.light_power = scene.light_power.astype(np.float32)
        rng = np.random.default_rng([o.seed, 9120])
        self.tex_tables = rng.random(
            (len(_TEX_WAVELENGTHS) + len(_TEX_SPOTS), _TEX_TABLE, _TEX_TABLE)).astype(np.float32)
        self.tex_offsets = rng.uniform(0, 50.0, size=(len(MATERIAL_ALBEDO), 3, 2)).astype(
            np.float32)
        self.body_shapes = body_shapes(e.body, self.mount)
        # a rigid body is intersected once; a wobbling one per frame (_body_at)
        self.body = (self._body_pixels(self.body_shapes)
                     if self.body_shapes is not None and e.body_wobble_deg == 0 else None)
        self._wobbled: tuple[int, _BodyPixels] | None = None
        self.occluder: Shapes | None = occluder_shapes() if e.occluder else None

    def body_mask(self, frame_index: int = 0) -> np.ndarray:
        """``(height, width)`` bool: pixels whose centre ray hits the camera-fixed body in frame
        ``frame_index`` (the same in every frame unless the body wobbles; in a given frame the
        scene can still be nearer, e.g. the floor at a tripod's feet)."""
        out = np.zeros(self.camera.height * self.camera.width, dtype=bool)
        b = self._body_at(frame_index)
        if b is not None:
            out[self.pixel_index[b.hits]] = True
        return out.reshape(self.camera.height, self.camera.width)

    def _body_at(self, frame_index: int) -> _BodyPixels | None:
        """The body's pixels in frame ``frame_index`` (the last wobbled frame is kept)."""
        if self.body is not None or self.body_shapes is None:
            return self.body
        k = int(frame_index)
        if self._wobbled is None or self._wobbled[0] != k:
            o = self.options
            self._wobbled = (k, self._body_pixels(
                self.body_shapes, body_wobble(o.effects, o.seed, k)))
        return self._wobbled[1]

    def _body_pixels(self, shapes: Shapes, cam_from_body: FloatArray | None = None
                     ) -> _BodyPixels:
        """Intersect the centre rays, and the sub-pixel rays of the body's outline, with the
        camera-fixed body turned by ``cam_from_body`` (``(3, 3)`` about the camera centre;
        None: not turned)."""
        P = len(self.pixel_index)
        t = np.full(P, np.inf, dtype=np.float32)
        rad = np.zeros((P, 3), dtype=np.float32)
        sid = np.full(P, -1, dtype=np.int32)
        origin = np.zeros(3)
        # a ray d meets the turned body where the ray cam_from_body^T d meets the body
        rot = None if cam_from_body is None else np.asarray(cam_from_body, np.float32)
        chunk = 1 << 18
        for i in range(0, P, chunk):
            rays = self.centre_rays[i:i + chunk]
            h = shapes.hit(origin, rays if rot is None else rays @ rot)
            ok = h.part >= 0
            t[i:i + chunk][ok] = h.t[ok]
            rad[i:i + chunk][ok] = h.radiance[ok]
            sid[i:i + chunk][ok] = _BODY_SID + h.part[ok]
        S2 = self.options.supersample**2
        sub_row = np.full(P, -1, dtype=np.int64)
        edge = (np.flatnonzero(self._edge_pixels(sid)) if S2 > 1
                else np.zeros(0, dtype=np.int64))
        sub_row[edge] = np.arange(len(edge))
        sub = self._subpixel_rays(edge) if len(edge) else np.zeros((S2, 0, 3), np.float32)
        hs = shapes.hit(origin, sub.reshape(-1, 3) if rot is None else sub.reshape(-1, 3) @ rot)
        ok = hs.part >= 0
        sub_sid = np.where(ok, _BODY_SID + hs.part, -1).astype(np.int32)
        return _BodyPixels(
            t=t, rad=rad, sid=sid, hits=np.flatnonzero(sid >= 0), sub_row=sub_row,
            sub_t=hs.t.astype(np.float32).reshape(S2, -1),
            sub_rad=hs.radiance.reshape(S2, -1, 3), sub_sid=sub_sid.reshape(S2, -1))

    def _pixel_uv(self) -> tuple[FloatArray, FloatArray]:
        w = self.camera.width
        return ((self.pixel_index % w).astype(np.float64),
                (self.pixel_index // w).astype(np.float64))

    def _centre_rays(self) -> tuple[FloatArray, FloatArray]:
        """``(P, 3)`` float32 rays of the valid pixel centres, ``(P,)`` pixel size (rad)."""
        u, v = self._pixel_uv()
        centre = self.camera.rays_from_pixels(np.stack([u, v], axis=1))
        size = np.zeros(len(u))
        for du, dv in ((0.5, 0.0), (-0.5, 0.0), (0.0, 0.5), (0.0, -0.5)):
            r = self.camera.rays_from_pixels(np.stack([u + du, v + dv], axis=1))
            step = 2.0 * np.linalg.norm(r - centre, axis=1)
            size = np.fmax(size, step)
        return centre.astype(np.float32), size.astype(np.float32)

    def _subpixel_rays(self, idx: np.ndarray) -> FloatArray:
        """``(S*S, len(idx), 3)`` float32 rays of the valid pixels ``idx`` at S x S sub-pixel
        positions; a sub-pixel ray outside the model's domain falls back to the centre's ray."""
        S = self.options.supersample
        u, v = self._pixel_uv()
        u, v = u[idx], v[idx]
        offs = (np.arange(S) + 0.5) / S - 0.5
        out = np.empty((S * S, len(u), 3), dtype=np.float32)
        k = 0
        back = self.centre_rays[idx, 2] < 0 if self.seam is not None else None
        for dv in offs:
            for du in offs:
                r = self.camera.rays_from_pixels(np.stack([u + du, v + dv], axis=1))
                if back is not None and self.seam is not None:
                    r[back] = r[back] @ self.seam.T
                bad = ~np.isfinite(r).all(axis=1)
                r[bad] = self.centre_rays[idx[bad]]
                out[k] = r
                k += 1
        return np.asarray(out)

    def cast(self, world_from_cam: FloatArray, position: FloatArray,
             rays_cam: FloatArray) -> dict[str, np.ndarray]:
        """Cast ``(..., 3)`` camera-frame rays from ``position``; Open3D's result as numpy."""
        R = np.asarray(world_from_cam, dtype=np.float32)
        d = rays_cam.reshape(-1, 3) @ R.T
        rays = np.empty((len(d), 6), dtype=np.float32)
        rays[:, :3] = np.asarray(position, dtype=np.float32)
        if isinstance(self.camera, RigCamera):  # each ray leaves from its lens's centre
            rays[:, :3] += self.camera.ray_origins(rays_cam.reshape(-1, 3)).astype(
                np.float32) @ R.T
        rays[:, 3:] = d
        res = self.raycaster.cast_rays(self.o3d.core.Tensor.from_numpy(rays))
        return {
            "t_hit": res["t_hit"].numpy(),
            "primitive_ids": res["primitive_ids"].numpy(),
            "normals": res["primitive_normals"].numpy(),
            "dirs": d,
            "origins": rays[:, :3],
        }

    def _shade(self, world_from_cam: FloatArray, position: FloatArray, rays_cam: FloatArray,
               ray_angle: FloatArray) -> tuple[FloatArray, np.ndarray, FloatArray, FloatArray]:
        """Linear radiance ``(M, 3)``, surface id ``(M,)`` (-1: nothing hit), distance ``(M,)``
        (inf: nothing hit) and world direction ``(M, 3)`` of ``(M, 3)`` unit rays whose samples
        stand for ``ray_angle`` (rad) wide pixels or sub-pixels."""
        hit = self.cast(world_from_cam, position, rays_cam)
        t = hit["t_hit"]
        ok = np.isfinite(t)
        tri = np.where(ok, hit["primitive_ids"], 0).astype(np.int64)
        mat = self.materials[tri]
        d = hit["dirs"]
        n = hit["normals"].astype(np.float32)
        # the side of the surface facing the camera
        cos_view = np.einsum("ij,ij->i", n, d)
        n *= -np.sign(cos_view)[:, None]
        tt = np.where(ok, t, 0).astype(np.float32)
        pts = hit["origins"] + tt[:, None] * d
        irr = _AMBIENT + _AMBIENT_TILT * (n @ _AMBIENT_DIR.astype(np.float32))
        for lp, lw in zip(self.light_pos, self.light_power, strict=True):
            to_l = lp - pts
            d2 = np.einsum("ij,ij->i", to_l, to_l)
            cos = np.einsum("ij,ij->i", n, to_l) / np.sqrt(d2)
            irr += lw * np.maximum(cos, 0) / (d2 + np.float32(_FALLOFF**2))
        albedo = MATERIAL_ALBEDO.astype(np.float32)[mat]
        if self.options.textured:
            # size of the sample's footprint on the surface, metres
            foot = tt * ray_angle / np.maximum(np.abs(cos_view), 0.25)
            albedo *= self._texture(pts, n, mat, foot)[:, None]
        rad = albedo * irr[:, None] + MATERIAL_EMISSION.astype(np.float32)[mat]
        rad[~ok] = 0.0
        sid = np.where(ok, self.surfaces[tri], -1)
        return rad, sid, t, d

    def _edge_pixels(self, sid: np.ndarray) -> np.ndarray:
        """``(P,)`` bool: valid pixels with a neighbour (8-neighbourhood) on another surface."""
        H, W = self.camera.height, self.camera.width
        flat = np.full(H * W, -2, dtype=np.int32)
        flat[self.pixel_index] = sid
        img = flat.reshape(H, W)
        edge = np.zeros((H, W), dtype=bool)

        def mark(a: slice, b: slice, c: slice, d: slice) -> None:
            x, y = img[a, b], img[c, d]
            diff = (x != y) & (x != -2) & (y != -2)
            edge[a, b] |= diff
            edge[c, d] |= diff

        full = slice(None)
        mark(full, slice(0, W - 1), full, slice(1, W))
        mark(slice(0, H - 1), full, slice(1, H), full)
        mark(slice(0, H - 1), slice(0, W - 1), slice(1, H), slice(1, W))
        mark(slice(0, H - 1), slice(1, W), slice(1, H), slice(0, W - 1))
        if self.wrap_u:  # the equirectangular image is periodic in u
            mark(full, slice(W - 1, W), full, slice(0, 1))
        return edge.ravel()[self.pixel_index]

    def radiance(self, world_from_cam: FloatArray, position: FloatArray, *,
                 occluder: FloatArray | None = None, frame_index: int = 0) -> FloatArray:
        """``(P, 3)`` linear radiance of the valid pixels (adaptively supersampled), with the
        body (as in frame ``frame_index``) and, at ``occluder`` (its feet, scene frame), the
        walking person."""
        return self._radiance(world_from_cam, position, occluder, frame_index)[0]

    def _radiance(self, world_from_cam: FloatArray, position: FloatArray,
                  occluder: FloatArray | None, frame_index: int = 0
                  ) -> tuple[FloatArray, np.ndarray, FloatArray, FloatArray]:
        """Radiance ``(P, 3)``, surface id ``(P,)``, distance ``(P,)`` and world direction
        ``(P, 3)`` of the valid pixels' centre rays (radiance supersampled on edges)."""
        rad, sid, t, dirs = self._shade(world_from_cam, position, self.centre_rays,
                                        self.pixel_angle)
        b = self._body_at(frame_index)
        if b is not None:
            h = b.hits[b.t[b.hits] < t[b.hits]]
            rad[h], sid[h], t[h] = b.rad[h], b.sid[h], b.t[h]
        if occluder is not None:
            self._composite_occluder(occluder, position, dirs, rad, sid, t)
        if self.options.supersample > 1:
            S2 = self.options.supersample**2
            idx = np.flatnonzero(self._edge_pixels(sid))
            sub = (self.sub_rays[:, idx] if self.sub_rays is not None
                   else self._subpixel_rays(idx)).reshape(-1, 3)
            angle = np.tile(self.pixel_angle[idx] / self.options.supersample, S2)
            rs, ss, ts, ds = self._shade(world_from_cam, position, sub, angle)
            if b is not None:
                self._composite_body_sub(b, idx, rs, ss, ts)
            if occluder is not None:
                self._composite_occluder(occluder, position, ds, rs, ss, ts)
            rad[idx] = rs.reshape(S2, len(idx), 3).mean(axis=0)
        return rad, sid, t, dirs

    def _composite_body_sub(self, b: _BodyPixels, idx: np.ndarray, rad: FloatArray,
                            sid: np.ndarray, t: FloatArray) -> None:
        """Put the body ``b`` in front of the ``(S*S * len(idx))`` sub-pixel samples of pixels
        ``idx`` where it is nearer (in place)."""
        S2, n = self.options.supersample**2, len(idx)
        tb = np.repeat(b.t[idx][None], S2, axis=0)
        sb = np.repeat(b.sid[idx][None], S2, axis=0)
        rb = np.repeat(b.rad[idx][None], S2, axis=0)
        rows = b.sub_row[idx]
        m = rows >= 0
        tb[:, m], sb[:, m], rb[:, m] = b.sub_t[:, rows[m]], b.sub_sid[:, rows[m]], \
            b.sub_rad[:, rows[m]]
        near = (tb < t.reshape(S2, n)).ravel()
        rad[near] = rb.reshape(-1, 3)[near]
        sid[near] = sb.ravel()[near]
        t[near] = tb.ravel()[near]

    def _composite_occluder(self, feet: FloatArray, position: FloatArray, dirs: FloatArray,
                            rad: FloatArray, sid: np.ndarray, t: FloatArray) -> None:
        """Put the walking person (feet at ``feet``, scene frame) in front of the samples with
        world directions ``dirs (M, 3)`` where it is nearer (in place)."""
        if self.occluder is None:  # a place given without the effect: draw the person anyway
            self.occluder = occluder_shapes()
        feet = np.asarray(feet, dtype=np.float64)
        cand = self.occluder.candidates(np.asarray(position, dtype=np.float64), dirs, feet)
        if len(cand) == 0:
            return
        h = self.occluder.hit(position, dirs[cand], feet)
        near = h.t < t[cand]
        sel = cand[near]
        rad[sel] = h.radiance[near]
        sid[sel] = _OCCLUDER_SID + h.part[near]
        t[sel] = h.t[near]

    def _texture(self, pts: np.ndarray, n: np.ndarray, mat: np.ndarray,
                 foot: np.ndarray) -> np.ndarray:
        """Albedo factor (around 1) from value noise and spots in the surface's two tangent
        coordinates, pre-filtered to the sample's footprint ``foot`` (m): octaves finer than
        the footprint fade to their mean and spot borders are blurred over it."""
        axis = np.argmax(np.abs(n), axis=1)
        ia = np.array([[1, 2], [0, 2], [0, 1]])[axis]
        rows = np.arange(len(pts))
        uv = np.stack([pts[rows, ia[:, 0]], pts[rows, ia[:, 1]]], axis=1).astype(np.float32)
        uv += self.tex_offsets[mat, axis]
        val = np.zeros(len(pts), dtype=np.float32)
        for k, (lam, w) in enumerate(zip(_TEX_WAVELENGTHS, _TEX_WEIGHTS, strict=True)):
            keep = np.clip((lam / 2 - foot) / (lam / 4), 0.0, 1.0)
            noise = _value_noise(uv * np.float32(1 / lam), self.tex_tables[k])
            val += np.float32(w) * (0.5 + keep * (noise - 0.5))
        # soft blotches (val in [0, 1], mean 0.5) plus sharp spots: the spots make point
        # features that are well localised at every image scale
        factor = 1.0 + np.float32(_TEX_AMPLITUDE) * np.tanh(3.0 * (val - 0.5))
        for k, (cell, rmin, rmax) in enumerate(_TEX_SPOTS):
            factor *= _spots(uv * np.float32(1 / cell), foot * np.float32(1 / cell),
                             self.tex_tables[len(_TEX_WAVELENGTHS) + k], rmin, rmax)
        return np.where(MATERIAL_TEXTURED[mat], factor, 1.0).astype(np.float32)

    def render(self, world_from_cam: FloatArray, position: FloatArray,
               frame_index: int = 0, *, shutter: Shutter | None = None,
               occluder: FloatArray | None = None) -> np.ndarray:
        """``(height, width, 3)`` uint8 RGB image of the camera at this pose.

        ``world_from_cam``: ``(3, 3)`` rotation of the camera's ray frame; ``position``: ``(3,)``
        camera centre (world, metres): the pose at mid-exposure. ``frame_index`` seeds this
        frame's sensor noise, drift and flicker. ``shutter``: the poses at shutter open and
        close, for motion blur (ignored unless ``effects.motion_blur > 0``; None: a still
        camera). ``occluder``: ``(3,)`` feet of the walking person (scene frame), or None.
        """
        o, e = self.options, self.options.effects
        rad, sid, t, dirs = self._radiance(world_from_cam, position, occluder, frame_index)
        if shutter is not None and e.motion_blur > 0:
            rad = self._motion_blur(position, shutter, rad, sid, t, dirs)
        gain = o.exposure * frame_gain(e, o.seed, frame_index)
        lin = rad * gain
        if self.vignette is not None:
            lin = lin * self.vignette[:, None]
        lin = np.clip(lin, 0.0, 1.0)
        val = 255.0 * lin ** (1 / 2.2)
        if o.noise_sigma > 0 and e.shot_noise == 0:
            rng = np.random.default_rng([o.seed, 5077, int(frame_index)])
            val += rng.normal(0.0, o.noise_sigma, size=val.shape)
        elif e.shot_noise > 0:
            rng = np.random.default_rng([o.seed, 5077, int(frame_index)])
            sigma = np.sqrt(np.float32(o.noise_sigma**2) + np.float32(e.shot_noise**2) * lin)
            val += rng.standard_normal(size=val.shape, dtype=np.float32) * sigma
        img = np.zeros((self.camera.height * self.camera.width, 3), dtype=np.uint8)
        img[self.pixel_index] = np.clip(np.rint(val), 0, 255).astype(np.uint8)
        return img.reshape(self.camera.height, self.camera.width, 3)

    def _motion_blur(self, position: FloatArray, shutter: Shutter, rad: FloatArray,
                     sid: np.ndarray, t: FloatArray, dirs: FloatArray) -> FloatArray:
        """``rad (P, 3)`` blurred along each pixel's flow during the exposure: the scene point
        it sees (distance ``t`` along world direction ``dirs``) projected at the shutter-open
        and shutter-close poses. Body pixels move with the camera (no flow); the occluder's
        own motion is ignored."""
        cam = self.camera
        H, W = cam.height, cam.width
        far = np.where(np.isfinite(t), t, 1e4).astype(np.float64)
        pts = np.asarray(position, dtype=np.float64) + far[:, None] * dirs
        uv = [cam.pixels_from_rays((pts - np.asarray(c, dtype=np.float64)) @ np.asarray(R))
              for R, c in ((shutter.open_rotation, shutter.open_position),
                           (shutter.close_rotation, shutter.close_position))]
        d = uv[1] - uv[0]
        if self.wrap_u:
            d[:, 0] = (d[:, 0] + W / 2) % W - W / 2
        d[~np.isfinite(d).all(axis=1)] = 0.0
        d[(sid >= _BODY_SID) & (sid < _OCCLUDER_SID)] = 0.0
        flow = np.zeros((H * W, 2), dtype=np.float32)
        flow[self.pixel_index] = d
        img = np.zeros((H * W, 3), dtype=np.float32)
        img[self.pixel_index] = rad
        out = blur_along_flow(img.reshape(H, W, 3), self.mask.astype(np.float32),
                              flow.reshape(H, W, 2), wrap_u=self.wrap_u)
        return np.asarray(out.reshape(-1, 3)[self.pixel_index])

    def depth_along_rays(self, world_from_cam: FloatArray, position: FloatArray,
                         rays_cam: FloatArray) -> FloatArray:
        """Distance (m, along each unit ray) to the first surface; inf where nothing is hit."""
        r = np.asarray(rays_cam, dtype=np.float32).reshape(-1, 3)
        r = r / np.linalg.norm(r, axis=1, keepdims=True)
        return np.asarray(self.cast(world_from_cam, position, r)["t_hit"], dtype=np.float64)


@dataclass(frozen=True)
class LineSamples:
    """Points of the true 3D segments that a frame sees, and their pixels.

    Attributes:
        uv: ``(M, 2)`` pixels (OpenCV convention) of the visible sample points.
        segment: ``(M,)`` index of the segment (into the scene's ``lines``) of each point.
        points: ``(M, 3)`` the sample points (world, metres).
    """

    uv: FloatArray
    segment: np.ndarray
    points: FloatArray


def visible_line_samples(renderer: Renderer, world_from_cam: FloatArray, position: FloatArray,
                         *, spacing: float = 0.01, mask_margin_px: int = 4,
                         occlusion_tol: float = 0.03) -> LineSamples:
    """Sample the scene's true segments every ``spacing`` metres and keep the points this
    camera pose sees: imaged by the model, at least ``mask_margin_px`` inside the valid mask
    (and the image), and not occluded (the ray to the point hits nothing more than
    ``occlusion_tol`` metres before it). Segment endpoints are left out."""
    import cv2

    cam = renderer.camera
    lines = renderer.scene.lines
    seg_len = lines.lengths
    counts = np.maximum(2, np.ceil(seg_len / spacing).astype(np.int64)) - 1
    seg = np.repeat(np.arange(len(lines)), counts)
    # parameter of each point along its segment, strictly inside (0, 1)
    first = np.cumsum(counts) - counts
    k = np.arange(len(seg)) - first[seg] + 1
    a = (k / (counts[seg] + 1))[:, None]
    pts = lines.starts[seg] + a * (lines.ends[seg] - lines.starts[seg])
    R = np.asarray(world_from_cam, dtype=np.float64)
    rays = (pts - np.asarray(position, dtype=np.float64)) @ R
    dist = np.linalg.norm(rays, axis=1)
    uv = cam.pixels_from_rays(rays)
    ok = np.isfinite(uv).all(axis=1) & (dist > 1e-6)
    mask: np.ndarray = renderer.mask.astype(np.uint8)
    if mask_margin_px > 0:
        ker = np.ones((2 * mask_margin_px + 1, 2 * mask_margin_px + 1), np.uint8)
        mask = np.asarray(cv2.erode(mask, ker, borderType=cv2.BORDER_CONSTANT, borderValue=0))
    ui = np.rint(np.where(ok[:, None], uv, -1)).astype(np.int64)
    ok &= (ui[:, 0] >= 0) & (ui[:, 0] < cam.width) & (ui[:, 1] >= 0) & (ui[:, 1] < cam.height)
    idx = np.flatnonzero(ok)
    ok[idx] = mask[ui[idx, 1], ui[idx, 0]] > 0
    idx = np.flatnonzero(ok)
    hit = renderer.depth_along_rays(R, position, rays[idx])
    ok[idx] = hit > dist[idx] - occlusion_tol
    return LineSamples(uv[ok], seg[ok], pts[ok])


def _value_noise(uv: np.ndarray, table: np.ndarray) -> np.ndarray:
    """2D value noise in [0, 1] with quintic interpolation; ``uv`` in lattice units."""
    m = table.shape[0] - 1
    f = np.floor(uv)
    fr = uv - f
    i = f.astype(np.int64) & m
    j = (i + 1) & m
    w = fr * fr * fr * (fr * (fr * 6 - 15) + 10)
    flat, n = table.ravel(), table.shape[1]  # one gather per corner: faster than 2D indexing
    i0, j0 = i[:, 0] * n, j[:, 0] * n
    a = flat[i0 + i[:, 1]]
    b = flat[j0 + i[:, 1]]
    c = flat[i0 + j[:, 1]]
    d = flat[j0 + j[:, 1]]
    top = a + (b - a) * w[:, 0]
    bot = c + (d - c) * w[:, 0]
    return np.asarray(top + (bot - top) * w[:, 1])


def _spots(uv: np.ndarray, foot: np.ndarray, table: np.ndarray, rmin: float,
           rmax: float) -> np.ndarray:
    """Albedo factor of one random disc per lattice cell (``uv`` and the footprint ``foot`` in
    cell units): radius in ``[rmin, rmax]`` cells, dark (x0.35) or light (x1.6), from the
    hashed ``table``; the border is blurred over the footprint."""
    m = table.shape[0] - 1
    f = np.floor(uv)
    fr = uv - f
    i = f.astype(np.int64) & m
    h = table.ravel()[i[:, 0] * table.shape[1] + i[:, 1]].astype(np.float64)
    # derive the disc's parameters from the single hash value of the cell (h >= 0: the
    # fractional part is x - floor(x), exactly x % 1.0 and faster)
    h2, h3, h4 = (x - np.floor(x) for x in (h * 7919.0, h * 104729.0, h * 1299709.0))
    r = rmin + (rmax - rmin) * h
    cx = r + (1 - 2 * r) * h2
    cy = r + (1 - 2 * r) * h3
    dist = np.hypot(fr[:, 0] - cx, fr[:, 1] - cy)
    fp = np.maximum(foot, 1e-6)
    inside = np.clip((r - dist) / fp + 0.5, 0.0, 1.0) * np.minimum(1.0, (2 * r / fp) ** 2)
    return 1.0 + inside * (np.where(h4 < 0.5, 0.35, 1.6) - 1.0)


@dataclass(frozen=True, kw_only=True)
class RenderOptions:
    scene: SceneName = SceneName.CORRIDOR
    """Which scene to render."""
    camera: str | Path | CameraModel = CameraKind.HYPERBOLOID.value
    """A camera kind (``hyperboloid``, ``equirectangular``), a camera file, or a model."""
    preset: Preset = Preset.PAPER
    """Default frame count and image size: ``small`` (tests) or ``paper`` (the paper's size)."""
    frames: int | None = None
    """Number of frames; None: the preset's."""
    width: int | None = None
    """Image width in pixels (camera kinds only); None: the preset's."""
    height: int | None = None
    """Image height in pixels (camera kinds only); None: the preset's."""
    textured: bool = False
    """Add procedural surface texture (point features) to the line-rich scene."""
    seed: int = 0
    """Seeds the path, the texture and the sensor noise."""
    video: bool = False
    """Write ``video.mp4`` instead of image frames."""
    video_codec: VideoCodec = VideoCodec.MP4V
    """Codec of ``video.mp4``: ``mp4v`` (OpenCV's MPEG-4 Part 2 writer) or ``h264`` (PyAV,
    libx264, yuv420p; what 360 cameras write, and the ``--footage`` default)."""
    video_crf: int = 18
    """H.264 constant rate factor, 0 (lossless) .. 51 (worst); x264's default is 23."""
    supersample: int = 3
    """Sub-pixel rays per edge pixel along each axis (1: no anti-aliasing)."""
    noise_sigma: float = 1.0
    """Read noise: Gaussian std-dev, 8-bit grey levels."""
    route: Route = Route.LANE
    """How the camera moves (``omni_sfm.synth.paths.Route``)."""
    path_length: float | None = None
    """Camera path length, metres; None: the route's default (1.5 m for ``lane``)."""
    mount: Mount | None = None
    """Camera mount; None: robot for the hyperboloid camera, hand-held otherwise."""
    fps: float = 15.0
    """Frame rate: written into ``video.mp4``; sets the occluder's steps per frame."""
    effects: Effects = field(default_factory=Effects)
    """Real-footage effects (:class:`omni_sfm.synth.effects.Effects`); all off by default."""


@dataclass(frozen=True)
class RenderSetup:
    """Everything needed to render a sequence: scene, camera, trajectory and the renderer.

    ``scene`` and ``groundtruth`` are in the scene frame (metres, +Z up, floor at z = 0), where
    the renderer works. The files of :func:`render_sequence` use omni-sfm's world instead, the
    first camera's frame (still metres): see :meth:`world_from_scene`.
    """

    scene: Scene
    camera: CameraModel
    groundtruth: Trajectory
    renderer: Renderer
    mount: Mount
    occluder_path: FloatArray | None = None
    """``(N, 3)`` feet of the walking occluder per frame (scene frame), if there is one."""

    def render_frame(self, k: int) -> np.ndarray:
        """``(H, W, 3)`` uint8 RGB frame ``k`` with every effect (motion blur from the ground
        truth's motion within the exposure, the occluder at its place)."""
        gt = self.groundtruth
        exposure = self.renderer.options.effects.motion_blur
        shutter = shutter_poses(gt, k, exposure) if exposure > 0 else None
        occ = self.occluder_path[k] if self.occluder_path is not None else None
        return self.renderer.render(gt.rotations[k], gt.positions[k], k, shutter=shutter,
                                    occluder=occ)

    def world_from_scene(self) -> tuple[FloatArray, FloatArray]:
        """``(R (3, 3), t (3,))`` with ``x_world = R @ x_scene + t``, world = first camera."""
        R0, c0 = self.groundtruth.rotations[0], self.groundtruth.positions[0]
        return R0.T, -R0.T @ c0

    def groundtruth_in_world(self) -> Trajectory:
        """The trajectory in the first camera's frame (the first pose is the identity)."""
        R, t = self.world_from_scene()
        gt = self.groundtruth
        return Trajectory(gt.timestamps.copy(), R @ gt.rotations, gt.positions @ R.T + t)

    def scene_in_world(self) -> Scene:
        """The scene (mesh, lines, lights) in the first camera's frame."""
        return self.scene.transformed(*self.world_from_scene())


def prepare(options: RenderOptions) -> RenderSetup:
    """Check ``options`` and build the scene, camera, trajectory and renderer."""
    o = options
    scene = make_scene(o.scene)
    try:
        preset = Preset(o.preset)
    except ValueError:
        raise OmniSfmError(
            f"unknown preset {o.preset!r} (known: {', '.join(p.value for p in Preset)})"
        ) from None
    frames = o.frames if o.frames is not None else PRESETS[preset].frames
    if isinstance(frames, bool) or not isinstance(frames, int) or frames <= 0:
        raise OmniSfmError(f"number of frames must be a positive integer, got {frames!r}")
    camera = make_camera(o.camera, width=o.width, height=o.height, preset=preset)
    try:
        mount = Mount(o.mount) if o.mount is not None else default_mount(camera)
    except ValueError:
        raise OmniSfmError(
            f"unknown mount {o.mount!r} (known: {', '.join(m.value for m in Mount)})"
        ) from None
    _check_output_options(o)
    check_effects(o.effects, camera.model)
    traj = camera_path(scene, PathOptions(num_frames=frames, route=o.route,
                                          path_length=o.path_length, mount=mount, seed=o.seed))
    renderer = Renderer(scene, camera, ShadingOptions(
        supersample=o.supersample, textured=o.textured, noise_sigma=o.noise_sigma, seed=o.seed,
        effects=o.effects), mount=mount)
    occ = occluder_path(traj, mount, o.fps, o.seed) if o.effects.occluder else None
    return RenderSetup(scene, camera, traj, renderer, mount, occ)


def _check_output_options(o: RenderOptions) -> None:
    if not (isinstance(o.fps, int | float) and not isinstance(o.fps, bool)
            and np.isfinite(o.fps) and o.fps > 0):
        raise OmniSfmError(f"frame rate must be > 0, got {o.fps!r}")
    try:
        VideoCodec(o.video_codec)
    except ValueError:
        raise OmniSfmError(f"unknown video codec {o.video_codec!r} "
                           f"(known: {', '.join(c.value for c in VideoCodec)})") from None
    crf = o.video_crf
    if isinstance(crf, bool) or not isinstance(crf, int) or not 0 <= crf <= 51:
        raise OmniSfmError(f"H.264 CRF must be an integer 0..51, got {crf!r}")
    if o.video and o.effects.jpeg_quality is not None:
        raise OmniSfmError("JPEG quality applies to image frames: not with --video (set the "
                           "video's compression with --video-crf)")


def footage_options(options: RenderOptions) -> RenderOptions:
    """``options`` with the ``--footage`` effects (:func:`~omni_sfm.synth.effects.footage_effects`
    for the camera's mount; JPEG frames, or H.264 at CRF 23 with ``video``)."""
    from dataclasses import replace

    from omni_sfm.synth.effects import footage_effects

    o = options
    try:
        preset = Preset(o.preset)
    except ValueError:
        raise OmniSfmError(f"unknown preset {o.preset!r}") from None
    camera = make_camera(o.camera, width=o.width, height=o.height, preset=preset)
    mount = Mount(o.mount) if o.mount is not None else default_mount(camera)
    return replace(o, effects=footage_effects(mount, video=o.video),
                   video_codec=VideoCodec.H264, video_crf=23)


def render_frames(options: RenderOptions) -> tuple[RenderSetup, np.ndarray]:
    """Render a whole sequence in memory: the setup and ``(N, H, W, 3)`` uint8 RGB images."""
    setup = prepare(options)
    imgs = np.stack([setup.render_frame(k) for k in range(len(setup.groundtruth))])
    return setup, imgs


@dataclass(frozen=True)
class RenderResult:
    """What :func:`render_sequence` wrote; ``groundtruth`` as in ``groundtruth.tum`` (world =
    first camera, metres)."""

    output: Path
    camera: CameraModel
    groundtruth: Trajectory
    num_frames: int
    seconds_per_frame: float


def render_sequence(output: Path | str, options: RenderOptions | None = None, *,
                    overwrite: bool = False, progress: bool = True) -> RenderResult:
    """Render a sequence into ``output`` (complete or absent; see docs/rendering.md)."""
    import cv2
    from tqdm import tqdm

    o = options or RenderOptions()
    output = Path(output)
    from omni_sfm.fileio import check_output_dir

    check_output_dir(output, overwrite=overwrite)
    setup = prepare(o)
    cam, gt = setup.camera, setup.groundtruth
    n = len(gt)
    t0 = time.perf_counter()
    quality = o.effects.jpeg_quality
    with atomic_output_dir(output, overwrite=overwrite) as tmp:
        writer = None
        if o.video:
            writer = VideoWriter(tmp / RenderFolder.VIDEO, o.video_codec, o.fps, cam.width,
                                 cam.height, o.video_crf)
        else:
            (tmp / RenderFolder.IMAGES).mkdir()
        try:
            for k in tqdm(range(n), desc=f"render {o.scene}", unit="frame",
                          disable=None if progress else True, leave=False):
                img = setup.render_frame(k)
                if writer is not None:
                    writer.write(img)
                    continue
                bgr = np.ascontiguousarray(img[:, :, ::-1])
                name = Path(video_frame_name(k))
                if quality is not None:
                    ok = cv2.imwrite(str(tmp / RenderFolder.IMAGES / name.with_suffix(".jpg")),
                                     bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
                else:
                    ok = cv2.imwrite(str(tmp / RenderFolder.IMAGES / name), bgr)
                if not ok:
                    raise OmniSfmError(f"{output}: could not write frame {k}")
        finally:
            if writer is not None:
                writer.close()
        seconds = (time.perf_counter() - t0) / n
        R_ws, t_ws = setup.world_from_scene()
        world_scene = setup.scene_in_world()
        up = R_ws[:, 2]
        write_camera_yaml(tmp / RenderFolder.CAMERA, cam)
        truth = setup.groundtruth_in_world()
        if o.video:  # stamped as omni-sfm stamps video frames: seconds, index / frame rate
            truth = Trajectory(truth.timestamps / float(o.fps), truth.rotations, truth.positions)
        write_tum(tmp / RenderFolder.GROUNDTRUTH, truth)
        world_scene.write_ply(tmp / RenderFolder.SCENE)
        write_lines3d(tmp / RenderFolder.LINES3D, world_scene.lines,
                      frame="world = first camera's ray frame, metres", up=up)
        meta: dict[str, Any] = {
            f.name: getattr(o, f.name) for f in fields(o)
        }
        for k, v in meta.items():
            if isinstance(v, Effects):
                meta[k] = effects_json(v)
            elif isinstance(v, StrEnum):
                meta[k] = v.value
            elif isinstance(v, CameraModel):
                meta[k] = v.model
            elif isinstance(v, Path):
                meta[k] = str(v)
        world_from_scene = np.eye(4)
        world_from_scene[:3, :3], world_from_scene[:3, 3] = R_ws, t_ws
        meta.update(mount=setup.mount.value, num_frames=n, width=cam.width, height=cam.height,
                    world="first camera's ray frame, metres",
                    world_from_scene=world_from_scene,
                    scene_frame="metres, +Z up, floor at z=0", up_in_world=up,
                    path_length_m=gt.path_length(), seconds_per_frame=seconds)
        atomic_write_text(tmp / RenderFolder.META, dumps_json(meta))
    return RenderResult(output, cam, truth, n, seconds)
