"""Step 2 of the global estimator: the positions of all frames and lines from known rotations
(omni_sfm/estimate/global_positions.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from omni_sfm.estimate.global_positions import solve_positions
from omni_sfm.evaluate import match_reflection, trajectory_errors
from omni_sfm.lines.tracks import reversed_frames
from omni_sfm.poses import Trajectory
from omni_sfm.synth.simulate import SimulationOptions, simulate


@pytest.fixture(scope="module")
def walk():
    """A 1,000-frame Manhattan walk of 3.5 lines a metre, each line seen in about 60 frames
    (the walk of scripts/bench/scaling.py)."""
    return simulate(SimulationOptions(world="manhattan", num_views=1000, path_length=49.95,
                                      noise_deg=0.1, visible_frames=60, line_density=3.5,
                                      seed=0))


def _ate(sim, positions) -> float:
    gt = sim.groundtruth
    est = Trajectory(gt.timestamps, gt.rotations, positions)
    return float(trajectory_errors(match_reflection(est, gt), gt).ate_rel)


def _solve(tracks, sim, rotations=None):
    F, M = tracks.num_frames, tracks.num_tracks
    R = sim.groundtruth.rotations if rotations is None else rotations
    return solve_positions(tracks, R, sim.line_directions, np.ones(F, bool), np.ones(M, bool))


def test_the_depths_keep_a_long_walk_whole(walk) -> None:
    """From the true rotations, the depths held on the side the rays see each line give the
    positions of a long walk of few lines to about the noise (0.12 % of the path); without
    rays the normalised eigenvector is several times further off."""
    with_rays = _ate(walk, _solve(walk.tracks, walk).positions)
    assert with_rays < 0.003
    without = _solve(replace(walk.tracks, obs_ray=None), walk)
    assert np.isclose(np.sum(without.positions**2), 1.0)
    assert 2 * with_rays < _ate(walk, without.positions) < 0.01


def test_reversed_order_gives_the_same_positions(walk) -> None:
    """The same observations in reversed frame order (its first frame, the origin, is the
    other end of the walk) give the same positions up to a similarity."""
    a = _solve(walk.tracks, walk).positions
    b = _solve(reversed_frames(walk.tracks), walk, walk.groundtruth.rotations[::-1]).positions
    t = walk.groundtruth.timestamps
    ref = Trajectory(t, walk.groundtruth.rotations, a)
    rev = Trajectory(t, walk.groundtruth.rotations, b[::-1].copy())
    assert trajectory_errors(rev, ref).ate_rel < 1e-5
