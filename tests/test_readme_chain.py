"""The README's chain, typed as shown, from an image folder and from a video.

The commands are read from README.md's "Using it on your own video" block and run one by one
in a fresh folder with relative paths (``cd`` included), exactly as written, with one change:
``compare`` runs only the ``lines`` initializer (the point-based ones are tested in
tests/test_compare.py). The final view must have the trajectory, the 3D lines and the map,
``compare``'s ``lines`` trajectory must be ``init``'s, and the two exports must hold the refined
poses (nerfstudio's ``transforms.json``, COLMAP's rig).

The video variant proves that every stage that reads frames reads them from a video: the example
is rendered with ``--video`` (and 12 frames rather than 20: the stages are the image folder's,
only their input differs) and ``images/`` becomes ``video.mp4`` wherever the README says so; it
leaves out the two commands that read no frames (``camera show`` and ``view``, which the image
folder's chain runs as typed), ``compare`` (whose ``lines`` run is ``init``'s, on the same
reader) and the ``nerfstudio`` export (the perspective views of the ``colmap-rig`` export, from
the same frames). Its checks are the image folder's on what it ran, on ``dense/`` as ``view``
would read it.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from helpers import assert_every_key_declared

from omni_sfm.export.nerfstudio import opencv_poses, read_transforms
from omni_sfm.export.pipeline import export_trajectory_of
from omni_sfm.poses import read_tum
from omni_sfm.reports import CompareResults, DenseReport, InitReport, RefineReport
from omni_sfm.view.scene import load_view_scene

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def readme_chain() -> list[list[str]]:
    """The commands of the README's chain block, as argument lists (comments dropped)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text[text.index("## Using it on your own video"):]
    block = re.search(r"```bash\n(.*?)```", section, re.S)
    assert block is not None, "README: no bash block under 'Using it on your own video'"
    cmds = [shlex.split(line, comments=True) for line in block.group(1).splitlines()]
    cmds = [c for c in cmds if c]
    assert [c[1] for c in cmds if c[0] == "omni-sfm"] == [
        "render", "camera", "init", "refine", "export", "export", "dense", "view", "compare"], cmds
    return cmds


# the video variant: the commands that read no frames are left out, and options added
VIDEO_SKIPS = ("camera", "view", "compare")
VIDEO_SKIP_FORMATS = ("nerfstudio",)  # the same perspective views as colmap-rig, from the frames
VIDEO_EXTRA = {"render": ["--video", "--frames", "12"]}  # the last --frames wins


def run_chain(tmp: Path, video: bool) -> Path:
    """Run the chain in ``tmp``; returns the folder the commands ended in."""
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    cwd = tmp
    for cmd in readme_chain():
        if cmd[0] == "cd":
            cwd = cwd / cmd[1]
            continue
        if video:
            if cmd[1] in VIDEO_SKIPS or (cmd[1] == "export" and
                                          cmd[cmd.index("--format") + 1] in VIDEO_SKIP_FORMATS):
                continue
            cmd = ["video.mp4" if a == "images/" else a for a in cmd]
            cmd = [*cmd, *VIDEO_EXTRA.get(cmd[1], [])]
        if cmd[1] == "compare":
            cmd = [*cmd, "--initializers", "lines"]
        r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True,
                           stdin=subprocess.DEVNULL, timeout=600)
        assert r.returncode == 0, f"{' '.join(cmd)} exited {r.returncode}: {r.stderr[-2000:]}"
        assert "Traceback" not in r.stderr, r.stderr
        if cmd[1] in ("init", "refine", "export", "dense", "view", "compare"):
            assert r.stdout.strip(), f"{cmd[1]} printed no summary on stdout"
    return cwd


@pytest.mark.slow(seconds=60)
@pytest.mark.parametrize("video", [False, True], ids=["image-folder", "video"])
def test_readme_chain_end_to_end(tmp_path: Path, video: bool) -> None:
    ex = run_chain(tmp_path, video)
    scene = load_view_scene(ex / "dense")
    n = len(read_tum(ex / "refined" / "trajectory.tum"))
    assert len(scene.trajectory) == n >= (12 if video else 18)
    assert len(scene.line_starts) >= 20          # the 3D lines came through refine and dense
    assert len(scene.points) >= 10_000           # the dense map
    if not video:                                # view ran (the video variant skips it)
        for name in ("view.png", "view.html", "lines3d.ply", "cameras.ply"):
            assert (ex / "dense" / name).is_file(), name
    # refine and dense found the frames init recorded, as stored paths
    for folder in ("refined", "dense"):
        assert (ex / folder / "camera.yaml").is_file()
    # refine adjusted the init's lines with the points (the joint adjustment, its default)
    reports = [(InitReport, ex / "init" / "report.json"),
               (RefineReport, ex / "refined" / "report.json"),
               (DenseReport, ex / "dense" / "report.json")]
    if not video:                                # compare ran (the video variant skips it)
        reports.append((CompareResults, ex / "cmp" / "results.json"))
    for cls, path in reports:
        assert_every_key_declared(cls, path)
    refined = json.loads((ex / "refined" / "report.json").read_text())
    joint = refined["bundle_adjustment"]["joint"]
    assert joint["line_observations"] > 0 and joint["point_observations"] > 0
    assert refined["lines3d"].startswith("adjusted")  # its lines3d.json: the adjusted lines
    init = read_tum(ex / "init" / "trajectory.tum")
    if video:
        assert not np.array_equal(init.timestamps, np.round(init.timestamps))  # seconds
    else:  # compare's lines are init's, on the same frames
        lines = read_tum(ex / "cmp" / "trajectories" / "lines.tum")
        np.testing.assert_array_equal(lines.timestamps, init.timestamps)
        np.testing.assert_allclose(lines.positions, init.positions, atol=1e-9)
        np.testing.assert_allclose(lines.rotations, init.rotations, atol=1e-9)
    # the splat-ready exports: the refined poses in nerfstudio's and COLMAP's rig conventions
    refined_traj = read_tum(ex / "refined" / "trajectory.tum")
    report = json.loads((ex / "rig" / "report.json").read_text())
    assert report["world"]["turned"]
    views = len(report["views"]["views"])
    want = export_trajectory_of(report, refined_traj)
    if not video:
        doc, frames = read_transforms(ex / "splat" / "transforms.json")
        assert doc["camera_model"] == "OPENCV" and len(frames) == views * n
        got = opencv_poses(np.asarray([m for _, m in frames]))
        np.testing.assert_allclose(got.positions[::views], want.positions, atol=1e-9)
    rig = pycolmap.Reconstruction(str(ex / "rig" / "sparse"))
    assert rig.num_rigs() == 1 and rig.num_frames() == n and rig.num_images() == n * views
    for frame in rig.frames.values():
        T = np.asarray(frame.rig_from_world.matrix())
        np.testing.assert_allclose(T[:, :3].T @ -T[:, 3], want.positions[frame.frame_id - 1],
                                   atol=1e-9)
