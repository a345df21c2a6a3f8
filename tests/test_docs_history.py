"""The docs and docstrings say what the software does now; its history is git's.

Greps README.md, docs/*.md and the sources of omni_sfm/, plugins/ and scripts/ (docstrings and
comments) for the marks of a lab notebook: dates, former figures ("(was 1.06 deg)", "was
0.01"), "until <date or commit>", "earlier builds", "before the fix", was/now tables. Past
tense as grammar ("the frame was skipped", "iterate until the cost settles") is not history
and is allowed. The measurement
records under docs/benchmarks/ carry their dates on purpose and are not searched.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MONTHS = "Jan|Feb|Mar|Apr|May|Jun|Jul|Aug|Sep|Oct|Nov|Dec"
HISTORY = re.compile("|".join([
    r"\b20\d\d-\d\d-\d\d\b",                                     # 2026-11-27
    rf"\b\d{{1,2}} (?:{MONTHS})[a-z]* 20\d\d\b",                 # 21 Nov 2026
    rf"\b(?:{MONTHS})[a-z]* \d{{1,2}},? 20\d\d\b",               # Nov 21, 2026
    r"\((?:was|were) ",                                          # (was 1.06 deg)
    r"\b(?:was|were) (?:-?\d|~)",                                # was 0.01
    r"\b[Uu]ntil (?:20\d\d|\d{1,2} [A-Z]|commit|the fix|the change|recently|now)\b",
    r"\b(?:earlier|older|previous) (?:builds?|code|versions?|commits?|sessions?)\b",
    r"\b(?:first|second|third|this|that|last) session\b",
    r"\bbefore (?:the|this|that) (?:fix|change|commit|session)\b",
    r"\|\s*was\s*\|\s*now\s*\|",                                 # | was | now | tables
    r"\bbefore\s*->\s*after\b",
]), re.I)


def sources() -> list[Path]:
    """README.md, docs/*.md and the Python and C sources of the library, its plugins and the
    scripts."""
    files = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    for folder in ("omni_sfm", "plugins", "scripts"):
        for ext in ("*.py", "*.c"):
            files += sorted((ROOT / folder).rglob(ext))
    return files


def history_lines(path: Path) -> list[str]:
    """``"path:line: text"`` for every line of ``path`` with a mark of history; each line is
    searched together with the start of the next, so that a date broken over two lines counts."""
    out = []
    lines = path.read_text(encoding="utf-8").splitlines()
    for k, line in enumerate(lines):
        following = lines[k + 1].strip().split(" ")[:3] if k + 1 < len(lines) else []
        if HISTORY.search(" ".join([line.strip(), *following])):
            out.append(f"{path.relative_to(ROOT)}:{k + 1}: {line.strip()}")
    return out


@pytest.mark.parametrize("path", sources(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_history(path: Path) -> None:
    found = history_lines(path)
    assert not found, "history in the docs (git has it):\n" + "\n".join(found)


@pytest.mark.parametrize("line", [
    "Until 2026-11-27 it had to score 1 % lower",
    "of dropping them (was 1.06 deg).",
    "with earlier builds the same walk took 189-199 s",
    "0.01 until 2026-11-27, which kept the worse",
    "(Room re-run on 21 Nov 2026, 11:40 UTC, with the weighted line bundle adjustment",
    "| option | was | now |",
    "by stage (`--stages`, before -> after): edge points",
    "the default was 0.5 before the fix",
    "### The tracker's cost (28 Nov 2026, second session)",
])
def test_history_is_recognised(line: str) -> None:
    assert HISTORY.search(line), line


@pytest.mark.parametrize("line", [
    "frames: the frames ``result`` was computed from (matched by their source index).",
    "reasons: frame index -> why it was not estimated.",
    "the worker's loop: an extractor, then frames until the input closes.",
    "alternate, until the cost settles, the world NVs",
    "On any exception the temporary folder is removed and ``path`` is left as it was",
])
def test_grammar_is_not_history(line: str) -> None:
    assert not HISTORY.search(line), line
