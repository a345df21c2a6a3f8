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
"""The init poses the render's first 16 frames; the other 4 are in the folder without a pose."""


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
    assert report.refined_frames == POSED and after.num_common == POSED
    # measured: 0.29 / 0.72 deg and 0.37 % before; after 0.020 / 0.037 deg, 0.017 %
    assert after.rot_mean_deg < 0.2 * before.rot_mean_deg, (before, after)
    assert after.rot_max_deg < 0.1 and after.ate_rel < 0.001, after.as_dict()
    # the lens baseline fixed the metric scale the init had twice too large (measured: 0.5 %
    # off with 320 x 320 lenses 4 cm apart, 1.0 % with all 20 frames posed, 1.9 % with 12;
    # on the corridor's 480 x 480 lenses, 0.2 %)
    assert report.rig is not None and report.rig.fixed
    assert report.rig.metres_per_unit == pytest.approx(after.alignment.scale, rel=0.02)
    assert abs(report.rig.metres_per_unit / unit - 1) < 0.05
    # the frames without an input pose are not registered, and the report says so
    assert report.frames["unposed_in_folder"] == 20 - POSED
    assert "not registered" in (report.mapper.skipped or "")
    assert report.joint_adjustment is not None


def test_the_refined_rig_model_follows_the_trajectory(dual_room: Path, refined_rig) -> None:
    """``sparse/`` is the rig at the poses of ``trajectory.tum``, its lens offsets in the
    trajectory's units (metres over ``rig.metres_per_unit``), with its points."""
    work, _ = refined_rig
    out = work / "out"
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    traj, rig = read_tum(out / "trajectory.tum"), load_camera(out / "camera.yaml")
    metres = RefineFolder(out).read_report().rig.metres_per_unit
    assert rec.num_rigs() == 1 and rec.num_frames() == POSED and rec.num_images() == 2 * POSED
    assert rec.num_points3D() > 500
    names = json.loads((out / InitFolder.MANIFEST).read_text())["image_names"]
    for k, name in enumerate(names):
        for lens in range(2):
            im = rec.find_image_with_name(f"lens{lens}/{name}")
            want = traj.positions[k] + traj.rotations[k] @ rig.rig_from_lens[lens][:3, 3] / metres
            np.testing.assert_allclose(im.projection_center(), want, atol=1e-9)
