"""The README's "session on the bench" runs as written against the rig emulator: the commands
come from README.md's bash block (benchmarks/bench_session.py), each runs or is skipped with a
stated reason, identify writes its models, and the closed-loop bringups print a tracking RMSE."""

from __future__ import annotations

import importlib.util
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "bench_session.py"


def _bench_session():
    spec = importlib.util.spec_from_file_location("bench_session", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def bench():
    return _bench_session()


@pytest.fixture(scope="module")
def short_run(tmp_path_factory, ros_env):
    """bench_session.py --short on the README's commands only: its output and workdir."""
    workdir = tmp_path_factory.mktemp("bench")
    run = subprocess.run([sys.executable, str(SCRIPT), "--short", "--no-day2", "--workdir",
                          str(workdir)], env=ros_env, capture_output=True, text=True,
                         timeout=480)
    return run, workdir


def test_readme_block_gives_the_commands_in_order(bench):
    commands = bench.readme_commands()
    subcommands = [shlex.split(c)[1] for c in commands]
    assert subcommands[0] == "rig-emulator"
    assert {"bringup", "identify", "diagnose"} <= set(subcommands)
    # continuation lines are joined: the sine bringup carries its last line's options
    sine = next(c for c in commands if "sine" in shlex.split(c))
    assert "--record day1_sine" in sine and "\\" not in sine and "#" not in sine


def test_a_command_removed_from_the_readme_no_longer_runs(bench, tmp_path):
    text = (ROOT / "README.md").read_text()
    line = next(ln for ln in text.splitlines() if ln.startswith("ipmc identify --data day1 --o"))
    edited = tmp_path / "README.md"
    edited.write_text(text.replace(line + "\n", ""))
    before, after = bench.readme_commands(), bench.readme_commands(edited)
    assert len(after) == len(before) - 1
    assert "ipmc identify --data day1 --out fwd.json" in before
    assert "ipmc identify --data day1 --out fwd.json" not in after


def test_short_mode_overrides_lengths_and_replaces_the_port(bench, tmp_path):
    b = bench.Bench(tmp_path, True, {}, port="/tmp/pty0")
    argv, reason = bench.adapt(shlex.split(
        "ipmc bringup --rig /dev/ttyUSB0 --model ff.json --seconds 60 --record x"), b)
    assert reason == "--model ff.json does not exist (nothing was written there)"
    (tmp_path / "ff.json").write_text("{}")
    argv, reason = bench.adapt(shlex.split(
        "ipmc bringup --rig /dev/ttyUSB0 --model ff.json --seconds 60 --record x"), b)
    assert not reason and "/tmp/pty0" in argv and argv[argv.index("--seconds") + 1] == "20"
    argv, _ = bench.adapt(shlex.split("ipmc bringup --rig /dev/ttyUSB0 --excite mixed"), b)
    assert argv[-2:] == ["--seconds", "60"]


def test_every_readme_command_ran_or_was_skipped_with_a_reason(bench, short_run):
    run, _ = short_run
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    lines = run.stdout.splitlines()
    told = [ln for ln in lines if re.match(r"\s*[\d.]+ s  ipmc |skipped  ipmc ", ln)]
    commands = bench.readme_commands()
    assert len(told) == len(commands), "\n".join(told)
    for command, line in zip(commands, told, strict=True):
        sub = shlex.split(command)[1]
        assert f"ipmc {sub}" in line
        if line.startswith("skipped"):
            reason = lines[lines.index(line) + 1]
            assert reason.strip().startswith("reason: ") and len(reason.strip()) > 12
        else:
            assert line.endswith("(exit 0)"), line
    assert any("ipmc investigate" in ln and ln.startswith("skipped") for ln in told)


def test_identify_wrote_models_and_closed_loop_printed_rmse(short_run):
    run, workdir = short_run
    for name in ("fwd", "ff"):
        assert (workdir / f"{name}.json").stat().st_size > 0
        assert (workdir / f"{name}.npz").exists()
    rmses = re.findall(r"^\s+tracking RMSE ([\d.]+) mm over \d+ samples", run.stdout, re.M)
    assert len(rmses) == 2, run.stdout[-3000:]
    assert all(0.0 < float(r) < 3.0 for r in rmses)
    assert re.search(r"hybrid sine tracking RMSE on the rig: [\d.]+ mm", run.stdout)
    assert re.search(r"constant hold RMSE after 2 s: [\d.]+ mm", run.stdout)
    assert re.search(r"recorded: README commands [\d.]+ min", run.stdout)
    assert (workdir / "day1_report" / "summary.json").exists()
