"""The package's import direction: stages import only earlier stages and the shared helpers.

Every module under ``omni_sfm/`` is parsed with :mod:`ast` (nothing is imported) and every
``import`` / ``from`` statement is collected, those inside functions included (lazy imports are
imports too). The pipeline runs one way, cameras -> lines -> vanishing -> estimate -> export ->
refine -> dense -> view; the shared helpers sit below all stages; the entry points that wire
the stages together (``pipelines``, and the initializer plugins' contract) sit above them;
simulation and rendering (``synth``) and the comparison with ground truth (``evaluate``) sit
above those, with the programs that use both (``compare``, ``pipelines.demo``, ``cli``).
No part imports another part's private module or name, and the shared machinery (frame
reading, the least-squares solver) is defined in its own module and imported from there.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "omni_sfm"

STAGES = ["cameras", "lines", "vanishing", "estimate", "export", "refine", "dense", "view"]
"""Pipeline stages in their order: a stage may import only itself and earlier stages."""
HELPERS = ["geometry", "transforms", "fileio", "folders", "reports", "libs", "poses", "errors",
           "registry", "frames", "solver", "corners"]
"""Shared helpers below the stages (top-level modules of ``omni_sfm``)."""
ENTRY_POINTS = ["pipelines", "plugin_contract"]
"""Above the stages: the programs that wire them together, and what a plugin gets and returns."""
UPPER = ["synth", "evaluate"]
"""Ground-truth side: only ``UPPER`` itself and the programs in ``CONSUMERS`` may import it."""
CONSUMERS = ["synth", "evaluate", "compare", "pipelines.demo", "cli"]
"""Parts of ``omni_sfm`` (a dotted name: that module and those under it) that may import
``UPPER``."""


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imported(path: Path, module: str) -> set[str]:
    """Absolute names of the modules (or module attributes) imported anywhere in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_package = path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                keep = len(base) - node.level + (1 if is_package else 0)
                prefix = ".".join(base[:keep])
                target = f"{prefix}.{node.module}" if node.module else prefix
            else:
                target = node.module or ""
            out.add(target)
            # ``from omni_sfm import evaluate`` imports the submodule
            out.update(f"{target}.{alias.name}" for alias in node.names if alias.name != "*")
    return out


def _all_imports() -> dict[str, set[str]]:
    mods = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        name = _module_name(path)
        mods[name] = {t for t in _imported(path, name) if t == "omni_sfm"
                      or t.startswith("omni_sfm.")}
    return mods


IMPORTS = _all_imports()


def _part(name: str) -> str | None:
    """The top-level part of ``omni_sfm`` a module name belongs to (None: the package)."""
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else None


def _within(name: str, parts: list[str]) -> bool:
    """Whether module ``name`` is one of ``parts`` of ``omni_sfm`` or under one of them."""
    return any(name == f"omni_sfm.{p}" or name.startswith(f"omni_sfm.{p}.") for p in parts)


def test_walk_finds_the_package():
    assert "omni_sfm.estimate.pipeline" in IMPORTS
    assert "omni_sfm.transforms" in IMPORTS["omni_sfm.estimate.global_estimator"]
    # function-level (lazy) imports are seen
    assert "omni_sfm.synth.render" in IMPORTS["omni_sfm.pipelines.demo"]
    for part in STAGES + HELPERS + ENTRY_POINTS + UPPER:
        assert any(_part(m) == part for m in IMPORTS), part


def test_relative_import_resolution():
    path = PACKAGE / "estimate" / "paper.py"
    assert _module_name(path) == "omni_sfm.estimate.paper"
    assert _module_name(PACKAGE / "lines" / "__init__.py") == "omni_sfm.lines"


@pytest.mark.parametrize("part", STAGES + HELPERS + ENTRY_POINTS)
def test_no_stage_or_helper_imports_synth_or_evaluate(part):
    bad = sorted(f"{mod} imports {target}" for mod, targets in IMPORTS.items()
                 if _part(mod) == part and not _within(mod, CONSUMERS)
                 for target in targets if _part(target) in UPPER)
    assert not bad, "\n".join(bad)


def test_only_consumers_import_synth_or_evaluate():
    bad = sorted(f"{mod} imports {target}" for mod, targets in IMPORTS.items()
                 if not _within(mod, CONSUMERS)
                 for target in targets if _part(target) in UPPER)
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("part", STAGES + HELPERS)
def test_no_stage_or_helper_imports_an_entry_point(part):
    bad = sorted(f"{mod} imports {target}" for mod, targets in IMPORTS.items()
                 if _part(mod) == part for target in targets
                 if _part(target) in ENTRY_POINTS + ["compare", "cli"])
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("stage", STAGES)
def test_stage_imports_no_later_stage(stage):
    rank = {s: k for k, s in enumerate(STAGES)}
    bad = sorted(f"{mod} imports {target}" for mod, targets in IMPORTS.items()
                 if _part(mod) == stage for target in targets
                 if _part(target) in rank and rank[_part(target)] > rank[stage])
    assert not bad, "\n".join(bad)


def _private(name: str) -> bool:
    """Whether a dotted name has a private part (``_x``; ``__init__`` and the like are not)."""
    return any(p.startswith("_") and not p.startswith("__") for p in name.split(".")[1:])


def test_no_part_imports_another_parts_private_module_or_name():
    bad = sorted(f"{mod} imports {target}" for mod, targets in IMPORTS.items()
                 for target in targets if _private(target) and _part(target) != _part(mod))
    assert not bad, "\n".join(bad)


def test_the_private_check_sees_private_modules_and_names():
    assert _private("omni_sfm.vanishing._groups")
    assert _private("omni_sfm.estimate.bundle._ReducedSystem")
    assert not _private("omni_sfm.lines.__init__") and not _private("omni_sfm.estimate.bundle")


def _defined(path: Path) -> set[str]:
    """Top-level function and class names defined in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    return {node.name for node in tree.body
            if isinstance(node, ast.FunctionDef | ast.ClassDef)}


HOMES = {
    "omni_sfm.frames": {"read_frames", "read_stream", "read_mask", "FrameSource", "FrameStore",
                        "Frame", "to_gray", "open_video"},
    "omni_sfm.solver": {"levenberg_marquardt", "LMProblem", "LandmarkDamping", "StepDistance",
                        "RobustLoss", "loss_weights", "robust_sigma", "damped", "gauge"},
}
"""Shared machinery below the stages: each name is defined in its home module only, and
imported from there."""


@pytest.mark.parametrize("home", sorted(HOMES))
def test_shared_machinery_is_defined_and_imported_in_its_own_module(home):
    names = HOMES[home]
    path = PACKAGE.parent / (home.replace(".", "/") + ".py")
    assert names <= _defined(path), sorted(names - _defined(path))
    elsewhere = sorted(f"{p.relative_to(PACKAGE.parent)} defines {n}"
                       for p in PACKAGE.rglob("*.py") if p != path
                       for n in _defined(p) & names)
    assert not elsewhere, "\n".join(elsewhere)
    # imported from the home module itself, never through another module that imports it
    bad = sorted(f"{mod} imports {target}" for mod, targets in IMPORTS.items() if mod != home
                 for target in targets if target.rpartition(".")[2] in names
                 and target.rpartition(".")[0] not in (home, "")
                 and target.rpartition(".")[0] in IMPORTS)
    assert not bad, "\n".join(bad)


def _folder_file_names() -> set[str]:
    """The file names (with an extension) the folder classes of ``omni_sfm.folders`` own."""
    import omni_sfm.folders as folders

    return {v for cls in vars(folders).values() if isinstance(cls, type)
            and cls.__module__ == folders.__name__
            for k, v in vars(cls).items() if k.isupper() and isinstance(v, str) and "." in v}


def test_folder_file_names_are_spelled_in_folders_only():
    names = _folder_file_names()
    assert {"trajectory.tum", "report.json", "tracks.json", "colmap.json", "lines.json"} <= names
    bad = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.name == "folders.py" and path.parent == PACKAGE:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        docs = {id(node.body[0].value) for node in ast.walk(tree)
                if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef
                              | ast.AsyncFunctionDef)
                and node.body and isinstance(node.body[0], ast.Expr)}
        bad += [f"{path.relative_to(PACKAGE.parent)}:{node.lineno} spells {node.value!r}"
                for node in ast.walk(tree) if isinstance(node, ast.Constant)
                and node.value in names and id(node) not in docs]
    assert not bad, "\n".join(bad)


JSON_READERS = {
    "omni_sfm/fileio.py": "read_json itself",
    "omni_sfm/reports.py": "every stage's report.json and compare's results.json",
    "omni_sfm/folders.py": "colmap.json (the COLMAP model's manifest)",
    "omni_sfm/lines3d.py": "lines3d.json",
    "omni_sfm/lines/tracks.py": "tracks.json",
    "omni_sfm/export/nerfstudio.py": "transforms.json (an export read back, for checks)",
}
"""The one module that parses each JSON artifact."""


def test_each_json_artifact_has_one_reader():
    """JSON is parsed (``read_json``, ``json.load``/``json.loads``) only by the reader of its
    artifact: a report is read through omni_sfm.reports, never as a dict of its own."""
    bad = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).as_posix()
        if rel in JSON_READERS:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if not isinstance(node, ast.Call):
                continue
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            owner = f.value.id if isinstance(f, ast.Attribute) and isinstance(
                f.value, ast.Name) else None
            if name == "read_json" or (owner == "json" and name in ("load", "loads")):
                bad.append(f"{rel}:{node.lineno} parses JSON")
    assert not bad, "\n".join(bad)


REPORT_WRITERS = {
    "omni_sfm/reports.py": "JsonReport.write: every report but init's line-based one",
    "omni_sfm/estimate/pipeline.py": "init's report.json, built by the estimator",
}


def test_reports_are_written_by_their_classes():
    """``report.json`` and ``results.json`` are written through their report class
    (:meth:`omni_sfm.reports.JsonReport.write`), not as text of a dict."""
    bad = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).as_posix()
        if rel in REPORT_WRITERS:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == \
                    "atomic_write_text" and node.args:
                target = ast.unparse(node.args[0])
                if any(name in target for name in ("REPORT", "RESULTS")) and \
                        "REPORT_MD" not in target:
                    bad.append(f"{rel}:{node.lineno} writes {target}")
    assert not bad, "\n".join(bad)


def test_no_function_of_the_estimator_is_longer_than_60_lines():
    # the estimator reads as its steps: each function one idea (the global-estimator issue)
    long = []
    for path in sorted((PACKAGE / "estimate").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                size = node.end_lineno - node.lineno + 1  # type: ignore[operator]
                if size > 60:
                    long.append(f"{path.name}:{node.name} ({size} lines)")
    assert not long, long
