"""Windows over partial tracks: planning, per-window tracks, similarity from overlaps, chaining."""

from __future__ import annotations

import numpy as np

from omni_sfm.estimate.windows import (
    Window,
    WindowOptions,
    chain_windows,
    max_rotation_step_deg,
    plan_windows,
    similarity_from_overlap,
    window_tracks,
)
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.geometry import rotvec_to_matrix
from omni_sfm.poses import Trajectory
from omni_sfm.synth.simulate import SimulationOptions, simulate


def _sim():
    return simulate(SimulationOptions(num_views=200, num_parallel=40, num_other=40,
                                      visible_frames=50, seed=11))


def test_plan_windows_cover_and_overlap():
    sim = _sim()
    vis = sim.tracks.visibility()
    opts = WindowOptions()
    ws = plan_windows(sim.tracks, sim.parallel, np.ones(200, bool), opts)
    covered = np.zeros(200, bool)
    for w in ws:
        covered[w.start:w.stop] = True
        assert w.stop - w.start >= 3 and w.stop - w.start <= opts.max_length
        # every listed track is seen in every frame of the window, and enough of each kind
        assert vis[w.tracks, w.start:w.stop].all()
        assert sim.parallel[w.tracks].sum() >= 3 and (~sim.parallel[w.tracks]).sum() >= 3
    assert covered.all()
    for a, b in zip(ws, ws[1:], strict=False):
        assert a.stop - b.start >= 3 and b.start > a.start


def test_window_tracks_renumbers_frames():
    sim = _sim()
    w = plan_windows(sim.tracks, sim.parallel, np.ones(200, bool))[1]
    sub = window_tracks(sim.tracks, w)
    assert sub.num_frames == w.stop - w.start
    assert sub.visibility().all()
    np.testing.assert_array_equal(sub.timestamps, sim.tracks.timestamps[w.start:w.stop])
    dn = sim.tracks.dense_normals()[w.tracks][:, w.start:w.stop]
    np.testing.assert_array_equal(sub.dense_normals(), dn)


def test_similarity_from_overlap_with_reflection():
    rng = np.random.default_rng(0)
    Ra = rotvec_to_matrix(rng.normal(size=(5, 3)))
    ca = rng.normal(size=(5, 3))
    Rs = rotvec_to_matrix(np.array([0.2, -0.4, 0.1]))
    for s in (2.5, -0.7):  # a negative scale: the window's solution is the reflected one
        t = np.array([1.0, 2.0, -1.0])
        Rb = Rs.T @ Ra
        cb = (ca - t) @ Rs / s
        R, s_est, t_est = similarity_from_overlap(Ra, ca, Rb, cb)
        np.testing.assert_allclose(R, Rs, atol=1e-12)
        assert abs(s_est - s) < 1e-12
        np.testing.assert_allclose(s_est * cb @ R.T + t_est, ca, atol=1e-12)


def test_chain_exact_window_solutions():
    sim = _sim()
    g = sim.groundtruth
    ws = plan_windows(sim.tracks, sim.parallel, np.ones(200, bool))
    rng = np.random.default_rng(1)
    sols = []
    for k, w in enumerate(ws):
        fr = w.frames
        R0, c0 = g.rotations[fr[0]], g.positions[fr[0]]
        sign = -1.0 if k % 2 else 1.0  # every other window on the reflected branch
        scale = rng.uniform(0.5, 3.0)
        sols.append((R0.T @ g.rotations[fr], sign * scale * (g.positions[fr] - c0) @ R0))
    sols[len(ws) // 2] = None if len(ws) > 4 else sols[len(ws) // 2]
    R, c, done, chained, _ = chain_windows(200, ws, sols)
    assert len(chained) >= 1 and done.sum() >= 3
    est = Trajectory(g.timestamps[done], R[done], c[done])
    err = trajectory_errors(est, g.subset(np.flatnonzero(done)))
    assert err.rot_max_deg < 1e-9 and err.ate_rel < 1e-9


def test_chain_keeps_the_longest_run():
    ws = [Window(0, 10, np.arange(6)), Window(20, 40, np.arange(6))]
    sols = []
    for w in ws:
        n = w.stop - w.start
        sols.append((np.broadcast_to(np.eye(3), (n, 3, 3)).copy(),
                     np.c_[np.arange(n), np.zeros(n), np.zeros(n)].astype(float)))
    R, c, done, chained, _ = chain_windows(40, ws, sols)
    assert chained == [1] and done[20:40].all() and not done[:20].any()
    assert np.isnan(c[:20]).all()


def _exact_solutions(sim, ws):
    g = sim.groundtruth
    sols = []
    for w in ws:
        fr = w.frames
        R0, c0 = g.rotations[fr[0]], g.positions[fr[0]]
        sols.append((R0.T @ g.rotations[fr], (g.positions[fr] - c0) @ R0))
    return sols


def test_max_rotation_step_sees_a_flipped_frame():
    sim = _sim()
    R = sim.groundtruth.rotations[:30].copy()
    smooth = max_rotation_step_deg(R)
    assert 0 < smooth < 5
    R[12] = R[12] @ rotvec_to_matrix(np.array([0.0, np.pi, 0.0]))
    assert max_rotation_step_deg(R) > 170


def test_chain_skips_a_disagreeing_window_or_takes_its_other_solution():
    sim = _sim()
    g = sim.groundtruth
    ws = plan_windows(sim.tracks, sim.parallel, np.ones(200, bool))
    assert len(ws) >= 3
    sols = _exact_solutions(sim, ws)
    good = sols[1]
    # window 1's rotations flipped by 180 deg in every other frame (shared ones included)
    flip = rotvec_to_matrix(np.array([0.0, 0.0, np.pi]))
    rot = good[0].copy()
    rot[1::2] = rot[1::2] @ flip
    sols[1] = (rot, good[1])
    # without the check the flip goes into the chain
    R, c, done, chained, _ = chain_windows(200, ws, sols)
    err = trajectory_errors(Trajectory(g.timestamps[done], R[done], c[done]),
                            g.subset(np.flatnonzero(done)))
    assert err.rot_max_deg > 90
    # with it the window is skipped; the chain goes on where the next window still overlaps
    R, c, done, chained, _ = chain_windows(200, ws, sols, max_disagreement_deg=5.0)
    assert 1 not in chained and done.sum() >= 3
    err = trajectory_errors(Trajectory(g.timestamps[done], R[done], c[done]),
                            g.subset(np.flatnonzero(done)))
    assert err.rot_max_deg < 1e-9 and err.ate_rel < 1e-9
    # with a resolver that gives the right solution, the window is chained
    asked = []

    def resolve(k):
        asked.append(k)
        return good

    R2, c2, done2, chained2, _ = chain_windows(200, ws, sols, max_disagreement_deg=5.0,
                                            resolve=resolve)
    assert asked == [1] and 1 in chained2 and done2.sum() >= done.sum()
    err = trajectory_errors(Trajectory(g.timestamps[done2], R2[done2], c2[done2]),
                            g.subset(np.flatnonzero(done2)))
    assert err.rot_max_deg < 1e-9 and err.ate_rel < 1e-9
