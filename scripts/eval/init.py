"""Full-size accuracy of ``omni-sfm init --lines --images`` on rendered sequences (issue 5).

Renders (or reuses, under ``--work``) each sequence, runs the line-based initialization on its
images exactly as the command line does, and compares with the ground truth: frames estimated,
maximum and mean rotation error relative to the first frame, ATE after similarity alignment
over the path length, wall time of the front end and the estimator. Prints a Markdown table
and writes the record ``docs/benchmarks/eval_init.json`` (docs/results.md renders it).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m scripts.eval.init --work /tmp/eval_init
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from omni_sfm.evaluate import trajectory_errors
from omni_sfm.lines.frontend import FrontEndOptions
from omni_sfm.pipelines.init import InitOptions, init_from_images
from omni_sfm.poses import read_tum
from omni_sfm.synth.render import RenderOptions, render_sequence
from omni_sfm.synth.scenes import SceneName
from scripts.benchlib import add_log_arguments, write_log

SEQUENCES = {
    "corridor-hyperboloid-800x600-200f": RenderOptions(scene=SceneName.CORRIDOR,
                                                        camera="hyperboloid", frames=200),
    "corridor-equirectangular-1600x800-200f": RenderOptions(scene=SceneName.CORRIDOR,
                                                             camera="equirectangular",
                                                             frames=200),
    "room-textured-hyperboloid-800x600-100f": RenderOptions(scene=SceneName.ROOM, textured=True,
                                                             camera="hyperboloid", frames=100),
}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True, help="folder for renders and results")
    p.add_argument("--only", nargs="*", choices=sorted(SEQUENCES), help="run only these")
    add_log_arguments(p)
    args = p.parse_args()
    rows = []
    for name, opts in SEQUENCES.items():
        if args.only and name not in args.only:
            continue
        seq = args.work / name
        if not (seq / "groundtruth.tum").is_file():
            render_sequence(seq, opts, overwrite=True)
        t0 = time.perf_counter()
        res = init_from_images(seq / "images", seq / "camera.yaml", args.work / f"{name}-init",
                               InitOptions(frontend=FrontEndOptions(progress=False),
                                           debug_view="none", colmap=False, progress=False),
                               overwrite=True)
        wall = time.perf_counter() - t0
        gt = read_tum(seq / "groundtruth.tum")
        err = trajectory_errors(res.estimation.trajectory, gt)
        rep = res.estimation.report
        row = {"sequence": name, "frames": len(gt), "estimated": err.num_common,
               "rot_max_deg": err.rot_max_deg, "rot_mean_deg": err.rot_mean_deg,
               "ate_pct": 100 * err.ate_rel, "tracks": rep.num_tracks,
               "parallel": len(rep.family_track_ids),
               "rejected": len(rep.rejected_tracks or []), "wall_s": wall,
               "front_end_ms_per_frame": res.frontend.summary().timings_ms_per_frame_median}
        rows.append(row)
        print(json.dumps(row), flush=True)
    table = [[r["sequence"], f"{r['estimated']}/{r['frames']}", r["rot_max_deg"],
              r["rot_mean_deg"], r["ate_pct"],
              f"{r['tracks']} / {r['parallel']} / {r['rejected']}", r["wall_s"]] for r in rows]
    print("\n".join(" | ".join(str(c) for c in row) for row in table))
    write_log(args, "eval_init", "init --lines on rendered sequences", [
        "sequence", "frames estimated", {"label": "max rot. err. (deg)", "format": ".3f"},
        {"label": "mean rot. err. (deg)", "format": ".3f"},
        {"label": "ATE (% of path)", "format": ".3f"}, "tracks / parallel / rejected",
        {"label": "init wall time (s)", "format": ".1f"}], table,
        headline="every frame; max rotation error {rows[0][2]} deg, ATE {rows[0][4]} % "
                 "(corridor, 800x600, 200 frames, {rows[0][6]} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
