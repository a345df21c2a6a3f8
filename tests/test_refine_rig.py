"""``omni-sfm refine`` of a rig camera (raw dual-fisheye frames): COLMAP's rig on the line-based
poses, the lens baseline fixing the metric scale (docs/colmap.md, "Refining a rig").

The seed is the rendered dual-fisheye room's ground truth with realistic errors (0.3 deg, 0.5 %
of the path) in units of its first-to-last distance, with a rough metric scale (twice the true
one, as ``init`` records where the lines are too far for the baseline).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from helpers import assert_every_key_declared

from omni_sfm.cameras import load_camera
from omni_sfm.cli import main
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.export.colmap import write_init_model
from omni_sfm.fileio import dumps_json
from omni_sfm.folders import InitFolder, RefineFolder
from omni_sfm.frames import FrameStore
from omni_sfm.poses import Trajectory, read_tum, write_tum
from omni_sfm.refine.synthetic import perturb
from omni_sfm.reports import RefineReport

POSED = 16
"""The init poses the render's first 16 frames; the other 4 are in the folder without a pose
(for refine's mapper)."""


def _rough_init(render: Path, out: Path) -> float:
    """An init folder of the render's first :data:`POSED` frames: perturbed true poses in units
    of their first-to-last distance, its ``rig.metres_per_unit`` twice the truth and not fixed.
    Returns the true metres per unit."""
    gt = read_tum(render / "groundtruth.tum").subset(np.arange(POSED))
    unit = float(np.linalg.norm(gt.positions[-1] - gt.positions[0]))
    noisy = perturb(gt, rotation_deg=0.3, position_fraction=0.005, seed=1)
    traj = Trajectory(noisy.timestamps, noisy.rotations, noisy.positions / unit)
    out.mkdir()
    (out / InitFolder.REPORT).write_text(dumps_json({"num_frames": POSED, "rig": {
        "metres_per_unit": 2 * unit, "note": "rough", "fixed": False}}), encoding="utf-8")
    write_tum(out / InitFolder.TRAJECTORY, traj)
    write_init_model(out, load_camera(render / "camera.yaml"), traj,
                     list(FrameStore(render / "images").names)[:POSED])
    return unit


@pytest.fixture(scope="module")
def refined_rig(dual_room: Path, tmp_path_factory: pytest.TempPathFactory
                ) -> tuple[Path, float]:
    work = tmp_path_factory.mktemp("refine_rig")
    unit = _rough_init(dual_room, work / "init")
    assert main(["refine", "--input", str(work / "init"), "--images",
                 str(dual_room / "images"), "--output", str(work / "out")]) == 0
    return work, unit


def test_refine_of_a_rig_is_accurate_and_metric(dual_room: Path, refined_rig) -> None:
    work, unit = refined_rig
    out = work / "out"
    assert_every_key_declared(RefineReport, out / RefineFolder.REPORT)
    report = RefineFolder(out).read_report()
    gt = read_tum(dual_room / "groundtruth.tum")
    before = trajectory_errors(read_tum(work / "init" / "trajectory.tum"), gt)
    after = trajectory_errors(read_tum(out / "trajectory.tum"), gt)
    assert report.refined_frames == POSED and after.num_common == 20
    # measured: 0.29 / 0.72 deg and 0.37 % before (16 frames); after 0.024 / 0.045 deg,
    # 0.013 % (20)
    assert after.rot_mean_deg < 0.2 * before.rot_mean_deg, (before, after)
    assert after.rot_max_deg < 0.1 and after.ate_rel < 0.001, after.as_dict()
    # the lens baseline fixed the metric scale the init had twice too large (measured: 0.7 %
    # off with 320 x 320 lenses 4 cm apart, parallax 1.86 px; on the corridor's 480 x 480
    # lenses, 0.2 %)
    assert report.rig is not None and report.rig.fixed
    assert report.rig.metres_per_unit == pytest.approx(after.alignment.scale, rel=0.02)
    assert abs(report.rig.metres_per_unit / unit - 1) < 0.05
    # the frames without an input pose registered by COLMAP's mapper, each with both lenses
    unposed = [f"{k:06d}.png" for k in range(POSED, 20)]
    assert report.frames["unposed_in_folder"] == 20 - POSED
    assert report.mapper.registered == unposed and report.mapper_added == unposed
    assert report.joint_adjustment is not None


def test_the_refined_rig_model_follows_the_trajectory(dual_room: Path, refined_rig) -> None:
    """``sparse/`` is the rig at the poses of ``trajectory.tum``, its lens offsets in the
    trajectory's units (metres over ``rig.metres_per_unit``), with its points."""
    work, _ = refined_rig
    out = work / "out"
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    traj, rig = read_tum(out / "trajectory.tum"), load_camera(out / "camera.yaml")
    metres = RefineFolder(out).read_report().rig.metres_per_unit
    assert rec.num_rigs() == 1 and rec.num_reg_frames() == 20 and rec.num_reg_images() == 40
    assert rec.num_points3D() > 500
    names = json.loads((out / InitFolder.MANIFEST).read_text())["image_names"]
    for k, name in enumerate(names):
        for lens in range(2):
            im = rec.find_image_with_name(f"lens{lens}/{name}")
            want = traj.positions[k] + traj.rotations[k] @ rig.rig_from_lens[lens][:3, 3] / metres
            np.testing.assert_allclose(im.projection_center(), want, atol=1e-9)



@pytest.mark.parametrize(("distance", "fixed"), [(2.0, True), (40.0, False)])
def test_the_scale_is_fixed_only_where_the_baseline_sees_the_points(distance: float,
                                                                     fixed: bool) -> None:
    """The lens baseline's parallax at the points (the median, in pixels) decides whether the
    refined metric scale is reported as fixed: 4 cm seen from 2 m by lenses of 960 x 960 (a
    270 px focal length) is about 5 px, from 40 m 0.3 px."""
    from omni_sfm.export.colmap_lenses import build_lens_rig
    from omni_sfm.refine.rig_pipeline import MIN_BASELINE_PARALLAX_PX, baseline_parallax_px
    from omni_sfm.synth.render import dual_fisheye_camera

    camera = dual_fisheye_camera(1920, 960)
    traj = Trajectory(np.arange(3.0), np.repeat(np.eye(3)[None], 3, 0),
                      np.column_stack([0.1 * np.arange(3.0), np.zeros(3), np.zeros(3)]))
    rec = build_lens_rig(camera, traj, ["a.png", "b.png", "c.png"], 1.0).reconstruction
    for im in rec.images.values():
        im.points2D = pycolmap.Point2DList([pycolmap.Point2D(np.array([10.0, 10.0 + j]))
                                            for j in range(20)])
    rng = np.random.default_rng(0)
    for j in range(20):
        track = pycolmap.Track()
        for image_id in rec.images:
            track.add_element(image_id, j)
        u = rng.normal(size=3)
        rec.add_point3D(distance * u / np.linalg.norm(u), track)
    focal = np.mean([c.mean_focal_length() for c in rec.cameras.values()])
    got = baseline_parallax_px(rec, camera)
    # the nearest frame is within 0.2 m of the origin the points are around
    assert 0.04 * focal / (distance + 0.2) <= got <= 0.04 * focal / (distance - 0.2)
    assert (got >= MIN_BASELINE_PARALLAX_PX) == fixed
