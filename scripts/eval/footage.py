"""What each effect of real footage costs ``omni-sfm init --lines`` (issue "Real footage").

Renders (or reuses, under ``--work``) the office walk (scene ``office``, route ``office``: an
L-shaped corridor of 23 m with a 90 deg turn, clutter not aligned with the walls) through each
camera, clean, with each effect of real footage alone and with all of them together, runs the
line-based ``init`` on the frames exactly as the command line does (automatic mask and camera
check included), and compares with the ground truth: frames estimated, maximum and mean rotation
error relative to the first frame, ATE after similarity alignment over the path length, wall
time. Also the camera-fixed body (operator / robot) unmasked against the same run with the body
masked by hand, a turn in place, and a stop-and-go walk (drive, stop, turn 90 deg in place,
drive on). Prints JSON lines and writes the record ``docs/benchmarks/eval_footage.json``
(docs/results.md renders it).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.eval.footage --work /tmp/footage \\
        --frames 600

``--frames`` scales the sequences (600 is the issue's length; fewer frames make each step
longer, so blur and tracking get harder, not easier).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

# as the omni-sfm command does: OpenBLAS's threads on the estimator's small matrices cost 5-10x
# the time on a 2-core machine (and change the last bits); set before numpy is imported
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.pipeline import EstimationOptions
from omni_sfm.evaluate import relative_rotation_errors_deg, trajectory_errors
from omni_sfm.lines.frontend import FrontEndOptions
from omni_sfm.pipelines.init import InitOptions, init_from_images
from omni_sfm.poses import read_tum
from omni_sfm.synth.effects import Body, Effects
from omni_sfm.synth.paths import Route
from omni_sfm.synth.render import RenderOptions, prepare, render_sequence
from omni_sfm.synth.scenes import SceneName
from omni_sfm.transforms import associate
from scripts.benchlib import add_log_arguments, write_log

CAMERAS: dict[str, tuple[str, int, int]] = {
    "hyperboloid-800x600": ("hyperboloid", 800, 600),
    "equirect-1280x640": ("equirectangular", 1280, 640),
}


def body_for(camera: str) -> Body:
    """The camera-fixed body of each kind: a robot under the mirror, the operator under a 360."""
    return Body.ROBOT if camera == "hyperboloid" else Body.OPERATOR


def variants(camera: str) -> dict[str, Effects]:
    body = body_for(camera)
    return {
        "clean": Effects(),
        "motion blur 0.5": Effects(motion_blur=0.5),
        "JPEG 85": Effects(jpeg_quality=85),
        "exposure drift 0.5 stop + flicker": Effects(exposure_drift=0.5, flicker=0.03),
        "shot noise 3": Effects(shot_noise=3.0),
        "vignetting 0.4": Effects(vignetting=0.4),
        f"{body.value} (not masked)": Effects(body=body),
        "person walking by": Effects(occluder=True),
        "all: blur, JPEG 85, drift, noise, vignetting": Effects(
            motion_blur=0.5, jpeg_quality=85, exposure_drift=0.5, flicker=0.03, shot_noise=3.0,
            vignetting=0.4),
    }


@dataclass(frozen=True)
class Case:
    name: str
    render: RenderOptions
    hand_mask: bool = False


def cases(frames: int, only: list[str] | None) -> list[Case]:
    out = []
    for cam_name, (camera, width, height) in CAMERAS.items():
        base = RenderOptions(scene=SceneName.OFFICE, route=Route.OFFICE, frames=frames,
                             camera=camera, width=width, height=height)
        for name, eff in variants(camera).items():
            out.append(Case(f"{cam_name} | {name}", replace(base, effects=eff)))
        body = Effects(body=body_for(camera))
        out.append(Case(f"{cam_name} | {body.body.value}, masked by hand",
                        replace(base, effects=body), hand_mask=True))
        turn = replace(base, route=Route.TURN, frames=max(20, frames // 3))
        out.append(Case(f"{cam_name} | turn in place 120 deg", turn))
        out.append(Case(f"{cam_name} | stop-and-go: drive, stop, turn 90 deg, drive on",
                        replace(base, route=Route.STOP_AND_GO)))
    return [c for c in out if not only or any(o in c.name for o in only)]


def slug(name: str) -> str:
    return "".join(ch if ch.isalnum() else "-" for ch in name).strip("-").replace("--", "-")


def run_case(case: Case, work: Path, estimator: str = "auto") -> dict[str, Any]:
    seq = work / slug(case.name)
    if not (seq / "groundtruth.tum").is_file():
        render_sequence(seq, case.render, overwrite=True)
    images = seq / "images"
    mask = None
    if case.hand_mask:
        # the body's pixels, grown by 5 px, as a careful user would mask them
        body = prepare(case.render).renderer.body_mask()
        grown = cv2.dilate(body.astype(np.uint8), np.ones((11, 11), np.uint8)) > 0
        mask = seq.parent / (seq.name + "-mask.png")
        cv2.imwrite(str(mask), np.where(grown, 0, 255).astype(np.uint8))
    t0 = time.perf_counter()
    row: dict[str, Any] = {"case": case.name}
    try:
        res = init_from_images(images, seq / "camera.yaml", work / (seq.name + "-init"),
                               InitOptions(frontend=FrontEndOptions(progress=False),
                                           estimation=EstimationOptions(estimator=estimator),
                                           debug_view="none", colmap=False, progress=False),
                               mask=mask, overwrite=True)
    except OmniSfmError as exc:
        row.update(error=str(exc), wall_s=time.perf_counter() - t0)
        return row
    wall = time.perf_counter() - t0
    gt = read_tum(seq / "groundtruth.tum")
    est = res.estimation.trajectory
    row.update(frames=len(gt), wall_s=wall, tracks=res.estimation.report.num_tracks,
               flagged=len(res.estimation.report.frames_uncertain or {}))
    if res.estimation.report.rotation_only:  # no positions to compare
        e, g = associate(est, gt)
        rot = relative_rotation_errors_deg(e, g)
        row.update(estimated=len(e), rot_max_deg=float(rot.max()),
                   rot_mean_deg=float(rot.mean()), ate_pct=None)
        return row
    err = trajectory_errors(est, gt)
    row.update(estimated=err.num_common, rot_max_deg=err.rot_max_deg,
               rot_mean_deg=err.rot_mean_deg, ate_pct=100 * err.ate_rel)
    return row


COLUMNS: list[str | dict] = [
    "camera", "footage", "frames estimated", {"label": "max rot. err. (deg)", "format": ".3f"},
    {"label": "mean rot. err. (deg)", "format": ".3f"},
    {"label": "ATE (% of path)", "format": ".3f"}, {"label": "init wall time (s)", "format": ".0f"}]


def table(rows: list[dict[str, Any]]) -> list[list[object]]:
    """The record's rows: one per case."""
    out: list[list[object]] = []
    for r in rows:
        cam, name = r["case"].split(" | ", 1)
        if "error" in r:
            out.append([cam, name, f"0/? (error: {r['error'][:120]})", None, None, None,
                        r["wall_s"]])
            continue
        ate = "rotation only" if r["ate_pct"] is None else r["ate_pct"]
        out.append([cam, name, f"{r['estimated']}/{r['frames']}", r["rot_max_deg"],
                    r["rot_mean_deg"], ate, r["wall_s"]])
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True, help="folder for renders and results")
    p.add_argument("--frames", type=int, default=600, help="frames of the walk (default 600)")
    p.add_argument("--only", nargs="*", help="run only cases whose name contains one of these")
    p.add_argument("--estimator", choices=["auto", "paper", "global"], default="auto",
                   help="init's estimator (default auto); global writes its own record, "
                        "eval_footage_global")
    add_log_arguments(p)
    args = p.parse_args()
    rows = []
    for case in cases(args.frames, args.only):
        row = run_case(case, args.work, args.estimator)
        rows.append(row)
        print(json.dumps(row), flush=True)
    cells = table(rows)
    print("\n".join(" | ".join(str(c) for c in row) for row in cells))
    # the headline: the walk with every effect at once, through each camera
    every = [k for k, r in enumerate(cells) if str(r[1]).startswith("all:")]
    headline = "; ".join(f"{{rows[{k}][0]}}: {{rows[{k}][2]}} frames, {{rows[{k}][3]}} deg, "
                         f"{{rows[{k}][5]}} % ATE" for k in every)
    name = "eval_footage" if args.estimator == "auto" else f"eval_footage_{args.estimator}"
    write_log(args, name, "The office walk, effect by effect", COLUMNS, cells,
              headline=f"{args.frames}-frame 23 m office walk with a 90 deg turn, every effect "
                       f"of real footage at once: {headline}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
