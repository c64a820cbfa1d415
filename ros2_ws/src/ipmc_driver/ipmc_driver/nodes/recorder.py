"""recorder: write chosen topics to a rosbag2 folder (MCAP or sqlite3) with ``rosbags``.

ros2cli/rosbag2 are not on PyPI, so this node stands in for ``ros2 bag record``; its bags are
split rosbag2 folders that ``ros2 bag info/play`` of a full ROS install reads (see
``ipmc_driver.bagio``).

- Timestamps: each message is stored at its *receive time* on the node's clock (what
  ``ros2 bag record`` does; with ``use_sim_time`` it is /clock time). The sampling instant stays
  in the message's header stamp, which ``ipmc_driver.dataio.load_record`` pairs on.
- Types come from the project's topic table (docs/interfaces.md); other topics are subscribed when
  a publisher appears, with its type and its reliability.
- Messages are taken raw (``raw=True``): the subscription hands over the publisher's CDR bytes,
  written as they are, with no deserialise/serialise round trip per message.
- ``await_publishers`` (lock-step runs; ``ipmc bringup`` and the launch files set it): those
  topics are subscribed first, and the others only once each has matched a publisher. A
  lock-step start waits for the recorder's displacement and reference subscriptions, so it
  then also waits for these: a late match once lost the first 1.9 s of model_server's
  feedforward, prediction and residual, with no warning.
- SIGINT and SIGTERM close the bag cleanly; a SIGKILL loses at most the data since the last
  flush (``flush_s``) after ``ipmc bag-recover``, at most the current split without it.
"""

from __future__ import annotations

import importlib
import sys
import time
from pathlib import Path

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import (
    QoSDurabilityPolicy,
    QoSHistoryPolicy,
    QoSProfile,
    QoSReliabilityPolicy,
)

from ipmc_driver.bagio import BagWriter
from ipmc_driver.matching import MatchGate
from ipmc_driver.node_runtime import (
    ParameterSpec,
    check_changes,
    declare_checked,
    one_of,
    positive,
    run_node,
)

DEFAULT_TOPICS = ["/ipmc/command", "/ipmc/voltage", "/ipmc/displacement", "/ipmc/reference"]
# docs/interfaces.md: topic -> (type, publishers known to be RELIABLE)
TOPIC_TABLE = {
    "/ipmc/command": ("std_msgs/msg/Float64", True),
    "/ipmc/voltage": ("geometry_msgs/msg/Vector3Stamped", True),
    "/ipmc/displacement": ("geometry_msgs/msg/PointStamped", True),
    "/ipmc/reference": ("geometry_msgs/msg/PointStamped", True),
    "/ipmc/feedforward": ("geometry_msgs/msg/Vector3Stamped", True),
    "/ipmc/predicted": ("geometry_msgs/msg/PointStamped", True),
    "/ipmc/residual": ("geometry_msgs/msg/PointStamped", True),
    "/diagnostics": ("diagnostic_msgs/msg/DiagnosticArray", None),
    "/clock": ("rosgraph_msgs/msg/Clock", None),
}
STORAGES = ("mcap", "sqlite3")
# Deep queue: a burst while a split is being closed must not overflow it.
RELIABLE_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=1000,
                          reliability=QoSReliabilityPolicy.RELIABLE,
                          durability=QoSDurabilityPolicy.VOLATILE)
BEST_EFFORT_QOS = QoSProfile(history=QoSHistoryPolicy.KEEP_LAST, depth=1000,
                             reliability=QoSReliabilityPolicy.BEST_EFFORT,
                             durability=QoSDurabilityPolicy.VOLATILE)
TICK_S = 0.1
AWAIT_LOG_S = 5.0   # how often to say which publishers the recorder still waits for, s


def _topics(value) -> str:
    names = [t for t in value if t]
    if not names:
        return "is empty; nothing to record"
    bad = [t for t in names if not t.startswith("/")]
    return f"must be absolute topic names, got {bad}" if bad else ""


# Every parameter is read-only: the bag is opened once, at start.
PARAMETERS = {
    "topics": ParameterSpec(list(DEFAULT_TOPICS), "topics to record", True, _topics),
    "output": ParameterSpec("", "bag folder to create ('' = ./ipmc_bag_<YYYYmmdd_HHMMSS>)",
                            True),
    "storage": ParameterSpec("mcap", "rosbag2 storage: mcap | sqlite3", True,
                             one_of(*STORAGES)),
    "split_s": ParameterSpec(60.0, "seconds per split file; a SIGKILL loses at most the "
                             "current one", True, positive),
    "flush_s": ParameterSpec(1.0, "seconds between pushes of buffered messages to the split "
                             "file", True, positive),
    "await_publishers": ParameterSpec(
        [""], "topics subscribed first; the others once each has matched a publisher (a "
        "lock-step start then waits for them too)", True),
}


def get_message(msgtype: str) -> type:
    """The message class of ``'pkg/msg/Type'`` (rosidl_runtime_py is not on PyPI)."""
    pkg, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


class Recorder(Node):
    def __init__(self, **node_kwargs) -> None:
        super().__init__("recorder", **node_kwargs)
        p = declare_checked(self, PARAMETERS)
        self.add_on_set_parameters_callback(lambda params: check_changes(PARAMETERS, params))

        topics = [t for t in p["topics"] if t]
        output = p["output"] or time.strftime("ipmc_bag_%Y%m%d_%H%M%S")
        storage = p["storage"]
        awaited = [t for t in p["await_publishers"] if t]
        wrong = [t for t in awaited if t not in topics or not TOPIC_TABLE.get(t, (0, 0))[1]]
        if wrong:
            known = ", ".join(t for t, (_, reliable) in TOPIC_TABLE.items() if reliable)
            raise ValueError(f"await_publishers {wrong}: each must be one of the recorded "
                             f"topics with reliable publishers ({known})")

        self.writer = BagWriter(Path(output).resolve(), storage=storage,
                                split_s=p["split_s"], flush_s=p["flush_s"])
        self._subs = {}
        self._pending = []
        for topic in awaited:
            self._subscribe(topic, TOPIC_TABLE[topic][0], RELIABLE_QOS)
        self._deferred = [t for t in topics if t not in awaited]
        self._await_gate = MatchGate(
            self.count_subscribers, [],
            inputs=[(self._subs[t], t, 1) for t in awaited if t in self._subs],
            count_publishers=self.count_publishers, warn=self.get_logger().warn)
        self._await_log = time.monotonic()
        self.get_logger().info(
            f"recording {', '.join(topics)} to {self.writer.path} ({storage}, split every "
            f"{self.writer.split_s:g} s); bag time = receive time"
            + (f"; the other topics once {', '.join(awaited)} have publishers" if awaited else ""))
        # Wall time: with use_sim_time a timer on /clock would not fire before the lock-step
        # start, which waits for the subscriptions this tick makes (and flushes must not stop
        # when simulated time does).
        self._timer = self.create_timer(TICK_S, self._on_tick,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._subscribe_deferred()

    def _subscribe_deferred(self) -> None:
        if not self._deferred:
            return
        if not self._await_gate.ready():
            if time.monotonic() - self._await_log >= AWAIT_LOG_S:
                self._await_log = time.monotonic()
                self.get_logger().info("waiting for publishers on " + ", ".join(
                    f"{t} ({m} of {n})" for t, (m, n) in self._await_gate.short().items()))
            return
        for topic in self._deferred:
            msgtype, reliable = TOPIC_TABLE.get(topic, (None, None))
            if msgtype and reliable:
                self._subscribe(topic, msgtype, RELIABLE_QOS)
            else:
                self._pending.append(topic)  # type or reliability from its publishers
        self._deferred = []

    def _subscribe(self, topic: str, msgtype: str, qos: QoSProfile) -> None:
        try:
            msg_class = get_message(msgtype)
            self.writer.add_topic(topic, msgtype)
        except (ValueError, ImportError, AttributeError) as exc:
            self.get_logger().error(f"not recording {topic}: {exc}")
            return
        self._subs[topic] = self.create_subscription(
            msg_class, topic, lambda data, t=topic: self._on_message(t, data), qos,
            raw=True)

    def _on_message(self, topic: str, data: bytes) -> None:
        self.writer.write(topic, self.get_clock().now().nanoseconds, data)

    def _on_tick(self) -> None:
        self.writer.tick()
        self._subscribe_deferred()
        for topic in list(self._pending):
            infos = self.get_publishers_info_by_topic(topic)
            if not infos:
                continue
            self._pending.remove(topic)
            msgtype = infos[0].topic_type
            # A reliable subscriber would not match a best-effort publisher: take the weaker.
            reliable = all(i.qos_profile.reliability == QoSReliabilityPolicy.RELIABLE
                           for i in infos)
            self._subscribe(topic, msgtype, RELIABLE_QOS if reliable else BEST_EFFORT_QOS)

    def destroy_node(self) -> None:
        # Every exit path comes here: the bag is closed (final split + metadata.yaml) once.
        if not self.writer.closed:
            self.writer.close()
            text = (f"closed {self.writer.path}: {self.writer.message_count} messages in "
                    f"{len(self.writer.files)} file(s)")
            if self.context.ok():
                self.get_logger().info(text)
            else:  # after SIGINT rclpy has shut the context down: /rosout is gone
                print(f"[recorder] {text}", file=sys.stderr)
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    # SIGINT and SIGTERM both unwind spin() into destroy_node(), which closes the bag.
    run_node(Recorder, args, name="recorder", doc=__doc__,
             usage="recorder [--ros-args -p output:=BAG -p topics:=[/ipmc/voltage,...] "
                   "-p storage:=mcap|sqlite3 -p split_s:=60.0 -p flush_s:=1.0 "
                   "-p await_publishers:=[/ipmc/feedforward,...]]")


if __name__ == "__main__":
    main()
