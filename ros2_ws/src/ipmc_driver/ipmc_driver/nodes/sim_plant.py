"""sim_plant: the simulated IPMC rig on the ROS graph (stands in when the rig is absent).

Subscribes ``/ipmc/command`` (std_msgs/Float64, V); publishes ``/ipmc/voltage``
(Vector3Stamped: x applied V, y requested V) and ``/ipmc/displacement`` (PointStamped, x in m)
at ``rate_hz``, stamped with the sampling instant.

Clocks (``clock_mode``):
- ``realtime``: a wall-clock timer samples the plant at ``rate_hz``. Sample ``k`` is stamped
  ``t0 + k / rate_hz`` and published once the node's clock has passed its period
  (``ipmc_driver.sample_clock``): a tick that comes late publishes the samples it missed, so
  the stamps stay with the clock however loaded the machine is. ``/diagnostics`` status
  ``sim_plant: rate`` (every ``diagnostics_period_s`` of wall time) gives the requested rate,
  the timer's achieved rate and the samples published late or skipped; it is WARN "rate not
  held: ..." when the timer fell behind.
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
  it), so the first samples cannot run ahead of a controller the graph does not list yet;
  once they have all left (an excitation at its end, a controller stopped), time stands still
  until one returns or the plant is stopped.
"""

from __future__ import annotations

import math
import time

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, Vector3Stamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import Float64

from ipmc_driver.dataio import stamp_ns
from ipmc_driver.matching import MatchGate
from ipmc_driver.node_runtime import (
    ParameterSpec,
    check_changes,
    declare_checked,
    non_negative,
    one_of,
    positive,
    run_node,
)
from ipmc_driver.plant import EFFECTS, IpmcPlant, load_plant_params
from ipmc_driver.qos import COMMAND_QOS, DIAGNOSTICS_QOS, LATCHED_CLOCK_QOS, SAMPLE_QOS
from ipmc_driver.sample_clock import SampleClock

CLOCK_MODES = ("realtime", "lockstep")
HARDWARE_ID = "ipmc"


def _effects(value) -> str:
    unknown = [e for e in value if e and e not in EFFECTS]
    return f"has unknown effects {unknown}; known: {', '.join(EFFECTS)}" if unknown else ""


PARAMETERS = {
    "rate_hz": ParameterSpec(100.0, "sample rate (Hz)", True, positive),
    "clock_mode": ParameterSpec("realtime", "realtime | lockstep (publishes /clock)", True,
                                one_of(*CLOCK_MODES)),
    "lockstep_timeout_s": ParameterSpec(
        0.2, "lockstep: longest wall-time wait for a command before stepping anyway",
        check=positive),
    "lockstep_min_subscribers": ParameterSpec(
        1, "lockstep: time starts once this many subscriptions to /ipmc/displacement have "
        "matched (so a late recorder misses nothing), and every one the graph shows on "
        "/ipmc/displacement, /ipmc/voltage and /clock (for at most 5 s)", True, non_negative),
    "lockstep_min_clock_subscribers": ParameterSpec(
        0, "lockstep: ... and this many to /clock (nodes on use_sim_time)", True,
        non_negative),
    "lockstep_min_command_publishers": ParameterSpec(
        0, "lockstep: ... and this many publishers of /ipmc/command_stamped (a controller "
        "with trigger:=measurement) have matched, and every one the graph shows on it and on "
        "/ipmc/command (for at most 5 s)", True, non_negative),
    "params_file": ParameterSpec("", "plant parameter YAML ('' = shipped default)", True),
    "effects": ParameterSpec([""], f"optional plant effects: {', '.join(EFFECTS)}", True,
                             _effects),
    "seed": ParameterSpec(0, "seed of the measurement noise", True, non_negative),
    "frame_id": ParameterSpec("ipmc_clamp", "frame of the samples", True),
    "diagnostics_period_s": ParameterSpec(1.0, "wall-clock period of /diagnostics, s", True,
                                          positive),
}


def to_time_msg(t_s: float) -> Time:
    # Round once to integer nanoseconds: rounding the fraction alone can give 1e9 ns.
    sec, nanosec = divmod(int(round(t_s * 1e9)), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


class SimPlant(Node):
    def __init__(self, **node_kwargs) -> None:
        super().__init__("sim_plant", **node_kwargs)
        p = declare_checked(self, PARAMETERS)
        self.add_on_set_parameters_callback(lambda params: check_changes(PARAMETERS, params))

        self.lockstep = p["clock_mode"] == "lockstep"
        self.dt_s = 1.0 / p["rate_hz"]
        effects = [e for e in p["effects"] if e]
        try:
            params = load_plant_params(p["params_file"] or None)
        except OSError as exc:
            raise ValueError(f"parameter params_file: {exc}") from None
        self.plant = IpmcPlant(params, effects=effects, seed=p["seed"], dt_s=self.dt_s)
        self.frame_id = p["frame_id"]
        self.command_v = 0.0
        self.command_count = 0
        self._count_at_sample = 0
        self._sample_wall = 0.0
        self.unanswered = 0       # lock-step samples stepped on without their command
        self.sample_clock = SampleClock(p["rate_hz"])

        self.pub_voltage = self.create_publisher(Vector3Stamped, "/ipmc/voltage", SAMPLE_QOS)
        self.pub_disp = self.create_publisher(PointStamped, "/ipmc/displacement", SAMPLE_QOS)
        self.pub_clock = (self.create_publisher(ClockMsg, "/clock", LATCHED_CLOCK_QOS)
                          if self.lockstep else None)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
        self.sub_command = self.create_subscription(Float64, "/ipmc/command", self._on_command,
                                                    COMMAND_QOS)
        self._sample_ns = -1      # stamp of the last published sample
        self._answer_v: float | None = None  # the stamped command answering it, V
        self.sub_command_stamped = (
            self.create_subscription(Vector3Stamped, "/ipmc/command_stamped",
                                     self._on_command_stamped, COMMAND_QOS)
            if self.lockstep else None)
        self._create_timers(p)
        self.get_logger().info(
            f"simulated IPMC at {p['rate_hz']:g} Hz, clock {p['clock_mode']}, effects "
            f"{effects or 'none'}")

    def _create_timers(self, p: dict) -> None:
        wall = Clock(clock_type=ClockType.STEADY_TIME)
        if self.lockstep:
            # Time stands still until everyone expected listens, matched by DDS and not only
            # seen on the graph: no sample is lost at start-up (ipmc_driver.matching).
            self._start_gate = MatchGate(self.count_subscribers, [
                (self.pub_disp, "/ipmc/displacement", max(1, p["lockstep_min_subscribers"])),
                (self.pub_voltage, "/ipmc/voltage", 0),
                (self.pub_clock, "/clock", p["lockstep_min_clock_subscribers"])],
                inputs=[
                    (self.sub_command_stamped, "/ipmc/command_stamped",
                     p["lockstep_min_command_publishers"]),
                    (self.sub_command, "/ipmc/command", 0)],
                count_publishers=self.count_publishers, warn=self.get_logger().warn)
            self._t0 = 0.0
            self.create_timer(0.0005, self._on_lockstep_tick, clock=wall)
        else:
            # Stamps come from the clock (SampleClock), not from counting ticks.
            self.sample_clock.start(self.get_clock().now().nanoseconds)
            self.create_timer(self.dt_s, self._on_tick, clock=wall)
        # Diagnostics on the wall clock: they keep coming when a simulated clock stalls.
        self._diag_wall_ns = time.monotonic_ns()
        self._diag_steps = 0
        self.create_timer(p["diagnostics_period_s"], self.publish_diagnostics, clock=wall)

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
        # Every sample whose period the clock has passed: a late tick catches up (a burst
        # stamped on the grid); samples beyond the burst are skipped, the plant still steps.
        ks, skipped = self.sample_clock.due(self.get_clock().now().nanoseconds)
        for _ in range(skipped):
            self.plant.step(self.command_v)
        for k in ks:
            u_applied_v, y_mm = self.plant.step(self.command_v)
            self._publish_sample(u_applied_v, y_mm, self.sample_clock.stamp_ns(k))

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
        if nobody and self.get_parameter("lockstep_min_command_publishers").value > 0:
            return   # the commanders time started with have left: it stands until one returns
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

    def _publish_sample(self, u_applied_v: float, y_mm: float, at_ns: int | None = None
                        ) -> None:
        # Lock-step: plant.t_s is already the next sample's time, this sample was taken one
        # period earlier. Real time: the stamp the sample clock gives (at_ns).
        stamp = (to_time_msg(self._t0 + self.plant.t_s - self.dt_s) if at_ns is None
                 else Time(sec=at_ns // 1_000_000_000, nanosec=at_ns % 1_000_000_000))
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

    def publish_diagnostics(self) -> None:
        """Publish ``sim_plant: rate``: requested and achieved rates (real time), or the
        samples per wall second (lock-step, where the graph sets the pace)."""
        now_wall_ns = time.monotonic_ns()
        if self.lockstep:
            dt_s = max(1e-9, (now_wall_ns - self._diag_wall_ns) * 1e-9)
            steps = self.plant_steps()
            rate = (steps - self._diag_steps) / dt_s
            self._diag_steps = steps
            status = self._status(DiagnosticStatus.OK, f"lock-step: {rate:.1f} samples per "
                                  "wall second", mode="lockstep", sample_hz=f"{rate:.2f}",
                                  unanswered=self.unanswered)
        else:
            r = self.sample_clock.report(self.get_clock().now().nanoseconds)
            status = self._status(
                DiagnosticStatus.OK if r.held else DiagnosticStatus.WARN, r.message,
                mode="realtime", requested_hz=f"{r.requested_hz:g}",
                tick_hz=f"{r.tick_hz:.2f}", sample_hz=f"{r.sample_hz:.2f}",
                caught_up=r.caught_up, skipped=r.skipped,
                skipped_total=self.sample_clock.skipped)
        self._diag_wall_ns = now_wall_ns
        arr = DiagnosticArray(status=[status])
        arr.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(arr)

    def plant_steps(self) -> int:
        """Samples the plant has taken since the start."""
        return int(round(self.plant.t_s / self.dt_s))

    def _status(self, level: bytes, message: str, **values) -> DiagnosticStatus:
        return DiagnosticStatus(level=level, name="sim_plant: rate", message=message,
                                hardware_id=HARDWARE_ID,
                                values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])


def main(args: list[str] | None = None) -> None:
    run_node(SimPlant, args, name="sim_plant", doc=__doc__,
             usage="sim_plant [--ros-args -p rate_hz:=100.0 -p clock_mode:=realtime|lockstep "
                   "-p effects:=[creep] -p seed:=0 -p params_file:=FILE.yaml]")


if __name__ == "__main__":
    main()
