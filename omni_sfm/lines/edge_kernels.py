"""The line extractor's per-edge-point loops, compiled (``_edges.c``).

:class:`~omni_sfm.lines.extract.LineExtractor` tests every Canny edge point for being
corner-like, links the line-like ones into segments, finds their sub-pixel positions and scores
great-circle hypotheses on them. Written in numpy each step was a dozen calls on arrays of one
row per edge point (tens of thousands in a textured frame), and the calls' overhead and their
temporary arrays were much of the extraction's time; here each is one loop over the points.
The formulas are those numpy evaluated before (``tests/test_edge_kernels.py`` keeps those
numpy versions), in the same precision and order of operations: the results are the same bits,
but for the corner test's window sums (see :func:`corner_test`).

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
