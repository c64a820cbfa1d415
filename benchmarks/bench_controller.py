"""Per-step compute time of the controller core, in process (no ROS): p50 / p99 / max.

Cases, each timed one step at a time with ``time.perf_counter_ns`` in a closed loop on the
simulated plant (the plant's own time is not counted):

1. ``PID``: ``PID.compute_command``;
2. ``hybrid (given u_ff)``: ``HybridController.compute_command`` with a feedforward value;
3. ``inverse model + hybrid``: ``InverseStepper.step`` + ``HybridController.compute_command`` +
   ``record_applied`` (what the in-process loop does each sample), when ``ipmc_model.narx`` is
   available. The inverse model is fitted here on a plant excitation, or loaded with
   ``--model FILE`` (``ipmc_model.persistence.load_model``);
4. ``forward inversion + hybrid`` (``--forward-model FILE``, a forward model with voltage
   channels, e.g. the demo's ``forward_ff.json``): ``ForwardInversionStepper.step`` +
   ``HybridController.compute_command`` + ``record_applied``, the forward model inverted
   online (``ipmc_model.forward_inversion``, its default method).

Then (``--graph SECONDS``, default 30; 0 skips it) it runs ``sim_plant`` (real-time clock),
``reference``, ``controller`` and, with a model, ``model_server`` (hybrid mode; serving the
forward inversion when ``--forward-model`` is given) as processes over DDS (own domain,
loopback) and reports the controller's own loop figures from /diagnostics: steps, deadline
misses (a 100 Hz tick later than 1.5 periods after the previous one, wall clock) and the step
time including the publish; and the intervals between
``/ipmc/command`` messages as a subscriber receives them.

Goals: p99 <= 200 us per step; deadline misses < 0.1 %. Prints tables; not part of
the pass/fail suite.

    .venv/bin/python benchmarks/bench_controller.py [--steps 20000] [--model FILE]
        [--forward-model FILE] [--graph 30]
"""

from __future__ import annotations

import argparse
import gc
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ipmc_control.hybrid import HybridController
from ipmc_control.pid import PID
from ipmc_control.references import RandomSineReference
from ipmc_driver.plant import IpmcPlant

DT_S = 0.01


def _stats(ns: list[int]) -> tuple[float, float, float]:
    us = np.asarray(ns, dtype=float) / 1e3
    return float(np.percentile(us, 50)), float(np.percentile(us, 99)), float(us.max())


def _loop(step, n_steps: int) -> tuple[list[int], list[int]]:
    """Closed loop on the plant; ``step(k, r_mm, y_mm) -> u_v`` is timed (wall and thread CPU
    time, ns), the plant is not."""
    plant = IpmcPlant(seed=0, dt_s=DT_S)
    ref = RandomSineReference(range_mm=(-2.0, 2.0), seed=1)
    r = ref.sample(n_steps * DT_S, 1.0 / DT_S)[1].tolist()
    y = 0.0
    wall, cpu = [], []
    clock, cpu_clock = time.perf_counter_ns, time.thread_time_ns
    gc.disable()  # a collection inside a step is the interpreter's jitter, not the controller's
    try:
        for k in range(n_steps):
            c0 = cpu_clock()
            t0 = clock()
            u = step(k, r[k], y)
            t1 = clock()
            c1 = cpu_clock()
            wall.append(t1 - t0)
            cpu.append(c1 - c0)
            _, y = plant.step(u)
    finally:
        gc.enable()
    return wall, cpu


def _feedforward_hybrid(stepper):
    """``step(k, r, y)`` of the in-process loop: the feedforward stepper's voltage, the hybrid
    command, and the applied voltage back into the stepper's history."""
    ctl = HybridController()

    def step(k, r, y):
        u_ff = stepper.step(r)
        u = ctl.compute_command(r, y, DT_S, u_ff)
        stepper.record_applied(u)
        return u

    return step


def _inverse_model(path: str | None):
    try:
        from ipmc_model.narx import InverseNarxModel
    except ImportError as exc:
        return None, f"ipmc_model.narx not available ({exc})"
    if path:
        from ipmc_model.persistence import load_model
        return load_model(path), f"loaded {path}"
    # A quick identification on the plant: 40 s of random-sine voltage at 100 Hz.
    plant = IpmcPlant(seed=2, dt_s=DT_S)
    drive = RandomSineReference(band_hz=(0.0, 0.7), range_mm=(-2.5, 2.5), seed=3)
    u = drive.sample(40.0, 1.0 / DT_S)[1]
    run = plant.run(u)
    t0 = time.perf_counter()
    model = InverseNarxModel().fit(run.u_v, run.y_mm)
    return model, f"fitted on 4000 plant samples in {time.perf_counter() - t0:.1f} s"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20000, help="steps per case")
    parser.add_argument("--model", help="inverse model file (default: fit one here)")
    parser.add_argument("--forward-model", help="forward model file with voltage channels: "
                        "time its online inversion too (and serve it in the graph run)")
    parser.add_argument("--graph", type=float, default=30.0, metavar="SECONDS",
                        help="also run the node graph over DDS (real-time clock) this long "
                             "(default 30; 0: skip)")
    args = parser.parse_args(argv)
    n = args.steps
    rows = []

    pid = PID()
    rows.append(("PID", _loop(lambda k, r, y: pid.compute_command(r, y, DT_S), n)))

    hyb = HybridController()
    rows.append(("hybrid (given u_ff)",
                 _loop(lambda k, r, y: hyb.compute_command(r, y, DT_S, 0.3 * r), n)))

    model, how = _inverse_model(args.model)
    if model is not None:
        rows.append(("inverse model + hybrid", _loop(_feedforward_hybrid(model.stepper()), n)))
        n_centers = getattr(model.regressor_, "n_centers_", "?")
        print(f"inverse model: {how}; {n_centers} kernel centres")
    else:
        print(f"inverse model case skipped: {how}")

    if args.forward_model:
        from ipmc_model.forward_inversion import ForwardInversionFeedforward
        from ipmc_model.persistence import load_model

        forward = load_model(args.forward_model)
        fwd = ForwardInversionFeedforward(forward).stepper()
        rows.append(("forward inversion + hybrid", _loop(_feedforward_hybrid(fwd), n)))
        print(f"forward model: {args.forward_model}; "
              f"{getattr(forward.regressor_, 'n_centers_', '?')} kernel centres; "
              f"{fwd.series_steps} of {n} steps by the series, bound "
              f"{fwd.series_error_bound_mm:.1e} mm")

    load = os.getloadavg()[0]
    print(f"\nper-step compute time, {n} steps each, closed loop on IpmcPlant at 100 Hz; "
          f"{os.cpu_count()} CPUs, load average {load:.1f}")
    print("wall = perf_counter (includes preemption by other processes), "
          "cpu = this thread's CPU time")
    print(f"{'case':<28}{'wall p50':>10}{'wall p99':>10}{'wall max':>10}"
          f"{'cpu p50':>10}{'cpu p99':>10}   (us)")
    for name, (wall, cpu) in rows:
        w50, w99, wmx = _stats(wall)
        c50, c99, _ = _stats(cpu)
        print(f"{name:<28}{w50:>10.1f}{w99:>10.1f}{wmx:>10.1f}{c50:>10.1f}{c99:>10.1f}")
    worst_wall = max(_stats(w)[1] for _, (w, _c) in rows)
    worst_cpu = max(_stats(c)[1] for _, (_w, c) in rows)
    for label, value in (("wall", worst_wall), ("cpu", worst_cpu)):
        verdict = "meets" if value <= 200.0 else "MISSES"
        print(f"worst {label} p99 {value:.1f} us: {verdict} the 200 us goal")
    if args.graph > 0 and args.forward_model:
        _graph(args.graph, args.forward_model, forward=True)
    elif args.graph > 0:
        model_file = args.model
        if model_file is None and model is not None:
            from ipmc_model.persistence import save_model

            model_file = str(save_model(model, Path(tempfile.mkdtemp()) / "inverse.json"))
        _graph(args.graph, model_file)
    return 0 if math.isfinite(worst_wall) else 1


def _graph(seconds: float, model_file: str | None, forward: bool = False) -> None:
    """sim_plant (real time) + reference + controller (+ model_server, hybrid, when there is an
    inverse model) over DDS; print the controller's loop diagnostics and the command intervals
    seen by a subscriber."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(1 + os.getpid() % 100),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray

    bin_dir = Path(sys.executable).parent
    mode = "hybrid" if model_file else "pid"
    argvs = [[str(bin_dir / "sim_plant")],
             [str(bin_dir / "reference"), "--ros-args", "-p", "kind:=sine"],
             [str(bin_dir / "controller"), "--ros-args", "-p", f"mode:={mode}"]]
    if model_file:
        argvs.append([str(bin_dir / "model_server"), "--ros-args", "-p",
                      f"{'model_file' if forward else 'inverse_model_file'}:={model_file}"]
                     + (["-p", "feedforward:=forward-inversion"] if forward else []))
    procs = [subprocess.Popen(a, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
             for a in argvs]
    loop: dict[str, str] = {}

    def on_diag(msg):
        for status in msg.status:
            if status.name == "controller: loop":
                loop.clear()
                loop.update({kv.key: kv.value for kv in status.values})

    rclpy.init()
    node = rclpy.create_node("bench_controller")
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    from std_msgs.msg import Float64

    arrivals: list[int] = []
    node.create_subscription(Float64, "/ipmc/command",
                             lambda m: arrivals.append(time.perf_counter_ns()), 100)
    try:
        # Measure from the first report with steps, so start-up (discovery) is not counted.
        deadline = time.monotonic() + 30.0
        while int(loop.get("ticks", 0)) == 0 and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        start = dict(loop)
        arrivals.clear()
        end_at = time.monotonic() + seconds
        while time.monotonic() < end_at:
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        for p in procs:
            p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                p.kill()
    if not start or not loop:
        print("\ngraph: no loop diagnostics from the controller")
        return
    ticks = int(loop["ticks"]) - int(start["ticks"])
    misses = int(loop["deadline_misses"]) - int(start["deadline_misses"])
    ratio = misses / ticks if ticks else math.nan
    verdict = "meets" if ratio < 1e-3 else "MISSES"
    print(f"\ngraph over DDS, {seconds:g} s at 100 Hz (sim_plant real time, {mode} mode"
          f"{', forward inversion in model_server' if forward else ''}): "
          f"{ticks} steps, {misses} deadline misses ({ratio:.3%}): {verdict} the 0.1 % goal; "
          f"step incl. publish p50 {loop['step_p50_us']} us, p99 {loop['step_p99_us']} us "
          f"(last 2000 steps)")
    if len(arrivals) > 2:
        gaps_ms = np.diff(np.asarray(arrivals, dtype=float)) / 1e6
        late = int(np.sum(gaps_ms > 15.0))
        print(f"/ipmc/command as received by a subscriber: {len(arrivals)} messages, interval "
              f"p50 {np.percentile(gaps_ms, 50):.2f} ms, p99 {np.percentile(gaps_ms, 99):.2f} "
              f"ms, max {gaps_ms.max():.2f} ms; {late} gaps > 1.5 periods "
              f"({late / gaps_ms.size:.3%}); load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    raise SystemExit(main())
