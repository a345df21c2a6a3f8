"""``omni-sfm export``: every format read back with its consumer's reader (pycolmap for the
COLMAP models and rigs, nerfstudio's documented schema for ``transforms.json``, LIMAP's track
layout), the poses equal to the folder's in the export's convention, and the gravity-up world
within 0.2 deg of the renders' true vertical through both cameras.

The init folders come from the renders other tests share (``rendered``); the views and rigs are
checked on small folders made of a render's ground truth (poses, camera, true 3D lines), so that
a projection error is the export's alone.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from helpers import EQUIRECT_CORRIDOR, assert_every_key_declared, assert_one_line_error

from omni_sfm.cameras import EquirectangularCamera, OpenCVFisheyeCamera, UnifiedCamera, load_camera
from omni_sfm.cli import main
from omni_sfm.export.colmap import trajectory_from_reconstruction
from omni_sfm.export.limap import read_track
from omni_sfm.export.nerfstudio import camera_intrinsics, opencv_poses, read_transforms
from omni_sfm.export.pipeline import export_trajectory_of
from omni_sfm.export.trajectories import read_kitti
from omni_sfm.export.up import UpFrame, find_up
from omni_sfm.geometry import normalize, rotvec_to_matrix
from omni_sfm.lines3d import LineSegments3D, read_lines3d
from omni_sfm.poses import Trajectory, read_tum, write_tum
from omni_sfm.reports import ExportReport, InitReport
from omni_sfm.synth.render import RenderOptions

# the renders test_init_images.py and test_one_pass.py use too (one render per session)
HYPERBOLOID = RenderOptions(camera="hyperboloid", frames=40, seed=1)
RENDERS = {"hyperboloid": HYPERBOLOID, "equirectangular": EQUIRECT_CORRIDOR}


def _angle_deg(a, b) -> float:
    a, b = normalize(np.asarray(a, float)), normalize(np.asarray(b, float))
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


@pytest.fixture(scope="module")
def inits(rendered, built_once):
    """``inits(name)``: ``(render folder, init folder)`` of the camera ``name``, init run once
    per camera and test run (``built_once``), when a test first asks for it."""
    def build(seq: Path, folder: Path) -> None:
        assert main(["init", "--images", str(seq / "images"), "--camera",
                     str(seq / "camera.yaml"), "--output", str(folder / "init"), "--quiet",
                     "--debug-view", "none"]) == 0

    def get(name: str) -> tuple[Path, Path]:
        seq = rendered(RENDERS[name]).output
        folder, _ = built_once(f"export-formats-init-{name}", lambda d: build(seq, d))
        assert_every_key_declared(InitReport, folder / "init" / "report.json")
        return seq, folder / "init"
    return get


def _export(folder: Path, fmt: str, out: Path, *extra: str) -> dict:
    assert main(["export", "--input", str(folder), "--format", fmt, "--output", str(out),
                 *extra]) == 0
    assert_every_key_declared(ExportReport, out / "report.json")
    return json.loads((out / "report.json").read_text())


def _truth_folder(seq: Path, dst: Path, frames: list[int]) -> Path:
    """A poses folder holding the render's ground truth for ``frames``: poses, camera, true 3D
    lines, and the render's frames recorded as its input."""
    dst.mkdir(parents=True)
    gt = read_tum(seq / "groundtruth.tum").subset(np.asarray(frames))
    write_tum(dst / "trajectory.tum", gt)
    shutil.copyfile(seq / "camera.yaml", dst / "camera.yaml")
    shutil.copyfile(seq / "lines3d.json", dst / "lines3d.json")
    (dst / "report.json").write_text(json.dumps({"input": {"images": str(seq / "images")}}))
    return dst


# --- the gravity-up world ----------------------------------------------------------------------

@pytest.mark.parametrize("name", [
    # the first to ask for the 360 corridor runs init on it (and renders it, unless
    # test_track.py did): 4-13 s (slow: this file starts first)
    pytest.param("equirectangular", marks=pytest.mark.slow(seconds=13)),
    "hyperboloid",
])
def test_up_world_is_the_true_vertical(name, inits, tmp_path):
    seq, init = inits(name)
    rep = _export(init, "tum", tmp_path / "tum", "--up")
    true_up = read_lines3d(seq / "lines3d.json").up       # the true vertical, first camera
    assert rep["world"]["turned"]
    assert _angle_deg(rep["world"]["vertical_in_world"], true_up) < 0.2
    # the exported world's +z is the true vertical, its origin the first camera
    m = np.asarray(rep["world"]["export_from_world"])
    assert _angle_deg(m[:3, :3] @ true_up, [0.0, 0.0, 1.0]) < 0.2
    out = read_tum(tmp_path / "tum" / "trajectory.tum")
    np.testing.assert_allclose(out.positions[0], 0.0, atol=1e-12)
    # and the poses are the folder's, turned (a rotation: distances kept)
    traj = read_tum(init / "trajectory.tum")
    want = export_trajectory_of(rep, traj)
    np.testing.assert_allclose(out.rotations, want.rotations, atol=1e-12)
    np.testing.assert_allclose(out.positions, want.positions, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(out.positions[-1]), 1.0, rtol=1e-9)


def _manhattan_lines(world_from_scene: np.ndarray, sizes: tuple[int, int, int]
                     ) -> LineSegments3D:
    """Lines along the scene's x, y and z axes (``sizes`` of each), in the world."""
    rng = np.random.default_rng(0)
    starts, ends, groups = [], [], []
    for g, n in enumerate(sizes):
        for _ in range(n):
            s = rng.uniform(-3, 3, 3)
            starts.append(s)
            ends.append(s + np.eye(3)[g])
            groups.append(g)
    R = world_from_scene
    return LineSegments3D(np.asarray(starts) @ R.T, np.asarray(ends) @ R.T, np.asarray(groups),
                          np.eye(3) @ R.T, ("x",) * len(starts))


def test_mount_axis_finds_the_vertical_when_it_is_not_the_largest_family():
    # a hand-held 360 camera tilted 10 deg walks along the scene's x; scene +z is up; the
    # horizontal x family is the largest
    tilt = rotvec_to_matrix(np.radians([10.0, 0.0, 0.0]))
    scene_from_cam0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]) @ tilt
    world_from_scene = scene_from_cam0.T
    n = 5
    rot = np.repeat(np.eye(3)[None], n, axis=0)
    pos = (np.linspace(0, 1, n)[:, None] * np.array([1.0, 0.0, 0.0])) @ world_from_scene.T
    traj = Trajectory(np.arange(n, dtype=float), rot, pos)
    lines = _manhattan_lines(world_from_scene, (30, 10, 12))
    up = find_up(traj, EquirectangularCamera(width=64, height=32), lines, None)
    assert up.vertical is not None
    assert _angle_deg(up.vertical, world_from_scene[:, 2]) < 1e-9
    assert up.family == 2
    np.testing.assert_allclose(up.up_from_world @ up.vertical, [0.0, 0.0, 1.0], atol=1e-12)
    # a rig held upright: its frame's -y is the mount axis, so up is up, not down
    from omni_sfm.synth.render import dual_fisheye_camera

    up = find_up(traj, dual_fisheye_camera(64, 32), lines, None)
    assert up.family == 2 and up.vertical is not None
    assert _angle_deg(up.vertical, world_from_scene[:, 2]) < 1e-9
    # a camera model without a mount axis: the family most nearly perpendicular to the motion,
    # the largest of those (z here, x is along the motion)
    lines = _manhattan_lines(world_from_scene, (30, 10, 12))
    cam = UnifiedCamera(width=64, height=64, fx=20.0, fy=20.0, cx=32.0, cy=32.0, xi=1.0)
    up = find_up(traj, cam, lines, None)
    assert up.family == 2
    # --up-axis names it; a mount axis no family is near is a one-line error
    up = find_up(traj, cam, lines, None, up_axis=np.array([0.0, -1.0, 0.0]))
    assert _angle_deg(up.vertical, world_from_scene[:, 2]) < 1e-9
    with pytest.raises(ValueError, match="mount axis"):
        find_up(traj, cam, _manhattan_lines(np.eye(3), (30, 10, 12)), None,
                up_axis=np.ones(3) / np.sqrt(3))           # 54.7 deg from every family


# --- trajectories and COLMAP ---------------------------------------------------------------

@pytest.mark.parametrize("up", ["--up", "--no-up"])
def test_trajectory_exports_round_trip(inits, tmp_path, up):
    _, init = inits("hyperboloid")
    traj = read_tum(init / "trajectory.tum")
    for fmt in ("tum", "kitti"):
        rep = _export(init, fmt, tmp_path / fmt, up)
        got = read_tum(tmp_path / fmt / "trajectory.tum") if fmt == "tum" else \
            read_kitti(tmp_path / fmt)
        want = export_trajectory_of(rep, traj)
        np.testing.assert_array_equal(got.timestamps, traj.timestamps)
        np.testing.assert_allclose(got.rotations, want.rotations, atol=1e-12)
        np.testing.assert_allclose(got.positions, want.positions, atol=1e-12)
        if up == "--no-up":
            np.testing.assert_allclose(got.positions, traj.positions, atol=1e-15)


def test_colmap_export_reads_back_with_pycolmap(inits, tmp_path):
    seq, init = inits("hyperboloid")
    rep = _export(init, "colmap", tmp_path / "c", "--up")
    rec = pycolmap.Reconstruction(str(tmp_path / "c" / "sparse"))
    camera = load_camera(tmp_path / "c" / "camera.yaml")
    export = camera.colmap_export()
    traj = read_tum(init / "trajectory.tum")
    names = json.loads((init / "colmap.json").read_text())["image_names"]
    got, ok = trajectory_from_reconstruction(rec, export, names, traj.timestamps)
    assert ok.all()
    want = export_trajectory_of(rep, traj)
    np.testing.assert_allclose(got.rotations, want.rotations, atol=1e-9)
    np.testing.assert_allclose(got.positions, want.positions, atol=1e-9)
    # the frames, as COLMAP must see them (mirrored for the mirror camera)
    img = cv2.imread(str(tmp_path / "c" / "images" / names[3]))
    src = cv2.imread(str(seq / "images" / names[3]))
    assert src is not None
    np.testing.assert_array_equal(img, export.image_to_colmap(src))
    assert rep["num_images"] == len(traj)


# --- nerfstudio --------------------------------------------------------------------------------

def _nerfstudio_equirect_dirs(ij: np.ndarray, intr: dict) -> np.ndarray:
    """nerfstudio's EQUIRECTANGULAR ray directions (OpenGL camera frame) of pixels ``(i, j)``,
    as nerfstudio.cameras.cameras.Cameras._generate_rays_from_coords computes them: the pixel
    centre ``(i + 0.5, j + 0.5)``, ``theta = -pi x``, ``phi = pi (0.5 - y)``."""
    x = (ij[:, 0] + 0.5 - intr["cx"]) / intr["fl_x"]
    y = -(ij[:, 1] + 0.5 - intr["cy"]) / intr["fl_y"]     # OpenCV -> OpenGL
    theta, phi = -np.pi * x, np.pi * (0.5 - y)
    return np.stack([-np.sin(theta) * np.sin(phi), np.cos(phi),
                     -np.cos(theta) * np.sin(phi)], axis=1)


def test_nerfstudio_equirectangular_rays_are_the_cameras(inits, tmp_path):
    _, init = inits("equirectangular")
    rep = _export(init, "nerfstudio", tmp_path / "ns")
    assert rep["world"]["turned"]                     # up by default for nerfstudio
    doc, frames = read_transforms(tmp_path / "ns" / "transforms.json")
    assert doc["camera_model"] == "EQUIRECTANGULAR"
    traj = read_tum(init / "trajectory.tum")
    want = export_trajectory_of(rep, traj)
    got = opencv_poses(np.asarray([m for _, m in frames]))
    np.testing.assert_allclose(got.rotations, want.rotations, atol=1e-12)
    np.testing.assert_allclose(got.positions, want.positions, atol=1e-12)
    np.testing.assert_allclose(doc["applied_transform"], np.asarray(
        rep["world"]["export_from_world"])[:3], atol=1e-15)
    # every pixel's ray by nerfstudio's formula is the camera's ray, in the same world
    camera = load_camera(init / "camera.yaml")
    rng = np.random.default_rng(0)
    ij = np.stack([rng.integers(0, camera.width, 200), rng.integers(0, camera.height, 200)], 1)
    for k in (0, len(frames) - 1):
        m = frames[k][1]
        ns = _nerfstudio_equirect_dirs(ij.astype(float), doc) @ m[:3, :3].T
        ours = camera.rays_from_pixels(ij.astype(float)) @ want.rotations[k].T
        np.testing.assert_allclose(ns, ours, atol=1e-9)
    img = cv2.imread(str(tmp_path / "ns" / frames[0][0]))
    assert img is not None and img.shape[:2] == (camera.height, camera.width)


def test_nerfstudio_fisheye_intrinsics_follow_its_rays():
    cam = OpenCVFisheyeCamera(width=640, height=480, fx=200.0, fy=201.0, cx=319.3, cy=240.6)
    intr = camera_intrinsics(cam)
    assert intr is not None and intr["camera_model"] == "OPENCV_FISHEYE"
    ij = np.array([[0.0, 0.0], [100.0, 400.0], [639.0, 479.0], [320.0, 12.0]])
    # nerfstudio's FISHEYE rays (no distortion): theta = |((x - cx) / fx, (y - cy) / fy)|
    c = np.stack([(ij[:, 0] + 0.5 - intr["cx"]) / intr["fl_x"],
                  (ij[:, 1] + 0.5 - intr["cy"]) / intr["fl_y"]], 1)
    th = np.linalg.norm(c, axis=1)
    ns = np.column_stack([c * (np.sin(th) / th)[:, None], np.cos(th)])   # OpenCV axes
    np.testing.assert_allclose(ns, cam.rays_from_pixels(ij), atol=1e-9)


def test_nerfstudio_perspective_views_of_the_mirror_camera(rendered, tmp_path):
    seq = rendered(HYPERBOLOID).output
    folder = _truth_folder(seq, tmp_path / "truth", [0, 7, 19])
    rep = _export(folder, "nerfstudio", tmp_path / "ns", "--views", "cubemap")
    doc, frames = read_transforms(tmp_path / "ns" / "transforms.json")
    assert doc["camera_model"] == "OPENCV" and doc["k1"] == 0.0
    views = rep["views"]["views"]
    assert len(frames) == 3 * len(views) and len(views) == 4
    want = export_trajectory_of(rep, read_tum(folder / "trajectory.tum"))
    got = opencv_poses(np.asarray([m for _, m in frames]))
    for k in range(3):
        for v, view in enumerate(views):
            r = k * len(views) + v
            np.testing.assert_allclose(got.rotations[r], want.rotations[k] @ np.asarray(
                view["cam_from_view"]), atol=1e-12)
            np.testing.assert_allclose(got.positions[r], want.positions[k], atol=1e-12)
    # a mask for every image (nerfstudio's dataparser takes all or none)
    entries = json.loads((tmp_path / "ns" / "transforms.json").read_text())["frames"]
    assert all((tmp_path / "ns" / f["mask_path"]).is_file() for f in entries)
    # the level views: the true vertical is the views' -y (their image rows stay level)
    true_up = read_lines3d(seq / "lines3d.json").up
    assert true_up is not None
    m = np.asarray(rep["world"]["export_from_world"])[:3, :3]
    for v in range(len(views)):
        down_in_view = got.rotations[v].T @ (m @ -true_up)
        assert _angle_deg(down_in_view, [0.0, 1.0, 0.0]) < 3.0   # the first frame's tilt


# --- the COLMAP rig ----------------------------------------------------------------------------

def _check_rig(seq: Path, out: Path, rep: dict, folder: Path) -> int:
    """The rig's views project the true 3D lines where the omni frames see them (0.5 px) and
    their images are the frames' pixels there; returns the number of points checked."""
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    camera = load_camera(folder / "camera.yaml")
    traj = read_tum(folder / "trajectory.tum")
    m = np.asarray(rep["world"]["export_from_world"])
    views = len(rep["views"]["views"])
    assert rec.num_rigs() == 1 and rec.num_frames() == len(traj)
    assert rec.num_images() == len(traj) * views
    rig = next(iter(rec.rigs.values()))
    assert rig.num_sensors() == views
    lines = read_lines3d(seq / "lines3d.json")
    t = np.linspace(0.0, 1.0, 25)[:, None, None]
    x_world = (lines.starts[None] * (1 - t) + lines.ends[None] * t).reshape(-1, 3)
    x_export = x_world @ m[:3, :3].T + m[:3, 3]
    valid = camera.valid_mask()
    names = [f"{int(s):06d}.png" for s in traj.timestamps]
    checked, worst, worst_grey = 0, 0.0, 0.0
    for image in rec.images.values():
        k = image.frame_id - 1
        cam = rec.cameras[image.camera_id]
        T = np.asarray(image.cam_from_world().matrix())
        xc = x_export @ T[:, :3].T + T[:, 3]
        front = xc[:, 2] > 1e-6
        uv = np.full((len(xc), 2), np.nan)
        uv[front] = np.asarray(cam.img_from_cam(xc[front]))
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & \
            (uv[:, 1] < cam.height)
        # where the omni frame sees the points (the folder's own pose and camera)
        rays = (x_world[inside] - traj.positions[k]) @ traj.rotations[k]
        p_omni = camera.pixels_from_rays(rays)
        ok = camera.in_image(p_omni)
        ok[ok] &= valid[np.rint(p_omni[ok, 1]).astype(int), np.rint(p_omni[ok, 0]).astype(int)]
        if not ok.any():
            continue
        # the view pixel's ray, back through the rig to the omni frame
        xy = np.asarray(cam.cam_from_img(uv[inside][ok]))
        ray_view = np.column_stack([xy, np.ones(len(xy))])
        ray_world_export = ray_view @ T[:, :3]                # export world
        ray_cam = (ray_world_export @ m[:3, :3]) @ traj.rotations[k]
        p_back = camera.pixels_from_rays(ray_cam)
        worst = max(worst, float(np.linalg.norm(p_back - p_omni[ok], axis=1).max()))
        checked += int(ok.sum())
        # the view image holds the frame's pixels there
        view_img = cv2.imread(str(out / "images" / image.name), cv2.IMREAD_GRAYSCALE)
        omni = cv2.imread(str(seq / "images" / names[k]), cv2.IMREAD_GRAYSCALE)
        assert view_img is not None and omni is not None
        px = np.rint(uv[inside][ok] - 0.5).astype(int)       # view pixels at the points
        px = px[(px[:, 0] < cam.width) & (px[:, 1] < cam.height)]
        xy = np.asarray(cam.cam_from_img(px + 0.5))
        src = camera.pixels_from_rays((np.column_stack([xy, np.ones(len(xy))]) @ T[:, :3]
                                       @ m[:3, :3]) @ traj.rotations[k]).astype(np.float32)
        good = camera.in_image(src) & (src[:, 0] > 1) & (src[:, 0] < camera.width - 2)
        ref = cv2.remap(omni, src[good, 0][:, None], src[good, 1][:, None], cv2.INTER_LINEAR)
        grey = np.abs(view_img[px[good, 1], px[good, 0]].astype(float) - ref[:, 0])
        worst_grey = max(worst_grey, float(grey.max()) if len(grey) else 0.0)
    assert worst < 0.5, worst
    assert worst_grey <= 2.0, worst_grey
    return checked


@pytest.mark.parametrize(("name", "views"), [("hyperboloid", "overlapping"),
                                             ("equirectangular", "cubemap")])
def test_colmap_rig_views_project_the_lines_where_the_frames_see_them(name, views, rendered,
                                                                        tmp_path):
    seq = rendered(RENDERS[name]).output
    folder = _truth_folder(seq, tmp_path / "truth", [0, 9])
    rep = _export(folder, "colmap-rig", tmp_path / "rig", "--views", views)
    assert _check_rig(seq, tmp_path / "rig", rep, folder) > 500
    # the rig's frames are the folder's poses: the reference view's centre and axes
    rec = pycolmap.Reconstruction(str(tmp_path / "rig" / "sparse"))
    want = export_trajectory_of(rep, read_tum(folder / "trajectory.tum"))
    cam_from_view0 = np.asarray(rep["views"]["views"][0]["cam_from_view"])
    for frame in rec.frames.values():
        T = np.asarray(frame.rig_from_world.matrix())
        k = frame.frame_id - 1
        np.testing.assert_allclose(T[:, :3].T @ -T[:, 3], want.positions[k], atol=1e-9)
        np.testing.assert_allclose(T[:, :3].T, want.rotations[k] @ cam_from_view0, atol=1e-12)


# --- LIMAP -------------------------------------------------------------------------------------

def test_limap_tracks_beside_the_colmap_model(inits, tmp_path):
    _, init = inits("equirectangular")
    rep = _export(init, "limap", tmp_path / "lm")
    out = tmp_path / "lm"
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    lines = read_lines3d(init / "lines3d.json")
    m = np.asarray(rep["world"]["export_from_world"])
    files = sorted((out / "finaltracks").glob("track_*.txt"))
    assert len(files) == len(lines) == rep["limap"]["tracks"]
    supported = 0
    for k in range(len(lines)):
        tr = read_track(out / "finaltracks" / f"track_{k}.txt")
        ends = np.stack([lines.starts[k], lines.ends[k]]) @ m[:3, :3].T + m[:3, 3]
        np.testing.assert_allclose(tr["line"], ends, atol=1e-8)
        assert tr["n_images"] == len(set(tr["image_ids"]))
        for image_id, seg in zip(tr["image_ids"], tr["line2d"], strict=True):
            image = rec.images[image_id]
            cam = rec.cameras[image.camera_id]
            T = np.asarray(image.cam_from_world().matrix())
            uv = np.asarray(cam.img_from_cam(ends @ T[:, :3].T + T[:, 3]))
            np.testing.assert_allclose(seg, uv.ravel(), atol=1e-4)
        supported += bool(tr["image_ids"])
    assert supported >= 0.8 * len(lines)
    fam = json.loads((out / "line_families.json").read_text())
    np.testing.assert_allclose([f["direction"] for f in fam["families"]],
                               lines.group_directions @ m[:3, :3].T, atol=1e-12)
    assert (out / "alltracks.txt").read_text().split("\n")[0] == str(len(lines))


# --- bad input ---------------------------------------------------------------------------------

def test_bad_input_one_line_exit_2_no_output(inits, tmp_path, capsys):
    _, init = inits("hyperboloid")
    out = tmp_path / "out"
    assert main(["export", "--input", str(tmp_path / "none"), "--format", "tum",
                 "--output", str(out)]) == 2
    assert_one_line_error(capsys, "not found")
    assert main(["export", "--input", str(init), "--format", "tum", "--up", "--up-axis", "w",
                 "--output", str(out)]) == 2
    assert_one_line_error(capsys, "--up-axis")
    bare = tmp_path / "bare"
    bare.mkdir()
    for f in ("trajectory.tum", "camera.yaml", "lines3d.json"):
        shutil.copyfile(init / f, bare / f)
    assert main(["export", "--input", str(bare), "--format", "colmap-rig",
                 "--output", str(out)]) == 2
    assert_one_line_error(capsys, "--images")
    assert not out.exists()
    (out / "x").mkdir(parents=True)
    assert main(["export", "--input", str(init), "--format", "tum", "--output", str(out)]) == 2
    assert_one_line_error(capsys, "--overwrite")


def test_identity_world_keeps_the_poses():
    up = UpFrame.identity()
    traj = Trajectory(np.arange(3.0), rotvec_to_matrix(np.ones((3, 3))), np.ones((3, 3)))
    got = up.trajectory(traj)
    np.testing.assert_array_equal(got.rotations, traj.rotations)
    np.testing.assert_array_equal(got.positions, traj.positions)
