"""Test-session settings and fixtures shared by every test file."""

import os
import stat
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

# The estimator works on many small matrices: OpenBLAS's thread pool only adds contention on
# small machines (5-10x slower on 2 busy cores). Must be set before numpy is imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The tests marked ``slow`` first (in their order), so that with one test process per
    core (``make test``) the long ones start at once and the short ones fill in around them,
    instead of one process running a minute-long test alone at the end."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


def _make_read_only(root: Path) -> None:
    """Remove every write permission below ``root`` (and of ``root``): a test that writes into
    a shared render fails at once instead of changing what other tests see."""
    for dirpath, _, filenames in os.walk(root, topdown=False):
        for name in filenames:
            p = Path(dirpath) / name
            p.chmod(p.stat().st_mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
        d = Path(dirpath)
        d.chmod(d.stat().st_mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    """``{relative path: (size, mtime_ns)}`` of everything below ``root``."""
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*"))}


@pytest.fixture(scope="session")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Callable[[Any], Any]]:
    """``rendered(options)``: the :class:`RenderResult` of ``render_sequence(folder, options)``,
    rendered once per test session for each distinct :class:`RenderOptions` (equal options,
    equal files), into a session temporary folder.

    The folder is shared by every test that asks for the same options: a test that needs to
    write next to the frames copies what it needs into its own folder. The folder is made
    read-only (which stops a test that writes into it, unless it runs as root), and at the end
    of the session it must hold exactly the files it was rendered with.
    """
    from omni_sfm.synth.render import RenderOptions, render_sequence

    cache: dict[RenderOptions, Any] = {}
    snapshots: dict[Path, dict[str, tuple[int, int]]] = {}

    def get(options: RenderOptions) -> Any:
        if options not in cache:
            out = tmp_path_factory.mktemp("render") / "seq"
            cache[options] = render_sequence(out, options, progress=False)
            _make_read_only(out)
            snapshots[out] = _snapshot(out)
        return cache[options]

    yield get
    for out, before in snapshots.items():
        assert _snapshot(out) == before, f"a test changed the shared render {out}"


@pytest.fixture(scope="session")
def corridor(rendered: Callable[[Any], Any]) -> Path:
    """The texture-poor corridor of the paper's set-up: hyperboloid 800 x 600, 40 frames,
    seed 1 (the session's read-only render)."""
    from omni_sfm.synth.render import RenderOptions

    out: Path = rendered(RenderOptions(camera="hyperboloid", frames=40, seed=1)).output
    return out


@pytest.fixture(scope="session")
def room(rendered: Callable[[Any], Any]) -> Path:
    """The textured room: hyperboloid 400 x 300, small preset without supersampling, 20
    frames, seed 3 (the session's read-only render)."""
    from omni_sfm.synth.render import RenderOptions

    out: Path = rendered(RenderOptions(camera="hyperboloid", width=400, height=300,
                                       supersample=1, preset="small", seed=3, scene="room",
                                       frames=20, textured=True)).output
    return out
