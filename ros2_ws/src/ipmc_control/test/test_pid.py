"""Tests of the discrete PID (ipmc_control.pid): hand-computed steps, limits, anti-windup,
derivative kick, bad-sample guards, bumpless gain changes. Plain pytest, no ROS."""

from __future__ import annotations

import copy
import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from ipmc_control.pid import PID, ControlParameterError

K, TI, TD = 1.2, 0.87, 0.13   # the paper's
N = 3.0   # ours (the paper gives none): ipmc_control.pid.DEFAULT_N says why
H = 0.01


def test_import_core_leaves_rclpy_out():
    code = ("import sys; import ipmc_control.pid, ipmc_control.hybrid, ipmc_control.references; "
            "sys.exit(1 if 'rclpy' in sys.modules else 0)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60)
    assert result.returncode == 0, result.stderr.decode()


def test_defaults_are_the_papers():
    pid = PID()
    assert (pid.k, pid.ti_s, pid.td_s, pid.n) == (K, TI, TD, N)
    assert (pid.u_clamp_min, pid.u_clamp_max) == (-3.0, 3.0)
    assert pid.antiwindup_strategy == "back_calculation"
    assert pid.tracking_time_constant is None
    assert_allclose(pid.tracking_time_constant_s, math.sqrt(TI * TD), rtol=1e-12)
    assert_allclose((pid.p, pid.i, pid.d), (K, K / TI, K * TD), rtol=1e-12)


def test_compute_command_matches_hand_computed_steps():
    pid = PID(u_clamp_max=math.inf, u_clamp_min=-math.inf)
    tf = TD / N
    # Step 1: r = 1, y = 0; no previous measurement, so D = 0. u = K e = 1.2.
    assert_allclose(pid.compute_command(1.0, 0.0, H), 1.2, rtol=1e-12)
    i1 = K * H / TI * 1.0
    assert_allclose(pid.i_term, i1, rtol=1e-12)
    # Step 2: y = 0.1, e = 0.9. D = -K TD (0.1 - 0) / (Tf + h).
    d2 = -K * TD * 0.1 / (tf + H)
    assert_allclose(pid.compute_command(1.0, 0.1, H), K * 0.9 + i1 + d2, rtol=1e-12)
    i2 = i1 + K * H / TI * 0.9
    # Step 3: y = 0.25, h = 0.02 (irregular sample), e = 0.75.
    d3 = (tf * d2 - K * TD * 0.15) / (tf + 0.02)
    assert_allclose(pid.compute_command(1.0, 0.25, 0.02), K * 0.75 + i2 + d3, rtol=1e-12)
    assert_allclose((pid.p_term, pid.d_term), (K * 0.75, d3), rtol=1e-12)
    assert_allclose(pid.i_term, i2 + K * 0.02 / TI * 0.75, rtol=1e-12)


def test_from_parallel_equals_standard_form():
    a = PID.from_parallel(p=2.0, i=4.0, d=0.5, n=8.0)
    b = PID(2.0, 0.5, 0.25, n=8.0)
    assert_allclose((a.k, a.ti_s, a.td_s), (2.0, 0.5, 0.25), rtol=1e-12)
    for r, y in ((1.0, 0.0), (1.0, 0.3), (0.5, 0.6), (0.0, 0.2)):
        assert a.compute_command(r, y, H) == b.compute_command(r, y, H)
    assert PID.from_parallel(p=1.0, i=0.0, d=0.0).ti_s == math.inf


def test_tracking_time_constant_default_without_derivative_is_ti():
    assert PID(td_s=0.0).tracking_time_constant_s == TI
    pid = PID(tracking_time_constant=0.2)
    assert pid.tracking_time_constant_s == 0.2
    pid.set_gains(tracking_time_constant=0.0)  # 0: back to the default rule (control_toolbox)
    assert pid.tracking_time_constant is None
    assert_allclose(pid.tracking_time_constant_s, math.sqrt(TI * TD))


def test_output_clipped_to_limits():
    pid = PID()
    assert pid.compute_command(10.0, 0.0, H) == 3.0
    assert pid.saturated
    assert pid.command_unsaturated == pytest.approx(12.0)
    pid.reset()
    assert pid.compute_command(-10.0, 0.0, H) == -3.0


def test_no_derivative_kick_on_setpoint_step():
    pid = PID(u_clamp_max=math.inf, u_clamp_min=-math.inf)
    for _ in range(50):
        pid.compute_command(0.0, 0.0, H)
    u_before = pid.command
    u_after = pid.compute_command(2.0, 0.0, H)
    # Only the proportional term moves with the setpoint; derivative stays exactly 0.
    assert pid.d_term == 0.0
    assert_allclose(u_after - u_before, K * 2.0, rtol=1e-12)


def test_derivative_on_measurement_follows_ramp_after_filter():
    pid = PID(ti_s=math.inf, u_clamp_max=math.inf, u_clamp_min=-math.inf)
    slope = 0.5  # mm/s
    for k in range(200):  # 2 s = 150 filter time constants
        pid.compute_command(0.0, slope * k * H, H)
    assert_allclose(pid.d_term, -K * TD * slope, rtol=1e-9)


def test_reference_rate_puts_derivative_on_error():
    slope = 0.5  # mm/s; a ramp tracked with a constant lag: the error does not change
    on_error = PID(ti_s=math.inf, u_clamp_max=math.inf, u_clamp_min=-math.inf)
    on_measurement = PID(ti_s=math.inf, u_clamp_max=math.inf, u_clamp_min=-math.inf)
    for k in range(200):
        r, y = slope * k * H, slope * k * H - 0.1
        on_error.compute_command(r, y, H, reference_rate=slope)
        on_measurement.compute_command(r, y, H)
    assert abs(on_error.d_term) < 1e-12  # d(r - y)/dt = 0
    assert_allclose(on_measurement.d_term, -K * TD * slope, rtol=1e-9)
    # The error's rate is what counts: the measurement stops, r keeps going.
    for _ in range(200):
        on_error.compute_command(1.0, 0.5, H, reference_rate=slope)
    assert_allclose(on_error.d_term, K * TD * slope, rtol=1e-9)


def test_reference_rate_zero_on_a_step_gives_no_kick():
    pid = PID(u_clamp_max=math.inf, u_clamp_min=-math.inf)
    for _ in range(50):
        pid.compute_command(0.0, 0.0, H, reference_rate=0.0)
    u_before = pid.command
    u_after = pid.compute_command(2.0, 0.0, H, reference_rate=0.0)  # a step train's rate
    assert pid.d_term == 0.0
    assert_allclose(u_after - u_before, K * 2.0, rtol=1e-12)


def test_nan_reference_rate_is_a_rejected_sample():
    pid = PID()
    u = pid.compute_command(1.0, 0.0, H)
    assert pid.compute_command(1.0, 0.0, H, reference_rate=math.nan) == u
    assert pid.rejected_steps == 1


def _saturating_loop(strategy: str, reachable_mm: float = 2.0):
    """First-order plant (gain 2 mm/V, tau 0.5 s) behind the 3 V limit: 5 s asking for the
    unreachable 10 mm, then ``reachable_mm``. Returns the PID, the peak |I| during saturation
    and the settling time after the switch (|e| < 0.1 mm for good), s."""
    pid = PID(antiwindup_strategy=strategy)
    y, i_peak = 0.0, 0.0
    for _ in range(500):
        u = pid.compute_command(10.0, y, H)
        y += H / 0.5 * (2.0 * u - y)
        i_peak = max(i_peak, abs(pid.i_term))
    last_bad = 0
    for k in range(1, 1001):
        u = pid.compute_command(reachable_mm, y, H)
        y += H / 0.5 * (2.0 * u - y)
        if abs(reachable_mm - y) >= 0.1:
            last_bad = k
    return pid, i_peak, last_bad * H


def test_back_calculation_keeps_integrator_bounded_under_saturation():
    _, i_peak, _ = _saturating_loop("back_calculation")
    _, i_peak_none, _ = _saturating_loop("none")
    # Back-calculation equilibrium: v - u = Tt K e / TI, so I stays near u + Tt K e/TI - K e,
    # a few volts; without anti-windup I grows about K/TI * e * 5 s = 28 V.
    assert i_peak < 6.0
    assert i_peak_none > 20.0


def test_back_calculation_recovers_quickly_after_saturation():
    _, _, settle = _saturating_loop("back_calculation")
    _, _, settle_none = _saturating_loop("none")
    # Measured: 3.2 s with back-calculation (the loop's own integral settling), 8.1 s without.
    assert settle < 4.0
    assert settle_none > 2.0 * settle


@pytest.mark.parametrize("bad", [
    {"reference": math.nan}, {"measurement": math.nan}, {"measurement": math.inf},
    {"reference": -math.inf}, {"feedforward": math.nan}, {"dt_s": 0.0}, {"dt_s": -0.01},
    {"dt_s": math.nan}, {"dt_s": math.inf}, {"u_applied": math.nan},
])
def test_bad_sample_returns_previous_command_and_keeps_state(bad):
    good = PID()
    probe = PID()
    for pid in (good, probe):
        pid.compute_command(1.0, 0.0, H)
        pid.compute_command(1.0, 0.2, H)
    args = {"reference": 1.0, "measurement": 0.3, "dt_s": H, "feedforward": 0.0} | bad
    assert probe.compute_command(**args) == good.command
    assert probe.rejected_steps == 1
    # The state is untouched: both controllers continue identically.
    assert probe.compute_command(1.0, 0.3, H) == good.compute_command(1.0, 0.3, H)
    assert probe.i_term == good.i_term


def test_bad_sample_before_any_good_one_returns_zero():
    pid = PID()
    assert pid.compute_command(math.nan, 0.0, H) == 0.0
    assert pid.compute_command(1.0, 0.0, 0.0) == 0.0


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(
    st.one_of(st.floats(-50, 50), st.just(math.nan), st.just(math.inf)),
    st.one_of(st.floats(-50, 50), st.just(math.nan)),
    st.one_of(st.floats(-1.0, 1.0), st.just(math.nan), st.just(0.0))), max_size=40))
def test_command_always_finite_and_within_limits(samples):
    pid = PID()
    for r, y, h in samples:
        u = pid.compute_command(r, y, h)
        assert math.isfinite(u)
        assert -3.0 <= u <= 3.0


def test_gain_change_is_bumpless():
    pid = PID(u_clamp_max=math.inf, u_clamp_min=-math.inf)
    for k in range(30):
        pid.compute_command(1.0, 0.02 * k, H)
    twin = copy.deepcopy(pid)
    pid.set_gains(k=2.4, ti_s=0.4, td_s=0.3)
    # Same inputs, an instant later: the output continues as if the gains had not changed
    # (a P-term jump alone would be (2.4 - 1.2) * 0.42 = 0.5 V).
    u_twin = twin.compute_command(1.0, 0.02 * 29, 1e-9)
    u_after = pid.compute_command(1.0, 0.02 * 29, 1e-9)
    assert_allclose(u_after, u_twin, atol=1e-6)
    assert (pid.k, pid.ti_s, pid.td_s) == (2.4, 0.4, 0.3)
    assert_allclose(pid.tracking_time_constant_s, math.sqrt(0.4 * 0.3))


def test_gain_change_without_bumpless_would_jump():
    # Guard that the bumpless test exercises something: the P-term jump is K change * e.
    pid = PID(u_clamp_max=math.inf, u_clamp_min=-math.inf)
    for _ in range(5):
        pid.compute_command(1.0, 0.0, H)
    i_before = pid.i_term
    pid.set_gains(k=2.4)
    assert_allclose(i_before - pid.i_term, (2.4 - K) * 1.0, rtol=1e-9)


def test_invalid_gains_raise_and_change_nothing():
    pid = PID()
    with pytest.raises(ControlParameterError, match="ti_s must be > 0"):
        pid.set_gains(ti_s=0.0)
    with pytest.raises(ControlParameterError, match="k must be finite"):
        pid.set_gains(k=math.nan)
    assert (pid.k, pid.ti_s) == (K, TI)
    with pytest.raises(ControlParameterError, match="u_clamp_min must be < u_clamp_max"):
        PID(u_clamp_max=1.0, u_clamp_min=2.0)
    with pytest.raises(ControlParameterError, match="antiwindup_strategy"):
        PID(antiwindup_strategy="legacy")
    with pytest.raises(ControlParameterError, match="n must be > 0"):
        PID(n=0)


def test_set_limits_changes_clip():
    pid = PID()
    pid.set_limits(-1.0, 1.0)
    assert pid.compute_command(10.0, 0.0, H) == 1.0
    with pytest.raises(ControlParameterError):
        pid.set_limits(1.0, -1.0)


def test_reset_clears_state_and_can_keep_integral():
    pid = PID()
    for _ in range(10):
        pid.compute_command(1.0, 0.0, H)
    i_term = pid.i_term
    pid.reset(save_i_term=True)
    assert (pid.i_term, pid.command, pid.d_term) == (i_term, 0.0, 0.0)
    pid.reset()
    assert pid.i_term == 0.0


def test_u_applied_makes_integrator_track_open_loop_command():
    pid = PID()
    for _ in range(500):  # 5 s = 15 Tt
        u = pid.compute_command(1.0, 0.5, H, feedforward=0.4, u_applied=0.4)
    assert u == 0.4
    # The unsaturated total has converged to the applied command.
    assert_allclose(pid.command_unsaturated, 0.4, atol=1e-6)
    frozen = PID(antiwindup_strategy="none")
    frozen.compute_command(1.0, 0.5, H, u_applied=0.4)
    assert frozen.i_term == 0.0


def test_pid_alone_tracks_slow_sine_on_simulated_plant():
    plant_mod = pytest.importorskip("ipmc_driver.plant")
    plant = plant_mod.IpmcPlant(seed=0, dt_s=H)
    pid = PID()
    t = np.arange(4000) * H
    r = 2.0 * np.sin(2 * np.pi * 0.05 * t)  # 2 mm at 0.05 Hz
    y, err, u_max = 0.0, [], 0.0
    for k in range(t.size):
        u = pid.compute_command(r[k], y, H)
        u_max = max(u_max, abs(u))
        _, y = plant.step(u)
        if k + 1 < t.size:
            err.append(r[k + 1] - y)
    e = np.asarray(err[1000:])  # after the first cycle's transient
    assert u_max <= 3.0
    # Measured 0.30 mm RMSE, 0.57 mm max on the default plant (seed 0); the paper's gains are
    # tuned for the hybrid law, the PID alone lags.
    assert np.sqrt(np.mean(e**2)) < 0.4
    assert np.max(np.abs(e)) < 0.8


@pytest.mark.parametrize("lo, hi", [(-3.0, 100.0), (5.0, 3.0), (0.5, 2.0), (-2.0, -0.5),
                                    (-4.0, 3.0), (float("nan"), 3.0), (-3.0, float("inf"))])
def test_actuator_limits_refuse_beyond_3_v_or_without_0_v(lo, hi):
    from ipmc_control.pid import check_actuator_limits

    with pytest.raises(ControlParameterError, match="u_clamp"):
        check_actuator_limits(lo, hi)


def test_actuator_limits_accept_a_pair_around_0_v_within_3_v():
    from ipmc_control.pid import check_actuator_limits

    assert check_actuator_limits(-3.0, 3.0) == (-3.0, 3.0)
    assert check_actuator_limits(0.0, 1.5) == (0.0, 1.5)
