"""The built-in example: a rendered texture-poor corridor, estimated from its lines alone."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from omni_sfm.evaluate import TrajectoryErrors, trajectory_errors
from omni_sfm.fileio import atomic_write_text
from omni_sfm.folders import RenderFolder
from omni_sfm.pipelines.init import InitOptions, init_from_images, plot_trajectory
from omni_sfm.poses import read_tum


@dataclass(frozen=True)
class DemoResult:
    sequence: Path
    reused: bool
    init_dir: Path
    frames: int
    estimated: int
    errors: TrajectoryErrors
    plot: Path


def run_demo(output: Path, *, camera: str = "hyperboloid", frames: int = 100,
             seed: int = 0) -> DemoResult:
    """Render ``output/sequence-...`` unless it exists with the same settings, then estimate
    its motion into ``output/init`` and compare with the ground truth."""
    from omni_sfm.synth.render import RenderOptions, render_sequence

    output = Path(output)
    opts = RenderOptions(camera=camera, frames=frames, seed=seed)
    seq = output / f"sequence-corridor-{camera}-{frames}f-seed{seed}"
    reused = (seq / RenderFolder.META).is_file() and (seq / RenderFolder.GROUNDTRUTH).is_file()
    if not reused:
        render_sequence(seq, opts, overwrite=True)
    init_dir = output / "init"
    res = init_from_images(seq / RenderFolder.IMAGES, seq / RenderFolder.CAMERA, init_dir,
                           InitOptions(), overwrite=True)
    gt = read_tum(seq / RenderFolder.GROUNDTRUTH)
    err = trajectory_errors(res.estimation.trajectory, gt)
    aligned = err.alignment.apply(res.estimation.trajectory)
    plot = init_dir / "trajectory_vs_groundtruth.png"
    plot_trajectory(plot, aligned, gt, title=(
        f"corridor, {camera}: max rotation error {err.rot_max_deg:.3f} deg, "
        f"ATE {100 * err.ate_rel:.3f} % of path"))
    atomic_write_text(init_dir / "demo_errors.json", json.dumps(err.as_dict(), indent=2) + "\n")
    return DemoResult(seq, reused, init_dir, res.frontend.tracks.num_frames,
                      int(res.estimation.estimated.sum()), err, plot)
