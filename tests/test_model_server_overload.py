"""model_server under overload, over real DDS: references faster than it answers them.

Every reference is either answered or counted on /diagnostics (``skipped``), and the newest
is answered: the server once left 45 % of a 2.8 kHz reference stream unanswered while its
diagnostics said "skipped: 0" (the subscription's queue overwrote them unseen).
"""

from __future__ import annotations

import time

import pytest

from ipmc_driver.plant import IpmcPlant
from ipmc_driver.signals import random_sine

rclpy = pytest.importorskip("rclpy")

RATE_HZ = 3000.0
SECONDS = 2.0


@pytest.fixture(scope="module")
def inverse_file(tmp_path_factory):
    from ipmc_model.lssvm import FixedSizeLSSVMRegressor
    from ipmc_model.narx import InverseNarxModel
    from ipmc_model.persistence import save_model

    _, u = random_sine(20.0, 100.0, amplitude=2.5, seed=1)
    run = IpmcPlant(seed=1).run(u)
    reg = FixedSizeLSSVMRegressor(C=100.0, sigma=3.0, n_prototypes=300, seed=0)
    model = InverseNarxModel(reg, lag_step=5).fit(run.u_v, run.y_mm)
    return str(save_model(model, tmp_path_factory.mktemp("overload") / "inverse.json"))


def _publish_fast(node, pub, n: int) -> None:
    """Publish ``n`` references at RATE_HZ (a busy loop: a timer cannot keep 3 kHz)."""
    from geometry_msgs.msg import PointStamped

    t0 = time.monotonic()
    for k in range(n):
        while time.monotonic() - t0 < k / RATE_HZ:
            pass
        msg = PointStamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(k * 333_333, 1_000_000_000)
        msg.point.x = 1e-3 * ((k % 300) / 150.0 - 1.0)
        pub.publish(msg)


def test_every_reference_is_answered_or_counted_and_the_newest_answered(
        inverse_file, processes, rclpy_context, spin):
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PointStamped, Vector3Stamped

    from ipmc_driver.qos import PAIRED_SAMPLE_QOS, SAMPLE_QOS

    processes.start_node("model_server", "model_server", {
        "inverse_model_file": inverse_file, "diagnostics_period_s": 0.5})
    node = rclpy.create_node("overload_probe", context=rclpy_context)
    stamps, status = [], []

    def on_diag(msg) -> None:
        status.extend(s for s in msg.status if s.name == "model_server: feedforward")

    try:
        pub = node.create_publisher(PointStamped, "/ipmc/reference", PAIRED_SAMPLE_QOS)
        node.create_subscription(Vector3Stamped, "/ipmc/feedforward", lambda m: stamps.append(
            m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec), SAMPLE_QOS)
        node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
        assert spin(node, lambda: pub.get_subscription_count() > 0 and node.count_publishers(
            "/ipmc/feedforward") > 0 and status, 30.0), processes.log("model_server")
        spin(node, lambda: False, 0.5)
        n = int(RATE_HZ * SECONDS)
        _publish_fast(node, pub, n)

        def values() -> dict:
            return {kv.key: kv.value for kv in status[-1].values}

        def accounted() -> bool:
            v = values()
            return int(v["count"]) + int(v["skipped"]) >= n

        spin(node, accounted, 10.0)
        v = values()
        print(f"{n} references: {v['count']} answered, {v['skipped']} skipped "
              f"({v.get('skipped_late')} late, {v.get('lost')} lost, "
              f"{v.get('skipped_invalid')} invalid)")
        assert int(v["count"]) + int(v["skipped"]) == n, v
        last_ns = (n - 1) * 333_333
        assert spin(node, lambda: last_ns in stamps, 5.0), "the newest reference unanswered"
        if int(v["skipped"]):
            assert any(s.level == b"\x01" and "unanswered" in s.message for s in status)
    finally:
        node.destroy_node()
    assert processes.stop("model_server") <= 2.0
