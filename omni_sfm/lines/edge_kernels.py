"""The line extractor's per-pixel and per-edge-point loops, compiled (``_edges.c``).

:class:`~omni_sfm.lines.extract.LineExtractor` finds edges (histogram, Sobel, Canny), tests
every Canny edge point for being corner-like, links the line-like ones into segments, finds
their sub-pixel positions and scores great-circle hypotheses on them;
:class:`~omni_sfm.lines.track.LineTracker` samples the lines and snaps tracked points to them.
Written in numpy each step was a dozen calls on arrays of one row per edge point (tens of
thousands in a textured frame), and the calls' overhead and their temporary arrays were much of
the extraction's time; here each is one loop over the points or pixels. The formulas are those
numpy or OpenCV evaluated before (``tests/test_edge_kernels.py`` keeps those versions), in the
same precision and order of operations: the results are the same bits, but for the corner
test's window sums (see :func:`corner_test`) and the planes' eigenvectors
(:func:`smallest_eigenvector3`), which are as accurate as before.

The extension is built by the project's install (``make setup``: ``pip install -e .``, any C
compiler and Python's headers).
"""

from __future__ import annotations

import numpy as np

from omni_sfm.geometry import FloatArray

try:
    from omni_sfm.lines import _edges  # (the package's __getattr__ types it as Any)
except ImportError as exc:  # pragma: no cover - a source tree without the install's build
    raise ImportError(
        "omni_sfm.lines._edges (the line extractor's compiled loops) is not built: install "
        "omni-sfm with `make setup` or `pip install -e .` (needs a C compiler)") from exc


def _i64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int64)


def _i32(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int32)


def _f32(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


def _c64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.complex64)


def _u8(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.uint8)


def histogram(gray: np.ndarray, mask: np.ndarray, roi: tuple[slice, slice]) -> np.ndarray:
    """``cv2.calcHist([gray[roi]], [0], mask[roi], [256], [0, 256]).ravel()``: the float32
    counts of each grey level of the uint8 image ``gray`` where the uint8 ``mask`` (at least as
    large) is not 0, in the region ``roi`` (two slices with start and stop), read in place."""
    g, m = _u8(gray), _u8(mask)
    if g.ndim != 2 or m.ndim != 2:
        raise ValueError(f"histogram: 2-D images, got {g.shape} and {m.shape}")
    ys, xs = roi
    out = np.empty(256, np.float32)
    _edges.histogram(ys.stop - ys.start, xs.stop - xs.start, g.shape[0], g.shape[1], g,
                     m.shape[0], m.shape[1], m, xs.start, ys.start, out)
    return out


def canny(dx16: np.ndarray, dy16: np.ndarray, low: float, high: float) -> np.ndarray:
    """``cv2.Canny(dx16, dy16, low, high, L2gradient=True)``: the uint8 edge map (255 on
    edges) of the int16 gradients, the same pixels (``tests/test_edge_kernels.py``)."""
    x, y = np.ascontiguousarray(dx16, np.int16), np.ascontiguousarray(dy16, np.int16)
    if x.ndim != 2 or x.shape != y.shape:
        raise ValueError(f"canny: two 2-D gradients of one shape, got {x.shape}, {y.shape}")
    lo, hi = (min(32767.0, float(v)) for v in (low, high))
    if lo > hi:
        lo, hi = hi, lo
    # OpenCV squares positive thresholds for the L2 magnitude and floors them
    lo2, hi2 = (int(np.floor(v * v if v > 0 else v)) for v in (lo, hi))
    out = np.empty(x.shape, np.uint8)
    _edges.canny(x.shape[0], x.shape[1], x, y, lo2, hi2, out)
    return out


def sobel_gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`gradients` of ``cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)`` and ``(0, 1)`` of the
    float32 image ``img`` (at least 2x2), with OpenCV's border and order of operations (the
    same bits), in one pass: no dx, dy images are made."""
    a = _f32(img)
    if a.ndim != 2:
        raise ValueError(f"sobel_gradients: a 2-D image, got {a.shape}")
    dx16, dy16 = np.empty(a.shape, np.int16), np.empty(a.shape, np.int16)
    dxy = np.empty(a.shape, np.complex64)
    _edges.sobel_gradients(a.shape[0], a.shape[1], a, dx16, dy16, dxy.view(np.float32))
    return dx16, dy16, dxy


def gradients(dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of the float32 Sobel images ``dx``, ``dy`` (same shape): Canny's int16 gradients,
    ``np.multiply(d, 8.0, out=d16, casting="unsafe")`` (numpy's cast on x86: truncated toward
    zero to int32, NaN, infinities and values past int32 giving -2^31, then the low 16 bits),
    and the complex64 image ``dx + i dy`` (``cv2.merge([dx, dy])`` viewed as complex64), in one
    pass over the pixels."""
    x, y = _f32(dx), _f32(dy)
    if x.shape != y.shape:
        raise ValueError(f"gradients: dx {x.shape} and dy {y.shape} differ")
    dx16, dy16 = np.empty(x.shape, np.int16), np.empty(x.shape, np.int16)
    dxy = np.empty(x.shape, np.complex64)
    _edges.gradients(x.size, x, y, dx16, dy16, dxy.view(np.float32))
    return dx16, dy16, dxy


def edge_points(edges: np.ndarray, mask: np.ndarray, origin: tuple[int, int] = (0, 0),
                cap: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The pixels of the ``(h, w)`` uint8 image ``edges`` where ``edges & mask`` is not 0, row
    by row: ``cv2.findNonZero(cv2.bitwise_and(edges, m))`` as int32 ``(N, 2)`` (x, y), and
    their flat indices ``y w + x`` (int64 ``(N,)``), where ``m`` is the part of the uint8
    ``mask`` (as large or larger) whose top-left pixel is ``origin`` (x, y): ``mask[y0 : y0 +
    h, x0 : x0 + w]``, read in place. ``cap``: at most that many points (the output arrays are
    allocated that large), the image's size where None."""
    e, m = _u8(edges), _u8(mask)
    if e.ndim != 2 or m.ndim != 2:
        raise ValueError(f"edge_points: 2-D images, got {e.shape} and {m.shape}")
    h, w = e.shape
    c = e.size if cap is None else min(int(cap), e.size)
    pix, flat = np.empty((c, 2), np.int32), np.empty(c, np.int64)
    n = _edges.edge_points(h, w, e, m.shape[0], m.shape[1], m, int(origin[0]), int(origin[1]),
                           c, pix, flat)
    return pix[:n], flat[:n]


def long_chains(pix: np.ndarray, flat: np.ndarray, shape: tuple[int, int],
                min_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points of 8-connected chains of at least ``min_points`` points among the points
    ``pix`` ``(N, 2)`` at the strictly increasing flat indices ``flat`` of an image of
    ``shape`` (h, w) (:func:`edge_points`' order): ``cv2.connectedComponents`` on the image of
    the points and each point's component size, by a union-find over the points. Returns the
    ``(N,)`` bool mask and the kept pixels and flat indices."""
    p, f = _i32(pix).reshape(-1, 2), _i64(flat).reshape(-1)
    if len(f) != len(p):
        raise ValueError(f"long_chains: {len(p)} pixels but {len(f)} indices")
    keep = np.empty(len(f), bool)
    out_pix, out_flat = np.empty((len(f), 2), np.int32), np.empty(len(f), np.int64)
    n = _edges.long_chains(len(f), int(shape[0]), int(shape[1]), p, f, int(min_points),
                           keep.view(np.uint8), out_pix, out_flat)
    return keep, out_pix[:n], out_flat[:n]


def corner_test(dxy: np.ndarray, pix: np.ndarray, flat: np.ndarray, win: np.ndarray,
                weights: np.ndarray, ratio2: float, origin: tuple[int, int] = (0, 0)
                ) -> tuple[np.ndarray, np.ndarray]:
    """The line-like points among the edge points ``pix`` ``(N, 2)`` (x, y) at the flat
    indices ``flat`` ``(N,)`` of the complex64 gradient image ``dxy`` (``dx + i dy``, any
    shape): those whose second-moment matrix ``M = sum_j w_j g_j g_j^T`` over the window
    (``flat + win``, float32 ``weights``) has eigenvalues with ``lmax >= ratio2 lmin``.
    Returns their pixels plus ``origin`` (int32 ``(n, 2)``) and their complex64 gradients
    ``(n,)``, in the order of the input.

    The float32 arithmetic is that of ``LineExtractor._edge_points`` before, except that each
    entry of ``M`` is summed over the window in order where numpy's BLAS matrix-vector product
    summed in an order of its own (last-bit differences in the entries; on the 100 rendered
    test frames, 2.9 million edge points, no point's decision changed)."""
    d = _c64(dxy).reshape(-1)
    p, f = _i32(pix).reshape(-1, 2), _i64(flat)
    wi, w = _i64(win), _f32(weights)
    if len(f) != len(p) or len(wi) != len(w):
        raise ValueError(f"corner_test: {len(p)} pixels and {len(f)} indices, {len(wi)} window "
                         f"offsets and {len(w)} weights")
    out_pix = np.empty((len(f), 2), np.int32)
    out_g = np.empty(len(f), np.complex64)
    n = _edges.corner_test(d.size, len(f), len(wi), d.view(np.float32), p, f, wi, w,
                           float(ratio2), int(origin[0]), int(origin[1]), out_pix,
                           out_g.view(np.float32))
    return out_pix[:n], out_g[:n]


def mod_pi(a: np.ndarray) -> FloatArray:
    """``np.mod(a, np.pi).astype(np.float64)`` of float32 ``a`` (float32 remainder by pi
    rounded to float32, as numpy computes it: ten times faster than numpy's ``fmodf`` loop)."""
    x = _f32(a).reshape(-1)
    out = np.empty(x.size)
    _edges.mod_pi(x.size, x, out)
    return out.reshape(np.shape(a))


def oriented_components(p: np.ndarray, shape: tuple[int, int], theta: FloatArray,
                        max_angle: float) -> tuple[int, np.ndarray]:
    """Connected components of the points ``p`` ``(N, 2)`` (x, y inside ``shape`` (h, w)),
    8-neighbours linked where their orientations ``theta`` (rad, mod pi) differ by less than
    ``max_angle`` (``d = |t_i - t_j|``, ``min(d, pi - d)``). Returns the number of components
    and the ``(N,)`` int64 labels, numbered in the order of each component's first point (as
    scipy's ``connected_components``). A union-find over the points."""
    pp = _i64(p).reshape(-1, 2)
    t = np.ascontiguousarray(theta, dtype=np.float64)
    if len(t) != len(pp):
        raise ValueError(f"oriented_components: {len(pp)} points but {len(t)} orientations")
    lab = np.empty(len(pp), np.int64)
    n = _edges.components(len(pp), int(shape[0]), int(shape[1]), pp, t, float(max_angle), lab)
    return int(n), lab


def subpixel(dxy: np.ndarray, pix: np.ndarray, grad: np.ndarray, sel: np.ndarray,
             origin: tuple[int, int]) -> FloatArray:
    """``(len(sel), 2)`` sub-pixel positions of the edge points ``pix[sel]`` (int32 ``(N, 2)``
    image pixels, x, y) with complex64 gradients ``grad[sel]``: the vertex of the parabola
    through the gradient magnitude at the point and one pixel either way along its gradient,
    the magnitudes bilinearly interpolated in the ``(h, w)`` complex64 gradient image ``dxy``
    whose top-left pixel is image pixel ``origin`` (x, y); the offset clipped to half a pixel
    (``extract._EdgePoints.subpixel``)."""
    d = _c64(dxy)
    if d.ndim != 2:
        raise ValueError(f"subpixel: the gradient image must be 2-D, got shape {d.shape}")
    p, g, s = _i32(pix).reshape(-1, 2), _c64(grad).reshape(-1), _i64(sel).reshape(-1)
    if len(g) != len(p):
        raise ValueError(f"subpixel: {len(p)} pixels but {len(g)} gradients")
    out = np.empty((len(s), 2))
    _edges.subpixel(len(p), len(s), d.shape[0], d.shape[1], d.view(np.float32), p,
                    g.view(np.float32), s, int(origin[0]), int(origin[1]), out)
    return out


def msac_costs(rays: np.ndarray, hyp: np.ndarray, seg: np.ndarray, start: np.ndarray,
               t2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The MSAC costs of ``LineExtractor._ransac``: for float32 rays ``(3, N)`` (x, y, z
    rows) sorted by segment ``seg`` ``(N,)`` (segments starting at ``start`` ``(S,)``) and
    float32 unit hypotheses ``hyp`` ``(3, S, H)``, ``d = r . hyp[seg]`` (summed x, y, z in that
    order), ``cost = min(d^2, t2) / t2`` ``(N, H)`` float32 (``t2`` ``(N,)`` float32) and
    ``(S, H)`` its sums per segment as ``np.add.reduceat(cost, start, axis=0)`` adds them."""
    r, h = _f32(rays), _f32(hyp)
    if r.ndim != 2 or r.shape[0] != 3 or h.ndim != 3 or h.shape[0] != 3:
        raise ValueError(f"msac_costs: rays (3, N) and hyp (3, S, H), got {r.shape} and "
                         f"{h.shape}")
    n, (s, nh) = r.shape[1], h.shape[1:]
    sg, st, t = _i64(seg), _i64(start), _f32(t2)
    if len(st) != s:
        raise ValueError(f"msac_costs: {s} segments' hypotheses but {len(st)} starts")
    cost = np.empty((n, nh), np.float32)
    seg_cost = np.empty((s, nh), np.float32)
    _edges.msac(n, s, nh, r, h, sg, st, t, cost, seg_cost)
    return cost, seg_cost


def _f64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


def scatter(rays: np.ndarray, weight: np.ndarray | None, seg: np.ndarray,
            nseg: int) -> FloatArray:
    """``(S, 3, 3)`` sums of ``w r r^T`` over the rays ``(N, 3)`` of each segment ``seg``
    ``(N,)`` (0..nseg-1, any order; ``weight`` ``(N,)`` or None for ones): ``extract._scatter``
    before, each entry summed in point order as ``np.bincount`` with weights does."""
    r, sg = _f64(rays).reshape(-1, 3), _i64(seg).reshape(-1)
    w = None if weight is None else _f64(weight).reshape(-1)
    if len(sg) != len(r) or (w is not None and len(w) != len(r)):
        raise ValueError(f"scatter: {len(r)} rays, {len(sg)} segment indices"
                         + ("" if w is None else f", {len(w)} weights"))
    out = np.empty((int(nseg), 3, 3))
    _edges.scatter(len(r), int(nseg), r, w, sg, out)
    return out


def smallest_eigenvector3(S: np.ndarray) -> FloatArray:
    """``geometry.smallest_eigenvector`` of symmetric ``S`` ``(K, 3, 3)``: ``(K, 3)`` unit
    eigenvectors of the smallest eigenvalues (arbitrary sign), by Jacobi rotations in C (as
    accurate as ``np.linalg.eigh``, whose per-call cost was most of the time on a frame's few
    dozen lines); NaN rows where a matrix holds a NaN or an infinity."""
    m = _f64(S)
    if m.ndim != 3 or m.shape[1:] != (3, 3):
        raise ValueError(f"smallest_eigenvector3: (K, 3, 3) matrices, got {m.shape}")
    out = np.empty((m.shape[0], 3))
    _edges.smallest_eigvec3(m.shape[0], m, out)
    return out


def arc_parameter(rays: np.ndarray, normals: np.ndarray, group: np.ndarray,
                  ngroup: int) -> FloatArray:
    """``extract._arc_parameter``: the angle of each ray ``(N, 3)`` along the great circle of
    its group (normal ``normals[group]``), from the mean direction of the group's rays, in
    ``(-pi, pi]``. The two coordinates are computed in C with the sums numpy made (the means
    as ``np.bincount``, the bases as ``geometry.completion_towards``, the dot products as
    ``np.einsum``), the angle by numpy's ``arctan2`` (its SIMD one on this build, not the C
    library's)."""
    r, n, g = _f64(rays).reshape(-1, 3), _f64(normals).reshape(-1, 3), _i64(group).reshape(-1)
    if len(g) != len(r) or len(n) != ngroup:
        raise ValueError(f"arc_parameter: {len(r)} rays, {len(g)} group indices, "
                         f"{len(n)} normals for {ngroup} groups")
    y, x = np.empty(len(r)), np.empty(len(r))
    _edges.arc_xy(len(r), int(ngroup), r, n, g, y, x)
    return np.arctan2(y, x)


def order_by(key: np.ndarray, t: np.ndarray, nkey: int) -> np.ndarray:
    """``np.lexsort((t, key))`` for ``key`` in 0..nkey-1 (a counting sort by key, then a
    stable merge sort by ``t`` within each key; NaN last, as numpy sorts)."""
    k, tt = _i64(key).reshape(-1), _f64(t).reshape(-1)
    if len(tt) != len(k):
        raise ValueError(f"order_by: {len(k)} keys but {len(tt)} values")
    order = np.empty(len(k), np.int64)
    _edges.order_by(len(k), int(nkey), k, tt, order)
    return order


def gap_pieces(seg: np.ndarray, t: np.ndarray, s: np.ndarray, nseg: int, max_gap: float,
               min_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``LineExtractor._split_gaps`` after the arc parameters ``t``: the points ordered by
    segment ``seg`` (0..nseg-1), then ``t``, cut where the segment changes or ``t`` steps by
    more than ``max_gap * s`` (``s`` of the later point), pieces under ``min_points`` points
    dropped. Returns the kept points' positions in the input, their piece (0..P-1) and each
    piece's segment ``(P,)``."""
    sg, tt, ss = _i64(seg).reshape(-1), _f64(t).reshape(-1), _f64(s).reshape(-1)
    n = len(sg)
    if len(tt) != n or len(ss) != n:
        raise ValueError(f"gap_pieces: {n} points, {len(tt)} t, {len(ss)} s")
    pos, piece, piece_seg = (np.empty(n, np.int64) for _ in range(3))
    nk, npc = _edges.gap_pieces(n, int(nseg), sg, tt, ss, float(max_gap), int(min_points),
                                pos, piece, piece_seg)
    return pos[:nk], piece[:nk], piece_seg[:npc]


def trim_ends(lab: np.ndarray, t: np.ndarray, s: np.ndarray, nlines: int, trim: float,
              min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """``LineExtractor._trim_ends`` after the arc parameters ``t``: the points further than
    ``trim * s`` from both ends of their line ``lab`` (0..nlines-1; ends: the least and
    largest ``t``) of the lines that keep at least ``min_points`` points. Returns their
    positions in the input (in its order) and their lines renumbered 0.. among those kept."""
    lb, tt, ss = _i64(lab).reshape(-1), _f64(t).reshape(-1), _f64(s).reshape(-1)
    n = len(lb)
    if len(tt) != n or len(ss) != n:
        raise ValueError(f"trim_ends: {n} points, {len(tt)} t, {len(ss)} s")
    pos, new = np.empty(n, np.int64), np.empty(n, np.int64)
    k = _edges.trim_ends(n, int(nlines), lb, tt, ss, float(trim), int(min_points), pos, new)
    return pos[:k], new[:k]


def package(rays: np.ndarray, normals: np.ndarray, lab: np.ndarray, t: np.ndarray,
            s: np.ndarray, noise: float) -> tuple[np.ndarray, FloatArray, FloatArray,
                                                  FloatArray, FloatArray, FloatArray]:
    """``LineExtractor._package``'s per-line figures for the points sorted by line ``lab``
    (0..L-1, each present) with rays ``(N, 3)``, arc parameters ``t`` and pixel angles ``s``
    and the lines' ``(L, 3)`` normals: ``(sizes, ends (L, 2, 3), residual_px, arc (rad), mean
    s, normal_sigma (L, 2))``, with the sums and dot products numpy made."""
    r, nrm = _f64(rays).reshape(-1, 3), _f64(normals).reshape(-1, 3)
    lb, tt, ss = _i64(lab).reshape(-1), _f64(t).reshape(-1), _f64(s).reshape(-1)
    n, nl = len(r), len(nrm)
    if len(lb) != n or len(tt) != n or len(ss) != n:
        raise ValueError(f"package: {n} rays, {len(lb)} labels, {len(tt)} t, {len(ss)} s")
    sizes = np.empty(nl, np.int64)
    ends = np.empty((nl, 2, 3))
    resid, arc, mean_s = np.empty(nl), np.empty(nl), np.empty(nl)
    sigma = np.empty((nl, 2))
    _edges.package(n, nl, r, nrm, lb, tt, ss, float(noise), sizes, ends, resid, arc, mean_s,
                   sigma)
    return sizes, ends, resid, arc, mean_s, sigma


def inliers(rays: np.ndarray, normals: np.ndarray, seg: np.ndarray,
            tol: np.ndarray) -> tuple[np.ndarray, FloatArray]:
    """``|r . n[seg]| < tol`` (einsum's dot product) for the rays ``(N, 3)`` and the
    segments' normals ``(S, 3)``, and the inliers' count per segment (float64, as
    ``np.bincount(seg, weights=mask)``)."""
    r, nrm = _f64(rays).reshape(-1, 3), _f64(normals).reshape(-1, 3)
    sg, tl = _i64(seg).reshape(-1), _f64(tol).reshape(-1)
    if len(sg) != len(r) or len(tl) != len(r):
        raise ValueError(f"inliers: {len(r)} rays, {len(sg)} segment indices, {len(tl)} "
                         f"tolerances")
    inl = np.empty(len(r), bool)
    count = np.empty(len(nrm))
    _edges.inliers(len(r), len(nrm), r, nrm, sg, tl, inl, count)
    return inl, count


def merge_labels(rays: np.ndarray, idx: np.ndarray, lab: np.ndarray, normals: np.ndarray,
                 cand: np.ndarray, max_gap: float) -> np.ndarray:
    """``LineExtractor._merge`` after its candidate pairs ``cand`` ``(C, 2)`` of pieces (the
    points ``idx`` into ``rays`` ``(R, 3)`` with pieces ``lab`` 0..L-1, ``normals`` ``(L, 3)``):
    each pair's gap along the great circle of its first piece (from that piece's mean ray:
    np.add.reduceat's sums), the pairs with ``0 <= gap <= max_gap`` (rad) joined by a
    union-find in pair order. Returns ``(L,)`` each piece's new label (the rank of its root).
    The coordinates in C, their angles by numpy's arctan2, the gaps and joins in C."""
    r, nrm = _f64(rays).reshape(-1, 3), _f64(normals).reshape(-1, 3)
    ix, lb, cd = _i64(idx).reshape(-1), _i64(lab).reshape(-1), _i64(cand).reshape(-1, 2)
    if len(lb) != len(ix):
        raise ValueError(f"merge_labels: {len(ix)} points but {len(lb)} labels")
    nl = len(nrm)
    if len(lb) and (lb.min() < 0 or lb.max() >= nl):
        raise IndexError(f"merge_labels: labels outside 0..{nl - 1}")
    if len(cd) and (cd.min() < 0 or cd.max() >= nl):
        raise IndexError(f"merge_labels: candidate pieces outside 0..{nl - 1}")
    size = np.bincount(lb, minlength=nl)
    total = int(size[cd].sum())
    y, x = np.empty(total), np.empty(total)
    _edges.merge_xy(len(r), len(ix), nl, len(cd), total, r, ix, lb, nrm, cd, y, x)
    t = np.arctan2(y, x)
    new = np.empty(nl, np.int64)
    _edges.merge_join(len(lb), nl, len(cd), total, lb, cd, t, float(max_gap), new)
    return new


def hypotheses(rays: np.ndarray, ia: np.ndarray, ib: np.ndarray) -> tuple[np.ndarray,
                                                                          np.ndarray]:
    """``LineExtractor._ransac``'s great-circle hypotheses through the pairs of rays ``(ia,
    ib)`` ``(S, H)`` (indices into ``rays`` ``(N, 3)``): ``np.cross`` over its
    ``np.linalg.norm`` (1 where that is 0), as float32 ``(3, S, H)`` (the layout of
    :func:`msac_costs`), and ``(S, H)`` whether the norm is under 1e-9."""
    r, a, b = _f64(rays).reshape(-1, 3), _i64(ia), _i64(ib)
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(f"hypotheses: ia and ib must be (S, H), got {a.shape} and {b.shape}")
    s, h = a.shape
    hyp = np.empty((3, s, h), np.float32)
    degenerate = np.empty((s, h), bool)
    _edges.hypotheses(len(r), s, h, r, a, b, hyp, degenerate)
    return hyp, degenerate


def line_samples(offsets: np.ndarray, points_uv: np.ndarray, spacing: float,
                 max_samples: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``LineTracker._samples``: points at constant intervals on each line (the line owns
    ``points_uv[offsets[l]:offsets[l + 1]]``, none empty): ``(S, 2)`` pixels, ``(S, 2)`` unit
    tangents of the edge there (0 where the points 2 before and 2 after coincide), ``(S,)``
    line index and ``(L,)`` samples per line, in the numpy code's float64 arithmetic (the same
    bits; ``tests/test_edge_kernels.py``)."""
    off, uv = _i64(offsets).reshape(-1), _f64(points_uv).reshape(-1, 2)
    nl = max(0, len(off) - 1)
    k = np.empty(nl, np.int64)
    m = float(max(1, int(max_samples)))
    n = _edges.line_samples(nl, len(uv), 0, off, uv, float(spacing), m, k, None, None, None,
                            None)
    pos, line = np.empty(n, np.int64), np.empty(n, np.int64)
    at, tangent = np.empty((n, 2)), np.empty((n, 2))
    _edges.line_samples(nl, len(uv), n, off, uv, float(spacing), m, k, pos, at, tangent, line)
    return at, tangent, line, k


def snap(points: np.ndarray, queries: np.ndarray, radius: float) -> np.ndarray | None:
    """For each query ``(K, 2)`` the index of the nearest of ``points`` ``(M, 2)`` within
    ``radius`` (squared distance under ``radius**2``; of equal distances the lowest index), -1
    where none is: a KD-tree query with ``distance_upper_bound`` (``LineTracker``'s snapping),
    from a grid of cells ``radius`` wide. None where the points are too sparse for a grid
    (spread over more than ``16 M + 65536`` cells) or not finite: use a tree then."""
    p, q = _f64(points).reshape(-1, 2), _f64(queries).reshape(-1, 2)
    nearest = np.empty(len(q), np.int64)
    if not _edges.snap(len(p), len(q), p, q, float(radius), nearest):
        return None
    return nearest
