"""Groups of parallel tracks: trimming, growing and merging against a group's own per-frame VPV
(docs/method.md §3), on the sparse observations.

A group's state (per-frame scatter matrices of its members, every observation's leave-one-out
residual, every track's mean and worst residual) is kept up to date as members come and go:
a change of one track only touches the frames it is seen in, and the observations there, so a
round of trimming or growing costs what the changed tracks see, not tracks x frames.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from omni_sfm.geometry import FloatArray, smallest_eigenvector_3x3
from omni_sfm.vanishing._observations import IntArray, ObsIndex

if TYPE_CHECKING:
    from omni_sfm.vanishing import VanishingOptions

_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


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


def _loo_residuals(S: FloatArray, n: FloatArray, own: np.ndarray) -> FloatArray:
    """Noise-normalised squared residual of each normal ``n (K, 3)`` against the VPV of the
    scatter ``S (K, 3, 3)`` of its frame's members, less ``n`` itself where ``own`` (leave one
    out): ``(n . v)^2 / (1 + n^T S^+ n)``, see :class:`GroupState`."""
    Sm = S - own[:, None, None] * (n[:, :, None] * n[:, None, :])
    vecs = smallest_eigenvector_3x3(Sm)
    r2 = np.einsum("ki,ki->k", n, vecs) ** 2
    trace = np.trace(Sm, axis1=1, axis2=2)
    T = Sm + trace[:, None, None] * (vecs[:, :, None] * vecs[:, None, :])
    return r2 / (1.0 + np.maximum(_quad_inv(T, n), 0.0))


class SortedMultiset:
    """Floats with a fast exact k-th smallest, for the median of a group's residuals.

    A sorted base, plus sorted pending insertions and deletions (deletions may name pending
    insertions): the count of elements up to ``x`` is three binary searches, and the k-th
    smallest is found by searching the base and the insertions for the first element whose
    count reaches ``k + 1``. Pending changes are merged into the base once they exceed an
    eighth of it, so an update costs about what it changes.
    """

    def __init__(self, values: FloatArray | None = None) -> None:
        self.base = np.sort(values) if values is not None else np.zeros(0)
        self.ins = np.zeros(0)
        self.dels = np.zeros(0)

    def copy(self) -> SortedMultiset:
        out = SortedMultiset()
        out.base, out.ins, out.dels = self.base.copy(), self.ins.copy(), self.dels.copy()
        return out

    @property
    def size(self) -> int:
        return int(self.base.size + self.ins.size - self.dels.size)

    def update(self, removed: FloatArray, added: FloatArray) -> None:
        """Remove the values ``removed`` (present) and insert ``added``."""
        if removed.size:         # merging two sorted runs (a stable sort finds them): O(n)
            self.dels = np.sort(np.concatenate([self.dels, np.sort(removed)]), kind="stable")
        if added.size:
            self.ins = np.sort(np.concatenate([self.ins, np.sort(added)]), kind="stable")
        if self.ins.size + self.dels.size > max(1024, self.base.size // 8):
            merged = np.sort(np.concatenate([self.base, self.ins]), kind="stable")  # 2 runs
            d = self.dels
            pos = np.searchsorted(merged, d, side="left") + \
                (np.arange(d.size) - np.searchsorted(d, d, side="left"))      # equal values
            keep = np.ones(merged.size, dtype=bool)
            keep[pos] = False
            self.base, self.ins, self.dels = merged[keep], np.zeros(0), np.zeros(0)

    def _rank(self, x: FloatArray) -> IntArray:
        """Elements ``<= x``."""
        return np.searchsorted(self.base, x, side="right") + \
            np.searchsorted(self.ins, x, side="right") - np.searchsorted(self.dels, x, side="right")

    def kth(self, k: int) -> float:
        """The k-th smallest element (0-based, ``0 <= k < size``)."""
        found = []
        lo, hi = 0, self.base.size                 # the answer's index in base is in [lo, hi)
        while hi - lo > 64:
            probe = np.unique(np.linspace(lo, hi - 1, 64).astype(np.int64))
            ok = np.flatnonzero(self._rank(self.base[probe]) > k)
            if ok.size == 0:
                lo = hi
                break
            hi = int(probe[ok[0]]) + 1
            lo = int(probe[ok[0] - 1]) + 1 if ok[0] > 0 else lo
        if lo < hi:
            ok = np.flatnonzero(self._rank(self.base[lo:hi]) > k)
            if ok.size:
                found.append(float(self.base[lo + ok[0]]))
        if self.ins.size:
            ok = np.flatnonzero(self._rank(self.ins) > k)
            if ok.size:
                found.append(float(self.ins[ok[0]]))
        return min(found)

    def median(self) -> float:
        """As ``np.median`` of the elements (the mean of the middle two for an even count)."""
        n = self.size
        if n % 2:
            return self.kth(n // 2)
        return (self.kth(n // 2 - 1) + self.kth(n // 2)) / 2.0


class GroupState:
    """Leave-one-out residuals of every track against a group's per-frame VPV.

    A member's normal is tested against the VPV of the *other* members seen in that frame, any
    other track against the VPV of all members. The squared residual ``(n . v)^2`` is divided by
    ``1 + n^T S^+ n`` (``S = sum n n^T`` of the lines defining ``v``, ``S^+`` its inverse across
    ``v``): the variance that ``v``'s own error adds, large where ``v`` rests on 2 nearby
    normals. Every normalised residual then has the same variance (that of ``n . v_true``).
    An observation is usable where at least 2 other members define the VPV, and, for a track
    that is not a member, where their planes are distinct (the middle eigenvalue of their
    scatter at least ``min_spread``, as for a triple): where the members' planes nearly
    coincide (lines along the walk, their planes constant, seen overhead), every line whose
    plane holds their common line fits, and a group grown there passes from one direction to
    another.

    :meth:`add` and :meth:`remove` recompute only the frames the changed tracks are seen in
    (from scratch there, so the state depends on the members only, not on their history).

    Attributes:
        members: ``(M,)`` bool.
        S: ``(F, 3, 3)`` scatter of the members' normals per frame; ``count (F,)`` members seen.
        res, usable: ``(K,)`` per observation (``res`` is 0 where not usable).
        mine: ``(K,)`` usable observations of the members; ``member_res`` their ``res``.
        total, n_usable, worst: ``(M,)`` sum, number and largest of each track's usable ``res``.
    """

    def __init__(self, idx: ObsIndex, opts: VanishingOptions) -> None:
        self.idx = idx
        self.opts = opts
        M, F, K = idx.num_tracks, idx.num_frames, idx.track.size
        self.members = np.zeros(M, dtype=bool)
        self.S = np.zeros((F, 3, 3))
        self.count = np.zeros(F, dtype=np.int64)
        self.res = np.zeros(K)
        self.usable = np.zeros(K, dtype=bool)
        self.mine = np.zeros(K, dtype=bool)
        self.member_res = SortedMultiset()
        self.total = np.zeros(M)
        self.n_usable = np.zeros(M, dtype=np.int64)
        self.worst = np.zeros(M)

    @classmethod
    def of(cls, idx: ObsIndex, opts: VanishingOptions, members: np.ndarray) -> GroupState:
        """The state of the group ``members`` (``(M,)`` bool)."""
        state = cls(idx, opts)
        state.add(np.flatnonzero(members))
        return state

    def copy(self) -> GroupState:
        out = GroupState.__new__(GroupState)
        out.__dict__.update({k: v.copy() if isinstance(v, np.ndarray | SortedMultiset) else v
                             for k, v in self.__dict__.items()})
        return out

    @property
    def num_obs(self) -> int:
        """Observations of the members."""
        return int(self.idx.lengths[self.members].sum())

    def add(self, tracks: IntArray) -> None:
        self.members[tracks] = True
        self._update(tracks)

    def remove(self, tracks: IntArray) -> None:
        self.members[tracks] = False
        self._update(tracks)

    def _update(self, tracks: IntArray) -> None:
        idx = self.idx
        obs, _ = idx.of_tracks(np.atleast_1d(np.asarray(tracks, dtype=np.int64)))
        frames = np.unique(idx.frame[obs])
        if frames.size == 0:
            return
        fobs, loc = idx.in_frames(frames)
        n = idx.normal[fobs]
        own = self.members[idx.track[fobs]]
        # the members' scatter and count in the changed frames, afresh
        S = np.zeros((frames.size, 3, 3))
        for a, b in _PAIRS:
            S[:, a, b] = S[:, b, a] = np.bincount(loc[own], weights=n[own, a] * n[own, b],
                                                  minlength=frames.size)
        count = np.bincount(loc[own], minlength=frames.size)
        self.S[frames] = S
        self.count[frames] = count
        # every observation there, against the VPV of the other members
        usable = count[loc] - own >= 2
        joining = usable & ~own  # a track joins only where the members' planes are distinct
        if np.any(joining):
            usable[joining] = np.linalg.eigvalsh(S[loc[joining]])[:, 1] >= self.opts.min_spread
        res = np.zeros(fobs.size)
        if np.any(usable):
            res[usable] = _loo_residuals(S[loc[usable]], n[usable], own[usable])
        mine = usable & own
        self.member_res.update(self.res[fobs][self.mine[fobs]], res[mine])
        self.res[fobs] = res
        self.usable[fobs] = usable
        self.mine[fobs] = mine
        # the tracks seen there: their mean and worst residual over all their frames
        tracks_there = np.unique(idx.track[fobs])
        tobs, seg = idx.of_tracks(tracks_there)
        u = self.usable[tobs]
        r = np.where(u, self.res[tobs], 0.0)
        lens = np.bincount(seg, minlength=tracks_there.size)       # all >= 1
        self.total[tracks_there] = np.bincount(seg, weights=r, minlength=tracks_there.size)
        self.n_usable[tracks_there] = np.bincount(seg, weights=u, minlength=tracks_there.size)
        self.worst[tracks_there] = np.maximum.reduceat(r, np.cumsum(lens) - lens)

    def mean(self) -> FloatArray:
        """``(M,)`` mean usable residual of each track (NaN where fewer than
        ``min_shared_frames`` are usable)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self.total / self.n_usable
        mean[self.n_usable < self.opts.min_shared_frames] = np.nan
        return mean

    def noise_level(self) -> float:
        """Robust variance of one residual ``n . v`` of the members (rad^2)."""
        med = self.member_res.median() / 0.455 if self.member_res.size else 0.0
        return max(med, np.radians(self.opts.min_noise_deg) ** 2)

    def firm(self) -> np.ndarray:
        """``(F,)`` whether the members' VPV is well determined in each frame: the middle
        eigenvalue of their scatter is at least ``min_spread`` (their planes are distinct, as
        in a triple's test)."""
        firm = np.zeros(self.idx.num_frames, dtype=bool)
        ok = np.flatnonzero(self.count >= 2)
        if ok.size:
            firm[ok] = np.linalg.eigvalsh(self.S[ok])[:, 1] >= self.opts.min_spread
        return firm

    def vpv(self) -> FloatArray:
        """``(F, 3)`` VPV of all members per frame (arbitrary sign; NaN where fewer than 2)."""
        v = np.full((self.idx.num_frames, 3), np.nan)
        ok = self.count >= 2
        if np.any(ok):
            v[ok] = smallest_eigenvector_3x3(self.S[ok])
        return v


def _fits(state: GroupState, mean: FloatArray, s2: float) -> np.ndarray:
    """``(M,)`` bool: the track fits the family (mean and every frame below the thresholds)."""
    opts = state.opts
    return (mean <= min(opts.p_th, opts.outlier_factor * s2)) & \
        (state.worst <= opts.frame_outlier_factor * s2)


def refine_state(state: GroupState, allowed: np.ndarray,
                 noise: float) -> tuple[GroupState, bool]:
    """Trim a group to tracks that fit its VPV, then grow it by every allowed track that fits.

    A track trimmed twice is not let back in (no oscillation at the threshold). ``noise`` is a
    floor of the noise level (from all seed triples): a small group's own estimate is unreliable.

    Returns the group's state (``state``, changed in place) and whether the group ended stable
    (every member fits and no allowed track joins) within ``max_refine_iter`` rounds. A round
    trims one track only, so a group holding more misfits than rounds ends unstable.
    """
    opts = state.opts
    trimmed = np.zeros(state.members.size, dtype=np.int64)
    for _ in range(opts.max_refine_iter):
        mean = state.mean()
        s2 = max(state.noise_level(), noise)
        fit = _fits(state, mean, s2)
        bad = state.members & ~fit
        if np.any(bad):
            # drop the worst offender only: it may have biased the others' residuals
            score = np.nan_to_num(mean / min(opts.p_th, opts.outlier_factor * s2), nan=np.inf)
            score = np.maximum(score, state.worst / (opts.frame_outlier_factor * s2))
            drop = np.flatnonzero(bad)[np.argmax(score[bad])]
            trimmed[drop] += 1
            state.remove(np.array([drop]))
            if state.members.sum() < 3:
                return state, False
            continue
        grow = allowed & ~state.members & (trimmed < 2) & fit
        if not np.any(grow):
            return state, True
        state.add(np.flatnonzero(grow))
    return state, False


class StateCache:
    """States of recent groups, to start unions and families from instead of from scratch.

    A state depends on its members only, so a union's state is a copy of the larger group's
    state plus the other group's tracks: merging a small group into a family that spans the
    sequence costs what the small group sees. The ``size`` states with the most member
    observations (the dearest to rebuild) are kept.
    """

    def __init__(self, idx: ObsIndex, opts: VanishingOptions, size: int = 4) -> None:
        self.idx, self.opts, self.size = idx, opts, size
        self.states: dict[bytes, GroupState] = {}

    def put(self, state: GroupState) -> None:
        """Keep ``state`` (not to be changed afterwards)."""
        self.states[np.packbits(state.members).tobytes()] = state
        if len(self.states) > self.size:
            cheapest = min(self.states, key=lambda k: self.states[k].num_obs)
            del self.states[cheapest]

    def state_of(self, members: np.ndarray) -> GroupState:
        """The state of group ``members`` (cached: copy it before changing it)."""
        key = np.packbits(members).tobytes()
        if key not in self.states:
            self.put(GroupState.of(self.idx, self.opts, members))
        return self.states.get(key) or GroupState.of(self.idx, self.opts, members)

    def union(self, a: np.ndarray, b: np.ndarray) -> GroupState:
        """A new state of the union of groups ``a`` and ``b``."""
        lengths = self.idx.lengths
        if lengths[b].sum() > lengths[a].sum():
            a, b = b, a
        state = self.state_of(a).copy()
        state.add(np.flatnonzero(b & ~a))
        return state


def connected_parts(idx: ObsIndex, members: np.ndarray) -> list[np.ndarray]:
    """The parts of a group (``members`` ``(M,)`` bool) that are seen together: two members are
    in one part where a chain of members links them, each pair of the chain seen in one frame.
    Nothing relates the directions of two parts (a group grown through a frame where its VPV
    rests on two lines can end as the lines of one direction before a turn and of another
    after it). Largest part (most observations) first; ties in track order."""
    tracks = np.flatnonzero(members)
    if tracks.size == 0:
        return []
    obs, pos = idx.of_tracks(tracks)
    frames, col = np.unique(idx.frame[obs], return_inverse=True)
    n = tracks.size + frames.size
    graph = coo_matrix((np.ones(obs.size), (pos, tracks.size + col)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    part = label[:tracks.size]
    size = np.bincount(part, weights=idx.lengths[tracks])
    first = np.full(size.size, tracks.size)
    np.minimum.at(first, part, np.arange(tracks.size))
    order = sorted(np.unique(part), key=lambda p: (-size[p], first[p]))
    out = []
    for p in order:
        m = np.zeros_like(members)
        m[tracks[part == p]] = True
        out.append(m)
    return out


def _shared_frames(count_a: IntArray, count_b: IntArray) -> int:
    """Frames that test two groups against each other, given their members seen per frame:
    members of both seen there, at least 3 in all (so that every member there is judged
    against a VPV that involves the other group)."""
    return int(np.count_nonzero((count_a >= 1) & (count_b >= 1) & (count_a + count_b >= 3)))


def _scatter(idx: ObsIndex, members: np.ndarray, frames: IntArray) -> FloatArray:
    """``(len(frames), 3, 3)`` scatter ``sum n n^T`` of the members' normals in ``frames``
    (increasing)."""
    obs, _ = idx.of_tracks(np.flatnonzero(members))
    loc = np.searchsorted(frames, idx.frame[obs])
    hit = loc < frames.size
    hit[hit] = frames[loc[hit]] == idx.frame[obs[hit]]
    loc, n = loc[hit], idx.normal[obs[hit]]
    S = np.zeros((frames.size, 3, 3))
    for a, b in _PAIRS:
        S[:, a, b] = S[:, b, a] = np.bincount(loc, weights=n[:, a] * n[:, b],
                                              minlength=frames.size)
    return S


MAX_VPV_SIN2 = 0.25
"""Two groups are not refined together when, over the frames where both define a firm VPV,
the median of ``sin^2`` of the angle between their VPVs exceeds this (30 deg): they are of
different directions (a Manhattan scene: 90 deg), and refining them together would only trim
for ``max_refine_iter`` rounds. Groups of one direction agree to a few degrees."""


def _vpvs_disagree(idx: ObsIndex, ga: np.ndarray, gb: np.ndarray, count_a: IntArray,
                   count_b: IntArray, opts: VanishingOptions) -> bool:
    """Whether the VPVs of two groups point apart where both are well determined (see
    :data:`MAX_VPV_SIN2`; False where there is no such frame)."""
    frames = np.flatnonzero((count_a >= 2) & (count_b >= 2))
    if frames.size == 0:
        return False
    Sa, Sb = _scatter(idx, ga, frames), _scatter(idx, gb, frames)
    firm = (np.linalg.eigvalsh(Sa)[:, 1] >= opts.min_spread) & \
        (np.linalg.eigvalsh(Sb)[:, 1] >= opts.min_spread)
    if not np.any(firm):
        return False
    cos = np.einsum("ki,ki->k", smallest_eigenvector_3x3(Sa[firm]),
                    smallest_eigenvector_3x3(Sb[firm]))
    return bool(np.median(1.0 - cos ** 2) > MAX_VPV_SIN2)


def _vpv_turns(state: GroupState) -> bool:
    """Whether a group's VPV turns by more than 30 deg (:data:`MAX_VPV_SIN2`) between two
    consecutive frames where it is well determined: the camera does not turn that fast between
    frames of a video, a group of lines of two directions does (two groups that meet only
    through lines whose planes nearly coincide: lines along the walk seen overhead, whose
    planes hold the vertical and the walk's direction alike; refined together, one group's
    lines are never judged against the other's VPV)."""
    firm = np.flatnonzero(state.firm())
    if firm.size < 2:
        return False
    v = smallest_eigenvector_3x3(state.S[firm])
    cos = np.einsum("ki,ki->k", v[:-1], v[1:])
    return bool(np.any(1.0 - cos ** 2 > MAX_VPV_SIN2))


def merge_groups(idx: ObsIndex, groups: list[np.ndarray], opts: VanishingOptions,
                 noise: float, cache: StateCache | None = None) -> list[np.ndarray]:
    """Merge groups of one direction that grew apart (partial tracks: two seeds in different
    stretches of the sequence): two groups merge if, refined together, the union ends stable
    with at least 90% of its tracks, and what is left of the two still shares at least
    ``min_shared_frames`` frames (see :func:`_shared_frames`); the merged group is then grown
    again.

    Groups that share no frames are never merged: nothing in the normals relates their
    directions (in a long sequence they are often of different directions), so refined
    together each would keep its own per-frame VPV and pass. Nor are groups whose shared
    frames are emptied by the refinement (the few tracks that met were trimmed: two
    directions that only touch). A union still trimming after
    ``max_refine_iter`` rounds (more misfits than rounds: two large families) does not merge
    either, however few of its tracks were trimmed by then, nor one whose VPV turns by more than
    30 deg from a frame to the next (:func:`_vpv_turns`); groups whose VPVs clearly point
    apart are not refined together at all (:data:`MAX_VPV_SIN2`).
    The outcome of a pair is remembered: after a merge the scan starts again, and pairs left
    unchanged are not refined twice.
    """
    cache = cache or StateCache(idx, opts)
    groups = list(groups)
    failed: set[tuple[bytes, bytes]] = set()
    counts: dict[bytes, IntArray] = {}

    def count_of(g: np.ndarray) -> IntArray:
        key = np.packbits(g).tobytes()
        if key not in counts:
            counts[key] = np.bincount(idx.frame[idx.of_tracks(np.flatnonzero(g))[0]],
                                      minlength=idx.num_frames)
        return counts[key]

    def refined_together(ga: np.ndarray, gb: np.ndarray) -> GroupState | None:
        """The state of the two groups refined together, or None if they do not merge."""
        key = (np.packbits(ga).tobytes(), np.packbits(gb).tobytes())
        if key in failed:
            return None
        union = ga | gb
        ca, cb = count_of(ga), count_of(gb)
        if _shared_frames(ca, cb) >= opts.min_shared_frames and \
                not _vpvs_disagree(idx, ga, gb, ca, cb, opts):
            state, stable = refine_state(cache.union(ga, gb), union, noise)
            kept = state.members
            if stable and kept.sum() >= 0.9 * union.sum() and not _vpv_turns(state) and \
                    _shared_frames(count_of(kept & ga), count_of(kept & gb)) >= \
                    opts.min_shared_frames:
                return state
        failed.add(key)
        return None

    merged = True
    while merged and len(groups) > 1:
        merged = False
        for a in range(len(groups)):
            for b in range(a + 1, len(groups)):
                both = refined_together(groups[a], groups[b])
                if both is not None:
                    others = np.zeros_like(both.members)
                    for k, g in enumerate(groups):
                        if k not in (a, b):
                            others |= g
                    state = refine_state(both, ~others, noise)[0]
                    cache.put(state)
                    groups[a] = state.members.copy()
                    del groups[b]
                    merged = True
                    break
            if merged:
                break
    return [g for g in groups if g.sum() >= opts.min_family_size]


def family_arrays(state: GroupState) -> tuple[FloatArray, FloatArray, FloatArray, IntArray,
                                                np.ndarray]:
    """The VPV per frame ``(F, 3)`` (sign unchained), each track's mean residual ``(M,)``, each
    frame's mean ``(n . v)^2`` over the members seen there ``(F,)``, their count ``(F,)``, and
    whether the VPV is well determined there ``(F,)`` (:meth:`GroupState.firm`)."""
    idx = state.idx
    v = state.vpv()
    count = state.count.copy()
    firm = state.firm()
    obs, _ = idx.of_tracks(np.flatnonzero(state.members))
    f = idx.frame[obs]
    r = np.einsum("ki,ki->k", idx.normal[obs], np.nan_to_num(v[f])) ** 2
    total = np.bincount(f, weights=r, minlength=idx.num_frames)
    with np.errstate(invalid="ignore", divide="ignore"):
        frame_res = np.where(count >= 2, total / count, np.nan)
    return v, state.mean(), frame_res, count, firm
