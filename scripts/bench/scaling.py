#!/usr/bin/env python
"""How the estimator scales with sequence length: `omni-sfm init --lines` on long Manhattan walks.

For each N in ``--frames`` (default 1,000, 5,000 and 20,000 frames) this simulates a walk through
office corridors (``omni-sfm simulate --world manhattan``: 0.05 m a frame, each line seen in
about 60 frames, 0.1 deg noise on the normals, a fixed seed), writes it to a temporary folder
and runs ``omni-sfm init --lines --tracks DIR/tracks.json --output OUT`` in a fresh process. Per
N it prints the wall time, the time per frame, the child's peak memory (its own maximum
resident set: each run goes through a wrapper process of its own, so runs do not mix), the
frames estimated, and against the ground truth (on the reflection branch nearer it,
``match_reflection``) the rotation error of the 500th and of the last frame relative to the
first, the mean rotation error and the ATE (RMS after a similarity alignment, per cent of the
path length). A run that fails or passes ``--timeout`` is reported with its last error line and
the next N goes on.

With ``--oracle`` it also prints the rotation errors of the maximum-likelihood floor on the frames
of the main trajectory (``orc@500``, ``orc@last``, ``orc mean``): the line bundle adjustment of
all frames started from the ground truth, every line of a family held on its true direction (as
the estimator holds the families it finds). Where the estimate's errors are the floor's, what
is left is the noise.

With ``--prefixes`` one walk of the longest length is simulated and each N runs on its first N
frames: the lengths then differ in nothing else (separate walks differ in how hard they are,
which the time per frame shows too).

    .venv/bin/python -m scripts.bench.scaling [--frames 1000 5000 20000] [--timeout 3600] \
        [--line-density 3.5] [--prefixes [--pieces]] [--oracle]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.bundle import BundleOptions, bundle_adjust
from omni_sfm.estimate.segments import frame_range
from omni_sfm.evaluate import match_reflection, trajectory_errors
from omni_sfm.lines.tracks import LineTracks, write_tracks
from omni_sfm.poses import Trajectory, read_tum, write_tum
from omni_sfm.synth.simulate import Simulation, SimulationOptions, simulate, write_simulation
from omni_sfm.transforms import associate
from scripts.benchlib import add_log_arguments, write_log

# Runs COMMAND with its output in LOG, kills its process group after TIMEOUT seconds, and
# writes the exit code, wall time and the peak RSS of its one child (bytes) to RESULT.
_WRAPPER = r"""
import json, os, resource, signal, subprocess, sys, time
timeout, log, result, cmd = float(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4:]
t0 = time.perf_counter()
timed_out = False
with open(log, "wb") as fh:
    p = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        rc = p.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        timed_out = True
        os.killpg(p.pid, signal.SIGKILL)
        rc = p.wait()
wall = time.perf_counter() - t0
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
unit = 1 if sys.platform == "darwin" else 1024
with open(result, "w") as fh:
    json.dump({"rc": rc, "timed_out": timed_out, "wall_s": wall,
               "peak_rss_bytes": ru.ru_maxrss * unit, "cpu_s": ru.ru_utime + ru.ru_stime}, fh)
"""

COLUMNS = (("frames", 7), ("lines", 6), ("obs", 8), ("sim s", 7), ("wall s", 8), ("ms/frame", 9),
           ("peak MB", 8), ("estimated", 12), ("rot@500", 8), ("rot@last", 9), ("rot mean", 9),
           ("ATE %", 7), ("segments", 9), ("in segs", 8), ("orc@500", 8), ("orc@last", 9),
           ("orc mean", 9))


def _last_error_line(log: Path) -> str:
    """The last line of the log that names an error, else its last non-empty line."""
    try:
        lines = [ln.strip() for ln in log.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return "(no output)"
    if not lines:
        return "(no output)"
    for ln in reversed(lines):
        if "error" in ln.lower() or "Error" in ln:
            return ln
    return lines[-1]


def _errors(est: Trajectory, gt: Trajectory, n: int, start: int = 0,
            prefix: str = "rot") -> dict[str, str]:
    """Frames estimated and the errors of the estimate, formatted for the table (a piece that
    starts at frame ``start`` of the walk: its last frame, not the walk's 500th)."""
    out = {"estimated": f"{len(est)}/{n}"} if prefix == "rot" else {}
    try:
        matched = match_reflection(est, gt)
        err = trajectory_errors(matched, gt)
    except OmniSfmError as exc:
        return out | {f"{prefix}@500": "-", f"{prefix}@last": "-", f"{prefix} mean": "-",
                      "note": str(exc)}
    common = associate(matched, gt)[0].timestamps   # rot_deg is per common frame
    for key, frame in (("@500", 499 if start == 0 else -1), ("@last", start + n - 1)):
        hit = np.flatnonzero(np.abs(common - frame) < 1e-6)
        out[prefix + key] = f"{err.rot_deg[hit[0]]:.3f}" if hit.size else "-"
    out[f"{prefix} mean"] = f"{err.rot_mean_deg:.3f}"
    if prefix == "rot":
        out["ATE %"] = f"{100 * err.ate_rel:.2f}"
    return out


def _oracle(sim: Simulation, start: int, n: int, frames: np.ndarray) -> dict[str, str]:
    """The maximum-likelihood floor's rotation errors on the frames of the main trajectory
    (``frames``: its timestamps) of frames ``start..start+n-1``, as the estimate's are measured
    on them: the line bundle adjustment of all those frames from the ground truth, each line
    of a parallel family (every line of the Manhattan walk) held on its true direction, as the
    estimator holds the families it finds (docs/estimator.md stage 5b)."""
    tracks, idx = frame_range(sim.tracks, start, start + n)
    d, p = sim.line_directions[idx], sim.line_points[idx]
    gt = sim.groundtruth.subset(np.arange(start, start + n))
    held = (np.abs(d @ d.T) > 1.0 - 1e-12).sum(1) >= 2  # a direction that another line shares
    try:
        res = bundle_adjust(tracks, gt.rotations, gt.positions, d, p, held_directions=held,
                            options=BundleOptions(reject_outliers=False))
    except OmniSfmError as exc:
        return {"note": f"oracle: {exc}"}
    f = res.frames & np.isin(gt.timestamps, frames)
    traj = Trajectory(gt.timestamps[f], res.rotations[f], res.positions[f])
    return _errors(traj, gt, n, start, prefix="orc")


def _options(n: int, args: argparse.Namespace) -> SimulationOptions:
    return SimulationOptions(world="manhattan", num_views=n, path_length=0.05 * (n - 1),
                             noise_deg=args.noise_deg, visible_frames=args.visible_frames,
                             line_density=args.line_density, seed=args.seed)


def _write_range(sim_dir: Path, sim: Simulation, start: int, n: int) -> LineTracks:
    """Frames ``start..start+n-1`` of ``sim`` as ``tracks.json`` and ``groundtruth.tum``,
    renumbered from 0."""
    tracks = frame_range(sim.tracks, start, start + n)[0]
    sim_dir.mkdir(parents=True, exist_ok=True)
    write_tracks(sim_dir / "tracks.json", tracks)
    write_tum(sim_dir / "groundtruth.tum", sim.groundtruth.subset(np.arange(start, start + n)))
    return tracks


def _run_one(n: int, args: argparse.Namespace, work: Path,
             whole: Simulation | None = None, start: int = 0) -> dict[str, str]:
    row = {"frames": str(n) if start == 0 else f"+{start}"}
    t0 = time.perf_counter()
    sim_dir = work / f"sim_{start}_{n}"
    if whole is not None:
        tracks = _write_range(sim_dir, whole, start, n)
    else:
        opts = _options(n, args)
        sim = simulate(opts)
        write_simulation(sim_dir, sim, opts)
        tracks = sim.tracks
        del sim
    row |= {"lines": str(tracks.num_tracks), "obs": str(tracks.num_observations),
            "sim s": f"{time.perf_counter() - t0:.1f}"}
    del tracks
    out_dir, log, result = (work / f"init_{start}_{n}{ext}" for ext in ("", ".log", ".json"))
    cmd = [sys.executable, "-m", "omni_sfm", "init", "--lines", "--tracks",
           str(sim_dir / "tracks.json"), "--output", str(out_dir), "--quiet", "--overwrite",
           *shlex.split(args.init_args)]
    env = dict(os.environ)
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    try:
        subprocess.run([sys.executable, "-c", _WRAPPER, str(args.timeout), str(log), str(result),
                        *cmd], env=env, check=True, timeout=args.timeout + 120)
        res = json.loads(result.read_text())
    except (subprocess.SubprocessError, OSError, ValueError) as exc:
        return row | {"note": f"wrapper failed: {exc}"}
    row |= {"wall s": f"{res['wall_s']:.1f}", "ms/frame": f"{1000 * res['wall_s'] / n:.2f}",
            "peak MB": f"{res['peak_rss_bytes'] / 2**20:.0f}"}
    if res["timed_out"]:
        return row | {"note": f"timed out after {args.timeout:g} s"}
    if res["rc"] != 0:
        return row | {"note": f"exit {res['rc']}: {_last_error_line(log)}"}
    traj = out_dir / "trajectory.tum"
    if not traj.exists():
        return row | {"note": f"no {traj.name}: {_last_error_line(log)}"}
    try:
        report = json.loads((out_dir / "report.json").read_text())
        segs = report.get("segments") or []
        row |= {"segments": str(len(segs)),
                "in segs": str(sum(int(sg["num_frames_estimated"]) for sg in segs))}
        est = read_tum(traj)
        row |= _errors(est, read_tum(sim_dir / "groundtruth.tum"), n, start)
        if args.oracle:
            row |= _oracle(whole if whole is not None else simulate(_options(n, args)), start, n,
                           est.timestamps)
        return row
    except (OmniSfmError, OSError) as exc:
        return row | {"note": f"evaluation failed: {exc}"}


def _print_row(row: dict[str, str]) -> None:
    print("".join(f"{row.get(name, '-'):>{w}}" for name, w in COLUMNS)
          + (f"  {row['note']}" if "note" in row else ""), flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[1000, 5000, 20000],
                    help="sequence lengths to run (default 1000 5000 20000)")
    ap.add_argument("--timeout", type=float, default=3600.0,
                    help="seconds allowed to each init run (default 3600)")
    ap.add_argument("--noise-deg", type=float, default=0.1)
    ap.add_argument("--visible-frames", type=int, default=60)
    ap.add_argument("--line-density", type=float, default=3.5,
                    help="3D lines per metre of route (simulate --line-density)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--init-args", default="",
                    help="extra arguments for 'omni-sfm init', e.g. '--no-refine'")
    ap.add_argument("--prefixes", action="store_true",
                    help="run each length on the first frames of one walk of the longest "
                         "length (the same place; otherwise each length is a walk of its own, "
                         "and the time per frame also varies with how hard each walk is)")
    ap.add_argument("--pieces", action="store_true",
                    help="with --prefixes: also run the longest walk cut into consecutive "
                         "pieces of the shortest length (rows +START), and print the median "
                         "time per frame of the pieces against the whole run's: the same "
                         "frames, short runs against one long one")
    ap.add_argument("--oracle", action="store_true",
                    help="also print the rotation errors of the maximum-likelihood floor "
                         "(orc@500, orc@last, orc mean): the line bundle adjustment started from "
                         "the ground truth, with the families' lines held on their true "
                         "directions")
    ap.add_argument("--keep", type=Path, default=None,
                    help="keep the simulations, outputs and logs in this folder")
    ap.add_argument("--log-name", default="bench_scaling",
                    help="the record's name (docs/results.md shows bench_scaling and, for "
                         "--line-density 7 --oracle, bench_scaling_drift)")
    add_log_arguments(ap)
    args = ap.parse_args()
    if any(n < 3 for n in args.frames):
        ap.error("every --frames value must be 3 or more")
    if args.pieces and not args.prefixes:
        ap.error("--pieces needs --prefixes")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"# omni-sfm init --lines {args.init_args}".rstrip()
          + f" on Manhattan walks (0.05 m a frame, lines seen in about {args.visible_frames} "
          f"frames, {args.line_density:g} lines per metre), noise {args.noise_deg} deg, "
          f"seed {args.seed}{', each the first frames of one walk' if args.prefixes else ''}"
          f", timeout {args.timeout:g} s; "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load average "
          f"{load:.1f}, OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', '1')}")
    print("# rot@500, rot@last, rot mean: rotation error (deg) relative to the first frame; "
          "ATE: RMS after similarity alignment, % of the path length", flush=True)
    print("".join(f"{name:>{w}}" for name, w in COLUMNS), flush=True)
    with tempfile.TemporaryDirectory(prefix="bench_scaling_") as tmp:
        work = Path(tmp) if args.keep is None else args.keep
        work.mkdir(parents=True, exist_ok=True)
        whole = simulate(_options(max(args.frames), args)) if args.prefixes else None
        rows = {}
        table: list[list[str]] = []
        for n in args.frames:
            try:
                rows[n] = row = _run_one(n, args, work, whole)
            except (OmniSfmError, OSError, MemoryError) as exc:
                row = {"frames": str(n), "note": f"{type(exc).__name__}: {exc}"}
            _print_row(row)
            table.append([row.get(name, "-") for name, _ in COLUMNS] + [row.get("note", "")])
        if args.pieces:
            n, longest = min(args.frames), max(args.frames)
            per = []
            for start in range(n, longest - n + 1, n):
                try:
                    row = _run_one(n, args, work, whole, start)
                except (OmniSfmError, OSError, MemoryError) as exc:
                    row = {"frames": f"+{start}", "note": f"{type(exc).__name__}: {exc}"}
                _print_row(row)
                table.append([row.get(name, "-") for name, _ in COLUMNS] + [row.get("note", "")])
                if "ms/frame" in row and "note" not in row:
                    per.append(float(row["ms/frame"]))
            first = rows.get(n, {})
            if "ms/frame" in first and "note" not in first:
                per.append(float(first["ms/frame"]))  # the first piece is the first prefix
            whole_ms = rows.get(longest, {}).get("ms/frame", "-")
            if per:
                print(f"# pieces of {n} frames: median {np.median(per):.2f} ms per frame over "
                      f"{len(per)} pieces (range {min(per):.2f}-{max(per):.2f}); the whole "
                      f"{longest}-frame walk in one run: {whole_ms} ms per frame", flush=True)
    shown = [k for k, (name, _) in enumerate(COLUMNS)
             if any(r[k] != "-" for r in table)]  # the oracle's columns only with --oracle
    last = len(table) - 1 if not args.pieces else len(args.frames) - 1
    ms = shown.index(5) if 5 in shown else 0  # "ms/frame"
    write_log(args, args.log_name, "Simulated corridor walks of growing length",
              [COLUMNS[k][0] for k in shown] + ["note"],
              [[r[k] for k in shown] + [r[-1]] for r in table],
              headline=f"{{rows[{last}][0]}} simulated frames at {{rows[{last}][{ms}]}} ms a "
                       f"frame ({{rows[0][{ms}]}} at {{rows[0][0]}})",
              notes=f"Manhattan walks, 0.05 m a frame, lines seen in about {args.visible_frames} "
                    f"frames, {args.line_density:g} lines a metre, {args.noise_deg} deg noise; "
                    "rot@500, rot@last, rot mean: rotation error (deg) relative to the first "
                    "frame; orc: the maximum-likelihood floor's on the same frames.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
