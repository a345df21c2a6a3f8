"""The simulator and ``omni-sfm simulate``: files, ground truth, noise, outliers, visibility."""

from __future__ import annotations

import json

import numpy as np
import pytest

from omni_sfm.cli import main
from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import angle_between, normalize
from omni_sfm.lines.tracks import read_tracks
from omni_sfm.poses import read_tum
from omni_sfm.synth.simulate import SimulationOptions, simulate


def _clean_normals(sim):
    g, tr = sim.groundtruth, sim.tracks
    t, f = tr.obs_track, tr.obs_frame
    n_w = normalize(np.cross(sim.line_points[t] - g.positions[f], sim.line_directions[t]))
    return np.einsum("kji,kj->ki", g.rotations[f], n_w)


def test_cli_writes_files_matching_the_library(tmp_path):
    out = tmp_path / "s"
    assert main(["simulate", "--output", str(out), "--views", "15", "--parallel", "4",
                 "--other", "5", "--noise-deg", "0.2", "--outliers", "0.2",
                 "--visible-frames", "8", "--seed", "9"]) == 0
    sim = simulate(SimulationOptions(num_views=15, num_parallel=4, num_other=5, noise_deg=0.2,
                                     outlier_fraction=0.2, visible_frames=8, seed=9))
    tr = read_tracks(out / "tracks.json")
    np.testing.assert_array_equal(tr.obs_frame, sim.tracks.obs_frame)
    np.testing.assert_allclose(tr.obs_normal, sim.tracks.obs_normal, atol=1e-14)
    gt = read_tum(out / "groundtruth.tum")
    np.testing.assert_allclose(gt.positions, sim.groundtruth.positions, atol=1e-14)
    lines = json.loads((out / "lines.json").read_text())
    assert [ln["parallel"] for ln in lines["lines"]] == sim.parallel.tolist()
    assert sum(ln["outlier"] for ln in lines["lines"]) == 2
    assert main(["simulate", "--output", str(out)]) == 2  # exists, no --overwrite


def test_ground_truth_world_is_first_camera_and_normals_exact():
    sim = simulate(SimulationOptions(num_views=10, seed=1))
    g = sim.groundtruth
    np.testing.assert_allclose(g.rotations[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(g.positions[0], 0, atol=1e-12)
    ang = angle_between(sim.tracks.obs_normal, _clean_normals(sim), unsigned_lines=True)
    assert ang.max() < 1e-9
    assert abs(g.path_length() - 1.0) < 0.6
    assert np.all(np.abs(sim.line_directions[sim.parallel] @ sim.parallel_direction) > 1 - 1e-12)


def test_noise_level():
    sim = simulate(SimulationOptions(num_views=50, noise_deg=0.5, seed=2))
    ang = np.degrees(angle_between(sim.tracks.obs_normal, _clean_normals(sim),
                                   unsigned_lines=True))
    # |N(0, s)| has mean s sqrt(2/pi)
    assert abs(ang.mean() - 0.5 * np.sqrt(2 / np.pi)) < 0.02


def test_partial_visibility_windows():
    sim = simulate(SimulationOptions(num_views=300, num_parallel=30, num_other=30,
                                     visible_frames=40, seed=3))
    vis = sim.tracks.visibility()
    assert np.all(vis.sum(1) == 40)
    # each track is seen in one run of consecutive frames
    assert np.all(np.abs(np.diff(vis.astype(int), axis=1)).sum(1) <= 2)
    # both kinds are spread along the path: every frame sees some of each
    assert vis[sim.parallel].sum(0).min() >= 2 and vis[~sim.parallel].sum(0).min() >= 2


@pytest.mark.parametrize("kw,msg", [({"num_views": 2}, "at least 3 views"),
                                    ({"noise_deg": -1.0}, "noise"),
                                    ({"outlier_fraction": 1.0}, "outlier fraction"),
                                    ({"visible_frames": 2}, "visible frames")])
def test_bad_options(kw, msg):
    with pytest.raises(OmniSfmError, match=msg):
        simulate(SimulationOptions(**kw))


# --- sparse generation and the Manhattan world -------------------------------------------------

def _manhattan(**kw):
    kw = {"world": "manhattan", "num_views": 1200, "path_length": 0.05 * 1199, "seed": 4} | kw
    return simulate(SimulationOptions(**kw))


def _in_plane_residuals(sim):
    """``|n . R^T (p - c)|`` and ``|n . R^T d|`` of every observation: 0 when the normal is
    orthogonal to the plane through the camera centre and the true line."""
    g, tr = sim.groundtruth, sim.tracks
    t, f = tr.obs_track, tr.obs_frame
    to_p = np.einsum("kji,kj,ki->k", g.rotations[f], sim.line_points[t] - g.positions[f],
                     tr.obs_normal)
    along = np.einsum("kji,kj,ki->k", g.rotations[f], sim.line_directions[t], tr.obs_normal)
    return np.abs(to_p), np.abs(along)


def test_sparse_random_world_is_the_dense_one_up_to_signs():
    kw = {"num_views": 300, "num_parallel": 30, "num_other": 30, "visible_frames": 40,
          "outlier_fraction": 0.2, "seed": 3}
    dense = simulate(SimulationOptions(**kw))
    sparse = simulate(SimulationOptions(sparse=True, **kw))
    np.testing.assert_array_equal(sparse.tracks.obs_track, dense.tracks.obs_track)
    np.testing.assert_array_equal(sparse.tracks.obs_frame, dense.tracks.obs_frame)
    np.testing.assert_array_equal(sparse.outlier, dense.outlier)
    np.testing.assert_array_equal(sparse.groundtruth.positions, dense.groundtruth.positions)
    dot = np.sum(sparse.tracks.obs_normal * dense.tracks.obs_normal, axis=1)
    np.testing.assert_allclose(np.abs(dot), 1.0, atol=1e-12)
    assert 0.2 < np.mean(dot > 0) < 0.8  # signs drawn afresh
    # every line in every frame: the same random draws, the same output
    kw = {"num_views": 20, "noise_deg": 0.3, "outlier_fraction": 0.1, "seed": 1}
    np.testing.assert_array_equal(simulate(SimulationOptions(sparse=True, **kw)).tracks.obs_normal,
                                  simulate(SimulationOptions(**kw)).tracks.obs_normal)


def test_manhattan_is_deterministic():
    a, b, c = _manhattan(noise_deg=0.1), _manhattan(noise_deg=0.1), _manhattan(seed=5)
    np.testing.assert_array_equal(a.tracks.obs_frame, b.tracks.obs_frame)
    np.testing.assert_array_equal(a.tracks.obs_normal, b.tracks.obs_normal)
    np.testing.assert_array_equal(a.groundtruth.positions, b.groundtruth.positions)
    np.testing.assert_array_equal(a.line_points, b.line_points)
    assert not np.array_equal(a.groundtruth.positions, c.groundtruth.positions)


def test_manhattan_ground_truth_and_exact_normals():
    sim = _manhattan()
    g = sim.groundtruth
    np.testing.assert_allclose(g.rotations[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(g.positions[0], 0, atol=1e-12)
    to_p, along = _in_plane_residuals(sim)
    assert to_p.max() < 1e-9 and along.max() < 1e-12
    # constant speed along a route of path_length metres (plus sway and bob)
    step = np.linalg.norm(np.diff(g.positions, axis=0), axis=1)
    assert abs(step.mean() - 0.05) < 0.005 and step.max() < 0.08
    assert abs(g.path_length() - 0.05 * 1199) < 3.0
    # the vertical family is world up; every line lies in one of 3 orthogonal directions
    up = sim.parallel_direction
    assert np.all(np.abs(sim.line_directions[sim.parallel] @ up) > 1 - 1e-12)
    assert np.all(np.abs(sim.line_directions[~sim.parallel] @ up) < 1e-12)
    assert abs(np.linalg.norm(up) - 1) < 1e-12 and up[2] > 0.99  # camera z is about up
    horiz = np.abs(sim.line_directions[~sim.parallel] @ sim.line_directions[~sim.parallel][0])
    assert np.all((horiz < 1e-12) | (horiz > 1 - 1e-12))
    assert 0.35 < sim.parallel.mean() < 0.65
    assert np.all(np.diff(sim.parallel.astype(int)) <= 0)  # parallel lines first
    # the camera stays upright (pitch and roll a few degrees), lines mostly 1 to 3 m away
    tilt = np.degrees(np.arccos(np.clip(g.rotations[:, 2, 2], -1, 1)))
    assert tilt.max() < 8.0
    tr = sim.tracks
    dist = np.linalg.norm(np.cross(sim.line_points[tr.obs_track] - g.positions[tr.obs_frame],
                                   sim.line_directions[tr.obs_track]), axis=1)
    assert dist.min() > 0.1 and np.percentile(dist, 1) > 0.8 and dist.max() < 3.5
    assert 0.9 < np.median(dist) < 1.6


def test_manhattan_visibility():
    sim = _manhattan(visible_frames=50)
    tr = sim.tracks
    per_frame = np.bincount(tr.obs_frame, minlength=tr.num_frames)
    vertical = np.bincount(tr.obs_frame[sim.parallel[tr.obs_track]], minlength=tr.num_frames)
    assert per_frame.min() >= 2 and per_frame.max() <= 30 and 6 <= np.median(per_frame) <= 15
    assert np.mean(vertical >= 2) > 0.95 and np.median(vertical) >= 4
    per_line = np.bincount(tr.obs_track)
    assert per_line.min() >= 3 and abs(np.median(per_line) - 50) <= 5
    # each line is seen in one run of consecutive frames (but for a rare one seen end-on)
    first = np.full(tr.num_tracks, tr.num_frames)
    np.minimum.at(first, tr.obs_track, tr.obs_frame)
    last = np.zeros(tr.num_tracks, dtype=int)
    np.maximum.at(last, tr.obs_track, tr.obs_frame)
    assert np.mean(last - first + 1 == per_line) > 0.98
    # more lines per metre, more lines per frame
    denser = _manhattan(visible_frames=50, line_density=7.0)
    assert 1.6 < denser.tracks.num_tracks / tr.num_tracks < 2.4


def test_manhattan_noise_and_outliers():
    sim = _manhattan(noise_deg=0.5, outlier_fraction=0.1)
    clean = _manhattan(outlier_fraction=0.1)
    assert sim.outlier.sum() == round(0.1 * sim.tracks.num_tracks)
    np.testing.assert_array_equal(sim.outlier, clean.outlier)
    tr = sim.tracks
    ok = ~sim.outlier[tr.obs_track]
    ang = np.degrees(angle_between(tr.obs_normal, _clean_normals(sim), unsigned_lines=True))
    assert abs(ang[ok].mean() - 0.5 * np.sqrt(2 / np.pi)) < 0.02
    # an outlier track switches to another line part-way: its later normals are off its line
    to_p, _ = _in_plane_residuals(clean)
    bad = to_p > 1e-6
    assert not bad[~clean.outlier[clean.tracks.obs_track]].any()
    frac = np.bincount(clean.tracks.obs_track, weights=bad) / np.bincount(clean.tracks.obs_track)
    assert np.all((frac[clean.outlier] > 0.15) & (frac[clean.outlier] < 0.85))


def test_manhattan_20000_frames_is_light():
    import time
    import tracemalloc

    tracemalloc.start()
    try:
        t0 = time.perf_counter()
        sim = _manhattan(num_views=20_000, path_length=1000.0, noise_deg=0.1, seed=0)
        elapsed = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    tr = sim.tracks
    assert tr.num_frames == 20_000 and len(sim.groundtruth) == 20_000
    assert 2500 < tr.num_tracks < 5000 and 150_000 < tr.num_observations < 300_000
    assert np.bincount(tr.obs_frame, minlength=20_000).min() >= 2
    assert peak < 500e6 and elapsed < 8.0


def test_cli_manhattan(tmp_path):
    out = tmp_path / "m"
    assert main(["simulate", "--world", "manhattan", "--output", str(out), "--views", "300",
                 "--noise-deg", "0.1", "--visible-frames", "40", "--seed", "2"]) == 0
    sim = simulate(SimulationOptions(world="manhattan", num_views=300, path_length=0.05 * 299,
                                     noise_deg=0.1, visible_frames=40, seed=2))
    tr = read_tracks(out / "tracks.json")
    np.testing.assert_array_equal(tr.obs_frame, sim.tracks.obs_frame)
    np.testing.assert_allclose(tr.obs_normal, sim.tracks.obs_normal, atol=1e-14)
    gt = read_tum(out / "groundtruth.tum")
    np.testing.assert_allclose(gt.positions, sim.groundtruth.positions, atol=1e-14)
    lines = json.loads((out / "lines.json").read_text())
    assert lines["options"]["world"] == "manhattan"
    assert [ln["parallel"] for ln in lines["lines"]] == sim.parallel.tolist()


@pytest.mark.parametrize("kw,msg", [({"world": "moon"}, "world must be one of"),
                                    ({"world": "manhattan", "num_views": 20_000},
                                     "route length in metres"),
                                    ({"world": "manhattan", "line_density": 0.0},
                                     "line density")])
def test_bad_world_options(kw, msg):
    with pytest.raises(OmniSfmError, match=msg):
        simulate(SimulationOptions(**kw))
