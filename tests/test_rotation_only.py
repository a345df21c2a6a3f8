"""The rotation-only estimator: a camera that turns in place (docs/method.md §13)."""

from pathlib import Path

import numpy as np
import pytest
from helpers import assert_every_key_declared

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.pipeline import estimate_poses, write_init_outputs
from omni_sfm.estimate.rotation_only import estimate_rotation_only, procrustes
from omni_sfm.geometry import line_plane_normals, normalize, rotation_about_axis
from omni_sfm.lines.tracks import LineTracks, make_tracks
from omni_sfm.reports import InitReport
from omni_sfm.synth.simulate import SimulationOptions, simulate


def turning(num_frames: int = 90, num_lines: int = 45, noise_deg: float = 0.0,
            visible: int | None = None, outliers: int = 0, sweep_deg: float = 150.0,
            seed: int = 0) -> tuple[LineTracks, np.ndarray]:
    """NVs of random lines (a third vertical) seen by a camera that turns about a fixed centre:
    a yaw sweep with a few degrees of pitch and roll. Returns the tracks and the true
    world_from_cam rotations (world = frame 0)."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, num_frames)
    z, y, x = np.eye(3)[2], np.eye(3)[1], np.eye(3)[0]
    R = (rotation_about_axis(z, np.radians(sweep_deg) * s)
         @ rotation_about_axis(y, np.radians(3.0) * np.sin(6 * s))
         @ rotation_about_axis(x, np.radians(2.0) * np.cos(5 * s)))
    R = np.einsum("ji,fjk->fik", R[0], R)
    dirs = normalize(rng.normal(size=(num_lines, 3)))
    dirs[: num_lines // 3] = [0.0, 0.0, 1.0]
    n = normalize(line_plane_normals(np.zeros(3), 3.0 * rng.normal(size=(num_lines, 3)), dirs))
    obs_t, obs_f, obs_n = [], [], []
    for m in range(num_lines):
        start = 0 if visible is None else int(rng.integers(0, num_frames - visible))
        stop = num_frames if visible is None else start + visible
        for f in range(start, stop):
            v = R[f].T @ n[m] + np.radians(noise_deg) * rng.normal(size=3)
            obs_t.append(m)
            obs_f.append(f)
            obs_n.append(normalize(v) * rng.choice([-1.0, 1.0]))
    normals = np.asarray(obs_n)
    t_arr, f_arr = np.asarray(obs_t), np.asarray(obs_f)
    for m in range(outliers):  # a wrong correspondence: random normals
        sel = t_arr == m
        normals[sel] = normalize(rng.normal(size=(int(sel.sum()), 3)))
    return make_tracks(num_frames, np.arange(num_lines), t_arr, f_arr, normals,
                       np.arange(num_frames, dtype=np.float64), source="test"), R


def rotation_errors_deg(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    d = np.einsum("fji,fjk->fik", est, truth)
    skew = np.stack([d[:, 2, 1] - d[:, 1, 2], d[:, 0, 2] - d[:, 2, 0], d[:, 1, 0] - d[:, 0, 1]], 1)
    return np.degrees(np.arctan2(np.linalg.norm(skew, axis=1) / 2,
                                 (np.trace(d, axis1=1, axis2=2) - 1) / 2))


def in_first_estimated(truth: np.ndarray, estimated: np.ndarray) -> np.ndarray:
    f0 = int(np.flatnonzero(estimated)[0])
    return np.einsum("ji,fjk->fik", truth[f0], truth)[estimated]


def test_procrustes_recovers_a_rotation() -> None:
    rng = np.random.default_rng(1)
    R = rotation_about_axis(normalize(rng.normal(size=3)), 1.1)
    a = normalize(rng.normal(size=(5, 3)))
    assert np.allclose(procrustes(a, a @ R.T, np.ones(5)), R, atol=1e-12)


def test_noise_free_rotations_are_exact() -> None:
    tracks, R = turning()
    res = estimate_rotation_only(tracks)
    assert res.estimated.all()
    assert rotation_errors_deg(res.rotations, R).max() < 1e-6
    assert res.median_deg < 1e-6


def test_short_tracks_noise_and_outliers() -> None:
    tracks, R = turning(num_frames=150, num_lines=90, noise_deg=0.05, visible=30, outliers=6,
                        seed=3)
    res = estimate_rotation_only(tracks)
    # every frame that sees 3 or more lines is estimated, the others say why not
    seen = np.bincount(tracks.obs_frame, minlength=tracks.num_frames)
    assert res.estimated[seen >= 3].all()
    assert sorted(res.reasons) == np.flatnonzero(~res.estimated).tolist()
    assert all("too few" in why for why in res.reasons.values())
    err = rotation_errors_deg(res.rotations[res.estimated], in_first_estimated(R, res.estimated))
    assert err.max() < 0.3, err.max()
    assert res.outliers[:6].all() and not res.outliers[6:].any()


def test_estimate_poses_turns_a_barely_moving_sequence_into_rotations(tmp_path: Path) -> None:
    tracks, R = turning(noise_deg=0.05, seed=5)
    res = estimate_poses(tracks)
    assert res.estimated.all()
    write_init_outputs(tmp_path, res)
    assert_every_key_declared(InitReport, tmp_path / "report.json")
    assert np.all(res.trajectory.positions == 0)
    assert res.report.motion is not None and res.report.motion.kind == "rotation only"
    assert "undetermined" in (res.report.motion.translation or "")
    assert rotation_errors_deg(res.trajectory.rotations, R).max() < 0.3
    # the vertical lines are found as the parallel family, pointing along world +-z
    assert abs(res.parallel_direction[2]) > 0.999


def test_translating_sequences_are_not_taken_for_rotation() -> None:
    sim = simulate(SimulationOptions(num_views=20, noise_deg=0.05, seed=2))
    assert estimate_rotation_only(sim.tracks).median_deg > 1.0
    res = estimate_poses(sim.tracks)
    assert not res.report.rotation_only
    assert np.linalg.norm(res.trajectory.positions[-1]) == pytest.approx(1.0)


def test_no_lines_to_start_from_is_an_error() -> None:
    tracks, _ = turning(num_lines=1)
    with pytest.raises(OmniSfmError, match="nothing to fix a rotation"):
        estimate_rotation_only(tracks)
