"""The console's subscriber of ``ipmc bringup``: feeds :class:`ipmc_control.console.RunStats`
with the displacement, the reference and the driver's link diagnostics (rclpy, in the
``bringup`` process; the counting and rendering live in ``console``)."""

from __future__ import annotations

import time

from ipmc_control.console import RunStats


class RunMonitor:
    """A node in its own context, spun a little at a time by :meth:`spin_for`."""

    def __init__(self, stats: RunStats) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PointStamped
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        from ipmc_driver.qos import DIAGNOSTICS_QOS, SAMPLE_QOS

        self.stats = stats
        self.context = rclpy.Context()
        # bringup's own handlers stop the graph; rclpy's would shut this context down first
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("bringup_console", context=self.context,
                                      start_parameter_services=False)
        self.node.create_subscription(PointStamped, "/ipmc/displacement", self._on_sample,
                                      SAMPLE_QOS)
        self.node.create_subscription(PointStamped, "/ipmc/reference", self._on_reference,
                                      SAMPLE_QOS)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics,
                                      DIAGNOSTICS_QOS)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    @staticmethod
    def _stamp_ns(msg) -> int:
        return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec

    def _on_sample(self, msg) -> None:
        self.stats.on_sample(self._stamp_ns(msg), msg.point.x * 1e3, time.monotonic())

    def _on_reference(self, msg) -> None:
        self.stats.on_reference(self._stamp_ns(msg), msg.point.x * 1e3)

    def _on_diagnostics(self, msg) -> None:
        for status in msg.status:
            if status.name == "driver: link":
                self.stats.on_link({kv.key: kv.value for kv in status.values})

    def spin_for(self, seconds: float) -> None:
        """Take the messages that arrive within ``seconds`` of wall time."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            self.executor.spin_once(timeout_sec=min(left, 0.05))

    def close(self) -> None:
        import rclpy

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
