"""Residual analysis of a model: correlation, spectrum, whiteness, and an online monitor.

Pure NumPy/SciPy (no ROS). The conventions follow MATLAB's ``resid`` and sysidentpy's residual
validation: the sample autocorrelation of the residual e and the cross-correlation of the input u
with e, normalised to [-1, 1], with 95 % confidence bounds +-1.96 / sqrt(N) under the null
hypothesis that e is white and independent of u. A good model leaves a residual whose ACF
(lags >= 1) and CCF stay inside the bounds.

For strongly autocorrelated signals (a free-run residual, a slowly varying signature) the
simple bound is far too tight; :func:`correlation_test` uses Bartlett's formula for the variance
of a sample correlation between two autocorrelated series, sum_k rho_e(k) rho_s(k) / N, which is
what MATLAB's ``resid`` does for the CCF.

:class:`ResidualMonitor` takes residual samples one at a time (from a 100 Hz loop) and says
when the model has gone stale (drift, dehydration): the free-run residual's window mean has moved
away from its value just after the fit (``test="drift"``), or the one-step residual stopped being
white (Ljung-Box on a sliding window, ``test="whiteness"``).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace

import numpy as np
from scipy import signal as sps
from scipy import stats

from ipmc_driver.validation import as_signal, same_length

#: Tests of :class:`ResidualMonitor`.
MONITOR_TESTS = ("whiteness", "drift", "both")
#: Two-sided 95 % quantile of the standard normal distribution.
Z95 = float(stats.norm.ppf(0.975))
#: Holds (:func:`find_holds`): the input within this share of its range of the hold's start.
HOLD_TOL_FRACTION = 0.005
#: Start of a hold skipped by :func:`hold_drift_test` (s): the simulated IPMC's fast response
#: (charging, back-relaxation tau 0.46 s) has settled to < 0.01 mm 3 s after a 4 V step.
HOLD_SKIP_S = 3.0
#: Smallest share of the predicted within-hold drift (lower confidence bound) that counts as
#: creep in time (:func:`hold_drift_test`).
HOLD_BETA_MIN = 0.25


def _xcorr(a: np.ndarray, b: np.ndarray, max_lag: int) -> np.ndarray:
    """r_ab(k) = sum_t a_t b_{t+k} / (N sd_a sd_b) for k = -max_lag..max_lag (means removed)."""
    n = a.size
    a = a - a.mean()
    b = b - b.mean()
    den = n * a.std() * b.std()
    if den == 0.0:
        return np.zeros(2 * max_lag + 1)
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    full = np.fft.irfft(np.conj(np.fft.rfft(a, nfft)) * np.fft.rfft(b, nfft), nfft)
    # full[k] = sum_t a_t b_{t+k}; negative k wrap to the end
    r = np.concatenate([full[nfft - max_lag:], full[: max_lag + 1]]) if max_lag else full[:1]
    return r / den


def _check_lag(max_lag: int, n: int) -> int:
    max_lag = int(max_lag)
    if max_lag < 1 or max_lag >= n:
        raise ValueError(f"max_lag must be in [1, {n - 1}] for {n} samples, got {max_lag}")
    return max_lag


@dataclass
class Correlation:
    """A correlation function with its confidence bound.

    Attributes
    ----------
    lags : ndarray of int
        Lags in samples.
    values : ndarray
        Normalised correlation at each lag, in [-1, 1].
    bound : float or ndarray
        95 % bound under the null hypothesis (white / independent); scalar or one per lag.
    """

    lags: np.ndarray
    values: np.ndarray
    bound: float | np.ndarray

    def outside(self, skip_zero: bool = False) -> np.ndarray:
        """Boolean mask of lags whose |value| exceeds the bound (lag 0 dropped if asked)."""
        out = np.abs(self.values) > self.bound
        if skip_zero:
            out &= self.lags != 0
        return out

    def fraction_outside(self, skip_zero: bool = True) -> float:
        """Share of lags (lag 0 excluded by default) outside the bound; ~0.05 if white."""
        keep = self.lags != 0 if skip_zero else np.ones(self.lags.size, bool)
        return float(np.mean(self.outside()[keep])) if keep.any() else 0.0


def acf(e, max_lag: int = 25) -> Correlation:
    """Sample autocorrelation of the residual ``e`` (N,) at lags 0..max_lag with +-1.96/sqrt(N).

    As MATLAB ``resid`` / sysidentpy: normalised by the lag-0 value; lag 0 is 1 by definition.
    """
    e = as_signal("e", e, min_length=3)
    max_lag = _check_lag(max_lag, e.size)
    r = _xcorr(e, e, max_lag)[max_lag:]
    return Correlation(np.arange(max_lag + 1), r, Z95 / np.sqrt(e.size))


def ccf(u, e, max_lag: int = 25, bound: str = "simple") -> Correlation:
    """Cross-correlation r_ue(k) = corr(u_t, e_{t+k}) at lags -max_lag..max_lag.

    Positive lags: the input leads the residual (an effect of past inputs the model missed,
    e.g. a transport delay); negative lags: the residual leads the input (feedback).

    Parameters
    ----------
    u, e : array_like, shape (N,)
        Input (V) and residual (mm).
    max_lag : int
        Largest lag in samples.
    bound : {"simple", "bartlett"}
        ``"simple"``: +-1.96/sqrt(N) (sysidentpy); ``"bartlett"``: +-1.96 sqrt(sum_k
        rho_u(k) rho_e(k) / N), which accounts for a coloured input and residual (MATLAB
        ``resid``).
    """
    u = as_signal("u", u, min_length=3)
    e = as_signal("e", e, min_length=3)
    same_length(u=u, e=e)
    max_lag = _check_lag(max_lag, u.size)
    r = _xcorr(u, e, max_lag)
    if bound == "simple":
        b = Z95 / np.sqrt(u.size)
    elif bound == "bartlett":
        b = _bartlett_bound(u, e, max_lag)
    else:
        raise ValueError(f"bound must be 'simple' or 'bartlett', got {bound!r}")
    return Correlation(np.arange(-max_lag, max_lag + 1), r, b)


def _bartlett_bound(a: np.ndarray, b: np.ndarray, max_lag: int) -> float:
    ra = _xcorr(a, a, max_lag)
    rb = _xcorr(b, b, max_lag)
    var = max(float(np.sum(ra * rb)), 1.0) / a.size
    return Z95 * float(np.sqrt(var))


def correlation_test(e, s, max_lag: int | None = None) -> dict:
    """Is the residual ``e`` correlated with a signature ``s``? Lag-0 test with Bartlett's bound.

    Both series may be strongly autocorrelated (a free-run residual, a slow creep signature), so
    the bound is 1.96 sqrt(sum_{|k| <= K} rho_e(k) rho_s(k) / N) rather than 1.96 / sqrt(N);
    K = ``max_lag`` (default N // 4).

    Returns
    -------
    dict
        ``{"r": correlation, "bound": 95 % bound, "significant": |r| > bound,
        "ratio": |r| / bound}``
    """
    e = as_signal("e", e, min_length=8)
    s = as_signal("s", s, min_length=8)
    same_length(e=e, s=s)
    n = e.size
    K = n // 4 if max_lag is None else _check_lag(max_lag, n)
    if e.std() == 0.0 or s.std() == 0.0:
        return {"r": 0.0, "bound": 1.0, "significant": False, "ratio": 0.0}
    r = float(np.corrcoef(e, s)[0, 1])
    b = _bartlett_bound(e, s, K)
    return {"r": r, "bound": b, "significant": bool(abs(r) > b), "ratio": abs(r) / b}


def block_jackknife_coef(e, X, blocks: int = 20) -> dict:
    """Least-squares coefficient of ``X``'s first column for ``e``, with a 95 % one-sided lower
    bound from a delete-one-block jackknife over ``blocks`` contiguous blocks.

    A slow, autocorrelated residual makes the ordinary least-squares standard error far too
    small: a few slow swings look like a trend. Leaving out one block at a time lets the scatter
    of the slow swings set the error instead (Kunsch's block jackknife). Written here because
    SciPy has no block jackknife and the project does not depend on statsmodels (HAC errors).

    Parameters
    ----------
    e : array_like, shape (N,)
        Response (a residual, mm).
    X : array_like, shape (N, p)
        Regressors; column 0 is the one tested, the others are nuisance terms.
    blocks : int
        Number of contiguous blocks (>= 3).

    Returns
    -------
    dict
        ``coef``, ``se`` (jackknife standard error), ``lower`` (coef - t_0.95(blocks - 1) se),
        ``blocks``.
    """
    e = as_signal("e", e, min_length=8)
    X = np.asarray(X, dtype=float)
    if X.ndim != 2 or X.shape[0] != e.size:
        raise ValueError(f"X must be ({e.size}, p), got {X.shape}")
    k = int(blocks)
    if k < 3 or e.size < 2 * k * X.shape[1]:
        raise ValueError(f"{e.size} samples cannot make {k} blocks for {X.shape[1]} regressors")
    if not np.all(np.isfinite(X)):
        raise ValueError("X must be finite")
    coef = float(np.linalg.lstsq(X, e, rcond=None)[0][0])
    parts = np.array_split(np.arange(e.size), k)
    loo = np.empty(k)
    for i in range(k):
        keep = np.concatenate(parts[:i] + parts[i + 1:])
        loo[i] = np.linalg.lstsq(X[keep], e[keep], rcond=None)[0][0]
    se = float(np.sqrt((k - 1) / k * np.sum((loo - loo.mean()) ** 2)))
    return {"coef": coef, "se": se, "lower": coef - float(stats.t.ppf(0.95, k - 1)) * se,
            "blocks": k}


def travel_low_pass(u, travel_v: float) -> np.ndarray:
    """The input (V) low-passed over its travel: m_k = m_{k-1} + w_k (u_k - m_{k-1}),
    w_k = min(1, |u_k - u_{k-1}| / ``travel_v``), from rest (u and m 0 before the record, as
    the models' other states).

    It forgets only while the input moves, about 1/e of the past per ``travel_v`` volts of
    travel, and holds still during input holds however long: a rate-independent memory, as a
    hysteresis has (a Bouc-Wen state forgets in proportion to |du|), unlike a low-pass in time.
    A time-varying recursion, so a loop (no SciPy filter takes per-sample coefficients).
    """
    u = as_signal("u", u, min_length=1)
    if not (np.isfinite(travel_v) and travel_v > 0):
        raise ValueError(f"travel_v must be a finite number of volts > 0, got {travel_v}")
    w = np.minimum(1.0, np.abs(np.diff(u, prepend=0.0)) / float(travel_v))
    m = np.empty(u.size)
    acc = 0.0
    for k, (wk, uk) in enumerate(zip(w.tolist(), u.tolist(), strict=True)):
        acc += wk * (uk - acc)
        m[k] = acc
    return m


def spectrum(e, rate_hz: float, nperseg: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Power spectral density of ``e`` by Welch's method (``scipy.signal.welch``, Hann window).

    Returns
    -------
    (f_hz, psd) : ndarrays
        Frequencies (Hz) and PSD (units of e squared per Hz, e.g. mm^2/Hz).
    """
    e = as_signal("e", e, min_length=8)
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
    nper = min(e.size, 1024) if nperseg is None else int(nperseg)
    return sps.welch(e - e.mean(), fs=float(rate_hz), nperseg=nper)


def low_frequency_share(e, rate_hz: float, f_cut_hz: float) -> float:
    """Share of the residual's power below ``f_cut_hz`` (Welch PSD); near the bandwidth share
    2 f_cut / rate for white noise, near 1 for a slow (creep, drift) residual."""
    f, p = spectrum(e, rate_hz, nperseg=min(as_signal("e", e).size, 4096))
    total = float(np.sum(p))
    return float(np.sum(p[f <= f_cut_hz]) / total) if total > 0 else 0.0


def noise_floor(y) -> float:
    """RMS of the measurement noise in ``y`` (same unit, mm), from the record itself.

    The second difference of a smooth signal sampled well above its bandwidth is noise: for
    white noise of RMS s its RMS is sqrt(6) s. The median absolute deviation keeps steps and
    fast transients out. On the simulated plant (noise 0.005 mm, quantisation 0.01 mm: 0.0058
    mm) it gives 0.0061 mm on random sines, steps and mixed inputs at 50 and 100 Hz.
    """
    d = np.diff(as_signal("y", y), 2)
    if d.size < 3:
        raise ValueError("noise_floor needs at least 5 samples")
    return float(stats.median_abs_deviation(d, scale="normal") / np.sqrt(6.0))


def ljung_box(e, lags: int = 20, n_params: int = 0) -> dict:
    """Ljung-Box portmanteau test of whiteness.

    Q = N (N + 2) sum_{k=1}^{h} r_k^2 / (N - k), chi-squared with h - ``n_params`` degrees of
    freedom under the null hypothesis "e is white".

    Returns
    -------
    dict
        ``{"q": Q, "dof": h - n_params, "p_value": p, "lags": h}``; a small p (< 0.05) rejects
        whiteness.
    """
    e = as_signal("e", e, min_length=4)
    h = _check_lag(lags, e.size)
    r = _xcorr(e, e, h)[h + 1:]
    n = e.size
    q = float(n * (n + 2) * np.sum(r * r / (n - np.arange(1, h + 1))))
    dof = max(h - int(n_params), 1)
    return {"q": q, "dof": dof, "p_value": float(stats.chi2.sf(q, dof)), "lags": h}


def whiteness_summary(e, u=None, max_lag: int = 25) -> dict:
    """One dict of the residual tests: RMS, ACF/CCF shares outside the 95 % bounds, Ljung-Box.

    ``u`` (the input) adds the CCF; every value is a plain float (JSON-ready).
    """
    e = as_signal("e", e, min_length=max_lag + 2)
    out = {"rms": float(np.sqrt(np.mean(e * e))), "samples": int(e.size)}
    out["acf_outside"] = acf(e, max_lag).fraction_outside()
    lb = ljung_box(e, max_lag)
    out["ljung_box_q"], out["ljung_box_p"] = lb["q"], lb["p_value"]
    if u is not None:
        out["ccf_outside"] = ccf(u, e, max_lag).fraction_outside(skip_zero=False)
    return out


def find_holds(u, dt_s: float, min_s: float, tol_fraction: float = HOLD_TOL_FRACTION
               ) -> list[tuple[int, int]]:
    """Input holds: maximal runs [start, stop) (samples) in which the input ``u`` (V) stays within
    ``tol_fraction`` of its range of the run's first value, at least ``min_s`` seconds long.

    The tolerance is small on purpose: the IPMC answers a 0.09 V step with a 0.25 mm transient,
    so a loose tolerance would call a small step a hold; a sine riding on a step is no hold either
    (it keeps moving the Bouc-Wen hysteresis, which then settles in time: docs/diagnose.md).
    """
    u = as_signal("u", u)
    if not dt_s > 0:
        raise ValueError(f"dt_s must be > 0, got {dt_s}")
    tol = float(tol_fraction) * float(np.ptp(u))
    n_min = max(1, int(np.ceil(min_s / dt_s - 1e-9)))
    holds, start = [], 0
    for k in range(1, u.size + 1):
        if k == u.size or abs(u[k] - u[start]) > tol:
            if k - start >= n_min:
                holds.append((start, k))
            start = k
    return holds


def hold_basis(t_s, fast_tau_s: float | None = None) -> np.ndarray:
    """Orthonormal columns (n, 1 or 2) spanning a constant and, with ``fast_tau_s`` (s), the
    fast settling ``exp(-t / fast_tau_s)`` over a hold's samples at ``t_s`` (s since the hold
    began): what the hold test, the creep's hold fit and the creep figure take off each hold
    (``x - Q @ (Q.T @ x)``)."""
    t = np.asarray(t_s, dtype=float)
    cols = [np.ones(t.size)] + ([] if fast_tau_s is None else [np.exp(-t / fast_tau_s)])
    return np.linalg.qr(np.column_stack(cols))[0]


def hold_drift_test(r, x, u, dt_s: float, *, skip_s: float = HOLD_SKIP_S,
                    min_use_s: float = 1.0, beta_min: float = HOLD_BETA_MIN,
                    alpha: float = 0.05, min_holds: int = 3,
                    fast_tau_s: float | None = None, nuisance=None) -> dict:
    """Does the residual ``r`` (mm) keep drifting during input holds as the signal ``x`` (mm)
    predicts? The time-behaviour evidence of creep.

    During each hold of ``u`` (:func:`find_holds`), from ``skip_s`` after its start (the fast
    dynamics have settled) to its end, r and x are taken relative to their hold means, and
    r = beta x + e is fitted by least squares over all holds. A per-hold constant absorbs what
    path memory (rate-independent hysteresis) leaves: a hold-dependent offset, but no drift in
    time. beta is the share of the predicted within-hold drift that is in the residual (1: all of
    it; 0: the residual stays flat). Its standard error is cluster-robust by hold (residuals
    within a hold are autocorrelated, holds nearly independent), the 1 - ``alpha`` lower
    confidence bound uses Student's t with G - 1 degrees of freedom (G holds).

    Significant: at least ``min_holds`` usable holds (>= ``min_use_s`` of finite r after the
    skip) and the lower bound of beta above ``beta_min``: statistical significance alone is not
    enough on a nearly noise-free residual (the clean plant's last hundredths of a millimetre of
    settling are "significant" against 0).

    With ``fast_tau_s`` the plant's own settling after the input jump is a nuisance too: per
    hold, r and x are taken off a constant *and* ``exp(-(t - t_start) / fast_tau_s)``
    (amplitude free per hold), as in the creep's hold fit
    (:func:`~ipmc_model.effects.fit_creep_on_holds`); then a shorter ``skip_s`` is usable.

    Parameters
    ----------
    r : array_like, shape (N,)
        Residual (mm); NaN samples are skipped.
    x : array_like, shape (N,)
        Predicted drift, e.g. the fitted creep state (mm) on the same samples.
    u : array_like, shape (N,)
        Input (V).
    dt_s : float
        Sample period (s).
    fast_tau_s : float, optional
        Time constant (s) of the per-hold fast exponential nuisance; default none (hold means
        only).
    nuisance : array_like, shape (N,), optional
        A signal with one coefficient over all holds taken off r and x before beta (as in the
        creep's hold fit: the input low-passed at the baseline's memory).

    Returns
    -------
    dict
        ``holds`` (usable G), ``min_holds``, ``min_hold_s`` (the shortest usable hold, s),
        ``beta``, ``se``, ``lower`` (bound), ``significant``, ``text``.
    """
    r = as_signal("r", r, allow_nan=True)
    x = as_signal("x", x, allow_nan=True)
    u = as_signal("u", u)
    if not (r.shape == x.shape == u.shape):
        raise ValueError(f"r, x, u must have the same shape, got {r.shape}, {x.shape}, {u.shape}")
    n = None if nuisance is None else as_signal("nuisance", nuisance)
    if n is not None and n.shape != u.shape:
        raise ValueError(f"nuisance must have the shape of u {u.shape}, got {n.shape}")
    skip = int(round(skip_s / dt_s))
    blocks, nblocks = [], []
    for s, e in find_holds(u, dt_s, skip_s + min_use_s):
        idx = np.arange(s + skip, e)
        idx = idx[np.isfinite(r[idx]) & np.isfinite(x[idx])]
        if idx.size * dt_s < min_use_s:
            continue
        Q = hold_basis((idx - s) * dt_s, fast_tau_s)
        blocks.append((r[idx] - Q @ (Q.T @ r[idx]), x[idx] - Q @ (Q.T @ x[idx])))
        if n is not None:
            nblocks.append(n[idx] - Q @ (Q.T @ n[idx]))
    snn = sum(float(bn @ bn) for bn in nblocks)
    if snn > 0.0:  # Frisch-Waugh: take the nuisance off r and x over all holds
        kr = sum(float(bn @ br) for bn, (br, _) in zip(nblocks, blocks, strict=True)) / snn
        kx = sum(float(bn @ bx) for bn, (_, bx) in zip(nblocks, blocks, strict=True)) / snn
        blocks = [(br - kr * bn, bx - kx * bn)
                  for bn, (br, bx) in zip(nblocks, blocks, strict=True)]
    G = len(blocks)
    out = {"holds": G, "beta": float("nan"), "se": float("nan"), "lower": float("nan"),
           "significant": False, "skip_s": float(skip_s), "beta_min": float(beta_min),
           "min_holds": int(min_holds), "min_hold_s": float(skip_s + min_use_s)}
    sxx = sum(float(bx @ bx) for _, bx in blocks)
    if G < min_holds or sxx <= 0.0:
        out["text"] = (f"drift during holds: {G} usable input hold(s) (constant input for >= "
                       f"{skip_s + min_use_s:g} s), needs {min_holds}: creep cannot be told "
                       "from path memory without holds")
        return out
    beta = sum(float(bx @ br) for br, bx in blocks) / sxx
    meat = sum(float(bx @ (br - beta * bx)) ** 2 for br, bx in blocks)
    se = float(np.sqrt(meat * G / (G - 1))) / sxx
    lower = beta - float(stats.t.ppf(1.0 - alpha, G - 1)) * se
    out.update(beta=beta, se=se, lower=lower, significant=bool(lower > beta_min))
    fast = "" if fast_tau_s is None else f", fast settling tau {fast_tau_s:g} s removed"
    out["fast_tau_s"] = None if fast_tau_s is None else float(fast_tau_s)
    out["text"] = (f"drift during {G} input holds (after {skip_s:g} s{fast}): residual follows "
                   f"{beta:.2f} +- {se:.2f} of the predicted drift, {100 * (1 - alpha):.0f} % "
                   f"lower bound {lower:.2f}, needs > {beta_min:g}")
    return out


@dataclass
class MonitorStatus:
    """What :meth:`ResidualMonitor.update` says after a sample.

    Attributes
    ----------
    level : int
        0 OK, 1 WARN (latest check not white), 2 STALE (``patience`` checks in a row not
        white); ``diagnostic_msgs/DiagnosticStatus`` levels OK / WARN / ERROR.
    message : str
        One sentence for ``DiagnosticStatus.message``.
    white : bool or None
        Result of the latest whiteness check; None before the window is full.
    p_value : float
        Ljung-Box p-value of the latest check (NaN before the first).
    rms : float
        RMS of the residual in the window (units of the residual).
    mean : float
        Mean of the residual in the window (a bias: offset drift).
    samples : int
        Samples seen since the last reset.
    spread : float
        Standard deviation of the residual in the window.
    reference_mean, reference_spread : float
        Mean m0 and standard deviation s0 of the reference residual (drift test; NaN until the
        reference is complete).
    shift : float
        ``mean - reference_mean``, the drift test's statistic (NaN before the reference).
    shift_limit, spread_limit : float
        The drift test's thresholds ``bias_factor * s0`` on |shift| and ``growth * s0`` on
        spread (NaN before the reference).
    q, q_limit : float
        Ljung-Box statistic of the latest check and its critical value at ``alpha``.
    failed : int
        Consecutive failed checks.
    reference_samples : int
        Samples in the reference so far (after decimation).
    """

    level: int
    message: str
    white: bool | None
    p_value: float
    rms: float
    mean: float
    samples: int
    spread: float = float("nan")
    reference_mean: float = float("nan")
    reference_spread: float = float("nan")
    shift: float = float("nan")
    shift_limit: float = float("nan")
    spread_limit: float = float("nan")
    q: float = float("nan")
    q_limit: float = float("nan")
    failed: int = 0
    reference_samples: int = 0


class ResidualMonitor:
    """Streaming whiteness check of a model residual: flags when the model goes stale.

    Keeps the last ``window`` residual samples; every ``check_every`` samples (once the window
    is full) it runs a Ljung-Box test on them (``lags`` lags, level ``alpha``) and a bias test
    (|mean| > 1.96 sd / sqrt(window / (1 + 2 sum_k r_k)), the mean's bound under the window's
    own autocorrelation). One failed check gives WARN; ``patience`` failed checks in a row give
    STALE; one passed check returns to OK.

    Feed it the one-step residual (measured - predicted, as on ``/ipmc/residual``) decimated
    to the model's bandwidth if the sample rate is far above it (``decimate``): at 100 Hz a
    one-step residual of a good model is close to white, a stale one (drift) is not.

    ``test="drift"`` is for the *free-run* residual (measured minus the model's simulation from
    the input alone), which is never white, so a whiteness test flags a good model too: the
    first ``reference`` samples after a reset (the freshly fitted model) give the residual's
    normal mean m0 and spread s0 (standard deviation); a check fails when the window's mean
    moves by more than ``bias_factor`` s0 from m0 (offset drift, dehydration) or its spread
    exceeds ``growth`` s0 (gain drift). ``"both"`` runs both tests.

    The drift defaults (``bias_factor`` 1.5, no spread test) were measured on the simulated
    plant at 100 Hz with ``decimate=10, window=600, reference=1200`` (a 60 s window against
    the first 120 s after the fit): on a clean plant the free-run residual's window mean
    wandered up to 1.24 s0 and its spread up to 2.4 s0 in 30 min (seeds 0-7), because the
    model error depends on what the input visits (at 0.75 and ``growth`` 1.5, four of six
    clean runs were flagged within 30 min). The plant's drift (3 %/min gain loss, 0.05 mm/min
    offset) moved the mean past 1.5 s0 in 3-10 min, while its spread stayed within what the
    clean plant shows, so the spread test only adds false alarms there. On 8 held-out seeds
    (8-15) two clean runs were flagged (after 12 and 22 min): a false alarm per ~4 h.

    Parameters
    ----------
    window : int
        Samples in the sliding window (after decimation).
    lags : int
        Ljung-Box lags h.
    alpha : float
        Test level (0.01: one false WARN in ~100 checks on a white residual).
    check_every : int
        Samples between checks (after decimation).
    patience : int
        Consecutive failed checks before STALE.
    decimate : int
        Keep every ``decimate``-th sample.
    test : {"whiteness", "drift", "both"}
        Ljung-Box and bias on the window (one-step residual; the default, as before), the
        reference drift test (free-run residual), or both.
    reference : int, optional
        Samples (after decimation) after a reset that define the normal residual (drift
        test); default ``window``.
    bias_factor : float
        Mean shift, in reference spreads, that fails the drift test.
    growth : float or None
        Spread ratio to the reference that fails the drift test; None: no spread test.
    unit : str
        Unit of the residual, for the messages (e.g. ``"mm"``).

    Examples
    --------
    >>> mon = ResidualMonitor(window=400, lags=20)
    >>> for e_mm in residual_stream:            # doctest: +SKIP
    ...     status = mon.update(e_mm)
    ...     if status.level == 2:
    ...         publish_stale(status.message)
    """

    def __init__(self, window: int = 500, lags: int = 20, alpha: float = 0.01,
                 check_every: int = 50, patience: int = 3, decimate: int = 1, *,
                 test: str = "whiteness", reference: int | None = None,
                 bias_factor: float = 1.5, growth: float | None = None, unit: str = ""):
        if int(window) < 20:
            raise ValueError(f"window must be >= 20 samples, got {window}")
        if not 1 <= int(lags) < int(window) // 2:
            raise ValueError(f"lags must be in [1, window/2), got {lags} for window {window}")
        if not 0.0 < float(alpha) < 0.5:
            raise ValueError(f"alpha must be in (0, 0.5), got {alpha}")
        if int(check_every) < 1 or int(patience) < 1 or int(decimate) < 1:
            raise ValueError("check_every, patience and decimate must be integers >= 1, got "
                             f"{check_every}, {patience}, {decimate}")
        if test not in MONITOR_TESTS:
            raise ValueError(f"test must be one of {MONITOR_TESTS}, got {test!r}")
        if not (float(bias_factor) > 0 and (growth is None or float(growth) > 1)):
            raise ValueError(f"bias_factor must be > 0 and growth > 1 (or None), got "
                             f"{bias_factor}, {growth}")
        self.test = test
        self.reference = int(window if reference is None else reference)
        if self.reference < 20:
            raise ValueError(f"reference must be >= 20 samples, got {reference}")
        self.bias_factor = float(bias_factor)
        self.growth = None if growth is None else float(growth)
        self.window = int(window)
        self.lags = int(lags)
        self.alpha = float(alpha)
        self.check_every = int(check_every)
        self.patience = int(patience)
        self.decimate = int(decimate)
        self.unit = f" {unit}" if unit else ""
        self._q_crit = float(stats.chi2.isf(self.alpha, self.lags))
        self.reset()

    def reset(self) -> None:
        """Forget the history (after a model update)."""
        self._buf: deque[float] = deque(maxlen=self.window)
        self._ref: list[float] = []
        self._ref_mean = self._ref_rms = float("nan")
        self._n_raw = 0
        self._since_check = 0
        self._failed = 0
        self._status = MonitorStatus(0, "collecting residual samples", None, float("nan"),
                                     float("nan"), float("nan"), 0, q_limit=self._q_crit)

    @property
    def status(self) -> MonitorStatus:
        """The latest status."""
        return self._status

    @property
    def stale(self) -> bool:
        """True when the residual has failed ``patience`` checks in a row."""
        return self._status.level == 2

    def update(self, e) -> MonitorStatus:
        """Add one residual sample (a float, units of the residual); return the status.

        A non-finite sample is skipped (a dropped measurement must not poison the window).
        """
        self._n_raw += 1
        e = float(e)
        if not np.isfinite(e) or (self._n_raw - 1) % self.decimate:
            return self._status
        self._buf.append(e)
        if len(self._ref) < self.reference:
            self._ref.append(e)
            if len(self._ref) == self.reference:
                x = np.asarray(self._ref)
                self._ref_mean = float(x.mean())
                self._ref_rms = float(np.sqrt(np.mean((x - x.mean()) ** 2)))
        self._since_check += 1
        if len(self._buf) == self.window and self._since_check >= self.check_every:
            self._since_check = 0
            self._check()
        else:
            self._status = replace(self._status, samples=self._n_raw,
                                   reference_samples=len(self._ref))
            if self.test == "drift" and len(self._ref) < self.reference:
                self._status.message = (f"measuring the reference residual ({len(self._ref)}/"
                                        f"{self.reference} samples)")
        return self._status

    def update_many(self, e) -> MonitorStatus:
        """Add several samples in order; return the final status."""
        for v in np.asarray(e, dtype=float).reshape(-1):
            self.update(v)
        return self._status

    def _check(self) -> None:
        x = np.fromiter(self._buf, float, len(self._buf))
        n = x.size
        mean = float(x.mean())
        rms = float(np.sqrt(np.mean(x * x)))
        spread = float(np.sqrt(np.mean((x - mean) ** 2)))
        r = _xcorr(x, x, self.lags)[self.lags + 1:]
        q = float(n * (n + 2) * np.sum(r * r / (n - np.arange(1, self.lags + 1))))
        p = float(stats.chi2.sf(q, self.lags))
        u = self.unit
        stat = dict(spread=spread, q=q, q_limit=self._q_crit,
                    reference_samples=len(self._ref))
        reasons = []
        if self.test in ("whiteness", "both"):
            # Bias: the mean's bound with the window's own autocorrelation (effective size).
            n_eff = n / max(1.0 + 2.0 * float(np.sum(np.clip(r, 0.0, None))), 1.0)
            biased = (spread > 0 and abs(mean) > Z95 * spread / np.sqrt(n_eff)
                      and abs(mean) > 0.5 * spread)
            if q > self._q_crit:
                reasons.append(f"not white: Ljung-Box Q {q:.4g} > {self._q_crit:.4g} "
                               f"(p = {p:.3g})")
            if biased:
                reasons.append(f"bias {mean:.4g}{u}")
        drift_ready = len(self._ref) >= self.reference
        if self.test in ("drift", "both") and drift_ready:
            s0 = max(self._ref_rms, 1e-12)
            shift = mean - self._ref_mean
            spread_limit = float("inf") if self.growth is None else self.growth * s0
            stat.update(reference_mean=self._ref_mean, reference_spread=s0, shift=shift,
                        shift_limit=self.bias_factor * s0, spread_limit=spread_limit)
            if abs(shift) > self.bias_factor * s0:
                reasons.append(f"residual mean moved {shift:+.3g}{u} from {self._ref_mean:.3g}"
                               f"{u} (|shift| > {self.bias_factor:g} x reference spread "
                               f"{s0:.3g}{u} = {self.bias_factor * s0:.3g}{u})")
            if spread > spread_limit:
                reasons.append(f"residual spread grew to {spread:.3g}{u} (> {self.growth:g} x "
                               f"reference spread {s0:.3g}{u} = {self.growth * s0:.3g}{u})")
        if self.test == "drift" and not drift_ready:
            self._status = MonitorStatus(
                0, f"measuring the reference residual ({len(self._ref)}/{self.reference} "
                   "samples)", None, p, rms, mean, self._n_raw, **stat)
            return
        white = not reasons
        self._failed = 0 if white else self._failed + 1
        why = "; ".join(reasons)
        if white:
            if "shift" not in stat:   # whiteness, or "both" before the reference is complete
                msg = f"residual white (Ljung-Box p = {p:.3g}), rms {rms:.4g}{u}"
            else:
                msg = (f"residual as when fitted: mean shift {stat['shift']:+.3g}{u} "
                       f"(limit +-{stat['shift_limit']:.3g}{u}), spread {spread:.3g}{u}")
                if self.growth is not None:
                    msg += f" (limit {stat['spread_limit']:.3g}{u})"
                if self.test == "both":
                    msg += f", Ljung-Box p = {p:.3g}"
            level = 0
        elif self._failed >= self.patience:
            level = 2
            msg = f"model stale: {why} ({self._failed} checks in a row)"
        else:
            level = 1
            msg = f"residual check failed ({self._failed}/{self.patience}): {why}"
        self._status = MonitorStatus(level, msg, white, p, rms, mean, self._n_raw,
                                     failed=self._failed, **stat)
