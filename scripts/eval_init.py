"""Full-size accuracy of ``omni-sfm init --lines --images`` on rendered sequences (issue 5).

Renders (or reuses, under ``--work``) each sequence, runs the line-based initialization on its
images exactly as the command line does, and compares with the ground truth: frames estimated,
maximum and mean rotation error relative to the first frame, ATE after similarity alignment
over the path length, wall time of the front end and the estimator. Writes a Markdown table.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/eval_init.py --work /tmp/eval_init \\
        --markdown docs/results_init.md
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
    p.add_argument("--markdown", type=Path, help="write the table here")
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
               "ate_pct": 100 * err.ate_rel, "tracks": rep["num_tracks"],
               "parallel": len(rep["parallel_family"]["track_ids"]),
               "rejected": len(rep["rejected_tracks"]), "wall_s": wall,
               "front_end_ms_per_frame": res.frontend.summary()["timings_ms_per_frame_median"]}
        rows.append(row)
        print(json.dumps(row), flush=True)
    lines = ["| sequence | frames estimated | max rot. err. (deg) | mean rot. err. (deg) | "
             "ATE (% of path) | tracks / parallel / rejected | init wall time (s) |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['sequence']} | {r['estimated']}/{r['frames']} | "
                     f"{r['rot_max_deg']:.3f} | {r['rot_mean_deg']:.3f} | {r['ate_pct']:.3f} | "
                     f"{r['tracks']} / {r['parallel']} / {r['rejected']} | {r['wall_s']:.1f} |")
    table = "\n".join(lines) + "\n"
    print(table)
    if args.markdown:
        args.markdown.write_text(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
