"""What the benchmark scripts share: running a command as a user would (a fresh process), with
its wall time and peak memory. Scripts only; the library never imports it."""

from __future__ import annotations

import os
import subprocess
import time


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
