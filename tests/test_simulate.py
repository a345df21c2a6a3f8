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
