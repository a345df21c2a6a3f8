"""The paper's estimator end to end (docs/method.md §3-§5) on seeded simulations."""

from __future__ import annotations

import numpy as np
import pytest

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.paper import PaperOptions, PaperSolution, estimate_paper
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.lines.tracks import LineTracks, make_tracks
from omni_sfm.poses import Trajectory
from omni_sfm.synth.simulate import Simulation, SimulationOptions, simulate
from omni_sfm.vanishing import ParallelFamily, detect_parallel_family


def _side_rays(sim: Simulation) -> np.ndarray:
    """``(K, 3)`` camera-frame rays from each view to the foot of its perpendicular on the line,
    as an image front end knows them (the segment's pixels), in the tracks' observation order."""
    gt = sim.groundtruth
    t = sim.tracks
    p, d = sim.line_points[t.obs_track], sim.line_directions[t.obs_track]
    c = gt.positions[t.obs_frame]
    foot = p + np.sum((c - p) * d, 1, keepdims=True) * d
    ray = np.einsum("kji,kj->ki", gt.rotations[t.obs_frame], foot - c)
    return ray / np.linalg.norm(ray, axis=1, keepdims=True)


def _errors(sol: PaperSolution, sim: Simulation, sign: float = 1.0) -> tuple[float, float,
                                                                               float, float]:
    gt = sim.groundtruth
    est = Trajectory(gt.timestamps.copy(), sol.rotations, sign * sol.positions)
    e = trajectory_errors(est, gt)
    return (float(e.rot_deg.max()), float(e.paper_trans.max()), float(e.rot_deg.mean()),
            float(e.paper_trans.mean()))


def _solve(sim: Simulation, **kw: object) -> PaperSolution:
    fam = detect_parallel_family(sim.tracks)
    return estimate_paper(sim.tracks, fam, side_rays=_side_rays(sim), **kw)  # type: ignore[arg-type]


@pytest.mark.parametrize("kw", [
    dict(num_views=3, num_parallel=3, num_other=3, seed=0),       # the minimal case
    dict(num_views=3, num_parallel=3, num_other=3, seed=1),
    dict(num_views=10, num_parallel=3, num_other=3, seed=2),      # the paper's noise-free case
    dict(num_views=10, num_parallel=3, num_other=3, seed=3),
    dict(num_views=20, num_parallel=20, num_other=20, seed=4),    # Fig. 12 set-up
    dict(num_views=200, num_parallel=10, num_other=5, seed=5),    # the paper's real case
])
def test_noise_free_is_exact(kw: dict) -> None:
    sim = simulate(SimulationOptions(**kw))
    sol = _solve(sim)
    rot_max, trans_max, _, _ = _errors(sol, sim)
    assert rot_max < 1e-6
    assert trans_max < 1e-6
    assert sol.sign_from_rays
    np.testing.assert_array_equal(sol.rotations[0], np.eye(3))
    np.testing.assert_array_equal(sol.positions[0], np.zeros(3))
    # scale convention: the in-plane part of the second view's position has length 1
    v = sol.parallel_direction
    pc = sol.positions[sol.second_view]
    assert abs(np.linalg.norm(pc - (pc @ v) * v) - 1.0) < 1e-9
    # the lines: directions and points on the true lines, in the scaled world
    scale = np.linalg.norm(sim.groundtruth.positions[sol.second_view]
                           - (sim.groundtruth.positions[sol.second_view] @ v) * v)
    d = sol.line_directions
    np.testing.assert_allclose(np.abs(np.sum(d * sim.line_directions, 1)), 1.0, atol=1e-9)
    off = sim.line_points / scale - sol.line_points
    off -= np.sum(off * d, 1, keepdims=True) * d
    assert np.abs(off).max() < 1e-7
    assert sol.costs["rms_deg"] < 1e-6
    np.testing.assert_array_equal(sol.parallel, sim.parallel)


def test_without_rays_the_sign_is_the_point_reflection_ambiguity() -> None:
    """NVs of arbitrary sign fit the scene and its reflection through the first camera equally:
    without rays the result is exact up to that reflection (and says so)."""
    for seed in range(4):
        sim = simulate(SimulationOptions(num_views=10, num_parallel=4, num_other=4, seed=seed))
        sol = estimate_paper(sim.tracks, detect_parallel_family(sim.tracks))
        assert not sol.sign_from_rays
        err = min(_errors(sol, sim, +1.0)[1], _errors(sol.reflected(), sim)[1])
        assert err < 1e-6


def test_alternative_starts_share_world_scale_and_branch() -> None:
    """The alternative starts (translations from other second views) are in the solution's
    world, scale and reflection branch: noise-free they equal it; none with the option off."""
    sim = simulate(SimulationOptions(num_views=20, num_parallel=20, num_other=20, seed=4))
    sol = _solve(sim)
    assert len(sol.alternatives) == PaperOptions().alternative_starts
    for R, c in sol.alternatives:
        np.testing.assert_array_equal(R, sol.rotations)
        assert np.abs(c - sol.positions).max() < 1e-9
    for _, c in sol.reflected().alternatives:
        assert np.abs(c + sol.positions).max() < 1e-9
    assert _solve(sim, options=PaperOptions(alternative_starts=0)).alternatives == ()


@pytest.mark.parametrize("noise", [0.1, 0.5])
def test_noise_fig12_setup(noise: float) -> None:
    """Fig. 12 set-up: 20 views, 40 lines (20 parallel); errors "nearly within the noise"."""
    rot, trans = [], []
    for seed in range(3):
        sim = simulate(SimulationOptions(num_views=20, num_parallel=20, num_other=20,
                                         noise_deg=noise, seed=seed))
        e = _errors(_solve(sim), sim)
        rot.append(e[2])
        trans.append(e[3])
    assert np.mean(rot) <= noise
    # the paper's Fig. 12: translation error (first-to-last = 1) ~0.05 per degree of noise
    assert np.mean(trans) <= 0.1 * noise


def test_weights_drop_a_track() -> None:
    """A wrong track with weight 0 changes nothing; with weight 1 it does."""
    sim = simulate(SimulationOptions(num_views=10, num_parallel=5, num_other=6, seed=6))
    t = sim.tracks
    fam = detect_parallel_family(t)
    bad = t.obs_normal.copy()
    sel = t.obs_track == 8
    rng = np.random.default_rng(0)
    bad[sel] = rng.normal(size=(sel.sum(), 3))
    bad[sel] /= np.linalg.norm(bad[sel], axis=1, keepdims=True)
    tb = LineTracks(t.num_frames, t.track_ids, t.obs_track, t.obs_frame, bad, t.timestamps)
    w = np.ones(t.num_tracks)
    w[8] = 0.0
    sol = estimate_paper(tb, fam, weights=w, side_rays=_side_rays(sim))
    assert max(_errors(sol, sim)[:2]) < 1e-6
    sol_bad = estimate_paper(tb, fam, side_rays=_side_rays(sim))
    assert _errors(sol_bad, sim)[0] > 1e-3


def test_second_view_option() -> None:
    sim = simulate(SimulationOptions(num_views=8, num_parallel=4, num_other=4, seed=7))
    fam = detect_parallel_family(sim.tracks)
    sol = estimate_paper(sim.tracks, fam, PaperOptions(second_view=3), side_rays=_side_rays(sim))
    assert sol.second_view == 3 and sol.rotation_second_view == 3
    assert max(_errors(sol, sim)[:2]) < 1e-6
    with pytest.raises(OmniSfmError, match="second_view"):
        estimate_paper(sim.tracks, fam, PaperOptions(second_view=8))


def _tracks_from_geometry(rot: np.ndarray, pos: np.ndarray, pts: np.ndarray,
                          dirs: np.ndarray, seed: int = 0) -> LineTracks:
    """Noise-free NVs (random signs) of lines ``pts, dirs`` seen from the poses ``rot, pos``."""
    n_world = np.cross(pts[:, None] - pos[None], dirs[:, None])
    n_world /= np.linalg.norm(n_world, axis=-1, keepdims=True)
    n_cam = np.einsum("fji,mfj->mfi", rot, n_world)
    n_cam *= np.random.default_rng(seed).choice([-1.0, 1.0], size=n_cam.shape[:2])[..., None]
    M, F = n_cam.shape[:2]
    mm, ff = np.meshgrid(np.arange(M), np.arange(F), indexing="ij")
    return make_tracks(F, np.arange(M), mm.ravel(), ff.ravel(), n_cam.reshape(-1, 3))


def _corridor(step: np.ndarray) -> LineTracks:
    """A corridor along z: 4 lines along z, 4 across; the camera turns and moves by ``step``."""
    rng = np.random.default_rng(1)
    F = 8
    rot = np.stack([np.eye(3)] * F)
    ang = np.radians(np.linspace(0, 20, F))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1] = (np.cos(ang), -np.sin(ang),
                                                              np.sin(ang), np.cos(ang))
    pos = np.arange(F)[:, None] * step[None]
    pts = np.array([[1.0, 1.0, 0.0], [-1.0, 1.0, 0.0], [1.0, -1.0, 0.0], [-1.0, -1.0, 0.0],
                    [0.0, 1.0, 3.0], [0.0, -1.0, 4.0], [1.0, 0.0, 5.0], [-1.0, 0.0, 6.0]])
    dirs = np.array([[0.0, 0.0, 1.0]] * 4 + [[1.0, 0.0, 0.0]] * 2 + [[0.0, 1.0, 0.0]] * 2)
    dirs[4:] += 0.2 * rng.normal(size=(4, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return _tracks_from_geometry(rot, pos, pts, dirs)


def test_moving_along_the_parallel_lines_is_degenerate() -> None:
    tracks = _corridor(np.array([0.0, 0.0, 0.3]))
    fam = detect_parallel_family(tracks)
    np.testing.assert_array_equal(fam.members, np.arange(8) < 4)
    with pytest.raises(OmniSfmError, match="no motion across the parallel lines"):
        estimate_paper(tracks, fam)
    # a little sideways motion makes it solvable
    ok = _corridor(np.array([0.05, 0.02, 0.3]))
    sol = estimate_paper(ok, detect_parallel_family(ok))
    assert sol.costs["rms_deg"] < 1e-6


def test_standing_still_is_degenerate() -> None:
    tracks = _corridor(np.zeros(3))
    fam = ParallelFamily(np.arange(8) < 4, np.full((8, 3), np.nan), np.zeros(8), np.zeros(8),
                         np.full(8, 4))
    with pytest.raises(OmniSfmError, match="degenerate motion: the camera barely moved"):
        estimate_paper(tracks, fam)


def test_bad_inputs() -> None:
    sim = simulate(SimulationOptions(num_views=6, num_parallel=4, num_other=4, seed=8))
    t = sim.tracks
    fam = detect_parallel_family(t)
    with pytest.raises(OmniSfmError, match="at least 3 parallel"):
        estimate_paper(t, fam, weights=np.array([1, 1, 0, 0, 1, 1, 1, 1.0]))
    with pytest.raises(OmniSfmError, match="not parallel"):
        estimate_paper(t, fam, weights=np.array([1, 1, 1, 1, 0, 0, 1, 1.0]))
    with pytest.raises(OmniSfmError, match="weights"):
        estimate_paper(t, fam, weights=np.ones(3))
    with pytest.raises(OmniSfmError, match="weights"):
        estimate_paper(t, fam, weights=-np.ones(8))
    # fewer than 3 frames
    keep = t.obs_frame < 2
    t2 = make_tracks(2, t.track_ids, t.obs_track[keep], t.obs_frame[keep], t.obs_normal[keep])
    with pytest.raises(OmniSfmError, match="at least 3 frames"):
        estimate_paper(t2, fam.select(frames=np.arange(2)))
    # a track missing from a frame
    drop = ~((t.obs_track == 5) & (t.obs_frame == 3))
    t3 = make_tracks(6, t.track_ids, t.obs_track[drop], t.obs_frame[drop], t.obs_normal[drop])
    with pytest.raises(OmniSfmError, match="every track in every frame.*track 5"):
        estimate_paper(t3, fam)
    # family for other tracks
    with pytest.raises(OmniSfmError, match="family.members"):
        estimate_paper(t, fam.select(tracks=np.arange(7)))
    with pytest.raises(OmniSfmError, match="side_rays"):
        estimate_paper(t, fam, side_rays=np.ones((3, 3)))


@pytest.mark.parametrize("seed", [0, 1])
def test_outlier_tracks_are_down_weighted(seed: int) -> None:
    """15% of the tracks switch to another line midway (wrong correspondences): plain least
    squares is off by degrees; the robust re-solves weight those tracks down and recover."""
    sim = simulate(SimulationOptions(num_views=20, num_parallel=20, num_other=20, noise_deg=0.1,
                                     outlier_fraction=0.15, seed=seed))
    fam = detect_parallel_family(sim.tracks)
    assert not np.any(fam.members & sim.outlier)
    plain = estimate_paper(sim.tracks, fam, PaperOptions(robust_rounds=0),
                           side_rays=_side_rays(sim))
    sol = estimate_paper(sim.tracks, fam, side_rays=_side_rays(sim))
    assert sol.costs["robust_rounds"] >= 1
    assert _errors(plain, sim)[2] > 1.0
    rot_mean, trans_mean = _errors(sol, sim)[2:]
    assert rot_mean < 0.15 and trans_mean < 0.01
    assert sol.weights[sim.outlier].max() < 0.05
    assert sol.weights[~sim.outlier].min() > 0.3
