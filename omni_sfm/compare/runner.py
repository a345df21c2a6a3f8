"""Running initializers on a sequence and writing what they did (:func:`compare`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm import registry
from omni_sfm.compare.metrics import Evaluation, evaluate_trajectory
from omni_sfm.compare.plots import plot_errors, plot_trajectories
from omni_sfm.compare.report import report_markdown
from omni_sfm.errors import OmniSfmError
from omni_sfm.evaluate import associate
from omni_sfm.fileio import atomic_output_dir, atomic_write_text
from omni_sfm.folders import CompareFolder
from omni_sfm.plugin_contract import (
    InitializerResult,
    SequenceInput,
    run_initializer,
)
from omni_sfm.poses import Trajectory, write_tum
from omni_sfm.registry import INITIALIZERS
from omni_sfm.reports import (
    CompareEntry,
    CompareResults,
    CompareSequence,
    InitializerInfo,
)

DEFAULT_INITIALIZERS = ("lines", "five-point", "colmap", "upright-3pt")
"""The initializers :func:`compare` runs when none are named (those installed)."""

def known_initializers() -> list[str]:
    """Names of the installed initializers."""
    return sorted(registry.available(INITIALIZERS))


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
        results: ``results.json``.
        evaluations: the evaluation of each initializer that produced a trajectory.
    """

    output: Path
    results: CompareResults
    evaluations: dict[str, Evaluation]


def run_comparison(sequence: SequenceInput, gt: Trajectory, names: Sequence[str],
                   options: Mapping[str, Mapping[str, Any]] | None = None,
                   progress: bool = False
                   ) -> tuple[CompareResults, dict[str, Trajectory], dict[str, Evaluation]]:
    """Run and evaluate ``names`` on ``sequence`` (nothing written).

    Returns ``results`` (the ``results.json`` content, trajectory paths
    ``trajectories/NAME.tum``), the trajectories written for each initializer that has one,
    and their evaluations.
    """
    from tqdm import tqdm

    options = options or {}
    entries: dict[str, CompareEntry] = {}
    trajs: dict[str, Trajectory] = {}
    evals: dict[str, Evaluation] = {}
    for name in tqdm(names, desc="compare", unit="initializer", disable=None if progress else True):
        res, dt = run_initializer(name, sequence, options.get(name, {}))
        entry, traj, ev = _evaluated_entry(name, res, sequence, gt, dt)
        if traj is not None:
            trajs[name] = traj
        if ev is not None:
            evals[name] = ev
        entries[name] = entry
    results = CompareResults(entries, CompareSequence(name=sequence.name,
                                                      frames=sequence.num_frames,
                                                      camera=sequence.camera.model))
    return results, trajs, evals


def _reflection_nearer(traj: Trajectory, gt: Trajectory) -> tuple[Trajectory, str | None]:
    """For normals-only results: the reflection branch nearer the ground truth, and a note
    when it is the reflected one."""
    from omni_sfm.evaluate import match_reflection

    try:
        chosen = match_reflection(traj, gt)
    except OmniSfmError:
        return traj, None
    if chosen is traj:
        return traj, None
    return chosen, ("positions reflected through the first camera (normals alone cannot tell "
                    "the two branches apart; the branch nearer the ground truth is evaluated)")


def _evaluated_entry(name: str, res: InitializerResult, sequence: SequenceInput,
                     gt: Trajectory, time_s: float
                     ) -> tuple[CompareEntry, Trajectory | None, Evaluation | None]:
    """One initializer's ``results.json`` entry (it ran ``time_s``), the trajectory to write
    (None when it registered nothing) and its evaluation (None when it has none)."""
    status = res.status
    traj = res.trajectory if res.trajectory is not None and len(res.trajectory) else None
    notes = [res.reason] if res.reason else []
    ev: Evaluation | None = None
    if traj is not None:
        if res.reflection_ambiguous:
            traj, note = _reflection_nearer(traj, gt)
            notes += [note] if note else []
        try:
            ev = evaluate_trajectory(traj, gt, sequence.num_frames)
        except OmniSfmError as exc:
            status = "failed"
            notes.append(f"cannot evaluate {len(traj)} registered frames: {exc}")
    elif res.status == "ok":
        status = "failed"
        notes.append("returned no poses")
    if status == "failed" and not notes:
        notes.append("failed without a reason")
    m = None if ev is None else ev.metrics

    def metric(key: str) -> float | None:
        return None if m is None else m[key]

    entry = CompareEntry(
        status=status, reason="; ".join(notes) if notes else None,
        trajectory=None if traj is None else CompareFolder.trajectory(name),
        registered=ev.registered if ev is not None else
        0.0 if traj is None else len(traj) / sequence.num_frames,
        rot_max_deg=metric("rot_max_deg"), rot_mean_deg=metric("rot_mean_deg"),
        ate_rel=metric("ate_rel"), rpe=metric("rpe"), rpe_rot_deg=metric("rpe_rot_deg"),
        step_error_after_alignment=metric("step_error_after_alignment"),
        frames_compared=0 if m is None else int(m["frames_compared"]),
        frames_registered=0 if traj is None else len(traj), time_s=time_s,
        info=InitializerInfo.from_json(res.info, f"{name}: info") if res.info else None)
    return entry, traj, ev


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
        folder = CompareFolder(tmp)
        (folder / folder.TRAJECTORIES).mkdir()
        for name, traj in trajs.items():
            write_tum(folder / folder.trajectory(name), traj)
        results.write(folder / folder.RESULTS)
        atomic_write_text(folder / folder.REPORT_MD, report_markdown(results))
        if plots:
            plot_trajectories(folder / folder.TRAJECTORIES_PLOT, evals, gt)
            plot_errors(folder / folder.ERRORS_PLOT, evals)
    return ComparisonResult(output, results, evals)


