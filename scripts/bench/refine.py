"""Benchmark ``omni-sfm refine`` on the issue's full case: rendered textured room, hyperboloid
camera, 800 x 600, 100 frames. Prints the per-stage times and the ATE before and after.

    .venv/bin/python -m scripts.bench.refine --work /tmp/bench_refine
    .venv/bin/python -m scripts.bench.refine --work /tmp/bench_refine --features klt sift
    .venv/bin/python -m scripts.bench.refine --work /tmp/bench_corridor --scene corridor
    .venv/bin/python -m scripts.bench.refine --work /tmp/bench_office --scene office --frames 1000
    .venv/bin/python -m scripts.bench.refine --work /tmp/bench_refine --init LINE_INIT_DIR
    .venv/bin/python -m scripts.bench.refine --work /tmp/bench_refine --frames 120 --versus-colmap
    .venv/bin/python -m scripts.bench.refine --work /tmp/bench_eq --camera equirectangular \
        --width 1920 --height 960 --lines-init --adjustment joint colmap
    .venv/bin/python -m scripts.bench.refine --work /tmp/bench_mappers --frames 30 --width 640 \
        --height 480 --versus-colmap --colmap-global --missing 8 9 10 11 20 \
        --mapper incremental global --record bench_refine_mappers

Without ``--init`` the seed is the ground truth with realistic errors (0.3 deg rotation noise and
0.5 % of the path position noise, fixed seed), written as an init directory by
``omni_sfm.refine.synthetic.write_perturbed_init``; with ``--init`` an existing init directory
(e.g. from ``omni-sfm init``) of the same frames is refined instead. The rendering is reused when
``WORK/render`` exists. ``--features`` names the feature sources to compare (default: the
default source only); they run back to back on the same render and seed, each with a fresh
database, into ``WORK/refined_<source>``. ``--matching guided colmap`` runs the SIFT refinement
with both matchers (guided along the input poses, the default; COLMAP's matcher), each with its
own database and output folder (``WORK/database_sift_colmap.db``,
``WORK/refined_sift_colmap_*``). The room is rendered with texture, the corridor without
(texture-poor). ATE is after a similarity alignment, relative to the path length.

``--versus-colmap`` compares the whole line-based chain with COLMAP's own incremental SfM in one
run: ``omni-sfm init --lines`` (a fresh process, timed) seeds the refinement instead of the
perturbed ground truth, and ``omni-sfm init --initializer colmap`` (COLMAP's feature extraction,
matching and incremental mapper with the exact camera, a fresh process, timed) runs on the same
frames; each refinement's line is followed by its ``init`` + ``refine`` time against COLMAP's
(only for a refinement that extracted and matched its features itself: the second adjustment on
one feature source reuses the first one's database). ``--colmap-global`` adds COLMAP's global
mapper (``pycolmap.global_mapping``, from scratch) on the database COLMAP's incremental SfM
built (both through the ``colmap`` initializer in fresh processes; the global mapper's time is
its own plus the database's).

``--missing K ...`` takes the poses of frames ``K`` out of the seed
(:func:`omni_sfm.refine.synthetic.write_init_without`): the frames the init missed, which the
mapper stage registers; ``--mapper incremental global`` runs refine with each way of registering
them, each with a fresh database, and the record gets the mapper stage's time and the errors of
those frames (after the similarity alignment of the whole trajectory) in every row.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.evaluate import associate, trajectory_errors
from omni_sfm.export.colmap import read_init_model
from omni_sfm.frames import FrameStore
from omni_sfm.poses import Trajectory, read_tum
from omni_sfm.refine import RefineOptions, refine
from omni_sfm.refine.database import FEATURE_SOURCES
from omni_sfm.refine.pipeline import MAPPERS
from omni_sfm.refine.synthetic import write_init_without, write_perturbed_init
from omni_sfm.synth.paths import Route
from omni_sfm.synth.render import RenderOptions, render_sequence
from omni_sfm.synth.scenes import SceneName
from scripts.benchlib import add_log_arguments, run_timed, write_log


def _parser() -> argparse.ArgumentParser:
    """The command line's arguments."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", type=Path, required=True, help="working folder (render reused)")
    p.add_argument("--scene", choices=["room", "corridor", "office"], default="room",
                   help="room (textured), corridor (texture-poor) or office: the textured "
                        "L-shaped office walk of scripts/bench/init.py at --metres-per-frame, "
                        "so that longer runs walk farther at the same speed")
    p.add_argument("--metres-per-frame", type=float, default=0.0115,
                   help="office: the camera's speed (default: scripts/bench/init.py's)")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--camera", choices=["hyperboloid", "equirectangular"],
                   default="hyperboloid", help="the rendered camera (equirectangular: give "
                   "--width and --height, say 1920 and 960)")
    p.add_argument("--width", type=int, default=800)
    p.add_argument("--height", type=int, default=600)
    p.add_argument("--overlap", type=int, default=RefineOptions().overlap)
    p.add_argument("--max-features", type=int, default=RefineOptions().max_features,
                   help="SIFT features per image at most")
    p.add_argument("--init", type=Path, default=None,
                   help="refine this init directory instead of the perturbed ground truth")
    p.add_argument("--seed", type=int, default=0, help="seed of the perturbation")
    p.add_argument("--adjustment", nargs="+", choices=["joint", "colmap"],
                   default=[RefineOptions().adjustment],
                   help="the adjustments to run, one after the other on the same features and "
                        "matches (each feature source's database is reused)")
    p.add_argument("--features", nargs="+", choices=list(FEATURE_SOURCES),
                   default=[RefineOptions().features],
                   help="feature sources to run, one after the other (default: %(default)s)")
    p.add_argument("--matching", nargs="+", choices=["guided", "colmap"],
                   default=["guided" if RefineOptions().guided_matching else "colmap"],
                   help="sift: match along the input poses (guided) or by COLMAP's matcher and "
                        "verification; each its own database (database_sift.db, "
                        "database_sift_colmap.db) and output folder")
    p.add_argument("--klt-verify", action="store_true",
                   help="KLT: run COLMAP's geometric verification on the track matches")
    p.add_argument("--versus-colmap", action="store_true",
                   help="seed with `init --lines` run here and compare init + refine with "
                        "COLMAP's incremental SfM on the same frames (times and errors)")
    p.add_argument("--lines-init", action="store_true",
                   help="seed with `init --lines` run here (timed), without COLMAP's SfM")
    p.add_argument("--colmap-global", action="store_true",
                   help="with --versus-colmap: also COLMAP's global mapper on the database of "
                        "COLMAP's incremental SfM")
    p.add_argument("--missing", nargs="+", type=int, default=[],
                   help="frame indices whose poses are taken out of the seed (for the mapper)")
    p.add_argument("--mapper", nargs="+", choices=list(MAPPERS),
                   default=[RefineOptions().mapper],
                   help="how refine registers the missing frames; several: each its own run "
                        "and fresh database")
    p.add_argument("--record", default="bench_refine_room",
                   help="name of the record under docs/benchmarks/ (default: %(default)s)")
    add_log_arguments(p)
    return p


def _render(args: argparse.Namespace) -> Path:
    """``WORK/render``: the scene rendered, unless it already is."""
    render = Path(args.work / "render")
    if not (render / "groundtruth.tum").is_file():
        t0 = time.perf_counter()
        if args.scene == "office":
            opts = RenderOptions(scene=SceneName.OFFICE, route=Route.OFFICE,
                                 camera=args.camera, width=args.width, height=args.height,
                                 frames=args.frames, textured=True,
                                 path_length=args.metres_per_frame * (args.frames - 1))
        else:
            opts = RenderOptions(scene=args.scene, camera=args.camera, width=args.width,
                                 height=args.height, frames=args.frames,
                                 textured=args.scene == "room")
        render_sequence(render, opts, progress=sys.stderr.isatty())
        print(f"render: {time.perf_counter() - t0:.1f} s")
    return render


def _seed(args: argparse.Namespace, render: Path) -> tuple[Path, str, list[str]]:
    """The init directory refined (the perturbed ground truth unless ``args.init``, without
    the ``--missing`` frames' poses), its description, and the names of the missing frames."""
    if args.init is None:
        init_dir = args.work / "init_perturbed"
        write_perturbed_init(render, init_dir, seed=args.seed, overwrite=True)
        kind = f"ground truth perturbed by 0.3 deg / 0.5 % of the path (seed {args.seed})"
    else:
        init_dir = args.init
        kind = f"init directory {init_dir}"
    missed = [list(FrameStore(render / "images").names)[k] for k in args.missing]
    if missed:  # the frames the init missed, for the mapper
        init_dir = write_init_without(init_dir, args.work / "init_missing", missed,
                                      overwrite=True)
        kind += f", without the poses of frames {', '.join(map(str, args.missing))}"
    return Path(init_dir), kind, missed


def main() -> int:
    p = _parser()
    args = p.parse_args()
    # freed memory kept for reuse in this process, as the omni-sfm command keeps it
    from omni_sfm.libs import keep_freed_memory

    keep_freed_memory()
    if (args.versus_colmap or args.lines_init) and args.init is not None:
        p.error("--versus-colmap and --lines-init run their own `init --lines`; leave out "
                "--init")

    render = _render(args)
    gt = read_tum(render / "groundtruth.tum")
    rows: list[list[object]] = []  # the record: run, frames, rotation mean / max, ATE, wall
    walls = _own_inits(args, render, gt, rows)
    if walls is None:
        return 1
    init_wall, colmap_wall = walls
    init_dir, kind, missed = _seed(args, render)
    init = read_init_model(init_dir).trajectory
    scene = {"room": "textured room", "corridor": "texture-poor corridor",
             "office": "textured office walk"}[args.scene]
    print(f"case: {scene}, {args.camera} {args.width}x{args.height}, {len(gt)} frames, "
          f"path {gt.path_length():.2f} m; seed: {kind}")
    before = trajectory_errors(init, gt)
    rows.append(["`init --lines`" if init_wall is not None else "input (seed)",
                 *_figures(init_dir / "trajectory.tum", gt, args.missing), init_wall, "-"])
    print(f"input: ATE / path length {100 * before.ate_rel:.4f} %, rotation error mean / max "
          f"{before.rot_mean_deg:.3f} / {before.rot_max_deg:.3f} deg")
    runs = [(f, m, mp) for f in args.features for m in (args.matching if f == "sift" else [""])
            for mp in args.mapper]
    speedups: list[tuple[int, str, float]] = []  # (row, run, COLMAP's time over init + refine)
    stages = ""
    for features, matching, mapper in runs:
        tag = features + ("_colmap" if matching == "colmap" else "") + (
            f"_{mapper}" if len(args.mapper) > 1 else "")
        database = args.work / f"database_{tag}.db"
        # each run from a fresh database (a database left by an earlier run of the script
        # would give its features and matches; the adjustments after the first share it)
        database.unlink(missing_ok=True)
        for adjustment in args.adjustment:
            t0 = time.perf_counter()
            res = refine(init_dir, render / "images",
                         args.work / f"refined_{tag}_{adjustment}",
                         RefineOptions(overlap=args.overlap, features=features,
                                       max_features=args.max_features,
                                       guided_matching=matching != "colmap",
                                       klt_verify=args.klt_verify, adjustment=adjustment,
                                       mapper=mapper),
                         database=database, overwrite=True, progress=sys.stderr.isatty())
            total = time.perf_counter() - t0
            label = features + (f", {matching} matching" if matching else "") + (
                f", {mapper} mapper" if missed else "")
            registered = res.report.mapper.registered
            mapper_cell: object = "-" if not missed else \
                f"{res.report.timings_s['mapper']:.1f} ({len(registered or [])} / " \
                f"{len(missed)} registered)"
            rows.append([f"`init` + `refine` ({label}, {adjustment} adjustment)",
                         *_figures(res.trajectory, gt, args.missing),
                         total if init_wall is None else f"{init_wall + total:.1f} "
                         f"({init_wall:.1f} + {total:.1f})", mapper_cell])
            _print_run(features + (f" ({matching} matching)" if matching else ""), adjustment,
                       res.report.to_json(), total, trajectory_errors(res.trajectory, gt),
                       len(init))
            if init_wall is not None and colmap_wall is not None and \
                    res.report.features.reused_images == 0:
                both = init_wall + total
                print(f"init + refine: {both:.1f} s ({init_wall:.1f} + {total:.1f}); COLMAP's "
                      f"incremental SfM {colmap_wall:.1f} s: {colmap_wall / both:.2f}x",
                      flush=True)
                speedups.append((len(rows) - 1, label, colmap_wall / both))
            if not stages:  # the first (default) refinement's stages
                stages = ", ".join(f"{k} {v:.1f} s" for k, v in res.report.timings_s.items()
                                   if v >= 0.05)
    columns: list[str | dict[str, str]] = [
        "run", "frames", "rotation error mean / max (deg)",
        {"label": "ATE (% of path)", "format": ".4f"}]
    if args.missing:
        columns.append("missed frames: rotation max (deg) / position max (% of path)")
    columns += [{"label": "wall time (s)", "format": ".1f"}, "mapper stage (s)"]
    headline = _headline(len(rows), len(columns), len(args.mapper) > 1)
    if speedups and not args.missing:
        w = len(columns) - 2  # the wall time's column
        headline = "; ".join(
            f"`init` + `refine` ({label}): {{rows[{k}][2]}} deg, {{rows[{k}][3]}} % ATE, "
            f"{{rows[{k}][{w}]}} s, "
            f"{x:.1f}x faster than COLMAP's incremental SfM ({{rows[0][{w}]}} s, "
            f"{{rows[0][2]}} deg, {{rows[0][3]}} %)" if i == 0 else
            f"{label}: {{rows[{k}][{w}]}} s, {x:.1f}x" for i, (k, label, x) in
            enumerate(speedups))
    write_log(args, args.record, "init + refine against COLMAP's incremental SfM", columns,
        rows, headline=headline,
        notes=f"{scene}, {args.camera} {args.width}x{args.height}, {len(gt)} frames; seed: "
              f"{kind}" + (f"; the first refinement's stages: {stages}" if stages else "") + ".")
    return 0


def _headline(n: int, m: int, mappers: bool) -> str:
    """The record's one-line summary (``str.format`` takes no negative index): the last run
    against the one before, or with two mappers the last two runs' mapper stages."""
    a, b = n - 2, n - 1
    if mappers:
        return (f"mapper stage (s): incremental {{rows[{a}][{m - 1}]}}, global "
                f"{{rows[{b}][{m - 1}]}}; ATE {{rows[{a}][3]}} and {{rows[{b}][3]}} %")
    return (f"{{rows[{b}][0]}}: {{rows[{b}][2]}} deg, {{rows[{b}][3]}} % ATE (from "
            f"{{rows[{a}][2]}} deg, {{rows[{a}][3]}} %)")


def _own_inits(args: argparse.Namespace, render: Path, gt: Trajectory,
               rows: list[list[object]]) -> tuple[float | None, float | None] | None:
    """With ``--versus-colmap`` / ``--lines-init``: COLMAP's SfM and ``init --lines`` on the
    render, each in a fresh process (their rows appended to ``rows``; ``args.init`` set to the
    line-based one); ``(init wall, COLMAP wall)``, None when ``init`` failed."""
    init_wall = colmap_wall = None
    exe = [sys.executable, "-m", "omni_sfm", "init"]
    common = ["--images", str(render / "images"), "--camera", str(render / "camera.yaml"),
              "--overwrite", "--quiet"]
    if args.versus_colmap or args.lines_init:
        print(f"# {os.cpu_count()} CPUs; `init` and COLMAP each in a fresh process", flush=True)
    if args.versus_colmap:
        database = args.work / "colmap_sfm.db"
        database.unlink(missing_ok=True)
        db_s = 0.0
        for mapper in ["incremental", "global"] if args.colmap_global else ["incremental"]:
            out = args.work / f"colmap_sfm_{mapper}"
            if args.colmap_global:  # the colmap initializer with its options, in a fresh process
                code_text = (
                    "from omni_sfm.pipelines.init import init_with_initializer as f; "
                    f"f({str(render / 'images')!r}, {str(render / 'camera.yaml')!r}, "
                    f"{str(out)!r}, 'colmap', overwrite=True, "
                    f"options={{'mapper': {mapper!r}, 'database': {str(database)!r}}})")
                cmd = [sys.executable, "-c", code_text]
            else:
                cmd = [*exe, "--initializer", "colmap", *common, "--output", str(out)]
            wall, peak, code, said = run_timed(cmd)
            what = f"COLMAP's {mapper} SfM"
            if code != 0:
                print(f"{what}: exit {code}: {said}")
                continue
            info = json.loads((out / "report.json").read_text()).get("info", {})
            traj = read_tum(out / "trajectory.tum")
            e = trajectory_errors(traj, gt)
            if mapper == "incremental":
                colmap_wall, db_s = wall, float(info.get("database_s", 0.0))
                cell: object = wall
            else:  # on the incremental run's database: its time counts too
                cell = f"{db_s + wall:.1f} ({db_s:.1f} database + {wall:.1f})"
            rows.append([what + (" (same database)" if mapper == "global" else ""),
                         *_figures(traj, gt, args.missing), cell,
                         f"{info['mapper_s']:.1f}" if "mapper_s" in info else "-"])
            print(f"{what}: {wall:.1f} s, peak {peak:.0f} MB; {len(traj)}/{len(gt)} frames, "
                  f"ATE {100 * e.ate_rel:.4f} %, rotation mean / max {e.rot_mean_deg:.3f} / "
                  f"{e.rot_max_deg:.3f} deg; {info}", flush=True)
    if args.versus_colmap or args.lines_init:
        args.init = args.work / "init_lines"
        init_wall, peak, code, said = run_timed([*exe, "--lines", *common,
                                                 "--output", str(args.init)])
        if code != 0:
            print(f"init --lines: exit {code}: {said}")
            return None
        print(f"init --lines: {init_wall:.1f} s, peak {peak:.0f} MB", flush=True)
    return init_wall, colmap_wall


def _figures(trajectory: Path | Trajectory, gt: Trajectory,
             missing: list[int] | None = None) -> list[object]:
    """``[frames posed / all, "rotation mean / max", ATE %]`` of a trajectory; with
    ``missing`` (frame indices) also the largest rotation and position error of those frames
    after the alignment of the whole trajectory ("-" when it lacks one of them)."""
    est = read_tum(trajectory) if isinstance(trajectory, Path) else trajectory
    e = trajectory_errors(est, gt)
    out: list[object] = [f"{len(est)} / {len(gt)}",
                         f"{e.rot_mean_deg:.3f} / {e.rot_max_deg:.3f}", 100 * e.ate_rel]
    if missing:
        est_c, gt_c = associate(est, gt)
        at = [int(k) for t in gt.timestamps[missing]
              for k in np.flatnonzero(np.isclose(gt_c.timestamps, t, rtol=0, atol=1e-6))]
        if len(at) < len(missing):
            out.append("-")
        else:
            pos = np.linalg.norm(e.alignment.apply(est_c).positions[at] - gt_c.positions[at],
                                 axis=1)
            out.append(f"{e.rot_deg[at].max():.3f} / "
                       f"{100 * pos.max() / gt.path_length():.4f}")
    return out


def _print_run(features: str, adjustment: str, r: dict[str, Any], total: float, after: Any,
               seeded: int) -> None:
    ba = r["bundle_adjustment"]
    f = r["features"]
    tracks = f" on {f['tracks']} tracks" if "tracks" in f else ""
    print(f"--- features: {features}, adjustment: {adjustment}"
          + (f" (joint skipped: {r['joint_adjustment']})" if "joint_adjustment" in r else ""))
    print(f"frames: {seeded} seeded, {r['refined_frames']} refined, "
          f"{len(r['kept_frames'])} kept ({r['kept_input_for_all'] or 'per frame'})")
    print(f"features: {f['keypoints']} keypoints{tracks} ({f['reused_images']} images reused "
          f"from the database); matching: {r['matching']['verified_pairs']} verified pairs, "
          f"{r['matching']['inlier_matches']} inlier matches")
    if "matching_guided" in r:
        g = r["matching_guided"]
        print(f"guided matching: {g['written']} of {g['pairs']} pairs written, {g['matches']} "
              "matches (the rest: COLMAP's matcher)")
    if "joint" in ba:
        j = ba["joint"]
        print(f"joint: {j['line_observations']} line and {j['point_observations']} point "
              f"observations ({j['point_observations_rejected']} rejected), noise "
              f"{j['line_noise_deg']:.4f} / {j['point_noise_deg']:.4f} deg, "
              f"{j['iterations']} iterations")
    else:
        rounds = ba.get("rounds") or [{}]
        print(f"points: {r['model']['points']}, observations: {r['model']['observations']}, "
              f"mean reprojection error: triangulated "
              f"{r['triangulation']['mean_reprojection_error_px']:.3f} px -> after BA "
              f"{rounds[-1].get('mean_reprojection_error_after_px', float('nan')):.3f} px")
    print("stage times (s): " + json.dumps(r["timings_s"]) + f"; total {total:.1f} s, "
          f"{1000 * total / max(seeded, 1):.0f} ms a frame")
    print(f"ATE / path length: {100 * after.ate_rel:.4f} %; rotation error mean / max: "
          f"{after.rot_mean_deg:.3f} / {after.rot_max_deg:.3f} deg", flush=True)


if __name__ == "__main__":
    sys.exit(main())
