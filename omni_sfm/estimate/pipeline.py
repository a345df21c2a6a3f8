"""The line-based estimator: tracks -> poses of all estimable frames, and a report.

Two estimators, one entry point (:func:`estimate_poses`); :func:`chosen_estimator` picks one
from which lines each frame sees (docs/estimator.md, "Which estimator runs"):

- **paper**: where one window covers the sequence (a vanishing point in every frame, at least
  3 lines of the parallel family and 3 others seen in every frame: the paper's setting), the
  paper's method on that window (:func:`~omni_sfm.estimate.paper.estimate_paper`), then the
  line bundle adjustment with outlier rejection from its solution and its distinct alternative
  starts, the lowest final cost kept (the maximum-likelihood criterion).
- **global**: anywhere else, the global estimator
  (:func:`~omni_sfm.estimate.global_estimator.solve_global`: rotations of all frames at once,
  positions of all frames at once, one robust bundle adjustment, flags). Parts of the sequence
  with nothing in common (no line seen on both sides of a frame: two videos one after the
  other) are solved each on its own: the part that poses most frames is the main trajectory,
  the others are segments in worlds and scales of their own.

A camera that only turned gets the rotation-only fit (docs/method.md §13) from either.
:func:`write_init_outputs` writes the documented artifacts (``trajectory.tum``,
``report.json``, docs/formats.md) for every input mode of ``omni-sfm init``.

Conventions of the result: world = the camera of the first estimated frame (frame 0 whenever it
is estimated), poses world_from_cam, and the scale set so that the distance between the first
and the last estimated camera is 1 (the paper's convention, Sec. VII).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from omni_sfm import __version__
from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.attempts import Attempt, Outcome, RunLog, failed
from omni_sfm.estimate.bundle import (
    BundleOptions,
    BundleResult,
    bundle_adjust,
    observation_residuals,
    scatter_rows,
    side_votes,
    triangulate_lines,
)
from omni_sfm.estimate.global_estimator import (
    GlobalOptions,
    GlobalSolution,
    settings,
    solve_global,
)
from omni_sfm.estimate.paper import PaperOptions, PaperSolution, estimate_paper
from omni_sfm.estimate.rotation_only import (
    RotationOnlyOptions,
    RotationOnlyResult,
    estimate_rotation_only,
)
from omni_sfm.estimate.segments import frame_range
from omni_sfm.estimate.windows import Window, max_rotation_step_deg, window_family, window_tracks
from omni_sfm.folders import REPORT_FILE, TRAJECTORY_FILE, UNCERTAIN_FILE
from omni_sfm.geometry import FloatArray
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.poses import Trajectory, write_tum
from omni_sfm.reports import (
    FamiliesFound,
    FamilyReport,
    InitMotion,
    InitReport,
    InitResiduals,
    InitSegment,
    PoseSpreadRecord,
    RigScaleRecord,
)
from omni_sfm.vanishing import (
    ParallelFamily,
    VanishingOptions,
    detect_parallel_families,
    detect_parallel_family,
)

SCALE_CONVENTION = ("world = camera of the first estimated frame; distance between the first "
                    "and the last estimated camera centres = 1")

REFLECTION_NOTE = ("line normals carry no sign, so the camera centres (and lines) are determined "
                   "only up to a point reflection through the first camera")

ESTIMATORS = ("auto", "paper", "global")

MIN_PARALLEL = 3
"""Fewest lines of the parallel family seen in every frame of the paper's window (its method
needs 3)."""
MIN_OTHER = 3
"""Fewest other lines seen in every frame of the paper's window (its method needs 3)."""
_MAX_STEP_DEG = 45.0
"""A paper solution that turns by more than this between two consecutive frames is taken for
a per-frame flip of its rotation search: the window is solved again without the rotation polish
(:attr:`PaperOptions.polish_rotation`), and that solution is kept if its steps stay below this."""
_HALF_TURN_DEG = 90.0
_VANISHING = VanishingOptions()
"""The parallel-family detection both estimators run (docs/method.md §3)."""
_PAPER = PaperOptions()
"""The paper's rotation and translation searches (docs/method.md §4-§5)."""
_BUNDLE = BundleOptions()
"""The line bundle adjustment both estimators run (docs/estimator.md)."""
_ROTATION_ONLY = RotationOnlyOptions()
"""The rotation-only fit, for a camera that turns without moving (docs/method.md §13)."""
_ROTATION_ONLY_MAX_MEDIAN_DEG = 0.2
"""Where the estimators find no motion, the rotation-only fit is the result if it explains the
NVs this well (median angle, degrees); otherwise their error stands. Translation changes the
NVs by the parallax the paper's method needs (at least ``PaperOptions.min_parallax_deg``),
which no rotation can explain."""
_ALTERNATIVE_MIN_DIFFERENCE = 0.05
"""An alternative start of the paper's method (scaled onto its solution by
:func:`~omni_sfm.estimate.paper.estimate_paper`) is adjusted only if its camera centres differ
from every start already adjusted by more than this fraction (RMS over the frames) of the RMS
distance of the cameras from the first: nearby starts fall into the same basin."""


def _finite_or_none(values: np.ndarray) -> list[float | None]:
    """Per frame: the value, rounded to 6 significant digits, or None where it is NaN or inf
    (JSON holds neither)."""
    return [float(f"{v:.6g}") if np.isfinite(v) else None for v in np.asarray(values, float)]


@dataclass(frozen=True, kw_only=True)
class EstimationOptions:
    estimator: str = "auto"
    """``"paper"``: the paper's method on one window that covers the sequence, then the line
    bundle adjustment; ``"global"``: the global estimator (rotations of all frames at once,
    positions of all frames at once, one bundle adjustment); ``"auto"``: the paper's method
    where one window covers the sequence, the global estimator otherwise
    (:func:`chosen_estimator`)."""
    refine: bool = True
    """The paper's estimator: run the bundle adjustment after the paper's method (False: the
    paper's method alone)."""
    progress: bool = False
    """A progress bar on stderr: the global estimator's steps."""
    workers: int | None = None
    """Processes that run independent solves at once (the global estimator's windows, starts
    and adjustments); 1: one after the other in this process; None: 2 where the machine has
    more than one core. The result is the same whatever the number."""
    global_: GlobalOptions = field(default_factory=GlobalOptions)
    """The global estimator's options: the frames it poses, how strict its flags are, the
    revisits (its ``workers`` are set from ``workers`` above)."""


SEGMENT_FILE = "trajectory_segment_{}.tum"


@dataclass(frozen=True)
class Segment:
    """A stretch of frames estimated on its own, in its own world and scale: nothing links it
    to the main trajectory (no line is seen on both sides of the gap).

    Attributes:
        number: 1, 2, ... (in the order of their first frame).
        frames: ``(F,)`` bool, its frames among all.
        trajectory: world_from_cam of its frames (world: its first frame's camera; distance
            between its first and last camera = 1).
        report: what the estimator reported about it (frames, residuals, reflection).
    """

    number: int
    frames: np.ndarray
    trajectory: Trajectory
    report: InitReport

    @property
    def file(self) -> str:
        return SEGMENT_FILE.format(self.number)


@dataclass(frozen=True)
class EstimationResult:
    """Poses of the estimated frames, the lines, and how they were obtained.

    Attributes:
        trajectory: world_from_cam of the estimated frames only (timestamps of the tracks).
        estimated: ``(F,)`` bool, frames estimated.
        initial_trajectory: the paper's (chained) solution of the same frames, before
            refinement, in the same world and scale convention.
        track_ids: ``(M,)`` the tracks' ids.
        parallel: ``(M,)`` bool, tracks of the parallel family.
        parallel_direction: ``(3,)`` unit direction of the family in the world frame.
        outliers: ``(M,)`` bool, tracks rejected as outliers.
        used_tracks: ``(M,)`` bool, tracks in the final solution.
        line_directions: ``(M, 3)`` unit line directions (world), NaN for unused tracks.
        line_points: ``(M, 3)`` closest point to the world origin of each line, NaN if unused.
        windows: ``[(start, stop), ...]`` frame windows solved by the paper's method.
        timings_ms: wall time per stage in milliseconds.
        residual_rms_initial_deg: RMS angle between observed and predicted NVs over the used
            observations, at the paper's solution.
        residual_rms_final_deg: the same after refinement.
        sigma_deg: robust estimate of the NV noise (per axis) at the solution, degrees.
        scale_convention: the world and scale of the result, in words.
        report: the report (``report.json`` without what ``init`` adds, docs/formats.md).
        segments: the stretches estimated on their own, each in its own world and scale.
    """

    trajectory: Trajectory
    estimated: np.ndarray
    initial_trajectory: Trajectory
    track_ids: np.ndarray
    parallel: np.ndarray
    parallel_direction: FloatArray
    outliers: np.ndarray
    used_tracks: np.ndarray
    line_directions: FloatArray
    line_points: FloatArray
    windows: list[tuple[int, int]]
    timings_ms: dict[str, float]
    residual_rms_initial_deg: float
    residual_rms_final_deg: float
    sigma_deg: float
    scale_convention: str
    report: InitReport
    segments: tuple[Segment, ...] = ()


@dataclass(frozen=True)
class _Solved:
    """The paper estimator's solution before the conventions: poses ``(F, ...)``, lines
    ``(M, 3)`` (NaN where not estimated / not used), the paper's own poses, and its family."""

    R: FloatArray
    c: FloatArray
    frames: np.ndarray
    d: FloatArray
    p: FloatArray
    used: np.ndarray
    outliers: np.ndarray
    rms0: float
    rms1: float
    sigma: float
    paper_R: FloatArray
    paper_c: FloatArray
    members: np.ndarray
    vpv: FloatArray
    families: list[int]
    switched: list[str]


def estimate_poses(tracks: LineTracks,
                   options: EstimationOptions = EstimationOptions()) -> EstimationResult:
    """Poses of all estimable frames from tracked line normals (see the module docstring).

    Raises:
        OmniSfmError: fewer than 3 frames, fewer than 3 parallel or 3 other lines, degenerate
            motion, or a sequence that determines nothing.
    """
    t_all = time.perf_counter()
    F, M = tracks.num_frames, tracks.num_tracks
    if F < 3:
        raise OmniSfmError(f"tracks have {F} frames; need at least 3")
    if M < 6:
        raise OmniSfmError(f"tracks have {M} lines; need at least 6 (3 parallel and 3 others)")
    start_workers(options)  # a bad number of workers fails here, whatever the sequence
    estimator, why = chosen_estimator(tracks, options)
    res = _global_result(tracks, options, t_all) if estimator == "global" else \
        _paper_result(tracks, options, t_all)
    return replace(res, report=replace(res.report, estimator=estimator, estimator_choice=why))


def _parts(tracks: LineTracks) -> list[tuple[int, int]]:
    """``[(start, stop)]`` the parts of the sequence with nothing in common (no line seen on
    both sides of the cut between two of them), in frame order."""
    out: list[tuple[int, int]] = []
    a = 0
    while True:
        sub = frame_range(tracks, a, tracks.num_frames)[0] if a else tracks
        cut = _first_cut(sub)
        if cut is None:
            return [*out, (a, tracks.num_frames)]
        out.append((a, a + cut))
        a += cut


def chosen_estimator(tracks: LineTracks, options: EstimationOptions) -> tuple[str, str]:
    """The estimator that ``options.estimator`` names (``paper`` or ``global``) and why.

    ``auto`` takes the paper's method where one window covers the sequence (a vanishing point
    in every frame and at least :data:`MIN_PARALLEL` lines of the parallel family and
    :data:`MIN_OTHER` others seen in every frame: the paper's setting, where its method reaches
    the maximum-likelihood floor, docs/estimator.md), and the global estimator anywhere else
    (lines that come and go, a walk longer than its lines, parts with nothing in common, a rig
    of lenses). The choice depends on which lines each frame sees, not on the frame order or on
    the normals' last bits.

    Raises:
        OmniSfmError: an unknown name; the paper's method asked for a rig's tracks.
    """
    if options.estimator not in ESTIMATORS:
        raise OmniSfmError(f"unknown estimator {options.estimator!r}: 'auto', 'paper' or "
                           f"'global'")
    if tracks.obs_offset is not None:  # a rig of lenses
        if options.estimator == "paper":
            raise OmniSfmError("the paper's method takes a central camera; a rig's tracks "
                               "(lens offsets) need the global estimator (--estimator global "
                               "or auto)")
        return "global", ("asked for" if options.estimator == "global" else
                          "auto: a rig of lenses (the global estimator takes each observation "
                          "from its lens)")
    if options.estimator != "auto":
        return options.estimator, "asked for"
    cut = _first_cut(tracks)
    if cut is not None:
        return "global", (f"auto: no line is seen on both sides of frame {cut} (parts with "
                          f"nothing in common: each is posed in a world of its own)")
    full = tracks.visibility().all(1)
    if int(full.sum()) < MIN_PARALLEL + MIN_OTHER:
        return "global", (f"auto: {int(full.sum())} lines seen in every frame, fewer than the "
                          f"paper's window needs ({MIN_PARALLEL} parallel + {MIN_OTHER} others)")
    family = detect_parallel_family(tracks, _VANISHING)
    members = np.asarray(family.members, bool)
    if bool(np.isfinite(family.vpv).all()) and int((full & members).sum()) >= MIN_PARALLEL \
            and int((full & ~members).sum()) >= MIN_OTHER:
        return "paper", (f"auto: one window covers every frame ({int((full & members).sum())} "
                         f"parallel and {int((full & ~members).sum())} other lines seen "
                         f"throughout)")
    return "global", (f"auto: no window covers every frame ({int((full & members).sum())} "
                      f"parallel and {int((full & ~members).sum())} other lines seen "
                      f"throughout, a vanishing point in "
                      f"{int(np.isfinite(family.vpv).all(1).sum())} of {tracks.num_frames} "
                      f"frames)")


# -- the paper's estimator --------------------------------------------------------------------

def _paper_result(tracks: LineTracks, options: EstimationOptions,
                  t_all: float) -> EstimationResult:
    """The paper's estimator's result; a camera that only turned gets the rotation-only fit
    (where the paper's method fails, or poses fewer frames than the rotations alone)."""
    run = RunLog()
    try:
        sol = _paper_solved(tracks, options, run)
    except OmniSfmError as exc:
        rot_only = _try_rotation_only(tracks, options, run, f"the paper's method failed: {exc}")
        if rot_only is None:
            raise
        return _rotation_only_result(tracks, rot_only, options, run, str(exc), t_all)
    result = _paper_assembled(tracks, sol, run, t_all)
    if result.estimated.all():
        return result
    why = (f"the paper's estimator posed only {int(result.estimated.sum())} of "
           f"{tracks.num_frames} frames")
    rot_only = _try_rotation_only(tracks, options, run, why, better_than=result)
    if rot_only is not None:
        return _rotation_only_result(tracks, rot_only, options, run, why, t_all)
    return replace(result, report=replace(result.report, attempts=run.entries))


def _covering_window(tracks: LineTracks, family: ParallelFamily) -> Window:
    """The window of the whole sequence and the lines seen in every frame.

    Raises:
        OmniSfmError: a frame without the family's vanishing point, or fewer than
            :data:`MIN_PARALLEL` of its lines or :data:`MIN_OTHER` others seen in every frame.
    """
    members = np.asarray(family.members, bool)
    full = tracks.visibility().all(1)
    vp = int(np.isfinite(family.vpv).all(1).sum())
    n_par, n_other = int((full & members).sum()), int((full & ~members).sum())
    if vp < tracks.num_frames or n_par < MIN_PARALLEL or n_other < MIN_OTHER:
        raise OmniSfmError(
            f"the paper's method needs one window over the whole sequence: a vanishing point "
            f"in every frame ({vp} of {tracks.num_frames}), {MIN_PARALLEL} lines of the "
            f"parallel family and {MIN_OTHER} others seen in every frame ({n_par} and "
            f"{n_other}); the global estimator (--estimator global or auto) takes any sequence")
    return Window(0, tracks.num_frames, np.flatnonzero(full))


def _paper_solved(tracks: LineTracks, options: EstimationOptions, run: RunLog) -> _Solved:
    """The paper's method on the window that covers the sequence (with another family where
    the largest one is degenerate for the motion), then the adjustment (``options.refine``)."""
    with run.timed("parallel_lines"):
        family = detect_parallel_family(tracks, _VANISHING)
        others = [f for f in detect_parallel_families(tracks, _VANISHING)[1:]
                  if f.size >= 3]
    members = np.asarray(family.members, bool)
    _check_counts(tracks, members)
    window = _covering_window(tracks, family)
    att = _solve_window(tracks, family, window, options, run)
    switched: list[str] = []
    if not att.ok:
        run.record(att)
        alt = _other_family(tracks, others, window, options, run)
        if alt is None:
            raise OmniSfmError(f"the paper's method failed: {att.why}")
        switched.append(f"frames 0-{tracks.num_frames - 1}: {alt.why} ({att.why})")
        att = alt
    paper = att.solution
    assert paper is not None
    run.add_times(paper.timings_ms)
    run.record(att)
    R0, c0 = np.asarray(paper.rotations), np.asarray(paper.positions)
    frames = np.ones(tracks.num_frames, bool)
    if options.refine:
        alternatives = [(np.asarray(R), np.asarray(c)) for R, c in paper.alternatives]
        ba = _refine(tracks, R0, c0, frames, alternatives, options, run)
        R, c, frames = ba.rotations, ba.positions, ba.frames
        d, p, used, outliers = ba.line_directions, ba.line_points, ba.used_tracks, \
            ba.outlier_tracks
        rms0, rms1, sigma = ba.rms_initial_deg, ba.rms_final_deg, ba.sigma_deg
    else:
        R, c = R0, c0
        d, p, used = triangulate_lines(tracks, R, c, frames, min_observations=3)
        outliers = np.zeros(tracks.num_tracks, bool)
        ang = observation_residuals(tracks, R, c, d, p)
        ok = np.isfinite(ang)
        rms0 = rms1 = float(np.degrees(np.sqrt(np.mean(ang[ok] ** 2)))) if ok.any() else np.nan
        sigma = float(np.degrees(np.median(ang[ok]) / np.sqrt(2 * np.log(2)))) if ok.any() \
            else np.nan
    return _Solved(R, c, frames, d, p, used, outliers, rms0, rms1, sigma, R0, c0, members,
                   np.asarray(family.vpv), [int(family.size)] + [int(f.size) for f in others],
                   switched)


def _paper(tracks: LineTracks, family: ParallelFamily, w: Window, paper: PaperOptions,
           strategy: str) -> Attempt[PaperSolution]:
    """Strategy: the paper's method (:func:`estimate_paper`) on window ``w`` with ``family``."""
    frames = (w.start, w.stop - 1)
    try:
        sol = estimate_paper(window_tracks(tracks, w), window_family(family, w), paper)
    except OmniSfmError as exc:
        return failed(strategy, frames, str(exc))
    return Attempt(strategy, frames, sol, cost_deg=float(sol.costs.get("rms_deg", np.nan)))


def _solve_window(tracks: LineTracks, family: ParallelFamily, w: Window,
                  options: EstimationOptions, run: RunLog,
                  strategy: str = "paper window") -> Attempt[PaperSolution]:
    """The paper's solution of one window; without the rotation polish where the polished
    rotations jump between consecutive frames (:data:`_MAX_STEP_DEG`; that attempt is
    recorded). Fails where the paper's method fails, or (frames consecutive:
    ``PaperOptions.rotation_continuity``) its solution still turns by a half turn between two
    consecutive frames."""
    att = _paper(tracks, family, w, _PAPER, strategy)
    if att.solution is None:
        return att
    if _PAPER.polish_rotation and \
            max_rotation_step_deg(np.asarray(att.solution.rotations)) > _MAX_STEP_DEG:
        alt = _paper(tracks, family, w, replace(_PAPER, polish_rotation=False),
                     "paper window, unpolished")
        jump = f"the polished rotations jump by more than {_MAX_STEP_DEG} deg between frames"
        if alt.solution is not None and \
                max_rotation_step_deg(np.asarray(alt.solution.rotations)) <= _MAX_STEP_DEG:
            run.record(att.judged(Outcome.REJECTED, jump))
            att = replace(alt, why=f"{strategy}: {jump}")
        elif alt.solution is not None:
            run.record(alt.judged(Outcome.REJECTED, "its rotations jump too"))
        else:
            run.record(alt)
    # a half turn between two video frames is a flip of the rotation search, not motion
    assert att.solution is not None
    step = max_rotation_step_deg(np.asarray(att.solution.rotations))
    if _PAPER.rotation_continuity and step > _HALF_TURN_DEG:
        return failed(att.strategy, att.frames, f"its solution turns by {step:.0f} deg between "
                                                f"two consecutive frames (a flip of the "
                                                f"rotation search)")
    return att


def _paper_assembled(tracks: LineTracks, sol: _Solved, run: RunLog,
                     t_all: float) -> EstimationResult:
    """The conventions (world, scale, reflection) and the report of the paper's estimator."""
    frames = sol.frames
    R_n, c_n, d_n, p_n = _normalise(sol.R, sol.c, frames, sol.d, sol.p)
    R_i, c_i, _, _ = _normalise(sol.paper_R, sol.paper_c, frames, sol.d, sol.p)
    idx = np.flatnonzero(frames)
    reflection, flip = _reflection(tracks, R_n, c_n, d_n, p_n, frames, sol.used)
    if flip:
        o = c_n[idx[0]].copy()
        c_n, p_n, c_i = 2.0 * o - c_n, 2.0 * o - p_n, 2.0 * o - c_i
    ts = tracks.timestamps
    traj = Trajectory(ts[idx].copy(), R_n[idx], c_n[idx])
    traj0 = Trajectory(ts[idx].copy(), R_i[idx], c_i[idx])
    # the family's direction in the world: mean of its refined lines, else the first frame's VPV
    direction = _family_direction(d_n, sol.members & sol.used)
    if not np.isfinite(direction).all():
        direction = R_n[idx[0]] @ sol.vpv[idx[0]]
    run.timings["total"] = (time.perf_counter() - t_all) * 1e3
    timings = dict(run.timings)
    windows = [(0, tracks.num_frames)]
    report = replace(
        _report(tracks, frames, sol.members, direction, sol.outliers, sol.used, windows,
                timings, sol.rms0, sol.rms1, sol.sigma),
        reflection=reflection, attempts=run.entries,
        parallel_families=FamiliesFound(sizes=sol.families,
                                        windows_with_another_family=sol.switched),
        frames_not_estimated_reasons={
            str(k): "fewer than 3 of its lines are left after the adjustment rejected outlier "
                    "tracks" for k in np.flatnonzero(~frames)})
    return EstimationResult(
        trajectory=traj, estimated=frames, initial_trajectory=traj0,
        track_ids=tracks.track_ids.copy(), parallel=sol.members, parallel_direction=direction,
        outliers=sol.outliers, used_tracks=sol.used, line_directions=d_n, line_points=p_n,
        windows=windows, timings_ms=timings, residual_rms_initial_deg=sol.rms0,
        residual_rms_final_deg=sol.rms1, sigma_deg=sol.sigma,
        scale_convention=SCALE_CONVENTION, report=report)


def _reflection(tracks: LineTracks, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
                frames: np.ndarray, used: np.ndarray) -> tuple[str, bool]:
    """``(report text, flip)``: whether the point reflection through the first camera puts
    more lines in front of the rays that see them (every observation is unchanged by it)."""
    front, behind = side_votes(tracks, R, c, d, p, frames, used)
    if front + behind == 0:
        return "unresolved: the tracks carry no rays (" + REFLECTION_NOTE + ")", False
    flip = behind > front
    if flip:
        front, behind = behind, front
    return (f"resolved by the observations' rays: {front} see their line in front, {behind} "
            f"behind"), flip


def _family_direction(d: FloatArray, lines: np.ndarray) -> FloatArray:
    """The mean direction of the ``lines`` (signs aligned); NaN where there are none."""
    pd = d[lines]
    if not len(pd):
        return np.full(3, np.nan)
    pd = pd * np.sign(pd @ pd[0])[:, None]
    return np.asarray(pd.mean(0) / np.linalg.norm(pd.mean(0)))


# -- the global estimator ---------------------------------------------------------------------

@dataclass(frozen=True)
class _Part:
    """A part of the sequence with nothing in common with the rest (:func:`_parts`): frames
    ``start..stop-1`` as tracks of their own (``index``: each track's index in the whole
    tracks) and the global estimator's solution of them, or why it failed."""

    start: int
    stop: int
    tracks: LineTracks
    index: np.ndarray
    solution: GlobalSolution | None
    error: OmniSfmError | None


def _solved_part(tracks: LineTracks, a: int, b: int, options: GlobalOptions,
                 whole: bool) -> _Part:
    """Frames ``a..b-1`` (all of ``tracks`` where ``whole``) solved by the global estimator."""
    sub, idx = (tracks, np.arange(tracks.num_tracks)) if whole else frame_range(tracks, a, b)
    try:
        return _Part(a, b, sub, idx, solve_global(sub, options), None)
    except OmniSfmError as exc:
        return _Part(a, b, sub, idx, None, exc)


def _global_result(tracks: LineTracks, options: EstimationOptions,
                   t_all: float) -> EstimationResult:
    """The global estimator's result: each part of the sequence with nothing in common
    (:func:`_parts`) solved on its own; the part that poses most frames (the earliest of equals)
    is the main trajectory, the others segments; a camera that only turned gets the
    rotation-only fit."""
    run = RunLog()
    gopts = settings(replace(options.global_, workers=start_workers(options),
                             progress=options.progress), vanishing=_VANISHING, bundle=_BUNDLE)
    spans = _parts(tracks)
    parts = [_solved_part(tracks, a, b, gopts, len(spans) == 1) for a, b in spans]
    ok = [q for q in parts if q.solution is not None]
    if not ok:
        error = parts[0].error
        assert error is not None
        why = str(error) if len(parts) == 1 else \
            f"no part of the sequence could be posed ({error})"
        rot_only = _try_rotation_only(tracks, options, run, f"the global estimator failed: "
                                                            f"{why}")
        if rot_only is None:
            raise OmniSfmError(why) from error
        return _rotation_only_result(tracks, rot_only, options, run, why, t_all)
    main = max(ok, key=lambda q: (int(_solution(q).frames.sum()), -q.start))
    whole = _lifted(_solution(main), main.start, main.index, tracks.num_frames,
                    tracks.num_tracks)
    result = _global_assembled(tracks, whole, t_all)
    if len(parts) == 1:
        return result
    return _with_segments(tracks, result, [q for q in parts if q is not main], t_all)


def _solution(part: _Part) -> GlobalSolution:
    """The solution of a part that has one."""
    assert part.solution is not None
    return part.solution


def _lifted(sol: GlobalSolution, start: int, idx: np.ndarray, F: int, M: int) -> GlobalSolution:
    """A solution of frames ``start..`` and tracks ``idx`` (:func:`frame_range`) in the indices
    of the whole sequence (``F`` frames, ``M`` tracks)."""
    if start == 0 and len(sol.frames) == F and len(idx) == M:
        return sol
    rows = slice(start, start + len(sol.frames))

    def frames_of(a: np.ndarray, fill: Any) -> np.ndarray:
        return scatter_rows(a, rows, F, fill)

    def tracks_of(a: np.ndarray, fill: Any) -> np.ndarray:
        return scatter_rows(a, idx, M, fill)

    return replace(
        sol, rotations=frames_of(sol.rotations, np.nan),
        positions=frames_of(sol.positions, np.nan), frames=frames_of(sol.frames, False),
        spread_deg=frames_of(sol.spread_deg, np.nan), spread_path=frames_of(sol.spread_path,
                                                                           np.nan),
        line_directions=tracks_of(sol.line_directions, np.nan),
        line_points=tracks_of(sol.line_points, np.nan),
        used_tracks=tracks_of(sol.used_tracks, False),
        outlier_tracks=tracks_of(sol.outlier_tracks, False),
        members=tracks_of(sol.members, False),
        uncertain={start + k: v for k, v in sol.uncertain.items()},
        not_posed={start + k: v for k, v in sol.not_posed.items()})


def _with_segments(tracks: LineTracks, main: EstimationResult, rest: list[_Part],
                   t_all: float) -> EstimationResult:
    """The ``main`` result with the other parts as segments (in the order of their first
    frame), each in its own world and scale, and why their frames are not in the main
    trajectory."""
    reasons = dict(main.report.frames_not_estimated_reasons or {})
    segments: list[Segment] = []
    for part in rest:
        a, b, sol = part.start, part.stop, part.solution
        if sol is None:
            why = f"its part (frames {a}-{b - 1}, no line in common with the rest) failed: " \
                  f"{part.error}"
        else:
            try:
                r = _global_assembled(part.tracks, sol, t_all)
            except OmniSfmError as exc:
                why = f"its part (frames {a}-{b - 1}) has no world and scale: {exc}"
            else:
                own = np.zeros(tracks.num_frames, bool)
                own[a:b] = r.estimated
                seg = Segment(len(segments) + 1, own, r.trajectory, r.report)
                segments.append(seg)
                for f in np.flatnonzero(own):
                    reasons[str(f)] = (f"estimated in segment {seg.number} ({seg.file}), in its "
                                       f"own world and scale: no line links frames {a}-{b - 1} "
                                       f"to the main trajectory")
                for k, v in sol.not_posed.items():
                    reasons[str(a + k)] = v
                continue
        for g in range(a, b):
            reasons[str(g)] = why
    report = replace(
        main.report, frames_not_estimated_reasons=dict(sorted(reasons.items(),
                                                              key=lambda kv: int(kv[0]))),
        segments=[InitSegment(
            file=seg.file,
            frames=[int(np.flatnonzero(seg.frames)[0]), int(np.flatnonzero(seg.frames)[-1])],
            num_frames_estimated=int(seg.frames.sum()),
            world="camera of the segment's first estimated frame (world_from_cam, TUM)",
            scale_convention="distance between the segment's first and last estimated "
                             "camera centres = 1",
            residual_rms_deg=seg.report.rms_final_deg,
        ) for seg in segments] or None)
    return replace(main, report=report, segments=tuple(segments))


def _global_assembled(tracks: LineTracks, sol: GlobalSolution,
                      t_all: float) -> EstimationResult:
    """The conventions (world, scale, reflection) and the report of the global estimator's
    solution ``sol`` of ``tracks``."""
    frames = sol.frames
    R_n, c_n, d_n, p_n = _normalise(sol.rotations, sol.positions, frames, sol.line_directions,
                                    sol.line_points)
    idx = np.flatnonzero(frames)
    reflection, flip = _reflection(tracks, R_n, c_n, d_n, p_n, frames, sol.used_tracks)
    if flip:
        o = c_n[idx[0]].copy()
        c_n, p_n = 2.0 * o - c_n, 2.0 * o - p_n
    members = sol.members
    direction = _family_direction(d_n, members & sol.used_tracks)
    timings = dict(sol.timings_ms)
    timings["total"] = (time.perf_counter() - t_all) * 1e3
    traj = Trajectory(tracks.timestamps[idx].copy(), R_n[idx], c_n[idx])
    report = replace(
        _report(tracks, frames, members, direction, sol.outlier_tracks, sol.used_tracks, [],
                timings, sol.rms_initial_deg, sol.rms_final_deg, sol.sigma_deg),
        reflection=reflection, steps=sol.steps,
        world_directions=[[float(x) for x in v @ sol.rotations[idx[0]]]
                          for v in sol.world_directions],
        frames_not_estimated_reasons={str(k): v for k, v in sorted(sol.not_posed.items())},
        frames_uncertain={str(k): v for k, v in sorted(sol.uncertain.items())},
        pose_spread=PoseSpreadRecord(rotation_deg=_finite_or_none(sol.spread_deg),
                                     position_pct_of_path=_finite_or_none(
                                         100.0 * sol.spread_path)),
        rig=_rig_record(sol, frames))
    return EstimationResult(
        trajectory=traj, estimated=frames, initial_trajectory=traj,
        track_ids=tracks.track_ids.copy(), parallel=members, parallel_direction=direction,
        outliers=sol.outlier_tracks, used_tracks=sol.used_tracks, line_directions=d_n,
        line_points=p_n, windows=[], timings_ms=timings,
        residual_rms_initial_deg=sol.rms_initial_deg, residual_rms_final_deg=sol.rms_final_deg,
        sigma_deg=sol.sigma_deg, scale_convention=SCALE_CONVENTION, report=report)


# -- shared by both ---------------------------------------------------------------------------

def _check_counts(tracks: LineTracks, members: np.ndarray) -> None:
    n_par = int(members.sum())
    n_other = tracks.num_tracks - n_par
    if n_par < 3:
        raise OmniSfmError(f"found {n_par} parallel lines; need at least 3 lines of one "
                           f"parallel family")
    if n_other < 3:
        raise OmniSfmError(f"found {n_par} parallel lines but only {n_other} other lines; need "
                           f"at least 3 lines not parallel to the family")


def _other_family(tracks: LineTracks, others: list[ParallelFamily], w: Window,
                  options: EstimationOptions, run: RunLog) -> Attempt[PaperSolution] | None:
    """The paper's solution of window ``w`` with the first other family that gives one (3 of
    its tracks and 3 others seen throughout the window); the attempts that fail are recorded."""
    for k, fam in enumerate(others):
        m = np.asarray(fam.members, bool)[w.tracks]
        if m.sum() < MIN_PARALLEL or (~m).sum() < MIN_OTHER:
            continue
        att = _solve_window(tracks, fam, w, options, run, "paper window, another family")
        if att.ok:
            return replace(att, why=f"family {k + 2}" + (f", {att.why}" if att.why else ""))
        run.record(att, family=k + 2)
    return None


def _normalise(R: FloatArray, c: FloatArray, frames: np.ndarray, d: FloatArray,
               p: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Apply the scale convention: world = first estimated camera, first-to-last distance 1."""
    idx = np.flatnonzero(frames)
    R0, c0 = R[idx[0]], c[idx[0]]
    s = float(np.linalg.norm(c[idx[-1]] - c0))
    if not s > 0:
        raise OmniSfmError("the first and last estimated cameras coincide: the scale convention "
                           "(first-to-last distance = 1) is undefined")
    R_n = np.einsum("ji,fjk->fik", R0, R)
    c_n = (c - c0) @ R0 / s
    d_n = d @ R0
    p_n = (p - c0) @ R0 / s
    p_n = p_n - np.sum(p_n * d_n, 1, keepdims=True) * d_n
    return R_n, c_n, d_n, p_n


def _bundle(tracks: LineTracks, R: FloatArray, c: FloatArray, frames: np.ndarray,
            options: EstimationOptions, strategy: str) -> Attempt[BundleResult]:
    """Strategy: the line bundle adjustment of ``frames`` from the poses ``R, c`` (lines
    triangulated from them)."""
    idx = np.flatnonzero(frames)
    span = (int(idx[0]), int(idx[-1]))
    try:
        d, p, _ = triangulate_lines(tracks, R, c, frames)
        ba = bundle_adjust(tracks, R, c, d, p, frames=frames, options=_BUNDLE)
    except OmniSfmError as exc:
        return failed(strategy, span, str(exc))
    return Attempt(strategy, span, ba, cost_deg=ba.rms_final_deg,
                   why=f"{int(ba.frames.sum())} frames, {int(ba.outlier_tracks.sum())} outlier "
                       f"tracks")


def _refine(tracks: LineTracks, R0: FloatArray, c0: FloatArray, frames: np.ndarray,
            alternatives: list[tuple[FloatArray, FloatArray]], options: EstimationOptions,
            run: RunLog) -> BundleResult:
    """The bundle adjustment from the paper's solution ``R0, c0`` and from its distinct
    ``alternatives`` (:data:`_ALTERNATIVE_MIN_DIFFERENCE`): the lowest final cost wins among
    those that pose as many frames with as many tracks. Raises where the adjustment of the
    paper's solution fails."""
    with run.timed("refinement"):
        first = _bundle(tracks, R0, c0, frames, options, "bundle adjustment")
    if first.solution is None:
        run.record(first)
        raise OmniSfmError(f"the bundle adjustment failed: {first.why}")
    best = first
    tried: list[Attempt[BundleResult]] = []
    idx = np.flatnonzero(frames)
    spread = float(np.sqrt(np.mean(np.sum((c0[idx] - c0[idx[0]]) ** 2, axis=1))))
    starts = [c0[idx]]
    for R_alt, c_alt in alternatives:
        ca = c_alt[idx]
        if min(float(np.sqrt(np.mean(np.sum((ca - t) ** 2, axis=1)))) for t in starts) <= \
                _ALTERNATIVE_MIN_DIFFERENCE * spread:
            continue  # the same basin as a start already adjusted
        starts.append(ca)
        with run.timed("refinement"):
            alt = _bundle(tracks, R_alt, c_alt, frames, options,
                          "bundle adjustment, another start")
        tried.append(alt)
        a, b = alt.solution, best.solution
        if a is not None and b is not None and a.frames.sum() >= b.frames.sum() and \
                a.used_tracks.sum() >= b.used_tracks.sum() and \
                a.rms_final_deg < b.rms_final_deg:
            best = alt
    kept = best.solution
    assert kept is not None
    for att in [first, *tried]:
        if att is best or att.solution is None:
            run.record(att)
            continue
        a = att.solution
        if a.frames.sum() < kept.frames.sum() or a.used_tracks.sum() < kept.used_tracks.sum():
            why = (f"{int(a.frames.sum())} frames and {int(a.used_tracks.sum())} tracks, the "
                   f"kept start {int(kept.frames.sum())} and {int(kept.used_tracks.sum())}")
        else:
            why = f"final cost not below the kept start's {kept.rms_final_deg:.6g} deg"
        run.record(att.judged(Outcome.REJECTED, f"{att.why}; {why}"))
    return kept


def _first_cut(tracks: LineTracks) -> int | None:
    """The first frame that no line is seen on both sides of (parts with nothing in common;
    frames that see nothing at the ends cut nothing); None where there is none."""
    first, last = tracks.frame_spans()
    seen = last >= 0
    spanning = np.zeros(tracks.num_frames + 1, np.int64)  # lines seen on both sides of a cut
    np.add.at(spanning, first[seen] + 1, 1)
    np.add.at(spanning, last[seen] + 1, -1)
    lo, hi = int(first[seen].min()), int(last[seen].max())
    cuts = lo + np.flatnonzero(np.cumsum(spanning)[lo + 1:hi + 1] == 0)
    return int(cuts[0]) + 1 if len(cuts) else None


def _rig_record(sol: GlobalSolution, frames: np.ndarray) -> RigScaleRecord | None:
    """The report's ``rig``: the metres one unit of the normalised trajectory spans (the
    solution's first-to-last distance, in metres where the lens offsets fix the scale, else
    over the rough units per metre of the start)."""
    scale = sol.offset_scale
    if scale is None:
        return None
    if not scale.scale > 0:
        return RigScaleRecord(metres_per_unit=None, note=(
            "the lines are too far for the lenses' baseline to give a metric scale (and for "
            "their offsets to matter): the lenses taken as one centre"), fixed=False)
    idx = np.flatnonzero(frames)
    span = float(np.linalg.norm(sol.positions[idx[-1]] - sol.positions[idx[0]]))
    if not scale.fixed:
        return RigScaleRecord(metres_per_unit=span / scale.scale, note=(
            "a rough metric scale: the lines are too far for the lenses' baseline to fix it "
            "(or for their offsets to matter), the lenses taken as one centre"), fixed=False)
    return RigScaleRecord(metres_per_unit=span, note=(
        "metric scale from the baseline between the lenses (the adjustment in metres, docs/"
        "estimator.md \"Rigs\")"), fixed=True)


def start_workers(options: EstimationOptions) -> int:
    """The processes that run the starts of :func:`_better_start` at once (``options.workers``;
    None: two where the machine has more than one core)."""
    if options.workers is not None:
        if options.workers < 1:
            raise OmniSfmError(f"workers must be at least 1, got {options.workers}")
        return int(options.workers)
    return 2 if (os.cpu_count() or 1) > 1 else 1


ROTATION_ONLY_CONVENTION = ("world = camera of the first estimated frame; the camera only "
                            "turned: every position is 0, translation and scale are undetermined")


def _try_rotation_only(tracks: LineTracks, options: EstimationOptions, run: RunLog,
                       why: str, better_than: EstimationResult | None = None
                       ) -> RotationOnlyResult | None:
    """Strategy: the rotation-only fit, tried because ``why``; kept if it explains the NVs (the
    camera turned in place) and estimates more frames than ``better_than``, else None."""
    span = (0, tracks.num_frames - 1)
    with run.timed("rotation_only"):
        try:
            res = estimate_rotation_only(tracks, _ROTATION_ONLY)
        except OmniSfmError as exc:
            run.record(failed("rotation only", span, f"{why}; {exc}"))
            return None
    att = Attempt("rotation only", span, res, cost_deg=res.rms_final_deg,
                  why=f"{why}; {int(res.estimated.sum())} frames, median "
                      f"{res.median_deg:.3g} deg")
    limit = _ROTATION_ONLY_MAX_MEDIAN_DEG
    if res.estimated.sum() < 3 or not res.median_deg <= limit:
        run.record(att.judged(Outcome.REJECTED, f"{att.why}: the rotations alone do not explain "
                                                f"the lines (median over {limit} deg)"))
        return None
    if better_than is not None and res.estimated.sum() <= better_than.estimated.sum():
        run.record(att.judged(Outcome.REJECTED, f"{att.why}: no more frames than the moving "
                                                f"camera's solution"))
        return None
    run.record(att)
    return res


def _rotation_only_result(tracks: LineTracks, res: RotationOnlyResult,
                          options: EstimationOptions, run: RunLog, why: str,
                          t_all: float) -> EstimationResult:
    """An :class:`EstimationResult` of a camera that only turned: rotations, positions 0."""
    M = tracks.num_tracks
    frames = res.estimated
    idx = np.flatnonzero(frames)
    # the family is reported only (the rotations do not use it); a camera that turns may see
    # none
    no_family = ""
    with run.timed("parallel_lines"):
        try:
            family = detect_parallel_family(tracks, _VANISHING)
            members = np.asarray(family.members, bool)
            vpv = np.asarray(family.vpv)[idx]
            ok = np.isfinite(vpv).all(axis=1)
            direction = res.rotations[idx[ok][0]] @ vpv[ok][0] if ok.any() else \
                np.full(3, np.nan)
        except OmniSfmError as exc:
            members, direction, no_family = np.zeros(M, bool), np.full(3, np.nan), str(exc)
    ts = tracks.timestamps
    traj = Trajectory(ts[idx].copy(), res.rotations[idx], np.zeros((len(idx), 3)))
    sigma = float(res.median_deg / np.sqrt(2 * np.log(2)))
    run.timings["total"] = (time.perf_counter() - t_all) * 1e3
    timings = dict(run.timings)
    nan3 = np.full((M, 3), np.nan)
    report = _report(tracks, frames, members, direction, res.outliers, res.used_tracks, [],
                     timings, res.rms_initial_deg, res.rms_final_deg, sigma)
    assert report.parallel_family is not None  # _report writes it
    report = replace(
        report,
        parallel_family=replace(report.parallel_family, none=no_family or None),
        scale_convention=ROTATION_ONLY_CONVENTION,
        motion=InitMotion(
            kind="rotation only",
            translation="undetermined: the camera turned without moving (positions are 0, "
                        "the scale and the 3D lines are undetermined)",
            why=f"the paper's method found no motion ({why}); the rotations alone explain "
                f"the line normals to {res.median_deg:.3g} deg (median)"),
        frames_not_estimated_reasons={str(k): v for k, v in res.reasons.items()},
        reflection="none: no translation", attempts=run.entries)
    return EstimationResult(
        trajectory=traj, estimated=frames, initial_trajectory=traj,
        track_ids=tracks.track_ids.copy(), parallel=members, parallel_direction=direction,
        outliers=res.outliers, used_tracks=res.used_tracks, line_directions=nan3,
        line_points=nan3.copy(), windows=[], timings_ms=timings,
        residual_rms_initial_deg=res.rms_initial_deg, residual_rms_final_deg=res.rms_final_deg,
        sigma_deg=sigma, scale_convention=ROTATION_ONLY_CONVENTION, report=report)


def _report(tracks: LineTracks, frames: np.ndarray, members: np.ndarray, direction: FloatArray,
            outliers: np.ndarray, used: np.ndarray, windows: list[tuple[int, int]],
            timings: dict[str, float], rms0: float, rms1: float,
            sigma: float) -> InitReport:
    """The report's keys every estimate has (the callers add their own)."""
    ids = tracks.track_ids
    return InitReport(
        omni_sfm_version=__version__,
        initializer="lines",
        num_frames=tracks.num_frames,
        num_frames_estimated=int(frames.sum()),
        frames_not_estimated=np.flatnonzero(~frames).tolist(),
        num_tracks=tracks.num_tracks,
        num_observations=tracks.num_observations,
        num_tracks_used=int(used.sum()),
        parallel_family=FamilyReport(track_ids=ids[members].tolist(),
                                     direction=[float(x) for x in direction]),
        rejected_tracks=ids[outliers].tolist(),
        unused_tracks=ids[~used & ~outliers].tolist(),
        windows=[[int(a), int(b) - 1] for a, b in windows],
        world="camera of the first estimated frame (world_from_cam, TUM)",
        scale_convention=SCALE_CONVENTION,
        reflection_ambiguity=REFLECTION_NOTE,
        timings_ms={k: round(float(v), 3) for k, v in timings.items()},
        residuals=InitResiduals(rms_initial_deg=float(rms0), rms_final_deg=float(rms1),
                                noise_sigma_deg=float(sigma)),
    )


def fixed_by_data(result: EstimationResult) -> np.ndarray:
    """``(N,)`` bool over ``result.trajectory``'s poses: those of frames the report does not
    flag as uncertain (``frames_uncertain``)."""
    idx = np.flatnonzero(result.estimated)
    return ~np.isin(idx, [int(k) for k in result.report.frames_uncertain or {}])


def trusted(result: EstimationResult) -> np.ndarray:
    """``(N,)`` bool over ``result.trajectory``'s poses: those the data fix
    (:func:`fixed_by_data`), where at least 3 are; else all."""
    keep = fixed_by_data(result)
    return keep if keep.sum() >= 3 else np.ones(len(keep), bool)


def write_init_outputs(directory: Path, result: EstimationResult,
                       report: InitReport | None = None, *,
                       keep_uncertain: bool = False) -> list[Path]:
    """Write ``trajectory.tum`` and ``report.json`` of ``result`` into ``directory``.

    The poses of the frames the report flags as uncertain go to ``trajectory_uncertain.tum``
    instead of ``trajectory.tum`` (so that no later stage takes them for fixed; the report
    says so in ``uncertain_poses``), unless ``keep_uncertain`` or fewer than 3 frames would be
    left (:func:`trusted`). ``report``: the report to write, ``result.report`` by default
    (``init`` gives it with what it adds: the input files, the front end's figures).
    Use inside :func:`omni_sfm.fileio.atomic_output_dir` so that the folder appears complete
    or not at all.
    """
    directory = Path(directory)
    keep = np.ones(len(result.trajectory), bool) if keep_uncertain else trusted(result)
    write_tum(directory / TRAJECTORY_FILE, result.trajectory.subset(keep))
    written = [directory / TRAJECTORY_FILE]
    if not keep.all():
        write_tum(directory / UNCERTAIN_FILE, result.trajectory.subset(~keep))
        written.append(directory / UNCERTAIN_FILE)
    for seg in result.segments:
        write_tum(directory / seg.file, seg.trajectory)
        written.append(directory / seg.file)
    report = result.report if report is None else report
    if not keep.all():
        report = replace(report, uncertain_poses=UNCERTAIN_FILE)
    report.write(directory / REPORT_FILE)
    return [*written, directory / REPORT_FILE]
