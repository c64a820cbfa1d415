"""``ipmc track``: the paper's tracking experiments on the simulated IPMC, in process or through
the ROS graph (separate processes over real DDS, lock-step clock).

    ipmc track --model INVERSE.json --reference sine|random|random-reachable|constant[-reachable]
               --mode pid|inverse|hybrid
               [--graph] [--plant-effect creep] --json OUT

``--model`` is an inverse model (``ipmc identify --inverse``) or a forward model with voltage
channels (``ipmc identify --input-memory-taus ...``): the feedforward then inverts the forward
model sample by sample (``ipmc_model.forward_inversion``), in process and, with ``--graph``, in
model_server (``feedforward:=forward-inversion``). It may also be an augmented model's
feedforward (``ipmc identify --inverse --effects-from model_after.json``): the inverse of the
baseline with the effects ``ipmc diagnose`` found undone around it (a creep's state subtracted).

Both ways run the same loop (``ipmc_control.experiment``), so their RMSEs agree closely; the
JSON is ``{"rmse_mm", "max_abs_mm", "u_max_v", "duration_s", "samples"}``. Every sample of the
run counts, as in the paper.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .bringup import mode_needs_model
from .experiment import (
    DEFAULT_DURATION_S,
    REFERENCE_KIND,
    REFERENCE_PARAMS,
    REFERENCES,
    paper_reference,
    plot_tracking,
    run_tracking,
    tracking_summary,
)
from .hybrid import MODES

# Longest wall-time wait of a lock-step graph run for a command or a controller input, s
# (2 s was once exceeded by model_server at a load average of 5-10 on 2 cores).
LOCKSTEP_WAIT_S = 5.0
# Wall time between "every node is up" and starting the plant, s.
DISCOVERY_SETTLE_S = 1.0
# Sample rate of the loop, in process and in the graph (bringup.graph_specs), Hz.
RATE_HZ = 100.0


def load_feedforward(path: str | None, mode: str):
    """The feedforward of a model file, or None in PID mode; ``ValueError`` with one sentence.

    An inverse model, also an augmented model's feedforward (``ipmc identify --inverse
    --effects-from``, checked against the loop's rate), is its own feedforward; a forward model
    with voltage channels gives a ``ForwardInversionFeedforward``; any other model is refused.
    """
    if mode == "pid":
        return None
    why = mode_needs_model(mode, path, "--model")
    if why:
        raise ValueError(why)
    from ipmc_model.effects import AugmentedInverse, AugmentedModel, load_any_model
    from ipmc_model.forward_inversion import ForwardInversionFeedforward
    from ipmc_model.hysteresis import GpiInverse
    from ipmc_model.narx import InverseNarxModel, NarxModel

    model = load_any_model(path, 1.0 / RATE_HZ)
    if isinstance(model, (InverseNarxModel, AugmentedInverse, GpiInverse)):
        check_gpi_rate(model, path)
        return model
    if isinstance(model, NarxModel) and model.uses_voltage_channels:
        return ForwardInversionFeedforward(model)
    if isinstance(model, AugmentedModel):
        raise ValueError(f"{path} is an augmented model (ipmc diagnose), not its feedforward; "
                         "make that with 'ipmc identify --model lssvm-narx --inverse "
                         f"--effects-from {path} --data RECORD'")
    raise ValueError(f"{path} holds a {type(model).__name__}, not an inverse model nor a forward "
                     "model with voltage channels; make one with 'ipmc identify --inverse' or "
                     "'ipmc identify --input-memory-taus 0.3 0.5 --no-raw-voltage'")


def check_gpi_rate(model, path) -> None:
    """A GPI feedforward runs at the rate it was identified at: its relaxations and charging
    are discretised with that period."""
    dt = getattr(getattr(model, "model", None), "dt_s", None)
    if dt is not None and abs(dt * RATE_HZ - 1.0) > 1e-6:
        raise ValueError(f"{path} was identified at {1 / dt:g} Hz; the loop runs at "
                         f"{RATE_HZ:g} Hz")


def reach_warning(model, reference: str, duration_s: float | None = None) -> str | None:
    """A sentence when the reference leaves the displacements the inverse was identified on
    (``ipmc_model.narx.reach_mm``): a hold beyond the held ones, a moving reference beyond
    any of them over ``duration_s`` (default: the reference's run); None within them, or for
    another feedforward. There the inverse extrapolates: a feedforward with the creep undone
    identified on steps up to 2.5 V held -4 mm worse than the plain one, and better on steps
    up to 3 V (docs/control.md)."""
    from ipmc_model.narx import out_of_reach, reach_mm

    held = REFERENCE_KIND[reference] == "constant"
    reach = reach_mm(model, held=held)
    if reach is None:
        return None
    lo, hi = reach
    if held:
        hold = REFERENCE_PARAMS[reference]["value_mm"]
        if not out_of_reach(hold, reach):
            return None
        return (f"the hold at {hold:g} mm lies beyond the displacements the inverse was "
                f"identified on as held ones ({lo:.2f} to {hi:.2f} mm), where it "
                "extrapolates: identify it on a record that holds there (steps up to the "
                "voltage the hold needs)")
    _, r = paper_reference(reference).sample(duration_s or DEFAULT_DURATION_S[reference],
                                             RATE_HZ)
    beyond = [v for v in (float(r.min()), float(r.max())) if out_of_reach(v, reach)]
    if not beyond:
        return None
    return (f"the reference reaches {' and '.join(f'{v:.2f}' for v in beyond)} mm, beyond the "
            f"displacements the inverse was identified on ({lo:.2f} to {hi:.2f} mm), where it "
            "extrapolates: identify it on a record that covers the reference's range")


# The name before forward models could serve as feedforward.
load_inverse = load_feedforward


def run_in_process(model, reference: str, mode: str, effects: list[str], duration_s: float,
                   seed: int = 0):
    from ipmc_driver.plant import IpmcPlant

    plant = IpmcPlant(effects=effects, seed=seed, dt_s=1.0 / RATE_HZ)
    return run_tracking(paper_reference(reference), duration_s, mode, inverse=model,
                        plant=plant, rate_hz=RATE_HZ)


def run_graph(model_path: str | None, reference: str, mode: str, effects: list[str],
              duration_s: float, *, log=sys.stderr, timeout_s: float | None = None,
              record: Path | None = None) -> dict:
    """Run the experiment through sim_plant (lock-step), model_server, controller, reference
    and recorder as processes; return the summary computed from the recorded bag (kept at
    ``record``, see :func:`_run_paths`). A forward model with voltage channels is served as
    ``model_file`` with ``feedforward:=forward-inversion`` (``bringup.graph_specs``)."""
    import rclpy
    import rclpy.executors
    from geometry_msgs.msg import PointStamped
    from rclpy.qos import QoSProfile, QoSReliabilityPolicy

    from ipmc_driver.dataio import stamp_ns
    from ipmc_driver.node_runtime import StopSignals

    from .bringup import Graph

    env = dict(os.environ)
    env.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})
    work, bag, logs = _run_paths(record)
    specs = _probe_specs(model_path, reference, mode, effects, bag)
    timeout_s = timeout_s or 90.0 + 3.0 * duration_s
    context = rclpy.Context()
    # rclpy's SIGINT handler only shuts the context down (the wait loop would never end):
    # StopSignals notes Ctrl-C and SIGTERM, the wait loop raises them, the Graph stops all.
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("ipmc_track_probe", context=context)
    first_ref, last_y = [], [0]
    qos = QoSProfile(depth=100, reliability=QoSReliabilityPolicy.RELIABLE)


    node.create_subscription(
        PointStamped, "/ipmc/reference",
        lambda m: first_ref or first_ref.append(stamp_ns(m.header.stamp)), qos)
    node.create_subscription(PointStamped, "/ipmc/displacement",
                             lambda m: last_y.__setitem__(0, stamp_ns(m.header.stamp)), qos)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)

    def spin_until(predicate, limit_s, what):
        deadline = time.monotonic() + limit_s
        while not predicate():
            stop.raise_if_signalled()
            if graph.failed():
                name, code = next(iter(graph.failed().items()))
                raise RuntimeError(f"{name} exited with code {code}:\n{graph.log_tail(name)}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"timed out after {limit_s:.0f} s waiting for {what}")
            executor.spin_once(timeout_sec=0.05)

    t_wall = time.monotonic()
    stop = StopSignals()
    try:
        with Graph(env, logs) as graph:
            plant_spec = _bring_up(graph, specs, node, spin_until, stop, mode)
            graph.start(plant_spec)
            print(f"graph up in {time.monotonic() - t_wall:.1f} s; running {duration_s:g} s "
                  "of simulated time (lock-step)", file=log, flush=True)
            spin_until(lambda: first_ref and last_y[0] >= first_ref[0] + duration_s * 1e9,
                       timeout_s, f"{duration_s:g} s of simulated time")
            exits = graph.stop_all(order=["reference", "controller", "model_server",
                                          "sim_plant", "recorder"])
    finally:
        stop.restore()
        executor.remove_node(node)
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    stop.raise_if_signalled()    # one that came while the graph stopped at the end of the run
    warned = _warn_from_logs(logs, mode, exits, log)
    summary, n = _summary_from_bag(bag, first_ref[0], duration_s)
    kept = work is None or warned
    print(f"graph run: {n} samples in {time.monotonic() - t_wall:.1f} s wall"
          + (f"; bag {bag}, logs {logs}" if kept else ""), file=log)
    if not kept:
        shutil.rmtree(work, ignore_errors=True)
    return summary


def _run_paths(record: Path | None) -> tuple[Path | None, Path, Path]:
    """(temporary folder or None, bag, logs folder) of a graph run: ``record`` and its
    ``_logs`` sibling, or both inside a new temporary folder (removed after a run that printed
    no warning)."""
    if record is not None:
        return None, Path(record), Path(record).parent / f"{Path(record).name}_logs"
    work = Path(tempfile.mkdtemp(prefix="ipmc_track_"))
    return work, work / "bag", work / "logs"


def _bring_up(graph, specs, node, spin_until, stop, mode: str):
    """Start every node but the plant, wait until each listener is matched, then ready the
    plant's clock for them; returns the plant's spec (started by the caller)."""
    plant_spec = next(s for s in specs if s.name == "sim_plant")
    for spec in specs:
        if spec is not plant_spec:
            graph.start(spec)
    need_ff = mode != "pid"
    # Every listener the run has, this probe included (graph_specs counts them): a
    # recorder missing from the graph here once matched 0.5 s of simulated time late
    # and lost it.
    n_listen = plant_spec.params["lockstep_min_subscribers"]
    n_ff = len({s.name for s in specs} & {"controller", "recorder"})
    spin_until(lambda: node.count_subscribers("/ipmc/displacement") >= n_listen
               and node.count_subscribers("/ipmc/reference") >= n_listen
               and node.count_publishers("/ipmc/reference") >= 1
               and (not need_ff or (node.count_publishers("/ipmc/feedforward") >= 1
                                    and node.count_subscribers("/ipmc/feedforward")
                                    >= n_ff)),
               30.0, "the graph's nodes to come up")
    # This probe sees every node; let the nodes see each other too (the controller
    # must know model_server is there to wait for its first feedforward).
    time.sleep(DISCOVERY_SETTLE_S)
    stop.raise_if_signalled()
    # The plant's clock starts only when it has matched every listener (DDS matches,
    # not the graph's list: lockstep_min_subscribers): a late match would cut the
    # start of the recording.
    plant_spec.params["lockstep_min_clock_subscribers"] = node.count_subscribers("/clock")
    return plant_spec


def _probe_specs(model_path, reference: str, mode: str, effects, bag: Path) -> list:
    """The graph's node specs for one tracking run, with this probe counted as a listener."""
    from .bringup import graph_specs

    specs = graph_specs(rig_port=None, lockstep=True, model=model_path if mode != "pid" else None,
                        mode=mode, reference=REFERENCE_KIND[reference], plant_effects=effects,
                        record=str(bag), rate_hz=RATE_HZ)
    for spec in specs:
        if spec.name == "reference":
            spec.params.update(REFERENCE_PARAMS[reference])
            spec.params["min_subscribers"] += 1    # this probe listens too
        # Lock-step means every sample waits for its command, and every command for its inputs:
        # on a loaded machine a process can stall for more than the defaults (0.2 s, 0.05 s),
        # and a plant stepping on without the command is no longer the in-process loop.
        if spec.name == "sim_plant":
            spec.params["lockstep_timeout_s"] = LOCKSTEP_WAIT_S
            spec.params["lockstep_min_subscribers"] += 1    # this probe listens too
        if spec.name == "controller":
            spec.params["pair_wait_s"] = LOCKSTEP_WAIT_S
    return specs


def _warn_from_logs(logs: Path, mode: str, exits: dict, log) -> bool:
    """Warnings of a graph run that is not the in-process loop sample for sample; whether
    there were any."""
    slow = {n: t for n, t in exits.items() if t > 2.0}
    if slow:
        print(f"warning: slow exits after SIGINT: {slow}", file=log)
    fallbacks = _count_in_log(logs / "controller.log", "feedforward stale")
    if fallbacks and mode != "pid":
        print(f"warning: the controller ran without the feedforward {fallbacks} time(s) (a node "
              f"stalled for more than {LOCKSTEP_WAIT_S:g} s of wall time): this run is not the "
              "in-process loop sample for sample; see " + str(logs), file=log)
    unanswered = _count_in_log(logs / "sim_plant.log", "lock-step: no command")
    if unanswered:
        print(f"warning: the plant stepped on without its command (a node stalled for more than "
              f"{LOCKSTEP_WAIT_S:g} s of wall time; {unanswered} warning(s) in the plant's log): "
              "this run is not the in-process loop sample for sample; see "
              + str(logs), file=log)
    return bool(slow or (fallbacks and mode != "pid") or unanswered)


def _summary_from_bag(bag: Path, first_ref_ns: int, duration_s: float) -> tuple[dict, int]:
    """The tracking summary of the recorded run, and the paired samples it rests on."""
    from ipmc_driver.dataio import DISPLACEMENT_TYPE, VOLTAGE_TYPE, read_stamped_series

    series = read_stamped_series(bag, {"/ipmc/reference": DISPLACEMENT_TYPE,
                                       "/ipmc/displacement": DISPLACEMENT_TYPE,
                                       "/ipmc/voltage": VOLTAGE_TYPE})
    ref, disp, volt = (series[t] for t in ("/ipmc/reference", "/ipmc/displacement",
                                           "/ipmc/voltage"))
    t_end = first_ref_ns + int(round(duration_s * 1e9))
    stamps = sorted(s for s in ref if first_ref_ns <= s < t_end and s in disp and s in volt)
    if len(stamps) < 10:
        raise RuntimeError(f"the recorded bag {bag} holds only {len(stamps)} paired samples")
    t = (np.array(stamps) - stamps[0]) * 1e-9
    summary = tracking_summary(t, [ref[s] * 1e3 for s in stamps],
                               [disp[s] * 1e3 for s in stamps], [volt[s] for s in stamps])
    return summary, len(stamps)


def _count_in_log(path: Path, text: str) -> int:
    try:
        return path.read_text(errors="replace").count(text)
    except OSError:
        return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="ipmc track",
        description="Track the paper's references on the simulated IPMC with PID, inverse "
                    "feedforward or both (hybrid); in process or through the ROS graph.")
    parser.add_argument("--model", help="inverse model file (ipmc identify --inverse; also "
                                        "with --effects-from: an augmented model's "
                                        "feedforward), or a forward model with voltage "
                                        "channels (ipmc identify --input-memory-taus ...), "
                                        "then inverted online")
    parser.add_argument("--reference", required=True, choices=REFERENCES)
    parser.add_argument("--mode", required=True, choices=MODES)
    parser.add_argument("--graph", action="store_true",
                        help="run through the node graph (separate processes, real DDS)")
    parser.add_argument("--plant-effect", action="append", default=[],
                        help="switch on a simulated plant effect (e.g. creep; repeatable)")
    parser.add_argument("--seconds", type=float,
                        help="duration, s (default: 4 periods of the sine, 60 s otherwise)")
    parser.add_argument("--record", metavar="BAG",
                        help="with --graph: keep the run's bag here and the nodes' logs in "
                             "BAG_logs beside it (default: a temporary folder, removed after "
                             "a run without warnings)")
    parser.add_argument("--json", metavar="OUT", help="write the summary as JSON")
    parser.add_argument("--plot", metavar="PNG", help="in-process run: write a figure")
    args = parser.parse_args(argv)
    duration = args.seconds or DEFAULT_DURATION_S[args.reference]
    try:
        from ipmc_driver.validation import check_output_file

        if args.json:
            check_output_file(args.json, option="--json", suffixes=(".json",))
        if args.record and Path(args.record).exists():
            raise ValueError(f"{args.record} exists already; a bag is never written over")
        if args.record and not args.graph:
            raise ValueError("--record keeps the bag of a graph run: add --graph")
        if args.plot:
            check_output_file(args.plot, option="--plot", suffixes=(".png", ".pdf", ".svg"))
        model = load_feedforward(args.model, args.mode)
        reach = reach_warning(model, args.reference, duration)
        if reach:
            print(f"ipmc track: warning: {reach}", file=sys.stderr)
        if args.graph:
            summary = run_graph(args.model, args.reference, args.mode, args.plant_effect,
                                duration, record=Path(args.record) if args.record else None)
        else:
            result = run_in_process(model, args.reference, args.mode, args.plant_effect,
                                    duration)
            summary = result.summary()
            if args.plot:
                plot_tracking(result, args.plot, f"{args.reference}, {args.mode}: RMSE "
                                                 f"{summary['rmse_mm']:.4f} mm")
    except (ValueError, RuntimeError, TimeoutError, OSError) as exc:
        print(f"ipmc track: error: {exc}", file=sys.stderr)
        return 1
    where = "graph" if args.graph else "in process"
    print(f"{args.reference} / {args.mode} ({where}"
          f"{', plant effects ' + ','.join(args.plant_effect) if args.plant_effect else ''}): "
          f"RMSE {summary['rmse_mm']:.4f} mm, max |e| {summary['max_abs_mm']:.3f} mm, "
          f"max |u| {summary['u_max_v']:.2f} V over {summary['duration_s']:.1f} s "
          f"({summary['samples']} samples)")
    if args.json:
        from ipmc_driver.dataio import write_atomic

        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        write_atomic({args.json: json.dumps(summary, indent=2) + "\n"})
    return 0


if __name__ == "__main__":
    sys.exit(main())
