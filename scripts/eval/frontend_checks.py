"""Front-end checks on rendered sequences: dark frames, the automatic mask, the camera check.

Measures the tables of docs/frontend.md ("Real footage: damaged frames, dark and low-contrast
images", "Automatic mask", "Camera check"). Renders (or reuses, under ``--work``) each
sequence, prints one JSON line per run and a Markdown table per part, and writes each part's
record, ``docs/benchmarks/eval_frontend_checks_{dark,mask,camera}.json``.

- ``dark``: the demo corridor (``omni-sfm demo``'s render: hyperboloid 800x600, 100 frames,
  seed 0) with every grey level multiplied by 1, 0.25, 0.1, 0.02, 0.01 and rounded (written as
  PNG), each run through ``init_from_images`` as ``omni-sfm init --no-colmap --debug-view none``
  does; frames estimated, max rotation error, ATE against ``groundtruth.tum``, the per-frame
  median grey and contrast the front end records, or the one-line error.
  ``--fixed-thresholds`` adds the same runs without the contrast normalisation
  (``ExtractionOptions(reference_contrast=0, min_contrast=0)``, the extraction before it);
  ``--repeat N`` runs each N times (an ill-conditioned run's figures differ from run to run).
- ``mask``: ``static_mask`` on 12-frame renders: clean sequences, a dark body painted at the
  nadir, and the renderer's camera-fixed bodies (``Effects(body=...)``) at 400x300 / 400x200.
- ``camera``: ``check_camera_fit`` on 4 frames of 12-frame renders with the right camera and
  wrong ones (COLMAP ``PINHOLE`` / ``OPENCV_FISHEYE`` ``cameras.txt`` written here, hyperboloid
  and equirectangular swapped), without and with added noise (sigma 4 grey levels).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.eval.frontend_checks --work /tmp/efc \\
        --only dark --fixed-thresholds --repeat 3
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np

from omni_sfm.cameras import CameraModel, load_camera
from omni_sfm.cameras.equirectangular import EquirectangularCamera
from omni_sfm.errors import OmniSfmError
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.lines.automask import static_mask
from omni_sfm.lines.camfit import check_camera_fit
from omni_sfm.lines.extract import ExtractionOptions, LineExtractor
from omni_sfm.lines.frontend import FrontEndOptions
from omni_sfm.pipelines.init import InitOptions, init_from_images
from omni_sfm.poses import read_tum
from omni_sfm.synth.effects import Body, Effects
from omni_sfm.synth.render import RenderOptions, hyperboloid_camera, prepare, render_sequence
from omni_sfm.synth.scenes import SceneName
from scripts.benchlib import add_log_arguments, markdown_table, write_log

DEMO = RenderOptions(camera="hyperboloid", frames=100, seed=0)  # as pipelines.demo.run_demo
DARK_FACTORS = {1.0: "original", 0.25: "a quarter", 0.1: "a tenth", 0.02: "2 %", 0.01: "1 %"}

SMALL = {
    "corridor-hyperboloid-800x600-12f": RenderOptions(camera="hyperboloid", frames=12),
    "room-hyperboloid-800x600-12f": RenderOptions(scene=SceneName.ROOM, camera="hyperboloid",
                                                  frames=12),
    "room-textured-hyperboloid-800x600-12f": RenderOptions(
        scene=SceneName.ROOM, camera="hyperboloid", frames=12, textured=True),
    "corridor-equirectangular-1200x600-12f": RenderOptions(
        camera="equirectangular", width=1200, height=600, frames=12),
    "room-textured-equirectangular-1200x600-12f": RenderOptions(
        scene=SceneName.ROOM, camera="equirectangular", width=1200, height=600, frames=12,
        textured=True),
}
BODY_SIZES = {"hyperboloid": (400, 300), "equirectangular": (400, 200)}
BODIES = (Body.OPERATOR, Body.TRIPOD, Body.ROBOT)
CAMFIT_FRAMES = 4
CAMFIT_NOISE = (0.0, 4.0)
FIGURES = ("bent_lines", "straight_in_image_curved_on_sphere", "empty_valid", "moving_outside")


# -- shared ---------------------------------------------------------------------------------
def _render(work: Path, name: str, options: RenderOptions) -> Path:
    seq = work / name
    if not (seq / "groundtruth.tum").is_file():
        t0 = time.perf_counter()
        render_sequence(seq, options, overwrite=True, progress=False)
        print(f"# rendered {name} in {time.perf_counter() - t0:.0f} s", file=sys.stderr,
              flush=True)
    return seq


def _imread(path: Path, flags: int = cv2.IMREAD_GRAYSCALE) -> np.ndarray:
    img = cv2.imread(str(path), flags)
    if img is None:
        raise OmniSfmError(f"{path}: does not decode")
    return img


def _frames(seq: Path) -> tuple[list[np.ndarray], CameraModel]:
    files = sorted((seq / "images").glob("*.png"))
    return ([_imread(f) for f in files],
            load_camera(seq / "camera.yaml"))


def _pct(x: float) -> str:
    v = 100.0 * x
    if not np.isfinite(v):
        return "n/a"
    if v == 0:
        return "0"
    return f"{v:.1f}" if v < 10 else f"{v:.0f}"


def _span(values: Sequence[float], fmt: Callable[[float], str] = _pct) -> str:
    """``lo-hi`` of the formatted values (NaN left out; ``n/a`` if all are NaN)."""
    v = [x for x in values if np.isfinite(x)]
    if not v:
        return "n/a"
    lo, hi = fmt(min(v)), fmt(max(v))
    return lo if lo == hi else f"{lo}-{hi}"


def _num(row: dict[str, object], key: str) -> float:
    """``row[key]`` as a float (NaN for None)."""
    v = row[key]
    return float("nan") if v is None else float(v)  # type: ignore[arg-type]


def _emit(row: dict[str, object]) -> None:
    print(json.dumps(row), flush=True)


# -- dark -----------------------------------------------------------------------------------
def _darken(src: Path, dst: Path, factor: float) -> Path:
    """``dst`` with every grey level of ``src``'s PNG frames multiplied by ``factor`` and
    rounded (kept if already written)."""
    files = sorted(src.glob("*.png"))
    if len(list(dst.glob("*.png"))) != len(files):
        dst.mkdir(parents=True, exist_ok=True)
        for f in files:
            img = _imread(f, cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(dst / f.name), np.round(img * factor).astype(np.uint8))
    return dst


def _image_stats(images: Path, camera: CameraModel,
                 extraction: ExtractionOptions) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame median grey and contrast as the extractor computes them (for a failed run,
    whose front-end result is not returned); camera mask only, no automatic mask."""
    ext = LineExtractor(camera, extraction)
    stats = [ext.image_stats(_imread(f))
             for f in sorted(images.glob("*.png"))]
    return np.array([s[0] for s in stats]), np.array([s[1] for s in stats])


def _dark_run(work: Path, seq: Path, factor: float, fixed: bool) -> dict[str, object]:
    images = seq / "images" if factor == 1 else _darken(seq / "images",
                                                        work / f"dark-x{factor:g}", factor)
    extraction = (ExtractionOptions(reference_contrast=0.0, min_contrast=0.0) if fixed
                  else ExtractionOptions())
    opts = InitOptions(frontend=FrontEndOptions(extraction=extraction, progress=False),
                       debug_view="none", colmap=False, progress=False)
    mode = "fixed" if fixed else "normalised"
    row: dict[str, object] = {"part": "dark", "factor": factor, "thresholds": mode}
    gt = read_tum(seq / "groundtruth.tum")
    t0 = time.perf_counter()
    try:
        res = init_from_images(images, seq / "camera.yaml", work / f"init-x{factor:g}-{mode}",
                               opts, overwrite=True)
    except OmniSfmError as exc:
        grey, contrast = _image_stats(images, load_camera(seq / "camera.yaml"), extraction)
        row.update(error=str(exc), stats_from="image_stats")
    else:
        err = trajectory_errors(res.estimation.trajectory, gt)
        grey, contrast = res.frontend.median_grey, res.frontend.contrast
        row.update(estimated=int(res.estimation.estimated.sum()), rot_max_deg=err.rot_max_deg,
                   ate_pct=100 * err.ate_rel, tracks=int(res.estimation.report.num_tracks or 0),
                   stats_from="frontend")
    row.update(frames=len(gt), wall_s=round(time.perf_counter() - t0, 1),
               median_grey=[float(np.nanmin(grey)), float(np.nanmax(grey))],
               contrast=[float(np.nanmin(contrast)), float(np.nanmax(contrast))])
    return row


def _dark_cell(runs: list[dict[str, object]]) -> str:
    """One table cell from the repeats of one run: the error, or the figures (``lo-hi`` where
    the repeats differ)."""
    errors = sorted({str(r["error"]) for r in runs if "error" in r})
    ok = [r for r in runs if "error" not in r]
    parts = [f"fails: `{e}`" for e in errors]
    if ok:
        def span(key: str, digits: int = 3) -> str:
            return _span([_num(r, key) for r in ok], lambda x: f"{x:.{digits}f}")

        parts.insert(0, f"{span('estimated', 0)}/{ok[0]['frames']}, {span('rot_max_deg')} deg, "
                        f"{span('ate_pct')} % ({span('tracks', 0)} tracks)")
    n = f" ({len(ok)} of {len(runs)} runs)" if ok and errors else ""
    return "; ".join(parts) + n


def _range(v: object) -> str:
    lo, hi = (f"{x:g}" for x in v)  # type: ignore[attr-defined]
    return lo if lo == hi else f"{lo}-{hi}"


def run_dark(work: Path, fixed: bool, repeat: int) -> str:
    seq = _render(work, "corridor-hyperboloid-800x600-100f-seed0", DEMO)
    modes = (False, True) if fixed else (False,)
    rows: dict[tuple[float, bool], list[dict[str, object]]] = {}
    for factor in DARK_FACTORS:
        for m in modes:
            rows[factor, m] = []
            for k in range(repeat):
                r = _dark_run(work, seq, factor, m)
                r["repeat"] = k
                rows[factor, m].append(r)
                _emit(r)
    cols = ["brightness", "median grey, contrast", *(["fixed thresholds"] if fixed else []),
            "contrast-scaled (the default)"]
    lines = ["| " + " | ".join(cols) + " |", "|" + " --- |" * len(cols)]
    for factor, label in DARK_FACTORS.items():
        r = rows[factor, False][0]
        cells = [label, f"{_range(r['median_grey'])}, {_range(r['contrast'])}"]
        if fixed:
            cells.append(_dark_cell(rows[factor, True]))
        cells.append(_dark_cell(rows[factor, False]))
        lines.append("| " + " | ".join(cells) + " |")
    if repeat > 1:
        lines.append(f"\n({repeat} runs of each; a range where they differ)")
    return "\n".join(lines)


# -- mask -----------------------------------------------------------------------------------
def painted_body(shape: tuple[int, int], equirectangular: bool) -> np.ndarray:
    """``(H, W)`` bool: a torso and two legs at the nadir of a hyperboloid image, or a body at
    the bottom middle of an equirectangular one (as in ``tests/test_automask_camfit.py``)."""
    h, w = shape
    m = np.zeros(shape, np.uint8)
    if equirectangular:
        polys = [np.array([[0.40 * w, h], [0.43 * w, 0.8 * h], [0.57 * w, 0.8 * h],
                           [0.60 * w, h]])]
    else:
        c, s = np.array([w / 2, h / 2]), min(w / 800, h / 600)

        def at(r: float, a: float) -> np.ndarray:
            return c + r * s * np.array([np.cos(np.radians(a)), np.sin(np.radians(a))])
        polys = [np.array([at(45, a0), at(r, a0 + d), at(r, a1 - d), at(45, a1)])
                 for a0, a1, r, d in ((60, 120, 150, 10), (200, 215, 200, 5),
                                      (320, 335, 200, 5))]
    for p in polys:
        cv2.fillPoly(m, [np.rint(p).astype(np.int32)], 1)
    return m > 0


def _paint(frames: Sequence[np.ndarray], body: np.ndarray) -> list[np.ndarray]:
    """The frames with ``body`` painted grey 40 (plus noise of 1 grey level)."""
    rng = np.random.default_rng(0)
    out = []
    for f in frames:
        g = f.astype(np.float64)
        g[body] = 40 + rng.normal(0, 1.0, int(body.sum()))
        out.append(np.clip(np.rint(g), 0, 255).astype(np.uint8))
    return out


def _mask_row(kind: str, name: str, frames: Sequence[np.ndarray], camera: CameraModel,
              body: np.ndarray | None) -> dict[str, object]:
    valid = camera.valid_mask()
    t0 = time.perf_counter()
    auto = static_mask(frames, camera)
    row: dict[str, object] = {"part": "mask", "kind": kind, "sequence": name,
                              "masked": auto.masked_fraction,
                              "static_edges": auto.static_edge_fraction,
                              "ms": round(1000 * (time.perf_counter() - t0)),
                              "reason": auto.reason}
    if body is not None:
        b = body & valid
        row.update(body=b.sum() / valid.sum(),
                   covered=(~auto.mask & b).sum() / b.sum() if b.any() else None,
                   outside=(~auto.mask & ~b & valid).sum() / valid.sum())
    return {k: float(v) if isinstance(v, np.floating) else v for k, v in row.items()}


def _still(frames: Sequence[np.ndarray], camera: CameraModel, name: str) -> dict[str, object]:
    """A camera that does not move: the first frame 12 times with fresh noise (1 grey level)."""
    rng = np.random.default_rng(1)
    still = [np.clip(np.rint(frames[0] + rng.normal(0, 1.0, frames[0].shape)), 0, 255)
             .astype(np.uint8) for _ in range(12)]
    auto = static_mask(still, camera)
    return {"part": "mask", "kind": "still", "sequence": name, "applied": auto.applied,
            "static_edges": auto.static_edge_fraction, "reason": auto.reason}


def _mask_table(rows: list[dict[str, object]]) -> str:
    def name(r: dict[str, object]) -> str:
        return str(r["sequence"]).replace("-12f", "").replace("-", " ")

    out = ["| sequence (body: % of the valid pixels) | masked | body covered | "
           "masked outside the body |",
           "| --- | --- | --- | --- |"]
    for r in rows:
        if r["kind"] == "clean":
            out.append(f"| {name(r)}, no body | {_pct(_num(r, 'masked'))} % | | |")
        elif r["kind"] in ("painted", "renderer"):
            label = ("painted body" if r["kind"] == "painted" else f"renderer's `{r['body_kind']}`")
            seq = name(r).removesuffix(f" {r.get('body_kind')}")
            covered = "n/a" if r["covered"] is None else f"{_pct(_num(r, 'covered'))} %"
            out.append(f"| {label}, {seq} ({_pct(_num(r, 'body'))} %) | "
                       f"{_pct(_num(r, 'masked'))} % | {covered} | "
                       f"{_pct(_num(r, 'outside'))} % |")
    still = [r for r in rows if r["kind"] == "still"]
    out += ["", "| still camera (12 copies of frame 0, noise 1) | persistent edges | applied |",
            "| --- | --- | --- |"]
    out += [f"| {name(r)} | {_pct(_num(r, 'static_edges'))} % | {r['applied']} |"
            for r in still]
    return "\n".join(out)


def run_mask(work: Path) -> str:
    rows: list[dict[str, object]] = []
    for name, opts in SMALL.items():
        frames, cam = _frames(_render(work, name, opts))
        equi = "equirectangular" in name
        for r in (_mask_row("clean", name, frames, cam, None), _still(frames, cam, name)):
            rows.append(r)
            _emit(r)
        body = painted_body(frames[0].shape, equi) & cam.valid_mask()
        r = _mask_row("painted", name, _paint(frames, body), cam, body)
        rows.append(r)
        _emit(r)
    for kind, (w, h) in BODY_SIZES.items():
        for body_kind in BODIES:
            opts = RenderOptions(camera=kind, width=w, height=h, frames=12,
                                 effects=Effects(body=body_kind))
            name = f"corridor-{kind}-{w}x{h}-12f-{body_kind}"
            frames, cam = _frames(_render(work, name, opts))
            r = _mask_row("renderer", name, frames, cam, prepare(opts).renderer.body_mask())
            r["body_kind"] = body_kind.value
            rows.append(r)
            _emit(r)
    return _mask_table(rows)


# -- camera ---------------------------------------------------------------------------------
def _colmap(work: Path, line: str) -> CameraModel:
    """A COLMAP ``cameras.txt`` holding ``line`` (written under ``work/cameras``), loaded."""
    d = work / "cameras" / line.replace(" ", "_")
    d.mkdir(parents=True, exist_ok=True)
    (d / "cameras.txt").write_text("# Camera list with one line of data per camera\n"
                                   f"1 {line}\n")
    return load_camera(d / "cameras.txt")


def _cameras(work: Path, equirectangular: bool) -> dict[str, tuple[str, CameraModel]]:
    """``label -> (table row, camera)``: the wrong cameras of a sequence's size."""
    if equirectangular:
        return {
            "hyperboloid": ("hyperboloid (scaled paper camera)", hyperboloid_camera(1200, 600)),
            "pinhole300": ("`PINHOLE 1200 600 300 300 600 300`",
                           _colmap(work, "PINHOLE 1200 600 300 300 600 300")),
            "fisheye200": ("`OPENCV_FISHEYE 1200 600 200 200 600 300 0 0 0 0`",
                           _colmap(work, "OPENCV_FISHEYE 1200 600 200 200 600 300 0 0 0 0")),
        }
    pin = "COLMAP `PINHOLE 800 600 f f 400 300`, f = 200, 300, 600"
    return {
        **{f"pinhole{f}": (pin, _colmap(work, f"PINHOLE 800 600 {f} {f} 400 300"))
           for f in (200, 300, 600)},
        "fisheye200": ("`OPENCV_FISHEYE 800 600 200 200 400 300 0 0 0 0`",
                       _colmap(work, "OPENCV_FISHEYE 800 600 200 200 400 300 0 0 0 0")),
        "equirectangular": ("equirectangular", EquirectangularCamera(width=800, height=600)),
    }


def _sample(frames: Sequence[np.ndarray], noise: float) -> list[np.ndarray]:
    """``CAMFIT_FRAMES`` frames spread over the sequence, with Gaussian noise of ``noise``
    grey levels added (seeded)."""
    idx = np.linspace(0, len(frames) - 1, CAMFIT_FRAMES).round().astype(int)
    rng = np.random.default_rng(0)
    return [np.clip(np.rint(frames[i] + rng.normal(0, noise, frames[i].shape)), 0, 255)
            .astype(np.uint8) if noise else frames[i] for i in idx]


def _camera_table(rows: list[dict[str, object]]) -> str:
    groups: dict[str, list[dict[str, object]]] = {}
    for r in rows:
        groups.setdefault(f"{r['frames']} / {r['row']}", []).append(r)
    out = ["| frames / camera file | bent lines | straight in image, curved on sphere | "
           "empty valid | moving outside | median residual (px) | verdict |",
           "| --- | --- | --- | --- | --- | --- | --- |"]
    for label, g in groups.items():
        figs = [_span([_num(r, k) for r in g]) + " %" for k in FIGURES]
        res = _span([_num(r, "median_residual_px") for r in g], lambda x: f"{x:.2f}")
        fits = sum(bool(r["ok"]) for r in g)
        verdict = (f"fits (all {len(g)})" if fits == len(g) else
                   f"warns (all {len(g)})" if fits == 0 else f"fits {fits} of {len(g)}")
        out.append(f"| {label} | " + " | ".join(figs) + f" | {res} | {verdict} |")
    return "\n".join(out)


def run_camera(work: Path) -> str:
    rows: list[dict[str, object]] = []
    order = ("hyperboloid", "equirectangular")
    for kind in order:
        for name, opts in SMALL.items():
            if kind not in name:
                continue
            frames, right = _frames(_render(work, name, opts))
            cams = {"right": ("right", right), **_cameras(work, kind == "equirectangular")}
            for noise in CAMFIT_NOISE:
                sample = _sample(frames, noise)
                for label, (row_name, cam) in cams.items():
                    t0 = time.perf_counter()
                    fit = check_camera_fit(sample, cam)
                    r: dict[str, object] = {
                        "part": "camera", "sequence": name, "frames": kind, "noise": noise,
                        "camera": label, "row": row_name, "ok": fit.ok,
                        **{k: float(v) for k, v in fit.figures.items()},
                        "s": round(time.perf_counter() - t0, 2), "message": fit.message}
                    rows.append(r)
                    _emit(r)
    rows.sort(key=lambda r: (order.index(str(r["frames"])), r["camera"] != "right"))
    return _camera_table(rows)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True, help="folder for renders and results")
    p.add_argument("--only", choices=("dark", "mask", "camera"), help="run only this part")
    p.add_argument("--fixed-thresholds", action="store_true",
                   help="dark: also run without the contrast normalisation")
    p.add_argument("--repeat", type=int, default=1,
                   help="dark: run each init this many times (the ill-conditioned runs differ "
                        "from run to run)")
    add_log_arguments(p)
    args = p.parse_args()
    if args.repeat < 1:
        p.error(f"--repeat must be >= 1, got {args.repeat}")
    args.work.mkdir(parents=True, exist_ok=True)
    parts: dict[str, Callable[[], str]] = {
        "dark": lambda: run_dark(args.work, args.fixed_thresholds, args.repeat),
        "mask": lambda: run_mask(args.work),
        "camera": lambda: run_camera(args.work),
    }
    titles = {"dark": "Dark and low-contrast frames", "mask": "The automatic mask",
              "camera": "The camera check"}
    for name, part in parts.items():
        if args.only in (None, name):
            text = part()
            print(f"\n{text}\n", flush=True)
            columns, rows = markdown_table(text)
            notes = " ".join(ln for ln in text.splitlines() if ln.startswith("("))
            write_log(args, f"eval_frontend_checks_{name}", titles[name], columns, rows,
                      headline=f"{len(rows)} runs", notes=notes)
    return 0


if __name__ == "__main__":
    sys.exit(main())
