"""What the benchmark and evaluation scripts share: running a command as a user would (a fresh
process), with its wall time and peak memory, and the record of a measurement.

A script's figures go to ``docs/benchmarks/<name>.json`` through :func:`write_log` (the command
as typed, the commit, the machine, the time, a table and a one-line headline);
``python -m scripts.render_results`` renders the docs' results tables from those records.
Scripts only; the library never imports it."""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
LOG_DIR = ROOT / "docs" / "benchmarks"


def tree_rss_mb(pid: int) -> float:
    """Resident memory (MB) of ``pid`` and all its descendants (Linux /proc)."""
    children: dict[int, list[int]] = {}
    rss: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        p = int(entry)
        children.setdefault(int(fields[1]), []).append(p)
        rss[p] = int(fields[21]) * os.sysconf("SC_PAGE_SIZE")
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        total += rss.get(p, 0)
        todo.extend(children.get(p, []))
    return total / 2**20


def run_timed(cmd: list[str]) -> tuple[float, float, int, str]:
    """``(wall s, peak MB, exit code, last line of output)`` of ``cmd``."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    peak = 0.0
    while proc.poll() is None:
        peak = max(peak, tree_rss_mb(proc.pid))
        time.sleep(0.2)
    wall = time.perf_counter() - t0
    out = (proc.stdout.read() if proc.stdout else "").strip().splitlines()
    return wall, peak, proc.returncode, out[0] if out else ""


def run_sampled(cmd: list[str], every_s: float = 0.5) -> tuple[float, list[tuple[float, float]],
                                                               int, str]:
    """``(wall s, samples, exit code, output)`` of ``cmd``: ``samples`` are ``(seconds since the
    start, resident MB of the process tree)`` every ``every_s``."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    samples: list[tuple[float, float]] = []
    while proc.poll() is None:
        samples.append((time.perf_counter() - t0, tree_rss_mb(proc.pid)))
        time.sleep(every_s)
    wall = time.perf_counter() - t0
    return wall, samples, proc.returncode, (proc.stdout.read() if proc.stdout else "").strip()


def at_tenths(samples: list[tuple[float, float]], wall: float) -> str:
    """The last sample (MB) at or before each tenth of ``wall``, "-" where none."""
    out = []
    for k in range(1, 11):
        at = [m for t, m in samples if t <= wall * k / 10]
        out.append(f"{at[-1]:.0f}" if at else "-")
    return " ".join(out)


# ------------------------------------------------------------------ the measurement log


def add_log_arguments(ap: argparse.ArgumentParser) -> None:
    """``--log-dir`` and ``--no-log``: where :func:`write_log` puts the script's record."""
    ap.add_argument("--log-dir", type=Path, default=LOG_DIR,
                    help="folder of the JSON record of this run (default: docs/benchmarks/; "
                         "python -m scripts.render_results renders the docs' tables from it)")
    ap.add_argument("--no-log", action="store_true", help="write no record")


def typed_command() -> str:
    """The command line that started this process, as a user types it from the repository root:
    ``OPENBLAS_NUM_THREADS`` when set, then ``.venv/bin/python -m <module> <arguments>``."""
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    module = spec.name if spec is not None else None
    argv = list(sys.argv[1:])
    for flag in ("--log-dir", "--no-log"):  # where the record goes changes no figure
        if flag in argv:
            k = argv.index(flag)
            del argv[k:k + (2 if flag == "--log-dir" else 1)]
    if module is not None:
        cmd = [".venv/bin/python", "-m", module, *argv]
    else:
        script = Path(sys.argv[0]).resolve()
        root = Path(__file__).resolve().parent.parent
        shown = script.relative_to(root) if script.is_relative_to(root) else script
        cmd = [".venv/bin/python", str(shown), *argv]
    threads = os.environ.get("OPENBLAS_NUM_THREADS")
    prefix = f"OPENBLAS_NUM_THREADS={threads} " if threads else ""
    return prefix + shlex.join(cmd)


def git_commit() -> str:
    """The short commit of the working tree, ``-dirty`` when tracked files other than the
    records (``docs/benchmarks/``) differ from it; ``unknown`` outside a git checkout."""
    def git(*a: str) -> str:
        return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    try:
        head = git("rev-parse", "--short", "HEAD")
        # the records themselves change as a run of several scripts goes on
        dirty = git("status", "--porcelain", "--untracked-files=no", "--", ".",
                    ":(exclude)docs/benchmarks")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("-dirty" if dirty else "")


def machine() -> str:
    """The processor model, CPU count, OS and Python of this machine, in one line."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            names = [ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    return (f"{cpu}, {os.cpu_count()} CPUs, {platform.system()} {platform.machine()}, "
            f"Python {platform.python_version()}")


def write_log(args: argparse.Namespace, name: str, title: str, columns: Sequence[str | dict],
              rows: Sequence[Sequence[Any]], headline: str = "", notes: str = "",
              merge: bool = False) -> Path | None:
    """Write the record ``<args.log_dir>/<name>.json`` of this run (unless ``args.no_log``).

    ``columns``: column labels, or ``{"label": ..., "format": ...}`` where numbers are shown
    with a format spec (``".3f"``); ``rows``: one list of cells per row (numbers or text);
    ``headline``: the one-line summary the README's results table shows, a ``str.format``
    template over ``rows`` as rendered (``"{rows[0][2]} deg"``); ``notes``: a sentence shown
    under the table. ``merge``: for a script that measures one row a run (one sequence): the
    record's other rows are kept, a row with the same first cell replaced, and each row keeps
    the command that measured it (``row_commands``). Returns the path written, or None."""
    if getattr(args, "no_log", False):
        return None
    path = Path(args.log_dir) / f"{name}.json"
    command = typed_command()
    new_rows = [[_plain(v) for v in row] for row in rows]
    row_commands = [command] * len(new_rows) if merge else None
    if merge and path.is_file():
        old = json.loads(path.read_text(encoding="utf-8"))
        cmds = old.get("row_commands") or [old["command"]] * len(old["rows"])
        mine = {row[0] for row in new_rows}
        kept = [(r, c) for r, c in zip(old["rows"], cmds, strict=True) if r[0] not in mine]
        new_rows = [r for r, _ in kept] + new_rows
        row_commands = [c for _, c in kept] + [command] * len(rows)
    record: dict[str, Any] = {
        "name": name,
        "title": title,
        "command": command,
        "commit": git_commit(),
        "machine": machine(),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "source": "measured",
        "columns": [c if isinstance(c, dict) else {"label": c} for c in columns],
        "rows": new_rows,
        "headline": headline,
        "notes": notes,
    }
    if row_commands is not None:
        record["row_commands"] = row_commands
    args.log_dir.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(record_json(record), encoding="utf-8")
    tmp.replace(path)
    print(f"# record: {path}", file=sys.stderr)
    return path


def record_json(record: dict[str, Any]) -> str:
    """The text of a record: one key a line, one table row a line (diffs stay readable)."""
    def dump(v: Any) -> str:
        return json.dumps(v, ensure_ascii=False)
    lines = []
    for k, v in record.items():
        if k in ("columns", "rows", "row_commands") and v:
            inner = ",\n".join(f"  {dump(x)}" for x in v)
            lines.append(f" {dump(k)}: [\n{inner}\n ]")
        else:
            lines.append(f" {dump(k)}: {dump(v)}")
    return "{\n" + ",\n".join(lines) + "\n}\n"


def markdown_table(text: str) -> tuple[list[str], list[list[str]]]:
    """``(columns, rows)`` of the first Markdown table in ``text`` (for a script that prints
    its results as one)."""
    lines: list[str] = []
    for ln in text.splitlines():
        if ln.strip().startswith("|"):
            lines.append(ln.strip())
        elif lines:  # the first table ends here
            break
    cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines]
    if len(cells) < 2:
        return [], []
    return cells[0], cells[2:]


def _plain(v: Any) -> Any:
    """A JSON value for a table cell: numpy scalars as Python numbers, floats to 6 significant
    digits."""
    if hasattr(v, "item") and callable(v.item):
        v = v.item()
    if isinstance(v, float):
        return float(f"{v:.6g}")
    return v
