"""Rendered routes and the office scene (docs/rendering.md, "Scenes" and "Routes").

- Every route gives the requested path length (1 %), keeps its clearance, has orthonormal
  rotations and keeps the mount's up axis near the world's up.
- ``office`` turns by 90 deg; ``stop-and-go`` stands exactly still, turns 90 deg in place and
  drives on at a right angle; ``turn-in-place`` never translates and sweeps the requested yaw;
  ``walk`` bobs at head height twice per stride and glances to the sides.
- The ``lane`` route is unchanged (a stored pose); bad lengths and scenes give one-line errors.
- The office scene's true lines lie on its mesh, run in many directions (clutter turned away
  from the walls), its floor is tiled in two textured materials, its route is free, and it
  renders.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import rotation_angle
from omni_sfm.lines3d import read_lines3d
from omni_sfm.synth.paths import (
    STEP_LENGTH,
    Mount,
    PathOptions,
    Route,
    camera_path,
)
from omni_sfm.synth.render import Preset, RenderOptions
from omni_sfm.synth.scenes import MATERIAL_TEXTURED, Material, SceneName, make_scene

UP_IN_CAM = {Mount.ROBOT: np.array([0.0, 0.0, 1.0]), Mount.HANDHELD: np.array([0.0, -1.0, 0.0])}
FORWARD_IN_CAM = {Mount.ROBOT: np.array([1.0, 0.0, 0.0]),
                  Mount.HANDHELD: np.array([0.0, 0.0, 1.0])}


@pytest.fixture(scope="module")
def scenes():
    return {name: make_scene(name) for name in SceneName}


def _heading_deg(traj, mount: Mount) -> np.ndarray:
    """Unwrapped heading (deg) of the carrier's forward axis, about the world's +Z."""
    f = traj.rotations @ FORWARD_IN_CAM[mount]
    return np.degrees(np.unwrap(np.arctan2(f[:, 1], f[:, 0])))


def _distances(scene, points: np.ndarray) -> np.ndarray:
    rc = scene.raycasting_scene()
    return rc.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


@pytest.mark.parametrize(
    ("route", "scene", "length", "expected"),
    [(Route.OFFICE, "office", None, 23.0), (Route.OFFICE, "office", 21.5, 21.5),
     (Route.OFFICE, "office", 4.0, 4.0), (Route.STOP_AND_GO, "office", None, 6.0),
     (Route.STOP_AND_GO, "office", 9.0, 9.0), (Route.WALK, "corridor", None, 10.0),
     (Route.WALK, "room", None, 6.0), (Route.WALK, "office", 20.0, 20.0),
     (Route.WALK, "cellhouse", None, 10.0), (Route.WALK, "cellhouse", 20.0, 20.0),
     (Route.LANE, "office", None, 1.5), (Route.TURN, "room", None, 0.0)],
)
@pytest.mark.parametrize("mount", list(Mount))
def test_routes_have_the_length_clearance_and_rotations_asked_for(scenes, route, scene, length,
                                                                    expected, mount):
    sc = scenes[scene]
    for seed in (0, 1):
        traj = camera_path(sc, PathOptions(route=route, path_length=length, mount=mount,
                                           num_frames=240, seed=seed))
        assert len(traj) == 240 and np.array_equal(traj.timestamps, np.arange(240))
        assert abs(traj.path_length() - expected) <= 0.01 * expected + 1e-9
        assert _distances(sc, traj.positions).min() >= 0.3
        R = traj.rotations
        np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, np.broadcast_to(np.eye(3), R.shape),
                                   atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
        up = R @ UP_IN_CAM[mount]
        tilt = np.degrees(np.arccos(np.clip(up[:, 2], -1, 1)))
        assert tilt.max() < 12.0
        steps = np.diff(traj.positions, axis=0)
        if expected > 0:  # smooth: no jumps in velocity
            speed = np.linalg.norm(steps, axis=1)
            assert np.linalg.norm(np.diff(steps, axis=0), axis=1).max() < 0.25 * speed.max()


@pytest.mark.parametrize("seed", range(4))
def test_office_route_turns_the_corner(scenes, seed):
    traj = camera_path(scenes["office"], PathOptions(route=Route.OFFICE, seed=seed,
                                                     mount=Mount.HANDHELD))
    heading = _heading_deg(traj, Mount.HANDHELD)
    assert abs(abs(heading[-1] - heading[0]) - 90.0) < 10.0
    # the displacement turns by 90 deg too: two straight legs at a right angle
    p = traj.positions
    first, last = p[20] - p[0], p[-1] - p[-21]
    cos = first[:2] @ last[:2] / np.linalg.norm(first[:2]) / np.linalg.norm(last[:2])
    assert abs(cos) < np.sin(np.radians(10))
    assert traj.path_length() >= 20.0


def _still_runs(traj) -> list[tuple[int, int]]:
    """Maximal runs ``(first, last)`` of frames with bitwise the same pose."""
    same = [np.array_equal(traj.positions[k], traj.positions[k + 1])
            and np.array_equal(traj.rotations[k], traj.rotations[k + 1])
            for k in range(len(traj) - 1)]
    runs, start = [], None
    for k, s in enumerate([*same, False]):
        if s and start is None:
            start = k
        elif not s and start is not None:
            runs.append((start, k))
            start = None
    return runs


@pytest.mark.parametrize(("mount", "seed", "frames"),
                         [(Mount.ROBOT, 0, 100), (Mount.HANDHELD, 1, 200), (Mount.ROBOT, 2, 20)])
def test_stop_and_go_stands_still_turns_in_place_and_drives_on(scenes, mount, seed, frames):
    traj = camera_path(scenes["office"], PathOptions(route=Route.STOP_AND_GO, mount=mount,
                                                     seed=seed, num_frames=frames))
    runs = _still_runs(traj)
    assert len(runs) == 2 and all(b - a >= 2 for a, b in runs)  # exactly still, 3+ frames
    (a1, b1), (a2, b2) = runs
    p, R = traj.positions, traj.rotations
    # between the two stops: the centre does not move at all, the camera turns 90 deg about
    # the vertical
    assert np.ptp(p[a1:b2 + 1], axis=0).max() == 0.0
    rel = R[b1].T @ R[a2]
    assert abs(np.degrees(rotation_angle(rel)) - 90.0) < 1e-9
    axis_world = R[b1] @ np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0],
                                   rel[1, 0] - rel[0, 1]])
    assert abs(abs(axis_world[2]) / np.linalg.norm(axis_world) - 1.0) < 1e-12
    # braking into the stop, driving off from it, on legs at a right angle
    speed = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert speed[a1 - 1] < 0.25 * speed[: a1 // 2].mean()
    assert speed[b2] < 0.25 * speed[-max(1, (len(p) - b2) // 3):].mean()
    d_in, d_out = p[a1] - p[0], p[-1] - p[b2]
    assert abs(d_in[:2] @ d_out[:2]) < 0.05 * np.linalg.norm(d_in) * np.linalg.norm(d_out)
    heading = _heading_deg(traj, mount)
    assert abs(abs(heading[a2] - heading[b1]) - 90.0) < 1e-9


@pytest.mark.parametrize(("scene", "turn"), [("corridor", 120.0), ("room", -180.0),
                                             ("office", 90.0)])
@pytest.mark.parametrize("mount", list(Mount))
def test_turn_in_place_sweeps_yaw_without_translation(scenes, scene, turn, mount):
    traj = camera_path(scenes[scene], PathOptions(route=Route.TURN, turn_deg=turn, mount=mount,
                                                  num_frames=60, seed=4))
    assert np.ptp(traj.positions, axis=0).max() == 0.0  # exactly no translation
    assert traj.path_length() == 0.0
    heading = _heading_deg(traj, mount)
    assert abs(heading[-1] - heading[0] - turn) < 1e-6
    assert np.all(np.sign(turn) * np.diff(heading) >= -1e-9)  # one way, no going back
    # a little pitch and roll: a few degrees
    up = traj.rotations @ UP_IN_CAM[mount]
    tilt = np.degrees(np.arccos(np.clip(up[:, 2], -1, 1)))
    assert 0.5 < tilt.max() < 6.0


@pytest.mark.parametrize("mount", list(Mount))
def test_walk_bobs_at_head_height_and_glances(scenes, mount):
    traj = camera_path(scenes["office"], PathOptions(route=Route.WALK, mount=mount,
                                                     num_frames=400, seed=2))
    z = traj.positions[:, 2]
    assert abs(z.mean() - 1.6) < 0.005
    assert 0.03 <= np.ptp(z) <= 0.045
    # twice per stride: one low point per step of the path
    lows = np.flatnonzero((z[1:-1] < z[:-2]) & (z[1:-1] <= z[2:]))
    assert abs(len(lows) - traj.path_length() / STEP_LENGTH) <= 1.5
    # glances: the view turns 20 deg and more away from the direction of travel, and back
    # (the direction of travel averaged over a stride, which the sway cancels out of)
    p = traj.positions
    w = round(STEP_LENGTH / np.linalg.norm(np.diff(p, axis=0), axis=1).mean())
    v = p[2 * w:] - p[:-2 * w]
    f = (traj.rotations @ FORWARD_IN_CAM[mount])[w:-w]
    off = np.degrees(np.abs(np.angle(np.exp(1j * (np.arctan2(f[:, 1], f[:, 0])
                                                   - np.arctan2(v[:, 1], v[:, 0]))))))
    assert off.max() > 18.0 and np.median(off) < 5.0
    assert off[:5].max() < 10.0 and off[-5:].max() < 10.0


def test_lane_route_is_unchanged(scenes):
    """The lane route's poses are those the cached renders and figures were made with."""
    traj = camera_path(scenes["corridor"], PathOptions(num_frames=12, seed=0))
    np.testing.assert_allclose(traj.positions[-1],
                               [12.093032658795623, 0.8847049434666187, 1.1308439226700244],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        traj.rotations[-1].ravel(),
        [0.9992173016509013, -0.03931113447459567, -0.004406675369486249, 0.03929849779309481,
         0.9992232536215543, -0.002918474457841755, 0.004517981042224905,
         0.0027430144504190746, 0.9999860317619576], rtol=0, atol=1e-12)
    explicit = camera_path(scenes["corridor"], PathOptions(num_frames=12, seed=0,
                                                           route=Route.LANE, path_length=1.5))
    np.testing.assert_array_equal(explicit.positions, traj.positions)
    np.testing.assert_array_equal(explicit.rotations, traj.rotations)


@pytest.mark.parametrize(
    ("scene", "options", "message"),
    [("office", dict(route=Route.OFFICE, path_length=40.0), "exceeds the 24.8 m route"),
     ("office", dict(route=Route.STOP_AND_GO, path_length=30.0), "exceeds the 24.0 m"),
     ("room", dict(route=Route.WALK, path_length=8.0), "exceeds the 6.0 m route"),
     ("corridor", dict(route=Route.LANE, path_length=12.0), "exceeds the 11.0 m walkway"),
     ("office", dict(route=Route.OFFICE, path_length=-1.0), "path length must be >= 0"),
     ("room", dict(route=Route.TURN, path_length=1.0), "does not translate"),
     ("corridor", dict(route=Route.OFFICE), "needs a scene whose route turns a corner"),
     ("room", dict(route=Route.STOP_AND_GO), "needs a scene whose route turns a corner"),
     ("office", dict(route=Route.STOP_AND_GO, num_frames=10), "needs at least 20 frames"),
     ("office", dict(route="spiral"), "unknown route 'spiral'"),
     ("office", dict(route=Route.WALK, height=2.6), "comes within"),
     ("office", dict(route=Route.TURN, turn_deg=float("nan")), "turn angle must be finite")],
)
def test_bad_routes_give_one_line_errors(scenes, scene, options, message):
    with pytest.raises(OmniSfmError, match=message) as err:
        camera_path(scenes[scene], PathOptions(**options))
    assert "\n" not in str(err.value)


def test_office_scene_lines_lie_on_the_mesh_in_many_directions(scenes):
    sc = scenes["office"]
    L = sc.lines
    for a in (0.1, 0.5, 0.9):
        assert _distances(sc, L.starts + a * (L.ends - L.starts)).max() < 2e-3
    cos = np.abs(L.directions @ L.group_directions.T)
    assert np.allclose(cos[np.arange(len(L)), L.groups], 1.0)
    # directions not along the walls' axes, each shared by several segments
    counts = np.bincount(L.groups)
    d = L.group_directions
    off_axis = (np.abs(d).max(axis=1) < np.cos(np.radians(2))) & (counts >= 4)
    assert off_axis.sum() >= 3
    horizontal_off = off_axis & (np.abs(d[:, 2]) < 1e-9)
    assert horizontal_off.sum() >= 6  # turned boxes and chairs
    kinds = set(L.kinds)
    assert {"poster", "floor_tile", "clutter", "chair", "door_frame", "window_frame",
            "light_panel", "baseboard"} <= kinds
    vertical = np.flatnonzero(np.isclose(np.abs(d[:, 2]), 1))
    assert counts[vertical[0]] >= 40


def test_office_scene_floor_is_tiled_and_textured_and_its_route_is_free(scenes):
    sc = scenes["office"]
    tri = sc.vertices[sc.triangles]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) / 2
    tiles = [Material.FLOOR_TILE, Material.FLOOR_TILE_DARK]
    on_floor = np.all(tri[:, :, 2] == 0.0, axis=1)
    tile_area = [area[sc.materials == m].sum() for m in tiles]
    # the whole L (15.6 x 2.4 + 2.4 x 12 m) in two shades of tile, checkerboard
    assert np.isclose(sum(tile_area), 15.6 * 2.4 + 2.4 * 12.0)
    assert abs(tile_area[0] - tile_area[1]) < 0.5
    assert np.all(on_floor[np.isin(sc.materials, tiles)])
    assert not np.any(sc.materials == Material.FLOOR)
    assert MATERIAL_TEXTURED[tiles].all()
    assert len(sc.route) == 3
    legs = np.diff(sc.route[:, :2], axis=0)
    assert abs(legs[0] @ legs[1]) < 1e-9 and np.linalg.norm(legs, axis=1).sum() >= 24.0
    np.testing.assert_array_equal(sc.walkway, sc.route[:2])
    # free for the half width on each side, above the clutter and below the ceiling
    t = np.linspace(0, 1, 300)[:, None]
    for a, b in zip(sc.route[:-1], sc.route[1:], strict=True):
        for z in (1.0, 1.6, 2.0):
            pts = a + t * (b - a) + [0, 0, z]
            assert _distances(sc, pts).min() >= sc.walkway_halfwidth - 1e-6
    plain = make_scene("corridor")
    np.testing.assert_array_equal(plain.route, plain.walkway)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    moved = sc.transformed(R, np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(moved.route, sc.route @ R.T + [1.0, 2.0, 3.0])


def test_office_scene_renders(rendered):
    opts = RenderOptions(scene=SceneName.OFFICE, route=Route.OFFICE, camera="equirectangular",
                         preset=Preset.SMALL, width=160, height=80, frames=3, seed=1)
    res = rendered(opts)
    # the ground truth is the office route (written in the first camera's frame)
    scene_gt = camera_path(make_scene("office"), PathOptions(route=Route.OFFICE, num_frames=3,
                                                             mount=Mount.HANDHELD, seed=1))
    R0, c0 = scene_gt.rotations[0], scene_gt.positions[0]
    np.testing.assert_allclose(res.groundtruth.positions, (scene_gt.positions - c0) @ R0,
                               atol=1e-9)
    np.testing.assert_allclose(res.groundtruth.rotations, R0.T @ scene_gt.rotations, atol=1e-9)
    images = sorted((res.output / "images").glob("*.png"))
    assert len(images) == 3
    import cv2

    img = cv2.imread(str(images[1]))
    assert img.shape == (80, 160, 3) and 40 < img.mean() < 220 and img.std() > 20
    lines = read_lines3d(res.output / "lines3d.json")
    assert len(lines) == len(make_scene("office").lines)


def test_cellhouse_scene_has_railings_along_the_walk_and_dense_bars_across_it(scenes):
    """The cell house (issue #54's railing corridor): every line on the mesh; long lines along
    the walk (galleries, railings, cross bars), dense verticals across it (bars every 0.125 m
    between posts every 1.5 m, two tiers on both sides), a free walkway."""
    sc = scenes["cellhouse"]
    L = sc.lines
    for a in (0.1, 0.5, 0.9):
        assert _distances(sc, L.starts + a * (L.ends - L.starts)).max() < 2e-3
    kinds = np.asarray(L.kinds)
    assert {"cell_bar", "cell_post", "cell_crossbar", "railing", "railing_post", "gallery",
            "cell_wall", "door_frame", "light_panel"} <= set(kinds)
    d = L.ends - L.starts
    length = np.linalg.norm(d, axis=1)
    along = np.abs(d[:, 0]) > 0.999 * length
    vertical = np.abs(d[:, 2]) > 0.999 * length
    assert np.sum(along & (length >= 20.0)) >= 16  # galleries' and rails' edges, the walls'
    assert np.sum(vertical & (kinds == "cell_bar")) >= 2000
    # the bars of one tier of one cell front: 0.125 m apart, between posts 1.5 m apart
    bars = (kinds == "cell_bar") & (L.starts[:, 1] < 3.1) & (L.starts[:, 2] < 0.1)
    x = np.unique(np.round(L.starts[bars, 0], 4))  # each bar's two faces, 0.025 m apart
    assert np.allclose(x[1::2] - x[::2], 0.025, atol=1e-3)
    assert np.isclose(np.median(np.diff(x[::2])), 0.125, atol=0.005)
    posts = np.unique(np.round(L.starts[kinds == "cell_post", 0], 3))  # faces 0.12 m apart
    assert np.isclose(np.median(np.diff(posts[::2])), 1.5, atol=0.01)
    t = np.linspace(0, 1, 300)[:, None]
    a, b = sc.walkway
    for z in (1.0, 1.6, 2.0):
        assert _distances(sc, a + t * (b - a) + [0, 0, z]).min() >= sc.walkway_halfwidth - 1e-6


@pytest.mark.parametrize("route", [Route.OFFICE, Route.WALK])
def test_block_routes_go_once_around_and_past_the_start(scenes, route):
    """The block (the loop of issue #52): a 45 m walk goes around the block, turning 360 deg,
    and comes back within 0.3 m of where it started, after more than 35 m, smoothly, never
    nearer a surface than 0.3 m."""
    sc = scenes["block"]
    L = sc.lines
    for a in (0.1, 0.5, 0.9):
        assert _distances(sc, L.starts + a * (L.ends - L.starts)).max() < 2e-3
    for seed in (0, 1, 2):
        traj = camera_path(sc, PathOptions(route=route, path_length=45.0, seed=seed,
                                           mount=Mount.ROBOT, num_frames=900))
        assert abs(traj.path_length() - 45.0) <= 0.45
        assert _distances(sc, traj.positions).min() >= 0.3
        steps = np.diff(traj.positions, axis=0)
        speed = np.linalg.norm(steps, axis=1)
        assert np.linalg.norm(np.diff(steps, axis=0), axis=1).max() < 0.25 * speed.max()
        heading = _heading_deg(traj, Mount.ROBOT)
        assert abs(abs(heading[-1] - heading[0]) - 360.0) < 40.0
        p = traj.positions
        along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
        later = along > 35.0
        assert np.linalg.norm(p[later] - p[0], axis=1).min() < 0.3


def test_cellhouse_scene_renders(rendered):
    res = rendered(RenderOptions(scene=SceneName.CELLHOUSE, route=Route.WALK,
                                 camera="equirectangular", preset=Preset.SMALL, width=160,
                                 height=80, frames=3, seed=1))
    import cv2

    images = sorted((res.output / "images").glob("*.png"))
    img = cv2.imread(str(images[1]))
    assert img.shape == (80, 160, 3) and 40 < img.mean() < 220 and img.std() > 20
