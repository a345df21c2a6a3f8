"""Line-based against point-based initialization on the same sequence (``omni-sfm compare``).

An *initializer* is a plugin registered in the entry-point group ``omni_sfm.initializers``
(:mod:`omni_sfm.registry`): a callable ``(sequence: SequenceInput, options: dict) ->
InitializerResult`` (the contract: :mod:`omni_sfm.plugin_contract`, docs/plugins.md). The core
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

from omni_sfm.compare.metrics import (
    METRIC_KEYS,
    Evaluation,
    evaluate_trajectory,
    recompute_results,
)
from omni_sfm.compare.plots import COLOURS, plot_errors, plot_trajectories
from omni_sfm.compare.report import report_markdown, table_rows
from omni_sfm.compare.runner import (
    DEFAULT_INITIALIZERS,
    ComparisonResult,
    compare,
    known_initializers,
    match_gt_frames,
    parse_initializer_names,
    run_comparison,
)
from omni_sfm.plugin_contract import (  # the contract, importable from here too
    Initializer,
    InitializerResult,
    PointObservations,
    SequenceInput,
    failed,
    run_initializer,
    sequence_from_frames,
)

__all__ = [
    "COLOURS", "DEFAULT_INITIALIZERS", "METRIC_KEYS", "ComparisonResult", "Evaluation",
    "Initializer", "InitializerResult", "PointObservations", "SequenceInput", "compare",
    "evaluate_trajectory", "failed", "known_initializers", "match_gt_frames",
    "parse_initializer_names", "plot_errors", "plot_trajectories", "recompute_results",
    "report_markdown", "run_comparison", "run_initializer", "sequence_from_frames", "table_rows",
]
