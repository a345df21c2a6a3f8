"""The shared foundation: geometry, trajectories and TUM files, errors, tracks, simulation."""

from __future__ import annotations

import json

import numpy as np
import pytest

from omni_sfm.errors import OmniSfmError
from omni_sfm.evaluate import trajectory_errors, umeyama
from omni_sfm.geometry import rotation_angle, rotvec_to_matrix
from omni_sfm.lines.tracks import read_tracks, write_tracks
from omni_sfm.poses import Trajectory, read_tum, write_tum
from omni_sfm.synth.simulate import SimulationOptions, simulate


def _random_traj(n: int, seed: int) -> Trajectory:
    rng = np.random.default_rng(seed)
    return Trajectory(np.arange(n, dtype=float), rotvec_to_matrix(rng.normal(size=(n, 3))),
                      rng.normal(size=(n, 3)))


def test_tum_round_trip(tmp_path):
    tr = _random_traj(7, 0)
    write_tum(tmp_path / "t.tum", tr)
    back = read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(back.positions, tr.positions, atol=1e-15)
    assert rotation_angle(np.swapaxes(back.rotations, 1, 2) @ tr.rotations).max() < 1e-12


@pytest.mark.parametrize("text,msg", [("0 1 2 3\n", "expected 8 numbers"),
                                      ("0 1 2 3 0 0 0 x\n", "not a number"),
                                      ("0 1 2 3 0 0 0 0\n", "zero quaternion"),
                                      ("# only a comment\n", "no poses")])
def test_tum_errors(tmp_path, text, msg):
    p = tmp_path / "bad.tum"
    p.write_text(text)
    with pytest.raises(OmniSfmError, match=msg):
        read_tum(p)


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(20, 3))
    R = rotvec_to_matrix(np.array([0.3, -0.2, 0.9]))
    y = 2.5 * x @ R.T + np.array([1.0, -2.0, 0.5])
    sim = umeyama(x, y)
    assert sim.scale == pytest.approx(2.5)
    np.testing.assert_allclose(sim.apply_points(x), y, atol=1e-12)


def test_errors_zero_for_similar_trajectory():
    gt = _random_traj(10, 2)
    R = rotvec_to_matrix(np.array([0.1, 0.2, 0.3]))
    est = Trajectory(gt.timestamps, R @ gt.rotations, 0.5 * gt.positions @ R.T + 3.0)
    err = trajectory_errors(est, gt)
    assert err.rot_max_deg < 1e-10 and err.ate_rel < 1e-12 and err.paper_trans.max() < 1e-12


def test_simulated_normals_are_orthogonal_to_lines():
    sim = simulate(SimulationOptions(num_views=8, num_parallel=3, num_other=3, seed=3))
    tr, gt = sim.tracks, sim.groundtruth
    n_world = np.einsum("kij,kj->ki", gt.rotations[tr.obs_frame], tr.obs_normal)
    d = sim.line_directions[tr.obs_track]
    to_line = sim.line_points[tr.obs_track] - gt.positions[tr.obs_frame]
    assert np.abs(np.sum(n_world * d, axis=1)).max() < 1e-12
    assert np.abs(np.sum(n_world * to_line, axis=1)).max() < 1e-12
    np.testing.assert_allclose(gt.rotations[0], np.eye(3), atol=1e-12)


def test_partial_visibility_window():
    sim = simulate(SimulationOptions(num_views=120, num_parallel=10, num_other=10,
                                     visible_frames=30, seed=4))
    counts = sim.tracks.visibility().sum(axis=1)
    assert counts.max() <= 30 and counts.min() >= 29


def test_tracks_round_trip_and_errors(tmp_path):
    sim = simulate(SimulationOptions(num_views=5, num_parallel=3, num_other=3, seed=5))
    write_tracks(tmp_path / "tracks.json", sim.tracks)
    back = read_tracks(tmp_path / "tracks.json")
    np.testing.assert_allclose(back.obs_normal, sim.tracks.obs_normal, atol=1e-14)
    data = json.loads((tmp_path / "tracks.json").read_text())
    data["tracks"][1]["normals"][0] = [1.0, 1.0, 0.0]
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(OmniSfmError, match="unit vectors"):
        read_tracks(tmp_path / "bad.json")
    (tmp_path / "broken.json").write_text("{")
    with pytest.raises(OmniSfmError, match="malformed tracks file"):
        read_tracks(tmp_path / "broken.json")
    data["tracks"][1]["normals"][0] = [0.0, 0.0, 1.0]
    data["tracks"][1]["frames"][0] = 99
    (tmp_path / "range.json").write_text(json.dumps(data))
    with pytest.raises(OmniSfmError, match="outside"):
        read_tracks(tmp_path / "range.json")


def test_atomic_outputs_have_ordinary_permissions(tmp_path):
    import os
    import stat

    from omni_sfm.fileio import atomic_output_dir, atomic_write_text

    old = os.umask(0o022)
    try:
        with atomic_output_dir(tmp_path / "out") as d:
            atomic_write_text(d / "a.txt", "x")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "out").stat().st_mode) == 0o755
    assert stat.S_IMODE((tmp_path / "out" / "a.txt").stat().st_mode) == 0o644


def test_atomic_output_dir_leaves_nothing_on_failure(tmp_path):
    from omni_sfm.fileio import atomic_output_dir

    with pytest.raises(RuntimeError), atomic_output_dir(tmp_path / "out") as d:
        (d / "partial.txt").write_text("half")
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_tracks_rays_round_trip_and_checks(tmp_path):
    from omni_sfm.lines.tracks import make_tracks

    n = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    r = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    tr = make_tracks(3, np.array([7]), np.zeros(3, int), np.array([2, 0, 1]), n, obs_ray=r)
    np.testing.assert_allclose(tr.obs_ray, r[[1, 2, 0]])  # sorted with the normals
    write_tracks(tmp_path / "t.json", tr)
    back = read_tracks(tmp_path / "t.json")
    np.testing.assert_allclose(back.obs_ray, tr.obs_ray)
    np.testing.assert_allclose(back.select_tracks(np.array([0])).obs_ray, tr.obs_ray)
    with pytest.raises(OmniSfmError, match="does not lie in its line's plane"):
        make_tracks(3, np.array([7]), np.zeros(3, int), np.arange(3), n, obs_ray=n)
    data = json.loads((tmp_path / "t.json").read_text())
    data["tracks"].append({"id": 8, "frames": [0], "normals": [[0.0, 0.0, 1.0]]})
    (tmp_path / "mixed.json").write_text(json.dumps(data))
    with pytest.raises(OmniSfmError, match="all tracks or for none"):
        read_tracks(tmp_path / "mixed.json")


def test_ray_line_closest_against_brute_force():
    from omni_sfm.geometry import normalize, ray_line_closest

    rng = np.random.default_rng(7)
    o, p = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    r, d = normalize(rng.normal(size=(50, 3))), normalize(rng.normal(size=(50, 3)))
    s, u, den = ray_line_closest(o, r, p, d)
    # at the closest points the connecting vector is perpendicular to both
    gap = (o + s[:, None] * r) - (p + u[:, None] * d)
    assert np.abs(np.sum(gap * r, axis=1)).max() < 1e-9
    assert np.abs(np.sum(gap * d, axis=1)).max() < 1e-9
    np.testing.assert_allclose(den, 1 - np.sum(r * d, axis=1) ** 2)


def test_tracks_sigmas_round_trip_and_checks(tmp_path):
    from omni_sfm.lines.tracks import make_tracks

    n = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    r = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    s = np.radians([[0.01, 0.1], [0.02, 0.2], [0.03, 0.3]])
    tr = make_tracks(3, np.array([7]), np.zeros(3, int), np.array([2, 0, 1]), n, obs_ray=r,
                     obs_sigma=s)
    np.testing.assert_allclose(tr.obs_sigma, s[[1, 2, 0]])  # sorted with the normals
    write_tracks(tmp_path / "t.json", tr)
    back = read_tracks(tmp_path / "t.json")
    np.testing.assert_allclose(back.obs_sigma, tr.obs_sigma, rtol=1e-8)
    np.testing.assert_allclose(back.select_tracks(np.array([0])).obs_sigma, tr.obs_sigma)
    with pytest.raises(OmniSfmError, match="sigmas need rays"):
        make_tracks(3, np.array([7]), np.zeros(3, int), np.arange(3), n, obs_sigma=s)
    with pytest.raises(OmniSfmError, match="finite and positive"):
        make_tracks(3, np.array([7]), np.zeros(3, int), np.arange(3), n, obs_ray=r,
                    obs_sigma=-s)
    data = json.loads((tmp_path / "t.json").read_text())
    data["tracks"][0]["sigmas_deg"] = [[0.1, 0.2]]
    (tmp_path / "short.json").write_text(json.dumps(data))
    with pytest.raises(OmniSfmError, match="one \\[along, across\\] pair"):
        read_tracks(tmp_path / "short.json")
