"""Does a walk once around a block close its loop? (issue "One global estimator": revisits)

Renders (or reuses, under ``--work``) a walk once around the ``block`` scene (an office floor
whose 2.4 m corridor runs around a block of offices) and on past its start, through each camera,
runs the line-based ``init`` on the frames exactly as the command line does, and compares with
the ground truth: frames estimated and flagged, rotation error relative to the first frame,
ATE after a similarity alignment over the path length, and where the walk passes its start
again, the relative pose of the two visits against the truth's (:func:`omni_sfm.evaluate.
revisit_errors`: the largest position error over the path length and rotation error).
Prints JSON lines and writes the record ``docs/benchmarks/eval_loop.json`` (the estimator's
defaults: revisited lines joined), or with ``--no-revisits`` (the first solution, nothing
joined) ``eval_loop_no_revisits.json``.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.eval.loop --work /tmp/loop \\
        --frames 1200 --path-length 45 [--seeds 0 1] [--no-revisits]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from omni_sfm.estimate.global_estimator import GlobalOptions  # noqa: E402
from omni_sfm.estimate.pipeline import EstimationOptions  # noqa: E402
from omni_sfm.estimate.revisits import RevisitOptions  # noqa: E402
from omni_sfm.evaluate import revisit_errors, trajectory_errors  # noqa: E402
from omni_sfm.lines.frontend import FrontEndOptions  # noqa: E402
from omni_sfm.pipelines.init import InitOptions, init_from_images  # noqa: E402
from omni_sfm.poses import read_tum  # noqa: E402
from omni_sfm.synth.effects import Effects  # noqa: E402
from omni_sfm.synth.paths import Mount, Route  # noqa: E402
from omni_sfm.synth.render import RenderOptions, render_sequence  # noqa: E402
from omni_sfm.synth.scenes import SceneName  # noqa: E402
from scripts.benchlib import add_log_arguments, write_log  # noqa: E402

CAMERAS: dict[str, tuple[str, int, int]] = {
    "hyperboloid-800x600": ("hyperboloid", 800, 600),
    "equirect-1280x640": ("equirectangular", 1280, 640),
}

FOOTAGE = Effects(motion_blur=0.5, jpeg_quality=85, exposure_drift=0.5, flicker=0.03,
                  shot_noise=3.0, vignetting=0.4)


def run(name: str, camera: str, width: int, height: int, seed: int, args: argparse.Namespace
        ) -> dict[str, Any]:
    seq = args.work / f"seed{seed}" / name
    options = RenderOptions(scene=SceneName.BLOCK, route=Route.OFFICE, mount=Mount.ROBOT,
                            camera=camera, width=width, height=height, frames=args.frames,
                            path_length=args.path_length, seed=seed,
                            effects=FOOTAGE if args.footage else Effects())
    if not (seq / "groundtruth.tum").is_file():
        render_sequence(seq, options, overwrite=True)
    t0 = time.perf_counter()
    estimation = EstimationOptions(global_=GlobalOptions(
        revisits=RevisitOptions(enabled=not args.no_revisits)))
    res = init_from_images(seq / "images", seq / "camera.yaml", seq.parent / (name + "-init"),
                           InitOptions(frontend=FrontEndOptions(progress=False),
                                       estimation=estimation, debug_view="none",
                                       colmap=False, progress=False),
                           overwrite=True)
    wall = time.perf_counter() - t0
    gt = read_tum(seq / "groundtruth.tum")
    est = res.estimation.trajectory
    err = trajectory_errors(est, gt)
    rev = revisit_errors(est, gt)
    joined = [st.joined for st in res.estimation.report.steps or [] if st.step == "revisits"]
    return {"camera": f"{name}, seed {seed}", "frames": len(gt), "estimated": err.num_common,
            "joined": joined[0] if joined else None,
            "flagged": len(res.estimation.report.frames_uncertain or {}),
            "rot_max_deg": err.rot_max_deg, "rot_mean_deg": err.rot_mean_deg,
            "ate_pct": 100 * err.ate_rel, "revisit_pairs": len(rev.pairs),
            "revisit_pos_pct": 100 * float(rev.pos_rel.max()) if len(rev.pairs) else None,
            "revisit_rot_deg": float(rev.rot_deg.max()) if len(rev.pairs) else None,
            "path_m": gt.path_length(), "wall_s": wall}


COLUMNS: list[str | dict] = [
    "camera", "frames estimated (flagged)", "tracks joined",
    {"label": "max rot. err. (deg)", "format": ".3f"},
    {"label": "ATE (% of path)", "format": ".3f"},
    {"label": "revisit: position (% of path)", "format": ".3f"},
    {"label": "revisit: rotation (deg)", "format": ".3f"},
    {"label": "init wall time (s)", "format": ".0f"}]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True, help="folder for renders and results")
    p.add_argument("--frames", type=int, default=1200)
    p.add_argument("--path-length", type=float, default=45.0)
    p.add_argument("--seeds", type=int, nargs="+", default=[0],
                   help="renders of the route (textures, noise), each through each camera")
    p.add_argument("--footage", action="store_true",
                   help="render with blur, JPEG 85, exposure drift, noise and vignetting")
    p.add_argument("--only", nargs="*", help="cameras whose name contains one of these")
    p.add_argument("--no-revisits", action="store_true",
                   help="the global estimator without its revisit step (lines seen on both "
                        "visits not joined)")
    add_log_arguments(p)
    args = p.parse_args()
    rows = []
    for seed in args.seeds:
        for name, (camera, width, height) in CAMERAS.items():
            if args.only and not any(o in name for o in args.only):
                continue
            row = run(name, camera, width, height, seed, args)
            rows.append(row)
            print(json.dumps(row), flush=True)
    cells: list[list[object]] = [
        [r["camera"], f"{r['estimated']}/{r['frames']} ({r['flagged']})", r["joined"],
         r["rot_max_deg"],
         r["ate_pct"], r["revisit_pos_pct"], r["revisit_rot_deg"], r["wall_s"]] for r in rows]
    path = rows[0]["path_m"] if rows else 0.0
    pos = max((r["revisit_pos_pct"] for r in rows if r["revisit_pos_pct"] is not None),
              default=float("nan"))
    rot = max((r["revisit_rot_deg"] for r in rows if r["revisit_rot_deg"] is not None),
              default=float("nan"))
    write_log(args, "eval_loop_no_revisits" if args.no_revisits else "eval_loop",
              "A walk once around a block and past its start"
              + (", revisits not joined" if args.no_revisits else ""), COLUMNS,
              cells, headline=f"{args.frames}-frame {path:.0f} m walk once around an office "
                              f"block and past its start ({len(rows)} runs"
                              f"{', revisits not joined' if args.no_revisits else ''}): the two "
                              f"visits within {pos:.3f} % of the path and {rot:.3f} deg")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
