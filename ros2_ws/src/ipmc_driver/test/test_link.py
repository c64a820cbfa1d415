"""The driver's link core without ROS: a fake port, a fake device path and a fake clock.

The state machine, the back-off and the device poll, the feeding of the rig's watchdog, the
command watchdog, non-finite commands, the sample counter, stamps and parameter checks. Time is
the test's: every figure is exact, nothing depends on this machine's scheduling.
"""

from __future__ import annotations

import math
import queue
import subprocess
import sys
import threading

import numpy as np
import pytest

from ipmc_driver.arc import ArcGeometry
from ipmc_driver.link import (
    BACKOFF_MAX_S,
    CONNECTED,
    DISCONNECTED,
    DRIVER_PARAMETERS,
    ERROR,
    FEED_PERIOD_S,
    OK,
    TICK_PERIOD_S,
    DriverLink,
    LinkConfig,
    SampleCounter,
    check_parameters,
)
from ipmc_driver.protocol import (
    RIG_WATCHDOG_S,
    FrameDecoder,
    Ping,
    Sample,
    SetVoltage,
    Status,
    encode_message,
    parse_frame,
)


class FakePort:
    """The PC's end of the line: what the link writes is decoded and kept with the fake time;
    ``feed`` queues bytes from the rig for the reader thread."""

    def __init__(self, clock):
        self.written: list[tuple[float, object]] = []
        self.closed = False
        self.read_error: OSError | None = None
        self._clock = clock
        self._rx: queue.SimpleQueue = queue.SimpleQueue()
        self._decoder = FrameDecoder()

    in_waiting = 0

    def read(self, size: int) -> bytes:
        if self.read_error is not None:
            raise self.read_error
        try:
            return self._rx.get(timeout=0.01)
        except queue.Empty:
            return b""

    def write(self, data: bytes) -> None:
        if self.closed:
            raise OSError("write to a closed port")
        self.written += [(self._clock(), parse_frame(f)) for f in self._decoder.feed(data)]

    def feed(self, data: bytes) -> None:
        self._rx.put(data)

    def reset_input_buffer(self) -> None:
        pass

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True

    def voltages(self) -> list[tuple[float, float]]:
        return [(t, m.voltage_v) for t, m in self.written if isinstance(m, SetVoltage)]


class FakeRig:
    """A device path that can vanish, opens that can fail, and the clock of the test."""

    def __init__(self):
        self.ticks = 0
        self.present = True
        self.open_error: str | None = None
        self.opens: list[float] = []
        self.ports: list[FakePort] = []
        self.frames = threading.Event()

    @property
    def now(self) -> float:
        return self.ticks * TICK_PERIOD_S

    def device_id(self, path: str):
        return (0, 1, 2) if self.present else None

    def open_port(self, path: str, baudrate: int) -> FakePort:
        self.opens.append(self.now)
        if self.open_error is not None:
            raise OSError(self.open_error)
        self.ports.append(FakePort(lambda: self.now))
        return self.ports[-1]

    def link(self, **config) -> DriverLink:
        self.log: list[tuple[str, str]] = []
        return DriverLink(LinkConfig(port="/dev/ttyRIG", **config), open_port=self.open_port,
                          device_id=self.device_id, clock=lambda: self.now,
                          on_frames=self.frames.set,
                          log=lambda level, text: self.log.append((level, text)))

    def run(self, link: DriverLink, until_s: float) -> None:
        """Tick the link every ``TICK_PERIOD_S`` up to ``until_s``."""
        while self.now < until_s - 1e-9:
            self.ticks += 1
            link.tick(self.now)


@pytest.fixture
def rig():
    rig = FakeRig()
    yield rig
    for port in rig.ports:
        port.close()


def test_import_leaves_rclpy_out():
    out = subprocess.run([sys.executable, "-c", "import sys, ipmc_driver.link; "
                          "print('rclpy' in sys.modules)"], capture_output=True, text=True)
    assert out.stdout.strip() == "False"


# --------------------------------------------------------------------------- parameters
def test_default_parameters_accepted():
    assert check_parameters({n: p.default for n, p in DRIVER_PARAMETERS.items()}) == ""
    assert LinkConfig.from_parameters({}).port == "/dev/ttyUSB0"


@pytest.mark.parametrize("name, value, reason", [
    ("u_max", 3.5, "u_max must be in (0, 3.0] V"),
    ("u_max", math.nan, "u_max must be in (0, 3.0] V"),
    ("u_max", "3", "u_max must be in (0, 3.0] V"),
    ("watchdog_s", -0.1, "watchdog_s must be > 0 s"),
    ("watchdog_s", math.inf, "watchdog_s must be > 0 s (and finite)"),
    ("stale_s", 0.0, "stale_s must be > 0 s"),
    ("diagnostics_period_s", -1.0, "diagnostics_period_s must be > 0 s"),
    ("sample_rate_hz", 70000.0, "sample_rate_hz must be in (0, 65535] Hz"),
    ("baudrate", True, "baudrate must be an integer"),
    ("port", " ", "port must name the serial device"),
    ("arc_l2_mm", 27.0, "arc_l2_mm must be in (0, l1_mm=27.0)"),
    ("arc_d_mm", math.inf, "arc_d_mm must be a finite number"),
])
def test_bad_parameter_refused_with_reason(name, value, reason):
    values = {n: p.default for n, p in DRIVER_PARAMETERS.items()} | {name: value}
    refusal = check_parameters(values)
    assert refusal.startswith(f"parameter {reason}")
    with pytest.raises(ValueError, match=name):
        LinkConfig.from_parameters({name: value})


# --------------------------------------------------------------------------- link states
def test_first_tick_opens_pings_and_sends_zero_volts(rig):
    link = rig.link()
    assert link.state == DISCONNECTED
    rig.run(link, TICK_PERIOD_S)
    assert link.state == CONNECTED and rig.opens == [TICK_PERIOD_S]
    messages = [m for _, m in rig.ports[0].written]
    assert messages == [Ping(), SetVoltage(0.0)]
    link.shutdown()


def test_failed_opens_back_off_doubling_to_the_cap(rig):
    rig.open_error = "Permission denied"
    link = rig.link()
    rig.run(link, 60.0)
    gaps = [b - a for a, b in zip(rig.opens, rig.opens[1:], strict=False)]
    # At the first tick at or after the attempt is due.
    expected = [0.5, 1.0, 2.0, 4.0, 8.0] + [BACKOFF_MAX_S] * (len(gaps) - 5)
    assert len(gaps) == 9
    for gap, due in zip(gaps, expected, strict=True):
        assert due - 1e-9 <= gap <= due + TICK_PERIOD_S + 1e-9
    assert link.state == DISCONNECTED
    assert "Permission denied" in link.last_error


@pytest.mark.parametrize("unplugged_s", [2.0, 8.0])
def test_device_opened_at_the_first_tick_after_it_reappears(rig, unplugged_s):
    link = rig.link()
    rig.run(link, 1.0)
    rig.present = False
    rig.run(link, 1.0 + TICK_PERIOD_S)
    assert link.state == DISCONNECTED  # noticed without a read error
    rig.run(link, 1.0 + unplugged_s)
    assert rig.opens == [TICK_PERIOD_S]  # no attempt while the path is absent
    rig.present = True
    rig.run(link, 1.0 + unplugged_s + TICK_PERIOD_S)
    assert link.state == CONNECTED
    assert rig.opens[1:] == [pytest.approx(1.0 + unplugged_s + TICK_PERIOD_S)]
    link.shutdown()


def test_reappearing_device_cuts_a_long_back_off_short(rig):
    rig.open_error = "Device or resource busy"
    link = rig.link()
    rig.run(link, 30.0)  # the back-off has reached its cap
    assert link.next_attempt_s - rig.now > 1.0
    rig.present = False
    rig.run(link, 31.0)
    rig.present, rig.open_error = True, None
    rig.run(link, 31.0 + TICK_PERIOD_S)
    assert link.state == CONNECTED
    link.shutdown()


def wait_until(predicate, timeout_s: float = 5.0) -> None:
    """Wait for the reader thread (a real thread) to have done something."""
    done = threading.Event()
    for _ in range(int(timeout_s / 0.005)):
        if predicate():
            return
        done.wait(0.005)
    raise AssertionError("timed out")


def test_read_error_closes_the_port_and_retries_after_the_back_off(rig):
    link = rig.link()
    rig.run(link, 0.5)
    rig.ports[0].read_error = OSError(5, "Input/output error")
    wait_until(lambda: link.link_error is not None)
    rig.run(link, 0.5 + TICK_PERIOD_S)
    assert link.state == DISCONNECTED and rig.ports[0].closed
    assert "Input/output error" in link.last_error
    rig.run(link, 1.0)  # the device is still there: the back-off (0.5 s) applies
    assert len(rig.opens) == 1
    rig.run(link, 1.0 + TICK_PERIOD_S)
    assert link.state == CONNECTED
    assert rig.opens[1] == pytest.approx(1.0 + TICK_PERIOD_S)
    link.shutdown()


def test_diagnostics_say_the_link_waits_for_the_device(rig):
    rig.present = False
    link = rig.link()
    rig.run(link, 0.5)
    link_status = link.diagnostics(rig.now)[0]
    assert link_status.level == ERROR
    assert "waiting for the device to appear" in link_status.message
    assert [level for level, text in rig.log if "absent" in text] == ["warn"]  # said once


# --------------------------------------------------------------------------- commands
def test_setpoint_repeated_often_enough_for_the_rig_watchdog(rig):
    link = rig.link(watchdog_s=5.0)
    rig.run(link, 0.1)
    link.command(1.5, rig.now)
    rig.run(link, 2.0)
    sent = rig.ports[0].voltages()
    times = [t for t, _ in sent]
    gaps = [b - a for a, b in zip(times, times[1:], strict=False)]
    # The protocol asks for a SET_VOLTAGE at least every N/2; the link repeats after N/4.
    assert max(gaps) <= FEED_PERIOD_S + TICK_PERIOD_S + 1e-9 <= RIG_WATCHDOG_S / 2
    assert [v for t, v in sent if t >= 0.1] == [1.5] * sum(t >= 0.1 for t in times)
    assert link.keepalives >= (2.0 - 0.1) / (FEED_PERIOD_S + TICK_PERIOD_S)
    link.shutdown()


def test_new_commands_make_repeats_unnecessary(rig):
    link = rig.link()
    rig.run(link, 0.1)
    keepalives = link.keepalives
    for k in range(40):  # a controller at 40 Hz: one command per tick
        link.command(0.01 * k, rig.now)
        rig.run(link, rig.now + TICK_PERIOD_S)
    assert link.keepalives == keepalives
    link.shutdown()


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_command_is_zero_volts_in_the_next_frame(rig, bad):
    link = rig.link(watchdog_s=5.0)
    rig.run(link, 0.1)
    link.command(-3.0, rig.now)
    n = len(rig.ports[0].voltages())
    assert link.command(bad, rig.now) == 0.0
    assert rig.ports[0].voltages()[n] == (rig.now, 0.0)  # at once, not at the next tick
    rig.run(link, 1.0)
    assert {v for _, v in rig.ports[0].voltages()[n:]} == {0.0}  # the repeats too
    assert link.requested_v == 0.0 and link.non_finite == 1
    assert link.watchdog_trips == 0
    link.command(bad, rig.now)
    assert [level for level, text in rig.log if "non-finite" in text] == ["warn"]  # once a run
    link.command(1.0, rig.now)
    assert rig.ports[0].voltages()[-1] == (rig.now, 1.0)
    link.shutdown()


def test_command_watchdog_sends_zero_volts_then_keeps_feeding_zero(rig):
    link = rig.link(watchdog_s=0.3)
    rig.run(link, 0.1)
    link.command(2.0, rig.now)
    rig.run(link, 0.4 - TICK_PERIOD_S)
    assert not link.watchdog_tripped
    rig.run(link, 0.4 + TICK_PERIOD_S)
    assert link.watchdog_tripped and link.setpoint_v == 0.0
    first_zero = next(t for t, v in rig.ports[0].voltages() if t > 0.1 and v == 0.0)
    assert 0.4 - 1e-9 <= first_zero <= 0.4 + TICK_PERIOD_S + 1e-9
    rig.run(link, 1.0)
    assert {v for t, v in rig.ports[0].voltages() if t >= first_zero} == {0.0}
    link.command(1.0, rig.now)
    assert not link.watchdog_tripped
    link.shutdown()


def test_commands_limited_to_u_max_and_a_lower_limit_applied_at_once(rig):
    link = rig.link()
    rig.run(link, 0.1)
    assert link.command(5.0, rig.now) == 3.0
    assert link.command(-1.0, rig.now) == -1.0
    link.reconfigure(LinkConfig(port="/dev/ttyRIG", u_max_v=0.5))
    assert rig.ports[0].voltages()[-1][1] == -0.5
    assert link.clamped == 2
    with pytest.raises(ValueError, match="fixed"):
        link.reconfigure(LinkConfig(port="/dev/other"))
    link.shutdown()


def test_reconnect_sends_the_requested_voltage_again(rig):
    link = rig.link(watchdog_s=30.0)
    rig.run(link, 0.1)
    link.command(1.2, rig.now)
    rig.present = False
    rig.run(link, 1.0)
    rig.present = True
    rig.run(link, 1.0 + TICK_PERIOD_S)
    assert [m for _, m in rig.ports[1].written][:2] == [Ping(), SetVoltage(1.2)]
    link.shutdown()


def test_shutdown_sends_zero_volts_and_closes(rig):
    link = rig.link()
    rig.run(link, 0.1)
    link.command(2.5, rig.now)
    link.shutdown()
    assert rig.ports[0].voltages()[-1][1] == 0.0
    assert rig.ports[0].closed and link.state == DISCONNECTED


# --------------------------------------------------------------------------- samples
def test_counter_unwraps_counts_drops_and_restarts():
    counter = SampleCounter()
    top = (1 << 32) - 2
    got = [counter.update(raw) for raw in (top, top + 1, 1, 1, 0, 5, 100)]
    assert got == [top, top + 1, top + 3, None, None, top + 7, top + 102]
    assert counter.dropped == 1 + 3 + 94
    assert counter.restarts == 0
    assert counter.update(50) == 50  # far behind: the firmware restarted
    assert counter.restarts == 1 and counter.last == 50


def received(link: DriverLink, rig: FakeRig, port: FakePort, messages) -> list:
    """Send ``messages`` from the rig; the samples ``drain`` returns once they are in."""
    rig.frames.clear()
    # One chunk: the reader queues all its frames before it signals.
    port.feed(b"".join(encode_message(m, seq=k % 256) for k, m in enumerate(messages)))
    wait_until(rig.frames.is_set)
    return link.drain(lambda: 10**12)


def test_samples_stamped_from_counter_compensated_and_paired(rig):
    link = rig.link(sample_rate_hz=200.0, watchdog_s=30.0)
    rig.run(link, 0.1)
    link.command(0.8, rig.now)
    geo = ArcGeometry()
    seq = link._tx_seq
    lo, hi = geo.reading_range_mm
    messages = [Sample(10, 0.8, geo.reading_scalar(-1.0), seq),
                Sample(11, 0.8, hi + 1.0, seq),  # the beam missed the actuator
                Sample(14, 0.8, None, seq),  # the sensor saw no target
                Status(14, 200, 0.8),
                Sample(15, 0.8, geo.reading_scalar(0.5), seq)]
    samples = received(link, rig, rig.ports[0], messages)
    assert [s.counter for s in samples] == [10, 15]
    assert samples[1].stamp_ns - samples[0].stamp_ns == 5 * 5_000_000
    # read in one chunk: the latest sample arrived nearest its instant and anchors them all
    assert samples[1].stamp_ns == 10**12
    assert [s.y_mm for s in samples] == pytest.approx([-1.0, 0.5], abs=5e-3)
    assert [s.requested_v for s in samples] == [0.8, 0.8]
    assert link.out_of_range == 2 and link.counter.dropped == 2
    assert link.rig_rate_hz == 200 and link.published == 2
    assert len(link.latencies_s) == 1
    assert [r.level for r in link.diagnostics(rig.now)][2:] == [OK, OK]
    link.shutdown()


def test_a_burst_of_buffered_samples_does_not_make_every_later_stamp_late(rig):
    """At connection the rig's transmit buffer empties in a burst: 0.5 s of old samples arrive
    at once. The stamps of the samples after it are their instants, not 0.5 s late, and all
    stamps increase."""
    link = rig.link(sample_rate_hz=100.0, watchdog_s=30.0)
    rig.run(link, 0.1)
    geo = ArcGeometry()

    def ros_now_ns() -> int:   # the node's clock: 1000 s ahead of the link's
        return int((1000.0 + rig.now) * 1e9)

    def arrive(counters) -> list:
        rig.frames.clear()
        rig.ports[0].feed(b"".join(encode_message(Sample(c, 0.0, geo.reading_scalar(0.0), 0),
                                                  seq=c % 256) for c in counters))
        wait_until(rig.frames.is_set)
        return link.drain(ros_now_ns)

    burst = arrive(range(50))          # samples 0-49, the last one taken now
    later = []
    for c in range(50, 60):            # then the next ones as they come, each after its instant
        rig.run(link, rig.now + 0.01)
        later += arrive([c])
    stamps = [s.stamp_ns for s in burst + later]
    assert np.all(np.diff(stamps) > 0)
    # the burst's samples too get their instants: 10 ms apart, the last one now
    assert np.diff([s.stamp_ns for s in burst]) == pytest.approx(10_000_000, abs=1)
    taken_s = burst[-1].arrival_s   # sample 49 was taken as the burst arrived
    for s in later:   # the instants, not 0.5 s late; never after the arrival
        assert s.stamp_ns == pytest.approx((1000.0 + taken_s + (s.counter - 49) * 0.01) * 1e9,
                                           abs=1e3)
        assert s.stamp_ns <= (1000.0 + s.arrival_s) * 1e9
    link.shutdown()
