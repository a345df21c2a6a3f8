"""The docs' results tables are the measurement records, rendered (scripts/render_results.py).

Every ``<!-- results:NAME -->`` block of README.md and docs/*.md must be exactly what the
generator renders from ``docs/benchmarks/NAME.json``; every record is shown somewhere; no
page has a table of measured figures outside such a block (written by hand); a benchmark
script writes a record that the generator reads back (one cheap run end to end).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # scripts/ is a package at the repository root
    sys.path.insert(0, str(ROOT))

from scripts import render_results  # noqa: E402
from scripts.benchlib import markdown_table, write_log  # noqa: E402


@pytest.fixture(scope="module")
def records() -> dict[str, dict]:
    return render_results.load_records()


@pytest.mark.parametrize("page", render_results.pages(), ids=lambda p: p.name)
def test_page_tables_match_their_records(page: Path, records: dict[str, dict]) -> None:
    text = page.read_text(encoding="utf-8")
    assert render_results.render_text(text, page, records) == text, (
        f"{page.relative_to(ROOT)}: a results block differs from its record; run "
        "`.venv/bin/python -m scripts.render_results`")


@pytest.mark.parametrize("page", render_results.pages(), ids=lambda p: p.name)
def test_no_measurement_table_outside_results_blocks(page: Path) -> None:
    found = render_results.measurement_tables(page.read_text(encoding="utf-8"))
    assert not found, (
        f"{page.relative_to(ROOT)}: measured figures in a hand-written table (line, header): "
        f"{found}; give them a record in docs/benchmarks/ (written by the script that measures "
        "them) and a results block, or say the one current figure and its command in prose")


def test_a_hand_written_measurement_table_is_caught() -> None:
    page = (ROOT / "docs" / "results.md").read_text(encoding="utf-8")
    assert "<!-- results:eval_init -->" in page
    assert render_results.measurement_tables(page) == []
    # the same table without its markers: figures typed into the page
    unmarked = page.replace("<!-- results:eval_init -->\n", "", 1) \
                   .replace("<!-- /results:eval_init -->", "", 1)
    found = render_results.measurement_tables(unmarked)
    assert len(found) == 1 and found[0][1].startswith("| sequence |"), found
    typed = ("Timed by hand:\n\n| sequence | wall | ATE |\n|---|---|---|\n"
             "| corridor | 12.4 s | 0.02 % |\n| room, 100 frames | 1:02 | 100/100, 0.04 deg |\n")
    assert render_results.measurement_tables(typed) == [(3, "| sequence | wall | ATE |")]
    assert render_results.measurement_tables("```\n" + typed + "```\n") == []  # an example
    reference = ("| key | meaning |\n|---|---|\n| `num_frames` | number of frames, 1 or more |\n"
                 "| `step` | every 5th frame (`--step 5`) |\n")
    assert render_results.measurement_tables(reference) == []


def test_a_printed_table_becomes_rows_of_the_first_table_only() -> None:
    printed = ("| part | share |\n| --- | --- |\n| a | 1 % |\n| b | 2 % |\n\n(a note)\n\n"
               "| still camera | edges |\n| --- | --- |\n| c | 95 % |\n")
    assert markdown_table(printed) == (["part", "share"], [["a", "1 %"], ["b", "2 %"]])


def test_every_record_is_shown(records: dict[str, dict]) -> None:
    shown = {n for page in render_results.pages()
             for n in render_results.block_names(page.read_text(encoding="utf-8"))}
    assert "summary" in shown  # the README's table
    shown |= {row.record for row in render_results.SUMMARY}
    assert set(records) <= shown, f"records no page shows: {sorted(set(records) - shown)}"
    assert shown - {"summary"} <= set(records), sorted(shown - {"summary"} - set(records))


def test_records_say_how_they_were_measured(records: dict[str, dict]) -> None:
    assert len(records) >= 10
    for name, rec in records.items():
        assert rec["command"].split()[0] in (".venv/bin/python", "OPENBLAS_NUM_THREADS=1"), name
        assert "-m scripts." in rec["command"] or \
            ".venv/bin/python scripts/" in rec["command"], name
        assert rec["machine"] and rec["commit"], name
        assert rec["source"] == "measured" or rec["source"].startswith("transcribed"), name
        render_results.headline(rec)  # the template names only cells that exist


def test_a_stale_table_is_caught(records: dict[str, dict], tmp_path: Path) -> None:
    page = ROOT / "docs" / "results.md"
    text = page.read_text(encoding="utf-8")
    rec = records["eval_init"]
    shown = render_results.cell(rec["rows"][0][2], rec["columns"][2])
    stale = text.replace(f"| {shown} |", "| 9.999 |", 1)
    assert stale != text
    assert render_results.render_text(stale, page, records) == text
    with pytest.raises(KeyError, match="no record"):
        render_results.render_text("<!-- results:nothing -->\n<!-- /results:nothing -->\n",
                                   page, records)


def test_merged_rows_keep_their_commands(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    args = argparse.Namespace(log_dir=tmp_path, no_log=False)
    cols: list[str | dict] = ["sequence", {"label": "ms", "format": ".1f"}]
    monkeypatch.setattr(sys, "argv", ["x", "--scene", "a"])
    write_log(args, "t", "title", cols, [["a", 1.0]], merge=True)
    monkeypatch.setattr(sys, "argv", ["x", "--scene", "b"])
    write_log(args, "t", "title", cols, [["b", 2.0]], merge=True)
    monkeypatch.setattr(sys, "argv", ["x", "--scene", "a", "--log-dir", str(tmp_path)])
    write_log(args, "t", "title", cols, [["a", 3.0]], merge=True)
    rec = json.loads((tmp_path / "t.json").read_text())
    assert rec["rows"] == [["b", 2.0], ["a", 3.0]]
    assert [c.split()[-1] for c in rec["row_commands"]] == ["b", "a"]  # --log-dir left out
    assert write_log(argparse.Namespace(log_dir=tmp_path, no_log=True), "u", "", cols, []) is None
    assert not (tmp_path / "u.json").exists()


def test_a_benchmark_writes_a_record_the_generator_reads(tmp_path: Path) -> None:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "plugins"),
                                          os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, "-m", "scripts.bench.backend", "--trials", "1",
                        "--log-dir", str(tmp_path)], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    rec = json.loads((tmp_path / "bench_backend.json").read_text())
    assert rec["command"] == ("OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.bench.backend "
                              "--trials 1")
    assert rec["source"] == "measured" and rec["machine"] and rec["commit"]
    stages = [row[0] for row in rec["rows"]]
    assert stages[:3] == ["parallel_lines", "rotation", "translation"]
    assert all(row[1] > 0 for row in rec["rows"][:3])
    table = render_results.render_table(rec, ROOT / "docs" / "estimator.md")
    assert "| parallel_lines |" in table and "scripts.bench.backend --trials 1" in table
