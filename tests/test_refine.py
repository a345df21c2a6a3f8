"""COLMAP refinement seeded by line-based poses: better on texture, never worse than its input.

The "line-based init" here is the rendered ground truth with realistic errors (0.3 deg rotation,
0.5 % of the path in position, fixed seed), written through the same ``write_init_model`` that
``omni-sfm init`` uses. Sequences are small (400 x 300, supersample 1) to keep the file fast.
"""

from __future__ import annotations

import json
import shutil
import sqlite3
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from helpers import assert_every_key_declared, assert_one_line_error, refine_perturbed

from omni_sfm.cameras import load_camera
from omni_sfm.cli import main
from omni_sfm.errors import OmniSfmError
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.export.colmap import (
    projection_centres,
    read_init_model,
    write_init_model,
)
from omni_sfm.fileio import dumps_json, read_json
from omni_sfm.folders import InitFolder, RefineFolder
from omni_sfm.poses import Trajectory, read_tum
from omni_sfm.refine import RefineOptions, refine
from omni_sfm.refine.synthetic import perturb, write_perturbed_init
from omni_sfm.reports import RefineReport
from omni_sfm.synth.render import RenderOptions

EXAMPLES = Path(__file__).resolve().parents[1] / "docs" / "examples" / "cameras"
MISSING = (6, 13)  # frames the "line stage" did not pose: the mapper should register them


def _render(rendered, **kw) -> Path:
    """The session's (read-only) render of the hyperboloid at 400 x 300, supersample 1."""
    return rendered(RenderOptions(camera="hyperboloid", width=400, height=300, supersample=1,
                                  preset="small", seed=3, **kw)).output


def _keypoints_in_database(db: Path) -> int:
    """Keypoints stored in a COLMAP database, read from its ``keypoints`` table with sqlite3
    (each row: one image's ``rows x cols`` float32 blob), independently of pycolmap."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        rows = con.execute("SELECT rows, cols, length(data) FROM keypoints").fetchall()
    finally:
        con.close()
    assert rows and all(r * c * 4 == n for r, c, n in rows), rows[:3]
    return sum(r for r, _, _ in rows)


@pytest.fixture(scope="module")
def room_refined(room, built_once):
    """``refine_perturbed`` of the room, once per test run (``built_once``: read-only)."""
    return built_once("refine-room-sift", lambda d: refine_perturbed(
        room, d, MISSING, RefineOptions(overlap=5, features="sift")))[1]


def _on(traj: Trajectory, ts: np.ndarray) -> Trajectory:
    idx = np.searchsorted(traj.timestamps, ts)
    assert np.allclose(traj.timestamps[idx], ts)
    return traj.subset(idx)


def test_init_model_layout_round_trip(room, tmp_path):
    cam = load_camera(room / "camera.yaml")
    gt = read_tum(room / "groundtruth.tum").subset(np.arange(4))
    names = [f"{k:06d}.png" for k in range(4)]
    imgs = [cv2.imread(str(room / "images" / n))[:, :, ::-1] for n in names]
    write_init_model(tmp_path, cam, gt, names, imgs, text=True)
    init = read_init_model(tmp_path)
    assert init.image_names == tuple(names)
    np.testing.assert_allclose(init.trajectory.positions, gt.positions, atol=1e-12)
    centres = projection_centres(pycolmap.Reconstruction(str(tmp_path / "sparse")))
    for k, n in enumerate(names):
        np.testing.assert_allclose(centres[n], gt.positions[k], atol=1e-9)
    assert (tmp_path / "sparse" / "images.txt").is_file()
    # COLMAP sees the hyperboloid's images mirrored left-right, RGB written as BGR files
    seen = cv2.imread(str(tmp_path / InitFolder.COLMAP_IMAGES / names[1]))
    np.testing.assert_array_equal(seen, imgs[1][:, ::-1, ::-1])
    mask = cv2.imread(str(tmp_path / "camera_mask.png"), cv2.IMREAD_GRAYSCALE)
    valid = cam.valid_mask()[:, ::-1]
    assert mask.shape == valid.shape and not mask[~valid].any()
    assert (mask[valid] > 0).mean() > 0.9


def test_sift_is_colmaps_in_colmaps_form(room):
    """refine's SIFT (OpenCV's, written as COLMAP stores it) finds COLMAP's own keypoints at
    their positions and with their descriptors: COLMAP's matcher and mapper read them as
    their own."""
    from scipy.spatial import cKDTree

    from omni_sfm.refine.database import colmap_sift

    gray = cv2.imread(str(sorted((room / "images").iterdir())[5]), cv2.IMREAD_GRAYSCALE)
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = 1
    ref = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu)
    ref_kp, ref_desc = ref.extract(pycolmap.Bitmap.from_array(gray))
    ref_kp = np.array([[k.x, k.y, k.a11, k.a12, k.a21, k.a22] for k in ref_kp])
    ref_desc = np.asarray(ref_desc.data)
    kp, desc = colmap_sift(gray, None, 8192)
    assert kp.shape[1] == 6 and desc.dtype == np.uint8 and len(kp) == len(desc) > 200
    dist, nearest = cKDTree(ref_kp[:, :2]).query(kp[:, :2])
    near = dist < 0.05
    assert near.mean() > 0.9                               # the same keypoints ...
    assert np.median(dist[near]) < 0.01                    # ... at the same pixel (+0.5)
    # ... with the same scale, orientation and descriptor (COLMAP may give a keypoint a second
    # orientation: the closest of the two nearest)
    scale = np.hypot(kp[:, 2], kp[:, 4])
    ref_scale = np.hypot(ref_kp[:, 2], ref_kp[:, 4])
    np.testing.assert_allclose(np.median(scale[near] / ref_scale[nearest[near]]), 1.0, atol=0.02)
    two = cKDTree(ref_kp[:, :2]).query(kp[near, :2], k=2)[1]
    turn = np.arctan2(kp[near, 4], kp[near, 2])[:, None] - np.arctan2(ref_kp[two, 4],
                                                                      ref_kp[two, 2])
    assert np.median(np.abs(np.angle(np.exp(1j * turn))).min(axis=1)) < np.deg2rad(5)
    d = np.linalg.norm(desc[near].astype(float)[:, None] - ref_desc[two].astype(float),
                       axis=2).min(axis=1)
    random = np.linalg.norm(desc[near].astype(float) - ref_desc[::-1][:near.sum()].astype(float),
                            axis=1)
    assert np.median(d) < 0.1 * np.median(random)


def test_refine_improves_a_perturbed_seed_on_a_textured_room(room_refined):
    work, gt, init, res = room_refined
    r = res.report
    # the folder's loader reads back the report refine returned, and the refined poses
    art = RefineFolder(work / "out").load()
    assert_every_key_declared(RefineReport, work / "out" / RefineFolder.REPORT)
    assert art.report.to_json() == json.loads(dumps_json(r.to_json()))
    # read and written again, the file is the same to the byte
    text = (work / "out" / RefineFolder.REPORT).read_text()
    assert dumps_json(art.report.to_json()) == text == dumps_json(r.to_json())
    np.testing.assert_allclose(art.trajectory.positions, res.trajectory.positions, atol=1e-9)
    before = trajectory_errors(init, gt)
    after_all = trajectory_errors(res.trajectory, gt)
    after = trajectory_errors(_on(res.trajectory, init.timestamps), gt)
    assert after.ate_rel < before.ate_rel
    assert after.ate_rel < 0.0025, after.ate_rel
    assert after.rot_mean_deg < 0.5 * before.rot_mean_deg
    assert r.refined_frames >= 0.8 * len(init)
    # the mapper registered the frames the seed lacked, and they are good too
    assert sorted(r.mapper.registered or []) == [f"{k:06d}.png" for k in MISSING]
    assert after_all.num_common == len(gt) and after_all.ate_rel < 0.0025
    ba = r.adjustment_rounds
    assert ba[-1].mean_reprojection_error_after_px < ba[0].mean_reprojection_error_before_px
    assert r.model.mean_reprojection_error_px < 1.0
    assert set(r.timings_s) >= {"features", "matching", "triangulation", "bundle adjustment"}
    # pairs of seeded frames were matched along their poses, the mapper's frames by COLMAP
    g = r.matching_guided
    assert g is not None and g.written >= 0.8 * g.pairs > 0 and g.matches > 100 * g.written
    assert r.matching["verified_pairs"] > g.written


def test_a_missed_frame_the_mapper_cannot_register_is_listed(room, tmp_path):
    """A frame without an input pose that too few points can pose (here a black frame but for
    a patch: enough corners tracked through it to enter COLMAP's correspondence graph, too few
    to pose it) is listed as not registered, and the rest is refined. The mapper's end removes
    the frame from the model; refine once raised KeyError there (this patch size reproduces
    it: a smaller one keeps the frame out of the graph, a larger one gets it registered)."""
    render = tmp_path / "render"
    shutil.copytree(room, render)
    img = cv2.imread(str(render / "images" / "000013.png"))
    dark = np.zeros_like(img)
    dark[40:120, 150:250] = img[40:120, 150:250]
    cv2.imwrite(str(render / "images" / "000013.png"), dark)
    _, gt, _, res = refine_perturbed(render, tmp_path, MISSING,
                                     RefineOptions(overlap=5, features="klt"))
    r = res.report  # type: ignore[attr-defined]
    assert r.mapper.registered == ["000006.png"]
    assert r.mapper.not_registered == ["000013.png"]
    assert len(res.trajectory) == len(gt) - 1  # type: ignore[attr-defined]


def test_refined_model_opens_in_pycolmap_and_matches_the_trajectory(room_refined):
    work, gt, init, res = room_refined
    out = work / "out"
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    stats = RefineFolder(out).read_report().model
    assert rec.num_reg_images() == stats.registered_images == len(gt)
    assert rec.num_points3D() == stats.points > 100
    assert stats.observations == rec.compute_num_observations()
    assert "num_points3D" in RefineFolder(out).read_report().summary
    traj = read_tum(out / "trajectory.tum")
    centres = projection_centres(rec)
    for k, ts in enumerate(traj.timestamps):
        np.testing.assert_allclose(centres[f"{round(ts):06d}.png"], traj.positions[k], atol=1e-6)


def test_cli_reuses_the_features_of_a_database(room, room_refined, tmp_path, capsys):
    """A second seed of the same frames: nothing is extracted again, and it improves too."""
    work, gt, _, _ = room_refined
    db = tmp_path / "database.db"
    shutil.copy(work / "out" / "database.db", db)
    stored = _keypoints_in_database(db)
    init = write_perturbed_init(room, tmp_path / "init", seed=2)
    rc = main(["refine", "--input", str(tmp_path / "init"), "--images", str(room / "images"),
               "--output", str(tmp_path / "out"), "--database", str(db), "--overlap", "5",
               "--no-guided-matching"])
    assert rc == 0
    assert "refined" in capsys.readouterr().out
    report = read_json(tmp_path / "out" / "report.json")
    assert "matching_guided" not in report and not report["options"]["guided_matching"]
    # the keypoints reported are those the database held, none added
    assert stored > 100 * len(gt)
    assert report["features"] == {"source": "sift", "extracted_images": 0,
                                  "reused_images": len(gt), "keypoints": stored}
    assert _keypoints_in_database(db) == stored
    assert not (tmp_path / "out" / "database.db").exists()  # the given database is used
    out = read_tum(tmp_path / "out" / "trajectory.tum")
    assert trajectory_errors(out, gt).ate_rel < trajectory_errors(init, gt).ate_rel


def test_a_large_correction_is_taken_only_where_the_images_back_it(room, room_refined,
                                                                      tmp_path):
    """One seeded pose 8 deg off (beyond the 5 deg plausibility bound): its observations fit the
    corrected pose to sub-pixel error, so the correction is taken, and the report lists it as a
    large change backed by the images. (Where the images back no adjustment, every frame keeps
    its input: the corridor test.)"""
    from omni_sfm.geometry import rotation_angle, rotvec_to_matrix
    from omni_sfm.poses import write_tum

    work, gt, _, _ = room_refined
    init = perturb(gt, seed=6)
    bad = 9
    rot = init.rotations.copy()
    rot[bad] = rot[bad] @ rotvec_to_matrix(np.radians([0.0, 0.0, 8.0]))
    write_tum(tmp_path / "init.tum", Trajectory(init.timestamps, rot, init.positions))
    init = read_tum(tmp_path / "init.tum")
    names = [f"{k:06d}.png" for k in range(len(init))]
    (tmp_path / "init").mkdir()
    write_tum(tmp_path / "init" / "trajectory.tum", init)
    write_init_model(tmp_path / "init", load_camera(room / "camera.yaml"), init, names)
    db = tmp_path / "database.db"
    shutil.copy(work / "out" / "database.db", db)
    res = refine(tmp_path / "init", room / "images", tmp_path / "out",
                 RefineOptions(overlap=5), database=db, progress=False)
    assert res.refined[bad]
    changes = res.report.pose_changes
    assert changes is not None
    assert list(changes.large_changes_backed_by_images or {}) == [names[bad]]
    # its observations disagree with the points the other frames triangulate: it is posed
    # again from them before the adjustment (without that it would have none)
    assert res.report.triangulation.frames_posed_again == [names[bad]]

    def rot_err(traj: Trajectory) -> float:  # frame `bad` relative to frame 0, vs ground truth
        rel = np.swapaxes(traj.rotations[0], 0, 1) @ traj.rotations[bad]
        rel_gt = np.swapaxes(gt.rotations[0], 0, 1) @ gt.rotations[bad]
        return float(np.degrees(rotation_angle(rel_gt.T @ rel)))

    assert rot_err(init) > 7.0 and rot_err(res.trajectory) < 0.5


def test_refine_keeps_the_input_on_a_texture_poor_corridor(rendered, tmp_path):
    """Too few SIFT points on the untextured corridor for a trustworthy adjustment: the whole
    input is kept, and the report says why."""
    corridor = _render(rendered, scene="corridor", frames=16)
    init = write_perturbed_init(corridor, tmp_path / "init", seed=4)
    res = refine(tmp_path / "init", corridor / "images", tmp_path / "out",
                 RefineOptions(overlap=5), progress=False)
    gt = read_tum(corridor / "groundtruth.tum")
    assert len(res.trajectory) == len(init) == len(gt)
    assert not res.refined.any()
    # kept means the input pose itself (up to the TUM file's quaternion round trip)
    np.testing.assert_allclose(res.trajectory.positions, init.positions, atol=1e-12)
    np.testing.assert_allclose(res.trajectory.rotations, init.rotations, atol=1e-12)
    assert trajectory_errors(res.trajectory, gt).ate_rel == pytest.approx(
        trajectory_errors(init, gt).ate_rel, rel=1e-9)
    r = res.report
    assert r.kept_input_for_all == ("too few points or well-observed frames for a "
                                       "trustworthy adjustment"), r.kept_input_for_all
    assert r.refined_frames == 0 and r.kept_frames == {}


def test_refine_improves_an_equirectangular_seed(rendered, tmp_path):
    """The camera whose COLMAP image is not mirrored and whose frame is COLMAP's own."""
    out = rendered(RenderOptions(scene="room", camera="equirectangular", width=384, height=192,
                                 frames=10, textured=True, supersample=1, preset="small",
                                 seed=3)).output
    init = write_perturbed_init(out, tmp_path / "init", seed=5)
    res = refine(tmp_path / "init", out / "images", tmp_path / "out", RefineOptions(overlap=4),
                 progress=False)
    gt = read_tum(out / "groundtruth.tum")
    before, after = trajectory_errors(init, gt), trajectory_errors(res.trajectory, gt)
    assert res.report.refined_frames == len(gt)
    assert after.ate_rel < 0.5 * before.ate_rel
    assert after.rot_mean_deg < 0.5 * before.rot_mean_deg


# --- bad input: one line, exit code 2 -------------------------------------------------------


@pytest.fixture()
def tiny_init(tmp_path):
    from omni_sfm.synth.render import hyperboloid_camera

    cam = hyperboloid_camera(160, 120)
    gt = perturb(Trajectory(np.arange(3.0), np.repeat(np.eye(3)[None], 3, 0),
                            np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0]])), seed=0)
    names = [f"{k:06d}.png" for k in range(3)]
    write_init_model(tmp_path / "init", cam, gt, names)
    (tmp_path / "images").mkdir()
    for n in names:
        cv2.imwrite(str(tmp_path / "images" / n), np.zeros((120, 160, 3), np.uint8))
    return tmp_path


def _refine_cli(tmp, capsys, init="init", images="images"):
    rc = main(["refine", "--input", str(tmp / init), "--images", str(tmp / images),
               "--output", str(tmp / "out")])
    assert rc == 2
    err = assert_one_line_error(capsys)
    assert not (tmp / "out").exists()
    return err


def test_bad_input_init_without_model(tiny_init, capsys):
    shutil.rmtree(tiny_init / "init" / "sparse")
    assert "no COLMAP model" in _refine_cli(tiny_init, capsys)


def test_bad_input_images_do_not_match_names(tiny_init, capsys):
    (tiny_init / "images" / "000001.png").rename(tiny_init / "images" / "frame1.png")
    assert "'000001.png'" in _refine_cli(tiny_init, capsys)


def test_bad_input_images_do_not_match_size(tiny_init, capsys):
    cv2.imwrite(str(tiny_init / "images" / "000002.png"), np.zeros((100, 160, 3), np.uint8))
    err = _refine_cli(tiny_init, capsys)
    assert "000002.png" in err and "160x100" in err


def test_bad_input_camera_without_exact_colmap_model(tiny_init, capsys):
    shutil.copy(EXAMPLES / "double_sphere.yaml", tiny_init / "init" / "camera.yaml")
    err = _refine_cli(tiny_init, capsys)
    assert "camera.yaml" in err and "no exact COLMAP model" in err


def _flag(init: Path, uncertain: dict[int, str], num_frames: int,
          not_estimated: tuple[int, ...] = ()) -> None:
    """Give the init folder ``init`` a ``report.json`` that flags ``uncertain`` (frame index ->
    reason) with their poses in ``trajectory.tum``, as ``init`` writes it where the data fix
    fewer than 3 frames or with ``--keep-uncertain``."""
    (init / InitFolder.REPORT).write_text(dumps_json({
        "num_frames": num_frames, "frames_not_estimated": list(not_estimated),
        "frames_uncertain": {str(k): v for k, v in uncertain.items()}}), encoding="utf-8")


def test_poses_the_data_do_not_fix_do_not_seed_colmap(tiny_init, tmp_path):
    from omni_sfm.refine.pipeline import _seed_without_uncertain

    init_dir = tiny_init / "init"
    # frame 1 of 4 not estimated: the three poses are frames 0, 2, 3; frame 2 flagged
    _flag(init_dir, {2: "the adjustment moved it"}, 4, not_estimated=(1,))
    init = read_init_model(init_dir)
    np.testing.assert_array_equal(init.artifacts.uncertain_rows(), [False, True, False])
    with pytest.raises(OmniSfmError, match="the data fix 2 of the 3 poses"):
        _seed_without_uncertain(init, init_dir, tmp_path / "scratch")
    # written to trajectory_uncertain.tum instead (uncertain_poses): nothing to leave out
    report = read_json(init_dir / InitFolder.REPORT)
    (init_dir / InitFolder.REPORT).write_text(dumps_json(
        {**report, "uncertain_poses": InitFolder.UNCERTAIN_TRAJECTORY}), encoding="utf-8")
    assert not init.artifacts.uncertain_rows().any()
    # a report that does not fit the poses is refused in one line
    _flag(init_dir, {2: "x"}, 5, not_estimated=(1,))
    with pytest.raises(OmniSfmError, match="4 frames estimated but .* holds 3 poses"):
        init.artifacts.uncertain_rows()


def test_refine_leaves_flagged_poses_to_the_mapper(room, tmp_path):
    write_perturbed_init(room, tmp_path / "init", seed=2)
    _flag(tmp_path / "init", {4: "a", 11: "b"}, 20)
    res = refine(tmp_path / "init", room / "images", tmp_path / "out", RefineOptions(overlap=5),
                 progress=False)
    r = res.report
    assert r.frames["input_poses"] == 18 and r.frames["input_poses_uncertain"] == 2
    assert sorted(r.mapper_added) == ["000004.png", "000011.png"]
    # registered from the images (measured: 20 of 20, 0.23 deg at most, 0.18 % ATE)
    e = trajectory_errors(res.trajectory, read_tum(room / "groundtruth.tum"))
    assert e.num_common == 20 and e.rot_max_deg < 0.5 and e.ate_rel < 0.005


def test_refine_refuses_an_init_whose_data_fix_fewer_than_3_poses(tiny_init, capsys):
    # init writes every pose to trajectory.tum where the data fix fewer than 3 frames
    _flag(tiny_init / "init", {0: "a", 1: "b"}, 3)
    err = _refine_cli(tiny_init, capsys)
    assert "the data fix 1 of the 3 poses" in err and "--initializer colmap" in err
