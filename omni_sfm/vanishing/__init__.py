"""Parallel-line families and their vanishing-point vectors (VPVs), docs/method.md §3.

The NV ``n`` of a line is orthogonal to the line's direction, so the NVs of parallel lines seen
in one frame are coplanar and orthogonal to the family's direction ``v_k`` in that camera frame
(eq. 4). Three tracks are tested for parallelism on the frames they share: per frame the smallest
eigenvalue of ``sum n n^T`` is ``min_|v|=1 sum (n . v)^2`` (eq. 5-6), averaged over the shared
frames. The passing triples (below ``p_th`` and a noise-adaptive threshold), best first, seed
groups: each group is trimmed of tracks that do not fit its per-frame VPV and grown by tracks that
do (noise-normalised leave-one-out residuals), until stable, and kept as one part (members
linked by frames that see two of them: ``_groups.connected_parts``); the largest group is the
parallel family, and the others (Manhattan scenes) are returned too. Its VPV is then
recomputed in every frame from all the members seen there (eq. 5) and its sign chained through
time, so that ``v_k`` points the same way in the world in every frame.

Works with partial tracks: a triple is only tested on the frames all three share. Everything
runs on the sparse observations (``_observations.ObsIndex``), never on ``tracks x frames``
arrays, so long videos (tens of thousands of frames, tracks seen in a few dozen) cost about
their number of observations: triples are drawn among tracks that share frames
(``_triples``), and a group's residuals are updated only in the frames of the tracks that
join or leave it (``_groups.GroupState``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray, smallest_eigenvector
from omni_sfm.lines.tracks import LineTracks
from omni_sfm.vanishing._groups import (
    GroupState,
    StateCache,
    connected_parts,
    family_arrays,
    merge_groups,
    refine_state,
)
from omni_sfm.vanishing._observations import ObsIndex
from omni_sfm.vanishing._triples import draw_triples, seed_threshold, triple_means


@dataclass(frozen=True, kw_only=True)
class VanishingOptions:
    """Options of the parallel-family detection."""

    p_th: float = 2e-3
    """Threshold of eq. (6) on the *mean* over the shared frames of ``min_v sum_i (n_i . v)^2``
    (for a triple), and on the mean ``(n . v_k)^2`` of one track against a family's VPV. Roughly
    the squared angle (rad^2) a normal may leave the VPV's great circle: 2e-3 ~ (2.6 deg)^2, well
    above the noise of real tracks (1.28 deg of noise gives ~2.5e-4) and far below non-parallel
    lines (a line 20 deg off the family gives ~6e-2)."""
    min_spread: float = 1e-2
    """A frame only tests a triple if the middle eigenvalue of ``sum n n^T`` is at least this
    (the three planes are distinct there: two identical normals would pass any third one)."""
    min_shared_frames: int = 3
    """Frames a triple (or a track and a family) must share, with ``min_spread``, to be tested."""
    max_triples: int = 3000
    """All triples are tested when there are at most this many; otherwise this many random
    triples of tracks that share frames are drawn."""
    min_family_size: int = 3
    """Smallest group reported as a family (the method needs 3 parallel lines)."""
    max_families: int = 3
    """At most this many families are returned by :func:`detect_parallel_families`."""
    outlier_factor: float = 8.0
    """A track only stays in a family if its mean squared (noise-normalised) residual is at most
    this times the family's noise level (the median squared residual of the members / 0.455,
    the median of a chi-square with 1 degree of freedom)."""
    seed_factor: float = 20.0
    """Triples seed families if their mean is at most this times the lower quartile of the
    means below ``p_th`` (a noise-adaptive eq. 6; see ``_seed_threshold``)."""
    max_seeds: int = 30
    """At most this many seed triples are grown into groups (best first)."""
    frame_outlier_factor: float = 40.0
    """... and no frame's squared residual exceeds this times the noise level (6.3 sigma): the
    paper asks eq. (6) to hold in every frame."""
    min_noise_deg: float = 0.01
    """Floor of the noise level (deg) used by the two factors above (noise-free data)."""
    max_refine_iter: int = 100
    """Rounds of trimming and growing a group against its own VPV."""
    seed: int = 0
    """Seed of the random triples."""


@dataclass(frozen=True)
class ParallelFamily:
    """A family of parallel line tracks and its VPV per frame.

    Attributes:
        members: ``(M,)`` bool, tracks in the family.
        vpv: ``(F, 3)`` unit VPV per frame in that frame's camera frame; its sign is consistent
            over time (it is the same world direction in every frame); NaN rows where fewer than
            2 member tracks are observed.
        track_residual: ``(M,)`` mean of ``(n . v_k)^2`` of each track over the frames where the
            VPV is defined by the *other* members (NaN where it cannot be tested); members are
            below ``p_th``.
        frame_residual: ``(F,)`` mean ``(n . v_k)^2`` of the members seen in frame ``k`` (NaN where
            the VPV is undefined).
        frame_members: ``(F,)`` int, member tracks observed in each frame.
    """

    members: np.ndarray
    vpv: FloatArray
    track_residual: FloatArray
    frame_residual: FloatArray
    frame_members: np.ndarray

    @property
    def size(self) -> int:
        return int(np.count_nonzero(self.members))

    def select(self, tracks: np.ndarray | None = None,
               frames: np.ndarray | None = None) -> ParallelFamily:
        """The family restricted to some tracks (int indices or bool mask, as in
        :meth:`LineTracks.select_tracks`) and/or frames (int indices), e.g. for a window.

        ``frame_members`` then still counts all members of the original track set.
        """
        out = self
        if tracks is not None:
            idx = np.flatnonzero(tracks) if np.asarray(tracks).dtype == bool else \
                np.asarray(tracks)
            out = replace(out, members=out.members[idx], track_residual=out.track_residual[idx])
        if frames is not None:
            fr = np.asarray(frames)
            out = replace(out, vpv=out.vpv[fr], frame_residual=out.frame_residual[fr],
                          frame_members=out.frame_members[fr])
        return out


def vpv_per_frame(normals: FloatArray, mask: np.ndarray,
                  weights: FloatArray | None = None) -> tuple[FloatArray, np.ndarray]:
    """Eq. (5): the unit ``v`` minimising ``sum_i w_i (n_ik . v)^2`` in each frame.

    Args:
        normals: ``(M, F, 3)`` dense normals (values where ``mask`` is False are ignored).
        mask: ``(M, F)`` bool, observation used.
        weights: ``(M,)`` optional non-negative weights.

    Returns:
        ``(F, 3)`` VPVs (arbitrary sign, NaN where fewer than 2 lines are used) and ``(F,)``
        the number of lines used per frame.
    """
    w = mask.astype(np.float64)
    if weights is not None:
        w = w * np.asarray(weights, dtype=np.float64)[:, None]
    n = np.where(mask[..., None], normals, 0.0)
    v = smallest_eigenvector(np.einsum("mf,mfi,mfj->fij", w, n, n))
    count = np.count_nonzero(mask & (w > 0), axis=0)
    v[count < 2] = np.nan
    return v, count


def chain_signs(vpv: FloatArray, reference: FloatArray | None = None) -> FloatArray:
    """Flip VPV rows so that consecutive defined rows point the same way (positive dot product).

    Assumes the camera turns the family's direction by less than 90 deg between consecutive
    frames where it is defined. With ``reference (F, 3)`` (NaN rows allowed), rows are instead
    flipped to agree with it wherever it is defined, and chained elsewhere.
    """
    out = np.array(vpv, dtype=np.float64, copy=True)
    ok = np.flatnonzero(np.isfinite(out).all(axis=1))
    if ok.size == 0:
        return out
    first = out[ok[0]]
    if reference is None:
        big = int(np.argmax(np.abs(first)))
        if first[big] < 0:
            out[ok[0]] = -first
    ref_ok: np.ndarray = np.zeros(out.shape[0], dtype=bool) if reference is None else \
        np.asarray(np.isfinite(reference).all(axis=1))
    prev = out[ok[0]]
    for k in ok:
        if ref_ok[k]:
            assert reference is not None
            if out[k] @ reference[k] < 0:
                out[k] = -out[k]
        elif out[k] @ prev < 0:
            out[k] = -out[k]
        prev = out[k]
    return out


def detect_parallel_families(tracks: LineTracks,
                             options: VanishingOptions | None = None) -> list[ParallelFamily]:
    """All parallel families with at least ``min_family_size`` tracks, largest first.

    A track belongs to at most one family. Man-made scenes typically give three.
    """
    opts = options or VanishingOptions()
    if tracks.num_tracks < 3:
        return []
    idx = ObsIndex.from_tracks(tracks)
    rng = np.random.default_rng(opts.seed)
    triples = draw_triples(idx, opts, rng)
    if len(triples) == 0:
        return []
    means = triple_means(idx, triples, opts)
    thresh = seed_threshold(means, opts)
    order = np.argsort(means)
    order = order[means[order] <= thresh]
    # the noise level of one residual, from the seeds (mostly parallel triples): the mean
    # lambda_min of a parallel triple estimates the variance of n . v
    noise = float(np.median(means[order])) if order.size else 0.0
    groups: list[np.ndarray] = []
    taken = np.zeros(tracks.num_tracks, dtype=bool)
    cache = StateCache(idx, opts)
    tried = 0
    for t in order:
        seed = triples[t]
        if taken[seed].any():
            continue
        tried += 1
        if tried > opts.max_seeds:
            break
        members = np.zeros(tracks.num_tracks, dtype=bool)
        members[seed] = True
        state = None
        if opts.max_refine_iter > 0:
            state = refine_state(GroupState.of(idx, opts, members), ~taken, noise)[0]
            members = state.members.copy()
            parts = connected_parts(idx, members)
            if len(parts) > 1:  # the rest is free to seed groups of its own
                members = parts[0]
                state.remove(np.flatnonzero(state.members & ~members))
        if members.sum() < opts.min_family_size:
            continue
        if state is not None:
            cache.put(state)
        groups.append(members)
        taken |= members
    groups = [part for g in merge_groups(idx, groups, opts, noise, cache)
              for part in connected_parts(idx, g) if part.sum() >= opts.min_family_size]
    families = [_family(cache.state_of(g)) for g in groups]
    families.sort(key=lambda f: f.size, reverse=True)
    return families[:opts.max_families]


def _family(state: GroupState) -> ParallelFamily:
    v, resid, frame_res, count, firm = family_arrays(state)
    return ParallelFamily(state.members.copy(), _chain_firm(v, firm), resid, frame_res,
                          count.astype(np.int64))


def _chain_firm(vpv: FloatArray, firm: np.ndarray) -> FloatArray:
    """:func:`chain_signs` over the frames whose VPV is well determined (``firm``); every other
    frame takes the sign that agrees with the nearest firm frame. A VPV resting on nearly
    coplanar normals can be far off, and chaining through it could flip the sign of the rest
    of the sequence (a sparse family in a long sequence). Where every frame is firm, as
    :func:`chain_signs`."""
    ok = np.isfinite(vpv).all(axis=1)
    anchor = np.flatnonzero(firm & ok)
    if anchor.size == 0:
        return chain_signs(vpv)
    out = chain_signs(np.where((firm & ok)[:, None], vpv, np.nan))
    rest = np.flatnonzero(ok & ~firm)
    right = np.minimum(np.searchsorted(anchor, rest), anchor.size - 1)
    left = np.maximum(right - 1, 0)
    near = np.where(np.abs(anchor[left] - rest) <= np.abs(anchor[right] - rest),
                    anchor[left], anchor[right])
    flip = np.sum(vpv[rest] * out[near], axis=1) < 0
    out[rest] = np.where(flip[:, None], -vpv[rest], vpv[rest])
    first = out[np.flatnonzero(ok)[0]]              # chain_signs' convention: the first
    if first[np.argmax(np.abs(first))] < 0:         # defined row's largest component > 0
        out = -out
    return out


def detect_parallel_family(tracks: LineTracks,
                           options: VanishingOptions | None = None) -> ParallelFamily:
    """The largest parallel family of ``tracks`` and its per-frame VPV (docs/method.md §3).

    Raises:
        OmniSfmError: fewer than ``min_family_size`` (3) parallel tracks were found.
    """
    opts = options or VanishingOptions()
    fams = detect_parallel_families(tracks, opts)
    if not fams or fams[0].size < max(3, opts.min_family_size):
        found = fams[0].size if fams else 0
        raise OmniSfmError(
            f"found {found} parallel line tracks among {tracks.num_tracks}; the method needs at "
            f"least 3 tracks of one 3D direction seen together in {opts.min_shared_frames} or more "
            f"frames (threshold p_th={opts.p_th:g})")
    return fams[0]
