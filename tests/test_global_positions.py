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
    positions of a long walk of few lines to about the noise (0.07 % of the path); without
    rays the normalised eigenvector is several times further off (0.47 %)."""
    with_rays = _ate(walk, _solve(walk.tracks, walk).positions)
    assert with_rays < 0.003
    without = _solve(replace(walk.tracks, obs_ray=None), walk)
    assert np.isclose(np.sum(without.positions**2), 1.0)
    assert 2 * with_rays < _ate(walk, without.positions) < 0.01


def test_a_sparse_walk_keeps_its_shape() -> None:
    """A walk of one parallel family and lines of random directions, each seen in 60 frames
    (2-13 lines a frame): from its true rotations the positions are within a few times the
    noise (the mean depth holds the scale: held by the nearest line's distance, the scale
    shrinks every other depth with it, 2.6 % of the path off)."""
    sim = simulate(SimulationOptions(num_views=600, num_parallel=40, num_other=40,
                                     noise_deg=0.1, visible_frames=60, seed=2))
    assert _ate(sim, _solve(sim.tracks, sim).positions) < 0.005


def test_reversed_order_gives_the_same_positions(walk) -> None:
    """The same observations in reversed frame order (its first frame, the origin, is the
    other end of the walk) give the same positions up to a similarity."""
    a = _solve(walk.tracks, walk).positions
    b = _solve(reversed_frames(walk.tracks), walk, walk.groundtruth.rotations[::-1]).positions
    t = walk.groundtruth.timestamps
    ref = Trajectory(t, walk.groundtruth.rotations, a)
    rev = Trajectory(t, walk.groundtruth.rotations, b[::-1].copy())
    assert trajectory_errors(rev, ref).ate_rel < 1e-5


def test_frames_the_adjustment_moves_far_from_the_linear_positions_are_flagged() -> None:
    """Where the adjustment ends far from the linear positions (after the similarity that best
    aligns them) the tracks disagree with one another, and those frames are flagged; a small
    disagreement everywhere (the two estimators' noise) flags nothing."""
    from types import SimpleNamespace

    from omni_sfm.estimate.global_estimator import GlobalOptions, _moved_far, settings

    t = np.linspace(0.0, 1.0, 50)
    c = np.stack([t, 0.1 * np.sin(3 * t), np.zeros_like(t)], axis=1)
    rng = np.random.default_rng(0)
    ba = SimpleNamespace(frames=np.ones(50, bool), positions=3.0 * c + 0.001 * rng.normal(
        size=c.shape))
    assert _moved_far(c, ba, settings(GlobalOptions()), {}) == {}
    bent = ba.positions.copy()
    bent[40:, 1] += 0.6  # the last ten frames 20 % of the path off
    flagged = _moved_far(c, SimpleNamespace(frames=ba.frames, positions=bent),
                         settings(GlobalOptions()), {})
    # the alignment spreads the bend over the other frames: its far end stands out most
    assert 49 in flagged and len(flagged) >= 10
    assert all("moved it" in v for v in flagged.values())
    # a part already flagged (tied to the rest by a few lines) lies in a world of its own:
    # the others are aligned without it, and none of them looks moved
    apart = ba.positions.copy()
    apart[25:] = 4.0 * apart[25:] + np.array([1.0, -2.0, 0.5])
    tied = {k: "weak ties" for k in range(25, 50)}
    moved = SimpleNamespace(frames=ba.frames, positions=apart)
    assert len(_moved_far(c, moved, settings(GlobalOptions()), {})) >= 10
    assert _moved_far(c, moved, settings(GlobalOptions()), tied) == {}


def test_a_few_trusted_frames_between_many_flagged_ones_are_flagged() -> None:
    """A stretch of fewer than ``min_trusted_run`` trusted frames with more flagged frames
    around it rests on them and is flagged; a flagged frame or two beside a long trusted
    stretch, frames not posed, and a video with nothing flagged change nothing."""
    from omni_sfm.estimate.global_estimator import _islands

    posed = np.ones(60, bool)
    flagged = {*range(0, 20), *range(23, 45), *range(50, 52)}
    got = _islands(posed, flagged, 10)
    # 20-22 (3 trusted between 42 flagged) and 45-49 (5 between 24); 52-59 (8 beside 2) stay
    assert sorted(got) == [20, 21, 22, 45, 46, 47, 48, 49]
    assert "one of 3 trusted frames (20-22) between 42 flagged ones" in got[20]
    assert "a trusted frame alone between 6 flagged ones" in \
        _islands(np.ones(9, bool), {0, 1, 2, 4, 5, 6}, 10)[3]
    assert _islands(posed, set(), 10) == {}
    assert _islands(posed, {30}, 10) == {}
    # frames not posed are skipped: they neither end a stretch nor count in it
    posed[21] = False
    assert sorted(_islands(posed, flagged, 10)) == [20, 22, 45, 46, 47, 48, 49]
    # every frame trusted but a few: nothing is an island
    assert _islands(np.ones(8, bool), {0, 1}, 10) == {}
