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


def test_tracks_as_written_are_what_the_file_gives_back(tmp_path):
    """``LineTracks.as_written`` are the numbers ``tracks.json`` holds: written and read back
    they are the same to the bit (rays and sigmas too), and written again the same file (the
    estimator on images takes these, so ``init --tracks`` finds its poses to the bit)."""
    from dataclasses import replace

    sim = simulate(SimulationOptions(num_views=40, num_parallel=6, num_other=6, seed=6))
    tr = sim.tracks
    rng = np.random.default_rng(0)
    n = tr.obs_normal * (1.0 + 1e-13 * rng.normal(size=tr.obs_normal.shape))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ray = np.cross(n, rng.normal(size=n.shape))
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    tr = replace(tr, obs_normal=n, obs_ray=ray,
                 obs_sigma=np.radians(0.05) * (1.0 + rng.random((len(n), 2))))
    w = tr.as_written()
    write_tracks(tmp_path / "a.json", w)
    back = read_tracks(tmp_path / "a.json")
    for name in ("obs_normal", "obs_ray", "obs_sigma", "obs_frame", "obs_track", "track_ids"):
        np.testing.assert_array_equal(getattr(back, name), getattr(w, name), err_msg=name)
    assert not np.array_equal(w.obs_normal, tr.obs_normal)  # rounded as the file stores them
    np.testing.assert_allclose(w.obs_normal, tr.obs_normal, rtol=0, atol=1e-14)
    write_tracks(tmp_path / "b.json", back)
    assert (tmp_path / "b.json").read_text() == (tmp_path / "a.json").read_text()


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


def test_background_writes_bounded_errors_raised_in_the_caller(tmp_path):
    import threading

    from omni_sfm.fileio import BackgroundWrites

    gate = threading.Event()
    started: list[int] = []

    def write(k: int) -> None:
        started.append(k)
        gate.wait(10)
        (tmp_path / f"{k}.txt").write_text(str(k))

    with BackgroundWrites(threads=1, pending=2) as writes:
        writes.submit(write, 0)
        writes.submit(write, 1)
        # a third waits for the oldest: at most `pending` queued or running
        t = threading.Thread(target=writes.submit, args=(write, 2))
        t.start()
        t.join(0.2)
        assert t.is_alive() and started == [0]
        gate.set()
        t.join(10)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["0.txt", "1.txt", "2.txt"]

    def fail(_: int) -> None:
        raise OmniSfmError("disk full")

    with pytest.raises(OmniSfmError, match="disk full"), BackgroundWrites(1) as writes:
        writes.submit(fail, 0)
        writes.wait()


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


# --- the shared math (omni_sfm.geometry, omni_sfm.transforms): one implementation, tested here

def _unit(rng, *shape):
    from omni_sfm.geometry import normalize

    return normalize(rng.normal(size=(*shape, 3)))


def test_cross3_is_np_cross_bit_for_bit():
    from omni_sfm.geometry import cross3, skew

    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(4, 5, 3)), rng.normal(size=(5, 3))
    np.testing.assert_array_equal(cross3(a, b), np.cross(a, b))
    np.testing.assert_allclose(skew(a) @ b[..., None], np.cross(a, b)[..., None], atol=1e-15)


@pytest.mark.parametrize("switch", [0.9, 0.6])
def test_orthonormal_completion(switch):
    from omni_sfm.geometry import cross3, orthonormal_completion

    rng = np.random.default_rng(1)
    axes = np.vstack([np.eye(3), -np.eye(3)])
    edge = np.array([[switch, np.sqrt(1 - switch**2), 0.0]])  # at the helper's switch
    n = np.vstack([axes, edge, _unit(rng, 50)])
    e1, e2 = orthonormal_completion(n, switch=switch)
    basis = np.stack([e1, e2, n], -1)
    np.testing.assert_allclose(np.swapaxes(basis, 1, 2) @ basis, np.broadcast_to(np.eye(3),
                                                                                 basis.shape),
                               atol=1e-15)
    np.testing.assert_allclose(cross3(e1, e2), n, atol=1e-15)  # right-handed
    # one vector at a time gives the same, and the helper follows |n_x| < switch
    one = orthonormal_completion(n[0], switch=switch)
    np.testing.assert_array_equal(one[0], e1[0])
    np.testing.assert_allclose(e1[1], [0.0, 0.0, -1.0])   # n = y: helper x, e1 = y x x
    np.testing.assert_allclose(e1[0], [0.0, 0.0, 1.0])    # n = x: helper y, e1 = x x y


def test_completion_towards_hint():
    from omni_sfm.geometry import completion_towards, cross3

    rng = np.random.default_rng(2)
    n, hint = _unit(rng, 30), rng.normal(size=(30, 3))
    e1, e2 = completion_towards(n, hint)
    np.testing.assert_allclose(np.sum(e1 * n, -1), 0.0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(e1, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(cross3(e1, e2), n, atol=1e-15)
    # e1 is the hint's in-plane direction: the hint lies in span(e1, n), on e1's side
    np.testing.assert_allclose(np.sum(hint * e2, -1), 0.0, atol=1e-14)
    assert (np.sum(hint * e1, -1) > 0).all()
    z = np.array([0.0, 0.0, 1.0])
    assert np.isnan(completion_towards(z, 2.0 * z)[0]).all()  # no in-plane direction


def test_smallest_eigenvector_of_scatter():
    from omni_sfm.geometry import smallest_eigenvector

    rng = np.random.default_rng(3)
    normal = _unit(rng, 4)
    # vectors in the plane perpendicular to each normal: the scatter's null direction
    x = rng.normal(size=(4, 20, 3))
    x -= np.sum(x * normal[:, None], -1, keepdims=True) * normal[:, None]
    v = smallest_eigenvector(np.einsum("kni,knj->kij", x, x))
    np.testing.assert_allclose(np.abs(np.sum(v * normal, -1)), 1.0, atol=1e-12)
    S = np.diag([3.0, 1.0, 2.0])
    np.testing.assert_allclose(np.abs(smallest_eigenvector(S)), [0.0, 1.0, 0.0])


def test_unsigned_angle():
    from omni_sfm.geometry import angle_between, rotation_about_axis, unsigned_angle

    rng = np.random.default_rng(4)
    a, b = _unit(rng, 40), _unit(rng, 40)
    ang = unsigned_angle(a, b)
    assert (ang >= 0).all() and (ang <= np.pi / 2).all()
    np.testing.assert_array_equal(unsigned_angle(-a, b), ang)
    np.testing.assert_array_equal(unsigned_angle(b, a), ang)
    np.testing.assert_allclose(ang, angle_between(a, b, unsigned_lines=True), atol=1e-15)
    expected = np.minimum(angle_between(a, b), np.pi - angle_between(a, b))
    np.testing.assert_allclose(ang, expected, atol=1e-14)
    # accurate for tiny angles (arccos of a dot product is not)
    tiny = rotation_about_axis(np.array([0.0, 0.0, 1.0]), 1e-9) @ np.array([1.0, 0.0, 0.0])
    assert unsigned_angle(np.array([1.0, 0.0, 0.0]), -tiny) == pytest.approx(1e-9, rel=1e-9)


def test_line_plane_and_predicted_normals():
    from omni_sfm.geometry import line_plane_normals, normalize, predicted_normals

    rng = np.random.default_rng(5)
    c, p = rng.normal(size=(10, 3)), rng.normal(size=(10, 3))
    d = _unit(rng, 10)
    n = line_plane_normals(c, p, d)
    # normal to the line and to the ray from the centre to any point of it
    for s in (-1.0, 0.0, 2.5):
        np.testing.assert_allclose(np.sum(n * (p + s * d - c), -1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(n * d, -1), 0.0, atol=1e-12)
    z = np.array([0.0, 0.0, 1.0])
    assert (line_plane_normals(p[0], p[0] + 3.0 * z, z) == 0.0).all()  # a camera on the line
    R = rotvec_to_matrix(rng.normal(size=(10, 3)))
    cam = predicted_normals(R, c, p, d)
    np.testing.assert_allclose(np.einsum("kij,kj->ki", R, cam), n, atol=1e-12)
    # a point of the line, seen from the camera, lies in the plane: ray_cam . n_cam = 0
    ray_cam = np.einsum("kji,kj->ki", R, normalize(p + 0.7 * d - c))
    np.testing.assert_allclose(np.sum(ray_cam * cam, -1), 0.0, atol=1e-12)


def _posed(rng, n):
    return rotvec_to_matrix(rng.normal(size=(n, 3))), rng.normal(size=(n, 3))


@pytest.mark.parametrize("scale", [2.5, -0.7])
def test_similarity_from_poses_exact(scale):
    from omni_sfm.transforms import similarity_from_poses

    rng = np.random.default_rng(6)
    R_src, c_src = _posed(rng, 6)
    Rs = rotvec_to_matrix(np.array([0.2, -0.4, 0.1]))
    t = np.array([1.0, 2.0, -1.0])
    R_dst, c_dst = Rs @ R_src, scale * c_src @ Rs.T + t
    sim = similarity_from_poses(R_dst, c_dst, R_src, c_src, allow_reflection=True)
    np.testing.assert_allclose(sim.rotation, Rs, atol=1e-12)
    assert sim.scale == pytest.approx(scale, abs=1e-12)
    np.testing.assert_allclose(sim.translation, t, atol=1e-12)
    np.testing.assert_allclose(sim.apply_points(c_src), c_dst, atol=1e-12)
    pos = similarity_from_poses(R_dst, c_dst, R_src, c_src, allow_reflection=False)
    np.testing.assert_allclose(pos.rotation, Rs, atol=1e-12)
    if scale > 0:
        assert pos.scale == pytest.approx(scale, abs=1e-12)
    else:  # no reflection: unit scale, the translation maps the mean centres
        assert pos.scale == 1.0
        np.testing.assert_allclose(pos.apply_points(c_src).mean(0), c_dst.mean(0), atol=1e-12)


def test_similarity_from_poses_rotation_from_rotations_on_a_straight_path():
    from omni_sfm.transforms import similarity_from_poses, umeyama

    rng = np.random.default_rng(7)
    R_src, _ = _posed(rng, 5)
    c_src = np.outer(np.arange(5.0), [1.0, 0.5, 0.0])  # collinear: centres leave a roll free
    Rs = rotvec_to_matrix(np.array([0.3, 0.1, -0.2]))
    R_dst, c_dst = Rs @ R_src, 0.5 * c_src @ Rs.T
    sim = similarity_from_poses(R_dst, c_dst, R_src, c_src, allow_reflection=True)
    np.testing.assert_allclose(sim.rotation, Rs, atol=1e-12)
    np.testing.assert_allclose(umeyama(c_src, c_dst).apply_points(c_src), c_dst, atol=1e-12)


def test_similarity_from_poses_degenerate_centres():
    from omni_sfm.transforms import similarity_from_poses

    rng = np.random.default_rng(8)
    R, c = _posed(rng, 4)
    still = np.zeros((4, 3))
    with pytest.raises(OmniSfmError, match="do not spread"):
        similarity_from_poses(R, c, R, still, allow_reflection=True)
    with pytest.raises(OmniSfmError, match="do not spread"):
        similarity_from_poses(R, still, R, c, allow_reflection=True)
    assert similarity_from_poses(R, c, R, still, allow_reflection=False).scale == 1.0
    assert similarity_from_poses(R, still, R, c, allow_reflection=False).scale == 1.0


def test_evaluate_reexports_the_transforms():
    from omni_sfm import evaluate, transforms

    for name in ("Similarity", "umeyama", "associate", "paper_translation_errors"):
        assert getattr(evaluate, name) is getattr(transforms, name)


def test_paper_translation_errors_invariant_to_similarity():
    from omni_sfm.transforms import Similarity, paper_normalised_positions, paper_translation_errors

    gt = _random_traj(8, 9)
    p = paper_normalised_positions(gt)
    np.testing.assert_allclose(p[0], 0.0, atol=1e-15)
    assert np.linalg.norm(p[-1]) == pytest.approx(1.0)
    moved = Similarity(rotvec_to_matrix(np.array([0.4, 0.0, -0.3])), np.array([1.0, 2.0, 3.0]),
                       3.0).apply(gt)
    assert paper_translation_errors(moved, gt).max() < 1e-12
    with pytest.raises(OmniSfmError, match="coincide"):
        paper_normalised_positions(Trajectory(gt.timestamps[:2], gt.rotations[:2],
                                              np.zeros((2, 3))))
