#!/usr/bin/env python
"""The sweep behind docs/comparison.md: line-based against point-based initializers.

Sequence kinds (each with several seeds), every installed initializer on each:

- ``sim``: the paper's simulation (Sec. VII: 20 views, 40 lines of which 20 parallel, Gaussian
  angular noise on the normals) plus ``--sim-points`` random 3D points seen as rays with the
  same angular noise (pixels for COLMAP through a virtual 1600 x 800 equirectangular camera);
  swept over ``--noise`` levels;
- ``corridor-hyperboloid``: the rendered texture-poor corridor, the paper's catadioptric camera;
- ``corridor-hyperboloid-textured``: the same corridor with surface texture (the texture axis);
- ``room-equirectangular-textured``: the rendered room with texture, a 360 camera.

Each task (kind, seed, noise) is independent: by default they run on a local process pool
(``concurrent.futures``, ``--workers``); with ``--scheduler ADDRESS`` on a Dask distributed
cluster, with identical results (every random choice is seeded; pycolmap runs single-threaded).
Results go to ``--output`` (``runs/<task>/results.json`` + trajectories, ``sweep.json``,
``summary.md``) and to the records ``docs/benchmarks/compare_init.json`` and
``compare_init_runs.json`` (docs/comparison.md renders them); ``--docs`` draws the plots into
docs/img.

    .venv/bin/python -m scripts.compare.init --output /tmp/sweep --docs
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from scripts.benchlib import add_log_arguments, write_log

ROOT = Path(__file__).resolve().parents[2]
KINDS = ("sim", "corridor-hyperboloid", "corridor-hyperboloid-textured",
         "room-equirectangular-textured")
RENDER: dict[str, dict[str, Any]] = {
    "corridor-hyperboloid": {"scene": "corridor", "camera": "hyperboloid", "textured": False},
    "corridor-hyperboloid-textured": {"scene": "corridor", "camera": "hyperboloid",
                                      "textured": True},
    "room-equirectangular-textured": {"scene": "room", "camera": "equirectangular",
                                      "textured": True},
    "room-equirectangular": {"scene": "room", "camera": "equirectangular", "textured": False},
}
IMAGE_ONLY = ("lines-refine",)
"""Initializers that need frames: added to the rendered sequences' runs unless --initializers."""
SIZES = {"hyperboloid": (640, 480), "equirectangular": (960, 480)}


def task_id(task: dict[str, Any]) -> str:
    tid = f"{task['kind']}-s{task['seed']}"
    if task.get("noise_deg") is not None:
        tid += f"-n{task['noise_deg']:g}"
    return tid


def make_tasks(kinds: Iterable[str], seeds: Iterable[int], noises: Iterable[float],
               frames: int, sim_points: int, initializers: list[str],
               image_only: Iterable[str] = ()) -> list[dict[str, Any]]:
    tasks = []
    for kind in kinds:
        for seed in seeds:
            if kind == "sim":
                for n in noises:
                    tasks.append({"kind": kind, "seed": seed, "noise_deg": float(n),
                                  "points": sim_points, "initializers": initializers})
            else:
                tasks.append({"kind": kind, "seed": seed, "frames": frames,
                              "initializers": initializers + [n for n in image_only
                                                              if n not in initializers]})
    return tasks


def simulated_sequence(task: dict[str, Any]) -> tuple[Any, Any, dict[str, Any]]:
    """The paper's simulation with point rays beside the lines (same noise in angle)."""
    from omni_sfm.cameras import EquirectangularCamera
    from omni_sfm.geometry import normalize
    from omni_sfm.plugin_contract import PointObservations, SequenceInput
    from omni_sfm.synth.simulate import SimulationOptions, simulate

    opts = SimulationOptions(num_views=20, num_parallel=20, num_other=20,
                             noise_deg=task["noise_deg"], seed=task["seed"])
    sim = simulate(opts)
    gt = sim.groundtruth
    rng = np.random.default_rng(10_000 + task["seed"])
    n, F = task["points"], opts.num_views
    anchor = gt.positions[rng.integers(0, F, n)]
    X = anchor + normalize(rng.normal(size=(n, 3))) * rng.uniform(
        *opts.line_distance, size=(n, 1)) * opts.path_length
    rays = normalize(np.einsum("fji,nfj->nfi", gt.rotations, X[:, None, :] - gt.positions[None]))
    if opts.noise_deg > 0:
        axis = normalize(np.cross(rays, rng.normal(size=rays.shape)))
        ang = np.radians(opts.noise_deg) * rng.normal(size=(n, F, 1))
        rays = rays * np.cos(ang) + np.cross(axis, rays) * np.sin(ang)
    cam = EquirectangularCamera(width=1600, height=800)
    tt, ff = np.meshgrid(np.arange(n), np.arange(F), indexing="ij")
    r = rays.reshape(-1, 3)
    pts = PointObservations(tt.ravel(), ff.ravel(), cam.pixels_from_rays(r), r)
    seq = SequenceInput(gt.timestamps.copy(), cam, line_tracks=sim.tracks, points=pts,
                        name=task_id(task))
    thr = max(3.0 * np.radians(opts.noise_deg), 1e-5)
    options = {"five-point": {"max_error_rad": thr}, "upright-3pt": {"max_error_rad": thr}}
    return seq, gt, options


def run_task(task: dict[str, Any]) -> dict[str, Any]:
    """One sequence, every initializer: results.json content and the trajectories as TUM text.

    Top-level and free of shared state so that a process pool or a Dask worker can run it; the
    rendered frames live in a temporary folder on the worker.
    """
    import cv2

    from omni_sfm.compare import run_comparison, sequence_from_frames

    cv2.setNumThreads(1)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="omni_sfm_sweep_") as tmp:
        if task["kind"] == "sim":
            seq, gt, options = simulated_sequence(task)
        else:
            from omni_sfm.synth.render import RenderOptions, render_sequence

            spec = RENDER[task["kind"]]
            w, h = SIZES[spec["camera"]]
            rr = render_sequence(Path(tmp) / "seq", RenderOptions(
                scene=spec["scene"], camera=spec["camera"], textured=spec["textured"],
                frames=task["frames"], width=w, height=h, seed=task["seed"]), progress=False)
            seq = sequence_from_frames(rr.output / "images", rr.camera)
            gt, options = rr.groundtruth, {}
        results, trajs, _ = run_comparison(seq, gt, task["initializers"], options)
    results = replace(results, sequence=replace(results.sequence, name=task_id(task)))
    return {"task": task, "results": results.to_json(),
            "tum": {k: v.to_tum() for k, v in trajs.items()},
            "groundtruth": gt.to_tum(), "wall_s": time.perf_counter() - t0}


def run_all(tasks: list[dict[str, Any]], scheduler: str | None, workers: int,
            on_done: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Run ``tasks`` on a process pool or a Dask cluster; results in task order."""
    out: list[dict[str, Any] | None] = [None] * len(tasks)
    if scheduler:
        from distributed import Client, as_completed

        with Client(scheduler) as client:
            futs = client.map(run_task, tasks, pure=False)
            index = {f.key: i for i, f in enumerate(futs)}
            for f in as_completed(futs):
                r = f.result()
                out[index[f.key]] = r
                if on_done:
                    on_done(r)
    else:
        import multiprocessing
        from concurrent.futures import as_completed as cf_completed

        # spawn, not fork: a forked child inherits OpenCV's and BLAS's thread pools half-locked
        # and deadlocks in its first cv2 call (seen in cv2.setNumThreads)
        ctx = multiprocessing.get_context("spawn")
        # spawned children import this module by name to find run_task, with the parent's
        # sys.path (multiprocessing copies it over): the repository root holds ``scripts``
        root = str(ROOT)
        if root not in sys.path:
            sys.path.insert(0, root)
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            pending = {pool.submit(run_task, t): i for i, t in enumerate(tasks)}
            for f in cf_completed(pending):
                r = f.result()
                out[pending[f]] = r
                if on_done:
                    on_done(r)
    return [r for r in out if r is not None]


def comparable(results: dict[str, Any]) -> dict[str, Any]:
    """``results`` without the wall times (every key ending in ``_s``, at any depth: what must
    be identical across schedulers)."""
    def strip(x: Any) -> Any:
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if not k.endswith("_s")}
        if isinstance(x, list):
            return [strip(v) for v in x]
        return x

    return dict(strip(json.loads(json.dumps(results))))


def write_runs(output: Path, done: list[dict[str, Any]]) -> None:
    from omni_sfm.fileio import atomic_write_text, dumps_json

    for r in done:
        d = output / "runs" / task_id(r["task"])
        (d / "trajectories").mkdir(parents=True, exist_ok=True)
        for name, text in r["tum"].items():
            atomic_write_text(d / "trajectories" / f"{name}.tum", text)
        atomic_write_text(d / "groundtruth.tum", r["groundtruth"])
        atomic_write_text(d / "results.json", dumps_json(r["results"]))
    atomic_write_text(output / "sweep.json", dumps_json(
        [{"task": r["task"], "results": r["results"], "wall_s": r["wall_s"]} for r in done]))


def _med(xs: list[float]) -> float:
    return float(np.median(xs)) if xs else float("nan")


def _f(x: float, digits: int = 3, pct: bool = False) -> str:
    if not np.isfinite(x):
        return "-"
    return f"{100 * x:.{digits}f} %" if pct else f"{x:.{digits}f}"


SUMMARY_COLUMNS = ["sequences", "initializer", "ok runs", "registered (mean)",
                   "rot max, deg (median)", "rot mean, deg (median)", "ATE / path (median)",
                   "time, s (median)"]
RUN_COLUMNS = ["run", "initializer", "status", "registered", "rot max (deg)", "ATE / path",
               "reason"]


def summary_rows(done: list[dict[str, Any]]) -> tuple[list[list[str]], list[list[str]]]:
    """Per kind and initializer, success and median errors; then every run (failures with their
    reasons): the rows of :data:`SUMMARY_COLUMNS` and :data:`RUN_COLUMNS`."""
    names: list[str] = []
    for r in done:
        names += [n for n in r["results"]["initializers"] if n not in names]
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in done:
        t = r["task"]
        key = t["kind"] if t.get("noise_deg") is None else f"sim, noise {t['noise_deg']:g} deg"
        groups.setdefault(key, []).append(r)
    summary = []
    for key, runs in groups.items():
        for n in names:
            es = [r["results"]["initializers"][n] for r in runs
                  if n in r["results"]["initializers"]]
            if not es:
                continue  # not run on this kind (lines-refine needs images)
            ok = [e for e in es if e["status"] == "ok"]
            summary.append([
                f"{key} ({len(runs)} seeds)", n, f"{len(ok)}/{len(es)}",
                _f(float(np.mean([e["registered"] for e in es])), 0, True),
                _f(_med([e["rot_max_deg"] for e in ok])),
                _f(_med([e["rot_mean_deg"] for e in ok])),
                _f(_med([e["ate_rel"] for e in ok]), 2, True),
                _f(_med([e["time_s"] for e in es]), 1)])
    every = []
    for r in done:
        for n, e in r["results"]["initializers"].items():
            reason = (e.get("reason") or "").replace("|", "/")
            if len(reason) > 140:
                reason = reason[:137] + "..."
            every.append([task_id(r["task"]), n, e["status"], _f(e["registered"], 0, True),
                          _f(e["rot_max_deg"] if e["rot_max_deg"] is not None else np.nan),
                          _f(e["ate_rel"] if e["ate_rel"] is not None else np.nan, 2, True),
                          reason])
    return summary, every


def markdown(columns: list[str], rows: list[list[str]]) -> str:
    """A Markdown table."""
    return "\n".join(["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns),
                      *("| " + " | ".join(r) + " |" for r in rows)])


def log_sweep(args: argparse.Namespace, done: list[dict[str, Any]], said: str) -> None:
    """The sweep's two records: ``compare_init`` (per kind and initializer) and
    ``compare_init_runs`` (every run)."""
    summary, every = summary_rows(done)
    corridor = [r for r in summary if r[0].startswith("corridor-hyperboloid (")]
    lines = next((r for r in corridor if r[1] == "lines"), None)
    head = ""
    if lines is not None:
        others = "; ".join(f"{r[1]} {r[2]} ok, {r[4]} deg, {r[6]}" for r in corridor
                           if r[1] not in ("lines", "lines-refine"))
        head = (f"texture-poor corridor: lines {lines[3]} of the frames at {lines[4]} deg / "
                f"{lines[6]} ATE (median); {others}").replace("{", "{{").replace("}", "}}")
    write_log(args, "compare_init", "Line-based against point-based initializers",
              SUMMARY_COLUMNS, summary, headline=head, notes=said)
    write_log(args, "compare_init_runs", "Every run of the comparison sweep", RUN_COLUMNS,
              every, headline=f"{len(every)} runs")


def plot_sweep(done: list[dict[str, Any]], prefix: Path | str) -> list[Path]:
    """``<prefix>noise.png`` (simulation: error against noise) and ``<prefix>texture.png``
    (rendered: registered share and ATE per sequence kind)."""
    import matplotlib

    matplotlib.use("Agg")
    names: list[str] = []
    for r in done:
        names += [n for n in r["results"]["initializers"] if n not in names]
    paths = []
    sims = [r for r in done if r["task"]["kind"] == "sim"]
    if sims:
        paths.append(_plot_noise(sims, names, prefix))
    kinds = [k for k in RENDER if any(r["task"]["kind"] == k for r in done)]
    if kinds:
        paths.append(_plot_texture(done, kinds, names, prefix))
    return paths


def _plot_noise(sims: list[dict[str, Any]], names: list[str], prefix: Path | str) -> Path:
    """``<prefix>noise.png``: each initializer's simulation errors against the noise."""
    import matplotlib.pyplot as plt

    from omni_sfm.compare import COLOURS

    noises = sorted({r["task"]["noise_deg"] for r in sims})
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=100)
    for n in names:
        for ax, key, scale in ((axes[0], "rot_max_deg", 1.0), (axes[1], "ate_rel", 100.0)):
            med, xs = [], []
            for nz in noises:
                v = [scale * r["results"]["initializers"][n][key] for r in sims
                     if r["task"]["noise_deg"] == nz
                     and n in r["results"]["initializers"]
                     and r["results"]["initializers"][n]["status"] == "ok"]
                if v:
                    xs.append(nz)
                    med.append(np.median(v))
                    ax.scatter([nz] * len(v), v, s=8, alpha=0.4, color=COLOURS.get(n))
            if xs:
                ax.plot(xs, med, "o-", color=COLOURS.get(n), label=n)
    axes[0].set_ylabel("max rotation error (deg)")
    axes[1].set_ylabel("ATE (% of path)")
    from matplotlib.ticker import NullFormatter

    for ax in axes:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(noises, [f"{x:g}" for x in noises])
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("noise on normals and rays (deg)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("simulation (paper's set-up): median over seeds, dots = runs (ok only)")
    fig.tight_layout()
    p = Path(f"{prefix}noise.png")
    fig.savefig(p)
    plt.close(fig)
    return p


def _plot_texture(done: list[dict[str, Any]], kinds: list[str], names: list[str],
                  prefix: Path | str) -> Path:
    """``<prefix>texture.png``: each initializer's registered share and ATE per rendered kind."""
    import matplotlib.pyplot as plt

    from omni_sfm.compare import COLOURS

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), dpi=100)
    w = 0.8 / max(1, len(names))
    for i, n in enumerate(names):
        reg, ate = [], []
        for k in kinds:
            es = [r["results"]["initializers"][n] for r in done if r["task"]["kind"] == k
                  and n in r["results"]["initializers"]]
            reg.append(100 * np.mean([e["registered"] for e in es]) if es else np.nan)
            ok = [100 * e["ate_rel"] for e in es if e["status"] == "ok"]
            ate.append(np.median(ok) if ok else np.nan)
        x = np.arange(len(kinds)) + (i - (len(names) - 1) / 2) * w
        axes[0].bar(x, reg, w, color=COLOURS.get(n), label=n)
        axes[1].bar(x, ate, w, color=COLOURS.get(n), label=n)
        for xi, a in zip(x, ate, strict=True):
            if not np.isfinite(a):
                axes[1].text(xi, 0.02, "all failed", rotation=90, ha="center", va="bottom",
                             fontsize=7, color=COLOURS.get(n),
                             transform=axes[1].get_xaxis_transform())
    labels = [k.replace("-", "\n", 1) for k in kinds]
    for ax in axes:
        ax.set_xticks(np.arange(len(kinds)), labels, fontsize=8)
    axes[0].set_ylabel("frames registered (% , mean over seeds)")
    axes[1].set_ylabel("ATE (% of path, median of ok runs)")
    axes[1].set_yscale("log")
    handles, labs = axes[0].get_legend_handles_labels()
    fig.legend(handles, labs, loc="lower center", ncol=len(names), fontsize=8)
    fig.suptitle("rendered sequences: texture-poor corridor vs textured scenes")
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    p = Path(f"{prefix}texture.png")
    fig.savefig(p)
    plt.close(fig)
    return p


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--output", type=Path, required=True, help="folder for runs and summary")
    ap.add_argument("--kinds", default=",".join(KINDS),
                    help=f"comma-separated sequence kinds (default: {','.join(KINDS)}; "
                         f"also: room-equirectangular)")
    ap.add_argument("--seeds", default="0,1,2", help="comma-separated seeds")
    ap.add_argument("--noise", default="0.04,0.16,0.64",
                    help="noise levels of the simulation, degrees")
    ap.add_argument("--frames", type=int, default=30, help="frames of rendered sequences")
    ap.add_argument("--sim-points", type=int, default=40,
                    help="point features of a simulated sequence (it has 40 lines)")
    ap.add_argument("--initializers", default=None,
                    help="comma-separated (default: the four of 'omni-sfm compare'; on rendered "
                         "sequences also lines-refine, the README's init + refine)")
    ap.add_argument("--workers", type=int, default=2, help="local processes")
    ap.add_argument("--scheduler", default=None,
                    help="Dask scheduler address (tcp://HOST:8786) instead of local processes")
    ap.add_argument("--replot", action="store_true",
                    help="only redraw the plots from OUTPUT/sweep.json (into docs/img with --docs)")
    ap.add_argument("--docs", action="store_true",
                    help="draw the plots into docs/img (the records go to --log-dir)")
    add_log_arguments(ap)
    a = ap.parse_args(argv)

    import importlib

    from omni_sfm.compare import parse_initializer_names
    from omni_sfm.registry import INITIALIZERS, available

    # fail early, before any task starts, if a plugin or the renderer cannot be imported
    importlib.import_module("omni_sfm.synth.render")
    for ep in available(INITIALIZERS).values():
        ep.load()

    if a.replot:
        done = json.loads((a.output / "sweep.json").read_text(encoding="utf-8"))
        plot_sweep(done, ROOT / "docs" / "img" / "comparison_" if a.docs else f"{a.output}/")
        return 0
    kinds = [k.strip() for k in a.kinds.split(",") if k.strip()]
    bad = [k for k in kinds if k != "sim" and k not in RENDER]
    if bad:
        ap.error(f"unknown kind {bad[0]!r}")
    names = parse_initializer_names(a.initializers)
    tasks = make_tasks(kinds, [int(s) for s in a.seeds.split(",")],
                       [float(x) for x in a.noise.split(",")], a.frames, a.sim_points, names,
                       IMAGE_ONLY if a.initializers is None else ())
    a.output.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    count = [0]

    def report(r: dict[str, Any]) -> None:
        count[0] += 1
        st = ", ".join(f"{n} {e['status']}" for n, e in r["results"]["initializers"].items())
        print(f"[{count[0]}/{len(tasks)}] {task_id(r['task'])} ({r['wall_s']:.0f} s): {st}",
              flush=True)

    done = run_all(tasks, a.scheduler, a.workers, report)
    wall = time.perf_counter() - t0
    write_runs(a.output, done)
    summary, every = summary_rows(done)
    (a.output / "summary.md").write_text(markdown(SUMMARY_COLUMNS, summary) + "\n\n"
                                         + markdown(RUN_COLUMNS, every) + "\n", encoding="utf-8")
    print(f"{len(done)} runs in {wall / 60:.1f} min; {a.output / 'summary.md'}")
    plot_sweep(done, ROOT / "docs" / "img" / "comparison_" if a.docs else f"{a.output}/")
    where = "Dask " + a.scheduler if a.scheduler else f"{a.workers} local processes"
    log_sweep(a, done, f"{len(done)} runs, {wall / 60:.0f} min wall on {where}.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
