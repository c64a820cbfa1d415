"""model_server's staleness monitor over real DDS: /diagnostics goes from OK to "model stale".

The test is the plant: it publishes /ipmc/voltage and /ipmc/displacement (the same stamp per
sample) computed in process from ``IpmcPlant`` with a fast ``drift`` (dehydration: gain loss and
offset), paced by the /ipmc/residual it gets back, so no sample is lost and 30 s of plant time
take a few seconds. model_server runs with its default monitor (free-run residual, drift test)
on a small window, so that the reference, the OK checks and the drift fit in those 30 s.
"""

from __future__ import annotations

import numpy as np
import pytest

from ipmc_driver.plant import IpmcPlant
from ipmc_driver.signals import random_sine

rclpy = pytest.importorskip("rclpy")

RATE_HZ = 100.0
N_OK = 600              # samples streamed before the OK check (reference 300 + 6 checks)
N_ALL = 3000            # 30 s of plant time
IN_FLIGHT = 20          # samples published ahead of the residuals received
GRACE_S = 2.0           # the SIGINT exit budget (conftest.GRACE_S)
# Fast dehydration, so that 30 s show it: at the plant's defaults (3 %/min, 0.05 mm/min) the
# monitor needs minutes (ros2_ws/src/ipmc_model/test/test_residuals.py).
DRIFT = {"drift": {"gain_loss_per_min": 0.5, "offset_mm_per_min": 3.0}}
MONITOR = {"monitor_decimate": 1, "monitor_window": 200, "monitor_reference": 300,
           "monitor_check_every": 50, "monitor_patience": 3}


@pytest.fixture(scope="module")
def forward_file(tmp_path_factory):
    """A small forward LSSVM-NARX (input lags only) fitted on 60 s of the clean plant."""
    from ipmc_model.lssvm import LSSVMRegressor
    from ipmc_model.narx import NarxModel
    from ipmc_model.persistence import save_model

    _, u = random_sine(60.0, RATE_HZ, amplitude=2.5, seed=1)
    run = IpmcPlant(seed=1).run(u)
    model = NarxModel(LSSVMRegressor(C=1000.0, sigma=3.0), input_lags=12, output_lags=0,
                      lag_step=10, max_rows=600).fit(run.u_v, run.y_mm)
    return model, save_model(model, tmp_path_factory.mktemp("models") / "forward.json")


def _stamp(k: int):
    from builtin_interfaces.msg import Time

    return Time(sec=1000 + k // 100, nanosec=(k % 100) * 10_000_000)


class Stream:
    """Publishes the plant's samples, receives residuals and model_server's residual status."""

    def __init__(self, context, u_v, y_mm):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PointStamped, Vector3Stamped
        from rclpy.qos import QoSHistoryPolicy, QoSProfile, QoSReliabilityPolicy

        qos = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=100,
                         reliability=QoSReliabilityPolicy.RELIABLE)
        self.node = rclpy.create_node("monitor_probe", context=context)
        self.pub_u = self.node.create_publisher(Vector3Stamped, "/ipmc/voltage", qos)
        self.pub_y = self.node.create_publisher(PointStamped, "/ipmc/displacement", qos)
        self.residuals = []
        self.node.create_subscription(PointStamped, "/ipmc/residual", self.residuals.append, qos)
        self.status = []     # model_server: residual
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        self.u_v, self.y_mm = u_v, y_mm
        self.k = 0

    def _on_diag(self, msg) -> None:
        self.status += [s for s in msg.status if s.name == "model_server: residual"]

    def publish_next(self) -> None:
        from geometry_msgs.msg import PointStamped, Vector3Stamped

        k = self.k
        u = Vector3Stamped()
        u.header.stamp, u.header.frame_id = _stamp(k), "ipmc_clamp"
        u.vector.x = u.vector.y = float(self.u_v[k])
        y = PointStamped()
        y.header = u.header
        y.point.x = float(self.y_mm[k]) * 1e-3
        self.pub_u.publish(u)
        self.pub_y.publish(y)
        self.k += 1

    def run_to(self, n: int, spin, timeout_s: float) -> bool:
        """Publish up to sample ``n``, at most IN_FLIGHT ahead of the residuals received."""
        def done() -> bool:
            while self.k < n and self.k < len(self.residuals) + IN_FLIGHT:
                self.publish_next()
            return len(self.residuals) >= n

        return spin(self.node, done, timeout_s)

    def status_after(self, n_residuals: int, spin, timeout_s: float = 5.0):
        """The first residual status published after the node had ``n_residuals``."""
        def later():
            return [s for s in self.status if int(_value(s, "residuals")) >= n_residuals]

        assert spin(self.node, lambda: bool(later()), timeout_s), "no /diagnostics"
        return later()[0]


def _value(status, key: str) -> str:
    return {kv.key: kv.value for kv in status.values}[key]


def test_diagnostics_turn_from_ok_to_model_stale_on_a_drifting_plant(
        forward_file, processes, rclpy_context, spin):
    model, path = forward_file
    t = np.arange(N_ALL) / RATE_HZ
    u = 2.0 * np.sin(2 * np.pi * 1.0 * t)
    y = IpmcPlant(seed=5, effects=DRIFT).run(u).y_mm
    processes.start_node("model_server", "model_server", {
        "model_file": path, "diagnostics_period_s": 0.2, **MONITOR})
    stream = Stream(rclpy_context, u, y)
    node = stream.node
    try:
        def matched() -> bool:
            return (stream.pub_u.get_subscription_count() > 0
                    and stream.pub_y.get_subscription_count() > 0
                    and node.count_publishers("/ipmc/residual") > 0
                    and bool(stream.status))

        assert spin(node, matched, 30.0), "graph did not come up:\n" + processes.log(
            "model_server")
        spin(node, lambda: False, 0.3)   # let the reader side of every match settle
        first = stream.status[-1]
        assert first.level == b"\x00"
        assert _value(first, "monitor_residual") == "free_run"   # the defaults
        assert _value(first, "monitor_test") == "drift"

        # (1) The reference and six checks on the freshly loaded model: OK.
        assert stream.run_to(N_OK, spin, 30.0), processes.log("model_server")
        ok = stream.status_after(N_OK, spin)
        print("OK phase:", ok.message)
        assert ok.level == b"\x00", ok.message
        assert ok.message.startswith("residual as when fitted"), ok.message
        assert _value(ok, "stale") == "False"
        assert _value(ok, "reference_samples") == "300/300"
        assert abs(float(_value(ok, "mean_shift_mm"))) < float(
            _value(ok, "mean_shift_limit_mm"))
        # the node's monitor saw the free-run residual: the same reference as in process
        stepper = model.stepper()
        e_ref = np.array([y[k] - stepper.step(u[k]) for k in range(300)])
        np.testing.assert_allclose(float(_value(ok, "reference_mean_mm")), e_ref.mean(),
                                   rtol=0, atol=1e-3)
        np.testing.assert_allclose(float(_value(ok, "reference_spread_mm")), e_ref.std(),
                                   rtol=1e-3, atol=1e-4)

        # (2) The plant keeps drifting: WARN "model stale" with the statistic and threshold.
        assert stream.run_to(N_ALL, spin, 60.0), processes.log("model_server")
        stale = stream.status_after(N_ALL, spin)
        print("stale phase:", stale.message)
        assert stale.level == b"\x01", stale.message
        assert stale.message.startswith("model stale: residual mean moved"), stale.message
        assert _value(stale, "stale") == "True"
        shift = float(_value(stale, "mean_shift_mm"))
        limit = float(_value(stale, "mean_shift_limit_mm"))
        assert shift > limit > 0       # offset drift is upwards
        assert f"{limit:.3g} mm" in stale.message
        assert int(_value(stale, "failed_checks")) >= 3
        levels = [s.level for s in stream.status]
        assert levels.index(b"\x01") > 0 and b"\x02" not in levels
    finally:
        node.destroy_node()
    assert processes.stop("model_server") < GRACE_S


def test_one_step_residual_keeps_the_whiteness_test_and_bad_values_are_refused(
        forward_file, processes, rclpy_context, spin):
    _, path = forward_file
    processes.start_node("model_server", "model_server", {
        "model_file": path, "diagnostics_period_s": 0.2, "monitor_residual": "one_step"})
    processes.start_node("bad", "model_server", {
        "model_file": path, "monitor_test": "sometimes"})
    stream = Stream(rclpy_context, np.zeros(1), np.zeros(1))
    try:
        assert spin(stream.node, lambda: bool(stream.status), 30.0), processes.log(
            "model_server")
        s = stream.status[-1]
        assert _value(s, "monitor_test") == "whiteness"
        assert _value(s, "monitor_residual") == "one_step"
        assert s.level == b"\x00"
    finally:
        stream.node.destroy_node()
    assert processes.procs["bad"].wait(timeout=30) == 1
    assert "monitor_test must be one of" in processes.log("bad")
    assert processes.stop("model_server") < GRACE_S
