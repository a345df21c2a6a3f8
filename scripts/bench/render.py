"""Speed of the renderer: seconds a frame of ``omni-sfm render`` with and without texture and
the effects of real footage (docs/rendering.md, "Speed").

For each camera (``--cameras``: the hyperboloid at 800 x 600, the equirectangular camera at
1280 x 640) and each of plain, ``--footage``, ``--textured`` and ``--textured --footage``, runs
``omni-sfm render --output TMP --overwrite --camera C --width W --height H --frames N [flags]``
as a user would (a fresh process; the default corridor and 1.5 m lane, so with the default 10
frames the motion blur's flow between frames is long: a worst case) and reads
``seconds_per_frame`` from the render's ``render.json`` (rendering and writing, without the
start-up). Writes the record ``docs/benchmarks/bench_render.json``.

    .venv/bin/python -m scripts.bench.render [--frames 10] [--cameras hyperboloid]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from scripts.benchlib import add_log_arguments, write_log

CAMERAS = {"hyperboloid": (800, 600), "equirectangular": (1280, 640)}
VARIANTS = {"plain": [], "--footage": ["--footage"], "--textured": ["--textured"],
            "--textured --footage": ["--textured", "--footage"]}


def seconds_per_frame(camera: str, size: tuple[int, int], frames: int, flags: list[str],
                      out: Path) -> tuple[float, str]:
    """``(seconds a frame, body)`` of one ``omni-sfm render`` run into ``out``."""
    cmd = [sys.executable, "-m", "omni_sfm", "render", "--output", str(out), "--overwrite",
           "--camera", camera, "--width", str(size[0]), "--height", str(size[1]),
           "--frames", str(frames), *flags]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"bench.render: {' '.join(cmd)} failed: {r.stderr.strip()[-500:]}")
    meta = json.loads((out / "render.json").read_text(encoding="utf-8"))
    body = (meta.get("effects") or {}).get("body") or "none"
    return float(meta["seconds_per_frame"]), str(body)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10, help="frames a run (default: %(default)s)")
    ap.add_argument("--cameras", nargs="+", choices=sorted(CAMERAS), default=list(CAMERAS))
    add_log_arguments(ap)
    args = ap.parse_args()
    if args.frames < 2:
        ap.error(f"--frames must be at least 2, got {args.frames}")
    rows: list[list[object]] = []
    bodies: dict[str, str] = {}
    with tempfile.TemporaryDirectory(prefix="bench_render_") as tmp:
        for camera in args.cameras:
            w, h = CAMERAS[camera]
            row: list[object] = [f"{camera} {w} x {h}"]
            for name, flags in VARIANTS.items():
                s, body = seconds_per_frame(camera, (w, h), args.frames, flags, Path(tmp) / "r")
                if "--footage" in flags:
                    bodies[camera] = body
                print(f"{camera} {w}x{h}, {name}: {s:.2f} s a frame", flush=True)
                row.append(s)
            rows.append(row)
    s_frame = {"format": ".2f"}
    write_log(args, "bench_render", "The renderer's seconds a frame", [
        "camera, size (corridor)",
        *({"label": (v if v == "plain" else f"`{v}`") + " (s a frame)", **s_frame}
          for v in VARIANTS)],
        rows,
        headline="{rows[0][1]} s a frame ({rows[0][0]}), {rows[0][4]} s textured with the "
                 "effects of real footage",
        notes=f"{args.frames} frames over the corridor's 1.5 m; `seconds_per_frame` of "
              "`render.json`: rendering and writing (JPEG with `--footage`, else PNG), without "
              "the start-up. The camera-fixed body of `--footage`: "
              + ", ".join(f"{c} `{b}`" for c, b in bodies.items()) + ".")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
