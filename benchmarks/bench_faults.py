"""Serial-link faults end to end: the rig emulator (a process, in real time) and the driver's link
core (``ipmc_driver.link.DriverLink``, stepped every 25 ms as the driver node steps it).

Scenarios, one after the other on one link, with a voltage sine commanded at 20 Hz: clean,
garbage bytes, bad CRCs, dropped frames, truncated frames, silence, unplug 2 s, unplug 8 s. For
each it prints the samples the link delivered, the frames lost (gaps in the rig's counter), the
corrupt samples delivered (any sample whose frame the rig did not send intact, or whose voltage
or displacement differs from the rig's own log: must be 0), and for the unplugs the time from
the device's return to the reopened port and to the first sample, and the frames lost after the
return. Then the safety figures:

- non-finite command: from ``command(nan)`` (and inf) to the arrival of the first sample at
  0 V, and the samples the rig took at the old voltage after it (at most the one in flight);
- driver killed (SIGKILL) while holding 2 V: a child process runs the link core; from the kill
  to the rig's firmware watchdog setting 0 V (bound: ``RIG_WATCHDOG_S`` + one sample period).

About 40 s of wall time. Prints figures; not part of the pass/fail suite.

    .venv/bin/python benchmarks/bench_faults.py [--rate-hz 100] [--kills 3]
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ipmc_driver.link import CONNECTED, TICK_PERIOD_S, DriverLink, LinkConfig, LinkSample
from ipmc_driver.protocol import RIG_WATCHDOG_S

COMMAND_PERIOD_S = 0.05  # a controller at 20 Hz
Y_TOLERANCE_MM = 0.01  # 16-bit laser counts: 4.6 um per count, times L1/L2 near rest
FAULTS = [("clean", None, 2.0), ("garbage 500 B", "garbage 500", 1.0),
          ("bad CRC x5", "badcrc 5", 1.0), ("dropped x5", "drop 5", 1.0),
          ("truncated x5", "truncate 5", 1.0), ("silence 1 s", "silence 1", 2.0),
          ("unplug 2 s", "unplug 2", 1.0), ("unplug 8 s", "unplug 8", 1.0)]


class Emulator:
    """``ipmc rig-emulator`` as a process: its device path, its events, faults on stdin."""

    def __init__(self, rate_hz: float, workdir: Path) -> None:
        self.log_path = workdir / "rig.csv"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ipmc_driver.emulator", "--rate-hz", f"{rate_hz:g}",
             "--events", "--log", str(self.log_path), "--link", str(workdir / "ttyRIG")],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1)
        self.port = self.proc.stdout.readline().strip()
        self.events: list[tuple[float, str]] = []
        threading.Thread(target=self._read_events, daemon=True).start()

    def _read_events(self) -> None:
        for line in self.proc.stdout:
            stamp, text = line.split(" ", 1)
            self.events.append((float(stamp), text.strip()))

    def fault(self, line: str) -> None:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def wait_event(self, prefix: str, after_s: float, timeout_s: float) -> float | None:
        """Monotonic time of the first event starting with ``prefix`` after ``after_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            found = [t for t, e in list(self.events) if t > after_s and e.startswith(prefix)]
            if found:
                return found[0]
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.01)

    def stop(self) -> list[dict]:
        """SIGINT (SIGKILL after 3 s); the rig's log, one row per sample."""
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(3.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        with open(self.log_path) as f:
            return list(csv.DictReader(f))


@dataclass
class Runner:
    """Steps a ``DriverLink`` as the node's timers do and keeps what it delivers."""

    link: DriverLink
    samples: list[tuple[str, LinkSample]] = field(default_factory=list)
    connected_at: list[float] = field(default_factory=list)
    label: str = ""

    def run(self, seconds: float, command: Callable[[float], float] | None = None) -> None:
        """Tick for ``seconds``; ``command(t)`` gives the voltage to command every 50 ms."""
        end = time.monotonic() + seconds
        next_command = 0.0
        while (now := time.monotonic()) < end:
            if command is not None and now >= next_command:
                self.link.command(command(now), now)
                next_command = now + COMMAND_PERIOD_S
            was = self.link.state
            self.link.tick(now)
            if self.link.state == CONNECTED and was != CONNECTED:
                self.connected_at.append(now)
            self.samples += [(self.label, s) for s in self.link.drain(time.monotonic_ns)]
            time.sleep(max(0.0, now + TICK_PERIOD_S - time.monotonic()))


def sine_v(t: float) -> float:
    return 1.5 * math.sin(2 * math.pi * 0.5 * t)


def snapshot(link: DriverLink) -> dict[str, int]:
    return {**link.decoder.stats.as_dict(), "dropped": link.counter.dropped}


def run_fault(emu: Emulator, runner: Runner, label: str, line: str | None,
              after_s: float) -> dict:
    """One scenario: the fault, the time it lasts, ``after_s`` more; its figures."""
    runner.label = label
    before, n_before = snapshot(runner.link), len(runner.samples)
    t0 = time.monotonic()
    row: dict = {"scenario": label}
    if line is not None:
        emu.fault(line)
    if line is not None and line.startswith("unplug"):
        row |= measure_unplug(emu, runner, t0, float(line.split()[1]))
    runner.run(after_s + (float(line.split()[1]) if line and line.startswith("silence")
                          else 0.0), sine_v)
    after = snapshot(runner.link)
    row |= {k: after[k] - before[k] for k in after}
    row["samples"] = len(runner.samples) - n_before
    return row


def measure_unplug(emu: Emulator, runner: Runner, t0: float, unplug_s: float) -> dict:
    """Run until the device is back and the link delivers again; times from its return."""
    n = len(runner.samples)
    while emu.wait_event("replugged", t0, 0.0) is None and time.monotonic() < t0 + unplug_s + 5:
        runner.run(TICK_PERIOD_S, sine_v)
    t_back = emu.wait_event("replugged", t0, 0.0)
    if t_back is None:
        return {"reconnect_s": math.inf, "first_sample_s": math.inf}

    def back() -> list[LinkSample]:
        return [s for _, s in runner.samples[n:] if s.arrival_s > t_back]

    while not back() or not runner.connected_at or runner.connected_at[-1] < t_back:
        if time.monotonic() > t_back + 10.0:
            return {"reconnect_s": math.inf, "first_sample_s": math.inf}
        runner.run(TICK_PERIOD_S, sine_v)
    first = back()[0]
    last = max(s.counter for _, s in runner.samples if s.counter < first.counter)
    return {"reconnect_s": runner.connected_at[-1] - t_back,
            "first_sample_s": first.arrival_s - t_back, "gap": (last, first.counter)}


def corrupt_samples(samples: list[tuple[str, LinkSample]], rows: list[dict]) -> dict[str, int]:
    """Per scenario: delivered samples the rig did not send intact or that differ from its log."""
    by_counter = {int(r["counter"]): r for r in rows}
    bad: dict[str, int] = {}
    for label, s in samples:
        r = by_counter.get(s.counter)
        wrong = (r is None or r["sent"] != "1"
                 or abs(s.applied_v - float(r["u_applied_v"])) > 1e-3
                 or abs(s.y_mm - float(r["y_mm"])) > Y_TOLERANCE_MM)
        bad[label] = bad.get(label, 0) + wrong
    return bad


def lost_after_return(gap: tuple[int, int], rows: list[dict]) -> int:
    """Frames the rig sent after the device returned but the link never read."""
    last, first = gap
    sent = {int(r["counter"]): r["sent"] == "1" for r in rows}
    k = last + 1
    while k < first and not sent.get(k, False):  # not sent: the device was gone
        k += 1
    return first - k


def nan_to_zero(runner: Runner, bad: float) -> dict:
    """Hold 2 V, then one non-finite command: the time until the first sample at 0 V arrives,
    and the samples the rig took at 2 V after the command (those in flight)."""
    runner.label = f"command {bad}"
    runner.run(0.6, lambda t: 2.0)
    sent_s = time.monotonic()
    runner.link.command(bad, sent_s)
    runner.run(0.4)
    held = [s for label, s in runner.samples if label == runner.label]
    last_before = max((s.counter for s in held if s.arrival_s < sent_s), default=None)
    first_zero = next((s for s in held if s.arrival_s >= sent_s and s.applied_v == 0.0), None)
    if last_before is None or first_zero is None:
        return {"what": f"command {bad}", "to_zero_s": math.inf, "late_samples": math.inf}
    return {"what": f"command {bad}", "to_zero_s": first_zero.arrival_s - sent_s,
            "late_samples": first_zero.counter - last_before - 1}


def hold_main(port: str, volts: float, rate_hz: float) -> int:
    """Child process: the link core holding ``volts`` until it is killed."""
    link = DriverLink(LinkConfig(port=port, sample_rate_hz=rate_hz, watchdog_s=60.0))
    Runner(link).run(math.inf, lambda t: volts)
    return 0


def kill_to_zero(emu: Emulator, rate_hz: float, rng: random.Random) -> float:
    """Start a link process at 2 V, SIGKILL it at a random phase of its 50 ms command period;
    seconds until the rig's watchdog set 0 V."""
    t_start = time.monotonic()
    child = subprocess.Popen([sys.executable, __file__, "--hold", emu.port, "--hold-v", "2.0",
                              "--rate-hz", f"{rate_hz:g}"])
    try:
        if emu.wait_event("setpoint 2.000", t_start, 20.0) is None:
            return math.inf
        time.sleep(0.5 + rng.uniform(0.0, COMMAND_PERIOD_S))
        t_kill = time.monotonic()
        os.kill(child.pid, signal.SIGKILL)
        t_zero = emu.wait_event("watchdog", t_kill, 3.0)
        return math.inf if t_zero is None else t_zero - t_kill
    finally:
        child.kill()
        child.wait()


def print_faults(rows: list[dict]) -> None:
    cols = [("scenario", 14, "s"), ("samples", 7, "d"), ("lost", 5, "d"), ("corrupt", 7, "d"),
            ("bad_crc", 7, "d"), ("truncated", 9, "d"), ("resyncs", 7, "d"),
            ("discarded_bytes", 15, "d"), ("reconnect_s", 11, ".3f"),
            ("first_sample_s", 14, ".3f"), ("lost_after_return", 17, "d")]
    print(" ".join(f"{name:>{w}}" for name, w, _ in cols))
    for row in rows:
        cells = []
        for name, w, fmt in cols:
            value = row.get("dropped" if name == "lost" else name)
            cells.append(f"{'-':>{w}}" if value is None else f"{value:>{w}{fmt}}")
        print(" ".join(cells))


def print_safety(nan_rows: list[dict], kills_s: list[float], rate_hz: float) -> bool:
    period_s = 1.0 / rate_hz
    bound_s = RIG_WATCHDOG_S + period_s
    ok = True
    print(f"{'safety':<42} {'figure':>22} {'bound':>22}  ok")
    for r in nan_rows:
        good = r["late_samples"] <= 1
        ok &= good
        print(f"{r['what'] + ': first 0 V sample after':<42} "
              f"{r['to_zero_s'] * 1e3:>8.1f} ms ({r['to_zero_s'] / period_s:.1f} periods) "
              f"{'next sample':>22}  {'yes' if good else 'NO'}")
        print(f"{'  samples at 2 V after it (in flight)':<42} {r['late_samples']:>22} "
              f"{'<= 1':>22}  {'yes' if good else 'NO'}")
    if kills_s:
        worst = max(kills_s)
        good = worst <= bound_s
        ok &= good
        print(f"{f'driver SIGKILL at 2 V -> rig 0 V (n={len(kills_s)})':<42} "
              f"{f'median {statistics.median(kills_s) * 1e3:.0f}, max {worst * 1e3:.0f} ms':>22} "
              f"{f'<= {RIG_WATCHDOG_S * 1e3:.0f} + {period_s * 1e3:.0f} ms':>22}  "
              f"{'yes' if good else 'NO'}")
    return ok


def run_all(args: argparse.Namespace, workdir: Path) -> tuple[list, list, list, Emulator]:
    emu = Emulator(args.rate_hz, workdir)
    runner = Runner(DriverLink(LinkConfig(port=emu.port, sample_rate_hz=args.rate_hz,
                                          watchdog_s=5.0)))
    rows, nan_rows, kills = [], [], []
    try:
        runner.run(1.0, sine_v)  # the first connection, the stamps' anchor
        rows = [run_fault(emu, runner, label, line, after_s) for label, line, after_s in FAULTS]
        nan_rows = [nan_to_zero(runner, bad) for bad in (math.nan, math.inf)]
        runner.link.shutdown()
        rng = random.Random(args.seed)
        kills = [kill_to_zero(emu, args.rate_hz, rng) for _ in range(args.kills)]
    finally:
        runner.link.shutdown()
        log = emu.stop()
    corrupt = corrupt_samples(runner.samples, log)
    for row in rows:
        row["corrupt"] = corrupt.get(row["scenario"], 0)
        if "gap" in row:
            row["lost_after_return"] = lost_after_return(row.pop("gap"), log)
    rows.append({"scenario": "all", "samples": len(runner.samples),
                 "corrupt": sum(corrupt.values())})
    return rows, nan_rows, kills, emu


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate-hz", type=float, default=100.0, help="rig sample rate")
    parser.add_argument("--kills", type=int, default=5, help="SIGKILL trials")
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill instants")
    parser.add_argument("--hold", default=None, help=argparse.SUPPRESS)  # the child's port
    parser.add_argument("--hold-v", type=float, default=2.0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.hold:
        return hold_main(args.hold, args.hold_v, args.rate_hz)
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="ipmc-faults-") as tmp:
        rows, nan_rows, kills, _ = run_all(args, Path(tmp))
    print(f"rig emulator at {args.rate_hz:g} Hz, link core ticked every "
          f"{TICK_PERIOD_S * 1e3:g} ms, rig watchdog {RIG_WATCHDOG_S * 1e3:g} ms; "
          f"machine: {os.cpu_count()} CPU(s), load {os.getloadavg()[0]:.2f}")
    print_faults(rows)
    print()
    ok = print_safety(nan_rows, kills, args.rate_hz)
    corrupt = rows[-1]["corrupt"]
    reconnect = [r["reconnect_s"] for r in rows if "reconnect_s" in r]
    print(f"\ncorrupt samples delivered: {corrupt} (must be 0); reconnect after the port "
          f"returns: max {max(reconnect):.3f} s (goal <= 0.5 s); safety bounds "
          f"{'met' if ok else 'NOT met'}; wall time {time.monotonic() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
