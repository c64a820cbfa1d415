"""The controller's safety rules without DDS: ipmc_control.supervisor driven input by input.

Clock readings are arguments, so every timeout is exact: no sleeping, no graph.
"""

from __future__ import annotations

import math
import subprocess
import sys

import pytest

from ipmc_control.hybrid import HybridController
from ipmc_control.pid import PID, ControlParameterError, check_actuator_limits
from ipmc_control.supervisor import (
    ERROR,
    OK,
    WARN,
    Supervisor,
    feedforward_status,
    measurement_status,
    saturation_status,
)

MS = 1_000_000
DT_S = 0.01


def _supervisor(mode: str = "hybrid", **kwargs) -> Supervisor:
    return Supervisor(HybridController(PID(), mode=mode), 100.0, **kwargs)


def _feed(s: Supervisor, k: int, now_s: float, ref_mm: float = 1.0, y_mm: float = 0.0,
          ff_v: float | None = 0.5) -> None:
    s.on_reference(k * 10 * MS, ref_mm, 0.0)
    s.on_measurement(k * 10 * MS, y_mm, now_s, now_s)
    if ff_v is not None:
        s.on_feedforward(k * 10 * MS, ff_v, now_s)


def test_importing_the_core_leaves_rclpy_out():
    code = ("import sys, ipmc_control.supervisor; "
            "assert 'rclpy' not in sys.modules, 'rclpy imported'")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_no_reference_means_0_v_and_a_reset():
    s = _supervisor()
    s.on_measurement(0, 1.0, 0.0, 0.0)
    c = s.on_tick(0.01)
    assert c.u_v == 0.0 and s.idle_reason == "no reference yet"
    # before a reference ever came it is the start: a note to log as information
    assert ("waiting", "no reference yet: command 0 V") in s.notes
    assert measurement_status(s, 0.01).level == ERROR


def test_a_silent_measurement_means_0_v_after_its_timeout():
    s = _supervisor(mode="pid", measurement_timeout_s=0.5)
    _feed(s, 0, 0.0, ref_mm=2.0, y_mm=0.0)
    assert s.on_tick(0.01).u_v > 0          # the loop runs
    s.on_reference(10 * MS, 2.0, 0.0)
    for k in range(2, 50):                    # within 0.5 s of it: still commanding
        assert s.on_tick(k * DT_S).u_v != 0.0
    c = s.on_tick(0.51)                       # 0.51 s after the last displacement
    assert c.u_v == 0.0 and s.idle_reason == "no fresh displacement"
    assert ("idle", "no fresh displacement: command 0 V") in s.notes   # lost: a warning
    assert s.hybrid.pid.i_term == 0.0         # the state was reset
    s.on_measurement(20 * MS, 0.0, 0.53, 0.53)
    assert s.on_tick(0.53).u_v > 0 and s.idle_reason == ""
    assert measurement_status(s, 0.53).level == OK


def test_a_stale_feedforward_falls_back_to_pid_and_returns():
    s = _supervisor(feedforward_timeout_s=0.2)
    for k in range(1, 11):                    # the last feedforward at 0.1 s
        _feed(s, k, k * DT_S)
        s.on_tick(k * DT_S)
    assert not s.fallback and s.hybrid.active_mode == "hybrid"
    for k in range(11, 40):                   # then silent
        t = k * DT_S
        _feed(s, k, t, ff_v=None)
        s.on_tick(t)
        assert s.fallback == (k >= 31), k     # stale beyond 0.2 s: from 0.31 s
    assert s.hybrid.active_mode == "pid"
    assert any(kind == "stale" and "PID alone" in text for kind, text in s.notes)
    assert feedforward_status(s, t).level == WARN
    _feed(s, 40, t + DT_S)
    s.on_tick(t + DT_S)
    assert not s.fallback and ("back", "feedforward back: mode hybrid") in s.notes
    assert feedforward_status(s, t + DT_S).level == OK


def test_inverse_mode_runs_open_loop_without_a_measurement_while_the_feedforward_is_fresh():
    s = _supervisor(mode="inverse")
    s.on_reference(0, 1.0, 0.0)
    s.on_feedforward(0, 0.7, 0.0)
    for k in range(1, 21):                    # the feedforward fresh for 0.2 s
        assert s.on_tick(k * DT_S).u_v == pytest.approx(0.7)
    assert s.on_tick(0.21).u_v == 0.0 and s.idle_reason == "no fresh displacement"


def test_commands_stay_within_the_limits():
    pid = PID(k=100.0, u_clamp_min=-1.0, u_clamp_max=2.0)
    s = Supervisor(HybridController(pid, mode="hybrid"), 100.0)
    t = 0.0
    for k in range(50):
        t += DT_S
        _feed(s, k, t, ref_mm=5.0 * (-1) ** (k // 10), ff_v=3.0 * (-1) ** (k // 10))
        assert -1.0 <= s.on_tick(t).u_v <= 2.0
    assert saturation_status(s).values["fraction"] != "0.000"
    with pytest.raises(ControlParameterError, match="H-bridge"):
        check_actuator_limits(-1.0, 5.0)
    with pytest.raises(ControlParameterError, match="0 V allowed"):
        check_actuator_limits(0.5, 2.0)


def test_a_clock_jump_holds_the_command_and_restarts_the_timing():
    s = _supervisor(mode="pid")
    _feed(s, 0, 0.0)
    u = s.on_tick(0.01).u_v
    assert s.on_tick(5.0).u_v == u and s.skipped_steps == 1
    assert s.on_tick(0.005).u_v == u and s.skipped_steps == 2   # back in time


def test_measurement_trigger_waits_for_its_feedforward_then_steps():
    s = _supervisor(trigger="measurement", pair_wait_s=0.05)
    s.on_reference(0, 1.0, 0.0)
    s.on_reference(10 * MS, 1.0, 0.0)
    assert s.on_measurement(0, 0.0, 0.0, wall_s=100.0) == []    # waits for u_ff of 10 ms
    (c,) = s.on_feedforward(10 * MS, 0.4, 0.0)
    assert c.answer_ns == 0 and s.unpaired_steps == 0
    s.on_reference(20 * MS, 1.0, 0.0)
    assert s.on_measurement(10 * MS, 0.0, 0.01, wall_s=100.01) == []
    assert s.on_pair_wait(wall_s=100.05) == []                  # not yet pair_wait_s
    (c,) = s.on_pair_wait(wall_s=100.07)                        # runs without it
    assert c.answer_ns == 10 * MS and s.unpaired_steps == 1 and s.fallback is False


def test_measurement_trigger_in_pid_mode_steps_when_its_reference_arrives():
    """In mode pid a step waits only for its reference; it runs as soon as that comes (it
    waited for pair_wait_s or the next reference before the reference was stored first)."""
    s = _supervisor(mode="pid", trigger="measurement")
    s.on_reference(0, 1.0, 0.0)
    assert s.on_measurement(0, 0.0, 0.0, wall_s=0.0) == []
    (c,) = s.on_reference(10 * MS, 1.0, 0.0)
    assert c.answer_ns == 0 and s.unpaired_steps == 0


def test_hybrid_starts_afresh_with_its_first_feedforward():
    """Before the first feedforward the loop runs PID alone (logged as information, not as a
    fault); the first feedforward starts the hybrid loop from a fresh PID, not bumplessly:
    the integral the PID wound up alone would be kept against the feedforward for seconds."""
    s = _supervisor(feedforward_timeout_s=0.2)
    for k in range(1, 60):                        # reference 1 mm, tip at 0: the PID winds up
        _feed(s, k, k * DT_S, ff_v=None)
        assert s.on_tick(k * DT_S).u_v > 0
    assert s.hybrid.active_mode == "pid" and s.hybrid.pid.i_term > 0.3
    assert any(kind == "waiting" and "PID alone" in text for kind, text in s.notes)
    assert not any(kind == "stale" for kind, _ in s.notes)
    _feed(s, 60, 60 * DT_S, ff_v=0.5)
    u = s.on_tick(60 * DT_S).u_v
    assert s.hybrid.active_mode == "hybrid"
    assert u == pytest.approx(0.5 + PID().k * 1.0, abs=0.2)    # ff + a fresh PID's response


def test_a_non_finite_input_is_ignored():
    s = _supervisor()
    assert s.on_reference(0, math.nan, 0.0) == [] and s.on_tick(0.01).u_v == 0.0
    s.on_reference(0, 1.0, math.nan)
    s.on_measurement(0, math.inf, 0.0, 0.0)
    assert s.on_tick(0.02).u_v == 0.0 and s.idle_reason == "no fresh displacement"
