"""``ipmc bringup`` for a session on the bench: an open-loop excitation recorded and stopped at
its end, references a user sets (refused in one sentence when out of reach), and the console's
progress and summary. Real processes over DDS on the session's domain."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ipmc_control.excitation import make_excitation

rclpy = pytest.importorskip("rclpy")

VENV_BIN = Path(sys.executable).parent
RUN_TIMEOUT_S = 50.0


def _bringup(processes, name: str, *argv: str) -> str:
    """Run ``ipmc bringup`` to its end; its console output (the test fails if it hangs)."""
    proc = processes.start(name, [str(VENV_BIN / "ipmc"), "bringup", *argv])
    try:
        proc.wait(timeout=RUN_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"bringup still running after {RUN_TIMEOUT_S} s:\n{processes.log(name)}")
    out = processes.log(name)
    assert proc.returncode == 0, out
    return out


def _played(commands_v: np.ndarray, u_v: np.ndarray) -> bool:
    """Whether ``u_v`` appears whole and in order in the recorded commands."""
    starts = np.flatnonzero(np.abs(commands_v - u_v[0]) < 1e-9)
    return any(commands_v.size - k >= u_v.size
               and np.allclose(commands_v[k:k + u_v.size], u_v, atol=1e-9) for k in starts)


def test_excite_records_the_excitation_with_its_holds_and_stops_at_its_end(commands_v, processes,
                                                                           tmp_path):
    from ipmc_driver.dataio import load_record
    from ipmc_model.residuals import find_holds

    bag = tmp_path / "day1"
    out = _bringup(processes, "bringup", "--sim", "--excite", "steps", "--seconds", "12",
                   "--hold-s", "3", "--record", str(bag))
    exc = make_excitation("steps", hold_s=3.0, seconds=12.0)
    assert _played(np.array(commands_v(bag)), exc.u_v), out
    record = load_record(bag)                 # what ipmc identify --data reads
    holds = find_holds(record.u_v, 0.01, 2.5)
    assert len(holds) >= 3, out
    assert {round(float(record.u_v[a]), 2) for a, _ in holds} >= {
        round(float(v), 2) for v in exc.u_v[::300][:3]}
    assert "excitation finished" in out
    summary = out[out.index("summary:"):]
    assert f"{record.u_v.size} samples recorded in {bag}" in summary, out
    assert f"logs in {tmp_path / 'day1_logs'}" in summary
    assert sorted(p.name for p in (tmp_path / "day1_logs").iterdir()) == [
        "excitation.log", "recorder.log", "sim_plant.log"]


def test_experiment_of_ipmc_diagnose_plays_open_loop_in_lockstep(commands_v, processes, tmp_path):
    from ipmc_model.diagnosis.experiment import Experiment, holds

    u = np.concatenate([holds([1.5, -2.0, 0.5], 4.0, 100.0), np.zeros(200)])
    path = tmp_path / "next_experiment.json"
    path.write_text(json.dumps(Experiment(100.0, 0.7, u, ()).as_dict()))
    bag = tmp_path / "day2"
    out = _bringup(processes, "bringup", "--sim", "--lockstep", "--experiment", str(path),
                   "--record", str(bag))
    assert _played(np.array(commands_v(bag)), u), out
    assert "14 s at 100 Hz" in out and "3 holds" in out
    # lock-step: the record is the excitation, with the plant's first sample before it and
    # the 0 V after it, and nothing more (the plant waits once the excitation has ended)
    from ipmc_driver.dataio import load_record

    record = load_record(bag)
    assert record.u_v.size == u.size + 2, out
    np.testing.assert_allclose(record.u_v[1:-1], u, atol=1e-9)


def test_references_out_of_reach_or_malformed_are_refused_in_one_sentence(ros_env,
                                                                          tmp_path):
    fast = tmp_path / "fast.csv"
    fast.write_text("t,u\n0,0\n0.005,1\n0.01,0\n")
    cases = [
        (["--mode", "pid", "--reference", "constant"], "asks for 4.00 mm"),
        (["--mode", "pid", "--reference", "steps", "--levels-mm", "1,x"],
         "--levels-mm '1,x' is not a number list"),
        (["--mode", "pid", "--reference", "sine", "--value-mm", "1"],
         "--value-mm sets a constant reference"),
        (["--excite", str(fast)], "sampled at 200 Hz but the plant at 100 Hz"),
        (["--excite", "mixed", "--amplitude-v", "3.5"], "<= 3 V"),
        (["--excite", "steps", "--amplitude-mm", "2"], "--amplitude-mm sets the closed loop"),
    ]
    for argv, sentence in cases:
        run = subprocess.run([str(VENV_BIN / "ipmc"), "bringup", "--sim", *argv,
                              "--record", str(tmp_path / "never")], env=ros_env,
                             capture_output=True, text=True, timeout=60)
        assert run.returncode == 1, (argv, run.stdout, run.stderr)
        lines = run.stderr.strip().splitlines()
        assert len(lines) == 1 and sentence in lines[0], (argv, run.stderr)
        assert not (tmp_path / "never").exists() and not (tmp_path / "never_logs").exists()


def test_closed_loop_summary_gives_the_tracking_error_of_the_levels_set(processes,
                                                                         tmp_path):
    bag = tmp_path / "hold"
    out = _bringup(processes, "bringup", "--sim", "--lockstep", "--mode", "pid",
                   "--reference", "steps", "--levels-mm=-1.5,1", "--hold-s", "3",
                   "--seconds", "10", "--record", str(bag))
    assert "reference steps: -1.50..1.00 mm" in out
    summary = out[out.index("summary:"):]
    rmse_mm = float(summary.split("tracking RMSE ")[1].split(" mm")[0])
    assert 0.0 < rmse_mm < 1.0, out
    assert f"logs in {tmp_path / 'hold_logs'}" in summary


def test_launch_files_take_the_reference_options_and_check_them():
    from test_launch_files import LAUNCH_DIR, run_launch_file

    launched = run_launch_file(LAUNCH_DIR / "sim.launch.py", mode="pid", reference="steps",
                               levels_mm="-2,0,1.5", hold_s="4")
    params = launched["reference"][2]
    assert params["levels_mm"] == [-2.0, 0.0, 1.5] and params["hold_s"] == 4.0
    rig = run_launch_file(LAUNCH_DIR / "rig.launch.py", port="/dev/ttyX", mode="pid",
                          reference="sine", amplitude_mm="1.5", frequency_hz="0.2")
    assert rig["reference"][2]["amplitude_mm"] == 1.5
    assert rig["reference"][2]["frequency_hz"] == 0.2
    with pytest.raises(ValueError, match="asks for 4.00 mm"):
        run_launch_file(LAUNCH_DIR / "sim.launch.py", mode="pid", reference="constant",
                        value_mm="4")


def _unplug_during(processes, emu, argv: list[str]) -> str:
    """Run bringup with ``argv``; unplug the emulated rig for 1 s after the first progress
    line; bringup's console output."""
    bringup = processes.start("bringup", [str(VENV_BIN / "ipmc"), "bringup", *argv])
    deadline = time.monotonic() + 30.0
    while "% played" not in processes.log("bringup") and time.monotonic() < deadline:
        time.sleep(0.2)
    emu.stdin.write("unplug 1.0\n")
    emu.stdin.flush()
    bringup.wait(timeout=RUN_TIMEOUT_S)
    out = processes.log("bringup")
    assert bringup.returncode == 0, out
    return out


def test_rig_run_shows_the_link_state_and_its_fault_on_the_console(processes, rig_emulator,
                                                                  tmp_path):
    """Through the rig emulator's pty and the driver: the progress names the link's state, the
    driver's warning of a lost link reaches the console as it happens, the summary counts it."""
    emu, port = rig_emulator
    out = _unplug_during(processes, emu, [
        "--rig", port, "--excite", "steps", "--seconds", "12", "--hold-s", "3",
        "--record", str(tmp_path / "rig")])
    assert "link connected" in out.split("excitation finished")[0]
    assert "[driver] [WARN]" in out and "lost" in out, out
    summary = out[out.index("summary:"):]
    assert "link: 1 faults, state connected" in summary, out
    assert "1 faults" in summary and "0 errors" in summary


@pytest.mark.parametrize("params,sentence", [
    (["-p", "kind:=file", "-p", "path:=/nonexistent/u.csv"], "/nonexistent/u.csv is not a file"),
    (["-p", "amplitude_v:=4.0"], "the amplitude must be > 0 and <= 3 V"),
    (["-p", "kind:=chirp"], "kind"),
])
def test_excitation_node_refuses_bad_parameters_in_one_sentence(ros_env, params, sentence):
    run = subprocess.run([str(VENV_BIN / "excitation"), "--ros-args", *params], env=ros_env,
                         capture_output=True, text=True, timeout=30)
    assert run.returncode == 1, run.stderr
    lines = [ln for ln in run.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("excitation: error:") and sentence in lines[0]
