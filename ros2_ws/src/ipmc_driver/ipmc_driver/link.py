"""The driver's serial link to the rig, as plain Python: the ``driver`` node maps topics,
parameters and timers onto it.

``DriverLink`` owns the port and everything that keeps the rig safe and the samples honest:

- a link state machine (disconnected -> connecting -> connected) stepped by ``tick``: a port that
  fails is closed and reopened with a back-off (0.5 s doubling to 10 s); while it is closed the
  device path is polled with one ``stat`` per tick, and a device that reappears (an adapter
  replugged, a rig emulator restarted) is opened at the next tick whatever the back-off;
- the commands: limited to ``u_max``; a non-finite command is 0 V, sent at once; without a
  command for ``watchdog_s`` the rig is commanded to 0 V;
- the feeding of the rig's firmware watchdog (``RIG_WATCHDOG_S``): when no SET_VOLTAGE has gone
  out for ``FEED_PERIOD_S`` the current setpoint is sent again;
- the samples: a reader thread decodes frames into a queue; ``drain`` unwraps the rig's 32-bit
  sample counter (lost samples, firmware restarts), stamps each sample ``t0 + counter / rate``,
  compensates the laser reading (Eq. 1) and drops readings outside its range;
- the diagnostics, as ``StatusReport`` objects.

No ROS import: the tests drive it with a fake port and a fake clock.
"""

from __future__ import annotations

import contextlib
import math
import os
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from fractions import Fraction

from .arc import D_MM, L1_MM, L2_MM, ArcGeometry
from .protocol import (
    RIG_WATCHDOG_S,
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

__all__ = [
    "U_MAX_LIMIT_V",
    "FEED_PERIOD_S",
    "TICK_PERIOD_S",
    "BACKOFF_FIRST_S",
    "BACKOFF_MAX_S",
    "DISCONNECTED",
    "CONNECTING",
    "CONNECTED",
    "OK",
    "WARN",
    "ERROR",
    "DriverParameter",
    "DRIVER_PARAMETERS",
    "check_parameter",
    "check_parameters",
    "LinkConfig",
    "SampleCounter",
    "LinkSample",
    "StatusReport",
    "DriverLink",
    "open_serial_port",
    "device_id",
]

U_MAX_LIMIT_V = 3.0  # above 3 V the paper's actuators bent past 90 degrees (section 2.1)
FEED_PERIOD_S = RIG_WATCHDOG_S / 4  # keepalive; the protocol asks for one every N/2 at most
TICK_PERIOD_S = 0.025  # the node's timer: half the keepalive period, the path poll's period
BACKOFF_FIRST_S = 0.5
BACKOFF_MAX_S = 10.0
COUNTER_MODULO = 1 << 32
LATE_DUPLICATE_SPAN = 4  # a counter this close behind the last one is a repeat, not a restart

DISCONNECTED, CONNECTING, CONNECTED = "disconnected", "connecting", "connected"
OK, WARN, ERROR = 0, 1, 2  # diagnostic levels (diagnostic_msgs/DiagnosticStatus)


# --------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class DriverParameter:
    """One driver parameter: default (its type is the parameter's type), meaning, read-only."""

    default: object
    description: str
    read_only: bool = False


DRIVER_PARAMETERS: dict[str, DriverParameter] = {
    "port": DriverParameter("/dev/ttyUSB0", "serial device of the RS-485 adapter", True),
    "baudrate": DriverParameter(115200, "serial baud rate", True),
    "sample_rate_hz": DriverParameter(
        100.0, "sample rate of the rig firmware (Hz); stamps = t0 + counter / rate", True),
    "arc_l1_mm": DriverParameter(L1_MM, "Eq. 1: actuator length L1 (mm)"),
    "arc_l2_mm": DriverParameter(L2_MM, "Eq. 1: clamp to laser line L2 (mm), 0 < L2 < L1"),
    "arc_d_mm": DriverParameter(D_MM, "Eq. 1: laser reading at rest d (mm)"),
    "u_max": DriverParameter(U_MAX_LIMIT_V, f"command limit (V), 0 < u_max <= {U_MAX_LIMIT_V}"),
    "watchdog_s": DriverParameter(0.5, "no command for this long -> command 0 V (s)"),
    "stale_s": DriverParameter(0.25, "no sample for this long while connected -> link WARN (s)"),
    "diagnostics_period_s": DriverParameter(1.0, "period of /diagnostics (s)", True),
    "frame_id": DriverParameter("ipmc_clamp", "frame of /ipmc/displacement", True),
}


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _is_text(value: object) -> bool:
    return isinstance(value, str) and value.strip() != ""


_RULES: dict[str, tuple[Callable[[object], bool], str]] = {
    "port": (_is_text, "must name the serial device"),
    "baudrate": (lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 < v <= 4_000_000,
                 "must be an integer in (0, 4000000] Bd"),
    "sample_rate_hz": (lambda v: _is_number(v) and 0 < v <= 65535,
                       "must be in (0, 65535] Hz (the rate field of STATUS frames)"),
    "u_max": (lambda v: _is_number(v) and 0 < v <= U_MAX_LIMIT_V,
              f"must be in (0, {U_MAX_LIMIT_V}] V (the H-bridge's limit)"),
    "watchdog_s": (lambda v: _is_number(v) and v > 0, "must be > 0 s (and finite)"),
    "stale_s": (lambda v: _is_number(v) and v > 0, "must be > 0 s (and finite)"),
    "diagnostics_period_s": (lambda v: _is_number(v) and v > 0, "must be > 0 s (and finite)"),
    "frame_id": (_is_text, "must name a frame"),
    "arc_l1_mm": (_is_number, "must be a finite number of mm"),
    "arc_l2_mm": (_is_number, "must be a finite number of mm"),
    "arc_d_mm": (_is_number, "must be a finite number of mm"),
}


def check_parameter(name: str, value: object) -> str:
    """Why the driver refuses ``value`` for parameter ``name`` alone ("must be ..., got ..."),
    or ``""``; the end of a sentence that starts with the parameter's name."""
    rule = _RULES.get(name)
    if rule is None or rule[0](value):
        return ""
    return f"{rule[1]}, got {value!r}"


def check_parameters(values: Mapping[str, object]) -> str:
    """The reason the first unacceptable driver parameter in ``values`` is refused, or ``""``.

    Parameters
    ----------
    values : mapping
        Parameter name -> value, the names of ``DRIVER_PARAMETERS`` (any subset). When the three
        ``arc_*`` lengths are all given, they must also form a valid ``ArcGeometry``.

    Returns
    -------
    str
        One sentence naming the parameter, the accepted values and the value given; empty when
        every value is acceptable.
    """
    for name, value in values.items():
        why = check_parameter(name, value)
        if why:
            return f"parameter {name} {why}"
    arc = [values.get(n) for n in ("arc_l1_mm", "arc_l2_mm", "arc_d_mm")]
    if all(v is not None for v in arc):
        try:
            ArcGeometry(*arc)
        except ValueError as exc:
            return f"parameter arc_{exc}"
    return ""


@dataclass(frozen=True)
class LinkConfig:
    """The link's settings, validated by ``check_parameters`` (``ValueError`` with its reason).

    ``u_max_v`` is the driver's ``u_max`` parameter; the others carry the parameter's name.
    """

    port: str
    baudrate: int = 115200
    sample_rate_hz: float = 100.0
    u_max_v: float = U_MAX_LIMIT_V
    watchdog_s: float = 0.5
    stale_s: float = 0.25
    geometry: ArcGeometry = field(default_factory=ArcGeometry)

    def __post_init__(self) -> None:
        reason = check_parameters(self.as_parameters())
        if reason:
            raise ValueError(reason)

    def as_parameters(self) -> dict[str, object]:
        """The settings under the driver's parameter names."""
        return {"port": self.port, "baudrate": self.baudrate,
                "sample_rate_hz": self.sample_rate_hz, "u_max": self.u_max_v,
                "watchdog_s": self.watchdog_s, "stale_s": self.stale_s,
                "arc_l1_mm": self.geometry.l1_mm, "arc_l2_mm": self.geometry.l2_mm,
                "arc_d_mm": self.geometry.d_mm}

    @classmethod
    def from_parameters(cls, values: Mapping[str, object]) -> LinkConfig:
        """Build from driver parameter values (missing names take their defaults)."""
        defaults = {name: p.default for name, p in DRIVER_PARAMETERS.items()}
        v = {**defaults, **values}
        reason = check_parameters(v)
        if reason:
            raise ValueError(reason)
        return cls(port=v["port"], baudrate=v["baudrate"],
                   sample_rate_hz=float(v["sample_rate_hz"]), u_max_v=float(v["u_max"]),
                   watchdog_s=float(v["watchdog_s"]), stale_s=float(v["stale_s"]),
                   geometry=ArcGeometry(float(v["arc_l1_mm"]), float(v["arc_l2_mm"]),
                                        float(v["arc_d_mm"])))


# --------------------------------------------------------------------------- samples
class SampleCounter:
    """Unwraps the rig's 32-bit sample counter; counts lost samples and firmware restarts."""

    def __init__(self) -> None:
        self.last: int | None = None  # unwrapped
        self.dropped = 0
        self.restarts = 0
        self._last_raw = 0

    def update(self, raw: int) -> int | None:
        """The unwrapped counter of a sample, or ``None`` for a repeated or older one.

        A counter far behind the last one means the firmware restarted: counting starts again
        from it (``restarts`` + 1); samples between two counters are lost (``dropped``).
        """
        if self.last is None:
            self._last_raw = self.last = raw
            return raw
        delta = (raw - self._last_raw) % COUNTER_MODULO
        if delta == 0:
            return None
        if delta >= COUNTER_MODULO // 2:  # went backwards
            if (self._last_raw - raw) % COUNTER_MODULO < LATE_DUPLICATE_SPAN:
                return None
            self.restarts += 1
            self._last_raw = self.last = raw
            return raw
        self.dropped += delta - 1
        self._last_raw = raw
        self.last += delta
        return self.last


@dataclass(frozen=True)
class LinkSample:
    """One sample ready to publish: unwrapped counter, stamp (ns on the node's clock), applied
    and requested voltage (V), arc-compensated tip displacement (mm), and the time its frame
    arrived (s, the link's clock)."""

    counter: int
    stamp_ns: int
    applied_v: float
    requested_v: float
    y_mm: float
    arrival_s: float


@dataclass(frozen=True)
class StatusReport:
    """One diagnostic status: name, level (``OK``/``WARN``/``ERROR``), message, values."""

    name: str
    level: int
    message: str
    values: dict[str, str]


# --------------------------------------------------------------------------- the port
def open_serial_port(path: str, baudrate: int) -> object:
    """Open ``path`` with pyserial (read timeout 50 ms: the reader thread checks its stop flag)."""
    import serial  # pyserial; imported here so that the pure parts load without it

    return serial.Serial(path, baudrate, timeout=0.05, write_timeout=0.2)


def device_id(path: str) -> tuple[int, int, int] | None:
    """Identity of the device ``path`` leads to (device, inode, rdev), or ``None`` if absent."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_rdev


class _State:
    """A link state: ``tick`` returns the state the link is in afterwards."""

    name = ""

    def tick(self, link: DriverLink, now_s: float) -> _State:
        raise NotImplementedError


class _Disconnected(_State):
    name = DISCONNECTED

    def tick(self, link: DriverLink, now_s: float) -> _State:
        if link.device_id(link.config.port) is None:
            link.note_port_absent()
            return self
        if link.port_reappeared() or now_s >= link.next_attempt_s:
            return link.open_port(now_s)
        return self


class _Connecting(_State):
    """Inside ``DriverLink.open_port`` only: the attempt ends in one of the other states."""

    name = CONNECTING

    def tick(self, link: DriverLink, now_s: float) -> _State:
        return self


class _Connected(_State):
    name = CONNECTED

    def tick(self, link: DriverLink, now_s: float) -> _State:
        error = link.link_error
        if error is None and link.device_id(link.config.port) is None:
            error = "the device vanished"
        if error is not None:
            return link.close_after_error(error, now_s)
        link.feed_rig_watchdog(now_s)
        return self


# --------------------------------------------------------------------------- the link
class DriverLink:
    """The serial link to the rig: port, commands, watchdogs, samples and diagnostics.

    Parameters
    ----------
    config : LinkConfig
        Port, rates, limits and geometry; replaced at run time with ``reconfigure``.
    log : callable, optional
        ``log(level, text)`` with level ``"info"`` or ``"warn"``; one call per event (state
        changes, trips), never one per tick.
    on_frames : callable, optional
        Called from the reader thread after it queued frames (the node wakes its executor).
    open_port : callable, optional
        ``open_port(path, baudrate)`` -> an object with ``read``, ``write``, ``in_waiting``,
        ``reset_input_buffer``, ``flush`` and ``close`` (default: pyserial).
    device_id : callable, optional
        ``device_id(path)`` -> a hashable identity, or ``None`` when the path is absent.
    clock : callable, optional
        Monotonic seconds, for arrival times (default ``time.monotonic``); ``tick`` and
        ``command`` take the time as an argument.

    Threads: ``tick``, ``command``, ``drain``, ``diagnostics``, ``reconfigure`` and ``shutdown``
    run on one thread (the node's executor); the reader thread only decodes and queues.
    """

    def __init__(self, config: LinkConfig, *, log: Callable[[str, str], None] | None = None,
                 on_frames: Callable[[], None] | None = None,
                 open_port: Callable[[str, int], object] = open_serial_port,
                 device_id: Callable[[str], object] = device_id,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self._log = log or (lambda level, text: None)
        self.on_frames = on_frames
        self._open_port = open_port
        self.device_id = device_id
        self._clock = clock
        self.decoder = FrameDecoder()
        self.counter = SampleCounter()
        self._state: _State = _Disconnected()
        self._init_port_state()
        self._init_command_state()
        self._init_sample_state()

    def _init_port_state(self) -> None:
        self._port = None
        self._write_lock = threading.Lock()
        self._reader: threading.Thread | None = None
        self._reader_stop = threading.Event()
        self._inbox: queue.SimpleQueue = queue.SimpleQueue()
        self.link_error: str | None = None  # set by the reader thread or a failed write
        self.last_error = ""
        self.next_attempt_s = -math.inf
        self._backoff_s = BACKOFF_FIRST_S
        self._port_absent = False
        self.connections = 0

    def _init_command_state(self) -> None:
        self._tx_seq = 0
        self._last_tx_s = -math.inf  # time of the last SET_VOLTAGE written
        self.requested_v = 0.0  # last requested voltage (0 V after a non-finite command)
        self.setpoint_v = 0.0  # last voltage sent to the rig (after u_max)
        self._requested_by_seq: dict[int, float] = {}
        self._sent_at: dict[int, float] = {}  # seq -> send time, until a sample echoes it
        self.latencies_s: deque[float] = deque(maxlen=200)
        self._last_command_s: float | None = None
        self.watchdog_tripped = False
        self.watchdog_trips = 0
        self.commands = 0
        self.clamped = 0
        self.non_finite = 0
        self._non_finite_run = False
        self.keepalives = 0

    def _init_sample_state(self) -> None:
        self._period_ns = (Fraction(10**9)
                           / Fraction(self.config.sample_rate_hz).limit_denominator(10**6))
        self._t0_ns: int | None = None
        self._last_stamp_ns = -1
        self.out_of_range = 0
        self.rig_errors = 0
        self._rig_error_logged_s = -math.inf
        self.rig_rate_hz: int | None = None
        self.published = 0
        self.last_sample_s: float | None = None
        self._published_at_diag = 0
        self._diag_s = self._clock()

    # ------------------------------------------------------------------ state
    @property
    def tx_seq(self) -> int:
        """Sequence number of the last SET_VOLTAGE frame built (1..255; 0 before the first)."""
        return self._tx_seq

    @property
    def state(self) -> str:
        """``"disconnected"``, ``"connected"``, or ``"connecting"`` inside an open attempt."""
        return self._state.name

    def tick(self, now_s: float) -> None:
        """Run the command watchdog and one step of the link state machine (every
        ``TICK_PERIOD_S``): reopen a port, notice a lost one, feed the rig's watchdog."""
        self._check_command_watchdog(now_s)
        self._state = self._state.tick(self, now_s)

    def reconfigure(self, config: LinkConfig) -> None:
        """Apply new limits or geometry (port and rates stay); a new ``u_max`` at once."""
        fixed = ("port", "baudrate", "sample_rate_hz")
        if any(getattr(config, n) != getattr(self.config, n) for n in fixed):
            raise ValueError("port, baudrate and sample_rate_hz are fixed while the link runs")
        u_max_changed = config.u_max_v != self.config.u_max_v
        self.config = config
        if u_max_changed:
            self._send_setpoint(self.requested_v, self._clock())

    # ------------------------------------------------------------------ port (states call these)
    def note_port_absent(self) -> None:
        """The device path is absent (said once, until it reappears)."""
        if not self._port_absent:
            self._port_absent = True
            self._log("warn", f"{self.config.port} is absent; opening it as soon as it appears")

    def port_reappeared(self) -> bool:
        """True once after the device path came back: it is opened then, whatever the
        back-off (the back-off is for a device that is there and fails)."""
        if not self._port_absent:
            return False
        self._port_absent = False
        self._backoff_s = BACKOFF_FIRST_S
        return True

    def open_port(self, now_s: float) -> _State:
        """Open the port, start the reader, ping, send the setpoint; on failure schedule the
        next attempt one back-off later. Returns the state the link is in afterwards."""
        self._state = _Connecting()
        port = None
        try:
            port = self._open_port(self.config.port, self.config.baudrate)
            port.reset_input_buffer()  # bytes queued while nobody listened are stale
        except (OSError, ValueError) as exc:
            if port is not None:
                with contextlib.suppress(Exception):
                    port.close()
            self.last_error = str(exc) or type(exc).__name__
            self._schedule_retry(now_s)
            self._log("warn", f"cannot open {self.config.port}: {self.last_error}; "
                              f"retry in {self.next_attempt_s - now_s:g} s")
            return _Disconnected()
        self.decoder.reset()
        self.link_error = None
        self._reader_stop = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, args=(port, self._reader_stop),
                                        name="driver-reader", daemon=True)
        with self._write_lock:
            self._port = port
        self._reader.start()
        self._backoff_s = BACKOFF_FIRST_S
        if self.connections or self.last_error:
            self._log("info", f"link to {self.config.port} up again")
        self.connections += 1
        self._write(encode_message(Ping(), 0))
        # The rig's watchdog has most likely zeroed it while the link was down: send ours.
        self._send_setpoint(self.requested_v, now_s)
        return _Connected()

    def close_after_error(self, error: str, now_s: float) -> _State:
        """Close a port that failed; reopen after the back-off, or when the device reappears."""
        self.last_error = error
        self._close_port()
        self._schedule_retry(now_s)
        self._log("warn", f"link to {self.config.port} lost: {error}; retry in "
                          f"{self.next_attempt_s - now_s:g} s or when the device reappears")
        return _Disconnected()

    def _schedule_retry(self, now_s: float) -> None:
        self.next_attempt_s = now_s + self._backoff_s
        self._backoff_s = min(2 * self._backoff_s, BACKOFF_MAX_S)

    def _close_port(self) -> None:
        self._reader_stop.set()
        with self._write_lock:
            port, self._port = self._port, None
        if port is not None:
            with contextlib.suppress(Exception):
                port.close()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(0.5)
        self._reader = None

    def _write(self, data: bytes) -> bool:
        with self._write_lock:
            port = self._port
            if port is None:
                return False
            try:
                port.write(data)
                return True
            except (OSError, ValueError) as exc:
                self.link_error = str(exc) or "write failed"
                return False

    def _read_loop(self, port, stop: threading.Event) -> None:
        """Reader thread: bytes -> decoder -> messages -> queue -> ``on_frames``."""
        try:
            while not stop.is_set():
                data = port.read(port.in_waiting or 1)
                if not data:
                    continue
                now = self._clock()
                frames = self.decoder.feed(data)
                for frame in frames:
                    try:
                        self._inbox.put((parse_frame(frame), now))
                    except ProtocolError:
                        self.rig_errors += 1  # a frame the decoder passed but cannot be read
                if frames and self.on_frames is not None:
                    self.on_frames()
        except (OSError, TypeError, ValueError) as exc:
            # TypeError, ValueError: pyserial reading a port closed under it by _close_port.
            if not stop.is_set():
                self.link_error = str(exc) or type(exc).__name__

    # ------------------------------------------------------------------ commands
    def command(self, voltage_v: float, now_s: float) -> float:
        """A new requested voltage (V) at ``now_s``; returns the setpoint sent to the rig.

        Limited to ``u_max``. A non-finite command (NaN, inf: a controller that diverged) is
        0 V, sent at once: it must neither reach the H-bridge nor leave the previous voltage
        applied until the watchdog.
        """
        self.commands += 1
        self._last_command_s = now_s
        if self.watchdog_tripped:
            self.watchdog_tripped = False
            self._log("info", "commands resumed: watchdog released")
        voltage_v = float(voltage_v)
        if not math.isfinite(voltage_v):
            self.non_finite += 1
            if not self._non_finite_run:
                self._log("warn", f"non-finite command ({voltage_v}): commanding 0 V")
            self._non_finite_run = True
            voltage_v = 0.0
        else:
            self._non_finite_run = False
        self.requested_v = voltage_v
        return self._send_setpoint(voltage_v, now_s)

    def _send_setpoint(self, requested_v: float, now_s: float) -> float:
        sent = min(max(requested_v, -self.config.u_max_v), self.config.u_max_v)
        if sent != requested_v:
            self.clamped += 1
        self.setpoint_v = sent
        self._transmit(now_s)
        return sent

    def _transmit(self, now_s: float) -> None:
        """Send the current setpoint in a SET_VOLTAGE frame with the next sequence number."""
        seq = self._tx_seq = self._tx_seq % 255 + 1  # 1..255: 0 is the rig's "none yet"
        self._requested_by_seq[seq] = self.requested_v
        if self._write(encode_message(SetVoltage(self.setpoint_v), seq)):
            self._sent_at[seq] = now_s
            self._last_tx_s = now_s

    def feed_rig_watchdog(self, now_s: float) -> None:
        """Repeat the setpoint when no SET_VOLTAGE went out for ``FEED_PERIOD_S``: the rig
        zeroes the H-bridge after ``RIG_WATCHDOG_S`` without one."""
        if now_s - self._last_tx_s >= FEED_PERIOD_S:
            self.keepalives += 1
            self._transmit(now_s)

    def _check_command_watchdog(self, now_s: float) -> None:
        if self.watchdog_tripped or self._last_command_s is None:
            return
        if now_s - self._last_command_s > self.config.watchdog_s:
            self.watchdog_tripped = True
            self.watchdog_trips += 1
            self.requested_v = 0.0
            self._send_setpoint(0.0, now_s)
            self._log("warn", f"watchdog: no command for {self.config.watchdog_s:g} s, "
                              "commanding 0 V")

    def shutdown(self) -> None:
        """Make the rig safe: command 0 V, let it leave the port, close the port."""
        self.requested_v = 0.0
        self._send_setpoint(0.0, self._clock())
        with self._write_lock:
            if self._port is not None:
                with contextlib.suppress(Exception):
                    self._port.flush()
        self._close_port()
        self._state = _Disconnected()

    # ------------------------------------------------------------------ samples
    def drain(self, ros_now_ns: Callable[[], int]) -> list[LinkSample]:
        """The samples the reader queued, ready to publish; handles STATUS and ERROR frames.

        Stamps are ``t0 + counter / rate`` on the node's clock (``ros_now_ns``), ``t0`` set
        at the first sample and again after a firmware restart (:meth:`_anchor`).
        """
        batch = []   # (counter, sample, arrival_s, restarted)
        while True:
            try:
                msg, arrival_s = self._inbox.get_nowait()
            except queue.Empty:
                break
            if isinstance(msg, Sample):
                counted = self._count(msg, arrival_s)
                if counted is not None:
                    batch.append(counted)
            elif isinstance(msg, Status):
                self.rig_rate_hz = msg.sample_rate_hz
            elif isinstance(msg, RigError):
                self.rig_errors += 1
                if arrival_s - self._rig_error_logged_s >= 1.0:
                    self._rig_error_logged_s = arrival_s
                    self._log("warn", f"rig reports error {msg.code} ({msg.detail})")
        now_ns, now_s = ros_now_ns(), self._clock()
        # each sample's earliest anchor: its own or a later one's of the batch (no restart
        # between), so a chunk of samples read together is stamped with its true spacing
        anchors = [now_ns - max(0, int((now_s - arrival) * 1e9)) - int(c * self._period_ns)
                   for c, _, arrival, _ in batch]
        for i in range(len(batch) - 2, -1, -1):
            if not batch[i + 1][3]:
                anchors[i] = min(anchors[i], anchors[i + 1])
        out = [self._stamped(*item, anchor) for item, anchor in zip(batch, anchors, strict=True)]
        return [s for s in out if s is not None]

    def _count(self, sample: Sample, arrival_s: float) -> tuple | None:
        """The sample's unwrapped counter (None: a duplicate or an old one), its latency."""
        sent_at = self._sent_at.pop(sample.command_seq, None)
        if sent_at is not None:
            self.latencies_s.append(arrival_s - sent_at)
        restarts = self.counter.restarts
        counter = self.counter.update(sample.counter)
        if counter is None:
            return None
        self.last_sample_s = arrival_s
        return counter, sample, arrival_s, self.counter.restarts != restarts

    def _stamped(self, counter: int, sample: Sample, arrival_s: float, restarted: bool,
                 anchor_ns: int) -> LinkSample | None:
        """A sample stamped ``t0 + counter / rate``. A sample cannot arrive before it was
        taken: one that arrives a period or more sooner after its instant than ``t0`` says
        shows that ``t0`` was set on a late sample (the rig's transmit buffer emptied in a
        burst at connection, a stalled reader), and ``t0`` moves back by whole periods (the
        stamps stay on one grid, and increasing). Arrival jitter below a period is left
        alone: the grid is what consumers align counters with."""
        offset = int(counter * self._period_ns)
        if self._t0_ns is None or restarted:
            self._t0_ns = anchor_ns
        elif anchor_ns <= self._t0_ns - self._period_ns:
            periods = min((self._t0_ns - anchor_ns) // self._period_ns,
                          (self._t0_ns + offset - self._last_stamp_ns - 1) // self._period_ns)
            self._t0_ns -= int(max(0, periods) * self._period_ns)
        geometry = self.config.geometry
        if sample.laser_mm is None or not geometry.in_range(sample.laser_mm):
            self.out_of_range += 1  # on /diagnostics, never published as a number
            return None
        self.published += 1
        self._last_stamp_ns = self._t0_ns + offset
        return LinkSample(counter, self._last_stamp_ns, sample.applied_v,
                          self._requested_by_seq.get(sample.command_seq, 0.0),
                          geometry.compensate_scalar(sample.laser_mm), arrival_s)

    # ------------------------------------------------------------------ diagnostics
    def diagnostics(self, now_s: float) -> list[StatusReport]:
        """One status per concern: link, stream (rate), command (limits), watchdog."""
        rate_hz = (self.published - self._published_at_diag) / max(now_s - self._diag_s, 1e-6)
        self._diag_s, self._published_at_diag = now_s, self.published
        return [self._link_status(now_s), self._stream_status(rate_hz),
                self._command_status(), self._watchdog_status()]

    def _link_status(self, now_s: float) -> StatusReport:
        stale_s = self.config.stale_s
        age = None if self.last_sample_s is None else now_s - self.last_sample_s
        if self.state == CONNECTED:
            if age is None or age > stale_s:
                level, msg = WARN, "connected, no samples" + (
                    "" if age is None else f" for {age:.2f} s")
            else:
                level, msg = OK, "connected"
        else:
            wait = max(0.0, self.next_attempt_s - now_s)
            level = ERROR
            msg = (f"{self.state}: {self.last_error or 'not opened yet'}; "
                   + ("waiting for the device to appear" if self._port_absent
                      else f"retry in {wait:.1f} s"))
        last = self.counter.last
        values = {"state": self.state, "port": self.config.port, "baudrate": self.config.baudrate,
                  "connections": self.connections, **self.decoder.stats.as_dict(),
                  "dropped": self.counter.dropped, "rig_errors": self.rig_errors,
                  "rig_resets": self.counter.restarts, "keepalives": self.keepalives,
                  "rig_watchdog_ms": round(RIG_WATCHDOG_S * 1e3),
                  "last_counter": "" if last is None else last}
        return StatusReport("link", level, msg, {k: str(v) for k, v in values.items()})

    def _stream_status(self, rate_hz: float) -> StatusReport:
        expected = self.config.sample_rate_hz
        level, msg = OK, f"{rate_hz:.1f} Hz"
        if self.rig_rate_hz is not None and self.rig_rate_hz != round(expected):
            level = WARN
            msg += (f"; rig samples at {self.rig_rate_hz} Hz but sample_rate_hz is "
                    f"{expected:g}: stamps are wrong")
        elif self.state == CONNECTED and rate_hz < 0.9 * expected:
            level = WARN
            msg += f", expected {expected:g} Hz"
        values = {"rate_hz": f"{rate_hz:.2f}", "expected_hz": expected,
                  "published": self.published, "out_of_range": self.out_of_range}
        return StatusReport("stream", level, msg, {k: str(v) for k, v in values.items()})

    def _command_status(self) -> StatusReport:
        lat = list(self.latencies_s)
        u_max = self.config.u_max_v
        level = WARN if self.clamped or self.non_finite else OK
        msg = f"setpoint {self.setpoint_v:.3f} V"
        if self.clamped:
            msg += f", {self.clamped} command(s) limited to {u_max:g} V"
        if self.non_finite:
            msg += f", {self.non_finite} non-finite command(s) sent as 0 V"
        values = {"requested_v": self.requested_v, "setpoint_v": self.setpoint_v,
                  "u_max": u_max, "commands": self.commands, "clamped": self.clamped,
                  "non_finite": self.non_finite,
                  "latency_last_ms": f"{lat[-1] * 1e3:.2f}" if lat else "",
                  "latency_mean_ms": f"{sum(lat) / len(lat) * 1e3:.2f}" if lat else "",
                  "latency_max_ms": f"{max(lat) * 1e3:.2f}" if lat else ""}
        return StatusReport("command", level, msg, {k: str(v) for k, v in values.items()})

    def _watchdog_status(self) -> StatusReport:
        watchdog_s = self.config.watchdog_s
        if self.watchdog_tripped:
            level, msg = WARN, f"tripped: no command for more than {watchdog_s:g} s, rig at 0 V"
        elif self._last_command_s is None:
            level, msg = OK, "no command yet, rig at 0 V"
        else:
            level, msg = OK, "commands arriving"
        values = {"tripped": self.watchdog_tripped, "trips": self.watchdog_trips,
                  "watchdog_s": watchdog_s}
        return StatusReport("watchdog", level, msg, {k: str(v) for k, v in values.items()})
