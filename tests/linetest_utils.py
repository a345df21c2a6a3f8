"""Synthetic omnidirectional images of a box-shaped room with exact 3D line ground truth.

A ray caster: every pixel's rays (``supersample`` x ``supersample`` sub-pixel rays, averaged for
anti-aliasing) hit the inside of an axis-aligned box; each face has a grey level and may hold
axis-aligned rectangles ("doors", "windows") of another grey. The straight edges of the picture
are exactly the box edges and the rectangles' edges, returned as 3D segments.

Why not the renderer's (Open3D) ray casting: this slab test in float32 and Open3D's triangle
intersection disagree on which face a ray grazing a box edge hits, so a few edge pixels differ
(frame 0 of the tests' hyperboloid path: 69 pixels, up to 10 grey levels) and the figures the
line tests quote would move. The cameras are the renderer's (identical models).

:func:`render` keeps the images it made (tests render the same poses again and again) and
returns a fresh copy each time, so a caller may paint on it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from omni_sfm.cameras import CameraModel, EquirectangularCamera, HyperboloidCamera
from omni_sfm.geometry import normalize
from omni_sfm.synth import render as synth_render


def hyperboloid_camera() -> HyperboloidCamera:
    """The paper's 800x600 hyperboloid camera (the renderer's)."""
    return synth_render.hyperboloid_camera(800, 600)


def equirect_camera() -> EquirectangularCamera:
    """The 1600x800 equirectangular camera (the renderer's paper size)."""
    cam = synth_render.make_camera(synth_render.CameraKind.EQUIRECTANGULAR,
                                   preset=synth_render.Preset.PAPER)
    assert isinstance(cam, EquirectangularCamera) and (cam.width, cam.height) == (1600, 800)
    return cam


# world z up; the equirectangular camera's +Y is down and +Z its image centre
EQUIRECT_WORLD_FROM_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class Rect:
    """An axis-aligned rectangle on face ``(axis, side)``: ``side`` 0 = the box's low face."""

    axis: int
    side: int
    lo: tuple[float, float]  # low corner in the face's two other axes (ascending axis order)
    hi: tuple[float, float]
    grey: float


@dataclass(frozen=True)
class Room:
    lo: tuple[float, float, float] = (-2.0, -1.5, -1.2)
    hi: tuple[float, float, float] = (3.0, 1.5, 1.3)
    greys: tuple[float, ...] = (110.0, 160.0, 90.0, 185.0, 60.0, 215.0)  # -x +x -y +y -z +z
    rects: tuple[Rect, ...] = field(default_factory=lambda: (
        Rect(0, 1, (-0.5, -1.2), (0.4, 0.9), 40.0),     # door, far wall
        Rect(1, 0, (-1.0, -1.2), (-0.1, 0.8), 230.0),   # door, right wall
        Rect(1, 1, (0.5, -0.2), (1.8, 0.7), 30.0),      # window, left wall
        Rect(1, 0, (1.0, -0.3), (2.2, 0.6), 200.0),     # window, right wall
        Rect(0, 0, (-0.8, -0.4), (0.6, 0.5), 215.0),    # picture, back wall
        Rect(2, 0, (-1.0, -0.6), (1.5, 0.6), 120.0),    # carpet
    ))

    def segments(self) -> np.ndarray:
        """``(S, 2, 3)`` the 3D straight edges of the rendered picture (world)."""
        lo, hi = np.array(self.lo), np.array(self.hi)
        segs = []
        for a in range(3):  # box edges parallel to axis a
            b, c = [k for k in range(3) if k != a]
            for vb in (lo[b], hi[b]):
                for vc in (lo[c], hi[c]):
                    p, q = np.zeros(3), np.zeros(3)
                    p[a], q[a] = lo[a], hi[a]
                    p[b] = q[b] = vb
                    p[c] = q[c] = vc
                    segs.append((p, q))
        for r in self.rects:
            b, c = [k for k in range(3) if k != r.axis]
            w = (lo if r.side == 0 else hi)[r.axis]
            corners = []
            for vb, vc in ((r.lo[0], r.lo[1]), (r.hi[0], r.lo[1]), (r.hi[0], r.hi[1]),
                           (r.lo[0], r.hi[1])):
                p = np.zeros(3)
                p[r.axis], p[b], p[c] = w, vb, vc
                corners.append(p)
            for k in range(4):
                segs.append((corners[k], corners[(k + 1) % 4]))
        return np.array(segs)

    def line_ids(self) -> np.ndarray:
        """``(S,)`` one id per distinct infinite 3D line: segments lying on one line (a door's
        bottom edge on the floor's edge) share the id of the first of them."""
        seg = self.segments()
        d = normalize(seg[:, 1] - seg[:, 0])
        ids = np.arange(len(seg))
        for i in range(len(seg)):
            for j in range(i):
                off = seg[i, 0] - seg[j, 0]
                if abs(d[i] @ d[j]) > 1 - 1e-9 and \
                        np.linalg.norm(off - (off @ d[j]) * d[j]) < 1e-9:
                    ids[i] = ids[j]
                    break
        return ids

    def shade(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Grey level seen along world rays ``dirs (N, 3)`` from ``origin`` inside the box."""
        lo, hi = np.array(self.lo), np.array(self.hi)
        d = np.asarray(dirs, np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            tk = (np.where(d > 0, hi, lo) - origin).astype(np.float32) / d
        tk[~(tk > 0)] = np.inf
        axis = np.argmin(tk, axis=1)
        rows = np.arange(len(d))
        t = tk[rows, axis]
        side = d[rows, axis] > 0
        face = 2 * axis + side
        grey = np.asarray(self.greys, np.float32)[face]
        for r in self.rects:
            b, c = [k for k in range(3) if k != r.axis]
            sel = np.flatnonzero(face == 2 * r.axis + r.side)
            hb = origin[b] + t[sel] * d[sel, b]
            hc = origin[c] + t[sel] * d[sel, c]
            on = (hb > r.lo[0]) & (hb < r.hi[0]) & (hc > r.lo[1]) & (hc < r.hi[1])
            grey[sel[on]] = r.grey
        return grey


@functools.lru_cache(maxsize=4)
def centre_rays(camera: CameraModel) -> np.ndarray:
    """``(H, W, 3)`` float32 rays of the pixel centres (NaN where invalid); cached."""
    return camera.pixel_grid_rays().astype(np.float32)


def render(camera: CameraModel, room: Room, world_from_cam: np.ndarray, position: np.ndarray,
           supersample: int = 4, background: float = 0.0, noise: float = 0.0,
           seed: int = 0) -> np.ndarray:
    """8-bit grey image of ``room`` from a camera at ``position`` with rotation
    ``world_from_cam``; invalid pixels get ``background``.

    Adaptive anti-aliasing: pixels whose centre value differs from a 4-neighbour's are
    re-rendered as the mean of ``supersample x supersample`` sub-pixel rays.

    Each distinct input is rendered once per test session; every call returns its own copy.
    """
    R = np.asarray(world_from_cam, np.float64)
    pos = np.asarray(position, np.float64)
    assert R.shape == (3, 3) and pos.shape == (3,), (R.shape, pos.shape)
    return _render_cached(camera, room, R.tobytes(), pos.tobytes(), supersample, background,
                          noise, seed).copy()


@functools.lru_cache(maxsize=64)
def _render_cached(camera: CameraModel, room: Room, world_from_cam: bytes, position: bytes,
                   supersample: int, background: float, noise: float, seed: int) -> np.ndarray:
    img = _render(camera, room, np.frombuffer(world_from_cam).reshape(3, 3),
                  np.frombuffer(position), supersample, background, noise, seed)
    img.flags.writeable = False
    return img


def _render(camera: CameraModel, room: Room, world_from_cam: np.ndarray, position: np.ndarray,
            supersample: int, background: float, noise: float, seed: int) -> np.ndarray:
    R = np.asarray(world_from_cam, np.float32)
    pos = np.asarray(position, float)
    rays = centre_rays(camera)
    h, w, _ = rays.shape
    flat = rays.reshape(-1, 3)
    ok = np.isfinite(flat[:, 0])
    grey = np.full(len(flat), np.nan, np.float32)
    grey[ok] = room.shade(pos, flat[ok] @ R.T)
    g = grey.reshape(h, w)
    pad = np.pad(g, 1, mode="edge")
    edge = np.zeros((h, w), bool)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        nb = pad[dy : dy + h, dx : dx + w]
        edge |= (nb != g) | (np.isnan(nb) != np.isnan(g))
    ys, xs = np.nonzero(edge)
    s = supersample
    off = (np.arange(s) + 0.5) / s - 0.5
    ou, ov = (a.ravel() for a in np.meshgrid(off, off))
    uv = np.stack([(xs[:, None] + ou).ravel(), (ys[:, None] + ov).ravel()], 1)
    sub = camera.rays_from_pixels(uv).astype(np.float32)
    good = np.isfinite(sub[:, 0])
    val = np.zeros(len(sub), np.float32)
    val[good] = room.shade(pos, sub[good] @ R.T)
    n = good.reshape(-1, s * s).sum(axis=1)
    tot = val.reshape(-1, s * s).sum(axis=1)
    g[ys, xs] = np.where(n > 0, tot / np.maximum(n, 1), np.nan)
    img = np.where(np.isfinite(g), g, background)
    if noise > 0:
        img = img + np.random.default_rng(seed).normal(0.0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def true_normals(segments: np.ndarray, world_from_cam: np.ndarray,
                 position: np.ndarray) -> np.ndarray:
    """``(S, 3)`` unit NVs in the camera frame of the 3D ``segments`` ``(S, 2, 3)``."""
    p = (segments - position) @ np.asarray(world_from_cam)  # cam = R^T (x - t)
    return normalize(np.cross(p[:, 0], p[:, 1]))


def nv_errors_deg(normals: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per extracted normal: smallest unsigned angle (deg) to any true NV, and its index."""
    if len(normals) == 0:
        return np.zeros(0), np.zeros(0, int)
    c = np.abs(normals @ truth.T)
    best = np.argmax(c, axis=1)
    ang = np.degrees(np.arccos(np.clip(c[np.arange(len(normals)), best], 0.0, 1.0)))
    return ang, best


def label_lines(lines, segments: np.ndarray, line_ids: np.ndarray, world_from_cam: np.ndarray,
                position: np.ndarray, max_deg: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """True line id of each extracted line (-1 if none) and the NV error (deg) to it.

    A line matches a segment if their NVs agree within ``max_deg`` and the extracted line's
    middle point lies on the segment's arc (within 1 deg), so coplanar segments are told apart.
    """
    nl = lines.num_lines
    if nl == 0:
        return np.zeros(0, int), np.zeros(0)
    tn = true_normals(segments, world_from_cam, position)
    c = np.abs(lines.normals @ tn.T)
    ang = np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))  # (L, S)
    mid = lines.point_rays[(lines.offsets[:-1] + lines.offsets[1:]) // 2]
    p = (segments - position) @ np.asarray(world_from_cam)
    a, b = normalize(p[:, 0]), normalize(p[:, 1])
    n = normalize(np.cross(a, b))
    s1 = np.einsum("lsk,sk->ls", np.cross(a[None], mid[:, None]), n)
    s2 = np.einsum("lsk,sk->ls", np.cross(mid[:, None], b[None]), n)
    tol = np.sin(np.radians(1.0))
    inside = (s1 > -tol) & (s2 > -tol)
    cost = np.where(inside & (ang < max_deg), ang, np.inf)
    best = np.argmin(cost, axis=1)
    err = cost[np.arange(nl), best]
    lab = np.where(np.isfinite(err), line_ids[best], -1)
    return lab, np.where(np.isfinite(err), err, ang.min(axis=1))
