"""Test-session settings and fixtures shared by every test file."""

import fcntl
import hashlib
import os
import pickle
import shutil
import stat
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

# The estimator works on many small matrices: OpenBLAS's thread pool only adds contention on
# small machines (5-10x slower on 2 busy cores). Must be set before numpy is imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The tests marked ``slow`` first, the longest first (``slow(seconds=N)``, 15 s when not
    given; equal ones in their order): ``make test`` hands its test processes one test at a
    time in this order, so the long ones start at once and the short ones fill in around them,
    instead of one process running a minute-long test alone at the end."""
    def key(item: pytest.Item) -> float:
        slow = item.get_closest_marker("slow")
        return 0.0 if slow is None else -float(slow.kwargs.get("seconds", 15))

    items.sort(key=key)


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


def _session_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder every test process of this run shares: with pytest-xdist each worker's
    temporary folder lies in it (``pytest-N/popen-gwK``), without it is the run's own."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@contextmanager
def _locked(lock: Path) -> Iterator[None]:
    """Hold an exclusive lock on the file ``lock`` (the test processes of a run take turns)."""
    with open(lock, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def built_once(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str, Callable[[Path], Any]],
                                                                     tuple[Path, Any]]:
    """``built_once(name, build)``: ``(folder, value)``, where ``value = build(folder)`` ran
    once per test run for ``name``, by the first test process that asked; the others wait for
    it and get the same folder and value (pickled beside it). ``build`` writes ``folder``
    whole before it returns (a process that finds a folder without its value builds it
    again); the folder is then made read-only: a test that needs to write next to it copies
    what it needs.

    For deterministic artefacts that several test files would otherwise each compute (and,
    under pytest-xdist's test-by-test scheduling, the tests of one file spread over the
    processes)."""
    root = _session_root(tmp_path_factory) / "built-once"
    root.mkdir(exist_ok=True)
    values: dict[str, tuple[Path, Any]] = {}

    def get(name: str, build: Callable[[Path], Any]) -> tuple[Path, Any]:
        if name not in values:
            folder, value_file = root / name, root / f"{name}.pickle"
            with _locked(root / f"{name}.lock"):
                if not value_file.exists():               # written last: the build is whole
                    shutil.rmtree(folder, ignore_errors=True)     # what a failed build left
                    folder.mkdir()
                    value = build(folder)
                    _make_read_only(folder)
                    value_file.write_bytes(pickle.dumps(value))
            values[name] = (folder, pickle.loads(value_file.read_bytes()))
        return values[name]

    return get


@pytest.fixture(scope="session")
def rendered(built_once: Callable[[str, Callable[[Path], Any]], tuple[Path, Any]]
             ) -> Iterator[Callable[[Any], Any]]:
    """``rendered(options)``: the :class:`RenderResult` of ``render_sequence(folder, options)``,
    rendered once per test run for each distinct :class:`RenderOptions` (equal options, equal
    files), by whichever test process asks first (``built_once``).

    The folder is shared by every test that asks for the same options: a test that needs to
    write next to the frames copies what it needs into its own folder. The folder is made
    read-only (which stops a test that writes into it, unless it runs as root), and at the end
    of the session it must hold exactly the files it was rendered with.
    """
    from omni_sfm.synth.render import render_sequence

    snapshots: dict[Path, dict[str, tuple[int, int]]] = {}

    def get(options: Any) -> Any:
        # the options' repr names every field and value: equal options, equal name
        name = "render-" + hashlib.sha256(repr(options).encode()).hexdigest()[:16]
        _, result = built_once(name, lambda d: render_sequence(d / "seq", options,
                                                                 progress=False))
        snapshots.setdefault(result.output, _snapshot(result.output))
        return result

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
def dual_room(rendered: Callable[[Any], Any]) -> Path:
    """The textured room in raw dual-fisheye frames: two 200 deg lenses of 320 x 320 side by
    side, 4 cm apart, 20 frames, seed 3 (the session's read-only render)."""
    from omni_sfm.synth.render import RenderOptions

    out: Path = rendered(RenderOptions(camera="dual-fisheye", width=640, height=320,
                                       supersample=1, preset="small", seed=3, scene="room",
                                       frames=20, textured=True)).output
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
