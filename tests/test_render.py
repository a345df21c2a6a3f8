"""The renderer's ground truth is exact: features and edges of rendered frames agree with it.

- SIFT matches of textured frames, turned into rays by the camera model, give pycolmap's
  five-point estimate of the relative pose; it agrees with the ground truth (rotation within
  0.2 deg, translation direction within 2 deg) for the hyperboloid and equirectangular cameras.
- The true 3D segments, projected with the camera model and the true pose, lie on Canny edges
  (median distance below 1 px), while a pose 1 deg off does measurably worse.
- Same seed, same images (bitwise); other seed, other images. Bad input: one-line errors, exit 2.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pycolmap
import pytest
from helpers import assert_one_line_error
from scipy.spatial.transform import Rotation

from omni_sfm.cameras import load_camera
from omni_sfm.cli import main as cli_main
from omni_sfm.errors import OmniSfmError
from omni_sfm.frames import FrameStore
from omni_sfm.geometry import angle_between, rotation_about_axis, rotation_angle
from omni_sfm.lines3d import read_lines3d
from omni_sfm.poses import read_tum
from omni_sfm.synth.paths import Mount, PathOptions, camera_path
from omni_sfm.synth.render import (
    Preset,
    RenderOptions,
    RenderSetup,
    make_camera,
    prepare,
    render_frames,
    render_sequence,
    visible_line_samples,
)
from omni_sfm.synth.scenes import SceneName, make_scene


def _frames(setup: RenderSetup, idx: tuple[int, ...]) -> dict[int, np.ndarray]:
    gt = setup.groundtruth
    return {k: setup.renderer.render(gt.rotations[k], gt.positions[k], k) for k in idx}


def _sift_rays(setup: RenderSetup, img1: np.ndarray, img2: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    cam = setup.camera
    mask = cv2.erode(cam.valid_mask().astype(np.uint8) * 255, np.ones((5, 5), np.uint8))
    sift = cv2.SIFT_create()
    k1, d1 = sift.detectAndCompute(cv2.cvtColor(img1, cv2.COLOR_RGB2GRAY), mask)
    k2, d2 = sift.detectAndCompute(cv2.cvtColor(img2, cv2.COLOR_RGB2GRAY), mask)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [m for m, n in pairs if m.distance < 0.8 * n.distance]
    uv1 = np.array([k1[m.queryIdx].pt for m in good], dtype=np.float64)
    uv2 = np.array([k2[m.trainIdx].pt for m in good], dtype=np.float64)
    r1, r2 = cam.rays_from_pixels(uv1), cam.rays_from_pixels(uv2)
    ok = np.isfinite(r1).all(axis=1) & np.isfinite(r2).all(axis=1)
    return r1[ok], r2[ok]


@pytest.mark.parametrize(
    ("camera", "size", "scene"),
    [("hyperboloid", (480, 360), "corridor"), ("equirectangular", (640, 320), "room")],
)
def test_five_point_on_sift_matches_agrees_with_ground_truth(camera, size, scene):
    setup = prepare(RenderOptions(scene=scene, camera=camera, preset=Preset.SMALL,
                                  width=size[0], height=size[1], textured=True, seed=3))
    gt = setup.groundtruth
    for i, j in ((0, 3), (7, 10)):
        imgs = _frames(setup, (i, j))
        rays1, rays2 = _sift_rays(setup, imgs[i], imgs[j])
        assert len(rays1) > 100, "too few SIFT matches on a textured render"
        opts = pycolmap.RANSACOptions()
        # rays overload: the threshold is an angle on the unit sphere (radians; checked on
        # synthetic rays), 0.3 to 0.5 px at these sizes
        opts.max_error = 0.003
        opts.random_seed = 0
        res = pycolmap.estimate_relative_pose(rays1, rays2, opts)
        assert res is not None
        assert res["num_inliers"] > 0.4 * len(rays1)
        ref = pycolmap.refine_relative_pose(res["cam2_from_cam1"], rays1, rays2,
                                            res["inlier_mask"])
        est = ref["cam2_from_cam1"] if ref is not None else res["cam2_from_cam1"]
        # ground truth is world_from_cam: cam2_from_cam1 = cam2_from_world @ world_from_cam1
        R1, R2 = gt.rotations[i], gt.rotations[j]
        rot_true = R2.T @ R1
        t_true = R2.T @ (gt.positions[i] - gt.positions[j])
        rot_err = np.degrees(rotation_angle(rot_true.T @ est.rotation.matrix()))
        t_err = np.degrees(angle_between(est.translation, t_true))
        assert rot_err < 0.2, f"frames {i}-{j}: rotation error {rot_err:.3f} deg"
        assert t_err < 2.0, f"frames {i}-{j}: translation direction error {t_err:.2f} deg"


def _edge_distances(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Distance (px) from each pixel position to the nearest Canny edge, one sample per
    image pixel (so that far, crowded segments do not dominate)."""
    edges = cv2.Canny(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), 20, 60)
    dt = cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 5)
    _, first = np.unique(np.rint(uv).astype(np.int64), axis=0, return_index=True)
    p = uv[first].astype(np.float32)
    return cv2.remap(dt, p[:, :1], p[:, 1:], cv2.INTER_LINEAR)[:, 0]


@pytest.mark.parametrize(
    ("camera", "size", "scene", "frame"),
    [("hyperboloid", (640, 480), "corridor", 0), ("hyperboloid", (640, 480), "room", 11),
     ("equirectangular", (960, 480), "room", 0),
     ("equirectangular", (960, 480), "corridor", 11)],
)
def test_true_lines_land_on_canny_edges(camera, size, scene, frame):
    setup = prepare(RenderOptions(scene=scene, camera=camera, preset=Preset.SMALL,
                                  width=size[0], height=size[1], seed=1))
    gt = setup.groundtruth
    img = _frames(setup, (frame,))[frame]
    R, t = gt.rotations[frame], gt.positions[frame]
    samples = visible_line_samples(setup.renderer, R, t)
    # most segments are seen, and occlusion removed some samples in the room
    assert len(np.unique(samples.segment)) > 0.3 * len(setup.scene.lines)
    d = _edge_distances(img, samples.uv)
    assert len(d) > 2000
    assert np.median(d) < 1.0
    assert np.mean(d < 1.0) > 0.8
    # the same check with a camera turned by 1 deg about any of its axes is clearly worse
    for axis in np.eye(3):
        wrong = visible_line_samples(setup.renderer, R @ rotation_about_axis(axis, np.radians(1)),
                                     t)
        dw = _edge_distances(img, wrong.uv)
        assert np.median(dw) > np.median(d) + 0.1
        assert np.mean(dw < 1.0) < np.mean(d < 1.0) - 0.1


def _gradient(img: np.ndarray) -> np.ndarray:
    """Gradient magnitude (grey levels per px, Sobel after a 1 px blur), max over 3 x 3."""
    g = cv2.GaussianBlur(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32), (0, 0), 1.0)
    mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    return cv2.dilate(mag, np.ones((3, 3), np.uint8))


def test_texture_keeps_the_lines():
    """--textured adds gradients everywhere but the true lines keep their contrast."""
    med = {}
    for textured in (False, True):
        setup = prepare(RenderOptions(scene="corridor", preset=Preset.SMALL, width=640,
                                      height=480, seed=2, textured=textured))
        gt = setup.groundtruth
        img = _frames(setup, (4,))[4]
        grad = _gradient(img)
        uv = np.rint(visible_line_samples(setup.renderer, gt.rotations[4],
                                          gt.positions[4]).uv).astype(np.int64)
        mask = cv2.erode(setup.camera.valid_mask().astype(np.uint8), np.ones((9, 9), np.uint8))
        med[textured] = (np.median(grad[uv[:, 1], uv[:, 0]]), np.median(grad[mask > 0]))
    (line_plain, all_plain), (line_tex, all_tex) = med[False], med[True]
    assert all_tex > 5 * all_plain  # the texture is there
    assert line_tex > 0.8 * line_plain  # the lines are as strong as without it
    assert line_tex > 1.5 * all_tex  # and stand out of the texture


def test_same_seed_same_images_other_seed_other_images():
    opts = RenderOptions(scene=SceneName.ROOM, camera="equirectangular", preset=Preset.SMALL,
                         frames=3, textured=True, seed=5)
    s1, a = render_frames(opts)
    s2, b = render_frames(opts)
    assert a.shape == (3, 160, 320, 3) and a.dtype == np.uint8
    assert np.array_equal(a, b)
    np.testing.assert_array_equal(s1.groundtruth.positions, s2.groundtruth.positions)
    s3, c = render_frames(RenderOptions(scene=SceneName.ROOM, camera="equirectangular",
                                        preset=Preset.SMALL, frames=3, textured=True, seed=6))
    assert not np.array_equal(a, c)
    assert not np.allclose(s1.groundtruth.positions, s3.groundtruth.positions)


def test_mask_is_black_and_surface_edges_have_contrast():
    setup, imgs = render_frames(RenderOptions(preset=Preset.SMALL, frames=1))
    mask = setup.camera.valid_mask()
    assert imgs[0][~mask].max() == 0
    inside = imgs[0][mask].astype(float)
    assert inside.mean() > 60 and inside.std() > 20


@pytest.mark.parametrize(("scene", "mount"), [("corridor", "robot"), ("room", "handheld")])
def test_path_is_smooth_full_3d_and_keeps_clearance(scene, mount):
    sc = make_scene(scene)
    traj = camera_path(sc, PathOptions(num_frames=200, mount=Mount(mount), seed=2))
    assert abs(traj.path_length() - 1.5) < 0.01
    assert np.ptp(traj.positions, axis=0).min() > 0.03  # moves along every axis
    steps = np.diff(traj.positions, axis=0)
    assert np.linalg.norm(np.diff(steps, axis=0), axis=1).max() < 0.2 * np.linalg.norm(
        steps, axis=1).mean()  # smooth: no jumps in velocity
    # rotation relative to the first frame has components about all three axes
    rel = np.einsum("ji,njk->nik", traj.rotations[0], traj.rotations)
    rv = Rotation.from_matrix(rel).as_rotvec()
    assert (np.degrees(np.ptp(rv, axis=0)) > 1.0).all()
    import open3d as o3d

    dist = sc.raycasting_scene().compute_distance(
        o3d.core.Tensor(traj.positions.astype(np.float32))).numpy()
    assert dist.min() >= 0.3
    up_cam = np.array([0, 0, 1.0]) if mount == "robot" else np.array([0, -1.0, 0])
    up_world = traj.rotations @ up_cam
    tilt = np.degrees(np.arccos(np.clip(up_world[:, 2], -1, 1)))
    assert tilt.max() < 12.0


@pytest.mark.parametrize("name", ["corridor", "room"])
def test_scene_lines_lie_on_the_mesh_in_several_directions(name):
    sc = make_scene(name)
    L = sc.lines
    mid = (L.starts + L.ends) / 2
    quarter = L.starts + 0.25 * (L.ends - L.starts)
    import open3d as o3d

    rc = sc.raycasting_scene()
    for p in (mid, quarter):
        d = rc.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()
        assert d.max() < 1e-3
    counts = np.bincount(L.groups)
    vertical = np.flatnonzero(np.isclose(np.abs(L.group_directions[:, 2]), 1))
    assert counts[vertical[0]] >= 20  # many parallel vertical lines (door frames, pillars)
    assert (counts >= 10).sum() >= 3
    if name == "room":
        assert len(counts) >= 5
    cos = np.abs(L.directions @ L.group_directions.T)
    assert np.allclose(cos[np.arange(len(L)), L.groups], 1.0)


def test_render_command_writes_every_file(tmp_path):
    out = tmp_path / "seq"
    rc = cli_main(["render", "--output", str(out), "--preset", "small", "--frames", "3",
                   "--scene", "room", "--seed", "4"])
    assert rc == 0
    pngs = sorted((out / "images").glob("*.png"))
    assert [p.name for p in pngs] == ["000000.png", "000001.png", "000002.png"]
    img = cv2.imread(str(pngs[0]))
    assert img.shape == (240, 320, 3)
    cam = load_camera(out / "camera.yaml")
    assert cam == make_camera("hyperboloid", preset=Preset.SMALL)
    gt = read_tum(out / "groundtruth.tum")
    assert len(gt) == 3 and np.array_equal(gt.timestamps, [0, 1, 2])
    # omni-sfm's world: the first camera (identity pose), metres
    np.testing.assert_allclose(gt.rotations[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(gt.positions[0], 0, atol=1e-12)
    setup = prepare(RenderOptions(scene=SceneName.ROOM, preset=Preset.SMALL, frames=3, seed=4))
    R_ws, t_ws = setup.world_from_scene()
    sg = setup.groundtruth
    np.testing.assert_allclose(gt.positions, sg.positions @ R_ws.T + t_ws, atol=1e-9)
    np.testing.assert_allclose(gt.rotations, R_ws @ sg.rotations, atol=1e-9)
    assert abs(gt.path_length() - sg.path_length()) < 1e-9
    rendered = setup.renderer.render(sg.rotations[1], sg.positions[1], 1)
    assert np.array_equal(cv2.imread(str(pngs[1]))[:, :, ::-1], rendered)
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(out / "scene.ply"))
    assert len(mesh.triangles) == len(setup.scene.triangles)
    np.testing.assert_allclose(np.asarray(mesh.vertices),
                               setup.scene.vertices @ R_ws.T + t_ws, atol=1e-5)
    lines = read_lines3d(out / "lines3d.json")
    assert lines.kinds == setup.scene.lines.kinds
    # the file's lines seen from the file's poses are the scene's lines seen by the renderer
    rays_file = (lines.starts - gt.positions[2]) @ gt.rotations[2]
    rays_scene = (setup.scene.lines.starts - sg.positions[2]) @ sg.rotations[2]
    np.testing.assert_allclose(rays_file, rays_scene, atol=1e-9)
    meta = json.loads((out / "render.json").read_text())
    assert meta["num_frames"] == 3 and meta["mount"] == "robot"
    np.testing.assert_allclose(np.array(meta["up_in_world"]), R_ws[:, 2])
    np.testing.assert_allclose(np.array(meta["world_from_scene"])[:3, :3], R_ws)
    # the written camera file renders the same frames
    again = tmp_path / "again"
    assert cli_main(["render", "--output", str(again), "--camera", str(out / "camera.yaml"),
                     "--frames", "3", "--scene", "room", "--seed", "4"]) == 0
    assert np.array_equal(cv2.imread(str(again / "images" / "000002.png")),
                          cv2.imread(str(pngs[2])))


def test_render_video_with_a_camera_object(tmp_path):
    out = tmp_path / "vid"
    cam = make_camera("equirectangular", width=200, height=100)
    res = render_sequence(out, RenderOptions(camera=cam, preset=Preset.SMALL, frames=4,
                                             video=True), progress=False)
    assert res.num_frames == 4 and res.camera == cam
    gt = read_tum(out / "groundtruth.tum")
    np.testing.assert_allclose(gt.positions, res.groundtruth.positions, atol=1e-12)
    # stamped as omni-sfm stamps the video's frames (seconds), so compare can match them
    np.testing.assert_array_equal(gt.timestamps, FrameStore(out / "video.mp4").timestamps)
    assert json.loads((out / "render.json").read_text())["mount"] == "handheld"
    assert not (out / "images").exists()
    cap = cv2.VideoCapture(str(out / "video.mp4"))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 4


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--scene", "kitchen"], "unknown scene 'kitchen'"),
        (["--camera", "pinhole"], "unknown camera 'pinhole'"),
        (["--camera", "missing.yaml"], "camera file not found"),
        (["--frames", "0"], "number of frames must be a positive integer"),
        (["--frames", "-2"], "number of frames must be a positive integer"),
        (["--width", "0"], "image width must be a positive integer"),
        (["--height", "-5"], "image height must be a positive integer"),
        (["--supersample", "0"], "supersample must be an integer 1..8"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, args, message):
    out = tmp_path / "o"
    rc = cli_main(["render", "--output", str(out), "--preset", "small", "--frames", "2", *args]
                  if "--frames" not in args else
                  ["render", "--output", str(out), "--preset", "small", *args])
    assert rc == 2
    assert_one_line_error(capsys, message)
    assert not out.exists()


def test_non_empty_output_is_refused_unless_overwrite(tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    argv = ["render", "--output", str(out), "--preset", "small", "--frames", "1"]
    assert cli_main(argv) == 2
    assert_one_line_error(capsys, "not empty (use --overwrite)")
    assert (out / "keep.txt").exists()
    assert cli_main([*argv, "--overwrite"]) == 0
    assert not (out / "keep.txt").exists() and (out / "images" / "000000.png").exists()
    with pytest.raises(OmniSfmError, match="not empty"):
        render_sequence(out, RenderOptions(preset=Preset.SMALL, frames=1))


def test_library_errors():
    with pytest.raises(OmniSfmError, match="width/--height cannot be combined"):
        make_camera("some.yaml", width=100)
    with pytest.raises(OmniSfmError, match="exceeds the"):
        camera_path(make_scene("room"), PathOptions(path_length=20.0))
    with pytest.raises(OmniSfmError, match="unknown mount"):
        prepare(RenderOptions(preset=Preset.SMALL, mount="tripod"))  # type: ignore[arg-type]
    with pytest.raises(OmniSfmError, match="noise sigma"):
        prepare(RenderOptions(preset=Preset.SMALL, noise_sigma=-1.0))
    with pytest.raises(OmniSfmError, match="unknown preset"):
        prepare(RenderOptions(preset="huge"))  # type: ignore[arg-type]
