"""Frames beyond the chained windows, registered from the lines already reconstructed
(omni_sfm/estimate/extend.py)."""

from dataclasses import replace

import numpy as np
from helpers import WINDOWS

from omni_sfm.estimate.pipeline import estimate_poses
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.synth.simulate import SimulationOptions, simulate


def test_frames_without_a_window_are_registered_from_known_lines() -> None:
    # the parallel lines leave the view at frame 45: no window of the paper's method forms
    # after it, but the other lines, already fixed in 3D, still pose those frames
    sim = simulate(SimulationOptions(num_views=60, num_parallel=12, num_other=24,
                                     noise_deg=0.05, seed=4))
    tr = sim.tracks
    keep = ~(sim.parallel[tr.obs_track] & (tr.obs_frame >= 45))
    tracks = tr.keep_observations(keep)
    chain_only = estimate_poses(tracks, replace(WINDOWS, extend=None))
    assert chain_only.estimated.sum() == 45
    res = estimate_poses(tracks, WINDOWS)
    assert res.estimated.all()
    err = trajectory_errors(res.trajectory, sim.groundtruth)
    assert err.rot_max_deg < 0.1 and err.ate_rel < 0.002
    assert res.timings_ms["extension"] > 0
    # the chain's own frames keep their accuracy
    before = trajectory_errors(chain_only.trajectory, sim.groundtruth)
    assert err.rot_deg[:45].max() < 2 * before.rot_max_deg + 0.01
    assert np.isfinite(res.trajectory.positions).all()
