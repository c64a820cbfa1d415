"""Tests of ipmc_model.residuals: ACF/CCF with bounds, whiteness tests, the streaming monitor."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from numpy.testing import assert_allclose

from ipmc_model.residuals import (
    ResidualMonitor,
    acf,
    ccf,
    correlation_test,
    ljung_box,
    low_frequency_share,
    spectrum,
    whiteness_summary,
)


def test_import_leaves_rclpy_out():
    # In a fresh interpreter: other tests of the session may have imported rclpy already.
    code = "import sys, ipmc_model.residuals; sys.exit('rclpy' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_acf_matches_direct_sum():
    rng = np.random.default_rng(1)
    e = rng.standard_normal(300)
    c = acf(e, 5)
    d = e - e.mean()
    direct = [np.sum(d[: d.size - k] * d[k:]) / np.sum(d * d) for k in range(6)]
    assert_allclose(c.values, direct, atol=1e-12)
    assert_allclose(c.bound, 1.96 / np.sqrt(300), rtol=1e-3)


def test_ccf_sign_convention_input_leads_residual():
    rng = np.random.default_rng(2)
    u = rng.standard_normal(2000)
    e = np.roll(u, 4)  # e_t = u_{t-4}: the input leads by 4 samples
    c = ccf(u, e, 10)
    assert c.lags[np.argmax(c.values)] == 4
    assert_allclose(c.values.max(), 1.0, atol=0.01)


def test_white_noise_passes_and_ar_fails():
    rng = np.random.default_rng(3)
    w = rng.standard_normal(3000)
    assert acf(w, 25).fraction_outside() <= 0.15
    assert ljung_box(w, 20)["p_value"] > 0.01
    ar = np.zeros_like(w)
    for k in range(1, w.size):
        ar[k] = 0.8 * ar[k - 1] + w[k]
    assert ljung_box(ar, 20)["p_value"] < 1e-6
    s = whiteness_summary(ar, u=w)
    assert s["acf_outside"] > 0.3 and s["ccf_outside"] > 0.0


def test_correlation_test_bartlett_bound_is_wider_for_slow_signals():
    rng = np.random.default_rng(4)
    n = 3000
    slow_a = np.cumsum(rng.standard_normal(n))
    slow_b = np.cumsum(rng.standard_normal(n))  # independent random walks: spurious corr
    res = correlation_test(slow_a, slow_b)
    assert res["bound"] > 5 * 1.96 / np.sqrt(n)
    strong = correlation_test(slow_a + 0.1 * rng.standard_normal(n), slow_a)
    assert strong["significant"] and strong["r"] > 0.9


def test_spectrum_and_low_frequency_share():
    t = np.arange(4000) / 100.0
    slow = np.sin(2 * np.pi * 0.05 * t)
    f, p = spectrum(slow, 100.0)
    assert f[np.argmax(p)] < 0.2
    assert low_frequency_share(slow, 100.0, 0.5) > 0.9
    w = np.random.default_rng(5).standard_normal(4000)
    assert low_frequency_share(w, 100.0, 0.5) < 0.1


def test_bad_lag_raises():
    with pytest.raises(ValueError, match="max_lag"):
        acf(np.ones(10), 20)
    with pytest.raises(ValueError, match="bound"):
        ccf(np.arange(10.0), np.arange(10.0), 2, bound="nope")


def test_monitor_stays_ok_on_white_and_flags_drift():
    rng = np.random.default_rng(6)
    mon = ResidualMonitor(window=400, lags=20, alpha=0.01, check_every=50, patience=3)
    levels = [mon.update(v).level for v in 0.01 * rng.standard_normal(4000)]
    assert mon.status.white is True
    assert sum(lv == 2 for lv in levels) == 0
    # the model goes stale: the residual gets a slow drift and an AR component
    drift = np.zeros(3000)
    for k in range(1, drift.size):
        drift[k] = 0.97 * drift[k - 1] + 0.01 * rng.standard_normal()
    status = mon.update_many(drift + np.linspace(0, 0.05, drift.size))
    assert status.level == 2 and mon.stale
    assert "stale" in status.message
    mon.reset()
    assert mon.status.level == 0 and mon.status.white is None


def test_monitor_skips_nan_and_validates():
    mon = ResidualMonitor(window=50, lags=5, check_every=10)
    assert mon.update(float("nan")).level == 0
    with pytest.raises(ValueError, match="window"):
        ResidualMonitor(window=5)
    with pytest.raises(ValueError, match="lags"):
        ResidualMonitor(window=50, lags=40)


def _free_run_residual(effects, seed, seconds=480.0, rate=50.0):
    """Free-run residual (mm) of a baseline fitted on the first 60 s of a plant record."""
    from ipmc_driver.plant import IpmcPlant
    from ipmc_driver.signals import random_sine, random_steps
    from ipmc_model.lssvm import LSSVMRegressor
    from ipmc_model.narx import NarxModel

    _, us = random_sine(seconds, rate, 2.5, (0.05, 1.0), 8, seed=seed + 2)
    _, st = random_steps(seconds, rate, 1.5, (3.0, 10.0), seed=seed + 3)
    u = np.clip(0.6 * us + st, -3, 3)
    y = IpmcPlant(effects=effects, seed=seed, dt_s=1 / rate).run(u).y_mm
    fit = int(60 * rate)
    m = NarxModel(LSSVMRegressor(C=1000.0, sigma=3.0), input_lags=12, output_lags=0,
                  lag_step=5, max_rows=600).fit(u[:fit], y[:fit])
    ys = m.simulate(u[fit:], y[fit:fit + m.max_lag_])
    return (y[fit:] - ys)[m.max_lag_:]


def _first_stale_s(e, rate=50.0):
    # 10 Hz after decimation: a 60 s window, the first 120 s after the fit as reference
    mon = ResidualMonitor(window=600, lags=20, decimate=5, test="drift", reference=1200)
    for k, v in enumerate(e):
        if mon.update(v).level == 2:
            return k / rate
    return None


@pytest.mark.parametrize("seed", [0, 2])
def test_monitor_drift_test_flags_drifting_plant_not_clean_one(seed):
    # plant drift at its defaults (gain loss 3 %/min, offset 0.05 mm/min), not told to the
    # monitor; seed 2 was not used to choose bias_factor / growth
    assert _first_stale_s(_free_run_residual({}, seed)) is None
    t_stale = _first_stale_s(_free_run_residual({"drift": {}}, seed))
    assert t_stale is not None and t_stale < 360.0  # within 6 min of the fit


def test_monitor_drift_test_needs_reference_first():
    mon = ResidualMonitor(window=50, lags=5, check_every=10, test="drift", reference=100)
    rng = np.random.default_rng(7)
    st = mon.update_many(0.1 * rng.standard_normal(90))
    assert st.level == 0 and "reference" in st.message
    st = mon.update_many(0.1 * rng.standard_normal(200))
    assert st.level == 0 and st.white is True
    st = mon.update_many(0.5 + 0.1 * rng.standard_normal(200))  # offset of 5 spreads
    assert st.level == 2 and "mean moved" in st.message
    with pytest.raises(ValueError, match="test"):
        ResidualMonitor(test="nope")
