"""The whole line-based estimator: tracks -> parallel family -> paper's solution(s) -> chaining ->
bundle adjustment with outlier rejection -> poses of all estimable frames, and a report.

Library entry point :func:`estimate_poses`; :func:`write_init_outputs` writes the documented
artifacts (``trajectory.tum``, ``report.json``, see docs/formats.md) and is shared by every
input mode of ``omni-sfm init`` (``--tracks`` and ``--images``).

Conventions of the result: world = the camera of the first estimated frame (frame 0 whenever it
is estimated), poses world_from_cam, and the scale set so that the distance between the first
and the last estimated camera is 1 (the paper's convention, Sec. VII).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from omni_sfm import __version__
from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.attempts import Attempt, CountedProgress, Outcome, RunLog, failed
from omni_sfm.estimate.bundle import (
    BundleOptions,
    BundleResult,
    bundle_adjust,
    camera_distance_ratio,
    observation_residuals,
    outlier_limit,
    resect_pose,
    scatter_rows,
    scattered,
    side_votes,
    triangulate_lines,
    truncated_cost,
    weighted_residuals,
)
from omni_sfm.estimate.families import camera_anchors, line_families, snap_to_families
from omni_sfm.estimate.global_estimator import GlobalOptions, GlobalSolution, solve_global
from omni_sfm.estimate.incremental import (
    IncrementalOptions,
    obs_index,
    register_frames,
)
from omni_sfm.estimate.paper import PaperOptions, PaperSolution, estimate_paper
from omni_sfm.estimate.rotation_only import (
    RotationOnlyOptions,
    RotationOnlyResult,
    estimate_rotation_only,
)
from omni_sfm.estimate.segments import frame_range, runs, similarity_from_lines
from omni_sfm.estimate.windows import (
    Window,
    WindowOptions,
    chain_windows,
    max_rotation_step_deg,
    plan_windows,
    window_family,
    window_tracks,
)
from omni_sfm.folders import REPORT_FILE, TRAJECTORY_FILE, UNCERTAIN_FILE
from omni_sfm.forked import Deferred, SharedCounters
from omni_sfm.geometry import FloatArray, rotation_angle
from omni_sfm.lines.tracks import LineTracks, reversed_frames
from omni_sfm.poses import Trajectory, write_tum
from omni_sfm.reports import (
    AttemptRecord,
    FamiliesFound,
    FamilyReport,
    InitMotion,
    InitReport,
    InitResiduals,
    InitSegment,
    PoseSpreadRecord,
    RigScaleRecord,
)
from omni_sfm.transforms import similarity_from_poses
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


def _finite_or_none(values: np.ndarray) -> list[float | None]:
    """Per frame: the value, rounded to 6 significant digits, or None where it is NaN or inf
    (JSON holds neither)."""
    return [float(f"{v:.6g}") if np.isfinite(v) else None for v in np.asarray(values, float)]


@dataclass(frozen=True, kw_only=True)
class EstimationOptions:
    vanishing: VanishingOptions = field(default_factory=VanishingOptions)
    """Parallel-family detection and VPVs (docs/method.md §3)."""
    paper: PaperOptions = field(default_factory=PaperOptions)
    """The paper's rotation and translation searches (docs/method.md §4-§5)."""
    windows: WindowOptions = field(default_factory=WindowOptions)
    """Windows over frames when no set of tracks is seen in every frame."""
    bundle: BundleOptions = field(default_factory=BundleOptions)
    """The joint refinement (line bundle adjustment)."""
    refine: bool = True
    """Run the bundle adjustment after the paper's method (False: the paper's method alone)."""
    progress: bool = False
    """A progress bar on stderr: the furthest frame the estimate has reached, and the stage."""
    local_iterations: int = 10
    """Iterations of the local bundle adjustment after each window is chained."""
    restart_without_outliers: bool = True
    """When the refinement flags outlier tracks, solve again from scratch without them and keep
    the better of the two solutions (robust initialisation)."""
    multistart: bool = True
    """When one window covers the sequence, also refine from the paper's alternative starting
    solutions (``PaperSolution.alternatives``: translations from other second views) and keep
    the solution with the lowest final cost, the maximum-likelihood criterion. At high noise
    the bundle adjustment from the paper's solution alone can stop in a wrong local minimum."""
    extend: IncrementalOptions | None = field(default_factory=IncrementalOptions)
    """Register the frames beyond the chained windows from the lines already reconstructed,
    frame by frame (docs/estimator.md, stage 5b); None: the chain's frames only."""
    rotation_only: RotationOnlyOptions = field(default_factory=RotationOnlyOptions)
    """The rotation-only fit, for a camera that turns without moving (docs/method.md §13)."""
    rotation_only_max_median_deg: float = 0.2
    """When the paper's method finds no motion, the rotation-only fit is the result if it
    explains the NVs this well (median angle, degrees); otherwise the paper's error stands.
    Translation changes the NVs by the parallax the paper's method needs (at least
    ``paper.min_parallax_deg``), which no rotation can explain."""
    readjust_rounds: int = 2
    """Adjust again from the adjusted solution at most this many times, while it lowers the
    cost (:func:`_readjusted`); 0: never."""
    line_camera_ratio: float = 0.05
    """A line of the main trajectory that passes this close to a camera that sees it (relative
    to its median distance from those cameras) is taken for a false minimum of the adjustment
    and moved off the camera (:func:`_lines_off_cameras`); 0: never. A real line that close
    would nearly touch the lens, where it is not imaged as a line."""
    line_camera_iterations: int = 1000
    """Levenberg-Marquardt iterations of the polish after :func:`_lines_off_cameras` moved
    lines off the cameras (the frames around them come back slowly)."""
    bootstrap_frames: int | None = 1000
    """In a longer sequence, the chain of windows is built on the first stretch of this many
    frames that gives one (then on the next half-overlapping stretch, ...), and the registration
    of stage 5b poses the rest: the cost per frame does not grow with the length. None: the
    windows cover the whole sequence."""
    short_bootstrap_frames: int | None = 100
    """In a sequence of at least twice this many frames (and a longer ``bootstrap_frames``),
    the whole estimate is also made from a chain of windows on a stretch of this many frames
    only, the registration posing the rest; also on the frames in reverse order; and the one
    whose poses explain the tracks best wins (:func:`_better_start`): a chain of windows can
    drift where each window holds few lines (a turn, short tracks) and the adjustment then
    stays in a wrong basin, where poses registered from lines already fixed do not; a short
    chain can itself start wrong. None: only ``bootstrap_frames``."""
    start_margin: float = 0.001
    """Another start than the first is kept only where its score (:func:`_better_start`) is
    below the first start's by more than this fraction: nearly equal scores (a tie) keep the
    first. Small, so that two fits half a percent apart are told apart."""
    min_segment_frames: int = 30
    """Where the registration stops and at least this many frames remain without a pose, the
    estimator starts again on them: a new segment in its own world and scale
    (``trajectory_segment_<k>.tum``). 0: no new segments."""
    max_segments: int | None = None
    """At most this many new starts (joined or not); None: as many as the stretches left
    without a pose need (each is at least ``min_segment_frames`` long, so a sequence of F
    frames has fewer than F / ``min_segment_frames`` new starts beside those that fail; a fixed
    cap would leave the later parts of a long video without a pose)."""
    join_max_angle_deg: float = 1.0
    """Two pieces are joined when their common lines' directions agree within this (median,
    degrees) under the similarity between them ..."""
    join_max_distance: float = 0.2
    """... and the lines' points within this fraction of the lines' distance from the cameras
    (median) ..."""
    max_half_turn_run: int = 30
    """Runs of at most this many frames turned by a half turn against the frames around them
    are turned back where the lines allow it (``_repair_half_turns``)."""
    join_max_gap: int = 20
    """Only pieces at most this many frames apart are joined (a rotation the lines allow is
    picked by the turn between them; Manhattan scenes allow several) ..."""
    join_max_speed_ratio: float = 2.0
    """... the camera's speed (median step) on the two sides of the junction differs by at
    most this factor under the similarity ..."""
    restart_overlap: int = 30
    """A new start next to a piece is grown, by the registration from its own lines, into up
    to this many of that piece's frames (strategy "overlap"), so that the two pieces pose some
    frames in common and are joined by those frames' poses (better fixed than by the few lines
    they share). 0: joined by their common lines only."""
    join_min_frames: int = 5
    """Two pieces that pose at least this many frames in common are joined by the similarity
    of those frames' poses (their rotations within ``join_max_frame_angle_deg``, median, and
    their centres within ``join_max_distance`` of the camera's path over those frames); fewer,
    or where that join fails: by their common lines."""
    join_max_frame_angle_deg: float = 3.0
    """See ``join_min_frames`` (each piece's rotations drift by up to a degree or two over the
    frames they share where each frame sees a handful of lines)."""
    join_window: int = 30
    """... and the frames this far from the junction are adjusted together to check that the
    pieces fit ..."""
    join_max_turn_deg: float = 10.0
    """The camera turns at most this much per frame across a break (it picks the rotation
    between the pieces among those the lines allow) ..."""
    join_max_residual_factor: float = 1.5
    """... and the bundle adjustment of the joined piece ends with an RMS residual at most this
    times the larger of the two pieces' own."""
    estimator: str = "auto"
    """``"windows"``: the paper's method on windows, chained, adjusted and rescued by the
    strategies below; ``"global"``: the global estimator (:mod:`omni_sfm.estimate.
    global_estimator`: rotations of all frames at once, positions of all frames at once, one
    bundle adjustment), which uses ``vanishing``, ``bundle`` and ``global_`` only; ``"auto"``:
    the windows where one window covers the sequence (the paper's setting), the global
    estimator otherwise (:func:`chosen_estimator`)."""
    auto_global_max_frames: int = 2000
    """``auto`` takes the windows for a sequence of more frames than this: on longer walks with
    few lines the frames the global estimator trusts are not yet reliable (docs/estimator.md,
    "Which estimator runs")."""
    global_: GlobalOptions = field(default_factory=GlobalOptions)
    """The global estimator's options (``estimator="global"``); its parallel-family detection
    and bundle adjustment are ``vanishing`` and ``bundle`` above."""
    workers: int | None = None
    """Processes that run independent solves at once: the global estimator's windows, starts
    and adjustments (``GlobalOptions.workers``), the windows estimator's starts of
    :func:`_better_start` (docs/estimator.md stage 9: the short bootstrap and the reversed
    start each in a child process of its own beside the first start); 1: one after the other
    in this process; None: 2 where the machine has more than one core. The result is the same
    whatever the number."""
    multistart_min_difference: float = 0.05
    """An alternative start is refined only if its camera centres differ from every start
    already refined by more than this fraction (RMS, after least-squares scaling) of the RMS
    distance of the cameras from the first: nearby starts fall into the same basin (at low
    noise all starts agree and nothing extra is run)."""


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


@dataclass
class _Init:
    rotations: FloatArray
    positions: FloatArray
    frames: np.ndarray
    windows: list[Window]
    failures: list[str]
    members: np.ndarray
    vpv: FloatArray
    alternatives: list[tuple[FloatArray, FloatArray]] = field(default_factory=list)
    reasons: dict[int, str] = field(default_factory=dict)
    """Why frames the incremental registration reached were not registered."""
    families: list[int] = field(default_factory=list)
    """Sizes of the parallel families found (largest first; the windows use the first)."""
    switched: list[str] = field(default_factory=list)
    """Windows solved with another family, because the first was degenerate there."""
    repairs: int = 0
    """Frames turned back from a half turn (``_repair_half_turns``)."""

    def registered(self, R: FloatArray, c: FloatArray, added: np.ndarray) -> _Init:
        """These initial poses with the frames ``added`` by a registration at their registered
        poses ``R``, ``c`` (the paper's method gave them none: the initial trajectory of a
        piece must have a pose for each of its frames)."""
        R0, c0 = self.rotations.copy(), self.positions.copy()
        R0[added], c0[added] = R[added], c[added]
        return replace(self, rotations=R0, positions=c0, frames=self.frames | added)


def _check_counts(tracks: LineTracks, members: np.ndarray) -> None:
    n_par = int(members.sum())
    n_other = tracks.num_tracks - n_par
    if n_par < 3:
        raise OmniSfmError(f"found {n_par} parallel lines; need at least 3 lines of one "
                           f"parallel family")
    if n_other < 3:
        raise OmniSfmError(f"found {n_par} parallel lines but only {n_other} other lines; need "
                           f"at least 3 lines not parallel to the family")


def _lift_init(i: _Init, start: int, idx: np.ndarray, F: int, M: int) -> _Init:
    """An :class:`_Init` of frames ``start..`` and tracks ``idx`` (:func:`frame_range`) in the
    indices of the whole sequence (``F`` frames, ``M`` tracks)."""
    rows = slice(start, start + len(i.frames))

    def frames_of(a: np.ndarray, fill: Any) -> np.ndarray:
        return scatter_rows(a, rows, F, fill)

    return _Init(frames_of(i.rotations, np.nan), frames_of(i.positions, np.nan),
                 frames_of(i.frames, False),
                 [Window(w.start + start, w.stop + start, idx[w.tracks]) for w in i.windows],
                 list(i.failures), scatter_rows(i.members, idx, M, False),
                 frames_of(i.vpv, np.nan),
                 reasons={start + k: v for k, v in i.reasons.items()}, families=i.families,
                 switched=i.switched, repairs=i.repairs)


def _initialise(tracks: LineTracks, options: EstimationOptions, run: RunLog) -> _Init:
    """The chain of windows that starts the solution: on the whole sequence, or for a long one
    on the first stretch of ``bootstrap_frames`` frames that gives one (the registration of
    stage 5b poses the rest; the cost per frame then does not grow with the length)."""
    F, M, L = tracks.num_frames, tracks.num_tracks, options.bootstrap_frames
    if L is None or F <= L:
        return _initialise_all(tracks, options, run)
    errors: list[str] = []
    for start in range(0, F - 2, L // 2):
        stop = min(F, start + L)
        sub, idx = frame_range(tracks, start, stop)
        try:
            init = _initialise_all(sub, options, run.at(start, share_timings=True))
        except OmniSfmError as exc:
            errors.append(f"frames {start}-{stop - 1}: {exc}")
            run.record(failed("bootstrap stretch", (start, stop - 1), str(exc)))
            continue
        run.record(Attempt("bootstrap stretch", (start, stop - 1), init,
                           why=f"{int(init.frames.sum())} frames chained"))
        return _lift_init(init, start, idx, F, M)
    raise OmniSfmError(errors[0] if len(errors) == 1 else
                       f"cannot estimate any frame: no stretch of {L} frames starts a "
                       f"solution ({errors[0]})")


def _window_plan(tracks: LineTracks, members: np.ndarray, frame_ok: np.ndarray,
                 options: EstimationOptions) -> list[Window]:
    """One window over the sequence where every frame has the family's VPV and enough of its
    lines and others are seen in every frame; else :func:`plan_windows`."""
    F, M = tracks.num_frames, tracks.num_tracks
    vis = tracks.visibility()
    full = vis[:, frame_ok].all(1) if frame_ok.any() else np.zeros(M, bool)
    if frame_ok.all() and (full & members).sum() >= options.windows.min_parallel and \
            (full & ~members).sum() >= options.windows.min_other:
        return [Window(0, F, np.flatnonzero(full))]
    return plan_windows(tracks, members, frame_ok, options.windows)


def _solve_windows(tracks: LineTracks, family: ParallelFamily, others: list[ParallelFamily],
                   windows: list[Window], options: EstimationOptions, run: RunLog
                   ) -> tuple[list[Attempt[PaperSolution]], list[str], list[str]]:
    """Each window by the paper's method with the largest family, else with another one:
    ``(attempts, failures, windows solved with another family)``."""
    solved: list[Attempt[PaperSolution]] = []
    failures: list[str] = []
    switched: list[str] = []
    for w in windows:
        att = _solve_window(tracks, family, w, options, run)
        run.reached(w.stop - 1)
        if not att.ok:
            # the family may be degenerate for this stretch (the corridor's direction, along
            # which the camera walks): the window's other families may condition it
            run.record(att)
            alt = _other_family(tracks, others, w, options, run)
            if alt is None:
                failures.append(f"frames {w.start}-{w.stop - 1}: {att.why}")
            else:
                switched.append(f"frames {w.start}-{w.stop - 1}: {alt.why} ({att.why})")
                att = alt
        if att.solution is not None:
            run.add_times(att.solution.timings_ms)
        solved.append(att)
    return solved, failures, switched


def _local_refine(tracks: LineTracks, local_opts: BundleOptions, run: RunLog, R: FloatArray,
                  c: FloatArray, local: np.ndarray, old: np.ndarray
                  ) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """:func:`chain_windows`' refinement: the ``local`` frames adjusted, the ``old`` ones
    holding the scale; where it fails, the chained poses stand (recorded)."""
    M = tracks.num_tracks
    try:
        res = bundle_adjust(tracks, R, c, np.full((M, 3), np.nan), np.full((M, 3), np.nan),
                            frames=local, scale_frames=old, options=local_opts)
    except OmniSfmError as exc:
        idx = np.flatnonzero(local)
        run.record(failed("local adjustment", (int(idx[0]), int(idx[-1])),
                          f"{exc}; the chained poses stand unadjusted"))
        return R, c, local
    return res.rotations, res.positions, res.frames


def _unpolished(tracks: LineTracks, family: ParallelFamily, windows: list[Window],
                options: EstimationOptions, run: RunLog, k: int
                ) -> tuple[FloatArray, FloatArray] | None:
    """:func:`chain_windows`' other solution of window ``k``, which disagrees with the chain:
    the paper's method without the rotation polish (None where the polish is off or it
    fails)."""
    if not options.paper.polish_rotation:
        return None
    att = _paper(tracks, family, windows[k], replace(options.paper, polish_rotation=False),
                 "paper window, unpolished")
    if att.solution is None:
        run.record(att)
        return None
    run.record(replace(att, why="the polished solution disagrees with the chain"))
    return np.asarray(att.solution.rotations), np.asarray(att.solution.positions)


def _initialise_all(tracks: LineTracks, options: EstimationOptions, run: RunLog) -> _Init:
    """Family, windows, the paper's method per window, chaining (world/scale of the chain)."""
    with run.timed("parallel_lines"):
        family = detect_parallel_family(tracks, options.vanishing)
        others = [f for f in detect_parallel_families(tracks, options.vanishing)[1:]
                  if f.size >= 3]
    members = np.asarray(family.members, bool)
    _check_counts(tracks, members)
    F = tracks.num_frames
    frame_ok: np.ndarray = np.asarray(np.isfinite(family.vpv).all(1))
    windows = _window_plan(tracks, members, frame_ok, options)
    solved, failures, switched = _solve_windows(tracks, family, others, windows, options, run)
    solutions = [None if a.solution is None else
                 (np.asarray(a.solution.rotations), np.asarray(a.solution.positions))
                 for a in solved]
    # a few iterations suffice to stop errors from accumulating along the chain
    local_opts = replace(options.bundle, max_rounds=2,
                         max_iterations=options.local_iterations,
                         final_loss=None)
    refine = partial(_local_refine, tracks, local_opts, run)
    resolve = partial(_unpolished, tracks, family, windows, options, run)
    with run.timed("chaining"):
        chain = chain_windows(F, windows, solutions, refine if len(windows) > 1 else None,
                              options.windows.max_disagreement_deg, resolve)
    for k, att in enumerate(solved):
        if att.solution is None or k in chain.chained:
            run.record(att)
        else:
            run.record(att.judged(Outcome.REJECTED, chain.skipped.get(k, "not chained")))
    done = chain.estimated
    if done.sum() < 3:
        why = "; ".join(failures[:3]) if failures else \
            "no stretch of 3 or more frames sees 3 parallel and 3 other lines in every frame"
        raise OmniSfmError(f"cannot estimate any frame: {why}")
    alternatives: list[tuple[FloatArray, FloatArray]] = []
    only = solved[0].solution
    if len(windows) == 1 and windows[0].start == 0 and windows[0].stop == F and \
            only is not None and done.all():
        # the chain is this window's solution as it is: its alternatives apply directly
        alternatives = [(np.asarray(R), np.asarray(c)) for R, c in only.alternatives]
    return _Init(chain.rotations, chain.positions, done, [windows[i] for i in chain.chained],
                 failures, members, np.asarray(family.vpv), alternatives,
                 families=[int(family.size)] + [int(f.size) for f in others],
                 switched=switched)


def _other_family(tracks: LineTracks, others: list[ParallelFamily], w: Window,
                  options: EstimationOptions, run: RunLog) -> Attempt[PaperSolution] | None:
    """The paper's solution of window ``w`` with the first other family that gives one (3 of
    its tracks and 3 others seen throughout the window); the attempts that fail are recorded."""
    for k, fam in enumerate(others):
        m = np.asarray(fam.members, bool)[w.tracks]
        if m.sum() < options.windows.min_parallel or (~m).sum() < options.windows.min_other:
            continue
        att = _solve_window(tracks, fam, w, options, run, "paper window, another family")
        if att.ok:
            return replace(att, why=f"family {k + 2}" + (f", {att.why}" if att.why else ""))
        run.record(att, family=k + 2)
    return None


_HALF_TURN_DEG = 90.0


def _paper(tracks: LineTracks, family: ParallelFamily, w: Window, paper: PaperOptions,
           strategy: str) -> Attempt[PaperSolution]:
    """Strategy: the paper's method (:func:`estimate_paper`) on window ``w`` with ``family``."""
    frames = (w.start, w.stop - 1)
    try:
        sol = estimate_paper(window_tracks(tracks, w), window_family(family, w), paper)
    except OmniSfmError as exc:
        return failed(strategy, frames, str(exc))
    return Attempt(strategy, frames, sol, cost_deg=_paper_cost(sol))


def _paper_cost(sol: PaperSolution) -> float:
    """RMS angle (deg) of the paper's solution against the window's normals, when it says."""
    return float(sol.costs.get("rms_deg", np.nan))


def _solve_window(tracks: LineTracks, family: ParallelFamily, w: Window,
                  options: EstimationOptions, run: RunLog,
                  strategy: str = "paper window") -> Attempt[PaperSolution]:
    """The paper's solution of one window; without the rotation polish where the polished
    rotations jump between consecutive frames (see ``WindowOptions.max_rotation_step_deg``;
    that attempt is recorded). Fails where the paper's method fails, or (frames consecutive:
    ``PaperOptions.rotation_continuity``) its solution still turns by a half turn between two
    consecutive frames."""
    att = _paper(tracks, family, w, options.paper, strategy)
    limit = options.windows.max_rotation_step_deg
    if att.solution is None:
        return att
    if options.paper.polish_rotation and \
            max_rotation_step_deg(np.asarray(att.solution.rotations)) > limit:
        alt = _paper(tracks, family, w, replace(options.paper, polish_rotation=False),
                     "paper window, unpolished")
        jump = f"the polished rotations jump by more than {limit} deg between frames"
        if alt.solution is not None and \
                max_rotation_step_deg(np.asarray(alt.solution.rotations)) <= limit:
            run.record(att.judged(Outcome.REJECTED, jump))
            att = replace(alt, why=f"{strategy}: {jump}")
        elif alt.solution is not None:
            run.record(alt.judged(Outcome.REJECTED, "its rotations jump too"))
        else:
            run.record(alt)
    # a half turn between two video frames is a flip of the rotation search, not motion: the
    # frames after it would carry the flip into the chain (frames that are not consecutive,
    # rotation_continuity off, may turn that much)
    assert att.solution is not None
    step = max_rotation_step_deg(np.asarray(att.solution.rotations))
    if options.paper.rotation_continuity and step > _HALF_TURN_DEG:
        return failed(att.strategy, att.frames, f"its solution turns by {step:.0f} deg between two "
                                            f"consecutive frames (a flip of the rotation search)")
    return att


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
        ba = bundle_adjust(tracks, R, c, d, p, frames=frames, options=options.bundle)
    except OmniSfmError as exc:
        return failed(strategy, span, str(exc))
    return Attempt(strategy, span, ba, cost_deg=ba.rms_final_deg,
                   why=f"{int(ba.frames.sum())} frames, {int(ba.outlier_tracks.sum())} outlier "
                       f"tracks")


def _refine(tracks: LineTracks, init: _Init, options: EstimationOptions,
            run: RunLog) -> BundleResult:
    """The bundle adjustment of the chain, and from the paper's distinct alternative starts
    (multi-start): the lowest final cost wins. Raises where the adjustment of the chain fails."""
    with run.timed("refinement"):
        first = _bundle(tracks, init.rotations, init.positions, init.frames, options,
                        "bundle adjustment")
    if first.solution is None:
        run.record(first)
        raise OmniSfmError(f"the bundle adjustment failed: {first.why}")
    best = first
    tried: list[Attempt[BundleResult]] = []
    if options.multistart and init.alternatives:
        # the same frames and at least as many tracks, so the final costs are comparable
        idx = np.flatnonzero(init.frames)
        c0 = init.positions[idx]
        spread = float(np.sqrt(np.mean(np.sum((c0 - c0[0]) ** 2, axis=1))))
        starts = [c0]
        for R_alt, c_alt in init.alternatives:
            ca = c_alt[idx]
            if min(float(np.sqrt(np.mean(np.sum((ca - t) ** 2, axis=1)))) for t in starts) <= \
                    options.multistart_min_difference * spread:
                continue  # the same basin as a start already refined
            starts.append(ca)
            with run.timed("refinement"):
                alt = _bundle(tracks, R_alt, c_alt, init.frames, options,
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


def estimate_poses(tracks: LineTracks,
                   options: EstimationOptions = EstimationOptions()) -> EstimationResult:
    """Poses of all estimable frames from tracked line normals (see the module docstring).

    Raises:
        OmniSfmError: fewer than 3 frames, fewer than 3 parallel or 3 other lines, degenerate
            motion, or no stretch of frames that the paper's method can solve.
    """
    t_all = time.perf_counter()
    F, M = tracks.num_frames, tracks.num_tracks
    if F < 3:
        raise OmniSfmError(f"tracks have {F} frames; need at least 3")
    if M < 6:
        raise OmniSfmError(f"tracks have {M} lines; need at least 6 (3 parallel and 3 others)")
    start_workers(options)  # a bad number of workers fails here, whatever the sequence
    estimator, why = chosen_estimator(tracks, options)
    if estimator == "global":
        res = _global_result(tracks, options, t_all)
        return replace(res, report=replace(res.report, estimator="global", estimator_choice=why))
    with tqdm(total=F, desc="poses", unit="frame", leave=False,
              disable=None if options.progress else True) as bar:
        res = _estimate(tracks, options, RunLog(progress=bar if options.progress else None),
                        t_all)
    return replace(res, report=replace(res.report, estimator="windows", estimator_choice=why))


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


def chosen_estimator(tracks: LineTracks, options: EstimationOptions) -> tuple[str, str]:
    """The estimator that ``options.estimator`` names (``windows`` or ``global``) and why.

    ``auto`` takes the windows where one window covers the sequence (a vanishing point in
    every frame and at least ``windows.min_parallel`` lines of the parallel family and
    ``windows.min_other`` others seen in every frame: the paper's setting, where its method
    reaches the maximum-likelihood floor, docs/estimator.md), where its parts share no line
    (each gets a world of its own) and for more than ``auto_global_max_frames`` frames.
    Anywhere else (lines that come and go, a walk longer than its lines) it takes the global
    estimator, which needs no line seen throughout. The choice depends on the number of
    frames and on which lines each sees, not on their order or on the normals' last bits.

    Raises:
        OmniSfmError: an unknown name; for ``auto``, lines seen throughout of which fewer than
            3 are parallel or fewer than 3 are not (the windows' own error).
    """
    if options.estimator not in ("auto", "windows", "global"):
        raise OmniSfmError(f"unknown estimator {options.estimator!r}: 'auto', 'windows' or "
                           f"'global'")
    if tracks.obs_offset is not None:  # a rig of lenses
        if options.estimator == "windows":
            raise OmniSfmError("the windows estimator takes a central camera; a rig's tracks "
                               "(lens offsets) need the global estimator (--estimator global "
                               "or auto)")
        return "global", ("asked for" if options.estimator == "global" else
                          "auto: a rig of lenses (the global estimator takes each observation "
                          "from its lens)")
    if options.estimator in ("windows", "global"):
        return options.estimator, "asked for"
    if tracks.num_frames > options.auto_global_max_frames:
        return "windows", (f"auto: {tracks.num_frames} frames, more than the global estimator "
                           f"takes ({options.auto_global_max_frames})")
    w = options.windows
    cut = _first_cut(tracks)
    if cut is not None:
        return "windows", (f"auto: no line is seen on both sides of frame {cut} (parts with "
                           f"nothing in common: the windows pose each in a world of its own)")
    full = tracks.visibility().all(1)
    if int(full.sum()) < w.min_parallel + w.min_other:
        return "global", (f"auto: {int(full.sum())} lines seen in every frame, fewer than one "
                          f"window needs ({w.min_parallel} parallel + {w.min_other} others)")
    family = detect_parallel_family(tracks, options.vanishing)
    members = np.asarray(family.members, bool)
    _check_counts(tracks, members)
    if bool(np.isfinite(family.vpv).all()) and int((full & members).sum()) >= w.min_parallel \
            and int((full & ~members).sum()) >= w.min_other:
        return "windows", (f"auto: one window covers every frame ({int((full & members).sum())} "
                           f"parallel and {int((full & ~members).sum())} other lines seen "
                           f"throughout)")
    return "global", (f"auto: no window covers every frame ({int((full & members).sum())} "
                      f"parallel and {int((full & ~members).sum())} other lines seen "
                      f"throughout, a vanishing point in "
                      f"{int(np.isfinite(family.vpv).all(1).sum())} of {tracks.num_frames} "
                      f"frames)")


def _estimate(tracks: LineTracks, options: EstimationOptions, run: RunLog,
              t_all: float) -> EstimationResult:
    try:
        result = _better_start(tracks, options, run, t_all)
    except OmniSfmError as exc:
        rot_only = _try_rotation_only(tracks, options, run, f"the moving camera's solution "
                                                            f"failed: {exc}")
        if rot_only is None:
            raise
        return _rotation_only_result(tracks, rot_only, options, run, str(exc), t_all)
    if result.estimated.all():
        return result
    # the paper's method found motion in a part of the sequence only: if the rotations alone
    # explain every frame, the camera turned in place and that "motion" was noise
    why = (f"the paper's method estimated only {int(result.estimated.sum())} of "
           f"{tracks.num_frames} frames")
    rot_only = _try_rotation_only(tracks, options, run, why, better_than=result)
    if rot_only is not None:
        return _rotation_only_result(tracks, rot_only, options, run, why, t_all)
    return replace(result, report=replace(result.report, attempts=run.entries))


def _global_result(tracks: LineTracks, options: EstimationOptions,
                   t_all: float) -> EstimationResult:
    """The global estimator's solution (:func:`solve_global`) with the conventions (world,
    scale, reflection) and the report of every estimate; a camera that only turned gets the
    rotation-only fit, as with the windows."""
    run = RunLog(progress=None)
    gopts = replace(options.global_, vanishing=options.vanishing, bundle=options.bundle,
                    workers=start_workers(options))
    try:
        sol = solve_global(tracks, gopts)
    except OmniSfmError as exc:
        rot_only = _try_rotation_only(tracks, options, run, f"the global estimator failed: "
                                                            f"{exc}")
        if rot_only is None:
            raise
        return _rotation_only_result(tracks, rot_only, options, run, str(exc), t_all)
    frames = sol.frames
    R_n, c_n, d_n, p_n = _normalise(sol.rotations, sol.positions, frames, sol.line_directions,
                                    sol.line_points)
    idx = np.flatnonzero(frames)
    front, behind = side_votes(tracks, R_n, c_n, d_n, p_n, frames, sol.used_tracks)
    reflection = "unresolved: the tracks carry no rays (" + REFLECTION_NOTE + ")"
    if front + behind > 0:
        if behind > front:
            o = c_n[idx[0]].copy()
            c_n, p_n = 2.0 * o - c_n, 2.0 * o - p_n
            front, behind = behind, front
        reflection = (f"resolved by the observations' rays: {front} see their line in front, "
                      f"{behind} behind")
    members = sol.members
    pd = d_n[members & sol.used_tracks]
    direction = np.full(3, np.nan)
    if len(pd):
        pd = pd * np.sign(pd @ pd[0])[:, None]
        direction = pd.mean(0) / np.linalg.norm(pd.mean(0))
    timings = dict(sol.timings_ms)
    timings["total"] = (time.perf_counter() - t_all) * 1e3
    traj = Trajectory(tracks.timestamps[idx].copy(), R_n[idx], c_n[idx])
    report = replace(
        _report(tracks, frames, members, direction, sol.outlier_tracks, sol.used_tracks, [], [],
                timings, sol.rms_initial_deg, sol.rms_final_deg, sol.sigma_deg),
        estimator="global", reflection=reflection, steps=sol.steps,
        world_directions=[[float(x) for x in v @ sol.rotations[idx[0]]]
                          for v in sol.world_directions],
        frames_not_estimated_reasons={str(k): v for k, v in sol.not_posed.items()},
        frames_uncertain={str(k): v for k, v in sol.uncertain.items()},
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
            "their offsets to matter): the lenses taken as one centre"))
    idx = np.flatnonzero(frames)
    span = float(np.linalg.norm(sol.positions[idx[-1]] - sol.positions[idx[0]]))
    if not scale.fixed:
        return RigScaleRecord(metres_per_unit=span / scale.scale, note=(
            "a rough metric scale: the lines are too far for the lenses' baseline to fix it "
            "(or for their offsets to matter), the lenses taken as one centre"))
    return RigScaleRecord(metres_per_unit=span, note=(
        "metric scale from the baseline between the lenses (the adjustment in metres, docs/"
        "estimator.md \"Rigs\")"))


def _capped_rms_deg(tracks: LineTracks, R: FloatArray, c: FloatArray, frames: np.ndarray,
                    limit: float, *, everywhere: bool = False) -> float:
    """:func:`~omni_sfm.estimate.bundle.truncated_cost` as an RMS angle in degrees: the score
    by which two solutions that rejected different tracks (or posed different frames) are
    compared."""
    return float(np.degrees(np.sqrt(truncated_cost(tracks, R, c, frames, limit,
                                                   everywhere=everywhere))))


@dataclass(frozen=True)
class _OtherStart:
    """A start beside the first one (:func:`_better_start`), computed on its own log: its
    solution and result (or the error that stopped it) and the attempts it recorded."""

    sol: _Solved | None
    result: EstimationResult | None
    error: OmniSfmError | None
    entries: list[AttemptRecord]


def _short_start(tracks: LineTracks, other: EstimationOptions, t_all: float,
                 progress: CountedProgress | None) -> _OtherStart:
    """Strategy "short bootstrap": the moving camera's solution from a chain of windows on
    ``other.bootstrap_frames`` frames, with its segments."""
    log = RunLog(progress=progress)
    try:
        sol = _solve_moving(tracks, other, log)
        return _OtherStart(sol, _with_segments(tracks, sol, other, log, t_all), None, log.entries)
    except OmniSfmError as exc:
        return _OtherStart(None, None, exc, log.entries)


def _reversed_job(tracks: LineTracks, options: EstimationOptions, t_all: float,
                  progress: CountedProgress | None) -> _OtherStart:
    """:func:`_reversed_start` on its own log."""
    log = RunLog(progress=progress)
    return _OtherStart(None, _reversed_start(tracks, options, log, t_all), None, log.entries)


def start_workers(options: EstimationOptions) -> int:
    """The processes that run the starts of :func:`_better_start` at once (``options.workers``;
    None: two where the machine has more than one core)."""
    if options.workers is not None:
        if options.workers < 1:
            raise OmniSfmError(f"workers must be at least 1, got {options.workers}")
        return int(options.workers)
    return 2 if (os.cpu_count() or 1) > 1 else 1


def _better_start(tracks: LineTracks, options: EstimationOptions, run: RunLog,
                  t_all: float) -> EstimationResult:
    """The moving camera's result from the chain of windows on ``bootstrap_frames`` and,
    where ``short_bootstrap_frames`` applies and the first result chained more than one
    window, three more (docs/estimator.md stage 9): strategy "short bootstrap", the same from a
    chain on that many frames, strategy "merged starts", the short one's main piece with
    the frames it lacks taken from the first one's (:func:`_merged_starts`), and strategy
    "reversed start", the first one's on the frames in reverse order (:func:`_reversed_start`).
    The kept one has the lowest cost over every observation of the sequence (each misfit
    capped at the first one's outlier limit, the observations of frames that a result leaves
    without a pose at the cap); another than the first must be lower by more than
    ``options.start_margin``. Raises
    where none gives a result.

    With more than one worker (:func:`start_workers`) the short bootstrap and the reversed
    start run in child processes of their own (:class:`~omni_sfm.forked.Deferred`) beside
    the first start, from the moment its chain is known to have more than one window (with
    one they are not run); with one worker, after it, in this process. Each start
    records its attempts on its own log, added to ``run``'s in the same order either way, and
    the result is the same."""
    F, short, long = tracks.num_frames, options.short_bootstrap_frames, options.bootstrap_frames
    others = not (short is None or 2 * short > F or (long is not None and long <= short))
    other = replace(options, bootstrap_frames=short, short_bootstrap_frames=None)
    if not others:
        return _best_of_starts(tracks, options, other, run, t_all, [], fork=False)
    # their progress: frames reached by each, summed on a bar of their own
    counters = SharedCounters(2)
    bars: list[tqdm[Any]] = []

    def refresh() -> None:  # the bar appears when this process first waits for them
        if run.progress is None:
            return
        if not bars:
            bars.append(tqdm(total=2 * F, desc="other starts", unit="frame", leave=False,
                             disable=None))
        bars[0].update(counters.total() - bars[0].n)

    shown = [CountedProgress(counters, k, refresh) if run.progress is not None else None
             for k in range(2)]
    jobs = [Deferred(lambda: _short_start(tracks, other, t_all, shown[0])),
            Deferred(lambda: _reversed_job(tracks, options, t_all, shown[1]))]
    try:
        return _best_of_starts(tracks, options, other, run, t_all, jobs,
                               fork=start_workers(options) > 1, refresh=refresh)
    finally:
        for job in jobs:
            job.cancel()
        for bar in bars:
            bar.close()


def _best_of_starts(tracks: LineTracks, options: EstimationOptions, other: EstimationOptions,
                    run: RunLog, t_all: float, jobs: list[Deferred[_OtherStart]], *,
                    fork: bool, refresh: Callable[[], None] | None = None) -> EstimationResult:
    """:func:`_better_start` with its other starts' ``jobs`` (none where they do not apply),
    started in child processes (``fork``) once the first start's chain has more than one
    window."""
    F, long = tracks.num_frames, options.bootstrap_frames
    sol_a: _Solved | None = None
    first: EstimationResult | None = None
    error: OmniSfmError | None = None

    def chained(init: _Init) -> None:
        if fork and len(init.windows) > 1:
            for job in jobs:
                job.start()

    try:
        sol_a = _solve_moving(tracks, options, run, chained)
        first = _with_segments(tracks, sol_a, options, run, t_all)
    except OmniSfmError as exc:
        error = exc
    if not jobs:
        if first is None:
            assert error is not None
            raise error
        return first
    if first is not None and len(first.report.windows or []) <= 1:
        # one window of the paper's method covers the sequence: no chain to drift
        run.record(Attempt("short bootstrap", (0, F - 1), None, outcome=Outcome.SKIPPED,
                           why="one window covers the sequence"))
        return replace(first, report=replace(first.report, attempts=run.entries))
    if refresh is not None:
        refresh()
    b = jobs[0].result(refresh)
    run.entries.extend(b.entries)
    if b.error is not None or b.sol is None or b.result is None:
        run.record(failed("short bootstrap", (0, F - 1), str(b.error)))
        if first is None:
            assert error is not None
            raise error from b.error
        return replace(first, report=replace(first.report, attempts=run.entries))
    sol_b, alt = b.sol, b.result
    if first is None or sol_a is None:
        run.record(Attempt("short bootstrap", (0, F - 1), alt,
                           why=f"{int(alt.estimated.sum())} frames; the chain on "
                               f"{long} frames failed: {error}"))
        return replace(alt, report=replace(alt.report, attempts=run.entries))
    candidates = [("short bootstrap", alt)]
    merged_sol = _merged_starts(tracks, sol_b, sol_a, other, run)
    if merged_sol is not None:
        candidates.append(("merged starts", _with_segments(tracks, merged_sol, other, run,
                                                           t_all)))
    c = jobs[1].result(refresh)
    run.entries.extend(c.entries)
    backwards = c.result
    if backwards is not None:
        candidates.append(("reversed start", backwards))
    kept = _kept_start(tracks, first, candidates, options, run)
    return replace(kept, report=replace(kept.report, attempts=run.entries))


def _kept_start(tracks: LineTracks, first: EstimationResult,
                candidates: list[tuple[str, EstimationResult]], options: EstimationOptions,
                run: RunLog) -> EstimationResult:
    """The first start's result or the best of the other starts' named ``candidates``, where
    it scores better by ``options.start_margin`` (every observation, misfits capped; ties by
    :func:`_least_squares_among_ties`); each candidate recorded as kept or rejected."""
    F = tracks.num_frames
    limit = outlier_limit(np.radians(first.sigma_deg), options.bundle)

    def score(r: EstimationResult) -> float:
        return _capped_rms_deg(tracks, scatter_rows(r.trajectory.rotations, r.estimated, F, np.nan),
                               scatter_rows(r.trajectory.positions, r.estimated, F, np.nan),
                               r.estimated, limit, everywhere=True)

    base = score(first)
    scores = [score(r) for _, r in candidates]
    best, ties = _least_squares_among_ties(candidates, scores, options.start_margin)
    kept = candidates[best][1] if scores[best] < (1.0 - options.start_margin) * base else first
    decided = kept is not first and best != int(np.argmin(scores))
    for i, ((name, r), sc) in enumerate(zip(candidates, scores, strict=True)):
        why = (f"{int(r.estimated.sum())} frames against {int(first.estimated.sum())}; every "
               f"observation, misfits capped at {np.degrees(limit):.3g} deg (frames without a "
               f"pose at the cap): {sc:.4g} deg RMS against {base:.4g}")
        if decided and i in ties:
            why += (f"; a tie with the same observations, decided by the adjustment's least "
                    f"squares: {r.residual_rms_final_deg:.7g} deg RMS")
        att = Attempt(name, (0, F - 1), r, cost_deg=sc, why=why)
        run.record(att if r is kept else att.judged(Outcome.REJECTED, why))
    return kept


def _least_squares_among_ties(candidates: list[tuple[str, EstimationResult]],
                              scores: list[float], margin: float) -> tuple[int, list[int]]:
    """The index of the best of ``candidates`` by their ``scores`` (capped, lines triangulated
    from the poses), except where others tie with it: one within ``margin`` of its score
    that explains the same observations (the same frames posed, the same tracks used) is
    compared with it by the adjustment's own least-squares cost, the maximum-likelihood
    criterion. The capped score is what compares solutions that kept different observations;
    between two that kept the same it is only an approximation of that cost (lines
    triangulated, not adjusted; misfits capped), whose error can exceed their difference:
    sparse seed 5, two minima 2e-6 apart in the adjustment's cost ranked the other way round
    by 4e-4 in the score (docs/estimator.md, stage 9). Also returns the indices of the tie
    (the best alone where there is none)."""
    best = int(np.argmin(scores))
    ref = candidates[best][1]
    ties = [i for i, (_, r) in enumerate(candidates)
            if scores[i] <= (1.0 + margin) * scores[best]
            and np.array_equal(r.estimated, ref.estimated)
            and np.array_equal(r.used_tracks, ref.used_tracks)]
    return min(ties, key=lambda i: (candidates[i][1].residual_rms_final_deg, i)), ties


def _reversed_start(tracks: LineTracks, options: EstimationOptions, run: RunLog,
                    t_all: float) -> EstimationResult | None:
    """Strategy "reversed start": the moving camera's solution of the frames in reverse order
    (the chain of windows on the last frames, the registration posing those before them), in
    this sequence's frame order, with its segments. A chain that starts wrong, or drifts as it
    goes, does so at the other end of the sequence. None where it fails (recorded)."""
    F = tracks.num_frames
    try:
        sol = _solve_moving(reversed_frames(tracks), options, run.reversed(F))
    except OmniSfmError as exc:
        run.record(failed("reversed start", (0, F - 1), str(exc)))
        return None
    return _with_segments(tracks, _flipped(sol, F), options, run, t_all)


def _flipped(sol: _Solved, F: int) -> _Solved:
    """A solution of the ``F`` frames in reverse order (:func:`reversed_frames`) in their own
    order: poses are per frame, lines per track."""
    i = sol.init
    init = replace(i, rotations=i.rotations[::-1].copy(), positions=i.positions[::-1].copy(),
                   frames=i.frames[::-1].copy(),
                   windows=[Window(F - w.stop, F - w.start, w.tracks) for w in i.windows[::-1]],
                   failures=[f"(frames counted from the last) {x}" for x in i.failures],
                   vpv=i.vpv[::-1].copy(),
                   alternatives=[(R[::-1].copy(), c[::-1].copy()) for R, c in i.alternatives],
                   reasons={F - 1 - k: v for k, v in i.reasons.items()})
    return replace(sol, init=init, R=sol.R[::-1].copy(), c=sol.c[::-1].copy(),
                   frames=sol.frames[::-1].copy())


def _merged_starts(tracks: LineTracks, base: _Solved, donor: _Solved, options: EstimationOptions,
                   run: RunLog, near: int = 30) -> _Solved | None:
    """Strategy: the main piece ``base`` with the frames it lacks taken from ``donor``'s main
    piece, each run of them moved into ``base``'s world by the similarity between the two
    pieces' poses on the common frames within ``near`` frames of it, then the bundle
    adjustment of all (and again from its own result). None where ``donor`` adds no frame
    (recorded as skipped) or the adjustment fails (recorded)."""
    F = tracks.num_frames
    add = donor.frames & ~base.frames
    R, c, frames = base.R.copy(), base.c.copy(), base.frames.copy()
    for a, b in runs(add):
        around = np.zeros(F, bool)
        around[max(0, a - near):min(F, b + near)] = True
        common = around & base.frames & donor.frames
        if common.sum() < 3:
            continue
        try:
            sim = similarity_from_poses(base.R[common], base.c[common], donor.R[common],
                                        donor.c[common], allow_reflection=True)
        except OmniSfmError:
            continue
        R[a:b] = sim.rotation @ donor.R[a:b]
        c[a:b] = sim.apply_points(donor.c[a:b])
        frames[a:b] = True
    if frames.sum() == base.frames.sum():
        run.record(Attempt("merged starts", (0, F - 1), None, outcome=Outcome.SKIPPED,
                           why="the first start's main piece poses no frame next to the "
                               "second's that it lacks"))
        return None
    att = _bundle(tracks, R, c, frames, options, "merged starts")
    if att.solution is None:
        run.record(att)
        return None
    ba = _readjusted(tracks, att.solution, options, run)
    init = replace(base.init.registered(ba.rotations, ba.positions, ba.frames & ~base.frames),
                   frames=ba.frames)
    return _Solved(init, ba.rotations, ba.positions, ba.frames, ba.line_directions,
                   ba.line_points, ba.used_tracks, ba.outlier_tracks, ba.rms_initial_deg,
                   ba.rms_final_deg, ba.sigma_deg)


@dataclass
class _Solved:
    """A moving camera's solution before the conventions: poses ``(F, ...)``, lines ``(M, 3)``
    (NaN where not estimated / not used), and how it was reached."""

    init: _Init
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


def _solve_moving(tracks: LineTracks, options: EstimationOptions, run: RunLog,
                  chained: Callable[[_Init], None] | None = None) -> _Solved:
    """Windows, chaining, refinement and registration of the frames beyond (world and scale of
    the chain); ``chained`` is called with the chain of windows as soon as it is known."""
    M = tracks.num_tracks
    init = _initialise(tracks, options, run)
    if chained is not None:
        chained(init)
    outliers = np.zeros(M, bool)
    if options.refine:
        ba = _refine(tracks, init, options, run)
        if options.restart_without_outliers and ba.outlier_tracks.any():
            att = _restart_without_outliers(tracks, ba, options, run)
            if att.solution is None:
                run.record(att)
            else:
                init, ba = _judge_restart(tracks, att, init, ba, options, run)
        ba = _readjusted(tracks, ba, options, run)
        if options.extend is not None and not ba.frames.all():
            ba, init = _extend(tracks, ba, init, options, run)
        R, c, frames = ba.rotations, ba.positions, ba.frames
        d, p, used, outliers = ba.line_directions, ba.line_points, ba.used_tracks, \
            ba.outlier_tracks
        rms0, rms1, sigma = ba.rms_initial_deg, ba.rms_final_deg, ba.sigma_deg
    else:
        R, c, frames = init.rotations, init.positions, init.frames
        d, p, used = triangulate_lines(tracks, R, c, frames, min_observations=3)
        ang = observation_residuals(tracks, R, c, d, p)
        ok = np.isfinite(ang)
        rms0 = rms1 = float(np.degrees(np.sqrt(np.mean(ang[ok] ** 2)))) if ok.any() else np.nan
        sigma = float(np.degrees(np.median(ang[ok]) / np.sqrt(2 * np.log(2)))) if ok.any() \
            else np.nan
    sol = _Solved(init, R, c, frames, d, p, used, outliers, rms0, rms1, sigma)
    if options.refine:
        sol = _repair_half_turns(tracks, sol, options, run)
    return sol


def _judge_restart(tracks: LineTracks, att: Attempt[tuple[_Init, BundleResult]], init: _Init,
                   ba: BundleResult, options: EstimationOptions,
                   run: RunLog) -> tuple[_Init, BundleResult]:
    """The restart without outliers (``att``) against the first solution ``init, ba``: the two
    rejected different tracks, so they are compared on all of them in the frames both pose,
    each track's misfit capped at the outlier limit; the one kept (the restart where it poses
    as many frames and scores no worse) and the judgement recorded."""
    assert att.solution is not None
    ba2 = att.solution[1]
    both = ba.frames & ba2.frames
    if both.sum() < 3:  # its chain started elsewhere: nothing to compare them on
        run.record(att.judged(Outcome.REJECTED, f"{att.why}; {int(both.sum())} frames in "
                                                f"common with the first solution"))
        return init, ba
    limit = outlier_limit(np.radians(ba.sigma_deg), options.bundle)
    score = [_capped_rms_deg(tracks, b.rotations, b.positions, both, limit) for b in (ba, ba2)]
    why = (f"{att.why}; all tracks, misfits capped at {np.degrees(limit):.3g} deg: "
           f"{score[1]:.4g} deg RMS, {score[0]:.4g} with the outliers")
    if ba2.frames.sum() >= ba.frames.sum() and score[1] <= score[0]:
        run.record(replace(att, why=why))
        return att.solution
    fewer = ba2.frames.sum() < ba.frames.sum()
    run.record(att.judged(Outcome.REJECTED, why + (
        f" (and {int(ba2.frames.sum())} frames against {int(ba.frames.sum())})"
        if fewer else "")))
    return init, ba


def _readjusted(tracks: LineTracks, ba: BundleResult, options: EstimationOptions,
                run: RunLog) -> BundleResult:
    """Strategy: the bundle adjustment again from ``ba``'s poses, with the tracks it did not
    use (but did not reject) triangulated from them, up to ``options.readjust_rounds`` times
    while the cost on all tracks (each misfit capped at the outlier limit) drops by more than
    1 %: from the paper's chained solution some tracks cannot be triangulated or are left
    out, and the adjustment stops short of the solution that all of them fix."""
    for _ in range(options.readjust_rounds):
        idx = np.flatnonzero(ba.frames)
        span = (int(idx[0]), int(idx[-1]))
        d = np.where(ba.used_tracks[:, None], ba.line_directions, np.nan)
        p = np.where(ba.used_tracks[:, None], ba.line_points, np.nan)
        try:
            with run.timed("refinement"):
                new = bundle_adjust(tracks, ba.rotations, ba.positions, d, p, frames=ba.frames,
                                    options=options.bundle)
        except OmniSfmError as exc:
            run.record(failed("adjustment from its own result", span, str(exc)))
            return ba
        limit = outlier_limit(np.radians(ba.sigma_deg), options.bundle)
        both = ba.frames & new.frames
        old_cost, new_cost = (_capped_rms_deg(tracks, b.rotations, b.positions, both, limit)
                              for b in (ba, new))
        why = (f"{int(new.used_tracks.sum())} tracks ({int(ba.used_tracks.sum())} before); all "
               f"tracks, misfits capped at {np.degrees(limit):.3g} deg: {new_cost:.4g} deg RMS, "
               f"{old_cost:.4g} before")
        att = Attempt("adjustment from its own result", span, new, cost_deg=new.rms_final_deg,
                      why=why)
        if new.frames.sum() < ba.frames.sum() or not new_cost < 0.99 * old_cost:
            run.record(att.judged(Outcome.REJECTED, why))
            return ba
        run.record(att)
        ba = new
    return ba


def _off_camera_adjustment(tracks: LineTracks, sol: _Solved, bad: np.ndarray, d: FloatArray,
                           p: FloatArray, left_out: bool, bo: BundleOptions) -> BundleResult:
    """One way of :func:`_lines_off_cameras`: the piece adjusted with the ``bad`` lines (NaN
    in ``d``, ``p``) triangulated again from its poses, or with them ``left_out`` of a first
    adjustment and triangulated from the poses that the others give."""
    R, c = sol.R, sol.c
    if left_out:
        keep = np.flatnonzero(~bad)
        first = scattered(bundle_adjust(tracks.select_tracks(~bad), R, c, d[keep], p[keep],
                                        frames=sol.frames, options=bo),
                          None, keep, tracks.num_frames, tracks.num_tracks)
        R, c = first.rotations, first.positions
        d = np.where(first.used_tracks[:, None], first.line_directions, np.nan)
        p = np.where(first.used_tracks[:, None], first.line_points, np.nan)
    return bundle_adjust(tracks, R, c, d, p, frames=sol.frames, options=bo)


def _longer_polish(tracks: LineTracks, ba: BundleResult, options: EstimationOptions,
                   run: RunLog, span: tuple[int, int]) -> BundleResult:
    """:func:`_lines_off_cameras`' polish of its kept adjustment: the frames around the lines
    through cameras bent to fit them, and the way back is slow for LM, hence
    ``options.line_camera_iterations`` of their own (``ba`` as it is where it fails)."""
    try:
        with run.timed("refinement"):
            return bundle_adjust(tracks, ba.rotations, ba.positions,
                                 np.where(ba.used_tracks[:, None], ba.line_directions, np.nan),
                                 np.where(ba.used_tracks[:, None], ba.line_points, np.nan),
                                 frames=ba.frames, options=replace(
                                     options.bundle,
                                     max_iterations=options.line_camera_iterations))
    except OmniSfmError as exc:
        run.record(failed("lines off the cameras", span, f"the longer polish: {exc}"))
        return ba


def _lines_off_cameras(tracks: LineTracks, sol: _Solved, options: EstimationOptions,
                       run: RunLog) -> _Solved:
    """Strategy "lines off the cameras": where lines of ``sol`` pass within
    ``options.line_camera_ratio`` of a camera that sees them (relative to their median
    distance from those cameras), two adjustments of the piece from there: with those lines
    triangulated again from its poses, and first without them, then with them triangulated
    from the poses that the others give. The one of lower cost over every observation of
    its frames (misfits capped at the outlier limit) is kept if it is lower than ``sol``'s,
    then polished for up to ``options.line_camera_iterations`` iterations.

    A line through a camera is a false minimum of the adjustment: the plane of an observation
    through a camera on the line turns freely, so it fits any normal there, and the frames
    around it bend to fit. Some of the sparse simulations of ``scripts/eval/sparse.py`` reach
    such lines, far closer to a camera than the true lines are (docs/estimator.md, stage 8)."""
    lim, M = options.line_camera_ratio, tracks.num_tracks
    if lim <= 0:
        return sol
    obs = sol.frames[tracks.obs_frame] & sol.used[tracks.obs_track]
    with np.errstate(invalid="ignore"):
        bad = sol.used & (camera_distance_ratio(tracks, sol.R, sol.c, sol.d, sol.p, obs, M) < lim)
    if not bad.any():
        return sol
    idx = np.flatnonzero(sol.frames)
    span = (int(idx[0]), int(idx[-1]))
    bo = options.bundle
    limit = outlier_limit(np.radians(sol.sigma), bo)
    old = _capped_rms_deg(tracks, sol.R, sol.c, sol.frames, limit)
    d = np.where((sol.used & ~bad)[:, None], sol.d, np.nan)
    p = np.where((sol.used & ~bad)[:, None], sol.p, np.nan)
    best: tuple[float, BundleResult, str] | None = None
    for how in ("triangulated again", "left out, then triangulated again"):
        try:
            with run.timed("refinement"):
                new = _off_camera_adjustment(tracks, sol, bad, d, p, how.startswith("left out"),
                                             bo)
        except OmniSfmError as exc:
            run.record(failed("lines off the cameras", span, f"{how}: {exc}"))
            continue
        cost = _capped_rms_deg(tracks, new.rotations, new.positions, sol.frames, limit)
        why = (f"{int(bad.sum())} lines {how}; all tracks, misfits capped at "
               f"{np.degrees(limit):.3g} deg: {cost:.4g} deg RMS, {old:.4g} before")
        att = Attempt("lines off the cameras", span, new, cost_deg=new.rms_final_deg, why=why)
        if new.frames.sum() < sol.frames.sum() or not cost < old or \
                (best is not None and not cost < best[0]):
            run.record(att.judged(Outcome.REJECTED, why))
            continue
        if best is not None:
            run.record(Attempt("lines off the cameras", span, best[1], why=best[2]).judged(
                Outcome.REJECTED, f"{best[2]}; the other is lower"))
        best = (cost, new, why)
    if best is None:
        return sol
    ba = _longer_polish(tracks, best[1], options, run, span)
    run.record(Attempt("lines off the cameras", span, ba, cost_deg=ba.rms_final_deg,
                       why=f"{best[2]}; polished for up to {options.line_camera_iterations} "
                           f"iterations: {ba.rms_final_deg:.4g} deg RMS"))
    return replace(sol, R=ba.rotations, c=ba.positions, frames=ba.frames,
                   d=ba.line_directions, p=ba.line_points, used=ba.used_tracks,
                   outliers=ba.outlier_tracks, rms1=ba.rms_final_deg, sigma=ba.sigma_deg)


def _restart_without_outliers(tracks: LineTracks, ba: BundleResult, options: EstimationOptions,
                              run: RunLog) -> Attempt[tuple[_Init, BundleResult]]:
    """Strategy: the whole solution again from scratch without the tracks the adjustment
    rejected (robust initialisation); its init and adjustment in the indices of ``tracks``."""
    M = tracks.num_tracks
    keep = ~ba.outlier_tracks
    idx = np.flatnonzero(keep)
    n_out = int(ba.outlier_tracks.sum())
    try:
        sub = tracks.select_tracks(keep)
        init = _initialise(sub, options, run)
        ba2 = _refine(sub, init, options, run)
    except OmniSfmError as exc:
        return failed("restart without outliers", None, f"without {n_out} tracks: {exc}")
    members = np.zeros(M, bool)
    members[idx] = init.members
    init = _Init(init.rotations, init.positions, init.frames, init.windows, init.failures,
                 members, init.vpv, families=init.families, switched=init.switched)
    return Attempt("restart without outliers", None, (init, _expand(ba2, idx, M,
                                                                     ba.outlier_tracks)),
                   cost_deg=ba2.rms_final_deg,
                   why=f"without {n_out} tracks: {int(ba2.frames.sum())} frames")


def _repair_half_turns(tracks: LineTracks, sol: _Solved, options: EstimationOptions,
                       run: RunLog) -> _Solved:
    """Short runs of frames turned by a half turn against the frames around them (a view that
    sees mostly lines perpendicular to the turn's axis fits both; video frames do not turn
    that much): each posed again from its lines, started at its (repaired) predecessor, and
    kept if it stays continuous and its residual is at most twice that of the half turn.
    Returns the solution (adjusted again if a frame changed; ``init.repairs`` counts them)."""
    idx = np.flatnonzero(sol.frames)
    if len(idx) < 3:
        return sol
    R, c = sol.R.copy(), sol.c.copy()
    step = np.degrees(rotation_angle(np.einsum("fji,fjk->fik", R[idx[:-1]], R[idx[1:]])))
    jumps = np.flatnonzero(step > 90.0)
    # a run of frames between two half-turn jumps, short against the frames around it
    odd = [k for j0, j1 in zip(jumps[:-1], jumps[1:], strict=True)
           if j1 - j0 <= options.max_half_turn_run for k in range(j0 + 1, j1 + 1)]
    if not odd:
        return sol
    by_frame, starts = obs_index(tracks.obs_frame, tracks.num_frames)
    known: np.ndarray = np.asarray(np.isfinite(sol.d).all(1) & np.isfinite(sol.p).all(1))
    repaired = 0
    for k in odd:
        f, a = int(idx[k]), int(idx[k - 1])
        b = int(idx[min(k + 1, len(idx) - 1)])
        obs = by_frame[starts[f]:starts[f + 1]]
        obs = obs[known[tracks.obs_track[obs]]]
        if len(obs) < 3:
            continue
        t = tracks.obs_track[obs]
        n, d, p = tracks.obs_normal[obs], sol.d[t], sol.p[t]
        _, _, now = resect_pose(n, d, p, R[f], c[f], scale=np.inf, iterations=0)
        R1, c1, ang = resect_pose(n, d, p, R[a], 0.5 * (c[a] + c[b]), scale=np.inf)
        # lines perpendicular to the turn's axis fit both: continuity decides unless the
        # lines clearly prefer the half turn
        if float(np.degrees(rotation_angle(R1.T @ R[a]))) < 90.0 and \
                np.sqrt(np.mean(ang ** 2)) <= 2.0 * np.sqrt(np.mean(now ** 2)):
            R[f], c[f] = R1, c1
            repaired += 1
    span = (int(idx[odd[0]]), int(idx[odd[-1]]))
    if not repaired:
        run.record(failed("half-turn repair", span, f"none of the {len(odd)} frames turned by "
                                                    f"a half turn fits its lines better turned "
                                                    f"back"))
        return sol
    run.record(Attempt("half-turn repair", span, repaired,
                       why=f"{repaired} of {len(odd)} frames turned back"))
    sol.init.repairs += repaired
    return _adjusted(tracks, replace(sol, R=R, c=c), options, run, "a half-turn repair")


def _moving_result(tracks: LineTracks, sol: _Solved, run: RunLog,
                   t_all: float) -> EstimationResult:
    """The conventions (world, scale, reflection) and the report of a solution."""
    init, R, c, frames, d, p = sol.init, sol.R, sol.c, sol.frames, sol.d, sol.p
    used, outliers, rms0, rms1, sigma = sol.used, sol.outliers, sol.rms0, sol.rms1, sol.sigma
    R_n, c_n, d_n, p_n = _normalise(R, c, frames, d, p)
    R_i, c_i, _, _ = _normalise(init.rotations, init.positions, frames, d, p)
    idx = np.flatnonzero(frames)
    front, behind = side_votes(tracks, R_n, c_n, d_n, p_n, frames, used)
    reflection = "unresolved: the tracks carry no rays (" + REFLECTION_NOTE + ")"
    if front + behind > 0:
        if behind > front:
            # every observation is unchanged by the point reflection through the first camera;
            # the rays say the lines lie on the other side
            o = c_n[idx[0]].copy()
            c_n, p_n, c_i = 2.0 * o - c_n, 2.0 * o - p_n, 2.0 * o - c_i
            front, behind = behind, front
        reflection = (f"resolved by the observations' rays: {front} see their line in front, "
                      f"{behind} behind")
    ts = tracks.timestamps
    traj = Trajectory(ts[idx].copy(), R_n[idx], c_n[idx])
    traj0 = Trajectory(ts[idx].copy(), R_i[idx], c_i[idx])
    members = init.members
    # the family's direction in the world: mean of its refined lines, else the first frame's VPV
    pd = d_n[members & used]
    if len(pd):
        pd = pd * np.sign(pd @ pd[0])[:, None]
        direction = pd.mean(0) / np.linalg.norm(pd.mean(0))
    else:
        v0 = init.vpv[idx[0]]
        direction = R_n[idx[0]] @ v0
    run.timings["total"] = (time.perf_counter() - t_all) * 1e3
    timings = dict(run.timings)
    windows = [(w.start, w.stop) for w in init.windows]
    report = replace(
        _report(tracks, frames, members, direction, outliers, used, windows, init.failures,
                timings, rms0, rms1, sigma),
        reflection=reflection, half_turns_repaired=init.repairs,
        parallel_families=FamiliesFound(sizes=init.families,
                                        windows_with_another_family=init.switched),
        frames_not_estimated_reasons={
            str(k): init.reasons.get(int(k), "not reached: the registration of the frames "
                                             "beyond the chain stopped before it")
            for k in np.flatnonzero(~frames)})
    return EstimationResult(
        trajectory=traj, estimated=frames, initial_trajectory=traj0,
        track_ids=tracks.track_ids.copy(), parallel=members, parallel_direction=direction,
        outliers=outliers, used_tracks=used, line_directions=d_n, line_points=p_n,
        windows=windows, timings_ms=timings, residual_rms_initial_deg=rms0,
        residual_rms_final_deg=rms1, sigma_deg=sigma, scale_convention=SCALE_CONVENTION,
        report=report)


def _lift(tracks: LineTracks, sub: _Solved, start: int, idx: np.ndarray) -> _Solved:
    """A solution of frames ``start..`` and tracks ``idx`` (:func:`frame_range`) in the indices
    of the whole ``tracks``."""
    F, M = tracks.num_frames, tracks.num_tracks
    rows = slice(start, start + len(sub.frames))

    def frames_of(a: np.ndarray, fill: Any) -> np.ndarray:
        return scatter_rows(a, rows, F, fill)

    def tracks_of(a: np.ndarray, fill: Any) -> np.ndarray:
        return scatter_rows(a, idx, M, fill)

    init = _lift_init(sub.init, start, idx, F, M)
    return _Solved(init, frames_of(sub.R, np.nan), frames_of(sub.c, np.nan),
                   frames_of(sub.frames, False), tracks_of(sub.d, np.nan),
                   tracks_of(sub.p, np.nan), tracks_of(sub.used, False),
                   tracks_of(sub.outliers, False), sub.rms0, sub.rms1, sub.sigma)


def _line_depth(sol: _Solved, lines: np.ndarray) -> float:
    """Median distance of ``lines`` from their nearest estimated camera (the scene's scale)."""
    c = sol.c[sol.frames]
    d, p = sol.d[lines], sol.p[lines]
    if len(c) > 400:
        c = c[np.linspace(0, len(c) - 1, 400).astype(int)]
    v = p[:, None, :] - c[None]
    v = v - np.sum(v * d[:, None, :], axis=2, keepdims=True) * d[:, None, :]
    return float(np.median(np.linalg.norm(v, axis=2).min(axis=1)))


def _speed(c: FloatArray, frames: np.ndarray, at: int, span: int = 10) -> float:
    """Median distance per frame between the consecutive ``frames`` (sorted) within ``span``
    of frame ``at``; centres ``c`` ``(F, 3)``."""
    near = frames[np.abs(frames - at) <= span]
    if len(near) < 2:
        return 0.0
    return float(np.median(np.linalg.norm(np.diff(c[near], axis=0), axis=1) / np.diff(near)))


def _join(tracks: LineTracks, a: _Solved, b: _Solved, options: EstimationOptions,
          reach: _Solved | None = None) -> tuple[_Solved | None, str]:
    """``b`` moved into ``a``'s world and merged with it (docs/estimator.md stage 8), else
    None and why: by the poses of the frames that ``reach`` (``b`` grown into ``a``'s frames,
    :func:`_reach_into`) and ``a`` both pose, where there are ``join_min_frames`` of them and
    that join holds, else by the lines ``a`` and ``b`` have in common."""
    whys: list[str] = []
    if reach is not None and (a.frames & reach.frames).sum() >= options.join_min_frames:
        fixed = _similarity_from_frames(a, reach, a.frames & reach.frames, options)
        if isinstance(fixed, str):
            whys.append(fixed)
        else:
            merged, why = _merge(tracks, a, reach, *fixed, options)
            if merged is not None:
                return merged, why
            whys.append(why)
    fixed = _similarity_from_common_lines(a, b, options)
    if isinstance(fixed, str):
        return None, "; ".join([*whys, fixed])
    merged, why = _merge(tracks, a, b, *fixed, options)
    return merged, why if merged is not None else "; ".join([*whys, why])


_Sim = tuple[FloatArray, float, FloatArray]
"""A similarity ``x_a = s R x_b + t`` as ``(R, s, t)``."""


def _similarity_from_common_lines(a: _Solved, b: _Solved, options: EstimationOptions
                                  ) -> tuple[_Sim, tuple[int, int], str] | str:
    """The similarity taking piece ``b``'s world to ``a``'s from the lines both reconstructed,
    the frames of ``a`` and ``b`` next to each other across the break, and how well it maps
    the lines; or why it does not."""
    common = np.isfinite(a.d).all(1) & np.isfinite(b.d).all(1)
    if common.sum() < 3:
        return f"{int(common.sum())} lines reconstructed in both; need 3"
    # the frames next to each other across the break: the camera turns little between them
    fa, fb = np.flatnonzero(a.frames), np.flatnonzero(b.frames)
    ka = int(np.argmin(np.minimum(np.abs(fa - fb[0]), np.abs(fa - fb[-1]))))
    kb = int(np.argmin(np.abs(fb - fa[ka])))
    steps = abs(int(fa[ka]) - int(fb[kb]))
    if steps > options.join_max_gap:
        return f"{steps} frames apart; at most {options.join_max_gap} are joined"
    near = a.R[fa[ka]] @ b.R[fb[kb]].T
    sim = similarity_from_lines(a.d[common], a.p[common], b.d[common], b.p[common], near=near,
                                near_deg=options.join_max_turn_deg * steps)
    if sim is None:
        return (f"the {int(common.sum())} common lines do not fix the similarity (fewer "
                f"than 3 agree, or all of one direction)")
    depth = _line_depth(a, np.flatnonzero(common))
    if sim.angle_deg > options.join_max_angle_deg or \
            sim.distance > options.join_max_distance * depth:
        return (f"the common lines disagree: {sim.angle_deg:.2g} deg, "
                f"{sim.distance / depth:.0%} of their distance")
    return ((sim.rotation, sim.scale, sim.translation), (int(fa[ka]), int(fb[kb])),
            f"{sim.lines} common lines, {sim.angle_deg:.2g} deg")


def _similarity_from_frames(a: _Solved, b: _Solved, both: np.ndarray,
                            options: EstimationOptions
                            ) -> tuple[_Sim, tuple[int, int], str] | str:
    """The similarity taking piece ``b``'s world to ``a``'s from the poses of the frames
    ``both`` that both pose, the first of them (twice: the junction), and how well it maps
    them; or why it does not."""
    try:
        sim = similarity_from_poses(a.R[both], a.c[both], b.R[both], b.c[both],
                                    allow_reflection=True)
    except OmniSfmError as exc:
        return f"the {int(both.sum())} frames both pieces pose: {exc}"
    turn = np.degrees(rotation_angle(np.einsum("fji,jk,fkl->fil", a.R[both], sim.rotation,
                                               b.R[both])))
    off = np.linalg.norm(sim.apply_points(b.c[both]) - a.c[both], axis=1)
    # against the way the camera went over those frames (the lines' distance is far larger
    # than a few dozen frames' motion: it would let a wrong scale through)
    path = float(np.linalg.norm(np.diff(a.c[both], axis=0), axis=1).sum())
    angle, dist = float(np.median(turn)), float(np.median(off))
    if angle > options.join_max_frame_angle_deg or dist > options.join_max_distance * path:
        return (f"the {int(both.sum())} frames both pieces pose disagree: {angle:.2g} deg, "
                f"{dist / max(path, 1e-300):.0%} of the way the camera went over them")
    f0 = int(np.flatnonzero(both)[0])
    return ((sim.rotation, sim.scale, sim.translation), (f0, f0),
            f"{int(both.sum())} frames in common, {angle:.2g} deg")


def _merge(tracks: LineTracks, a: _Solved, b: _Solved, sim: _Sim, at: tuple[int, int],
           how: str, options: EstimationOptions) -> tuple[_Solved | None, str]:
    """``b`` moved into ``a``'s world by ``sim`` and merged with it (the frames both pose keep
    ``a``'s poses), where the camera's speed across the junction (frames ``at`` of ``a`` and
    ``b``) is kept and the frames around it fit together (:func:`_junction_misfit`); else
    None and why."""
    Rs, s, t = sim
    fa, fb = np.flatnonzero(a.frames), np.flatnonzero(b.frames)
    # lines triangulated near a piece's end fix its depth poorly: the scale must also keep the
    # camera's speed across the break (video does not jump in speed)
    va, vb = _speed(a.c, fa, at[0]), abs(s) * _speed(b.c, fb, at[1])
    if max(va, vb) > 0 and min(va, vb) < max(va, vb) / options.join_max_speed_ratio:
        return None, (f"the similarity changes the camera's speed across the break by "
                      f"{max(va, vb) / max(min(va, vb), 1e-300):.2g}x")
    R, c = a.R.copy(), a.c.copy()
    only_b = b.frames & ~a.frames  # the frames both pose keep a's poses
    R[only_b] = np.einsum("ij,fjk->fik", Rs, b.R[only_b])
    c[only_b] = s * b.c[only_b] @ Rs.T + t
    d, p = a.d.copy(), a.p.copy()
    new = np.isfinite(b.d).all(1) & ~np.isfinite(a.d).all(1)
    d[new] = b.d[new] @ Rs.T
    q = s * b.p[new] @ Rs.T + t
    p[new] = q - np.sum(q * d[new], axis=1, keepdims=True) * d[new]
    ia, ib = a.init, b.init
    frames = a.frames | b.frames
    r0, c0 = ia.rotations.copy(), ia.positions.copy()
    r0[only_b] = np.einsum("ij,fjk->fik", Rs, ib.rotations[only_b])
    c0[only_b] = s * ib.positions[only_b] @ Rs.T + t
    reasons = {k: v for k, v in {**ia.reasons, **ib.reasons}.items() if not frames[k]}
    vpv = np.where(np.isfinite(ia.vpv).all(1, keepdims=True), ia.vpv, ib.vpv)
    init = _Init(r0, c0, frames, ia.windows + ib.windows, ia.failures + ib.failures,
                 ia.members | (ib.members & ~a.used), vpv, reasons=reasons,
                 families=ia.families, switched=ia.switched + ib.switched,
                 repairs=ia.repairs + ib.repairs)
    merged = _Solved(init, R, c, frames, d, p, a.used | b.used,
                     (a.outliers | b.outliers) & ~(a.used | b.used), max(a.rms0, b.rms0),
                     max(a.rms1, b.rms1), max(a.sigma, b.sigma))
    misfit = _junction_misfit(tracks, merged, min(at), max(at), options)
    if misfit:
        return None, f"the adjustment of the frames around the junction: {misfit}"
    return merged, how


def _junction_misfit(tracks: LineTracks, sol: _Solved, first: int, last: int,
                     options: EstimationOptions) -> str:
    """Why the pieces do not fit together ("" where they do): whether a bundle adjustment of
    the frames around a junction (``first..last`` and ``join_window`` frames on each side) and
    their lines, every other frame that sees those lines held, keeps those frames and ends
    with a residual of at most ``join_max_residual_factor`` times the pieces' own (the pieces
    fit together). Only a test:
    its poses are not kept (a short piece's weak lines can let it wander to another fit of the
    same residual; the adjustment of the whole joined piece follows)."""
    w = options.join_window
    at = np.arange(len(sol.frames))
    free: np.ndarray = np.asarray(sol.frames & (at >= first - w) & (at <= last + w))
    known: np.ndarray = np.asarray(np.isfinite(sol.d).all(1) & np.isfinite(sol.p).all(1))
    obs = np.flatnonzero(free[tracks.obs_frame] & known[tracks.obs_track])
    lines = np.unique(tracks.obs_track[obs])
    obs = np.flatnonzero(np.isin(tracks.obs_track, lines) & sol.frames[tracks.obs_frame])
    frames = np.unique(tracks.obs_frame[obs])
    held = ~free[frames]
    if len(lines) < 3 or not held.any():
        return f"{len(lines)} lines seen around it, {int(held.sum())} frames to hold"
    sub = tracks.subset(obs, lines, frames)
    spread = held.sum() > 1 and float(np.ptp(sol.c[frames[held]], axis=0).max()) > 0
    try:
        ba = bundle_adjust(sub, sol.R[frames], sol.c[frames], sol.d[lines], sol.p[lines],
                           held_frames=held, scale_frames=held if spread else None,
                           options=options.bundle)
    except OmniSfmError as exc:
        return str(exc)
    # held frames that see fewer than 3 of these lines drop out of the problem; the frames
    # around the junction must not
    if not ba.frames[~held].all():
        return f"{int((~ba.frames[~held]).sum())} of its frames drop out"
    if ba.rms_final_deg > options.join_max_residual_factor * sol.rms1:
        return (f"residual {ba.rms_final_deg:.3g} deg, over {options.join_max_residual_factor}"
                f" times the pieces' {sol.rms1:.3g} deg")
    return ""


def _adjusted(tracks: LineTracks, sol: _Solved, options: EstimationOptions, run: RunLog,
              why: str) -> _Solved:
    """Strategy: the bundle adjustment of a piece after a join or a repair (``why``); the piece
    as it is where it fails (recorded). With ``options.extend.families``, the lines of each
    parallel family that its lines show are given the family's direction and hold it
    (:mod:`omni_sfm.estimate.families`), as in the registration, so that the rotations are
    measured against the same world directions all along; unless those lines do not fit their
    families (:func:`_held_in_families`: that attempt is recorded, and the directions are
    freed)."""
    idx = np.flatnonzero(sol.frames)
    span = (int(idx[0]), int(idx[-1]))
    fo = options.extend
    try:
        ba = None
        if fo is not None and fo.families:
            D, fam = line_families(sol.d, max_angle_deg=fo.family_angle_deg,
                                   min_lines=fo.min_family_lines)
            if (fam >= 0).any():
                anchors = camera_anchors(tracks.obs_frame, tracks.obs_track,
                                         np.where(sol.frames[:, None], sol.c, np.nan),
                                         tracks.num_tracks)
                d, p = snap_to_families(sol.d, sol.p, D, fam, anchors)
                free_rms = _line_rms_deg(tracks, sol.R, sol.c, sol.d, sol.p, sol.frames)
                ba = _held_in_families(tracks, sol.R, sol.c, sol.frames, d, p, fam >= 0,
                                       free_rms, options, run, span)
        if ba is None:
            ba = bundle_adjust(tracks, sol.R, sol.c, sol.d, sol.p, frames=sol.frames,
                               options=options.bundle)
    except OmniSfmError as exc:
        run.record(failed("bundle adjustment of a piece", span,
                          f"after {why}: {exc}; the piece stands unadjusted"))
        return sol
    run.record(Attempt("bundle adjustment of a piece", span, ba, cost_deg=ba.rms_final_deg,
                       why=f"after {why}"))
    return replace(sol, R=ba.rotations, c=ba.positions, frames=ba.frames,
                   d=ba.line_directions, p=ba.line_points, used=ba.used_tracks,
                   outliers=ba.outlier_tracks, rms1=ba.rms_final_deg, sigma=ba.sigma_deg)


def _line_rms_deg(tracks: LineTracks, R: FloatArray, c: FloatArray, d: FloatArray,
                  p: FloatArray, frames: np.ndarray) -> FloatArray:
    """``(M,)`` each line's RMS weighted residual (deg) over its observations in ``frames``
    (NaN for a line with none or no 3D line)."""
    ang = weighted_residuals(tracks, R, c, d, p)
    ok = np.isfinite(ang) & frames[tracks.obs_frame]
    M = tracks.num_tracks
    cnt = np.bincount(tracks.obs_track[ok], minlength=M)
    ss = np.bincount(tracks.obs_track[ok], weights=ang[ok] ** 2, minlength=M)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, np.degrees(np.sqrt(ss / np.maximum(cnt, 1))), np.nan)


def _held_in_families(tracks: LineTracks, R: FloatArray, c: FloatArray, frames: np.ndarray,
                      d: FloatArray, p: FloatArray, held: np.ndarray, free_rms_deg: FloatArray,
                      options: EstimationOptions, run: RunLog,
                      span: tuple[int, int]) -> BundleResult | None:
    """The bundle adjustment of ``frames`` with the directions of the ``held`` ``(M,)`` lines
    held (lines ``d``, ``p``: those on their families' directions); None if those lines (the
    ones it rejects as outliers too) fit more than ``options.extend.max_family_misfit`` times
    as badly as with their directions free (median RMS residual, against theirs in
    ``free_rms_deg`` ``(M,)``, NaN: unknown): the families do not describe the scene (lines
    of other directions put in one, a place that is not Manhattan).

    Raises:
        OmniSfmError: the adjustment fails.
    """
    assert options.extend is not None
    res = bundle_adjust(tracks, R, c, d, p, frames=frames, held_directions=held,
                        options=options.bundle)
    h = held & np.isfinite(res.track_rms_deg) & np.isfinite(free_rms_deg)
    held_rms, free_rms = (float(np.median(r[h])) if h.any() else np.nan
                          for r in (res.track_rms_deg, free_rms_deg))
    att = Attempt("families held", span, res, cost_deg=res.rms_final_deg,
                  why=f"{int(held.sum())} lines held on their families' directions: median "
                      f"{held_rms:.3g} deg against {free_rms:.3g} free")
    if h.any() and held_rms > options.extend.max_family_misfit * free_rms:
        run.record(att.judged(Outcome.REJECTED, f"{att.why}, over "
                                                f"{options.extend.max_family_misfit}x"))
        return None
    run.record(att)
    return res


def _with_segments(tracks: LineTracks, sol: _Solved, options: EstimationOptions, run: RunLog,
                   t_all: float) -> EstimationResult:
    """Start again on the stretches the main solution leaves (docs/estimator.md, stage 8);
    join each new piece to the main one where common lines fix the similarity, else keep it
    as a segment in its own world and scale; then the result of the main one."""
    covered = sol.frames.copy()
    todo = _stretches(covered, 0, tracks.num_frames, options)
    pieces = [sol]  # the main piece first
    grown = [False]
    failures: dict[tuple[int, int], str] = {}
    joined = 0
    t0 = time.perf_counter()
    cap = options.max_segments
    tried: set[tuple[int, int]] = set()
    while todo and (cap is None or len(pieces) - 1 + joined < cap):
        a, b = todo.pop(0)
        if (a, b) in tried:  # a widened stretch the new start on it left without a pose
            continue
        tried.add((a, b))
        lifted = _new_start(tracks, a, b, options, run, failures)
        if lifted is None:
            continue
        reach = _reach_into(tracks, lifted, covered, options, run)
        if reach is None and (lifted.frames & covered).any():
            reach = lifted  # a short stretch widened into its neighbour's frames
        covered |= lifted.frames
        todo += _stretches(covered, a, b, options)
        into = _join_nearest(tracks, pieces, lifted, reach, (a, b), options, run)
        if into is None:
            pieces.append(lifted)
            grown.append(False)
        else:
            joined += 1
            grown[into] = True
    for k in np.flatnonzero(grown):
        pieces[k] = _adjusted(tracks, pieces[k], options, run, "joining pieces")
    # the main trajectory is the largest piece
    pieces.sort(key=lambda q: -int(q.frames.sum()))
    pieces[0] = _lines_off_cameras(tracks, pieces[0], options, run)
    # after it: the lines it triangulates again may be the ones a frame lacked
    pieces[0] = _registered_again(tracks, pieces[0], options, run)
    run.timings["segments"] += (time.perf_counter() - t0) * 1e3
    result = _moving_result(tracks, pieces[0], run, t_all)
    segments, reasons_lost = _segments_beside(tracks, pieces[1:], result)
    report = replace(
        result.report, joined_pieces=joined, attempts=run.entries,
        frames_not_estimated_reasons=_reasons_not_estimated(
            {**(result.report.frames_not_estimated_reasons or {}), **reasons_lost}, segments,
            failures, covered),
        segments=[InitSegment(
            file=seg.file,
            frames=[int(np.flatnonzero(seg.frames)[0]), int(np.flatnonzero(seg.frames)[-1])],
            num_frames_estimated=int(seg.frames.sum()),
            world="camera of the segment's first estimated frame (world_from_cam, TUM)",
            scale_convention="distance between the segment's first and last estimated "
                             "camera centres = 1",
            residual_rms_deg=seg.report.rms_final_deg,
        ) for seg in segments] or None)
    return replace(result, report=report, segments=tuple(segments))


def _join_nearest(tracks: LineTracks, pieces: list[_Solved], lifted: _Solved,
                  reach: _Solved | None, span: tuple[int, int], options: EstimationOptions,
                  run: RunLog) -> int | None:
    """The new piece ``lifted`` (from a start on frames ``span = (a, b)``) joined to the
    nearest piece in time (within ``options.join_max_gap``) that shares enough lines with it:
    that piece replaced in ``pieces`` by the join and its index returned; None where no piece
    joins it. Each try recorded."""
    a, b = span
    gap = [max(0, int(np.flatnonzero(q.frames)[0]) - b, a - int(np.flatnonzero(
        q.frames)[-1])) for q in pieces]
    for k in np.argsort(gap, kind="stable"):
        if gap[k] > options.join_max_gap:
            continue
        merged, why = _join(tracks, pieces[k], lifted, options, reach)
        fk = np.flatnonzero(pieces[k].frames)
        run.record(Attempt("join", (a, b - 1), merged, why=why,
                           outcome=Outcome.KEPT if merged is not None else Outcome.FAILED),
                   to_frames=[int(fk[0]), int(fk[-1])])
        if merged is not None:
            pieces[k] = merged
            return int(k)
    return None


def _segments_beside(tracks: LineTracks, pieces: list[_Solved],
                     result: EstimationResult) -> tuple[list[Segment], dict[str, str]]:
    """The ``pieces`` other than the main one as numbered segments (in the order of their
    first frame) with the frames they pose and the main ``result`` does not; also why the
    frames of a piece that has no world and scale are lost (by frame)."""
    segments: list[Segment] = []
    reasons_lost: dict[str, str] = {}
    for piece in sorted(pieces, key=lambda q: int(np.flatnonzero(q.frames)[0])):
        try:
            r = _moving_result(tracks, piece, RunLog(), time.perf_counter())
        except OmniSfmError as exc:
            fk = np.flatnonzero(piece.frames)
            for g in fk:
                reasons_lost[str(int(g))] = (f"its segment (frames {fk[0]}-{fk[-1]}) has no "
                                             f"world and scale: {exc}")
            continue
        own = r.estimated & ~result.estimated
        if own.any():  # a widened new start may pose only frames the main piece poses
            segments.append(Segment(len(segments) + 1, own, r.trajectory, r.report))
    return segments, reasons_lost


def _reasons_not_estimated(reasons: dict[str, str], segments: list[Segment],
                           failures: dict[tuple[int, int], str],
                           covered: np.ndarray) -> dict[str, str]:
    """``reasons`` (by frame) with the frames of ``segments`` said to be in them, and the
    reasons of the frames still not ``covered`` extended by the new starts that ``failures``
    record on them."""
    for seg in segments:
        for f in np.flatnonzero(seg.frames):
            reasons[str(f)] = (f"estimated in segment {seg.number} ({seg.file}), in its own "
                               f"world and scale: too few lines link it to the main trajectory")
    for (a, b), why in failures.items():
        for j in range(a, b):
            if str(j) in reasons and not covered[j]:
                reasons[str(j)] = f"{reasons[str(j)]}; a new start on frames {a}-{b - 1} " \
                                  f"failed: {why}"
    return reasons


def _registered_again(tracks: LineTracks, sol: _Solved, options: EstimationOptions,
                      run: RunLog) -> _Solved:
    """Strategy "registration again": up to ``restart_overlap`` frames before and after the
    piece ``sol`` registered from the lines it knows now (the pieces joined to it bring lines
    that its first registration lacked, and the adjustments since may have taken back lines
    that were outliers then), then the adjustment of the piece; ``sol`` as it is where no
    frame is added (recorded). Up to three rounds, the next only where the adjustment took
    back a line that a frame still without a pose sees, within the first round's reach. The
    reach is bounded: registered on and on, the piece would run into stretches that the other
    pieces pose better (docs/estimator.md, stage 8)."""
    if sol.frames.all():
        return sol
    F, ov = tracks.num_frames, options.restart_overlap
    fk = np.flatnonzero(sol.frames)
    within = (max(0, int(fk[0]) - ov), min(F, int(fk[-1]) + 1 + ov))
    for _ in range(3):
        known = sol.used & ~sol.outliers
        grown = _reach_into(tracks, sol, np.ones(F, bool), options, run, "registration again",
                            within)
        if grown is None:
            return sol
        sol = _adjusted(tracks, grown, options, run, "registration again")
        # again where the adjustment took back a line that a frame still without a pose sees
        # (sparse seed 13: frames 598-599 saw 3 known lines, the fourth an outlier until then)
        left = np.zeros(F, bool)
        left[within[0]:within[1]] = ~sol.frames[within[0]:within[1]]
        back = sol.used & ~sol.outliers & ~known
        if not back[tracks.obs_track[left[tracks.obs_frame]]].any():
            return sol
    return sol


def _stretches(covered: np.ndarray, a: int, b: int,
               options: EstimationOptions) -> list[tuple[int, int]]:
    """The stretches of frames ``a..b-1`` without a pose (``~covered``) to start again on:
    those of ``min_segment_frames`` or more, and shorter ones of 3 or more next to posed
    frames widened into them to that length (the new start then poses frames in common with
    the piece beside it, by which the two are joined)."""
    n, F = options.min_segment_frames, len(covered)
    if n <= 0:
        return []
    out = []
    for x, y in runs(~covered[a:b]):
        x, y = a + x, a + y
        if y - x >= n:
            out.append((x, y))
        elif y - x >= 3 and n <= F:
            if x > 0 and covered[x - 1]:
                out.append((max(0, y - n), max(y, n)))
            elif y < F and covered[y]:
                out.append((min(x, F - n), min(F, x + n)))
    return out


def _new_start(tracks: LineTracks, a: int, b: int, options: EstimationOptions, run: RunLog,
               failures: dict[tuple[int, int], str]) -> _Solved | None:
    """Strategy "new start": the moving camera's solution of frames ``a..b-1`` (none posed,
    docs/estimator.md stage 8) in the indices of the whole sequence; None where it fails
    (recorded, and in ``failures``)."""
    sub_tracks, idx = frame_range(tracks, a, b)
    try:
        sub = _solve_moving(sub_tracks, options, run.at(a))
    except OmniSfmError as exc:
        failures[(a, b)] = str(exc)
        run.record(failed("new start", (a, b - 1), str(exc)))
        return None
    run.record(Attempt("new start", (a, b - 1), sub, cost_deg=sub.rms1,
                       why=f"{int(sub.frames.sum())} frames estimated"))
    return _lift(tracks, sub, a, idx)


def _reach_into(tracks: LineTracks, piece: _Solved, covered: np.ndarray,
                options: EstimationOptions, run: RunLog,
                strategy: str = "overlap", within: tuple[int, int] | None = None
                ) -> _Solved | None:
    """Strategy "overlap": ``piece`` (a new start) grown by the registration from its lines
    into up to ``restart_overlap`` frames of the pieces beside it (``covered``), so that the
    two pose some frames in common and are joined by those frames' poses (no further than
    frames ``within[0]..within[1]-1`` where given). None where it poses none of them
    (recorded)."""
    F, ov = tracks.num_frames, options.restart_overlap
    fk = np.flatnonzero(piece.frames)
    a, b = int(fk[0]), int(fk[-1]) + 1
    lo = max(0, a - ov) if a > 0 and covered[a - 1] else a
    hi = min(F, b + ov) if b < F and covered[b] else b
    if within is not None:
        lo, hi = min(a, max(lo, within[0])), max(b, min(hi, within[1]))
    if ov <= 0 or options.extend is None or (lo, hi) == (a, b):
        return None
    sub, idx = frame_range(tracks, lo, hi)
    keep = ~piece.outliers[idx]
    rows = slice(lo, hi)
    try:
        reg = register_frames(sub.select_tracks(keep), piece.R[rows], piece.c[rows],
                              piece.frames[rows], piece.d[idx[keep]], piece.p[idx[keep]],
                              piece.sigma, options.bundle, options.extend)
    except OmniSfmError as exc:
        run.record(failed(strategy, (lo, hi - 1), str(exc)))
        return None
    R, c, frames = piece.R.copy(), piece.c.copy(), piece.frames.copy()
    R[rows], c[rows], frames[rows] = reg.rotations, reg.positions, reg.estimated
    both = int((frames & covered & ~piece.frames).sum())
    if both == 0:
        run.record(failed(strategy, (lo, hi - 1), "no frame of the pieces beside it "
                                                   "registered from its lines"))
        return None
    d, p = piece.d.copy(), piece.p.copy()
    d[idx[keep]], p[idx[keep]] = reg.line_directions, reg.line_points
    used = piece.used.copy()
    used[idx[keep]] |= np.isfinite(reg.line_directions).all(1)
    run.record(Attempt(strategy, (lo, hi - 1), reg,
                       why=f"{both} frames of the pieces beside it registered"))
    return replace(piece, R=R, c=c, frames=frames, d=d, p=p, used=used,
                   init=piece.init.registered(R, c, frames & ~piece.frames))


def _extend(tracks: LineTracks, ba: BundleResult, init: _Init, options: EstimationOptions,
            run: RunLog) -> tuple[BundleResult, _Init]:
    """Strategy: frames beyond the chain registered from its lines, then the bundle adjustment
    of all; the result unchanged when no frame is added or the adjustment fails."""
    assert options.extend is not None
    keep = ~ba.outlier_tracks
    sub = tracks.select_tracks(keep)
    with run.timed("extension"):
        reg = register_frames(sub, ba.rotations, ba.positions, ba.frames,
                              ba.line_directions[keep], ba.line_points[keep], ba.sigma_deg,
                              options.bundle, options.extend, on_frame=run.reached)
    R, c, frames = reg.rotations, reg.positions, reg.estimated
    added = frames & ~ba.frames
    init0, init = init, replace(init, reasons=dict(reg.reasons))
    F = tracks.num_frames
    stops = "; ".join(f"stopped {'forwards' if way > 0 else 'backwards'} at frame {f}"
                      for f, way in reg.stops)
    if not added.any():
        run.record(failed("registration", (0, F - 1), f"no frame added{': ' if stops else ''}"
                                                      f"{stops}"))
        return ba, init
    run.record(Attempt("registration", (0, F - 1), reg,
                       why=f"{int(added.sum())} frames added{'; ' if stops else ''}{stops}"))
    with run.timed("refinement"):
        d = np.full((tracks.num_tracks, 3), np.nan)
        p = d.copy()
        d[keep], p[keep] = reg.line_directions, reg.line_points
        held = np.zeros(tracks.num_tracks, bool)
        held[keep] = reg.family >= 0  # the lines of a family keep its direction
        try:
            if held.any():
                # against how the chain's lines fitted with their directions free
                new = _held_in_families(tracks, R, c, frames, d, p, held,
                                        np.where(ba.used_tracks, ba.track_rms_deg, np.nan),
                                        options, run, (0, F - 1))
            else:
                new = bundle_adjust(tracks, R, c, d, p, frames=frames, options=options.bundle)
        except OmniSfmError as exc:
            run.record(failed("bundle adjustment after registration", (0, F - 1),
                              f"{exc}; the chain's frames alone are kept"))
            return ba, init
    if new is None:  # the families do not fit the scene: the registration again without them
        return _extend(tracks, ba, init0,
                       replace(options, extend=replace(options.extend, families=False)), run)
    run.record(Attempt("bundle adjustment after registration", (0, F - 1), new,
                       cost_deg=new.rms_final_deg, why=f"{int(new.frames.sum())} frames"))
    return new, replace(init.registered(R, c, added), frames=new.frames)


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
            res = estimate_rotation_only(tracks, options.rotation_only)
        except OmniSfmError as exc:
            run.record(failed("rotation only", span, f"{why}; {exc}"))
            return None
    att = Attempt("rotation only", span, res, cost_deg=res.rms_final_deg,
                  why=f"{why}; {int(res.estimated.sum())} frames, median "
                      f"{res.median_deg:.3g} deg")
    limit = options.rotation_only_max_median_deg
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
            family = detect_parallel_family(tracks, options.vanishing)
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
                     [], timings, res.rms_initial_deg, res.rms_final_deg, sigma)
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


def _expand(ba: BundleResult, idx: np.ndarray, M: int, first_outliers: np.ndarray) -> BundleResult:
    """A BundleResult on the tracks ``idx`` of M, expanded back to all M tracks."""
    out = scattered(ba, None, idx, len(ba.frames), M)
    return replace(out, outlier_tracks=out.outlier_tracks | first_outliers)


def _report(tracks: LineTracks, frames: np.ndarray, members: np.ndarray, direction: FloatArray,
            outliers: np.ndarray, used: np.ndarray, windows: list[tuple[int, int]],
            failures: list[str], timings: dict[str, float], rms0: float, rms1: float,
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
        window_failures=failures,
        world="camera of the first estimated frame (world_from_cam, TUM)",
        scale_convention=SCALE_CONVENTION,
        reflection_ambiguity=REFLECTION_NOTE,
        timings_ms={k: round(float(v), 3) for k, v in timings.items()},
        residuals=InitResiduals(rms_initial_deg=float(rms0), rms_final_deg=float(rms1),
                                noise_sigma_deg=float(sigma)),
    )


def trusted(result: EstimationResult) -> np.ndarray:
    """``(N,)`` bool over ``result.trajectory``'s poses: those of frames the report does not
    flag as uncertain (``frames_uncertain``), where at least 3 are; else all."""
    idx = np.flatnonzero(result.estimated)
    flagged = [int(k) for k in result.report.frames_uncertain or {}]
    keep = ~np.isin(idx, flagged)
    return keep if keep.sum() >= 3 else np.ones(len(idx), bool)


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
