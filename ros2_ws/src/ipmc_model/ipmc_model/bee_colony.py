"""Artificial bee colony optimiser (Karaboga 2005; paper section 3.4, Eq. 16-18).

Each cycle has three phases: employed bees try one neighbour move per food source (Eq. 16,
greedy selection), onlooker bees pick sources with probability proportional to their fitness
(Eq. 17) and try a move there, and a scout replaces the most exhausted source (no improvement
for ``limit`` trials) by a random one (Eq. 18). Seeded and reproducible. The module is not
named ``abc`` because that shadows the standard library's abstract base classes.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import OptimizeResult

from .pso import _check_bounds, _evaluator


def _fitness(f: np.ndarray) -> np.ndarray:
    # Karaboga's fitness of a cost: 1 / (1 + f) for f >= 0, 1 + |f| otherwise.
    return np.where(f >= 0, 1.0 / (1.0 + np.where(f >= 0, f, 0.0)), 1.0 + np.abs(f))


def minimize_abc(
    fun,
    bounds,
    *,
    n_sources: int = 100,
    n_cycles: int = 100,
    limit: int | None = None,
    seed: int | None = None,
    vectorized: bool = False,
    callback=None,
) -> OptimizeResult:
    """Minimise ``fun`` over a box with an artificial bee colony.

    Parameters
    ----------
    fun : callable
        ``fun(x) -> float`` for x of shape (d,), or with ``vectorized=True``
        ``fun(X) -> ndarray (P,)``. Non-finite values count as +inf.
    bounds : sequence of (low, high), length d
        Search box (for LSSVM tuning: log10 C and log10 sigma).
    n_sources : int
        Number of food sources = employed bees = onlooker bees (paper: 100).
    n_cycles : int
        Number of cycles (paper: 100). Evaluations: about ``n_sources * (2 n_cycles + 1)``.
    limit : int, optional
        Trials without improvement before a source is abandoned; default ``n_sources * d``.
    seed : int or None
        Seed of ``numpy.random.default_rng``.
    callback : callable, optional
        ``callback(cycle, best_fun)`` after each cycle.

    Returns
    -------
    scipy.optimize.OptimizeResult
        ``x`` (d,), ``fun``, ``nfev``, ``nit``, ``history`` (best cost after each cycle).
    """
    lo, hi = _check_bounds(bounds)
    if n_sources < 2 or n_cycles < 1:
        raise ValueError(f"need n_sources >= 2 and n_cycles >= 1, got {n_sources}, {n_cycles}")
    rng = np.random.default_rng(seed)
    evaluate, count = _evaluator(fun, vectorized)
    d = lo.size
    limit = n_sources * d if limit is None else int(limit)
    x = lo + rng.random((n_sources, d)) * (hi - lo)
    f = evaluate(x)
    trials = np.zeros(n_sources, dtype=int)
    b = int(np.argmin(f))
    best_x, best_f = x[b].copy(), float(f[b])

    def neighbours(idx: np.ndarray) -> np.ndarray:
        # Eq. 16: x'_ij = x_ij + phi (x_ij - x_kj), one random dimension j, partner k != i.
        k = rng.integers(0, n_sources - 1, idx.size)
        k = k + (k >= idx)
        j = rng.integers(0, d, idx.size)
        phi = rng.uniform(-1.0, 1.0, idx.size)
        cand = x[idx].copy()
        rows = np.arange(idx.size)
        cand[rows, j] = x[idx, j] + phi * (x[idx, j] - x[k, j])
        return np.clip(cand, lo, hi)

    def greedy(idx: np.ndarray, cand: np.ndarray, fc: np.ndarray) -> None:
        for i, xc, fi in zip(idx, cand, fc, strict=True):
            if fi < f[i]:
                x[i], f[i], trials[i] = xc, fi, 0
            else:
                trials[i] += 1

    history = []
    all_idx = np.arange(n_sources)
    for cycle in range(n_cycles):
        cand = neighbours(all_idx)  # employed bees
        greedy(all_idx, cand, evaluate(cand))
        p = _fitness(f)
        p = p / p.sum()  # Eq. 17
        idx = rng.choice(n_sources, size=n_sources, p=p)  # onlooker bees
        cand = neighbours(idx)
        greedy(idx, cand, evaluate(cand))
        b = int(np.argmin(f))
        if f[b] < best_f:
            best_x, best_f = x[b].copy(), float(f[b])
        s = int(np.argmax(trials))  # scout bee, Eq. 18
        if trials[s] > limit:
            x[s] = lo + rng.random(d) * (hi - lo)
            f[s] = evaluate(x[s : s + 1])[0]
            trials[s] = 0
            if f[s] < best_f:
                best_x, best_f = x[s].copy(), float(f[s])
        history.append(best_f)
        if callback is not None:
            callback(cycle + 1, best_f)
    return OptimizeResult(
        x=best_x, fun=best_f, nfev=count[0], nit=n_cycles, history=np.array(history), success=True
    )
