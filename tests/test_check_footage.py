"""``scripts/check_footage.py``: init --lines against COLMAP on the same frames, without ground
truth. On a small rendered 360 walk (the texture-poor corridor, 640x320 H.264, 10 frames), with
the ground truth standing in for COLMAP's poses (``--colmap-from``) so that the agreement it
reports must equal init's own error figures, and with COLMAP itself, which builds no model on
these white walls (the paper's case): the check reports that failure with its reason."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from omni_sfm.evaluate import trajectory_errors
from omni_sfm.poses import Trajectory, read_tum
from omni_sfm.synth.effects import VideoCodec
from omni_sfm.synth.render import RenderOptions

ROOT = Path(__file__).resolve().parents[1]
# the 2:1 walk of tests/test_equirect_input.py (one render per session for both files)
WIDE = RenderOptions(camera="equirectangular", width=640, height=320, frames=10, seed=4,
                     video=True, video_codec=VideoCodec.H264)


def _script():
    spec = importlib.util.spec_from_file_location("check_footage",
                                                  ROOT / "scripts" / "check_footage.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def wide(rendered) -> Path:
    return rendered(WIDE).output


def test_agreement_with_the_truth_as_reference_is_inits_error(wide, tmp_path, capsys):
    check = _script()
    ref = tmp_path / "ref"
    ref.mkdir()
    (ref / "trajectory.tum").write_text((wide / "groundtruth.tum").read_text())
    (ref / "report.json").write_text(json.dumps({"wall_time_s": {"initializer": 1.5}}))
    out = tmp_path / "check"
    assert check.main(["--images", str(wide / "video.mp4"), "--camera", "equirectangular",
                       "--output", str(out), "--colmap-from", str(ref),
                       "--groundtruth", str(wide / "groundtruth.tum")]) == 0
    text = capsys.readouterr().out
    res = json.loads((out / "check.json").read_text())
    li, co, ag = res["lines"], res["colmap"], res["agreement"]
    assert li["status"] == "ok" and li["posed"] == WIDE.frames and co["posed"] == WIDE.frames
    assert co["time_s"] == 1.5 and li["time_s"] > 0
    assert li["uncertain_key"] is None and "n/a (no flags in report.json)" in text
    # the reference is the truth: the agreement is init's error against it
    est = read_tum(out / "init" / "trajectory.tum")
    err = trajectory_errors(est, read_tum(wide / "groundtruth.tum"))
    assert ag["frames_compared"] == WIDE.frames
    assert ag["position_pct_of_path"]["rmse"] == pytest.approx(100 * err.ate_rel, rel=1e-9)
    assert li["groundtruth"]["ate_pct_of_path"] == pytest.approx(100 * err.ate_rel, rel=1e-9)
    # rotation gauge fitted to all frames: never worse than fixing it on the first frame twice
    assert 0 < ag["rotation_deg"]["max"] <= 2 * err.rot_max_deg + 1e-9
    assert len(ag["per_frame"]) == WIDE.frames and ag["worst_rotation"][0]["rotation_deg"] == \
        ag["rotation_deg"]["max"]
    assert ag["per_frame"][0]["name"] == "000000.png"
    assert f"{li['posed']} of {WIDE.frames}" in text and "largest rotation differences" in text


def test_colmap_failure_is_reported_with_its_reason(wide, tmp_path, capsys):
    check = _script()
    out = tmp_path / "check"
    assert check.main(["--images", str(wide / "video.mp4"), "--camera", "equirectangular",
                       "--output", str(out), "--init-arg=--workers=1"]) == 0
    text = capsys.readouterr().out
    res = json.loads((out / "check.json").read_text())
    assert res["lines"]["status"] == "ok" and res["lines"]["posed"] == WIDE.frames
    assert res["colmap"]["status"] == "failed" and "COLMAP" in res["colmap"]["reason"]
    assert "COLMAP failed: " in text and "agreement" not in res


def test_uncertain_flags_and_frame_selection(wide, tmp_path):
    check = _script()
    assert check.uncertain_frames({}) == (None, None, {})
    assert check.uncertain_frames({"frames_uncertain": ["a.png", "b.png"]})[1] == \
        ["a.png", "b.png"]
    key, names, why = check.uncertain_frames(
        {"frames_uncertain": [{"name": "a.png", "reason": "2 lines"}]})
    assert key == "frames_uncertain" and names == ["a.png"] and why == {"a.png": "2 lines"}
    assert check.uncertain_frames({"uncertain_frames": {"c.png": "drift"}})[1] == ["c.png"]
    # the agreement on trusted frames leaves the flagged ones out
    n = 6
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    rots = Rotation.from_rotvec(0.1 * rng.normal(size=(n, 3))).as_matrix()
    ref = Trajectory(np.arange(n, dtype=float), rots, np.c_[np.arange(n), np.zeros((n, 2))])
    bad = rots.copy()
    bad[2] = Rotation.from_rotvec([0, 0, np.radians(5)]).as_matrix() @ bad[2]
    est = Trajectory(ref.timestamps, bad, ref.positions * 0.3)
    names_by_t = {float(k): f"{k:06d}.png" for k in range(n)}
    every = check.agreement(est, ref, names_by_t)
    trusted = check.agreement(est, ref, names_by_t, keep=set(names_by_t.values()) - {
        "000002.png"})
    assert every["worst_rotation"][0]["name"] == "000002.png"
    assert every["rotation_deg"]["max"] > 3 and trusted["rotation_deg"]["max"] < 1e-6
    assert trusted["frames_compared"] == n - 1
    assert trusted["position_pct_of_path"]["max"] < 1e-6
    # --start/--end/--step: the chosen frames as PNGs named by their frame number
    sel = check.frame_selection(wide / "video.mp4", 1, 8, 3, tmp_path / "frames")
    assert sorted(p.name for p in sel.iterdir()) == ["000001.png", "000004.png", "000007.png"]
    assert check.frame_selection(wide / "video.mp4", 0, None, 1, tmp_path / "x") == \
        wide / "video.mp4"


def test_record_row_holds_inits_figures_against_the_truth(wide, tmp_path):
    """``--record`` adds init's figures as one row (its label's), kept beside the others."""
    check = _script()
    logs = tmp_path / "logs"
    for label in ("first", "second"):
        out = tmp_path / label
        assert check.main(["--images", str(wide / "video.mp4"), "--camera", "equirectangular",
                           "--output", str(out), "--no-colmap", "--groundtruth",
                           str(wide / "groundtruth.tum"), "--record", "eval_walks", "--label",
                           label, "--log-dir", str(logs),
                           *(["--init-arg=--estimator=global"] if label == "second" else [])
                           ]) == 0
    rec = json.loads((logs / "eval_walks.json").read_text())
    assert [r[0] for r in rec["rows"]] == ["first", "second"]
    res = json.loads((tmp_path / "second" / "check.json").read_text())
    row = rec["rows"][1]
    assert row[2] == f"{res['lines']['posed']}/{WIDE.frames}"
    t = res["lines"]["groundtruth"]
    assert row[8] == pytest.approx(t["ate_pct_of_path"])
    # how honest the flags are, counted against the truth (the windows flag nothing)
    assert row[4:6] == [t["flagged_but_fine"], t["off_not_flagged"]]
    assert 0 <= t["flagged_but_fine"] <= row[3] and t["off_not_flagged"] >= 0
    assert rec["rows"][0][3:6] == ["n/a", "n/a", "n/a"]
    assert len(rec["row_commands"]) == 2
