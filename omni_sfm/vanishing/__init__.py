"""Parallel-line families and their vanishing-point vectors (VPVs), docs/method.md §3.

The NV ``n`` of a line is orthogonal to the line's direction, so the NVs of parallel lines seen
in one frame are coplanar and orthogonal to the family's direction ``v_k`` in that camera frame
(eq. 4). Three tracks are tested for parallelism on the frames they share: per frame the smallest
eigenvalue of ``sum n n^T`` is ``min_|v|=1 sum (n . v)^2`` (eq. 5-6), averaged over the shared
frames. The passing triples (below ``p_th`` and a noise-adaptive threshold), best first, seed
groups: each group is trimmed of tracks that do not fit its per-frame VPV and grown by tracks that
do (noise-normalised leave-one-out residuals), until stable; the largest group is the parallel
family, and the others (Manhattan scenes) are returned too. Its VPV is then
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
from omni_sfm.geometry import FloatArray, smallest_eigenvector
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
    r = np.sqrt(np.maximum(p / 3.0, 1e-100))
    th = np.arccos(np.clip(q / (2.0 * r ** 3), -1.0, 1.0)) / 3.0      # in [0, pi/3]
    # roots 2 r cos(th - 2 pi k / 3): k = 2 is the smallest, k = 1 the middle one
    lam_min = 1.0 + 2.0 * r * np.cos(th + 2.0 * np.pi / 3.0)
    lam_mid = 1.0 + 2.0 * r * np.cos(th - 2.0 * np.pi / 3.0)
    return np.maximum(lam_min, 0.0), lam_mid


def _smallest_eigvec3(S: FloatArray) -> FloatArray:
    """Unit eigenvectors ``(K, 3)`` of the smallest eigenvalue of symmetric PSD ``S (K, 3, 3)``.

    Closed form (much faster than a batched ``eigh`` for many small matrices): the eigenvalue
    by the trigonometric formula, the vector as the largest cross product of two rows of
    ``S - lambda I``.
    """
    a, b, c = S[:, 0, 0], S[:, 1, 1], S[:, 2, 2]
    d, e, f = S[:, 0, 1], S[:, 0, 2], S[:, 1, 2]
    tr = (a + b + c) / 3.0
    a0, b0, c0 = a - tr, b - tr, c - tr
    p = np.sqrt(np.maximum((a0 * a0 + b0 * b0 + c0 * c0 + 2.0 * (d * d + e * e + f * f)) / 6.0,
                           1e-200))
    det = a0 * (b0 * c0 - f * f) - d * (d * c0 - f * e) + e * (d * f - b0 * e)
    th = np.arccos(np.clip(det / (2.0 * p ** 3), -1.0, 1.0)) / 3.0
    lam = tr + 2.0 * p * np.cos(th + 2.0 * np.pi / 3.0)
    a1, b1, c1 = a - lam, b - lam, c - lam
    # rows r0 = (a1, d, e), r1 = (d, b1, f), r2 = (e, f, c1) and their cross products
    x01 = np.stack([d * f - e * b1, e * d - a1 * f, a1 * b1 - d * d], 1)
    x02 = np.stack([d * c1 - e * f, e * e - a1 * c1, a1 * f - d * e], 1)
    x12 = np.stack([b1 * c1 - f * f, f * e - d * c1, d * f - b1 * e], 1)
    cand = np.stack([x01, x02, x12], 1)
    norms = np.einsum("kij,kij->ki", cand, cand)
    best = np.argmax(norms, axis=1)
    k = np.arange(S.shape[0])
    return cand[k, best] / np.sqrt(np.maximum(norms[k, best], 1e-300))[:, None]


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
    key = np.unique((out[:, 0] * M + out[:, 1]) * M + out[:, 2])
    return np.stack([key // (M * M), (key // M) % M, key % M], 1)


def _triple_means(normals: FloatArray, vis: np.ndarray, triples: np.ndarray,
                  opts: VanishingOptions, chunk: int = 2000) -> FloatArray:
    """``(T,)`` mean over the shared frames of ``min_v sum_i (n_i . v)^2`` (eq. 5-6) of each
    triple; ``inf`` where fewer than ``min_shared_frames`` frames test it (``min_spread``)."""
    out = np.full(len(triples), np.inf)
    for s in range(0, len(triples), chunk):
        t = triples[s:s + chunk]
        n1, n2, n3 = normals[t[:, 0]], normals[t[:, 1]], normals[t[:, 2]]
        shared = vis[t[:, 0]] & vis[t[:, 1]] & vis[t[:, 2]]
        lam_min, lam_mid = _triple_eigs(n1, n2, n3)
        use = shared & (lam_mid >= opts.min_spread)
        cnt = use.sum(1)
        mean = np.where(use, lam_min, 0.0).sum(1) / np.maximum(cnt, 1)
        out[s:s + chunk] = np.where(cnt >= opts.min_shared_frames, mean, np.inf)
    return out


def _seed_threshold(means: FloatArray, opts: VanishingOptions) -> float:
    """Noise-adaptive threshold on a triple's mean: ``min(p_th, seed_factor * q25)``.

    ``q25`` is the lower quartile of the means that pass ``p_th``: parallel triples have the
    smallest means (about the noise variance), so as long as they are a quarter of the passing
    ones it measures the noise; accidental near-coplanar triples lie far above.
    """
    cand = means[means <= opts.p_th]
    if cand.size == 0:
        return opts.p_th
    q = float(np.quantile(cand, 0.25))
    return min(opts.p_th, max(opts.seed_factor * q, np.radians(opts.min_noise_deg) ** 2))


def _quad_inv(T: FloatArray, n: FloatArray) -> FloatArray:
    """``n^T T^-1 n`` for symmetric ``T (K, 3, 3)`` and ``n (K, 3)`` (adjugate formula)."""
    a, b, c = T[:, 0, 0], T[:, 1, 1], T[:, 2, 2]
    d, e, f = T[:, 0, 1], T[:, 0, 2], T[:, 1, 2]
    A00, A11, A22 = b * c - f * f, a * c - e * e, a * b - d * d
    A01, A02, A12 = e * f - d * c, d * f - e * b, d * e - a * f
    det = a * A00 + d * A01 + e * A02
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    num = A00 * x * x + A11 * y * y + A22 * z * z + 2.0 * (A01 * x * y + A02 * x * z + A12 * y * z)
    return num / np.where(np.abs(det) > 1e-300, det, 1e-300)


def _track_residuals(normals: FloatArray, vis: np.ndarray, members: np.ndarray,
                     opts: VanishingOptions) -> tuple[FloatArray, FloatArray, FloatArray,
                                                      np.ndarray, np.ndarray]:
    """Leave-one-out residuals of every track against the members' VPV, noise-normalised.

    A member's normal is tested against the VPV of the *other* members seen in that frame, any
    other track against the VPV of all members. The squared residual ``(n . v)^2`` is divided by
    ``1 + n^T S^+ n`` (``S = sum n n^T`` of the lines defining ``v``, ``S^+`` its inverse across
    ``v``): the variance that ``v``'s own error adds, large where ``v`` rests on 2 nearby
    normals. Every normalised residual then has the same variance (that of ``n . v_true``).

    Returns ``(M, F)`` normalised squared residuals, ``(M, F)`` usable mask (at least 2 other
    members define the VPV), ``(M,)`` mean over usable frames (NaN where fewer than
    ``min_shared_frames``), the VPV of all members ``(F, 3)`` and the member count ``(F,)``.
    """
    mask = vis & members[:, None]
    n_mask = np.where(mask[..., None], normals, 0.0)
    S = np.einsum("mfi,mfj->fij", n_mask, n_mask)
    count = mask.sum(0)
    v_all = np.full((vis.shape[1], 3), np.nan)
    okf = count >= 2
    if np.any(okf):
        v_all[okf] = _smallest_eigvec3(S[okf])
    others = count[None, :] - mask.astype(np.int64)
    usable = vis & (others >= 2)
    res = np.zeros(vis.shape)
    mm, ff = np.nonzero(usable)
    n = normals[mm, ff]
    own = mask[mm, ff]
    Sm = S[ff] - own[:, None, None] * (n[:, :, None] * n[:, None, :])
    vecs = _smallest_eigvec3(Sm)
    r2 = np.einsum("ki,ki->k", n, vecs) ** 2
    trace = np.trace(Sm, axis1=1, axis2=2)
    T = Sm + trace[:, None, None] * (vecs[:, :, None] * vecs[:, None, :])
    factor = 1.0 + np.maximum(_quad_inv(T, n), 0.0)
    res[mm, ff] = r2 / factor
    cnt = usable.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(usable, res, 0.0).sum(1) / cnt
    mean[cnt < opts.min_shared_frames] = np.nan
    return res, usable, mean, v_all, count


def _noise_level(res: FloatArray, usable: np.ndarray, members: np.ndarray,
                 opts: VanishingOptions) -> float:
    """Robust variance of one residual ``n . v`` of the members (rad^2)."""
    sel = usable & members[:, None]
    med = float(np.median(res[sel])) / 0.455 if np.any(sel) else 0.0
    return max(med, np.radians(opts.min_noise_deg) ** 2)


def _fits(res: FloatArray, usable: np.ndarray, mean: FloatArray, s2: float,
          opts: VanishingOptions) -> np.ndarray:
    """``(M,)`` bool: the track fits the family (mean and every frame below the thresholds)."""
    worst = np.where(usable, res, 0.0).max(axis=1)
    return (mean <= min(opts.p_th, opts.outlier_factor * s2)) & \
        (worst <= opts.frame_outlier_factor * s2)


def _refine_group(normals: FloatArray, vis: np.ndarray, group: np.ndarray,
                  allowed: np.ndarray, opts: VanishingOptions, noise: float = 0.0) -> np.ndarray:
    """Trim a group to tracks that fit its VPV, then grow it by every allowed track that fits.

    A track trimmed twice is not let back in (no oscillation at the threshold). ``noise`` is a
    floor of the noise level (from all seed triples): a small group's own estimate is unreliable.
    """
    M = vis.shape[0]
    members = np.zeros(M, dtype=bool)
    members[group] = True
    trimmed = np.zeros(M, dtype=np.int64)
    for _ in range(opts.max_refine_iter):
        res, usable, mean, _, _ = _track_residuals(normals, vis, members, opts)
        s2 = max(_noise_level(res, usable, members, opts), noise)
        fit = _fits(res, usable, mean, s2, opts)
        bad = members & ~fit
        if np.any(bad):
            # drop the worst offender only: it may have biased the others' residuals
            score = np.nan_to_num(mean / min(opts.p_th, opts.outlier_factor * s2), nan=np.inf)
            worst_frame = np.where(usable, res, 0.0).max(axis=1) / (opts.frame_outlier_factor * s2)
            score = np.maximum(score, worst_frame)
            drop = np.flatnonzero(bad)[np.argmax(score[bad])]
            members[drop] = False
            trimmed[drop] += 1
            if members.sum() < 3:
                return members
            continue
        grow = allowed & ~members & (trimmed < 2) & fit
        if not np.any(grow):
            break
        members |= grow
    return members


def _family(normals: FloatArray, vis: np.ndarray, members: np.ndarray,
            opts: VanishingOptions) -> ParallelFamily:
    _, _, resid, v, count = _track_residuals(normals, vis, members, opts)
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
    means = _triple_means(normals, vis, triples, opts)
    thresh = _seed_threshold(means, opts)
    order = np.argsort(means)
    order = order[means[order] <= thresh]
    # the noise level of one residual, from the seeds (mostly parallel triples): the mean
    # lambda_min of a parallel triple estimates the variance of n . v
    noise = float(np.median(means[order])) if order.size else 0.0
    groups: list[np.ndarray] = []
    taken = np.zeros(tracks.num_tracks, dtype=bool)
    tried = 0
    for t in order:
        seed = triples[t]
        if taken[seed].any():
            continue
        tried += 1
        if tried > opts.max_seeds:
            break
        members = _refine_group(normals, vis, seed, ~taken, opts, noise)
        if members.sum() < opts.min_family_size:
            continue
        groups.append(members)
        taken |= members
    groups = _merge_groups(normals, vis, groups, opts, noise)
    families = [_family(normals, vis, g, opts) for g in groups]
    families.sort(key=lambda f: f.size, reverse=True)
    return families[:opts.max_families]


def _merge_groups(normals: FloatArray, vis: np.ndarray, groups: list[np.ndarray],
                  opts: VanishingOptions, noise: float) -> list[np.ndarray]:
    """Merge groups of one direction that grew apart (partial tracks: two seeds in different
    stretches of the sequence): two groups merge if, refined together, at least 90% of their
    tracks stay; the merged group is then grown again."""
    groups = list(groups)
    merged = True
    while merged and len(groups) > 1:
        merged = False
        for a in range(len(groups)):
            for b in range(a + 1, len(groups)):
                union = groups[a] | groups[b]
                both = _refine_group(normals, vis, np.flatnonzero(union), union, opts, noise)
                if both.sum() >= 0.9 * union.sum():
                    others = np.zeros_like(union)
                    for k, g in enumerate(groups):
                        if k not in (a, b):
                            others |= g
                    groups[a] = _refine_group(normals, vis, np.flatnonzero(both), ~others, opts,
                                              noise)
                    del groups[b]
                    merged = True
                    break
            if merged:
                break
    return [g for g in groups if g.sum() >= opts.min_family_size]


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
