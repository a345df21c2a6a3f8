"""How stage folders chain: outputs that would destroy their input are refused, paths are
stored so that folders can be moved, bad input to compare is one line and exit 2, and the
summaries say which frames have no pose and which frame is the world."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_every_key_declared, assert_one_line_error

from omni_sfm.cli import main as cli_main
from omni_sfm.cli.cmd_init import summary
from omni_sfm.errors import OmniSfmError
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.export.colmap import read_init_model
from omni_sfm.fileio import check_output_dir, resolve_stored, stored_path
from omni_sfm.folders import recorded_images
from omni_sfm.poses import read_tum
from omni_sfm.reports import FamilyReport, InitReport, InitResiduals, PluginInitReport
from omni_sfm.synth.render import RenderOptions, render_sequence


def test_output_that_is_holds_or_lies_inside_the_input_is_refused(tmp_path: Path) -> None:
    inp = tmp_path / "init"
    inp.mkdir()
    (inp / "tracks.json").write_text("{}")
    for out, words in ((inp, "is the input"), (inp / "sub", "inside the input"),
                       (tmp_path, "holds the input")):
        with pytest.raises(OmniSfmError, match=words):
            check_output_dir(out, overwrite=True, inputs=(inp,))
    check_output_dir(tmp_path / "other", overwrite=True, inputs=(inp, None))


def test_refine_onto_its_own_input_keeps_the_input(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    inp = tmp_path / "init"
    inp.mkdir()
    (inp / "tracks.json").write_text("{}")
    assert cli_main(["refine", "--input", str(inp), "--output", str(inp), "--overwrite"]) == 2
    assert "is the input" in assert_one_line_error(capsys)
    assert (inp / "tracks.json").read_text() == "{}"


def test_stored_paths_are_relative_inside_and_absolute_outside(tmp_path: Path) -> None:
    folder = tmp_path / "out"
    assert stored_path(folder / "frames", folder) == "frames"
    outside = stored_path(tmp_path / "video.mp4", folder)
    assert Path(outside).is_absolute()
    assert resolve_stored("frames", tmp_path / "moved") == tmp_path / "moved" / "frames"
    assert resolve_stored(outside, tmp_path / "moved") == tmp_path / "video.mp4"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("tiny") / "r"
    render_sequence(out, RenderOptions(scene="room", frames=5, width=160, height=120),
                    progress=False)
    return out


def test_compare_with_a_camera_of_another_size_is_exit_2(tiny: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    other = tmp_path / "other"
    render_sequence(other, RenderOptions(scene="room", frames=3, width=200, height=150),
                    progress=False)
    out = tmp_path / "cmp"
    assert cli_main(["compare", "--images", str(tiny / "images"), "--camera",
                     str(other / "camera.yaml"), "--groundtruth", str(tiny / "groundtruth.tum"),
                     "--output", str(out)]) == 2
    err = assert_one_line_error(capsys)
    assert "160x120" in err and "200x150" in err
    assert not out.exists()


def test_init_summary_names_the_world_frame_and_frames_without_a_pose() -> None:
    rep = InitReport(num_frames=20, parallel_family=FamilyReport(track_ids=[1, 2, 3]),
                     rejected_tracks=[], residuals=InitResiduals(rms_final_deg=0.03))
    est = [f"{k:06d}.png" for k in range(12, 20)]
    missing = [f"{k:06d}.png" for k in range(12) if k != 5]
    text = summary(rep, Path("init"), est, missing, ["000005.png"])
    lines = text.splitlines()
    assert lines[0].startswith("init: 8 of 21 frames estimated")
    assert "world: the camera of frame 000012.png" in lines[1]
    assert lines[2].startswith("not estimated: 11 frames (000000.png")
    assert lines[3].startswith("unreadable: 1 frames could not be decoded (000005.png)")


@pytest.fixture(scope="module")
def textured(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("textured") / "r"
    render_sequence(out, RenderOptions(scene="room", textured=True, frames=12, width=400,
                                       height=300), progress=False)
    return out


def test_init_with_an_initializer_plugin_makes_an_init_folder(
        textured: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``init --initializer five-point``: the plugin's poses, normalised like init's, as a
    folder that refine reads (COLMAP model, camera) and that records its frames."""
    out = tmp_path / "init5"
    assert cli_main(["init", "--initializer", "five-point", "--images",
                     str(textured / "images"), "--camera", str(textured / "camera.yaml"),
                     "--output", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "init: 12 of 12 frames estimated by five-point" in printed
    model = read_init_model(out)
    traj = read_tum(out / "trajectory.tum")
    np.testing.assert_allclose(traj.rotations[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(traj.positions[0], 0.0, atol=1e-12)
    assert np.linalg.norm(traj.positions[-1]) == pytest.approx(1.0)
    assert list(model.image_names) == [f"{k:06d}.png" for k in range(12)]
    assert recorded_images(out) == (textured / "images").resolve()
    assert_every_key_declared(PluginInitReport, out / "report.json")
    report = json.loads((out / "report.json").read_text())
    assert report["initializer"] == "five-point" and report["num_frames_estimated"] == 12
    # the poses are the plugin's: the same frames against the truth as compare measures them
    errs = trajectory_errors(traj, read_tum(textured / "groundtruth.tum"))
    assert errs.rot_max_deg < 1.0


def test_init_with_an_unknown_or_misused_initializer_is_exit_2(
        textured: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    common = ["--images", str(textured / "images"), "--camera", str(textured / "camera.yaml")]
    assert cli_main(["init", "--initializer", "nope", *common, "--output",
                     str(tmp_path / "a")]) == 2
    assert "unknown initializer 'nope'" in assert_one_line_error(capsys)
    assert cli_main(["init", "--initializer", "five-point", *common, "--no-refine",
                     "--output", str(tmp_path / "b")]) == 2
    assert "--no-refine applies to the line-based method" in assert_one_line_error(capsys)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_init_folder_load_reads_every_artifact_typed(tmp_path: Path) -> None:
    """``InitFolder.load``: the camera, poses, 3D lines, recorded frames and user's mask as
    written, the tracks on demand; a folder without the optional files gives None for them,
    and one without its poses a one-line error."""
    from omni_sfm.cameras import write_camera_yaml
    from omni_sfm.folders import InitFolder
    from omni_sfm.frames import write_mask
    from omni_sfm.lines.tracks import write_tracks
    from omni_sfm.lines3d import LineSegments3D, write_lines3d
    from omni_sfm.poses import write_tum
    from omni_sfm.synth.render import hyperboloid_camera
    from omni_sfm.synth.simulate import SimulationOptions, simulate

    sim = simulate(SimulationOptions(num_views=6, num_parallel=3, num_other=3, seed=2))
    cam = hyperboloid_camera(160, 120)
    bare, full = tmp_path / "bare", tmp_path / "full"
    for d in (bare, full):
        d.mkdir()
        write_camera_yaml(d / "camera.yaml", cam)
        write_tum(d / "trajectory.tum", sim.groundtruth)
    lines = LineSegments3D(sim.line_points, sim.line_points + sim.line_directions,
                           np.zeros(len(sim.line_points), int), sim.line_directions[:1],
                           ("estimated",) * len(sim.line_points),
                           track_ids=np.arange(len(sim.line_points)))
    write_lines3d(full / "lines3d.json", lines)
    write_tracks(full / "tracks.json", sim.tracks)
    mask = np.ones((cam.height, cam.width), bool)
    write_mask(full / "mask.png", mask)
    (tmp_path / "frames").mkdir()
    (full / "report.json").write_text(json.dumps({"input": {"images": str(tmp_path / "frames")}}))

    art = InitFolder(full).load()
    assert art.camera == cam and art.folder == InitFolder(full)
    np.testing.assert_allclose(art.trajectory.positions, sim.groundtruth.positions, atol=1e-9)
    assert art.lines3d is not None
    np.testing.assert_allclose(art.lines3d.starts, lines.starts, atol=1e-9)
    assert art.images == tmp_path / "frames" and art.user_mask == full / "mask.png"
    tracks = art.read_tracks()
    assert tracks is not None
    np.testing.assert_array_equal(tracks.obs_frame, sim.tracks.obs_frame)

    empty = InitFolder(bare).load()
    assert empty.lines3d is None and empty.images is None and empty.user_mask is None
    assert empty.read_tracks() is None
    (bare / "trajectory.tum").unlink()
    with pytest.raises(OmniSfmError, match="trajectory.tum"):
        InitFolder(bare).load()
