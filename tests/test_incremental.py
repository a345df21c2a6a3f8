"""Incremental registration beyond the windows (omni_sfm/estimate/incremental.py): frames posed
from lines already reconstructed, through stops and turns in place."""

from __future__ import annotations

import re
from dataclasses import replace
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import WINDOWS, assert_every_key_declared

from omni_sfm.cli import main
from omni_sfm.estimate.bundle import resect_pose
from omni_sfm.estimate.incremental import centre_given_rotation, rotation_from_directions
from omni_sfm.estimate.pipeline import (
    EstimationOptions,
    estimate_poses,
    write_init_outputs,
)
from omni_sfm.evaluate import match_reflection, trajectory_errors
from omni_sfm.geometry import line_plane_normals, normalize, rotvec_to_matrix
from omni_sfm.lines.tracks import LineTracks, make_tracks, write_tracks
from omni_sfm.poses import Trajectory, read_tum
from omni_sfm.reports import InitReport
from omni_sfm.synth.paths import PathOptions, Route, camera_path
from omni_sfm.synth.scenes import SceneName, make_scene
from omni_sfm.synth.simulate import Simulation, SimulationOptions, simulate


def _observe(gt: Trajectory, starts: np.ndarray, ends: np.ndarray, noise_deg: float,
             max_range: float, seed: int) -> LineTracks:
    """Each true segment's line as a track in the frames that see its middle within
    ``max_range`` and under an angle of 5 deg or more, with Gaussian noise on the normals."""
    rng = np.random.default_rng(seed)
    mid, d = (starts + ends) / 2.0, normalize(ends - starts)
    c = gt.positions
    dist = np.linalg.norm(mid[:, None, :] - c[None], axis=2)  # (L, F)
    a = normalize(starts[:, None, :] - c[None])
    b = normalize(ends[:, None, :] - c[None])
    span = np.degrees(np.arccos(np.clip(np.sum(a * b, 2), -1, 1)))
    seen = (dist < max_range) & (span > 5.0)
    m, f = np.nonzero(seen)
    n_w = normalize(line_plane_normals(c[f], mid[m], d[m]))
    n = np.einsum("kji,kj->ki", gt.rotations[f], n_w)
    ax = normalize(np.cross(n, rng.normal(size=n.shape)))
    ang = np.radians(noise_deg) * rng.normal(size=(len(n), 1))
    n = n * np.cos(ang) + np.cross(ax, n) * np.sin(ang)
    return make_tracks(len(gt), np.arange(len(starts)), m, f, n, source="test")


@lru_cache(maxsize=1)
def _stop_and_go() -> tuple[LineTracks, Trajectory]:
    scene = make_scene(SceneName.OFFICE)
    gt = camera_path(scene, PathOptions(num_frames=120, route=Route.STOP_AND_GO))
    segs = scene.lines
    return _observe(gt, segs.starts, segs.ends, 0.05, 5.0, 0), gt


def test_stop_and_go_is_one_trajectory() -> None:
    # drive, stop, turn 90 deg in place, drive on: one trajectory in one world and scale
    tracks, gt = _stop_and_go()
    step = np.linalg.norm(np.diff(gt.positions, axis=0), axis=1)
    assert (step < 1e-9).sum() >= 20  # the stop is in the data
    res = estimate_poses(tracks)
    assert res.estimated.all()
    err = trajectory_errors(res.trajectory, gt)
    assert err.rot_max_deg < 0.5 and err.ate_rel < 0.01
    # the stopped frames stay together (the estimate's path length is 1 from first to last)
    pos = res.trajectory.positions[1:][step < 1e-9]
    assert np.ptp(pos, axis=0).max() < 0.01


def test_resection_from_known_lines_is_exact() -> None:
    rng = np.random.default_rng(3)
    d = normalize(rng.normal(size=(8, 3)))
    p = rng.normal(size=(8, 3)) * 3
    R = rotvec_to_matrix(np.array([0.2, -0.4, 0.9]))
    c = np.array([0.3, -0.2, 0.5])
    n = normalize(line_plane_normals(c[None], p, d)) @ R  # camera frame
    n *= rng.choice([-1.0, 1.0], size=(8, 1))
    # from a start 10 deg and 0.3 away
    R0 = R @ rotvec_to_matrix(np.radians([6.0, -5.0, 6.0]))
    R1 = rotation_from_directions(n, d, R0)
    assert np.allclose(R1, R, atol=1e-9)
    c1 = centre_given_rotation(n, d, p, R1)
    assert c1 is not None and np.allclose(c1, c, atol=1e-9)
    R2, c2, ang = resect_pose(n, d, p, R0, c + 0.3, scale=np.inf)
    assert np.allclose(R2, R, atol=1e-9) and np.allclose(c2, c, atol=1e-9)
    assert ang.max() < 1e-9
    # lines of one direction leave the centre along it free
    d1 = np.repeat(d[:1], 4, 0)
    n1 = normalize(line_plane_normals(c[None], p[:4], d1)) @ R
    assert centre_given_rotation(n1, d1, p[:4], R) is None


def test_reasons_name_every_frame_not_registered() -> None:
    tracks, gt = _stop_and_go()
    # cut every line out of the last 15 frames but 2: nothing can pose them
    last = tracks.obs_frame >= len(gt) - 15
    keep = ~last | (tracks.obs_track < 2)
    t2 = tracks.keep_observations(keep)
    res = estimate_poses(t2, WINDOWS)
    assert res.estimated[:len(gt) - 15].all() and not res.estimated[len(gt) - 15:].any()
    reasons = (res.report.frames_not_estimated_reasons or {})
    assert sorted(map(int, reasons)) == list(range(len(gt) - 15, len(gt)))
    assert "lines already reconstructed" in reasons[str(len(gt) - 15)]


def _two_walks() -> tuple[LineTracks, Trajectory, Trajectory]:
    """Two simulated walks one after the other (frames 0-49, 50-89), no line in common."""
    a = simulate(SimulationOptions(num_views=50, num_parallel=10, num_other=10, noise_deg=0.05,
                                   seed=1))
    b = simulate(SimulationOptions(num_views=40, num_parallel=10, num_other=10, noise_deg=0.05,
                                   seed=2))
    ta, tb = a.tracks, b.tracks
    tracks = make_tracks(90, np.arange(ta.num_tracks + tb.num_tracks),
                         np.concatenate([ta.obs_track, tb.obs_track + ta.num_tracks]),
                         np.concatenate([ta.obs_frame, tb.obs_frame + 50]),
                         np.concatenate([ta.obs_normal, tb.obs_normal]), source="test")
    return tracks, a.groundtruth, b.groundtruth


def test_a_gap_gives_a_separate_segment(tmp_path: Path) -> None:
    # two walks with no line in common: the second is estimated again from scratch, in its own
    # world and scale, written beside the main trajectory and listed in the report
    tracks, gt_a, gt_b = _two_walks()
    res = estimate_poses(tracks)
    assert res.estimated[:50].all() and not res.estimated[50:].any()
    assert trajectory_errors(res.trajectory, gt_a).rot_max_deg < 0.2
    (seg,) = res.segments
    assert seg.number == 1 and seg.frames[50:].all() and not seg.frames[:50].any()
    tr = seg.trajectory
    err = trajectory_errors(Trajectory(tr.timestamps - 50, tr.rotations, tr.positions),
                            gt_b)
    assert err.rot_max_deg < 0.2 and err.ate_rel < 0.01
    assert res.report.segment_list[0].frames == [50, 89]
    assert "segment 1" in (res.report.frames_not_estimated_reasons or {})["60"]
    (start,) = [a for a in (res.report.attempts or []) if a.strategy == "new start"]
    assert start.frames == [50, 89] and start.result == "kept"
    assert start.why == "40 frames estimated"
    (join,) = [a for a in (res.report.attempts or []) if a.strategy == "join"]
    assert join.result == "failed" and "lines reconstructed in both" in join.why
    # the new start's own windows are recorded too, in the frames of the whole sequence
    assert any(a.strategy == "paper window" and a.frames[0] >= 50
               for a in (res.report.attempts or []))
    # no new start where none is allowed (by default as many as the stretches left need)
    capped = estimate_poses(tracks, EstimationOptions(max_segments=0))
    assert not capped.segments and not capped.estimated[50:].any()
    written = write_init_outputs(tmp_path, res)
    assert_every_key_declared(InitReport, tmp_path / "report.json")
    assert tmp_path / "trajectory_segment_1.tum" in written
    assert len(read_tum(tmp_path / "trajectory_segment_1.tum")) == 40
    assert len(read_tum(tmp_path / "trajectory.tum")) == 50


def test_init_names_the_segments(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    tracks, _, _ = _two_walks()
    write_tracks(tmp_path / "tracks.json", tracks)
    assert main(["init", "--lines", "--tracks", str(tmp_path / "tracks.json"), "--output",
                 str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "init: 50 of 90 frames estimated" in out
    assert "segments: 40 more frames in 1 separate piece" in out
    assert "trajectory_segment_1.tum" in out and "not estimated" not in out
    assert (tmp_path / "out" / "trajectory_segment_1.tum").is_file()


def test_a_walk_along_the_largest_family_uses_another_one() -> None:
    # 14 lines along the corridor, the way the camera walks (the largest family: the paper's
    # in-plane translation is degenerate), 9 vertical and 7 cross lines: the window is solved
    # with the vertical family instead, and the report says so
    rng = np.random.default_rng(0)
    F = 40
    along, up, cross = np.eye(3)[0], np.eye(3)[2], np.eye(3)[1]
    s = np.linspace(0, 1, F)
    pos = s[:, None] * along * 3.0
    R = rotvec_to_matrix(np.stack([0.05 * np.sin(3 * s), 0.04 * np.cos(2 * s),
                                   0.3 * np.sin(2 * s)], 1))
    gt = Trajectory(np.arange(F, dtype=float), R, pos)
    dirs = np.array([along] * 14 + [up] * 9 + [cross] * 7)
    pts = rng.uniform(-2, 2, size=(len(dirs), 3))
    pts[:, 0] = rng.uniform(0, 3, len(dirs))
    pts[:, 1] += np.sign(pts[:, 1]) * 0.8
    m, f = (a.ravel() for a in np.meshgrid(np.arange(len(dirs)), np.arange(F), indexing="ij"))
    n = np.einsum("kji,kj->ki", R[f], normalize(line_plane_normals(pos[f], pts[m], dirs[m])))
    ang = np.radians(0.05) * rng.normal(size=(len(n), 1))
    n = n * np.cos(ang) + np.cross(normalize(np.cross(n, rng.normal(size=n.shape))), n) * \
        np.sin(ang)
    res = estimate_poses(make_tracks(F, np.arange(len(dirs)), m, f, n, source="test"), WINDOWS)
    assert res.estimated.all()
    fam = res.report.parallel_families
    assert fam is not None and fam.sizes == [14, 9, 7]
    assert len(fam.windows_with_another_family) == 1
    # every attempt is in the report: the paper's method failed with the largest family, the
    # vertical family (the second) gave the window, the adjustment of the chain was kept
    tried = [(a.strategy, a.result) for a in (res.report.attempts or [])]
    assert tried[:2] == [("paper window", "failed"), ("paper window, another family", "kept")]
    assert ("bundle adjustment", "kept") in tried
    first, second = (res.report.attempts or [])[:2]
    assert "degenerate motion" in first.why and second.why.startswith("family 2")
    assert second.frames == [0, F - 1] and 0 < second.cost_rms_deg < 1.0
    err = trajectory_errors(match_reflection(res.trajectory, gt), gt)
    assert err.rot_max_deg < 0.2 and err.ate_rel < 0.005


def test_an_adjustment_stopped_short_is_adjusted_again_from_its_result() -> None:
    # the strategy "adjustment from its own result": from an adjustment that stopped short
    # (one iteration from poses 1 deg and 2 cm off) it adjusts again and keeps the result,
    # which lowers the cost on all tracks; from that converged result it changes nothing
    from omni_sfm.estimate.attempts import RunLog
    from omni_sfm.estimate.bundle import BundleOptions, bundle_adjust
    from omni_sfm.estimate.pipeline import _readjusted

    sim = simulate(SimulationOptions(num_views=30, num_parallel=10, num_other=10,
                                     noise_deg=0.1, seed=5))
    g = sim.groundtruth
    rng = np.random.default_rng(0)
    R = g.rotations @ np.stack([rotvec_to_matrix(v) for v in
                                rng.normal(scale=np.radians(1.0) / np.sqrt(3), size=(30, 3))])
    c = g.positions + rng.normal(scale=0.02, size=(30, 3))
    nan = np.full((sim.tracks.num_tracks, 3), np.nan)
    short = bundle_adjust(sim.tracks, R, c, nan, nan,
                          options=BundleOptions(max_rounds=1, robust_iterations=1,
                                                final_loss=None))
    run = RunLog()
    again = _readjusted(sim.tracks, short, EstimationOptions(), run)
    kept = [a for a in run.entries if a.result == "kept"]
    assert kept and all(a.strategy == "adjustment from its own result" for a in run.entries)
    assert again.rms_final_deg < short.rms_final_deg
    # where the whole adjustment from the same start ends
    full = bundle_adjust(sim.tracks, R, c, nan, nan)
    errors = [trajectory_errors(Trajectory(g.timestamps, b.rotations, b.positions), g)
              for b in (short, again, full)]
    assert errors[1].rot_mean_deg < errors[0].rot_mean_deg
    assert errors[1].rot_mean_deg <= 1.01 * errors[2].rot_mean_deg
    run = RunLog()
    assert _readjusted(sim.tracks, again, EstimationOptions(), run) is again
    assert [a.result for a in run.entries] == ["rejected"]


def test_a_short_run_turned_by_a_half_turn_is_turned_back() -> None:
    # the exact solution of a simulated walk with frames 20-22 turned by 180 deg about the
    # vertical (as a window's solution can come out where the view fits both): the repair
    # turns them back from their lines, and only them
    from omni_sfm.estimate.attempts import RunLog
    from omni_sfm.estimate.pipeline import _Init, _repair_half_turns, _Solved
    from omni_sfm.geometry import rotation_angle

    sim = simulate(SimulationOptions(num_views=40, num_parallel=10, num_other=10, seed=3))
    g, F, M = sim.groundtruth, 40, sim.tracks.num_tracks
    R = g.rotations.copy()
    half = rotvec_to_matrix(np.array([0.0, 0.0, np.pi]))
    R[20:23] = R[20:23] @ half
    frames = np.ones(F, bool)
    init = _Init(R, g.positions, frames, [], [], sim.parallel, np.zeros((F, 3)))
    sol = _Solved(init, R, g.positions.copy(), frames, sim.line_directions.copy(),
                  sim.line_points.copy(), np.ones(M, bool), np.zeros(M, bool), 0.0, 0.0, 0.0)
    run = RunLog()
    fixed = _repair_half_turns(sim.tracks, sol, EstimationOptions(), run)
    assert fixed.init.repairs == 3
    err = np.degrees(rotation_angle(np.einsum("fji,fjk->fik", fixed.R, g.rotations)))
    assert err.max() < 1e-3
    repair, adjust = run.entries[0], run.entries[-1]
    assert repair.strategy == "half-turn repair" and repair.frames == [20, 22]
    assert repair.result == "kept" and repair.why == "3 of 3 frames turned back"
    assert adjust.strategy == "bundle adjustment of a piece"
    # nothing to repair: nothing changes, nothing is tried
    exact = _Solved(replace(init, repairs=0), g.rotations, g.positions, frames,
                    sim.line_directions, sim.line_points, np.ones(M, bool), np.zeros(M, bool),
                    0.0, 0.0, 0.0)
    run = RunLog()
    assert _repair_half_turns(sim.tracks, exact, EstimationOptions(), run).init.repairs == 0
    assert run.entries == []


@pytest.mark.slow
@pytest.mark.parametrize(("seed", "strategy", "how"), [
    # the chain of windows over all 600 frames drifts; the chain on the last frames,
    # registered backwards, scores 1.4 % below the first start (before the embedded line
    # iterations the second start, on the first 100 frames, was kept)
    (2, "reversed start", "kept"),
    # the default (auto) takes the global estimator: no window covers the sequence
    (3, None, None),
    # the registration of the second start stops at frame 532 (it sees too few known lines);
    # the new start on frames 532-599 shares too few lines with the main piece to be joined
    # by them (1.2 deg apart), but grown backwards by its own lines it poses 29 of the main
    # piece's frames, whose poses join the two (before: 532 frames and a segment of 68)
    (4, "join", "frames in common"),
])
def test_sparse_tracks_reach_the_oracle(seed: int, strategy: str | None,
                                       how: str | None) -> None:
    """The every-frame issue's sparse case (600 frames, 4-13 lines a frame, each seen for about
    60 frames, 0.1 deg noise; no line seen throughout, so more than one window): every frame in
    one trajectory, rotation and translation errors within 2x of the maximum-likelihood
    oracle's: the windows estimator through the strategy named (kept, its ``why`` saying how
    where given), or without one the default, which takes the global estimator."""
    from omni_sfm.estimate.bundle import oracle

    sim = simulate(SimulationOptions(num_views=600, num_parallel=40, num_other=40,
                                     noise_deg=0.1, visible_frames=60, seed=seed))
    g = sim.groundtruth
    assert not sim.tracks.visibility().all(1).any()  # no line is seen throughout
    if strategy is None:
        res = estimate_poses(sim.tracks)
        assert res.report.estimator == "global" and res.estimated.all()
    else:
        res = estimate_poses(sim.tracks, WINDOWS)
        assert res.estimated.all() and not res.segments and len(res.windows) > 1
    e = trajectory_errors(match_reflection(res.trajectory, g), g)
    o = oracle(sim.tracks, g.rotations, g.positions, sim.line_directions, sim.line_points)
    eo = trajectory_errors(Trajectory(g.timestamps[o.frames], o.rotations[o.frames],
                                      o.positions[o.frames]), g)
    assert e.rot_mean_deg <= 2.0 * eo.rot_mean_deg
    assert e.paper_trans.mean() <= 2.0 * eo.paper_trans.mean()
    assert strategy is None or any(
        a.result == "kept" and (how == "kept" or str(how) in (a.why or ""))
        for a in (res.report.attempts or []) if a.strategy == strategy)


@pytest.mark.slow
def test_a_chain_that_ends_wrong_is_started_again_from_the_end() -> None:
    """The sparse case's seed 13, its last 300 frames: every start from the first frames
    scores 0.087-0.093 deg (capped RMS over every observation; on all 600 frames they were
    2.7x / 12.8x the oracle's errors); run on the frames in reverse order, the chain of windows
    and the registration score 0.078 and reach the oracle's errors, and that start is kept
    (or ties with a forward start that later strategies repaired as far)."""
    from omni_sfm.estimate.bundle import oracle
    from omni_sfm.estimate.segments import frame_range

    sim = simulate(SimulationOptions(num_views=600, num_parallel=40, num_other=40,
                                     noise_deg=0.1, visible_frames=60, seed=13))
    tracks, idx = frame_range(sim.tracks, 300, 600)
    g = sim.groundtruth.subset(np.arange(300, 600))
    res = estimate_poses(tracks, WINDOWS)
    assert res.estimated.all() and not res.segments
    e = trajectory_errors(match_reflection(res.trajectory, g), g)
    o = oracle(tracks, g.rotations, g.positions, sim.line_directions[idx], sim.line_points[idx])
    eo = trajectory_errors(Trajectory(g.timestamps[o.frames], o.rotations[o.frames],
                                      o.positions[o.frames]), g)
    assert e.rot_mean_deg <= 2.0 * eo.rot_mean_deg
    assert e.paper_trans.mean() <= 2.0 * eo.paper_trans.mean()
    # the reversed start reaches the best score over all frames: kept, or tied with the
    # forward start as repaired by the later strategies (numpy 2.4 / scipy 1.17: "lines off
    # the cameras" polished it to the same 0.0755 deg)
    attempts = (res.report.attempts or [])
    rev = [a for a in attempts if a.strategy == "reversed start"]
    assert len(rev) == 1 and rev[0].frames == [0, 299]
    if rev[0].result != "kept":  # "<its score> deg RMS against <the estimate's>"
        m = re.search(r"([0-9.]+) deg RMS against ([0-9.]+)", rev[0].why)
        assert m is not None and float(m.group(1)) <= float(m.group(2)), rev
    # its own attempts are in this sequence's frame order, marked
    back = [a for a in (res.report.attempts or []) if a.reversed]
    assert back and all(0 <= a.frames[0] <= a.frames[1] <= 299
                        for a in back if a.frames is not None)


def _piece_of_the_truth(first: int) -> tuple[Simulation, Any]:
    """40 simulated frames (0.05 deg noise) and a piece of the estimator posing frames
    ``first``-39 at their true poses, with the true lines."""
    from omni_sfm.estimate.pipeline import _Init, _Solved

    sim = simulate(SimulationOptions(num_views=40, num_parallel=10, num_other=10, seed=3,
                                     noise_deg=0.05))
    g, F, M = sim.groundtruth, 40, sim.tracks.num_tracks
    frames = np.arange(F) >= first
    R = np.where(frames[:, None, None], g.rotations, np.nan)
    c = np.where(frames[:, None], g.positions, np.nan)
    init = _Init(R, c, frames, [], [], sim.parallel, np.zeros((F, 3)))
    return sim, _Solved(init, R, c, frames, sim.line_directions.copy(),
                        sim.line_points.copy(), np.ones(M, bool), np.zeros(M, bool), 0.0, 0.0,
                        0.05)


def test_frames_a_new_start_reaches_into_keep_an_initial_pose() -> None:
    # a new start on frames 20-39 grown by its lines into frames 10-19 of the piece beside it:
    # the frames it added carry their registered poses as their initial ones, so that the
    # piece, when it stays a segment of its own, still gets its conventions (before, their
    # initial poses were NaN and the whole segment was lost: 558 frames of a 5,000-frame walk)
    from omni_sfm.estimate.attempts import RunLog
    from omni_sfm.estimate.pipeline import _moving_result, _reach_into

    sim, piece = _piece_of_the_truth(20)
    F = 40
    frames = piece.frames
    covered = np.arange(F) < 20  # the neighbour's frames
    opts = EstimationOptions()
    grown = _reach_into(sim.tracks, piece, covered, opts, RunLog())
    assert grown is not None
    added = grown.frames & ~frames
    assert added.sum() >= 5 and np.flatnonzero(added).min() >= 20 - opts.restart_overlap
    assert np.isfinite(grown.init.positions[grown.frames]).all()
    assert np.isfinite(grown.init.rotations[grown.frames]).all()
    res = _moving_result(sim.tracks, grown, RunLog(), 0.0)
    assert np.isfinite(res.initial_trajectory.positions).all()
    assert len(res.initial_trajectory) == grown.frames.sum()


def test_a_line_through_a_camera_is_moved_off_it() -> None:
    # a solution of a simulated walk with one line put through the camera of frame 20 (the
    # false minimum the sparse seeds 5, 6, 8 and 9 ended in, where few lines are seen at a
    # time): the strategy moves it off the camera, at a lower cost, with the poses at the
    # noise level
    from omni_sfm.estimate.attempts import RunLog
    from omni_sfm.estimate.bundle import camera_distance_ratio
    from omni_sfm.estimate.pipeline import _Init, _lines_off_cameras, _Solved

    sim = simulate(SimulationOptions(num_views=40, num_parallel=10, num_other=10, seed=5,
                                     noise_deg=0.05))
    g, F, M, tr = sim.groundtruth, 40, sim.tracks.num_tracks, sim.tracks
    d, p = sim.line_directions.copy(), sim.line_points.copy()
    k = 3
    p[k] = g.positions[20] - (g.positions[20] @ d[k]) * d[k]  # through the camera of frame 20
    frames = np.ones(F, bool)
    obs = frames[tr.obs_frame]
    assert camera_distance_ratio(tr, g.rotations, g.positions, d, p, obs, M)[k] < 1e-9
    init = _Init(g.rotations, g.positions, frames, [], [], sim.parallel, np.zeros((F, 3)))
    sol = _Solved(init, g.rotations.copy(), g.positions.copy(), frames, d, p,
                  np.ones(M, bool), np.zeros(M, bool), 0.0, 0.05, 0.05)
    run = RunLog()
    out = _lines_off_cameras(tr, sol, EstimationOptions(), run)
    ratio = camera_distance_ratio(tr, out.R, out.c, out.d, out.p, obs, M)
    assert ratio[k] > 0.2 and out.used[k]
    kept = [a for a in run.entries if a.result == "kept"]
    assert len(kept) == 1 and kept[0].strategy == "lines off the cameras"
    assert kept[0].why.startswith("1 lines ")
    err = trajectory_errors(Trajectory(g.timestamps, out.R, out.c), g)
    assert err.rot_max_deg < 0.2 and err.ate_rel < 0.01
    # nothing through a camera: nothing is tried
    run = RunLog()
    assert _lines_off_cameras(tr, out, EstimationOptions(), run) is out and not run.entries


def test_a_main_piece_that_lacks_its_first_frames_is_registered_again_without_a_join() -> None:
    # frames 0 and 1 left out of the main piece, too few for a new start, no piece joined: the
    # registration runs again at the end from the lines the piece knows then (sparse seed 14:
    # its first two frames stayed without a pose, as the registration had run without two of
    # their lines, outliers of the chain then and taken back later)
    from omni_sfm.estimate.attempts import RunLog
    from omni_sfm.estimate.pipeline import _with_segments

    sim, piece = _piece_of_the_truth(2)
    g = sim.groundtruth
    run = RunLog()
    res = _with_segments(sim.tracks, piece, EstimationOptions(), run, 0.0)
    assert res.estimated.all() and not res.segments
    again = [a for a in run.entries if a.strategy == "registration again"]
    assert [a.result for a in again] == ["kept"]
    e = trajectory_errors(match_reflection(res.trajectory, g), g)
    assert e.rot_max_deg < 0.2


def test_registration_again_goes_on_where_its_adjustment_takes_back_a_line() -> None:
    # the sparse case's seed 13, frames 500-599, posed at the truth up to frame 587, one line
    # (track 78, seen in frames 540-599) still an outlier: frames 588-597 see 4 other known
    # lines and are registered, frames 598-599 see only 3 besides it; the adjustment after
    # the registration takes the line back, and a second round poses them (before: 598 of
    # the 600 frames of seed 13 posed, those two "sees 3 lines already reconstructed")
    from omni_sfm.estimate.attempts import RunLog
    from omni_sfm.estimate.pipeline import _Init, _registered_again, _Solved
    from omni_sfm.estimate.segments import frame_range

    sim = simulate(SimulationOptions(num_views=600, num_parallel=40, num_other=40,
                                     noise_deg=0.1, visible_frames=60, seed=13))
    tr, idx = frame_range(sim.tracks, 500, 600)
    g = sim.groundtruth.subset(np.arange(500, 600))
    F, M = tr.num_frames, tr.num_tracks
    frames = np.arange(F) < 88
    R = np.where(frames[:, None, None], g.rotations, np.nan)
    c = np.where(frames[:, None], g.positions, np.nan)
    outlier = idx == 78
    assert outlier.sum() == 1 and (tr.visibility()[outlier][0, 98:]).all()
    init = _Init(R, c, frames, [], [], sim.parallel[idx], np.zeros((F, 3)))
    sol = _Solved(init, R, c, frames, sim.line_directions[idx].copy(),
                  sim.line_points[idx].copy(), np.ones(M, bool), outlier, 0.0, 0.0, 0.1)
    run = RunLog()
    res = _registered_again(tr, sol, EstimationOptions(), run)
    assert res.frames.all()
    again = [a for a in run.entries if a.strategy == "registration again"]
    assert [a.result for a in again] == ["kept", "kept"]
    assert again[1].why.startswith("2 frames")
    # near the maximum-likelihood oracle on these frames (measured: rotation 1.09x mean, 1.26x
    # max, translation 1.01x)
    from omni_sfm.estimate.bundle import oracle

    e = trajectory_errors(match_reflection(Trajectory(g.timestamps, res.R, res.c), g), g)
    o = oracle(tr, g.rotations, g.positions, sim.line_directions[idx], sim.line_points[idx])
    eo = trajectory_errors(Trajectory(g.timestamps, o.rotations, o.positions), g)
    assert e.rot_mean_deg <= 1.5 * eo.rot_mean_deg and e.rot_max_deg <= 1.5 * eo.rot_max_deg
    assert e.paper_trans.mean() <= 1.5 * eo.paper_trans.mean()
