"""NARX models (paper Eq. 7-8 and 19) around a regression core (by default an LSSVM).

Forward model (Eq. 8), input lags m and output lags n (paper: 3 and 3):

    y_k = f(u_k, u_{k-1}, ..., u_{k-m}, y_{k-1}, ..., y_{k-n})

``u`` may carry extra exogenous channels, shape (N, c), each with its own input lags; this is
how an augmented model (a filtered input for creep, a time signal for drift) reuses the same
machinery. A forward model may instead build its input channels from the voltage itself
(``input_memory_taus_s``, ``include_voltage``): the voltage low-passed with each time constant,
optionally with the voltage; then ``fit``, ``predict``, ``simulate`` and ``stepper`` all take
the raw voltage (N,) and the channels are part of the model. Inverse model (Eq. 19), used as a
feedforward compensator:

    u_l = h(y_l, y_{l-1}, ..., y_{l-n}, u_{l-1}, ..., u_{l-m})

Regressors and targets are standardised with the training mean and standard deviation, stored
in the model, so ``sigma`` is in standard deviations. The first ``max_lag_`` samples of every
output are initial conditions, not predictions; metrics skip them.

``predict`` is the one-step-ahead prediction from measured past outputs; ``simulate`` is the
free run from the input alone (past outputs are the model's own). ``stepper()`` gives a
sample-by-sample object for 100 Hz loops (one kernel row per step).
"""

from __future__ import annotations

import copy
import hashlib
import math
from collections import OrderedDict

import numpy as np

from ipmc_driver.validation import as_signal, same_length

from .errors import check_fitted
from .lssvm import FixedSizeLSSVMRegressor, LSSVMRegressor

#: Paper's hand-picked LSSVM hyperparameters (section 3.3).
PAPER_C = 998.0867
PAPER_SIGMA = 0.2


def make_lssvm(
    C: float = PAPER_C,
    sigma: float = PAPER_SIGMA,
    n_samples: int = 0,
    max_exact: int = 4000,
    n_prototypes: int = 1000,
    seed: int | None = 0,
):
    """An exact LSSVM for up to ``max_exact`` rows, the fixed-size variant above that."""
    if n_samples > max_exact:
        return FixedSizeLSSVMRegressor(C=C, sigma=sigma, n_prototypes=n_prototypes, seed=seed)
    return LSSVMRegressor(C=C, sigma=sigma)


def _as_inputs(name: str, u, min_length: int = 1) -> np.ndarray:
    """Input signal(s) as a float array of shape (N, c)."""
    arr = np.asarray(u, dtype=float) if not isinstance(u, np.ndarray) else u.astype(float)
    if arr.ndim == 2 and arr.shape[1] > 1:
        cols = [as_signal(f"{name}[:, {j}]", arr[:, j], min_length=min_length)
                for j in range(arr.shape[1])]
        return np.column_stack(cols)
    return as_signal(name, arr, min_length=min_length)[:, None]


def _initial_outputs(y_init, L: int) -> np.ndarray:
    """A free run's first ``L`` outputs (mm): ``y_init``, checked, or zeros (rest)."""
    if y_init is None:
        return np.zeros(L)
    y0 = np.atleast_1d(np.asarray(y_init, dtype=float))
    if y0.shape != (L,) or not np.all(np.isfinite(y0)):
        raise ValueError(f"y_init must be {L} finite values (max lag), got {y0.shape}")
    return y0


def _lags_per_channel(input_lags, n_channels: int) -> tuple[int, ...]:
    lags = (input_lags,) * n_channels if np.isscalar(input_lags) else tuple(input_lags)
    if len(lags) != n_channels:
        raise ValueError(
            f"input_lags needs one entry per input channel ({n_channels}), got {lags}"
        )
    if any(int(m) != m or m < 0 for m in lags):
        raise ValueError(f"input lags must be integers >= 0, got {lags}")
    return tuple(int(m) for m in lags)


def _lag_sets(in_lags, n: int, step: int) -> tuple[list[np.ndarray], np.ndarray]:
    """Delays per input channel {0, s, .., m s} and of the output {1, 1 + s, .., 1 + (n-1) s}."""
    ins = [np.arange(m + 1) * step for m in in_lags]
    out = 1 + np.arange(n) * step
    return ins, out


def _build_rows(us: np.ndarray, ys: np.ndarray, in_sets, out_set, L: int) -> np.ndarray:
    """Regressor rows for k = L..N-1: [u_{k-d} for d in each input set, y_{k-d} for d in out]."""
    N = us.shape[0]
    cols = [us[L - d : N - d, c] for c, ds in enumerate(in_sets) for d in ds]
    cols += [ys[L - d : N - d] for d in out_set]
    return np.column_stack(cols) if cols else np.empty((N - L, 0))


class NarxModel:
    """Forward NARX model y_k = f(u_k..u_{k-m}, y_{k-1}..y_{k-n}) (paper Eq. 8).

    Parameters
    ----------
    regressor : estimator, optional
        Object with ``fit(X, y)``, ``predict(X)`` and ideally ``predict_one(x)``; it is copied,
        not modified. Default: an LSSVM with the paper's C = 998.0867, sigma = 0.2, exact up to
        4000 rows, fixed-size (1000 prototypes) above.
    input_lags : int or sequence of int
        m (per input channel); the current input u_k is always included.
    output_lags : int
        n.
    lag_step : int
        Spacing s of the lags in samples: input delays {0, s, .., m s}, output delays
        {1, 1 + s, .., 1 + (n - 1) s}. 1 (default) is the paper's consecutive lags; at a high
        sample rate a larger s lets three lags span the actuator's time constants.
    standardize : bool
        Scale inputs and output to zero mean, unit variance (stored in the model).
    max_rows : int, optional
        Fit on at most this many regressor rows, evenly spaced in time (hyperparameter
        tuning uses it to make one evaluation cheap); default all rows.
    input_memory_taus_s : sequence of float
        Voltage channels: time constants (s) of the voltage low-passed from rest,
        ``m_j,k = a_j m_j,k-1 + (1 - a_j) u_k``, ``a_j = exp(-dt_s / tau_j)``, each one input
        channel (with its own input lags). Default none: ``u`` is used as given.
    include_voltage : bool
        With voltage channels: the voltage itself is the first channel (default True). False
        with ``input_memory_taus_s`` (0.3, 0.5) and no output lags is the forward model that
        inverts smoothly (:mod:`ipmc_model.forward_inversion`).
    dt_s : float
        Sample period of the data, s (discretises the voltage channels; unused without).

    With voltage channels (``input_memory_taus_s`` given or ``include_voltage=False``) every
    method takes the voltage ``u`` as a 1-D record (V) and builds the channels itself (see
    :func:`voltage_channels`); lags, scalings and the regressor see the channels.

    Attributes
    ----------
    regressor_ : fitted estimator
    max_lag_ : int
        Number of leading samples that are initial conditions (skipped by metrics).
    n_inputs_ : int
        Number of input channels c seen by the regressor (the voltage channels, if any).
    u_mean_, u_scale_ : ndarray (c,)
    y_mean_, y_scale_ : float
    """

    def __init__(self, regressor=None, input_lags=3, output_lags: int = 3, lag_step: int = 1,
                 standardize=True, max_rows: int | None = None, input_memory_taus_s=(),
                 include_voltage: bool = True, dt_s: float = 0.01):
        self.regressor = regressor
        self.input_lags = input_lags
        self.output_lags = output_lags
        self.lag_step = lag_step
        self.standardize = standardize
        self.max_rows = max_rows
        self.input_memory_taus_s = input_memory_taus_s
        self.include_voltage = include_voltage
        self.dt_s = dt_s
        self.regressor_ = None

    @property
    def uses_voltage_channels(self) -> bool:
        """Whether the model builds its input channels from a 1-D voltage record."""
        return bool(len(self.input_memory_taus_s)) or not self.include_voltage

    def voltage_poles(self) -> np.ndarray:
        """Discrete poles exp(-dt_s / tau) of the low-passed voltage channels (may be empty)."""
        taus = tuple(float(t) for t in self.input_memory_taus_s)
        return memory_poles(taus, float(self.dt_s)) if taus else np.zeros(0)

    def input_channels(self, u, name: str = "u", min_length: int = 1) -> np.ndarray:
        """Regressor input channels (N, c) for an input record: the voltage channels built from
        a 1-D voltage (V) if the model has them, else ``u`` as given, (N,) or (N, c)."""
        if not self.uses_voltage_channels:
            return _as_inputs(name, u, min_length)
        arr = np.asarray(u, dtype=float)
        if arr.ndim != 1:
            raise ValueError(f"{name} must be a 1-D voltage record (V): this model builds its "
                             f"input channels from the voltage, got shape {arr.shape}")
        return voltage_channels(as_signal(name, arr, min_length=min_length),
                                tuple(float(t) for t in self.input_memory_taus_s),
                                float(self.dt_s), include_voltage=bool(self.include_voltage))

    # -- helpers -----------------------------------------------------------------------------
    def _check_pair(self, u, y, min_length: int = 1):
        us = self.input_channels(u, "u", min_length)
        ys = as_signal("y", y, min_length=min_length)
        same_length(u=us[:, 0], y=ys)
        return us, ys

    def _scale_u(self, us):
        return (us - self.u_mean_) / self.u_scale_

    def _scale_y(self, ys):
        return (ys - self.y_mean_) / self.y_scale_

    def _unscale_y(self, zs):
        return zs * self.y_scale_ + self.y_mean_

    def _check_inputs(self, us):
        if us.shape[1] != self.n_inputs_:
            raise ValueError(f"u must have {self.n_inputs_} channel(s), got {us.shape[1]}")

    def _rows(self, us, ys):
        return _build_rows(self._scale_u(us), self._scale_y(ys), self.in_delays_,
                           self.out_delays_, self.max_lag_)

    # -- fitting -----------------------------------------------------------------------------
    def fit(self, u, y) -> NarxModel:
        """Fit on input ``u`` (N,) or (N, c) (V) and output ``y`` (N,) (mm); returns self."""
        n = self.output_lags
        if not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"output_lags must be an integer >= 0, got {n!r}")
        step = self.lag_step
        if not isinstance(step, (int, np.integer)) or step < 1:
            raise ValueError(f"lag_step must be an integer >= 1, got {step!r}")
        us, ys = self._check_pair(u, y)
        in_lags = _lags_per_channel(self.input_lags, us.shape[1])
        in_sets, out_set = _lag_sets(in_lags, int(n), int(step))
        L = int(max([ds.max() for ds in in_sets] + [out_set.max() if n else 0]))
        d = sum(m + 1 for m in in_lags) + int(n)
        need = max(d + 1, 10)
        if us.shape[0] - L < need:
            raise ValueError(
                f"too few samples for the lags: got {us.shape[0]}, the lags need {L} initial "
                f"samples plus at least {need} to fit, so {L + need}"
            )
        u_std = us.std(axis=0)
        for c, sd in enumerate(u_std):
            if sd == 0.0:
                name = "u" if us.shape[1] == 1 else f"u[:, {c}]"
                raise ValueError(f"{name} is constant; the model cannot be identified from it")
        if ys.std() == 0.0:
            raise ValueError("y is constant; the model cannot be identified from it")
        if self.standardize:
            self.u_mean_, self.u_scale_ = us.mean(axis=0), u_std
            self.y_mean_, self.y_scale_ = float(ys.mean()), float(ys.std())
        else:
            self.u_mean_, self.u_scale_ = np.zeros(us.shape[1]), np.ones(us.shape[1])
            self.y_mean_, self.y_scale_ = 0.0, 1.0
        self.input_lags_, self.in_delays_, self.out_delays_ = in_lags, in_sets, out_set
        self.max_lag_, self.n_inputs_, self.n_features_ = L, us.shape[1], d
        X = self._rows(us, ys)
        t = self._scale_y(ys)[L:]
        if self.max_rows is not None and X.shape[0] > int(self.max_rows):
            keep = np.linspace(0, X.shape[0] - 1, int(self.max_rows)).round().astype(int)
            X, t = X[keep], t[keep]
        reg = make_lssvm(n_samples=X.shape[0]) if self.regressor is None else self.regressor
        self.regressor_ = copy.deepcopy(reg).fit(X, t)
        return self

    # -- use ---------------------------------------------------------------------------------
    def predict(self, u, y) -> np.ndarray:
        """One-step-ahead prediction (mm) from input ``u`` and measured output ``y``.

        Returns an array of shape (N,); the first ``max_lag_`` entries are copied from ``y``.
        """
        check_fitted(self, "regressor_")
        us, ys = self._check_pair(u, y, min_length=self.max_lag_ + 1)
        self._check_inputs(us)
        out = ys.copy()
        out[self.max_lag_ :] = self._unscale_y(self.regressor_.predict(self._rows(us, ys)))
        return out

    def simulate(self, u, y_init=None) -> np.ndarray:
        """Free-run simulation (mm) from input ``u`` alone.

        Parameters
        ----------
        u : array_like, shape (N,) or (N, c)
            Input (V); (N,) from rest with voltage channels.
        y_init : array_like, shape (max_lag_,), optional
            The first ``max_lag_`` outputs (initial conditions, mm); default zeros (rest).

        Returns
        -------
        ndarray, shape (N,)
            Simulated output; entries ``[:max_lag_]`` are ``y_init``. If the simulation
            diverges (|standardised output| > 1e6) the rest is NaN.
        """
        return self._unscale_y(self._free_run(*self._run_inputs(u, y_init)))

    def _run_inputs(self, u, y_init) -> tuple[np.ndarray, np.ndarray]:
        """A free run's checked input channels and initial outputs (mm)."""
        check_fitted(self, "regressor_")
        L = self.max_lag_
        us = self.input_channels(u, "u", min_length=L + 1)
        self._check_inputs(us)
        return us, _initial_outputs(y_init, L)

    def _free_run(self, us: np.ndarray, y0: np.ndarray) -> np.ndarray:
        """The free run in standardised units from input channels ``us`` and initial outputs
        ``y0`` (mm)."""
        L = self.max_lag_
        N = us.shape[0]
        zu = _build_rows(self._scale_u(us), np.zeros(N), self.in_delays_, np.zeros(0, int), L)
        du = zu.shape[1]
        z = np.empty(N)
        z[:L] = self._scale_y(y0)
        out_delays = self.out_delays_
        if out_delays.size == 0:
            # no output feedback (a nonlinear FIR model, the diagnosis's baseline): the free
            # run is the batch prediction of its input rows
            z[L:] = self.regressor_.predict(zu)
            bad = np.flatnonzero(~(np.abs(z[L:]) < 1e6))
            if bad.size:
                z[L + bad[0] :] = np.nan
            return z
        x = np.empty(du + out_delays.size)
        f = getattr(self.regressor_, "predict_one", None)
        if f is None:
            def f(row, _p=self.regressor_.predict):
                return float(_p(row[None, :])[0])
        for k in range(L, N):
            x[:du] = zu[k - L]
            x[du:] = z[k - out_delays]
            zk = f(x)
            if not abs(zk) < 1e6:  # diverged (or NaN): report it instead of overflowing
                z[k:] = np.nan
                break
            z[k] = zk
        return z

    def stepper(self, u_history=None, y_history=None) -> NarxStepper:
        """Sample-by-sample free-run predictor; see :class:`NarxStepper`."""
        check_fitted(self, "regressor_")
        return NarxStepper(self, u_history, y_history)

    @property
    def history_samples(self) -> int:
        """Past samples a stepper going on from a history needs: the lags, and
        :data:`HISTORY_TAUS` of the longest low-passed voltage channel's time constant."""
        check_fitted(self, "regressor_")
        return samples_to_settle(self.max_lag_, self.input_memory_taus_s, self.dt_s)

    def get_params(self) -> dict:
        return {
            "input_lags": self.input_lags if np.isscalar(self.input_lags)
            else [int(m) for m in self.input_lags],
            "output_lags": self.output_lags,
            "lag_step": self.lag_step,
            "standardize": self.standardize,
            "input_memory_taus_s": [float(t) for t in self.input_memory_taus_s],
            "include_voltage": bool(self.include_voltage),
            "dt_s": float(self.dt_s),
        }


class NarxCommittee:
    """The mean of several forward NARX models fitted on the same record (a committee).

    Models that differ in their memory, such as their input window, make partly independent
    errors on input they were not fitted on. So the mean of their outputs errs less than any
    one of them. On 24 clean records of the simulated plant, three nonlinear FIR models with
    1.2, 1.8 and 2.4 s windows gave a held-out free-run RMSE 24 % lower in sum than the single
    1.2 s model, and lower on 22 of the 24 (a committee of three windows).

    ``fit``, ``predict``, ``simulate`` and ``stepper`` work as :class:`NarxModel`'s and give
    the members' mean. Every member sees the same input channels, and none may build voltage
    channels. The first ``max_lag_`` outputs (the longest member's) are initial conditions;
    a member with a shorter window starts from the first of them.

    Parameters
    ----------
    members : sequence of NarxModel
        Two or more templates, fitted in place by ``fit``.

    Attributes
    ----------
    regressor_ : tuple
        The members' fitted regressors (refitting replaces the tuple).
    max_lag_ : int
    n_inputs_ : int
    """

    def __init__(self, members):
        self.members = list(members)
        self.regressor_ = None

    def _check_members(self) -> None:
        if len(self.members) < 2:
            raise ValueError(f"a committee needs at least 2 members, got {len(self.members)}")
        for m in self.members:
            if not isinstance(m, NarxModel):
                raise ValueError(f"committee members must be NarxModel, got {type(m).__name__}")
            if m.uses_voltage_channels:
                raise ValueError("committee members cannot build voltage channels; give the "
                                 "channels as input")

    def _set_fitted(self) -> NarxCommittee:
        self.regressor_ = tuple(m.regressor_ for m in self.members)
        self.max_lag_ = max(int(m.max_lag_) for m in self.members)
        self.n_inputs_ = int(self.members[0].n_inputs_)
        return self

    @property
    def uses_voltage_channels(self) -> bool:
        return False

    @property
    def out_delays_(self) -> np.ndarray:
        return np.unique(np.concatenate([m.out_delays_ for m in self.members])).astype(int)

    @property
    def lag_step(self) -> int:
        return self.members[0].lag_step

    @property
    def max_rows(self) -> int | None:
        return self.members[0].max_rows

    @max_rows.setter
    def max_rows(self, rows: int | None) -> None:
        for m in self.members:
            m.max_rows = rows

    def fit(self, u, y) -> NarxCommittee:
        """Fit every member on input ``u`` (N,) or (N, c) (V) and output ``y`` (N,) (mm);
        returns self."""
        self._check_members()
        for m in self.members:
            m.fit(u, y)
        return self._set_fitted()

    def predict(self, u, y) -> np.ndarray:
        """One-step-ahead prediction (mm): the members' mean; the first ``max_lag_`` entries
        are copied from ``y``."""
        check_fitted(self, "regressor_")
        out = np.mean([m.predict(u, y) for m in self.members], axis=0)
        out[: self.max_lag_] = np.asarray(y, dtype=float)[: self.max_lag_]
        return out

    def simulate(self, u, y_init=None) -> np.ndarray:
        """Free run (mm) from input ``u``: the members' mean; entries ``[:max_lag_]`` are
        ``y_init`` (default zeros, rest). NaN where a member diverged."""
        return self._free_run(*self._run_inputs(u, y_init))

    def _run_inputs(self, u, y_init) -> tuple[np.ndarray, np.ndarray]:
        check_fitted(self, "regressor_")
        L = self.max_lag_
        us = _as_inputs("u", u, min_length=L + 1)
        self.members[0]._check_inputs(us)  # the members share their input channels
        return us, _initial_outputs(y_init, L)

    def _free_run(self, us: np.ndarray, y0: np.ndarray) -> np.ndarray:
        # in mm: a committee has no scaling of its own (the cache calls _scale_y, _unscale_y)
        runs = [m._unscale_y(m._free_run(us, y0[: m.max_lag_])) for m in self.members]
        z = np.mean(runs, axis=0)
        z[: self.max_lag_] = y0
        return z

    def _scale_y(self, y):
        return np.asarray(y, dtype=float)

    def _unscale_y(self, z):
        return z

    def stepper(self, u_history=None, y_history=None) -> CommitteeStepper:
        """Sample-by-sample free-run predictor; see :class:`CommitteeStepper`."""
        check_fitted(self, "regressor_")
        return CommitteeStepper(self, u_history, y_history)

    @property
    def history_samples(self) -> int:
        """Past samples a stepper going on from a history needs: the longest member's."""
        return max(m.history_samples for m in self.members)

    def get_params(self) -> dict:
        return {"members": [m.get_params() for m in self.members]}


class CommitteeStepper:
    """:class:`NarxStepper` of every member of a :class:`NarxCommittee`; ``step`` returns
    their mean (mm), ``correct_output`` and ``reset`` go to each."""

    def __init__(self, model: NarxCommittee, u_history=None, y_history=None):
        self._steppers = [m.stepper(u_history, y_history) for m in model.members]

    def reset(self, u_history=None, y_history=None) -> None:
        for s in self._steppers:
            s.reset(u_history, y_history)

    def step(self, u_k) -> float:
        return float(np.mean([s.step(u_k) for s in self._steppers]))

    def correct_output(self, y_measured_k: float) -> None:
        for s in self._steppers:
            s.correct_output(y_measured_k)


def members_of(model: NarxModel | NarxCommittee) -> list[NarxModel]:
    """The NARX models a model is made of: a committee's members, or the model itself."""
    return list(model.members) if isinstance(model, NarxCommittee) else [model]


class FreeRunCache:
    """Free runs of one fitted :class:`NarxModel`, kept by their input channels.

    A fit that scores many values of a block around a model kept as it is (a given model in
    ``ipmc diagnose``) runs the same baseline input again and again: every value of an output
    block (saturation, the bending asymmetry) leaves it unchanged, and the split-half fits score
    the same grid as the full fit. Each distinct input is run once. Exact: a free run is a
    function of the input channels and, with output lags, the initial outputs only; without
    output lags the initial outputs are only its first ``max_lag_`` entries, set per call.

    Parameters
    ----------
    model : NarxModel or NarxCommittee
        Fitted; the cache empties itself if the model is refitted.
    max_bytes : int
        Runs kept at most (least recently used dropped first), in bytes of float64.

    Attributes
    ----------
    hits, misses : int
        Calls that found their run, and calls that ran it.
    """

    def __init__(self, model: NarxModel | NarxCommittee, max_bytes: int = 64 * 2**20):
        check_fitted(model, "regressor_")
        if not max_bytes > 0:
            raise ValueError(f"max_bytes must be > 0, got {max_bytes}")
        self.model = model
        self.max_bytes = int(max_bytes)
        self._regressor = model.regressor_
        self._runs: OrderedDict = OrderedDict()
        self._bytes = 0
        self.hits = 0
        self.misses = 0

    def simulate(self, u, y_init=None) -> np.ndarray:
        """:meth:`NarxModel.simulate` of the cache's model (mm), looked up if run before."""
        m = self.model
        us, y0 = m._run_inputs(u, y_init)
        us = np.ascontiguousarray(us)
        if m.regressor_ is not self._regressor:  # refitted since: every run is stale
            self._runs.clear()
            self._bytes = 0
            self._regressor = m.regressor_
        recurrent = m.out_delays_.size > 0
        h = hashlib.blake2b(us.view(np.uint8), digest_size=16)
        if recurrent:
            h.update(y0.tobytes())
        key = (us.shape, h.digest())
        z = self._runs.get(key)
        if z is None:
            self.misses += 1
            z = m._free_run(us, y0)
            self._runs[key] = z
            self._bytes += z.nbytes
            while self._bytes > self.max_bytes and len(self._runs) > 1:
                self._bytes -= self._runs.popitem(last=False)[1].nbytes
        else:
            self.hits += 1
            self._runs.move_to_end(key)
        z = z.copy()
        z[: m.max_lag_] = m._scale_y(y0)
        return m._unscale_y(z)


class NarxStepper:
    """One NARX step per call: free run, or one-step when measurements are fed back.

    ``step(u_k) -> y_k`` predicts from the stored history and appends the prediction;
    ``correct_output(y_measured_k)`` replaces that last output by a measurement (then the
    next step is a one-step-ahead prediction). Cost per step: one kernel row plus a few
    small array copies.

    With voltage channels, ``step`` takes the voltage (a float, V) and advances the channels'
    filters itself, and ``u_history`` is the past voltage (N_h,) (filtered from rest over it).

    Parameters
    ----------
    model : fitted NarxModel
    u_history, y_history : array_like, optional
        Past inputs (N_h,) or (N_h, c) and outputs (N_h,), oldest first, physical units; the
        missing past is the rest state 0 V / 0 mm.
    """

    def __init__(self, model: NarxModel, u_history=None, y_history=None):
        self._model = model
        self._channels = model.uses_voltage_channels
        self._a = model.voltage_poles() if self._channels else np.zeros(0)
        self._raw = int(bool(model.include_voltage))
        self._mem = np.zeros(self._a.size)
        self._ch = np.empty(model.n_inputs_)
        self._f = model.regressor_.predict_one
        self._u_mean = np.asarray(model.u_mean_, dtype=float)
        self._u_scale = np.asarray(model.u_scale_, dtype=float)
        c = model.n_inputs_
        # Newest-first buffers; between steps _ub[j] = u_{k-1-j} and _yb[j] = y_{k-1-j}, k being
        # the next sample. step() shifts _ub first, so then _ub[d] = u_{k-d}.
        self._depth_u = 1 + max(int(ds.max()) for ds in model.in_delays_)
        self._depth_y = int(model.out_delays_.max()) if model.out_delays_.size else 1
        self._y_idx = model.out_delays_ - 1
        self._u_idx = [(ds, ch) for ch, ds in enumerate(model.in_delays_)]
        self._ub = np.zeros((self._depth_u, c))
        self._yb = np.zeros(self._depth_y)
        self._du = sum(ds.size for ds in model.in_delays_)
        self._x = np.empty(self._du + model.out_delays_.size)
        self.reset(u_history, y_history)

    def reset(self, u_history=None, y_history=None) -> None:
        """Reload the history (oldest first, physical units); missing past is 0 V / 0 mm."""
        m = self._model
        c = m.n_inputs_
        self._mem[:] = 0.0
        if u_history is None:
            uh = np.zeros((0, c))
        elif self._channels:
            uh = m.input_channels(u_history, "u_history")
            self._mem[:] = uh[-1, self._raw:]
        else:
            uh = _as_inputs("u_history", u_history)
        if uh.shape[1] != c:
            raise ValueError(f"u_history must have {c} channel(s), got {uh.shape[1]}")
        yh = np.zeros(0) if y_history is None else as_signal("y_history", y_history)
        ub = np.zeros((self._depth_u, c))
        tail = uh[::-1][: self._depth_u - 1]
        ub[: tail.shape[0]] = tail
        self._ub[:] = (ub - self._u_mean) / self._u_scale
        yb = np.zeros(self._depth_y)
        tail = yh[::-1][: self._depth_y]
        yb[: tail.size] = tail
        self._yb[:] = m._scale_y(yb)

    def step(self, u_k) -> float:
        """Feed the input u_k (V; a float, or (c,) for several channels); return y_k (mm)."""
        ub, yb, x, du = self._ub, self._yb, self._x, self._du
        if self._channels:
            u = float(u_k)
            a = self._a
            self._mem = a * self._mem + (1.0 - a) * u
            ch = self._ch
            if self._raw:
                ch[0] = u
            ch[self._raw:] = self._mem
            u_k = ch
        ub[1:] = ub[:-1]
        ub[0] = (np.asarray(u_k, dtype=float) - self._u_mean) / self._u_scale
        pos = 0
        for ds, ch in self._u_idx:
            x[pos : pos + ds.size] = ub[ds, ch]
            pos += ds.size
        x[du:] = yb[self._y_idx]
        zk = self._f(x)
        yb[1:] = yb[:-1]
        yb[0] = zk
        return zk * self._model.y_scale_ + self._model.y_mean_

    def correct_output(self, y_measured_k: float) -> None:
        """Replace the last predicted output by the measured one (mm)."""
        self._yb[0] = (float(y_measured_k) - self._model.y_mean_) / self._model.y_scale_


def memory_poles(memory_taus_s, dt_s: float) -> np.ndarray:
    """Discrete poles exp(-dt_s / tau) of memory channels (time constants and period in s)."""
    taus = np.asarray(memory_taus_s, dtype=float)
    if np.any(~np.isfinite(taus)) or np.any(taus <= 0.0):
        raise ValueError(f"memory_taus_s must be positive time constants (s), got "
                         f"{list(memory_taus_s)}")
    if not (dt_s > 0.0 and np.isfinite(dt_s)):
        raise ValueError(f"dt_s must be a positive sample period (s), got {dt_s!r}")
    return np.exp(-dt_s / taus)


def memory_channels(y: np.ndarray, memory_taus_s, dt_s: float) -> np.ndarray:
    """Displacement (N,) -> inverse-model regressor channels: y itself when there are no memory
    channels, else (N, 1 + J): y and y low-passed with each time constant (from rest)."""
    if not len(memory_taus_s):
        return y
    from scipy.signal import lfilter

    cols = [y] + [lfilter([1.0 - a], [1.0, -a], y) for a in memory_poles(memory_taus_s, dt_s)]
    return np.column_stack(cols)


def voltage_channels(u_v, input_memory_taus_s, dt_s: float = 0.01, *,
                     include_voltage: bool = True) -> np.ndarray:
    """Forward-model input channels from a voltage record.

    Parameters
    ----------
    u_v : array_like, shape (N,)
        Applied voltage, V, from rest (the filters start at 0 V).
    input_memory_taus_s : sequence of float
        Time constants of the low-passed voltage channels, s.
    dt_s : float
        Sample period, s.
    include_voltage : bool
        Put the voltage itself first.

    Returns
    -------
    ndarray, shape (N, include_voltage + len(input_memory_taus_s))
        V.
    """
    u = np.asarray(u_v, dtype=float)
    if u.ndim != 1 or not np.all(np.isfinite(u)):
        raise ValueError(f"u_v must be a finite 1-D voltage record (V), got shape {u.shape}")
    if not include_voltage and not len(input_memory_taus_s):
        raise ValueError("no channel: give input_memory_taus_s or include_voltage=True")
    cols = memory_channels(u, tuple(input_memory_taus_s), dt_s)
    cols = cols.reshape(u.size, -1)
    return cols if include_voltage else cols[:, 1:]


class InverseNarxModel:
    """Inverse NARX model u_l = h(y_l..y_{l-n}, u_{l-1}..u_{l-m}, m_1,l..m_J,l) (paper Eq. 19).

    A feedforward compensator: given the desired displacement it returns the voltage. It is a
    :class:`NarxModel` with the roles of the signals swapped (attribute ``narx_``).

    ``memory_taus_s`` adds memory channels: the displacement low-passed with each time constant,
    ``m_j,l = a_j m_j,l-1 + (1 - a_j) y_l``, ``a_j = exp(-dt_s / tau_j)``, fed to the regressor
    beside the lagged displacements. Why: the IPMC relaxes back part of its bending (water
    back-diffusion, tau ~ 0.5 s); the inverse of that relaxation has a pole about twice as slow
    (tau / (1 - share) ~ 1 s), which a few lags spaced tens of ms apart cannot represent and
    past voltages represent only by a free-running recursion that drifts at 100 Hz. A low-passed
    displacement is that pole, fed from the desired trajectory alone, so it cannot drift
    (the orthonormal-basis / Laguerre idea of linear system identification).

    Parameters
    ----------
    regressor : estimator, optional
        As :class:`NarxModel`.
    output_lags : int
        n: past displacements y_{l-1}..y_{l-n} besides y_l (paper: 3).
    input_lags : int
        m: past voltages u_{l-1}..u_{l-m} (paper: 3).
    lag_step, standardize, max_rows
        As :class:`NarxModel`.
    memory_taus_s : sequence of float
        Time constants of the memory channels, s (default none: the paper's structure).
    dt_s : float
        Sample period of the data the model is fitted on and run at, s (the memory channels
        are discretised with it).
    """

    def __init__(self, regressor=None, output_lags: int = 3, input_lags: int = 3,
                 lag_step: int = 1, standardize=True, max_rows: int | None = None,
                 memory_taus_s=(), dt_s: float = 0.01):
        self.regressor = regressor
        self.output_lags = output_lags
        self.input_lags = input_lags
        self.lag_step = lag_step
        self.standardize = standardize
        self.max_rows = max_rows
        self.memory_taus_s = tuple(float(v) for v in memory_taus_s)
        self.dt_s = float(dt_s)
        self.narx_ = None

    def _memory_poles(self) -> np.ndarray:
        return memory_poles(self.memory_taus_s, self.dt_s)

    def _channels(self, y: np.ndarray) -> np.ndarray:
        return memory_channels(y, self.memory_taus_s, self.dt_s)

    def fit(self, u, y) -> InverseNarxModel:
        """Fit on the plant's input ``u`` (V) and output ``y`` (mm); returns self."""
        u = as_signal("u", u)
        y = as_signal("y", y)
        same_length(u=u, y=y)
        # Checked here so that the messages name the physical signals, not the swapped roles.
        if np.ptp(u) == 0.0:
            raise ValueError("u is constant; the model cannot be identified from it")
        if np.ptp(y) == 0.0:
            raise ValueError("y is constant; the model cannot be identified from it")
        self._memory_poles()
        lags = self.output_lags
        if self.memory_taus_s:
            lags = [self.output_lags] + [0] * len(self.memory_taus_s)
        self.narx_ = NarxModel(self.regressor, input_lags=lags,
                               output_lags=self.input_lags, lag_step=self.lag_step,
                               standardize=self.standardize, max_rows=self.max_rows)
        self.narx_.fit(self._channels(y), u)
        return self

    @property
    def max_lag_(self) -> int:
        check_fitted(self, "narx_")
        return self.narx_.max_lag_

    @property
    def regressor_(self):
        check_fitted(self, "narx_")
        return self.narx_.regressor_

    @property
    def history_samples(self) -> int:
        """Past samples a stepper going on from a history needs: the lags, and
        :data:`HISTORY_TAUS` of the longest memory channel's time constant."""
        return samples_to_settle(self.max_lag_, self.memory_taus_s, self.dt_s)

    @property
    def settled_range_mm(self) -> tuple[float, float] | None:
        """The displacements (mm) the inverse was identified on as held ones: the range of its
        slowest memory channel (the displacement low-passed) over its regressor rows, or of
        the displacement itself without one; None for a regressor without stored rows. A
        reference held beyond it asks the inverse to extrapolate."""
        return self._channel_range_mm(len(self.narx_.in_delays_) - 1)

    @property
    def identified_range_mm(self) -> tuple[float, float] | None:
        """The displacements (mm) the inverse was identified on: the range of the displacement
        channel over its regressor rows (transients included); None for a regressor without
        stored rows. A reference beyond it asks the inverse to extrapolate."""
        return self._channel_range_mm(0)

    def _channel_range_mm(self, ch: int) -> tuple[float, float] | None:
        b = self.narx_
        centers = getattr(self.regressor_, "centers_", None)
        if centers is None:
            return None
        start = sum(len(ds) for ds in b.in_delays_[:ch])
        v = centers[:, start:start + len(b.in_delays_[ch])] * b.u_scale_[ch] + b.u_mean_[ch]
        return float(v.min()), float(v.max())

    def predict(self, y, u) -> np.ndarray:
        """One-step inverse: voltage (V) from displacement ``y`` and the measured past ``u``."""
        check_fitted(self, "narx_")
        return self.narx_.predict(self._channels(as_signal("y", y)), u)

    def simulate(self, y_desired, u_init=None) -> np.ndarray:
        """Free-run compensator: voltages (V) for a desired trajectory (mm), from rest."""
        check_fitted(self, "narx_")
        return self.narx_.simulate(self._channels(as_signal("y_desired", y_desired)), u_init)

    def stepper(self, y_history=None, u_history=None) -> InverseStepper:
        """Sample-by-sample compensator for a control loop; see :class:`InverseStepper`."""
        check_fitted(self, "narx_")
        return InverseStepper(self, y_history, u_history)

    def get_params(self) -> dict:
        return {
            "output_lags": self.output_lags,
            "input_lags": self.input_lags,
            "lag_step": self.lag_step,
            "standardize": self.standardize,
            "memory_taus_s": list(self.memory_taus_s),
            "dt_s": self.dt_s,
        }


#: Time constants of history after which a state started from rest is within 0.7 % of one
#: that lived through everything before (exp(-5)): what a stepper's history must span.
HISTORY_TAUS = 5.0


#: How far beyond the displacements an inverse was identified on a reference may go before
#: :func:`out_of_reach` says so: this share of their span.
REACH_TOLERANCE_SHARE = 0.02


def reach_mm(feedforward, held: bool = False) -> tuple[float, float] | None:
    """The displacements (mm) an inverse feedforward was identified on: held ones for a hold
    (``settled_range_mm``), any for a moving reference (``identified_range_mm``). An
    augmented model's feedforward is judged by its inverse. None for a feedforward that does
    not tell (a forward model's inversion, a regressor without stored rows)."""
    # by attribute: effects.AugmentedInverse imports this module
    inverse = getattr(feedforward, "inverse", feedforward)
    if not isinstance(inverse, InverseNarxModel):
        return None
    return inverse.settled_range_mm if held else inverse.identified_range_mm


def out_of_reach(r_mm: float, reach: tuple[float, float] | None) -> bool:
    """Whether a reference ``r_mm`` (mm) lies beyond ``reach`` (:func:`reach_mm`) by more
    than :data:`REACH_TOLERANCE_SHARE` of its span: there the inverse extrapolates."""
    if reach is None:
        return False
    lo, hi = reach
    tol = REACH_TOLERANCE_SHARE * (hi - lo)
    return not lo - tol <= r_mm <= hi + tol


def samples_to_settle(max_lag: int, memory_taus_s, dt_s: float) -> int:
    """Past samples a stepper going on from a history needs: ``max_lag`` for its lags, and
    :data:`HISTORY_TAUS` of the longest memory time constant (s) at the period ``dt_s`` (s)."""
    slow = max((float(t) for t in memory_taus_s), default=0.0)
    return max(int(max_lag), math.ceil(HISTORY_TAUS * slow / float(dt_s)))


#: What a feedforward's voltage history holds after each step: the voltage that reached the
#: actuator (PID included), the feedforward's own output limited to the actuator's range, or
#: its own output as returned (model_server's ``history_voltage``, ``run_tracking``'s).
HISTORY_VOLTAGES = ("applied", "clamped", "model")


class InverseStepper:
    """The inverse model one sample at a time: ``step(y_desired_mm) -> u_v``.

    The history holds past desired displacements and past voltages. By default the voltage the
    model returned is taken as applied; if the loop applies something else (PID correction
    added, 3 V limit), call ``record_applied(u_applied_v)`` after ``step`` so that the next step
    sees the voltage that really went to the actuator.
    """

    def __init__(self, model: InverseNarxModel, y_history=None, u_history=None):
        self._model = model
        self._a = model._memory_poles()
        self._mem = np.zeros(self._a.size)
        self._inner = NarxStepper(model.narx_)
        self.reset(y_history, u_history)

    def reset(self, y_history=None, u_history=None) -> None:
        """Reload the history (oldest first; mm and V); missing past is 0 mm / 0 V."""
        if y_history is None or not self._a.size:
            self._mem[:] = 0.0
            self._inner.reset(y_history, u_history)
            return
        channels = self._model._channels(as_signal("y_history", y_history))
        self._mem[:] = channels[-1, 1:]
        self._inner.reset(channels, u_history)

    def step(self, y_desired_mm: float) -> float:
        """Desired displacement y_k (mm) -> feedforward voltage u_k (V)."""
        if not self._a.size:
            return self._inner.step(y_desired_mm)
        y = float(y_desired_mm)
        self._mem = self._a * self._mem + (1.0 - self._a) * y
        return self._inner.step(np.concatenate(([y], self._mem)))

    def record_applied(self, u_applied_v: float) -> None:
        """Replace the last returned voltage in the history by the applied one (V)."""
        self._inner.correct_output(u_applied_v)
