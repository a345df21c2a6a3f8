"""The initializer plugins: discoverable through entry points, accurate on simulated data,
PoseLib's upright convention, and `lines` on the rendered texture-poor corridor."""

from __future__ import annotations

import time

import numpy as np
import pytest

from omni_sfm.compare import run_initializer
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.geometry import normalize, rotvec_to_matrix
from omni_sfm.plugin_contract import InitializerResult, PointObservations, SequenceInput
from omni_sfm.poses import read_tum
from omni_sfm.registry import INITIALIZERS, available, load

NAMES = ("lines", "five-point", "colmap", "upright-3pt")


def simulated(noise_deg: float = 0.05, num_points: int = 40, seed: int = 0
              ) -> tuple[SequenceInput, object]:
    """The paper's simulation (40 lines, 20 views) with point rays under the same noise."""
    from omni_sfm.cameras import EquirectangularCamera
    from omni_sfm.synth.simulate import SimulationOptions, simulate

    sim = simulate(SimulationOptions(noise_deg=noise_deg, seed=seed))
    gt = sim.groundtruth
    rng = np.random.default_rng(seed + 77)
    F = len(gt)
    X = gt.positions[rng.integers(0, F, num_points)] + \
        normalize(rng.normal(size=(num_points, 3))) * rng.uniform(0.8, 3.0, (num_points, 1))
    rays = normalize(np.einsum("fji,nfj->nfi", gt.rotations, X[:, None] - gt.positions[None]))
    axis = normalize(np.cross(rays, rng.normal(size=rays.shape)))
    ang = np.radians(noise_deg) * rng.normal(size=(num_points, F, 1))
    rays = rays * np.cos(ang) + np.cross(axis, rays) * np.sin(ang)
    cam = EquirectangularCamera(width=1600, height=800)
    tt, ff = np.meshgrid(np.arange(num_points), np.arange(F), indexing="ij")
    r = rays.reshape(-1, 3)
    pts = PointObservations(tt.ravel(), ff.ravel(), cam.pixels_from_rays(r), r)
    return SequenceInput(gt.timestamps.copy(), cam, line_tracks=sim.tracks, points=pts,
                         name="sim"), gt


def test_entry_points_discoverable() -> None:
    eps = available(INITIALIZERS)
    for name in NAMES:
        assert name in eps, f"{name} not registered in {INITIALIZERS}"
        assert callable(load(INITIALIZERS, name))


@pytest.mark.parametrize("name", NAMES)
def test_each_initializer_on_simulation(name: str) -> None:
    seq, gt = simulated()
    thr = 3 * np.radians(0.05)
    opts = {"max_error_rad": thr} if name in ("five-point", "upright-3pt") else {}
    t0 = time.perf_counter()
    res, dt = run_initializer(name, seq, opts)
    elapsed = time.perf_counter() - t0
    assert res.status == "ok", res.reason
    assert res.trajectory is not None and len(res.trajectory) == seq.num_frames
    traj = res.trajectory
    if res.reflection_ambiguous:
        from omni_sfm.evaluate import match_reflection

        traj = match_reflection(traj, gt)
    e = trajectory_errors(traj, gt)
    assert e.rot_max_deg < 0.3, e.as_dict()
    assert e.ate_rel < 0.01, e.as_dict()
    assert 0 < dt <= elapsed  # the initializer's own wall time, within the call's


def test_too_few_points_fail_with_reason() -> None:
    seq, _ = simulated(num_points=8)
    for name in ("five-point", "upright-3pt"):
        res, _ = run_initializer(name, seq, {"max_error_rad": 0.003})
        assert res.status == "failed"
        assert "correspondences" in res.reason or "points" in res.reason, res.reason


def test_upright_basis_and_poselib_convention() -> None:
    """Rays turned by A (A v = +y) give PoseLib's upright problem; the pose comes back."""
    import poselib
    from omni_sfm_plugins.initializers.points import upright_basis
    from omni_sfm_plugins.initializers.upright import upright_ransac

    rng = np.random.default_rng(3)
    for v in (normalize(rng.normal(size=3)), np.array([0.0, -1.0, 0.0]),
              np.array([0.0, 1.0, 0.0])):
        A = upright_basis(v)
        assert np.allclose(A @ v, [0, 1, 0], atol=1e-12)
        assert np.allclose(A @ A.T, np.eye(3), atol=1e-12) and np.linalg.det(A) > 0
    # a relative pose whose rotation keeps the world direction d: R2^T d = v2, R1^T d = v1
    d = normalize(rng.normal(size=3))
    R1 = rotvec_to_matrix(rng.normal(size=3) * 0.3)
    R2 = rotvec_to_matrix(d * 0.4) @ R1  # turn about d
    c1, c2 = np.zeros(3), np.array([0.3, -0.1, 0.2])
    X = rng.normal(size=(60, 3)) * 2 + [0, 0, 3]
    x1 = normalize((X - c1) @ R1)
    x2 = normalize((X - c2) @ R2)
    v1, v2 = R1.T @ d, R2.T @ d
    A1, A2 = upright_basis(v1), upright_basis(v2)
    res = upright_ransac(x1 @ A1.T, x2 @ A2.T, 1e-6, 50, rng)
    assert res is not None
    Ry, t, inl = res
    assert abs(Ry[1, 1] - 1) < 1e-12  # rotation about y (PoseLib's upright axis)
    R = A2.T @ Ry @ A1
    R_true = R2.T @ R1
    t_true = R2.T @ (c1 - c2)
    assert np.degrees(np.arccos(np.clip((np.trace(R.T @ R_true) - 1) / 2, -1, 1))) < 1e-5
    assert np.allclose(A2.T @ t, t_true / np.linalg.norm(t_true), atol=1e-6)
    assert inl.all()
    assert hasattr(poselib, "relpose_upright_3pt")


@pytest.fixture(scope="module")
def small_corridor(rendered):
    """The rendered texture-poor corridor, paper's camera at 640 x 480, 20 frames, seed 2 (the
    session's read-only render; smaller than conftest's ``corridor``)."""
    from omni_sfm.synth.render import RenderOptions

    return rendered(RenderOptions(scene="corridor", camera="hyperboloid", frames=20,
                                  width=640, height=480, seed=2))


def test_lines_on_texture_poor_corridor(small_corridor) -> None:
    """Every frame registered, rotation error <= 0.5 deg, ATE <= 1 % of the path; the
    reflection is decided by the segments' ends, not by the ground truth."""
    from omni_sfm.compare import sequence_from_frames

    seq = sequence_from_frames(small_corridor.output / "images", small_corridor.camera)
    res, _ = run_initializer("lines", seq, {})
    assert res.status == "ok", res.reason
    assert not res.reflection_ambiguous
    assert res.trajectory is not None and len(res.trajectory) == seq.num_frames
    e = trajectory_errors(res.trajectory, read_tum(small_corridor.output / "groundtruth.tum"))
    assert e.rot_max_deg <= 0.5, e.as_dict()
    assert e.ate_rel <= 0.01, e.as_dict()


def test_colmap_of_a_rig_gives_the_rigs_poses_in_metres() -> None:
    """The ``colmap`` initializer on a rig camera reads COLMAP's rig model back as the rig's
    poses (world_from_rig, metres: the lens offsets are held in metres): a model posed at known
    rig poses (:func:`~omni_sfm.export.colmap_lenses.build_lens_rig`, a tilted rig) comes back
    as those poses to 1e-9, and ``init --initializer colmap`` records the scale that survives
    its normalisation (the first-to-last distance in metres). Measured with COLMAP itself
    (``scripts/check_footage.py`` on a rendered dual-fisheye corridor): docs/comparison.md."""
    from omni_sfm.export.colmap_lenses import build_lens_rig
    from omni_sfm.pipelines.init import _plugin_rig_scale
    from omni_sfm.poses import Trajectory
    from omni_sfm.refine.rig import rig_trajectory
    from tests.test_export_colmap_rig import _tilted_rig

    camera = _tilted_rig()
    rng = np.random.default_rng(4)
    traj = Trajectory(np.arange(5, dtype=float), rotvec_to_matrix(0.5 * rng.normal(size=(5, 3))),
                      rng.normal(size=(5, 3)))
    names = [f"{k:06d}.png" for k in range(5)]
    rec = build_lens_rig(camera, traj, names, 1.0).reconstruction
    got, posed = rig_trajectory(rec, camera, names, 10.0 * np.arange(5))
    assert posed.all()
    np.testing.assert_allclose(got.timestamps, 10.0 * np.arange(5))
    np.testing.assert_allclose(got.rotations, traj.rotations, atol=1e-9)
    np.testing.assert_allclose(got.positions, traj.positions, atol=1e-9)
    res = InitializerResult(traj, info={"metres_per_unit": 1.0})
    scale = _plugin_rig_scale(camera, res, "colmap")
    assert scale is not None and scale.fixed
    assert scale.metres_per_unit == pytest.approx(
        float(np.linalg.norm(traj.positions[-1] - traj.positions[0])), rel=1e-12)
    assert _plugin_rig_scale(camera, InitializerResult(traj), "x") is None
