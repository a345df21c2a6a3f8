"""Render the docs' results tables from the measurement log, ``docs/benchmarks/*.json``.

Each record (written by a script through :func:`scripts.benchlib.write_log`) is shown where a
page has the marker pair ``<!-- results:NAME -->`` ... ``<!-- /results:NAME -->``: its table,
then the command that measured it, the commit and the machine. ``<!-- results:summary -->`` is
the README's table of headlines, one row per entry of :data:`SUMMARY`. Everything between the
markers is rewritten; the rest of the page is left alone.

A table of measured figures belongs in such a block: :func:`measurement_tables` finds the
tables outside the blocks (and outside code blocks) whose cells are mostly figures, and
``--check`` fails on them as on a stale block.

    .venv/bin/python -m scripts.render_results          # rewrite the blocks in README.md, docs/
    .venv/bin/python -m scripts.render_results --check  # exit 1 where a block differs, or a
                                                        # page has a hand-written measurement table

tests/test_docs_benchmarks.py runs the check.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
LOG_DIR = ROOT / "docs" / "benchmarks"
REQUIRED = ("name", "title", "command", "commit", "machine", "source", "columns", "rows",
            "headline")
BLOCK = re.compile(r"(<!-- results:(?P<name>[A-Za-z0-9_-]+) -->\n)(?P<body>.*?)"
                   r"(<!-- /results:(?P=name) -->)", re.S)

# A figure: a number, with its unit if it has one ("0.12 %", "16.6 s", "1.3x", "662k").
FIGURE = re.compile(r"[-+~<>]?\d[\d,]*(?:\.\d+)?(?:e-?\d+)?"
                    r"(?:\s?(?:ms|s|min|h|%|deg|fps|MB|MiB|GB|GiB|kB|mm|cm|px|k)(?!\w)|x(?!\w))?")
#: A table is a measurement table when at least this share of its cells (the first column,
#: the rows' names, left out) are figures.
MEASURED_SHARE = 0.5
#: Reference tables whose cells are mostly numbers that are settings, not measurements, by
#: their header row.
REFERENCE_TABLES = frozenset({
    "| preset | frames | hyperboloid | equirectangular |",  # docs/rendering.md: image sizes
    "| kind | what | seeds |",  # docs/comparison.md: the sweep's sequences and their seeds
})


@dataclass(frozen=True)
class SummaryRow:
    """One row of the README's results table: what, which record's headline, which page."""

    what: str
    record: str
    page: str


SUMMARY = (
    SummaryRow("Paper reproduction (simulated, Fig. 12 set-up)", "repro_paper",
               "docs/paper_reproduction.md"),
    SummaryRow("Estimator speed (200 views, 10 + 5 lines)", "bench_backend",
               "docs/estimator.md"),
    SummaryRow("Front end (lines extracted and tracked)", "bench_frontend", "docs/frontend.md"),
    SummaryRow("`init` on rendered sequences", "eval_init", "docs/results.md"),
    SummaryRow("`init` on footage-like video (office walk)", "eval_footage_global",
               "docs/estimator.md"),
    SummaryRow("`init` against COLMAP's mapper", "bench_init",
               "docs/results.md"),
    SummaryRow("Long video (3,000 frames, 1920x960 H.264)",
               "bench_long_video", "docs/results.md"),
    SummaryRow("Short tracks against the oracle", "eval_sparse_global", "docs/estimator.md"),
    SummaryRow("`init` on hand-held 640x320 H.264 along a cell house (not yet: the bars are "
               "not tracked)", "eval_cellhouse", "docs/comparison.md"),
    SummaryRow("Global estimator (where lines come and go)", "eval_global_manhattan",
               "docs/estimator.md"),
    SummaryRow("`init` on raw dual-fisheye frames (rendered, 1920x960, a rig of two lenses)",
               "eval_rig", "docs/estimator.md"),
    SummaryRow("A loop around an office block (45 m, both cameras)", "eval_loop",
               "docs/estimator.md"),
    SummaryRow("`refine` (lines and points adjusted together)", "bench_refine_room",
               "docs/colmap.md"),
    SummaryRow("`refine` on the office walk", "bench_refine_office", "docs/colmap.md"),
    SummaryRow("`dense` map", "bench_dense", "docs/dense.md"),
    SummaryRow("`track` (online poses)", "bench_track", "docs/track.md"),
    SummaryRow("Lines against points (`compare`)", "compare_init", "docs/comparison.md"),
)


def load_records(log_dir: Path = LOG_DIR) -> dict[str, dict[str, Any]]:
    """Every record of ``log_dir`` by name; a record without a required key, with rows of the
    wrong width or named unlike its file is an error."""
    records: dict[str, dict[str, Any]] = {}
    for path in sorted(log_dir.glob("*.json")):
        rec = json.loads(path.read_text(encoding="utf-8"))
        missing = [k for k in REQUIRED if k not in rec]
        if missing:
            raise ValueError(f"{path}: no {', '.join(missing)}")
        if rec["name"] != path.stem:
            raise ValueError(f"{path}: named {rec['name']!r}")
        width = len(rec["columns"])
        for row in rec["rows"]:
            if len(row) != width:
                raise ValueError(f"{path}: a row of {len(row)} cells for {width} columns: {row}")
        records[rec["name"]] = rec
    return records


def cell(value: Any, column: dict[str, Any]) -> str:
    """A table cell: numbers in the column's format (when it has one), text as it is."""
    if value is None:
        return "-"
    if isinstance(value, int | float) and not isinstance(value, bool) and column.get("format"):
        return format(value, column["format"])
    return str(value)


def rendered_rows(rec: dict[str, Any]) -> list[list[str]]:
    """The record's rows as the table shows them."""
    return [[cell(v, c) for v, c in zip(row, rec["columns"], strict=True)]
            for row in rec["rows"]]


def headline(rec: dict[str, Any]) -> str:
    """The record's one-line summary, its template filled with the rendered rows."""
    return str(rec["headline"]).format(rows=rendered_rows(rec))


def _link(page: Path, target: Path) -> str:
    return Path(os.path.relpath(target, page.parent)).as_posix()


def render_table(rec: dict[str, Any], page: Path) -> str:
    """The Markdown of one record on ``page``: table, notes, provenance."""
    labels = [c["label"] for c in rec["columns"]]
    out = ["| " + " | ".join(labels) + " |", "|" + "---|" * len(labels)]
    out += ["| " + " | ".join(r) + " |" for r in rendered_rows(rec)]
    out.append("")
    if rec.get("notes"):
        out += [rec["notes"], ""]
    log = _link(page, LOG_DIR / f"{rec['name']}.json")
    commands = list(dict.fromkeys(rec.get("row_commands") or [rec["command"]]))
    out.append("Measured by " + ", ".join(f"`{c}`" for c in commands)
               + f" (commit {rec['commit']}; {rec['machine']}; "
               f"record [{rec['name']}.json]({log})).")
    return "\n".join(out) + "\n"


def render_summary(records: dict[str, dict[str, Any]], page: Path) -> str:
    """The README's results table: one headline a row, with the page that details it."""
    out = ["| what | measured | details |", "|---|---|---|"]
    for row in SUMMARY:
        if row.record not in records:
            raise KeyError(f"summary: no record {row.record!r} in {LOG_DIR}")
        out.append(f"| {row.what} | {headline(records[row.record])} | "
                   f"[{Path(row.page).name}]({_link(page, ROOT / row.page)}) |")
    return "\n".join(out) + "\n"


def render_text(text: str, page: Path, records: dict[str, dict[str, Any]]) -> str:
    """``text`` (the page ``page``) with every results block rendered from ``records``."""
    def block(m: re.Match[str]) -> str:
        name = m.group("name")
        if name == "summary":
            body = render_summary(records, page)
        elif name in records:
            body = render_table(records[name], page)
        else:
            raise KeyError(f"{page}: block results:{name} has no record {name}.json")
        return m.group(1) + body + m.group(4)
    return BLOCK.sub(block, text)


def block_names(text: str) -> list[str]:
    """The names of the results blocks in ``text``, in order."""
    return [m.group("name") for m in BLOCK.finditer(text)]


def figure_cell(text: str) -> bool:
    """Whether a table cell is a figure: a number (with its unit, or several such, as in
    ``100/100, 0.05 deg, 0.01 %``) and at most two words beside it; code spans do not count."""
    text = re.sub(r"`[^`]*`", "", text)
    if not re.search(r"\d", text):
        return False
    return len(re.findall(r"[A-Za-z]{2,}", FIGURE.sub(" ", text))) <= 2


def markdown_tables(text: str) -> list[tuple[int, str, list[list[str]]]]:
    """``(line number, header row, body rows as cells)`` of every Markdown table of ``text``
    outside results blocks and fenced code blocks."""
    text = BLOCK.sub(lambda m: "\n" * m.group(0).count("\n"), text)
    lines = text.split("\n")
    out: list[tuple[int, str, list[list[str]]]] = []
    fence, i = False, 0
    while i < len(lines):
        if lines[i].lstrip().startswith(("```", "~~~")):
            fence = not fence
        elif (not fence and lines[i].strip().startswith("|") and i + 1 < len(lines)
              and re.fullmatch(r"\s*\|[\s:|-]+\|\s*", lines[i + 1])):
            j = i + 2
            while j < len(lines) and lines[j].strip().startswith("|"):
                j += 1
            body = [[c.strip() for c in ln.strip().strip("|").split("|")]
                    for ln in lines[i + 2:j]]
            out.append((i + 1, lines[i].strip(), body))
            i = j
            continue
        i += 1
    return out


def measurement_tables(text: str) -> list[tuple[int, str]]:
    """``(line number, header row)`` of the tables of ``text`` outside results blocks whose
    cells are mostly figures (:data:`MEASURED_SHARE`, the first column left out), but for
    :data:`REFERENCE_TABLES`: measurements written by hand instead of rendered from a record."""
    found = []
    for line, header, body in markdown_tables(text):
        cells = [c for row in body for c in row[1:]]
        if not cells or header in REFERENCE_TABLES:
            continue
        if sum(map(figure_cell, cells)) >= MEASURED_SHARE * len(cells):
            found.append((line, header))
    return found


def pages() -> list[Path]:
    """The pages that may hold results blocks: README.md and docs/*.md."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true",
                    help="change nothing; exit 1 when a block differs from its record")
    args = ap.parse_args()
    records = load_records()
    stale: list[Path] = []
    by_hand: list[str] = []
    for page in pages():
        text = page.read_text(encoding="utf-8")
        new = render_text(text, page, records)
        if new != text:
            stale.append(page.relative_to(ROOT))
            if not args.check:
                page.write_text(new, encoding="utf-8")
        for line, header in measurement_tables(new):
            by_hand.append(f"{page.relative_to(ROOT)}:{line}: a measurement table outside a "
                           f"results block: {header}")
    verb = "differ from their records" if args.check else "rewritten"
    for p in stale:
        print(f"{p}: results blocks {verb}")
    for msg in by_hand:
        print(msg)
    return 1 if (args.check and stale) or by_hand else 0


if __name__ == "__main__":
    sys.exit(main())
