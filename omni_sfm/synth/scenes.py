"""Man-made scenes for rendering: triangle meshes with materials, lights and true 3D lines.

Every scene is built from axis-aligned (or yawed) boxes and flat rectangles. World frame: metres,
``+Z`` up, the floor at ``z = 0``. Thin "bands" (baseboards, door frames, doors, window frames,
light panels) lie :data:`BAND_OFFSET` in front of the surface they decorate, so each visible
straight edge is a real edge of the mesh, and the true line segments are recorded on the visible
surface, where the image edge is.

The true segments (:class:`LineSegments3D`) are the straight edges a person would see: where
walls meet floor and ceiling, baseboard tops, door and window frames, light panels, pillar and
furniture edges. Each carries a direction group (segments parallel to each other share a group;
group 0 is the most populated one) and a kind naming what it is.
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
        walkway_halfwidth: free distance (m) on each side of the walkway line, floor to ceiling.
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

    def transformed(self, rotation: FloatArray, translation: FloatArray) -> Scene:
        """The scene in another frame: ``x' = rotation @ x + translation`` (mesh, lines, lights,
        walkway; ``ceiling_height`` keeps its meaning in the scene frame)."""
        R, t = np.asarray(rotation), np.asarray(translation)
        return replace(self, vertices=self.vertices @ R.T + t,
                       lines=self.lines.transformed(R, t),
                       light_positions=self.light_positions @ R.T + t,
                       walkway=self.walkway @ R.T + t)

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
        self.verts.append(np.stack([o_, o_ + a, o_ + a + b, o_ + b]))
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
            yaw_deg: float = 0.0, top_mat: Material | None = None) -> None:
        """Closed box standing upright, yawed about +Z; all 12 edges become lines."""
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
        for p, q in ((o, o + ex), (o, o + ey), (o + ex, o + ex + ey), (o + ey, o + ex + ey)):
            self.line(p, q, kind)
            self.line(p + ez, q + ez, kind)

    def light(self, pos: ArrayLike, power: float) -> None:
        self.lights.append((np.asarray(pos, dtype=np.float64), power))

    def build(self, name: str, walkway: FloatArray, halfwidth: float, ceiling: float) -> Scene:
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


SCENES = {SceneName.CORRIDOR: corridor, SceneName.ROOM: room}


def make_scene(name: str | SceneName) -> Scene:
    """Build a named scene; OmniSfmError for an unknown name."""
    try:
        key = SceneName(name)
    except ValueError:
        raise OmniSfmError(
            f"unknown scene {name!r} (known: {', '.join(s.value for s in SceneName)})"
        ) from None
    return SCENES[key]()
