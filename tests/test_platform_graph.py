"""sim_plant and recorder as separate processes over real DDS."""

from __future__ import annotations

import time

import numpy as np
import pytest

from ipmc_driver.dataio import load_record

rclpy = pytest.importorskip("rclpy")
from geometry_msgs.msg import PointStamped  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402

from ipmc_driver.qos import SAMPLE_QOS  # noqa: E402

LEVELS_V = [0.0, 1.5, -2.0, 0.5, 0.0]
HOLD_S = 1.0


def wait_for(predicate, timeout_s, what):
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def test_commands_through_sim_plant_are_recorded_without_gaps(processes, rclpy_context, spin,
                                                               tmp_path):
    bag = tmp_path / "run_bag"
    processes.start_node("sim_plant", "sim_plant", {"rate_hz": 100.0, "seed": 4})
    processes.start_node("recorder", "recorder", {"output": str(bag), "split_s": 2.0})
    node = rclpy.create_node("platform_test", context=rclpy_context)
    try:
        pub = node.create_publisher(Float64, "/ipmc/command", 10)
        seen = []
        node.create_subscription(PointStamped, "/ipmc/displacement",
                                 lambda m: seen.append(m), SAMPLE_QOS)
        # The recorder must be listening before the sequence starts.
        assert spin(node, lambda: len(seen) > 5 and node.count_subscribers(
            "/ipmc/displacement") >= 2, 20.0), "sim_plant or recorder did not come up"
        for level in LEVELS_V:
            pub.publish(Float64(data=level))
            spin(node, lambda: False, HOLD_S)
    finally:
        node.destroy_node()
    exit_s = processes.stop_all()
    assert exit_s["recorder"] <= 2.0 and exit_s["sim_plant"] <= 2.0, exit_s

    rec = load_record(bag)
    dt = np.diff(rec.t_s)
    np.testing.assert_allclose(dt, 0.01, atol=1e-6)  # contiguous: no gap, no duplicate
    assert len(rec) >= int(len(LEVELS_V) * HOLD_S * 100 * 0.9)
    # Every commanded level was applied for most of its hold, in order.
    change = np.flatnonzero(np.diff(rec.u_v)) + 1
    runs = [float(v) for v in rec.u_v[np.r_[0, change]]]
    assert runs == LEVELS_V
    held = np.diff(np.r_[change, len(rec)]) * 0.01  # the last level until the recorder stopped
    np.testing.assert_allclose(held[:-1], HOLD_S, atol=0.15)
    # The tip answers: negative voltage bends negative, positive bends positive.
    assert rec.y_mm[rec.u_v == -2.0].min() < -1.0
    assert rec.y_mm[rec.u_v == 1.5].max() > 0.3


def test_lockstep_runs_faster_than_real_time_and_publishes_clock(processes, rclpy_context,
                                                                 spin):
    processes.start_node("sim_plant", "sim_plant", {"clock_mode": "lockstep"})
    node = rclpy.create_node("lockstep_test", context=rclpy_context)
    try:
        clocks, samples = [], []
        node.create_subscription(Clock, "/clock", lambda m: clocks.append(
            m.clock.sec + m.clock.nanosec * 1e-9), 10)
        node.create_subscription(PointStamped, "/ipmc/displacement",
                                 lambda m: samples.append(m), SAMPLE_QOS)
        assert spin(node, lambda: len(samples) > 0, 20.0), "no sample in lock-step mode"
        t_wall = time.monotonic()
        n0 = len(samples)
        spin(node, lambda: False, 3.0)
        wall = time.monotonic() - t_wall
        sim = (len(samples) - n0) * 0.01
    finally:
        node.destroy_node()
    assert processes.stop("sim_plant") <= 2.0
    assert sim > 1.5 * wall, f"{sim:.2f} s simulated in {wall:.2f} s of wall time"
    assert np.all(np.diff(clocks) > 0)


def test_lockstep_applies_the_command_stamped_for_each_sample(processes, rclpy_context, spin):
    """A stamped command answers one sample: stale and duplicate commands never shift the rest
    by a sample (a bare Float64 cannot say which sample it answers)."""
    from geometry_msgs.msg import Vector3Stamped

    # Time waits until the plant's own subscription has matched the stamped publisher: the
    # test's side can see the match first, and a plant that has not seen it yet steps on
    # without waiting for the answers.
    processes.start_node("sim_plant", "sim_plant", {"clock_mode": "lockstep",
                                                    "lockstep_timeout_s": 5.0,
                                                    "lockstep_min_command_publishers": 1})
    node = rclpy.create_node("stamped_command_test", context=rclpy_context)
    try:
        pub = node.create_publisher(Vector3Stamped, "/ipmc/command_stamped", 10)
        pub_plain = node.create_publisher(Float64, "/ipmc/command", 10)
        applied = {}   # sample stamp (ns) -> applied voltage (V)
        answered = []  # stamps answered so far

        def stamp_ns(m):
            return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec

        def on_voltage(m):
            applied[stamp_ns(m)] = m.vector.x
            k = len(answered)
            if k >= 40:
                return
            # For each sample: a stale command (previous stamp) and a bare Float64 first, both
            # wrong; then the right one, stamped with this sample, and a duplicate of it later.
            sec, nsec = m.header.stamp.sec, m.header.stamp.nanosec
            wrong = Vector3Stamped()
            wrong.header.stamp.sec, wrong.header.stamp.nanosec = sec, max(0, nsec - 10_000_000)
            wrong.vector.x = -2.5
            pub.publish(wrong)
            pub_plain.publish(Float64(data=-2.9))
            right = Vector3Stamped()
            right.header.stamp.sec, right.header.stamp.nanosec = sec, nsec
            right.vector.x = 0.05 * (k % 20)
            pub.publish(right)
            pub.publish(right)
            answered.append(stamp_ns(m))

        node.create_subscription(Vector3Stamped, "/ipmc/voltage", on_voltage, SAMPLE_QOS)
        assert spin(node, lambda: pub.get_subscription_count() > 0, 20.0), "plant not up"
        node.create_subscription(PointStamped, "/ipmc/displacement", lambda m: None, SAMPLE_QOS)
        assert spin(node, lambda: len(applied) > 40, 30.0), f"only {len(applied)} samples"
    finally:
        node.destroy_node()
    processes.stop("sim_plant")
    stamps = sorted(applied)
    # The command answering sample k is applied over the next one (k + 1).
    for k, s in enumerate(answered[1:39], start=1):
        nxt = stamps[stamps.index(s) + 1]
        assert applied[nxt] == pytest.approx(0.05 * (k % 20)), (k, applied[nxt])


def test_lockstep_time_waits_for_the_stamped_commander(processes, rclpy_context, spin):
    """With ``lockstep_min_command_publishers`` the plant's time stands still, listeners matched,
    until a ``/ipmc/command_stamped`` publisher has matched; then sample 0 waits for its command
    like every other. (The ROS graph can list the controller late: a plant that read "nobody
    commands me" from it once ran nine samples ahead of the controller in ``make test``.)"""
    from geometry_msgs.msg import Vector3Stamped

    processes.start_node("sim_plant", "sim_plant", {"clock_mode": "lockstep",
                                                    "lockstep_timeout_s": 5.0,
                                                    "lockstep_min_command_publishers": 1})
    node = rclpy.create_node("commander_gate_test", context=rclpy_context)
    try:
        applied = {}   # sample stamp (ns) -> applied voltage (V)
        pub = None

        def stamp_ns(m):
            return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec

        def on_voltage(m):
            applied[stamp_ns(m)] = m.vector.x
            if pub is not None and len(applied) <= 30:
                answer = Vector3Stamped()
                answer.header.stamp = m.header.stamp
                answer.vector.x = 0.1 * len(applied)
                pub.publish(answer)

        node.create_subscription(Vector3Stamped, "/ipmc/voltage", on_voltage, SAMPLE_QOS)
        node.create_subscription(PointStamped, "/ipmc/displacement", lambda m: None, SAMPLE_QOS)
        assert spin(node, lambda: node.count_publishers("/ipmc/displacement") > 0, 20.0), \
            "plant not up"
        # Listeners are matched, but no commander: time must not start.
        spin(node, lambda: False, 2.0)
        assert applied == {}, f"time started without a commander: {sorted(applied)[:5]}"
        pub = node.create_publisher(Vector3Stamped, "/ipmc/command_stamped", 10)
        assert spin(node, lambda: len(applied) > 30, 30.0), f"only {len(applied)} samples"
    finally:
        node.destroy_node()
    processes.stop("sim_plant")
    assert "no command for the sample" not in processes.log("sim_plant")
    stamps = sorted(applied)
    assert stamps[0] == 0
    # Sample k (from 0) was answered with 0.1 (k + 1) V, applied over sample k + 1.
    for k in range(29):
        assert applied[stamps[k + 1]] == pytest.approx(0.1 * (k + 1)), (k, applied)


def test_recorder_subscribes_the_rest_once_awaited_publishers_have_matched(
        processes, rclpy_context, spin, tmp_path):
    """With ``await_publishers``, the recorder's displacement subscription (which a lock-step
    start waits for) appears only once the awaited topic has matched a publisher, so the
    awaited topic's first sample is in the bag (a late match once lost 1.9 s of them)."""
    from geometry_msgs.msg import Vector3Stamped

    from ipmc_driver.dataio import read_stamped_series
    from ipmc_driver.qos import PAIRED_SAMPLE_QOS

    bag = tmp_path / "await_bag"
    processes.start_node("recorder", "recorder", {
        "output": str(bag), "topics": ["/ipmc/displacement", "/ipmc/feedforward"],
        "await_publishers": ["/ipmc/feedforward"]})
    node = rclpy.create_node("await_test", context=rclpy_context)
    try:
        disp = node.create_publisher(PointStamped, "/ipmc/displacement", SAMPLE_QOS)
        assert spin(node, lambda: node.count_subscribers("/ipmc/feedforward") >= 1, 20.0), \
            "recorder did not come up"
        spin(node, lambda: disp.get_subscription_count() > 0, 2.0)
        assert disp.get_subscription_count() == 0, "displacement subscribed before feedforward"
        ff = node.create_publisher(Vector3Stamped, "/ipmc/feedforward", PAIRED_SAMPLE_QOS)
        assert spin(node, lambda: disp.get_subscription_count() == 1, 20.0), \
            "displacement never subscribed after the feedforward publisher appeared"
        spin(node, lambda: ff.get_subscription_count() == 1, 5.0)
        for k in range(3):
            stamp = (k + 1) * 10_000_000
            m_ff, m_y = Vector3Stamped(), PointStamped()
            m_ff.header.stamp.nanosec = m_y.header.stamp.nanosec = stamp
            m_ff.vector.x, m_y.point.x = 0.5 * k, 1e-3 * k
            ff.publish(m_ff)
            disp.publish(m_y)
        spin(node, lambda: False, 1.0)
    finally:
        node.destroy_node()
    assert processes.stop("recorder") <= 2.0
    series = read_stamped_series(bag, {"/ipmc/feedforward": "geometry_msgs/msg/Vector3Stamped",
                                       "/ipmc/displacement": "geometry_msgs/msg/PointStamped"})
    assert sorted(series["/ipmc/feedforward"]) == [10_000_000, 20_000_000, 30_000_000]
    assert sorted(series["/ipmc/displacement"]) == [10_000_000, 20_000_000, 30_000_000]
