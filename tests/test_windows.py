"""The paper's window: its tracks renumbered, and a flipped frame seen in its rotations."""

from __future__ import annotations

import numpy as np

from omni_sfm.estimate.windows import Window, max_rotation_step_deg, window_tracks
from omni_sfm.geometry import rotvec_to_matrix
from omni_sfm.synth.simulate import SimulationOptions, simulate


def _sim():
    return simulate(SimulationOptions(num_views=200, num_parallel=40, num_other=40,
                                      visible_frames=50, seed=11))


def test_window_tracks_renumbers_frames():
    sim = _sim()
    vis = sim.tracks.visibility()
    w = Window(60, 90, np.flatnonzero(vis[:, 60:90].all(1)))
    sub = window_tracks(sim.tracks, w)
    assert sub.num_frames == w.stop - w.start
    assert sub.visibility().all()
    np.testing.assert_array_equal(sub.timestamps, sim.tracks.timestamps[w.start:w.stop])
    dn = sim.tracks.dense_normals()[w.tracks][:, w.start:w.stop]
    np.testing.assert_array_equal(sub.dense_normals(), dn)


def test_max_rotation_step_sees_a_flipped_frame():
    sim = _sim()
    R = sim.groundtruth.rotations[:30].copy()
    smooth = max_rotation_step_deg(R)
    assert 0 < smooth < 5
    R[12] = R[12] @ rotvec_to_matrix(np.array([0.0, np.pi, 0.0]))
    assert max_rotation_step_deg(R) > 170

