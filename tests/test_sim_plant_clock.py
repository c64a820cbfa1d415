"""sim_plant in real time: stamps from the clock, and /diagnostics say when the rate is not held.

``SampleClock`` is driven with clock readings (no timers, no ROS); one graph test runs
sim_plant at a rate its timer cannot hold and checks the stamps stay with the clock.
"""

from __future__ import annotations

import sys

import pytest

from ipmc_driver.sample_clock import SampleClock

MS = 1_000_000


def test_importing_the_sample_clock_leaves_rclpy_out():
    import subprocess

    code = ("import sys, ipmc_driver.sample_clock; "
            "assert 'rclpy' not in sys.modules, 'rclpy imported'")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_samples_follow_the_clock_when_ticks_come_late():
    clock = SampleClock(100.0)
    clock.start(1000 * MS)
    assert list(clock.due(1010 * MS)[0]) == [0]          # on time: one sample
    assert list(clock.due(1020.4 * MS)[0]) == [1]        # a little late: still one
    ks, skipped = clock.due(1070 * MS)                   # 50 ms late: the 5 it missed
    assert list(ks) == [2, 3, 4, 5, 6] and skipped == 0
    assert clock.stamp_ns(6) == 1060 * MS                # within one period of the clock
    assert list(clock.due(1079.6 * MS)[0]) == [7]        # a little early: due all the same
    assert list(clock.due(1080 * MS)[0]) == []           # no sample twice


def test_a_long_stall_skips_samples_beyond_the_burst_and_counts_them():
    clock = SampleClock(1000.0, max_burst=10)
    clock.start(0)
    ks, skipped = clock.due(100 * MS)                    # 100 samples due
    assert skipped == 90 and list(ks) == list(range(90, 100))
    assert clock.stamp_ns(ks[-1]) == 99 * MS
    report = clock.report(100 * MS)
    assert not report.held and report.skipped == 90 and report.caught_up == 9
    assert "rate not held" in report.message and "90 skipped" in report.message


def test_rate_report_says_held_only_when_the_timer_kept_its_period():
    clock = SampleClock(100.0)
    clock.start(0)
    for i in range(1, 101):
        clock.due(i * 10 * MS)
    held = clock.report(1000 * MS)
    assert held.held and held.tick_hz == pytest.approx(100.0)
    assert held.message == "rate held: 100.0 Hz"
    for i in range(1, 51):                               # the timer at half the rate
        clock.due(1000 * MS + i * 20 * MS)
    late = clock.report(2000 * MS)
    assert not late.held
    assert late.tick_hz == pytest.approx(50.0) and late.sample_hz == pytest.approx(100.0)
    assert late.caught_up == 50 and late.skipped == 0


def test_realtime_stamps_stay_with_the_clock_when_the_rate_is_not_held(processes,
                                                                       rclpy_context, spin):
    """At a rate its timer cannot hold, sim_plant's stamps once fell behind the clock by the
    ticks it missed (seconds within seconds); now a late tick publishes the samples it missed,
    stamped on time, and /diagnostics say the rate was not held."""
    rclpy = pytest.importorskip("rclpy")
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PointStamped

    from ipmc_driver.qos import SAMPLE_QOS

    processes.start_node("sim_plant", "sim_plant", {"rate_hz": 5000.0,
                                                    "diagnostics_period_s": 0.5})
    node = rclpy.create_node("sim_plant_clock_test", context=rclpy_context)
    delays_s, rate = [], []

    def on_sample(msg, info) -> None:
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        delays_s.append((info["received_timestamp"] - stamp_ns) * 1e-9)

    def on_diag(msg) -> None:
        rate.extend(s for s in msg.status if s.name == "sim_plant: rate")

    try:
        node.create_subscription(PointStamped, "/ipmc/displacement", on_sample, SAMPLE_QOS)
        node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
        assert spin(node, lambda: len(delays_s) > 0, 20.0), processes.log("sim_plant")
        n = len(delays_s)
        spin(node, lambda: False, 4.0)
        late = delays_s[n:]
        assert len(late) > 1000
        worst = sorted(late)[int(0.95 * len(late))]
        assert worst < 0.5, f"stamps {worst:.2f} s behind the clock"
        assert any(s.level == b"\x01" and "rate not held" in s.message for s in rate), \
            [s.message for s in rate]
    finally:
        node.destroy_node()
    assert processes.stop("sim_plant") <= 2.0
