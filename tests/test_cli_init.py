"""``omni-sfm init --lines --tracks`` end to end, and bad input: one line, exit 2, no output."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import assert_one_line_error

from omni_sfm.cli import main
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.folders import InitFolder
from omni_sfm.lines.tracks import read_tracks, write_tracks
from omni_sfm.poses import read_tum
from omni_sfm.synth.simulate import SimulationOptions, simulate


def test_simulate_then_init_end_to_end(tmp_path, capsys):
    sim_dir, out = tmp_path / "sim", tmp_path / "out"
    assert main(["simulate", "--output", str(sim_dir), "--views", "12", "--parallel", "5",
                 "--other", "5", "--noise-deg", "0", "--seed", "3"]) == 0
    assert main(["init", "--lines", "--tracks", str(sim_dir / "tracks.json"),
                 "--output", str(out)]) == 0
    est = read_tum(out / "trajectory.tum")
    gt = read_tum(sim_dir / "groundtruth.tum")
    np.testing.assert_array_equal(est.timestamps, np.arange(12.0))
    assert np.abs(est.positions[0]).max() == 0 and abs(np.linalg.norm(est.positions[-1]) - 1) \
        < 1e-9
    err = trajectory_errors(est, gt)
    refl = trajectory_errors(type(est)(est.timestamps, est.rotations, -est.positions), gt)
    assert err.rot_max_deg < 1e-6
    assert min(err.paper_trans.max(), refl.paper_trans.max()) < 1e-6
    assert "estimator: paper (auto: one window covers every frame" in capsys.readouterr().out
    rep = json.loads((out / "report.json").read_text())
    assert rep["num_frames"] == 12 and rep["num_frames_estimated"] == 12
    assert rep["estimator"] == "paper" and rep["estimator_choice"].startswith("auto: ")
    assert rep["num_tracks"] == 10 and rep["frames_not_estimated"] == []
    typed = InitFolder(out).read_report()
    assert typed.to_json() == rep  # every key read back, sections typed
    assert sorted(typed.family_track_ids) == [0, 1, 2, 3, 4]
    assert rep["rejected_tracks"] == [] and "first" in rep["scale_convention"]
    assert {"parallel_lines", "rotation", "translation", "refinement"} <= \
        rep["timings_ms"].keys()
    assert typed.residuals is not None and (typed.residuals.rms_final_deg or 1.0) < 1e-6
    # an existing output is refused without --overwrite, replaced with it
    assert main(["init", "--tracks", str(sim_dir / "tracks.json"), "--output", str(out)]) == 2
    assert_one_line_error(capsys, "--overwrite")
    assert main(["init", "--tracks", str(sim_dir / "tracks.json"), "--output", str(out),
                 "--overwrite"]) == 0


def _tracks_json(sim) -> dict:
    return sim.tracks.to_json_dict()


@pytest.fixture()
def good():
    return simulate(SimulationOptions(num_views=8, num_parallel=4, num_other=4, seed=1))


def _bad_cases(good):
    d = _tracks_json(good)
    cases = {}
    cases["malformed"] = ("{not json", "malformed")
    x = json.loads(json.dumps(d))
    x["tracks"][0]["normals"][0] = [2.0, 0.0, 0.0]
    cases["non_unit"] = (x, "unit")
    x = json.loads(json.dumps(d))
    x["tracks"][1]["normals"][2] = [float("nan"), 0.0, 1.0]
    cases["non_finite"] = (x, "finite")
    x = json.loads(json.dumps(d))
    x["num_frames"] = 2
    for t in x["tracks"]:
        t["frames"], t["normals"] = t["frames"][:2], t["normals"][:2]
        if "rays" in t:
            t["rays"] = t["rays"][:2]
    x.pop("timestamps")
    cases["two_frames"] = (x, "at least 3")
    x = json.loads(json.dumps(d))
    x["tracks"][0]["frames"][-1] = 8
    cases["frame_out_of_range"] = (x, "outside")
    two_par = simulate(SimulationOptions(num_views=20, num_parallel=2, num_other=6, seed=1))
    cases["two_parallel"] = (_tracks_json(two_par), "parallel")
    # every line of one direction: nothing fixes the turn about it
    one = simulate(SimulationOptions(num_views=8, num_parallel=8, num_other=0, seed=1))
    cases["one_direction"] = (_tracks_json(one), "too few frames or lines for the rotations")
    return cases


@pytest.mark.parametrize("case", ["malformed", "non_unit", "non_finite", "two_frames",
                                  "frame_out_of_range", "two_parallel", "one_direction"])
def test_bad_input_one_line_exit_2_no_output(tmp_path, capsys, good, case):
    content, msg = _bad_cases(good)[case]
    path = tmp_path / "tracks.json"
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    out = tmp_path / "out"
    assert main(["init", "--lines", "--tracks", str(path), "--output", str(out)]) == 2
    assert_one_line_error(capsys, msg)
    assert not out.exists()
    assert not any(p.name.startswith(".out") for p in tmp_path.iterdir())


def test_missing_tracks_file(tmp_path, capsys):
    assert main(["init", "--tracks", str(tmp_path / "nope.json"), "--output",
                 str(tmp_path / "o")]) == 2
    assert_one_line_error(capsys, "not found", "nope.json")


def test_write_tracks_round_trip_is_accepted(tmp_path, good):
    """What write_tracks writes reads back as the same tracks, and init on it recovers the
    noise-free simulation's poses."""
    write_tracks(tmp_path / "t.json", good.tracks)
    back = read_tracks(tmp_path / "t.json")
    np.testing.assert_array_equal(back.track_ids, good.tracks.track_ids)
    np.testing.assert_array_equal(back.obs_track, good.tracks.obs_track)
    np.testing.assert_array_equal(back.obs_frame, good.tracks.obs_frame)
    np.testing.assert_allclose(back.obs_normal, good.tracks.obs_normal, rtol=0, atol=1e-15)
    assert main(["init", "--tracks", str(tmp_path / "t.json"), "--output",
                 str(tmp_path / "o")]) == 0
    est = read_tum(tmp_path / "o" / "trajectory.tum")
    assert len(est) == good.tracks.num_frames
    err = trajectory_errors(est, good.groundtruth)
    refl = trajectory_errors(type(est)(est.timestamps, est.rotations, -est.positions),
                             good.groundtruth)
    assert err.rot_max_deg < 1e-6
    assert min(err.paper_trans.max(), refl.paper_trans.max()) < 1e-6
