"""Online poses (``omni_sfm.estimate.online``, ``omni-sfm track``): causal accuracy on rendered
sequences, statuses on simulated lines (lost, rotation-only, relocalised), bounded state, the
command's outputs, a video read as a stream, Ctrl-C and bad input.

Sized for CI (40 rendered frames; the 200-frame figures and the latency come from
``scripts/bench/track.py``, quoted in docs/track.md). No wall-clock limits.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import EQUIRECT_CORRIDOR, assert_one_line_error

from omni_sfm.cameras import load_camera
from omni_sfm.cli import main
from omni_sfm.estimate.online import (
    OnlineEstimator,
    OnlineOptions,
    Status,
    TrackedPose,
    poses_trajectory,
)
from omni_sfm.evaluate import associate, relative_rotation_errors_deg, trajectory_errors
from omni_sfm.folders import TrackFolder
from omni_sfm.frames import Frame
from omni_sfm.pipelines.track import Tracker
from omni_sfm.poses import read_tum
from omni_sfm.synth.render import RenderOptions
from omni_sfm.synth.simulate import SimulationOptions, simulate_manhattan

START = OnlineOptions().start_frames
"""Frames before the first pose: the start's buffer."""
"""The corridor of tests/test_init_images.py (shared render): 800 x 600, 1.5 m in 40 frames."""


def _track(seq: Path, frames: int | None = None) -> list[TrackedPose]:
    tracker = Tracker(load_camera(seq / "camera.yaml"))
    files = sorted((seq / "images").glob("*.png"))[:frames]
    return [tracker.add_frame(cv2.imread(str(f), cv2.IMREAD_UNCHANGED), float(k))
            for k, f in enumerate(files)]


@pytest.fixture(scope="module")
def corridor_poses(corridor, built_once) -> list[TrackedPose]:
    """The corridor's poses frame by frame, tracked once per test run (``built_once``)."""
    poses: list[TrackedPose] = built_once("track-corridor-poses", lambda _: _track(corridor))[1]
    return poses


@pytest.mark.parametrize("which", [
    "hyperboloid",
    # renders its 40 frames and tracks them: 17 s in make test (slow: this file starts first)
    pytest.param("equirectangular", marks=pytest.mark.slow),
])
def test_causal_accuracy_on_rendered_corridors(which, corridor, corridor_poses, rendered):
    if which == "hyperboloid":
        seq, poses = corridor, corridor_poses
    else:
        seq = rendered(EQUIRECT_CORRIDOR).output
        poses = _track(seq)
    status = [p.status for p in poses]
    assert status[:START - 1] == [Status.INITIALISING] * (START - 1)
    assert status[START - 1:] == [Status.TRACKING] * (len(poses) - START + 1)
    assert all(p.world == 0 and p.reason is None for p in poses[START - 1:])
    # the start's frames are given with the frame where it succeeded
    assert [p.frame for p in poses[START - 1].start_poses] == list(range(START - 1))
    gt = read_tum(seq / "groundtruth.tum")
    err = trajectory_errors(poses_trajectory(poses), gt)
    assert err.num_common == len(gt)
    # measured: hyperboloid 0.069 deg, 0.034 %
    assert err.rot_max_deg <= 1.0
    assert err.ate_rel <= 0.02
    # the poses returned frame by frame (not the start's): the same bound
    tracked = poses_trajectory(poses, with_start=False)
    assert len(tracked) == len(gt) - START + 1
    assert trajectory_errors(tracked, gt).rot_max_deg <= 1.0


def test_rotation_does_not_drift_on_rendered_corridor(corridor, corridor_poses):
    """Rotations referred to the world directions (issue 52): within 0.5 deg at every frame
    and not growing with the frame index (the last third's worst no worse than the first
    third's + 0.2 deg). Measured on these 40 frames: 0.069 deg at worst, 0.019 in the first
    third and 0.065 in the last (before the world directions: the 200-frame corridor of
    docs/track.md drifted to 27.9 deg)."""
    gt = read_tum(corridor / "groundtruth.tum")
    e, g = associate(poses_trajectory(corridor_poses), gt)
    err = relative_rotation_errors_deg(e, g)
    third = len(err) // 3
    msg = f"rotation errors (deg): {np.round(err, 3).tolist()}"
    assert len(err) == len(gt)
    assert err.max() <= 0.5, msg
    assert err[-third:].max() <= err[:third].max() + 0.2, msg


# -- simulated lines: below the front end ------------------------------------------------------
def _manhattan(frames: int) -> tuple[object, list[tuple[np.ndarray, np.ndarray]]]:
    """A straight stretch of a simulated office corridor (no rays), each frame's (ids,
    normals)."""
    sim = simulate_manhattan(SimulationOptions(world="manhattan", num_views=frames,
                                               path_length=0.05 * (frames - 1), noise_deg=0.02,
                                               line_density=8.0, seed=1))
    tr = sim.tracks
    out = []
    for k in range(frames):
        sel = tr.obs_frame == k
        out.append((tr.track_ids[tr.obs_track[sel]], tr.obs_normal[sel]))
    return sim, out


@pytest.fixture(scope="module")
def walk():
    return _manhattan(150)


def _feed(obs, n: int | None = None, edit=None) -> tuple[OnlineEstimator, list[TrackedPose]]:
    est = OnlineEstimator()
    poses = []
    for k, (ids, nrm) in enumerate(obs[:n]):
        if edit is not None:
            ids, nrm = edit(k, ids, nrm)
        poses.append(est.add(ids, nrm, timestamp=float(k)))
    return est, poses


def test_pose_of_a_frame_does_not_depend_on_later_frames(walk):
    _, obs = walk
    _, short = _feed(obs, 60)
    _, full = _feed(obs)
    for a, b in zip(short, full[:60], strict=True):
        assert a.status == b.status and a.reason == b.reason
        assert (a.rotation is None) == (b.rotation is None)
        if a.has_pose:
            np.testing.assert_array_equal(a.rotation, b.rotation)
            np.testing.assert_array_equal(a.position, b.position)
    assert sum(p.status == Status.TRACKING for p in full) >= 150 - START


def test_blank_frames_lost_then_relocalised_in_a_new_world(walk):
    sim, obs = walk
    blank = range(60, 76)

    def edit(k, ids, nrm):
        return (ids[:0], nrm[:0]) if k in blank else (ids, nrm)

    est, poses = _feed(obs, edit=edit)
    by = {p.frame: p for p in poses}
    miss = OnlineOptions().registration.max_misses
    for k in blank:
        assert by[k].status == Status.LOST and not by[k].has_pose and by[k].reason
    assert "restarting" in by[60 + miss - 1].reason
    assert "lost since frame 60" in by[60 + miss].reason
    back = [p for p in poses if p.status == Status.RELOCALISED]
    assert len(back) == 1 and back[0].frame > blank[-1] and back[0].world == 1
    assert all(p.world == 1 and p.status == Status.TRACKING for p in poses[back[0].frame + 1:])
    # the new world's poses fit the ground truth on their own (rotation; positions up to a
    # similarity and the reflection that normals without rays leave open)
    new = poses_trajectory(poses[back[0].frame:])
    gt = sim.groundtruth.subset(new.timestamps.astype(int))
    rel_e = new.rotations[0].T @ new.rotations
    rel_g = gt.rotations[0].T @ gt.rotations
    ang = np.degrees(np.arccos(np.clip((np.trace(np.swapaxes(rel_g, 1, 2) @ rel_e, axis1=1,
                                                 axis2=2) - 1) / 2, -1, 1)))
    assert ang.max() < 1.0
    assert est.num_frames_held <= OnlineOptions().window


def test_a_start_is_tried_every_few_frames_while_nothing_is_seen():
    o = OnlineOptions()
    est = OnlineEstimator(o)
    poses = [est.add(np.zeros(0, int), np.zeros((0, 3))) for _ in range(100)]
    tries = [p.frame for p in poses if "start on" in (p.reason or "")]
    assert tries == list(range(o.start_frames - 1, 100, o.start_retry))
    assert all(p.status == Status.INITIALISING and not p.has_pose for p in poses)
    assert est.num_frames_held == o.max_start_frames


def test_vanishing_directions_keep_the_rotation(walk):
    sim, obs = walk
    few = range(100, 104)
    fam = np.where(sim.parallel, 0, np.argmax(np.abs(sim.line_directions[:, :2]), axis=1) + 1)

    def edit(k, ids, nrm):
        if k not in few:
            return ids, nrm
        # three lines in two directions seen since frame 90: too few to place the camera
        seen = set(obs[90][0].tolist())
        pick = [j for j, t in enumerate(ids.tolist()) if t in seen]
        vert = [j for j in pick if fam[ids[j]] == 0][:2]
        other = [j for j in pick if fam[ids[j]] != 0][:1]
        sel = np.array(vert + other)
        assert len(sel) == 3
        return ids[sel], nrm[sel]

    _, poses = _feed(obs, 120, edit=edit)
    for k in few:
        p = poses[k]
        assert p.status == Status.ROTATION_ONLY and p.position is None and p.reason
        gt = sim.groundtruth
        e = poses[99].rotation.T @ p.rotation
        g = gt.rotations[99].T @ gt.rotations[k]
        assert np.degrees(np.arccos(np.clip((np.trace(g.T @ e) - 1) / 2, -1, 1))) < 0.5
    assert all(p.status == Status.TRACKING for p in poses[few[-1] + 1:])


def test_state_is_bounded(walk):
    _, obs = walk
    est = OnlineEstimator()
    held, lines = [], []
    for k, (ids, nrm) in enumerate(obs):
        est.add(ids, nrm, timestamp=float(k))
        held.append(est.num_frames_held)
        lines.append(est.num_lines)
    window = OnlineOptions().window
    assert max(held) == window and held[-1] == window
    # the lines held are those the window's frames see: no more than those seen in 30 frames
    per_frame = np.mean([len(i) for i, _ in obs])
    assert max(lines) < 3 * per_frame


def test_json_line_and_options():
    p = TrackedPose(3, 0.2, Status.ROTATION_ONLY, np.eye(3), None, 12, 4, 1.5, "why", 1)
    d = p.to_json()
    assert json.loads(json.dumps(d)) == d
    assert d["status"] == "rotation-only" and d["position"] is None
    assert d["quaternion_xyzw"] == [0.0, 0.0, 0.0, 1.0]
    for bad in (dict(window=10), dict(start_frames=2), dict(start_retry=0)):
        with pytest.raises(Exception, match="window|start"):
            OnlineOptions(**bad)


# -- the command --------------------------------------------------------------------------------
def _stream_lines(out: str) -> list[dict]:
    return [json.loads(line) for line in out.splitlines()]


def _lossless_video(frames: list[Path], video: Path) -> Path:
    """``frames`` written as a lossless (FFV1) video at 10 frames a second."""
    first = cv2.imread(str(frames[0]))
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"FFV1"), 10.0,
                             (first.shape[1], first.shape[0]))
    for f in frames:
        writer.write(cv2.imread(str(f)))
    writer.release()
    return video


def test_video_read_as_a_stream_gives_the_folder_poses(corridor, corridor_poses, tmp_path,
                                                       capsys):
    n = START + 4
    video = _lossless_video(sorted((corridor / "images").glob("*.png"))[:n],
                            tmp_path / "seq.avi")
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["track", "--images", video.resolve().as_uri(), "--camera",
                 str(corridor / "camera.yaml"), "-o", str(out), "--stream"]) == 0
    cap = capsys.readouterr()
    lines = _stream_lines(cap.out)
    assert [d["frame"] for d in lines] == list(range(n))
    assert {d["status"] for d in lines[:START - 1]} == {"initialising"}
    assert {d["status"] for d in lines[START - 1:]} == {"tracking"}
    for d in lines:
        assert set(d) == {"frame", "timestamp", "status", "world", "position",
                          "quaternion_xyzw", "lines", "lines_known", "latency_ms", "reason",
                          "start_poses"}
        assert d["latency_ms"] > 0 and d["lines"] > 10
    given = lines[START - 1]["start_poses"]
    assert [d["frame"] for d in given] == list(range(START - 1))
    assert all(len(d["position"]) == 3 and len(d["quaternion_xyzw"]) == 4 for d in given)
    assert all(d["start_poses"] == [] for d in lines[START:])
    np.testing.assert_allclose([d["timestamp"] for d in lines], np.arange(n) / 10.0)
    assert cap.err.startswith("track: ") and cap.err.count("\n") == 1
    # the stream's poses are the folder run's poses of those frames: none used a later frame
    traj = read_tum(out / "trajectory.tum")
    ref = poses_trajectory(corridor_poses).subset(np.arange(n))
    np.testing.assert_allclose(traj.positions, ref.positions, atol=1e-12)
    np.testing.assert_allclose(traj.rotations, ref.rotations, atol=1e-12)
    assert [json.loads(s) for s in (out / "frames.jsonl").read_text().splitlines()] == lines
    assert [f.to_json() for f in TrackFolder(out).read_frames()] == lines  # the typed reader


def test_ctrl_c_ends_cleanly_with_the_poses_so_far(corridor, corridor_poses, tmp_path,
                                                   monkeypatch, capsys):
    import omni_sfm.frames as frames_mod

    n = START + 1
    files = sorted((corridor / "images").glob("*.png"))

    def frames(path, size=None, **_: object) -> Iterator[Frame]:
        for k, f in enumerate(files[:n]):
            yield Frame(k, float(k), cv2.imread(str(f), cv2.IMREAD_UNCHANGED))
        raise KeyboardInterrupt

    monkeypatch.setattr(frames_mod, "read_frames", frames)
    out = tmp_path / "out"
    assert main(["track", "--images", str(corridor / "images"), "--camera",
                 str(corridor / "camera.yaml"), "-o", str(out)]) == 130
    said = capsys.readouterr().out
    assert "interrupted" in said and f"{n} poses" in said
    traj = read_tum(out / "trajectory.tum")
    assert len(traj) == n
    np.testing.assert_allclose(traj.positions,
                               poses_trajectory(corridor_poses).positions[:n], atol=1e-12)
    assert len((out / "frames.jsonl").read_text().splitlines()) == n


def test_bad_input_is_one_line_and_exit_code_2(corridor, tmp_path, capsys):
    cam = str(corridor / "camera.yaml")
    images = str(corridor / "images")
    out = str(tmp_path / "out")
    cases = [
        (["--images", str(tmp_path / "missing"), "--camera", cam], "no such file"),
        (["--images", images, "--camera", str(tmp_path / "none.yaml")], "camera file"),
        (["--images", images, "--camera", str(sorted(Path(images).glob("*.png"))[0])],
         "camera file"),
        (["--images", (tmp_path / "missing.avi").as_uri(), "--camera", cam],
         "cannot open this stream"),
        (["--images", images, "--camera", cam, "--frames", "0"], "--frames"),
    ]
    for argv, needle in cases:
        assert main(["track", *argv, "-o", out]) == 2, argv
        assert_one_line_error(capsys, needle)


def test_offline_refinement_of_a_stream_at_the_end(corridor, tmp_path, capsys):
    # --offline on a stream keeps its frames and runs init on the frames read (20 of 40):
    # every one of them posed with the whole run's evidence, in init's output folder
    n = 20
    video = _lossless_video(sorted((corridor / "images").glob("*.png")), tmp_path / "seq.avi")
    out = tmp_path / "out"
    assert main(["track", "--images", video.resolve().as_uri(), "--camera",
                 str(corridor / "camera.yaml"), "-o", str(out), "--frames", str(n),
                 "--offline"]) == 0
    assert f"offline: {n} of {n} frames" in capsys.readouterr().out
    assert len(list((out / "frames").glob("*.png"))) == n
    offline = read_tum(out / "offline" / "trajectory.tum")
    np.testing.assert_array_equal(offline.timestamps, np.arange(n))
    gt = read_tum(corridor / "groundtruth.tum").subset(np.arange(n))
    e = trajectory_errors(offline, gt)
    assert e.rot_max_deg < 0.5 and e.ate_rel < 0.01
    assert (out / "offline" / "report.json").is_file() and (out / "offline" / "sparse").is_dir()


def test_start_waits_for_parallax(rendered):
    """A slow camera (the corridor at 7.5 mm a frame, as in docs/track.md's 200-frame drift
    renders): the start is not taken on 15 frames whose lines' planes turn too little (there
    its scale came out of proportion and the tracking relaxed it into an 11-15 % scale drift:
    1.29 % ATE over 200 frames), but a few frames later; then every frame is tracked."""
    o = OnlineOptions()
    seq = rendered(RenderOptions(camera="hyperboloid", frames=30, path_length=0.0075 * 29,
                                 seed=0)).output
    poses = _track(seq)
    first = next(p.frame for p in poses if p.has_pose)
    msg = [p.reason for p in poses[:first]]
    assert first >= o.start_frames - 1 + o.start_retry, msg
    assert "planes turn by" in str(poses[o.start_frames - 1].reason), msg
    assert all(p.status == Status.TRACKING for p in poses[first:])
    err = trajectory_errors(poses_trajectory(poses), read_tum(seq / "groundtruth.tum"))
    assert err.num_common == len(poses)
    assert err.rot_max_deg <= 0.5
    assert err.ate_rel <= 0.005
