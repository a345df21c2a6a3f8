"""Benchmark of ``omni-sfm dense`` on the rendered textured room (docs/dense.md, "Speed").

Renders the room (hyperboloid 800 x 600, 100 frames, textured; ``--scene`` and ``--untextured``
change that) once into ``--render`` unless it exists, writes the true poses at an arbitrary
similarity (scale 0.37, rotated, shifted: what line-based poses look like) as a poses folder,
runs the dense pipeline with ``--known-distance`` (the true first-to-last distance) and prints
the time per keyframe of depth estimation and of fusion (medians), the whole run's wall and CPU
time, and the accuracy against the renderer's mesh after similarity alignment of the trajectory
(median distance of the dense points to the true surface relative to the mean scene depth,
completeness)::

    .venv/bin/python -m scripts.bench.dense --render /tmp/room100 --output /tmp/room100_dense
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path

import numpy as np

from omni_sfm.dense import DenseOptions, read_dense_input, run_dense
from omni_sfm.dense.evaluate import evaluate_dense
from omni_sfm.evaluate import umeyama
from omni_sfm.geometry import rotvec_to_matrix
from omni_sfm.libs import open3d_module
from omni_sfm.poses import Trajectory, read_tum, write_tum
from omni_sfm.synth.render import RenderOptions, render_sequence
from scripts.benchlib import add_log_arguments, write_log

ROTATION = rotvec_to_matrix(np.array([0.3, -0.5, 0.9]))
SHIFT = np.array([2.0, -1.0, 0.5])


def similar_poses(gt: Trajectory, scale: float) -> Trajectory:
    """``gt`` under an arbitrary similarity (fixed rotation and shift, given scale)."""
    return Trajectory(gt.timestamps.copy(), ROTATION @ gt.rotations,
                      scale * gt.positions @ ROTATION.T + SHIFT)


def similar_lines(doc: dict, scale: float) -> dict:
    """A ``lines3d.json`` document under the same similarity (for the view's 3D lines)."""
    out = dict(doc)
    out["segments"] = [{**s, **{k: (scale * ROTATION @ np.asarray(s[k]) + SHIFT).tolist()
                                for k in ("start", "end")}} for s in doc["segments"]]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--render", type=Path, default=Path("/tmp/omni_bench/room100"))
    ap.add_argument("--output", type=Path, default=Path("/tmp/omni_bench/room100_dense"))
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--width", type=int, default=800)
    ap.add_argument("--height", type=int, default=600)
    ap.add_argument("--camera", default="hyperboloid")
    ap.add_argument("--keyframe-step", type=int, default=None)
    ap.add_argument("--scene", default="room", help="room or corridor")
    ap.add_argument("--untextured", action="store_true", help="render without texture")
    add_log_arguments(ap)
    args = ap.parse_args()
    if not (args.render / "groundtruth.tum").is_file():
        t0 = time.perf_counter()
        render_sequence(args.render, RenderOptions(
            scene=args.scene, camera=args.camera, textured=not args.untextured, frames=args.frames,
            width=args.width, height=args.height), progress=True)
        print(f"rendered in {time.perf_counter() - t0:.0f} s")
    gt = read_tum(args.render / "groundtruth.tum")
    poses = args.output.with_name(args.output.name + "_poses")
    poses.mkdir(parents=True, exist_ok=True)
    write_tum(poses / "trajectory.tum", similar_poses(gt, 0.37))
    shutil.copy(args.render / "camera.yaml", poses / "camera.yaml")
    lines = json.loads((args.render / "lines3d.json").read_text())
    (poses / "lines3d.json").write_text(json.dumps(similar_lines(lines, 0.37)))
    first_last = float(np.linalg.norm(gt.positions[-1] - gt.positions[0]))
    opts = DenseOptions(known_distance=first_last, keyframe_step=args.keyframe_step)
    t0, c0 = time.perf_counter(), time.process_time()
    res = run_dense(poses, args.render / "images", args.output, opts, overwrite=True)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    r = res.report.to_json()
    sec = r["seconds"]
    print(f"frames {len(gt)}, keyframes {r['num_keyframes']} (step {r['keyframe_step']}), "
          f"views {r['views']['width']}x{r['views']['height']} f={r['views']['focal_px']:.0f}")
    print(f"depth per keyframe  (median): {sec['depth_per_keyframe']:.2f} s "
          f"(total {sec['depth_total']:.1f} s)")
    print(f"fusion per keyframe (median): {sec['fusion_per_keyframe']:.2f} s "
          f"(total {sec['fusion_total']:.1f} s)")
    print(f"calibration {sec['calibration']:.1f} s, extraction {sec['extraction']:.1f} s, "
          f"whole run incl. reading and writing {wall:.1f} s wall, {cpu:.1f} s CPU "
          f"(both cores; load average {os.getloadavg()[0]:.1f})")
    print(f"scale factor {res.scale:.4f} (true 1/0.37 = {1 / 0.37:.4f}), median depth "
          f"{res.median_depth:.2f} m, voxel {res.voxel_size * 1000:.1f} mm, depth share "
          f"median {r['depth_share']['median']:.2f} (min {r['depth_share']['min']:.2f})")
    inp = read_dense_input(poses, args.render / "images")
    sim = umeyama(res.trajectory.positions, gt.positions)
    pts = sim.apply_points(res.points)
    mesh = open3d_module().io.read_triangle_mesh(str(args.render / "scene.ply"))
    e = evaluate_dense(pts, mesh, gt, inp.camera)
    print(f"points {e.num_points}, median distance {1000 * e.median_distance:.1f} mm = "
          f"{100 * e.relative_median:.2f}% of the mean scene depth {e.mean_scene_depth:.2f} m "
          f"(p90 {1000 * e.p90_distance:.1f} mm); within {1000 * e.threshold:.0f} mm: "
          f"{100 * e.inlier_share:.0f}% of the points, completeness {100 * e.completeness:.0f}%")
    texture = "" if args.untextured else "textured "
    write_log(args, "bench_dense", "Dense map from the true poses at an arbitrary similarity", [
        "sequence", "keyframes", "points", {"label": "median distance (mm)", "format": ".1f"},
        {"label": "median / mean scene depth (%)", "format": ".2f"},
        {"label": "completeness (%)", "format": ".0f"},
        {"label": "depth per keyframe (s)", "format": ".2f"},
        {"label": "wall (s)", "format": ".0f"}, {"label": "CPU (s)", "format": ".0f"}],
        [[f"{texture}{args.scene}, {args.camera} {args.width}x{args.height}, {len(gt)} frames",
          r["num_keyframes"], e.num_points, 1000 * e.median_distance, 100 * e.relative_median,
          100 * e.completeness, sec["depth_per_keyframe"], wall, cpu]],
        headline="median distance to the true surface {rows[0][4]} % of the mean scene depth "
                 "({rows[0][0]}), {rows[0][7]} s",
        notes=f"Scale recovered from --known-distance: {res.scale:.4f} "
              f"(true 1/0.37 = {1 / 0.37:.4f}).", merge=True)


if __name__ == "__main__":
    main()
