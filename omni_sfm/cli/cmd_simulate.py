"""``omni-sfm simulate``: simulated line tracks with exact ground truth (the paper's Sec. VII)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="simulate tracked line observations with ground truth",
        description="Simulate a camera path, P parallel and Q other 3D lines and their observed "
                    "normals (NVs); or, with --world manhattan, a long walk through office "
                    "corridors with lines in the three Manhattan directions, each seen while "
                    "the camera passes it (the vertical ones are the parallel family). Writes "
                    "OUTPUT/tracks.json, OUTPUT/groundtruth.tum (TUM, world_from_cam, world = "
                    "first camera) and OUTPUT/lines.json (true lines).",
    )
    p.add_argument("--output", type=Path, required=True, help="output folder (must be new/empty)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.add_argument("--world", choices=["random", "manhattan"], default="random",
                   help="random: the paper's set-up, P parallel and Q random lines near a smooth "
                        "path (the default); manhattan: a corridor walk with 90 deg turns, "
                        "2-20 lines a frame (--path-length in metres, --parallel and --other "
                        "not used; docs/formats.md)")
    p.add_argument("--views", type=int, default=20, help="number of views (default 20)")
    p.add_argument("--parallel", type=int, default=20, help="parallel lines (default 20)")
    p.add_argument("--other", type=int, default=20, help="non-parallel lines (default 20)")
    p.add_argument("--noise-deg", type=float, default=0.0,
                   help="std-dev of the angular noise on the normals, degrees (default 0)")
    p.add_argument("--outliers", type=float, default=0.0,
                   help="fraction of tracks with a wrong correspondence (default 0)")
    p.add_argument("--visible-frames", type=int, default=None,
                   help="each line seen in only about this many consecutive frames "
                        "(default: every line in every frame; manhattan: 60)")
    p.add_argument("--path-length", type=float, default=None,
                   help="approximate length of the camera path (default 1); manhattan: the "
                        "route length in metres (default 0.05 m a frame, a walk filmed at "
                        "30 fps)")
    p.add_argument("--line-density", type=float, default=3.5,
                   help="manhattan: lines per metre of route (default 3.5)")
    p.add_argument("--sparse", action="store_true",
                   help="random: generate only the visible observations (for long sequences "
                        "with --visible-frames; other noise draws than without it)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from omni_sfm.fileio import atomic_output_dir
    from omni_sfm.synth.simulate import SimulationOptions, simulate, write_simulation

    length = args.path_length
    if length is None:
        length = 0.05 * (args.views - 1) if args.world == "manhattan" else 1.0
    opts = SimulationOptions(num_views=args.views, num_parallel=args.parallel,
                             num_other=args.other, noise_deg=args.noise_deg,
                             outlier_fraction=args.outliers, visible_frames=args.visible_frames,
                             path_length=length, seed=args.seed, world=args.world,
                             sparse=args.sparse, line_density=args.line_density)
    sim = simulate(opts)
    with atomic_output_dir(args.output, overwrite=args.overwrite) as tmp:
        write_simulation(tmp, sim, opts)
    print(f"wrote {args.output}: {sim.tracks.num_frames} frames, {sim.tracks.num_tracks} tracks, "
          f"{sim.tracks.num_observations} observations")
    return 0
