"""Benchmark ``omni-sfm refine`` on the issue's full case: rendered textured room, hyperboloid
camera, 800 x 600, 100 frames. Prints the per-stage times and the ATE before and after.

    .venv/bin/python scripts/bench_refine.py --work /tmp/bench_refine
    .venv/bin/python scripts/bench_refine.py --work /tmp/bench_refine --features klt sift
    .venv/bin/python scripts/bench_refine.py --work /tmp/bench_corridor --scene corridor
    .venv/bin/python scripts/bench_refine.py --work /tmp/bench_refine --init LINE_INIT_DIR

Without ``--init`` the seed is the ground truth with realistic errors (0.3 deg rotation noise and
0.5 % of the path position noise, fixed seed), written as an init directory by
``omni_sfm.refine.synthetic.write_perturbed_init``; with ``--init`` an existing init directory
(e.g. from ``omni-sfm init``) of the same frames is refined instead. The rendering is reused when
``WORK/render`` exists. ``--features`` names the feature sources to compare (default: the
default source only); they run back to back on the same render and seed, each with a fresh
database, into ``WORK/refined_<source>``. The room is rendered with texture, the corridor
without (texture-poor). ATE is after a similarity alignment, relative to the path length.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from omni_sfm.evaluate import trajectory_errors
from omni_sfm.export.colmap import read_init_model
from omni_sfm.poses import read_tum
from omni_sfm.refine import RefineOptions, refine
from omni_sfm.refine.database import FEATURE_SOURCES
from omni_sfm.refine.synthetic import write_perturbed_init
from omni_sfm.synth.render import RenderOptions, render_sequence


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", type=Path, required=True, help="working folder (render reused)")
    p.add_argument("--scene", choices=["room", "corridor"], default="room")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--width", type=int, default=800)
    p.add_argument("--height", type=int, default=600)
    p.add_argument("--overlap", type=int, default=RefineOptions().overlap)
    p.add_argument("--init", type=Path, default=None,
                   help="refine this init directory instead of the perturbed ground truth")
    p.add_argument("--seed", type=int, default=0, help="seed of the perturbation")
    p.add_argument("--features", nargs="+", choices=list(FEATURE_SOURCES),
                   default=[RefineOptions().features],
                   help="feature sources to run, one after the other (default: %(default)s)")
    p.add_argument("--klt-verify", action="store_true",
                   help="KLT: run COLMAP's geometric verification on the track matches")
    args = p.parse_args()

    render = args.work / "render"
    if not (render / "groundtruth.tum").is_file():
        t0 = time.perf_counter()
        render_sequence(render, RenderOptions(scene=args.scene, camera="hyperboloid",
                                              width=args.width, height=args.height,
                                              frames=args.frames,
                                              textured=args.scene == "room"),
                        progress=sys.stderr.isatty())
        print(f"render: {time.perf_counter() - t0:.1f} s")
    gt = read_tum(render / "groundtruth.tum")
    if args.init is None:
        init_dir = args.work / "init_perturbed"
        write_perturbed_init(render, init_dir, seed=args.seed, overwrite=True)
        kind = f"ground truth perturbed by 0.3 deg / 0.5 % of the path (seed {args.seed})"
    else:
        init_dir = args.init
        kind = f"init directory {init_dir}"
    init = read_init_model(init_dir).trajectory
    scene = "textured room" if args.scene == "room" else "texture-poor corridor"
    print(f"case: {scene}, hyperboloid {args.width}x{args.height}, {len(gt)} frames, "
          f"path {gt.path_length():.2f} m; seed: {kind}")
    before = trajectory_errors(init, gt)
    for features in args.features:
        t0 = time.perf_counter()
        res = refine(init_dir, render / "images", args.work / f"refined_{features}",
                     RefineOptions(overlap=args.overlap, features=features,
                                   klt_verify=args.klt_verify), overwrite=True,
                     progress=sys.stderr.isatty())
        total = time.perf_counter() - t0
        r = res.report
        after = trajectory_errors(res.trajectory, gt)
        ba = r["bundle_adjustment"].get("rounds") or [{}]
        f = r["features"]
        tracks = f" on {f['tracks']} tracks" if "tracks" in f else ""
        print(f"--- features: {features}")
        print(f"frames: {len(init)} seeded, {r['refined_frames']} refined, "
              f"{len(r['kept_frames'])} kept ({r['kept_input_for_all'] or 'per frame'})")
        print(f"features: {f['keypoints']} keypoints{tracks}; matching: "
              f"{r['matching']['verified_pairs']} verified pairs, "
              f"{r['matching']['inlier_matches']} inlier matches")
        print(f"points: {r['model']['points']}, observations: {r['model']['observations']}, "
              f"mean reprojection error: triangulated "
              f"{r['triangulation']['mean_reprojection_error_px']:.3f} px -> after BA "
              f"{ba[-1].get('mean_reprojection_error_after_px', float('nan')):.3f} px")
        print("stage times (s): " + json.dumps(r["timings_s"]) + f"; total {total:.1f} s")
        print(f"ATE / path length: before {100 * before.ate_rel:.3f} %  after "
              f"{100 * after.ate_rel:.3f} %")
        print(f"mean rotation error (deg): before {before.rot_mean_deg:.3f}  after "
              f"{after.rot_mean_deg:.3f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
