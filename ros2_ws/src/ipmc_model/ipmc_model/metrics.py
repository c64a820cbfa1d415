"""Error metrics of a model output against a measurement, in the units of the signal (mm or V).

Every metric skips the first ``skip`` samples: for a NARX model these are the initial
conditions (the first max-lag samples), which the model copies instead of predicting.
"""

from __future__ import annotations

import numpy as np

from ipmc_driver.validation import as_signal, same_length

METRIC_KEYS = ("rmse", "nrmse", "fit_percent", "max_abs")


def _pair(y, y_hat, skip: int) -> tuple[np.ndarray, np.ndarray]:
    y = as_signal("y", y)
    y_hat = as_signal("y_hat", y_hat)
    same_length(y=y, y_hat=y_hat)
    skip = int(skip)
    if skip < 0 or skip >= y.size:
        raise ValueError(f"skip must be in [0, {y.size - 1}], got {skip}")
    return y[skip:], y_hat[skip:]


def rmse(y, y_hat, skip: int = 0) -> float:
    """Root-mean-square error sqrt(mean((y - y_hat)^2)) over samples ``skip:``, units of ``y``."""
    y, y_hat = _pair(y, y_hat, skip)
    return float(np.sqrt(np.mean((y - y_hat) ** 2)))


def nrmse(y, y_hat, skip: int = 0) -> float:
    """RMSE divided by the range (max - min) of the measured ``y`` (dimensionless).

    Returns ``inf`` for a constant measurement with a nonzero error, 0 if both are equal.
    """
    y, y_hat = _pair(y, y_hat, skip)
    err = float(np.sqrt(np.mean((y - y_hat) ** 2)))
    span = float(np.ptp(y))
    if span == 0.0:
        return 0.0 if err == 0.0 else float("inf")
    return err / span


def fit_percent(y, y_hat, skip: int = 0) -> float:
    """Fit in percent, 100 (1 - ||y - y_hat|| / ||y - mean(y)||), as MATLAB's ``compare``.

    100 is a perfect model, 0 is as good as the mean, negative is worse than the mean.
    """
    y, y_hat = _pair(y, y_hat, skip)
    den = float(np.linalg.norm(y - y.mean()))
    num = float(np.linalg.norm(y - y_hat))
    if den == 0.0:
        return 100.0 if num == 0.0 else float("-inf")
    return 100.0 * (1.0 - num / den)


def max_abs(y, y_hat, skip: int = 0) -> float:
    """Largest absolute error max|y - y_hat| over samples ``skip:``, units of ``y``."""
    y, y_hat = _pair(y, y_hat, skip)
    return float(np.max(np.abs(y - y_hat)))


def score(y, y_hat, skip: int = 0) -> dict:
    """All four metrics as a dict with the keys of :data:`METRIC_KEYS`.

    Parameters
    ----------
    y, y_hat : array_like, shape (N,)
        Measured and modelled signal, same units.
    skip : int
        Number of leading samples left out (initial conditions).
    """
    return {
        "rmse": rmse(y, y_hat, skip),
        "nrmse": nrmse(y, y_hat, skip),
        "fit_percent": fit_percent(y, y_hat, skip),
        "max_abs": max_abs(y, y_hat, skip),
    }


def effective_samples(e: np.ndarray) -> float:
    """n / (1 + 2 sum rho_k): the residual's samples worth of independent ones, the
    autocorrelations summed up to the first that is not positive (Geyer's initial positive
    sequence); a slow residual has few."""
    e = e - e.mean()
    f = np.fft.rfft(e, 2 * e.size)
    acf = np.fft.irfft(f * np.conj(f))[:e.size]
    acf = acf / acf[0]
    stop = int(np.argmax(acf[1:] <= 0)) + 1 if np.any(acf[1:] <= 0) else e.size
    return float(e.size / max(1.0, 1.0 + 2.0 * acf[1:stop].sum()))


def independent_samples(rows: np.ndarray, block_rows: float) -> int:
    """Independent samples among ``rows`` (sorted sample indices) of a signal correlated over
    ``block_rows`` samples: each run of rows (gaps below ``block_rows`` joined) counts one,
    and one more per ``block_rows`` it lasts."""
    if rows.size == 0:
        return 0
    breaks = np.flatnonzero(np.diff(rows) > block_rows)
    starts, ends = rows[np.r_[0, breaks + 1]], rows[np.r_[breaks, rows.size - 1]]
    return int(np.sum(1 + (ends - starts) // block_rows))
