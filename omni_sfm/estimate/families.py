"""Parallel families as fixed world directions (docs/method.md §14; the global estimator's world
directions, docs/estimator.md).

Man-made places have a few dominant directions (the verticals, a corridor's own direction, the
cross direction). Once a piece of the sequence is reconstructed, its 3D lines show them:
:func:`world_families` clusters the lines' directions. From then on a line of a family has that
direction, fixed: the registration of a new frame uses it even before the line's position is
known (its normal must be orthogonal to it, which constrains the frame's rotation), a new line
of a family is triangulated with its direction given (two parameters, not four), and the
adjustments hold the directions. The rotation of every frame is then measured against the same
world directions, so it does not drift along a long video when two families or more are seen.

A line not yet triangulated is put in a family when the planes of its registered views all
contain that family's direction and no other family's (:func:`family_of_planes`): a line seen
along its own direction (the corridor's rails, walking along the corridor) has no parallax to be
triangulated, but its family is known and its views constrain the rotation.
"""

from __future__ import annotations

import numpy as np

from omni_sfm.estimate.rotation_only import procrustes
from omni_sfm.geometry import FloatArray, orthonormal_completion, smallest_eigenvector


def _align(directions: FloatArray, ref: FloatArray) -> FloatArray:
    """Unsigned directions ``(K, 3)`` flipped to point to the side of ``ref`` ``(3,)``."""
    s = np.sign(directions @ ref)
    s[s == 0] = 1.0
    return directions * s[:, None]


def world_families(directions: FloatArray, *, max_angle_deg: float = 2.0, min_lines: int = 3,
                   max_families: int = 6, min_separation_deg: float = 15.0) -> FloatArray:
    """``(K, 3)`` the dominant directions among the unit line directions ``(M, 3)`` (unsigned):
    greedily, the direction with the most lines within ``max_angle_deg``, refined to their
    mean, while at least ``min_lines`` lines share it; at most ``max_families``. A direction
    within ``min_separation_deg`` of one already found is not another family (lines of a family
    triangulated from short baselines scatter around it) and its lines are set aside."""
    d = np.asarray(directions, np.float64)
    d = d[np.isfinite(d).all(1)]
    cos_t = np.cos(np.radians(max_angle_deg))
    free = np.ones(len(d), bool)
    out: list[FloatArray] = []
    while len(out) < max_families and free.sum() >= min_lines:
        rest = d[free]
        close = np.abs(rest @ rest.T) >= cos_t
        k = int(np.argmax(close.sum(1)))
        if close[k].sum() < min_lines:
            break
        mean = np.sum(_align(rest[close[k]], rest[k]), axis=0)
        mean /= np.linalg.norm(mean)
        members = np.abs(d @ mean) >= cos_t
        members &= free
        if members.sum() < min_lines:
            break
        mean = np.sum(_align(d[members], mean), axis=0)
        mean /= np.linalg.norm(mean)
        free &= ~members
        if out and np.max(np.abs(np.asarray(out) @ mean)) > np.cos(np.radians(min_separation_deg)):
            continue
        out.append(mean)
    return np.asarray(out, np.float64).reshape(-1, 3)


def family_of_lines(directions: FloatArray, families: FloatArray, *,
                    max_angle_deg: float = 2.0) -> np.ndarray:
    """``(M,)`` the family (index into ``families`` ``(K, 3)``) within ``max_angle_deg`` of each
    line direction ``(M, 3)``, -1 for none (or NaN)."""
    d = np.asarray(directions, np.float64)
    out = np.full(len(d), -1)
    if len(families) == 0 or len(d) == 0:
        return out
    ok = np.isfinite(d).all(1)
    g = np.abs(d[ok] @ families.T)
    best = np.argmax(g, axis=1)
    hit = g[np.arange(len(best)), best] >= np.cos(np.radians(max_angle_deg))
    out[np.flatnonzero(ok)[hit]] = best[hit]
    return out


def family_of_planes(world_normals: FloatArray, track: np.ndarray, num_tracks: int,
                     families: FloatArray, *, max_angle_deg: float,
                     min_views: int = 2) -> np.ndarray:
    """``(M,)`` the family of each track from its registered views' world plane normals
    ``(K, 3)`` (``track`` ``(K,)`` in ``0..num_tracks-1``): the one family whose direction lies
    in every plane (within ``max_angle_deg``) when exactly one does and the track has
    ``min_views`` views or more; -1 otherwise (none, several, or too few views)."""
    out = np.full(num_tracks, -1)
    if len(families) == 0 or len(track) == 0:
        return out
    off = np.abs(np.asarray(world_normals, np.float64) @ families.T)  # (K, F) sines
    worst = np.zeros((num_tracks, len(families)))
    np.maximum.at(worst, track, off)
    views = np.bincount(track, minlength=num_tracks)
    fits = worst <= np.sin(np.radians(max_angle_deg))
    one = (fits.sum(1) == 1) & (views >= min_views)
    out[one] = np.argmax(fits[one], axis=1)
    return out


def point_given_direction(world_normals: FloatArray, centres: FloatArray,
                          direction: FloatArray, *,
                          range_iterations: int = 2) -> tuple[FloatArray, float]:
    """The line of known ``direction`` ``(3,)`` whose planes (world normals ``(K, 3)``, each
    through its camera centre ``(K, 3)``) fit best: ``(p, spread)``, its point closest to the
    origin, and the angle (radians) by which the planes turn about it (the parallax measure of
    the triangulation, :meth:`omni_sfm.estimate.incremental.Growth.triangulate`).

    The least squares of the distances from the planes, each normal first made orthogonal to
    the direction (a normal's noise along the direction would otherwise count times its
    camera's distance along the line from the world's origin: 40 m along a corridor, a tenth
    of a degree of noise fitted a cross line's views 2-3 deg off), then ``range_iterations``
    times again with each plane weighted by the inverse of its camera's distance from the line
    found, so that what is minimised is close to the bundle adjustment's angular residual."""
    direction = np.asarray(direction, np.float64)
    a, b = orthonormal_completion(direction)
    m = np.asarray(world_normals, np.float64)
    m = m - np.outer(m @ direction, direction)
    m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)
    A = np.stack([m @ a, m @ b], axis=1)  # m . (x a + y b) = m . c
    rhs = np.sum(m * centres, axis=1)
    u = A / np.maximum(np.linalg.norm(A, axis=1, keepdims=True), 1e-300)
    ev = np.linalg.eigvalsh(u.T @ u)  # the triangulation's parallax measure, in 2D
    spread = float(2.0 * np.arcsin(np.sqrt(np.clip(ev[0] / max(ev.sum(), 1e-300), 0.0, 1.0))))
    xy = np.linalg.lstsq(A, rhs, rcond=None)[0]
    for _ in range(range_iterations):
        q = centres - (xy[0] * a + xy[1] * b)
        r = np.linalg.norm(q - np.outer(q @ direction, direction), axis=1)
        w = 1.0 / np.maximum(r, 1e-9 * max(float(r.max()), 1e-300))
        xy = np.linalg.lstsq(A * w[:, None], rhs * w, rcond=None)[0]
    return xy[0] * a + xy[1] * b, spread


def manhattan(families: FloatArray, sizes: np.ndarray, *,
              max_deviation_deg: float = 2.5, complete_deg: float | None = None) -> FloatArray:
    """The families ``(K, 3)`` with those that are mutually orthogonal within
    ``max_deviation_deg`` made exactly orthogonal (a Manhattan frame: the rotation that best
    aligns them with three orthogonal axes, each family weighted by its ``sizes``); the others
    (an Atlanta world's further horizontal directions) as they are.

    With ``complete_deg``, the two families that make the frame fix its third axis: a family
    within ``complete_deg`` of it takes it exactly (a family of a few lines, whose direction
    their short baseline leaves off by degrees), and where none is, the axis is appended as
    one more row (a direction not seen yet: the corridor round the next corner)."""
    D = np.asarray(families, np.float64).copy()
    if len(D) < 2:
        return D
    tol = np.sin(np.radians(max_deviation_deg))
    a = 0
    cand = [k for k in range(1, len(D)) if abs(float(D[k] @ D[a])) <= tol]
    if not cand:
        return D
    b = max(cand, key=lambda k: float(sizes[k]))
    D = _manhattan_frame(D, sizes, a, b, max_deviation_deg)
    if complete_deg is None:
        return D
    third = np.cross(D[a], D[b])
    third /= np.linalg.norm(third)
    cos = D @ third
    near = np.abs(cos) >= np.cos(np.radians(complete_deg))
    near[[a, b]] = False
    if not near.any():
        return np.vstack([D, third])
    D[near] = np.sign(cos[near])[:, None] * third
    return D


def _manhattan_frame(D: FloatArray, sizes: np.ndarray, a: int, b: int,
                     max_deviation_deg: float) -> FloatArray:
    """:func:`manhattan`'s snap onto the frame of the orthogonal families ``a`` and ``b``."""
    e2 = D[b] - float(D[b] @ D[a]) * D[a]
    axes = np.stack([D[a], e2 / np.linalg.norm(e2), np.cross(D[a], e2 / np.linalg.norm(e2))])
    g = D @ axes.T  # (K, 3) cosines
    ax = np.argmax(np.abs(g), axis=1)
    on = np.abs(g[np.arange(len(D)), ax]) >= np.cos(np.radians(max_deviation_deg))
    sign = np.sign(g[np.arange(len(D)), ax])
    # Wahba: the rotation Q with Q axes[ax_k] closest to sign_k D_k, weighted by size
    Q = procrustes(axes[ax[on]], sign[on, None] * D[on], np.asarray(sizes, float)[on])
    D[on] = sign[on, None] * (axes[ax[on]] @ Q.T)
    return D


def line_families(directions: FloatArray, *, max_angle_deg: float = 2.0,
                  min_lines: int = 4) -> tuple[FloatArray, np.ndarray]:
    """The families of the lines ``(M, 3)`` (NaN rows: unknown lines): ``(D, family)``, the
    :func:`world_families` of the known ones made Manhattan where they nearly are
    (:func:`manhattan`, each weighted by its lines) and each line's family within
    ``max_angle_deg`` of those (:func:`family_of_lines`, -1 for none)."""
    d = np.asarray(directions, np.float64)
    known = np.isfinite(d).all(1)
    D = world_families(d[known], max_angle_deg=max_angle_deg, min_lines=min_lines)
    fam = family_of_lines(d, D, max_angle_deg=max_angle_deg)
    D = manhattan(D, np.bincount(fam[fam >= 0], minlength=len(D)))
    return D, family_of_lines(d, D, max_angle_deg=max_angle_deg)


def snap_to_families(directions: FloatArray, points: FloatArray, families: FloatArray,
                     family: np.ndarray, anchors: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Copies of the lines ``(M, 3)`` (unit directions, points) with each line of a family
    (``family`` ``(M,)`` >= 0, index into ``families`` ``(K, 3)``) given exactly its family's
    direction (same sign), turned about its point nearest its ``anchors`` ``(M, 3)`` row (e.g.
    the mean centre of the cameras that see it: the part of the line they see barely moves; a
    NaN row turns it about its point nearest the origin). The points returned are the lines'
    points nearest the origin."""
    d = np.array(directions, np.float64)
    p = np.array(points, np.float64)
    k = np.flatnonzero(np.asarray(family) >= 0)
    if len(k) == 0:
        return d, p
    D = np.asarray(families, np.float64)[np.asarray(family)[k]]
    sign = np.where(np.sum(D * d[k], axis=1) < 0, -1.0, 1.0)
    D = D * sign[:, None]
    s = np.sum((np.asarray(anchors, np.float64)[k] - p[k]) * d[k], axis=1)
    x = p[k] + np.where(np.isfinite(s), s, 0.0)[:, None] * d[k]
    d[k] = D
    p[k] = x - np.sum(x * D, axis=1, keepdims=True) * D
    return d, p


def camera_anchors(obs_frame: np.ndarray, obs_track: np.ndarray, centres: FloatArray,
                   num_tracks: int) -> FloatArray:
    """``(M, 3)`` the mean centre of the cameras that see each line, over the observations
    ``(obs_frame, obs_track)`` whose frame has a finite centre in ``centres`` ``(F, 3)`` (NaN
    for a line with none): the anchors of :func:`snap_to_families`."""
    c = np.asarray(centres, np.float64)
    ok = np.isfinite(c[obs_frame]).all(1)
    s = np.zeros((num_tracks, 3))
    np.add.at(s, obs_track[ok], c[obs_frame[ok]])
    n = np.bincount(obs_track[ok], minlength=num_tracks).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return s / n[:, None]


def plane_directions(world_normals: FloatArray, group: np.ndarray, num_groups: int
                     ) -> FloatArray:
    """``(G, 3)`` each group's direction from the world plane normals ``(K, 3)`` of its lines'
    views (``group`` ``(K,)`` in ``0..num_groups-1``): the unit vector most nearly
    perpendicular to all of them (the smallest eigenvector of their scatter). For a parallel
    family this is its vanishing direction in the world: it rests on every view of every
    member, not on the members' triangulated directions (which a short baseline leaves off by
    degrees). NaN rows for groups with no views."""
    m = np.asarray(world_normals, np.float64)
    S = np.zeros((num_groups, 3, 3))
    np.add.at(S, group, m[:, :, None] * m[:, None, :])
    out = smallest_eigenvector(S)
    out[np.bincount(group, minlength=num_groups) < 2] = np.nan
    return np.asarray(out)
