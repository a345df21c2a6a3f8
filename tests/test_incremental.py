"""Frames posed through stops and gaps: stop-and-go in one trajectory, resection from known lines
(omni_sfm/estimate/incremental.py, as the online tracker uses it), parts with nothing in common
as segments, the paper's method with another family."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_every_key_declared

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
from omni_sfm.synth.simulate import SimulationOptions, simulate


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
    # two walks with no line in common: each is estimated on its own, the second in its own
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
    assert res.report.estimator == "global" and "nothing in common" in \
        (res.report.estimator_choice or "")
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
    res = estimate_poses(make_tracks(F, np.arange(len(dirs)), m, f, n, source="test"),
                         EstimationOptions(estimator="paper"))
    assert res.estimated.all()
    fam = res.report.parallel_families
    assert fam is not None and fam.sizes == [14, 9, 7]
    assert len(fam.windows_with_another_family) == 1
    # every attempt is in the report: the paper's method failed with the largest family, the
    # vertical family (the second) gave the window, its adjustment was kept
    tried = [(a.strategy, a.result) for a in (res.report.attempts or [])]
    assert tried[:2] == [("paper window", "failed"), ("paper window, another family", "kept")]
    assert ("bundle adjustment", "kept") in tried
    first, second = (res.report.attempts or [])[:2]
    assert "degenerate motion" in first.why and second.why.startswith("family 2")
    assert second.frames == [0, F - 1] and 0 < second.cost_rms_deg < 1.0
    err = trajectory_errors(match_reflection(res.trajectory, gt), gt)
    assert err.rot_max_deg < 0.2 and err.ate_rel < 0.005


@pytest.mark.slow
@pytest.mark.parametrize("seed", [2, 3, 4])
def test_sparse_tracks_reach_the_oracle(seed: int) -> None:
    """The every-frame issue's sparse case (600 frames, 4-13 lines a frame, each seen for about
    60 frames, 0.1 deg noise; no line seen throughout): the default takes the global estimator,
    every frame in one trajectory, rotation and translation errors within 2x of the
    maximum-likelihood oracle's."""
    from omni_sfm.estimate.bundle import oracle

    sim = simulate(SimulationOptions(num_views=600, num_parallel=40, num_other=40,
                                     noise_deg=0.1, visible_frames=60, seed=seed))
    g = sim.groundtruth
    assert not sim.tracks.visibility().all(1).any()  # no line is seen throughout
    res = estimate_poses(sim.tracks)
    assert res.report.estimator == "global" and res.estimated.all() and not res.segments
    e = trajectory_errors(match_reflection(res.trajectory, g), g)
    o = oracle(sim.tracks, g.rotations, g.positions, sim.line_directions, sim.line_points)
    eo = trajectory_errors(Trajectory(g.timestamps[o.frames], o.rotations[o.frames],
                                      o.positions[o.frames]), g)
    assert e.rot_mean_deg <= 2.0 * eo.rot_mean_deg
    assert e.paper_trans.mean() <= 2.0 * eo.paper_trans.mean()
