"""Parallel-line families and their vanishing-point vectors (VPVs), METHOD.md §3.

The NV ``n`` of a line is orthogonal to the line's direction, so the NVs of parallel lines seen
in one frame are coplanar and orthogonal to the family's direction ``v_k`` in that camera frame
(eq. 4). Three tracks are tested for parallelism on the frames they share: per frame the smallest
eigenvalue of ``sum n n^T`` is ``min_|v|=1 sum (n . v)^2`` (eq. 5-6). Passing triples are merged,
each merged group is verified (trimmed of tracks that do not fit the group's per-frame VPV) and
grown (tracks that fit are added), and the largest group is the parallel family. Its VPV is then
recomputed in every frame from all the members seen there (eq. 5) and its sign chained through
time, so that ``v_k`` points the same way in the world in every frame.

Works with partial tracks: a triple is only tested on the frames all three share.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from itertools import combinations
from math import comb

import numpy as np

from omni_sfm.errors import OmniSfmError
from omni_sfm.geometry import FloatArray
from omni_sfm.lines.tracks import LineTracks


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
    max_triples: int = 6000
    """All triples are tested when there are at most this many; otherwise this many random
    triples of tracks that share frames are drawn."""
    min_family_size: int = 3
    """Smallest group reported as a family (the method needs 3 parallel lines)."""
    max_families: int = 3
    """At most this many families are returned by :func:`detect_parallel_families`."""
    max_refine_iter: int = 20
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
    S = np.einsum("mf,mfi,mfj->fij", w, n, n)
    _, vecs = np.linalg.eigh(S)
    v = vecs[:, :, 0]
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


def _triple_eigs(n1: FloatArray, n2: FloatArray, n3: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Smallest and middle eigenvalue of ``sum n n^T`` for three unit normals ``(..., 3)``.

    Via the Gram matrix ``G = [[1,a,b],[a,1,c],[b,c,1]]`` (same eigenvalues): ``G = I + B`` and
    the eigenvalues of ``B`` solve the depressed cubic ``mu^3 - (a^2+b^2+c^2) mu - 2abc = 0``,
    three real roots given by the trigonometric formula. Sign-invariant in each normal.
    """
    a = np.sum(n1 * n2, -1)
    b = np.sum(n1 * n3, -1)
    c = np.sum(n2 * n3, -1)
    p = a * a + b * b + c * c
    q = 2.0 * a * b * c
    r = np.sqrt(np.maximum(p / 3.0, 1e-300))
    arg = np.clip(q / (2.0 * r ** 3), -1.0, 1.0)
    th = np.arccos(arg) / 3.0
    mu = 2.0 * r[..., None] * np.cos(th[..., None] - 2.0 * np.pi * np.arange(3) / 3.0)
    mu.sort(axis=-1)
    lam = 1.0 + mu
    return np.maximum(lam[..., 0], 0.0), lam[..., 1]


def _draw_triples(vis: np.ndarray, opts: VanishingOptions,
                  rng: np.random.Generator) -> np.ndarray:
    """``(T, 3)`` sorted unique track triples to test (all of them if few enough)."""
    M = vis.shape[0]
    if comb(M, 3) <= opts.max_triples:
        return np.array(list(combinations(range(M), 3)), dtype=np.int64).reshape(-1, 3)
    visf = vis.astype(np.float32)
    overlap = visf @ visf.T
    np.fill_diagonal(overlap, 0)
    s = opts.min_shared_frames
    T = opts.max_triples
    ok_i = np.flatnonzero((overlap >= s).sum(1) >= 2)
    if ok_i.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    i = rng.choice(ok_i, size=T)
    key = rng.random((T, M)) * (overlap[i] >= s)
    j = np.argmax(key, axis=1)
    good = key[np.arange(T), j] > 0
    i, j = i[good], j[good]
    both = (vis[i] & vis[j]).astype(np.float32)
    tri = both @ visf.T                                                  # (T, M) triple overlap
    tri[np.arange(len(i)), i] = 0
    tri[np.arange(len(i)), j] = 0
    key = rng.random(tri.shape) * (tri >= s)
    k = np.argmax(key, axis=1)
    good = key[np.arange(len(i)), k] > 0
    out = np.sort(np.stack([i[good], j[good], k[good]], 1), axis=1)
    return np.unique(out, axis=0)


def _passing_triples(normals: FloatArray, vis: np.ndarray, triples: np.ndarray,
                     opts: VanishingOptions, chunk: int = 2000) -> np.ndarray:
    """Bool ``(T,)``: the triple's NVs are coplanar (eq. 6) on average over its shared frames."""
    out = np.zeros(len(triples), dtype=bool)
    for s in range(0, len(triples), chunk):
        t = triples[s:s + chunk]
        n1, n2, n3 = normals[t[:, 0]], normals[t[:, 1]], normals[t[:, 2]]
        shared = vis[t[:, 0]] & vis[t[:, 1]] & vis[t[:, 2]]
        lam_min, lam_mid = _triple_eigs(n1, n2, n3)
        use = shared & (lam_mid >= opts.min_spread)
        cnt = use.sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(use, lam_min, 0.0).sum(1) / cnt
        out[s:s + chunk] = (cnt >= opts.min_shared_frames) & (mean <= opts.p_th)
    return out


def _components(M: int, triples: np.ndarray) -> list[np.ndarray]:
    """Connected groups of tracks linked by passing triples (union-find), largest first."""
    parent = np.arange(M)

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = int(parent[x])
        return x

    for a, b, c in triples:
        ra, rb, rc = find(int(a)), find(int(b)), find(int(c))
        parent[rb] = ra
        parent[find(rc)] = ra
    roots = np.array([find(m) for m in range(M)])
    used = np.unique(triples) if len(triples) else np.zeros(0, dtype=np.int64)
    groups = [np.intersect1d(np.flatnonzero(roots == r), used) for r in np.unique(roots[used])]
    groups.sort(key=len, reverse=True)
    return groups


def _track_residuals(normals: FloatArray, vis: np.ndarray, members: np.ndarray,
                     opts: VanishingOptions) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Leave-one-out residual of every track against the members' VPV.

    Returns the ``(M,)`` mean ``(n . v)^2`` over the frames where at least 2 *other* members
    define the VPV (NaN where fewer than ``min_shared_frames`` such frames), the VPV of all
    members ``(F, 3)`` and the member count per frame ``(F,)``.
    """
    mask = vis & members[:, None]
    v_all, count = vpv_per_frame(normals, mask)
    resid_all = np.einsum("mfi,fi->mf", np.where(vis[..., None], normals, 0.0),
                          np.nan_to_num(v_all)) ** 2
    res = resid_all.copy()
    # members: recompute with themselves left out where they are observed (VPV of the others)
    n_mask = np.where(mask[..., None], normals, 0.0)
    S = np.einsum("mfi,mfj->fij", n_mask, n_mask)
    for m in np.flatnonzero(members):
        Sm = S - np.einsum("fi,fj->fij", n_mask[m], n_mask[m])
        _, vecs = np.linalg.eigh(Sm[vis[m]])
        res[m, vis[m]] = np.einsum("fi,fi->f", normals[m, vis[m]], vecs[:, :, 0]) ** 2
    others = count[None, :] - mask.astype(np.int64)
    usable = vis & (others >= 2)
    cnt = usable.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(usable, res, 0.0).sum(1) / cnt
    mean[cnt < opts.min_shared_frames] = np.nan
    return mean, v_all, count


def _refine_group(normals: FloatArray, vis: np.ndarray, group: np.ndarray,
                  allowed: np.ndarray, opts: VanishingOptions) -> np.ndarray:
    """Trim a group to tracks that fit its VPV, then grow it by every allowed track that fits."""
    M = vis.shape[0]
    members = np.zeros(M, dtype=bool)
    members[group] = True
    for _ in range(opts.max_refine_iter):
        resid, _, _ = _track_residuals(normals, vis, members, opts)
        bad = members & ~(resid <= opts.p_th)
        if np.any(bad):
            worst = np.flatnonzero(bad)[np.argmax(np.nan_to_num(resid[bad], nan=np.inf))]
            members[worst] = False
            if members.sum() < 3:
                return members
            continue
        grow = allowed & ~members & (resid <= opts.p_th)
        if not np.any(grow):
            break
        members |= grow
    return members


def _family(normals: FloatArray, vis: np.ndarray, members: np.ndarray,
            opts: VanishingOptions) -> ParallelFamily:
    resid, v, count = _track_residuals(normals, vis, members, opts)
    v = chain_signs(v)
    mask = vis & members[:, None]
    r = np.einsum("mfi,fi->mf", np.where(mask[..., None], normals, 0.0), np.nan_to_num(v)) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        frame_res = np.where(count >= 2, r.sum(0) / count, np.nan)
    return ParallelFamily(members.copy(), v, resid, frame_res, count.astype(np.int64))


def detect_parallel_families(tracks: LineTracks,
                             options: VanishingOptions | None = None) -> list[ParallelFamily]:
    """All parallel families with at least ``min_family_size`` tracks, largest first.

    A track belongs to at most one family. Man-made scenes typically give three.
    """
    opts = options or VanishingOptions()
    if tracks.num_tracks < 3:
        return []
    vis = tracks.visibility()
    normals = np.nan_to_num(tracks.dense_normals())
    rng = np.random.default_rng(opts.seed)
    triples = _draw_triples(vis, opts, rng)
    if len(triples) == 0:
        return []
    passing = triples[_passing_triples(normals, vis, triples, opts)]
    families: list[ParallelFamily] = []
    taken = np.zeros(tracks.num_tracks, dtype=bool)
    for group in _components(tracks.num_tracks, passing):
        group = group[~taken[group]]
        if len(group) < opts.min_family_size:
            continue
        members = _refine_group(normals, vis, group, ~taken, opts)
        if members.sum() < opts.min_family_size:
            continue
        families.append(_family(normals, vis, members, opts))
        taken |= members
    families.sort(key=lambda f: f.size, reverse=True)
    return families[:opts.max_families]


def detect_parallel_family(tracks: LineTracks,
                           options: VanishingOptions | None = None) -> ParallelFamily:
    """The largest parallel family of ``tracks`` and its per-frame VPV (METHOD.md §3).

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
