"""``omni-sfm demo``: render (or reuse) a corridor, run ``init --lines``, print the errors."""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo", help="render a texture-poor corridor and estimate its motion from lines",
        description="Renders (or reuses) an omnidirectional corridor sequence with exact ground "
        "truth, runs 'omni-sfm init --lines' on it, prints the errors against the ground truth "
        "and writes plots. Needs no input.")
    p.add_argument("--output", type=Path, default=Path("omni-sfm-demo"),
                   help="folder for the sequence and the results (default: ./omni-sfm-demo)")
    p.add_argument("--camera", default="hyperboloid", choices=["hyperboloid", "equirectangular"],
                   help="camera of the rendered sequence (default: hyperboloid, the paper's)")
    p.add_argument("--frames", type=int, default=100, help="frames to render (default: 100)")
    p.add_argument("--seed", type=int, default=0, help="seed of path, noise (default: 0)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from omni_sfm.pipelines.demo import run_demo

    t0 = time.perf_counter()
    res = run_demo(args.output, camera=args.camera, frames=args.frames, seed=args.seed)
    e = res.errors
    print(f"sequence:   {res.sequence} ({'reused' if res.reused else 'rendered'})")
    print(f"results:    {res.init_dir}")
    print(f"estimated:  {res.estimated} of {res.frames} frames")
    print(f"rotation error (relative to the first frame): max {e.rot_max_deg:.3f} deg, "
          f"mean {e.rot_mean_deg:.3f} deg")
    print(f"ATE after similarity alignment: {100 * e.ate_rel:.3f} % of the path length")
    print(f"plots:      {res.plot}")
    print(f"            {res.init_dir / 'debug'} (tracked lines; blue: parallel family)")
    print(f"total time: {time.perf_counter() - t0:.1f} s")
    return 0
