"""Line-based against point-based initialization on the same sequence (``omni-sfm compare``).

An *initializer* is a plugin registered in the entry-point group ``omni_sfm.initializers``
(:mod:`omni_sfm.registry`): a callable ``(sequence: SequenceInput, options: dict) ->
InitializerResult`` (the contract: :mod:`omni_sfm.initializer`, docs/plugins.md). The core
never imports one by name. omni-sfm ships four (package ``omni_sfm_plugins.initializers``):
``lines``, ``five-point``, ``colmap`` and ``upright-3pt`` (docs/comparison.md).

:func:`compare` runs the chosen initializers on one sequence, evaluates each trajectory against
ground truth with :func:`omni_sfm.evaluate.trajectory_errors` and writes, into one output folder
that appears complete or not at all:

- ``results.json``: ``{"initializers": {NAME: {"status": "ok"|"failed", "reason"?,
  "trajectory": "trajectories/NAME.tum" | null, "registered": fraction of the frames,
  "rot_max_deg", "rot_mean_deg", "ate_rel", "rpe", "rpe_rot_deg", "step_error_after_alignment",
  "time_s", ...}}}``;
- ``trajectories/NAME.tum``: the poses each initializer registered (world_from_cam, TUM);
- ``report.md``: the table; ``trajectories.png`` (top view over ground truth) and
  ``errors.png`` (rotation and position error per frame).

A failure is recorded with its reason, never dropped. The figures in ``results.json`` are
exactly what :func:`evaluate_trajectory` computes from the written TUM file
(``tests/test_compare.py`` recomputes them).
"""

from __future__ import annotations

import math
import time
import traceback
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm.cameras.base import CameraModel
from omni_sfm.errors import OmniSfmError
from omni_sfm.evaluate import associate, trajectory_errors
from omni_sfm.fileio import atomic_output_dir, atomic_write_text, dumps_json, read_json
from omni_sfm.geometry import FloatArray
from omni_sfm.initializer import (  # the contract (importable from here too)
    Initializer,
    InitializerResult,
    SequenceInput,
    check_result,
    failed,
)
from omni_sfm.initializer import PointObservations as PointObservations
from omni_sfm.lines.video import FrameStore
from omni_sfm.poses import Trajectory, read_tum, write_tum
from omni_sfm.registry import INITIALIZERS, PluginError, available, load

DEFAULT_INITIALIZERS = ("lines", "five-point", "colmap", "upright-3pt")
"""The initializers :func:`compare` runs when none are named (those installed)."""

METRIC_KEYS = ("rot_max_deg", "rot_mean_deg", "ate_rel", "rpe", "rpe_rot_deg",
               "step_error_after_alignment")


def sequence_from_frames(images: Path, camera: CameraModel) -> SequenceInput:
    """Every frame of an image folder (sorted by name; timestamp = index) or a video
    (timestamps in seconds), named and stamped as ``init`` names them. One-line OmniSfmError
    when there are fewer than 3 frames or the first does not have the camera's size."""
    frames = FrameStore(images)
    if len(frames) < 3:
        raise OmniSfmError(f"{images}: {len(frames)} frames; need at least 3")
    path = Path(images)
    name = path.resolve().parent.name if path.name == "images" else path.stem
    seq = SequenceInput(frames.timestamps.copy(), camera, images=frames, name=name)
    seq.read_image(0)  # a camera for other images fails here, before any initializer runs
    return seq


def known_initializers() -> list[str]:
    """Names of the installed initializers."""
    return sorted(available(INITIALIZERS))


def parse_initializer_names(text: str | Sequence[str] | None) -> list[str]:
    """Checked initializer names from ``"a,b"`` or a list; None: the default ones installed."""
    known = known_initializers()
    if text is None:
        names = [n for n in DEFAULT_INITIALIZERS if n in known]
    else:
        items = text.split(",") if isinstance(text, str) else list(text)
        names = [n.strip() for n in items if n.strip()]
    if not names:
        raise OmniSfmError(f"no initializer named (known: {', '.join(known) or 'none'})")
    for n in names:
        if n not in known:
            raise OmniSfmError(f"unknown initializer {n!r} (known: {', '.join(known)})")
    if len(set(names)) != len(names):
        raise OmniSfmError(f"initializer named twice in {','.join(names)}")
    return names


def run_initializer(name: str, sequence: SequenceInput,
                    options: Mapping[str, Any] | None = None) -> tuple[InitializerResult, float]:
    """Run one initializer; any exception becomes a failed result with its one-line reason,
    and so does a plugin that cannot be loaded or returns what breaks the contract
    (:func:`omni_sfm.initializer.check_result`).

    Returns the result and the wall time in seconds.

    Raises:
        OmniSfmError: no initializer ``name`` is installed.
    """
    try:
        fn: Initializer = load(INITIALIZERS, name)
    except PluginError as exc:
        return failed(str(exc)), 0.0
    t0 = time.perf_counter()
    try:
        res = check_result(fn(sequence, dict(options or {})))
    except OmniSfmError as exc:
        res = failed(str(exc))
    except Exception as exc:  # a crash of one initializer must not lose the others' results
        tb = traceback.extract_tb(exc.__traceback__)
        where = f" ({Path(tb[-1].filename).name}:{tb[-1].lineno})" if tb else ""
        res = failed(f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
                     f"{where}")
    return res, time.perf_counter() - t0


@dataclass(frozen=True)
class Evaluation:
    """Errors of one trajectory against ground truth (see :mod:`omni_sfm.evaluate`).

    Attributes:
        registered: fraction of the sequence's frames in the trajectory that have ground truth.
        metrics: ``rot_max_deg``, ``rot_mean_deg``, ``ate_rel``, ``rpe`` (TUM/evo translational
            RPE over one frame, RMSE over the mean true step), ``rpe_rot_deg``,
            ``step_error_after_alignment``, ``frames_compared``.
        timestamps: ``(N,)`` the compared frames.
        rot_deg: ``(N,)`` rotation error relative to the first compared frame, degrees.
        pos_err_rel: ``(N,)`` camera-centre error after the similarity alignment, divided by
            the ground-truth path length.
        aligned: the estimate after the similarity alignment onto the ground truth.
    """

    registered: float
    metrics: dict[str, float]
    timestamps: FloatArray
    rot_deg: FloatArray
    pos_err_rel: FloatArray
    aligned: Trajectory


def evaluate_trajectory(est: Trajectory, gt: Trajectory, num_frames: int) -> Evaluation:
    """Errors of ``est`` against ``gt``; ``num_frames``: frames of the sequence.

    Raises:
        OmniSfmError: fewer than 3 frames in common with the ground truth.
    """
    e = trajectory_errors(est, gt)
    ea, ga = associate(est, gt)
    aligned = e.alignment.apply(ea)
    pos = np.linalg.norm(aligned.positions - ga.positions, axis=1) / ga.path_length()
    m = {"rot_max_deg": e.rot_max_deg, "rot_mean_deg": e.rot_mean_deg, "ate_rel": e.ate_rel,
         "rpe": e.rpe.trans_rel, "rpe_rot_deg": e.rpe.rot_mean_deg,
         "step_error_after_alignment": e.step_error_after_alignment,
         "frames_compared": e.num_common}
    return Evaluation(e.num_common / num_frames, m, ea.timestamps, e.rot_deg, pos, aligned)


def match_gt_frames(sequence: SequenceInput, gt: Trajectory, gt_name: str = "ground truth"
                    ) -> int:
    """Frames of the sequence that have a ground-truth pose; OmniSfmError when fewer than 3."""
    probe = Trajectory(sequence.timestamps.copy(),
                       np.broadcast_to(np.eye(3), (sequence.num_frames, 3, 3)).copy(),
                       np.zeros((sequence.num_frames, 3)))
    try:
        e, _ = associate(probe, gt)
    except OmniSfmError:
        raise OmniSfmError(
            f"{gt_name}: no timestamp matches a frame (frames have timestamps "
            f"{sequence.timestamps[0]:g}..{sequence.timestamps[-1]:g}, the ground truth "
            f"{gt.timestamps[0]:g}..{gt.timestamps[-1]:g})") from None
    if len(e) < 3:
        raise OmniSfmError(f"{gt_name}: only {len(e)} timestamps match a frame; need 3")
    return len(e)


@dataclass(frozen=True)
class ComparisonResult:
    """What :func:`compare` wrote.

    Attributes:
        output: the output folder.
        results: the content of ``results.json``.
        evaluations: the evaluation of each initializer that produced a trajectory.
    """

    output: Path
    results: dict[str, Any]
    evaluations: dict[str, Evaluation]


def run_comparison(sequence: SequenceInput, gt: Trajectory, names: Sequence[str],
                   options: Mapping[str, Mapping[str, Any]] | None = None,
                   progress: bool = False
                   ) -> tuple[dict[str, Any], dict[str, Trajectory], dict[str, Evaluation]]:
    """Run and evaluate ``names`` on ``sequence`` (nothing written).

    Returns ``results`` (the ``results.json`` content, trajectory paths
    ``trajectories/NAME.tum``), the trajectories written for each initializer that has one,
    and their evaluations.
    """
    from tqdm import tqdm

    options = options or {}
    entries: dict[str, Any] = {}
    trajs: dict[str, Trajectory] = {}
    evals: dict[str, Evaluation] = {}
    for name in tqdm(names, desc="compare", unit="initializer", disable=None if progress else True):
        res, dt = run_initializer(name, sequence, options.get(name, {}))
        entry: dict[str, Any] = {"status": res.status}
        traj = res.trajectory
        notes = [res.reason] if res.reason else []
        ev: Evaluation | None = None
        if traj is not None and len(traj):
            if res.reflection_ambiguous:
                from omni_sfm.estimate.pipeline import match_reflection

                try:
                    chosen = match_reflection(traj, gt)
                except OmniSfmError:
                    chosen = traj
                if chosen is not traj:
                    notes.append("positions reflected through the first camera (normals alone "
                                 "cannot tell the two branches apart; the branch nearer the "
                                 "ground truth is evaluated)")
                traj = chosen
            try:
                ev = evaluate_trajectory(traj, gt, sequence.num_frames)
            except OmniSfmError as exc:
                entry["status"] = "failed"
                notes.append(f"cannot evaluate {len(traj)} registered frames: {exc}")
        elif res.status == "ok":
            entry["status"] = "failed"
            notes.append("returned no poses")
        if entry["status"] == "failed" and not notes:
            notes.append("failed without a reason")
        if notes:
            entry["reason"] = "; ".join(notes)
        if traj is not None and len(traj):
            entry["trajectory"] = f"trajectories/{name}.tum"
            trajs[name] = traj
        else:
            entry["trajectory"] = None
        if ev is not None:
            evals[name] = ev
            entry["registered"] = ev.registered
            entry.update({k: ev.metrics[k] for k in METRIC_KEYS})
            entry["frames_compared"] = int(ev.metrics["frames_compared"])
        else:
            entry["registered"] = 0.0 if traj is None else len(traj) / sequence.num_frames
            entry.update({k: None for k in METRIC_KEYS})
            entry["frames_compared"] = 0
        entry["frames_registered"] = 0 if traj is None else len(traj)
        entry["time_s"] = dt
        if res.info:
            entry["info"] = res.info
        entries[name] = entry
    results = {"initializers": entries, "sequence": {"name": sequence.name,
                                                      "frames": sequence.num_frames,
                                                      "camera": sequence.camera.model}}
    return results, trajs, evals


def compare(sequence: SequenceInput, gt: Trajectory, output: Path,
            names: Sequence[str] | None = None, *,
            options: Mapping[str, Mapping[str, Any]] | None = None, overwrite: bool = False,
            plots: bool = True, progress: bool = False,
            inputs: tuple[Path | None, ...] = ()) -> ComparisonResult:
    """Run the initializers ``names`` on ``sequence``, evaluate and write ``output``.

    Raises:
        OmniSfmError: ground truth matching fewer than 3 frames, an unknown initializer, an
            output folder that exists and is not empty (unless ``overwrite``) or that is, holds
            or lies inside one of ``inputs``.
    """
    chosen = parse_initializer_names(names if names is None or isinstance(names, str)
                                     else list(names))
    match_gt_frames(sequence, gt)
    output = Path(output)
    with atomic_output_dir(output, overwrite=overwrite, inputs=inputs) as tmp:
        results, trajs, evals = run_comparison(sequence, gt, chosen, options, progress)
        (tmp / "trajectories").mkdir()
        for name, traj in trajs.items():
            write_tum(tmp / results["initializers"][name]["trajectory"], traj)
        atomic_write_text(tmp / "results.json", dumps_json(results))
        atomic_write_text(tmp / "report.md", report_markdown(results))
        if plots:
            plot_trajectories(tmp / "trajectories.png", evals, gt)
            plot_errors(tmp / "errors.png", evals)
    return ComparisonResult(output, results, evals)


def _fmt(x: Any, digits: int = 3, pct: bool = False) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{100 * x:.{digits}f} %" if pct else f"{x:.{digits}f}"


def table_rows(entries: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """Markdown table (header included) of the ``initializers`` entries of results.json."""
    rows = ["| initializer | status | registered | rot max (deg) | rot mean (deg) | ATE / path "
            "| RPE / step | RPE rot (deg) | time (s) |",
            "|---|---|---|---|---|---|---|---|---|"]
    for name, e in entries.items():
        rows.append(f"| {name} | {e['status']} | {_fmt(e.get('registered'), 0, pct=True)} | "
                    f"{_fmt(e.get('rot_max_deg'))} | {_fmt(e.get('rot_mean_deg'))} | "
                    f"{_fmt(e.get('ate_rel'), 2, pct=True)} | {_fmt(e.get('rpe'))} | "
                    f"{_fmt(e.get('rpe_rot_deg'))} | "
                    f"{_fmt(e.get('time_s'), 1)} |")
    return rows


def report_markdown(results: Mapping[str, Any]) -> str:
    """``report.md``: the table, the reasons of failures and notes."""
    seq = results.get("sequence", {})
    entries = results["initializers"]
    lines = [f"# Initializers on {seq.get('name', 'the sequence')}", "",
             f"{seq.get('frames', '?')} frames, camera `{seq.get('camera', '?')}`. Rotation error "
             "relative to the first frame; ATE = RMSE of camera centres after similarity "
             "alignment, over the ground-truth path length; RPE = relative pose error between "
             "consecutive frames (TUM/evo, no alignment, scale fixed): RMSE of its translation "
             "over the mean true step, mean angle of its rotation (omni_sfm.evaluate). Errors "
             "are over the registered frames.", ""]
    lines += table_rows(entries)
    notes = [f"- `{n}`: {e['reason']}" for n, e in entries.items() if e.get("reason")]
    if notes:
        lines += ["", "Notes and reasons:", "", *notes]
    lines += ["", "![trajectories](trajectories.png)", "", "![errors](errors.png)", ""]
    return "\n".join(lines)


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


def recompute_results(output: Path, gt: Trajectory, num_frames: int) -> dict[str, dict[str, Any]]:
    """The figures of ``output/results.json`` recomputed from its TUM files (for checks)."""
    res = read_json(Path(output) / "results.json")
    out: dict[str, dict[str, Any]] = {}
    for name, e in res["initializers"].items():
        if e.get("trajectory") is None or e["rot_max_deg"] is None:
            continue
        ev = evaluate_trajectory(read_tum(Path(output) / e["trajectory"]), gt, num_frames)
        out[name] = {"registered": ev.registered, **ev.metrics}
    return out
