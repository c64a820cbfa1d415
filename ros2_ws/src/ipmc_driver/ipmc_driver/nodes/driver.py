"""driver: the IPMC rig on the ROS graph over RS-485 (the only node that touches hardware).

Subscribes ``/ipmc/command`` (std_msgs/Float64, V); publishes ``/ipmc/voltage``
(Vector3Stamped: x applied V, y requested V) and ``/ipmc/displacement`` (PointStamped, x in m,
arc-compensated) for every sample frame of the rig, stamped ``t0 + counter / sample_rate_hz``
from the rig's sample counter, and ``/diagnostics`` (link, stream, command, watchdog).

Safety: commands are limited to ``u_max`` (never above 3 V); a non-finite command is sent as
0 V at once; without a command for ``watchdog_s`` the rig is commanded to 0 V; the setpoint is
repeated every 50 ms so that the rig's own watchdog (200 ms, docs/protocol.md) zeroes the
H-bridge only when this node or the cable is gone; on shutdown the rig is commanded to 0 V and
the port closed. A vanished port is reopened as soon as its device path reappears (else with a
back-off of 0.5 s doubling to 10 s). Parameters are checked at start-up and at run time; a bad
one is refused with its reason.

The link itself (state machine, watchdogs, counter, stamps) is ``ipmc_driver.link.DriverLink``;
this node maps topics, parameters and timers onto it.
"""

from __future__ import annotations

import time
from functools import partial

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_msgs.msg import Float64

from ipmc_driver.link import (
    DRIVER_PARAMETERS,
    TICK_PERIOD_S,
    DriverLink,
    LinkConfig,
    LinkSample,
    check_parameter,
    check_parameters,
)
from ipmc_driver.node_runtime import ParameterError, ParameterSpec, declare_checked, run_node
from ipmc_driver.qos import COMMAND_QOS, DIAGNOSTICS_QOS, SAMPLE_QOS

# The link's table with its checks, for declare_checked (a wrong type is one sentence too).
PARAMETERS = {name: ParameterSpec(p.default, p.description, p.read_only,
                                  partial(check_parameter, name))
              for name, p in DRIVER_PARAMETERS.items()}


class Driver(Node):
    def __init__(self, **node_kwargs) -> None:
        # node_kwargs (context, parameter_overrides) let tests build the node in process.
        super().__init__("driver", **node_kwargs)
        try:
            values = declare_checked(self, PARAMETERS)
            reason = check_parameters(values)  # the three arc lengths together
            if reason:
                raise ParameterError(reason)
        except ValueError:
            Node.destroy_node(self)
            raise
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.frame_id = values["frame_id"]
        self.link = DriverLink(LinkConfig.from_parameters(values), log=self._log,
                               on_frames=lambda: self._guard.trigger())

        self.pub_voltage = self.create_publisher(Vector3Stamped, "/ipmc/voltage", SAMPLE_QOS)
        self.pub_disp = self.create_publisher(PointStamped, "/ipmc/displacement", SAMPLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
        self.create_subscription(Float64, "/ipmc/command", self._on_command, COMMAND_QOS)
        self._guard = self.create_guard_condition(self._publish_samples)

        # Steady clock: the link and the watchdogs must not follow sim time.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(TICK_PERIOD_S, self._on_tick, clock=steady)
        self.create_timer(float(values["diagnostics_period_s"]), self._publish_diagnostics,
                          clock=steady)
        c = self.link.config
        self.get_logger().info(
            f"driver on {c.port} at {c.baudrate} Bd, rig sampling {c.sample_rate_hz:g} Hz, "
            f"u_max {c.u_max_v:g} V, watchdog {c.watchdog_s:g} s")

    # ------------------------------------------------------------------ parameters
    def _parameter_values(self) -> dict[str, object]:
        return {name: self.get_parameter(name).value for name in PARAMETERS}

    def _validate_parameters(self, params) -> SetParametersResult:
        values = self._parameter_values() | {p.name: p.value for p in params}
        reason = check_parameters(values)
        return SetParametersResult(successful=not reason, reason=reason)

    def _apply_parameters(self, params) -> None:
        self.link.reconfigure(LinkConfig.from_parameters(self._parameter_values()))

    # ------------------------------------------------------------------ callbacks
    def _log(self, level: str, text: str) -> None:
        # One call site per severity: rclpy refuses a call site whose severity changes.
        if level == "warn":
            self.get_logger().warn(text)
        else:
            self.get_logger().info(text)

    def _on_command(self, msg: Float64) -> None:
        self.link.command(msg.data, time.monotonic())

    def _on_tick(self) -> None:
        self.link.tick(time.monotonic())

    def _publish_samples(self) -> None:
        for sample in self.link.drain(lambda: self.get_clock().now().nanoseconds):
            self._publish(sample)

    def _publish(self, sample: LinkSample) -> None:
        v = Vector3Stamped()
        v.header.stamp.sec, v.header.stamp.nanosec = divmod(sample.stamp_ns, 1_000_000_000)
        v.header.frame_id = self.frame_id
        v.vector.x = sample.applied_v
        v.vector.y = sample.requested_v
        d = PointStamped()
        d.header = v.header
        d.point.x = sample.y_mm * 1e-3
        self.pub_voltage.publish(v)
        self.pub_disp.publish(d)

    def _publish_diagnostics(self) -> None:
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [
            DiagnosticStatus(level=bytes([r.level]), name=f"driver: {r.name}", message=r.message,
                             hardware_id=self.link.config.port,
                             values=[KeyValue(key=k, value=v) for k, v in r.values.items()])
            for r in self.link.diagnostics(time.monotonic())]
        self.pub_diag.publish(array)

    # ------------------------------------------------------------------ shutdown
    def destroy_node(self) -> None:
        """Make the rig safe first (0 V), then close the port and stop the reader."""
        self.link.shutdown()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    run_node(Driver, args, name="driver", doc=__doc__,
             usage="driver --ros-args -p port:=/dev/ttyUSB0 [-p baudrate:=115200 "
                   "-p sample_rate_hz:=100.0 -p u_max:=3.0 -p watchdog_s:=0.5 "
                   "-p arc_l2_mm:=20.0 -p arc_d_mm:=150.0]")


if __name__ == "__main__":
    main()
