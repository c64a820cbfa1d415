"""Emulator of the rig controller firmware on a pseudo-terminal (``ipmc rig-emulator``).

It opens a pty (a real tty device), runs the simulated plant (``IpmcPlant``) in real time at the
configured sample rate and speaks the RS-485 protocol of ``ipmc_driver.protocol`` on it: one
SAMPLE frame per sampling period (sample counter, applied voltage, raw laser reading), a STATUS
heartbeat every second and on PING, SET_VOLTAGE frames in. Like the firmware, it sets the H-bridge
to 0 V when no SET_VOLTAGE frame has arrived for ``RIG_WATCHDOG_S`` (a PC or a cable that died
must not leave the actuator driven). The tip displacement y of the plant is
turned into the raw laser reading x by the inverse of Eq. 1 (``ArcGeometry.reading``) and
quantised to the 16-bit laser counts of the protocol, so the driver's arc compensation gives y
back.

The device is exposed as a stable symlink (``--link``, default in a fresh temporary directory)
to the current ``/dev/pts/N``; its path is printed alone on the first stdout line. Faults are read
on stdin, one per line::

    garbage N    write N random bytes before the next frame
    badcrc N     corrupt the CRC of the next N sample frames
    drop N       do not send the next N sample frames (the counter still advances)
    truncate N   send only the first half of the next N sample frames
    silence S    send nothing for S seconds (the rig keeps sampling)
    unplug S     the device vanishes for S seconds: the pty is closed and the symlink removed,
                 then a new pty is opened and the symlink re-created

The firmware keeps sampling (and counting) through every fault, like the real controller.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import math
import os
import queue
import select
import signal
import sys
import tempfile
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .arc import D_MM, L1_MM, L2_MM, ArcGeometry
from .protocol import (
    CRC_LEN,
    ERROR_BAD_FRAME,
    ERROR_UNKNOWN_TYPE,
    FLAG_LASER_NO_TARGET,
    FLAG_VOLTAGE_CLAMPED,
    LASER_MAX_MM,
    LASER_MIN_MM,
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

__all__ = ["FAULT_KINDS", "Fault", "parse_fault", "RigEmulator", "main"]

TX_BUFFER_BYTES = 4096  # transmit buffer of the emulated firmware

FAULT_KINDS = {
    "garbage": int,
    "badcrc": int,
    "drop": int,
    "truncate": int,
    "silence": float,
    "unplug": float,
}


@dataclass(frozen=True)
class Fault:
    """One fault command: ``kind`` from ``FAULT_KINDS`` and its amount (bytes, frames or s)."""

    kind: str
    amount: float


def parse_fault(line: str) -> Fault:
    """Parse one stdin line such as ``"garbage 100"`` or ``"unplug 1.5"``.

    Raises ``ValueError`` with the accepted forms when the line is not a fault command.
    """
    parts = line.split()
    usage = "expected one of: " + ", ".join(
        f"{k} {'S' if t is float else 'N'}" for k, t in FAULT_KINDS.items()
    )
    if len(parts) != 2 or parts[0] not in FAULT_KINDS:
        raise ValueError(f"bad fault command {line.strip()!r}; {usage}")
    kind, text = parts
    try:
        amount = FAULT_KINDS[kind](text)
    except ValueError:
        raise ValueError(f"bad amount {text!r} for '{kind}'; {usage}") from None
    if not math.isfinite(amount) or amount < 0:
        raise ValueError(f"amount of '{kind}' must be >= 0, got {text}")
    return Fault(kind, amount)


class RigEmulator:
    """The controller firmware: plant + laser + protocol on a pty.

    Parameters
    ----------
    plant : IpmcPlant
        The simulated actuator, stepped once per sample with ``dt_s = 1 / sample_rate_hz``.
    sample_rate_hz : float
        Sampling rate of the rig, Hz.
    link_path : str or Path
        Path of the symlink to the pty slave that clients open.
    geometry : ArcGeometry
        Laser geometry used to turn the tip displacement into the raw laser reading.
    u_limit_v : float
        Firmware voltage limit, V (setpoints beyond it are clamped and flagged).
    seed : int
        Seed of the garbage bytes.
    watchdog_s : float
        Firmware watchdog, s: the setpoint falls to 0 V at the first sample due this long after
        the last SET_VOLTAGE frame received (default ``RIG_WATCHDOG_S``).
    log_path : str or Path, optional
        CSV log, one row per sample: ``counter,t_s,setpoint_v,u_applied_v,y_mm,x_mm,sent``
        (``sent`` is 1 when the sample frame went out intact).
    events : file, optional
        Where to print one line per event (faults, setpoint changes, unplug/replug).
    """

    def __init__(
        self,
        plant,
        *,
        sample_rate_hz: float = 100.0,
        link_path: str | Path,
        geometry: ArcGeometry | None = None,
        u_limit_v: float = 3.0,
        seed: int = 0,
        watchdog_s: float = RIG_WATCHDOG_S,
        log_path: str | Path | None = None,
        events=None,
    ):
        if not (math.isfinite(sample_rate_hz) and 0 < sample_rate_hz <= 65535):
            raise ValueError(f"sample_rate_hz must be in (0, 65535], got {sample_rate_hz}")
        if not (math.isfinite(watchdog_s) and watchdog_s > 0):
            raise ValueError(f"watchdog_s must be a finite number > 0, got {watchdog_s}")
        self.plant = plant
        self.sample_rate_hz = float(sample_rate_hz)
        self.link_path = Path(link_path)
        self.geometry = geometry or ArcGeometry()
        self.u_limit_v = float(u_limit_v)
        self.watchdog_s = float(watchdog_s)
        self.watchdog_trips = 0
        self._last_command_at = -math.inf  # monotonic time of the last SET_VOLTAGE received
        self._rng = np.random.default_rng(seed)
        self._events = events
        self._faults: queue.SimpleQueue[Fault] = queue.SimpleQueue()
        self._rx = FrameDecoder()
        self._master: int | None = None
        self._slave: int | None = None
        self._tx_seq = 0
        self._setpoint_v = 0.0
        self._command_seq = 0
        self._counter = 0
        self._pending = {"garbage": 0, "badcrc": 0, "drop": 0, "truncate": 0}
        self._silent_from = 0.0
        self._silent_until = 0.0
        self._unplugged_until = 0.0
        self._log_file = open(log_path, "w", newline="") if log_path else None  # noqa: SIM115
        self._log = csv.writer(self._log_file) if self._log_file else None
        if self._log:
            self._log.writerow(
                ["counter", "t_s", "setpoint_v", "u_applied_v", "y_mm", "x_mm", "sent"]
            )
        self.bytes_sent = 0
        self._tx_backlog = bytearray()

    # ------------------------------------------------------------------ device
    @property
    def connected(self) -> bool:
        return self._master is not None

    def open_device(self) -> str:
        """Open a new pty and point the symlink at it; return the symlink path."""
        master, slave = os.openpty()
        # Raw mode before anyone opens it: with echo on, the line discipline would send the PC's
        # bytes straight back, and canonical mode would hold bytes until a newline.
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self._rx = FrameDecoder()
        tmp = self.link_path.with_name(self.link_path.name + ".new")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.link_path)
        return str(self.link_path)

    def close_device(self) -> None:
        """Remove the symlink and close the pty: clients see the device vanish."""
        with contextlib.suppress(FileNotFoundError):
            self.link_path.unlink()
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None
        self._tx_backlog.clear()

    def close(self) -> None:
        """Close the device and the log."""
        self.close_device()
        if self._log_file:
            self._log_file.close()
            self._log_file = None
            self._log = None

    # ------------------------------------------------------------------ faults
    def inject(self, fault: Fault) -> None:
        """Queue a fault; thread-safe (the stdin reader calls it)."""
        self._faults.put(fault)

    def _apply_faults(self, now: float) -> None:
        while True:
            try:
                fault = self._faults.get_nowait()
            except queue.Empty:
                return
            self._event(f"fault {fault.kind} {fault.amount:g}")
            if fault.kind in self._pending:
                self._pending[fault.kind] += int(fault.amount)
            elif fault.kind == "silence":
                # In rig time: the samples due in [now, now + S) are not sent, even if a late
                # (starved) loop produces them afterwards.
                if now >= self._silent_until:
                    self._silent_from = now
                self._silent_until = max(self._silent_until, now + fault.amount)
            elif fault.kind == "unplug":
                self._unplugged_until = now + fault.amount
                if self.connected:
                    self.close_device()
                    self._event("unplugged")

    def _event(self, text: str) -> None:
        if self._events is not None:
            print(f"{time.monotonic():.3f} {text}", file=self._events, flush=True)

    # ------------------------------------------------------------------ protocol
    def _send(self, data: bytes) -> None:
        """Write to the pty; what does not fit waits in a bounded transmit buffer."""
        if self._master is None:
            return
        self._tx_backlog += data
        try:
            n = os.write(self._master, self._tx_backlog)
        except BlockingIOError:
            n = 0
        except OSError:
            n = len(self._tx_backlog)  # no client: the bytes are lost, as on a real UART
        self.bytes_sent += n
        del self._tx_backlog[:n]
        if len(self._tx_backlog) > TX_BUFFER_BYTES:
            # Nobody reads the port: the firmware's transmit buffer overflows and is emptied
            # (whole frames are lost, a partial one stays possible at the cut).
            self._tx_backlog.clear()

    def _next_seq(self) -> int:
        seq = self._tx_seq
        self._tx_seq = (seq + 1) & 0xFF
        return seq

    def _receive(self) -> bool:
        """Handle the frames the PC sent; False when there was nothing to read."""
        if self._master is None:
            return False
        got = False
        while True:
            try:
                data = os.read(self._master, 4096)
            except (BlockingIOError, OSError):
                # EAGAIN: nothing to read; EIO: no client has the slave open.
                return got
            if not data:
                return got
            got = True
            bad_before = self._rx.stats.bad_crc + self._rx.stats.truncated
            for frame in self._rx.feed(data):
                try:
                    msg = parse_frame(frame)
                except ProtocolError:
                    self._send(encode_message(RigError(ERROR_UNKNOWN_TYPE, frame.msg_type), 0))
                    continue
                if isinstance(msg, SetVoltage):
                    self._last_command_at = time.monotonic()
                    self._command_seq = frame.seq
                    if msg.voltage_v != self._setpoint_v:
                        self._event(f"setpoint {msg.voltage_v:.3f}")
                    self._setpoint_v = msg.voltage_v
                elif isinstance(msg, Ping):
                    self._send(encode_message(self._status(), self._next_seq()))
                else:
                    self._send(encode_message(RigError(ERROR_UNKNOWN_TYPE, frame.msg_type), 0))
            if self._rx.stats.bad_crc + self._rx.stats.truncated > bad_before:
                self._send(encode_message(RigError(ERROR_BAD_FRAME, 0), self._next_seq()))

    def _check_watchdog(self, due_at: float) -> None:
        """Zero the setpoint when the sample due at ``due_at`` comes ``watchdog_s`` or more
        after the last command. Judged in rig time: samples a starved loop produces late, after
        reading a command that waited in the pty, are not counted as a silent PC."""
        if self._setpoint_v != 0.0 and due_at - self._last_command_at > self.watchdog_s:
            self._setpoint_v = 0.0
            self.watchdog_trips += 1
            self._event(f"watchdog 0 V after {self.watchdog_s * 1e3:g} ms without a command")

    def _status(self) -> Status:
        return Status(self._counter, round(self.sample_rate_hz), self._setpoint_v, 0)

    def _sample_frame(self) -> tuple[bytes, list]:
        """Step the plant once; return the (possibly faulty) frame bytes and the log row."""
        counter = self._counter
        self._counter += 1
        setpoint = self._setpoint_v
        flags = 0
        if abs(setpoint) > self.u_limit_v:
            flags |= FLAG_VOLTAGE_CLAMPED
            setpoint = math.copysign(self.u_limit_v, setpoint)
        u_applied, y_mm = self.plant.step(setpoint)
        x_mm = self.geometry.reading_scalar(y_mm)
        if x_mm is None or not LASER_MIN_MM <= x_mm <= LASER_MAX_MM:
            x_mm = None
            flags |= FLAG_LASER_NO_TARGET
        sample = Sample(counter, u_applied, x_mm, self._command_seq, flags)
        frame = encode_message(sample, self._next_seq())
        pending = self._pending
        sent = 1
        if pending["drop"]:
            pending["drop"] -= 1
            frame, sent = b"", 0
        elif pending["badcrc"]:
            pending["badcrc"] -= 1
            crc = int.from_bytes(frame[-CRC_LEN:], "little") ^ 0x5A5A
            frame, sent = frame[:-CRC_LEN] + crc.to_bytes(CRC_LEN, "little"), 0
        elif pending["truncate"]:
            pending["truncate"] -= 1
            frame, sent = frame[: len(frame) // 2], 0
        row = [counter, f"{counter / self.sample_rate_hz:.6f}", f"{self._setpoint_v:.4f}",
               f"{u_applied:.4f}", f"{y_mm:.5f}", "" if x_mm is None else f"{x_mm:.5f}", sent]
        return frame, row

    # ------------------------------------------------------------------ real-time loop
    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        """Sample in real time until ``stop`` is set (or ``duration_s`` has passed).

        Samples are due at ``start + k / sample_rate_hz``; when the process is late (a loaded
        machine) the due samples are produced back to back so the counter stays tied to time.
        """
        period = 1.0 / self.sample_rate_hz
        status_every = max(1, round(self.sample_rate_hz))
        start = time.monotonic()
        produced = 0
        while not stop.is_set():
            now = time.monotonic()
            if duration_s is not None and now - start >= duration_s:
                break
            self._apply_faults(now)
            if not self.connected and now >= self._unplugged_until:
                self.open_device()
                self._event("replugged")
            self._receive()
            due = int((now - start) / period) + 1
            out = bytearray()
            while produced < due:
                due_at = start + produced * period
                silent = (self._silent_from <= due_at < self._silent_until
                          or not self.connected)
                if self._pending["garbage"] and not silent:
                    out += self._rng.integers(0, 256, self._pending["garbage"], np.uint8).tobytes()
                    self._pending["garbage"] = 0
                self._check_watchdog(due_at)
                frame, row = self._sample_frame()
                if silent:
                    row[-1] = 0
                else:
                    out += frame
                if self._log:
                    self._log.writerow(row)
                produced += 1
                if produced % status_every == 0 and not silent:
                    out += encode_message(self._status(), self._next_seq())
            if out:
                self._send(bytes(out))
            if self._log_file and produced % status_every == 0:
                self._log_file.flush()
            sleep_s = start + produced * period - time.monotonic()
            if sleep_s > 0:
                self._wait(stop, min(sleep_s, 0.05))

    def _wait(self, stop: threading.Event, timeout_s: float) -> None:
        """Wait for the next sample, waking for bytes from the PC: a command is taken (and
        feeds the watchdog) when it arrives, as by the firmware's UART interrupt, and applied
        from the next sample on."""
        if self._master is None:
            stop.wait(timeout_s)
            return
        try:
            readable, _, _ = select.select([self._master], [], [], timeout_s)
        except (OSError, ValueError):
            readable = []
        if readable and not self._receive():
            stop.wait(timeout_s)  # readable without data (a hang-up): do not spin


def _read_stdin(emulator: RigEmulator, fd: int = 0) -> None:
    # os.read, not sys.stdin: a daemon thread blocked inside sys.stdin holds its buffer lock,
    # which the interpreter needs at exit (a stall, or "could not acquire lock ... at interpreter
    # shutdown, possibly due to daemon threads").
    pending = b""
    while True:
        try:
            chunk = os.read(fd, 4096)
        except OSError:
            return
        if not chunk:
            return
        pending += chunk
        *lines, pending = pending.split(b"\n")
        for raw in lines:
            line = raw.decode("utf-8", "replace")
            if not line.strip():
                continue
            try:
                emulator.inject(parse_fault(line))
            except ValueError as exc:
                print(f"rig_emulator: {exc}", file=sys.stderr, flush=True)


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ipmc rig-emulator",
        description="Emulate the IPMC rig controller on a pseudo-terminal. Prints the device "
        "path on the first stdout line; reads fault commands on stdin (garbage N, badcrc N, "
        "drop N, truncate N, silence S, unplug S).",
    )
    parser.add_argument("--rate-hz", type=float, default=100.0, help="sample rate (Hz)")
    parser.add_argument(
        "--link", default=None, help="device symlink to create (default: in a new temp dir)"
    )
    parser.add_argument("--params", default=None, help="plant parameter YAML (default: shipped)")
    parser.add_argument(
        "--effects", default="", help="comma-separated plant effects (creep,drift,...)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of noise and garbage")
    parser.add_argument("--l1-mm", type=float, default=L1_MM, help="actuator length L1 (mm)")
    parser.add_argument("--l2-mm", type=float, default=L2_MM, help="clamp to laser line L2 (mm)")
    parser.add_argument("--d-mm", type=float, default=D_MM, help="laser reading at rest d (mm)")
    parser.add_argument("--u-limit-v", type=float, default=3.0, help="firmware voltage limit")
    parser.add_argument("--log", default=None, help="CSV log of every sample")
    parser.add_argument(
        "--events", action="store_true",
        help="after the path, print one stdout line per event: '<time.monotonic()> <event>' "
        "(fault ..., setpoint V, watchdog ..., unplugged, replugged)"
    )
    parser.add_argument("--duration-s", type=float, default=None, help="stop after this time")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the rig emulator until SIGINT/SIGTERM (or ``--duration-s``)."""
    args = _build_parser().parse_args(argv)
    from .plant import IpmcPlant, load_plant_params  # the plant pulls in YAML and SciPy-free code

    try:
        geometry = ArcGeometry(args.l1_mm, args.l2_mm, args.d_mm)
        effects = [e for e in args.effects.split(",") if e]
        plant = IpmcPlant(
            load_plant_params(args.params), effects=effects, seed=args.seed,
            dt_s=1.0 / args.rate_hz,
        )
    except ValueError as exc:
        print(f"rig_emulator: {exc}", file=sys.stderr)
        return 2
    tmpdir = None
    if args.link is None:
        tmpdir = tempfile.mkdtemp(prefix="ipmc-rig-")
        link = Path(tmpdir) / "ttyIPMC0"
    else:
        link = Path(args.link)
    emulator = RigEmulator(
        plant, sample_rate_hz=args.rate_hz, link_path=link, geometry=geometry,
        u_limit_v=args.u_limit_v, seed=args.seed, log_path=args.log,
        events=sys.stdout if args.events else None,
    )
    stop = threading.Event()
    # Both signals only set the event: the loop ends at its next wait (<= 50 ms), never with an
    # exception thrown into the middle of a write or a plant step.
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        print(emulator.open_device(), flush=True)
        threading.Thread(target=_read_stdin, args=(emulator, sys.stdin.fileno()),
                         daemon=True).start()
        emulator.run(stop, args.duration_s)
    except KeyboardInterrupt:
        pass
    finally:
        emulator.close()
        if tmpdir:
            with contextlib.suppress(OSError):
                os.rmdir(tmpdir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
