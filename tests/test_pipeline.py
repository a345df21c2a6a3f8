"""The whole estimator on seeded simulations, against ground truth and the oracle.

Line normals have no sign, so poses are determined up to a point reflection of all camera
centres through the first camera; errors are measured on the matching branch
(:func:`match_reflection`). "Within k x the oracle" compares MEAN errors over a few seeds.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from helpers import assert_every_key_declared

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.bundle import oracle
from omni_sfm.estimate.pipeline import (
    EstimationOptions,
    chosen_estimator,
    estimate_poses,
    write_init_outputs,
)
from omni_sfm.estimate.segments import frame_range
from omni_sfm.evaluate import match_reflection, trajectory_errors
from omni_sfm.lines.tracks import make_tracks, reversed_frames
from omni_sfm.poses import Trajectory
from omni_sfm.reports import InitInput, InitReport
from omni_sfm.synth.simulate import SimulationOptions, simulate


def _err(traj: Trajectory, sim) -> tuple[float, float]:
    e = trajectory_errors(match_reflection(traj, sim.groundtruth), sim.groundtruth)
    return e.rot_mean_deg, float(e.paper_trans.mean())


def _oracle_err(sim) -> tuple[float, float]:
    clean = ~sim.outlier
    g = sim.groundtruth
    o = oracle(sim.tracks.select_tracks(clean), g.rotations, g.positions,
               sim.line_directions[clean], sim.line_points[clean])
    return _err(Trajectory(g.timestamps[o.frames], o.rotations[o.frames],
                           o.positions[o.frames]), sim)


@pytest.mark.parametrize("views,par,oth", [(10, 3, 3), (3, 3, 3), (20, 20, 20)])
def test_noise_free_exact(views, par, oth):
    sim = simulate(SimulationOptions(num_views=views, num_parallel=par, num_other=oth, seed=2))
    res = estimate_poses(sim.tracks)
    assert res.estimated.all() and not res.outliers.any()
    for traj in (res.initial_trajectory, res.trajectory):
        rot, tr = _err(traj, sim)
        assert rot < 1e-6 and tr < 1e-6
    # the family is found, the scale convention holds
    np.testing.assert_array_equal(res.parallel, sim.parallel)
    assert abs(np.linalg.norm(res.trajectory.positions[-1]) - 1) < 1e-12
    assert abs(abs(res.parallel_direction @ sim.parallel_direction) - 1) < 1e-6


@pytest.mark.parametrize("noise", [0.04, 0.32])
def test_fig12_within_1p1_oracle(noise):
    seeds = range(3)
    ref, orc, paper = [], [], []
    for seed in seeds:
        sim = simulate(SimulationOptions(num_views=20, num_parallel=20, num_other=20,
                                         noise_deg=noise, seed=100 + seed))
        res = estimate_poses(sim.tracks)
        assert res.estimated.all()
        ref.append(_err(res.trajectory, sim))
        paper.append(_err(res.initial_trajectory, sim))
        orc.append(_oracle_err(sim))
    ref_m, orc_m, paper_m = (np.mean(x, axis=0) for x in (ref, orc, paper))
    assert ref_m[0] <= 1.1 * orc_m[0] and ref_m[1] <= 1.1 * orc_m[1]
    # the paper's method alone: mean rotation error within the noise level
    assert paper_m[0] <= noise


def test_fig12_highest_noise_reaches_the_oracle():
    """1.28 deg, the Fig. 12 set-up: from the paper's solution alone the bundle adjustment stops
    in a wrong local minimum in these trials (seed 100: 3.5 deg / 0.06 against the oracle's
    0.84 deg / 0.025; seed 1009: 3.1 deg / 0.43); the multi-start over the paper's alternative
    starts reaches the oracle's minimum in every one."""
    ref, orc = [], []
    for seed in (0, 100, 1009, 1030):
        sim = simulate(SimulationOptions(num_views=20, num_parallel=20, num_other=20,
                                         noise_deg=1.28, seed=seed))
        res = estimate_poses(sim.tracks)
        assert res.estimated.all() and not res.outliers.any()
        g = sim.groundtruth
        o = oracle(sim.tracks, g.rotations, g.positions, sim.line_directions, sim.line_points)
        # the same least-squares cost as the oracle's (the maximum-likelihood minimum)
        assert res.residual_rms_final_deg <= o.rms_final_deg * (1 + 1e-6)
        ref.append(_err(res.trajectory, sim))
        orc.append(_oracle_err(sim))
    ref_m, orc_m = np.mean(ref, axis=0), np.mean(orc, axis=0)
    assert ref_m[0] <= 1.1 * orc_m[0] and ref_m[1] <= 1.1 * orc_m[1]


def test_200_views_paper_real_case_within_1p1_oracle():
    ref, orc = [], []
    for seed in range(2):
        sim = simulate(SimulationOptions(num_views=200, num_parallel=10, num_other=5,
                                         noise_deg=0.1, seed=200 + seed))
        res = estimate_poses(sim.tracks)
        assert res.estimated.all()
        ref.append(_err(res.trajectory, sim))
        orc.append(_oracle_err(sim))
    ref_m, orc_m = np.mean(ref, axis=0), np.mean(orc, axis=0)
    assert ref_m[0] <= 1.1 * orc_m[0] and ref_m[1] <= 1.1 * orc_m[1]


def test_outlier_tracks_rejected_and_named():
    """15 % of the tracks are outliers (6 of 40): each trial names all of them (and at most one
    good track more), and the mean error stays within 1.5 x the oracle's (without outliers)."""
    ref, orc = [], []
    for seed in (300, 301, 302):
        sim = simulate(SimulationOptions(num_views=20, num_parallel=20, num_other=20,
                                         noise_deg=0.1, outlier_fraction=0.15, seed=seed))
        res = estimate_poses(sim.tracks)
        true_ids = set(sim.tracks.track_ids[sim.outlier].tolist())
        named = set(res.report.rejected_tracks or [])
        assert len(true_ids) == 6
        assert true_ids <= named and len(named - true_ids) <= 1, (seed, true_ids, named)
        ref.append(_err(res.trajectory, sim))
        orc.append(_oracle_err(sim))
    ref_m, orc_m = np.mean(ref, axis=0), np.mean(orc, axis=0)
    assert ref_m[0] <= 1.5 * orc_m[0] and ref_m[1] <= 1.5 * orc_m[1]


def test_too_few_other_lines_for_the_paper():
    # the paper's method needs 3 lines of another direction; the global estimator poses the
    # frames from 5 parallel lines and 2 others
    sim = simulate(SimulationOptions(num_views=10, num_parallel=5, num_other=2, seed=4))
    with pytest.raises(OmniSfmError, match="at least 3 lines not parallel"):
        estimate_poses(sim.tracks, EstimationOptions(estimator="paper"))
    res = estimate_poses(sim.tracks)
    assert res.report.estimator == "global" and res.estimated.all()
    e = trajectory_errors(match_reflection(res.trajectory, sim.groundtruth), sim.groundtruth)
    assert e.rot_max_deg < 1e-6 and e.ate_rel < 1e-6


def test_auto_takes_the_paper_where_one_window_covers_the_sequence():
    """``estimator="auto"`` (the default): the paper's data (every line in every frame) go to
    the paper's method, a walk whose lines come and go to the global estimator, and so do two
    walks with no line in common (each part in a world of its own); the same choice in reversed
    frame order; the report says which ran and why; the paper's method asked for where no
    window covers the sequence is a clear error."""
    paper = simulate(SimulationOptions(num_views=12, num_parallel=5, num_other=5, seed=1))
    walk = simulate(SimulationOptions(num_views=120, num_parallel=12, num_other=12,
                                      visible_frames=40, seed=1))
    a = simulate(SimulationOptions(num_views=30, num_parallel=6, num_other=6, seed=2)).tracks
    b = simulate(SimulationOptions(num_views=20, num_parallel=6, num_other=6, seed=3)).tracks
    apart = make_tracks(50, np.arange(a.num_tracks + b.num_tracks),
                        np.concatenate([a.obs_track, b.obs_track + a.num_tracks]),
                        np.concatenate([a.obs_frame, b.obs_frame + 30]),
                        np.concatenate([a.obs_normal, b.obs_normal]), source="test")
    for tracks, want, why in ((paper.tracks, "paper", "one window covers every frame"),
                              (walk.tracks, "global", "lines seen in every frame"),
                              (apart, "global", "no line is seen on both sides of frame")):
        for t in (tracks, reversed_frames(tracks)):
            got, reason = chosen_estimator(t, EstimationOptions())
            assert got == want and why in reason, (got, reason)
    res = estimate_poses(paper.tracks)
    assert res.report.estimator == "paper" and "auto: one window" in \
        (res.report.estimator_choice or "")
    res = estimate_poses(paper.tracks, EstimationOptions(estimator="global"))
    assert (res.report.estimator, res.report.estimator_choice) == ("global", "asked for")
    with pytest.raises(OmniSfmError, match="unknown estimator 'best'"):
        estimate_poses(paper.tracks, EstimationOptions(estimator="best"))
    with pytest.raises(OmniSfmError, match="the paper's method needs one window over the whole "
                                           "sequence"):
        estimate_poses(walk.tracks, EstimationOptions(estimator="paper"))
    with pytest.raises(OmniSfmError, match="workers must be at least 1"):
        estimate_poses(paper.tracks, EstimationOptions(workers=0))


def test_too_few_frames():
    tr = make_tracks(2, np.arange(6), np.repeat(np.arange(6), 2), np.tile([0, 1], 6),
                     np.tile([1.0, 0.0, 0.0], (12, 1)))
    with pytest.raises(OmniSfmError, match="need at least 3"):
        estimate_poses(tr)


def test_paper_alone_option_and_outputs(tmp_path):
    sim = simulate(SimulationOptions(num_views=12, num_parallel=6, num_other=6, noise_deg=0.05,
                                     seed=5))
    res = estimate_poses(sim.tracks, EstimationOptions(refine=False))
    assert res.estimated.all()
    write_init_outputs(tmp_path, res, replace(res.report, input=InitInput(tracks="x")))
    assert_every_key_declared(InitReport, tmp_path / "report.json")
    rep = json.loads((tmp_path / "report.json").read_text())
    for key in ("num_frames", "num_tracks", "parallel_family", "rejected_tracks",
                "frames_not_estimated", "scale_convention", "timings_ms", "residuals"):
        assert key in rep
    assert rep["input"] == {"tracks": "x"}
    assert len((tmp_path / "trajectory.tum").read_text().splitlines()) == 13


def test_a_corridor_stretch_with_a_half_turn_ambiguity_comes_out_right():
    # on this corridor walk the paper's rotation search turned frames 402-435 of a window by a
    # half turn (fitting its lines as well); the global estimator's rotations of all frames at
    # once leave no window to flip
    sim = simulate(SimulationOptions(world="manhattan", num_views=1000, path_length=0.05 * 999,
                                     noise_deg=0.1, visible_frames=60, seed=0,
                                     line_density=7.0))
    sub, _ = frame_range(sim.tracks, 300, 520)
    g = sim.groundtruth
    gt = Trajectory(g.timestamps[300:520], g.rotations[300:520], g.positions[300:520])
    res = estimate_poses(sub)
    assert res.estimated.all() and res.report.estimator == "global"
    e = trajectory_errors(match_reflection(res.trajectory, gt), gt)
    assert e.rot_max_deg < 0.5 and e.ate_rel < 0.005

