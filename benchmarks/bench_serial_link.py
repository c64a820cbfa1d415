"""Highest sustained sample rate through the rig emulator link, as a fraction of the baud limit.

The link: the rig emulator process (plant + laser + protocol, real time) -> pty -> pyserial ->
``FrameDecoder`` -> ``parse_frame``, the same read path as the driver's reader thread
(``read(in_waiting or 1)``). A pty has no baud rate, so the baud limit is computed: a SAMPLE
frame is ``SAMPLE_FRAME_LEN`` bytes, a byte on the UART is 10 bits (start, 8 data, stop), plus one
STATUS frame a second::

    limit_hz = (baudrate / 10 - status_bytes_per_s) / SAMPLE_FRAME_LEN

A rate is *sustained* when, over ``--seconds`` of streaming, every sample arrives (no counter gap,
no decoder loss) and the pipeline keeps up: the lag of a sample behind its schedule
(``arrival - (counter - first_counter) / rate``) does not grow by more than ``--max-lag-growth-s``
from the first to the last quarter of the window (medians; a stall of the shared machine that is
caught up again does not count). The rate ladder doubles until a rate fails, then bisects. Prints
figures; not part of the pass/fail suite. On a shared machine the figure moves with the load:
the load average is printed with it.

    .venv/bin/python benchmarks/bench_serial_link.py [--baudrate 115200] [--seconds 2]
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import statistics
import subprocess
import sys
import time

import serial

from ipmc_driver.protocol import (
    MSG_SET_VOLTAGE,
    MSG_STATUS,
    SAMPLE_FRAME_LEN,
    FrameDecoder,
    Sample,
    SetVoltage,
    Status,
    encode_message,
    frame_length,
    parse_frame,
)

BITS_PER_BYTE = 10  # start + 8 data + stop, no parity


def baud_limit_hz(baudrate: int, command_every_sample: bool = False) -> float:
    """Highest sample rate the UART can carry for the protocol's frame sizes (Hz)."""
    per_s = baudrate / BITS_PER_BYTE - frame_length(MSG_STATUS)  # 1 Hz heartbeat
    per_sample = SAMPLE_FRAME_LEN + (frame_length(MSG_SET_VOLTAGE) if command_every_sample else 0)
    return per_s / per_sample


def measure(rate_hz: float, seconds: float) -> dict:
    """Stream from a fresh emulator process at ``rate_hz`` for ``seconds``; return figures."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "ipmc_driver.emulator", "--rate-hz", f"{rate_hz:g}"],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, text=True,
    )
    try:
        path = proc.stdout.readline().strip()
        port = serial.Serial(path, 115200, timeout=0.05)
        port.reset_input_buffer()
        port.write(encode_message(SetVoltage(1.0), seq=1))
        dec = FrameDecoder()
        counters: list[int] = []
        arrivals: list[float] = []
        cpu0 = time.process_time()
        # Warm-up (process start, first reads), then the measured window.
        end_warm = time.monotonic() + 0.3
        while time.monotonic() < end_warm:
            dec.feed(port.read(port.in_waiting or 1))
        dec = FrameDecoder()
        port.reset_input_buffer()
        t0 = time.monotonic()
        cpu0 = time.process_time()
        nbytes = 0
        statuses = 0
        while time.monotonic() - t0 < seconds:
            data = port.read(port.in_waiting or 1)
            now = time.monotonic()
            nbytes += len(data)
            for frame in dec.feed(data):
                msg = parse_frame(frame)
                if isinstance(msg, Sample):
                    counters.append(msg.counter)
                    arrivals.append(now)
                elif isinstance(msg, Status):
                    statuses += 1
        elapsed = time.monotonic() - t0
        cpu = time.process_time() - cpu0
        port.close()
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(2.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    # The first counter after the flush may follow a partial frame: count from there.
    gaps = sum(b - a - 1 for a, b in zip(counters, counters[1:], strict=False) if b - a != 1)
    received_hz = len(counters) / elapsed
    lag = [a - (c - counters[0]) / rate_hz for a, c in zip(arrivals, counters, strict=True)]
    q = max(1, len(lag) // 4)
    lag_growth = statistics.median(lag[-q:]) - statistics.median(lag[:q]) if lag else math.inf
    return {
        "lag_growth_s": lag_growth,
        "lag_max_s": max(lag) - min(lag) if lag else math.inf,
        "rate_hz": rate_hz,
        "received_hz": received_hz,
        "ratio": received_hz / rate_hz,
        "gaps": gaps,
        "bad": dec.stats.bad_crc + dec.stats.truncated,
        "bytes_per_s": nbytes / elapsed,
        "reader_cpu": cpu / elapsed,
    }


def sustained(m: dict, max_lag_growth_s: float) -> bool:
    return m["gaps"] == 0 and m["bad"] == 0 and m["lag_growth_s"] <= max_lag_growth_s


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baudrate", type=int, default=115200)
    parser.add_argument("--seconds", type=float, default=2.0, help="measured window per rate")
    parser.add_argument("--max-hz", type=float, default=64000.0, help="top of the rate ladder")
    parser.add_argument("--bisect", type=int, default=3, help="bisection steps after the ladder")
    parser.add_argument("--max-lag-growth-s", type=float, default=0.05,
                        help="largest growth of the schedule lag still counted as keeping up")
    args = parser.parse_args(argv)

    limit = baud_limit_hz(args.baudrate)
    limit_cmd = baud_limit_hz(args.baudrate, command_every_sample=True)
    print(f"frame: SAMPLE {SAMPLE_FRAME_LEN} B, SET_VOLTAGE {frame_length(MSG_SET_VOLTAGE)} B, "
          f"STATUS {frame_length(MSG_STATUS)} B at 1 Hz; {BITS_PER_BYTE} bits per byte")
    print(f"baud limit at {args.baudrate} Bd: {limit:.1f} Hz samples only; "
          f"{limit_cmd:.1f} Hz with one SET_VOLTAGE per sample on the half-duplex RS-485 bus")
    print(f"machine: {os.cpu_count()} CPU(s), load {os.getloadavg()[0]:.2f}; "
          f"window {args.seconds:g} s per rate")
    print(f"{'rate_hz':>9} {'x_limit':>8} {'recv_hz':>9} {'recv/nom':>8} {'gaps':>5} "
          f"{'bad':>4} {'bytes/s':>9} {'lag+_ms':>8} {'lagmax_ms':>9} {'reader_cpu':>10} "
          f"sustained")

    def run(rate):
        m = measure(rate, args.seconds)
        ok = sustained(m, args.max_lag_growth_s)
        print(f"{rate:9.1f} {rate / limit:8.2f} {m['received_hz']:9.1f} {m['ratio']:8.4f} "
              f"{m['gaps']:5d} {m['bad']:4d} {m['bytes_per_s']:9.0f} "
              f"{m['lag_growth_s'] * 1e3:8.1f} {m['lag_max_s'] * 1e3:9.1f} "
              f"{m['reader_cpu']:10.2f} "
              f"{'yes' if ok else 'NO'}", flush=True)
        return ok

    best, fail = 0.0, None
    rate = 100.0
    for rate in [100.0, 250.0, limit] + [limit * 2**k for k in range(1, 16)]:
        if rate > args.max_hz:
            break
        if run(rate):
            best = rate
        else:
            fail = rate
            break
    if fail is not None and best > 0:
        lo, hi = best, fail
        for _ in range(args.bisect):
            mid = (lo + hi) / 2
            if run(mid):
                lo = best = mid
            else:
                hi = mid
    print(f"highest sustained sample rate: {best:.0f} Hz = {best / limit:.2f} x the "
          f"{args.baudrate} Bd limit ({limit:.1f} Hz for {SAMPLE_FRAME_LEN}-byte frames)"
          + ("" if fail is not None else f" (ladder stopped at --max-hz {args.max_hz:g})"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
