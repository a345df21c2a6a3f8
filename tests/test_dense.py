"""Dense mapping (omni_sfm.dense, ``omni-sfm dense``) on a rendered textured room.

The renderer's true poses are given at an arbitrary similarity (scale 0.37, rotated, shifted),
as line-based poses would be; the dense map must come out metric with ``--known-distance`` and,
after aligning the trajectory to the truth, lie on the true mesh (``scene.ply``).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import assert_every_key_declared, assert_one_line_error

from omni_sfm.cameras import load_camera
from omni_sfm.cli import main as cli_main
from omni_sfm.dense import read_dense_input
from omni_sfm.dense.evaluate import evaluate_dense
from omni_sfm.dense.pipeline import _floor_scale
from omni_sfm.dense.relpose import PairPoseOptions, frame_features, pair_pose
from omni_sfm.dense.views import ViewGeometry, stereo_rig
from omni_sfm.errors import OmniSfmError
from omni_sfm.evaluate import umeyama
from omni_sfm.fileio import dumps_json, stored_path
from omni_sfm.folders import DenseFolder
from omni_sfm.geometry import angle_between, rotation_angle, rotvec_to_matrix
from omni_sfm.libs import open3d_module
from omni_sfm.poses import Trajectory, read_tum, write_tum
from omni_sfm.reports import DenseReport

SCALE = 0.37


def _similar(gt: Trajectory, scale: float) -> Trajectory:
    R = rotvec_to_matrix(np.array([0.3, -0.5, 0.9]))
    return Trajectory(gt.timestamps.copy(), R @ gt.rotations,
                      scale * gt.positions @ R.T + np.array([2.0, -1.0, 0.5]))


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """This module's folder for what it writes beside the render."""
    return tmp_path_factory.mktemp("dense")


def _write_poses(room: Path, d: Path) -> Path:
    """Write into ``d`` a poses folder: the true poses at scale 0.37, the camera and the true
    3D lines."""
    d.mkdir()
    write_tum(d / "trajectory.tum", _similar(read_tum(room / "groundtruth.tum"), SCALE))
    shutil.copyfile(room / "camera.yaml", d / "camera.yaml")
    lines = json.loads((room / "lines3d.json").read_text())
    R = rotvec_to_matrix(np.array([0.3, -0.5, 0.9]))
    for s in lines["segments"]:
        for key in ("start", "end"):
            s[key] = (SCALE * R @ np.array(s[key]) + [2.0, -1.0, 0.5]).tolist()
    (d / "lines3d.json").write_text(json.dumps(lines))
    return d


@pytest.fixture(scope="module")
def poses(room: Path, work: Path) -> Path:
    """This module's (writable) poses folder of the room (``_write_poses``)."""
    return _write_poses(room, work / "poses")


@pytest.fixture(scope="module")
def dense_out(room: Path, built_once) -> Path:
    """``dense --known-distance`` on the room's poses folder, run once per test run
    (``built_once``: read-only, shared by the test processes)."""
    gt = read_tum(room / "groundtruth.tum")
    first_last = float(np.linalg.norm(gt.positions[-1] - gt.positions[0]))

    def build(d: Path) -> None:
        rc = cli_main(["dense", "--input", str(_write_poses(room, d / "poses")), "--images",
                       str(room / "images"), "--output", str(d / "dense"),
                       "--known-distance", f"first-last={first_last!r}"])
        assert rc == 0

    folder, _ = built_once("dense-room", build)
    return folder / "dense"


def test_rig_views_are_rectified() -> None:
    """A world point lands on the same row of the reference and source views of a rig, with
    disparity f b / z: the pair is rectified whatever the poses."""
    rng = np.random.default_rng(3)
    g = ViewGeometry(focal=120.0, width=300, height=240)
    c_ref, c_src = rng.normal(size=3), rng.normal(size=3)
    rig = stereo_rig(g, c_ref, c_src, rotvec_to_matrix(rng.normal(size=3)))
    assert np.allclose(rig.world_from_views.transpose(0, 2, 1) @ rig.world_from_views, np.eye(3))
    assert np.allclose(np.linalg.det(rig.world_from_views), 1.0)
    assert np.allclose(rig.world_from_views[:, :, 0], (c_src - c_ref) / rig.baseline)
    for v in range(4):
        X = c_ref + rig.world_from_views[v] @ np.array([0.3, -0.2, 2.5])  # in front of view v
        p_ref = rig.world_from_views[v].T @ (X - c_ref)
        p_src = rig.world_from_views[v].T @ (X - c_src)
        u_ref, v_ref = g.focal * p_ref[:2] / p_ref[2]
        u_src, v_src = g.focal * p_src[:2] / p_src[2]
        assert v_ref == pytest.approx(v_src, abs=1e-9)
        assert u_ref - u_src == pytest.approx(g.focal * rig.baseline / p_ref[2], rel=1e-9)


def _assert_on_true_surface(points: np.ndarray, render: Path, completeness: float) -> None:
    """At least 50k ``points`` (aligned to the truth), their median distance to the render's
    true mesh under 2 % of the mean scene depth, 75 % of them within it, and the surface seen
    from the true poses covered to ``completeness``."""
    true_mesh = open3d_module().io.read_triangle_mesh(str(render / "scene.ply"))
    e = evaluate_dense(points, true_mesh, read_tum(render / "groundtruth.tum"),
                       load_camera(render / "camera.yaml"))
    assert e.num_points >= 50_000
    assert e.relative_median <= 0.02, e
    assert e.inlier_share >= 0.75, e
    assert e.completeness >= completeness, e


def test_dense_room_accuracy_scale_and_files(room: Path, dense_out: Path) -> None:
    o3d = open3d_module()
    report = json.loads((dense_out / "report.json").read_text())
    # the folder's loader reads the report as written, keys in the documented order
    loaded = DenseFolder(dense_out).load()
    assert_every_key_declared(DenseReport, dense_out / "report.json")
    assert loaded.report.to_json() == report and list(report)[:3] == ["input", "scale",
                                                                      "median_depth"]
    assert dumps_json(loaded.report.to_json()) == (dense_out / "report.json").read_text()
    assert loaded.points == dense_out / "dense.ply" and loaded.mesh == dense_out / "mesh.ply"
    assert loaded.images is not None and loaded.images.resolve() == (room / "images").resolve()
    # --known-distance undoes the arbitrary pose scale
    assert loaded.report.scale.source == "known_distance"
    assert loaded.report.scale.factor == pytest.approx(1 / SCALE, rel=1e-9)
    gt = read_tum(room / "groundtruth.tum")
    traj = read_tum(dense_out / "trajectory.tum")
    sim = umeyama(traj.positions, gt.positions)
    assert sim.scale == pytest.approx(1.0, abs=1e-6)
    # every output opens with Open3D's readers
    pcd = o3d.io.read_point_cloud(str(dense_out / "dense.ply"))
    mesh = o3d.io.read_triangle_mesh(str(dense_out / "mesh.ply"))
    assert pcd.has_colors() and len(mesh.triangles) > 10_000
    pts = sim.apply_points(np.asarray(pcd.points))
    true_mesh = o3d.io.read_triangle_mesh(str(room / "scene.ply"))
    # observed: 174k points, median 1.7 cm = 0.54 % of the 3.15 m mean depth, 86 % of the
    # points within 2 % of it, completeness 58 %
    _assert_on_true_surface(pts, room, completeness=0.4)
    # the mesh lies on the true surface too
    verts = sim.apply_points(np.asarray(mesh.vertices))
    assert evaluate_dense(verts, true_mesh, gt, load_camera(room / "camera.yaml"),
                          frames=2).relative_median <= 0.02
    # colours come from the images (textured grey walls: not all one colour)
    assert np.asarray(pcd.colors).std(axis=0).min() > 0.02
    # per-frame report: every keyframe got depth on a part of its views
    frames = loaded.report.frames
    assert len(frames) == loaded.report.num_keyframes >= 8
    shares = np.array([f.depth_share for f in frames])
    assert np.all((shares > 0.02) & (shares < 1.0))
    assert all(len(f.sources) == 2 for f in frames)
    # lines are carried over, scaled to metres
    lines = json.loads((dense_out / "lines3d.json").read_text())
    truth = json.loads((room / "lines3d.json").read_text())
    s = np.array([x["start"] for x in lines["segments"]])
    s_true = np.array([x["start"] for x in truth["segments"]])
    assert np.allclose(sim.apply_points(s), s_true, atol=1e-6)


def test_camera_height_finds_the_floor(room: Path, dense_out: Path) -> None:
    """The floor found in the (metric) dense points reproduces the true camera height."""
    o3d = open3d_module()
    render = json.loads((room / "render.json").read_text())
    wfs = np.array(render["world_from_scene"])
    gt = read_tum(room / "groundtruth.tum")
    heights = (gt.positions - wfs[:3, 3]) @ wfs[:3, :3]           # scene frame, floor z = 0
    true_height = float(np.median(heights[:, 2]))
    traj = read_tum(dense_out / "trajectory.tum")
    pts = np.asarray(o3d.io.read_point_cloud(str(dense_out / "dense.ply")).points)
    voxel = json.loads((dense_out / "report.json").read_text())["voxel_size"]
    info = _floor_scale(pts, traj, np.array([0.0, 0.0, 1.0]), true_height, voxel)
    assert info.factor == pytest.approx(1.0, abs=0.01)       # observed within 0.1 %
    # the floor's normal against the cameras' mean mirror axis (the mount tilts ~1.6 deg here)
    assert info.floor_tilt_deg is not None and info.floor_tilt_deg < 3.0
    assert info.floor_points is not None and info.floor_points > 5000


def test_camera_height_cli(room: Path, poses: Path, work: Path) -> None:
    """``--camera-height`` end to end (up axis from the camera model, ``--keyframe-step``)."""
    render = json.loads((room / "render.json").read_text())
    wfs = np.array(render["world_from_scene"])
    gt = read_tum(room / "groundtruth.tum")
    true_height = float(np.median(((gt.positions - wfs[:3, 3]) @ wfs[:3, :3])[:, 2]))
    out = work / "dense_height"
    assert cli_main(["dense", "-i", str(poses), "--images", str(room / "images"), "-o", str(out),
                     "--camera-height", repr(true_height), "--keyframe-step", "4",
                     "--resolution-scale", "0.5"]) == 0
    report = DenseFolder(out).read_report()
    assert report.keyframe_step == 4 and report.num_keyframes == -(-len(gt) // 4)
    assert report.scale.source == "camera_height" and report.scale.camera_height == true_height
    assert report.scale.factor == pytest.approx(1 / SCALE, rel=0.01)
    assert_every_key_declared(DenseReport, out / "report.json")


def test_pair_pose_undoes_rotation_drift(room: Path) -> None:
    """A source pose turned by 0.3 deg (line-based drift over a stereo baseline) is put back
    by the pair's image-based relative pose; exact poses are left alone."""
    cam = load_camera(room / "camera.yaml")
    gt = read_tum(room / "groundtruth.tum")
    mask = cv2.erode(cam.valid_mask().astype(np.uint8) * 255, np.ones((7, 7), np.uint8))
    opts = PairPoseOptions()
    feats = {k: frame_features(cv2.imread(str(room / "images" / f"{k:06d}.png"))[:, :, ::-1]
                               .copy(), cam, mask, opts) for k in (10, 14)}
    R_ref, c_ref, R_src, c_src = gt.rotations[10], gt.positions[10], gt.rotations[14], \
        gt.positions[14]
    exact = pair_pose(feats[10], feats[14], R_ref, c_ref, R_src, c_src, opts)
    assert not exact.corrected and exact.rotation_change_deg < 0.1 and exact.inliers > 200
    drift = rotvec_to_matrix(np.radians(0.3) * np.array([0.2, -0.3, 0.93]))
    fixed = pair_pose(feats[10], feats[14], R_ref, c_ref, R_src @ drift, c_src, opts)
    assert fixed.corrected
    assert fixed.rotation_change_deg == pytest.approx(0.3, abs=0.06)
    assert np.degrees(rotation_angle(fixed.world_from_src.T @ R_src)) < 0.06
    assert np.linalg.norm(fixed.centre_src - c_ref) == pytest.approx(
        np.linalg.norm(c_src - c_ref), rel=1e-12)
    assert np.degrees(angle_between(fixed.centre_src - c_ref, c_src - c_ref)) < 2.0


def test_poses_folder_records_its_frames_and_can_be_moved(room: Path, poses: Path,
                                                         tmp_path: Path) -> None:
    """Without --images, dense reads the frames the poses folder records in report.json
    (relative inside the folder, absolute outside), also after the folder has moved."""
    folder = tmp_path / "refined"
    shutil.copytree(poses, folder)
    (folder / "report.json").write_text(json.dumps(
        {"input": {"images": stored_path(room / "images", folder)}}))
    moved = tmp_path / "elsewhere" / "moved"
    moved.parent.mkdir()
    shutil.move(folder, moved)
    inp = read_dense_input(moved)
    assert inp.camera == load_camera(poses / "camera.yaml")
    assert inp.frames.path == (room / "images").resolve()
    num_frames = len(read_tum(room / "groundtruth.tum"))
    assert list(inp.image_names) == [f"{k:06d}.png" for k in range(num_frames)]
    # frames inside the folder are recorded relative to it
    shutil.copytree(room / "images", moved / "frames")
    (moved / "report.json").write_text(json.dumps(
        {"input": {"images": stored_path(moved / "frames", moved)}}))
    assert json.loads((moved / "report.json").read_text())["input"]["images"] == "frames"
    again = tmp_path / "again"
    shutil.move(moved, again)
    assert read_dense_input(again).frames.path == again / "frames"
    # a folder that records nothing needs --images
    (again / "report.json").unlink()
    with pytest.raises(OmniSfmError, match="give --images"):
        read_dense_input(again)


def test_bad_input_one_line_errors(room: Path, poses: Path, tmp_path: Path,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    images = str(room / "images")
    # no trajectory in the poses folder
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli_main(["dense", "-i", str(empty), "--images", images, "-o",
                     str(tmp_path / "o1")]) == 2
    assert_one_line_error(capsys, "trajectory.tum")
    # no images
    assert cli_main(["dense", "-i", str(poses), "--images", str(tmp_path / "nope"), "-o",
                     str(tmp_path / "o2")]) == 2
    assert_one_line_error(capsys, "no such image folder or video file")
    # a static camera: all centres equal
    static = tmp_path / "static"
    static.mkdir()
    gt = read_tum(room / "groundtruth.tum")
    write_tum(static / "trajectory.tum", Trajectory(
        gt.timestamps, gt.rotations, np.zeros_like(gt.positions)))
    shutil.copyfile(room / "camera.yaml", static / "camera.yaml")
    assert cli_main(["dense", "-i", str(static), "--images", images, "-o",
                     str(tmp_path / "o3")]) == 2
    assert_one_line_error(capsys, "baseline")
    # the poses say the camera moves, the images say it does not: no parallax, no depth
    frozen = tmp_path / "frozen"
    frozen.mkdir()
    first = cv2.imread(str(room / "images" / "000000.png"))
    for k in range(len(gt)):
        cv2.imwrite(str(frozen / f"{k:06d}.png"), first)
    # (every 10th frame a keyframe: the stereo of all of them fails alike, ~4x slower)
    assert cli_main(["dense", "-i", str(poses), "--images", str(frozen), "-o",
                     str(tmp_path / "o4"), "--keyframe-step", "10"]) == 2
    assert_one_line_error(capsys, "baseline")
    # two ways to fix the scale at once; a malformed distance (argparse: exit 2, one line)
    for extra, msg in ((["--known-distance", "first-last=1", "--camera-height", "1.1"],
                        "not allowed with"), (["--known-distance", "last=1"], "first-last=D")):
        with pytest.raises(SystemExit) as exc:
            cli_main(["dense", "-i", str(poses), "--images", images, "-o",
                      str(tmp_path / "o5"), *extra])
        assert exc.value.code == 2
        assert_one_line_error(capsys, msg, prefix="omni-sfm dense: error: ")
    assert cli_main(["dense", "-i", str(poses), "--images", images, "-o", str(tmp_path / "o6"),
                     "--camera-height", "-1"]) == 2
    assert_one_line_error(capsys, "must be > 0")
    for name in ("o1", "o2", "o3", "o4", "o5", "o6"):
        assert not (tmp_path / name).exists()


def test_existing_output_refused(room: Path, poses: Path, dense_out: Path,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["dense", "-i", str(poses), "--images", str(room / "images"), "-o",
                     str(dense_out)]) == 2
    assert_one_line_error(capsys, "--overwrite")


def _write_rig_poses(room: Path, d: Path) -> Path:
    """A poses folder of a rig as ``init`` writes it: the true poses at scale 0.37, the rig's
    camera file and the report's metric scale of the poses."""
    d.mkdir()
    write_tum(d / "trajectory.tum", _similar(read_tum(room / "groundtruth.tum"), SCALE))
    shutil.copyfile(room / "camera.yaml", d / "camera.yaml")
    (d / "report.json").write_text(json.dumps({
        "num_frames": 20, "rig": {"metres_per_unit": 1 / SCALE, "note": "test", "fixed": True}}))
    return d


def test_each_lens_of_a_rig_sits_at_its_offset(dual_room: Path, tmp_path: Path) -> None:
    """Each lens's poses are the rig's composed with the lens's placement, its centre the
    lens offset (metres) in the poses' units; its frames are its part of the image."""
    from omni_sfm.cameras import RigCamera
    from omni_sfm.dense.pipeline import _Frames, _lenses

    inp = read_dense_input(_write_rig_poses(dual_room, tmp_path / "poses"),
                           dual_room / "images")
    rig = inp.camera
    assert isinstance(rig, RigCamera) and inp.metres_per_unit == pytest.approx(1 / SCALE)
    lenses = _lenses(inp)
    assert len(lenses) == 2
    traj = inp.trajectory
    full = cv2.imread(str(dual_room / "images" / inp.image_names[7]))[:, :, ::-1]
    for k, lens in enumerate(lenses):
        T = rig.rig_from_lens[k]
        assert lens.camera == rig.lenses[k]
        assert np.allclose(lens.trajectory.rotations, traj.rotations @ T[:3, :3], atol=1e-12)
        offset = lens.trajectory.positions - traj.positions
        assert np.allclose(np.linalg.norm(offset, axis=1),
                           SCALE * np.linalg.norm(T[:3, 3]), rtol=1e-9)
        assert np.allclose(np.einsum("kji,kj->ki", traj.rotations, offset),
                           SCALE * T[:3, 3], atol=1e-12)
        x, y = lens.corner
        crop = _Frames(inp, lens)(7)
        assert crop.shape[:2] == (lens.camera.height, lens.camera.width)
        assert np.array_equal(crop, full[y:y + lens.camera.height, x:x + lens.camera.width])
    assert inp.metric
    # a rough scale (init's where the lens baseline does not fix it) places the lenses but
    # does not make the map metric
    report = tmp_path / "poses" / "report.json"
    doc = json.loads(report.read_text())
    doc["rig"]["fixed"] = False
    report.write_text(json.dumps(doc))
    rough = read_dense_input(tmp_path / "poses", dual_room / "images")
    assert rough.metres_per_unit == inp.metres_per_unit and not rough.metric
    # a rig's poses without their metric scale: one line, nothing written
    report.unlink()
    with pytest.raises(OmniSfmError, match="report"):
        read_dense_input(tmp_path / "poses", dual_room / "images")


def test_dense_dual_fisheye_room_is_metric_and_accurate(dual_room: Path, tmp_path: Path) -> None:
    """Raw dual-fisheye frames: both lenses' stereo fused into one map, in metres from the
    rig's lens offsets, on the true surface."""
    o3d = open3d_module()
    out = tmp_path / "dense"
    assert cli_main(["dense", "--input", str(_write_rig_poses(dual_room, tmp_path / "poses")),
                     "--images", str(dual_room / "images"), "--output", str(out)]) == 0
    report = DenseFolder(out).load().report
    assert report.scale.source == "rig"
    assert report.scale.factor == pytest.approx(1 / SCALE, rel=1e-12)
    gt = read_tum(dual_room / "groundtruth.tum")
    sim = umeyama(read_tum(out / "trajectory.tum").positions, gt.positions)
    assert sim.scale == pytest.approx(1.0, abs=1e-6)
    pts = sim.apply_points(np.asarray(o3d.io.read_point_cloud(str(out / "dense.ply")).points))
    # observed: 177k points, median 1.2 cm = 0.46 % of the 2.59 m mean depth, 88 % within
    # 2 % of it, completeness 79 % (the lenses taken as one centre: 1.6 cm, 86 %)
    _assert_on_true_surface(pts, dual_room, completeness=0.5)
    # every keyframe's stereo in both lenses: four pairs
    assert all(len(f.pair_pose) == 4 for f in report.frames) and len(report.frames) >= 8
    # the folder records its poses' metric scale (metres), so the COLMAP rig export of the
    # dense folder places each lens at its offset
    import pycolmap

    assert report.rig is not None and report.rig.metres_per_unit == pytest.approx(1.0)
    assert cli_main(["export", "--input", str(out), "--images", str(dual_room / "images"),
                     "--format", "colmap", "--output", str(tmp_path / "colmap")]) == 0
    rec = pycolmap.Reconstruction(str(tmp_path / "colmap" / "sparse"))
    traj, rig = read_tum(out / "trajectory.tum"), load_camera(dual_room / "camera.yaml")
    assert rec.num_rigs() == 1 and rec.num_images() == 40
    for k, fr in enumerate(sorted(rec.frames.values(), key=lambda fr: fr.frame_id)):
        pose = fr.rig_from_world  # COLMAP's rig frame: lens 0's
        centre = -pose.rotation.matrix().T @ pose.translation
        lens0 = traj.rotations[k] @ rig.rig_from_lens[0][:3, 3]
        assert np.allclose(centre, traj.positions[k] + lens0, atol=1e-9)
