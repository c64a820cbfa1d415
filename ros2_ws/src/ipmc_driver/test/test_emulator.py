"""Rig emulator on a real pty: stream, commands, every fault kind, unplug, the firmware
watchdog, the CLI."""

from __future__ import annotations

import contextlib
import csv
import os
import signal
import subprocess
import sys
import threading
import time

import pytest
import serial
from numpy.testing import assert_allclose

from ipmc_driver.arc import ArcGeometry
from ipmc_driver.emulator import Fault, RigEmulator, parse_fault
from ipmc_driver.plant import IpmcPlant
from ipmc_driver.protocol import (
    FLAG_VOLTAGE_CLAMPED,
    RIG_WATCHDOG_S,
    FrameDecoder,
    Sample,
    SetVoltage,
    Status,
    encode_message,
    parse_frame,
)

RATE_HZ = 200.0
# Most tests send one command and read for a while: a firmware watchdog far longer than any
# test keeps the command applied whatever the scheduling of this process. The watchdog's own
# tests use the protocol's value.
LONG_WATCHDOG_S = 30.0


@pytest.fixture
def rig(tmp_path):
    """An emulator running in a thread; yields (emulator, open serial port, log path)."""
    with running_rig(tmp_path, LONG_WATCHDOG_S) as running:
        yield running


@contextlib.contextmanager
def running_rig(tmp_path, watchdog_s: float):
    log = tmp_path / "rig.csv"
    emu = RigEmulator(
        IpmcPlant(seed=1, dt_s=1.0 / RATE_HZ),
        sample_rate_hz=RATE_HZ,
        link_path=tmp_path / "ttyRIG",
        watchdog_s=watchdog_s,
        log_path=log,
    )
    emu.open_device()
    stop = threading.Event()
    thread = threading.Thread(target=emu.run, args=(stop,), daemon=True)
    thread.start()
    port = serial.Serial(str(emu.link_path), 115200, timeout=0.02)
    port.reset_input_buffer()
    try:
        yield emu, port, log
    finally:
        port.close()
        stop.set()
        thread.join(2.0)
        assert not thread.is_alive()
        emu.close()


def read_for(port, dec: FrameDecoder, seconds: float) -> list:
    msgs = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        msgs += [parse_frame(f) for f in dec.feed(port.read(port.in_waiting or 1))]
    return msgs


def samples_of(msgs) -> list[Sample]:
    return [m for m in msgs if isinstance(m, Sample)]


def test_parse_fault_accepts_every_kind():
    assert parse_fault("garbage 100\n") == Fault("garbage", 100)
    assert parse_fault("badcrc 3") == Fault("badcrc", 3)
    assert parse_fault("drop 2") == Fault("drop", 2)
    assert parse_fault("truncate 1") == Fault("truncate", 1)
    assert parse_fault("silence 0.5") == Fault("silence", 0.5)
    assert parse_fault("  unplug 1 ") == Fault("unplug", 1.0)


@pytest.mark.parametrize(
    "line, match",
    [("explode 3", "bad fault command"), ("garbage", "bad fault command"),
     ("drop 1.5", "bad amount"), ("silence -1", "must be >= 0")],
)
def test_parse_fault_rejects_bad_lines(line, match):
    with pytest.raises(ValueError, match=match):
        parse_fault(line)


def test_stream_contiguous_at_rate_with_heartbeat(rig):
    emu, port, _ = rig
    dec = FrameDecoder()
    t0 = time.monotonic()
    msgs = read_for(port, dec, 1.2)
    elapsed = time.monotonic() - t0
    counters = [s.counter for s in samples_of(msgs)]
    assert counters == list(range(counters[0], counters[0] + len(counters)))
    assert len(counters) == pytest.approx(elapsed * RATE_HZ, rel=0.15)
    statuses = [m for m in msgs if isinstance(m, Status)]
    assert statuses and statuses[0].sample_rate_hz == RATE_HZ
    assert dec.stats.discarded_bytes == 0


def test_set_voltage_applied_clamped_and_echoed(rig):
    emu, port, log = rig
    dec = FrameDecoder()
    port.write(encode_message(SetVoltage(1.5), seq=7))
    msgs = samples_of(read_for(port, dec, 0.3))
    assert msgs[-1].applied_v == pytest.approx(1.5, abs=1e-3)
    assert msgs[-1].command_seq == 7
    port.write(encode_message(SetVoltage(5.0), seq=8))
    msgs = samples_of(read_for(port, dec, 0.2))
    assert msgs[-1].applied_v == pytest.approx(3.0, abs=1e-3)
    assert msgs[-1].flags & FLAG_VOLTAGE_CLAMPED


def test_laser_reading_compensates_back_to_plant_displacement(rig):
    emu, port, log = rig
    dec = FrameDecoder()
    port.write(encode_message(SetVoltage(-2.0), seq=1))
    msgs = samples_of(read_for(port, dec, 0.6))
    emu._log_file.flush()
    with open(log) as f:
        y_log = {int(r["counter"]): float(r["y_mm"]) for r in csv.DictReader(f)}
    geo = ArcGeometry()
    got = [(geo.compensate(s.laser_mm), y_log[s.counter]) for s in msgs if s.counter in y_log]
    assert len(got) > 50
    y_rx, y_true = zip(*got, strict=True)
    # 16-bit laser counts: 4.6 um per count, times L1/L2 near rest.
    assert_allclose(y_rx, y_true, rtol=0, atol=5e-3)
    assert min(y_true) < -0.5  # the actuator did move


@pytest.mark.parametrize(
    "fault, stat, expected",
    [(Fault("badcrc", 3), "bad_crc", 3), (Fault("truncate", 2), "truncated", 2)],
)
def test_frame_faults_counted_by_decoder(rig, fault, stat, expected):
    emu, port, _ = rig
    dec = FrameDecoder()
    before = samples_of(read_for(port, dec, 0.2))
    assert before, "no sample before the fault"
    emu.inject(fault)
    msgs = samples_of(read_for(port, dec, 0.3))
    assert getattr(dec.stats, stat) == expected
    # from the last sample before the fault: the damaged frames may be the first ones after it
    counters = [before[-1].counter] + [s.counter for s in msgs]
    gaps = [b - a - 1 for a, b in zip(counters, counters[1:], strict=False) if b - a != 1]
    assert gaps == [expected]  # the damaged frames are missing, nothing else


def test_garbage_resyncs(rig):
    emu, port, _ = rig
    dec = FrameDecoder()
    read_for(port, dec, 0.1)
    emu.inject(Fault("garbage", 300))
    msgs = samples_of(read_for(port, dec, 0.3))
    assert dec.stats.resyncs >= 1
    assert dec.stats.discarded_bytes >= 300 - 20  # a tail may sit in a skipped false candidate
    counters = [s.counter for s in msgs]
    assert counters == list(range(counters[0], counters[0] + len(counters)))


def counters_until_gap(port, dec, last: int, timeout_s=10.0, after=10):
    """Sample counters read until a gap and ``after`` samples past it are in (a starved
    emulator thread may apply a fault late: seen at 3 s with load 9), or ``timeout_s``.
    ``last`` is the counter read just before the fault: with the port drained, the first
    frames the fault removes follow it directly, and the gap is between it and the next."""
    counters, t0 = [last], time.monotonic()
    while time.monotonic() < t0 + timeout_s:
        counters += [m.counter for m in samples_of(read_for(port, dec, 0.05))]
        gaps = [i for i in range(1, len(counters)) if counters[i] - counters[i - 1] != 1]
        if gaps and len(counters) - gaps[0] >= after:
            break
    return counters


def test_drop_and_silence_leave_counter_gaps(rig):
    emu, port, _ = rig
    dec = FrameDecoder()
    before = samples_of(read_for(port, dec, 0.1))
    emu.inject(Fault("drop", 4))
    counters = counters_until_gap(port, dec, before[-1].counter)
    assert [b - a for a, b in zip(counters, counters[1:], strict=False) if b - a != 1] == [5]
    emu.inject(Fault("silence", 0.3))
    t_fault = time.monotonic()
    arrivals = [(0.0, counters[-1])]  # the last counter before the fault, as for the drop
    # Read until the gap and some samples after it are in (a starved emulator thread may apply
    # the fault late); give up after 3 s.
    while time.monotonic() < t_fault + 3.0:
        for f in dec.feed(port.read(port.in_waiting or 1)):
            msg = parse_frame(f)
            if isinstance(msg, Sample):
                arrivals.append((time.monotonic() - t_fault, msg.counter))
        counters = [c for _, c in arrivals]
        jumped = [i for i in range(1, len(counters)) if counters[i] - counters[i - 1] > 1]
        if jumped and len(counters) - jumped[0] >= 10:
            break
    # The rig's counter runs on through the silence: the jump is the silence in rig time.
    # (Arrival times are not asserted: on a loaded machine the reader gets frames in bursts.)
    jumps = [b[1] - a[1] for a, b in zip(arrivals, arrivals[1:], strict=False)]
    assert max(jumps) == pytest.approx(0.3 * RATE_HZ, abs=0.1 * RATE_HZ)
    assert sorted(jumps)[-2] == 1  # one gap only, every other sample contiguous
    assert dec.stats.discarded_bytes == 0


def test_unplug_removes_device_and_brings_it_back(rig):
    emu, port, _ = rig
    dec = FrameDecoder()
    read_for(port, dec, 0.1)
    first = os.path.realpath(emu.link_path)
    emu.inject(Fault("unplug", 0.5))
    t_fault = time.monotonic()
    with pytest.raises(serial.SerialException):
        while time.monotonic() - t_fault < 1.0:
            dec.feed(port.read(port.in_waiting or 1))
    assert not os.path.lexists(emu.link_path)
    port.close()
    while not os.path.exists(emu.link_path):
        assert time.monotonic() - t_fault < 1.5
        time.sleep(0.01)
    assert time.monotonic() - t_fault >= 0.45  # not back before the unplug time (late is load)
    port2 = serial.Serial(str(emu.link_path), 115200, timeout=0.02)
    try:
        msgs = samples_of(read_for(port2, FrameDecoder(), 0.2))
    finally:
        port2.close()
    assert len(msgs) >= 0.1 * RATE_HZ
    assert first.startswith("/dev/pts/")


def test_cli_prints_path_takes_faults_and_exits_on_sigint(tmp_path):
    log = tmp_path / "cli.csv"
    proc = subprocess.Popen(
        [sys.executable, "-m", "ipmc_driver.emulator", "--rate-hz", "100", "--events",
         "--log", str(log)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )
    try:
        path = proc.stdout.readline().strip()
        assert os.path.exists(path) and os.path.realpath(path).startswith("/dev/pts/")
        proc.stdin.write("drop 2\nnonsense\n")
        proc.stdin.flush()
        port = serial.Serial(path, 115200, timeout=0.02)
        try:
            read_for(port, FrameDecoder(), 0.3)
        finally:
            port.close()
        line = proc.stdout.readline()
        assert line.split()[1:] == ["fault", "drop", "2"]
    finally:
        proc.send_signal(signal.SIGINT)
        t0 = time.monotonic()
        try:
            rc = proc.wait(2.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            pytest.fail("rig emulator did not exit within 2 s of SIGINT")
    assert rc == 0 and time.monotonic() - t0 < 2.0
    assert not os.path.lexists(path)
    with open(log) as f:
        rows = list(csv.DictReader(f))
    assert [int(r["counter"]) for r in rows] == list(range(len(rows)))
    assert sum(r["sent"] == "0" for r in rows) == 2


def test_watchdog_zeroes_setpoint_without_valid_commands(tmp_path):
    with running_rig(tmp_path, RIG_WATCHDOG_S) as (emu, port, _):
        dec = FrameDecoder()
        read_for(port, dec, 0.05)
        good = encode_message(SetVoltage(1.5), seq=9)
        port.write(good)
        damaged = good[:-1] + bytes([good[-1] ^ 0xFF])  # a SET_VOLTAGE with a bad CRC
        samples: list[Sample] = []
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            port.write(damaged)  # does not feed the watchdog
            samples += samples_of(read_for(port, dec, 0.05))
            held = [s for s in samples if s.command_seq == 9]
            if held and held[-1].applied_v == 0.0:
                break
        applied = [s.applied_v for s in samples if s.command_seq == 9]
        assert applied and applied[-1] == 0.0, "the rig kept the voltage without commands"
        at_command = [v for v in applied if v == pytest.approx(1.5, abs=1e-3)]
        # Not before the watchdog period (in rig time: one sample per period).
        assert len(at_command) >= RIG_WATCHDOG_S * RATE_HZ - 2
        assert applied == at_command + [0.0] * (len(applied) - len(at_command))
        assert emu.watchdog_trips == 1
        # A valid command applies again at once.
        port.write(encode_message(SetVoltage(-1.0), seq=10))
        again = [s for s in samples_of(read_for(port, dec, 0.1)) if s.command_seq == 10]
        assert again and again[0].applied_v == pytest.approx(-1.0, abs=1e-3)


def test_watchdog_held_off_by_repeated_commands(tmp_path):
    # Half a second: this test's own scheduling may delay a frame by much more than the
    # protocol's 50 ms keepalive period without the rig tripping.
    with running_rig(tmp_path, 0.5) as (emu, port, _):
        dec = FrameDecoder()
        samples: list[Sample] = []
        for seq in range(1, 31):
            port.write(encode_message(SetVoltage(1.0), seq=seq))
            samples += samples_of(read_for(port, dec, 0.05))
        applied = [s.applied_v for s in samples if s.command_seq > 0]
        assert len(applied) > 100
        assert applied == pytest.approx([1.0] * len(applied), abs=1e-3)
        assert emu.watchdog_trips == 0
