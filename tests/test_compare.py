"""``omni-sfm compare`` and the sweep: results.json is what the written trajectories give
(recomputed here from the TUM files with numpy, independently of omni_sfm.evaluate), failures
are kept with their reasons, bad input is one line and exit code 2, and the sweep gives the same
results on a Dask cluster as on the local process pool."""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import (
    assert_every_key_declared,
    assert_one_line_error,
    independent_trajectory_errors,
)

from omni_sfm.cli import main
from omni_sfm.compare import compare, evaluate_trajectory, recompute_results
from omni_sfm.poses import Trajectory, read_tum, write_tum
from omni_sfm.reports import CompareResults
from omni_sfm.synth.render import RenderOptions

ROOT = Path(__file__).resolve().parents[1]
KEYS = {"status", "trajectory", "registered", "rot_max_deg", "rot_mean_deg", "ate_rel", "rpe",
        "rpe_rot_deg", "step_error_after_alignment", "time_s"}

sys.path.insert(0, str(Path(__file__).parent))
from test_initializers import simulated  # noqa: E402

FIGURES = ("registered", "rot_max_deg", "rot_mean_deg", "ate_rel", "rpe", "rpe_rot_deg",
           "step_error_after_alignment")


def check_results_match_trajectories(out: Path, gt_tum: Path, num_frames: int) -> dict:
    """Every figure of results.json equals its recomputation from the TUM files: by
    ``recompute_results`` (what ``compare`` uses) and, independently, by numpy from the
    definitions (tests/helpers.py); a failure has a reason and no figures."""
    assert_every_key_declared(CompareResults, out / "results.json")
    res = json.loads((out / "results.json").read_text())
    again = recompute_results(out, read_tum(gt_tum), num_frames)
    for name, e in res["initializers"].items():
        assert set(e) >= KEYS, (name, sorted(e))
        assert e["status"] in ("ok", "failed")
        if e["status"] == "failed":
            assert e.get("reason"), f"{name} failed without a reason"
            assert e["trajectory"] is None and e["rot_max_deg"] is None, (name, e)
            assert name not in again
        if e["status"] == "ok":
            assert (out / e["trajectory"]).is_file()
            hand = independent_trajectory_errors(out / e["trajectory"], gt_tum, num_frames)
            for k in FIGURES:
                assert e[k] == pytest.approx(again[name][k], rel=1e-9, abs=1e-12), (name, k)
                assert e[k] == pytest.approx(hand[k], rel=1e-9, abs=1e-9), (name, k, hand[k])
    assert set(again) == {n for n, e in res["initializers"].items() if e["status"] == "ok"}
    return res


def test_compare_simulation_results_recomputed(tmp_path: Path) -> None:
    seq, gt = simulated(noise_deg=0.1)
    write_tum(tmp_path / "gt.tum", gt)
    thr = {"max_error_rad": 3 * np.radians(0.1)}
    out = tmp_path / "cmp"
    r = compare(seq, gt, out, ["lines", "five-point"], options={"five-point": thr})
    res = check_results_match_trajectories(out, tmp_path / "gt.tum", seq.num_frames)
    assert set(res["initializers"]) == {"lines", "five-point"}
    assert all(e["status"] == "ok" for e in res["initializers"].values())
    assert r.results.to_json() == res
    report = (out / "report.md").read_text()
    for name in res["initializers"]:
        assert f"| {name} | ok |" in report
    for png in ("trajectories.png", "errors.png"):
        img = cv2.imread(str(out / png))
        assert img is not None and img.shape[0] > 100
    # a hand-edited figure would no longer match its trajectory
    e = res["initializers"]["lines"]
    tum = read_tum(out / e["trajectory"])
    moved = Trajectory(tum.timestamps, tum.rotations,
                       tum.positions + np.linspace(0, 0.2, len(tum))[:, None])
    write_tum(out / e["trajectory"], moved)
    assert recompute_results(out, gt, seq.num_frames)["lines"]["ate_rel"] != \
        pytest.approx(e["ate_rel"], rel=1e-6)
    assert independent_trajectory_errors(out / e["trajectory"], tmp_path / "gt.tum",
                                         seq.num_frames)["ate_rel"] != \
        pytest.approx(e["ate_rel"], rel=1e-6)


def test_failure_kept_with_reason(tmp_path: Path) -> None:
    seq, gt = simulated(num_points=8)
    write_tum(tmp_path / "gt.tum", gt)
    compare(seq, gt, tmp_path / "cmp", ["lines", "five-point"], plots=False)
    res = check_results_match_trajectories(tmp_path / "cmp", tmp_path / "gt.tum", seq.num_frames)
    fp = res["initializers"]["five-point"]
    assert fp["status"] == "failed" and fp["trajectory"] is None and fp["registered"] == 0
    assert "correspondences" in fp["reason"] or "points" in fp["reason"]
    assert res["initializers"]["lines"]["status"] == "ok"
    assert "| five-point | failed |" in (tmp_path / "cmp" / "report.md").read_text()


@pytest.fixture(scope="module")
def tiny(rendered):
    """A tiny rendered textured corridor (paper's camera, 400 x 300, 10 frames; read-only)."""
    return rendered(RenderOptions(scene="corridor", camera="hyperboloid", frames=10, width=400,
                                  height=300, textured=True, seed=4))


def test_cli_every_initializer_on_rendered_sequence(tiny, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    d = tiny.output
    out = tmp_path / "cmp"
    rc = main(["compare", "--images", str(d / "images"), "--camera", str(d / "camera.yaml"),
               "--groundtruth", str(d / "groundtruth.tum"), "--output", str(out)])
    assert rc == 0
    res = check_results_match_trajectories(out, d / "groundtruth.tum", 10)
    inits = res["initializers"]
    assert set(inits) == {"lines", "five-point", "colmap", "upright-3pt"}
    # point features abound here: the point-based standards work, on every frame, near the
    # truth; at this size the texture leaves the line front end 4 tracks (docs/comparison.md,
    # the texture axis), too few for the line-based methods, which fail and say so
    assert {n: e["status"] for n, e in inits.items()} == {
        "lines": "failed", "five-point": "ok", "colmap": "ok", "upright-3pt": "failed"}
    for name in ("five-point", "colmap"):
        e = inits[name]
        assert e["registered"] == 1.0, (name, e)
        assert np.isfinite(e["rot_max_deg"]) and np.isfinite(e["ate_rel"]), (name, e)
    e = inits["five-point"]
    assert e["rot_max_deg"] < 2.0 and e["ate_rel"] < 0.05, e
    # COLMAP's incremental mapper on these 10 small frames follows its RANSAC's last bits (seed
    # 0: 45.5 deg at the last frame on an Intel Xeon, under 2 deg on an AMD EPYC; seeds 1-3 on
    # the Xeon: 0.07 deg): of this run (seed 0) and seeds 1 and 2, two or more are near the
    # truth (a camera, image or pose hand-off gone wrong would put every seed off)
    from omni_sfm.cameras import load_camera
    from omni_sfm.plugin_contract import run_initializer, sequence_from_frames

    seq = sequence_from_frames(d / "images", load_camera(d / "camera.yaml"))
    gt = read_tum(d / "groundtruth.tum")
    near = [inits["colmap"]["rot_max_deg"] < 2.0 and inits["colmap"]["ate_rel"] < 0.05]
    for seed in (1, 2):
        res, _ = run_initializer("colmap", seq, {"seed": seed})
        assert res.trajectory is not None, res
        m = evaluate_trajectory(res.trajectory, gt, 10).metrics
        near.append(m["rot_max_deg"] < 2.0 and m["ate_rel"] < 0.05)
    assert sum(near) >= 2, near
    assert "need at least 6" in inits["lines"]["reason"]
    assert "no vanishing direction" in inits["upright-3pt"]["reason"]
    printed = capsys.readouterr().out
    for name in inits:
        assert name in printed
    # refuses to overwrite without --overwrite
    rc = main(["compare", "--images", str(d / "images"), "--camera", str(d / "camera.yaml"),
               "--groundtruth", str(d / "groundtruth.tum"), "--output", str(out),
               "--initializers", "lines"])
    assert rc == 2


def _one_line_error(capsys: pytest.CaptureFixture[str], argv: list[str], *needles: str) -> None:
    assert main(argv) == 2
    assert_one_line_error(capsys, *needles)


def test_bad_input_exit_2(tiny, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = tiny.output
    gt = read_tum(d / "groundtruth.tum")
    shifted = tmp_path / "shifted.tum"
    write_tum(shifted, Trajectory(gt.timestamps + 1000.5, gt.rotations, gt.positions))
    base = ["compare", "--images", str(d / "images"), "--camera", str(d / "camera.yaml"),
            "--groundtruth", str(d / "groundtruth.tum")]
    _one_line_error(capsys, [*base[:-1], str(shifted), "-o", str(tmp_path / "a")],
                    "no timestamp matches a frame")
    _one_line_error(capsys, [*base, "-o", str(tmp_path / "b"), "--initializers",
                             "lines,sift-magic"], "unknown initializer 'sift-magic'", "five-point")
    bad_cam = tmp_path / "camera.yaml"
    bad_cam.write_text("model: hyperboloid\nwidth: 400\n")
    _one_line_error(capsys, ["compare", "--images", str(d / "images"), "--camera", str(bad_cam),
                             "--groundtruth", str(d / "groundtruth.tum"),
                             "-o", str(tmp_path / "c")], str(bad_cam))
    for name in "abc":
        assert not (tmp_path / name).exists()


def _sweep_module():
    # scripts/ is a package at the repository root (run as ``python -m scripts.compare.init``)
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    return importlib.import_module("scripts.compare.init")


def test_sweep_dask_equals_process_pool() -> None:
    import distributed  # installed by the set-up (the 'compare' extra): a missing one must fail
    sweep = _sweep_module()
    tasks = sweep.make_tasks(["sim"], [0, 1], [0.16], 10, 40, ["five-point", "colmap"])
    local = sweep.run_all(tasks, None, 1)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        remote = sweep.run_all(tasks, cluster.scheduler_address, 1)
    assert [r["task"] for r in local] == tasks == [r["task"] for r in remote]
    for a, b in zip(local, remote, strict=True):
        assert sweep.comparable(a["results"]) == sweep.comparable(b["results"])
        assert a["tum"] == b["tum"]
        assert all(e["status"] == "ok" for e in a["results"]["initializers"].values())


def test_five_point_with_klt_tracks(tiny) -> None:
    from omni_sfm.compare import run_initializer, sequence_from_frames

    seq = sequence_from_frames(tiny.output / "images", tiny.camera)
    res, _ = run_initializer("five-point", seq, {"features": "klt"})
    assert res.status == "ok", res.reason
    assert res.info["features"] == "klt"
    assert res.trajectory is not None
    ev = evaluate_trajectory(res.trajectory, read_tum(tiny.output / "groundtruth.tum"), 10)
    assert ev.metrics["rot_max_deg"] < 2.0 and ev.metrics["ate_rel"] < 0.05, ev.metrics
