"""The one decision rule, the same for every effect.

A candidate block is accepted when adding it to the current model (both fitted on the same
fit rows) lowers the held-out free-run squared error significantly and materially:

* the loss differential ``d_k = e_cur_k^2 - e_new_k^2`` over the held-out samples (those
  within the fit part's voltage range, :meth:`DiagnosisRecord.judged_for`: on a record
  played from a proposed experiment, the rows of the effect's own probe), each error taken
  about its mean over its record's held-out rows, is tested by Diebold-Mariano: its mean
  over a HAC (Bartlett, Newey-West) standard error, with the Harvey-Leybourne-Newbold
  small-sample factor, one-sided against Student's t; the bandwidth covers the
  differential's own autocorrelation (a free-run error is slow, so its samples are far from
  independent); the held-out offset, one draw per record, cannot be tested;
* the round's p-values are adjusted by Holm's weighted step-down, holding the family-wise
  error of the candidates the round may accept (the testable ones) at ``family_alpha``; each
  candidate's weight is its z on the fit rows (the square root of their likelihood ratio),
  fixed without the held-out rows: alpha goes where the fit rows see a block, and a
  candidate they barely support does not halve the level of one they show clearly;
* the mean gain must be at least ``material_noise_share`` times the noise floor squared,
  both that of the errors about their means (what the test found significant: a block
  whose tested gain is below the margin is not material however large its untested offset
  gain) and that of the errors as they are (a block must not move the level away).

A candidate the rule does not accept, whose block the fit rows support and whose held-out
gain has the right sign, is undecided rather than rejected when the held-out rows are too
few to decide it: when the test would pass with less than ``min_power`` probability at the
gain the fit rows show (:func:`power`, at its first Holm level). A record with its probe
decides it.

Of the candidates that pass, the round accepts the one with the largest mean gain; the next
round refits the rest around it. Written by hand: SciPy has no Diebold-Mariano test and the
project does not depend on statsmodels for one HAC variance.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats
from scipy.signal import correlate

from .results import LossTest


def newey_west_lag(n: int) -> int:
    """Newey-West's automatic bandwidth, 4 (n / 100)^(2/9)."""
    return int(math.floor(4.0 * (n / 100.0) ** (2.0 / 9.0)))


def decorrelation_lag(d: np.ndarray) -> int:
    """The first lag at which the autocorrelation of ``d`` falls inside the 95 % white-noise
    band 1.96 / sqrt(n): the samples further apart are nearly independent."""
    x = d - d.mean()
    n = x.size
    acov = correlate(x, x, mode="full", method="fft")[n - 1:] / n
    if acov[0] <= 0:
        return 0
    inside = np.flatnonzero(np.abs(acov / acov[0]) < 1.96 / math.sqrt(n))
    return int(inside[0]) if inside.size else n - 1


def about_means(e, groups=None) -> np.ndarray:
    """``e`` less its mean over each group (``groups``: a label per sample; None: one)."""
    e = np.asarray(e, float)
    if groups is None:
        return e - e.mean()
    groups = np.asarray(groups)
    out = e.copy()
    for g in np.unique(groups):
        out[groups == g] -= e[groups == g].mean()
    return out


def loss_differential_test(e_current, e_candidate, margin_mm2: float, groups=None
                           ) -> LossTest:
    """Diebold-Mariano test that the candidate's squared held-out error is lower, on each
    error about its mean over each record's held-out rows (``groups``: the record of each
    sample): an error constant over a record's held-out part (the free run's offset, set by
    where the model's slow misfit stands when that part begins) is one draw however many
    rows carry it, which a HAC variance over at most a quarter of the rows would count as
    many. Materiality (:attr:`LossTest.material`) is judged on both gains, the tested one
    about the means and that of the errors as they are: a block that explains the error's
    course but moves its level away is no better."""
    e_cur, e_new = np.asarray(e_current, float), np.asarray(e_candidate, float)
    gain = float(np.mean(e_cur ** 2 - e_new ** 2))
    d = about_means(e_cur, groups) ** 2 - about_means(e_new, groups) ** 2
    n = d.size
    mean = float(d.mean())
    lag = min(max(newey_west_lag(n), decorrelation_lag(d)), n // 4)
    x = d - mean
    acov = correlate(x, x, mode="full", method="fft")[n - 1:n + lag] / n
    weights = 1.0 - np.arange(1, lag + 1) / (lag + 1.0)
    var = float(acov[0] + 2.0 * np.sum(weights * acov[1:lag + 1]))
    if not var > 0:
        stat = math.inf if mean > 0 else -math.inf if mean < 0 else 0.0
    else:
        stat = mean / math.sqrt(var / n) * math.sqrt((n - 1.0) / n)  # HLN factor, horizon 1
    p = float(stats.t.sf(stat, df=n - 1))
    se = math.sqrt(var / n) if var > 0 else 0.0
    return LossTest(gain, float(stat), p, int(lag), float(margin_mm2), se, mean)


def power(test: LossTest, expected_gain_mm2: float, alpha: float) -> float:
    """Probability that the one-sided test at level ``alpha`` passes on these held-out rows
    when the mean gain is ``expected_gain_mm2``, with the test's own standard error (normal
    approximation)."""
    se = test.standard_error_mm2
    if not se > 0:
        return 1.0
    return float(stats.norm.sf(stats.norm.isf(alpha) - expected_gain_mm2 / se))


def holm(p_values: dict[str, float], weights: dict[str, float] | None = None
         ) -> dict[str, float]:
    """Holm's step-down adjusted p-values (reject where adjusted p <= alpha), weighted (Holm
    1979): each hypothesis gets the share ``w_i / sum(w)`` of the alpha left at its step, in
    the order of ``p_i / w_i``; equal weights (None) give the plain procedure. Weights fixed
    independently of the p-values keep the family-wise error at alpha."""
    w = {n: 1.0 for n in p_values} if weights is None else {n: weights[n] for n in p_values}
    if any(not v > 0 for v in w.values()):
        raise ValueError(f"Holm's weights must be positive: {w}")
    order = sorted(p_values, key=lambda n: p_values[n] / w[n])
    left, running, out = sum(w.values()), 0.0, {}
    for name in order:
        running = max(running, min(1.0, left * p_values[name] / w[name]))
        out[name] = running
        left -= w[name]
    return out


def passes(test: LossTest, p_holm: float, family_alpha: float) -> bool:
    """Significant after Holm and material: the rule's verdict on one candidate."""
    return p_holm <= family_alpha and test.material
