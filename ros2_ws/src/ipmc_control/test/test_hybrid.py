"""Tests of the hybrid inverse-feedforward + PID law (ipmc_control.hybrid). Plain pytest."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from ipmc_control.hybrid import MODES, HybridController
from ipmc_control.pid import PID, ControlParameterError

H = 0.01


def test_modes_are_the_three_of_the_issue():
    assert MODES == ("pid", "inverse", "hybrid")
    with pytest.raises(ControlParameterError, match="mode must be one of"):
        HybridController(mode="feedforward")
    ctl = HybridController()
    with pytest.raises(ControlParameterError, match="mode must be one of"):
        ctl.mode = "open"
    assert ctl.mode == "hybrid"


def test_pid_mode_ignores_feedforward():
    ctl = HybridController(mode="pid")
    ref = PID()
    for r, y in ((1.0, 0.0), (1.0, 0.2), (0.5, 0.4)):
        assert ctl.compute_command(r, y, H, feedforward_v=2.0) == ref.compute_command(r, y, H)
    assert ctl.active_mode == "pid"
    assert ctl.feedforward_v == 0.0


def test_inverse_mode_is_open_loop_feedforward_clipped():
    ctl = HybridController(mode="inverse")
    assert ctl.compute_command(1.0, -5.0, H, feedforward_v=1.7) == 1.7
    assert ctl.compute_command(1.0, 5.0, H, feedforward_v=1.7) == 1.7
    assert ctl.compute_command(1.0, 0.0, H, feedforward_v=4.2) == 3.0
    assert ctl.compute_command(1.0, 0.0, H, feedforward_v=-9.0) == -3.0
    assert ctl.active_mode == "inverse"


def test_hybrid_first_step_is_feedforward_plus_proportional():
    ctl = HybridController()
    # Eq. 22: u_l = u + u_i; the first PID output is K e (no derivative history).
    assert_allclose(ctl.compute_command(1.0, 0.5, H, feedforward_v=0.8), 0.8 + 1.2 * 0.5,
                    rtol=1e-12)
    assert ctl.active_mode == "hybrid"
    assert ctl.feedforward_v == 0.8


def test_total_is_clipped_and_antiwindup_sees_total_saturation():
    # Feedforward 2.5 V + K e = 1.2 V exceeds 3 V: the total is clipped and the integrator,
    # seeing the total saturation, does not wind up as a lone unsaturated PID's would.
    ctl = HybridController()
    lone = PID()
    for _ in range(100):
        u = ctl.compute_command(1.0, 0.0, H, feedforward_v=2.5)
        u_lone = lone.compute_command(1.0, 0.0, H)
    assert u == 3.0
    assert ctl.saturated
    assert ctl.pid.i_term < 0.0  # pulled down so that 2.5 + P + I stays near 3 V
    assert not lone.saturated and u_lone < 3.0
    assert_allclose(lone.i_term, 1.2 / 0.87 * 1.0, rtol=1e-9)  # K/TI * e * 1 s


def test_fallback_to_pid_when_feedforward_missing_then_recovers_without_bump():
    ctl = HybridController()
    y = 0.2
    for _ in range(100):
        u_hybrid = ctl.compute_command(1.0, y, H, feedforward_v=1.0)
    u_fallback = ctl.compute_command(1.0, y, H, feedforward_v=None)
    assert ctl.active_mode == "pid"
    assert ctl.feedforward_v == 0.0
    # The integral takes over the feedforward's 1 V: no jump (only one step of integration).
    assert abs(u_fallback - u_hybrid) < 0.02
    u_nan = ctl.compute_command(1.0, y, H, feedforward_v=math.nan)
    assert ctl.active_mode == "pid"
    assert abs(u_nan - u_fallback) < 0.02
    u_back = ctl.compute_command(1.0, y, H, feedforward_v=1.1)
    assert ctl.active_mode == "hybrid"
    assert abs(u_back - u_nan) < 0.02


def test_inverse_mode_falls_back_to_pid_without_feedforward():
    ctl = HybridController(mode="inverse")
    ctl.compute_command(1.0, 0.0, H, feedforward_v=0.5)
    u = ctl.compute_command(1.0, 0.0, H, feedforward_v=None)
    assert ctl.active_mode == "pid"
    assert math.isfinite(u)


@pytest.mark.parametrize(("first", "second"), [
    ("inverse", "hybrid"), ("inverse", "pid"), ("hybrid", "pid"), ("pid", "hybrid"),
    ("hybrid", "inverse"),
])
def test_mode_switch_is_bumpless(first, second):
    ctl = HybridController(mode=first)
    for _ in range(600):  # 6 s, long enough for the inverse mode's tracking to settle
        u_before = ctl.compute_command(1.0, 0.7, H, feedforward_v=0.9)
    ctl.mode = second
    u_after = ctl.compute_command(1.0, 0.7, H, feedforward_v=0.9)
    # Into "inverse" the command is the feedforward by definition; elsewhere it continues.
    expected = 0.9 if second == "inverse" else u_before
    assert abs(u_after - expected) < 0.02


def test_bad_dt_returns_previous_command():
    ctl = HybridController()
    u = ctl.compute_command(1.0, 0.0, H, feedforward_v=0.5)
    assert ctl.compute_command(1.0, 0.0, 0.0, feedforward_v=0.5) == u
    assert ctl.compute_command(math.nan, 0.0, H, feedforward_v=0.5) == u
    assert ctl.pid.rejected_steps == 2
    assert ctl.active_mode == "hybrid"


def test_reset_forgets_everything():
    ctl = HybridController()
    for _ in range(10):
        ctl.compute_command(1.0, 0.0, H, feedforward_v=0.5)
    ctl.reset()
    assert (ctl.command, ctl.pid.i_term, ctl.feedforward_v) == (0.0, 0.0, 0.0)
    assert_allclose(ctl.compute_command(1.0, 0.5, H, feedforward_v=0.8), 0.8 + 0.6, rtol=1e-12)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(
    st.sampled_from(MODES),
    st.one_of(st.floats(-20, 20), st.just(math.nan)),
    st.one_of(st.floats(-20, 20), st.just(math.inf)),
    st.one_of(st.floats(0.0, 0.1), st.just(-0.01)),
    st.one_of(st.none(), st.floats(-10, 10), st.just(math.nan))), max_size=40))
def test_command_always_finite_and_within_3v(steps):
    ctl = HybridController()
    for mode, r, y, h, ff in steps:
        ctl.mode = mode
        u = ctl.compute_command(r, y, h, feedforward_v=ff)
        assert math.isfinite(u)
        assert abs(u) <= 3.0


def test_gpi_inverse_tracks_a_sine_in_the_hybrid_loop():
    """The GPI inverse (ipmc identify's default family) as the hybrid's feedforward."""
    import math

    from ipmc_control.experiment import run_tracking
    from ipmc_control.references import SineReference
    from ipmc_driver.plant import IpmcPlant
    from ipmc_driver.signals import mixed
    from ipmc_model.hysteresis import GeneralizedPI

    _, u = mixed(180.0, 100.0, 3.0, (0.02, 0.8), seed=1)
    model = GeneralizedPI().fit(u, IpmcPlant(seed=1).run(u).y_mm)
    res = run_tracking(SineReference(amplitude_mm=2.5, frequency_hz=1 / (2 * math.pi)), 25.0,
                       "hybrid", inverse=model.inverse())
    assert res.summary()["rmse_mm"] < 0.02
