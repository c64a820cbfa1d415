"""ABC and PSO on standard test functions, beside scipy's differential evolution at the same
number of objective evaluations (the DE run gets at least as many)."""

import numpy as np
import pytest
from scipy.optimize import differential_evolution, rosen

from ipmc_model.bee_colony import minimize_abc
from ipmc_model.pso import minimize_pso


def sphere(x):
    return float(np.sum(np.asarray(x) ** 2))


def rastrigin(x):
    x = np.asarray(x)
    return float(10 * x.size + np.sum(x**2 - 10 * np.cos(2 * np.pi * x)))


CASES = [
    ("sphere", sphere, [(-5.0, 5.0)] * 3, 1e-3),
    ("rosenbrock", rosen, [(-2.0, 2.0)] * 2, 1e-2),
    ("rastrigin", rastrigin, [(-5.12, 5.12)] * 2, 1e-2),
]


def _de(fun, bounds, budget, seed):
    d = len(bounds)
    popsize = 10
    maxiter = max(1, budget // (popsize * d) - 1)
    return differential_evolution(fun, bounds, popsize=popsize, maxiter=maxiter, tol=0,
                                  polish=False, seed=seed)


@pytest.mark.parametrize("name,fun,bounds,tol", CASES)
def test_abc_matches_differential_evolution(name, fun, bounds, tol):
    res = minimize_abc(fun, bounds, n_sources=20, n_cycles=60, seed=1)
    de = _de(fun, bounds, res.nfev, seed=1)
    assert de.nfev <= res.nfev + 10 * len(bounds) * 10
    assert res.fun < tol, f"ABC on {name}: {res.fun}"
    assert res.fun <= max(10 * de.fun, tol), f"ABC {res.fun} vs DE {de.fun} on {name}"


@pytest.mark.parametrize("name,fun,bounds,tol", CASES)
def test_pso_matches_differential_evolution(name, fun, bounds, tol):
    res = minimize_pso(fun, bounds, n_particles=20, n_iter=100, seed=1)
    de = _de(fun, bounds, res.nfev, seed=1)
    assert res.fun < tol, f"PSO on {name}: {res.fun}"
    assert res.fun <= max(10 * de.fun, tol), f"PSO {res.fun} vs DE {de.fun} on {name}"


def test_optimizers_reproducible_with_seed():
    a = minimize_abc(rastrigin, [(-5.12, 5.12)] * 2, n_sources=10, n_cycles=10, seed=7)
    b = minimize_abc(rastrigin, [(-5.12, 5.12)] * 2, n_sources=10, n_cycles=10, seed=7)
    np.testing.assert_array_equal(a.x, b.x)
    c = minimize_pso(rastrigin, [(-5.12, 5.12)] * 2, n_particles=10, n_iter=10, seed=7)
    d = minimize_pso(rastrigin, [(-5.12, 5.12)] * 2, n_particles=10, n_iter=10, seed=7)
    np.testing.assert_array_equal(c.x, d.x)


def test_optimizers_vectorized_equals_scalar():
    def vec(x):
        return np.sum(x**2, axis=1)

    a = minimize_pso(sphere, [(-1, 1)] * 2, n_particles=8, n_iter=5, seed=0)
    b = minimize_pso(vec, [(-1, 1)] * 2, n_particles=8, n_iter=5, seed=0, vectorized=True)
    np.testing.assert_allclose(a.x, b.x)


def test_optimizers_reject_bad_bounds():
    with pytest.raises(ValueError, match="high > low"):
        minimize_abc(sphere, [(1.0, 0.0)])
    with pytest.raises(ValueError, match="high > low"):
        minimize_pso(sphere, [(0.0, np.inf)])
