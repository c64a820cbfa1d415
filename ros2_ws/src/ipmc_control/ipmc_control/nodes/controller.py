"""controller: the hybrid inverse-feedforward + PID loop of the paper (section 4) on the graph.

Subscribes ``/ipmc/reference`` (PointStamped, x in m, y its rate in m/s),
``/ipmc/displacement`` (PointStamped, x in m) and ``/ipmc/feedforward`` (Vector3Stamped, x in
V); publishes ``/ipmc/command`` (std_msgs/Float64, V, |u| <= 3 V), with
``trigger:=measurement`` the same command on ``/ipmc/command_stamped`` (Vector3Stamped, x in V,
stamped with the displacement sample the step answers: a lock-step ``sim_plant`` pairs each
sample with its own command by it), and ``/diagnostics``.

- ``trigger:=timer`` (default): one command every ``1/rate_hz`` s of the node's clock (ROS time,
  so with ``use_sim_time:=true`` it follows ``/clock`` of ``sim_plant`` in lock-step mode);
  ``dt`` is the clock's. ``trigger:=measurement``: one command per displacement sample, ``dt``
  from the samples' stamps (exact in lock-step: no race between ``/clock`` and the sample).
- Gains ``k`` (V/mm), ``ti_s``, ``td_s`` (s), ``n``, ``tracking_time_constant`` (s, 0: default
  ``sqrt(TI TD)``), the limits ``u_clamp_max``/``u_clamp_min`` (V) and ``mode`` (pid | inverse
  | hybrid) can be changed at run time; invalid values are refused with the reason. Gain changes
  are bumpless.
- ``use_reference_rate`` (default true): the PID's derivative acts on the error, with the
  reference's rate taken from ``point.y`` of ``/ipmc/reference`` (the paper's Eq. 21; the
  ``reference`` node fills it in; a publisher that leaves it 0 gets derivative on the
  measurement). false: derivative on the measurement alone.
- The feedforward is stale when older than ``feedforward_timeout_s`` on the node's clock: the
  loop then runs PID alone (bumplessly), says so on ``/diagnostics`` and in the log, and returns
  to the requested mode when feedforward messages come back.
- The feedforward answers one reference sample. When its header stamp equals the stamp of a
  recent reference message (model_server copies it), the step uses that reference with it, so
  u_ff and the PID's error refer to the same desired displacement, as in an in-process loop;
  otherwise the latest reference.
- With ``trigger:=measurement`` the command computed on the sample stamped ``t`` is applied
  over the next period, so it aims at the reference stamped ``t + 1/rate_hz`` when that sample
  is known (the ``reference`` node publishes ahead with ``preview_s``), with the feedforward
  answering that same reference, while the PID's error uses the reference stamped ``t`` (the
  measurement's own instant; the first sample's reference when there is none): the graph then
  runs the in-process loop of
  ``ipmc_control.experiment`` sample for sample. When that reference sample or its feedforward
  has not arrived yet (a busy reference node or model_server) the step waits for them, at most
  ``pair_wait_s`` of wall time (lock-step ``sim_plant`` waits for the command meanwhile); steps
  run without them are counted (``unpaired_steps`` on /diagnostics). Steps aiming before the
  first reference sample idle (0 V), so the loop starts on the reference's first sample.
- Without a reference, or without a displacement younger than ``measurement_timeout_s`` when
  feedback is needed, the command is 0 V and the controller state is reset.

These rules live in the pure core ``ipmc_control.supervisor``; this node maps topics,
parameters and timers onto it, and measures the loop's timing.
"""

from __future__ import annotations

import math
import time
from collections import deque

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_msgs.msg import Float64

from ipmc_control.hybrid import MODES, HybridController
from ipmc_control.pid import (
    ANTIWINDUP_STRATEGIES,
    DEFAULT_N,
    PID,
    ControlParameterError,
    check_actuator_limits,
    check_parameter,
)
from ipmc_control.supervisor import (
    Command,
    Status,
    Supervisor,
    feedforward_status,
    measurement_status,
    saturation_status,
)
from ipmc_driver.dataio import stamp_ns
from ipmc_driver.node_runtime import (
    ParameterSpec,
    check_changes,
    declare_checked,
    one_of,
    positive,
    run_node,
)
from ipmc_driver.qos import COMMAND_WRITER_QOS, DIAGNOSTICS_QOS, PAIRED_SAMPLE_QOS, SAMPLE_QOS

# Inputs: reliable and deep like their publishers (docs/interfaces.md), so that a lock-step
# burst loses no sample; the loop keys references and feedforwards by stamp.
INPUT_QOS = SAMPLE_QOS
TRIGGERS = ("timer", "measurement")
GAIN_PARAMS = ("k", "ti_s", "td_s", "n", "tracking_time_constant")
LIMIT_PARAMS = ("u_clamp_min", "u_clamp_max")
HARDWARE_ID = "ipmc"
LEVELS = {0: DiagnosticStatus.OK, 1: DiagnosticStatus.WARN, 2: DiagnosticStatus.ERROR}
# A tick later than this many periods counts as a deadline miss (wall clock).
MISS_FACTOR = 1.5


def _number(name: str, **bounds):
    """A ParameterSpec check by ``ipmc_control.pid.check_parameter``."""
    def check(value) -> str:
        try:
            check_parameter(name, value, **bounds)
        except ControlParameterError as exc:
            return str(exc).removeprefix(f"{name} ")
        return ""
    return check


PARAMETERS = {
    "rate_hz": ParameterSpec(100.0, "command rate with trigger 'timer', Hz", True, positive),
    "trigger": ParameterSpec("timer", "timer: fixed rate on the node clock | measurement: one "
                             "command per displacement sample", True, one_of(*TRIGGERS)),
    "mode": ParameterSpec("hybrid", "pid | inverse | hybrid", check=one_of(*MODES)),
    "k": ParameterSpec(1.2, "proportional gain K, V/mm (paper Eq. 21)",
                       check=_number("k", low=0.0)),
    "ti_s": ParameterSpec(0.87, "integral time TI, s (> 0)",
                          check=_number("ti_s", low=0.0, low_open=True, allow_inf=True)),
    "td_s": ParameterSpec(0.13, "derivative time TD, s (>= 0)", check=_number("td_s", low=0.0)),
    "n": ParameterSpec(DEFAULT_N, "derivative filter ratio N: filter time constant TD/N "
                       "(default 3: see ipmc_control.pid.DEFAULT_N)",
                       check=_number("n", low=0.0, low_open=True)),
    "tracking_time_constant": ParameterSpec(
        0.0, "back-calculation tracking time Tt, s; 0 = sqrt(TI TD)",
        check=_number("tracking_time_constant", low=0.0)),
    "u_clamp_max": ParameterSpec(3.0, "upper command limit, V",
                                 check=_number("u_clamp_max")),
    "u_clamp_min": ParameterSpec(-3.0, "lower command limit, V",
                                 check=_number("u_clamp_min")),
    "antiwindup_strategy": ParameterSpec("back_calculation", "back_calculation | none", True,
                                         one_of(*ANTIWINDUP_STRATEGIES)),
    "use_reference_rate": ParameterSpec(
        True, "derivative on the error using the reference's rate (point.y of /ipmc/reference, "
        "m/s); false: derivative on the measurement"),
    "feedforward_timeout_s": ParameterSpec(
        0.2, "feedforward older than this (node clock) -> PID alone, s", check=positive),
    "measurement_timeout_s": ParameterSpec(
        0.5, "displacement older than this (node clock) -> 0 V, s", check=positive),
    "diagnostics_period_s": ParameterSpec(1.0, "wall-clock period of /diagnostics, s", True,
                                          positive),
    "pair_wait_s": ParameterSpec(
        0.05, "trigger 'measurement': longest wall-time wait for the feedforward of the "
        "reference sample a step aims at, s", True, positive),
}


def _build_pid(p: dict) -> PID:
    """The PID of a full set of gain and limit parameters; ControlParameterError if refused."""
    check_actuator_limits(p["u_clamp_min"], p["u_clamp_max"])
    return PID(p["k"], p["ti_s"], p["td_s"], n=p["n"], u_clamp_max=p["u_clamp_max"],
               u_clamp_min=p["u_clamp_min"],
               antiwindup_strategy=p.get("antiwindup_strategy", "back_calculation"),
               tracking_time_constant=p["tracking_time_constant"])


class Controller(Node):
    def __init__(self, **node_kwargs) -> None:
        super().__init__("controller", **node_kwargs)
        p = declare_checked(self, PARAMETERS)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        pid = _build_pid(p)
        self.rate_hz, self.trigger = p["rate_hz"], p["trigger"]
        self.supervisor = Supervisor(
            HybridController(pid, mode=p["mode"]), self.rate_hz, trigger=self.trigger,
            feedforward_timeout_s=p["feedforward_timeout_s"],
            measurement_timeout_s=p["measurement_timeout_s"], pair_wait_s=p["pair_wait_s"],
            use_reference_rate=p["use_reference_rate"],
            reference_publishers=lambda: self.count_publishers("/ipmc/reference"))
        self.hybrid = self.supervisor.hybrid
        self._sim_time = bool(self.get_parameter("use_sim_time").value)
        # Loop timing (wall clock) for /diagnostics and the benchmark.
        self._last_wall: float | None = None
        self._answer_ns = 0   # stamp of the sample the last command answered
        self.deadline_misses = 0
        self.step_us: deque[float] = deque(maxlen=2000)

        self.pub_command = self.create_publisher(Float64, "/ipmc/command", COMMAND_WRITER_QOS)
        self.pub_command_stamped = (
            self.create_publisher(Vector3Stamped, "/ipmc/command_stamped", COMMAND_WRITER_QOS)
            if self.trigger == "measurement" else None)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
        # trigger:=measurement pairs references and feedforwards by stamp and waits for them:
        # take those published before this subscription matched too (their publishers keep 100).
        paired_qos = PAIRED_SAMPLE_QOS if self.trigger == "measurement" else INPUT_QOS
        self.create_subscription(PointStamped, "/ipmc/reference", self._on_reference,
                                 paired_qos)
        self.create_subscription(PointStamped, "/ipmc/displacement", self._on_displacement,
                                 INPUT_QOS)
        self.create_subscription(Vector3Stamped, "/ipmc/feedforward", self._on_feedforward,
                                 paired_qos)
        wall = Clock(clock_type=ClockType.STEADY_TIME)
        if self.trigger == "timer":
            self.create_timer(1.0 / self.rate_hz, self._on_tick)
        else:
            self.create_timer(min(0.005, p["pair_wait_s"] / 2), self._on_pair_wait, clock=wall)
        # Diagnostics on the wall clock: they keep coming when the simulated clock stalls.
        self.create_timer(p["diagnostics_period_s"], self.publish_diagnostics, clock=wall)
        self.get_logger().info(
            f"controller: mode {self.hybrid.mode}, K={pid.k} V/mm, TI={pid.ti_s} s, "
            f"TD={pid.td_s} s, |u| <= {pid.u_clamp_max} V, trigger {self.trigger}")

    # -- parameters -----------------------------------------------------------------------------
    def _validate_parameters(self, params) -> SetParametersResult:
        result = check_changes(PARAMETERS, params)
        new = {p.name: p.value for p in params}
        if result.successful and any(n in new for n in GAIN_PARAMS + LIMIT_PARAMS):
            # Try the whole new set on a scratch controller: all or nothing.
            cur = {n: self.get_parameter(n).value for n in GAIN_PARAMS + LIMIT_PARAMS}
            cur.update({n: v for n, v in new.items() if n in cur})
            try:
                _build_pid(cur)
            except ControlParameterError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        return result

    def _apply_parameters(self, params) -> None:
        names = {p.name for p in params}
        g = self.get_parameter
        pid, sup = self.hybrid.pid, self.supervisor
        if names & set(LIMIT_PARAMS):
            pid.set_limits(g("u_clamp_min").value, g("u_clamp_max").value)
        if names & set(GAIN_PARAMS):
            pid.set_gains(g("k").value, g("ti_s").value, g("td_s").value, n=g("n").value,
                          tracking_time_constant=g("tracking_time_constant").value)
            self.get_logger().info(f"gains: K={pid.k} V/mm, TI={pid.ti_s} s, TD={pid.td_s} s, "
                                   f"N={pid.n}, Tt={pid.tracking_time_constant_s:.3g} s")
        if "mode" in names:
            self.hybrid.mode = g("mode").value
            self.get_logger().info(f"mode: {self.hybrid.mode}")
        sup.ff_timeout_s = g("feedforward_timeout_s").value
        sup.y_timeout_s = g("measurement_timeout_s").value
        sup.use_reference_rate = g("use_reference_rate").value
        self._sim_time = bool(g("use_sim_time").value)

    # -- inputs ---------------------------------------------------------------------------------
    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _on_reference(self, msg: PointStamped) -> None:
        self._publish(self.supervisor.on_reference(
            stamp_ns(msg.header.stamp), msg.point.x * 1e3, msg.point.y * 1e3))

    def _on_feedforward(self, msg: Vector3Stamped) -> None:
        self._publish(self.supervisor.on_feedforward(
            stamp_ns(msg.header.stamp), msg.vector.x, self._now_s()))

    def _on_displacement(self, msg: PointStamped) -> None:
        self._publish(self.supervisor.on_measurement(
            stamp_ns(msg.header.stamp), msg.point.x * 1e3, self._now_s(), time.monotonic()))

    def _on_pair_wait(self) -> None:
        self._publish(self.supervisor.on_pair_wait(time.monotonic()))

    def _on_tick(self) -> None:
        self._publish([self.supervisor.on_tick(self._now_s())])

    # -- outputs --------------------------------------------------------------------------------
    def _publish(self, commands: list[Command]) -> None:
        """Publish the supervisor's commands, time the loop and log what it noted."""
        for c in commands:
            wall = time.perf_counter()
            self._count_deadline(wall)
            self._publish_command(c.u_v, c.answer_ns)
            self.step_us.append((time.perf_counter() - wall) * 1e6)
        for kind, text in self.supervisor.notes:
            if kind in ("back", "waiting"):
                self.get_logger().info(text)
            else:
                if kind == "stale":
                    text += f" ({self.count_publishers('/ipmc/feedforward')} publisher(s))"
                self.get_logger().warn(text)
            if kind in ("stale", "back"):
                self.publish_diagnostics()
        self.supervisor.notes.clear()

    def _publish_command(self, u_v: float, answer_ns: int) -> None:
        self._answer_ns = answer_ns
        self.pub_command.publish(Float64(data=u_v))
        if self.pub_command_stamped is None:
            return
        msg = Vector3Stamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(answer_ns, 1_000_000_000)
        msg.vector.x = u_v
        self.pub_command_stamped.publish(msg)

    def _count_deadline(self, wall: float) -> None:
        if self._last_wall is not None and self.trigger == "timer" and not self._sim_time:
            if wall - self._last_wall > MISS_FACTOR / self.rate_hz:
                self.deadline_misses += 1
        self._last_wall = wall

    # -- diagnostics ----------------------------------------------------------------------------
    def publish_diagnostics(self) -> None:
        """Publish one DiagnosticArray: feedforward, measurement, saturation, loop."""
        s, now = self.supervisor, self._now_s()
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [self._status("feedforward", feedforward_status(s, now)),
                      self._status("measurement", measurement_status(s, now)),
                      self._status("saturation", saturation_status(s)),
                      self._status("loop", self._loop_status())]
        self.pub_diag.publish(arr)

    @staticmethod
    def _status(name: str, status: Status) -> DiagnosticStatus:
        return DiagnosticStatus(
            level=LEVELS[status.level], name=f"controller: {name}", message=status.message,
            hardware_id=HARDWARE_ID,
            values=[KeyValue(key=k, value=str(v)) for k, v in status.values.items()])

    def _loop_status(self) -> Status:
        s = self.supervisor
        us = sorted(self.step_us)
        p50 = us[len(us) // 2] if us else math.nan
        p99 = us[min(len(us) - 1, int(0.99 * len(us)))] if us else math.nan
        miss = self.deadline_misses / s.ticks if s.ticks else 0.0
        return Status(1 if miss > 1e-3 else 0, f"{s.ticks} steps, {miss:.2%} deadline misses",
                      dict(rate_hz=self.rate_hz, trigger=self.trigger, ticks=s.ticks,
                           deadline_misses=self.deadline_misses,
                           skipped_steps=s.skipped_steps, unpaired_steps=s.unpaired_steps,
                           rejected_steps=self.hybrid.pid.rejected_steps,
                           step_p50_us=f"{p50:.1f}", step_p99_us=f"{p99:.1f}"))

    def destroy_node(self) -> None:
        # Leave the actuator at rest if the graph still carries messages (best effort: after an
        # external shutdown the context is gone; the driver's own command timeout covers that).
        try:
            self._publish_command(0.0, self._answer_ns)
        except Exception:  # noqa: BLE001 - any failure here must not mask the shutdown
            pass
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    run_node(Controller, args, name="controller", doc=__doc__,
             usage="controller [--ros-args -p mode:=pid|inverse|hybrid -p k:=1.2 -p ti_s:=0.87 "
                   "-p td_s:=0.13 -p rate_hz:=100.0 -p trigger:=timer|measurement "
                   "-p use_sim_time:=true]")


if __name__ == "__main__":
    main()
