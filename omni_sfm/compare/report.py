"""``report.md`` of a comparison: the table, the reasons of failures, notes."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from omni_sfm.folders import CompareFolder
from omni_sfm.reports import CompareEntry, CompareResults


def _fmt(x: Any, digits: int = 3, pct: bool = False) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{100 * x:.{digits}f} %" if pct else f"{x:.{digits}f}"


def table_rows(entries: Mapping[str, CompareEntry]) -> list[str]:
    """Markdown table (header included) of the ``initializers`` entries of results.json."""
    rows = ["| initializer | status | registered | rot max (deg) | rot mean (deg) | ATE / path "
            "| RPE / step | RPE rot (deg) | time (s) |",
            "|---|---|---|---|---|---|---|---|---|"]
    for name, e in entries.items():
        rows.append(f"| {name} | {e.status} | {_fmt(e.registered, 0, pct=True)} | "
                    f"{_fmt(e.rot_max_deg)} | {_fmt(e.rot_mean_deg)} | "
                    f"{_fmt(e.ate_rel, 2, pct=True)} | {_fmt(e.rpe)} | "
                    f"{_fmt(e.rpe_rot_deg)} | "
                    f"{_fmt(e.time_s, 1)} |")
    return rows


def report_markdown(results: CompareResults) -> str:
    """``report.md``: the table, the reasons of failures and notes."""
    seq = results.sequence
    entries = results.initializers
    name = "the sequence" if seq.name is None else seq.name
    frames = "?" if seq.frames is None else seq.frames
    camera = "?" if seq.camera is None else seq.camera
    lines = [f"# Initializers on {name}", "",
             f"{frames} frames, camera `{camera}`. Rotation error "
             "relative to the first frame; ATE = RMSE of camera centres after similarity "
             "alignment, over the ground-truth path length; RPE = relative pose error between "
             "consecutive frames (TUM/evo, no alignment, scale fixed): RMSE of its translation "
             "over the mean true step, mean angle of its rotation (omni_sfm.evaluate). Errors "
             "are over the registered frames.", ""]
    lines += table_rows(entries)
    notes = [f"- `{n}`: {e.reason}" for n, e in entries.items() if e.reason]
    if notes:
        lines += ["", "Notes and reasons:", "", *notes]
    lines += ["", f"![trajectories]({CompareFolder.TRAJECTORIES_PLOT})", "",
              f"![errors]({CompareFolder.ERRORS_PLOT})", ""]
    return "\n".join(lines)


