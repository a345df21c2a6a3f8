"""The stages' reports (omni_sfm/reports.py): each written and read back is the same report,
with the keys docs/formats.md documents in the order written; the folders' loaders read them
typed; a report lacking a required key is a one-line error."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from omni_sfm.cameras import write_camera_yaml
from omni_sfm.cameras.equirectangular import EquirectangularCamera
from omni_sfm.cli.cmd_init import summary
from omni_sfm.errors import OmniSfmError
from omni_sfm.fileio import dumps_json
from omni_sfm.folders import (
    CompareFolder,
    DenseFolder,
    ExportFolder,
    InitFolder,
    RefineFolder,
    StageFolder,
    TrackFolder,
    recorded_images,
)
from omni_sfm.poses import Trajectory, write_tum
from omni_sfm.reports import (
    CompareEntry,
    CompareResults,
    CompareSequence,
    DenseReport,
    ExportReport,
    ExportWorld,
    InitializerInfo,
    InitReport,
    JsonReport,
    PluginInitInput,
    PluginInitReport,
    RefineReport,
    RigWritten,
    StageReport,
    TrackFrame,
    TrackPose,
)


def _stats(**extra: Any) -> dict[str, Any]:
    return {"cameras": 1, "images": 5, "registered_images": 5, "points": 120,
            "observations": 600, "mean_track_length": 5.0, "mean_observations_per_image": 120.0,
            "mean_reprojection_error_px": 0.5, **extra}


def _refine(**changes: Any) -> RefineReport:
    doc: dict[str, Any] = dict(
        input={"init": "../init", "images": "/data/frames", "database": "database.db"},
        camera={"model": "equirectangular", "colmap_model": "OPENCV",
                "image_mirrored_for_colmap": False},
        frames={"input_poses": 4, "images_in_folder": 5, "unposed_in_folder": 1},
        options={"features": "sift", "overlap": 5},
        features={"source": "sift", "extracted_images": 5, "reused_images": 0,
                  "keypoints": 900},
        matching={"verified_pairs": 10, "inlier_matches": 800},
        triangulation=_stats(frames_posed_again=[]),
        mapper={"registered": ["000004.png"], "not_registered": [],
                "added_to_trajectory": ["000004.png"], "timestamps": "affine in the frame index"},
        bundle_adjustment={"rounds": [{"mean_reprojection_error_before_px": 0.9,
                                       "mean_reprojection_error_after_px": 0.5}],
                           "after": _stats()},
        kept_input_for_all=None, refined_frames=4, kept_frames={},
        alignment_to_input={"rotation": np.eye(3), "translation": np.zeros(3), "scale": 1.0,
                            "rotation_deg": 0.0},
        pose_changes={"rotation_deg_max": 0.1}, model=_stats(),
        summary="Reconstruction:\n\tnum_points3D = 120", carried_from_input=["camera.yaml"],
        trajectory_frames=5, timings_s={"features": 1.0, "matching": 0.5},
        matching_guided={"pairs": 6, "written": 6, "matches": 700})
    doc.update(changes)
    return RefineReport.from_json(doc)


def _dense() -> DenseReport:
    return DenseReport.from_json(dict(
        input={"poses": "../refined", "images": "frames"},
        scale={"source": "known_distance", "unit": "m", "known_distance": 2.0, "factor": 2.0},
        median_depth=1.5, stereo_baseline=0.1, voxel_size=0.01,
        calibration={"frame": 0, "frame_offset": 2, "trials": [
            {"offset": 2, "baseline": 0.1, "median_disparity_px": 8.0, "depth_share": 0.5}]},
        views={"focal_px": 100.0, "width": 64, "height": 64, "per_pair": 4,
               "num_disparities": 32}, keyframe_step=2,
        pair_pose={"enabled": True, "pairs": 4, "corrected": 1,
                   "median_rotation_change_deg": 0.2},
        num_keyframes=3, num_points=1000,
        num_triangles=500, depth_share={"median": 0.4, "min": 0.1, "max": 0.6},
        seconds={"depth_per_keyframe": 0.2, "fusion_per_keyframe": 0.1},
        frames=[{"frame": 0, "timestamp": 0.0, "image": "000000.png", "sources": [2],
                 "baselines": [0.1], "depth_share": 0.4,
                 "pair_pose": [{"corrected": True, "inliers": 80, "rotation_change_deg": 0.2,
                                "direction_change_deg": 1.0}]}],
        warnings=["few points"], backend={"stereo": "cv2.StereoSGBM (CPU)",
                                          "fusion": "open3d"}, note="n"))


def _export() -> ExportReport:
    return ExportReport(
        omni_sfm_version="1.0", format="colmap-rig", input="../refined", num_poses=4,
        world=ExportWorld(turned=True, export_from_world=np.eye(4).tolist(),
                          vertical_in_world=[0.0, 0.0, 1.0], how="parallel family"),
        camera_model="equirectangular",
        written=RigWritten(num_images=24, num_frames=4, views={"views": []},
                           images="images/VIEW/NAME.png", masks="masks/VIEW/NAME.png.png"),
        seconds=1.25)


def _compare() -> CompareResults:
    ok = CompareEntry(status="ok", trajectory="trajectories/lines.tum", registered=1.0,
                      rot_max_deg=0.2, rot_mean_deg=0.1, ate_rel=0.01, rpe=0.02,
                      rpe_rot_deg=0.05, step_error_after_alignment=0.03, frames_compared=10,
                      frames_registered=10, time_s=1.5,
                      info=InitializerInfo(tracks=40))
    failed = CompareEntry(status="failed", trajectory=None, registered=0.0, rot_max_deg=None,
                          rot_mean_deg=None, ate_rel=None, rpe=None, rpe_rot_deg=None,
                          step_error_after_alignment=None, frames_compared=0,
                          frames_registered=0, time_s=0.5, reason="too few points")
    return CompareResults({"lines": ok, "five-point": failed},
                          CompareSequence(name="room", frames=10, camera="hyperboloid"))


def _plugin_init() -> PluginInitReport:
    return PluginInitReport(
        input=PluginInitInput(images="frames", camera="camera.yaml", timestamps="frame index"),
        initializer="five-point", status="ok", reason=None,
        info=InitializerInfo(features="sift", stride=1), num_frames=12,
        num_frames_estimated=11, frames_not_estimated_names=["000011.png"],
        wall_time_s={"initializer": 2.0}, scale_convention="first-to-last distance = 1")


REPORTS: dict[str, Callable[[], JsonReport]] = {
    "refine": _refine, "dense": _dense, "export": _export, "compare": _compare,
    "plugin init": _plugin_init}


@pytest.mark.parametrize("kind", sorted(REPORTS))
def test_a_report_written_and_read_back_is_the_same(kind: str, tmp_path: Path) -> None:
    report = REPORTS[kind]()
    report.write(tmp_path / "r.json")
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc == json.loads(dumps_json(report.to_json()))  # numpy arrays become lists
    again = type(report).read(tmp_path / "r.json")
    assert again.to_json() == doc
    assert type(report).from_json(doc) == again
    assert list(doc) == list(again.to_json())  # the order written survives the round trip
    again.write(tmp_path / "again.json")  # and the file is the same to the byte
    assert (tmp_path / "again.json").read_bytes() == (tmp_path / "r.json").read_bytes()


def test_refine_report_keys_are_written_in_the_documented_order() -> None:
    doc = _refine(joint_adjustment={"skipped": "no tracks"}, lines3d="adjusted").to_json()
    assert list(doc) == ["input", "camera", "frames", "options", "features", "matching_guided",
                         "matching", "triangulation", "mapper", "joint_adjustment",
                         "bundle_adjustment", "kept_input_for_all", "refined_frames",
                         "kept_frames", "alignment_to_input", "pose_changes", "model",
                         "summary", "lines3d", "carried_from_input", "trajectory_frames",
                         "timings_s"]
    assert doc["kept_input_for_all"] is None  # null is written, not left out
    plain = _refine(matching_guided=None).to_json()
    assert "matching_guided" not in plain and "joint_adjustment" not in plain
    typed = _refine(joint_adjustment={"failed": "singular"})
    assert typed.joint_adjustment is not None and typed.joint_adjustment.failed == "singular"
    assert typed.camera.colmap_model == "OPENCV" and not typed.camera.image_mirrored_for_colmap
    assert typed.pose_changes is not None and typed.pose_changes.rotation_deg_max == 0.1
    assert typed.alignment_to_input is not None and typed.alignment_to_input.scale == 1.0
    assert typed.matching_guided is not None and typed.matching_guided.written == 6


def test_typed_views_of_the_reports() -> None:
    r = _refine()
    assert r.mapper_added == ["000004.png"] and r.joint is None
    assert r.adjustment_rounds[0].mean_reprojection_error_after_px == 0.5
    assert r.model.points == 120 and r.triangulation.frames_posed_again == []
    assert r.features.reused_images == 0 and r.mapper.registered == ["000004.png"]
    assert r.bundle_adjustment.after is not None and r.bundle_adjustment.after.observations == 600
    with pytest.raises(OmniSfmError, match="report: model: no 'images' key"):
        _refine(model={"cameras": 1})
    # keys a section does not name are kept, at their place
    extra = _refine(mapper={"registered": [], "why": "test"}).to_json()["mapper"]
    assert extra == {"registered": [], "why": "test"}
    joint = _refine(bundle_adjustment={"joint": {"line_observations": 3,
                                                 "point_observations": 9, "after": _stats()}})
    assert joint.joint is not None and joint.adjustment_rounds == []
    assert (joint.joint.line_observations, joint.joint.point_observations) == (3, 9)
    assert joint.joint.after is not None and joint.joint.after.points == 120
    e = _export()
    assert e.turned and e.num_images == 24
    assert e.world.how == "parallel family" and "convention" not in e.to_json()["world"]
    assert ExportReport.from_json(e.to_json()).world == e.world
    assert list(e.to_json())[-1] == "seconds" and e.to_json()["num_images"] == 24
    assert _dense().to_json()["input"] == {"poses": "../refined", "images": "frames"}
    assert list(_dense().to_json())[0] == "input"
    d = _dense()
    assert d.scale.factor == 2.0 and d.scale.known_distance == 2.0 and d.scale.other == {}
    assert d.calibration.trials[0].median_disparity_px == 8.0 and d.views.per_pair == 4
    assert d.frames[0].pair_pose is not None and d.frames[0].pair_pose[0].corrected
    assert d.frames[0].view_share is None and "view_share" not in d.to_json()["frames"][0]
    assert d.pair_pose.median_rotation_change_deg == 0.2 and d.backend.pycolmap_cuda is None
    doc = _compare().to_json()["initializers"]
    assert "reason" not in doc["lines"] and doc["five-point"]["reason"] == "too few points"
    assert list(doc["five-point"])[:3] == ["status", "reason", "trajectory"]


def _init_doc(**extra: Any) -> dict[str, Any]:
    return {"omni_sfm_version": "1.0", "initializer": "lines",
            "input": {"images": "frames", "camera": "camera.yaml", "mask": None, "start": 0,
                      "end": None, "step": 1, "timestamps": "frame index"},
            "num_frames": 10, "num_frames_estimated": 9,
            "parallel_family": {"track_ids": [1, 2, 3], "direction": [0.0, 0.0, 1.0]},
            "rejected_tracks": [7], "residuals": {"rms_final_deg": 0.25},
            "world": "first camera", **extra}


def test_init_report_reads_what_its_readers_use(tmp_path: Path) -> None:
    rep = InitReport.from_json(_init_doc())
    assert (rep.num_frames, rep.family_track_ids, rep.rejected_tracks) == (10, [1, 2, 3], [7])
    assert rep.rms_final_deg == 0.25 and not rep.rotation_only and rep.segment_list == []
    assert rep.world == "first camera" and rep.other == {}
    assert InitReport.from_json(_init_doc(note="x")).other == {"note": "x"}  # another writer's
    assert rep.to_json() == _init_doc()
    assert rep.images(tmp_path) == tmp_path / "frames"
    assert rep.parallel_family is not None and rep.parallel_family.direction == [0.0, 0.0, 1.0]
    assert rep.residuals is not None and rep.residuals.rms_initial_deg is None
    turned = InitReport.from_json(_init_doc(motion={"kind": "rotation only"}))
    assert turned.rotation_only and turned.motion is not None
    assert turned.motion.kind == "rotation only" and turned.motion.why is None
    seg = {"file": "segment_1.tum", "frames": [5, 9], "num_frames_estimated": 5, "note": "x"}
    pieces = InitReport.from_json(_init_doc(segments=[seg]))
    assert pieces.segment_list[0].frames == [5, 9] and pieces.segment_list[0].other == {
        "note": "x"}
    assert pieces.to_json()["segments"] == [seg]
    text = summary(turned, tmp_path, ["0", "1"], [], [])
    assert "rotation only" in text and "3 parallel lines, 1 outlier tracks" in text
    assert "first-to-last camera distance = 1" in summary(rep, tmp_path, ["0"], [], [])
    assert "uncertain" not in summary(rep, tmp_path, ["0"], [], [])
    flagged = {str(k): "position not fixed" for k in (0, 1, 2, 5, 7, 8)}
    text = summary(InitReport.from_json(_init_doc(frames_uncertain=flagged)), tmp_path, ["0"],
                   [], [])
    assert "uncertain: 6 frames the data do not fix (frames 0-2, 5, 7-8;" in text
    every = {str(k): "position not fixed" for k in range(10)}
    text = summary(InitReport.from_json(_init_doc(frames_uncertain=every)), tmp_path, ["0"],
                   [], [])
    assert "uncertain: every frame estimated (10): the data fix none of them, do not trust" in text
    with pytest.raises(OmniSfmError, match="no 'num_frames' key"):
        InitReport.from_json({"input": {}}, "init/report.json")
    with pytest.raises(OmniSfmError, match="not a JSON object"):
        RefineReport.from_json([1, 2])


def test_stage_report_finds_frames_and_the_previous_folder(tmp_path: Path) -> None:
    folder = tmp_path / "dense"
    folder.mkdir()
    assert StageFolder(folder).read_stage_report() is None and recorded_images(folder) is None
    _dense().write(folder / StageFolder.REPORT)
    rep = StageFolder(folder).read_stage_report()
    prev = None if rep is None else rep.previous_folder(folder)
    assert prev is not None and prev.resolve() == (tmp_path / "refined").resolve()
    assert recorded_images(folder) == folder / "frames"
    fam = StageReport.from_json(_init_doc())
    assert fam.family_direction == [0.0, 0.0, 1.0] and fam.family_track_ids == [1, 2, 3]


def _stage_files(folder: Path) -> Trajectory:
    folder.mkdir()
    n = 4
    traj = Trajectory(np.arange(n, dtype=float), np.repeat(np.eye(3)[None], n, axis=0),
                      np.c_[np.arange(n, dtype=float), np.zeros(n), np.zeros(n)])
    write_tum(folder / StageFolder.TRAJECTORY, traj)
    write_camera_yaml(folder / StageFolder.CAMERA, EquirectangularCamera(width=64, height=32))
    return traj


def test_folder_loaders_return_typed_artifacts(tmp_path: Path) -> None:
    refined, dense = tmp_path / "refined", tmp_path / "dense"
    traj = _stage_files(refined)
    _refine().write(refined / RefineFolder.REPORT)
    art = RefineFolder(refined).load()
    np.testing.assert_allclose(art.trajectory.positions, traj.positions)
    assert art.camera.model == "equirectangular" and art.lines3d is None
    assert art.report.refined_frames == 4 and art.images == Path("/data/frames")
    assert art.user_mask is None and art.sparse == refined / "sparse"

    _stage_files(dense)
    _dense().write(dense / DenseFolder.REPORT)
    (dense / DenseFolder.POINTS).write_text("ply\n")
    d = DenseFolder(dense).load()
    assert d.report.num_points == 1000 and d.images == dense / "frames"
    assert d.points == dense / DenseFolder.POINTS and d.mesh is None
    assert len(d.trajectory) == len(traj)

    init = tmp_path / "init"
    _stage_files(init)
    (init / InitFolder.REPORT).write_text(json.dumps(_init_doc()))
    i = InitFolder(init).load()
    rep = i.read_report()
    assert rep is not None and rep.num_frames == 10 and i.images == init / "frames"
    assert InitFolder(init).read_report() == rep

    _export().write(tmp_path / "x" / ExportFolder.REPORT)
    assert ExportFolder(tmp_path / "x").read_report() == ExportReport.read(
        tmp_path / "x" / ExportFolder.REPORT)
    _compare().write(tmp_path / "c" / CompareFolder.RESULTS)
    res = CompareFolder(tmp_path / "c").read_results()
    assert res.initializers["lines"].ate_rel == 0.01


def test_any_stage_folder_loads_for_what_they_all_hold(tmp_path: Path) -> None:
    folder = tmp_path / "poses"
    traj = _stage_files(folder)
    art = StageFolder(folder).load_stage()
    assert art.camera is not None and art.camera.model == "equirectangular"
    assert art.report is None and art.images is None and art.lines3d is None
    assert len(art.trajectory) == len(traj)
    (folder / StageFolder.CAMERA).write_text("not: [a camera")
    assert StageFolder(folder).load_stage(camera=False).camera is None  # the caller's own
    _dense().write(folder / StageFolder.REPORT)
    art = DenseFolder(folder).load_stage(camera=False)
    assert art.report is not None and art.images == folder / "frames"
    (folder / StageFolder.TRAJECTORY).unlink()
    with pytest.raises(OmniSfmError, match="trajectory.tum"):
        StageFolder(folder).load_stage()


@pytest.mark.parametrize("loader", [RefineFolder, DenseFolder])
def test_a_loader_without_its_report_is_a_one_line_error(loader: Any, tmp_path: Path) -> None:
    _stage_files(tmp_path / "f")
    with pytest.raises(OmniSfmError, match="report.json"):
        loader(tmp_path / "f").load()


def test_track_frames_read_back_as_written(tmp_path: Path) -> None:
    from omni_sfm.estimate.online import Status, TrackedPose

    start = TrackedPose(0, 0.0, Status.INITIALISING, np.eye(3), np.zeros(3), 5, 0, 1.0)
    poses = [TrackedPose(1, 0.1, Status.TRACKING, np.eye(3), np.array([1.0, 0, 0]), 9, 7,
                         2.5, world=0, start_poses=(start,)),
             TrackedPose(2, 0.2, Status.LOST, None, None, 2, 0, 0.5, reason="too few lines")]
    docs = [p.to_json() for p in poses]
    folder = TrackFolder(tmp_path)
    (tmp_path / TrackFolder.FRAMES).write_text("".join(json.dumps(d) + "\n" for d in docs))
    frames = folder.read_frames()
    assert [f.to_json() for f in frames] == docs
    assert frames[0].has_pose and not frames[1].has_pose and frames[1].reason == "too few lines"
    assert frames[0].start_poses[0].frame == 0 and frames[0].status == "tracking"
    (tmp_path / TrackFolder.FRAMES).write_text(json.dumps(docs[0]) + "\n{\n")
    with pytest.raises(OmniSfmError, match=r"frames.jsonl:2: not JSON"):
        folder.read_frames()


def test_every_report_class_is_a_json_report() -> None:
    for cls in (InitReport, StageReport, RefineReport, DenseReport, ExportReport,
                CompareEntry, CompareResults, PluginInitReport, TrackFrame, TrackPose):
        assert issubclass(cls, JsonReport)


def test_refine_settings_are_the_refine_options() -> None:
    """``options`` of refine's report names every field of ``RefineOptions``, in order."""
    from dataclasses import asdict, fields

    from omni_sfm.refine.pipeline import RefineOptions
    from omni_sfm.reports import RefineSettings

    assert [f.name for f in fields(RefineSettings) if f.name != "other"] == \
        [f.name for f in fields(RefineOptions)]
    doc = asdict(RefineOptions(features="klt"))
    settings = RefineSettings.from_json(doc)
    assert settings.features == "klt" and settings.to_json() == doc and settings.other == {}


def test_undeclared_keys_name_where_another_writer_added_keys() -> None:
    from omni_sfm.reports import InitInput, undeclared_keys

    assert undeclared_keys(_refine()) == [] and undeclared_keys(_dense()) == []
    odd = _refine(mapper={"registered": [], "why": "test"},
                  pose_changes={"rotation_deg_max": 0.1, "large_changes_backed_by_images": {
                      "a.png": {"rotation_deg": 1.0, "position_fraction_of_path": 0.1,
                                "observations": 50, "mean_reprojection_error_px": 0.3,
                                "note": "x"}}})
    assert undeclared_keys(odd) == [
        "mapper.why", "pose_changes.large_changes_backed_by_images.a.png.note"]
    # init's input: the frames' keys, null where not given; of --tracks, the file alone
    assert InitInput(tracks="t.json").to_json() == {"tracks": "t.json"}
    frames = InitInput(images="f", camera="c.yaml", start=0, step=1, timestamps="frame index")
    assert frames.to_json() == {"images": "f", "camera": "c.yaml", "mask": None, "start": 0,
                                "end": None, "step": 1, "timestamps": "frame index"}
