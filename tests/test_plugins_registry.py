"""The plugin registry checks what it loads, a broken initializer is a recorded failure (never a
traceback), and the third-party distribution of docs/plugins.md, built from the page's text,
is discovered through its entry point and runs."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from collections.abc import Iterator, Mapping
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import omni_sfm.registry as registry_mod
from omni_sfm.compare import compare, run_initializer
from omni_sfm.errors import OmniSfmError
from omni_sfm.plugin_contract import InitializerResult, SequenceInput, check_result, failed
from omni_sfm.poses import Trajectory
from omni_sfm.registry import INITIALIZERS, PluginError, available, load

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "plugins.md"
EXAMPLE = "omni-sfm-straight"
EXAMPLE_MODULE = "omni_sfm_straight"


# ------------------------------------------------------------------ a tiny simulated sequence


@pytest.fixture(scope="module")
def sim() -> tuple[SequenceInput, Trajectory]:
    """The paper's simulation cut to 6 views (line normals only, no images) and its truth."""
    from omni_sfm.cameras import EquirectangularCamera
    from omni_sfm.synth.simulate import SimulationOptions, simulate

    s = simulate(SimulationOptions(num_views=6, seed=1))
    seq = SequenceInput(s.groundtruth.timestamps.copy(), EquirectangularCamera(width=800,
                                                                               height=400),
                        line_tracks=s.tracks, name="sim6")
    return seq, s.groundtruth


# ------------------------------------------------------------------ fake plugins of this module


def good(sequence: SequenceInput, options: Mapping[str, Any]) -> InitializerResult:
    """Keeps the contract: identity rotations on a helix."""
    ts = sequence.timestamps.copy()
    pos = np.stack([np.cos(ts), np.sin(ts), 0.1 * ts], axis=1)
    return InitializerResult(Trajectory(ts, np.repeat(np.eye(3)[None], len(ts), 0), pos))


def returns_a_string(sequence: SequenceInput, options: Mapping[str, Any]) -> Any:
    return "trajectory.tum"


def returns_an_array(sequence: SequenceInput, options: Mapping[str, Any]) -> Any:
    return InitializerResult(np.zeros((sequence.num_frames, 7)))  # type: ignore[arg-type]


def returns_a_bad_status(sequence: SequenceInput, options: Mapping[str, Any]) -> Any:
    return InitializerResult(good(sequence, options).trajectory, status="success")


def raises(sequence: SequenceInput, options: Mapping[str, Any]) -> InitializerResult:
    raise RuntimeError("the plugin's own bug")


NOT_CALLABLE = 42

FAKES = {  # name: (entry point value, the failure's reason must contain this)
    "good": (f"{__name__}:good", None),
    "returns-a-string": (f"{__name__}:returns_a_string",
                         "broken plugin: returned builtins.str, not an InitializerResult"),
    "returns-an-array": (f"{__name__}:returns_an_array",
                         "broken plugin: returned a trajectory of type ndarray, not a "
                         "Trajectory or None"),
    "returns-a-bad-status": (f"{__name__}:returns_a_bad_status",
                             "broken plugin: returned status 'success', not one of 'ok', "
                             "'failed'"),
    "raises": (f"{__name__}:raises", "RuntimeError: the plugin's own bug (test_plugins_registry"
                                     ".py:"),
    "not-callable": (f"{__name__}:NOT_CALLABLE",
                     f"plugin 'not-callable' of {INITIALIZERS} ({__name__}:NOT_CALLABLE) loads "
                     "an object of type int, not a callable"),
    "no-attribute": (f"{__name__}:no_such_function",
                     "cannot be loaded: AttributeError"),
    "no-module": ("omni_sfm_no_such_module:f",
                  "cannot be loaded: ModuleNotFoundError: No module named "
                  "'omni_sfm_no_such_module'"),
}


@pytest.fixture
def fake_plugins(monkeypatch: pytest.MonkeyPatch) -> dict[str, EntryPoint]:
    """The installed entry points plus :data:`FAKES` in the initializers group."""
    real = registry_mod.available
    fakes = {name: EntryPoint(name=name, value=value, group=INITIALIZERS)
             for name, (value, _) in FAKES.items()}

    def patched(group: str) -> dict[str, EntryPoint]:
        found = real(group)
        return {**found, **fakes} if group == INITIALIZERS else found

    monkeypatch.setattr(registry_mod, "available", patched)
    return fakes


def test_load_checks_what_an_entry_point_loads(fake_plugins: dict[str, EntryPoint]) -> None:
    assert load(INITIALIZERS, "good") is good
    assert "lines" in available(INITIALIZERS)  # the installed ones are still there
    for name in ("not-callable", "no-attribute", "no-module"):
        with pytest.raises(PluginError) as info:
            load(INITIALIZERS, name)
        msg = str(info.value)
        assert FAKES[name][1] in msg and "\n" not in msg, msg
    with pytest.raises(OmniSfmError, match="unknown initializer 'nope' \\(known: .*good") as e:
        load(INITIALIZERS, "nope")
    assert not isinstance(e.value, PluginError)


def test_run_initializer_records_a_broken_plugin(fake_plugins: dict[str, EntryPoint],
                                                 sim: tuple[SequenceInput, Trajectory]) -> None:
    seq, _ = sim
    for name, (_, expected) in FAKES.items():
        res, dt = run_initializer(name, seq, {})
        assert isinstance(res, InitializerResult)
        if expected is None:
            assert res.status == "ok" and res.trajectory is not None, res.reason
            continue
        assert res.status == "failed" and res.trajectory is None
        assert expected in res.reason and "\n" not in res.reason, res.reason
        assert dt >= 0
    with pytest.raises(OmniSfmError, match="unknown initializer 'nope'"):
        run_initializer("nope", seq, {})


def test_compare_records_broken_plugins_in_results(fake_plugins: dict[str, EntryPoint],
                                                   sim: tuple[SequenceInput, Trajectory],
                                                   tmp_path: Path) -> None:
    seq, gt = sim
    res = compare(seq, gt, tmp_path / "out", list(FAKES), plots=False)
    entries = res.results.to_json()["initializers"]
    assert list(entries) == list(FAKES)
    for name, (_, expected) in FAKES.items():
        e = entries[name]
        if expected is None:
            assert e["status"] == "ok" and e["trajectory"] == "trajectories/good.tum"
            assert e["frames_compared"] == seq.num_frames and e["rot_max_deg"] is not None
            continue
        assert e["status"] == "failed" and expected in e["reason"], e
        assert e["trajectory"] is None and e["rot_max_deg"] is None and e["registered"] == 0
    report = (tmp_path / "out" / "report.md").read_text()
    assert "broken plugin: returned builtins.str" in report


@pytest.mark.parametrize(("res", "expected"), [
    (None, "returned builtins.NoneType, not an InitializerResult"),
    ({"trajectory": None, "status": "ok"}, "returned builtins.dict, not an InitializerResult"),
    (InitializerResult(None, status="OK"), "returned status 'OK', not one of 'ok', 'failed'"),
    (InitializerResult(None, reason=3),  # type: ignore[arg-type]
     "returned a reason of type int, not a str"),
    (InitializerResult(None, info=[1]),  # type: ignore[arg-type]
     "returned info of type list, not a dict"),
])
def test_check_result_names_the_breach(res: object, expected: str) -> None:
    out = check_result(res)
    assert out.status == "failed" and out.trajectory is None
    assert out.reason == f"broken plugin: {expected}"


def test_check_result_passes_a_good_result_through() -> None:
    for res in (failed("no frames", tried=3), InitializerResult(None, "ok", "nothing")):
        assert check_result(res) is res


# ------------------------------------------------------------------ the example of docs/plugins.md


def doc_example_files() -> dict[str, str]:
    """The files of the example distribution, from docs/plugins.md: each is a fenced block right
    after a line `` `omni-sfm-straight/PATH`: ``; ``{PATH: text}``."""
    lines = DOC.read_text(encoding="utf-8").splitlines()
    files: dict[str, str] = {}
    for k, line in enumerate(lines):
        m = re.fullmatch(rf"`{EXAMPLE}/([^`]+)`:\s*", line)
        if not m:
            continue
        start = next(j for j in range(k + 1, len(lines)) if lines[j].strip())
        assert lines[start].startswith("```"), f"{DOC}:{start + 1}: no block after {line}"
        end = next(j for j in range(start + 1, len(lines)) if lines[j].startswith("```"))
        files[m[1]] = "\n".join(lines[start + 1:end]) + "\n"
    return files


@pytest.fixture
def example_src(tmp_path: Path) -> Iterator[Path]:
    """The example distribution's folder, written from the doc's text."""
    files = doc_example_files()
    assert set(files) == {"pyproject.toml", f"{EXAMPLE_MODULE}.py"}, sorted(files)
    src = tmp_path / EXAMPLE
    for rel, text in files.items():
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        (src / rel).write_text(text, encoding="utf-8")
    yield src
    sys.modules.pop(EXAMPLE_MODULE, None)  # each test imports its own installed copy


def check_example_installed(site: Path, seq: SequenceInput, gt: Trajectory,
                            tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With ``site`` on sys.path, the example is discovered and keeps what the doc says."""
    assert "straight-line" not in available(INITIALIZERS)
    monkeypatch.syspath_prepend(str(site))  # also invalidates the import caches
    eps = available(INITIALIZERS)
    assert eps["straight-line"].value == "omni_sfm_straight:straight_line"
    assert eps["straight-line"].dist is not None
    assert eps["straight-line"].dist.name == EXAMPLE
    assert "lines" in eps

    res, _ = run_initializer("straight-line", seq, {"speed": 0.5})
    assert res.status == "ok", res.reason
    assert res.trajectory is not None and len(res.trajectory) == seq.num_frames
    np.testing.assert_array_equal(res.trajectory.timestamps, seq.timestamps)
    np.testing.assert_array_equal(res.trajectory.rotations,
                                  np.repeat(np.eye(3)[None], seq.num_frames, 0))
    np.testing.assert_allclose(res.trajectory.positions[:, 0],
                               0.5 * (seq.timestamps - seq.timestamps[0]), rtol=0, atol=1e-15)
    assert "ignores the images" in res.reason and res.info == {"speed": 0.5,
                                                               "frames": seq.num_frames}
    # the failure the doc quotes
    res, _ = run_initializer("straight-line", seq, {"sped": 1})
    assert (res.status, res.reason) == ("failed", "unknown option(s) sped (known: speed)")

    out = compare(seq, gt, tmp_path / "cmp", ["straight-line"], plots=False)
    e = out.results.to_json()["initializers"]["straight-line"]
    assert e["status"] == "ok" and e["frames_compared"] == seq.num_frames
    assert e["reason"].startswith("baseline:")


def test_doc_example_discovered_from_its_dist_info(example_src: Path, tmp_path: Path,
                                                  sim: tuple[SequenceInput, Trajectory],
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """What an installer leaves (the module and a dist-info with the doc's entry points), made
    here without a build backend: the discovery is importlib.metadata's, as for a real one."""
    meta = tomllib.loads((example_src / "pyproject.toml").read_text())
    project = meta["project"]
    assert meta["tool"]["setuptools"]["py-modules"] == [EXAMPLE_MODULE]
    site = tmp_path / "site"
    site.mkdir()
    (site / f"{EXAMPLE_MODULE}.py").write_text((example_src / f"{EXAMPLE_MODULE}.py").read_text())
    dist_info = site / f"{project['name'].replace('-', '_')}-{project['version']}.dist-info"
    dist_info.mkdir()
    (dist_info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {project['name']}\n"
                                        f"Version: {project['version']}\n")
    (dist_info / "entry_points.txt").write_text("".join(
        f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()) + "\n"
        for group, eps in project["entry-points"].items()))
    check_example_installed(site, *sim, tmp_path, monkeypatch)


def test_doc_example_installs_with_pip(example_src: Path, tmp_path: Path,
                                       sim: tuple[SequenceInput, Trajectory],
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """``pip install`` of the doc's folder (no network, no dependencies), then discovery.
    The set-up installs what building needs without network (the ``dev`` extra's
    setuptools >= 77 and wheel)."""
    site = tmp_path / "site"
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-index",
         "--no-build-isolation", "--disable-pip-version-check", "--target", str(site),
         str(example_src)],
        capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (site / f"{EXAMPLE_MODULE}.py").is_file()
    check_example_installed(site, *sim, tmp_path, monkeypatch)
