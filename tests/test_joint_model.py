"""The joint adjustment on a COLMAP model (omni_sfm.refine.joint_model): the frames the mapper
registered are adjusted with the init's, in one frame."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap

from omni_sfm.cameras import load_camera
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.export.colmap import build_reconstruction, trajectory_from_reconstruction
from omni_sfm.geometry import rotvec_to_matrix
from omni_sfm.lines3d import LineSegments3D
from omni_sfm.poses import Trajectory
from omni_sfm.refine.joint import JointOptions, points_seen
from omni_sfm.refine.joint_model import LineEvidence, adjust_model
from omni_sfm.synth.simulate import SimulationOptions, simulate

EXAMPLES = Path(__file__).resolve().parents[1] / "docs" / "examples" / "cameras"
REGISTERED = (12, 29)  # the mapper's frames; the tracks end before frame 29


def _model(camera, truth: Trajectory, poses: Trajectory, X: np.ndarray) -> pycolmap.Reconstruction:
    """Every frame an image at ``poses`` that sees each point of ``X`` exactly (``truth``)."""
    export = camera.colmap_export()
    F, P = len(truth), len(X)
    rec = build_reconstruction(camera, poses, [f"{k:06d}.png" for k in range(F)]).reconstruction
    f, j = np.repeat(np.arange(F), P), np.tile(np.arange(P), F)
    xy = export.pixels_to_colmap(camera.pixels_from_rays(
        points_seen(truth.rotations, truth.positions, X, f, j))).reshape(F, P, 2)
    for k in range(F):
        rec.images[k + 1].points2D = pycolmap.Point2DList([pycolmap.Point2D(u) for u in xy[k]])
    for q in range(P):
        track = pycolmap.Track()
        for k in range(F):
            track.add_element(k + 1, q)
        rec.add_point3D(X[q] + 0.02, track)
    return rec


def test_the_mappers_frames_are_adjusted_with_the_inits() -> None:
    """Noise-free lines and points, every pose off by about 0.5 deg and 1 cm: the init's
    frames and the two the mapper registered (one of them beyond the line tracks) all come
    out exact, in one frame; held at their mapper poses, the two would stay 0.5 deg off."""
    sim = simulate(SimulationOptions(num_views=30, num_parallel=6, num_other=6,
                                     noise_deg=0.0, seed=1))
    truth = sim.groundtruth
    camera = load_camera(EXAMPLES / "equirectangular.yaml")
    rng = np.random.default_rng(1)
    X = rng.uniform(-3.0, 3.0, (40, 3))
    F = len(truth)
    R = truth.rotations @ rotvec_to_matrix(rng.normal(0, np.radians(0.5), (F, 3)))
    c = truth.positions + rng.normal(0, 0.01, (F, 3))
    R[0], c[0] = truth.rotations[0], truth.positions[0]
    poses = Trajectory(truth.timestamps, R, c)
    rec = _model(camera, truth, poses, X)
    t = sim.tracks  # the line tracks end one frame early: frame 29 is seen by points only
    seen = t.obs_frame < F - 1
    tracks = replace(t, num_frames=F - 1, timestamps=t.timestamps[:F - 1],
                     obs_track=t.obs_track[seen], obs_frame=t.obs_frame[seen],
                     obs_normal=t.obs_normal[seen],
                     obs_ray=None if t.obs_ray is None else t.obs_ray[seen],
                     obs_sigma=None if t.obs_sigma is None else t.obs_sigma[seen])
    init = np.array([k for k in range(F) if k not in REGISTERED])
    lines = LineEvidence(tracks, sim.line_directions + 0.01, sim.line_points + 0.01, init,
                         LineSegments3D.empty())
    names = [f"{k:06d}.png" for k in REGISTERED]
    res, report = adjust_model(rec, [int(k) + 1 for k in init], poses.subset(init), lines,
                               camera, JointOptions(line_noise_deg=0.01, point_noise_deg=0.01),
                               registered=names,
                               registered_timestamps=truth.timestamps[list(REGISTERED)])
    out, ok = trajectory_from_reconstruction(rec, camera.colmap_export(),
                                             [f"{k:06d}.png" for k in range(F)],
                                             truth.timestamps)
    assert ok.all()
    err = trajectory_errors(out, truth)
    assert err.rot_max_deg < 1e-5 and err.ate_rel < 1e-6, err
    assert res.frames.sum() == F and res.rotations.shape[0] == F  # one frame appended
    reg = report.registered_frames
    assert reg is not None and reg.names == names
    ev = reg.evidence_per_frame
    assert ev.lines[0] > 0 and ev.lines[1] == 0 and min(ev.points) == len(X)
    assert min(c for c in ev.rotation_change_deg if c is not None) > 0.1  # moved, not held
    assert report.evidence_per_frame is not None
    assert len(report.evidence_per_frame.lines) == len(init)
