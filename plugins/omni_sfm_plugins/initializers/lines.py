"""``lines``: omni-sfm's line-based initialization, exactly what ``omni-sfm init --lines`` runs.

Images go through :func:`omni_sfm.lines.frontend.track_lines` with ``init``'s default options,
and :meth:`~omni_sfm.lines.frontend.FrontEndResult.estimator_tracks` turns the front end's
result into the estimator's input (rays and per-normal uncertainties) as it does for ``init``;
:func:`omni_sfm.estimate.pipeline.estimate_poses` then settles the point reflection that normals
leave open from the observations' rays. A simulated sequence gives its line tracks directly;
without rays the positions are known only up to that reflection, the result says
``reflection_ambiguous`` and the comparison evaluates the branch nearer the ground truth,
saying so.

The result holds the frames ``init`` writes to ``trajectory.tum``: those the data fix, without
the ones its report lists as uncertain (``frames_uncertain``); where fewer than 3 are fixed it
fails, saying so (``init`` then writes every pose and tells the user not to trust them).

Options: ``refine`` (True: the line bundle adjustment after the paper's method).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from omni_sfm.plugin_contract import InitializerResult, SequenceInput, failed


def lines(sequence: SequenceInput, options: Mapping[str, Any]) -> InitializerResult:
    """The ``lines`` initializer (module docstring)."""
    from omni_sfm.errors import OmniSfmError
    from omni_sfm.estimate.pipeline import EstimationOptions, estimate_poses, fixed_by_data

    if sequence.images is not None:
        from omni_sfm.lines.frontend import FrontEndOptions, track_lines

        frames = ((k, float(sequence.timestamps[k]), sequence.read_gray(k))
                  for k in range(sequence.num_frames))
        fe = track_lines(frames, sequence.camera, FrontEndOptions(progress=False))
        tracks = fe.estimator_tracks(sequence.camera)
    elif sequence.line_tracks is not None:
        tracks = sequence.line_tracks
    else:
        return failed("the sequence has neither images nor line tracks")
    try:
        res = estimate_poses(tracks, EstimationOptions(refine=bool(options.get("refine", True))))
    except OmniSfmError as exc:
        return failed(str(exc), tracks=int(tracks.num_tracks))
    info: dict[str, Any] = {"tracks": int(tracks.num_tracks),
                            "parallel_tracks": int(np.count_nonzero(res.parallel)),
                            "residual_rms_deg": float(res.residual_rms_final_deg),
                            "reflection": res.report.reflection}
    # what init presents: the frames the data fix (trajectory.tum), not those it flags
    fixed = fixed_by_data(res)
    if fixed.sum() < 3:
        return failed(f"the data fix {int(fixed.sum())} of the {len(fixed)} frames it poses "
                      "(init lists the others as uncertain); need 3", **info)
    reason = "" if fixed.all() else \
        f"{int((~fixed).sum())} frames posed but uncertain (init's frames_uncertain), left out"
    return InitializerResult(res.trajectory.subset(fixed), "ok", reason,
                             reflection_ambiguous=tracks.obs_ray is None, info=info)
