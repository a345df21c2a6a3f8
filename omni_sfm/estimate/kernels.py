"""The line bundle adjustment's per-observation loops, compiled (``_lines.c``).

After every step of every adjustment, :class:`~omni_sfm.estimate.bundle.LineProblem`
evaluates the residuals of all observations and gives each line Gauss-Newton iterations of
its own. Written in numpy these were some sixty calls on arrays of a few thousand rows each,
and numpy's per-call overhead was most of the estimator's time on real tracks
(docs/estimator.md, "Speed"); here they are one loop over the observations. The formulas are
those of ``bundle.py`` (its docstrings), written out per observation; the values agree with
numpy's to round-off (``tests/test_kernels.py``).

The extension is built by the project's install (``make setup``: ``pip install -e .``, any C
compiler and Python's headers).
"""

from __future__ import annotations

import numpy as np

from omni_sfm.geometry import FloatArray

try:
    from omni_sfm.estimate import _lines  # type: ignore[attr-defined]
except ImportError as exc:  # pragma: no cover - a source tree without the install's build
    raise ImportError(
        "omni_sfm.estimate._lines (the line adjustment's compiled loops) is not built: "
        "install omni-sfm with `make setup` or `pip install -e .` (needs a C compiler)") from exc

LOSS_CODES = {"linear": 0, "huber": 1, "cauchy": 2}
"""The robust losses by name (``solver.RobustLoss`` values) as the kernel numbers them."""


def _f64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


def _i64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int64)


def residuals(R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray, f: np.ndarray,
              t: np.ndarray, B: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``(e (K, 2), u (K, 3))``: each observation's residual ``e = B normalise(u)`` and its
    unnormalised predicted normal ``u = R_f^T ((p_t - c_f) x d_t)`` (``R`` ``(F, 3, 3)``
    world_from_cam, ``c`` ``(F, 3)``, lines ``d, p`` ``(M, 3)``, observation ``k`` of frame
    ``f[k]`` and line ``t[k]`` with residual basis ``B[k]`` ``(2, 3)``)."""
    K = len(f)
    e, u = np.empty((K, 2)), np.empty((K, 3))
    _lines.residuals(len(R), len(d), K, _f64(R), _f64(c), _f64(d), _f64(p), _i64(f), _i64(t),
                     _f64(B), e, u)
    return e, u


def refit_lines(R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray, f: np.ndarray,
                t: np.ndarray, B: FloatArray, free: np.ndarray, loss: str, scale: float,
                iterations: int) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``iterations`` Gauss-Newton iterations of each line alone at the poses ``R, c``
    (:meth:`omni_sfm.estimate.bundle.LineProblem._refit_lines`: each line's cost under
    ``loss`` at ``scale``, the step damped by ``H + mu diag(H)`` per line from ``mu = 1e-6``,
    undone and damped tenfold where the line's cost does not fall, ``free`` ``(M, 4)`` the
    line parameters that may move). Returns new ``d, p`` and the residuals ``e`` and
    predicted normals ``u`` there (as :func:`residuals`)."""
    K = len(f)
    d2, p2 = np.array(d, dtype=np.float64, order="C"), np.array(p, dtype=np.float64, order="C")
    e, u = np.empty((K, 2)), np.empty((K, 3))
    _lines.refit_lines(len(R), len(d), K, _f64(R), _f64(c), d2, p2, _i64(f), _i64(t), _f64(B),
                       np.ascontiguousarray(free, dtype=np.uint8), LOSS_CODES[loss],
                       float(scale), int(iterations), e, u)
    return d2, p2, e, u


def jacobians(R: FloatArray, c: FloatArray, d: FloatArray, p: FloatArray, f: np.ndarray,
              t: np.ndarray, B: FloatArray, u: FloatArray, pose_free: np.ndarray,
              line_free: np.ndarray, b1: FloatArray, b2: FloatArray
              ) -> tuple[FloatArray, FloatArray]:
    """Per observation ``(K, 2, 6)`` d e / d pose (the camera-frame rotation increment, then
    the centre) and ``(K, 2, 4)`` d e / d line (the line moved along its tangent basis ``b1,
    b2`` ``(M, 3)``), columns held by ``pose_free`` ``(F, 6)`` and ``line_free`` ``(M, 4)``
    zero (:meth:`omni_sfm.estimate.bundle.LineProblem.jacobian`; ``u`` as
    :func:`residuals`)."""
    K = len(f)
    Jp, Jl = np.empty((K, 2, 6)), np.empty((K, 2, 4))
    _lines.jacobians(len(R), len(d), K, _f64(R), _f64(c), _f64(d), _f64(p), _i64(f), _i64(t),
                     _f64(B), _f64(u), np.ascontiguousarray(pose_free, dtype=np.uint8),
                     np.ascontiguousarray(line_free, dtype=np.uint8), _f64(b1), _f64(b2), Jp, Jl)
    return Jp, Jl


def normal_blocks(J_pose: FloatArray, J_line: FloatArray, e: FloatArray, w: FloatArray,
                  f: np.ndarray, t: np.ndarray, F: int, M: int
                  ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The blocks of ``J^T W J`` and ``J^T W e`` (weights ``w`` ``(K,)``): ``(F, 6, 6)``,
    ``(M, 4, 4)``, ``(K, 6, 4)``, ``(F, 6)``, ``(M, 4)``, summed over each frame's and each
    line's observations in their order."""
    K = len(f)
    Hpp, Hll, Hpl = np.empty((F, 6, 6)), np.empty((M, 4, 4)), np.empty((K, 6, 4))
    gp, gl = np.empty((F, 6)), np.empty((M, 4))
    _lines.blocks(F, M, K, _f64(J_pose), _f64(J_line), _f64(e), _f64(w), _i64(f), _i64(t),
                  Hpp, Hll, Hpl, gp, gl)
    return Hpp, Hll, Hpl, gp, gl


def eliminate_poses(Hpp: FloatArray, Hpl: FloatArray, gp: FloatArray, f: np.ndarray
                    ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The poses' blocks eliminated from the normal equations: ``L^-1`` ``(F, 6, 6)`` of each
    damped pose block's Cholesky factor (``Hpp = L L^T``), ``G = L_f^-1 Hpl`` ``(K, 6, 4)`` and
    ``L^-1 gp`` ``(F, 6)``. Raises ``numpy.linalg.LinAlgError`` where a block is not positive
    definite (as ``numpy.linalg.cholesky``)."""
    F, K = len(Hpp), len(f)
    Li, G, gpt = np.empty((F, 6, 6)), np.empty((K, 6, 4)), np.empty((F, 6))
    if not _lines.eliminate_poses(F, K, _f64(Hpp), _f64(Hpl), _f64(gp), _i64(f), Li, G, gpt):
        raise np.linalg.LinAlgError("a pose block is not positive definite")
    return Li, G, gpt


def back_substitute(Li: FloatArray, Hpl: FloatArray, gp: FloatArray, dl: FloatArray,
                    f: np.ndarray, t: np.ndarray) -> FloatArray:
    """The poses' step ``(F, 6)`` once the lines' ``dl`` ``(M, 4)`` is known:
    ``Hpp dp = -gp - sum_k Hpl_k dl_t[k]``, through :func:`eliminate_poses`' ``L^-1``."""
    F, K = len(Li), len(f)
    dp = np.empty((F, 6))
    _lines.back_substitute(F, len(dl), K, _f64(Li), _f64(Hpl), _f64(gp), _f64(dl), _i64(f),
                           _i64(t), dp)
    return dp


class PairIndex:
    """Which observations share a frame: the observations in frame order and by line, for
    :func:`block_pattern` and :func:`reduce_lines` (``f`` ``(K,)`` frames in ``0..F-1``,
    ``tc`` ``(K,)`` lines in ``0..Ma-1``)."""

    def __init__(self, f: np.ndarray, tc: np.ndarray, F: int, Ma: int) -> None:
        self.f, self.tc, self.F, self.Ma = _i64(f), _i64(tc), F, Ma
        self.by_frame = _i64(np.argsort(self.f, kind="stable"))
        self.frame_start = _i64(np.searchsorted(self.f[self.by_frame], np.arange(F + 1)))
        self.by_line = _i64(np.argsort(self.tc, kind="stable"))
        self.line_start = _i64(np.searchsorted(self.tc[self.by_line], np.arange(Ma + 1)))
        n = np.diff(self.frame_start)
        self.num_pairs = int(np.sum(n * (n + 1) // 2))
        """Pairs of observations that share a frame (each with itself included)."""


def block_pattern(index: PairIndex) -> tuple[np.ndarray, np.ndarray]:
    """The lines seen in a frame together with each line (itself included): ``ptr``
    ``(Ma + 1,)`` and ``rows``, line ``j``'s sorted in ``rows[ptr[j]:ptr[j + 1]]`` (the block
    rows of block column ``j`` of the reduced system)."""
    F, Ma, K = index.F, index.Ma, len(index.f)
    nb = np.zeros(Ma, np.int64)
    ptr = np.zeros(Ma + 1, np.int64)
    args = (index.f, index.tc, index.by_frame, index.frame_start, index.by_line,
            index.line_start)
    _lines.pattern(F, Ma, K, -1, *args, nb, ptr, np.zeros(0, np.int64))
    ptr[1:] = np.cumsum(nb)
    rows = np.zeros(int(ptr[-1]), np.int64)
    _lines.pattern(F, Ma, K, len(rows), *args, nb, ptr, rows)
    return ptr, rows


def pair_offsets(index: PairIndex, pattern: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Where each pair of a frame's observations adds its block, and its transpose, in the
    data of the block-sparse matrix of ``pattern`` (:func:`block_pattern`): ``(2 P,)`` for
    the ``P`` pairs, in the order :func:`reduce_lines` visits them, found once per problem
    (a binary search each) instead of at every step."""
    ptr, rows = pattern
    offs = np.empty(2 * index.num_pairs, np.int64)
    _lines.pair_offsets(index.F, index.Ma, len(index.f), len(rows), index.num_pairs, index.tc,
                        index.by_frame, index.frame_start, ptr, rows, offs)
    return offs


def reduce_lines(index: PairIndex, G: FloatArray, Hll: FloatArray, gpt: FloatArray,
                 gl: FloatArray, pattern: tuple[np.ndarray, np.ndarray] | None,
                 offsets: np.ndarray | None = None) -> tuple[FloatArray, FloatArray]:
    """``S = diag(Hll) - G^T G`` and ``rhs = -gl + G^T gpt`` (``G`` ``(K, 6, 4)``, one block
    per observation; ``Hll`` ``(Ma, 4, 4)``, ``gpt`` ``(F, 6)``, ``gl`` ``(Ma, 4)``), each
    frame's part summed over the pairs of its observations. ``S`` dense ``(4 Ma, 4 Ma)``
    where ``pattern`` is None, else the data of the block-sparse matrix of
    :func:`block_pattern` (``16 len(rows)`` values: block column ``j``'s column ``4 j + c``
    holds its block rows' 4 rows each; ``offsets``: :func:`pair_offsets` of that pattern,
    worked out here where not given)."""
    F, Ma, K = index.F, index.Ma, len(index.f)
    rhs = np.empty(4 * Ma)
    S: FloatArray
    if pattern is None:
        S, nnz = np.empty((4 * Ma, 4 * Ma)), -1
        ptr = rows = np.zeros(0, np.int64)
        offs = np.zeros(0, np.int64)
    else:
        ptr, rows = pattern
        S = np.empty(16 * len(rows))
        nnz = S.size
        offs = pair_offsets(index, pattern) if offsets is None else offsets
    _lines.reduce(F, Ma, K, nnz, index.num_pairs, _f64(G), index.f, index.tc, index.by_frame,
                  index.frame_start, _f64(Hll), _f64(gpt), _f64(gl), ptr, rows, S, rhs, offs)
    return S, rhs


class BlockCholesky:
    """``S = L L^T`` of the reduced system's block-sparse ``S`` (:func:`block_pattern`'s
    ``ptr, rows``, the data as :func:`reduce_lines` writes it), ``L`` block lower triangular
    (4x4 blocks) in the fill-reducing order ``perm`` (``perm[k]``: the line of block ``k``).
    The factor's structure is worked out here, once; :meth:`factor` fills in the numbers of
    each step's ``S`` and :meth:`solve` solves with them."""

    def __init__(self, pattern: tuple[np.ndarray, np.ndarray], perm: np.ndarray) -> None:
        ptr, rows = _i64(pattern[0]), _i64(pattern[1])
        Ma = len(ptr) - 1
        self.ptr, self.rows, self.Ma = ptr, rows, Ma
        self.perm = _i64(perm)
        self.iperm = np.empty(Ma, np.int64)
        self.iperm[self.perm] = np.arange(Ma)
        parent = np.empty(Ma, np.int64)
        self.Lp, self.Rp = np.empty(Ma + 1, np.int64), np.empty(Ma + 1, np.int64)
        z = np.zeros(0, np.int64)
        args = (ptr, rows, self.perm, self.iperm, parent)
        _lines.chol_analyse(Ma, len(rows), -1, *args, self.Lp, self.Rp, z, z)
        self.nnz = int(self.Lp[-1])
        """Blocks of ``L`` (the diagonal included)."""
        self.Li = np.empty(self.nnz, np.int64)
        self.RR = np.empty(2 * (self.nnz - Ma), np.int64)
        _lines.chol_analyse(Ma, len(rows), self.nnz, *args, self.Lp, self.Rp, self.Li, self.RR)
        self.Lx = np.empty(16 * self.nnz)
        self._work = np.empty(16 * max(Ma, 1))

    def factor(self, S: np.ndarray) -> bool:
        """The factor of ``S`` (the block-sparse data); False where ``S`` is not positive
        definite."""
        return bool(_lines.chol_factor(self.Ma, len(self.rows), self.nnz, self.ptr, self.rows,
                                       _f64(S), self.perm, self.iperm, self.Lp, self.Li,
                                       self.Rp, self.RR, self.Lx, self._work))

    def solve(self, b: np.ndarray) -> FloatArray:
        """``S^-1 b`` for ``b`` ``(4 Ma,)``, with the last :meth:`factor`'s numbers."""
        x, y = np.empty(4 * self.Ma), np.empty(4 * self.Ma)
        _lines.chol_solve(self.Ma, self.nnz, self.perm, self.Lp, self.Li, self.Lx, _f64(b), x, y)
        return x


def resect(B: FloatArray, d: FloatArray, p: FloatArray, m: FloatArray, D: FloatArray,
           R: FloatArray, c: FloatArray, loss: str, scale: float, iterations: int,
           tolerance: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """One camera's pose from lines held (:func:`omni_sfm.estimate.bundle.resect_pose`):
    Levenberg-Marquardt over the camera-frame rotation increment and the centre from ``R``
    ``(3, 3)`` world_from_cam, ``c`` ``(3,)``, as :func:`omni_sfm.solver.levenberg_marquardt`
    runs it (first damping 1e-4, each 3-vector's diagonal its mean, at most ``iterations``,
    stops on a relative decrease below ``tolerance``) on the residuals ``B normalise(u)`` of
    the lines ``d, p`` ``(K, 3)`` (residual bases ``B`` ``(K, 2, 3)``) and ``m . R^T D`` of the
    direction-only normals ``m`` of world directions ``D`` ``(J, 3)``, under ``loss`` at
    ``scale``. Returns ``(R, c, e, u)``: the pose, the residuals ``(K + J, 2)`` and the
    predicted normals ``(K, 3)`` at it."""
    K, J = len(d), len(m)
    R_out, c_out = _f64(R).copy(), _f64(c).copy()
    e, u = np.empty((K + J, 2)), np.empty((K, 3))
    _lines.resect(K, J, _f64(B), _f64(d), _f64(p), _f64(m), _f64(D), LOSS_CODES[loss],
                  float(scale), R_out, c_out, int(iterations), float(tolerance), e, u)
    return R_out, c_out, e, u
