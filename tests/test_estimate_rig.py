"""A rig of lenses (raw dual-fisheye frames): every observation taken from its lens's centre."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.bundle import LineProblem
from omni_sfm.estimate.pipeline import EstimationOptions, estimate_poses
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.geometry import normalize, predicted_normals, rotvec_to_matrix
from omni_sfm.lines.tracks import LineTracks, make_tracks, read_tracks, write_tracks
from omni_sfm.synth.simulate import SimulationOptions, simulate


def test_the_adjustment_jacobian_carries_the_lens_offsets() -> None:
    """Finite differences of the residuals with lens offsets match the Jacobian (the offset
    turns with the rig: its centre columns enter the rotation's)."""
    rng = np.random.default_rng(0)
    F, M = 4, 6
    R = np.stack([rotvec_to_matrix(rng.normal(0, 0.3, 3)) for _ in range(F)])
    c = rng.normal(0, 1, (F, 3))
    d = normalize(rng.normal(0, 1, (M, 3)))
    p = rng.normal(0, 3, (M, 3))
    p -= np.sum(p * d, 1, keepdims=True) * d
    t, f = np.repeat(np.arange(M), F), np.tile(np.arange(F), M)
    tr = make_tracks(F, np.arange(M), t, f, normalize(rng.normal(0, 1, (len(t), 3))),
                     obs_offset=rng.normal(0, 0.3, (len(t), 3)))
    prob = LineProblem(tr, np.ones(F, bool), np.ones(M, bool), 0, 1, 0, hold_rotation=False)
    prob.pose_free[:] = True
    e0, u0 = prob.residuals(R, c, d, p)
    Jp, Jl = prob.jacobian(R, c, d, p, u0)
    h = 1e-7
    for fr in range(F):
        for j in range(6):
            step = np.zeros((F, 6))
            step[fr, j] = h
            e1, _ = prob.residuals(*prob._moved(R, c, d, p, step, np.zeros((M, 4))))
            ana = np.where((tr.obs_frame == fr)[:, None], Jp[:, :, j], 0.0)
            assert np.abs((e1 - e0) / h - ana).max() < 1e-5
    for m in range(M):
        for j in range(4):
            step = np.zeros((M, 4))
            step[m, j] = h
            e1, _ = prob.residuals(*prob._moved(R, c, d, p, np.zeros((F, 6)), step))
            ana = np.where((tr.obs_track == m)[:, None], Jl[:, :, j], 0.0)
            assert np.abs((e1 - e0) / h - ana).max() < 1e-5


def _rig_walk(seed: int, noise_deg: float, baseline: float = 0.04
              ) -> tuple[LineTracks, object]:
    """Simulated tracks of a back-to-back dual fisheye ``baseline`` metres long: each line seen
    by the lens its closest point faces (lens 0 at z = +b/2 looks along +z)."""
    sim = simulate(SimulationOptions(num_views=60, seed=seed, path_length=8.0,
                                     line_distance=(1.0, 4.0), visible_frames=15))
    tr, gt = sim.tracks, sim.groundtruth
    f, t = tr.obs_frame, tr.obs_track
    p, d = sim.line_points[t], sim.line_directions[t]
    q = p - gt.positions[f]
    q -= np.sum(q * d, 1, keepdims=True) * d
    ray = normalize(np.einsum("kji,kj->ki", gt.rotations[f], q))
    off = np.zeros((len(f), 3))
    off[:, 2] = np.where(ray[:, 2] >= 0, baseline / 2, -baseline / 2)
    centres = gt.positions[f] + np.einsum("kij,kj->ki", gt.rotations[f], off)
    n = normalize(predicted_normals(gt.rotations[f], centres, p, d))
    rng = np.random.default_rng(seed)
    b1 = normalize(np.cross(n, rng.normal(size=n.shape)))
    a = np.radians(noise_deg) * rng.normal(size=(len(n), 2))
    n = normalize(n + a[:, :1] * b1 + a[:, 1:] * np.cross(n, b1))
    return replace(tr, obs_normal=n, obs_ray=ray, obs_sigma=None, obs_offset=off), gt


def test_lens_offsets_make_a_dual_fisheye_exact_where_one_centre_is_not() -> None:
    """With 0.001 deg noise the rig's poses come out 10x closer to the truth than those of
    the same observations taken from one centre (4 cm between the lenses, lines 1-4 m), and
    its metric scale within 1 %."""
    tracks, gt = _rig_walk(0, 0.001)
    opts = EstimationOptions(estimator="global", progress=False)
    rig = estimate_poses(tracks, opts)
    central = estimate_poses(replace(tracks, obs_offset=None), opts)
    e_rig = trajectory_errors(rig.trajectory, gt)  # type: ignore[arg-type]
    e_one = trajectory_errors(central.trajectory, gt)  # type: ignore[arg-type]
    assert e_rig.rot_deg.max() < 0.05 and e_rig.ate_rel < 2e-4
    assert e_one.rot_deg.mean() > 10 * e_rig.rot_deg.mean()
    assert rig.report.rig is not None and rig.report.rig.metres_per_unit is not None
    # the adjustment in metres: the baseline between the lenses gives the metric scale
    span = float(np.linalg.norm(gt.positions[-1] - gt.positions[0]))  # type: ignore[attr-defined]
    assert abs(rig.report.rig.metres_per_unit / span - 1.0) < 0.01
    assert rig.report.rig.fixed is True
    assert central.report.rig is None
    assert rig.report.estimator_choice == "asked for"


def test_offsets_survive_the_tracks_file_and_the_windows_refuse_them(tmp_path: Path) -> None:
    tracks, _ = _rig_walk(1, 0.01)
    write_tracks(tmp_path / "tracks.json", tracks)
    back = read_tracks(tmp_path / "tracks.json")
    assert back.obs_offset is not None
    assert np.array_equal(back.obs_offset, tracks.as_written().obs_offset)
    assert np.allclose(back.obs_offset, tracks.obs_offset, atol=1e-12)
    with pytest.raises(OmniSfmError, match="the paper's method takes a central camera"):
        estimate_poses(tracks, EstimationOptions(estimator="paper", progress=False))


def test_a_rendered_dual_fisheye_walk_end_to_end(tmp_path: Path) -> None:
    """Rendered raw dual-fisheye frames (two 200 deg lenses of 480 x 480 side by side, 4 cm
    apart, a 1.5 m corridor walk): ``init`` poses every frame within 0.5 deg and 1 % ATE, its
    metric scale within 5 %, and the COLMAP rig it writes reads back in pycolmap with the
    same poses (COLMAP's rig frame is lens 0's)."""
    import pycolmap

    from omni_sfm.cli import main
    from omni_sfm.folders import InitFolder
    from omni_sfm.poses import read_tum

    render, init = tmp_path / "r", tmp_path / "init"
    assert main(["render", "-o", str(render), "--scene", "corridor", "--camera", "dual-fisheye",
                 "--width", "960", "--height", "480", "--frames", "30"]) == 0
    assert main(["init", "--lines", "--images", str(render / "images"), "--camera",
                 str(render / "camera.yaml"), "-o", str(init), "--quiet"]) == 0
    traj, gt = read_tum(init / "trajectory.tum"), read_tum(render / "groundtruth.tum")
    assert len(traj) == 30  # every frame trusted
    e = trajectory_errors(traj, gt)
    assert e.rot_deg.max() < 0.5 and e.ate_rel < 0.01
    report = InitFolder(init).read_report()
    assert report.rig is not None and report.rig.metres_per_unit is not None
    span = float(np.linalg.norm(gt.positions[-1] - gt.positions[0]))
    assert abs(report.rig.metres_per_unit / span - 1.0) < 0.05
    # COLMAP: frame k's rig (lens 0) centre is the rig's centre plus lens 0's offset
    rec = pycolmap.Reconstruction(str(init / "sparse"))
    assert len(rec.rigs) == 1 and len(rec.cameras) == 2 and len(rec.images) == 60
    lens0 = np.array([0.0, 0.0, 0.02]) / report.rig.metres_per_unit
    frames = sorted(rec.frames.values(), key=lambda fr: fr.frame_id)
    for k, fr in enumerate(frames):
        pose = fr.rig_from_world
        centre = -pose.rotation.matrix().T @ pose.translation
        assert np.allclose(centre, traj.positions[k] + traj.rotations[k] @ lens0, atol=1e-9)
