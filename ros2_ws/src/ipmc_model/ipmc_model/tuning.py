"""Hyperparameter tuning of an LSSVM-NARX model (C, sigma, lag step) by artificial bee colony.

The search runs in log10 space of C and sigma (paper 3.4). The record is split
chronologically: the first ``1 - val_fraction`` fits the model, the last ``val_fraction`` scores
it. The default objective is the *free-run* simulation RMSE on that validation slice
(:func:`free_run_rmse_objective`), because a 100 Hz one-step predictor is nearly the identity
and its error says little about the model; the paper-style *one-step* RMSE is available as
:func:`one_step_rmse_objective`.

The tuning is posed on the model that is finally fitted. Every candidate uses the regressor
:func:`~ipmc_model.narx.make_lssvm` gives for that many rows (exact LSSVM up to ``max_exact``
rows, fixed-size with ``n_prototypes`` k-means++ prototypes above, same seed), fitted on the
same rows (all of them by default, or at most ``max_train_rows`` evenly spaced); the final
fit on the whole record uses the same class, size and row rule, so C means the same thing in
both. Fixed-size candidates are made cheap by keeping the sigma-dependent Gram matrix
(:class:`~ipmc_model.lssvm.FixedSizeStatistics`): a new C costs one M x M Cholesky. For that,
log10 sigma is rounded to a grid of ``log10_sigma_resolution`` (0.05 decade, 12 %).

The lag spacing can be searched too (``lag_step="auto"`` or a list): one ABC run per
candidate spacing, the best validation score wins.
"""

from __future__ import annotations

import contextlib
import copy
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from ipmc_driver.validation import as_signal, same_length

from .bee_colony import minimize_abc
from .lssvm import (
    FixedSizeLSSVMRegressor,
    FixedSizeStatistics,
    LSSVMRegressor,
    select_prototypes,
)
from .narx import InverseNarxModel, NarxModel, make_lssvm, memory_channels, voltage_channels

OBJECTIVES = ("free_run", "one_step")

#: Default ABC budget (sources x cycles), about 10 * (2 * 10 + 1) = 210 model fits; the paper's
#: is 100 x 100 (about 20 000 fits): pass ``n_sources=100, n_cycles=100`` for it.
DEFAULT_SOURCES, DEFAULT_CYCLES = 10, 10

#: Lag spacings (samples) tried by ``lag_step="auto"``.
DEFAULT_LAG_STEPS = (1, 5, 10, 20)

#: Largest row count fitted by the exact LSSVM in identification (fixed-size above); the
#: exact solve is O(N^3) per tuning candidate, 2000 rows take about 1 s.
DEFAULT_MAX_EXACT = 2000

#: Memory kept for fixed-size Gram matrices while tuning (bytes, shared by the folds).
_CACHE_BYTES = 400 * 2**20


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
    lag_step: int | None = None
    per_lag_step: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"C": self.C, "sigma": self.sigma, "objective": self.objective,
                "score_rmse": self.score_mm, "nfev": self.nfev, "seconds": self.seconds,
                "history": [float(h) for h in self.history], "lag_step": self.lag_step,
                "per_lag_step": {str(k): v for k, v in self.per_lag_step.items()}}


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


class _RowCapture:
    """A stand-in regressor that keeps the rows NarxModel.fit builds (no fitting)."""

    def fit(self, X, y):
        self.X_, self.y_ = X, y
        return self


def _lag_steps(lag_step) -> tuple[int, ...]:
    if isinstance(lag_step, str):
        if lag_step != "auto":
            raise ValueError(f"lag_step must be an integer >= 1, a list of them or 'auto', "
                             f"got {lag_step!r}")
        return DEFAULT_LAG_STEPS
    steps = (lag_step,) if np.isscalar(lag_step) else tuple(lag_step)
    if not steps or any(not isinstance(s, (int, np.integer)) or s < 1 for s in steps):
        raise ValueError(f"lag_step must be an integer >= 1, a list of them or 'auto', "
                         f"got {lag_step!r}")
    return tuple(int(s) for s in steps)


class _CandidateFactory:
    """Fits candidate regressors on one structure's rows, as the final fit will (see module
    docstring), keeping fixed-size Gram matrices per sigma."""

    def __init__(self, X, t, exact: bool, n_prototypes: int, seed,
                 cache_bytes: int = _CACHE_BYTES):
        self.X, self.t = X, t
        self.cache_bytes = cache_bytes
        self.n_prototypes, self.seed = n_prototypes, seed
        self.exact = exact
        self.idx = None if self.exact else select_prototypes(X, n_prototypes, "kmeans++", seed)
        self.cache: OrderedDict = OrderedDict()

    def __call__(self, C: float, sigma: float):
        if self.exact:
            return LSSVMRegressor(C=C, sigma=sigma).fit(self.X, self.t)
        stats = self.cache.get(sigma)
        if stats is None:
            stats = FixedSizeStatistics(self.X, self.t, self.idx, sigma)
            self.cache[sigma] = stats
            while len(self.cache) > 1 and sum(v.nbytes for v in self.cache.values()) > \
                    self.cache_bytes:
                self.cache.popitem(last=False)
        else:
            self.cache.move_to_end(sigma)
        reg = FixedSizeLSSVMRegressor(C=C, sigma=sigma, n_prototypes=self.n_prototypes,
                                      seed=self.seed)
        return stats.solve(C, reg)


def tune_lssvm_narx(
    u,
    y,
    *,
    input_lags: int = 3,
    output_lags: int = 3,
    lag_step=1,
    inverse: bool = False,
    memory_taus_s=(),
    dt_s: float = 0.01,
    input_memory_taus_s=(),
    include_voltage: bool = True,
    objective: str = "free_run",
    val_fraction: float = 0.3,
    n_sources: int = DEFAULT_SOURCES,
    n_cycles: int = DEFAULT_CYCLES,
    log10_C_bounds: tuple[float, float] = (0.0, 7.0),
    log10_sigma_bounds: tuple[float, float] = (-1.0, 1.5),
    max_train_rows: int | None = None,
    max_val_samples: int = 3000,
    seed: int | None = 0,
    progress=None,
    max_exact: int = DEFAULT_MAX_EXACT,
    n_prototypes: int = 1000,
    log10_sigma_resolution: float = 0.05,
    n_folds: int = 1,
) -> TuningResult:
    """Tune C and sigma (and optionally the lag spacing) of an LSSVM-NARX model by ABC.

    Parameters
    ----------
    u, y : array_like, shape (N,)
        Input (V) and output (mm), one uniformly sampled record.
    input_lags, output_lags : int
        NARX structure, as :class:`~ipmc_model.narx.NarxModel` (for ``inverse=True``, as
        :class:`~ipmc_model.narx.InverseNarxModel`); ``input_memory_taus_s`` and
    ``include_voltage`` give a forward model voltage channels (see
    :class:`~ipmc_model.narx.NarxModel`).
    lag_step : int, sequence of int or "auto"
        Lag spacing in samples; a sequence (or ``"auto"`` = ``DEFAULT_LAG_STEPS``) runs one
        ABC per spacing and keeps the best (``TuningResult.lag_step``).
    inverse : bool
        Tune the inverse model (scored on the voltage it predicts, V).
    memory_taus_s : sequence of float, dt_s : float
        Memory channels of the inverse model (time constants and sample period, s).
    input_memory_taus_s : sequence of float, include_voltage : bool
        Voltage channels of a forward model (s; see :class:`~ipmc_model.narx.NarxModel`). The
        channels are built once from the whole record, so each validation slice starts from
        the low-pass filters' true state, as the final model's own free run does.
    objective : {"free_run", "one_step"}
        Validation RMSE of the free-run simulation (default) or of the one-step prediction.
    val_fraction : float
        Chronological share of the record used for validation.
    n_sources, n_cycles : int
        ABC size per lag spacing (default 10 x 10; paper 100 x 100).
    log10_C_bounds, log10_sigma_bounds : (float, float)
        Search box in log10 units; sigma is in standard deviations of the standardised regressor.
    max_train_rows : int or None
        Fit candidates on at most this many regressor rows (evenly spaced); default all rows.
        :func:`identify_lssvm_narx` applies the same cap to the final fit.
    max_val_samples : int
        Score on at most this many validation samples per block (its start); ``ipmc
        identify`` and the experiments use 10000.
    seed : int or None
        ABC seed, also the prototype-selection seed.
    progress : callable, optional
        ``progress(cycle, n_cycles, best_rmse, nfev)`` after each cycle (cycles counted over
        all lag spacings).
    max_exact, n_prototypes : int
        Regressor choice, as :func:`~ipmc_model.narx.make_lssvm` (must match the final fit).
    log10_sigma_resolution : float
        Grid of log10 sigma (decades) so that Gram matrices are reused; 0 for none.
    n_folds : int
        1: score on the last ``val_fraction`` (chronological holdout). K >= 2: blocked
        cross-validation, the record cut into K contiguous blocks, each scored (its first
        ``max_val_samples``) by a model fitted on the rows outside it; the objective is the
        mean of the K RMSEs. K times the fits, a less noisy choice.

    Returns
    -------
    TuningResult
        With ``lag_step`` the chosen spacing and ``per_lag_step`` the best of each spacing.
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    steps = _lag_steps(lag_step)
    if not isinstance(n_folds, (int, np.integer)) or n_folds < 1:
        raise ValueError(f"n_folds must be an integer >= 1, got {n_folds!r}")
    (u_tr, y_tr), (u_val, _) = _split(u, y, val_fraction, max_val_samples)
    u = np.concatenate([u_tr, u_val]) if n_folds == 1 else as_signal("u", u)
    y = as_signal("y", y)[: u.size] if n_folds == 1 else as_signal("y", y)
    N = u.size
    if n_folds == 1:  # chronological holdout: the last val_fraction
        blocks = [(u_tr.size, N)]
    else:  # blocked cross-validation: K contiguous blocks, each scored once
        edges = np.linspace(0, N, n_folds + 1).round().astype(int)
        blocks = [(int(lo), int(min(hi, lo + max_val_samples)))
                  for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
    score = _OBJECTIVE_FUNCS[objective]
    channels = len(input_memory_taus_s) > 0 or not include_voltage
    if channels and inverse:
        raise ValueError("input_memory_taus_s / include_voltage are for a forward model; an "
                         "inverse model's channels are memory_taus_s")
    # the inverse model maps y -> u: it is scored on the voltage it predicts
    memory = {"memory_taus_s": tuple(memory_taus_s), "dt_s": dt_s}
    if inverse:
        x_all, t_all = memory_channels(y, memory_taus_s, dt_s), u
    elif channels:  # the same rows as the final model with voltage channels builds
        x_all, t_all = voltage_channels(u, tuple(input_memory_taus_s), dt_s,
                                        include_voltage=include_voltage), y
    else:
        x_all, t_all = u, y

    def skeleton(reg, step):
        if inverse:
            return InverseNarxModel(reg, output_lags=output_lags, input_lags=input_lags,
                                    lag_step=step, **memory).fit(u, y).narx_
        return NarxModel(reg, input_lags=input_lags, output_lags=output_lags,
                         lag_step=step).fit(x_all, y)

    res_step = float(log10_sigma_resolution)

    def snap(p):
        ls = round(p[1] / res_step) * res_step if res_step > 0 else p[1]
        return 10.0 ** p[0], float(10.0 ** np.clip(ls, *log10_sigma_bounds))

    counter = {"n": 0}
    t0 = time.perf_counter()
    per_step: dict = {}
    best = None
    with np.errstate(over="ignore", invalid="ignore"), _single_thread_blas():
        for i, step in enumerate(steps):
            # Fail early, with the caller's message, on bad data (NaN, constant, too short).
            try:
                skel = skeleton(_RowCapture(), step)
            except ValueError:
                if len(steps) == 1:
                    raise
                continue  # this spacing needs more samples than the record has
            rows, L = skel.regressor_, skel.max_lag_
            k = np.arange(L, N)  # row r predicts sample k = L + r
            # the final fit's row count decides exact vs fixed-size, as make_lssvm does
            n_final = k.size if max_train_rows is None else min(k.size, int(max_train_rows))
            folds = []
            for lo, hi in blocks:
                # train on the rows whose target and lags all lie outside the scored block
                keep = np.flatnonzero((k < lo) | (k >= hi + L))
                cap = None if max_train_rows is None else int(max_train_rows * keep.size / k.size)
                if cap is not None and keep.size > cap:
                    keep = keep[np.linspace(0, keep.size - 1, cap).round().astype(int)]
                make = _CandidateFactory(rows.X_[keep], rows.y_[keep], n_final <= max_exact,
                                         n_prototypes, seed, _CACHE_BYTES // len(blocks))
                folds.append((lo, hi, make))

            def cost(p, _skel=skel, _folds=folds):
                counter["n"] += 1
                C, sigma = snap(p)
                try:
                    errs = []
                    for lo, hi, make in _folds:
                        model = copy.copy(_skel)
                        model.regressor_ = make(C, sigma)
                        errs.append(score(model, x_all[lo:hi], t_all[lo:hi]))
                    return float(np.mean(errs))
                except (ValueError, FloatingPointError, np.linalg.LinAlgError):
                    return float("inf")

            def cb(cycle, fbest, _i=i):
                if progress is not None:
                    progress(_i * n_cycles + cycle, len(steps) * n_cycles, fbest, counter["n"])

            res = minimize_abc(cost, [log10_C_bounds, log10_sigma_bounds], n_sources=n_sources,
                               n_cycles=n_cycles, seed=seed, callback=cb)
            C, sigma = snap(res.x)
            per_step[step] = {"C": C, "sigma": sigma, "score_rmse": float(res.fun)}
            if best is None or res.fun < best[1].fun:
                best = (step, res, C, sigma)
    if best is None:
        raise ValueError(f"too few samples for any of the lag steps {steps}")
    step, res, C, sigma = best
    return TuningResult(C=C, sigma=sigma, objective=objective, score_mm=float(res.fun),
                        nfev=int(counter["n"]), seconds=time.perf_counter() - t0,
                        history=list(res.history), lag_step=int(step), per_lag_step=per_step)


def identify_lssvm_narx(
    u,
    y,
    *,
    C: float | None = None,
    sigma: float | None = None,
    input_lags: int = 3,
    output_lags: int = 3,
    lag_step=1,
    inverse: bool = False,
    memory_taus_s=(),
    dt_s: float = 0.01,
    input_memory_taus_s=(),
    include_voltage: bool = True,
    max_exact: int = DEFAULT_MAX_EXACT,
    n_prototypes: int = 1000,
    seed: int | None = 0,
    **tune_kwargs,
):
    """Identify an LSSVM-NARX model (forward or inverse) from one record.

    If ``C`` and ``sigma`` are both given they are used as they are (``lag_step`` must then be
    one integer); otherwise they, and the lag spacing if ``lag_step`` is a list or ``"auto"``,
    are tuned by :func:`tune_lssvm_narx` (``tune_kwargs`` go there) with the same regressor
    rule as the final fit. The final model is fitted on the whole record: exact LSSVM up to
    ``max_exact`` rows, fixed-size with ``n_prototypes`` above; at most ``max_train_rows``
    rows (evenly spaced) if that cap was given to the tuning. ``memory_taus_s`` (s) and
    ``dt_s`` (the record's sample period, s) give an inverse model memory channels (see
    :class:`~ipmc_model.narx.InverseNarxModel`).

    Returns
    -------
    (NarxModel or InverseNarxModel, TuningResult or None)
    """
    tuning = None
    max_rows = tune_kwargs.get("max_train_rows")
    if C is None or sigma is None:
        tuning = tune_lssvm_narx(u, y, input_lags=input_lags, output_lags=output_lags,
                                 lag_step=lag_step, inverse=inverse, seed=seed,
                                 memory_taus_s=memory_taus_s, dt_s=dt_s,
                                 input_memory_taus_s=input_memory_taus_s,
                                 include_voltage=include_voltage, max_exact=max_exact,
                                 n_prototypes=n_prototypes, **tune_kwargs)
        C, sigma, lag_step = tuning.C, tuning.sigma, tuning.lag_step
    else:
        steps = _lag_steps(lag_step)
        if len(steps) != 1:
            raise ValueError("lag_step 'auto' or a list needs tuning: leave C or sigma unset")
        lag_step = steps[0]
    n = as_signal("u", u).size
    if max_rows is not None:
        n = min(n, int(max_rows))
    reg = make_lssvm(C, sigma, n_samples=n, max_exact=max_exact, n_prototypes=n_prototypes,
                     seed=seed)
    if inverse:
        model = InverseNarxModel(reg, output_lags=output_lags, input_lags=input_lags,
                                 lag_step=lag_step, max_rows=max_rows,
                                 memory_taus_s=memory_taus_s, dt_s=dt_s).fit(u, y)
    else:
        model = NarxModel(reg, input_lags=input_lags, output_lags=output_lags,
                          lag_step=lag_step, max_rows=max_rows,
                          input_memory_taus_s=tuple(input_memory_taus_s),
                          include_voltage=include_voltage, dt_s=dt_s).fit(u, y)
    return model, tuning
