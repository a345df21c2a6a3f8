"""The paper's estimator: poses of every view of a window from its parallel family and the other
lines (docs/method.md §3-§5), with the choice of the second view and degeneracy checks.

Input: a window of :class:`~omni_sfm.lines.tracks.LineTracks` in which every track is observed in
every frame, and the parallel family found by :func:`omni_sfm.vanishing.detect_parallel_family`.

Output conventions (:class:`PaperSolution`):

- ``rotations`` are world_from_cam, world = the camera of frame 0 (``rotations[0] = I``).
- ``positions`` are camera centres in the world, ``positions[0] = 0``. Scale as in the paper
  (eq. 18): the component of the second view's position perpendicular to the parallel direction
  has length 1, ``|positions[c] - (positions[c] . v) v| = 1``.
- Overall sign: NVs of arbitrary sign cannot distinguish the scene from its point reflection
  through the first camera (``positions -> -positions``, line points likewise, same rotations:
  every normal is reproduced exactly). Pass ``side_rays`` (a ray towards each observed segment)
  to fix it by cheirality; otherwise the convention is that ``positions[c]`` has a non-negative
  component along the first in-plane basis vector ``a`` of
  :func:`omni_sfm.estimate.translation.plane_basis` (``sign_from_rays = False``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.estimate.rotation import (
    RotationProblem,
    RotationResult,
    estimate_rotations,
    polish_angles,
)
from omni_sfm.estimate.translation import (
    estimate_plane,
    estimate_vertical,
    in_plane_parallax,
    line_directions,
    line_parallax,
    line_points,
    normal_residuals,
    resolve_sign,
    translation_all_views,
)
from omni_sfm.geometry import FloatArray
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.vanishing import ParallelFamily, chain_signs, vpv_per_frame


@dataclass(frozen=True, kw_only=True)
class PaperOptions:
    """Options of :func:`estimate_paper`."""

    rotation_grid: int = 64
    """Coarse grid points of the rotation search over ``phi_c`` in ``[-pi, pi)`` (5.6 deg)."""
    rotation_starts: int = 2
    """Lowest grid minima polished by Brent's method."""
    rotation_xtol: float | None = None
    """Absolute tolerance (radians) of the Brent polishing of ``phi_c``; ``None``: 1e-6 when
    ``polish_rotation`` is on (the joint polish then converges to machine precision anyway),
    else 1e-10."""
    rotation_search_views: int = 40
    """With ``polish_rotation``, the 1-DOF search evaluates ``E_rot`` on at most this many views
    (evenly spread); the joint polish then uses all of them."""
    second_view: int | None = None
    """The second view ``c``; ``None`` chooses it: for the rotation the view whose line normals
    changed most against view 0 (rotation-invariant proxy), for the translation the view with the
    largest in-plane parallax of the parallel lines."""
    min_parallax_deg: float = 0.25
    """Degenerate motion: raise if no view shows at least this (median over lines, against view
    0) of: change of the angles between line planes (rotation-free: the camera barely moved),
    parallax of the other lines' planes, or in-plane parallax of the parallel lines (no motion
    across them)."""
    max_plane_ratio: float = 0.3
    """Degenerate motion: raise if the two eigenvalues of the in-plane cost ``S`` are closer than
    this ratio (the in-plane direction of travel is not determined by the data)."""
    rotation_softening: float = 0.1
    """``s0`` of :class:`~omni_sfm.estimate.rotation.RotationProblem`: lines with less parallax
    than about ``asin(s0)`` between views 0 and ``c`` fade out of ``E_rot`` (0: the paper's
    cost exactly; noise-free results are exact either way)."""
    rotation_rival_factor: float = 1.5
    """With ``polish_rotation``, other local minima of ``E_rot`` (all views) up to this factor
    above the best are polished too, and the full model picks the winner (noise can make the
    basins of ``E_rot`` compete)."""
    rotation_continuity: bool = True
    """Views are consecutive video frames: among the rotation search's minima prefer those whose
    angles about the parallel direction never jump by more than 90 deg between neighbouring
    views, and undo such jumps where the half turn fits the lines about as well
    (:func:`~omni_sfm.estimate.rotation.keep_continuity`). Lines perpendicular to the parallel
    direction (a corridor's verticals and cross lines) cannot tell a view from its half turn
    about it. False: the paper's per-view minima as they are (unordered views)."""
    polish_rotation: bool = True
    """Also solve the angles about ``v`` with all views jointly (``polish_angles``) and keep
    whichever rotations give the full model (all lines triangulated) the smaller RMS angle."""
    polish_translation: bool = True
    """Also solve the positions with all views at once (``translation_all_views``, given the
    rotations) and keep them if they explain the normals better (smaller RMS angle)."""
    robust_rounds: int = 6
    """Up to this many re-solves with Cauchy track weights from each track's RMS angle (tracks
    that switched to another line, i.e. wrong correspondences). Only runs when some track's
    RMS exceeds ``robust_trigger`` times the robust scale (1.4826 x the median track RMS), so
    clean data costs nothing extra; stops when the weights settle. 0: plain least squares as
    in the paper."""
    robust_factor: float = 2.0
    """Scale of the Cauchy weights ``1 / (1 + (r / (factor * scale))^2)``."""
    robust_trigger: float = 3.0
    """Reweighting starts only if some track's RMS exceeds this times the robust scale."""
    robust_min_scale_deg: float = 1e-3
    """Floor of the robust scale, degrees (noise-free data)."""
    irls_iter: int = 2
    """Reweighting rounds of the translation steps (0: the plain algebraic residuals)."""
    rerun_rotation: bool = True
    """Re-solve the rotation with a better-conditioned second view when the solved rotations
    show one (much larger parallax of the non-parallel lines than the proxy's choice)."""
    alternative_starts: int = 4
    """Also solve the translation (§5, all-view polish off) with this many other second views
    ``c`` (those with the most in-plane parallax) and return the results as
    :attr:`PaperSolution.alternatives`: at high noise the choice of ``c`` decides which basin a
    later bundle adjustment falls into, so a caller can refine from each and keep the lowest
    cost. 0: none."""


@dataclass(frozen=True)
class PaperSolution:
    """Poses and lines of one window by the paper's method.

    Attributes:
        rotations: ``(F, 3, 3)`` world_from_cam, world = frame 0's camera (``rotations[0] = I``).
        positions: ``(F, 3)`` camera centres in the world, ``positions[0] = 0``; the in-plane
            part (perpendicular to ``parallel_direction``) of ``positions[second_view]`` has
            length 1 (eq. 18).
        second_view: the ``c`` of the translation (scale and in-plane direction).
        rotation_second_view: the ``c`` of the rotation search.
        line_directions: ``(M, 3)`` world unit direction of every track's 3D line (parallel
            members: ``parallel_direction``).
        line_points: ``(M, 3)`` the point of each 3D line closest to the world origin.
        parallel_direction: ``(3,)`` ``v`` in the world (frame 0's VPV).
        parallel: ``(M,)`` bool, the family members used.
        sign_from_rays: the overall sign of the translation was fixed by ``side_rays``.
        timings_ms: ``rotation`` (search and polish), ``translation`` (all of §5 for every
            rotation candidate, plus line triangulation), ``translation_plane`` and
            ``translation_vertical`` (the chosen candidate's steps a and b), ``total``.
        costs: ``E_rot`` (eq. 14 at the search's minimum), ``E_rot_all_views`` (after the joint
            polish, NaN if off), ``E_t1``, ``E_t`` (weighted sums of squared residuals, ~ rad^2),
            ``plane_ratio`` (in-plane conditioning, small is good), ``rms_deg`` (RMS angle
            between observed and modelled NVs of all used tracks) and ``polished_rotation``
            (1.0 if the jointly polished rotations were kept), ``polished_translation`` (1.0 if
            the all-view positions were kept), ``robust_rounds`` (reweighted re-solves run).
        weights: ``(M,)`` the effective track weights of the final solve: the caller's times
            the robust (Cauchy) weights; small values mark suspected outlier tracks.
        alternatives: ``((rotations (F,3,3), positions (F,3)), ...)`` other starting solutions
            (same rotations, translations from other second views, see
            ``PaperOptions.alternative_starts``), each scaled (least squares, the sign
            included) onto ``positions``: same world, scale and reflection branch.
    """

    rotations: FloatArray
    positions: FloatArray
    second_view: int
    rotation_second_view: int
    line_directions: FloatArray
    line_points: FloatArray
    parallel_direction: FloatArray
    parallel: np.ndarray
    sign_from_rays: bool
    timings_ms: dict[str, float]
    costs: dict[str, float]
    weights: FloatArray
    alternatives: tuple[tuple[FloatArray, FloatArray], ...] = ()

    def reflected(self) -> PaperSolution:
        """The point reflection through the first camera: positions and line points negated.

        It reproduces every (unsigned) normal exactly as well, so where no ``side_rays`` fixed
        the sign, chaining windows or comparing with other estimates must allow for it (e.g. a
        least-squares similarity whose scale may be negative).
        """
        return replace(self, positions=-self.positions, line_points=-self.line_points,
                       alternatives=tuple((R, -c) for R, c in self.alternatives))


def _motion_scores(normals: FloatArray) -> FloatArray:
    """``(F,)`` median change (rad) of the pairwise angles between line planes against view 0.

    Angles between the NVs of two lines seen in one view do not depend on the camera rotation,
    only on its position: their change is a rotation-free measure of the motion. ``normals
    (F, M, 3)``.
    """
    G = np.abs(np.einsum("fmi,fni->fmn", normals, normals))
    ang = np.arccos(np.clip(G, 0.0, 1.0))
    M = normals.shape[1]
    iu = np.triu_indices(M, 1)
    change = np.abs(ang[:, iu[0], iu[1]] - ang[:1, iu[0], iu[1]])
    score = np.median(change, axis=1)
    score[0] = 0.0
    return score


def _check_inputs(tracks: LineTracks, family: ParallelFamily,
                  weights: FloatArray | None) -> FloatArray:
    F, M = tracks.num_frames, tracks.num_tracks
    if F < 3:
        raise OmniSfmError(f"the paper's method needs at least 3 frames, got {F}")
    members = np.asarray(family.members)
    if members.shape != (M,) or members.dtype != bool:
        raise OmniSfmError(f"family.members must be a bool array of shape ({M},), got "
                           f"{members.dtype} {members.shape}")
    if np.asarray(family.vpv).shape != (F, 3):
        raise OmniSfmError(f"family.vpv must have shape ({F}, 3), got {family.vpv.shape}")
    vis = tracks.visibility()
    missing = np.flatnonzero(~vis.all(axis=1))
    if missing.size:
        m = int(missing[0])
        raise OmniSfmError(
            f"the paper's method needs every track in every frame of the window; track "
            f"{int(tracks.track_ids[m])} is missing in {int((~vis[m]).sum())} of {F} frames "
            f"({missing.size} tracks incomplete): the global estimator takes such tracks")
    w = np.ones(M) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (M,) or not np.isfinite(w).all() or (w < 0).any():
        raise OmniSfmError(f"weights must be {M} finite non-negative numbers, got shape {w.shape}")
    n_par = int(np.count_nonzero(members & (w > 0)))
    n_oth = int(np.count_nonzero(~members & (w > 0)))
    if n_par < 3:
        raise OmniSfmError(f"the paper's method needs at least 3 parallel lines, got {n_par}")
    if n_oth < 3:
        raise OmniSfmError(f"the paper's method needs at least 3 lines that are not parallel to "
                           f"the family, got {n_oth}")
    return w


def _cauchy_weights(sol: PaperSolution, normals: FloatArray, w_user: FloatArray,
                    opts: PaperOptions) -> tuple[FloatArray, bool]:
    """``(weights, fits)``: the user's track weights times Cauchy weights of each track's RMS
    angle under ``sol`` (robust to tracks that switched to another line), and whether every
    weighted track fits within ``opts.robust_trigger`` times the robust scale."""
    m = np.einsum("fij,fmj->fmi", sol.rotations, normals)
    ang = normal_residuals(m, sol.line_directions, sol.line_points, sol.positions)
    rt = np.nan_to_num(np.sqrt(np.mean(ang ** 2, axis=0)), nan=np.pi / 2)
    scale = max(1.4826 * float(np.median(rt[w_user > 0])),
                np.radians(opts.robust_min_scale_deg))
    fits = bool(np.all(rt[w_user > 0] <= opts.robust_trigger * scale))
    return w_user / (1.0 + (rt / (opts.robust_factor * scale)) ** 2), fits


def estimate_paper(tracks: LineTracks, family: ParallelFamily,
                   options: PaperOptions | None = None, *,
                   weights: FloatArray | None = None,
                   side_rays: FloatArray | None = None) -> PaperSolution:
    """Poses of every frame of a window by the paper's method (docs/method.md §4-§5).

    Args:
        tracks: the window; every track observed in every frame, at least 3 frames.
        family: its parallel family (``members`` over these tracks; ``vpv`` rows over these
            frames give the VPV sign, the VPV itself is recomputed from the weighted members).
        options: see :class:`PaperOptions`.
        weights: ``(M,)`` non-negative per-track weights (0 ignores a track), e.g. to
            down-weight suspected outliers.
        side_rays: ``(K, 3)`` optional unit rays in the camera frame, one per observation (in
            ``tracks``' order), pointing at a point of the observed segment; they fix the
            overall sign of the translation by cheirality.

    Raises:
        OmniSfmError: fewer than 3 frames, parallel or non-parallel lines; a track missing from
            a frame; degenerate motion (no parallax across the parallel lines).
    """
    opts = options or PaperOptions()
    t_start = time.perf_counter()
    w_user = _check_inputs(tracks, family, weights)
    if side_rays is not None and np.asarray(side_rays).shape != (tracks.num_observations, 3):
        raise OmniSfmError(f"side_rays must have shape ({tracks.num_observations}, 3), got "
                           f"{np.asarray(side_rays).shape}")
    F = tracks.num_frames
    if opts.second_view is not None and not 1 <= opts.second_view < F:
        raise OmniSfmError(f"second_view must be in [1, {F}), got {opts.second_view}")
    normals = tracks.dense_normals().transpose(1, 0, 2)                  # (F, M, 3)
    w = w_user
    sol = _solve_once(tracks, family, opts, w, side_rays)
    timings = dict(sol.timings_ms)
    rounds = 0
    for _ in range(opts.robust_rounds):
        # skipped when every track fits (clean data)
        w_new, fits = _cauchy_weights(sol, normals, w_user, opts)
        if rounds == 0 and fits:
            break
        if rounds > 0 and np.max(np.abs(w_new - w)) < 0.05:
            break
        try:
            new = _solve_once(tracks, family, opts, w_new, side_rays)
        except OmniSfmError:
            break
        for k, val in new.timings_ms.items():
            timings[k] = timings.get(k, 0.0) + val
        sol, w = new, w_new
        rounds += 1
    t_alt = time.perf_counter()
    alternatives = _alternatives(sol, normals, w, opts)
    timings["translation"] = timings.get("translation", 0.0) + \
        (time.perf_counter() - t_alt) * 1e3
    timings["total"] = (time.perf_counter() - t_start) * 1e3
    costs = dict(sol.costs)
    costs["robust_rounds"] = float(rounds)
    return replace(sol, timings_ms=timings, costs=costs, weights=w, alternatives=alternatives)


def _alternatives(sol: PaperSolution, normals: FloatArray, w: FloatArray,
                  opts: PaperOptions) -> tuple[tuple[FloatArray, FloatArray], ...]:
    """Translations of ``sol.rotations`` from other second views (``opts.alternative_starts``)."""
    if opts.alternative_starts <= 0 or opts.second_view is not None:
        return ()
    members = sol.parallel
    par = np.flatnonzero(members & (w > 0))
    oth = np.flatnonzero(~members & (w > 0))
    v = sol.parallel_direction
    m_world = np.einsum("fij,fmj->fmi", sol.rotations, normals)
    pp = np.median(in_plane_parallax(m_world[:, par], v), axis=1)
    order = [int(k) for k in np.argsort(-pp, kind="stable") if k != sol.second_view and k != 0]
    ref = sol.positions
    out: list[tuple[FloatArray, FloatArray]] = []
    for c in order[: opts.alternative_starts]:
        alt_opts = replace(opts, second_view=c, polish_translation=False)
        try:
            t = _translate(sol.rotations, normals, v, members, par, oth, w, alt_opts)
        except OmniSfmError:
            continue
        k = float(np.sum(t.positions * ref) / max(float(np.sum(t.positions ** 2)), 1e-300))
        out.append((sol.rotations, k * t.positions))
    return tuple(out)


def _solve_once(tracks: LineTracks, family: ParallelFamily, opts: PaperOptions, w: FloatArray,
                side_rays: FloatArray | None) -> PaperSolution:
    """One weighted solve (inputs already checked)."""
    t_start = time.perf_counter()
    F = tracks.num_frames
    members = np.asarray(family.members, dtype=bool)
    normals = tracks.dense_normals().transpose(1, 0, 2)                  # (F, M, 3)
    par = np.flatnonzero(members & (w > 0))
    oth = np.flatnonzero(~members & (w > 0))

    # VPV from the weighted members (eq. 5), sign as the family's (or chained)
    vpv, _ = vpv_per_frame(normals[:, par].transpose(1, 0, 2), np.ones((len(par), F), bool),
                           w[par])
    ref = np.asarray(family.vpv, dtype=np.float64)
    vpv = chain_signs(vpv, ref if np.isfinite(ref).all(axis=1).any() else None)

    t0 = time.perf_counter()
    rot, c_rot = _rotation_search(normals, vpv, w, par, oth, opts)
    candidates, polished_cost = _rotation_candidates(normals, vpv, w, oth, rot, c_rot, opts)
    v = vpv[0]
    t1 = time.perf_counter()
    best_sol = _best_translation(candidates, normals, v, members, par, oth, w, opts)
    R, positions, dirs, points = best_sol.R, best_sol.positions, best_sol.dirs, best_sol.points
    t3 = time.perf_counter()
    sign_from_rays = side_rays is not None
    if side_rays is not None:
        positions, points = _signed_by_rays(tracks, R, positions, points, dirs, w, side_rays)
    t4 = time.perf_counter()
    timings = {"rotation": (t1 - t0) * 1e3, "translation": (t3 - t1) * 1e3,
               "translation_plane": best_sol.ms_plane,
               "translation_vertical": best_sol.ms_vertical, "total": (t4 - t_start) * 1e3}
    costs = {"E_rot": rot.cost, "E_rot_all_views": polished_cost, "E_t1": best_sol.cost_plane,
             "E_t": best_sol.cost_vertical, "plane_ratio": best_sol.ratio,
             "rms_deg": float(np.degrees(best_sol.rms)),
             "polished_rotation": float(best_sol.R is not candidates[-1]),
             "polished_translation": float(best_sol.all_views)}
    return PaperSolution(R, positions, best_sol.c, rot.second_view, dirs, points, v,
                         members.copy(), sign_from_rays, timings, costs, w.copy())


def _rotation_search(normals: FloatArray, vpv: FloatArray, w: FloatArray, par: np.ndarray,
                     oth: np.ndarray, opts: PaperOptions) -> tuple[RotationResult, int]:
    """The paper's global 1-DOF search over phi_c (docs/method.md §4), with the second view
    ``c`` (returned with the search) chosen by motion and, unless ``opts`` fixes it, again by
    the parallax of the lines the first search places.

    Raises:
        OmniSfmError: the camera barely moved (``opts.min_parallax_deg``).
    """
    xtol = opts.rotation_xtol if opts.rotation_xtol is not None else \
        (1e-6 if opts.polish_rotation else 1e-10)
    search_views = opts.rotation_search_views if opts.polish_rotation else None
    motion = _motion_scores(normals[:, np.concatenate([par, oth])])
    if np.max(motion) < np.radians(opts.min_parallax_deg):
        raise OmniSfmError(
            f"degenerate motion: the camera barely moved (the angles between line planes change "
            f"by at most {np.degrees(np.max(motion)):.3g} deg, min_parallax_deg="
            f"{opts.min_parallax_deg:g})")
    c_rot = opts.second_view if opts.second_view is not None else int(np.argmax(motion))
    rot = estimate_rotations(normals[:, oth], vpv, w[oth], c_rot, num_grid=opts.rotation_grid,
                             num_starts=opts.rotation_starts, xtol=xtol,
                             softening=opts.rotation_softening, polish=False,
                             search_views=search_views, continuity=opts.rotation_continuity)
    m_world = np.einsum("fij,fmj->fmi", rot.rotations, normals)
    parallax = line_parallax(m_world[:, oth])
    lp = np.median(parallax, axis=1)
    # a quarter of the lines suffices: lines along the direction of travel (a corridor's
    # baseboards, when another family is the parallel one) show none whatever the motion
    lp_upper = np.percentile(parallax, 75, axis=1)
    if np.max(lp_upper) < np.radians(opts.min_parallax_deg):
        raise OmniSfmError(
            f"degenerate motion: the non-parallel lines show at most "
            f"{np.degrees(np.max(lp_upper)):.3g} deg of parallax (upper quartile, "
            f"min_parallax_deg={opts.min_parallax_deg:g}); the camera barely moved")
    if opts.second_view is None and opts.rerun_rotation:
        best = int(np.argmax(lp))
        if best != c_rot and lp[best] > 1.5 * lp[c_rot]:
            c_rot = best
            rot = estimate_rotations(normals[:, oth], vpv, w[oth], c_rot,
                                     num_grid=opts.rotation_grid,
                                     num_starts=opts.rotation_starts, xtol=xtol,
                                     softening=opts.rotation_softening, polish=False,
                                     search_views=search_views,
                                     continuity=opts.rotation_continuity)
    return rot, c_rot


def _rotation_candidates(normals: FloatArray, vpv: FloatArray, w: FloatArray, oth: np.ndarray,
                         rot: RotationResult, c_rot: int,
                         opts: PaperOptions) -> tuple[list[FloatArray], float]:
    """The rotations the full model decides among: (if polishing) the search's minimum, then
    every local minimum of E_rot within ``opts.rotation_rival_factor`` of the best, each
    polished with all views; last the search's own rotations. Also returns the polished cost
    of the search's minimum (NaN without polishing)."""
    prob = RotationProblem.build(normals[:, oth], vpv, w[oth], c_rot)
    starts = [rot.phi]
    if opts.polish_rotation:
        starts += [phi for phi, f in zip(rot.other_minima, rot.other_costs, strict=True)
                   if f <= opts.rotation_rival_factor * rot.cost]
    candidates: list[FloatArray] = []
    polished_cost = float("nan")
    for k, phi0 in enumerate(starts):
        if opts.polish_rotation:
            phi, _, cost_k = polish_angles(prob, phi0.copy())
            if k == 0:
                polished_cost = cost_k
            R_pol = prob.rotations(phi)
            R_pol[0] = np.eye(3)
            candidates.append(R_pol)
    candidates.append(rot.rotations)
    return candidates, polished_cost


def _best_translation(candidates: list[FloatArray], normals: FloatArray, v: FloatArray,
                      members: np.ndarray, par: np.ndarray, oth: np.ndarray, w: FloatArray,
                      opts: PaperOptions) -> _Translation:
    """The translation (docs/method.md §5) of the candidate rotations whose model has the
    least RMS angle; a candidate that fails is skipped.

    Raises:
        OmniSfmError: every candidate fails (the last one's error).
    """
    best_sol: _Translation | None = None
    for k, R in enumerate(candidates):
        try:
            sol = _translate(R, normals, v, members, par, oth, w, opts)
        except OmniSfmError:
            if k == len(candidates) - 1 and best_sol is None:
                raise
            continue
        if best_sol is None or sol.rms < best_sol.rms:
            best_sol = sol
    assert best_sol is not None
    return best_sol


def _signed_by_rays(tracks: LineTracks, R: FloatArray, positions: FloatArray, points: FloatArray,
                    dirs: FloatArray, w: FloatArray,
                    side_rays: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``positions`` and line ``points``, reflected through the first camera where the rays
    towards the observed segments say so (cheirality of the weighted lines)."""
    F, M = tracks.num_frames, tracks.num_tracks
    rays = np.asarray(side_rays, dtype=np.float64)
    dense = np.zeros((F, M, 3))
    dense[tracks.obs_frame, tracks.obs_track] = rays
    rays_w = np.einsum("fij,fmj->fmi", R, dense)
    sel = np.zeros((F, M), dtype=bool)
    sel[:, w > 0] = True
    if resolve_sign(rays_w, positions, points, dirs, sel) < 0:
        positions, points = -positions, -points
    return positions, points


@dataclass(frozen=True)
class _Translation:
    R: FloatArray
    positions: FloatArray
    dirs: FloatArray
    points: FloatArray
    c: int
    cost_plane: float
    cost_vertical: float
    ratio: float
    rms: float
    ms_plane: float
    ms_vertical: float
    all_views: bool


def _translate(R: FloatArray, normals: FloatArray, v: FloatArray, members: np.ndarray,
               par: np.ndarray, oth: np.ndarray, w: FloatArray,
               opts: PaperOptions) -> _Translation:
    """docs/method.md §5 for given rotations, then all lines triangulated and the model's RMS
    angle."""
    t1 = time.perf_counter()
    m_world = np.einsum("fij,fmj->fmi", R, normals)
    pp = np.median(in_plane_parallax(m_world[:, par], v), axis=1)
    if np.max(pp) < np.radians(opts.min_parallax_deg):
        raise OmniSfmError(
            f"degenerate motion: no motion across the parallel lines (their in-plane parallax "
            f"is at most {np.degrees(np.max(pp)):.3g} deg, min_parallax_deg="
            f"{opts.min_parallax_deg:g}); the paper's method cannot fix the scale, e.g. when "
            f"the camera moves along the parallel lines")
    c = opts.second_view if opts.second_view is not None else int(np.argmax(pp))
    plane = estimate_plane(m_world[:, par], v, w[par], c, irls_iter=opts.irls_iter)
    if plane.ratio > opts.max_plane_ratio:
        raise OmniSfmError(
            f"degenerate motion: the in-plane direction of travel is undetermined (eigenvalue "
            f"ratio {plane.ratio:.3g} > max_plane_ratio={opts.max_plane_ratio:g})")
    t2 = time.perf_counter()
    d_oth = line_directions(m_world[:, oth])
    vert = estimate_vertical(m_world[:, oth], d_oth, v, plane.positions, w[oth], c,
                             irls_iter=opts.irls_iter)
    positions = plane.positions + vert.omega[:, None] * v
    t3 = time.perf_counter()
    if not np.isfinite(positions).all():
        bad = np.flatnonzero(~np.isfinite(positions).all(axis=1))
        raise OmniSfmError(f"the position of frame(s) {bad[:5].tolist()} is undetermined by the "
                           f"lines (too few with parallax)")
    dirs = line_directions(m_world)
    dirs[members] = v
    points = line_points(m_world, dirs, positions)
    used = w > 0

    def rms_of(pos: FloatArray, pts: FloatArray) -> float:
        ang = normal_residuals(m_world[:, used], dirs[used], pts[used], pos)
        return float(np.sqrt(np.average(ang ** 2, weights=np.broadcast_to(w[used], ang.shape))))

    rms = rms_of(positions, points)
    all_views = False
    if opts.polish_translation:
        pos2, _, _ = translation_all_views(m_world, dirs, w, irls_iter=1, reference=positions)
        if np.isfinite(pos2).all():
            pts2 = line_points(m_world, dirs, pos2)
            rms2 = rms_of(pos2, pts2)
            if rms2 < rms:
                positions, points, rms, all_views = pos2, pts2, rms2, True
    return _Translation(R, positions, dirs, points, c, plane.cost, vert.cost, plane.ratio, rms,
                        (t2 - t1) * 1e3, (t3 - t2) * 1e3, all_views)
