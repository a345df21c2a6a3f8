"""Triples of tracks tested for parallelism (eq. 5-6 of docs/method.md §3), from the sparse
observations: only tracks that share frames are paired, and a triple's test runs over the
observations of its shortest track, so the cost follows the observations, not tracks x frames.
"""

from __future__ import annotations

from itertools import combinations
from math import comb
from typing import TYPE_CHECKING

import numpy as np
from scipy.sparse import csr_matrix

from omni_sfm.geometry import FloatArray
from omni_sfm.vanishing._observations import IntArray, ObsIndex, concat_ranges

if TYPE_CHECKING:
    from omni_sfm.vanishing import VanishingOptions


def triple_eigs(n1: FloatArray, n2: FloatArray, n3: FloatArray) -> tuple[FloatArray, FloatArray]:
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


def _rows(rows: IntArray, cols: IntArray, num_rows: int) -> tuple[IntArray, IntArray]:
    """CSR ``(indptr, indices)`` of the entries ``(rows, cols)``, columns increasing per row."""
    order = np.lexsort((cols, rows))
    indptr = np.searchsorted(rows[order], np.arange(num_rows + 1), side="left")
    return indptr, cols[order].astype(np.int64)


def _pick(rng: np.random.Generator, num_tracks: int, indptr: IntArray, indices: IntArray,
          rows: IntArray | None = None,
          chunk_values: int = 1 << 20) -> tuple[IntArray, np.ndarray]:
    """One random candidate per row: the candidate whose draw is largest in that row of
    ``rng.random((num_rows, num_tracks))`` (a uniform choice among the row's candidates).

    ``rows`` selects the CSR rows (default: all, in order). The draws are made in chunks of
    rows, which consumes ``rng`` exactly as the one ``(num_rows, num_tracks)`` array would (the
    same triples as ever for a given seed) while holding at most ``chunk_values`` of them.
    Returns the chosen column per row and whether the row had a candidate.
    """
    if rows is None:
        rows = np.arange(len(indptr) - 1)
    n = len(rows)
    chosen = np.zeros(n, dtype=np.int64)
    good = np.zeros(n, dtype=bool)
    step = max(1, chunk_values // max(num_tracks, 1))
    for s in range(0, n, step):
        e = min(n, s + step)
        draws = rng.random((e - s, num_tracks))
        lens = indptr[rows[s:e] + 1] - indptr[rows[s:e]]
        cand = indices[concat_ranges(indptr[rows[s:e]], lens)]
        if cand.size == 0:
            continue
        local = np.repeat(np.arange(e - s), lens)
        vals = draws[local, cand]
        has = lens > 0
        best = np.zeros(e - s)
        best[has] = np.maximum.reduceat(vals, (np.cumsum(lens) - lens)[has])
        hit = np.flatnonzero(vals == best[local])
        hit_rows, first = np.unique(local[hit], return_index=True)      # lowest column on ties
        chosen[s + hit_rows] = cand[hit[first]]
        good[s:e] = has & (best > 0)
    return chosen, good


def draw_triples(idx: ObsIndex, opts: VanishingOptions, rng: np.random.Generator) -> IntArray:
    """``(T, 3)`` sorted unique track triples to test (all of them if few enough).

    Otherwise ``max_triples`` random ones: a track ``i`` that shares ``min_shared_frames``
    frames with at least two others, one of those partners ``j``, and a third track ``k`` that
    shares that many frames with both at once. The pair overlaps and the triple overlaps come
    from sparse products of the ``(M, F)`` visibility, whose cost is the sum over frames of
    (tracks seen)^2, not ``M^2 F``.
    """
    M = idx.num_tracks
    if comb(M, 3) <= opts.max_triples:
        return np.array(list(combinations(range(M), 3)), dtype=np.int64).reshape(-1, 3)
    s = opts.min_shared_frames
    vis = idx.visibility_matrix()
    pairs = (vis @ vis.T).tocoo()
    keep = (pairs.row != pairs.col) & (pairs.data >= s)
    indptr, indices = _rows(pairs.row[keep].astype(np.int64), pairs.col[keep], M)
    ok_i = np.flatnonzero(np.diff(indptr) >= 2)
    if ok_i.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    i = rng.choice(ok_i, size=opts.max_triples)
    j, good = _pick(rng, M, indptr, indices, rows=i)
    i, j = i[good], j[good]
    if i.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    both = csr_matrix(vis[i].multiply(vis[j]))                        # frames i and j share
    tri = (both @ vis.T).tocoo()                                         # ... and k sees too
    r = tri.row.astype(np.int64)
    keep = (tri.data >= s) & (tri.col != i[r]) & (tri.col != j[r])
    indptr, indices = _rows(r[keep], tri.col[keep], len(i))
    k, good = _pick(rng, M, indptr, indices)
    out = np.sort(np.stack([i[good], j[good], k[good]], 1), axis=1)
    key = np.unique((out[:, 0] * M + out[:, 1]) * M + out[:, 2])
    return np.stack([key // (M * M), (key // M) % M, key % M], 1)


def triple_means(idx: ObsIndex, triples: IntArray, opts: VanishingOptions,
                 chunk: int = 4000) -> FloatArray:
    """``(T,)`` mean over the shared frames of ``min_v sum_i (n_i . v)^2`` (eq. 5-6) of each
    triple; ``inf`` where fewer than ``min_shared_frames`` frames test it (``min_spread``).

    The shared frames are found by looking the other two tracks up in each frame of the
    triple's shortest track.
    """
    out = np.full(len(triples), np.inf)
    lengths = idx.lengths
    for s in range(0, len(triples), chunk):
        t = np.asarray(triples[s:s + chunk], dtype=np.int64)
        n = len(t)
        shortest = t[np.arange(n), np.argmin(lengths[t], axis=1)]
        obs, tri = idx.of_tracks(shortest)
        frames = idx.frame[obs]
        o = [idx.lookup(t[tri, c], frames) for c in range(3)]
        shared = (o[0] >= 0) & (o[1] >= 0) & (o[2] >= 0)
        tri = tri[shared]
        lam_min, lam_mid = triple_eigs(*(idx.normal[oc[shared]] for oc in o))
        use = lam_mid >= opts.min_spread
        cnt = np.bincount(tri[use], minlength=n)
        total = np.bincount(tri[use], weights=lam_min[use], minlength=n)
        mean = total / np.maximum(cnt, 1)
        out[s:s + n] = np.where(cnt >= opts.min_shared_frames, mean, np.inf)
    return out


def seed_threshold(means: FloatArray, opts: VanishingOptions) -> float:
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
