#!/usr/bin/env python
"""A real-footage check anyone can run: omni-sfm's ``init --lines`` and COLMAP's SfM on the
same frames, without ground truth (docs/comparison.md, "Checking real footage").

    .venv/bin/python scripts/check_footage.py --images walk.mp4 --camera equirectangular \\
        --output check/ [--start S --end E --step K] [--colmap-threads N]

Runs, on the frames of ``--images`` (an image folder or a video; with ``--start/--end/--step``
the chosen frames are first written to ``OUTPUT/frames/`` as PNGs named by their frame number,
so that both methods see exactly those):

1. ``omni-sfm init --lines`` as a user types it, in a fresh process (``--quiet --debug-view
   none --no-colmap``, plus any ``--init-arg``), into ``OUTPUT/init/``;
2. COLMAP's incremental SfM through omni-sfm's ``colmap`` initializer (the exact camera model,
   COLMAP SIFT, sequential matching, intrinsics fixed; ``init --initializer colmap``) into
   ``OUTPUT/colmap/``; ``--colmap-from DIR`` reuses such a folder (COLMAP takes long on long
   clips), ``--no-colmap`` skips it.

and reports, as a table on stdout and in ``OUTPUT/check.json``: frames posed by each, frames
``init`` flagged as uncertain (read from its ``report.json`` where it writes such flags, under
one of :data:`UNCERTAIN_KEYS`; "n/a" otherwise), the wall time of each, and their agreement on
the frames both posed: the rotation difference after aligning the rotation gauge (the chordal
mean of the per-frame differences, :func:`omni_sfm.transforms.similarity_from_poses`) and the
position difference after a similarity (Umeyama) alignment of init's centres onto COLMAP's
(:func:`omni_sfm.evaluate.trajectory_errors`), in % of COLMAP's path length, with the frames
that disagree most. Where ``init`` flags frames, the agreement is also given on its trusted
frames alone. ``--groundtruth GT.tum`` (renders) adds each method's errors against the truth.

Neither result is the truth: where the two agree to a fraction of a degree, both are likely
right; where they disagree, look at the frames named (and at init's debug view).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
UNCERTAIN_KEYS = ("frames_uncertain", "uncertain_frames", "frames_flagged",
                  "frames_uncertain_names")
"""Keys of ``report.json`` read as init's per-frame uncertainty flags (a list of frame names or
of ``{"name": ..., "reason": ...}`` entries, or a mapping name -> reason)."""
WORST = 5
"""Frames named in the table as those that disagree most."""


def frame_selection(images: Path, start: int, end: int | None, step: int, out: Path) -> Path:
    """``images`` itself when every frame is used, else the chosen frames written to
    ``out`` as ``NNNNNN.png`` (NNNNNN: their frame number in ``images``)."""
    import cv2

    from omni_sfm.frames import read_frames, video_frame_name

    if (start, end, step) == (0, None, 1):
        return images
    out.mkdir(parents=True)
    n = 0
    for frame in read_frames(images, start, end, step):
        cv2.imwrite(str(out / video_frame_name(frame.number)), frame.image)
        n += 1
    if n < 3:
        raise SystemExit(f"check_footage: {n} frames chosen; need at least 3")
    return out


def uncertain_frames(report: dict[str, Any]) -> tuple[str | None, list[str] | None,
                                                      dict[str, str]]:
    """``(key, names, reasons)``: where init's report flags frames as uncertain, the key, the
    flagged frame names and their reasons; ``(None, None, {})`` when it has no such key."""
    for key in UNCERTAIN_KEYS:
        if key not in report:
            continue
        val = report[key]
        reasons: dict[str, str] = {}
        if isinstance(val, dict) and not {"names", "frames"} & set(val):
            reasons = {str(k): str(v) for k, v in val.items()}
            return key, list(reasons), reasons
        if isinstance(val, dict):  # {"names": [...], ...} or {"frames": [...]}
            val = val.get("names", val.get("frames"))
        if isinstance(val, int | float):
            return key, None, {}
        names = []
        for item in val or []:
            if isinstance(item, dict):
                name = str(item.get("name", item.get("frame", item.get("image", ""))))
                reasons[name] = str(item.get("reason", ""))
                names.append(name)
            else:
                names.append(str(item))
        return key, names, reasons
    return None, None, {}


def _flags_by_name(lines: dict[str, Any], frame_names: Sequence[str]) -> None:
    """init's report keys its flags by frame index: name them as the frames are named."""
    flagged = lines.get("uncertain")
    if not flagged or set(flagged) & set(frame_names) or \
            not all(str(k).isdigit() and int(k) < len(frame_names) for k in flagged):
        return
    lines["uncertain"] = [frame_names[int(k)] for k in flagged]
    lines["uncertain_reasons"] = {frame_names[int(k)]: v
                                  for k, v in lines.get("uncertain_reasons", {}).items()}


def _with_uncertain(traj: Any, path: Path) -> Any:
    """init's poses with those of the frames it flags (kept apart in ``trajectory_uncertain.
    tum`` beside ``path`` unless ``--keep-uncertain``): the check judges every pose it gave."""
    from omni_sfm.folders import UNCERTAIN_FILE
    from omni_sfm.poses import Trajectory, read_tum

    extra = path.parent / UNCERTAIN_FILE
    if not extra.is_file():
        return traj
    more = read_tum(extra)
    order = np.argsort(np.concatenate([traj.timestamps, more.timestamps]), kind="stable")
    return Trajectory(np.concatenate([traj.timestamps, more.timestamps])[order],
                      np.concatenate([traj.rotations, more.rotations])[order],
                      np.concatenate([traj.positions, more.positions])[order])


def run_init(images: Path, camera: str | None, out: Path, extra: list[str]) -> dict[str, Any]:
    """``omni-sfm init --lines`` in a fresh process: status, time and what its folder says."""
    cmd = [sys.executable, "-m", "omni_sfm", "init", "--lines", "--images", str(images),
           *(["--camera", camera] if camera is not None else []),
           "--output", str(out), "--quiet", "--debug-view", "none", "--no-colmap", *extra]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    res: dict[str, Any] = {"command": " ".join(["omni-sfm", *cmd[3:]]), "time_s": wall,
                           "stdout": proc.stdout.strip().splitlines(),
                           "stderr": proc.stderr.strip().splitlines()}
    if proc.returncode != 0:
        errs = [ln for ln in res["stderr"] if ln.startswith("omni-sfm: error")]
        res.update(status="failed", reason=(errs or res["stderr"] or ["?"])[-1])
        return res
    from omni_sfm.folders import InitFolder

    typed = InitFolder(out).read_report()
    report = typed.to_json()
    key, names, reasons = uncertain_frames(report)
    segs = typed.segment_list
    res.update(status="ok", trajectory=str(out / "trajectory.tum"),
               segments_frames=int(sum(int(s.num_frames_estimated) for s in segs)),
               uncertain_key=key, uncertain=names, uncertain_reasons=reasons,
               uncertain_count=(len(names) if names is not None else
                                report.get(key) if key else None),
               warnings=report.get("warnings", []))
    return res


def run_colmap(images: Path, camera: Any, out: Path, options: dict[str, Any]) -> dict[str, Any]:
    """COLMAP's SfM on the frames (the ``colmap`` initializer, as ``init --initializer``)."""
    from omni_sfm.errors import OmniSfmError
    from omni_sfm.pipelines.init import init_with_initializer

    t0 = time.perf_counter()
    try:
        init_with_initializer(images, camera, out, "colmap", options=options)
    except OmniSfmError as exc:
        return {"status": "failed", "reason": str(exc), "time_s": time.perf_counter() - t0}
    return colmap_folder(out, time.perf_counter() - t0)


def colmap_folder(folder: Path, wall: float | None = None) -> dict[str, Any]:
    """What a ``colmap`` init folder holds (its time: ``wall``, else its report's)."""
    from omni_sfm.folders import StageFolder

    # a colmap init folder, or a reference made by hand: a report with what it has
    report = StageFolder(folder).read_stage_report()
    doc = {} if report is None else report.other
    return {"status": "ok", "trajectory": str(folder / "trajectory.tum"),
            "time_s": wall if wall is not None else
            (doc.get("wall_time_s") or {}).get("initializer"),
            "reason": doc.get("reason", ""), "info": doc.get("info", {})}


def agreement(lines: Any, colmap: Any, names: dict[float, str],
              keep: set[str] | None = None) -> dict[str, Any]:
    """How far init's poses are from COLMAP's on the frames both posed (``keep``: only those
    names): rotation after the gauge alignment, position after a similarity alignment."""
    from omni_sfm.errors import OmniSfmError
    from omni_sfm.evaluate import trajectory_errors
    from omni_sfm.geometry import rotation_angle
    from omni_sfm.transforms import associate, similarity_from_poses

    try:
        a, b = associate(lines, colmap)
    except OmniSfmError as exc:
        return {"frames_compared": 0, "reason": str(exc)}
    if keep is not None:
        pick = np.flatnonzero([_name(names, t) in keep for t in a.timestamps])
        a, b = a.subset(pick), b.subset(pick)
    out: dict[str, Any] = {"frames_compared": len(a)}
    if len(a) < 3:
        out["reason"] = f"{len(a)} frames posed by both; need 3"
        return out
    gauge = similarity_from_poses(b.rotations, b.positions, a.rotations, a.positions,
                                  allow_reflection=False).rotation
    rot = np.degrees(rotation_angle(np.swapaxes(b.rotations, -1, -2) @ gauge @ a.rotations))
    out["rotation_deg"] = {"mean": float(rot.mean()), "median": float(np.median(rot)),
                           "max": float(rot.max())}
    per: list[dict[str, Any]] = [{"name": _name(names, t), "rotation_deg": float(r)}
                                 for t, r in zip(a.timestamps, rot, strict=True)]
    try:
        err = trajectory_errors(a, b)  # Umeyama of init's centres onto COLMAP's
    except OmniSfmError as exc:  # COLMAP's path has no length (the camera only turned)
        out["position_reason"] = str(exc)
    else:
        aligned = err.alignment.apply(a)
        dist = np.linalg.norm(aligned.positions - b.positions, axis=1) / b.path_length()
        out["position_pct_of_path"] = {"rmse": 100 * err.ate_rel,
                                       "max": float(100 * dist.max())}
        for entry, d in zip(per, dist, strict=True):
            entry["position_pct_of_path"] = float(100 * d)
    out["worst_rotation"] = sorted(per, key=lambda e: -float(e["rotation_deg"]))[:WORST]
    out["per_frame"] = per
    return out


def _name(names: dict[float, str], t: float) -> str:
    if t in names:
        return names[t]
    keys = np.fromiter(names, float)
    k = float(keys[np.argmin(np.abs(keys - t))]) if keys.size else t
    return names.get(k, f"t={t:g}")


def truth(traj: Any, gt_path: Path, flagged: set[float] | None = None) -> dict[str, Any]:
    """The errors against the ground truth; with ``flagged`` (the timestamps of the frames
    init flags as uncertain) also how honest the flags are: the flagged frames that are within
    0.2 deg and 0.2 % of the path anyway, and the frames off by more than 1 deg or 2 % that
    are not flagged."""
    from omni_sfm.errors import OmniSfmError
    from omni_sfm.evaluate import trajectory_errors
    from omni_sfm.poses import read_tum

    try:
        e = trajectory_errors(traj, read_tum(gt_path))
    except OmniSfmError as exc:
        return {"reason": str(exc)}
    out = {"frames_compared": e.num_common, "rot_max_deg": e.rot_max_deg,
           "rot_mean_deg": e.rot_mean_deg, "ate_pct_of_path": 100 * e.ate_rel}
    if flagged is not None:
        times = np.fromiter(flagged, float)
        hit = np.array([times.size > 0 and float(np.min(np.abs(times - t))) < 1e-6
                        for t in e.timestamps], bool)
        fine = (e.rot_deg < 0.2) & (100 * e.pos_rel < 0.2)
        off = (e.rot_deg > 1.0) | (100 * e.pos_rel > 2.0)
        out.update(flagged_but_fine=int((hit & fine).sum()),
                   off_not_flagged=int((off & ~hit).sum()))
    return out


def table(res: dict[str, Any]) -> str:
    """The check as text: one row per method, then the agreement."""
    n = res["frames"]
    rows = [("method", "frames posed", "uncertain", "time"), ]
    li, co = res["lines"], res["colmap"]
    for label, r in (("init --lines", li), ("COLMAP", co)):
        if r.get("status") == "skipped":
            rows.append((label, "skipped", "", ""))
            continue
        time_s = "?" if r.get("time_s") is None else f"{r['time_s']:.1f} s"
        if r["status"] != "ok":
            rows.append((label, "failed", "", time_s))
            continue
        posed = f"{r['posed']} of {n}"
        if r.get("segments_frames"):
            posed += f" (+{r['segments_frames']} in segments)"
        unc = "-" if label == "COLMAP" else (
            "n/a (no flags in report.json)" if li.get("uncertain_key") is None
            else str(li.get("uncertain_count")))
        rows.append((label, posed, unc, time_s))
    w = [max(len(r[i]) for r in rows) for i in range(4)]
    lines = ["  ".join(c.ljust(w[i]) for i, c in enumerate(r)).rstrip() for r in rows]
    for label, r in (("init --lines", li), ("COLMAP", co)):
        if r.get("status") == "failed":
            lines.append(f"{label} failed: {r['reason']}")
    for key, title in (("agreement", "agreement"),
                       ("agreement_trusted", "agreement on init's trusted frames")):
        ag = res.get(key)
        if not ag:
            continue
        if "rotation_deg" not in ag:
            lines.append(f"{title}: n/a ({ag.get('reason', '')})")
            continue
        r = ag["rotation_deg"]
        text = (f"{title} on {ag['frames_compared']} frames: rotation (gauge aligned) mean "
                f"{r['mean']:.3f}, median {r['median']:.3f}, max {r['max']:.3f} deg")
        p = ag.get("position_pct_of_path")
        text += (f"; position (similarity aligned) RMSE {p['rmse']:.2f} %, max {p['max']:.2f} "
                 "% of COLMAP's path" if p else f"; position: n/a ({ag['position_reason']})")
        lines.append(text)
        if key == "agreement":
            lines.append("largest rotation differences: " + ", ".join(
                f"{e['name']} {e['rotation_deg']:.2f} deg" for e in ag["worst_rotation"]))
    for label, key in (("init --lines", "lines"), ("COLMAP", "colmap")):
        t = res[key].get("groundtruth")
        if t and "rot_max_deg" in t:
            lines.append(f"{label} against the ground truth: rotation max {t['rot_max_deg']:.3f}"
                         f" deg, mean {t['rot_mean_deg']:.3f} deg, ATE {t['ate_pct_of_path']:.3f}"
                         " % of the path")
        if t and "flagged_but_fine" in t:
            lines.append(f"{label} flags against the ground truth: {t['flagged_but_fine']} "
                         "flagged frames within 0.2 deg and 0.2 % of the path; "
                         f"{t['off_not_flagged']} frames off by more than 1 deg or 2 % not "
                         "flagged")
    return "\n".join(lines)


def _parser() -> argparse.ArgumentParser:
    """The command line's arguments."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=Path, required=True, help="image folder or video")
    ap.add_argument("--camera", default=None,
                    help="camera file or 'equirectangular' (default: the video's spherical "
                         "metadata, as init reads it)")
    ap.add_argument("--output", "-o", type=Path, required=True, help="output folder")
    ap.add_argument("--overwrite", action="store_true", help="replace a non-empty OUTPUT")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--end", type=int, default=None)
    ap.add_argument("--step", type=int, default=1)
    ap.add_argument("--init-arg", action="append", default=[], metavar="ARG",
                    help="one more argument for init (repeat; e.g. --init-arg=--workers=2)")
    ap.add_argument("--no-colmap", action="store_true", help="skip COLMAP")
    ap.add_argument("--colmap-from", type=Path, default=None, metavar="DIR",
                    help="reuse COLMAP's poses from an earlier check's colmap/ folder (or an "
                         "'init --initializer colmap' folder) of the same frames")
    ap.add_argument("--colmap-threads", type=int, default=1)
    ap.add_argument("--max-features", type=int, default=4000)
    ap.add_argument("--overlap", type=int, default=10, help="COLMAP's sequential overlap")
    ap.add_argument("--groundtruth", type=Path, default=None,
                    help="ground truth TUM (renders): adds each method's errors")
    ap.add_argument("--record", default=None, metavar="NAME",
                    help="with --groundtruth: add init's figures as the row --label of the "
                         "record docs/benchmarks/NAME.json (python -m scripts.render_results "
                         "renders it into the docs)")
    ap.add_argument("--label", default=None, help="the record's row label (default: --images)")
    ap.add_argument("--log-dir", type=Path, default=Path(__file__).resolve().parent.parent
                    / "docs" / "benchmarks", help="folder of the record")
    return ap


def _record(args: argparse.Namespace, res: dict[str, Any]) -> None:
    """Add init's figures against the truth as one row of the record ``args.record``."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from scripts.benchlib import write_log

    li = res["lines"]
    t = li.get("groundtruth") or {}
    if li.get("status") != "ok" or "rot_max_deg" not in t:
        raise SystemExit(f"check_footage: no figures to record ({li.get('reason', 'no truth')})")
    extra = " ".join(args.init_arg) or "(defaults)"
    posed = f"{li['posed']}/{res['frames']}"
    if li.get("segments_frames"):
        posed += f" (+{li['segments_frames']} in segments)"
    flagged = li.get("uncertain")
    row = [args.label or str(args.images), extra, posed,
           "n/a" if flagged is None else len(flagged),
           t.get("flagged_but_fine", "n/a"), t.get("off_not_flagged", "n/a"),
           t["rot_mean_deg"], t["rot_max_deg"], t["ate_pct_of_path"], li["time_s"]]
    write_log(args, args.record, "init on footage against its ground truth", [
        "footage", "init arguments", "frames posed", "flagged",
        "flagged, within 0.2 deg and 0.2 %", "off by > 1 deg or 2 %, not flagged",
        {"label": "rotation mean (deg)", "format": ".3f"},
        {"label": "rotation max (deg)", "format": ".3f"}, {"label": "ATE (%)", "format": ".2f"},
        {"label": "time (s)", "format": ".1f"}], [row], merge=True,
        headline="{rows[0][0]}: {rows[0][2]} frames posed, {rows[0][3]} flagged, {rows[0][5]} "
                 "off by more than 1 deg or 2 % and not flagged; ATE {rows[0][8]} %")


def _fresh_output(out: Path, overwrite: bool) -> None:
    """Make ``out`` an empty folder (a non-empty one only with ``overwrite``)."""
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise SystemExit(f"check_footage: {out} is not empty (--overwrite to replace it)")
        import shutil

        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)

    from omni_sfm.errors import OmniSfmError
    from omni_sfm.fileio import dumps_json
    from omni_sfm.frames import FrameStore
    from omni_sfm.lines.source_camera import camera_for_frames
    from omni_sfm.poses import read_tum

    out: Path = args.output
    _fresh_output(out, args.overwrite)
    try:
        camera = camera_for_frames(args.camera, args.images,
                                   note=lambda t: print(f"note: {t}", file=sys.stderr))
        images = frame_selection(args.images, args.start, args.end, args.step, out / "frames")
        store = FrameStore(images)
    except OmniSfmError as exc:
        raise SystemExit(f"check_footage: {exc}") from None
    names = {float(t): n for t, n in zip(store.timestamps, store.names, strict=True)}
    res: dict[str, Any] = {"images": str(args.images), "frames_used": str(images),
                           "camera": args.camera or camera.model,
                           "camera_size": [camera.width, camera.height], "frames": len(store)}
    print(f"check_footage: {len(store)} frames of {args.images}, init --lines ...",
          file=sys.stderr, flush=True)
    # the frames written out lose a video's spherical metadata, which only ever means this
    init_camera = args.camera if args.camera is not None or images == args.images \
        else "equirectangular"
    res["lines"] = run_init(images, init_camera, out / "init", args.init_arg)
    _flags_by_name(res["lines"], store.names)
    if args.no_colmap:
        res["colmap"] = {"status": "skipped"}
    elif args.colmap_from is not None:
        res["colmap"] = colmap_folder(args.colmap_from)
        res["colmap"]["reused"] = str(args.colmap_from)
    else:
        print("check_footage: COLMAP ...", file=sys.stderr, flush=True)
        res["colmap"] = run_colmap(images, camera, out / "colmap",
                                   {"threads": args.colmap_threads,
                                    "max_features": args.max_features, "overlap": args.overlap})
    trajs = {}
    for key in ("lines", "colmap"):
        r = res[key]
        if r.get("status") == "ok":
            trajs[key] = _with_uncertain(read_tum(Path(r["trajectory"])), Path(r["trajectory"]))
            r["posed"] = len(trajs[key])
            if args.groundtruth is not None:
                flagged = res["lines"].get("uncertain") if key == "lines" else None
                times = None if flagged is None else \
                    {t for t, n in names.items() if n in set(flagged)}
                r["groundtruth"] = truth(trajs[key], args.groundtruth, times)
    if len(trajs) == 2:
        res["agreement"] = agreement(trajs["lines"], trajs["colmap"], names)
        flagged = res["lines"].get("uncertain")
        if flagged:
            trusted = set(names.values()) - set(flagged)
            res["agreement_trusted"] = agreement(trajs["lines"], trajs["colmap"], names,
                                                 keep=trusted)
    text = table(res)
    res["table"] = text.splitlines()
    (out / "check.json").write_text(dumps_json(res))
    if args.record:
        _record(args, res)
    print(text)
    print(f"wrote {out / 'check.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
