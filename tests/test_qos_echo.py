"""What ``ros2 topic echo`` needs on the transient-local sample topics (docs/interfaces.md).

ros2cli is not on PyPI; its echo (Jazzy) subscribes with the ``sensor_data`` preset (keep last
5) and, without QoS flags, takes the publishers' durability when all offer the same: transient
local on ``/ipmc/reference`` and ``/ipmc/feedforward``. Fast DDS then reports lost messages on
that depth-5 transient-local reader ("A message was lost!!!"). The documented flags
``--qos-reliability reliable --qos-durability volatile`` give the subscription built here:
it receives the stream without a lost message, bursts of a lock-step reference included.
"""

from __future__ import annotations

import time

import pytest

rclpy = pytest.importorskip("rclpy")


def echo_qos(reliability: str, durability: str):
    """The profile ``ros2 topic echo --qos-reliability R --qos-durability D`` subscribes with:
    the sensor_data preset with those two policies replaced."""
    from rclpy.qos import (
        QoSDurabilityPolicy,
        QoSPresetProfiles,
        QoSReliabilityPolicy,
    )

    qos = QoSPresetProfiles.get_from_short_key("sensor_data")
    qos.reliability = QoSReliabilityPolicy.get_from_short_key(reliability)
    qos.durability = QoSDurabilityPolicy.get_from_short_key(durability)
    return qos


def test_echo_with_the_documented_flags_gets_the_reference_without_losses(
        processes, rclpy_context, spin):
    from geometry_msgs.msg import PointStamped
    from rclpy.event_handler import SubscriptionEventCallbacks
    from rclpy.qos import QoSDurabilityPolicy

    # 1 kHz with 20 ms of preview: bursts like a lock-step run's
    processes.start_node("reference", "reference", {"rate_hz": 1000.0, "preview_s": 0.02})
    node = rclpy.create_node("echo_like", context=rclpy_context)
    got, lost = [], []

    def printed(msg) -> None:
        got.append(msg)
        time.sleep(0.001)   # echo formats and prints each message: a slow reader

    try:
        assert spin(node, lambda: node.get_publishers_info_by_topic("/ipmc/reference"), 20.0)
        infos = node.get_publishers_info_by_topic("/ipmc/reference")
        # why echo needs the flags: every publisher offers transient local
        assert all(i.qos_profile.durability == QoSDurabilityPolicy.TRANSIENT_LOCAL
                   for i in infos)
        node.create_subscription(
            PointStamped, "/ipmc/reference", printed, echo_qos("reliable", "volatile"),
            event_callbacks=SubscriptionEventCallbacks(
                message_lost=lambda status: lost.append(status.total_count_change)))
        spin(node, lambda: False, 3.0)
    finally:
        node.destroy_node()
    assert len(got) > 300, len(got)
    assert lost == [], f"{sum(lost)} messages reported lost"
