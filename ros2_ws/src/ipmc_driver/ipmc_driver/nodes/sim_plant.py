"""sim_plant: the simulated IPMC rig on the ROS graph (stands in when the rig is absent).

Subscribes ``/ipmc/command`` (std_msgs/Float64, V); publishes ``/ipmc/voltage``
(Vector3Stamped: x applied V, y requested V) and ``/ipmc/displacement`` (PointStamped, x in m)
at ``rate_hz``, stamped with the sampling instant.

Clocks (``clock_mode``):
- ``realtime``: a wall-clock timer samples the plant at ``rate_hz``.
- ``lockstep``: the plant owns time and publishes ``/clock``; after each sample it waits for the
  next command (at most ``lockstep_timeout_s`` of wall time; not at all when nobody publishes
  commands), so an experiment runs as fast as the graph answers. Other nodes set
  ``use_sim_time:=true``. When someone publishes ``/ipmc/command_stamped`` (Vector3Stamped, x
  in V, stamped with the sample it answers: the ``controller`` does), the plant waits for the
  command stamped with the sample it just published and applies that one: a late command for
  an older sample, or a second one for the same sample, can then never shift every later
  command by a sample (a bare Float64 cannot say which sample it answers). A sample stepped on
  without its command is logged as a warning ("lock-step: no command for the sample at ...").
  Who publishes commands is read from the DDS matches of the plant's own subscriptions, not
  from the ROS graph, which can lag them; time starts once ``lockstep_min_command_publishers``
  publishers of ``/ipmc/command_stamped`` have matched (``ipmc track`` and ``ipmc bringup`` set
  it), so the first samples cannot run ahead of a controller the graph does not list yet.
"""

from __future__ import annotations

import math
import time

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PointStamped, Vector3Stamped
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import Float64

from ipmc_driver.dataio import stamp_ns
from ipmc_driver.matching import MatchGate
from ipmc_driver.node_runtime import run_node
from ipmc_driver.plant import EFFECTS, IpmcPlant, load_plant_params
from ipmc_driver.qos import COMMAND_QOS, LATCHED_CLOCK_QOS, SAMPLE_QOS

CLOCK_MODES = ("realtime", "lockstep")


def to_time_msg(t_s: float) -> Time:
    # Round once to integer nanoseconds: rounding the fraction alone can give 1e9 ns.
    sec, nanosec = divmod(int(round(t_s * 1e9)), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


class SimPlant(Node):
    def __init__(self) -> None:
        super().__init__("sim_plant")
        ro = ParameterDescriptor(read_only=True)
        self.declare_parameter("rate_hz", 100.0, ParameterDescriptor(
            description="sample rate (Hz)", read_only=True))
        self.declare_parameter("clock_mode", "realtime", ParameterDescriptor(
            description="realtime | lockstep (publishes /clock)", read_only=True))
        self.declare_parameter("lockstep_timeout_s", 0.2, ParameterDescriptor(
            description="lockstep: longest wall-time wait for a command before stepping anyway"))
        self.declare_parameter("lockstep_min_subscribers", 1, ParameterDescriptor(
            description="lockstep: time starts once this many subscriptions to "
                        "/ipmc/displacement have matched (so a late recorder misses nothing), "
                        "and every one the graph shows on /ipmc/displacement, /ipmc/voltage and "
                        "/clock (for at most 5 s)", read_only=True))
        self.declare_parameter("lockstep_min_clock_subscribers", 0, ParameterDescriptor(
            description="lockstep: ... and this many to /clock (nodes on use_sim_time)",
            read_only=True))
        self.declare_parameter("lockstep_min_command_publishers", 0, ParameterDescriptor(
            description="lockstep: ... and this many publishers of /ipmc/command_stamped (a "
                        "controller with trigger:=measurement) have matched, and every one the "
                        "graph shows on it and on /ipmc/command (for at most 5 s)",
            read_only=True))
        self.declare_parameter("params_file", "", ParameterDescriptor(
            description="plant parameter YAML ('' = shipped default)", read_only=True))
        self.declare_parameter("effects", [""], ParameterDescriptor(
            description=f"optional plant effects: {', '.join(EFFECTS)}", read_only=True))
        self.declare_parameter("seed", 0, ro)
        self.declare_parameter("frame_id", "ipmc_clamp", ro)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        rate_hz = float(self.get_parameter("rate_hz").value)
        mode = self.get_parameter("clock_mode").value
        if rate_hz <= 0 or mode not in CLOCK_MODES:
            raise ValueError(f"need rate_hz > 0 and clock_mode in {CLOCK_MODES}, "
                             f"got {rate_hz} and '{mode}'")
        self.lockstep = mode == "lockstep"
        self.dt_s = 1.0 / rate_hz
        effects = [e for e in self.get_parameter("effects").value if e]
        params = load_plant_params(self.get_parameter("params_file").value or None)
        self.plant = IpmcPlant(params, effects=effects, seed=self.get_parameter("seed").value,
                               dt_s=self.dt_s)
        self.frame_id = self.get_parameter("frame_id").value
        self.command_v = 0.0
        self.command_count = 0
        self._count_at_sample = 0
        self._sample_wall = 0.0
        self.unanswered = 0       # lock-step samples stepped on without their command

        self.pub_voltage = self.create_publisher(Vector3Stamped, "/ipmc/voltage", SAMPLE_QOS)
        self.pub_disp = self.create_publisher(PointStamped, "/ipmc/displacement", SAMPLE_QOS)
        self.pub_clock = (self.create_publisher(ClockMsg, "/clock", LATCHED_CLOCK_QOS)
                          if self.lockstep else None)
        self.sub_command = self.create_subscription(Float64, "/ipmc/command", self._on_command,
                                                    COMMAND_QOS)
        self._sample_ns = -1      # stamp of the last published sample
        self._answer_v: float | None = None  # the stamped command answering it, V
        self.sub_command_stamped = (
            self.create_subscription(Vector3Stamped, "/ipmc/command_stamped",
                                     self._on_command_stamped, COMMAND_QOS)
            if self.lockstep else None)

        wall = Clock(clock_type=ClockType.STEADY_TIME)
        if self.lockstep:
            # Time stands still until everyone expected listens, matched by DDS and not only
            # seen on the graph: no sample is lost at start-up (ipmc_driver.matching).
            self._start_gate = MatchGate(self.count_subscribers, [
                (self.pub_disp, "/ipmc/displacement",
                 max(1, int(self.get_parameter("lockstep_min_subscribers").value))),
                (self.pub_voltage, "/ipmc/voltage", 0),
                (self.pub_clock, "/clock",
                 int(self.get_parameter("lockstep_min_clock_subscribers").value))],
                inputs=[
                    (self.sub_command_stamped, "/ipmc/command_stamped",
                     int(self.get_parameter("lockstep_min_command_publishers").value)),
                    (self.sub_command, "/ipmc/command", 0)],
                count_publishers=self.count_publishers, warn=self.get_logger().warn)
            self._t0 = 0.0
            self.create_timer(0.0005, self._on_lockstep_tick, clock=wall)
        else:
            self._t0 = self.get_clock().now().nanoseconds * 1e-9
            self.create_timer(self.dt_s, self._on_tick, clock=wall)
        self.get_logger().info(
            f"simulated IPMC at {rate_hz:g} Hz, clock {mode}, effects {effects or 'none'}")

    def _on_set_parameters(self, params) -> SetParametersResult:
        for p in params:
            if p.name == "lockstep_timeout_s" and not (p.value > 0):
                return SetParametersResult(successful=False,
                                           reason="lockstep_timeout_s must be > 0 seconds")
        return SetParametersResult(successful=True)

    def _on_command(self, msg: Float64) -> None:
        if math.isfinite(msg.data):
            self.command_v = float(msg.data)
            self.command_count += 1
        else:
            self.get_logger().warn("ignoring a non-finite command", throttle_duration_sec=1.0)

    def _on_command_stamped(self, msg: Vector3Stamped) -> None:
        if stamp_ns(msg.header.stamp) == self._sample_ns and math.isfinite(msg.vector.x):
            self._answer_v = float(msg.vector.x)

    def _on_tick(self) -> None:
        self._publish_sample(*self.plant.step(self.command_v))

    def _on_lockstep_tick(self) -> None:
        if not self._start_gate.ready():
            return
        waited = time.monotonic() - self._sample_wall
        timeout = self.get_parameter("lockstep_timeout_s").value
        # Matched publishers, not the graph's: the graph can list them late (see above).
        if self.sub_command_stamped.get_publisher_count() > 0:
            if self._answer_v is not None:
                self.command_v = self._answer_v
            elif waited < timeout:
                return
            else:
                self._note_unanswered(timeout)
            self._publish_sample(*self.plant.step(self.command_v))
            return
        answered = self.command_count > self._count_at_sample
        nobody = self.sub_command.get_publisher_count() == 0
        if answered or nobody or waited >= timeout:
            if not (answered or nobody):
                self._note_unanswered(timeout)
            self._publish_sample(*self.plant.step(self.command_v))

    def _note_unanswered(self, timeout_s: float) -> None:
        # A sample stepped on without its command: the graph is no longer the in-process loop.
        if self._sample_ns < 0:
            return   # time starts: no sample was waiting
        self.unanswered += 1
        self.get_logger().warn(
            f"lock-step: no command for the sample at {self._sample_ns * 1e-9:.3f} s within "
            f"{timeout_s:g} s: stepped on with the last one ({self.unanswered} so far)",
            throttle_duration_sec=1.0)

    def _publish_sample(self, u_applied_v: float, y_mm: float) -> None:
        # plant.t_s is already the next sample's time: this sample was taken one period earlier.
        stamp = to_time_msg(self._t0 + self.plant.t_s - self.dt_s)
        self._sample_ns = stamp_ns(stamp)
        self._answer_v = None
        if self.pub_clock is not None:
            self.pub_clock.publish(ClockMsg(clock=stamp))
        v = Vector3Stamped()
        v.header.stamp = stamp
        v.header.frame_id = self.frame_id
        v.vector.x = u_applied_v
        v.vector.y = self.command_v
        d = PointStamped()
        d.header = v.header
        d.point.x = y_mm * 1e-3
        self.pub_voltage.publish(v)
        self.pub_disp.publish(d)
        self._count_at_sample = self.command_count
        self._sample_wall = time.monotonic()


def main(args: list[str] | None = None) -> None:
    run_node(SimPlant, args, name="sim_plant", doc=__doc__,
             usage="sim_plant [--ros-args -p rate_hz:=100.0 -p clock_mode:=realtime|lockstep "
                   "-p effects:=[creep] -p seed:=0 -p params_file:=FILE.yaml]")


if __name__ == "__main__":
    main()
