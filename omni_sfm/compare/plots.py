"""The plots of a comparison: trajectories over the ground truth, errors per frame."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from omni_sfm.compare.metrics import Evaluation
from omni_sfm.poses import Trajectory

COLOURS = {"lines": "tab:red", "lines-refine": "tab:purple", "five-point": "tab:blue",
           "colmap": "tab:green",
           "upright-3pt": "tab:orange"}


def _top_axes(gt: Trajectory) -> tuple[int, int]:
    """The two world axes of the ground truth's largest spread (the "top view")."""
    spread = gt.positions.std(0)
    a, b = np.argsort(spread)[::-1][:2]
    return int(min(a, b)), int(max(a, b))


def plot_trajectories(path: Path, evals: Mapping[str, Evaluation], gt: Trajectory) -> None:
    """Top view (the two axes of largest ground-truth spread) of each aligned trajectory."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    i, j = _top_axes(gt)
    fig, ax = plt.subplots(figsize=(6, 4.5), dpi=100)
    ax.plot(gt.positions[:, i], gt.positions[:, j], "k-", lw=2.5, alpha=0.4,
            label="ground truth")
    for name, ev in evals.items():
        p = ev.aligned.positions
        ax.plot(p[:, i], p[:, j], ".-", ms=3, lw=1, color=COLOURS.get(name),
                label=f"{name} (ATE {100 * ev.metrics['ate_rel']:.2f} %)")
    ax.set_xlabel(f"world {'xyz'[i]} (m)")
    ax.set_ylabel(f"world {'xyz'[j]} (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=8)
    ax.set_title("trajectories after similarity alignment (top view)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_errors(path: Path, evals: Mapping[str, Evaluation]) -> None:
    """Rotation error and aligned position error per frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(6, 5), dpi=100, sharex=True)
    for name, ev in evals.items():
        a1.plot(ev.timestamps, ev.rot_deg, ".-", ms=3, lw=1, color=COLOURS.get(name),
                label=name)
        a2.plot(ev.timestamps, 100 * ev.pos_err_rel, ".-", ms=3, lw=1, color=COLOURS.get(name),
                label=name)
    a1.set_ylabel("rotation error (deg)")
    a2.set_ylabel("position error (% of path)")
    a2.set_xlabel("frame timestamp")
    a1.legend(fontsize=8)
    a1.set_title("error per frame")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


