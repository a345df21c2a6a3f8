"""A rig camera (raw dual-fisheye frames) goes to COLMAP as a COLMAP 4.2 rig: one camera per
lens, one rig, one frame per pose, one image per lens and frame, the lens offsets in the poses'
units (docs/colmap.md, "A rig camera in COLMAP")."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap
import pytest

from omni_sfm.cameras import RigCamera
from omni_sfm.cli import main
from omni_sfm.errors import OmniSfmError
from omni_sfm.export.colmap import write_init_model
from omni_sfm.export.colmap_lenses import rig_metres_per_unit
from omni_sfm.geometry import rotvec_to_matrix
from omni_sfm.poses import Trajectory
from omni_sfm.synth.render import dual_fisheye_camera

METRES_PER_UNIT = 0.37


def _tilted_rig() -> RigCamera:
    """Two fisheye lenses neither of whose frames is the rig's: lens 0 turned 10 deg and off
    the origin, lens 1 looking back and sideways."""
    base = dual_fisheye_camera(192, 96)
    T = np.repeat(np.eye(4)[None], 2, axis=0)
    T[0, :3, :3] = rotvec_to_matrix(np.radians([3.0, 10.0, -2.0]))
    T[0, :3, 3] = [0.01, -0.005, 0.02]
    T[1, :3, :3] = rotvec_to_matrix(np.radians([0.0, 170.0, 5.0]))
    T[1, :3, 3] = [-0.004, 0.003, -0.021]
    return RigCamera(width=base.width, height=base.height, lenses=base.lenses, rig_from_lens=T)


RIGS = {"dual_fisheye": lambda: dual_fisheye_camera(192, 96), "tilted": _tilted_rig}


def _trajectory(n: int, seed: int) -> Trajectory:
    rng = np.random.default_rng(seed)
    return Trajectory(np.arange(n, dtype=float), rotvec_to_matrix(0.4 * rng.normal(size=(n, 3))),
                      rng.normal(size=(n, 3)))


def _init_folder(path: Path, camera: RigCamera, traj: Trajectory, names: list[str],
                 images: list[np.ndarray] | None = None) -> Path:
    """An init folder's COLMAP side, written as ``omni-sfm init`` writes it: the report (the
    estimator's metric scale) first, then :func:`write_init_model`."""
    path.mkdir(parents=True)
    (path / "report.json").write_text(json.dumps({
        "num_frames": 3, "rig": {"metres_per_unit": METRES_PER_UNIT, "note": "test"}}))
    write_init_model(path, camera, traj, names, images)
    return path


def _inverse(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _lens_from_world(camera: RigCamera, traj: Trajectory, k: int, lens: int) -> np.ndarray:
    """COLMAP's cam_from_world of ``lens`` at pose ``k``: its COLMAP frame from ours, ours from
    the rig (the centre in the poses' units), the rig from the world."""
    world_from_rig = np.eye(4)
    world_from_rig[:3, :3], world_from_rig[:3, 3] = traj.rotations[k], traj.positions[k]
    rig_from_lens = camera.rig_from_lens[lens].copy()
    rig_from_lens[:3, 3] /= METRES_PER_UNIT
    colmap_from_lens = np.eye(4)
    colmap_from_lens[:3, :3] = camera.lenses[lens].colmap_export().colmap_cam_from_cam
    return colmap_from_lens @ _inverse(rig_from_lens) @ _inverse(world_from_rig)


def _matrix(rigid: pycolmap.Rigid3d) -> np.ndarray:
    out = np.eye(4)
    out[:3] = np.asarray(rigid.matrix())
    return out


@pytest.mark.parametrize("name", sorted(RIGS))
def test_the_init_model_of_a_rig_is_a_colmap_rig(name: str, tmp_path: Path) -> None:
    camera = RIGS[name]()
    traj = _trajectory(4, 0)
    names = [f"{k:06d}.png" for k in range(len(traj))]
    init = _init_folder(tmp_path / "init", camera, traj, names)
    rec = pycolmap.Reconstruction(str(init / "sparse"))
    assert rec.num_cameras() == 2 and rec.num_rigs() == 1 and rec.num_frames() == len(traj)
    assert rec.num_images() == 2 * len(traj)
    rig = next(iter(rec.rigs.values()))
    assert rig.num_sensors() == 2
    for lens in range(2):
        assert rec.cameras[lens + 1].model_name == \
            camera.lenses[lens].colmap_export().camera.model_name
    by_name = {im.name: im for im in rec.images.values()}
    assert sorted(by_name) == sorted(f"lens{k}/{n}" for k in range(2) for n in names)
    for k, n in enumerate(names):
        frame = rec.frame(by_name[f"lens0/{n}"].frame_id)
        # COLMAP's rig frame is lens 0's COLMAP camera frame
        assert np.allclose(_matrix(frame.rig_from_world), _lens_from_world(camera, traj, k, 0),
                           atol=1e-9)
        for lens in range(2):
            im = by_name[f"lens{lens}/{n}"]
            assert im.frame_id == frame.frame_id and im.camera_id == lens + 1
            assert np.allclose(_matrix(im.cam_from_world()),
                               _lens_from_world(camera, traj, k, lens), atol=1e-9)
    manifest = json.loads((init / "colmap.json").read_text())
    assert manifest["image_names"] == names and manifest["metres_per_unit"] == METRES_PER_UNIT
    assert [m["images"] for m in manifest["lenses"]] == ["lens0/", "lens1/"]
    assert (init / "camera_mask_lens0.png").is_file() and (init / "camera_mask_lens1.png").is_file()
    # COLMAP's rig_configurator reads the same rig: prefixes, exact cameras, sensor poses
    config = pycolmap.read_rig_config(str(init / "rig_config.json"))
    assert len(config) == 1 and [c.image_prefix for c in config[0].cameras] == ["lens0/", "lens1/"]
    assert config[0].cameras[0].ref_sensor and not config[0].cameras[1].ref_sensor
    sensor = pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=2)
    assert np.allclose(_matrix(config[0].cameras[1].cam_from_rig),
                       _matrix(rig.sensor_from_rig(sensor)), atol=1e-12)
    for lens in range(2):
        assert config[0].cameras[lens].camera.model_name == rec.cameras[lens + 1].model_name
        assert np.allclose(config[0].cameras[lens].camera.params, rec.cameras[lens + 1].params)


def test_colmap_projects_world_points_where_the_lens_sees_them(tmp_path: Path) -> None:
    camera = _tilted_rig()
    traj = _trajectory(3, 1)
    names = ["a.png", "b.png", "c.png"]
    rec = pycolmap.Reconstruction(str(_init_folder(tmp_path / "i", camera, traj, names)
                                      / "sparse"))
    rng = np.random.default_rng(2)
    checked = 0
    for k, n in enumerate(names):
        x_world = traj.positions[k] + rng.normal(size=(300, 3))
        x_rig = (x_world - traj.positions[k]) @ traj.rotations[k]
        for lens, cam in enumerate(camera.lenses):
            T = camera.rig_from_lens[lens]
            x_lens = (x_rig - T[:3, 3] / METRES_PER_UNIT) @ T[:3, :3]
            uv = cam.pixels_from_rays(x_lens / np.linalg.norm(x_lens, axis=1, keepdims=True))
            # (COLMAP projects no point behind the lens, ours up to 100 deg off its axis)
            ok = np.isfinite(uv).all(axis=1) & (x_lens[:, 2] > 0.05)
            im = rec.find_image_with_name(f"lens{lens}/{n}")
            x_cam = np.asarray([im.cam_from_world() * p for p in x_world[ok]])
            uv_colmap = np.asarray(rec.cameras[im.camera_id].img_from_cam(x_cam))
            expected = cam.colmap_export().pixels_to_colmap(uv[ok])
            assert np.abs(uv_colmap - expected).max() < 1e-6
            checked += int(ok.sum())
    assert checked > 500


def test_images_colmap_hold_each_lens_part_of_the_frame(tmp_path: Path) -> None:
    camera = dual_fisheye_camera(192, 96)
    traj = _trajectory(2, 3)
    names = ["f0.png", "f1.png"]
    rng = np.random.default_rng(4)
    frames = [rng.integers(0, 256, size=(96, 192, 3), dtype=np.uint8) for _ in names]
    init = _init_folder(tmp_path / "init", camera, traj, names, frames)
    for frame, n in zip(frames, names, strict=True):
        left = cv2.imread(str(init / "images_colmap" / "lens0" / n))[:, :, ::-1]
        right = cv2.imread(str(init / "images_colmap" / "lens1" / n))[:, :, ::-1]
        assert np.array_equal(left, frame[:, :96]) and np.array_equal(right, frame[:, 96:])


def test_the_rig_needs_the_estimators_metric_scale(tmp_path: Path) -> None:
    camera = dual_fisheye_camera(192, 96)
    traj = _trajectory(3, 5)
    (tmp_path / "report.json").write_text(json.dumps({"num_frames": 3}))
    with pytest.raises(OmniSfmError, match="no metric scale for the rig's lens offsets"):
        write_init_model(tmp_path, camera, traj, ["a", "b", "c"])
    with pytest.raises(OmniSfmError, match="report not found"):
        rig_metres_per_unit(tmp_path / "elsewhere")
    (tmp_path / "report.json").write_text(json.dumps({
        "num_frames": 3, "rig": {"metres_per_unit": -1, "note": "test"}}))
    with pytest.raises(OmniSfmError, match="positive"):
        rig_metres_per_unit(tmp_path)


def _one_line_error(capsys: pytest.CaptureFixture[str], *words: str) -> None:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    for w in words:
        assert w in err, err


def _random_frames(folder: Path, names: list[str], seed: int
                   ) -> tuple[Path, list[np.ndarray]]:
    """Random 192 x 96 frames (the test rigs' size) written as ``names`` in ``folder``."""
    folder.mkdir()
    rng = np.random.default_rng(seed)
    frames = [rng.integers(0, 256, size=(96, 192, 3), dtype=np.uint8) for _ in names]
    for n, f in zip(names, frames, strict=True):
        cv2.imwrite(str(folder / n), f)
    return folder, frames


def test_export_colmap_writes_the_rig_and_refine_refuses_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    camera = dual_fisheye_camera(192, 96)
    traj = _trajectory(3, 6)
    names = ["000000.png", "000001.png", "000002.png"]
    frames_dir, frames = _random_frames(tmp_path / "frames", names, 7)
    init = _init_folder(tmp_path / "init", camera, traj, names)
    from omni_sfm.poses import write_tum

    write_tum(init / "trajectory.tum", traj)
    out = tmp_path / "export"
    assert main(["export", "--input", str(init), "--images", str(frames_dir), "--format",
                 "colmap", "--output", str(out)]) == 0
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    assert rec.num_rigs() == 1 and rec.num_frames() == 3 and rec.num_images() == 6
    assert np.array_equal(cv2.imread(str(out / "images" / "lens1" / names[2])),
                          frames[2][:, 96:])
    assert (out / "rig_config.json").is_file() and (out / "camera_mask_lens1.png").is_file()
    report = json.loads((out / "report.json").read_text())
    assert report["camera_model"] == "rig"
    assert report["rig"]["metres_per_unit"] == METRES_PER_UNIT
    # an init folder without its COLMAP side (init --no-colmap): the rig built from the poses
    shutil.rmtree(init / "sparse")
    assert main(["export", "--input", str(init), "--images", str(frames_dir), "--format",
                 "colmap", "--output", str(tmp_path / "built")]) == 0
    built = pycolmap.Reconstruction(str(tmp_path / "built" / "sparse"))
    for im in rec.images.values():
        assert np.allclose(_matrix(built.find_image_with_name(im.name).cam_from_world()),
                           _matrix(im.cam_from_world()), atol=1e-12)


def _rig_export(tmp_path: Path, fmt: str, lines: Any = None
                ) -> tuple[RigCamera, Trajectory, list[str], list[np.ndarray], Path]:
    """A tilted rig's init folder of two random frames (and ``lines``, its lines3d.json)
    exported as ``fmt`` (``--no-up``): ``(camera, poses, frame names, frames, export
    folder)``."""
    from omni_sfm.lines3d import write_lines3d
    from omni_sfm.poses import write_tum

    camera = _tilted_rig()
    traj = _trajectory(2, 11)
    names = ["000000.png", "000001.png"]
    frames_dir, frames = _random_frames(tmp_path / "frames", names, 2)
    init = _init_folder(tmp_path / "init", camera, traj, names)
    write_tum(init / "trajectory.tum", traj)
    if lines is not None:
        write_lines3d(init / "lines3d.json", lines)
    out = tmp_path / fmt
    assert main(["export", "--input", str(init), "--images", str(frames_dir), "--format", fmt,
                 "--no-up", "--output", str(out)]) == 0
    return camera, traj, names, frames, out


def _lens_views(camera: RigCamera, lens_k: int, frame: np.ndarray) -> tuple[Any, np.ndarray]:
    """Lens ``lens_k``'s view layout (``--no-up``: the rig's mount axis -y is up, each lens
    lays its views out by it) and its views of ``frame``."""
    from omni_sfm.export.perspective import view_layout

    lens = camera.lenses[lens_k]
    layout = view_layout(lens, camera.rig_from_lens[lens_k, :3, :3].T @ np.array([0.0, -1.0, 0.0]),
                         "overlapping")
    views, _ = layout.render(camera.lens_image(frame, lens_k), lens.valid_mask())
    return layout, views


def _lens_pose(camera: RigCamera, traj: Trajectory, k: int, lens_k: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """world_from_lens of ``lens_k`` at pose ``k``, its centre at its offset in pose units."""
    T = camera.rig_from_lens[lens_k]
    return (traj.rotations[k] @ T[:3, :3],
            traj.positions[k] + traj.rotations[k] @ T[:3, 3] / METRES_PER_UNIT)


def test_nerfstudio_views_of_each_lens_see_the_world_where_the_lens_does(tmp_path: Path) -> None:
    """``export --format nerfstudio`` of a rig: pinhole views rendered from each lens's part of
    the frames, each posed at its lens (the lens's rotation and centre at its offset, in the
    poses' units) turned by the view's rotation: a world point 0.5 m from a view's centre,
    through one of its pixels, is where the lens images it (the view's remap table there,
    float32: to 1e-3 px)."""
    from omni_sfm.export.nerfstudio import opencv_poses, read_transforms

    camera, traj, names, frames, out = _rig_export(tmp_path, "nerfstudio")
    doc, entries = read_transforms(out / "transforms.json")
    assert doc["camera_model"] == "OPENCV"
    report = json.loads((out / "report.json").read_text())
    lenses = report["views"]["lenses"]
    assert [lens["lens"] for lens in lenses] == [0, 1]
    poses = opencv_poses(np.asarray([m for _, m in entries]))
    K = np.array([[doc["fl_x"], 0.0, doc["cx"] - 0.5], [0.0, doc["fl_y"], doc["cy"] - 0.5],
                  [0.0, 0.0, 1.0]])
    r = 0
    for k, name in enumerate(names):
        for lens_k, lens_json in enumerate(lenses):
            lens = camera.lenses[lens_k]
            R_lens, c_lens = _lens_pose(camera, traj, k, lens_k)
            layout, views = _lens_views(camera, lens_k, frames[k])
            for v, view in enumerate(lens_json["views"]):
                assert entries[r][0] == f"images/lens{lens_k}/{view['name']}/{name}"
                # the view is rendered from this lens's part of the frame
                assert np.array_equal(cv2.imread(str(out / entries[r][0])), views[v])
                R_view = R_lens @ np.asarray(view["cam_from_view"])
                np.testing.assert_allclose(poses.rotations[r], R_view, atol=1e-12)
                np.testing.assert_allclose(poses.positions[r], c_lens, atol=1e-12)
                ok = np.argwhere(layout.valid[v])
                py, px = ok[len(ok) // 2]
                X = c_lens + 0.5 / METRES_PER_UNIT * R_view @ np.linalg.solve(
                    K, [float(px), float(py), 1.0])
                seen = lens.pixels_from_rays((R_lens.T @ (X - c_lens))[None])[0]
                np.testing.assert_allclose(seen, layout.tables[v][py, px], atol=1e-3)
                r += 1
    assert r == len(entries)


def test_colmap_rig_of_a_rig_holds_every_lens_view_at_its_lens(tmp_path: Path) -> None:
    """``export --format colmap-rig`` of a rig: one COLMAP rig whose sensors are the views of
    both lenses, each image's cam_from_world the inverse of its lens's pose turned by the
    view (1e-9), its image the view rendered from that lens's part of the frame."""
    camera, traj, names, frames, out = _rig_export(tmp_path, "colmap-rig")
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    report = json.loads((out / "report.json").read_text())
    lenses = report["views"]["lenses"]
    per_frame = sum(len(lens["views"]) for lens in lenses)
    assert rec.num_rigs() == 1 and rec.num_frames() == 2
    assert rec.num_images() == 2 * per_frame
    for k, name in enumerate(names):
        for lens_k, lens_json in enumerate(lenses):
            layout, views = _lens_views(camera, lens_k, frames[k])
            R_lens, c_lens = _lens_pose(camera, traj, k, lens_k)
            for v, view in enumerate(lens_json["views"]):
                im = rec.find_image_with_name(f"lens{lens_k}/{view['name']}/{name}")
                R_view = R_lens @ layout.cam_from_views[v]
                want = np.eye(4)
                want[:3, :3], want[:3, 3] = R_view.T, -R_view.T @ c_lens
                np.testing.assert_allclose(_matrix(im.cam_from_world()), want, atol=1e-9)
                got = cv2.imread(str(out / "images" / im.name))
                assert np.array_equal(got, views[v])


def test_limap_tracks_of_a_rig_lie_in_each_lens_image_that_sees_them(tmp_path: Path) -> None:
    """``export --format limap`` of a rig: the COLMAP rig model and LIMAP line tracks whose
    2D segments are in the lens images (``lensK/NAME``) of the poses, where COLMAP's model of
    that lens at its place projects the segment's ends (1e-4 px); segments seen by both
    lenses of a frame have both images."""
    from omni_sfm.export.limap import read_track
    from omni_sfm.lines3d import LineSegments3D

    rng = np.random.default_rng(5)
    starts = rng.uniform(-3.0, 3.0, size=(60, 3))
    dirs = rng.normal(size=(60, 3))
    ends = starts + dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    lines = LineSegments3D(starts, ends, np.zeros(60, int), np.array([[1.0, 0.0, 0.0]]),
                           ("test",) * 60, frame="poses' world")
    _, _, _, _, out = _rig_export(tmp_path, "limap", lines)
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    lenses_seen: set[str] = set()
    both = 0
    for k in range(len(lines)):
        tr = read_track(out / "finaltracks" / f"track_{k}.txt")
        np.testing.assert_allclose(tr["line"], [starts[k], ends[k]], atol=1e-8)
        frames_of = []
        for image_id, seg in zip(tr["image_ids"], tr["line2d"], strict=True):
            image = rec.images[image_id]
            cam = rec.cameras[image.camera_id]
            T = np.asarray(image.cam_from_world().matrix())
            uv = np.asarray(cam.img_from_cam(np.stack([starts[k], ends[k]]) @ T[:, :3].T
                                             + T[:, 3]))
            np.testing.assert_allclose(seg, uv.ravel(), atol=1e-4)
            lenses_seen.add(image.name.split("/")[0])
            frames_of.append(image.frame_id)
        both += len(frames_of) != len(set(frames_of))
    assert lenses_seen == {"lens0", "lens1"} and both > 0
