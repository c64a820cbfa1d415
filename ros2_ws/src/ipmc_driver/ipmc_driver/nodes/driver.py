"""driver: the IPMC rig on the ROS graph over RS-485 (the only node that touches hardware).

Subscribes ``/ipmc/command`` (std_msgs/Float64, V); publishes ``/ipmc/voltage``
(Vector3Stamped: x applied V, y requested V) and ``/ipmc/displacement`` (PointStamped, x in m,
arc-compensated) for every sample frame of the rig, stamped ``t0 + counter / sample_rate_hz``
from the rig's sample counter, and ``/diagnostics`` (link, stream, command, watchdog).

Safety: commands are limited to ``u_max`` (never above 3 V); without a command for
``watchdog_s`` the rig is commanded to 0 V; on shutdown the rig is commanded to 0 V and the port
closed. A link state machine (disconnected -> connecting -> connected), run by a timer, reopens a
vanished port with back-off 0.5 s doubling to 10 s. A reader thread per connection feeds decoded
frames to the executor through a guard condition.
"""

from __future__ import annotations

import contextlib
import math
import queue
import threading
import time
from collections import deque
from fractions import Fraction

import serial
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, Vector3Stamped
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_msgs.msg import Float64

from ipmc_driver.arc import D_MM, L1_MM, L2_MM, ArcGeometry
from ipmc_driver.node_runtime import run_node
from ipmc_driver.protocol import (
    FrameDecoder,
    Ping,
    ProtocolError,
    RigError,
    Sample,
    SetVoltage,
    Status,
    encode_message,
    parse_frame,
)
from ipmc_driver.qos import COMMAND_QOS, DIAGNOSTICS_QOS, SAMPLE_QOS

U_MAX_LIMIT_V = 3.0  # above 3 V the paper's actuators bent past 90 degrees (section 2.1)
BACKOFF_FIRST_S = 0.5
BACKOFF_MAX_S = 10.0
LINK_PERIOD_S = 0.05
COUNTER_MODULO = 1 << 32

DISCONNECTED, CONNECTING, CONNECTED = "disconnected", "connecting", "connected"


class Driver(Node):
    def __init__(self, **node_kwargs) -> None:
        # node_kwargs (context, parameter_overrides) let tests build the node in process.
        super().__init__("driver", **node_kwargs)
        ro = dict(read_only=True)
        self.declare_parameter("port", "/dev/ttyUSB0", ParameterDescriptor(
            description="serial device of the RS-485 adapter", **ro))
        self.declare_parameter("baudrate", 115200, ParameterDescriptor(
            description="serial baud rate", **ro))
        self.declare_parameter("sample_rate_hz", 100.0, ParameterDescriptor(
            description="sample rate of the rig firmware (Hz); stamps = t0 + counter / rate",
            **ro))
        self.declare_parameter("arc_l1_mm", L1_MM, ParameterDescriptor(
            description="Eq. 1: actuator length L1 (mm)"))
        self.declare_parameter("arc_l2_mm", L2_MM, ParameterDescriptor(
            description="Eq. 1: clamp to laser line L2 (mm), 0 < L2 < L1"))
        self.declare_parameter("arc_d_mm", D_MM, ParameterDescriptor(
            description="Eq. 1: laser reading at rest d (mm)"))
        self.declare_parameter("u_max", U_MAX_LIMIT_V, ParameterDescriptor(
            description=f"command limit (V), 0 < u_max <= {U_MAX_LIMIT_V}"))
        self.declare_parameter("watchdog_s", 0.5, ParameterDescriptor(
            description="no command for this long -> command 0 V (s)"))
        self.declare_parameter("stale_s", 0.25, ParameterDescriptor(
            description="no sample for this long while connected -> link WARN (s)"))
        self.declare_parameter("diagnostics_period_s", 1.0, ParameterDescriptor(
            description="period of /diagnostics (s)", **ro))
        self.declare_parameter("frame_id", "ipmc_clamp", ParameterDescriptor(
            description="frame of /ipmc/displacement", **ro))
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self.port_name = self.get_parameter("port").value
        self.baudrate = int(self.get_parameter("baudrate").value)
        self.rate_hz = float(self.get_parameter("sample_rate_hz").value)
        if not (self.rate_hz > 0 and self.baudrate > 0):
            raise ValueError(f"need sample_rate_hz > 0 and baudrate > 0, got {self.rate_hz} "
                             f"and {self.baudrate}")
        self.frame_id = self.get_parameter("frame_id").value
        self.geometry = self._geometry_from({})
        self.u_max = float(self.get_parameter("u_max").value)
        self.watchdog_s = float(self.get_parameter("watchdog_s").value)
        self.stale_s = float(self.get_parameter("stale_s").value)
        bad = self._check({"u_max": self.u_max, "watchdog_s": self.watchdog_s,
                           "stale_s": self.stale_s})
        if bad:
            raise ValueError(bad)

        # Core objects and state.
        self.decoder = FrameDecoder()
        self._period_ns = Fraction(10**9) / Fraction(self.rate_hz).limit_denominator(10**6)
        self._frames: queue.SimpleQueue = queue.SimpleQueue()
        self._serial: serial.Serial | None = None
        self._write_lock = threading.Lock()
        self._reader: threading.Thread | None = None
        self._reader_stop = threading.Event()
        self._link_error: str | None = None
        self.link_state = DISCONNECTED
        self._backoff_s = BACKOFF_FIRST_S
        self._next_attempt = 0.0  # monotonic time of the next open attempt
        self._last_error = ""
        self.reconnects = 0
        self._tx_seq = 0
        self._requested_v = 0.0  # last requested voltage (from /ipmc/command)
        self._setpoint_v = 0.0  # last voltage sent to the rig (after u_max)
        self._requested_by_seq: dict[int, float] = {}
        self._sent_at: dict[int, float] = {}  # seq -> monotonic send time, until acknowledged
        self._latencies_s: deque[float] = deque(maxlen=200)
        self._last_command = None  # monotonic time of the last /ipmc/command
        self.watchdog_tripped = False
        self.watchdog_trips = 0
        self.commands = 0
        self.clamped = 0
        self._t0_ns: int | None = None
        self._last_counter: int | None = None  # unwrapped
        self._last_raw_counter = 0
        self.dropped = 0
        self.out_of_range = 0
        self.rig_errors = 0
        self.rig_resets = 0
        self.published = 0
        self._published_at_diag = 0
        self._last_sample_wall: float | None = None
        self._rig_rate_hz: int | None = None
        self._diag_wall = time.monotonic()

        # Publishers and subscriptions.
        self.pub_voltage = self.create_publisher(Vector3Stamped, "/ipmc/voltage", SAMPLE_QOS)
        self.pub_disp = self.create_publisher(PointStamped, "/ipmc/displacement", SAMPLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
        self.create_subscription(Float64, "/ipmc/command", self._on_command, COMMAND_QOS)
        self._guard = self.create_guard_condition(self._drain_frames)

        # Timers (steady clock: link and watchdog must not follow sim time).
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(LINK_PERIOD_S, self._on_link_timer, clock=steady)
        self.create_timer(min(0.05, self.watchdog_s / 4), self._on_watchdog_timer, clock=steady)
        self.create_timer(float(self.get_parameter("diagnostics_period_s").value),
                          self._publish_diagnostics, clock=steady)
        self.get_logger().info(
            f"driver on {self.port_name} at {self.baudrate} Bd, rig sampling {self.rate_hz:g} Hz, "
            f"u_max {self.u_max:g} V, watchdog {self.watchdog_s:g} s")

    # ------------------------------------------------------------------ parameters
    def _geometry_from(self, changes: dict) -> ArcGeometry:
        value = {n: changes.get(n, self.get_parameter(n).value)
                 for n in ("arc_l1_mm", "arc_l2_mm", "arc_d_mm")}
        return ArcGeometry(float(value["arc_l1_mm"]), float(value["arc_l2_mm"]),
                           float(value["arc_d_mm"]))

    @staticmethod
    def _check(values: dict) -> str:
        if "u_max" in values and not 0 < values["u_max"] <= U_MAX_LIMIT_V:
            return f"u_max must be in (0, {U_MAX_LIMIT_V}] V, got {values['u_max']}"
        for name in ("watchdog_s", "stale_s"):
            if name in values and not values[name] > 0:
                return f"{name} must be > 0 s, got {values[name]}"
        return ""

    def _validate_parameters(self, params) -> SetParametersResult:
        changes = {p.name: p.value for p in params}
        numeric = {k: float(v) for k, v in changes.items()
                   if k in ("u_max", "watchdog_s", "stale_s")
                   or k.startswith("arc_")}
        reason = self._check(numeric)
        if not reason and any(k.startswith("arc_") for k in numeric):
            try:
                self._geometry_from(numeric)
            except ValueError as exc:
                reason = str(exc)
        return SetParametersResult(successful=not reason, reason=reason)

    def _apply_parameters(self, params) -> None:
        names = {p.name for p in params}
        if any(n.startswith("arc_") for n in names):
            self.geometry = self._geometry_from({})
        if "u_max" in names:
            self.u_max = float(self.get_parameter("u_max").value)
            self._send_setpoint(self._requested_v)  # re-apply the limit at once
        if "watchdog_s" in names:
            self.watchdog_s = float(self.get_parameter("watchdog_s").value)
        if "stale_s" in names:
            self.stale_s = float(self.get_parameter("stale_s").value)

    # ------------------------------------------------------------------ commands
    def _on_command(self, msg: Float64) -> None:
        v = float(msg.data)
        if not math.isfinite(v):
            self.get_logger().warn("ignoring a non-finite command", throttle_duration_sec=1.0)
            return
        self.commands += 1
        self._last_command = time.monotonic()
        if self.watchdog_tripped:
            self.watchdog_tripped = False
            self.get_logger().info("commands resumed: watchdog released")
        self._requested_v = v
        self._send_setpoint(v)

    def _send_setpoint(self, requested_v: float) -> None:
        """Limit to ``u_max`` and send; remembers the value to re-send after a reconnect."""
        sent = min(max(requested_v, -self.u_max), self.u_max)
        if sent != requested_v:
            self.clamped += 1
        self._setpoint_v = sent
        seq = self._tx_seq = self._tx_seq % 255 + 1  # 1..255: 0 is the rig's "none yet"
        self._requested_by_seq[seq] = requested_v
        if self._write(encode_message(SetVoltage(sent), seq)):
            self._sent_at[seq] = time.monotonic()

    def _write(self, data: bytes) -> bool:
        with self._write_lock:
            ser = self._serial
            if ser is None or self.link_state != CONNECTED:
                return False
            try:
                ser.write(data)
                return True
            except (serial.SerialException, OSError) as exc:
                self._link_error = str(exc) or "write failed"
                return False

    def _on_watchdog_timer(self) -> None:
        if self.watchdog_tripped or self._last_command is None:
            return
        if time.monotonic() - self._last_command > self.watchdog_s:
            self.watchdog_tripped = True
            self.watchdog_trips += 1
            self._requested_v = 0.0
            self._send_setpoint(0.0)
            self.get_logger().warn(
                f"watchdog: no command for {self.watchdog_s:g} s, commanding 0 V")

    # ------------------------------------------------------------------ link state machine
    def _on_link_timer(self) -> None:
        now = time.monotonic()
        if self.link_state == CONNECTED and self._link_error is not None:
            self._disconnect(self._link_error)
        if self.link_state == DISCONNECTED and now >= self._next_attempt:
            self._connect()

    def _connect(self) -> None:
        self.link_state = CONNECTING
        try:
            ser = serial.Serial(self.port_name, self.baudrate, timeout=0.05, write_timeout=0.2)
            ser.reset_input_buffer()  # bytes queued while nobody listened are stale
        except (serial.SerialException, OSError, ValueError) as exc:
            self.link_state = DISCONNECTED
            self._last_error = str(exc)
            self._next_attempt = time.monotonic() + self._backoff_s
            self.get_logger().warn(
                f"cannot open {self.port_name}: {exc}; retry in {self._backoff_s:g} s",
                throttle_duration_sec=5.0)
            self._backoff_s = min(2 * self._backoff_s, BACKOFF_MAX_S)
            return
        self.decoder.reset()
        self._link_error = None
        self._serial = ser
        self._reader_stop = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, args=(ser, self._reader_stop),
                                        name="driver-reader", daemon=True)
        self.link_state = CONNECTED
        self._reader.start()
        self._backoff_s = BACKOFF_FIRST_S
        if self.reconnects or self._last_error:
            self.get_logger().info(f"link to {self.port_name} up again")
        self.reconnects += 1
        self._write(encode_message(Ping(), 0))
        # The rig keeps its setpoint through a cable fault; send ours again to be sure.
        self._send_setpoint(self._requested_v)

    def _disconnect(self, reason: str) -> None:
        self.get_logger().warn(f"link to {self.port_name} lost: {reason}; "
                               f"retry in {self._backoff_s:g} s")
        self._last_error = reason
        self._close_port()
        self.link_state = DISCONNECTED
        self._next_attempt = time.monotonic() + self._backoff_s
        self._backoff_s = min(2 * self._backoff_s, BACKOFF_MAX_S)

    def _close_port(self) -> None:
        self._reader_stop.set()
        with self._write_lock:
            ser, self._serial = self._serial, None
        if ser is not None:
            with contextlib.suppress(Exception):
                ser.close()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(0.5)
        self._reader = None

    def _read_loop(self, ser: serial.Serial, stop: threading.Event) -> None:
        """Reader thread: bytes -> decoder -> messages -> queue -> guard condition."""
        try:
            while not stop.is_set():
                data = ser.read(ser.in_waiting or 1)
                if not data:
                    continue
                now = time.monotonic()
                frames = self.decoder.feed(data)
                for frame in frames:
                    try:
                        self._frames.put((parse_frame(frame), now))
                    except ProtocolError:
                        self.rig_errors += 1
                if frames:
                    self._guard.trigger()
        except (serial.SerialException, OSError, TypeError) as exc:
            # TypeError: pyserial reading a port closed under it by _close_port.
            if not stop.is_set():
                self._link_error = str(exc) or type(exc).__name__

    # ------------------------------------------------------------------ samples
    def _drain_frames(self) -> None:
        while True:
            try:
                msg, arrival = self._frames.get_nowait()
            except queue.Empty:
                return
            if isinstance(msg, Sample):
                self._on_sample(msg, arrival)
            elif isinstance(msg, Status):
                self._rig_rate_hz = msg.sample_rate_hz
            elif isinstance(msg, RigError):
                self.rig_errors += 1
                self.get_logger().warn(f"rig reports error {msg.code} ({msg.detail})",
                                       throttle_duration_sec=1.0)

    def _unwrap(self, raw: int) -> int | None:
        """Unwrapped sample counter, or None for a duplicate/older sample."""
        if self._last_counter is None:
            self._last_raw_counter = raw
            return raw
        delta = (raw - self._last_raw_counter) % COUNTER_MODULO
        if delta == 0:
            return None
        if delta >= COUNTER_MODULO // 2:  # went backwards: the firmware restarted
            if (self._last_raw_counter - raw) % COUNTER_MODULO < 4:
                return None  # a late duplicate, not a restart
            self.rig_resets += 1
            self._t0_ns = None
            self._last_counter = None
            self._last_raw_counter = raw
            return raw
        self._last_raw_counter = raw
        return self._last_counter + delta

    def _on_sample(self, sample: Sample, arrival: float) -> None:
        sent_at = self._sent_at.pop(sample.command_seq, None)
        if sent_at is not None:
            self._latencies_s.append(arrival - sent_at)
        counter = self._unwrap(sample.counter)
        if counter is None:
            return
        if self._last_counter is not None and counter - self._last_counter > 1:
            self.dropped += counter - self._last_counter - 1
        self._last_counter = counter
        self._last_sample_wall = arrival
        if self._t0_ns is None:
            # Anchor the rig's counter to the ROS clock once; afterwards the counter alone gives
            # the sampling instants, whatever the serial and scheduling jitter.
            self._t0_ns = self.get_clock().now().nanoseconds - int(counter * self._period_ns)
        if sample.laser_mm is None or not self.geometry.in_range(sample.laser_mm):
            self.out_of_range += 1  # flagged on /diagnostics, never published as a number
            return
        y_mm = self.geometry.compensate_scalar(sample.laser_mm)
        stamp_ns = self._t0_ns + int(counter * self._period_ns)
        v = Vector3Stamped()
        v.header.stamp.sec, v.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        v.header.frame_id = self.frame_id
        v.vector.x = sample.applied_v
        v.vector.y = self._requested_by_seq.get(sample.command_seq, 0.0)
        d = PointStamped()
        d.header = v.header
        d.point.x = y_mm * 1e-3
        self.pub_voltage.publish(v)
        self.pub_disp.publish(d)
        self.published += 1

    # ------------------------------------------------------------------ diagnostics
    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        period = max(now - self._diag_wall, 1e-6)
        rate = (self.published - self._published_at_diag) / period
        self._diag_wall, self._published_at_diag = now, self.published
        stats = self.decoder.stats
        hw = self.port_name

        def status(name, level, message, values):
            return DiagnosticStatus(
                level=level, name=f"driver: {name}", message=message, hardware_id=hw,
                values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])

        age = None if self._last_sample_wall is None else now - self._last_sample_wall
        if self.link_state == CONNECTED:
            if age is None or age > self.stale_s:
                link = (DiagnosticStatus.WARN, "connected, no samples"
                        + ("" if age is None else f" for {age:.2f} s"))
            else:
                link = (DiagnosticStatus.OK, "connected")
        else:
            wait = max(0.0, self._next_attempt - now)
            link = (DiagnosticStatus.ERROR,
                    f"{self.link_state}: {self._last_error or 'not opened yet'}; "
                    f"retry in {wait:.1f} s")
        link_values = {"state": self.link_state, "port": hw, "baudrate": self.baudrate,
                       "connections": self.reconnects, **stats.as_dict(),
                       "dropped": self.dropped, "rig_errors": self.rig_errors,
                       "rig_resets": self.rig_resets,
                       "last_counter": self._last_counter if self._last_counter is not None
                       else ""}
        s_level, s_msg = DiagnosticStatus.OK, f"{rate:.1f} Hz"
        if self._rig_rate_hz is not None and self._rig_rate_hz != round(self.rate_hz):
            s_level = DiagnosticStatus.WARN
            s_msg += (f"; rig samples at {self._rig_rate_hz} Hz but sample_rate_hz is "
                      f"{self.rate_hz:g}: stamps are wrong")
        elif self.link_state == CONNECTED and rate < 0.9 * self.rate_hz:
            s_level = DiagnosticStatus.WARN
            s_msg += f", expected {self.rate_hz:g} Hz"
        stream_values = {"rate_hz": f"{rate:.2f}", "expected_hz": self.rate_hz,
                         "published": self.published, "out_of_range": self.out_of_range}
        lat = list(self._latencies_s)
        lat_ms = {"latency_last_ms": f"{lat[-1] * 1e3:.2f}" if lat else "",
                  "latency_mean_ms": f"{sum(lat) / len(lat) * 1e3:.2f}" if lat else "",
                  "latency_max_ms": f"{max(lat) * 1e3:.2f}" if lat else ""}
        c_level = DiagnosticStatus.WARN if self.clamped else DiagnosticStatus.OK
        c_msg = (f"setpoint {self._setpoint_v:.3f} V"
                 + (f", {self.clamped} command(s) limited to {self.u_max:g} V"
                    if self.clamped else ""))
        cmd_values = {"requested_v": self._requested_v, "setpoint_v": self._setpoint_v,
                      "u_max": self.u_max, "commands": self.commands, "clamped": self.clamped,
                      **lat_ms}
        if self.watchdog_tripped:
            w = (DiagnosticStatus.WARN,
                 f"tripped: no command for more than {self.watchdog_s:g} s, rig at 0 V")
        elif self._last_command is None:
            w = (DiagnosticStatus.OK, "no command yet, rig at 0 V")
        else:
            w = (DiagnosticStatus.OK, "commands arriving")
        wd_values = {"tripped": self.watchdog_tripped, "trips": self.watchdog_trips,
                     "watchdog_s": self.watchdog_s}
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status("link", *link, link_values),
                        status("stream", s_level, s_msg, stream_values),
                        status("command", c_level, c_msg, cmd_values),
                        status("watchdog", *w, wd_values)]
        self.pub_diag.publish(array)

    # ------------------------------------------------------------------ shutdown
    def destroy_node(self) -> None:
        """Make the rig safe first (0 V), then close the port and stop the reader."""
        self._requested_v = 0.0
        self._send_setpoint(0.0)
        with self._write_lock:
            if self._serial is not None:
                with contextlib.suppress(Exception):
                    self._serial.flush()
        self._close_port()
        self.link_state = DISCONNECTED
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    run_node(Driver, args, name="driver", doc=__doc__,
             usage="driver --ros-args -p port:=/dev/ttyUSB0 [-p baudrate:=115200 "
                   "-p sample_rate_hz:=100.0 -p u_max:=3.0 -p watchdog_s:=0.5 "
                   "-p arc_l2_mm:=20.0 -p arc_d_mm:=150.0]")


if __name__ == "__main__":
    main()
