"""Hand-held footage (docs/frontend.md, "Automatic mask"): the hand that holds the camera
wobbles a few pixels with it, and people walk past.

- A textured office walk (equirectangular 384x192, 16 frames) with the renderer's operator
  turned about the camera centre by up to 1.5 deg per axis from frame to frame: the automatic
  mask covers most of the body the render knows and little else; with only the edges that stay
  within 1 px (the default, ``wobble_px=0``) it does not find the body.
- A person walking past (simulated tracks of the two vertical edges of their silhouette): the
  estimator rejects both tracks as outliers and the poses are those without them.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from omni_sfm.estimate.pipeline import EstimationOptions, estimate_poses
from omni_sfm.evaluate import match_reflection, trajectory_errors
from omni_sfm.frames import read_frames
from omni_sfm.geometry import normalize
from omni_sfm.lines.automask import HAND_HELD_WOBBLE, AutoMaskOptions, static_mask
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.synth.effects import Body, Effects
from omni_sfm.synth.paths import Route
from omni_sfm.synth.render import RenderOptions, prepare
from omni_sfm.synth.scenes import SceneName
from omni_sfm.synth.simulate import SimulationOptions, simulate

HANDHELD = RenderOptions(scene=SceneName.OFFICE, route=Route.WALK, textured=True,
                         camera="equirectangular", width=384, height=192, frames=16,
                         effects=Effects(body=Body.OPERATOR, body_wobble_deg=1.5,
                                         shot_noise=2.0))


def _frames(seq: Path, cam) -> list[np.ndarray]:
    return [g for _, _, g in read_frames(seq / "images", size=(cam.width, cam.height))]


@pytest.fixture(scope="module")
def walk(rendered):
    res = rendered(HANDHELD)
    renderer = prepare(HANDHELD).renderer
    bodies = np.array([renderer.body_mask(k) for k in range(HANDHELD.frames or 0)])
    return res.output, res.camera, bodies


def test_wobbling_hand_is_masked(walk):
    seq, cam, bodies = walk
    frames = _frames(seq, cam)
    valid = cam.valid_mask()
    anywhere, always = bodies.any(axis=0), bodies.all(axis=0)
    assert (anywhere & ~always).sum() > 0.1 * always.sum()  # it wobbles
    auto = static_mask(frames, cam, options=AutoMaskOptions(wobble_px=HAND_HELD_WOBBLE))
    assert auto.applied, auto.reason
    assert "within 2 px" in auto.reason and auto.wobbling_edge_fraction > 0
    masked = ~auto.mask
    assert (masked & always).sum() > 0.6 * always.sum()
    assert (masked & ~anywhere & valid).sum() < 0.05 * valid.sum()
    # the edges that stay put within 1 px alone do not find it
    strict = static_mask(frames, cam)  # the default
    assert (~strict.mask & always).sum() < 0.2 * always.sum(), strict.reason


def _with_walker(sim, frames: range, speed: float) -> LineTracks:
    """The simulated tracks plus the two silhouette edges of a person (vertical lines 0.5 m
    apart, 0.75 m to the side of the camera's mid-walk position) walking at ``speed`` m per
    frame against the camera's direction of travel (negative: with it), seen in ``frames``."""
    tr, gt = sim.tracks, sim.groundtruth
    up = sim.parallel_direction
    fwd = gt.positions[-1] - gt.positions[0]
    fwd = normalize(fwd - up * (fwd @ up))
    side = np.cross(up, fwd)
    mid = (frames[0] + frames[-1]) / 2
    rng = np.random.default_rng(0)
    obs_track, obs_frame, obs_normal, obs_ray = [], [], [], []
    for j, along in enumerate((-0.25, 0.25)):
        for k in frames:
            p = gt.positions[int(mid)] + 0.75 * side + ((mid - k) * speed + along) * fwd
            n = gt.rotations[k].T @ normalize(np.cross(p - gt.positions[k], up))
            obs_track.append(tr.num_tracks + j)
            obs_frame.append(k)
            obs_normal.append(normalize(n + np.radians(0.1) * rng.normal(size=3)))
            ray = gt.rotations[k].T @ (p - gt.positions[k])  # to the walker, the side seen
            obs_ray.append(normalize(ray - (ray @ obs_normal[-1]) * obs_normal[-1]))
    track = np.append(tr.obs_track, obs_track)
    frame = np.append(tr.obs_frame, obs_frame)
    order = np.lexsort((frame, track))
    return replace(tr, track_ids=np.append(tr.track_ids, [9000, 9001]),
                   obs_track=track[order], obs_frame=frame[order],
                   obs_normal=np.vstack([tr.obs_normal, obs_normal])[order],
                   obs_ray=None if tr.obs_ray is None else
                   np.vstack([tr.obs_ray, obs_ray])[order])


def test_walker_tracks_are_rejected():
    """People walking past (item 3 of the issue): their silhouette edges are vertical lines,
    parallel to the scene's verticals, whose motion disagrees with the scene's; the
    estimator's outlier rejection drops them and the poses stay those without them."""
    sim = simulate(SimulationOptions(num_views=60, world="manhattan", path_length=4.0,
                                     noise_deg=0.1, seed=3))
    opts = EstimationOptions(estimator="global")
    clean = estimate_poses(sim.tracks, opts)
    for frames, speed in ((range(20, 41), 1.3 / 15), (range(10, 51), -1.2 * 4.0 / 60)):
        res = estimate_poses(_with_walker(sim, frames, speed), opts)
        assert res.estimated.all()
        assert {9000, 9001} <= set(res.report.rejected_tracks or [])
        e = trajectory_errors(match_reflection(res.trajectory, sim.groundtruth),
                              sim.groundtruth)
        e0 = trajectory_errors(match_reflection(clean.trajectory, sim.groundtruth),
                               sim.groundtruth)
        assert abs(e.rot_max_deg - e0.rot_max_deg) < 1e-3
        assert abs(e.ate_rel - e0.ate_rel) < 1e-4
