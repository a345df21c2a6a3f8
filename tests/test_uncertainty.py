"""The pose spread (omni_sfm/estimate/uncertainty.py): the error that the adjustment's
covariance expects of each frame is the error of the adjustment over many noisy runs, it grows
where the lines leave a stretch weak, and the global estimator flags the frames it leaves
unfixed (and no frame of a walk the data fix)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from omni_sfm.estimate.bundle import oracle
from omni_sfm.estimate.pipeline import EstimationOptions, estimate_poses
from omni_sfm.estimate.uncertainty import pose_spread
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.geometry import matrix_to_rotvec, normalize
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.synth.simulate import Simulation, SimulationOptions, simulate

SPREAD_REASON = "covariance expects"


def _walk(views: int, seed: int, noise_deg: float = 0.0) -> Simulation:
    """A corridor walk of the Manhattan world (as tests/test_global_estimator.py's)."""
    return simulate(SimulationOptions(num_views=views, world="manhattan",
                                      path_length=40.0 * views / 600, noise_deg=noise_deg,
                                      seed=seed))


def _noisy(tracks: LineTracks, sigma: float, rng: np.random.Generator) -> LineTracks:
    """The normals moved by Gaussian noise of ``sigma`` radians along each of their two
    tangent axes."""
    n = tracks.obs_normal
    a = normalize(np.cross(n, rng.normal(size=n.shape)))
    b = np.cross(n, a)
    step = sigma * (rng.normal(size=(len(n), 1)) * a + rng.normal(size=(len(n), 1)) * b)
    return replace(tracks, obs_normal=normalize(n + step))


def _spread(sim: Simulation, tracks: LineTracks, sigma: float):
    g = sim.groundtruth
    return pose_spread(tracks, g.rotations, g.positions, sim.line_directions, sim.line_points,
                       np.ones(len(g), bool), np.ones(tracks.num_tracks, bool), sigma)


def test_spread_is_the_error_of_noisy_adjustments() -> None:
    """Twenty noisy copies of a 40-frame walk, each adjusted from the truth and aligned to it
    (the centres by a similarity, the rotations counted from the first frame's, as
    omni_sfm.evaluate counts them): the RMS errors over the runs and frames are the
    covariance's expected errors (within the spread of 20 runs)."""
    sim = _walk(40, seed=2)
    g = sim.groundtruth
    sigma = np.radians(0.1)
    spread = _spread(sim, sim.tracks, sigma)
    rng = np.random.default_rng(0)
    rot, pos = [], []
    for _ in range(20):
        ba = oracle(_noisy(sim.tracks, sigma, rng), g.rotations, g.positions,
                    sim.line_directions, sim.line_points)
        a = trajectory_errors(replace(g, rotations=ba.rotations, positions=ba.positions),
                              g).alignment
        moved = a.scale * ba.positions @ a.rotation.T + a.translation
        pos.append(np.linalg.norm(moved - g.positions, axis=1))
        turn = matrix_to_rotvec(ba.rotations @ np.transpose(g.rotations, (0, 2, 1)))
        rot.append(np.degrees(np.linalg.norm(turn - turn[0], axis=1)))
    r_ratio = np.sqrt(np.mean(np.square(rot))) / np.sqrt(np.mean(spread.rotation_deg**2))
    p_ratio = np.sqrt(np.mean(np.square(pos))) / np.sqrt(np.mean(spread.position**2))
    assert 0.8 < r_ratio < 1.25, r_ratio
    assert 0.8 < p_ratio < 1.25, p_ratio


def test_a_weak_stretch_has_a_large_spread_and_is_flagged() -> None:
    """Frames 50-74 of a 120-frame walk see the lines of one world direction only: their
    spread is many times that of the same frames on the whole walk, and the global estimator
    flags those it poses; on the whole walk it flags no frame by the spread."""
    sim = _walk(120, seed=6, noise_deg=0.1)
    tr = sim.tracks
    axis = np.argmax(np.abs(sim.line_directions), axis=1)
    cut = (tr.obs_frame >= 50) & (tr.obs_frame < 75) & (axis[tr.obs_track] != 0)
    one = tr.keep_observations(~cut)
    sigma = np.radians(0.1)
    whole, weak = _spread(sim, tr, sigma), _spread(sim, one, sigma)
    inside = np.arange(55, 70)
    assert np.median(weak.position[inside]) > 5 * np.median(whole.position[inside])
    opts = EstimationOptions(estimator="global")
    res = estimate_poses(one, opts)
    flags = res.report.frames_uncertain or {}
    posed = {k for k in range(55, 70) if res.estimated[k]}
    assert len(posed) >= 10 and posed <= {int(k) for k in flags}
    flags = estimate_poses(tr, opts).report.frames_uncertain or {}
    assert not [k for k, v in flags.items() if SPREAD_REASON in v]


def test_frames_that_see_one_direction_only_are_left_free() -> None:
    """A walk whose frames see lines of one world direction only, but for frames 20-25 (the
    cell house at 640x320, where only the railings along the walk are tracked): those frames'
    turn about it and their motion along it are free, and although that freedom moves most
    frames, their spread is infinite (not left out as a split into two parts would be)."""
    sim = _walk(60, seed=3)
    tr = sim.tracks
    axis = np.argmax(np.abs(sim.line_directions), axis=1)
    keep = (axis[tr.obs_track] == 0) | ((tr.obs_frame >= 20) & (tr.obs_frame <= 25))
    one = tr.keep_observations(keep)
    spread = _spread(sim, one, np.radians(0.1))
    free = ~np.isfinite(spread.rotation_deg) | ~np.isfinite(spread.position)
    assert free.sum() >= 50
    assert not free[20:26].any()
