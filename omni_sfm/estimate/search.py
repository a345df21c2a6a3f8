"""Global minimisation of a 1-DOF cost: a coarse grid that finds the basins, then Brent polishing.

The paper searches its 1-DOF costs (docs/method.md §4-§5) exhaustively on a fixed fine grid. Here a
coarse grid, evaluated in one vectorised call, brackets every local minimum it sees; the few best
brackets are polished by Brent's method (parabolic interpolation with golden-section safeguard)
to a tolerance near machine precision. The grid only has to be finer than the narrowest basin
that could hold the global minimum, so the search is as global as the exhaustive one and much
more precise.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from omni_sfm.geometry import FloatArray

VectorCost = Callable[[FloatArray], FloatArray]
"""A cost evaluated at many parameter values at once: ``(G,) -> (G,)``."""


@dataclass(frozen=True)
class SearchResult:
    """Outcome of :func:`global_minimize_1d`.

    Attributes:
        x: the minimiser (for a periodic search, wrapped into ``[lo, hi)``).
        fx: the cost at ``x``.
        num_evals: cost evaluations in total (grid points count one each).
        grid_x: ``(G,)`` the coarse grid.
        grid_f: ``(G,)`` the cost on the coarse grid (to inspect the landscape).
        minima: every polished local minimum ``(x, fx)``, lowest first (``x`` wrapped like
            ``x``); the first is ``(x, fx)``.
    """

    x: float
    fx: float
    num_evals: int
    grid_x: FloatArray
    grid_f: FloatArray
    minima: tuple[tuple[float, float], ...] = ()


def global_minimize_1d(cost: VectorCost, lo: float, hi: float, *, num_grid: int = 64,
                       periodic: bool = False, num_starts: int = 3, xtol: float = 1e-12,
                       max_iter: int = 200) -> SearchResult:
    """Global minimum of ``cost`` on ``[lo, hi]`` (or the circle ``[lo, hi)`` if ``periodic``).

    Args:
        cost: vectorised cost ``(G,) -> (G,)``; non-finite values count as ``+inf``.
        lo, hi: the search interval.
        num_grid: coarse grid points (for a periodic search they are spaced ``(hi-lo)/num_grid``
            and ``hi`` is not sampled, being ``lo``).
        periodic: the cost has period ``hi - lo``.
        num_starts: how many of the lowest grid minima are polished.
        xtol: absolute tolerance on ``x`` of the polishing.
        max_iter: iteration cap of each polishing run.

    Returns:
        the best polished minimum, never worse than the best grid point.
    """
    if not hi > lo or num_grid < 3 or num_starts < 1:
        raise ValueError(f"bad search set-up: {lo=} {hi=} {num_grid=} {num_starts=}")
    xs, fs, cand = _grid(cost, lo, hi, num_grid, periodic)
    step = xs[1] - xs[0]
    best_x, best_f = float(xs[int(np.argmin(fs))]), float(np.min(fs))
    evals = num_grid
    if not np.isfinite(best_f):
        return SearchResult(best_x, best_f, evals, xs, fs, ((best_x, best_f),))
    found: list[tuple[float, float]] = [(best_x, best_f)]

    count = [0]

    def scalar(x: float) -> float:
        count[0] += 1
        val = float(np.asarray(cost(np.array([x], dtype=np.float64)))[0])
        return val if np.isfinite(val) else np.inf

    for g in cand[np.argsort(fs[cand], kind="stable")][:num_starts]:
        x0 = float(xs[g])
        a, c = x0 - step, x0 + step
        if not periodic:
            a, c = max(a, lo), min(c, hi)
        fa = fs[(g - 1) % num_grid] if (periodic or g > 0) else np.inf
        fc = fs[(g + 1) % num_grid] if (periodic or g < num_grid - 1) else np.inf
        if a == x0 or c == x0:
            # a minimum at the end of a closed interval: polish on the one-sided bracket
            x, f = _golden_edge(scalar, x0, a if a != x0 else c, xtol, max_iter)
        elif fs[g] < fa and fs[g] < fc:
            x, f = _brent(scalar, a, x0, c, float(fs[g]), xtol, max_iter)
        else:
            # a plateau on the grid: a bounded golden-section search over the bracket
            x, f = _golden(scalar, a, c, xtol, max_iter)
        if periodic or lo <= x <= hi:
            found.append((float(x), float(f)))
    evals += count[0]
    if periodic:
        found = [(lo + float(np.mod(x - lo, hi - lo)), f) for x, f in found]
    minima = _distinct(found, lo, hi, periodic, 0.5 * step)
    return SearchResult(minima[0][0], minima[0][1], evals, xs, fs, tuple(minima))


def _distinct(found: list[tuple[float, float]], lo: float, hi: float, periodic: bool,
              min_dist: float) -> list[tuple[float, float]]:
    """The ``(x, f)`` minima ``found``, lowest first, each at least ``min_dist`` from every
    lower one (the raw grid point is dropped where polishing found the same basin)."""
    minima: list[tuple[float, float]] = []
    for x, f in sorted(found, key=lambda xf: xf[1]):
        if all(_dist(x, y, lo, hi, periodic) > min_dist for y, _ in minima):
            minima.append((x, f))
    return minima


def _grid(cost: VectorCost, lo: float, hi: float, num_grid: int, periodic: bool
          ) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """``(xs, fs, cand)``: the coarse grid of :func:`global_minimize_1d`, its costs
    (non-finite ones as ``+inf``) and the indices of its local minima with a finite cost."""
    if periodic:
        xs = lo + (hi - lo) * np.arange(num_grid) / num_grid
    else:
        xs = np.linspace(lo, hi, num_grid)
    fs = np.asarray(cost(xs), dtype=np.float64)
    if fs.shape != xs.shape:
        raise ValueError(f"cost returned shape {fs.shape}, expected {xs.shape}")
    fs = np.where(np.isfinite(fs), fs, np.inf)
    if periodic:
        prev, nxt = np.roll(fs, 1), np.roll(fs, -1)
        is_min = (fs <= prev) & (fs <= nxt)
    else:
        prev = np.concatenate([[np.inf], fs[:-1]])
        nxt = np.concatenate([fs[1:], [np.inf]])
        is_min = (fs <= prev) & (fs <= nxt)
    return xs, fs, np.flatnonzero(is_min & np.isfinite(fs))


def _dist(x: float, y: float, lo: float, hi: float, periodic: bool) -> float:
    d = abs(x - y)
    return min(d, (hi - lo) - d) if periodic else d


_INV_PHI = (np.sqrt(5.0) - 1.0) / 2.0
_CGOLD = 1.0 - _INV_PHI


def _brent(f: Callable[[float], float], a: float, x: float, b: float, fx: float, xtol: float,
           max_iter: int) -> tuple[float, float]:
    """Brent's minimisation in the bracket ``a < x < b`` with ``f(x) = fx`` below both ends.

    Parabolic interpolation through the three best points, golden section where the parabola
    is not trusted (Brent 1973, as in Numerical Recipes' ``brent``); the bracket's known value
    is reused, so no evaluation is spent re-bracketing. ``xtol`` is absolute.
    """
    w = v = x
    fw = fv = fx
    d = e = 0.0
    for _ in range(max_iter):
        xm = 0.5 * (a + b)
        tol1 = max(xtol, 4e-16 * abs(x))
        tol2 = 2.0 * tol1
        if abs(x - xm) <= tol2 - 0.5 * (b - a):
            break
        golden = True
        if abs(e) > tol1:
            r = (x - w) * (fx - fv)
            q = (x - v) * (fx - fw)
            p = (x - v) * q - (x - w) * r
            q = 2.0 * (q - r)
            if q > 0.0:
                p = -p
            q = abs(q)
            etemp, e = e, d
            if abs(p) < abs(0.5 * q * etemp) and q * (a - x) < p < q * (b - x):
                d = p / q
                u = x + d
                if u - a < tol2 or b - u < tol2:
                    d = tol1 if xm >= x else -tol1
                golden = False
        if golden:
            e = (a - x) if x >= xm else (b - x)
            d = _CGOLD * e
        u = x + d if abs(d) >= tol1 else x + (tol1 if d >= 0 else -tol1)
        fu = f(u)
        if fu <= fx:
            if u >= x:
                a = x
            else:
                b = x
            v, w, x = w, x, u
            fv, fw, fx = fw, fx, fu
        else:
            if u < x:
                a = u
            else:
                b = u
            if fu <= fw or w == x:
                v, w = w, u
                fv, fw = fw, fu
            elif fu <= fv or v in (x, w):
                v, fv = u, fu
    return x, fx


def _golden(f: Callable[[float], float], a: float, b: float, xtol: float,
            max_iter: int) -> tuple[float, float]:
    """Golden-section minimum of ``f`` on ``[a, b]``."""
    c, d = b - _INV_PHI * (b - a), a + _INV_PHI * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(max_iter):
        if abs(b - a) < xtol:
            break
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - _INV_PHI * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + _INV_PHI * (b - a)
            fd = f(d)
    return (c, fc) if fc < fd else (d, fd)


def _golden_edge(f: Callable[[float], float], x0: float, x1: float, xtol: float,
                 max_iter: int) -> tuple[float, float]:
    """Minimum near the interval end ``x0`` on the segment towards ``x1``."""
    lo, hi = min(x0, x1), max(x0, x1)
    x, fx = _golden(f, lo, hi, xtol, max_iter)
    f0 = f(x0)
    return (x, fx) if fx < f0 else (x0, f0)
