"""Every ```python block of README.md and docs/*.md runs as written, so no example can rot.

Each block is executed with ``exec`` in a fresh namespace, in a temporary working directory that
holds the small data the blocks refer to by relative name (built once per session):

- ``seq/``: a rendered corridor (hyperboloid camera, 400 x 300, 10 frames): ``images/``,
  ``camera.yaml``, ``groundtruth.tum``, ... as ``omni-sfm render`` writes them;
- ``camera.yaml``, ``images/``: copies of ``seq/camera.yaml`` and ``seq/images/``;
- ``init/``: ``omni-sfm init`` of ``seq/`` (with the COLMAP model and ``images_colmap/``).

A block that raises fails its test, named by file and line of the block's opening fence.
"""

from __future__ import annotations

import re
import shutil
import traceback
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^```python\s*$")


def python_blocks(path: Path) -> list[tuple[int, str]]:
    """``(line of the opening fence, code)`` of every ```python block of a Markdown file."""
    blocks: list[tuple[int, str]] = []
    lines = path.read_text(encoding="utf-8").splitlines()
    k = 0
    while k < len(lines):
        if FENCE.match(lines[k]):
            start = k + 1
            end = start
            while end < len(lines) and not lines[end].startswith("```"):
                end += 1
            if end == len(lines):
                raise ValueError(f"{path}:{k + 1}: unclosed ```python block")
            blocks.append((k + 1, "\n".join(lines[start:end]) + "\n"))
            k = end
        k += 1
    return blocks


BLOCKS = [(path, line, code) for path in DOC_FILES for line, code in python_blocks(path)]


def run_block(path: Path, line: int, code: str) -> dict:
    """Execute ``code`` in a fresh namespace; tracebacks point at the Markdown file's lines."""
    namespace: dict = {"__name__": "__doc_example__"}
    exec(compile("\n" * line + code, str(path), "exec"), namespace)
    return namespace


@pytest.fixture(scope="session")
def doc_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from omni_sfm.pipelines.init import InitOptions, init_from_images
    from omni_sfm.synth.render import RenderOptions, render_sequence

    root = tmp_path_factory.mktemp("docs_data")
    seq = root / "seq"
    render_sequence(seq, RenderOptions(scene="corridor", camera="hyperboloid", frames=10,
                                       width=400, height=300, seed=4), progress=False)
    shutil.copy(seq / "camera.yaml", root / "camera.yaml")
    shutil.copytree(seq / "images", root / "images")
    init_from_images(seq / "images", seq / "camera.yaml", root / "init",
                     InitOptions(debug_view="none", progress=False))
    return root


@pytest.fixture
def doc_cwd(doc_data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    import matplotlib

    monkeypatch.setenv("MPLBACKEND", "Agg")
    matplotlib.use("Agg")
    work = tmp_path / "work"
    shutil.copytree(doc_data, work)
    monkeypatch.chdir(work)
    return work


def test_the_docs_have_python_blocks() -> None:
    assert len(BLOCKS) >= 8
    assert {p.name for p, _, _ in BLOCKS} >= {"cameras.md", "frontend.md", "dense.md"}


def test_a_raising_block_fails(tmp_path: Path) -> None:
    md = tmp_path / "broken.md"
    md.write_text("text\n\n```python\nx = 1\ny = undefined_name\n```\n")
    [(line, code)] = python_blocks(md)
    assert line == 3
    with pytest.raises(NameError) as info:
        run_block(md, line, code)
    # the traceback names the Markdown line of the failing statement
    frames = traceback.extract_tb(info.value.__traceback__)
    assert (frames[-1].filename, frames[-1].lineno) == (str(md), 5)


@pytest.mark.parametrize(("path", "line", "code"), BLOCKS,
                         ids=[f"{p.relative_to(ROOT)}:{n}" for p, n, _ in BLOCKS])
def test_doc_block_runs(path: Path, line: int, code: str, doc_cwd: Path) -> None:
    run_block(path, line, code)
