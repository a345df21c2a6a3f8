"""Man-made scenes for rendering: triangle meshes with materials, lights and true 3D lines.

Every scene is built from axis-aligned (or yawed) boxes, flat rectangles and, for bins, upright
polygonal prisms. World frame: metres, ``+Z`` up, the floor at ``z = 0``. Thin "bands"
(baseboards, door frames, doors, window frames, light panels, posters) lie :data:`BAND_OFFSET`
in front of the surface they decorate, so each visible straight edge is a real edge of the mesh,
and the true line segments are recorded on the visible surface, where the image edge is.

The true segments (:class:`LineSegments3D`) are the straight edges a person would see: where
walls meet floor and ceiling, baseboard tops, door and window frames, light panels, pillar and
furniture edges, posters, floor-tile seams. Each carries a direction group (segments parallel to
each other share a group; group 0 is the most populated one) and a kind naming what it is. Bins
stand for cylinders: 24-sided prisms whose facet edges and rims are not in the line list (a real
cylinder's outline is a silhouette that moves with the viewer, not a fixed 3D line).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from enum import IntEnum, StrEnum
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray, rotation_about_axis
from omni_sfm.libs import open3d_module
from omni_sfm.lines3d import LineSegments3D

BAND_OFFSET = 0.0005
"""Distance (m) of decorative bands in front of the surface they lie on (0.5 mm: far below a
pixel at any distance the cameras see, far above the ray caster's float32 resolution)."""


class SceneName(StrEnum):
    CORRIDOR = "corridor"
    ROOM = "room"
    OFFICE = "office"
    CELLHOUSE = "cellhouse"
    BLOCK = "block"


class Material(IntEnum):
    """Surface materials; per-triangle ids of :attr:`Scene.materials`."""

    WALL = 0
    FLOOR = 1
    CEILING = 2
    BASEBOARD = 3
    DOOR_FRAME = 4
    DOOR = 5
    LIGHT = 6
    PILLAR = 7
    WINDOW_FRAME = 8
    WINDOW = 9
    FURNITURE = 10
    FURNITURE_DARK = 11
    END_WALL = 12
    FLOOR_TILE = 13
    FLOOR_TILE_DARK = 14
    POSTER = 15
    POSTER_RED = 16
    POSTER_BLUE = 17
    BOX = 18
    BIN = 19
    CHAIR = 20
    CHAIR_SEAT = 21


# linear RGB albedo, emitted radiance (linear RGB), textured by --textured
MATERIAL_ALBEDO = np.array([
    [0.62, 0.58, 0.50],  # WALL: warm off-white
    [0.30, 0.28, 0.26],  # FLOOR: grey linoleum
    [0.78, 0.78, 0.76],  # CEILING
    [0.10, 0.09, 0.08],  # BASEBOARD: dark
    [0.80, 0.80, 0.78],  # DOOR_FRAME: white paint
    [0.36, 0.20, 0.10],  # DOOR: wood
    [0.00, 0.00, 0.00],  # LIGHT: emissive only
    [0.50, 0.52, 0.56],  # PILLAR: concrete grey
    [0.14, 0.14, 0.15],  # WINDOW_FRAME: dark aluminium
    [0.00, 0.00, 0.00],  # WINDOW: emissive sky
    [0.55, 0.40, 0.24],  # FURNITURE: light wood
    [0.12, 0.16, 0.22],  # FURNITURE_DARK: dark blue laminate
    [0.45, 0.52, 0.50],  # END_WALL: green-grey accent
    [0.31, 0.30, 0.29],  # FLOOR_TILE: carpet tile, light
    [0.23, 0.24, 0.26],  # FLOOR_TILE_DARK: carpet tile, dark blue-grey
    [0.85, 0.84, 0.80],  # POSTER: paper
    [0.55, 0.13, 0.10],  # POSTER_RED: printed picture
    [0.10, 0.22, 0.45],  # POSTER_BLUE: printed picture
    [0.52, 0.37, 0.20],  # BOX: cardboard
    [0.16, 0.30, 0.22],  # BIN: green plastic
    [0.07, 0.07, 0.08],  # CHAIR: black frame
    [0.20, 0.28, 0.45],  # CHAIR_SEAT: blue fabric
], dtype=np.float64)
MATERIAL_EMISSION = np.zeros_like(MATERIAL_ALBEDO)
MATERIAL_EMISSION[Material.LIGHT] = [2.0, 2.0, 1.9]
MATERIAL_EMISSION[Material.WINDOW] = [0.75, 0.85, 1.0]
MATERIAL_TEXTURED = np.ones(len(Material), dtype=bool)
MATERIAL_TEXTURED[[Material.LIGHT, Material.WINDOW]] = False


@dataclass(frozen=True)
class Scene:
    """A renderable scene.

    Attributes:
        name: scene name.
        vertices: ``(V, 3)`` mesh vertices (world, metres).
        triangles: ``(T, 3)`` int32 vertex indices.
        materials: ``(T,)`` int :class:`Material` of each triangle.
        surfaces: ``(T,)`` int id of the flat rectangle each triangle belongs to.
        lines: the true 3D line segments.
        light_positions: ``(K, 3)`` point lights (world, metres).
        light_power: ``(K,)`` light strengths (irradiance ``power / (d^2 + 1 m^2)`` at distance d).
        walkway: ``(2, 3)`` ends of a straight free lane at floor level; camera paths run along it.
        walkway_halfwidth: free distance (m) on each side of the walkway line (and of the route),
            floor to ceiling.
        route: ``(K, 3)`` floor-level polyline, the centre line of the free path through the
            whole scene (routes that turn corners follow it); the walkway's two points in scenes
            without a corner, its first segment is the walkway in the office.
        ceiling_height: height (m) of the ceiling.
    """

    name: str
    vertices: FloatArray
    triangles: np.ndarray
    materials: np.ndarray
    surfaces: np.ndarray
    lines: LineSegments3D
    light_positions: FloatArray
    light_power: FloatArray
    walkway: FloatArray
    walkway_halfwidth: float
    ceiling_height: float
    route: FloatArray

    def transformed(self, rotation: FloatArray, translation: FloatArray) -> Scene:
        """The scene in another frame: ``x' = rotation @ x + translation`` (mesh, lines, lights,
        walkway, route; ``ceiling_height`` keeps its meaning in the scene frame)."""
        R, t = np.asarray(rotation), np.asarray(translation)
        return replace(self, vertices=self.vertices @ R.T + t,
                       lines=self.lines.transformed(R, t),
                       light_positions=self.light_positions @ R.T + t,
                       walkway=self.walkway @ R.T + t, route=self.route @ R.T + t)

    def to_open3d(self) -> Any:
        """A legacy ``open3d.geometry.TriangleMesh`` with per-vertex material colours."""
        o3d = open3d_module()
        # every vertex belongs to one rectangle, i.e. to one material
        vmat = np.zeros(len(self.vertices), dtype=np.int64)
        vmat[self.triangles.ravel()] = np.repeat(self.materials, 3)
        albedo = MATERIAL_ALBEDO + np.minimum(MATERIAL_EMISSION, 1.0)
        colours = np.clip(albedo[vmat], 0.0, 1.0) ** (1 / 2.2)
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices),
            o3d.utility.Vector3iVector(self.triangles.astype(np.int32)),
        )
        mesh.vertex_colors = o3d.utility.Vector3dVector(colours)
        mesh.compute_triangle_normals()
        return mesh

    def write_ply(self, path: Path) -> None:
        """Write the mesh as a binary PLY readable by ``open3d.io.read_triangle_mesh``."""
        o3d = open3d_module()
        path = Path(path)
        if not o3d.io.write_triangle_mesh(str(path), self.to_open3d(), write_ascii=False):
            raise OmniSfmError(f"{path}: Open3D could not write the scene mesh")

    def raycasting_scene(self) -> Any:
        """An ``open3d.t.geometry.RaycastingScene`` holding the mesh (geometry id 0)."""
        o3d = open3d_module()
        rc = o3d.t.geometry.RaycastingScene()
        rc.add_triangles(
            o3d.core.Tensor(self.vertices.astype(np.float32)),
            o3d.core.Tensor(self.triangles.astype(np.uint32)),
        )
        return rc


class _Builder:
    """Collects rectangles (two triangles each) and line segments."""

    def __init__(self) -> None:
        self.verts: list[FloatArray] = []
        self.mats: list[int] = []
        self.seg: list[tuple[FloatArray, FloatArray, str]] = []
        self.lights: list[tuple[FloatArray, float]] = []

    def rect(self, o: ArrayLike, e1: ArrayLike, e2: ArrayLike,
             mat: Material) -> None:
        """Rectangle with corner ``o`` and edge vectors ``e1``, ``e2``."""
        o_, a, b = (np.asarray(x, dtype=np.float64) for x in (o, e1, e2))
        self.quad(o_, o_ + a, o_ + a + b, o_ + b, mat)

    def quad(self, p0: ArrayLike, p1: ArrayLike, p2: ArrayLike, p3: ArrayLike,
             mat: Material) -> None:
        """Flat convex quadrilateral ``p0 p1 p2 p3`` (triangles ``p0 p1 p2`` and ``p0 p2 p3``)."""
        self.verts.append(np.stack([np.asarray(p, dtype=np.float64) for p in (p0, p1, p2, p3)]))
        self.mats.append(int(mat))

    def line(self, a: ArrayLike, b: ArrayLike, kind: str) -> None:
        self.seg.append((np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64), kind))

    def rect_lines(self, o: ArrayLike, e1: ArrayLike, e2: ArrayLike,
                   mat: Material, kind: str, edges: str = "0123") -> None:
        """Rectangle plus its edges as lines (``edges`` picks: 0 = o..o+e1, 1 = o+e1..o+e1+e2,
        2 = o+e2..o+e1+e2, 3 = o..o+e2)."""
        self.rect(o, e1, e2, mat)
        o_, a, b = (np.asarray(x, dtype=np.float64) for x in (o, e1, e2))
        ends = {"0": (o_, o_ + a), "1": (o_ + a, o_ + a + b), "2": (o_ + b, o_ + a + b),
                "3": (o_, o_ + b)}
        for k in edges:
            self.line(*ends[k], kind)

    def box(self, centre: ArrayLike, size: ArrayLike, mat: Material, kind: str,
            yaw_deg: float = 0.0, top_mat: Material | None = None,
            vertical_only: bool = False) -> None:
        """Closed box standing upright, yawed about +Z; all 12 edges become lines (only the 4
        vertical ones with ``vertical_only``, for thin legs)."""
        c = np.asarray(centre, dtype=np.float64)
        h = np.asarray(size, dtype=np.float64) / 2
        R = rotation_about_axis([0.0, 0.0, 1.0], np.radians(yaw_deg))
        ex, ey, ez = R[:, 0] * 2 * h[0], R[:, 1] * 2 * h[1], R[:, 2] * 2 * h[2]
        o = c - (ex + ey + ez) / 2
        self.rect(o, ey, ex, mat)  # bottom
        self.rect(o + ez, ex, ey, top_mat if top_mat is not None else mat)  # top
        self.rect(o, ex, ez, mat)
        self.rect(o + ey, ez, ex, mat)
        self.rect(o, ez, ey, mat)
        self.rect(o + ex, ey, ez, mat)
        corners = [o, o + ex, o + ey, o + ex + ey]
        for p in corners:
            self.line(p, p + ez, kind)
        if vertical_only:
            return
        for p, q in ((o, o + ex), (o, o + ey), (o + ex, o + ex + ey), (o + ey, o + ex + ey)):
            self.line(p, q, kind)
            self.line(p + ez, q + ez, kind)

    def prism(self, centre: ArrayLike, radius: float, height: float, mat: Material,
              sides: int = 24) -> None:
        """Closed upright prism on a regular ``sides``-gon (a cylinder to the eye), standing on
        ``centre`` (floor-level centre of its base); no lines (see the module docstring)."""
        c = np.asarray(centre, dtype=np.float64)
        ang = 2 * np.pi * np.arange(sides + 1) / sides
        ring = c + radius * np.column_stack([np.cos(ang), np.sin(ang), np.zeros(sides + 1)])
        up = np.array([0.0, 0.0, height])
        for k in range(sides):
            self.quad(ring[k], ring[k + 1], ring[k + 1] + up, ring[k] + up, mat)
        # the lid and the base as fans of quads (two triangles of the fan each)
        for k in range(0, sides, 2):
            self.quad(c + up, ring[k] + up, ring[k + 1] + up, ring[k + 2] + up, mat)
            self.quad(c, ring[k + 2], ring[k + 1], ring[k], mat)

    def light(self, pos: ArrayLike, power: float) -> None:
        self.lights.append((np.asarray(pos, dtype=np.float64), power))

    def build(self, name: str, walkway: FloatArray, halfwidth: float, ceiling: float,
              route: FloatArray | None = None) -> Scene:
        quads = np.stack(self.verts)
        n = len(quads)
        base = 4 * np.arange(n)[:, None]
        tris = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=0).astype(np.int32)
        mats = np.concatenate([self.mats, self.mats]).astype(np.int64)
        lines = _group_lines(self.seg)
        return Scene(
            name=name,
            vertices=quads.reshape(-1, 3),
            triangles=tris,
            materials=mats,
            surfaces=np.concatenate([np.arange(n), np.arange(n)]),
            lines=lines,
            light_positions=np.stack([p for p, _ in self.lights]),
            light_power=np.array([w for _, w in self.lights], dtype=np.float64),
            walkway=np.asarray(walkway, dtype=np.float64),
            walkway_halfwidth=halfwidth,
            ceiling_height=ceiling,
            route=np.asarray(walkway if route is None else route, dtype=np.float64),
        )


def _group_lines(seg: list[tuple[FloatArray, FloatArray, str]], tol_deg: float = 1.0
                 ) -> LineSegments3D:
    """Drop degenerate segments and label direction groups (largest group first)."""
    seg = [s for s in seg if np.linalg.norm(s[1] - s[0]) > 1e-6]
    starts = np.stack([s[0] for s in seg])
    ends = np.stack([s[1] for s in seg])
    d = ends - starts
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    label = -np.ones(len(seg), dtype=np.int64)
    reps: list[FloatArray] = []
    cos_tol = np.cos(np.radians(tol_deg))
    for i in range(len(seg)):
        for g, r in enumerate(reps):
            if abs(float(d[i] @ r)) >= cos_tol:
                label[i] = g
                break
        else:
            label[i] = len(reps)
            reps.append(d[i])
    counts = np.bincount(label)
    order = np.argsort(-counts, kind="stable")
    remap = np.empty_like(order)
    remap[order] = np.arange(len(order))
    dirs = np.stack([reps[g] for g in order])
    # a canonical sign: the largest component positive
    dirs *= np.sign(dirs[np.arange(len(dirs)), np.argmax(np.abs(dirs), axis=1)])[:, None]
    return LineSegments3D(starts, ends, remap[label], dirs, tuple(s[2] for s in seg))


def _add_shell(b: _Builder, size: tuple[float, float, float], wall: Material = Material.WALL,
               end_wall: Material = Material.WALL) -> None:
    """Floor, ceiling and four walls of the box ``[0,X] x [0,Y] x [0,Z]``; its 12 edges."""
    X, Y, Z = size
    b.rect((0, 0, 0), (X, 0, 0), (0, Y, 0), Material.FLOOR)
    b.rect((0, 0, Z), (0, Y, 0), (X, 0, 0), Material.CEILING)
    b.rect((0, 0, 0), (0, 0, Z), (X, 0, 0), wall)  # y = 0
    b.rect((0, Y, 0), (X, 0, 0), (0, 0, Z), wall)  # y = Y
    b.rect((0, 0, 0), (0, Y, 0), (0, 0, Z), end_wall)  # x = 0
    b.rect((X, 0, 0), (0, 0, Z), (0, Y, 0), end_wall)  # x = X
    ends: list[tuple[tuple[float, float], tuple[float, float]]] = [
        ((0, 0), (X, 0)), ((0, Y), (X, Y)), ((0, 0), (0, Y)), ((X, 0), (X, Y))]
    for p, q in ends:
        b.line((*p, 0), (*q, 0), "wall_floor")
        b.line((*p, Z), (*q, Z), "wall_ceiling")
    for p in ((0, 0), (X, 0), (0, Y), (X, Y)):
        b.line((*p, 0), (*p, Z), "wall_corner")


class _Wall:
    """A wall plane seen from inside: ``origin`` at floor level, ``along`` unit horizontal,
    ``inward`` unit normal into the room; positions on the wall are ``(s, z)``."""

    def __init__(self, origin: ArrayLike, along: ArrayLike,
                 inward: ArrayLike, length: float) -> None:
        self.o = np.asarray(origin, dtype=np.float64)
        self.a = np.asarray(along, dtype=np.float64)
        self.n = np.asarray(inward, dtype=np.float64)
        self.length = length

    def point(self, s: float, z: float, depth: float = BAND_OFFSET) -> FloatArray:
        return np.asarray(self.o + s * self.a + np.array([0, 0, z]) + depth * self.n)

    def band(self, b: _Builder, s0: float, s1: float, z0: float, z1: float, mat: Material,
             kind: str, edges: str = "0123", depth: float = BAND_OFFSET) -> None:
        """A flat rectangle on the wall; edges 0 bottom, 1 right (s1), 2 top, 3 left (s0)."""
        o = self.point(s0, z0, depth)
        e1 = (s1 - s0) * self.a
        e2 = np.array([0.0, 0.0, z1 - z0])
        # the winding does not matter for rendering (shading uses the visible side)
        b.rect_lines(o, e1, e2, mat, kind, edges)

    def line(self, b: _Builder, s0: float, z0: float, s1: float, z1: float, kind: str) -> None:
        """A segment on the wall's band plane, from ``(s0, z0)`` to ``(s1, z1)``."""
        b.line(self.point(s0, z0), self.point(s1, z1), kind)

    def door(self, b: _Builder, s0: float, width: float, height: float = 2.05,
             frame: float = 0.07) -> None:
        """Door leaf inside a frame (jambs and head); its outer and inner edges are lines."""
        s1 = s0 + width
        self.band(b, s0, s0 + frame, 0.0, height, Material.DOOR_FRAME, "door_frame", "")
        self.band(b, s1 - frame, s1, 0.0, height, Material.DOOR_FRAME, "door_frame", "")
        self.band(b, s0 + frame, s1 - frame, height - frame, height, Material.DOOR_FRAME,
                  "door_frame", "")
        self.band(b, s0 + frame, s1 - frame, 0.0, height - frame, Material.DOOR, "door", "")
        # outer edges (wall | frame) and inner edges (frame | door leaf)
        hi, si0, si1 = height - frame, s0 + frame, s1 - frame
        for a0, c0, a1, c1 in ((s0, 0, s0, height), (s1, 0, s1, height), (s0, height, s1, height),
                               (si0, 0, si0, hi), (si1, 0, si1, hi), (si0, hi, si1, hi)):
            self.line(b, a0, c0, a1, c1, "door_frame")

    def window(self, b: _Builder, s0: float, width: float, z0: float, height: float,
               frame: float = 0.06, bar: float = 0.04) -> None:
        """Window: glass (emissive) in a frame with a vertical mullion and a transom. Lines: the
        frame's outer edges and the four panes' edges (frame | glass)."""
        s1, z1 = s0 + width, z0 + height
        sm, zm = s0 + width / 2, z0 + 0.6 * height
        kind = "window_frame"
        mat = Material.WINDOW_FRAME
        self.band(b, s0, s1, z0, z0 + frame, mat, kind, "0")
        self.band(b, s0, s1, z1 - frame, z1, mat, kind, "2")
        self.band(b, s0, s0 + frame, z0 + frame, z1 - frame, mat, kind, "")
        self.band(b, s1 - frame, s1, z0 + frame, z1 - frame, mat, kind, "")
        self.line(b, s0, z0, s0, z1, kind)
        self.line(b, s1, z0, s1, z1, kind)
        # mullion and transom, split so that no two bands overlap
        self.band(b, sm - bar / 2, sm + bar / 2, z0 + frame, z1 - frame, mat, kind, "")
        self.band(b, s0 + frame, sm - bar / 2, zm - bar / 2, zm + bar / 2, mat, kind, "")
        self.band(b, sm + bar / 2, s1 - frame, zm - bar / 2, zm + bar / 2, mat, kind, "")
        for a0, a1 in ((s0 + frame, sm - bar / 2), (sm + bar / 2, s1 - frame)):
            for c0, c1 in ((z0 + frame, zm - bar / 2), (zm + bar / 2, z1 - frame)):
                self.band(b, a0, a1, c0, c1, Material.WINDOW, kind, "0123")

    def poster(self, b: _Builder, s0: float, z0: float, width: float, height: float,
               ink: Material, tilt_deg: float = 0.0, margin: float = 0.05) -> None:
        """A paper poster (lower-left corner ``(s0, z0)`` before the tilt) turned by
        ``tilt_deg`` in the wall plane about its centre, with a printed picture inset by
        ``margin`` (three times that at the bottom, for a caption) lying one band further out.
        Lines: the paper's and the picture's edges."""
        t = np.radians(tilt_deg)
        u = np.cos(t) * self.a + np.array([0.0, 0.0, np.sin(t)])
        v = -np.sin(t) * self.a + np.array([0.0, 0.0, np.cos(t)])
        centre = self.point(s0 + width / 2, z0 + height / 2, 0.0)
        for depth, mat, (left, right, bot, top) in (
                (BAND_OFFSET, Material.POSTER, (0.0, 0.0, 0.0, 0.0)),
                (2 * BAND_OFFSET, ink, (margin, margin, 3 * margin, margin))):
            o = centre + depth * self.n + (left - width / 2) * u + (bot - height / 2) * v
            b.rect_lines(o, (width - left - right) * u, (height - bot - top) * v, mat, "poster")

    def baseboard(self, b: _Builder, gaps: Sequence[tuple[float, float]],
                  height: float = 0.1) -> None:
        """Baseboard pieces along the wall between the ``gaps`` (s intervals of doors)."""
        cuts = sorted(gaps)
        s = 0.0
        pieces = []
        for g0, g1 in cuts:
            pieces.append((s, g0))
            s = g1
        pieces.append((s, self.length))
        for p0, p1 in pieces:
            if p1 - p0 > 1e-6:
                self.band(b, p0, p1, 0.0, height, Material.BASEBOARD, "baseboard", "2")


def _ceiling_light(b: _Builder, cx: float, cy: float, ceiling: float, sx: float, sy: float,
                   power: float) -> None:
    z = ceiling - 2 * BAND_OFFSET
    b.rect_lines((cx - sx / 2, cy - sy / 2, z), (sx, 0, 0), (0, sy, 0), Material.LIGHT,
                 "light_panel")
    b.light((cx, cy, ceiling - 0.3), power)


def corridor() -> Scene:
    """A 14 m x 2 m x 2.5 m corridor along +X: six side doors, a door in each end wall,
    baseboards and five ceiling light panels. Texture-poor; lines along X, Y and Z."""
    X, Y, Z = 14.0, 2.0, 2.5
    b = _Builder()
    _add_shell(b, (X, Y, Z), end_wall=Material.END_WALL)
    # side walls: y = 0 (facing +Y) and y = Y (facing -Y); end walls x = 0 and x = X
    right = _Wall((0, 0, 0), (1, 0, 0), (0, 1, 0), X)
    left = _Wall((X, Y, 0), (-1, 0, 0), (0, -1, 0), X)
    far0 = _Wall((0, Y, 0), (0, -1, 0), (1, 0, 0), Y)
    far1 = _Wall((X, 0, 0), (0, 1, 0), (-1, 0, 0), Y)
    door_w = 0.9
    for wall, starts in ((right, (1.3, 4.6, 8.2, 11.6)), (left, (2.2, 5.6, 9.3))):
        for s0 in starts:
            wall.door(b, s0, door_w)
        wall.baseboard(b, [(s0, s0 + door_w) for s0 in starts])
    for wall in (far0, far1):
        wall.door(b, 0.5, 1.0)
        wall.baseboard(b, [(0.5, 1.5)])
    for cx in (1.6, 4.3, 7.0, 9.7, 12.4):
        _ceiling_light(b, cx, Y / 2, Z, 1.2, 0.6, 1.6)
    walkway = np.array([[1.5, Y / 2, 0.0], [X - 1.5, Y / 2, 0.0]])
    return b.build("corridor", walkway, 0.6, Z)


def room() -> Scene:
    """An 8 m x 6 m x 3 m room: two square pillars, three windows, a door, a table, a shelf and
    two cabinets yawed by 30 and -20 deg (so lines run in five directions), four light panels."""
    X, Y, Z = 8.0, 6.0, 3.0
    b = _Builder()
    _add_shell(b, (X, Y, Z))
    south = _Wall((0, 0, 0), (1, 0, 0), (0, 1, 0), X)  # y = 0
    north = _Wall((X, Y, 0), (-1, 0, 0), (0, -1, 0), X)  # y = Y
    west = _Wall((0, Y, 0), (0, -1, 0), (1, 0, 0), Y)  # x = 0
    east = _Wall((X, 0, 0), (0, 1, 0), (-1, 0, 0), Y)  # x = X
    west.door(b, 3.6, 1.0)
    west.baseboard(b, [(3.6, 4.6)])
    for wall in (south, north, east):
        wall.baseboard(b, [])
    north.window(b, 1.4, 1.4, 0.9, 1.5)
    north.window(b, 4.6, 1.4, 0.9, 1.5)
    east.window(b, 2.3, 1.6, 0.9, 1.5)
    for px in (2.6, 5.4):
        b.box((px, 1.9, Z / 2), (0.4, 0.4, Z), Material.PILLAR, "pillar")
    b.box((4.0, 5.1, 0.375), (1.6, 0.8, 0.75), Material.FURNITURE, "furniture")
    b.box((7.0, 0.25, 0.9), (1.4, 0.45, 1.8), Material.FURNITURE_DARK, "furniture",
          top_mat=Material.FURNITURE)
    b.box((1.1, 1.2, 0.5), (1.0, 0.5, 1.0), Material.FURNITURE, "furniture", yaw_deg=30.0,
          top_mat=Material.FURNITURE_DARK)
    b.box((6.7, 5.0, 0.45), (1.2, 0.5, 0.9), Material.FURNITURE_DARK, "furniture",
          yaw_deg=-20.0)
    for cx in (2.0, 6.0):
        for cy in (1.8, 4.2):
            _ceiling_light(b, cx, cy, Z, 1.2, 0.6, 2.2)
    walkway = np.array([[1.0, 3.4, 0.0], [7.0, 3.4, 0.0]])
    return b.build("room", walkway, 0.75, Z)


def _l_outline() -> FloatArray:
    """The office's floor plan, counter-clockwise: leg A along +X (15.6 m x 2.4 m), leg B
    along +Y (2.4 m x 14.4 m) from its far end."""
    return np.array([[0.0, 0.0], [15.6, 0.0], [15.6, 14.4], [13.2, 14.4], [13.2, 2.4],
                     [0.0, 2.4]])


def _add_walls(b: _Builder, outline: FloatArray, ceiling: float,
               mats: Sequence[Material]) -> list[_Wall]:
    """Walls along a counter-clockwise floor plan, their floor, ceiling and corner edges."""
    walls = []
    for k, (p, q) in enumerate(zip(outline, np.roll(outline, -1, axis=0), strict=True)):
        along = q - p
        length = float(np.linalg.norm(along))
        a = along / length
        b.rect((*p, 0.0), (*along, 0.0), (0.0, 0.0, ceiling), mats[k])
        b.line((*p, 0.0), (*q, 0.0), "wall_floor")
        b.line((*p, ceiling), (*q, ceiling), "wall_ceiling")
        b.line((*p, 0.0), (*p, ceiling), "wall_corner")
        walls.append(_Wall((*p, 0.0), (*a, 0.0), (-a[1], a[0], 0.0), length))
    return walls


def _office_floor(b: _Builder, ceiling: float, tiles: bool, tile: float = 0.6) -> None:
    """Floor and ceiling of the L. With ``tiles``: 0.6 m carpet tiles in two shades laid as a
    checkerboard, every seam a line (``floor_tile``)."""
    legs = (((0.0, 0.0), (15.6, 2.4)), ((13.2, 2.4), (15.6, 14.4)))
    for (x0, y0), (x1, y1) in legs:
        b.rect((x0, y0, ceiling), (0, y1 - y0, 0), (x1 - x0, 0, 0), Material.CEILING)
        if not tiles:
            b.rect((x0, y0, 0), (x1 - x0, 0, 0), (0, y1 - y0, 0), Material.FLOOR)
            continue
        for i in range(round(x0 / tile), round(x1 / tile)):
            for j in range(round(y0 / tile), round(y1 / tile)):
                mat = Material.FLOOR_TILE if (i + j) % 2 == 0 else Material.FLOOR_TILE_DARK
                b.rect((i * tile, j * tile, 0), (tile, 0, 0), (0, tile, 0), mat)
    if tiles:
        for k in range(1, 26):  # seams across leg A (and along leg B beyond x = 13.2)
            b.line((k * tile, 0, 0), (k * tile, 2.4 if k <= 22 else 14.4, 0), "floor_tile")
        for k in range(1, 24):  # seams along leg A (and across leg B)
            b.line((0.0 if k <= 3 else 13.2, k * tile, 0), (15.6, k * tile, 0), "floor_tile")


def _against(wall: _Wall, s: float, half: tuple[float, float], yaw_deg: float,
             gap: float = 0.03) -> tuple[FloatArray, float]:
    """Floor-level centre and world yaw (deg) of a footprint with half sizes ``(along,
    across)`` turned by ``yaw_deg`` from the wall's direction, standing ``gap`` from the wall
    at ``s``."""
    t = np.radians(yaw_deg)
    reach = abs(np.cos(t)) * half[1] + abs(np.sin(t)) * half[0]
    wall_yaw = np.degrees(np.arctan2(wall.a[1], wall.a[0]))
    return wall.point(s, 0.0, gap + reach), float(wall_yaw + yaw_deg)


def _box_against(b: _Builder, wall: _Wall, s: float, size: tuple[float, float, float],
                 yaw_deg: float, mat: Material, top_mat: Material | None = None
                 ) -> tuple[FloatArray, float]:
    """A box (``size``: along the wall, across, height) on the floor by the wall; its floor
    centre and world yaw."""
    c, yaw = _against(wall, s, (size[0] / 2, size[1] / 2), yaw_deg)
    b.box(c + [0, 0, size[2] / 2], size, mat, "clutter", yaw_deg=yaw, top_mat=top_mat)
    return c, yaw


def _chair(b: _Builder, wall: _Wall, s: float, yaw_deg: float) -> None:
    """A chair (0.44 m seat at 0.44 m, four legs, a back up to 0.97 m) by the wall, turned by
    ``yaw_deg`` from facing along it."""
    c, yaw = _against(wall, s, (0.23, 0.23), yaw_deg)
    R = rotation_about_axis([0.0, 0.0, 1.0], np.radians(yaw))
    seat_top = 0.465
    b.box(c + [0, 0, 0.44], (0.44, 0.44, 0.05), Material.CHAIR_SEAT, "chair", yaw_deg=yaw)
    for lx in (-0.19, 0.19):
        for ly in (-0.19, 0.19):
            b.box(c + R @ [lx, ly, 0.2075], (0.03, 0.03, 0.415), Material.CHAIR, "chair",
                  yaw_deg=yaw, vertical_only=True)
    b.box(c + R @ [-0.205, 0.0, seat_top + 0.2525], (0.03, 0.42, 0.505), Material.CHAIR,
          "chair", yaw_deg=yaw)


def _dress(b: _Builder, *, doors: Sequence[tuple[_Wall, Sequence[tuple[float, float]]]],
           windows: Sequence[tuple[_Wall, float]], window_width: float,
           posters: Sequence[tuple[_Wall, float, float, float, Material, float]]) -> None:
    """Doors ``(start, width)`` on each wall with the baseboard between them, windows ``(wall,
    start)`` ``window_width`` wide from 0.9 to 2.3 m, posters ``(wall, start, width, height,
    ink, tilt)`` 1.2 m up."""
    for wall, ds in doors:
        for s0, width in ds:
            wall.door(b, s0, width)
        wall.baseboard(b, [(s0, s0 + width) for s0, width in ds])
    for wall, s0 in windows:
        wall.window(b, s0, window_width, 0.9, 1.4)
    for wall, s0, w, h, ink, tilt in posters:
        wall.poster(b, s0, 1.2, w, h, ink, tilt)


def office(tiled_floor: bool = True) -> Scene:
    """An L-shaped office corridor 2.4 m wide and 2.7 m high: leg A 15.6 m along +X, then a
    90 deg left turn into leg B, 14.4 m along +Y. Doors, windows, baseboards, nine light panels,
    posters (two of them hung a few degrees crooked), carpet tiles (``tiled_floor``; else a
    plain floor) and clutter along the walls turned by various angles: cardboard boxes (one
    stacked on another), a cabinet, a low shelf, three chairs and three round bins. The route
    runs along the centre line of both legs (25.2 m as a polyline)."""
    Z = 2.7
    b = _Builder()
    wall_mats = [Material.WALL] * 6
    wall_mats[2] = wall_mats[5] = Material.END_WALL
    # south (y=0), east (x=15.6), north end of B, west of B (x=13.2), north of A (y=2.4),
    # west end of A
    south, east, end_b, west_b, north_a, end_a = _add_walls(b, _l_outline(), Z, wall_mats)
    _office_floor(b, Z, tiled_floor)
    # doors (start along the wall, width): one ends each leg, three on each inner wall
    red, blue = Material.POSTER_RED, Material.POSTER_BLUE
    _dress(b, doors=((south, ()), (east, ((0.7, 1.0),)), (end_b, ((0.7, 1.0),)),
                     (west_b, ((1.8, 0.9), (5.8, 0.9), (9.0, 0.9))),
                     (north_a, ((1.5, 0.9), (5.5, 0.9), (9.5, 0.9))), (end_a, ((0.7, 1.0),))),
           windows=((south, 2.0), (south, 6.2), (south, 10.4), (east, 4.6), (east, 9.2)),
           window_width=1.6,
           posters=((south, 4.3, 0.6, 0.85, red, 0.0), (south, 8.7, 0.8, 0.55, blue, 0.0),
                    (south, 12.6, 0.5, 0.7, blue, 0.0), (east, 2.4, 0.6, 0.8, red, 0.0),
                    (east, 7.2, 0.6, 0.85, blue, 0.0), (east, 11.8, 0.7, 0.5, red, 0.0),
                    (west_b, 3.6, 0.6, 0.85, red, 0.0), (west_b, 7.3, 0.7, 0.9, blue, -5.0),
                    (north_a, 3.3, 0.7, 0.9, blue, 0.0), (north_a, 6.8, 0.6, 0.8, red, 4.0),
                    (north_a, 11.0, 0.9, 0.6, red, 0.0)))
    _office_clutter(b, south, east, west_b, north_a)
    for cx in (1.8, 4.6, 7.4, 10.2):
        _ceiling_light(b, cx, 1.2, Z, 1.2, 0.6, 1.6)
    _ceiling_light(b, 14.4, 1.2, Z, 0.6, 0.6, 1.2)
    for cy in (4.2, 7.0, 9.8, 12.6):
        _ceiling_light(b, 14.4, cy, Z, 0.6, 1.2, 1.6)
    route = np.array([[1.2, 1.2, 0.0], [14.4, 1.2, 0.0], [14.4, 13.2, 0.0]])
    return b.build("office", route[:2], 0.5, Z, route=route)


def _office_clutter(b: _Builder, south: _Wall, east: _Wall, west_b: _Wall,
                    north_a: _Wall) -> None:
    """Boxes, a cabinet, a shelf, chairs and bins along the office's walls, none of them
    aligned with the walls (world yaws differ by several degrees from each other, so each
    object adds its own pair of horizontal line directions), all within 0.7 m of a wall."""
    box, dark, wood = Material.BOX, Material.FURNITURE_DARK, Material.FURNITURE
    _box_against(b, south, 4.8, (0.5, 0.4, 0.4), 17.0, box)
    c, _ = _box_against(b, south, 9.0, (0.6, 0.45, 0.5), -8.0, box)
    b.box(c + [0, 0, 0.64], (0.34, 0.28, 0.28), box, "clutter", yaw_deg=30.0)  # stacked on it
    b.prism(south.point(12.6, 0.0, 0.21), 0.17, 0.55, Material.BIN)
    _box_against(b, north_a, 8.3, (0.5, 0.45, 1.15), 4.0, dark, top_mat=wood)
    _chair(b, north_a, 3.8, 55.0)
    b.prism(north_a.point(11.4, 0.0, 0.2), 0.16, 0.45, Material.BIN)
    _chair(b, east, 3.3, -140.0)
    _box_against(b, east, 7.6, (0.55, 0.45, 0.45), -22.0, box)
    _chair(b, east, 12.3, 72.0)
    _box_against(b, west_b, 1.0, (0.5, 0.5, 0.35), 78.0, box)
    _box_against(b, west_b, 4.3, (1.0, 0.35, 0.8), 10.0, wood, top_mat=dark)
    b.prism(west_b.point(7.6, 0.0, 0.24), 0.2, 0.6, Material.BIN)


def _cell_front(b: _Builder, x0: float, x1: float, y: float, side: float, z0: float,
                z1: float, cell: float = 1.5, bar: float = 0.025, spacing: float = 0.125) -> None:
    """A tier of cell fronts in the plane ``y`` from ``x0`` to ``x1`` and ``z0`` to ``z1``: a
    post every ``cell`` metres, vertical bars (``bar`` square) every ``spacing`` metres between
    the posts and a flat cross bar across each cell at a third and two thirds of the height, on
    the corridor's side (``side``: +1 or -1 along ``Y``). Lines: every vertical edge of posts
    and bars, the cross bars' long edges (along ``X``)."""
    dark = Material.FURNITURE_DARK
    h = z1 - z0
    posts = np.arange(x0, x1 + 1e-9, cell)
    for px in posts:
        b.box((px, y, z0 + h / 2), (0.12, 0.12, h), dark, "cell_post", vertical_only=True)
    for a, c in zip(posts[:-1], posts[1:], strict=True):
        n = int(round((c - a - 0.12) / spacing))
        for k in range(1, n):
            b.box((a + 0.06 + k * (c - a - 0.12) / n, y, z0 + h / 2), (bar, bar, h), dark,
                  "cell_bar", vertical_only=True)
        for zc in (z0 + h / 3, z0 + 2 * h / 3):
            b.rect_lines((a + 0.06, y + side * 0.03, zc - 0.02), (c - a - 0.12, 0.0, 0.0),
                         (0.0, 0.0, 0.04), dark, "cell_crossbar", "02")


def _gallery(b: _Builder, x0: float, x1: float, y_front: float, y_edge: float, z: float,
             post_every: float = 1.5) -> None:
    """An upper-tier walkway: a slab from the cell fronts (``y_front``) to its edge
    (``y_edge``) at height ``z`` (0.2 m thick), and a railing along its edge: posts every
    ``post_every`` metres, a top rail 1 m and a middle rail 0.5 m above the slab. Lines: the
    slab's and the rails' edges along ``X``, the posts' vertical edges."""
    dark = Material.FURNITURE_DARK
    yc, depth = (y_front + y_edge) / 2, abs(y_edge - y_front)
    b.box(((x0 + x1) / 2, yc, z - 0.1), (x1 - x0, depth, 0.2), Material.PILLAR, "gallery")
    inward = np.sign(y_front - y_edge)
    yr = y_edge + inward * 0.05
    for px in np.arange(x0 + 0.25, x1 - 0.2, post_every):
        b.box((px, yr, z + 0.5), (0.05, 0.05, 1.0), dark, "railing_post", vertical_only=True)
    for zr in (z + 0.5, z + 1.0):
        b.box(((x0 + x1) / 2, yr, zr), (x1 - x0 - 0.2, 0.05, 0.05), dark, "railing")


def cellhouse() -> Scene:
    """A prison cell house 24 m x 9 m x 6.5 m along ``+X``: a corridor 3 m wide between two
    blocks of cells, each block two tiers high (2.5 m each, a 0.2 m floor between them; the
    upper tier reached by a gallery 1 m wide with a railing along it), every cell 1.5 m wide
    behind a front of vertical bars (0.025 m every 0.125 m) with two cross bars, partition walls
    between the cells, a door in each end wall, lights under the ceiling and along the corridor.
    Long lines along the walk (galleries, railings, cross bars, where walls meet floor and
    ceiling) and dense short verticals across it (bars, posts): the lines along the walk leave
    the motion along them free, the verticals fix it."""
    X, Y, Z = 24.0, 9.0, 6.5
    front_s, front_n = 3.0, 6.0  # the cell fronts: south block y < 3, north block y > 6
    tier, slab = 2.5, 0.2
    b = _Builder()
    _add_shell(b, (X, Y, Z), end_wall=Material.END_WALL)
    x0, x1 = 1.5, X - 1.5
    for z0 in (0.0, tier + slab):
        for y, side in ((front_s, 1.0), (front_n, -1.0)):
            _cell_front(b, x0, x1, y, side, z0, z0 + tier)
    # partition walls between the cells (and at both ends of each block), full height
    for px in np.arange(x0, x1 + 1e-9, 1.5):
        # lines: where the partition meets the floor and the back wall, its top
        for ya, yb, edges in ((0.0, front_s - 0.06, "023"), (front_n + 0.06, Y, "012")):
            b.rect_lines((px, ya, 0.0), (0.0, yb - ya, 0.0), (0.0, 0.0, 2 * tier + slab),
                         Material.WALL, "cell_wall", edges)
    # the upper cells' floor (the lower cells' ceiling), and the galleries in front of them
    for ya, yb in ((0.0, front_s - 0.06), (front_n + 0.06, Y)):
        b.box(((x0 + x1) / 2, (ya + yb) / 2, tier + slab / 2), (x1 - x0, yb - ya, slab),
              Material.PILLAR, "cell_floor")
    _gallery(b, x0, x1, front_s, front_s + 1.0, tier + slab)
    _gallery(b, x0, x1, front_n, front_n - 1.0, tier + slab)
    far0 = _Wall((0, Y, 0), (0, -1, 0), (1, 0, 0), Y)
    far1 = _Wall((X, 0, 0), (0, 1, 0), (-1, 0, 0), Y)
    for wall in (far0, far1):
        wall.door(b, Y / 2 - 0.6, 1.2, height=2.3)
    for cx in np.arange(2.0, X, 4.0):
        _ceiling_light(b, float(cx), Y / 2, Z, 1.2, 0.6, 2.0)
        b.light((float(cx) + 2.0, Y / 2, tier - 0.2), 1.2)
    walkway = np.array([[2.0, Y / 2, 0.0], [X - 2.0, Y / 2, 0.0]])
    return b.build("cellhouse", walkway, 0.7, Z)


def _tiled_floor(b: _Builder, cells: set[tuple[int, int]], tile: float) -> None:
    """Carpet tiles (two shades, a checkerboard) on the grid cells ``cells`` (``(i, j)``: the
    square ``[i, i+1] x [j, j+1]`` times ``tile``); every seam between two tiles a line, each
    straight run of seams one segment."""
    for i, j in sorted(cells):
        mat = Material.FLOOR_TILE if (i + j) % 2 == 0 else Material.FLOOR_TILE_DARK
        b.rect((i * tile, j * tile, 0), (tile, 0, 0), (0, tile, 0), mat)
    for axis in (0, 1):  # seams at x = i * tile (between cells i-1 and i), then at y = j * tile
        step = (1, 0) if axis == 0 else (0, 1)
        seams = sorted((c[axis], c[1 - axis]) for c in cells
                       if (c[0] - step[0], c[1] - step[1]) in cells)
        k = 0
        while k < len(seams):
            at, start = seams[k]
            end = start + 1
            while k + 1 < len(seams) and seams[k + 1] == (at, end):
                k, end = k + 1, end + 1
            k += 1
            p, q = [at * tile, start * tile, 0.0], [at * tile, end * tile, 0.0]
            if axis == 1:
                p[:2], q[:2] = p[1::-1], q[1::-1]
            b.line(p, q, "floor_tile")


def block() -> Scene:
    """An office floor 14.4 m x 9.6 m x 2.7 m whose corridor, 2.4 m wide, runs once around a
    block of offices (9.6 m x 4.8 m) in the middle: the loop route of a camera that comes back
    to where it started. Doors into the block's offices and in the outer walls, windows in
    the outer walls, posters, baseboards, carpet tiles, clutter along the walls turned by
    various angles and light panels along the corridor. The route runs along the corridor's
    centre line once around (38.4 m as a polyline) and on along its first leg (50.4 m)."""
    Z, tile = 2.7, 0.6
    b = _Builder()
    outer = np.array([[0.0, 0.0], [14.4, 0.0], [14.4, 9.6], [0.0, 9.6]])
    inner = np.array([[2.4, 2.4], [2.4, 7.2], [12.0, 7.2], [12.0, 2.4]])  # clockwise: faces out
    south, east, north, west = _add_walls(b, outer, Z, [Material.WALL, Material.END_WALL,
                                                        Material.WALL, Material.END_WALL])
    in_w, in_n, in_e, in_s = _add_walls(b, inner, Z, [Material.END_WALL, Material.WALL,
                                                      Material.END_WALL, Material.WALL])
    cells = {(i, j) for i in range(24) for j in range(16)
             if not (4 <= i < 20 and 4 <= j < 12)}
    _tiled_floor(b, cells, tile)
    for i, j in sorted(cells):
        b.rect((i * tile, j * tile, Z), (0, tile, 0), (tile, 0, 0), Material.CEILING)
    red, blue = Material.POSTER_RED, Material.POSTER_BLUE
    _dress(b, doors=((south, ((0.7, 1.0),)), (east, ((4.3, 1.0),)), (north, ((12.7, 1.0),)),
                     (west, ()), (in_s, ((1.4, 0.9), (4.6, 0.9), (7.8, 0.9))),
                     (in_e, ((1.9, 0.9),)), (in_n, ((0.9, 0.9), (4.2, 0.9), (7.3, 0.9))),
                     (in_w, ((2.6, 0.9),))),
           windows=((south, 2.6), (south, 6.4), (south, 10.2), (east, 1.2), (east, 6.6),
                    (north, 1.8), (north, 5.6), (north, 9.4), (west, 2.2), (west, 6.2)),
           window_width=1.4,
           posters=((in_s, 0.4, 0.6, 0.8, red, 0.0), (in_s, 3.0, 0.7, 0.5, blue, 0.0),
                    (in_s, 6.1, 0.6, 0.85, blue, 3.0), (in_s, 8.9, 0.5, 0.7, red, 0.0),
                    (in_e, 0.5, 0.6, 0.8, blue, 0.0), (in_e, 3.3, 0.7, 0.6, red, 0.0),
                    (in_n, 2.4, 0.8, 0.55, red, 0.0), (in_n, 5.7, 0.6, 0.85, blue, -4.0),
                    (in_n, 8.5, 0.6, 0.8, red, 0.0), (in_w, 0.6, 0.7, 0.9, blue, 0.0),
                    (south, 4.6, 0.6, 0.8, red, 0.0), (north, 3.9, 0.6, 0.8, blue, 0.0),
                    (east, 3.1, 0.5, 0.7, red, 0.0), (west, 4.4, 0.6, 0.9, blue, 0.0)))
    _block_clutter(b, south, east, north, west, in_s, in_n)
    for cx in (1.2, 4.6, 7.2, 9.8, 13.2):
        for cy in (1.2, 8.4):
            _ceiling_light(b, cx, cy, Z, 1.2 if 1.2 < cx < 13.2 else 0.6, 0.6, 1.6)
    for cy in (3.6, 6.0):
        for cx in (1.2, 13.2):
            _ceiling_light(b, cx, cy, Z, 0.6, 1.2, 1.6)
    route = np.array([[1.2, 1.2, 0.0], [13.2, 1.2, 0.0], [13.2, 8.4, 0.0], [1.2, 8.4, 0.0],
                      [1.2, 1.2, 0.0], [13.2, 1.2, 0.0]])
    return b.build("block", route[:2], 0.5, Z, route=route)


def _block_clutter(b: _Builder, south: _Wall, east: _Wall, north: _Wall, west: _Wall,
                   in_s: _Wall, in_n: _Wall) -> None:
    """Boxes, cabinets, chairs and bins along the block's corridor walls, each turned by its
    own angle from its wall (its own pair of horizontal line directions), within 0.7 m of it."""
    box, dark, wood = Material.BOX, Material.FURNITURE_DARK, Material.FURNITURE
    _box_against(b, south, 5.2, (0.5, 0.4, 0.4), 14.0, box)
    c, _ = _box_against(b, south, 12.1, (0.6, 0.45, 0.5), -9.0, box)
    b.box(c + [0, 0, 0.64], (0.34, 0.28, 0.28), box, "clutter", yaw_deg=27.0)
    _chair(b, east, 2.6, -130.0)
    _box_against(b, east, 6.1, (0.55, 0.45, 0.45), -19.0, box)
    _box_against(b, north, 7.5, (0.5, 0.45, 1.15), 5.0, dark, top_mat=wood)
    _chair(b, north, 11.2, 61.0)
    b.prism(north.point(2.9, 0.0, 0.2), 0.16, 0.45, Material.BIN)
    _box_against(b, west, 1.3, (0.5, 0.5, 0.35), 71.0, box)
    _box_against(b, in_s, 5.7, (1.0, 0.35, 0.8), 8.0, wood, top_mat=dark)
    b.prism(in_s.point(8.1, 0.0, 0.24), 0.2, 0.6, Material.BIN)
    _chair(b, in_n, 3.5, 48.0)
    _box_against(b, in_n, 6.6, (0.5, 0.4, 0.4), -24.0, box)


SCENES = {SceneName.CORRIDOR: corridor, SceneName.ROOM: room, SceneName.OFFICE: office,
          SceneName.CELLHOUSE: cellhouse, SceneName.BLOCK: block}


def make_scene(name: str | SceneName) -> Scene:
    """Build a named scene; OmniSfmError for an unknown name."""
    try:
        key = SceneName(name)
    except ValueError:
        raise OmniSfmError(
            f"unknown scene {name!r} (known: {', '.join(s.value for s in SceneName)})"
        ) from None
    return SCENES[key]()
