"""Smooth camera trajectories through a rendered scene (robot-carried or hand-held).

Five routes (:class:`Route`, docs/rendering.md "Routes"): ``lane`` runs along the scene's
walkway (a straight free lane) with smooth lateral sway, vertical bob, yaw about the heading and
a few degrees of pitch and roll, so translation and rotation have components about every axis;
``office`` follows the scene's route polyline through its 90 deg corner; ``stop-and-go`` drives,
stops, turns in place and drives on; ``turn-in-place`` only rotates; ``walk`` is a hand-held
walk with head bob, sway and glances. Poses are ``world_from_cam`` of the camera model's ray
frame, world = the scene frame (metres, +Z up); the poses are the ground truth: the renderer
renders exactly these.

Mounts:
- ``robot``: the camera's +Z (a catadioptric camera's mirror axis) points up, +X forward.
- ``handheld``: an upright 360 camera in the OpenCV/pycolmap convention: +Z forward,
  +Y down (so -Y is up), +X to the right.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray, rotation_about_axis
from omni_sfm.libs import open3d_module
from omni_sfm.poses import Trajectory
from omni_sfm.synth.scenes import Scene


class Mount(StrEnum):
    ROBOT = "robot"
    HANDHELD = "handheld"


class Route(StrEnum):
    """How the camera moves through the scene (docs/rendering.md, "Routes")."""

    LANE = "lane"
    """Along the scene's straight walkway with smooth sway, bob and yaw (the default)."""
    OFFICE = "office"
    """An office walk of 20 m or more with a 90 deg turn (scene ``office``)."""
    STOP_AND_GO = "stop-and-go"
    """Drive, stop, turn 90 deg in place, drive on."""
    TURN = "turn-in-place"
    """Turn in place (a yaw sweep with a little pitch and roll), no translation."""
    WALK = "walk"
    """A hand-held walk: head height, walking bob and sway, glances to the sides."""


# body frame: x forward, y left, z up.  Columns: the camera's axes in the body frame.
BODY_FROM_CAM = {
    Mount.ROBOT: np.eye(3),
    Mount.HANDHELD: np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
}

DEFAULT_PATH_LENGTH = {Route.LANE: 1.5, Route.OFFICE: 23.0, Route.STOP_AND_GO: 6.0,
                       Route.TURN: 0.0, Route.WALK: 10.0}
"""Path length (m) of each route when :attr:`PathOptions.path_length` is None (``walk``: at
most the scene's route)."""

STEP_LENGTH = 0.7
"""Length (m) of one step of the ``walk`` route; a stride is two steps."""


@dataclass(frozen=True)
class _Motion:
    """Resolved amplitudes of the wobble (metres, radians)."""

    height: float
    sway: float
    bob: float
    yaw: float
    tilt: float


# per route: (height, sway, bob, yaw_deg, tilt_deg), each (robot, hand-held)
_MOTION_DEFAULTS: dict[Route, tuple[tuple[float, float], ...]] = {
    Route.LANE: ((1.1, 1.45), (0.12, 0.12), (0.04, 0.08), (12.0, 12.0), (3.0, 7.0)),
    Route.OFFICE: ((1.1, 1.45), (0.12, 0.12), (0.04, 0.08), (12.0, 12.0), (3.0, 7.0)),
    Route.STOP_AND_GO: ((1.1, 1.45), (0.03, 0.03), (0.01, 0.03), (3.0, 3.0), (1.0, 3.0)),
    Route.TURN: ((1.1, 1.45), (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), (3.0, 3.0)),
    Route.WALK: ((1.6, 1.6), (0.025, 0.025), (0.018, 0.018), (2.0, 2.0), (2.0, 2.0)),
}


@dataclass(frozen=True, kw_only=True)
class PathOptions:
    num_frames: int = 200
    """Number of poses."""
    route: Route = Route.LANE
    """How the camera moves (see :class:`Route`)."""
    path_length: float | None = None
    """Length of the camera path, metres (arc length of the camera centre); None: the
    route's default (:data:`DEFAULT_PATH_LENGTH`: 1.5 m for ``lane``)."""
    mount: Mount = Mount.ROBOT
    """How the camera is carried (see the module docstring)."""
    height: float | None = None
    """Mean camera height above the floor, metres; None: 1.1 (robot) or 1.45 (hand-held), 1.6
    (head height) for ``walk``."""
    sway: float | None = None
    """Amplitude of the lateral sway, metres; None: the route's (0.12 for ``lane``)."""
    bob: float | None = None
    """Amplitude of the vertical motion, metres; None: the route's (``lane``: 0.04 robot,
    0.08 hand-held)."""
    yaw_deg: float | None = None
    """Amplitude of the yaw oscillation about the heading, degrees; None: the route's (12 for
    ``lane``)."""
    tilt_deg: float | None = None
    """Amplitude of pitch and roll, degrees; None: the route's (``lane``: 3 robot, 7
    hand-held)."""
    turn_deg: float = 120.0
    """Yaw sweep of ``turn-in-place``, degrees (positive: to the left, counter-clockwise seen
    from above)."""
    clearance: float = 0.3
    """Minimum distance (m) from every camera centre to any surface."""
    seed: int = 0
    """Seeds the start point, heading jitter, and the frequencies and phases of the motion."""


def _wave(s: FloatArray, rng: np.random.Generator, terms: int = 2) -> FloatArray:
    """A smooth random signal on ``s in [0, 1]`` with peak magnitude about 1."""
    out = np.zeros_like(s)
    for k in range(terms):
        freq = rng.uniform(0.3, 1.1) * (k + 1)
        out += rng.uniform(0.5, 1.0) / (k + 1) * np.sin(2 * np.pi * freq * s
                                                        + rng.uniform(0, 2 * np.pi))
    peak = float(np.max(np.abs(out))) if len(s) > 1 else 1.0
    return out / max(peak, 1e-9)


def _smoothstep(u: FloatArray) -> FloatArray:
    """``3u^2 - 2u^3`` of ``u`` clipped to [0, 1]: 0 to 1 with zero slope at both ends."""
    c = np.clip(u, 0.0, 1.0)
    return np.asarray(c * c * (3.0 - 2.0 * c))


def _world_from_cam(yaw: FloatArray, pitch: FloatArray, roll: FloatArray,
                    mount: Mount) -> FloatArray:
    """``(N, 3, 3)`` rotations: body yaw about +Z, then pitch about the body's y (left), then
    roll about its x (forward), radians; then the mount's camera axes."""
    z, y, x = np.eye(3)[2], np.eye(3)[1], np.eye(3)[0]
    world_from_body = (rotation_about_axis(z, yaw) @ rotation_about_axis(y, pitch)
                       @ rotation_about_axis(x, roll))
    return np.asarray(world_from_body @ BODY_FROM_CAM[mount])


def _arc_length(pos: FloatArray) -> float:
    return float(np.linalg.norm(np.diff(pos, axis=0), axis=1).sum()) if len(pos) > 1 else 0.0


def _fit_length(positions: Callable[[float], FloatArray], length: float
                ) -> tuple[FloatArray, float]:
    """``(positions(scale), scale)`` with ``scale`` (the forward distance) shrunk until the
    arc length, which sway and bob lengthen, equals ``length``."""
    scale = length
    pos = positions(scale)
    if length <= 0 or _arc_length(pos) <= 0:
        return pos, scale
    for _ in range(20):
        scale *= length / _arc_length(pos)
        pos = positions(scale)
    return pos, scale


def _dense_time(num_frames: int, samples: int = 4001) -> FloatArray:
    """Normalised time ``[0, 1]`` finely enough sampled that the long routes' arc length is
    that of the continuous path, whatever the number of frames (see :func:`_frames`)."""
    return np.linspace(0.0, 1.0, max(num_frames, samples))


def _frames(o: PathOptions, u: FloatArray, pos: FloatArray, yaw: FloatArray, pitch: FloatArray,
            roll: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Positions and rotations of the frames, evenly spaced in the normalised time ``u`` of
    the densely sampled motion (linear interpolation between its samples)."""
    t = np.linspace(0.0, 1.0, o.num_frames)
    at = np.column_stack([np.interp(t, u, v) for v in (*pos.T, yaw, pitch, roll)])
    return at[:, :3], _world_from_cam(at[:, 3], at[:, 4], at[:, 5], o.mount)


class _CentreLine:
    """A floor-plan polyline with each corner rounded by a turn whose heading follows a
    smoothstep of arc length (zero turn rate where it joins the straights): ``blend`` metres
    of path per 90 deg of turn. Evaluated from a dense table (``step`` m apart) of position
    and heading by arc length; heading is exact, position exact on the straights."""

    def __init__(self, points: FloatArray, blend: float = 2.0, step: float = 0.002) -> None:
        p = np.asarray(points, dtype=np.float64)[:, :2]
        edges = np.diff(p, axis=0)
        lengths = np.linalg.norm(edges, axis=1)
        units = edges / lengths[:, None]
        heads = np.arctan2(units[:, 1], units[:, 0])
        s_parts: list[FloatArray] = []
        xy_parts: list[FloatArray] = []
        h_parts: list[FloatArray] = []
        self.turns: list[tuple[float, float, float]] = []
        """(start, end arc length, signed turn angle in radians) of each rounded corner."""
        cursor, s_at = p[0], 0.0
        trims = np.zeros(len(p))
        curves = []
        for k in range(1, len(p) - 1):
            phi = float(np.angle(np.exp(1j * (heads[k] - heads[k - 1]))))
            arc = blend * abs(phi) / (np.pi / 2)
            n = max(int(np.ceil(arc / step)), 2) + 1
            t = np.linspace(0.0, arc, n)
            theta = phi * _smoothstep(t / max(arc, 1e-12))
            steps = np.diff(t)[:, None] * (np.column_stack([np.cos(theta), np.sin(theta)])[1:]
                                           + np.column_stack([np.cos(theta), np.sin(theta)])[:-1]
                                           ) / 2
            local = np.vstack([[0.0, 0.0], np.cumsum(steps, axis=0)])
            trims[k] = local[-1, 0] / (1.0 + np.cos(phi)) if arc > 0 else 0.0
            curves.append((t, theta, local, phi))
        if np.any(trims[:-1] + trims[1:] > lengths + 1e-9):
            raise ValueError(f"corners too close for the turn blend: {lengths=} {trims=}")
        for k in range(len(p) - 1):
            end = p[k + 1] - trims[k + 1] * units[k]
            straight = float(np.linalg.norm(end - cursor))
            m = max(int(np.ceil(straight / step)), 1) + 1
            a = np.linspace(0.0, 1.0, m)
            s_parts.append(s_at + straight * a)
            xy_parts.append(cursor + np.outer(a, end - cursor))
            h_parts.append(np.full(m, heads[k]))
            s_at += straight
            cursor = end
            if k + 1 < len(p) - 1:
                t, theta, local, phi = curves[k]
                c, s_ = np.cos(heads[k]), np.sin(heads[k])
                world = cursor + local @ np.array([[c, s_], [-s_, c]])
                s_parts.append(s_at + t[1:])
                xy_parts.append(world[1:])
                h_parts.append(heads[k] + theta[1:])
                self.turns.append((s_at, s_at + float(t[-1]), phi))
                s_at += float(t[-1])
                # the turn ends on the next straight (up to the quadrature's ~1e-9 m)
                cursor = world[-1]
        self.s = np.concatenate(s_parts)
        self.xy = np.vstack(xy_parts)
        self.heading = np.concatenate(h_parts)
        self.length = s_at

    def at(self, s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``(N, 2)`` floor position and ``(N,)`` heading (rad) at arc lengths ``s``."""
        xy = np.column_stack([np.interp(s, self.s, self.xy[:, 0]),
                              np.interp(s, self.s, self.xy[:, 1])])
        return xy, np.interp(s, self.s, self.heading)


def _route_xy(scene: Scene, reverse: bool) -> FloatArray:
    pts = np.asarray(scene.route, dtype=np.float64)[:, :2]
    return pts[::-1] if reverse else pts


def _needs_corner(scene: Scene, route: Route) -> None:
    if len(scene.route) < 3:
        raise OmniSfmError(
            f"route {route.value!r} needs a scene whose route turns a corner (scene "
            f"'office'); scene {scene.name!r} has a straight lane only"
        )


def _too_long(length: float, available: float, what: str, scene: Scene) -> OmniSfmError:
    return OmniSfmError(
        f"path length {length} m exceeds the {available:.1f} m {what} of scene {scene.name!r}"
    )


def _lane(scene: Scene, o: PathOptions, m: _Motion, length: float
          ) -> tuple[FloatArray, FloatArray]:
    rng = np.random.default_rng([o.seed, 7411])
    tilt = m.tilt
    a, b = scene.walkway[0, :2], scene.walkway[1, :2]
    lane = float(np.linalg.norm(b - a))
    slack = lane - length
    if slack < 0:
        raise _too_long(length, lane, "walkway", scene)
    heading = (b - a) / lane
    if rng.random() < 0.5:  # walk either way along the lane
        a, b, heading = b, a, -heading
    start = a + heading * rng.uniform(0.0, slack)
    jitter = np.radians(rng.uniform(-5.0, 5.0))
    c, s_ = np.cos(jitter), np.sin(jitter)
    fwd = np.array([c * heading[0] - s_ * heading[1], s_ * heading[0] + c * heading[1]])
    side = np.array([-fwd[1], fwd[0]])

    n = o.num_frames
    s = np.linspace(0.0, 1.0, n)
    # ease in and out of the forward motion a little, as a carried camera would
    prog = s + 0.08 * np.sin(2 * np.pi * s) / (2 * np.pi) * rng.uniform(-1, 1)
    lateral = m.sway * _wave(s, rng)
    vertical = m.bob * _wave(s, rng)
    lateral -= lateral[0]
    vertical -= vertical[0]

    def positions(scale: float) -> FloatArray:
        xy = start + scale * prog[:, None] * fwd + lateral[:, None] * side
        return np.column_stack([xy, m.height + vertical])

    pos = positions(length)
    arc = _arc_length(pos)
    if arc > 0 and length > 0:
        # the sway lengthens the path: shrink the forward part until the arc length matches
        scale = length
        for _ in range(20):
            pos = positions(scale)
            arc = _arc_length(pos)
            scale *= length / arc
        pos = positions(scale)

    yaw0 = np.arctan2(fwd[1], fwd[0])
    yaw = yaw0 + m.yaw * _wave(s, rng)
    pitch = tilt * _wave(s, rng)
    roll = tilt * _wave(s, rng)
    return pos, _world_from_cam(yaw, pitch, roll, o.mount)


def _office(scene: Scene, o: PathOptions, m: _Motion, length: float
            ) -> tuple[FloatArray, FloatArray]:
    """Along the scene's route polyline through its first corner, heading along the path."""
    _needs_corner(scene, Route.OFFICE)
    rng = np.random.default_rng([o.seed, 7412])
    line = _CentreLine(_route_xy(scene, rng.random() < 0.5))
    slack = line.length - length
    if slack < 0:
        raise _too_long(length, line.length, "route", scene)
    t0, t1, _ = line.turns[0]
    lo, hi = max(0.0, t1 - length), min(slack, t0)
    # take in the whole turn when it fits, else centre the path on it
    s0 = (rng.uniform(lo, hi) if lo <= hi
          else float(np.clip((t0 + t1 - length) / 2, 0.0, slack)))
    s = _dense_time(o.num_frames)
    prog = s + 0.05 * np.sin(2 * np.pi * s) / (2 * np.pi) * rng.uniform(-1, 1)
    # wobble wavelengths of metres, whatever the length of the route
    w = s * max(1.0, length / 4.0)
    lateral = m.sway * _wave(w, rng, 3)
    vertical = m.bob * _wave(w, rng, 3)

    def positions(scale: float) -> FloatArray:
        xy, head = line.at(s0 + scale * prog)
        side = np.column_stack([-np.sin(head), np.cos(head)])
        return np.column_stack([xy + lateral[:, None] * side, m.height + vertical])

    pos, scale = _fit_length(positions, length)
    _, head = line.at(s0 + scale * prog)
    yaw = head + m.yaw * _wave(w, rng, 3)
    pitch = m.tilt * _wave(w, rng, 3)
    roll = m.tilt * _wave(w, rng, 3)
    return _frames(o, s, pos, yaw, pitch, roll)


def _drive_profile(u: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Driving at full speed, then braking to a stop over the last 40 % of ``u in [0, 1]``:
    ``(distance in [0, 1], speed / full speed)``; distance 1 and speed 0 exactly at u = 1."""
    brake = 0.4
    r = np.clip((u - (1 - brake)) / brake, 0.0, 1.0)
    speed = np.where(u < 1 - brake, 1.0, 0.5 * (1.0 + np.cos(np.pi * r)))
    dist = np.minimum(u, 1 - brake) + 0.5 * brake * (r + np.sin(np.pi * r) / np.pi)
    total = 1 - brake + 0.5 * brake
    dist = np.where(u >= 1.0, total, dist) / total
    return dist, speed


def _stop_and_go(scene: Scene, o: PathOptions, m: _Motion, length: float
                 ) -> tuple[FloatArray, FloatArray]:
    """Drive ``length / 2`` up to the route's first corner while braking to a stop, stand,
    turn in place by the corner's angle, stand, drive ``length / 2`` on along the next leg."""
    _needs_corner(scene, Route.STOP_AND_GO)
    n = o.num_frames
    if n < 20:
        raise OmniSfmError(f"route 'stop-and-go' needs at least 20 frames, got {n}")
    rng = np.random.default_rng([o.seed, 7413])
    pts = _route_xy(scene, rng.random() < 0.5)
    corner = pts[1]
    legs = pts[[0, 2]] - corner
    leg_len = np.linalg.norm(legs, axis=1)
    e_in, e_out = -legs[0] / leg_len[0], legs[1] / leg_len[1]
    available = 2 * float(leg_len.min())
    if length > available:
        raise OmniSfmError(
            f"path length {length} m exceeds the {available:.1f} m that route 'stop-and-go' "
            f"fits in scene {scene.name!r} (twice the shorter leg at its corner)"
        )
    h_in = float(np.arctan2(e_in[1], e_in[0]))
    phi = float(np.angle(np.exp(1j * (np.arctan2(e_out[1], e_out[0]) - h_in))))
    # key frames: arrive (k1), start turning (k2), end turning (k3), drive off (k4)
    hold = max(2, round(0.1 * (n - 1)))
    k1 = round(0.3 * (n - 1))
    k2 = k1 + hold
    k3 = k2 + max(3, round(0.2 * (n - 1)))
    k4 = k3 + hold
    k = np.arange(n, dtype=np.float64)
    dist1, speed1 = _drive_profile(np.minimum(k / k1, 1.0))
    d2, s2 = _drive_profile(np.clip(1.0 - (k - k4) / (n - 1 - k4), 0.0, 1.0))
    dist2 = 1.0 - d2
    env = np.where(k <= k1, speed1, np.where(k >= k4, s2, 0.0))
    # wobble wavelengths of a few metres of the path, whatever the number of frames
    w = k / (n - 1) * max(1.0, length / 2.0)
    lateral = m.sway * env * _wave(w, rng)
    vertical = m.bob * env * _wave(w, rng)

    def positions(scale: float) -> FloatArray:
        along = np.where(k <= k1, -(1.0 - dist1), np.where(k >= k4, dist2, 0.0)) * scale / 2
        fwd = np.where((k <= k1)[:, None], e_in, e_out)
        side = np.column_stack([-fwd[:, 1], fwd[:, 0]])
        xy = corner + along[:, None] * fwd + lateral[:, None] * side
        return np.column_stack([xy, m.height + vertical])

    pos, _ = _fit_length(positions, length)
    turning = phi * 0.5 * (1.0 - np.cos(np.pi * np.clip((k - k2) / (k3 - k2), 0.0, 1.0)))
    yaw = h_in + np.where(k <= k1, 0.0, turning) + m.yaw * env * _wave(w, rng)
    pitch = m.tilt * env * _wave(w, rng)
    roll = m.tilt * env * _wave(w, rng)
    rot = _world_from_cam(yaw, pitch, roll, o.mount)
    # standing still means exactly the same pose
    stop = np.array([*corner, m.height])
    pos[k1:k4 + 1] = stop
    rot[k1:k2 + 1] = _world_from_cam(np.array(h_in), np.array(0.0), np.array(0.0), o.mount)
    rot[k3:k4 + 1] = _world_from_cam(np.array(h_in + phi), np.array(0.0), np.array(0.0),
                                     o.mount)
    return pos, rot


def _turn(scene: Scene, o: PathOptions, m: _Motion, length: float
          ) -> tuple[FloatArray, FloatArray]:
    """A yaw sweep of ``turn_deg`` (cosine ease in and out) with pitch and roll of a few
    degrees, the camera centre fixed at a point of the walkway."""
    if length != 0:
        raise OmniSfmError(
            f"route 'turn-in-place' does not translate: path length must be 0 or unset, "
            f"got {length}"
        )
    if not np.isfinite(o.turn_deg):
        raise OmniSfmError(f"turn angle must be finite, got {o.turn_deg}")
    rng = np.random.default_rng([o.seed, 7414])
    a, b = scene.walkway[0, :2], scene.walkway[1, :2]
    centre = a + (b - a) * rng.uniform(0.3, 0.7)
    yaw0 = np.arctan2(b[1] - a[1], b[0] - a[0]) + np.radians(rng.uniform(-30.0, 30.0))
    yaw0 += np.pi * (rng.random() < 0.5)
    n = o.num_frames
    u = np.linspace(0.0, 1.0, n)
    yaw = yaw0 + np.radians(o.turn_deg) * 0.5 * (1.0 - np.cos(np.pi * u))
    pitch = m.tilt * _wave(u, rng)
    roll = m.tilt * _wave(u, rng)
    pos = np.tile([*centre, m.height], (n, 1))
    return pos, _world_from_cam(yaw, pitch, roll, o.mount)


def _glances(d: FloatArray, length: float, rng: np.random.Generator) -> FloatArray:
    """Yaw (rad) of glances to the side: one per about 4 m walked (none under 2 m), each
    20 to 40 deg to a random side, held for a while over 1.2 to 2 m of walking; ``d``: the
    distance walked (m) at each frame."""
    count = max(round(length / 4.0), 1 if length >= 2.0 else 0)
    out = np.zeros_like(d)
    for j in range(count):
        width = rng.uniform(1.2, 2.0)
        slot = length / count
        centre = (j + 0.5 + rng.uniform(-0.15, 0.15)) * slot
        centre = float(np.clip(centre, width / 2, max(width / 2, length - width / 2)))
        x = (d - centre + width / 2) / width
        bump = _smoothstep(x / 0.3) * _smoothstep((1.0 - x) / 0.3)
        out += np.radians(rng.uniform(20.0, 40.0)) * rng.choice([-1.0, 1.0]) * bump
    return out


def _walk(scene: Scene, o: PathOptions, m: _Motion, length: float
          ) -> tuple[FloatArray, FloatArray]:
    """A hand-held walk along the scene's route (round its corners): head bob twice per
    stride, sway, roll and yaw once per stride, glances to the sides."""
    rng = np.random.default_rng([o.seed, 7415])
    line = _CentreLine(_route_xy(scene, rng.random() < 0.5))
    slack = line.length - length
    if slack < 0:
        raise _too_long(length, line.length, "route", scene)
    s0 = rng.uniform(0.0, slack)
    u = _dense_time(o.num_frames)
    prog = u + 0.03 * np.sin(2 * np.pi * u) / (2 * np.pi) * rng.uniform(-1, 1)
    phase = rng.uniform(0, 2 * np.pi, size=4)
    drift = 0.03 * _wave(u * max(1.0, length / 4.0), rng)

    def positions(scale: float) -> FloatArray:
        d = scale * prog
        step = 2 * np.pi * d / STEP_LENGTH
        xy, head = line.at(s0 + d)
        side = np.column_stack([-np.sin(head), np.cos(head)])
        lateral = m.sway * np.sin(step / 2 + phase[0]) + drift
        # lowest at each heel strike, highest when passing over the standing leg
        vertical = -m.bob * np.cos(step)
        return np.column_stack([xy + lateral[:, None] * side, m.height + vertical])

    pos, scale = _fit_length(positions, length)
    d = scale * prog
    step = 2 * np.pi * d / STEP_LENGTH
    _, head = line.at(s0 + d)
    yaw = head + m.yaw * np.sin(step / 2 + phase[1]) + _glances(d, scale, rng)
    roll = m.tilt * np.sin(step / 2 + phase[2])
    pitch = 0.5 * m.tilt * np.sin(step + phase[3]) + m.tilt * _wave(u, rng)
    return _frames(o, u, pos, yaw, pitch, roll)


_ROUTES = {Route.LANE: _lane, Route.OFFICE: _office, Route.STOP_AND_GO: _stop_and_go,
           Route.TURN: _turn, Route.WALK: _walk}


def _motion(o: PathOptions, route: Route) -> _Motion:
    i = 0 if o.mount == Mount.ROBOT else 1
    h, sway, bob, yaw, tilt = (v[i] for v in _MOTION_DEFAULTS[route])
    return _Motion(
        height=o.height if o.height is not None else h,
        sway=o.sway if o.sway is not None else sway,
        bob=o.bob if o.bob is not None else bob,
        yaw=float(np.radians(o.yaw_deg if o.yaw_deg is not None else yaw)),
        tilt=float(np.radians(o.tilt_deg if o.tilt_deg is not None else tilt)),
    )


def camera_path(scene: Scene, options: PathOptions | None = None) -> Trajectory:
    """The route's trajectory through ``scene``; timestamps are frame indices 0..N-1.

    Raises OmniSfmError for an unknown route or mount, a route the scene cannot hold (a
    corner needed, a path longer than the scene's route) or a path that comes closer than the
    clearance to a surface.
    """
    o = options or PathOptions()
    if o.num_frames < 1:
        raise OmniSfmError(f"number of frames must be positive, got {o.num_frames}")
    try:
        route = Route(o.route)
    except ValueError:
        raise OmniSfmError(
            f"unknown route {o.route!r} (known: {', '.join(r.value for r in Route)})"
        ) from None
    try:
        o = replace(o, route=route, mount=Mount(o.mount))
    except ValueError:
        raise OmniSfmError(
            f"unknown mount {o.mount!r} (known: {', '.join(m.value for m in Mount)})"
        ) from None
    length = DEFAULT_PATH_LENGTH[route] if o.path_length is None else o.path_length
    if o.path_length is None and route == Route.WALK:
        length = min(length, _CentreLine(scene.route).length)
    if not length >= 0:
        raise OmniSfmError(f"path length must be >= 0 m, got {length}")
    pos, rot = _ROUTES[route](scene, o, _motion(o, route), length)

    rc = scene.raycasting_scene()
    o3d = open3d_module()
    dist = rc.compute_distance(o3d.core.Tensor(pos.astype(np.float32))).numpy()
    if float(dist.min()) < o.clearance:
        k = int(np.argmin(dist))
        raise OmniSfmError(
            f"camera path comes within {dist[k]:.2f} m of a surface at frame {k} of scene "
            f"{scene.name!r} (clearance {o.clearance} m): reduce sway, bob or height"
        )
    return Trajectory(np.arange(len(pos), dtype=np.float64), rot, pos)
