"""``ipmc bringup``: start the ipmc-ros graph as processes and stop it cleanly (pip-only launch).

`ros2 launch` is not on PyPI, so this starts the same nodes as ``launch/sim.launch.py`` /
``launch/rig.launch.py`` as child processes of one command, prints where their logs go, and on
Ctrl-C (or SIGTERM) stops them all: SIGINT first, SIGKILL after a grace period.

    ipmc bringup --sim [--lockstep] [--model MODEL.json] [--mode hybrid] [--reference sine]
    ipmc bringup --rig /dev/ttyUSB0 --model MODEL.json --record run1

MODEL is an inverse model (``ipmc identify --inverse``) or a forward model with voltage channels
(``ipmc identify --input-memory-taus ...``), which model_server inverts online.
"""

from __future__ import annotations

import argparse
import os
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
              "reference": "ipmc_control"}


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
                rate_hz: float = 100.0) -> list[NodeSpec]:
    """The nodes of the standard graph (the same as the launch files)."""
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
    ref = {**common, "kind": reference, "rate_hz": rate_hz, "preview_s": 2.0 / rate_hz}
    if sim_time:
        # the first samples wait until every listener started here has matched (reference)
        ref["min_subscribers"] = listeners
    specs.append(NodeSpec("reference", "reference", ref))
    if rig_port:
        specs.append(NodeSpec("driver", "driver", {"port": rig_port,
                                                   "sample_rate_hz": rate_hz}))
    else:
        plant = {"rate_hz": rate_hz, "clock_mode": "lockstep" if lockstep else "realtime"}
        if lockstep:
            # Time starts once the controller's stamped commands have matched (sim_plant).
            plant["lockstep_min_command_publishers"] = 1
            plant["lockstep_min_subscribers"] = max(1, listeners)
        if plant_effects:  # an empty list on the command line has no type: leave the default
            plant["effects"] = list(plant_effects)
        specs.append(NodeSpec("sim_plant", "sim_plant", plant))
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


def launch_arguments(*, rig: bool) -> list[tuple[str, str | None, str]]:
    """(name, default or None if required, description) of each argument of ``rig.launch.py``
    (``rig=True``) or ``sim.launch.py``."""
    models = [
        ("model", "", "feedforward model file: inverse, or forward with voltage channels"),
        ("forward_model", "", "forward model file; alone it is inverted for the feedforward, "
                              "beside an inverse model it serves predictions and the residual"),
        ("mode", "hybrid", "pid|inverse|hybrid"),
        ("reference", "sine", "constant|sine|random|steps|file"),
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
    specs = graph_specs(
        rig_port=args["port"] if rig else None,
        lockstep=False if rig else _launch_bool("lockstep", args.get("lockstep", "false")),
        model=model or forward or None, mode=mode, reference=args.get("reference", "sine"),
        plant_effects=[] if rig else _launch_list(args.get("plant_effects", "")),
        record=args.get("record") or None)
    if model and forward:
        server = next(s for s in specs if s.name == "model_server")
        if "model_file" in server.params:
            raise ValueError(f"model:={model} is a forward model; give it once, as "
                             "forward_model:= or model:=")
        server.params["model_file"] = str(Path(forward).resolve())
    return specs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="ipmc bringup",
        description="Start the ipmc-ros graph (plant or rig, model server, controller, "
                    "reference, optional recorder) as processes; Ctrl-C stops them all.")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--sim", action="store_true", help="simulated plant (default)")
    where.add_argument("--rig", metavar="PORT", help="real rig through the driver on PORT")
    parser.add_argument("--lockstep", action="store_true",
                        help="simulation: lock-step clock, faster than real time")
    parser.add_argument("--model", help="model file for the feedforward: an inverse model, or a "
                        "forward model with voltage channels (inverted online)")
    parser.add_argument("--mode", default="hybrid", choices=("pid", "inverse", "hybrid"))
    parser.add_argument("--reference", default="sine",
                        help="reference kind: constant | sine | random | steps | file")
    parser.add_argument("--plant-effect", action="append", default=[],
                        help="simulated plant effect (repeatable)")
    parser.add_argument("--record", metavar="BAG", help="record the graph's topics to BAG")
    parser.add_argument("--seconds", type=float, default=0.0,
                        help="stop after this many wall seconds (default: until Ctrl-C)")
    args = parser.parse_args(argv)
    why = mode_needs_model(args.mode, args.model, "--model")
    if why:
        parser.error(why)
    specs = graph_specs(rig_port=args.rig, lockstep=args.lockstep, model=args.model,
                        mode=args.mode, reference=args.reference,
                        plant_effects=args.plant_effect, record=args.record)
    stop = {"now": False}

    def on_signal(signum, frame):
        stop["now"] = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    with Graph() as graph:
        for spec in specs:
            graph.start(spec)
            print(f"started {spec.name} (log {graph.log_dir / spec.name}.log)", flush=True)
        t0 = time.monotonic()
        while not stop["now"]:
            if graph.failed():
                for name, code in graph.failed().items():
                    print(f"{name} exited with code {code}:\n{graph.log_tail(name)}",
                          file=sys.stderr)
                break
            if args.seconds and time.monotonic() - t0 >= args.seconds:
                break
            time.sleep(0.1)
        took = graph.stop_all(order=["reference", "controller", "sim_plant", "driver"])
    print("stopped: " + ", ".join(f"{n} {t:.2f} s" for n, t in took.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
