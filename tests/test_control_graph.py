"""The control graph as separate processes over real DDS.

sim_plant, reference, controller and the real model_server (serving a small inverse LSSVM-NARX
fitted here on 30 s of the simulated plant, fixed-size LSSVM with 200 centres) run as processes:

- model_server is killed (SIGKILL) mid-run: the controller keeps |u| <= 3 V, falls back to PID
  alone, says so on /diagnostics, and returns to hybrid when a new model_server comes up;
- run-time parameters are validated (refused with the reason);
- SIGINT to every node of a lock-step graph: each exits within 2 s.
"""

from __future__ import annotations

import functools
import signal
import time

import pytest

from ipmc_driver.plant import IpmcPlant
from ipmc_driver.signals import random_sine

rclpy = pytest.importorskip("rclpy")
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402

U_LIMIT_V = 3.0
EXIT_BUDGET_S = 2.0
OK, WARN = DiagnosticStatus.OK[0], DiagnosticStatus.WARN[0]


@pytest.fixture(scope="module")
def inverse_file(tmp_path_factory):
    """A small inverse model: good enough to drive a hybrid loop, quick to fit (~1 s)."""
    from threadpoolctl import threadpool_limits

    from ipmc_model.lssvm import FixedSizeLSSVMRegressor
    from ipmc_model.narx import InverseNarxModel
    from ipmc_model.persistence import save_model

    _, u = random_sine(30.0, 100.0, amplitude=3.0, seed=1)
    run = IpmcPlant(seed=1).run(u)
    reg = FixedSizeLSSVMRegressor(C=1e4, sigma=2.0, n_prototypes=200, seed=0)
    with threadpool_limits(1):
        model = InverseNarxModel(reg, input_lags=0, output_lags=6, lag_step=5)
        model.fit(run.u_v, run.y_mm)
    return save_model(model, tmp_path_factory.mktemp("control") / "inverse.json")


class Probe:
    """Listens to /ipmc/command and the controller's feedforward diagnostics."""

    def __init__(self, node):
        self.node = node
        self.commands: list[float] = []
        self.feedforward: list[tuple[int, str]] = []  # (level, message)
        node.create_subscription(Float64, "/ipmc/command",
                                 lambda m: self.commands.append(m.data), 100)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        self.params = node.create_client(SetParameters, "/controller/set_parameters")

    def _on_diag(self, msg):
        for s in msg.status:
            if s.name == "controller: feedforward":
                self.feedforward.append((s.level[0] if isinstance(s.level, bytes) else s.level,
                                         s.message))

    def last_feedforward(self):
        return self.feedforward[-1] if self.feedforward else (None, "")


def _start_model_server(processes, inverse_file, sim: dict):
    processes.start_node("model_server", "model_server",
                         {"inverse_model_file": inverse_file, "diagnostics_period_s": 0.5,
                          **sim})


def _start_graph(processes, inverse_file, lockstep: bool):
    sim = {"use_sim_time": "true"} if lockstep else {}
    processes.start_node("sim_plant", "sim_plant",
                         {"clock_mode": "lockstep" if lockstep else "realtime"})
    processes.start_node("reference", "reference", {"kind": "sine", "preview_s": 0.02, **sim})
    processes.start_node("controller", "controller",
                         {"mode": "hybrid", "feedforward_timeout_s": 0.2,
                          "diagnostics_period_s": 0.25,
                          "trigger": "measurement" if lockstep else "timer", **sim})
    _start_model_server(processes, inverse_file, sim)


def test_controller_falls_back_when_model_server_dies_and_recovers(
        processes, rclpy_context, spin, inverse_file):
    _start_graph(processes, inverse_file, lockstep=False)
    node = rclpy.create_node("control_graph_test", context=rclpy_context)
    hybrid = (OK, "fresh, mode hybrid")
    try:
        probe = Probe(node)
        assert spin(node, lambda: probe.last_feedforward() == hybrid
                    and len(probe.commands) > 100, 30.0), \
            f"hybrid loop did not come up: {probe.feedforward[-3:]}"
        processes.stop("model_server", signal.SIGKILL)
        assert spin(node, lambda: probe.last_feedforward()[0] == WARN, 5.0), \
            "no WARN on /diagnostics after model_server died"
        assert "PID alone" in probe.last_feedforward()[1]
        n_fallback = len(probe.commands)
        spin(node, lambda: False, 2.0)
        assert len(probe.commands) > n_fallback + 100, "commands stopped during the fallback"
        _start_model_server(processes, inverse_file, {})
        assert spin(node, lambda: probe.last_feedforward() == hybrid, 30.0), \
            f"did not return to hybrid: {probe.feedforward[-3:]}"
        n_back = len(probe.commands)
        assert spin(node, lambda: len(probe.commands) > n_back + 50, 5.0)
        assert max(abs(u) for u in probe.commands) <= U_LIMIT_V
        assert "feedforward stale" in processes.log("controller")
        assert "feedforward back" in processes.log("controller")
    finally:
        node.destroy_node()


def _set(node, client, call, log, **values):
    req = SetParameters.Request(parameters=[
        Parameter(k, value=v).to_parameter_msg() for k, v in values.items()])
    return call(node, client, req, timeout_s=20.0, server_log=log).results


def test_controller_parameters_validated_at_run_time(processes, rclpy_context, call):
    processes.start_node("controller", "controller")
    node = rclpy.create_node("control_params_test", context=rclpy_context)
    try:
        probe = Probe(node)
        log = functools.partial(processes.log, "controller")
        (res,) = _set(node, probe.params, call, log, ti_s=-1.0)
        assert not res.successful and "ti_s must be > 0" in res.reason
        (res,) = _set(node, probe.params, call, log, mode="open")
        assert not res.successful and "mode must be one of" in res.reason
        (res,) = _set(node, probe.params, call, log, u_clamp_min=5.0)
        assert not res.successful and "0 <= u_clamp_max <= 3" in res.reason
        (res,) = _set(node, probe.params, call, log, u_clamp_max=100.0)
        assert not res.successful and "the H-bridge's limit" in res.reason
        results = _set(node, probe.params, call, log, k=2.0, ti_s=0.5, mode="pid")
        assert all(r.successful for r in results), [r.reason for r in results]
    finally:
        node.destroy_node()


def test_sigint_stops_every_node_within_2s(processes, rclpy_context, spin, inverse_file):
    _start_graph(processes, inverse_file, lockstep=True)
    node = rclpy.create_node("control_sigint_test", context=rclpy_context)
    try:
        probe = Probe(node)
        assert spin(node, lambda: probe.last_feedforward() == (OK, "fresh, mode hybrid")
                    and len(probe.commands) > 50, 30.0), \
            f"lock-step hybrid loop not running: {probe.feedforward[-3:]}"
    finally:
        node.destroy_node()
    time.sleep(0.5)
    names = sorted(processes.procs)
    exit_s = processes.stop_all()
    assert sorted(exit_s) == names == ["controller", "model_server", "reference", "sim_plant"]
    assert all(t <= EXIT_BUDGET_S for t in exit_s.values()), exit_s
    # A clean exit, not a traceback: a signal raised inside rclpy's message conversion once
    # ended model_server with "RuntimeError: Unable to convert call argument" and status 1.
    assert processes.returncodes == {n: 0 for n in names}, {
        n: processes.log(n)[-600:] for n, c in processes.returncodes.items() if c != 0}


def test_realtime_reference_starts_its_time_once_min_subscribers_matched(processes,
                                                                          rclpy_context, spin):
    """In real time the reference's time 0 waits for ``min_subscribers`` matched listeners
    (model_server subscribes once its model has loaded): nothing is published before, and the
    first sample is the generator's value at t = 0, whenever the last listener came."""
    from geometry_msgs.msg import PointStamped

    from ipmc_driver.qos import SAMPLE_QOS

    processes.start_node("reference", "reference", {"kind": "sine", "amplitude_mm": 2.0,
                                                    "phase_rad": 1.5707963,
                                                    "min_subscribers": 2})
    node = rclpy.create_node("reference_realtime_gate_test", context=rclpy_context)
    try:
        first, second = [], []
        node.create_subscription(PointStamped, "/ipmc/reference",
                                 lambda m: first.append(m.point.x), SAMPLE_QOS)
        assert spin(node, lambda: node.count_publishers("/ipmc/reference") > 0, 20.0), \
            "reference not up"
        spin(node, lambda: False, 2.0)
        assert first == [], f"published before min_subscribers matched: {first[:5]}"
        node.create_subscription(PointStamped, "/ipmc/reference",
                                 lambda m: second.append(m.point.x), SAMPLE_QOS)
        assert spin(node, lambda: len(first) >= 3 and len(second) >= 3, 20.0), (first, second)
    finally:
        node.destroy_node()
    processes.stop("reference")
    # a sine with phase pi/2 starts at its crest: t = 0 came when the gate opened
    assert first[0] == pytest.approx(2.0e-3, rel=1e-3), first[:3]


def test_lockstep_reference_holds_its_first_samples_for_min_subscribers(processes,
                                                                         rclpy_context, spin):
    """On use_sim_time the reference's first burst waits until /ipmc/reference has matched
    ``min_subscribers`` subscriptions, even when the graph lists fewer (it can list a
    subscription late: model_server once missed the first three references and a lock-step
    run stalled 5 s at sample 0)."""
    from geometry_msgs.msg import PointStamped
    from rosgraph_msgs.msg import Clock

    from ipmc_driver.qos import LATCHED_CLOCK_QOS, SAMPLE_QOS

    processes.start_node("reference", "reference", {"kind": "sine", "preview_s": 0.02,
                                                    "use_sim_time": "true",
                                                    "min_subscribers": 2})
    node = rclpy.create_node("reference_gate_test", context=rclpy_context)
    try:
        first, second = [], []

        def stamp_ns(m):
            return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec

        node.create_subscription(PointStamped, "/ipmc/reference",
                                 lambda m: first.append(stamp_ns(m)), SAMPLE_QOS)
        clock = node.create_publisher(Clock, "/clock", LATCHED_CLOCK_QOS)
        clock.publish(Clock())   # t = 0
        assert spin(node, lambda: node.count_publishers("/ipmc/reference") > 0, 20.0), \
            "reference not up"
        # One listener of the two required: the burst stays held.
        spin(node, lambda: False, 2.0)
        assert first == [], f"published before min_subscribers matched: {first[:5]}"
        node.create_subscription(PointStamped, "/ipmc/reference",
                                 lambda m: second.append(stamp_ns(m)), SAMPLE_QOS)
        assert spin(node, lambda: len(first) >= 3 and len(second) >= 3, 20.0), (first, second)
    finally:
        node.destroy_node()
    processes.stop("reference")
    # Both volatile listeners got the burst from t = 0: 0, 10, 20 ms (preview 0.02 s).
    assert first[:3] == second[:3] == [0, 10_000_000, 20_000_000]
