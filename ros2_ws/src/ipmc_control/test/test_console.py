"""Tests of bringup's console (ipmc_control.console). Plain pytest, no ROS."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ipmc_control.console import LogTail, RunStats, alarm_line, summary_lines, tracking_rmse_mm


def test_log_tail_gives_each_complete_line_once(tmp_path):
    log = tmp_path / "n.log"
    tail = LogTail(log)
    assert tail.read() == []            # no file yet
    log.write_text("[INFO] [1.0] [n]: up\n[WARN] [2.0] [n]: ha")
    assert tail.read() == ["[INFO] [1.0] [n]: up"]
    with log.open("a") as f:
        f.write("lf\n")
    assert tail.read() == ["[WARN] [2.0] [n]: half"]
    assert tail.read() == []


def test_warnings_and_errors_are_picked_and_named():
    assert alarm_line("driver", "[WARN] [1.0] [driver]: link lost\n") == \
        "[driver] [WARN] [1.0] [driver]: link lost"
    assert alarm_line("model_server", "[ERROR] [1.0] [model_server]: x").startswith(
        "[model_server] [ERROR]")
    assert alarm_line("excitation", "excitation: error: u.csv is not a file")
    assert alarm_line("controller", "[INFO] [1.0] [controller]: WARN in text") is None
    stats = RunStats(started_s=0.0)
    for line in ("[driver] [WARN] a", "[driver] [ERROR] b", "[x] x: error: c"):
        stats.on_alarm(line)
    assert (stats.warnings, stats.errors) == (1, 2)


def test_tracking_rmse_interpolates_the_reference_at_the_sample_stamps():
    """Reference and plant run on grids offset by 3 ms (two clocks); the first 2 s are left
    out; a constant error of 0.1 mm gives 0.1 mm."""
    t_ref = np.arange(1000) * 10_000_000
    ref = {int(t): float(np.sin(t * 1e-9)) for t in t_ref}
    disp = {int(t) + 3_000_000: float(np.sin((t + 3_000_000) * 1e-9)) + 0.1 for t in t_ref}
    rmse, n = tracking_rmse_mm(ref, disp)
    assert rmse == pytest.approx(0.1, abs=1e-4)
    assert n == 799          # 2.003 .. 9.983 s within the reference's span, skipping 2 s
    assert tracking_rmse_mm({}, disp) is None


def test_link_faults_count_losses_and_reconnections():
    stats = RunStats(started_s=0.0)
    stats.on_link({"state": "connected", "connections": "1"})
    stats.on_link({"state": "disconnected", "connections": "1"})
    assert stats.link_faults == 1
    stats.on_link({"state": "connected", "connections": "3"})   # a loss between two reports
    assert stats.link_faults == 2


def test_progress_and_summary_name_samples_rate_link_rmse_and_logs():
    stats = RunStats(started_s=100.0)
    for k in range(500):
        stats.on_sample(k * 10_000_000, 0.0, 100.0 + k * 0.01)
    stats.on_link({"state": "connected", "connections": "1", "dropped": "2",
                   "rig_errors": "0"})
    line = stats.progress_line(105.0, total_samples=1000)
    assert line.startswith("   5.0 s: 500 samples, 100.0 per s, link connected, 50 % played")
    lines = summary_lines(stats, elapsed_s=6.0, log_dir=Path("/x/bag_logs"),
                          bag=Path("/x/bag"), samples=512, sample_rate_hz=100.0,
                          rmse=(0.0123, 400), rig=True)
    assert lines[0] == "summary: 6.0 s, 512 samples recorded in /x/bag, 100.0 Hz"
    assert lines[1].startswith("link: 0 faults, state connected, 2 frames dropped")
    assert "tracking RMSE 0.0123 mm over 400 samples" in lines[2]
    assert lines[-1] == "0 warnings, 0 errors; logs in /x/bag_logs"
