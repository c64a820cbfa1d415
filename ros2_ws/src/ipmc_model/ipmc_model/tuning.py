"""Hyperparameter tuning of an LSSVM-NARX model (C, sigma) by artificial bee colony (paper 3.4).

The search runs in log10 space of C and sigma. The record is split chronologically: the first
``1 - val_fraction`` fits the model, the last ``val_fraction`` scores it. The default objective
is the *free-run* simulation RMSE on that validation slice (:func:`free_run_rmse_objective`),
because a 100 Hz one-step predictor is nearly the identity and its error says little about the
model; the paper-style *one-step* RMSE is available as :func:`one_step_rmse_objective`.

To keep one evaluation cheap on long records, the candidate models are fitted on at most
``max_train_rows`` regressor rows (evenly spaced in time, exact LSSVM) and scored on at most
``max_val_samples`` validation samples. :func:`identify_lssvm_narx` then refits the winner on
the whole record (exact up to 4000 rows, fixed-size above).
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field

import numpy as np

from ipmc_driver.validation import as_signal, same_length

from .bee_colony import minimize_abc
from .lssvm import LSSVMRegressor
from .narx import InverseNarxModel, NarxModel, make_lssvm

OBJECTIVES = ("free_run", "one_step")

#: Default ABC budget (sources x cycles), about 10 * (2 * 10 + 1) = 210 model fits; the paper's
#: is 100 x 100 (about 20 000 fits): pass ``n_sources=100, n_cycles=100`` for it.
DEFAULT_SOURCES, DEFAULT_CYCLES = 10, 10


@dataclass
class TuningResult:
    """Outcome of :func:`tune_lssvm_narx`. ``score_mm`` is the objective's RMSE (mm, or V for
    an inverse model) on the validation slice, named by ``objective``."""

    C: float
    sigma: float
    objective: str
    score_mm: float
    nfev: int
    seconds: float
    history: list = field(default_factory=list)

    def as_dict(self) -> dict:
        return {"C": self.C, "sigma": self.sigma, "objective": self.objective,
                "score_rmse": self.score_mm, "nfev": self.nfev, "seconds": self.seconds,
                "history": [float(h) for h in self.history]}


def _split(u, y, val_fraction: float, max_val_samples: int):
    u = as_signal("u", u)
    y = as_signal("y", y)
    same_length(u=u, y=y)
    if not 0.05 <= val_fraction <= 0.5:
        raise ValueError(f"val_fraction must be in [0.05, 0.5], got {val_fraction}")
    cut = int(round(u.size * (1.0 - val_fraction)))
    u_val, y_val = u[cut:], y[cut:]
    if u_val.size > max_val_samples:
        u_val, y_val = u_val[:max_val_samples], y_val[:max_val_samples]
    return (u[:cut], y[:cut]), (u_val, y_val)


def free_run_rmse_objective(model, u_val, y_val) -> float:
    """Free-run RMSE of a fitted model on a validation slice, started from the measured first
    ``max_lag_`` samples and skipping them; ``inf`` if the simulation diverges."""
    L = model.max_lag_
    y_sim = model.simulate(u_val, y_val[:L])
    if not np.all(np.isfinite(y_sim)):
        return float("inf")
    return float(np.sqrt(np.mean((y_sim[L:] - y_val[L:]) ** 2)))


def one_step_rmse_objective(model, u_val, y_val) -> float:
    """One-step-ahead RMSE of a fitted model on a validation slice, skipping ``max_lag_``."""
    L = model.max_lag_
    y_hat = model.predict(u_val, y_val)
    return float(np.sqrt(np.mean((y_hat[L:] - y_val[L:]) ** 2)))


def _single_thread_blas():
    """Limit BLAS to one thread while tuning: each candidate is a small (<= 1000 row) solve, for
    which multithreaded OpenBLAS is slower, and up to 10x slower on a shared, loaded machine
    (threads spin waiting for cores). threadpoolctl comes with scikit-learn; without it, no-op.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


_OBJECTIVE_FUNCS = {"free_run": free_run_rmse_objective, "one_step": one_step_rmse_objective}


def tune_lssvm_narx(
    u,
    y,
    *,
    input_lags: int = 3,
    output_lags: int = 3,
    lag_step: int = 1,
    inverse: bool = False,
    objective: str = "free_run",
    val_fraction: float = 0.3,
    n_sources: int = DEFAULT_SOURCES,
    n_cycles: int = DEFAULT_CYCLES,
    log10_C_bounds: tuple[float, float] = (0.0, 7.0),
    log10_sigma_bounds: tuple[float, float] = (-1.0, 1.5),
    max_train_rows: int = 1000,
    max_val_samples: int = 3000,
    seed: int | None = 0,
    progress=None,
) -> TuningResult:
    """Tune C and sigma of an LSSVM-NARX model by ABC in log10 space.

    Parameters
    ----------
    u, y : array_like, shape (N,)
        Input (V) and output (mm), one uniformly sampled record.
    input_lags, output_lags, lag_step : int
        NARX structure, as :class:`~ipmc_model.narx.NarxModel` (for ``inverse=True``, as
        :class:`~ipmc_model.narx.InverseNarxModel`).
    inverse : bool
        Tune the inverse model (scored on the voltage it predicts, V).
    objective : {"free_run", "one_step"}
        Validation RMSE of the free-run simulation (default) or of the one-step prediction.
    val_fraction : float
        Chronological share of the record used for validation.
    n_sources, n_cycles : int
        ABC size (default 10 x 10; paper 100 x 100).
    log10_C_bounds, log10_sigma_bounds : (float, float)
        Search box in log10 units; sigma is in standard deviations of the standardised regressor.
    max_train_rows, max_val_samples : int
        Caps that keep one evaluation cheap (see module docstring).
    seed : int or None
        ABC seed.
    progress : callable, optional
        ``progress(cycle, n_cycles, best_rmse, nfev)`` after each cycle (for a progress line).

    Returns
    -------
    TuningResult
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    (u_tr, y_tr), (u_val, y_val) = _split(u, y, val_fraction, max_val_samples)
    score = _OBJECTIVE_FUNCS[objective]
    if inverse:
        # the inverse model maps y -> u: score it on the voltage it predicts
        def build(reg):
            inv = InverseNarxModel(reg, output_lags=output_lags, input_lags=input_lags,
                                   lag_step=lag_step, max_rows=max_train_rows)
            return inv.fit(u_tr, y_tr).narx_

        x_val, t_val = y_val, u_val
    else:
        def build(reg):
            return NarxModel(reg, input_lags=input_lags, output_lags=output_lags,
                             lag_step=lag_step, max_rows=max_train_rows).fit(u_tr, y_tr)

        x_val, t_val = u_val, y_val
    # Fail early, with the caller's message, on bad data (NaN, constant, too short).
    build(LSSVMRegressor(C=1.0, sigma=1.0))

    def cost(p):
        try:
            model = build(LSSVMRegressor(C=10.0 ** p[0], sigma=10.0 ** p[1]))
            return score(model, x_val, t_val)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError):
            return float("inf")

    counter = {"n": 0}

    def counted(p):
        counter["n"] += 1
        return cost(p)

    def cb(cycle, best):
        if progress is not None:
            progress(cycle, n_cycles, best, counter["n"])

    t0 = time.perf_counter()
    with np.errstate(over="ignore", invalid="ignore"), _single_thread_blas():
        res = minimize_abc(counted, [log10_C_bounds, log10_sigma_bounds], n_sources=n_sources,
                           n_cycles=n_cycles, seed=seed, callback=cb)
    return TuningResult(C=float(10.0 ** res.x[0]), sigma=float(10.0 ** res.x[1]),
                        objective=objective, score_mm=float(res.fun), nfev=int(res.nfev),
                        seconds=time.perf_counter() - t0, history=list(res.history))


def identify_lssvm_narx(
    u,
    y,
    *,
    C: float | None = None,
    sigma: float | None = None,
    input_lags: int = 3,
    output_lags: int = 3,
    lag_step: int = 1,
    inverse: bool = False,
    max_exact: int = 4000,
    n_prototypes: int = 1000,
    seed: int | None = 0,
    **tune_kwargs,
):
    """Identify an LSSVM-NARX model (forward or inverse) from one record.

    If ``C`` and ``sigma`` are both given they are used as they are; otherwise they are tuned
    by :func:`tune_lssvm_narx` (``tune_kwargs`` go there). The final model is fitted on the
    whole record: exact LSSVM up to ``max_exact`` rows, fixed-size with ``n_prototypes``
    above.

    Returns
    -------
    (NarxModel or InverseNarxModel, TuningResult or None)
    """
    tuning = None
    if C is None or sigma is None:
        tuning = tune_lssvm_narx(u, y, input_lags=input_lags, output_lags=output_lags,
                                 lag_step=lag_step, inverse=inverse, seed=seed, **tune_kwargs)
        C, sigma = tuning.C, tuning.sigma
    n = as_signal("u", u).size
    reg = make_lssvm(C, sigma, n_samples=n, max_exact=max_exact, n_prototypes=n_prototypes,
                     seed=seed)
    if inverse:
        model = InverseNarxModel(reg, output_lags=output_lags, input_lags=input_lags,
                                 lag_step=lag_step).fit(u, y)
    else:
        model = NarxModel(reg, input_lags=input_lags, output_lags=output_lags,
                          lag_step=lag_step).fit(u, y)
    return model, tuning
