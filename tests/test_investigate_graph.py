"""``ipmc investigate --sim`` through the lock-step graph (``ipmc bringup --experiment``): a round
recorded as a bag and diagnosed, and Ctrl-C: the graph stopped with its last command 0 V, the
record readable, the report of what finished written. Real processes over DDS on the test
domain."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

VENV_BIN = Path(sys.executable).parent


def _investigate(processes, report: Path, *argv: str):
    return processes.start("investigate", [str(VENV_BIN / "ipmc"), "investigate", "--sim",
                                           "--report", str(report), *argv])


@pytest.mark.timeout(240)
def test_a_round_through_the_lockstep_graph_is_recorded_and_diagnosed(processes, tmp_path):
    from ipmc_driver.dataio import load_record

    report = tmp_path / "inv"
    proc = _investigate(processes, report, "--first-input", "mixed", "--first-seconds", "60",
                        "--budget-min", "1.5")
    proc.wait(timeout=200)
    out = processes.log("investigate")
    assert proc.returncode == 0, out
    summary = json.loads((report / "summary.json").read_text())
    first = summary["rounds"][0]
    assert first["record"] == str(report / "round_1" / "bag")
    record = load_record(report / "round_1" / "bag")
    assert 59.0 < record.t_s[-1] - record.t_s[0] < 61.0
    assert "lock-step graph" in summary["runner"]
    assert summary["effects_found"] == [] and len(summary["rounds"]) == 1, out
    assert summary["stopped_because"].startswith(("budget", "nothing undecided")), out
    assert "round 1: recorded" in out and (report / "report.md").is_file()


@pytest.mark.timeout(120)
def test_ctrl_c_stops_the_graph_at_0_v_and_keeps_the_record(commands_v, processes, tmp_path):
    from ipmc_driver.dataio import load_record

    report = tmp_path / "inv"
    proc = _investigate(processes, report, "--plant-effect", "creep")
    bag = report / "round_1" / "bag"
    log = report / "round_1" / "bringup.log"
    deadline = time.monotonic() + 90.0

    def recorded() -> int:   # samples the last progress line reports (a loaded machine: few)
        text = log.read_text(errors="replace") if log.exists() else ""
        counts = re.findall(r"(\d+) samples", text)
        return int(counts[-1]) if counts and "% played" in text else 0

    while recorded() < 200:
        assert time.monotonic() < deadline, processes.log("investigate")
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=45)
    except subprocess.TimeoutExpired:
        pytest.fail(f"investigate still running 45 s after SIGINT:\n"
                    f"{processes.log('investigate')}")
    out = processes.log("investigate")
    assert proc.returncode == 130, out
    summary = json.loads((report / "summary.json").read_text())
    assert summary["interrupted"] and summary["rounds"] == []
    assert summary["stopped_because"].startswith("interrupted during round 1")
    assert np.array(commands_v(bag))[-1] == 0.0
    assert len(load_record(bag)) > 100


@pytest.mark.timeout(150)
def test_a_round_on_the_emulated_rig_through_the_driver(processes, rig_emulator, tmp_path):
    """--rig on the rig emulator's pty: the driver streams the record in real time."""
    _, port = rig_emulator
    report = tmp_path / "inv"
    proc = processes.start("investigate", [
        str(VENV_BIN / "ipmc"), "investigate", "--rig", port, "--first-seconds", "30",
        "--budget-min", "0.6", "--report", str(report)])
    proc.wait(timeout=120)
    out = processes.log("investigate")
    assert proc.returncode == 0, out
    summary = json.loads((report / "summary.json").read_text())
    assert summary["runner"] == f"the rig on {port} through the driver"
    assert len(summary["rounds"]) == 1 and summary["stopped_because"].startswith("budget"), out
    assert 29.0 < summary["rounds"][0]["recorded_s"] < 31.0
