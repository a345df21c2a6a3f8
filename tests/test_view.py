"""``omni-sfm view``: PNG snapshot, offline HTML page (in headless chromium), Open3D line sets."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import assert_one_line_error

from omni_sfm.cameras import write_camera_yaml
from omni_sfm.cli import main as cli_main
from omni_sfm.geometry import rotation_about_axis
from omni_sfm.libs import open3d_module
from omni_sfm.poses import Trajectory, write_tum
from omni_sfm.synth.render import hyperboloid_camera
from omni_sfm.synth.scenes import make_scene

BACKGROUND = np.array([244, 244, 242])  # the page's background colour (RGB)


@pytest.fixture(scope="module")
def result_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A results folder as ``omni-sfm dense`` writes it: the room's true lines, points sampled
    on its mesh (coloured by height), 30 poses crossing the room (mirror axis up)."""
    o3d = open3d_module()
    d = tmp_path_factory.mktemp("view") / "result"
    d.mkdir()
    scene = make_scene("room")
    n = 30
    yaw = np.linspace(0.0, 0.6, n)
    R = rotation_about_axis(np.array([0.0, 0.0, 1.0]), yaw)
    c = np.stack([np.linspace(2.0, 5.0, n), np.full(n, 3.0), np.full(n, 1.1)], axis=1)
    write_tum(d / "trajectory.tum", Trajectory(np.arange(n, dtype=float), R, c))
    write_camera_yaml(d / "camera.yaml", hyperboloid_camera(400, 300))
    (d / "lines3d.json").write_text(json.dumps(scene.lines.to_json()))
    mesh = scene.to_open3d()
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)]          # (T, 3, 3)
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(1)
    pick = rng.choice(len(tri), 40_000, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(40_000))[:, None], rng.random(40_000)[:, None]
    t = tri[pick]
    pts = (1 - r1) * t[:, 0] + r1 * (1 - r2) * t[:, 1] + r1 * r2 * t[:, 2]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    h = (pts[:, 2] - pts[:, 2].min()) / np.ptp(pts[:, 2])
    pcd.colors = o3d.utility.Vector3dVector(np.stack([h, 0.4 + 0.0 * h, 1 - h], axis=1))
    o3d.io.write_point_cloud(str(d / "dense.ply"), pcd)
    return d


def _chromium() -> str:
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        pytest.fail("chromium is not installed: `make setup` installs Debian's chromium")
    return path


def _browser(page: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """Headless chromium on ``page`` (offline: no network features), console to stderr."""
    with tempfile.TemporaryDirectory() as profile:
        return subprocess.run(
            [_chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
             "--no-first-run", "--disable-background-networking", "--disable-component-update",
             "--disable-sync", f"--user-data-dir={profile}", "--enable-logging=stderr", "--v=0",
             "--virtual-time-budget=5000", "--window-size=800,600", *args, page.as_uri()],
            capture_output=True, text=True, timeout=120, check=False)


def _js_errors(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines()
            if "Uncaught" in ln or ("CONSOLE" in ln and "rror" in ln)]


def test_view_files(result_dir: Path, tmp_path: Path) -> None:
    o3d = open3d_module()
    out = tmp_path / "snap.png"
    assert cli_main(["view", "--input", str(result_dir), "--output", str(out)]) == 0
    img = cv2.imread(str(out))
    assert img is not None and img.shape[0] >= 500 and img.shape[1] >= 700
    # not blank: many pixels off white, several hues (group colours, points)
    assert (img.min(axis=2) < 200).mean() > 0.03
    assert len(np.unique(img.reshape(-1, 3) // 32, axis=0)) > 20
    # lines: one segment per true line, one colour per parallel group
    lines = json.loads((result_dir / "lines3d.json").read_text())
    ls = o3d.io.read_line_set(str(tmp_path / "lines3d.ply"))
    assert len(ls.lines) == len(lines["segments"])
    cols = np.asarray(ls.colors)
    groups = np.array([s["group"] for s in lines["segments"]])
    for g in np.unique(groups):
        assert np.allclose(cols[groups == g], cols[groups == g][0])
    firsts = np.array([cols[groups == g][0] for g in np.unique(groups)[:10]])
    assert len(np.unique(firsts.round(3), axis=0)) == len(firsts)
    seg = np.asarray(ls.points)[np.asarray(ls.lines)]
    assert np.allclose(seg[:, 0], [s["start"] for s in lines["segments"]])
    # cameras: the path (29 segments) and 3 axes per drawn pose (every 2nd of 30, and the last)
    cams = o3d.io.read_line_set(str(tmp_path / "cameras.ply"))
    assert len(cams.lines) == 29 + 3 * 16
    # the HTML page is self-contained: nothing to fetch
    html = (tmp_path / "snap.html").read_text()
    assert not re.search(r"https?://|\bsrc\s*=|<link\b|@import", html)


def test_html_in_headless_chromium(result_dir: Path, tmp_path: Path) -> None:
    assert cli_main(["view", "--input", str(result_dir), "--output",
                     str(tmp_path / "v.png")]) == 0
    page = tmp_path / "v.html"
    shot = tmp_path / "shot.png"
    run = _browser(page, f"--screenshot={shot}")
    assert not _js_errors(run.stderr), _js_errors(run.stderr)
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (600, 800)
    off = np.abs(img[:, :, ::-1].astype(int) - BACKGROUND).sum(axis=2) > 30
    assert off.mean() > 0.05, off.mean()          # points and lines drawn, not an empty page
    dom = _browser(page, "--dump-dom")
    m = re.search(r'data-drawn="(\d+)"', dom.stdout)
    assert m is not None and int(m.group(1)) > 10_000, dom.stdout[-500:]
    assert re.search(r"drawn: \d+ points, \d+ segments", dom.stdout)


def test_js_error_check_can_fail(tmp_path: Path) -> None:
    """The error check above sees an uncaught exception (it is not vacuous)."""
    page = tmp_path / "bad.html"
    page.write_text("<!DOCTYPE html><html><body><script>null.draw();</script></body></html>")
    assert _js_errors(_browser(page, "--dump-dom").stderr)


def test_view_without_points_or_lines(result_dir: Path, tmp_path: Path) -> None:
    d = tmp_path / "poses"
    d.mkdir()
    shutil.copy(result_dir / "trajectory.tum", d / "trajectory.tum")
    assert cli_main(["view", "--input", str(d)]) == 0
    assert (d / "view.png").is_file() and (d / "view.html").is_file()
    assert (d / "cameras.ply").is_file() and not (d / "lines3d.ply").exists()


def test_view_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["view", "--input", str(tmp_path / "missing")]) == 2
    assert_one_line_error(capsys, "missing")
    assert cli_main(["view", "--input", str(tmp_path)]) == 2
    assert_one_line_error(capsys, "trajectory.tum")
