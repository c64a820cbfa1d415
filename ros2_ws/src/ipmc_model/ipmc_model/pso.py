"""Particle swarm optimisation with a linearly decreasing inertia weight (paper Eq. 4-6).

Seeded and reproducible: the same ``seed`` gives the same result. The objective may be
evaluated one particle at a time or, with ``vectorized=True``, on the whole swarm at once.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import OptimizeResult


def _check_bounds(bounds) -> tuple[np.ndarray, np.ndarray]:
    b = np.asarray(bounds, dtype=float)
    if b.ndim != 2 or b.shape[1] != 2 or b.shape[0] < 1:
        raise ValueError(f"bounds must be a sequence of (low, high) pairs, got shape {b.shape}")
    lo, hi = b[:, 0], b[:, 1]
    if not (np.all(np.isfinite(b)) and np.all(hi > lo)):
        raise ValueError("bounds must be finite with high > low in every dimension")
    return lo, hi


def _evaluator(fun, vectorized: bool):
    """Return f(X: (P, d)) -> (P,) with non-finite costs replaced by +inf, and a counter."""
    count = [0]

    def evaluate(x: np.ndarray) -> np.ndarray:
        count[0] += x.shape[0]
        if vectorized:
            f = np.asarray(fun(x), dtype=float).reshape(x.shape[0])
        else:
            f = np.array([float(fun(xi)) for xi in x])
        return np.where(np.isfinite(f), f, np.inf)

    return evaluate, count


def minimize_pso(
    fun,
    bounds,
    *,
    n_particles: int = 100,
    n_iter: int = 100,
    w_max: float = 0.9,
    w_min: float = 0.4,
    c1: float = 2.0,
    c2: float = 2.0,
    v_max_fraction: float = 0.2,
    seed: int | None = None,
    vectorized: bool = False,
    callback=None,
) -> OptimizeResult:
    """Minimise ``fun`` over a box with a particle swarm.

    Parameters
    ----------
    fun : callable
        ``fun(x) -> float`` for x of shape (d,), or with ``vectorized=True``
        ``fun(X) -> ndarray (P,)`` for X of shape (P, d). Non-finite values count as +inf.
    bounds : sequence of (low, high), length d
        Search box; particles are clipped to it.
    n_particles, n_iter : int
        Swarm size and number of iterations (paper: 100, 100).
    w_max, w_min : float
        Inertia weight, decreasing linearly from ``w_max`` to ``w_min`` (Eq. 5).
    c1, c2 : float
        Cognitive and social acceleration constants (Eq. 4).
    v_max_fraction : float
        Velocity limit as a fraction of each dimension's range.
    seed : int or None
        Seed of ``numpy.random.default_rng``.
    callback : callable, optional
        ``callback(iteration, best_fun)`` after each iteration.

    Returns
    -------
    scipy.optimize.OptimizeResult
        ``x`` (d,), ``fun``, ``nfev``, ``nit``, ``history`` (best cost after each iteration).
    """
    lo, hi = _check_bounds(bounds)
    if n_particles < 2 or n_iter < 1:
        raise ValueError(f"need n_particles >= 2 and n_iter >= 1, got {n_particles}, {n_iter}")
    rng = np.random.default_rng(seed)
    evaluate, count = _evaluator(fun, vectorized)
    d = lo.size
    span = hi - lo
    v_max = v_max_fraction * span
    x = lo + rng.random((n_particles, d)) * span
    v = rng.uniform(-1.0, 1.0, (n_particles, d)) * v_max
    f = evaluate(x)
    p_best, p_f = x.copy(), f.copy()
    g = int(np.argmin(p_f))
    g_best, g_f = p_best[g].copy(), float(p_f[g])
    history = []
    for t in range(n_iter):
        w = w_max - t * (w_max - w_min) / max(n_iter - 1, 1)
        r1 = rng.random((n_particles, d))
        r2 = rng.random((n_particles, d))
        v = w * v + c1 * r1 * (p_best - x) + c2 * r2 * (g_best - x)
        v = np.clip(v, -v_max, v_max)
        x = np.clip(x + v, lo, hi)
        f = evaluate(x)
        better = f < p_f
        p_best[better], p_f[better] = x[better], f[better]
        g = int(np.argmin(p_f))
        if p_f[g] < g_f:
            g_best, g_f = p_best[g].copy(), float(p_f[g])
        history.append(g_f)
        if callback is not None:
            callback(t + 1, g_f)
    return OptimizeResult(
        x=g_best, fun=g_f, nfev=count[0], nit=n_iter, history=np.array(history), success=True
    )
