"""The global estimator: every frame's pose from one problem, solved once (docs/estimator.md,
"Global estimator").

Steps:

1. **Rotations** of all frames at once (:mod:`~omni_sfm.estimate.global_rotations`): every
   observation says that its line's direction lies in its plane; the largest parallel family
   (the paper's VPVs) anchors two degrees of freedom of every frame that sees it; the lines'
   directions are then clustered into world directions (:func:`~omni_sfm.estimate.families.
   world_families`) and the problem solved again with each world direction shared by its lines,
   so that rotation error does not accumulate along the video.
2. **Positions** of all frames and lines at once, the rotations given: one sparse linear
   problem with every line's depth held positive on the side its rays see it
   (:mod:`~omni_sfm.estimate.global_positions`).
3. **One robust bundle adjustment** of all cameras and lines from that start
   (:func:`~omni_sfm.estimate.bundle.bundle_adjust`, outlier tracks rejected), and one from
   the start with the positions settled on the rotations first; the lower cost is kept
   (:func:`_adjusted`).
4. **Per-frame information**: frames that see 3 lines only, parts of the video tied to the rest
   only through such frames, and frames whose rotation or position the data leave (nearly)
   free where their interpolation can be far off are listed in the report with the reason
   (``frames_uncertain``; :func:`_uncertain`); of the others, each frame's expected error from
   the adjustment's covariance (:mod:`~omni_sfm.estimate.uncertainty`, ``pose_spread`` in the
   report), and those it leaves weak are listed too (:func:`_spread_flags`).

5. **Revisits** (``revisits``): a line seen again after the camera left it (a loop, a
   return) is joined to its earlier track (:mod:`~omni_sfm.estimate.revisits`) and, where
   ``revisits.min_joins`` or more are joined, steps 1-4 run again on the joined tracks from
   the first solution's rotations, so that the two visits share their lines in one solve.

Only the start rotations follow the frame order (they chain neighbouring frames); the joint
problems replace them by their own minimum wherever the start lies in its basin. Where one
family is the only world direction and the other lines point anywhere (docs/estimator.md,
known limits) the start can drift out of it, and the answer then follows the order.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace
from functools import partial
from typing import Any

import numpy as np
from tqdm import tqdm

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.bundle import (
    BundleOptions,
    BundleResult,
    bundle_adjust,
    outlier_limit,
    polished,
    truncated_cost,
    truncated_costs,
)
from omni_sfm.estimate.families import world_families
from omni_sfm.estimate.global_positions import (
    GlobalPositionOptions,
    GlobalPositions,
    solve_positions,
)
from omni_sfm.estimate.global_rotations import (
    GlobalRotationOptions,
    GlobalRotations,
    chained_start,
    solve_rotations,
    world_normals,
)
from omni_sfm.estimate.revisits import (
    RevisitOptions,
    join_revisits,
    revisit_groups,
)
from omni_sfm.estimate.rig_scale import OffsetScale, facing_lines, offset_scale
from omni_sfm.estimate.segments import runs
from omni_sfm.estimate.uncertainty import SpreadCache, observation_noise, pose_spread
from omni_sfm.estimate.windows import window_starts
from omni_sfm.forked import run_all
from omni_sfm.geometry import (
    FloatArray,
    matrix_to_rotvec,
    nearest_rotation,
    rotation_about_axis,
    rotation_angle,
)
from omni_sfm.lines.tracks import LineTracks, reversed_frames
from omni_sfm.reports import EstimatorStep
from omni_sfm.solver import RobustLoss
from omni_sfm.transforms import umeyama
from omni_sfm.vanishing import ParallelFamily, VanishingOptions, detect_parallel_families


@dataclass(frozen=True, kw_only=True)
class GlobalOptions:
    """What a user of the global estimator may choose: which frames count as posed and how
    strict the flags are, the revisits, the workers. The values the design fixes are
    :class:`Settings`."""

    min_lines: int = 3
    """A frame is posed when it sees at least this many lines (of tracks seen twice or more)."""
    uncertain_deg: float = 0.5
    uncertain_path: float = 0.005
    """A frame that its own lines leave free is flagged where its interpolation between the
    frames that fix it can be off by more than this (degrees; fraction of the path length;
    :func:`_uncertain`)."""
    spread_deg: float = 0.6
    spread_path: float = 0.01
    """A frame is flagged where twice the error the adjustment's covariance expects exceeds
    this (degrees; fraction of the path length; :func:`_spread_flags`): a frame left unflagged
    is then off by more than 1 deg or 2 % of the path only beyond three times that error
    (rotations counted from the first trusted frame, as the errors are; docs/estimator.md,
    step 4)."""
    moved_path: float = 0.02
    """A frame that the adjustment moves by more than this fraction of the path from the
    linear positions is flagged (:func:`_moved_far`)."""
    revisits: RevisitOptions = field(default_factory=RevisitOptions)
    """Step 5: lines seen again on a revisit joined, and the problem solved again
    (:mod:`~omni_sfm.estimate.revisits`)."""
    progress: bool = False
    """A progress bar on stderr: the step running (the start windows show none)."""
    workers: int = 1
    """Processes at most that run the independent solves at once (the windows of the start,
    the two starts, the adjustment's starts; :func:`~omni_sfm.forked.run_all`): the result is
    the same to the bit whatever their number."""


@dataclass(frozen=True, kw_only=True)
class Settings(GlobalOptions):
    """The options and the values the design fixes (docs/estimator.md, "The global
    estimator"): the parallel-family detection and the adjustment as the caller runs them, and
    the steps' own thresholds. Studies and tests vary them; :func:`solve_global` takes the
    defaults."""

    vanishing: VanishingOptions = field(default_factory=VanishingOptions)
    """Parallel-family detection (the largest family anchors the start)."""
    rotations: GlobalRotationOptions = field(default_factory=GlobalRotationOptions)
    """Step 1, the joint rotation problem."""
    positions: GlobalPositionOptions = field(default_factory=GlobalPositionOptions)
    """Step 2, the linear position problem."""
    bundle: BundleOptions = field(default_factory=BundleOptions)
    """Step 3, the bundle adjustment."""
    world_direction_deg: float = 2.0
    """Lines whose directions (step 1, each line its own) agree within this share one world
    direction in the second solve."""
    member_sigmas: float = 2.5
    """A line keeps its world direction (step 1) only where its planes miss it by at most this
    many times the lines' own noise (:func:`_pruned`; on a 2.3 m walk through a textured office
    half the lines the families give a direction lie 7-40 deg off it, and held to it they
    turn the rotations by 0.85 deg); 0: no such test ..."""
    member_rounds: int = 3
    """... made at most this many times, each followed by the solve without the lines it
    left out."""
    snap_deg: float = 20.0
    """A family first seen within this of a known world direction (or of the axis completing
    two known perpendicular ones) is taken to have that direction."""
    start_window: int = 60
    """Posed frames of the windows whose own solutions make the start rotations
    (:func:`windows_start`); 0: the start of :func:`anchored_start` alone."""
    min_family_size: int = 5
    """Families of fewer tracks share no direction in the first solve (a few lines seen
    together in a few frames can look parallel without being so)."""
    min_spread_deg: float = 0.5
    """Lines whose planes turn by less than this (RMS, degrees) between the frames that see
    them have no known direction: they take no part in the positions (the adjustment
    triangulates them from the poses)."""
    outlier_sigmas: float = 3.0
    """Tracks whose rotation residuals (their normals against their direction, RMS) exceed
    this many times the residuals' robust spread are left out of the positions (a wrong
    correspondence; the adjustment judges them again)."""
    settled_start: bool = True
    """The adjustment also starts from the positions and lines settled on the rotations held,
    and the lower cost is kept (:func:`_adjusted`); the windows of the start do without."""
    hold_world_directions: bool = True
    """The adjustment holds the direction of every line of a world direction (the directions
    man-made places repeat are exact: their lines' noise then moves no rotation, and a frame
    whose other lines leave a turn weak keeps it)."""
    uncertain_information: float = 1e-3
    """A frame's own lines leave its position free where the smallest eigenvalue of its
    position information (its observations, the lines held) is below this fraction of the
    median frame's largest (its rotation: the same with its rotation information)."""
    spread_window: int = 300
    """Posed frames a window of the covariance takes at most
    (:func:`~omni_sfm.estimate.uncertainty.pose_spread`)."""
    min_trusted_run: int = 10
    """A stretch of fewer trusted frames than this, with more flagged frames than its own
    around it, is flagged too (:func:`_islands`)."""


def settings(options: GlobalOptions, **fixed: Any) -> Settings:
    """``options`` with the fixed values (their defaults, or those given in ``fixed``)."""
    if isinstance(options, Settings):
        return replace(options, **fixed)
    return Settings(**{f.name: getattr(options, f.name) for f in fields(GlobalOptions)},
                    **fixed)


@dataclass(frozen=True)
class GlobalSolution:
    """Poses and lines of all posed frames, in the first posed frame's world (no scale
    convention applied yet).

    Attributes:
        rotations, positions: ``(F, 3, 3)``, ``(F, 3)`` world_from_cam (NaN: not posed).
        frames: ``(F,)`` bool, posed frames.
        line_directions, line_points: ``(M, 3)`` (NaN: not used).
        used_tracks, outlier_tracks: ``(M,)`` bool.
        members: ``(M,)`` bool, the largest parallel family's tracks.
        world_directions: ``(K, 3)`` the world directions found.
        rms_initial_deg, rms_final_deg, sigma_deg: the adjustment's residuals.
        uncertain: ``{frame: reason}`` frames the data do not fix.
        spread_deg, spread_path: ``(F,)`` the RMS error the adjustment's covariance expects of
            each frame's rotation (degrees) and centre (fraction of the path), the frames not
            flagged aligned to the truth (:func:`_spread`; NaN: not posed or too few frames
            left unflagged; inf: left free).
        not_posed: ``{frame: reason}``.
        steps: what each step did (for the report).
        timings_ms: wall time per step.
        offset_scale: for a rig of lenses, the scale its start was found at
            (:func:`_rig_start`): where its lens offsets fix it, ``positions`` are in metres;
            None for a central camera.
    """

    rotations: FloatArray
    positions: FloatArray
    frames: np.ndarray
    line_directions: FloatArray
    line_points: FloatArray
    used_tracks: np.ndarray
    outlier_tracks: np.ndarray
    members: np.ndarray
    world_directions: FloatArray
    rms_initial_deg: float
    rms_final_deg: float
    sigma_deg: float
    uncertain: dict[int, str]
    spread_deg: FloatArray
    spread_path: FloatArray
    not_posed: dict[int, str]
    steps: list[EstimatorStep]
    timings_ms: dict[str, float]
    offset_scale: OffsetScale | None = None


def _posable(tracks: LineTracks, min_lines: int) -> tuple[np.ndarray, np.ndarray]:
    """``(frames, lines)``: tracks seen in two frames or more, frames that see ``min_lines``
    of them."""
    counts = np.bincount(tracks.obs_track, minlength=tracks.num_tracks)
    lines = counts >= 2
    per_frame = np.bincount(tracks.obs_frame[lines[tracks.obs_track]],
                            minlength=tracks.num_frames)
    return per_frame >= min_lines, lines


def _turn_onto(u: FloatArray, v: FloatArray) -> FloatArray:
    """The smallest rotation taking unit ``u`` onto unit ``v`` (each ``(3,)``)."""
    axis = np.cross(u, v)
    s = float(np.linalg.norm(axis))
    if s < 1e-15:
        return np.eye(3)
    return rotation_about_axis(axis / s, float(np.arctan2(s, u @ v)))


def _heading(axis: FloatArray, a: FloatArray, v: FloatArray) -> FloatArray:
    """The rotation about unit ``axis`` nearest the identity that makes the world normals
    ``a`` ``(K, 3)`` perpendicular to their lines' known directions ``v`` ``(K, 3)`` (least
    squares, a few Gauss-Newton steps from 0: eq. 13 of the paper for one frame; the other
    minimum, half a turn away, is not reached from a start that is right to a quarter turn)."""
    phi = 0.0
    for _ in range(5):
        Rz = rotation_about_axis(axis, phi)
        b = a @ Rz.T
        r = np.einsum("ij,ij->i", b, v)
        J = np.einsum("ij,ij->i", np.cross(axis, b), v)
        den = float(J @ J)
        if den < 1e-12:
            break
        step = -float(J @ r) / den
        phi += float(np.clip(step, -0.5, 0.5))
        if abs(step) < 1e-12:
            break
    return rotation_about_axis(axis, phi)


def _world_direction(u: FloatArray, world: FloatArray, snap_deg: float) -> tuple[FloatArray, int]:
    """The world direction of a family first seen along ``u`` (world, unit) and its index
    among ``world`` ``(K, 3)`` (NaN rows: not yet known): the known direction, or the third
    axis completing two known perpendicular ones, within ``snap_deg`` of ``u`` (its sign
    matched), else ``u`` itself as a new one (index -1). Man-made places repeat a few
    directions; a family of new lines along a known direction is the same world direction."""
    known = world[np.isfinite(world).all(axis=1)]
    cands = [w for w in known]
    for a in range(len(known)):
        for b in range(a + 1, len(known)):
            c = np.cross(known[a], known[b])
            if np.linalg.norm(c) > 0.9:
                cands.append(c / np.linalg.norm(c))
    best, idx = u, -1
    if cands:
        C = np.asarray(cands)
        g = C @ u
        i = int(np.argmax(np.abs(g)))
        if abs(g[i]) >= np.cos(np.radians(snap_deg)):
            best = C[i] * np.sign(g[i])
            idx = i if i < len(known) else -1
    return best, idx


def _assign_lines(S: FloatArray, count: np.ndarray, line_world: np.ndarray,
                  world: FloatArray, tracks_now: np.ndarray, min_views: int,
                  max_deg: float) -> None:
    """Give the lines ``tracks_now`` not yet assigned (``line_world`` -1) the known world
    direction that all their planes so far contain (RMS angle below ``max_deg`` over at least
    ``min_views`` views, every other known direction at least three times as far); ``S``
    ``(M, 3, 3)`` holds each line's scatter of world normals, ``count`` its views."""
    cand = tracks_now[(line_world[tracks_now] < 0) & (count[tracks_now] >= min_views)]
    ok = np.flatnonzero(np.isfinite(world[:, 0]))
    if len(cand) == 0 or len(ok) == 0:
        return
    W = world[ok]
    ms = np.einsum("ja,kab,jb->kj", W, S[cand], W) / count[cand][:, None]
    ang = np.degrees(np.sqrt(np.maximum(ms, 0.0)))
    best = np.argmin(ang, axis=1)
    first = ang[np.arange(len(cand)), best]
    ang[np.arange(len(cand)), best] = np.inf
    second = ang.min(axis=1) if ang.shape[1] > 1 else np.full(len(cand), np.inf)
    hit = (first < max_deg) & (second > 3 * first)
    line_world[cand[hit]] = ok[best[hit]]


def _anchored(Rk: FloatArray, vpv: FloatArray, normals: FloatArray, line_world: np.ndarray,
              world: FloatArray, vpv_deg: float) -> FloatArray:
    """A frame's start rotation ``Rk`` (the step from the previous frame) turned by the least
    rotation that puts the largest family's ``vpv`` (camera frame) on its world direction
    ``world[0]``, where it lies within ``vpv_deg`` of it, then about that direction so that its
    lines of known world direction (``line_world`` ``(K,)``: the world direction of each of
    the frame's ``normals`` ``(K, 3)``; -1: none, 0: the largest family's) are perpendicular to
    it (:func:`_heading`)."""
    u = Rk @ vpv
    if u @ world[0] >= np.cos(np.radians(vpv_deg)):
        # a VPV far from where the step from the previous frame puts it is wrong
        # (a frame with two or three of the family's lines, nearly coplanar)
        Rk = _turn_onto(u, world[0]) @ Rk
    known = (line_world > 0) & np.isfinite(world[np.maximum(line_world, 0), 0])
    if known.any():
        a = normals[known] @ Rk.T
        Rk = _heading(world[0], a, world[line_world[known]]) @ Rk
    return Rk


def anchored_start(tracks: LineTracks, frames: np.ndarray, families: list[ParallelFamily],
                   snap_deg: float = 20.0, min_views: int = 5, line_deg: float = 8.0,
                   min_family_size: int = 5, vpv_deg: float = 5.0
                   ) -> tuple[FloatArray, np.ndarray]:
    """Start rotations ``(F, 3, 3)``, frame after frame: the step from the previous frame
    (:func:`chained_start`), then the smallest turn that puts the largest family's VPV on its
    world direction (the paper's step V-a), then the turn about it that makes the frame's lines
    of known world direction perpendicular to it. A family's world direction is taken where
    its VPV is first seen (snapped to a known one within ``snap_deg``); a line joins a world
    direction once all its planes so far contain it (:func:`_assign_lines`). The chain's
    parallax and drift are left only where a frame sees no line of known direction but the
    largest family's. Families of fewer than ``min_family_size`` tracks but the largest give no
    world direction (a few lines that look parallel for a while need not be); a VPV more than
    ``vpv_deg`` from where the step from the previous frame puts it is not used (two or three
    of the family's lines seen nearly in one plane give a wrong one, and a step is right to a
    fraction of a degree). Returns the rotations and, per family, the family whose world
    direction it shares."""
    R_chain = chained_start(tracks, frames)
    if not families:
        return R_chain, np.zeros(0, int)
    M = tracks.num_tracks
    vpv = [np.asarray(f.vpv) for f in families]
    line_world = np.full(M, -1)
    big = [j for j, f in enumerate(families) if j == 0 or f.size >= min_family_size]
    for j in big[::-1]:
        line_world[np.asarray(families[j].members, bool)] = j
    order = np.argsort(tracks.obs_frame, kind="stable")
    starts = np.searchsorted(tracks.obs_frame[order], np.arange(tracks.num_frames + 1))
    world = np.full((len(families), 3), np.nan)
    same = np.arange(len(families))  # the family whose world direction each one shares
    S = np.zeros((M, 3, 3))
    count = np.zeros(M, int)
    R = R_chain.copy()
    prev = None
    for k in np.flatnonzero(frames):
        Rk = R_chain[k] if prev is None else R[prev] @ (R_chain[prev].T @ R_chain[k])
        obs = order[starts[k]:starts[k + 1]]
        t = tracks.obs_track[obs]
        if np.isfinite(vpv[0][k]).all():
            if not np.isfinite(world[0]).all():
                world[0] = Rk @ vpv[0][k]
            Rk = _anchored(Rk, vpv[0][k], tracks.obs_normal[obs], line_world[t], world,
                           vpv_deg)
        for j in big:
            if not np.isfinite(world[j]).all() and np.isfinite(vpv[j][k]).all():
                known_rows = np.flatnonzero(np.isfinite(world[:, 0]))
                world[j], i = _world_direction(Rk @ vpv[j][k], world, snap_deg)
                if i >= 0:
                    same[j] = same[known_rows[i]]
        R[k] = Rk
        m = tracks.obs_normal[obs] @ Rk.T
        S[t] += m[:, :, None] * m[:, None, :]
        count[t] += 1
        _assign_lines(S, count, line_world, world, t, min_views, line_deg)
        prev = k
    return R, same


def _closest_turn(axis: FloatArray, R: FloatArray, target: FloatArray) -> FloatArray:
    """``Rot(axis, phi) @ R`` nearest ``target`` (Frobenius): the turn about ``axis`` alone."""
    M = R @ target.T
    tr = float(np.trace(M))
    aMa = float(axis @ M @ axis)
    s = float(np.trace(np.cross(axis, np.eye(3)) @ M))
    # tr(Rot M) = cos(phi) (tr M - a.Ma) + sin(phi) tr([a]x M) + a.Ma
    return rotation_about_axis(axis, float(np.arctan2(-s, tr - aMa))) @ R


def free_turns_interpolated(rot: GlobalRotations, free: np.ndarray) -> FloatArray:
    """The rotations with each ``free`` frame (``(F,)`` bool: its lines leave a turn free)
    turned about its free axis to the rotation interpolated (slerp, in frame order) between
    the nearest fixed frames before and after it; the turn the data fix is kept."""
    from scipy.spatial.transform import Rotation, Slerp

    R = rot.rotations.copy()
    fixed = np.flatnonzero(rot.frames & ~free)
    if len(fixed) == 0:
        return R
    slerp = Slerp(fixed.astype(float), Rotation.from_matrix(R[fixed])) if len(fixed) > 1 \
        else None
    for k in np.flatnonzero(free & rot.frames):
        x = float(np.clip(k, fixed[0], fixed[-1]))
        target = slerp([x]).as_matrix()[0] if slerp is not None else R[fixed[0]]
        if np.isfinite(rot.free_axis[k]).all():
            R[k] = _closest_turn(rot.free_axis[k], R[k], target)
    return R


def _window_solution(tracks: LineTracks, sel: np.ndarray, options: Settings
                     ) -> FloatArray | None:
    """The rotations ``(len(sel), 3, 3)`` (NaN: not posed) of the frames ``sel`` solved on their
    own (steps 1-3 from :func:`anchored_start`); None where they determine nothing."""
    obs = np.flatnonzero(np.isin(tracks.obs_frame, sel))
    sub = tracks.subset(obs, np.unique(tracks.obs_track[obs]), sel)
    # a start needs the basin, not the last digit: two robust rounds, no polish
    local = replace(options, start_window=0, settled_start=False, workers=1,
                    member_sigmas=0.0, revisits=replace(options.revisits, enabled=False),
                    rotations=replace(options.rotations, max_iterations=20, every_line=True),
                    bundle=replace(options.bundle, max_rounds=2, final_loss=None))
    try:
        return _solve_once(sub, local, window=True).rotations
    except OmniSfmError:
        return None


def windows_start(tracks: LineTracks, frames: np.ndarray, R0: FloatArray,
                  options: Settings) -> FloatArray:
    """Start rotations ``(F, 3, 3)`` from windows of ``options.start_window`` posed frames,
    overlapping by a sixth, each solved on its own (rotations, positions, adjustment: within a
    window the chain of :func:`anchored_start` drifts little and the lines' positions fix the
    turns that their directions alone leave weak; :func:`_window_solution`). Each window's
    solution is turned onto its predecessor's by the rotation that best aligns their shared
    frames (a step that depends on the two windows alone, whichever way the video runs), and
    each frame takes the mean of its windows' rotations. Frames in no window that is kept take the
    step of ``R0`` from the nearest frame that is."""
    idx = np.flatnonzero(frames)
    window = options.start_window
    # consecutive windows share a sixth of their frames: enough to turn one onto the other
    sels = [idx[a:a + window] for a in window_starts(len(idx), window, window - window // 6)]
    solved = run_all([partial(_window_solution, tracks, sel, options) for sel in sels],
                     options.workers)
    kept = [(sel, got) for sel, got in zip(sels, solved, strict=True) if got is not None]
    if not kept:
        return R0
    acc = np.zeros((len(frames), 3, 3))
    prev: tuple[np.ndarray, FloatArray] | None = None
    for sel, R in kept:
        good = np.asarray(np.isfinite(R).all(axis=(1, 2)))
        if prev is None:
            A = np.eye(3)
        else:
            psel, pR = prev  # pR already turned into the common world
            _, i, j = np.intersect1d(psel, sel, return_indices=True)
            both = np.isfinite(pR[i]).all(axis=(1, 2)) & good[j]
            if both.sum() >= 3:
                A = nearest_rotation(np.einsum("kij,klj->il", pR[i][both], R[j][both]))
            else:  # no frames in common: the step of R0 between the nearest frames
                p = psel[np.flatnonzero(np.isfinite(pR).all(axis=(1, 2)))[-1]]
                q = int(np.flatnonzero(good)[0])
                target = pR[np.searchsorted(psel, p)] @ R0[p].T @ R0[sel[q]]
                A = target @ R[q].T
        R = np.einsum("ij,kjl->kil", A, R)
        acc[sel[good]] += R[good]
        prev = (sel, R)
    covered = np.abs(acc).sum(axis=(1, 2)) > 0
    R = R0.copy()
    R[covered] = nearest_rotation(acc[covered])
    fixed = np.flatnonzero(covered)
    for k in np.flatnonzero(frames & ~covered):
        n = fixed[np.argmin(np.abs(fixed - k))]
        R[k] = R[n] @ R0[n].T @ R0[k]
    first = idx[0]
    return np.asarray(np.einsum("ij,kjl->kil", R[first].T, R))


def _groups(lines: np.ndarray, label: np.ndarray) -> np.ndarray:
    """The direction variable of each track: one per label (``label`` ``(M,)``, -1: none),
    one per unlabelled line, -1 for tracks not used."""
    group = np.full(len(lines), -1)
    lab = np.where(lines, label, -1)
    nxt = 0
    for k in np.unique(lab[lab >= 0]):
        group[lab == k] = nxt
        nxt += 1
    rest = lines & (lab < 0)
    group[rest] = nxt + np.arange(int(rest.sum()))
    return group


def _family_labels(tracks: LineTracks, families: list[ParallelFamily], same: np.ndarray,
                   min_size: int) -> np.ndarray:
    """``(M,)`` the world direction (one of ``same``'s values) of each member of a family of
    at least ``min_size`` tracks, -1 for the rest."""
    label = np.full(tracks.num_tracks, -1)
    for j, f in enumerate(families):
        if f.size >= min_size:
            label[np.asarray(f.members, bool)] = same[j]
    return label


def _labels(tracks: LineTracks, R: FloatArray, frames: np.ndarray, lines: np.ndarray,
            worlds: FloatArray, max_deg: float) -> np.ndarray:
    """``(M,)`` the world direction (index into ``worlds``) whose planes each line's planes
    contain: RMS angle of its world normals from perpendicular to it below ``max_deg``, and
    every other world direction at least three times (and 1 deg) as far; -1 where none or where
    two fit (a line whose planes barely turn contains every direction of its plane)."""
    label = np.full(tracks.num_tracks, -1)
    if len(worlds) == 0:
        return label
    ok = frames[tracks.obs_frame] & lines[tracks.obs_track]
    m = world_normals(tracks, R, ok)
    t = tracks.obs_track[ok]
    sq = np.zeros((tracks.num_tracks, len(worlds)))
    np.add.at(sq, t, (m @ worlds.T) ** 2)
    n = np.maximum(np.bincount(t, minlength=tracks.num_tracks), 1)
    ang = np.degrees(np.arcsin(np.sqrt(np.clip(sq / n[:, None], 0.0, 1.0))))
    best = np.argmin(ang, axis=1)
    first = ang[np.arange(len(ang)), best]
    ang[np.arange(len(ang)), best] = np.inf
    second = ang.min(axis=1)
    hit = lines & (first < max_deg) & (second > np.maximum(3 * first, 1.0))
    label[hit] = best[hit]
    return label


def _pruned(tracks: LineTracks, frames: np.ndarray, lines: np.ndarray, rot: GlobalRotations,
            label: np.ndarray, sigmas: float) -> np.ndarray:
    """``label`` without the lines that do not hold their shared direction: a line whose
    planes miss it by more than ``sigmas`` times the lines' own noise (RMS angle of its world
    normals from perpendicular to the direction, against the median over the lines of that
    angle for each line's own best direction). Over a short stretch a line's planes barely
    turn and contain, to a degree or two, directions tens of degrees from its own."""
    ok = frames[tracks.obs_frame] & lines[tracks.obs_track]
    m = world_normals(tracks, rot.rotations, ok)
    t = tracks.obs_track[ok]
    n = np.maximum(np.bincount(t, minlength=tracks.num_tracks), 1)
    S = np.zeros((tracks.num_tracks, 3, 3))
    np.add.at(S, t, m[:, :, None] * m[:, None, :])
    own = np.sqrt(np.clip(np.linalg.eigvalsh(S)[:, 0], 0.0, None) / n)
    shared = np.zeros(tracks.num_tracks)
    d = np.nan_to_num(rot.directions)
    np.add.at(shared, t, np.einsum("ki,ki->k", m, d[t]) ** 2)
    shared = np.sqrt(shared / n)
    noise = float(np.median(own[lines & (n >= 3)])) if np.any(lines & (n >= 3)) else 0.0
    out = label.copy()
    out[lines & (label >= 0) & (shared > sigmas * noise)] = -1
    return out


def _family_direction(directions: FloatArray, family: ParallelFamily) -> FloatArray:
    """The shared direction of a family's members after a solve (unit)."""
    d = directions[np.asarray(family.members, bool)]
    d = d[np.isfinite(d).all(axis=1)]
    return np.asarray(d[0] if len(d) else np.full(3, np.nan))


def _horizontal_directions(rot: GlobalRotations, families: list[ParallelFamily],
                           options: Settings) -> FloatArray:
    """``(K, 3)`` the directions of the families (of ``options.min_family_size`` or more)
    perpendicular to the largest one's within ``snap_deg``, and the axis completing the first
    of them with the largest's: the world directions across the largest family."""
    if not families:
        return np.zeros((0, 3))
    v0 = _family_direction(rot.directions, families[0])
    out: list[FloatArray] = []
    for f in families[1:]:
        if f.size < options.min_family_size:
            continue
        v = _family_direction(rot.directions, f)
        if not np.isfinite(v).all() or abs(v @ v0) > np.sin(np.radians(options.snap_deg)):
            continue
        v = v - (v @ v0) * v0
        v /= np.linalg.norm(v)
        if all(abs(v @ w) < np.cos(np.radians(options.snap_deg)) for w in out):
            out.append(v)
    if len(out) == 1:
        out.append(np.cross(v0, out[0]))
    return np.asarray(out).reshape(-1, 3)


def _backward_start(tracks: LineTracks, frames: np.ndarray, families: list[ParallelFamily],
                    R0: FloatArray, options: Settings) -> FloatArray:
    """The anchored chain (:func:`anchored_start`) run from the last frame to the first, in
    the gauge of ``R0`` (the forward chain's: the first posed frame's rotation the same). With
    both chains among the starts, the same tracks in the other frame order start from the same
    two, and the solution kept (:func:`kept_start`) does not follow the order."""
    back = [replace(f, vpv=f.vpv[::-1], frame_residual=f.frame_residual[::-1],
                    frame_members=f.frame_members[::-1]) for f in families]
    Rb, _ = anchored_start(reversed_frames(tracks), frames[::-1], back, options.snap_deg,
                           min_family_size=options.min_family_size)
    Rb = Rb[::-1]
    k = int(np.flatnonzero(frames)[0])
    return np.einsum("ij,fjk->fik", R0[k] @ Rb[k].T, Rb)


def kept_start(tracks: LineTracks, frames: np.ndarray, lines: np.ndarray,
               starts: dict[str, FloatArray], group: np.ndarray, options: Settings
               ) -> tuple[str, GlobalRotations]:
    """The joint rotation problem (the tracks of ``group`` sharing its directions) solved
    from each of the ``starts`` (name: ``(F, 3, 3)`` rotations): the name and the solution
    whose positions (step 2 on its rotations, :func:`_positions_costs`) fit best the
    observations of the lines seen where the solutions disagree (ties go to the later start).
    The directions alone can fit a wrong turn better than the right one: where one family is
    the only shared direction, the turn about it rests on the other lines' positions, and a
    stretch turned by a start whose chain carried the lines' parallax fits their directions as
    well; its positions do not fit. A stretch turned by 90 deg in a Manhattan world fits its
    own lines as well as the right one: only the lines seen on both sides of where it turns
    tell them apart, and over every observation of a long video their misfit weighs less than
    the two solutions' small differences elsewhere (:func:`_disagreeing_tracks`)."""
    names = list(starts)
    solved = dict(zip(names, run_all([partial(solve_rotations, tracks, frames, starts[name],
                                              group, options.rotations) for name in names],
                                     options.workers), strict=True))
    # starts that reach the same minimum need no positions to tell them apart
    names = [name for k, name in enumerate(names)
             if not any(_same_rotations(solved[name], solved[other]) for other in names[:k])]
    if len(names) == 1:
        return names[0], solved[names[0]]
    sigma = min(solved[name].sigma for name in names)
    costs = dict(zip(names, run_all([partial(_positions_costs, tracks, solved[name], frames,
                                             lines, sigma, options) for name in names],
                                    options.workers), strict=True))
    seen = _disagreeing_tracks(tracks, [solved[name].rotations for name in names], frames)
    where = seen[tracks.obs_track]
    cost = {name: float(np.mean(costs[name][where])) for name in names}
    best = min(reversed(names), key=lambda name: cost[name])
    return best, solved[best]


def _same_rotations(a: GlobalRotations, b: GlobalRotations, tolerance_deg: float = 1e-3
                    ) -> bool:
    """Whether two solutions of the joint rotation problem (the same gauge) are one minimum:
    every frame's rotations within ``tolerance_deg``."""
    if not np.array_equal(a.frames, b.frames):
        return False
    rel = np.einsum("fji,fjk->fik", a.rotations[a.frames], b.rotations[b.frames])
    return bool(np.degrees(rotation_angle(rel)).max(initial=0.0) <= tolerance_deg)


_DISAGREE_DEG = 2.0
"""Two start solutions disagree on a frame whose rotations differ by more than this
(:func:`_disagreeing_tracks`; where both are right they agree to a few tenths of a degree)."""


def _disagreeing_tracks(tracks: LineTracks, rotations: list[FloatArray], frames: np.ndarray
                        ) -> np.ndarray:
    """``(M,)`` the tracks seen in a frame where two of the ``rotations`` (each ``(F, 3, 3)``,
    the same gauge) differ by more than :data:`_DISAGREE_DEG`; every track where they agree
    on every frame."""
    idx = np.flatnonzero(frames)
    apart = np.zeros(tracks.num_frames, bool)
    for k, a in enumerate(rotations):
        for b in rotations[k + 1:]:
            rel = np.einsum("fji,fjk->fik", a[idx], b[idx])
            apart[idx] |= np.degrees(rotation_angle(rel)) > _DISAGREE_DEG
    if not apart.any():
        return np.ones(tracks.num_tracks, bool)
    seen = np.zeros(tracks.num_tracks, bool)
    seen[tracks.obs_track[apart[tracks.obs_frame]]] = True
    return seen


def _positions_costs(tracks: LineTracks, rot: GlobalRotations, frames: np.ndarray,
                     lines: np.ndarray, sigma: float, options: Settings) -> FloatArray:
    """``(K,)`` each observation's truncated cost (:func:`~omni_sfm.estimate.bundle.
    truncated_costs`, the limit of noise ``sigma``) at the positions :func:`_positions_step`
    finds from ``rot``; inf where it finds none."""
    try:
        R, c, _, _ = _positions_step(tracks, rot, frames, lines, options)
    except OmniSfmError:
        return np.full(tracks.num_observations, np.inf)
    posed = frames & np.isfinite(c).all(axis=1)
    return truncated_costs(tracks, R, c, posed, outlier_limit(sigma, options.bundle))


def _snapped(tracks: LineTracks, frames: np.ndarray, lines: np.ndarray, first: GlobalRotations,
             families: list[ParallelFamily], options: Settings,
             steps: list[EstimatorStep]) -> GlobalRotations:
    """Step 1's second solve, where the families give horizontal directions: a line across the
    largest family whose planes contain one of the other families' directions up to a few
    degrees is of that direction (a stretch whose start turned before that family was seen is
    pulled back by its lines). ``first``: the first solve's rotations, returned where there is
    no such direction."""
    horizontal = _horizontal_directions(first, families, options)
    if not len(horizontal):
        return first
    v0 = _family_direction(first.directions, families[0])
    own = np.abs(np.nan_to_num(first.directions) @ v0) < np.sin(
        np.radians(options.world_direction_deg))
    label = _labels(tracks, first.rotations, frames, lines & own, horizontal, options.snap_deg)
    label[lines & np.asarray(families[0].members, bool)] = len(horizontal)
    rot = solve_rotations(tracks, frames, first.rotations, _groups(lines, label),
                          options.rotations)
    steps.append(EstimatorStep(step="rotations, lines across the largest family snapped to the "
                                    "other families' directions",
                               directions=len(horizontal), iterations=rot.iterations,
                               sigma_deg=float(np.degrees(rot.sigma))))
    return rot


def _rotations(tracks: LineTracks, frames: np.ndarray, lines: np.ndarray,
               families: list[ParallelFamily], options: Settings,
               steps: list[EstimatorStep], previous: FloatArray | None = None
               ) -> tuple[GlobalRotations, FloatArray, np.ndarray]:
    """Step 1: the start, the solve with the families' world directions shared, the solve
    with the lines' world directions (clusters of their directions) shared.

    The first solve runs from two starts (from ``previous`` alone where given: an earlier
    solution's rotations), the chain anchored on the families' directions
    (:func:`anchored_start`) and the windows solved on their own (:func:`windows_start`),
    and keeps the rotations whose positions fit every line best (:func:`kept_start`): where
    the families anchor every frame the chain is right to a fraction of a degree and a window
    solved in a stretch of few lines can be off by tens of degrees; where one family anchors a
    random world the chain drifts about it and the windows do not."""
    R0, same = anchored_start(tracks, frames, families, options.snap_deg,
                              min_family_size=options.min_family_size)
    label = _family_labels(tracks, families, same, options.min_family_size)
    group = _groups(lines, label)
    starts = {"anchored": R0}
    if previous is not None:  # an earlier solution (the anchored chain where it posed none)
        starts = {"previous": np.where(np.isfinite(previous), previous, R0)}
    elif options.start_window:  # (not inside a window of the windows' start: 0 there)
        starts["anchored backwards"] = _backward_start(tracks, frames, families, R0, options)
        if frames.sum() > options.start_window:
            starts["windows"] = windows_start(tracks, frames, R0, options)
    start, first = kept_start(tracks, frames, lines, starts, group, options)
    steps.append(EstimatorStep(step="rotations, the families' world directions shared",
                               families=[f.size for f in families], start=start,
                               iterations=first.iterations,
                               sigma_deg=float(np.degrees(first.sigma))))
    rot = _snapped(tracks, frames, lines, first, families, options, steps)
    used = np.flatnonzero(lines)
    angle = options.world_direction_deg
    worlds = world_families(rot.directions[used], max_angle_deg=angle)
    label = _labels(tracks, rot.rotations, frames, lines, worlds, angle)
    rot = solve_rotations(tracks, frames, rot.rotations, _groups(lines, label),
                          options.rotations)
    for _ in range(options.member_rounds if options.member_sigmas > 0 else 0):
        kept = _pruned(tracks, frames, lines, rot, label, options.member_sigmas)
        if np.array_equal(kept, label):
            break
        label = kept
        rot = solve_rotations(tracks, frames, rot.rotations, _groups(lines, label),
                              options.rotations)
    steps.append(EstimatorStep(step="rotations, world directions shared",
                               world_directions=len(worlds), iterations=rot.iterations,
                               sigma_deg=float(np.degrees(rot.sigma))))
    return rot, worlds, label


def _resected(tracks: LineTracks, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
              frames: np.ndarray, free: np.ndarray) -> FloatArray:
    """``(F, 3)`` the centres with each ``free`` frame's (its rotation's turn and so its
    position left out of the linear steps) interpolated between its neighbours and moved, its
    rotation held, to the lines with a position that it sees: the smallest move that puts
    each line in its observed plane (least squares, minimum norm), so that the directions its
    lines leave free (along them, where they all have one direction) keep the interpolation,
    and its rotation is not turned by a few lines whose positions the linear step gives
    roughly."""
    c = c.copy()
    fixed = np.flatnonzero(frames & ~free)
    todo = np.flatnonzero(frames & free)
    if len(todo) == 0 or len(fixed) == 0:
        return c
    for a in range(3):
        c[todo, a] = np.interp(todo, fixed, c[fixed, a])
    known = np.asarray(np.isfinite(p).all(axis=1) & np.isfinite(d).all(axis=1))
    usable = np.flatnonzero(known[tracks.obs_track])
    usable = usable[np.argsort(tracks.obs_frame[usable], kind="stable")]
    bounds = np.searchsorted(tracks.obs_frame[usable], np.arange(len(frames) + 1))
    for k in todo:
        obs = usable[bounds[k]:bounds[k + 1]]
        if len(obs) < 2:
            continue
        t = tracks.obs_track[obs]
        m = tracks.obs_normal[obs] @ R[k].T
        m = m - np.einsum("ki,ki->k", m, d[t])[:, None] * d[t]
        m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)
        # m . (p - c) = 0 for each line: the move of c that satisfies them best
        move = np.linalg.lstsq(m, np.einsum("ki,ki->k", m, p[t] - c[k]), rcond=1e-6)[0]
        c[k] = c[k] + move
    return c


def _direction_rms(tracks: LineTracks, R: FloatArray, d: FloatArray, frames: np.ndarray
                   ) -> FloatArray:
    """``(M,)`` RMS of each track's residuals ``(R n) . d`` over the posed frames (radians; NaN
    without a direction)."""
    ok = frames[tracks.obs_frame]
    m = world_normals(tracks, R, ok)
    r2 = np.einsum("ki,ki->k", m, d[tracks.obs_track[ok]]) ** 2
    n = np.bincount(tracks.obs_track[ok], minlength=tracks.num_tracks)
    sq = np.bincount(tracks.obs_track[ok], r2, minlength=tracks.num_tracks)
    return np.asarray(np.sqrt(sq / np.maximum(n, 1)))


def plane_spread_deg(tracks: LineTracks, R: FloatArray, frames: np.ndarray) -> FloatArray:
    """``(M,)`` how far each line's planes turn between the posed ``frames`` (the RMS angle of
    its world normals about their mean plane normal, degrees; 0 for a line seen once): a line
    whose planes barely turn lies in a known plane but has no known direction within it."""
    ok = frames[tracks.obs_frame]
    m = world_normals(tracks, R, ok)
    S = np.zeros((tracks.num_tracks, 3, 3))
    np.add.at(S, tracks.obs_track[ok], m[:, :, None] * m[:, None, :])
    n = np.maximum(np.bincount(tracks.obs_track[ok], minlength=tracks.num_tracks), 1)
    ev = np.linalg.eigvalsh(S / n[:, None, None])
    return np.asarray(np.degrees(np.sqrt(np.maximum(ev[:, 1], 0.0))))


def _rotation_free(rot: GlobalRotations, frames: np.ndarray, options: Settings
                   ) -> np.ndarray:
    """``(F,)`` posed frames whose lines leave a turn free (their rotation information below
    ``options.uncertain_information`` times the median frame's)."""
    rinfo = rot.frame_information
    ok = frames & np.isfinite(rinfo)
    ref = float(np.median(rinfo[ok])) if ok.any() else 1.0
    return ok & (rinfo < options.uncertain_information * ref)


def _gap_errors(free: np.ndarray, values: FloatArray, direction: FloatArray | None = None,
                lag: int = 4) -> FloatArray:
    """``(N,)`` the error to expect (two standard deviations) where the ``free`` items of a
    sequence ``values`` ``(N, D)`` are interpolated between the fixed ones on either side.
    The motion is taken as an integrated random walk whose second differences have the spread
    that the fixed items show over ``lag`` steps (along ``direction`` ``(N, D)``, each item's,
    where given; over several steps, so that the estimates' own noise counts little): its
    variance at the ``i``-th of a gap of ``G`` steps is ``s^2 i^3 (G - i)^3 / (3 G^3)``
    between two fixed items, ``s^2 i^3 / 3`` beyond the last one."""
    out = np.zeros(len(free))
    h = lag
    k = np.arange(h, len(free) - h)
    k = k[~free[k] & ~free[k - h] & ~free[k + h]]
    if not free.any() or len(k) == 0:
        return out
    d2 = values[k + h] - 2 * values[k] + values[k - h]
    size = np.abs(np.einsum("ki,ki->k", d2, direction[k])) if direction is not None else \
        np.linalg.norm(d2, axis=1)
    size = size[np.isfinite(size)]
    if len(size) == 0:
        return out
    spread = 1.4826 * float(np.median(size)) / np.sqrt((2 * h**3 + h) / 3)
    for a, b in runs(free):
        i = np.arange(a, b) - a + 1.0
        G = b - a + 1.0
        if a > 0 and b < len(free):
            var = i**3 * (G - i) ** 3 / (3 * G**3)
        else:
            var = (i if a > 0 else G - i) ** 3 / 3
        out[a:b] = 2.0 * spread * np.sqrt(var)
    return out


def _used_observations(tracks: LineTracks, ba: BundleResult) -> tuple[np.ndarray, np.ndarray]:
    """``(used, seen)``: ``(K,)`` the observations the adjustment used (its tracks in its posed
    frames) and ``(F,)`` their count in each frame."""
    used = ba.frames[tracks.obs_frame] & ba.used_tracks[tracks.obs_track]
    return used, np.bincount(tracks.obs_frame[used], minlength=tracks.num_frames)


def _weak_ties(tracks: LineTracks, ba: BundleResult, used: np.ndarray, seen: np.ndarray,
               flagged: Collection[int] = (), min_ties: int = 4,
               listed: Collection[int] = ()) -> dict[int, str]:
    """Frames in another part of the video than the largest, where the parts are cut between
    two frames that see more than 3 lines and are not ``flagged`` (with a stretch of frames
    that see 3 lines or fewer, are flagged or are not posed, between them, or none) across
    which fewer than ``min_ties`` lines are seen on both sides: the pose of one part relative
    to the other then rests on those few lines (or frames whose lines fix them with nothing to
    spare, or not at all), and nothing checks it (a turn of 90 deg or a wrong scale fits as
    well: a fast turn that the tracker loses most lines through). The largest part is the one
    with the most tying frames not ``listed`` already (a part flagged before is not the one the
    others are measured against).
    ``used``: ``(K,)`` the observations the adjustment used; ``seen``: ``(F,)`` their count in
    each frame."""
    tying = ba.frames & (seen > 3)
    tying[list(flagged)] = False
    strong = np.flatnonzero(tying)
    if len(strong) < 2:
        return {}
    first, last = tracks.frame_spans(used)
    cuts = [(int(a), int(b), int(np.sum((first <= a) & (last >= b))))
            for a, b in zip(strong[:-1], strong[1:], strict=True)]
    cuts = [c for c in cuts if c[2] < min_ties]
    if not cuts:
        return {}
    edges = [0, *[b for _, b, _ in cuts], tracks.num_frames]
    parts = [(lo, hi) for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
    counted = strong[~np.isin(strong, list(listed))]
    size = [(int(np.sum((counted >= lo) & (counted < hi))),
             int(np.sum((strong >= lo) & (strong < hi)))) for lo, hi in parts]
    main = parts[max(range(len(parts)), key=size.__getitem__)]
    fixed = strong[(strong >= main[0]) & (strong < main[1])]
    out: dict[int, str] = {}
    for lo, hi in parts:
        if (lo, hi) == main:
            continue
        # the cut between this part and the main one, on the main one's side
        a, b, n = next(c for c in cuts if c[1] == (main[0] if hi <= main[0] else main[1]))
        through = f"frames {a + 1}-{b - 1}, which see 3 lines or fewer or are flagged, and " \
            if b - a > 1 else ""
        for k in np.flatnonzero(ba.frames[lo:hi]) + lo:
            out[int(k)] = (f"tied to frames {fixed[0]}-{fixed[-1]} only through {through}{n} "
                           f"lines seen on both sides of frames {a}-{b}: its pose relative to "
                           "them is not checked by the data")
    return out


def _uncertain(tracks: LineTracks, rot: GlobalRotations, pos: GlobalPositions,
               ba: BundleResult, options: Settings) -> dict[int, str]:
    """Frames that see 3 lines only (they fit several poses exactly: nothing checks the one
    found), and frames whose rotation or position the data leave (nearly) free and whose
    interpolation between the frames that fix them can be off by more than
    ``options.uncertain_deg`` or ``options.uncertain_path`` of the path, with the reason
    (:func:`_gap_errors`: the walk's own curvature over the length of the stretch; a frame or
    two between fixed ones are interpolated well)."""
    idx = np.flatnonzero(ba.frames)
    if len(idx) < 3:
        return {}
    R, c = ba.rotations[idx], ba.positions[idx]
    rfree = _rotation_free(rot, ba.frames, options)[idx]
    pfree = ~rfree & (pos.frame_information[idx] < options.uncertain_information)
    # rotations as rotation vectors from the first frame's (small turns between frames:
    # their second differences are the turns' second differences)
    rvec = matrix_to_rotvec(np.einsum("ji,kjl->kil", R[0], R))
    path = max(float(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1))), 1e-300)
    rot_err = np.degrees(_gap_errors(rfree, rvec))
    # the motion along the direction the frame's lines fix least (a frame whose lines all run
    # along the walk is free along the walk, where walking is smooth)
    pos_err = 100.0 * _gap_errors(rfree | pfree, c, np.nan_to_num(pos.free_direction[idx])) / path
    used, seen_all = _used_observations(tracks, ba)
    seen = seen_all[idx]
    out = _weak_ties(tracks, ba, used, seen_all)
    for j, k in enumerate(idx):
        if int(k) in out:
            continue
        if seen[j] <= 3:
            out[int(k)] = (f"sees {seen[j]} lines only: they fix its pose with nothing to spare "
                           f"(several poses fit them exactly, and no other line tells which)")
        elif rfree[j] and (rot_err[j] > options.uncertain_deg or
                         pos_err[j] > 100 * options.uncertain_path):
            out[int(k)] = (f"rotation not fixed: its lines have (nearly) one direction; the "
                           f"turn about it comes from the neighbouring frames (up to "
                           f"{rot_err[j]:.2f} deg, {pos_err[j]:.2f} % of the path)")
        elif pfree[j] and pos_err[j] > 100 * options.uncertain_path:
            out[int(k)] = (f"position not fixed by its own lines (they leave a direction of "
                           f"motion free); it comes from the neighbouring frames (up to "
                           f"{pos_err[j]:.2f} % of the path)")
    return out


def _spread(tracks: LineTracks, ba: BundleResult, flagged: dict[int, str],
            options: Settings, held: np.ndarray | None = None,
            cache: SpreadCache | None = None) -> tuple[FloatArray, FloatArray]:
    """``(rotation_deg, path)`` ``(F,)`` the RMS error the adjustment's covariance expects of
    each posed frame (degrees; fraction of the path length of the frames not ``flagged``), the
    frames not ``flagged`` aligned to the truth (:func:`~omni_sfm.estimate.uncertainty.
    pose_spread`, over every posed frame: the flagged ones tie the others together; inf where
    the data leave the pose free; the lines ``held`` keep their direction, as the adjustment
    held them; the noise its residuals show scaled up for the parameters they fit:
    :func:`~omni_sfm.estimate.uncertainty.observation_noise`; ``cache``: the windows' figures
    kept between the flags' rounds)."""
    nan = np.full(tracks.num_frames, np.nan)
    trusted = ba.frames.copy()
    trusted[list(flagged)] = False
    if trusted.sum() < 3:
        return nan, nan.copy()
    c = ba.positions[trusted]
    path = max(float(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1))), 1e-300)
    sigma = observation_noise(float(np.radians(ba.sigma_deg)), tracks, ba.frames,
                              ba.used_tracks, held)
    spread = pose_spread(tracks, ba.rotations, ba.positions, ba.line_directions,
                         ba.line_points, ba.frames, ba.used_tracks, sigma,
                         window=options.spread_window, aligned=trusted,
                         held_directions=held, cache=cache)
    return spread.rotation_deg, spread.position / path


_PEEL = 10.0
"""The frames the covariance leaves weak are flagged in rounds (:func:`_spread_flags`): each
round those within this factor of the weakest."""


def _spread_flags(rotation_deg: FloatArray, path: FloatArray, options: Settings,
                  listed: Collection[int] = ()) -> dict[int, str]:
    """The frames whose pose the whole of the data fix to no better than
    ``options.spread_deg`` or ``options.spread_path`` of their path (twice the error
    :func:`_spread` expects): a stretch whose lines leave the walk's speed or bend nearly
    free, although each frame's own lines look enough. The weakest first: of the frames not
    ``listed`` already, only those within ``_PEEL`` of the weakest (relative to the limits)
    are listed; the caller measures the spread of the rest again without them (a stretch
    whose pose nothing fixes would otherwise spread its error, through the alignment, over the
    frames the data do fix)."""
    rot, pos = 2.0 * rotation_deg, 2.0 * path
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.fmax(rot / options.spread_deg, pos / options.spread_path)
        ratio[list(listed)] = np.nan
        weak = ratio > 1.0
        if weak.any():
            weak &= ratio >= np.nanmax(ratio[weak]) / _PEEL
    out = {}
    for k in np.flatnonzero(weak):
        if not np.isfinite(rot[k] + pos[k]):
            out[int(k)] = ("the data leave its pose free (a direction of the adjustment that "
                           "moves it, and few other frames, is not fixed by any line)")
            continue
        out[int(k)] = (f"the data fix its pose only to {rot[k]:.2f} deg and "
                       f"{100 * pos[k]:.2f} % of the path (twice the error the adjustment's "
                       f"covariance expects): the lines leave the walk's speed or bend between "
                       f"it and the other frames nearly free")
    return out


def _adjusted(tracks: LineTracks, R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray,
              frames: np.ndarray, held: np.ndarray | None, options: Settings
              ) -> BundleResult:
    """Step 3: the robust adjustment of all cameras and lines from the start as it is and, with
    ``options.settled_start``, from the start with the positions and lines first settled on the
    rotations held (one robust round, no track rejected), under the adjustment's loss, and from
    the start as it is under the Cauchy loss; the one with the lowest truncated cost
    (:func:`~omni_sfm.estimate.bundle.truncated_cost`, every observation) is kept.

    Where the parallax is low the linear positions can be off by many times the noise: from
    them the rotations turn to absorb the error and can settle in another minimum, and from the
    settled start too at times. Gross outlier tracks (a tracker that jumped between two
    parallel lines) pull a Huber adjustment off a good start before its rounds reject them, and
    a stretch then collapses onto the lines that agree with the pull; the Cauchy loss gives them
    no weight, but on its own it rejects more of the weakly tied lines elsewhere. Which of them
    holds depends on the data, not on the frame order. Candidates whose robust rounds kept the
    same tracks polish to one minimum: of those only the one of lowest cost is polished
    (:func:`~omni_sfm.estimate.bundle.polished`; the polish is the adjustment's longest
    solve). Returns the adjustment kept."""
    def settled_first(bo: BundleOptions) -> BundleResult:
        settled = bundle_adjust(tracks, R, c, d, p, frames=frames, held_directions=held,
                                held_rotations=frames,
                                options=replace(bo, reject_outliers=False, max_rounds=1,
                                                final_loss=None))
        return bundle_adjust(tracks, settled.rotations, settled.positions,
                             settled.line_directions, settled.line_points,
                             frames=settled.frames, held_directions=held, options=bo)

    solves: list[Callable[[], BundleResult]] = []
    for loss in dict.fromkeys((options.bundle.loss, RobustLoss.CAUCHY)):
        # the robust rounds find the basin and the outliers; the polish comes after the choice
        bo = replace(options.bundle, loss=loss, final_loss=None)
        solves.append(partial(bundle_adjust, tracks, R, c, d, p, frames=frames,
                             held_directions=held, options=bo))
        if options.settled_start and loss == options.bundle.loss:
            solves.append(partial(settled_first, bo))
    candidates = run_all(solves, options.workers)
    limit = outlier_limit(float(np.radians(max(x.sigma_deg for x in candidates))),
                          options.bundle)

    def cost(x: BundleResult) -> float:
        return truncated_cost(tracks, x.rotations, x.positions, x.frames, limit,
                              everywhere=True)

    # candidates that kept the same tracks polish to one minimum: the lowest of each set
    best: dict[bytes, tuple[float, BundleResult]] = {}
    for x in candidates:
        key, cx = np.packbits(x.used_tracks).tobytes(), cost(x)
        if key not in best or cx < best[key][0]:
            best[key] = (cx, x)
    kept = run_all([partial(polished, tracks, x, held_directions=held, options=options.bundle)
                    for _, x in best.values()], options.workers)
    return kept[int(np.argmin([cost(x) for x in kept]))]


def _positions_step(tracks: LineTracks, rot: GlobalRotations, frames: np.ndarray,
                    lines: np.ndarray, options: Settings
                    ) -> tuple[FloatArray, FloatArray, GlobalPositions, np.ndarray]:
    """Step 2: ``(R, c, positions, dir_ok)``. The frames whose lines leave a turn free get it
    interpolated (:func:`free_turns_interpolated`); the lines with a known direction
    (``dir_ok``: their planes turn, their normals fit it) take part in the linear positions;
    the free frames' centres are then moved onto those lines, their rotations held
    (:func:`_resected`)."""
    free = _rotation_free(rot, frames, options)
    R = free_turns_interpolated(rot, free)
    dir_ok = lines & np.isfinite(rot.directions).all(axis=1) & \
        (plane_spread_deg(tracks, R, frames) >= options.min_spread_deg) & \
        (_direction_rms(tracks, R, rot.directions, frames) <=
         options.outlier_sigmas * rot.sigma)
    pos = solve_positions(tracks, R, rot.directions, frames & ~free, dir_ok, options.positions)
    c = _resected(tracks, R, pos.positions, rot.directions, pos.points, frames, free)
    return R, c, pos, dir_ok


def _adjustment_step(tracks: LineTracks, R: FloatArray, c: FloatArray, rot: GlobalRotations,
                     pos: GlobalPositions, dir_ok: np.ndarray, label: np.ndarray,
                     frames: np.ndarray, options: Settings) -> BundleResult:
    """Step 3: the robust adjustment from the positions' start (:func:`_adjusted`), the lines
    of a world direction (``label``) held to step 1's."""
    d0 = np.where(dir_ok[:, None], rot.directions, np.nan)
    # the lines of a world direction keep it: only their positions move (and with two world
    # directions or more they hold the rotation gauge)
    return _adjusted(tracks, R, c, d0, pos.points, frames, _held(dir_ok, label, options),
                     options)


def _held(dir_ok: np.ndarray, label: np.ndarray, options: Settings) -> np.ndarray | None:
    """The lines whose world direction (``label``) the adjustment holds to step 1's."""
    return dir_ok & (label >= 0) if options.hold_world_directions else None


def _flags(tracks: LineTracks, rot: GlobalRotations, pos: GlobalPositions, c: FloatArray,
           ba: BundleResult, options: Settings, held: np.ndarray | None = None
           ) -> tuple[dict[int, str], FloatArray, FloatArray]:
    """Step 4: ``(uncertain, spread_deg, spread_path)``, the frames the data do not fix with the
    reason (:func:`_uncertain`, then :func:`_spread_flags` on the covariance's spread, then
    :func:`_moved_far` from the linear positions ``c``, then :func:`_weak_ties` with the
    frames whose pose the data leave free tying nothing; again on the frames left while that
    cuts off more: the spread of a part is measured against its own path, and a part that
    shrank to a point while the rest of the walk moved has none). The lines ``held`` keep
    their direction in the covariance, as the adjustment held them."""
    uncertain = _uncertain(tracks, rot, pos, ba, options)
    used, seen = _used_observations(tracks, ba)
    free: set[int] = set()
    cache = SpreadCache()
    while True:
        spread_deg, spread_path = _spread(tracks, ba, uncertain, options, held, cache)
        weak = _spread_flags(spread_deg, spread_path, options, listed=list(uncertain))
        uncertain.update(weak)
        uncertain.update({k: v for k, v in _moved_far(c, ba, options, uncertain).items()
                          if k not in uncertain})
        with np.errstate(invalid="ignore"):
            free |= {int(k) for k in np.flatnonzero(ba.frames & ~np.isfinite(
                spread_deg + spread_path)) if int(k) in uncertain}
        cut = {k: v for k, v in _weak_ties(tracks, ba, used, seen, free,
                                           listed=list(uncertain)).items()
               if k not in uncertain}
        cut |= _islands(ba.frames, {*uncertain, *cut}, options.min_trusted_run)
        if not cut and not weak:
            return uncertain, spread_deg, spread_path
        uncertain.update(cut)


def _islands(posed: np.ndarray, flagged: Collection[int], min_run: int) -> dict[int, str]:
    """The posed frames not ``flagged`` in a stretch of fewer than ``min_run`` such frames
    that has more flagged frames than its own around it (the stretches of flagged frames just
    before and after it), with the reason. Where the tracks disagree or leave the poses weak,
    the measures that flag a frame pass and fail from one frame to the next: a few frames that
    pass between many that fail are judged by the same data and rest on the flagged frames
    around them (a hand-held walk at 640 x 320 left 13 such frames in 4 stretches of 2-6, 10 of
    them off by more than 1 deg or 2 % of the path). A flagged frame or two beside a long
    trusted stretch do not make it one. Frames not posed are skipped."""
    idx = np.flatnonzero(posed)
    if not len(flagged) or len(idx) == 0:
        return {}
    bad = np.isin(idx, list(flagged))
    # runs of equal values: [start, end) in idx, alternating trusted and flagged
    edges = np.r_[0, np.flatnonzero(np.diff(bad.astype(np.int8))) + 1, len(idx)]
    runs = list(zip(edges[:-1], edges[1:], strict=True))
    out: dict[int, str] = {}
    for r, (a, b) in enumerate(runs):
        if bad[a] or b - a >= min_run:
            continue
        around = sum(d - c for c, d in runs[max(r - 1, 0):r + 2] if bad[c])
        if around <= b - a:
            continue
        what = f"one of {b - a} trusted frames ({idx[a]}-{idx[b - 1]})" if b - a > 1 else \
            "a trusted frame alone"
        for k in idx[a:b]:
            out[int(k)] = (f"{what} between {around} flagged ones: the poses of so few rest on "
                           f"the flagged frames around them")
    return out


def _moved_far(c: FloatArray, ba: BundleResult, options: Settings,
               flagged: dict[int, str]) -> dict[int, str]:
    """The posed frames not already ``flagged`` that the adjustment moved by more than
    ``options.moved_path`` of the path from the linear positions ``c`` (step 2; after the
    similarity that best aligns the two on those frames: a part of the walk flagged for its
    weak ties lies in a world of its own, and aligned with the rest it would make every frame
    look moved), with the reason. Both estimate the same poses from the same tracks; where they
    disagree by that much, the tracks disagree with one another (a tracker that matched the
    wrong line through a fast turn) and the adjustment's least squares, however well its
    covariance says the data fix it, need not be the truth (docs/estimator.md, "Rigs")."""
    both = ba.frames & np.isfinite(c).all(axis=1)
    both[list(flagged)] = False
    if both.sum() < 3:
        return {}
    a, b = c[both], ba.positions[both]
    path = float(np.sum(np.linalg.norm(np.diff(b, axis=0), axis=1)))
    if path <= 0.0:
        return {}
    moved = np.linalg.norm(umeyama(a, b).apply_points(a) - b, axis=1) / path
    return {int(k): (f"the adjustment moved it {100 * m:.1f} % of the path from the linear "
                     f"positions: its tracks disagree with one another (a wrong match), and the "
                     f"least squares of them need not be the truth")
            for k, m in zip(np.flatnonzero(both), moved, strict=True)
            if m > options.moved_path}


def _rig_start(tracks: LineTracks, R: FloatArray, c: FloatArray, pos: GlobalPositions,
               frames: np.ndarray, options: Settings
               ) -> tuple[LineTracks, OffsetScale, FloatArray, GlobalPositions]:
    """Step 2 for a rig (``tracks`` with lens offsets in metres): the linear positions'
    reflection settled by the observations' rays (the offsets do not mirror with it), then the
    start in metres: divided by the offsets' units per metre where the robust cost at these
    poses is least (:func:`~omni_sfm.estimate.rig_scale.offset_scale`). The adjustment then
    holds no coordinate for the scale: the lens offsets fix it
    (:func:`~omni_sfm.estimate.bundle.metric_offsets`). Where the lines are too far for the
    baseline to fix it, the tracks go on without their offsets (too small to matter) and the
    scale is held as for one centre. Returns the tracks for the adjustment, the scale found and
    the start."""
    c, points = facing_lines(tracks, R, c, frames, pos.points)
    scale = offset_scale(tracks, R, c, frames, outlier_limit(pos.residual_sigma, options.bundle))
    if not scale.fixed:
        return replace(tracks, obs_offset=None), scale, c, replace(pos, positions=c,
                                                                   points=points)
    c, points = c / scale.scale, points / scale.scale
    return tracks, scale, c, replace(pos, positions=c, points=points)


def _decisive(options: BundleOptions) -> BundleOptions:
    """``options`` with each robust round run to a relative decrease of 1e-6 (60 iterations at
    most) before it judges the tracks: a track near the outlier limit judged before the poses
    settle would be kept or rejected by the path the solver took, which follows the frame
    order; judged at convergence, both orders keep the same tracks."""
    return replace(options, robust_tolerance=min(options.robust_tolerance, 1e-6),
                   robust_iterations=max(options.robust_iterations, 60))


def solve_global(tracks: LineTracks, options: GlobalOptions = GlobalOptions()
                 ) -> GlobalSolution:
    """Steps 1-5 of the module docstring: the solution of :func:`_solve_once`, and where a place
    is seen again (:func:`~omni_sfm.estimate.revisits.revisit_groups`: enough of its lines
    joined), the solution of the joined tracks from the first one's rotations, every original
    track given its group's line.

    ``options``: the user's (:class:`GlobalOptions`), or :class:`Settings` (the fixed values
    other than their defaults).

    Raises:
        OmniSfmError: as :func:`_solve_once`.
    """
    options = settings(options)
    sol = _solve_once(tracks, options)
    if not options.revisits.enabled:
        return sol
    t = time.perf_counter()
    group = revisit_groups(tracks, sol.rotations, sol.positions, sol.line_directions,
                           sol.line_points, sol.used_tracks, options.revisits)
    if group is None:  # no place seen again: the solution stands
        return replace(sol, steps=[*sol.steps, EstimatorStep(step="revisits", joined=0)])
    joins = tracks.num_tracks - len(np.unique(group))
    joined, merged_of = join_revisits(tracks, group)
    again = _solve_once(joined, options, sol.rotations)
    timings = {**again.timings_ms, "revisits": (time.perf_counter() - t) * 1e3}
    return replace(
        again, line_directions=again.line_directions[merged_of],
        line_points=again.line_points[merged_of], used_tracks=again.used_tracks[merged_of],
        outlier_tracks=again.outlier_tracks[merged_of], members=again.members[merged_of],
        steps=[*again.steps, EstimatorStep(step="revisits", joined=joins)],
        timings_ms=timings)


class _Steps:
    """The steps' wall times (milliseconds) and, where shown, a progress bar of them."""

    def __init__(self, show: bool) -> None:
        self.timings: dict[str, float] = {}
        self.bar = tqdm(total=5, desc="global estimator", unit="step", leave=False,
                        disable=None if show else True)

    @contextmanager
    def step(self, name: str) -> Iterator[None]:
        """Time the ``with`` block as step ``name``, shown on the bar while it runs."""
        self.bar.set_postfix_str(name.replace("_", " "), refresh=False)
        t = time.perf_counter()
        try:
            yield
        finally:
            self.timings[name] = (time.perf_counter() - t) * 1e3
            self.bar.update(1)


def _solve_once(tracks: LineTracks, options: Settings,
                start: FloatArray | None = None, *, window: bool = False) -> GlobalSolution:
    """Steps 1-4 of the module docstring; with ``start`` (``(F, 3, 3)``, NaN where none: an
    earlier solution's rotations) the rotations are solved from it alone. A ``window`` of
    :func:`windows_start` needs only its basin: steps 1-3, the adjustment's robust rounds as
    ``options.bundle`` has them (the whole video's run to convergence, :func:`_decisive`), no
    frame flagged and no spread.

    Raises:
        OmniSfmError: fewer than 3 frames that see ``options.min_lines`` lines, or a step that
            finds the data do not determine it.
    """
    prog = _Steps(options.progress and not window)
    steps: list[EstimatorStep] = []
    try:
        with prog.step("parallel_lines"):
            frames, lines = _posable(tracks, options.min_lines)
            if frames.sum() < 3:
                raise OmniSfmError(f"only {int(frames.sum())} frames see {options.min_lines} "
                                   f"or more tracked lines; need 3")
            families = detect_parallel_families(tracks, options.vanishing)
        with prog.step("rotations"):
            rot, worlds, label = _rotations(tracks, frames, lines, families, options, steps,
                                            start)
        with prog.step("positions"):
            R, c, pos, dir_ok = _positions_step(tracks, rot, frames, lines, options)
        steps.append(EstimatorStep(step="positions",
                                   sigma_deg=float(np.degrees(pos.residual_sigma))))
        with prog.step("bundle_adjustment"):
            opts = options if window else replace(options, bundle=_decisive(options.bundle))
            scale: OffsetScale | None = None
            if tracks.obs_offset is not None:
                tracks, scale, c, pos = _rig_start(tracks, R, c, pos, frames, opts)
            ba = _adjustment_step(tracks, R, c, rot, pos, dir_ok, label, frames, opts)
        steps.append(EstimatorStep(step="bundle adjustment", iterations=ba.iterations,
                                   outlier_tracks=int(ba.outlier_tracks.sum()),
                                   rms_final_deg=float(ba.rms_final_deg)))
        with prog.step("pose_spread"):
            nan = np.full(tracks.num_frames, np.nan)
            uncertain, spread_deg, spread_path = ({}, nan, nan.copy()) if window else \
                _flags(tracks, rot, pos, c, ba, options, _held(dir_ok, label, options))
    finally:
        prog.bar.close()
    timings = prog.timings
    not_posed = {int(k): f"sees fewer than {options.min_lines} lines that are tracked"
                 for k in np.flatnonzero(~frames)}
    for k in np.flatnonzero(frames & ~ba.frames):
        not_posed[int(k)] = ("fewer than 3 of its lines are left after the adjustment rejected "
                             "outlier tracks")
    members = np.asarray(families[0].members, bool) if families else \
        np.zeros(tracks.num_tracks, bool)
    return GlobalSolution(
        rotations=ba.rotations, positions=ba.positions, frames=ba.frames,
        line_directions=ba.line_directions, line_points=ba.line_points,
        used_tracks=ba.used_tracks, outlier_tracks=ba.outlier_tracks, members=members,
        world_directions=worlds, rms_initial_deg=ba.rms_initial_deg,
        rms_final_deg=ba.rms_final_deg, sigma_deg=ba.sigma_deg,
        uncertain=uncertain, spread_deg=spread_deg, spread_path=spread_path,
        not_posed=not_posed, steps=steps, timings_ms=timings, offset_scale=scale)
