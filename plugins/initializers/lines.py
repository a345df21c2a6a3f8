"""``lines``: omni-sfm's line-based initialization (front end + estimator, METHOD.md).

Images go through :func:`omni_sfm.lines.frontend.track_lines` and the tracks through
:func:`omni_sfm.estimate.pipeline.estimate_poses`; a simulated sequence gives its line tracks
directly. Line normals have no sign, so the normals alone fix the camera centres only up to the
point reflection through the first camera (``omni_sfm.estimate.pipeline.reflect_positions``).
From images the ends of the observed segments decide it: the reconstructed line must lie in
front of the rays to its observed ends, not behind them (majority of the observations). From
normals alone the result says ``reflection_ambiguous`` and the comparison evaluates the branch
nearer the ground truth, saying so.

Options: ``refine`` (True: the line bundle adjustment after the paper's method).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from omni_sfm.compare import InitializerResult, SequenceInput, failed
from omni_sfm.geometry import FloatArray


def reflection_votes(result: Any, obs_track: np.ndarray, obs_frame: np.ndarray,
                     endpoint_rays: FloatArray) -> tuple[int, int]:
    """Observations whose reconstructed line lies in front of / behind its observed segment.

    For an observation with end rays ``e0, e1`` in frame ``f`` (camera centre ``c``, rotation
    ``R``), the world ray ``c + s R normalize(e0 + e1)`` meets the reconstructed line (up to
    noise, it lies in the line's plane); its parameter ``s`` at the closest approach is > 0 on
    the right branch and < 0 on the reflected one.
    """
    est = np.flatnonzero(result.estimated)
    row = np.full(len(result.estimated), -1)
    row[est] = np.arange(len(est))
    traj = result.trajectory
    d, p = result.line_directions, result.line_points
    r = row[obs_frame]
    ok = (r >= 0) & np.isfinite(d[obs_track]).all(1) & result.used_tracks[obs_track]
    if not ok.any():
        return 0, 0
    m = endpoint_rays[ok].sum(1)
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    w = np.einsum("kij,kj->ki", traj.rotations[r[ok]], m)
    c = traj.positions[r[ok]]
    dd, pp = d[obs_track[ok]], p[obs_track[ok]]
    dw = np.sum(dd * w, 1)
    q = pp - c
    with np.errstate(invalid="ignore", divide="ignore"):
        s = (np.sum(q * w, 1) - np.sum(q * dd, 1) * dw) / (1 - dw**2)
    s = s[np.isfinite(s) & (np.abs(dw) < 0.99)]
    return int((s > 0).sum()), int((s < 0).sum())


def lines(sequence: SequenceInput, options: Mapping[str, Any]) -> InitializerResult:
    """The ``lines`` initializer (module docstring)."""
    from omni_sfm.errors import OmniSfmError
    from omni_sfm.estimate.pipeline import EstimationOptions, estimate_poses, reflect_positions

    fe = None
    if sequence.images is not None:
        from omni_sfm.lines.frontend import FrontEndOptions, track_lines

        frames = ((k, float(sequence.timestamps[k]), sequence.read_gray(k))
                  for k in range(sequence.num_frames))
        fe = track_lines(frames, sequence.camera, FrontEndOptions(progress=False))
        tracks = fe.tracks
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
                            "residual_rms_deg": float(res.residual_rms_final_deg)}
    traj = res.trajectory
    if fe is None:
        return InitializerResult(traj, "ok", reflection_ambiguous=True, info=info)
    front, behind = reflection_votes(res, tracks.obs_track, tracks.obs_frame,
                                     fe.obs_endpoint_rays)
    info["reflection_votes"] = {"in_front": front, "behind": behind}
    if behind > front:
        traj = reflect_positions(traj)
    return InitializerResult(traj, "ok", reflection_ambiguous=front == behind, info=info)
