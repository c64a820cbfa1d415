"""``ipmc bringup``: start the ipmc-ros graph as processes and stop it cleanly (pip-only launch).

`ros2 launch` is not on PyPI, so this starts the same nodes as ``launch/sim.launch.py`` /
``launch/rig.launch.py`` as child processes of one command and on Ctrl-C (or SIGTERM) stops
them all: SIGINT first, SIGKILL after a grace period.

    ipmc bringup --sim [--lockstep] [--model MODEL.json] [--mode hybrid] [--reference sine]
        [--amplitude-mm 2.5] [--frequency-hz 0.159] [--value-mm 1.5] [--levels-mm=-2,0,2]
        [--hold-s 5] [--range-mm=-4,2] [--path REF.csv]
    ipmc bringup --rig /dev/ttyUSB0 --model MODEL.json --record run1
    ipmc bringup --sim|--rig PORT --excite mixed|steps|random-sine|FILE [--amplitude-v 3]
        [--hold-s 8] [--seconds 240] --record day1
    ipmc bringup --sim|--rig PORT --experiment next_experiment.json --record day2

MODEL is an inverse model (``ipmc identify --inverse``) or a forward model with voltage channels
(``ipmc identify --input-memory-taus ...``), which model_server inverts online. The reference's
span is checked before the start: against where +-3 V settles or swings on the simulated IPMC
(``--sim``) and against the displacements the inverse model was identified on.

``--excite`` (or ``--experiment``) runs open loop: the ``excitation`` node drives the voltage,
one value per sample (``ipmc_control.excitation``: holds at levels spanning the range for creep,
steps for a delay, the whole +-amplitude), no controller and no model server; the run stops at
the excitation's end.

The console shows every node's warnings and errors as they happen (``[node] ...``), a progress
line every 5 s (time, samples, rate, the driver's link state, the tracking error so far) and a
summary at the end (from the bag when recorded). The nodes' logs go to ``BAG_logs`` beside the
bag, else to one temporary folder the summary names.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

GRACE_S = 2.0


def _bin(name: str) -> str:
    """The console script ``name`` next to this interpreter (the venv), else on PATH."""
    local = Path(sys.executable).parent / name
    return str(local) if local.exists() else name


def ros_args(params: dict) -> list[str]:
    """``--ros-args -p k:=v ...`` for a node's parameters (lists as YAML flow sequences)."""
    argv = ["--ros-args"]
    for key, value in params.items():
        if isinstance(value, bool):
            value = "true" if value else "false"
        elif isinstance(value, list | tuple):
            value = "[" + ",".join(str(v) for v in value) + "]"
        argv += ["-p", f"{key}:={value}"]
    return argv


#: The ROS package that installs each node executable (launch files need it).
PACKAGE_OF = {"sim_plant": "ipmc_driver", "driver": "ipmc_driver", "recorder": "ipmc_driver",
              "model_server": "ipmc_model", "controller": "ipmc_control",
              "reference": "ipmc_control", "excitation": "ipmc_control"}


@dataclass
class NodeSpec:
    """One process of the graph: executable name and ROS parameters."""

    name: str
    executable: str
    params: dict = field(default_factory=dict)

    @property
    def package(self) -> str:
        return PACKAGE_OF[self.executable]


class Graph:
    """A set of node processes sharing one environment; stops them all on exit."""

    def __init__(self, env: dict | None = None, log_dir: str | Path | None = None):
        self.env = dict(os.environ if env is None else env)
        self.log_dir = Path(log_dir or tempfile.mkdtemp(prefix="ipmc_graph_"))
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, spec: NodeSpec) -> subprocess.Popen:
        log = open(self.log_dir / f"{spec.name}.log", "w")  # noqa: SIM115 - closed in stop()
        argv = [_bin(spec.executable), *ros_args(spec.params)]
        proc = subprocess.Popen(argv, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL)
        proc._log = log  # type: ignore[attr-defined]
        self.procs[spec.name] = proc
        return proc

    def failed(self) -> dict[str, int]:
        """Processes that have exited already, with their return codes."""
        return {n: p.returncode for n, p in self.procs.items() if p.poll() is not None}

    def log_tail(self, name: str, lines: int = 15) -> str:
        path = self.log_dir / f"{name}.log"
        return "\n".join(path.read_text().splitlines()[-lines:]) if path.exists() else ""

    def stop(self, name: str) -> float:
        """SIGINT, then SIGKILL after ``GRACE_S``; seconds to exit (inf if killed)."""
        proc = self.procs.pop(name)
        t0 = time.monotonic()
        took = 0.0
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=GRACE_S)
                took = time.monotonic() - t0
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
                took = float("inf")
        proc._log.close()
        return took

    def stop_all(self, order: list[str] | None = None) -> dict[str, float]:
        names = [n for n in (order or []) if n in self.procs] + \
            [n for n in reversed(list(self.procs)) if n not in (order or [])]
        return {n: self.stop(n) for n in names}

    def __enter__(self) -> Graph:
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()


def feedforward_server_params(model: str) -> dict:
    """model_server parameters that serve the model file ``model`` as the feedforward.

    An inverse model (``ipmc identify --inverse``, also an augmented model's feedforward from
    ``--effects-from``) goes to ``inverse_model_file``; a forward model with voltage channels
    (``ipmc identify --input-memory-taus ...``) to ``model_file`` with
    ``feedforward:=forward-inversion`` (it also serves predictions and the residual). Any
    other file, or one that cannot be read, goes to ``inverse_model_file``: model_server then
    says why.
    """
    from ipmc_model.persistence import ModelFileError, read_model_document

    path = str(Path(model).resolve())
    try:
        doc = read_model_document(path)
    except ModelFileError:
        return {"inverse_model_file": path}
    params = (doc.get("model") or {}).get("params") or {}
    if doc["kind"] == "lssvm-narx" and params.get("input_memory_taus_s"):
        return {"model_file": path, "feedforward": "forward-inversion"}
    return {"inverse_model_file": path}


#: Nodes of the graph that subscribe /ipmc/reference and /ipmc/displacement: in lock-step,
#: time and the reference wait until all those started have matched.
LISTENERS = ("controller", "model_server", "recorder")


def graph_specs(*, rig_port: str | None, lockstep: bool, model: str | None, mode: str,
                reference: str, plant_effects: list[str], record: str | None,
                rate_hz: float = 100.0, reference_params: dict | None = None
                ) -> list[NodeSpec]:
    """The nodes of the standard graph (the same as the launch files); ``reference_params``
    (``amplitude_mm``, ``levels_mm``, ...) set the reference node's generator."""
    sim_time = lockstep and rig_port is None
    common = {"use_sim_time": sim_time}
    specs = []
    if record:
        rec = {**common, "output": record, "topics": [
            "/ipmc/command", "/ipmc/voltage", "/ipmc/displacement", "/ipmc/reference",
            "/ipmc/feedforward", "/ipmc/predicted", "/ipmc/residual"]}
        if sim_time:
            # the start waits for the recorder on displacement and reference, and the recorder
            # subscribes those once the controller's and model_server's outputs have matched
            rec["await_publishers"] = ["/ipmc/command"] + (
                ["/ipmc/feedforward", "/ipmc/predicted", "/ipmc/residual"] if model else [])
        specs.append(NodeSpec("recorder", "recorder", rec))
    if model:
        # clamped: the feedforward is a filter of the reference alone, as in ipmc track.
        specs.append(NodeSpec("model_server", "model_server",
                              {**common, **feedforward_server_params(model),
                               "history_voltage": "clamped"}))
    specs.append(NodeSpec("controller", "controller", {
        **common, "mode": mode, "rate_hz": rate_hz,
        "trigger": "measurement" if sim_time else "timer"}))
    listeners = sum(s.name in LISTENERS for s in specs)
    ref = {**common, "kind": reference, "rate_hz": rate_hz, "preview_s": 2.0 / rate_hz,
           **(reference_params or {})}
    # the reference's time 0 waits until every listener started here has matched: in
    # lock-step none loses the first samples; in real time the loop starts with the
    # feedforward served (model_server subscribes once its model has loaded)
    ref["min_subscribers"] = listeners
    specs.append(NodeSpec("reference", "reference", ref))
    specs.append(plant_spec(rig_port=rig_port, lockstep=lockstep, rate_hz=rate_hz,
                            plant_effects=plant_effects, listeners=listeners))
    return specs


def plant_spec(*, rig_port: str | None, lockstep: bool, rate_hz: float,
               plant_effects: list[str], listeners: int) -> NodeSpec:
    """The driver on ``rig_port``, else the simulated plant; in lock-step its time starts once
    one stamped commander and ``listeners`` subscribers of its samples have matched."""
    if rig_port:
        return NodeSpec("driver", "driver", {"port": rig_port, "sample_rate_hz": rate_hz})
    plant = {"rate_hz": rate_hz, "clock_mode": "lockstep" if lockstep else "realtime"}
    if lockstep:
        # Time starts once the controller's stamped commands have matched (sim_plant).
        plant["lockstep_min_command_publishers"] = 1
        plant["lockstep_min_subscribers"] = max(1, listeners)
    if plant_effects:  # an empty list on the command line has no type: leave the default
        plant["effects"] = list(plant_effects)
    return NodeSpec("sim_plant", "sim_plant", plant)


#: Topics an open-loop excitation run records.
EXCITE_TOPICS = ["/ipmc/command", "/ipmc/voltage", "/ipmc/displacement"]


def excite_specs(*, rig_port: str | None, lockstep: bool, excitation: dict,
                 plant_effects: list[str], record: str | None, rate_hz: float = 100.0
                 ) -> list[NodeSpec]:
    """The open-loop graph: the ``excitation`` node (parameters ``excitation``: ``kind``,
    ``path``, ``amplitude_v``, ...) drives the plant or rig, an optional recorder records it;
    no controller, no model server. The excitation starts once its commands reach the plant
    and the recorder."""
    sim_time = lockstep and rig_port is None
    specs = []
    if record:
        rec = {"use_sim_time": sim_time, "output": record, "topics": list(EXCITE_TOPICS)}
        if sim_time:
            rec["await_publishers"] = ["/ipmc/command"]
        specs.append(NodeSpec("recorder", "recorder", rec))
    listeners = 1 + bool(record)    # the excitation and the recorder take every sample
    # Lock-step: the excitation stays, answering nothing after its end, so the plant waits
    # until bringup stops it (GraphRun) instead of running on alone with nobody commanding.
    specs.append(NodeSpec("excitation", "excitation", {
        **excitation, "rate_hz": rate_hz, "min_subscribers": listeners,
        "exit_at_end": not sim_time, "use_sim_time": sim_time}))
    plant = plant_spec(rig_port=rig_port, lockstep=lockstep, rate_hz=rate_hz,
                       plant_effects=plant_effects, listeners=listeners)
    if sim_time:   # the wait for a command that will not come: no "stepped on" warnings
        plant.params["lockstep_timeout_s"] = 5.0
    specs.append(plant)
    return specs


def mode_needs_model(mode: str, model: str | None, given_as: str = "a model") -> str | None:
    """Why ``mode`` cannot run without a feedforward model file, or None if it can;
    ``given_as`` names how the user gives one (``--model`` on the command line)."""
    if mode != "pid" and not model:
        return (f"mode {mode} needs {given_as} (an inverse model file from 'ipmc identify "
                "--inverse', or a forward model with voltage channels); use mode pid without one")
    return None


def _launch_bool(name: str, text: str) -> bool:
    if text.strip().lower() in ("true", "1"):
        return True
    if text.strip().lower() in ("false", "0"):
        return False
    raise ValueError(f"launch argument {name}:={text!r}: expected true or false")


def _launch_list(text: str) -> list[str]:
    """``"['creep', 'drift']"`` (YAML) or ``"creep,drift"``; empty for ``""`` or ``"[]"``."""
    text = text.strip()
    if text.startswith("["):
        import yaml
        return [str(v) for v in yaml.safe_load(text) or []]
    return [v.strip() for v in text.split(",") if v.strip()]


#: The reference's settings a user gives: node parameter -> (type, meaning); on the command
#: line as ``--amplitude-mm`` etc., in the launch files as ``amplitude_mm:=``.
REFERENCE_OPTIONS = {
    "amplitude_mm": (float, "sine: amplitude, mm"),
    "frequency_hz": (float, "sine: frequency, Hz"),
    "value_mm": (float, "constant: the displacement held, mm"),
    "levels_mm": (list, "steps: levels, mm, comma-separated"),
    "hold_s": (float, "steps: time per level, s"),
    "range_mm": (list, "random: displacement range min,max, mm"),
    "path": (str, "file: reference CSV with columns t, y (s, mm)"),
}


def reference_params(given: dict[str, str | None]) -> dict:
    """The reference node's parameters from the options' text (None or "" = not given):
    numbers parsed, levels a list of floats, a path made absolute. Raises ``ValueError``
    naming the option for text that is not a number."""
    out: dict = {}
    for name, (kind, _) in REFERENCE_OPTIONS.items():
        text = given.get(name)
        if text is None or str(text).strip() == "":
            continue
        try:
            if kind is float:
                out[name] = float(text)
            elif kind is list:
                out[name] = [float(v) for v in _launch_list(str(text))]
            else:
                out[name] = str(Path(text).resolve())
        except ValueError:
            raise ValueError(f"{name} {text!r} is not a number"
                             + (" list (e.g. -2,0,2)" if kind is list else "")) from None
    return out


def check_reference(kind: str, params: dict, *, sim: bool, model: str | None,
                    rate_hz: float = 100.0) -> tuple[float, float]:
    """The reference's span (mm), checked against what 3 V reaches on the simulated IPMC
    (``sim``) and the model's identified range; ``ipmc_control.reach.ReachError`` (a
    ``ValueError``) in one sentence when it cannot be tracked."""
    from ipmc_control.reach import build_reference, check_reach, reference_span_mm

    given = dict(params)
    if "levels_mm" in given and not given["levels_mm"]:
        raise ValueError("levels_mm needs one or more levels")
    ref = build_reference(kind, given)
    span = reference_span_mm(ref, kind, rate_hz)
    check_reach(span, kind, plant=sim, model=model, rate_hz=rate_hz)
    return span


def launch_arguments(*, rig: bool) -> list[tuple[str, str | None, str]]:
    """(name, default or None if required, description) of each argument of ``rig.launch.py``
    (``rig=True``) or ``sim.launch.py``."""
    models = [
        ("model", "", "feedforward model file: inverse, or forward with voltage channels"),
        ("forward_model", "", "forward model file; alone it is inverted for the feedforward, "
                              "beside an inverse model it serves predictions and the residual"),
        ("mode", "hybrid", "pid|inverse|hybrid"),
        ("reference", "sine", "constant|sine|random|steps|file"),
        *((name, "", text) for name, (_, text) in REFERENCE_OPTIONS.items()),
        ("record", "", "bag folder to record")]
    if rig:
        return [("port", None, "serial device of the RS-485 adapter"), *models]
    return [*models, ("lockstep", "false", "lock-step clock, faster than real time"),
            ("plant_effects", "", "simulated plant effects, e.g. \"['creep']\" or creep,drift")]


def launch_specs(args: dict[str, str], *, rig: bool) -> list[NodeSpec]:
    """The graph of ``sim.launch.py`` (``rig=False``) or ``rig.launch.py`` from the launch
    arguments' strings: the same nodes and parameters as ``ipmc bringup``.

    ``model`` is the feedforward model (inverse, or forward with voltage channels);
    ``forward_model`` alone serves as the feedforward too, and beside an inverse ``model`` it
    serves the predictions and the residual.
    """
    model, forward = args.get("model", ""), args.get("forward_model", "")
    mode = args.get("mode", "hybrid")
    why = mode_needs_model(mode, model or forward)
    if why:
        raise ValueError(why)
    ref_params = reference_params({k: args.get(k) for k in REFERENCE_OPTIONS})
    check_reference(args.get("reference", "sine"), ref_params, sim=not rig,
                    model=model or forward or None)
    specs = graph_specs(
        rig_port=args["port"] if rig else None,
        lockstep=False if rig else _launch_bool("lockstep", args.get("lockstep", "false")),
        model=model or forward or None, mode=mode, reference=args.get("reference", "sine"),
        plant_effects=[] if rig else _launch_list(args.get("plant_effects", "")),
        record=args.get("record") or None, reference_params=ref_params)
    if model and forward:
        server = next(s for s in specs if s.name == "model_server")
        if "model_file" in server.params:
            raise ValueError(f"model:={model} is a forward model; give it once, as "
                             "forward_model:= or model:=")
        server.params["model_file"] = str(Path(forward).resolve())
    return specs


def count_console(specs: list[NodeSpec]) -> None:
    """Count the console's subscriptions (displacement, reference) in the lock-step starts'
    minimums: else the console stands in for a listener not yet subscribed (a recorder whose
    sample subscriptions wait for the commands' publisher) and time starts without it."""
    for spec in specs:
        for name in ("lockstep_min_subscribers", "min_subscribers"):
            if spec.executable in ("sim_plant", "reference") and name in spec.params:
                spec.params[name] += 1


class GraphRun:
    """One run of a graph from the console: start the nodes, echo their warnings and errors
    as they happen, print progress every ``PROGRESS_S``, stop them all, and summarise.

    The run ends on Ctrl-C (SIGINT/SIGTERM), after ``seconds``, when a node exits (an error,
    but the excitation's exit with code 0 is the end of its excitation)."""

    #: Stop order: the commanders first (the controller's last command is 0 V), then the
    #: plant or driver, the recorder last (it keeps the final samples). Open loop, the plant
    #: or driver first (the driver leaves the rig at 0 V; the excitation commands 0 V at its
    #: end and its exit), so that no sample follows the excitation's end.
    STOP_ORDER = ["controller", "reference", "sim_plant", "driver"]
    EXCITE_STOP_ORDER = ["sim_plant", "driver", "excitation"]
    #: The excitation's log line at its end.
    FINISHED = "excitation: finished"

    def __init__(self, specs: list[NodeSpec], log_dir: Path, *, rig: bool,
                 total_samples: int | None = None) -> None:
        from ipmc_control.console import RunStats

        self.specs, self.log_dir, self.rig = specs, Path(log_dir), rig
        self.total_samples = total_samples
        self.stats = RunStats(started_s=time.monotonic())
        self.tails: dict = {}
        self.elapsed_s = 0.0
        self.until_ns: int | None = None

    def run(self, stop: dict, seconds: float | None) -> int:
        """Run until the end (class doc); 0, or 1 when a node failed."""
        from ipmc_control.console import LogTail

        monitor = self._monitor()
        if monitor is not None:
            count_console(self.specs)
        code: int | None = None
        with Graph(env={**os.environ, "PYTHONUNBUFFERED": "1"}, log_dir=self.log_dir) as graph:
            for spec in self.specs:
                graph.start(spec)
                self.tails[spec.name] = LogTail(graph.log_dir / f"{spec.name}.log")
            print(f"started {', '.join(s.name for s in self.specs)}; logs in {graph.log_dir}",
                  flush=True)
            t0 = self.stats.started_s = time.monotonic()
            next_progress_s = t0 + PROGRESS_S
            while not stop["now"] and code is None:
                if monitor is not None:
                    monitor.spin_for(0.1)
                else:
                    time.sleep(0.1)
                code = 0 if self.echo() else self._exits(graph)
                now = time.monotonic()
                if seconds and now - t0 >= seconds:
                    break
                if now >= next_progress_s and code is None:
                    print(self.stats.progress_line(now, self.total_samples), flush=True)
                    next_progress_s += PROGRESS_S
            # the last sample of the running loop: the summary's tracking error ends there
            self.until_ns = max(self.stats.displacement_mm, default=None)
            took = graph.stop_all(order=self.EXCITE_STOP_ORDER if self.total_samples
                                  else self.STOP_ORDER)
            self.elapsed_s = time.monotonic() - t0
        if monitor is not None:
            monitor.close()
        self.echo()
        print("stopped: " + ", ".join(f"{n} {t:.2f} s" for n, t in took.items()), flush=True)
        return code or 0

    def _monitor(self):
        try:
            from ipmc_control.run_monitor import RunMonitor
            return RunMonitor(self.stats)
        except ImportError as exc:   # rclpy absent: logs and the bag still tell
            print(f"note: no progress on the console ({exc})", file=sys.stderr)
            return None

    def _exits(self, graph: Graph) -> int | None:
        """None while every node runs; 0 when the excitation ended; 1 when a node failed."""
        failed = graph.failed()
        if not failed:
            return None
        if failed == {"excitation": 0}:
            return 0
        for name, code in failed.items():
            print(f"{name} exited with code {code}:\n{graph.log_tail(name)}", file=sys.stderr)
        return 1

    def echo(self) -> bool:
        """Print the warning and error lines the nodes have logged since the last call;
        whether the excitation logged its end among them."""
        from ipmc_control.console import alarm_line

        finished = False
        for name, tail in self.tails.items():
            for line in tail.read():
                finished |= name == "excitation" and self.FINISHED in line
                alarm = alarm_line(name, line)
                if alarm:
                    self.stats.on_alarm(alarm)
                    print(alarm, flush=True)
        if finished:
            print("excitation finished", flush=True)
        return finished

    def summary(self, bag: Path | None) -> list[str]:
        """The end-of-run summary (``console.summary_lines``), from the bag when recorded."""
        from ipmc_control.console import bag_figures, summary_lines

        figures: dict = {"rmse": self.stats.tracking_rmse_mm()}
        notes = []
        if bag is not None:
            try:
                figures = bag_figures(bag, with_reference=self.total_samples is None,
                                      until_ns=self.until_ns)
            except (ValueError, OSError) as exc:
                notes.append(f"the bag could not be summarised: {exc}")
        return notes + summary_lines(self.stats, elapsed_s=self.elapsed_s,
                                     log_dir=self.log_dir, bag=bag, rig=self.rig, **figures)


#: Seconds between progress lines on the console.
PROGRESS_S = 5.0
#: Excitation defaults: the length and the hold of ``--excite``, s.
EXCITE_SECONDS = 240.0
EXCITE_HOLD_S = 8.0


def _parser() -> argparse.ArgumentParser:
    from ipmc_control.excitation import KINDS

    parser = argparse.ArgumentParser(
        prog="ipmc bringup",
        description="Start the ipmc-ros graph (plant or rig, model server, controller, "
                    "reference, optional recorder) as processes; or, with --excite, drive the "
                    "plant or rig open loop with an identification voltage and record it. "
                    "Warnings of every node appear on the console; Ctrl-C stops them all.")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--sim", action="store_true", help="simulated plant (default)")
    where.add_argument("--rig", metavar="PORT", help="real rig through the driver on PORT")
    parser.add_argument("--lockstep", action="store_true",
                        help="simulation: lock-step clock, faster than real time")
    parser.add_argument("--model", help="model file for the feedforward: an inverse model, or a "
                        "forward model with voltage channels (inverted online)")
    parser.add_argument("--mode", choices=("pid", "inverse", "hybrid"),
                        help="closed loop: control mode (default hybrid)")
    parser.add_argument("--reference", default="sine",
                        help="reference kind: constant | sine | random | steps | file")
    for name, (kind, text) in REFERENCE_OPTIONS.items():
        flag = "--" + name.replace("_", "-")
        more = {"hold_s": f"; with --excite: each held voltage, s (default {EXCITE_HOLD_S:g})",
                }.get(name, "")
        if kind is list:
            more += f" (a first value below 0 after '=': {flag}=-2,2)"
        parser.add_argument(flag, dest=name, metavar={list: "A,B,..", str: "CSV"}.get(
            kind, "X"), help=f"reference {text}{more}")
    opened = parser.add_mutually_exclusive_group()
    opened.add_argument("--excite", metavar="KIND|FILE",
                        help=f"open loop: drive the voltage with {' | '.join(KINDS)} (holds at "
                             "levels spanning +-amplitude, steps, the whole range) or a FILE "
                             "(t,u CSV, or next_experiment.json of ipmc diagnose), and stop at "
                             "its end; no controller, no model server")
    opened.add_argument("--experiment", metavar="FILE",
                        help="open loop: play ipmc diagnose's next_experiment.json (as --excite "
                             "FILE)")
    parser.add_argument("--amplitude-v", type=float, default=3.0,
                        help="--excite: largest |voltage|, V (<= 3, the H-bridge's limit)")
    parser.add_argument("--seed", type=int, default=0, help="--excite: seed of the voltages")
    parser.add_argument("--plant-effect", action="append", default=[],
                        help="simulated plant effect (repeatable)")
    parser.add_argument("--record", metavar="BAG", help="record the graph's topics to BAG "
                        "(a new folder; the nodes' logs go to BAG_logs beside it)")
    parser.add_argument("--seconds", type=float, default=None,
                        help="stop after this many wall seconds (default: until Ctrl-C); with "
                             f"--excite: the excitation's length (default {EXCITE_SECONDS:g} "
                             "s; a FILE: at most this long)")
    return parser


def log_dir_for(record: str | None) -> Path:
    """The nodes' log folder: ``BAG_logs`` beside the bag, else one new temporary folder."""
    if record:
        bag = Path(record).resolve()
        return bag.parent / f"{bag.name}_logs"
    return Path(tempfile.mkdtemp(prefix="ipmc_bringup_"))


def plan_excitation(args: argparse.Namespace, rate_hz: float) -> tuple[dict, object]:
    """The excitation node's parameters and the excitation they give (checked here, so
    that a bad file or amplitude stops ``bringup`` before any node starts)."""
    from ipmc_control.excitation import KINDS, load_excitation, make_excitation

    source = args.experiment or args.excite
    hold_s = float(args.hold_s) if args.hold_s else EXCITE_HOLD_S
    if source in KINDS:
        seconds = args.seconds or EXCITE_SECONDS
        exc = make_excitation(source, amplitude_v=args.amplitude_v, hold_s=hold_s,
                              seconds=seconds, rate_hz=rate_hz, seed=args.seed)
        return {"kind": source, "amplitude_v": args.amplitude_v, "hold_s": hold_s,
                "duration_s": seconds, "seed": args.seed}, exc
    exc = load_excitation(source, rate_hz, args.seconds)
    return {"kind": "file", "path": str(Path(source).resolve()),
            "duration_s": float(args.seconds or 0.0)}, exc


def plan(args: argparse.Namespace, rate_hz: float = 100.0) -> tuple[list[NodeSpec], int | None]:
    """The nodes to start, and the excitation's samples (None for a closed loop); a
    ``ValueError`` in one sentence for settings that cannot run."""
    if args.record and Path(args.record).exists():
        raise ValueError(f"{args.record} exists already; a bag is never written over")
    given = reference_params({k: getattr(args, k) for k in REFERENCE_OPTIONS})
    if args.excite or args.experiment:
        stray = [f"--{k.replace('_', '-')}" for k in given if k != "hold_s"]
        stray += ["--model"] * bool(args.model) + ["--mode"] * bool(args.mode)
        if stray:
            raise ValueError(f"{stray[0]} sets the closed loop; --excite drives the voltage "
                             "open loop without a controller")
        params, exc = plan_excitation(args, rate_hz)
        print(f"excitation {exc.describe()}", flush=True)
        return excite_specs(rig_port=args.rig, lockstep=args.lockstep, excitation=params,
                            plant_effects=args.plant_effect, record=args.record,
                            rate_hz=rate_hz), exc.u_v.size
    mode = args.mode or "hybrid"
    why = mode_needs_model(mode, args.model, "--model")
    if why:
        raise ValueError(why)
    lo, hi = check_reference(args.reference, given, sim=args.rig is None,
                             model=args.model if mode != "pid" else None, rate_hz=rate_hz)
    print(f"reference {args.reference}: {lo:.2f}..{hi:.2f} mm", flush=True)
    return graph_specs(rig_port=args.rig, lockstep=args.lockstep, model=args.model, mode=mode,
                       reference=args.reference, plant_effects=args.plant_effect,
                       record=args.record, rate_hz=rate_hz, reference_params=given), None


def as_options(text: str) -> str:
    """A message about the reference's parameters in the words of the command line
    (``levels_mm`` -> ``--levels-mm``)."""
    names = "|".join(REFERENCE_OPTIONS)
    return re.sub(rf"\b({names})\b", lambda m: "--" + m.group(1).replace("_", "-"), text)


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        specs, total_samples = plan(args)
    except ValueError as exc:
        print(f"ipmc bringup: error: {as_options(str(exc))}", file=sys.stderr)
        return 1
    stop = {"now": False}

    def on_signal(signum, frame):
        stop["now"] = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    run = GraphRun(specs, log_dir_for(args.record), rig=bool(args.rig),
                   total_samples=total_samples)
    code = run.run(stop, None if total_samples else args.seconds)
    for line in run.summary(Path(args.record).resolve() if args.record else None):
        print(line, flush=True)
    keep_experiment(args.experiment, args.record)
    return code


def keep_experiment(experiment: str | None, record: str | None) -> None:
    """A copy of the experiment a bag recorded, in the bag's folder: ``ipmc diagnose --data
    BAG`` then splits the record where the experiment's held-out part starts, as with
    ``--experiment FILE``."""
    from ipmc_model.diagnosis.experiment import BAG_EXPERIMENT

    if experiment and record and Path(record).is_dir():
        shutil.copyfile(experiment, Path(record) / BAG_EXPERIMENT)
        print(f"the experiment played: {Path(record) / BAG_EXPERIMENT}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
