"""The driver node in process, the test playing the rig on the other end of a pty.

Precise control of what the "rig" sends: stamps from the counter, dropped samples, out-of-range
readings, the voltage limit, non-finite commands, the watchdog, the repeated setpoint that feeds
the rig's watchdog, 0 V on destroy, parameter validation (a table of bad values, each at start-up
and at run time). The link's logic without ROS is test_link.py; the whole graph
with the emulator and the recorder as processes is tests/test_driver_graph.py.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
import tty

import pytest

rclpy = pytest.importorskip("rclpy")
from geometry_msgs.msg import PointStamped, Vector3Stamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, QoSReliabilityPolicy  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402

from ipmc_driver.arc import ArcGeometry  # noqa: E402
from ipmc_driver.nodes.driver import Driver  # noqa: E402
from ipmc_driver.protocol import (  # noqa: E402
    FrameDecoder,
    Sample,
    SetVoltage,
    encode_message,
    parse_frame,
)

QOS = QoSProfile(depth=100, reliability=QoSReliabilityPolicy.RELIABLE)
PERIOD_NS = 10_000_000


@pytest.fixture
def graph():
    """A driver on a pty (the test holds the master end), a probe node, one executor."""
    # 215-232: DDS ports above Linux's ephemeral range; one domain per test session.
    keys = {"ROS_DOMAIN_ID": str(215 + os.getpid() % 18),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    old = {k: os.environ.get(k) for k in keys}
    os.environ.update(keys)
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    context = rclpy.Context()
    rclpy.init(context=context)
    driver = Driver(context=context, parameter_overrides=[
        Parameter("port", value=os.ttyname(slave)),
        Parameter("watchdog_s", value=0.3),
    ])
    probe = rclpy.create_node("probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(driver)
    executor.add_node(probe)
    rig = Rig(master, executor, probe)
    try:
        yield driver, rig
    finally:
        executor.shutdown()
        if driver.handle is not None:
            driver.destroy_node()
        probe.destroy_node()
        rclpy.try_shutdown(context=context)
        os.close(master)
        os.close(slave)
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class Rig:
    """The test's side of the serial line, plus what the driver published."""

    def __init__(self, master, executor, probe):
        self.master = master
        self.executor = executor
        self.decoder = FrameDecoder()
        self.commands: list[float] = []
        self.disp: list[tuple[int, float]] = []
        self.volt: list[tuple[int, float, float]] = []
        probe.create_subscription(PointStamped, "/ipmc/displacement", self._on_disp, QOS)
        probe.create_subscription(Vector3Stamped, "/ipmc/voltage", self._on_volt, QOS)
        self.command = probe.create_publisher(Float64, "/ipmc/command", 10)
        self.seq = 0

    @staticmethod
    def _ns(h):
        return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec

    def _on_disp(self, m):
        self.disp.append((self._ns(m.header), m.point.x))

    def _on_volt(self, m):
        self.volt.append((self._ns(m.header), m.vector.x, m.vector.y))

    def send(self, sample: Sample):
        self.seq = (self.seq + 1) & 0xFF
        os.write(self.master, encode_message(sample, self.seq))

    def spin(self, seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.005)
            try:
                data = os.read(self.master, 4096)
            except (BlockingIOError, OSError):
                data = b""
            for frame in self.decoder.feed(data):
                msg = parse_frame(frame)
                if isinstance(msg, SetVoltage):
                    self.commands.append(msg.voltage_v)

    def wait(self, predicate, timeout_s=5.0):
        deadline = time.monotonic() + timeout_s
        while not predicate():
            assert time.monotonic() < deadline, "timed out"
            self.spin(0.02)


def send_at_instants(rig, samples) -> None:
    """Send each sample when the rig takes it (its counter's period after the first): sent
    all at once they would be a buffered burst, which the driver re-anchors."""
    t0, first = time.monotonic(), samples[0].counter
    for sample in samples:
        time.sleep(max(0.0, t0 + (sample.counter - first) * PERIOD_NS * 1e-9 - time.monotonic()))
        rig.send(sample)


def test_stamps_from_counter_and_dropped_samples(graph):
    driver, rig = graph
    rig.wait(lambda: driver.link.state == "connected")
    geo = ArcGeometry()
    send_at_instants(rig, [Sample(c, 0.5, geo.reading(-c * 0.01))  # 103, 104 lost
                           for c in (100, 101, 102, 105, 106)])
    rig.wait(lambda: len(rig.disp) == 5 and len(rig.volt) == 5)
    stamps = [s for s, _ in rig.disp]
    assert [s - stamps[0] for s in stamps] == [0, 1 * PERIOD_NS, 2 * PERIOD_NS, 5 * PERIOD_NS,
                                               6 * PERIOD_NS]
    # Arc-compensated, in metres; 16-bit laser counts: within 5 um.
    assert [y * 1e3 for _, y in rig.disp] == pytest.approx([-1.0, -1.01, -1.02, -1.05, -1.06],
                                                          abs=5e-3)
    assert all(v[1] == pytest.approx(0.5) for v in rig.volt)
    assert driver.link.counter.dropped == 2
    # A repeated (or older) counter is not a new sample.
    rig.send(Sample(106, 0.5, 150.0))
    rig.spin(0.1)
    assert len(rig.disp) == 5


def test_out_of_range_readings_counted_not_published(graph):
    driver, rig = graph
    rig.wait(lambda: driver.link.state == "connected")
    lo, hi = ArcGeometry().reading_range_mm
    send_at_instants(rig, [Sample(1, 0.0, 150.0),
                           Sample(2, 0.0, hi + 1.0),  # beyond Eq. 1's range
                           Sample(3, 0.0, None),  # the sensor saw no target
                           Sample(4, 0.0, lo),  # the open end of the range
                           Sample(5, 0.0, 151.0)])
    rig.wait(lambda: len(rig.disp) == 2)
    rig.spin(0.1)
    assert len(rig.disp) == len(rig.volt) == 2
    assert driver.link.out_of_range == 3
    assert rig.disp[1][0] - rig.disp[0][0] == 4 * PERIOD_NS


def test_commands_limited_to_u_max(graph):
    driver, rig = graph
    rig.wait(lambda: driver.link.state == "connected")
    rig.wait(lambda: rig.command.get_subscription_count() >= 1)
    for v in (1.25, 5.0, -7.0):
        rig.command.publish(Float64(data=v))
        rig.spin(0.05)
    # the watchdog's 0 V may follow 0.3 s after the last command, before a loaded machine
    # polls (it can under heavy parallel load)
    rig.wait(lambda: [c for c in rig.commands if c != 0.0][-2:] == [3.0, -3.0])
    assert 1.25 in rig.commands
    assert max(abs(v) for v in rig.commands) <= 3.0
    assert driver.link.clamped == 2


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_command_sends_zero_volts_at_once(graph, bad):
    driver, rig = graph
    driver.set_parameters([Parameter("watchdog_s", value=30.0)])  # only the command acts
    rig.wait(lambda: driver.link.state == "connected")
    rig.wait(lambda: rig.command.get_subscription_count() >= 1)
    rig.command.publish(Float64(data=-3.0))
    rig.wait(lambda: rig.commands and rig.commands[-1] == -3.0)
    rig.command.publish(Float64(data=bad))
    rig.wait(lambda: rig.commands[-1] == 0.0)
    after = rig.commands[rig.commands.index(-3.0):]
    # -3 V (and its repeats) until the non-finite command, then 0 V: nothing in between.
    assert set(after) == {-3.0, 0.0}
    assert after == sorted(after)
    assert driver.link.non_finite == 1
    assert driver.link.watchdog_trips == 0


def test_setpoint_repeated_without_new_commands(graph):
    driver, rig = graph
    driver.set_parameters([Parameter("watchdog_s", value=30.0)])
    rig.wait(lambda: driver.link.state == "connected")
    rig.wait(lambda: rig.command.get_subscription_count() >= 1)
    rig.command.publish(Float64(data=1.5))
    rig.wait(lambda: rig.commands and rig.commands[-1] == 1.5)
    first = len(rig.commands)
    # The rig's watchdog needs a SET_VOLTAGE every 100 ms: the driver repeats the setpoint.
    rig.wait(lambda: len(rig.commands) >= first + 5)
    assert rig.commands[first:] == [1.5] * (len(rig.commands) - first)
    assert driver.link.keepalives >= 5


def test_watchdog_commands_zero_volts(graph):
    driver, rig = graph
    rig.wait(lambda: driver.link.state == "connected")
    rig.wait(lambda: rig.command.get_subscription_count() >= 1)
    rig.command.publish(Float64(data=2.0))
    rig.wait(lambda: rig.commands and rig.commands[-1] == 2.0)
    t0 = time.monotonic()
    rig.wait(lambda: rig.commands[-1] == 0.0, timeout_s=2.0)
    assert 0.25 < time.monotonic() - t0 < 0.6
    assert driver.link.watchdog_tripped


def test_destroy_node_commands_zero_then_closes(graph):
    driver, rig = graph
    rig.wait(lambda: driver.link.state == "connected")
    rig.wait(lambda: rig.command.get_subscription_count() >= 1)
    rig.command.publish(Float64(data=-1.5))
    rig.wait(lambda: rig.commands and rig.commands[-1] == -1.5)
    driver.destroy_node()
    rig.spin(0.05)
    assert rig.commands[-1] == 0.0
    assert driver.link.state == "disconnected"


# Each bad value, the reason given at start-up, the reason given at run time (read-only
# parameters are refused as such while the node runs).
READ_ONLY = "read-only"
WRONG_TYPE = "Wrong parameter type"
BAD_PARAMETERS = [
    ("u_max", 5.0, "u_max must be in (0, 3.0] V", None),
    ("u_max", 0.0, "u_max must be in (0, 3.0] V", None),
    ("u_max", -1.0, "u_max must be in (0, 3.0] V", None),
    ("u_max", math.nan, "u_max must be in (0, 3.0] V", None),
    ("u_max", "abc", "u_max must be a float", WRONG_TYPE),
    ("u_max", 3, "u_max must be a float", WRONG_TYPE),
    ("watchdog_s", 0.0, "watchdog_s must be > 0 s", None),
    ("watchdog_s", -0.5, "watchdog_s must be > 0 s", None),
    ("watchdog_s", math.inf, "watchdog_s must be > 0 s (and finite)", None),
    ("watchdog_s", "abc", "watchdog_s must be a float", WRONG_TYPE),
    ("stale_s", -1.0, "stale_s must be > 0 s", None),
    ("stale_s", 0.0, "stale_s must be > 0 s", None),
    ("arc_l2_mm", 30.0, "arc_l2_mm must be in (0, l1_mm=27.0)", None),
    ("arc_l1_mm", -1.0, "arc_l1_mm must be > 0", None),
    ("arc_d_mm", math.nan, "arc_d_mm must be a finite number", None),
    ("sample_rate_hz", 0.0, "sample_rate_hz must be in (0, 65535] Hz", READ_ONLY),
    ("sample_rate_hz", -100.0, "sample_rate_hz must be in (0, 65535] Hz", READ_ONLY),
    ("baudrate", 0, "baudrate must be an integer in (0, 4000000]", READ_ONLY),
    ("baudrate", 115200.0, "baudrate must be an integer, got 115200.0", READ_ONLY),
    ("diagnostics_period_s", -1.0, "diagnostics_period_s must be > 0 s", READ_ONLY),
    ("diagnostics_period_s", 0.0, "diagnostics_period_s must be > 0 s", READ_ONLY),
    ("port", "", "port must name the serial device", READ_ONLY),
    ("frame_id", "", "frame_id must name a frame", READ_ONLY),
]


@pytest.fixture
def bare_context():
    """An rclpy context and a pty for drivers that are expected not to start."""
    keys = {"ROS_DOMAIN_ID": str(215 + os.getpid() % 18),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    old = {k: os.environ.get(k) for k in keys}
    os.environ.update(keys)
    master, slave = os.openpty()
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        yield context, os.ttyname(slave)
    finally:
        rclpy.try_shutdown(context=context)
        os.close(master)
        os.close(slave)
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@pytest.mark.parametrize("name, value, at_start, at_run", BAD_PARAMETERS)
def test_bad_parameter_refused_at_start_up_with_reason(bare_context, name, value, at_start,
                                                       at_run):
    context, port = bare_context
    overrides = [Parameter("port", value=port), Parameter(name, value=value)]
    with pytest.raises(ValueError) as refused:
        Driver(context=context, parameter_overrides=overrides)
    assert at_start in str(refused.value)
    assert "\n" not in str(refused.value)


@pytest.mark.parametrize("name, value, at_start, at_run", BAD_PARAMETERS)
def test_bad_parameter_refused_at_run_time_with_reason(graph, name, value, at_start, at_run):
    driver, _ = graph
    before = driver.get_parameter(name).value
    result = driver.set_parameters([Parameter(name, value=value)])[0]
    assert not result.successful
    assert (at_run or at_start) in result.reason
    assert driver.get_parameter(name).value == before
    assert driver.link.config.as_parameters().get(name, before) == before


@pytest.mark.parametrize("arg, reason", [
    ("watchdog_s:=abc", "parameter watchdog_s must be a float"),
    ("stale_s:=-1.0", "parameter stale_s must be > 0 s"),
])
def test_driver_process_with_bad_parameter_exits_with_one_sentence(arg, reason):
    env = dict(os.environ, ROS_DOMAIN_ID=str(215 + os.getpid() % 18),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    done = subprocess.run([sys.executable, "-m", "ipmc_driver.nodes.driver", "--ros-args",
                           "-p", "port:=/dev/null", "-p", arg],
                          env=env, capture_output=True, text=True, timeout=60)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1
    assert len(lines) == 1 and lines[0].startswith("driver: error: ")
    assert reason in lines[0]
    assert "Traceback" not in done.stderr + done.stdout


def test_good_parameters_applied(graph):
    driver, _ = graph
    results = driver.set_parameters([Parameter("u_max", value=2.0),
                                     Parameter("arc_l2_mm", value=15.0)])
    assert all(r.successful for r in results)
    assert driver.link.config.u_max_v == 2.0
    assert driver.link.config.geometry.l2_mm == 15.0
    result = driver.set_parameters([Parameter("port", value="/dev/null")])[0]
    assert not result.successful  # read-only
