"""Smooth camera trajectories through a rendered scene (robot-carried or hand-held).

The path runs along the scene's walkway (a straight free lane) with smooth lateral sway,
vertical bob, yaw about the heading and a few degrees of pitch and roll, so translation and
rotation have components about every axis. Poses are ``world_from_cam`` of the camera model's
ray frame, world = the scene frame (metres, +Z up).

Mounts:
- ``robot``: the camera's +Z (a catadioptric camera's mirror axis) points up, +X forward.
- ``handheld``: an upright 360 camera in the OpenCV/pycolmap convention: +Z forward,
  +Y down (so -Y is up), +X to the right.
"""

from __future__ import annotations

from dataclasses import dataclass
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


@dataclass(frozen=True, kw_only=True)
class PathOptions:
    num_frames: int = 200
    """Number of poses."""
    route: Route = Route.LANE
    """How the camera moves (see :class:`Route`)."""
    path_length: float | None = None
    """Length of the camera path, metres (arc length of the camera centre); None: the
    route's default (1.5 m for ``lane``)."""
    mount: Mount = Mount.ROBOT
    """How the camera is carried (see the module docstring)."""
    height: float | None = None
    """Mean camera height above the floor, metres; None: 1.1 (robot) or 1.45 (hand-held)."""
    sway: float = 0.12
    """Amplitude of the lateral sway, metres."""
    bob: float | None = None
    """Amplitude of the vertical motion, metres; None: 0.04 (robot) or 0.08 (hand-held)."""
    yaw_deg: float = 12.0
    """Amplitude of the yaw oscillation about the heading, degrees."""
    tilt_deg: float | None = None
    """Amplitude of pitch and roll, degrees; None: 3 (robot) or 7 (hand-held)."""
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


def camera_path(scene: Scene, options: PathOptions | None = None) -> Trajectory:
    """A smooth trajectory along ``scene.walkway``; timestamps are frame indices 0..N-1.

    Raises OmniSfmError when the requested path does not fit in the scene with the clearance.
    """
    o = options or PathOptions()
    length = 1.5 if o.path_length is None else o.path_length
    if o.num_frames < 1:
        raise OmniSfmError(f"number of frames must be positive, got {o.num_frames}")
    if not length >= 0:
        raise OmniSfmError(f"path length must be >= 0 m, got {length}")
    rng = np.random.default_rng([o.seed, 7411])
    robot = o.mount == Mount.ROBOT
    height = o.height if o.height is not None else (1.1 if robot else 1.45)
    bob = o.bob if o.bob is not None else (0.04 if robot else 0.08)
    tilt = np.radians(o.tilt_deg if o.tilt_deg is not None else (3.0 if robot else 7.0))

    a, b = scene.walkway[0, :2], scene.walkway[1, :2]
    lane = float(np.linalg.norm(b - a))
    slack = lane - length
    if slack < 0:
        raise OmniSfmError(
            f"path length {length} m exceeds the {lane:.1f} m walkway of scene "
            f"{scene.name!r}"
        )
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
    lateral = o.sway * _wave(s, rng)
    vertical = bob * _wave(s, rng)
    lateral -= lateral[0]
    vertical -= vertical[0]

    def positions(scale: float) -> FloatArray:
        xy = start + scale * prog[:, None] * fwd + lateral[:, None] * side
        return np.column_stack([xy, height + vertical])

    pos = positions(length)
    arc = float(np.linalg.norm(np.diff(pos, axis=0), axis=1).sum()) if n > 1 else 0.0
    if arc > 0 and length > 0:
        # the sway lengthens the path: shrink the forward part until the arc length matches
        scale = length
        for _ in range(20):
            pos = positions(scale)
            arc = float(np.linalg.norm(np.diff(pos, axis=0), axis=1).sum())
            scale *= length / arc
        pos = positions(scale)

    yaw0 = np.arctan2(fwd[1], fwd[0])
    yaw = yaw0 + np.radians(o.yaw_deg) * _wave(s, rng)
    pitch = tilt * _wave(s, rng)
    roll = tilt * _wave(s, rng)
    z, y, x = np.eye(3)[2], np.eye(3)[1], np.eye(3)[0]
    world_from_body = (rotation_about_axis(z, yaw) @ rotation_about_axis(y, pitch)
                       @ rotation_about_axis(x, roll))
    rotations = world_from_body @ BODY_FROM_CAM[o.mount]

    rc = scene.raycasting_scene()
    o3d = open3d_module()
    dist = rc.compute_distance(o3d.core.Tensor(pos.astype(np.float32))).numpy()
    if float(dist.min()) < o.clearance:
        k = int(np.argmin(dist))
        raise OmniSfmError(
            f"camera path comes within {dist[k]:.2f} m of a surface at frame {k} of scene "
            f"{scene.name!r} (clearance {o.clearance} m): reduce sway, bob or height"
        )
    return Trajectory(np.arange(n, dtype=np.float64), rotations, pos)
