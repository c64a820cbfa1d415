"""Prandtl-Ishlinskii (PI) hysteresis model: a weighted sum of play operators (paper Eq. 2).

The PI model maps an input voltage u (V) to a displacement y (mm):

    y_k = sum_i a_i F_{r_i}[u]_k + c,    F_r[u]_k = max(u_k - r, min(u_k + r, F_r[u]_{k-1}))

with thresholds r_i >= 0 (never negative: a play operator with r < 0 is not a hysteresis
operator), weights a_i and an optional offset c. Two fits are offered:

* ``method="pso"``: the paper's route, particle swarm over the 2 n weights and thresholds
  (100 particles, 100 iterations, linearly decreasing inertia weight, Eq. 3-6).
* ``method="nnls"``: the better-posed route, thresholds on a uniform grid r_i = i r_max / n
  (i = 0..n-1, so r_0 = 0 is the linear term) and weights by non-negative least squares.
  Positive weights make the model invertible: :meth:`PrandtlIshlinskii.inverse` returns the
  analytic inverse (Kuhnen's formula), itself a PI model.

The PI model has no output feedback, so its one-step prediction equals its free run.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

from ipmc_driver.validation import as_signal, same_length

from .errors import NotFittedError, check_fitted
from .pso import minimize_pso


def play_operators(u, thresholds, initial_state=None) -> np.ndarray:
    """Outputs of play operators (paper Eq. 2) driven by one input.

    Parameters
    ----------
    u : array_like, shape (N,)
        Input signal.
    thresholds : array_like, shape (n,) or (P, n)
        Thresholds r >= 0; a 2-D array evaluates P sets of operators at once (used by PSO).
    initial_state : array_like, shape like ``thresholds``, optional
        Operator states before the first sample; default 0 (so F_r[u]_0 = f_r(u_0, 0)).

    Returns
    -------
    ndarray, shape (N, n) or (N, P, n)
        ``out[k]`` is the operator output at sample k.
    """
    u = as_signal("u", u)
    r = np.asarray(thresholds, dtype=float)
    if np.any(r < 0) or not np.all(np.isfinite(r)):
        raise ValueError("thresholds must be finite and >= 0 (a play threshold is a half-width)")
    w = np.zeros_like(r) if initial_state is None else np.array(initial_state, dtype=float)
    if w.shape != r.shape:
        raise ValueError(f"initial_state must have shape {r.shape}, got {w.shape}")
    out = np.empty((u.size,) + r.shape)
    for k, uk in enumerate(u):
        w = np.maximum(uk - r, np.minimum(uk + r, w))
        out[k] = w
    return out


class PrandtlIshlinskii:
    """Prandtl-Ishlinskii hysteresis model fitted from input u (V) and output y (mm).

    Parameters
    ----------
    n_operators : int
        Number of play operators n (paper: 10).
    method : {"nnls", "pso"}
        "nnls": thresholds on a grid, non-negative weights by NNLS (invertible);
        "pso": weights and thresholds by particle swarm, as in the paper.
    r_max : float, optional
        Largest threshold; default max|u| of the training input.
    min_linear_fraction : float
        NNLS only: the weight of the zero-threshold (linear) operator is kept at least this
        fraction of the sum of weights, so the analytic inverse exists and its gain stays
        bounded (at most 1 / fraction times the inverse of the sum of weights). 0 = plain NNLS.
    fit_offset : bool
        Fit a constant output offset c (mm).
    weight_bounds : (float, float)
        PSO search interval of the weights (paper: [-10, 10]).
    n_particles, n_iter : int
        PSO size (paper: 100 and 100).
    seed : int or None
        Seed of the PSO.
    progress : callable, optional
        ``progress(iteration, best_rmse)`` called by the PSO each iteration.

    Attributes
    ----------
    thresholds_ : ndarray, shape (n,)
    weights_ : ndarray, shape (n,)
    offset_ : float
    train_rmse_ : float
        Training RMSE (mm, free-run = one-step for PI).
    """

    def __init__(
        self,
        n_operators: int = 10,
        method: str = "nnls",
        r_max: float | None = None,
        min_linear_fraction: float = 0.05,
        fit_offset: bool = True,
        weight_bounds: tuple[float, float] = (-10.0, 10.0),
        n_particles: int = 100,
        n_iter: int = 100,
        seed: int | None = 0,
        progress=None,
    ):
        self.n_operators = n_operators
        self.method = method
        self.r_max = r_max
        self.min_linear_fraction = min_linear_fraction
        self.fit_offset = fit_offset
        self.weight_bounds = weight_bounds
        self.n_particles = n_particles
        self.n_iter = n_iter
        self.seed = seed
        self.progress = progress
        self.thresholds_ = None
        self.weights_ = None
        self.offset_ = None

    # -- fitting -----------------------------------------------------------------------------
    def fit(self, u, y) -> PrandtlIshlinskii:
        """Fit weights and thresholds to input ``u`` (V) and output ``y`` (mm); returns self."""
        n = int(self.n_operators)
        if n < 1:
            raise ValueError(f"n_operators must be >= 1, got {self.n_operators}")
        u = as_signal("u", u, min_length=n + 1)
        y = as_signal("y", y, min_length=n + 1)
        same_length(u=u, y=y)
        if np.ptp(u) == 0.0:
            raise ValueError("u is constant; a hysteresis model needs a varying input")
        r_max = float(np.max(np.abs(u))) if self.r_max is None else float(self.r_max)
        if not r_max > 0:
            raise ValueError(f"r_max must be > 0, got {r_max}")
        if self.method == "nnls":
            self._fit_nnls(u, y, n, r_max)
        elif self.method == "pso":
            self._fit_pso(u, y, n, r_max)
        else:
            raise ValueError(f"method must be 'nnls' or 'pso', got {self.method!r}")
        self.train_rmse_ = float(np.sqrt(np.mean((self.simulate(u) - y) ** 2)))
        return self

    def _fit_nnls(self, u, y, n, r_max):
        r = np.arange(n) * (r_max / n)
        phi = play_operators(u, r)
        f = float(self.min_linear_fraction)
        if not 0.0 <= f < 1.0:
            raise ValueError(f"min_linear_fraction must be in [0, 1), got {f}")
        # a_0 = c sum_{i>=1} a_i + s with s >= 0 and c = f / (1 - f) keeps a_0 >= f sum(a)
        # while every unknown stays non-negative, so plain NNLS still applies.
        c = f / (1.0 - f)
        design = phi.copy()
        design[:, 1:] += c * phi[:, :1]
        cols = [design]
        if self.fit_offset:
            # nnls has no free variables: a signed offset is the difference of two columns.
            cols.append(np.ones((u.size, 1)))
            cols.append(-np.ones((u.size, 1)))
        a_full, _ = nnls(np.hstack(cols), y, maxiter=50 * (n + 2))
        a = a_full[:n].copy()
        a[0] += c * a[1:].sum()
        self.thresholds_ = r
        self.weights_ = a
        self.offset_ = float(a_full[n] - a_full[n + 1]) if self.fit_offset else 0.0

    def _fit_pso(self, u, y, n, r_max):
        lo_w, hi_w = (float(b) for b in self.weight_bounds)
        bounds = [(lo_w, hi_w)] * n + [(0.0, r_max)] * n
        y_mean = y.mean()

        def cost(pos):  # pos: (P, 2n) -> (P,) RMSE, Eq. 3
            a, r = pos[:, :n], pos[:, n:]
            out = play_operators(u, np.clip(r, 0.0, None))  # (N, P, n)
            y_hat = np.einsum("kpn,pn->kp", out, a)
            if self.fit_offset:
                y_hat = y_hat + (y_mean - y_hat.mean(axis=0))
            return np.sqrt(np.mean((y_hat - y[:, None]) ** 2, axis=0))

        res = minimize_pso(
            cost,
            bounds,
            n_particles=self.n_particles,
            n_iter=self.n_iter,
            seed=self.seed,
            vectorized=True,
            callback=self.progress,
        )
        a, r = res.x[:n], np.clip(res.x[n:], 0.0, None)
        order = np.argsort(r)
        self.weights_, self.thresholds_ = a[order], r[order]
        if self.fit_offset:
            y_fit = play_operators(u, self.thresholds_) @ self.weights_
            self.offset_ = float(y_mean - y_fit.mean())
        else:
            self.offset_ = 0.0
        self.pso_result_ = res

    # -- use ---------------------------------------------------------------------------------
    def simulate(self, u) -> np.ndarray:
        """Free-run output y (mm), shape (N,), from input ``u`` (V), operators starting at 0."""
        check_fitted(self, "weights_")
        u = as_signal("u", u)
        return play_operators(u, self.thresholds_) @ self.weights_ + self.offset_

    def predict(self, u, y=None) -> np.ndarray:
        """One-step prediction; the PI model has no output feedback, so this equals simulate."""
        return self.simulate(u)

    def inverse(self) -> InversePrandtlIshlinskii:
        """Analytic inverse (Kuhnen): a PI compensator mapping desired y (mm) to u (V).

        Needs a zero threshold with a positive weight and non-negative other weights (the
        ``method="nnls"`` fit gives this). Raises ``ValueError`` otherwise.
        """
        check_fitted(self, "weights_")
        r, a = np.asarray(self.thresholds_), np.asarray(self.weights_)
        order = np.argsort(r)
        r, a = r[order], a[order]
        if r[0] > 1e-12 * max(1.0, r[-1]) or a[0] <= 0:
            raise ValueError(
                "the analytic PI inverse needs a zero-threshold operator with a positive weight; "
                "fit with method='nnls'"
            )
        if np.any(a < 0):
            raise ValueError(
                "the analytic PI inverse needs non-negative weights; fit with method='nnls'"
            )
        partial = np.cumsum(a)  # a_0 + ... + a_j
        r_inv = np.array([np.sum(a[: j + 1] * (r[j] - r[: j + 1])) for j in range(r.size)])
        a_inv = np.empty_like(a)
        a_inv[0] = 1.0 / a[0]
        a_inv[1:] = -a[1:] / (partial[1:] * partial[:-1])
        return InversePrandtlIshlinskii(r_inv, a_inv, self.offset_)

    def get_params(self) -> dict:
        """Constructor hyperparameters (for persistence)."""
        return {
            "n_operators": self.n_operators,
            "method": self.method,
            "r_max": self.r_max,
            "min_linear_fraction": self.min_linear_fraction,
            "fit_offset": self.fit_offset,
            "weight_bounds": list(self.weight_bounds),
            "n_particles": self.n_particles,
            "n_iter": self.n_iter,
            "seed": self.seed,
        }


class InversePrandtlIshlinskii:
    """Inverse PI compensator u = P^-1[y_desired - c] (analytic, Kuhnen's formula).

    Build it with :meth:`PrandtlIshlinskii.inverse`. ``simulate`` maps a whole desired
    trajectory (mm) to voltages (V); ``step`` does one sample at a time for a controller and
    keeps the operator states between calls (``reset`` zeroes them).

    Parameters
    ----------
    thresholds : ndarray, shape (n,)
        Inverse thresholds (mm), sorted, first 0.
    weights : ndarray, shape (n,)
        Inverse weights (V/mm).
    offset : float
        Offset c (mm) of the forward model.
    """

    def __init__(self, thresholds, weights, offset: float = 0.0):
        self.thresholds = np.asarray(thresholds, dtype=float)
        self.weights = np.asarray(weights, dtype=float)
        self.offset = float(offset)
        self.reset()

    def reset(self) -> None:
        """Zero the operator states (the rest state of the forward model)."""
        self._state = np.zeros_like(self.thresholds)

    def simulate(self, y_desired) -> np.ndarray:
        """Voltages u (V), shape (N,), that make the forward PI model follow ``y_desired`` (mm)."""
        y = as_signal("y_desired", y_desired)
        return play_operators(y - self.offset, self.thresholds) @ self.weights

    def step(self, y_desired_mm: float) -> float:
        """One compensator step: desired displacement (mm) -> voltage (V); keeps state."""
        v = float(y_desired_mm) - self.offset
        r = self.thresholds
        self._state = np.maximum(v - r, np.minimum(v + r, self._state))
        return float(self._state @ self.weights)


__all__ = [
    "InversePrandtlIshlinskii",
    "NotFittedError",
    "PrandtlIshlinskii",
    "play_operators",
]
