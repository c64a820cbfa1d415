"""The README's "session on the bench", run as written against the rig emulator, then the day-2
checks on emulators with creep and with drift. Prints each step's wall time and the figures:
hybrid sine tracking RMSE on the rig, the constant hold's RMSE after 2 s, what day 2 names with
the emulator's creep (its tau and 95 % interval) and with its drift, whether the feedforward with
the creep undone lowers the hold's error, what a clean day names, and the recorded minutes.

    .venv/bin/python benchmarks/bench_session.py [--short] [--no-day2] [--workdir DIR]

The commands come from README.md's bash block under "## A session on the bench", continuation
lines joined, each run verbatim except: ``ipmc rig-emulator`` is started here in the background
and its pty replaces ``/dev/ttyUSB0``; ``--short`` sets ``--seconds`` on every bringup (open loop
60 s, closed loop 20 s) and skips ``ipmc investigate``; the full mode keeps the README's lengths
and gives ``ipmc investigate`` ``--budget-min 2``. A command whose input file does not exist (the
next experiment when the diagnosis proposed none) is skipped with the reason printed. Everything
started here is stopped on exit, Ctrl-C or failure. Not part of the pass/fail suite.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SECTION = "## A session on the bench"
README_PORT = "/dev/ttyUSB0"
IPMC = str(Path(sys.executable).parent / "ipmc")
SHORT_OPEN_LOOP_S = 60.0
SHORT_CLOSED_LOOP_S = 20.0
FULL_EXCITE_S = 240.0          # bringup's default excitation length
INVESTIGATE_BUDGET_MIN = 2.0
STOP_GRACE_S = 15.0
COMMAND_MARGIN_S = 600.0       # beyond a command's recorded time: fits, start and stop
GOAL_SINE_MM = 0.02
GOAL_HOLD_MM = 0.05
GOAL_RECORDED_MIN = 15.0
EMULATOR_CREEP_TAU_S = 20.0
PATH_OPTIONS = ("--experiment", "--model", "--data", "--effects-from")


@dataclass
class Step:
    """One command as run (or skipped): its argv, output, wall time and exit code."""

    label: str
    argv: list[str]
    wall_s: float = 0.0
    returncode: int | None = None
    output: str = ""
    skipped: str = ""           # the reason, when not run

    @property
    def ran(self) -> bool:
        return not self.skipped


@dataclass
class Bench:
    """Where the commands run and what they started; :meth:`stop_all` stops it all."""

    workdir: Path
    short: bool
    env: dict
    procs: list[subprocess.Popen] = field(default_factory=list)
    steps: list[Step] = field(default_factory=list)
    port: str = ""


def readme_commands(readme: Path = README) -> list[str]:
    """The commands of the bash block under the bench section, continuation lines joined and
    comments removed, in order."""
    text = readme.read_text()
    start = text.index(SECTION)
    block = re.search(r"```bash\n(.*?)```", text[start:], re.DOTALL)
    if block is None:
        raise ValueError(f"{readme}: no ```bash block under {SECTION!r}")
    commands, pending = [], ""
    for line in block.group(1).splitlines():
        joined = line.rstrip().endswith("\\") and not line.lstrip().startswith("#")
        code = shlex.join(shlex.split(line.rstrip().removesuffix("\\"), comments=True))
        pending = f"{pending} {code}".strip()
        if not joined and pending:
            commands.append(pending)
            pending = ""
    if pending:
        commands.append(pending)
    return commands


def child_env() -> dict:
    """The environment of the commands: unbuffered, one BLAS thread, DDS on localhost in a
    domain of this process unless one is set."""
    env = dict(os.environ)
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    env.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def option(argv: list[str], name: str) -> str | None:
    """The value after ``name`` in ``argv`` (``--name=value`` too), or None."""
    for i, arg in enumerate(argv):
        if arg == name and i + 1 < len(argv):
            return argv[i + 1]
        if arg.startswith(name + "="):
            return arg.split("=", 1)[1]
    return None


def set_option(argv: list[str], name: str, value: str) -> list[str]:
    """``argv`` with ``name value`` overridden or appended."""
    out = [a for a in argv if not a.startswith(name + "=")]
    if name in out:
        out[out.index(name) + 1] = value
        return out
    return out + [name, value]


def adapt(argv: list[str], bench: Bench) -> tuple[list[str], str]:
    """The command as run here (the emulator's pty, short lengths) and, when it cannot run,
    why."""
    argv = [IPMC if a == "ipmc" else bench.port if a == README_PORT else a for a in argv]
    sub = argv[1] if len(argv) > 1 else ""
    for name in PATH_OPTIONS:
        value = option(argv, name)
        if value is not None and not (bench.workdir / value).exists():
            return argv, f"{name} {value} does not exist (nothing was written there)"
    if sub == "bringup" and bench.short:
        open_loop = option(argv, "--excite") or option(argv, "--experiment")
        argv = set_option(argv, "--seconds",
                          f"{SHORT_OPEN_LOOP_S if open_loop else SHORT_CLOSED_LOOP_S:g}")
    if sub == "investigate":
        if bench.short:
            return argv, "ipmc investigate is left out in --short mode (minutes of recording)"
        argv = set_option(argv, "--budget-min", f"{INVESTIGATE_BUDGET_MIN:g}")
    return argv, ""


def start_emulator(bench: Bench, argv: list[str], effects: str = "") -> Step:
    """Start ``ipmc rig-emulator`` in the background; its first stdout line is the pty."""
    argv = [IPMC if a == "ipmc" else a for a in argv]
    if effects:
        argv = set_option(argv, "--effects", effects)
    step = Step(" ".join(argv[1:]), argv)
    t0 = time.monotonic()
    proc = subprocess.Popen(argv, cwd=bench.workdir, env=bench.env, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, start_new_session=True)
    bench.procs.append(proc)
    bench.port = proc.stdout.readline().strip()
    step.wall_s = time.monotonic() - t0
    if not bench.port:
        raise RuntimeError(f"{' '.join(argv)} printed no device path (exit {proc.poll()})")
    step.output = f"device {bench.port}"
    step.returncode = 0
    return step


def stop(proc: subprocess.Popen, grace_s: float = STOP_GRACE_S) -> None:
    """SIGINT to the process group, SIGKILL after ``grace_s``."""
    if proc.poll() is not None:
        return
    for sig, wait_s in ((signal.SIGINT, grace_s), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=wait_s)
            return
        except subprocess.TimeoutExpired:
            continue


def stop_all(bench: Bench) -> None:
    """Stop every process this script started, newest first."""
    while bench.procs:
        stop(bench.procs.pop())


def expected_s(argv: list[str]) -> float:
    """The recorded time a command asks for (0 for those that record nothing)."""
    if len(argv) < 2 or argv[1] not in ("bringup", "investigate"):
        return 0.0
    if argv[1] == "investigate":
        return float(option(argv, "--budget-min") or 20) * 60.0 + 120.0
    seconds = option(argv, "--seconds")
    return float(seconds) if seconds else FULL_EXCITE_S


def run_command(bench: Bench, argv: list[str], label: str) -> Step:
    """Run one command in the workdir to its end; its output is kept in logs/ and the step."""
    step = Step(label, argv)
    log_path = bench.workdir / "logs" / f"{len(bench.steps):02d}_{argv[1]}.log"
    log_path.parent.mkdir(exist_ok=True)
    t0 = time.monotonic()
    with log_path.open("w") as log:
        proc = subprocess.Popen(argv, cwd=bench.workdir, env=bench.env, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
        bench.procs.append(proc)
        try:
            proc.wait(timeout=expected_s(argv) + COMMAND_MARGIN_S)
        except subprocess.TimeoutExpired:
            print(f"  timed out after {time.monotonic() - t0:.0f} s; stopping it", flush=True)
        finally:
            stop(proc)
            bench.procs.remove(proc)
    step.wall_s = time.monotonic() - t0
    step.returncode = proc.returncode
    step.output = log_path.read_text()
    return step


def tell(step: Step, tail_lines: int = 4) -> None:
    """Print a step: its command, wall time and exit code, the load average (a loaded machine
    starves the real-time loop), and its last lines."""
    shown = " ".join(shlex.quote(a) for a in [("ipmc" if a == IPMC else a) for a in step.argv])
    if step.skipped:
        print(f"skipped  {shown}\n  reason: {step.skipped}", flush=True)
        return
    print(f"{step.wall_s:7.1f} s  {shown}  (exit {step.returncode})", flush=True)
    print(f"    load average after it: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores",
          flush=True)
    lines = [ln for ln in step.output.splitlines()
             if ln.strip() and not re.match(r"\s*[\d.]+ s: ", ln)]
    for line in lines[-tail_lines:]:
        print(f"    {line}", flush=True)


def run_step(bench: Bench, command: str, effects: str = "", label: str = "") -> Step:
    """Run (or skip) one README command on the bench; a failure raises after printing."""
    argv = shlex.split(command)
    if argv[1:2] == ["rig-emulator"]:
        stop_all(bench)
        step = start_emulator(bench, argv, effects)
    else:
        argv, reason = adapt(argv, bench)
        step = (Step(label or command, argv, skipped=reason) if reason
                else run_command(bench, argv, label or command))
    bench.steps.append(step)
    tell(step)
    if step.returncode not in (None, 0):
        raise RuntimeError(f"exit {step.returncode}: {command}")
    return step


def run_readme(bench: Bench, commands: list[str]) -> list[Step]:
    """Every README command in order on a clean emulator."""
    print(f"README {SECTION[3:]!r}: {len(commands)} commands", flush=True)
    return [run_step(bench, command) for command in commands]


def tracking_rmse_mm(step: Step | None) -> float | None:
    """The tracking RMSE of bringup's summary line."""
    if step is None or not step.ran:
        return None
    found = re.search(r"^tracking RMSE ([\d.]+) mm over", step.output, re.MULTILINE)
    return float(found.group(1)) if found else None


def recorded_s(step: Step) -> float:
    """Seconds a step recorded: bringup's summary or investigate's final line."""
    found = re.search(r"summary: ([\d.]+) s, \d+ samples recorded", step.output)
    if found:
        return float(found.group(1))
    found = re.search(r"([\d.]+) min recorded", step.output)
    return float(found.group(1)) * 60.0 if found else 0.0


def find_command(commands: list[str], *needles: str) -> str | None:
    """The first README command holding every one of ``needles`` (tokens)."""
    for command in commands:
        argv = shlex.split(command)
        if all(n in argv for n in needles):
            return command
    return None


def retarget(command: str, **options: str) -> str:
    """``command`` with options overridden: ``record="day2_creep"`` sets ``--record``."""
    argv = shlex.split(command)
    for key, value in options.items():
        argv = set_option(argv, "--" + key.replace("_", "-"), value)
    return shlex.join(argv)


def record_day2(bench: Bench, commands: list[str], name: str) -> Step | None:
    """Day 2's record under ``name``: the README's next experiment when it exists, otherwise
    the README's day-1 excitation again."""
    experiment = find_command(commands, "--record", "day2")
    if experiment and (bench.workdir / (option(shlex.split(experiment), "--experiment")
                                        or "-")).exists():
        return run_step(bench, retarget(experiment, record=name))
    excite = find_command(commands, "--excite", "--record")
    print(f"  no next experiment to play; day 2 is the day-1 excitation again: {excite}",
          flush=True)
    return run_step(bench, retarget(excite, record=name)) if excite else None


def run_day2(bench: Bench, commands: list[str], effects: str) -> dict:
    """Day 2 on an emulator with ``effects``: record, then the README's day-2 diagnosis with
    day 1's model. Returns the diagnosis's summary.json (empty when it did not run)."""
    emulator = find_command(commands, "rig-emulator") or "ipmc rig-emulator"
    print(f"\nday 2, emulator with {effects}", flush=True)
    run_step(bench, emulator, effects=effects)
    name = f"day2_{effects}"
    record_day2(bench, commands, name)
    diagnose = find_command(commands, "diagnose", "--model") or (
        "ipmc diagnose --data day2 --model day1_report/model_after.json --report day2_report")
    step = run_step(bench, retarget(diagnose, data=name, report=f"{name}_report"))
    summary = bench.workdir / f"{name}_report" / "summary.json"
    return json.loads(summary.read_text()) if step.ran and summary.exists() else {}


def named_effects(summary: dict) -> list[str]:
    """What a diagnosis names: the effects it accepted and those it left undecided."""
    names = list(summary.get("effects_found", []))
    names += [f"{c['name']} undecided" for c in summary.get("candidates", [])
              if "undecided" in c.get("reason", "")]
    names += [f"{name} undecided" for name in summary.get("undecided", [])]  # investigate's
    return names


def creep_candidate(summary: dict) -> dict:
    """The creep candidate of a diagnosis, accepted or not (empty when absent)."""
    return next((c for c in summary.get("candidates", []) if c["name"] == "creep"), {})


def creep_params(summary: dict) -> dict:
    """The accepted creep's parameters in the diagnosis (empty when none)."""
    cand = creep_candidate(summary)
    return (cand.get("evidence") or {}).get("params", {}) if cand.get("accepted") else {}


def hold_with_creep_undone(bench: Bench, commands: list[str]) -> tuple[Step | None, Step | None]:
    """On the creep emulator: the README's hold with day 1's feedforward, then with the
    feedforward identified on day 2 with the creep the diagnosis found undone."""
    hold = find_command(commands, "--reference", "constant")
    model_after = "day2_creep_report/model_after.json"
    identify = (f"ipmc identify --data day2_creep --inverse --effects-from {model_after} "
                "--out ff_creep.json")
    if hold is None:
        print("  the README has no constant hold: no comparison", flush=True)
        return None, None
    before = run_step(bench, retarget(hold, record="day2_creep_hold"))
    summary = bench.workdir / "day2_creep_report" / "summary.json"
    if not summary.exists() or not creep_params(json.loads(summary.read_text())):
        bench.steps.append(Step(identify, shlex.split(identify),
                                skipped="day 2's diagnosis named no creep to undo"))
        tell(bench.steps[-1])
        return before, None
    run_step(bench, identify)
    after = run_step(bench, retarget(hold, model="ff_creep.json", record="day2_creep_hold_ffc"))
    return before, after


def verdict(ok: bool | None) -> str:
    return "n/a (not run)" if ok is None else "met" if ok else "NOT met"


def readme_step(steps: list[Step], *needles: str) -> Step | None:
    """The README step whose argv holds every one of ``needles``."""
    return next((s for s in steps if all(n in s.argv for n in needles)), None)


def bag_tracking(bag: Path, settle_s: float = 2.0) -> str:
    """From a closed-loop bag: when the first feedforward came (s after the first sample) and
    the tracking RMSE from it + ``settle_s`` to the last nonzero voltage, the reference
    interpolated at the displacement's stamps."""
    import numpy as np

    from ipmc_driver.dataio import DataError, read_stamped_series

    point, vector = "geometry_msgs/msg/PointStamped", "geometry_msgs/msg/Vector3Stamped"
    try:
        s = read_stamped_series(bag, {"/ipmc/displacement": point, "/ipmc/reference": point,
                                      "/ipmc/voltage": vector, "/ipmc/feedforward": vector})
    except DataError as exc:
        return f"bag not read ({exc})"
    stamps_ns = np.array(sorted(s["/ipmc/displacement"]))
    ref_ns = np.array(sorted(s["/ipmc/reference"]))
    ff_ns = min(s["/ipmc/feedforward"], default=None)
    commands = [k for k, v in s["/ipmc/voltage"].items() if v != 0.0]
    if ff_ns is None or not commands or ref_ns.size == 0:
        return "no feedforward, reference or voltage in the bag"
    y_mm = np.array([s["/ipmc/displacement"][k] for k in stamps_ns]) * 1e3
    r_mm = np.interp(stamps_ns, ref_ns, [s["/ipmc/reference"][k] * 1e3 for k in ref_ns])
    window = (stamps_ns > ff_ns + settle_s * 1e9) & (stamps_ns <= max(commands))
    if not window.any():
        return f"feedforward from {(ff_ns - stamps_ns[0]) / 1e9:.1f} s: no samples after it"
    rmse_mm = float(np.sqrt(np.mean((y_mm - r_mm)[window] ** 2)))
    return (f"feedforward from {(ff_ns - stamps_ns[0]) / 1e9:.1f} s; RMSE {rmse_mm:.4f} mm "
            f"from {settle_s:g} s after it to the last voltage ({window.sum()} samples)")


def report_tracking(bench: Bench, readme_steps: list[Step]) -> None:
    """The README's closed-loop figures against their goals: bringup's summary and, from the
    bag, the error once the feedforward runs."""
    for what, kind, goal in (("hybrid sine tracking RMSE on the rig", "sine", GOAL_SINE_MM),
                             ("constant hold RMSE after 2 s", "constant", GOAL_HOLD_MM)):
        step = readme_step(readme_steps, "--reference", kind)
        rmse = tracking_rmse_mm(step)
        shown = "none printed" if rmse is None else f"{rmse:.4f} mm"
        print(f"{what}: {shown} (goal <= {goal} mm): "
              f"{verdict(None if rmse is None else rmse <= goal)}")
        if step is not None and step.ran:
            print(f"  bag: {bag_tracking(bench.workdir / option(step.argv, '--record'))}")


def rounded(values: list[float] | None, digits: int) -> list[float] | None:
    return None if values is None else [round(float(v), digits) for v in values]


def report_creep(summary: dict) -> None:
    """Day 2 with creep: what is named, the creep candidate's parameters and intervals
    (accepted or not), and whether creep is named with the emulator's tau in its interval."""
    cand = creep_candidate(summary)
    p = (cand.get("evidence") or {}).get("params", {})
    print(f"day 2 with creep names: {named_effects(summary) or 'nothing'}")
    if cand:
        print(f"  creep candidate {cand.get('outcome')}: {cand.get('reason')}")
    tau_ci = p.get("tau_ci_s")
    if p:
        print(f"  creep tau {p.get('tau_s', float('nan')):.1f} s, 95 % interval "
              f"{rounded(tau_ci, 1)} s; gain {p.get('gain_mm_per_v', float('nan')):.4f} mm/V, "
              f"interval {rounded(p.get('gain_ci_mm_per_v'), 4)}; taus "
              f"{rounded(p.get('taus_s'), 1)} s, gains {rounded(p.get('gains_mm_per_v'), 4)} mm/V")
    tau_ok = bool(tau_ci) and tau_ci[0] <= EMULATOR_CREEP_TAU_S <= tau_ci[1]
    print(f"  creep named, its interval holding the emulator's tau {EMULATOR_CREEP_TAU_S:g} s: "
          f"{verdict(bool(cand.get('accepted')) and tau_ok)} (interval holds it: "
          f"{'yes' if tau_ok else 'no'})")


def report_day2(creep: dict, drift: dict, holds: tuple[Step | None, Step | None]) -> None:
    """Day 2's figures: creep named with tau in its interval, the hold with the creep undone,
    drift named."""
    if creep:
        report_creep(creep)
    before, after = (tracking_rmse_mm(s) for s in holds)
    if before is not None:
        shown = "not run" if after is None else f"{after:.4f} mm"
        print(f"hold on the creep emulator: day 1's feedforward {before:.4f} mm, with the creep "
              f"undone {shown}: lower {verdict(None if after is None else after < before)}")
    if drift:
        found = "drift" in drift.get("effects_found", [])
        print(f"day 2 with drift names: {named_effects(drift) or 'nothing'}; drift named: "
              f"{verdict(found)}")


def report_clean(workdir: Path) -> None:
    """What the clean days' diagnoses and the investigation on the clean emulator name (goal:
    nothing, in the data or otherwise)."""
    for report in ("day1_report", "day2_report", "inv"):
        path = workdir / report / "summary.json"
        if not path.exists():
            print(f"clean {report}: not written")
            continue
        names = named_effects(json.loads(path.read_text()))
        found = [n for n in names if not n.endswith(" undecided")]
        undecided = [n for n in names if n.endswith(" undecided")]
        print(f"clean {report}: effects found {found or 'none'}: {verdict(not found)}; "
              f"left undecided (untested, not claimed): {undecided or 'none'}")


def report_time(readme_steps: list[Step], all_steps: list[Step]) -> None:
    """Recorded minutes of the README's commands and of everything, and the wall time."""
    readme_min = sum(recorded_s(s) for s in readme_steps) / 60.0
    all_min = sum(recorded_s(s) for s in all_steps) / 60.0
    wall_min = sum(s.wall_s for s in all_steps) / 60.0
    print(f"recorded: README commands {readme_min:.1f} min (goal <= {GOAL_RECORDED_MIN:g} min: "
          f"{verdict(readme_min <= GOAL_RECORDED_MIN)}); with the day-2 checks {all_min:.1f} "
          f"min; wall time of the steps {wall_min:.1f} min")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--short", action="store_true",
                   help=f"bringups of {SHORT_OPEN_LOOP_S:g} s open loop, "
                        f"{SHORT_CLOSED_LOOP_S:g} s closed loop; no ipmc investigate")
    p.add_argument("--no-day2", action="store_true",
                   help="the README's commands only (no creep and drift days)")
    p.add_argument("--workdir", type=Path, help="folder to run in (default: a new temp folder)")
    p.add_argument("--readme", type=Path, default=README, help="README to take the block from")
    return p.parse_args(argv)


def run_all(bench: Bench, commands: list[str], day2: bool) -> None:
    """The README's commands, then the day-2 checks, then the figures."""
    readme_steps = run_readme(bench, commands)
    creep, drift, holds = {}, {}, (None, None)
    if day2:
        creep = run_day2(bench, commands, "creep")
        if creep:
            holds = hold_with_creep_undone(bench, commands)
        drift = run_day2(bench, commands, "drift")
    stop_all(bench)
    print("\nfigures")
    report_tracking(bench, readme_steps)
    report_day2(creep, drift, holds)
    report_clean(bench.workdir)
    report_time(readme_steps, bench.steps)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    commands = readme_commands(args.readme)
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="ipmc_bench_"))
    workdir.mkdir(parents=True, exist_ok=True)
    bench = Bench(workdir.resolve(), args.short, child_env())
    print(f"working in {bench.workdir} ({'short' if args.short else 'full'} lengths)", flush=True)
    # SIGTERM, and SIGINT even where a shell started this in the background with it ignored,
    # stop everything started here through the KeyboardInterrupt path.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        run_all(bench, commands, not args.no_day2)
    except KeyboardInterrupt:
        print("interrupted: everything started here stopped", flush=True)
        return 130
    except RuntimeError as exc:
        print(f"failed: {exc}; logs in {bench.workdir / 'logs'}", flush=True)
        return 1
    finally:
        stop_all(bench)
    return 0


if __name__ == "__main__":
    sys.exit(main())
