"""``omni-sfm view``: a PNG snapshot, an offline HTML page and Open3D line sets of a result."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "view",
        help="snapshot (PNG), interactive offline page (HTML) and line sets (PLY) of a result",
        description=(
            "Draw the trajectory with camera axes, the 3D lines coloured by parallel group and "
            "the dense points of a dense, init or refine output folder. Writes FILE (PNG), "
            "FILE with .html (self-contained, orbit and zoom, works offline), cameras.ply and "
            "lines3d.ply (Open3D line sets) beside it (see docs/dense.md)."),
    )
    p.add_argument("--input", "-i", type=Path, required=True,
                   help="results folder with trajectory.tum (dense.ply, lines3d.json optional)")
    p.add_argument("--output", "-o", type=Path, default=None,
                   help="PNG file (default: INPUT/view.png)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from omni_sfm.view import make_view

    out = make_view(args.input, args.output)
    extra = f", {out.lines3d}" if out.lines3d is not None else ""
    print(f"view: wrote {out.png}, {out.html}, {out.cameras}{extra}")
    return 0
