"""Hand-held 360 footage: a wobbling hand and people walking past (issue "Real 360 footage",
item 2; docs/frontend.md, "Automatic mask").

Renders (or reuses, under ``--work``) a hand-held walk through the textured office (route
``walk``, 10 m unless told; equirectangular, 640x320 unless told; H.264 at CRF 23 and every
effect of ``--footage``; the operator holding the camera and a person walking past), with the
operator wobbling about the camera centre by ``--wobble`` degrees per axis or rigidly fixed,
runs ``init --lines --estimator global`` on the video as the command line does, and reports:
frames estimated and flagged, rotation error relative to the first frame and ATE after
similarity alignment (all estimated frames), the worst rotation and position error of a frame
the estimator does not flag (aligned on those frames alone, as a user reads ``trajectory.tum``;
0 where fewer than 3 are left), the automatic mask's share of the hand (the body's
pixels in every frame) and of the rest, the tracks that lie on the body and on the walker (an
observation whose middle half lies mostly on it, in its frame) and what the estimator made of
the walker's tracks (rejected as outliers, left unused, or used). The wobbling walk runs twice:
with the automatic mask's wobbling edges (``init --mask-wobbling``) and without them (the
default: only edges that stay within 1 px). Prints JSON lines and
writes the record ``docs/benchmarks/eval_handheld_mask.json`` (a run's rows replace the rows
of the same image size).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.eval.handheld --work /tmp/handheld
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.pipeline import EstimationOptions
from omni_sfm.evaluate import trajectory_errors
from omni_sfm.geometry import normalize
from omni_sfm.lines.frontend import FrontEndOptions, FrontEndResult
from omni_sfm.pipelines.init import InitOptions, init_from_images
from omni_sfm.poses import read_tum
from omni_sfm.synth.effects import Body, occluder_shapes
from omni_sfm.synth.paths import Route
from omni_sfm.synth.render import (
    RenderOptions,
    RenderSetup,
    footage_options,
    prepare,
    render_sequence,
)
from omni_sfm.synth.scenes import SceneName
from scripts.benchlib import add_log_arguments, write_log


@dataclass(frozen=True)
class Case:
    name: str
    render: RenderOptions
    wobbling_edges: bool


def walk(frames: int, wobble: float, path_length: float | None, width: int, height: int
         ) -> RenderOptions:
    o = footage_options(RenderOptions(
        scene=SceneName.OFFICE, route=Route.WALK, textured=True, camera="equirectangular",
        width=width, height=height, frames=frames, path_length=path_length, video=True))
    return replace(o, effects=replace(o.effects, body=Body.OPERATOR, body_wobble_deg=wobble,
                                      occluder=True))


def cases(frames: int, wobble: float, path_length: float | None, width: int, height: int
          ) -> list[Case]:
    w = walk(frames, wobble, path_length, width, height)
    r = walk(frames, 0.0, path_length, width, height)
    size = f"{width}x{height}"
    return [Case(f"{size}, hand wobbling {wobble:g} deg, automatic mask", w, True),
            Case(f"{size}, hand wobbling {wobble:g} deg, edges within 1 px only", w, False),
            Case(f"{size}, hand rigid, automatic mask", r, True)]


def _on(fe: FrontEndResult, width: int, height: int, camera: Any,
        regions: dict[int, np.ndarray]) -> np.ndarray:
    """``(M,)`` bool: tracks with an observation whose middle half lies mostly in
    ``regions[frame]`` (``(H, W)`` bool, grown by 2 px)."""
    ends = fe.obs_endpoint_rays
    t = np.linspace(0.25, 0.75, 9)[:, None, None]
    pts = normalize((1 - t) * ends[None, :, 0] + t * ends[None, :, 1])
    uv = np.rint(camera.pixels_from_rays(pts.reshape(-1, 3))).astype(int).reshape(9, -1, 2)
    uv[..., 0] %= width
    uv[..., 1] = np.clip(uv[..., 1], 0, height - 1)
    frames = fe.frame_numbers[fe.tracks.obs_frame]
    k3 = np.ones((5, 5), np.uint8)
    grown = {f: cv2.dilate(m.astype(np.uint8), k3) > 0 for f, m in regions.items()}
    on_obs = np.zeros(len(frames), bool)
    for f in np.unique(frames):
        sel = np.flatnonzero(frames == f)
        g = grown[int(f)]
        on_obs[sel] = g[uv[:, sel, 1], uv[:, sel, 0]].mean(axis=0) > 0.5
    out = np.zeros(fe.tracks.num_tracks, bool)
    out[fe.tracks.obs_track[on_obs]] = True
    return out


def walker_pixels(setup: RenderSetup, k: int) -> np.ndarray:
    """``(H, W)`` bool: pixels of frame ``k`` whose centre ray sees the walking person."""
    r, cam = setup.renderer, setup.camera
    out = np.zeros(cam.height * cam.width, bool)
    if setup.occluder_path is None:
        return out.reshape(cam.height, cam.width)
    R, c = setup.groundtruth.rotations[k], setup.groundtruth.positions[k]
    dirs = r.centre_rays @ np.asarray(R, np.float32).T
    shapes, feet = occluder_shapes(), setup.occluder_path[k]
    cand = shapes.candidates(c, dirs, feet)
    if len(cand):
        hit = shapes.hit(c, dirs[cand], feet)
        depth = r.depth_along_rays(R, c, r.centre_rays[cand])
        out[r.pixel_index[cand[hit.t < depth]]] = True
    return out.reshape(cam.height, cam.width)


def run_case(case: Case, work: Path) -> dict[str, Any]:
    o = case.render
    seq = work / (f"walk-{o.width}x{o.height}-{o.frames}-{o.path_length}-"
                  f"{o.effects.body_wobble_deg:g}")
    if not (seq / "groundtruth.tum").is_file():
        render_sequence(seq, case.render, overwrite=True, progress=False)
    row: dict[str, Any] = {"case": case.name}
    opts = InitOptions(frontend=FrontEndOptions(progress=False),
                       estimation=EstimationOptions(estimator="global"),
                       debug_view="none", colmap=False, progress=False,
                       mask_wobbling=case.wobbling_edges)
    t0 = time.perf_counter()
    try:
        res = init_from_images(seq / "video.mp4", "equirectangular",
                               work / (seq.name + f"-init-{int(case.wobbling_edges)}"),
                               opts, overwrite=True)
    except OmniSfmError as exc:
        row.update(error=str(exc), wall_s=time.perf_counter() - t0)
        return row
    wall = time.perf_counter() - t0
    gt = read_tum(seq / "groundtruth.tum")
    rep = res.estimation.report
    err = trajectory_errors(res.estimation.trajectory, gt)
    # the frames the report does not flag (where it flags all but 2, trajectory.tum keeps
    # every frame, and the summary says to trust none)
    posed = np.flatnonzero(res.estimation.estimated)
    flagged = [int(k) for k in rep.frames_uncertain or {}]
    # their errors as a user reads trajectory.tum: aligned on them alone
    traj = res.estimation.trajectory
    kept = ~np.isin(posed, flagged)
    trusted_err = trajectory_errors(traj.subset(kept), gt) if kept.sum() >= 3 else None
    setup = prepare(case.render)
    n = len(setup.groundtruth)
    bodies = np.array([setup.renderer.body_mask(k) for k in range(n)])
    valid = setup.camera.valid_mask()
    always, anywhere = bodies.all(axis=0), bodies.any(axis=0)
    masked = _masked(res.output, setup)
    fe, cam = res.frontend, setup.camera
    on_body = _on(fe, cam.width, cam.height, cam, {k: bodies[k] for k in range(n)})
    walker = {k: walker_pixels(setup, k) for k in range(n)}
    on_walker = _on(fe, cam.width, cam.height, cam, walker)
    ids = fe.tracks.track_ids
    rejected = np.isin(ids, rep.rejected_tracks or [])
    unused = np.isin(ids, rep.unused_tracks or [])
    row.update(
        frames=n, estimated=err.num_common, flagged=len(rep.frames_uncertain or {}),
        rot_max_deg=err.rot_max_deg, rot_mean_deg=err.rot_mean_deg, ate_pct=100 * err.ate_rel,
        unflagged_rot_max_deg=0.0 if trusted_err is None else trusted_err.rot_max_deg,
        unflagged_pos_max_pct=0.0 if trusted_err is None else
        100 * float(trusted_err.pos_rel.max()),
        wall_s=wall,
        auto_mask=json.loads((res.output / "report.json").read_text())["auto_mask"]["reason"],
        hand_masked=float((masked & always).sum() / max(1, always.sum())),
        other_masked=float((masked & ~anywhere & valid).sum() / valid.sum()),
        tracks=int(fe.tracks.num_tracks), body_tracks=int(on_body.sum()),
        body_tracks_used=int((on_body & ~rejected & ~unused).sum()),
        walker_tracks=int(on_walker.sum()),
        walker_rejected=int((on_walker & rejected).sum()),
        walker_unused=int((on_walker & unused).sum()),
        walker_used=int((on_walker & ~rejected & ~unused).sum()),
        camera_fixed_dropped=len(rep.camera_fixed_tracks or []))
    return row


def _masked(init_dir: Path, setup: RenderSetup) -> np.ndarray:
    """``(H, W)`` bool: what ``init`` masked (its ``mask.png``; nothing without one)."""
    from omni_sfm.frames import read_mask

    f = init_dir / "mask.png"
    cam = setup.camera
    if not f.is_file():
        return np.zeros((cam.height, cam.width), bool)
    return ~read_mask(f, (cam.width, cam.height))


COLUMNS: list[str | dict] = [
    "case", "frames estimated", "flagged", {"label": "max rot. err. (deg)", "format": ".3f"},
    {"label": "mean rot. err. (deg)", "format": ".3f"},
    {"label": "ATE (% of path)", "format": ".3f"},
    {"label": "worst unflagged frame: rot. (deg)", "format": ".2f"},
    {"label": "worst unflagged frame: position (% of path)", "format": ".2f"},
    {"label": "hand masked", "format": ".0%"}, {"label": "rest masked", "format": ".1%"},
    "tracks on the hand (used)", "walker tracks: rejected / unused / used"]


def table(rows: list[dict[str, Any]]) -> list[list[object]]:
    out: list[list[object]] = []
    for r in rows:
        if "error" in r:
            out.append([r["case"], f"0/? (error: {r['error'][:120]})", *[None] * 10])
            continue
        out.append([r["case"], f"{r['estimated']}/{r['frames']}", r["flagged"],
                    r["rot_max_deg"], r["rot_mean_deg"], r["ate_pct"],
                    r["unflagged_rot_max_deg"], r["unflagged_pos_max_pct"], r["hand_masked"],
                    r["other_masked"], f"{r['body_tracks']} ({r['body_tracks_used']})",
                    f"{r['walker_rejected']} / {r['walker_unused']} / {r['walker_used']}"])
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True, help="folder for renders and results")
    p.add_argument("--frames", type=int, default=60, help="frames of the walk (default 60)")
    p.add_argument("--path-length", type=float, default=None,
                   help="metres walked (default: the walk route's 10 m)")
    p.add_argument("--width", type=int, default=640, help="image width (default 640)")
    p.add_argument("--height", type=int, default=320, help="image height (default 320)")
    p.add_argument("--wobble", type=float, default=1.5,
                   help="the hand's wobble, degrees per axis (default 1.5)")
    add_log_arguments(p)
    args = p.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in cases(args.frames, args.wobble, args.path_length, args.width, args.height):
        row = run_case(case, args.work)
        rows.append(row)
        print(json.dumps(row), flush=True)
    cells = table(rows)
    print("\n".join(" | ".join(str(c) for c in row) for row in cells))
    # one run per image size: its rows replace that size's rows of the record
    write_log(args, "eval_handheld_mask", "Hand-held walk: a wobbling hand and a walker", COLUMNS,
              cells, merge=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
