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
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict, deque

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, Vector3Stamped
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_msgs.msg import Float64

from ipmc_control.hybrid import HybridController, check_mode
from ipmc_control.pid import DEFAULT_N, PID, ControlParameterError, check_actuator_limits
from ipmc_driver.dataio import stamp_ns
from ipmc_driver.node_runtime import run_node
from ipmc_driver.qos import COMMAND_QOS, PAIRED_SAMPLE_QOS, SAMPLE_QOS

# Inputs: reliable and deep like their publishers (docs/interfaces.md), so that a lock-step
# burst loses no sample; the loop keys references and feedforwards by stamp.
INPUT_QOS = SAMPLE_QOS
TRIGGERS = ("timer", "measurement")
GAIN_PARAMS = ("k", "ti_s", "td_s", "n", "tracking_time_constant")
LIMIT_PARAMS = ("u_clamp_min", "u_clamp_max")
HARDWARE_ID = "ipmc"
# Recent reference samples kept to pair a feedforward with the reference it answers.
REFERENCE_MEMORY = 64
# A tick later than this many periods counts as a deadline miss (wall clock).
MISS_FACTOR = 1.5


def _stamp_s(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def _stamp_ns(msg) -> int:
    return stamp_ns(msg.header.stamp)


class Controller(Node):
    def _declare_parameters(self) -> None:
        """Every parameter with its default and meaning (units in the description)."""
        d = ParameterDescriptor
        self.declare_parameter("rate_hz", 100.0, d(
            description="command rate with trigger 'timer', Hz", read_only=True))
        self.declare_parameter("trigger", "timer", d(
            description="timer: fixed rate on the node clock | measurement: one command per "
                        "displacement sample", read_only=True))
        self.declare_parameter("mode", "hybrid", d(description="pid | inverse | hybrid"))
        self.declare_parameter("k", 1.2, d(description="proportional gain K, V/mm (paper Eq. 21)"))
        self.declare_parameter("ti_s", 0.87, d(description="integral time TI, s (> 0)"))
        self.declare_parameter("td_s", 0.13, d(description="derivative time TD, s (>= 0)"))
        self.declare_parameter("n", DEFAULT_N, d(
            description="derivative filter ratio N: filter time constant TD/N (default 3: "
                        "see ipmc_control.pid.DEFAULT_N)"))
        self.declare_parameter("tracking_time_constant", 0.0, d(
            description="back-calculation tracking time Tt, s; 0 = sqrt(TI TD)"))
        self.declare_parameter("u_clamp_max", 3.0, d(description="upper command limit, V"))
        self.declare_parameter("u_clamp_min", -3.0, d(description="lower command limit, V"))
        self.declare_parameter("antiwindup_strategy", "back_calculation", d(
            description="back_calculation | none", read_only=True))
        self.declare_parameter("use_reference_rate", True, d(
            description="derivative on the error using the reference's rate (point.y of "
                        "/ipmc/reference, m/s); false: derivative on the measurement"))
        self.declare_parameter("feedforward_timeout_s", 0.2, d(
            description="feedforward older than this (node clock) -> PID alone, s"))
        self.declare_parameter("measurement_timeout_s", 0.5, d(
            description="displacement older than this (node clock) -> 0 V, s"))
        self.declare_parameter("diagnostics_period_s", 1.0, d(
            description="wall-clock period of /diagnostics, s", read_only=True))
        self.declare_parameter("pair_wait_s", 0.05, d(
            description="trigger 'measurement': longest wall-time wait for the feedforward of "
                        "the reference sample a step aims at, s", read_only=True))

    def _read_loop_parameters(self) -> None:
        """Rate, trigger and pairing wait (read-only), checked."""
        g = self.get_parameter
        self.rate_hz = float(g("rate_hz").value)
        self.trigger = g("trigger").value
        self.pair_wait_s = float(g("pair_wait_s").value)
        if not (self.pair_wait_s > 0 and math.isfinite(self.pair_wait_s)):
            raise ControlParameterError(f"pair_wait_s must be > 0 s, got {self.pair_wait_s}")
        if not self.rate_hz > 0 or self.trigger not in TRIGGERS:
            raise ControlParameterError(f"need rate_hz > 0 and trigger in {TRIGGERS}, got "
                                        f"{self.rate_hz} and {self.trigger!r}")

    def __init__(self) -> None:
        super().__init__("controller")
        self._declare_parameters()
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        g = self.get_parameter
        self._read_loop_parameters()
        check_actuator_limits(g("u_clamp_min").value, g("u_clamp_max").value)
        pid = PID(g("k").value, g("ti_s").value, g("td_s").value, n=g("n").value,
                  u_clamp_max=g("u_clamp_max").value, u_clamp_min=g("u_clamp_min").value,
                  antiwindup_strategy=g("antiwindup_strategy").value,
                  tracking_time_constant=g("tracking_time_constant").value)
        self.hybrid = HybridController(pid, mode=check_mode(g("mode").value))
        self.ff_timeout_s = float(g("feedforward_timeout_s").value)
        self.y_timeout_s = float(g("measurement_timeout_s").value)
        self.use_reference_rate = bool(g("use_reference_rate").value)
        self._sim_time = bool(g("use_sim_time").value)

        # Latest inputs (mm, V) and their receive times on the node clock (s).
        self._ref_mm: float | None = None
        self._ref_rate = 0.0                  # rate of the latest reference, mm/s
        self._first_ref_ns: int | None = None   # a step aiming before it has no reference
        # Recent reference samples by stamp: (displacement mm, rate mm/s).
        self._recent_refs: OrderedDict[int, tuple[float, float]] = OrderedDict()
        self._ff_ref: tuple[float, float] | None = None  # the one the last feedforward answers
        self._recent_ffs: OrderedDict[int, float] = OrderedDict()
        self._y_mm: float | None = None
        self._y_rx_s = -math.inf
        self._y_stamp_s: float | None = None
        self._ff_v: float | None = None
        self._ff_rx_s = -math.inf
        self._last_t_s: float | None = None
        self._last_wall: float | None = None
        self._fallback = False
        self._idle_reason = "starting"
        # trigger 'measurement': (t_s, now, target_ns, wall) of a step waiting for its u_ff.
        self._pending: tuple[float, float, int, float] | None = None
        self._stepped = False   # a step has run (the first one waits for the reference)
        # Loop statistics for /diagnostics and the benchmark.
        self.ticks = 0
        self.deadline_misses = 0
        self.skipped_steps = 0
        self.unpaired_steps = 0   # steps run without the feedforward of their reference
        self.step_us = deque(maxlen=2000)
        self._saturated = deque(maxlen=200)

        self.pub_command = self.create_publisher(Float64, "/ipmc/command", COMMAND_QOS)
        self.pub_command_stamped = (
            self.create_publisher(Vector3Stamped, "/ipmc/command_stamped", COMMAND_QOS)
            if self.trigger == "measurement" else None)
        self._answer_ns = 0  # stamp of the sample the next command answers
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # trigger:=measurement pairs references and feedforwards by stamp and waits for them:
        # take those published before this subscription matched too (their publishers keep 100).
        paired_qos = PAIRED_SAMPLE_QOS if self.trigger == "measurement" else INPUT_QOS
        self.create_subscription(PointStamped, "/ipmc/reference", self._on_reference,
                                 paired_qos)
        self.create_subscription(PointStamped, "/ipmc/displacement", self._on_displacement,
                                 INPUT_QOS)
        self.create_subscription(Vector3Stamped, "/ipmc/feedforward", self._on_feedforward,
                                 paired_qos)

        if self.trigger == "timer":
            self.create_timer(1.0 / self.rate_hz, self._on_tick)
        else:
            self.create_timer(min(0.005, self.pair_wait_s / 2), self._on_pair_wait,
                              clock=Clock(clock_type=ClockType.STEADY_TIME))
        # Diagnostics on the wall clock: they keep coming when the simulated clock stalls.
        self.create_timer(float(g("diagnostics_period_s").value), self.publish_diagnostics,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f"controller: mode {self.hybrid.mode}, K={pid.k} V/mm, TI={pid.ti_s} s, "
            f"TD={pid.td_s} s, |u| <= {pid.u_clamp_max} V, trigger {self.trigger}")

    # -- parameters -----------------------------------------------------------------------------
    def _validate_parameters(self, params) -> SetParametersResult:
        new = {p.name: p.value for p in params}
        try:
            if "mode" in new:
                check_mode(new["mode"])
            if "use_reference_rate" in new and not isinstance(new["use_reference_rate"], bool):
                raise ControlParameterError("use_reference_rate must be true or false")
            for name in ("feedforward_timeout_s", "measurement_timeout_s"):
                if name in new and not (isinstance(new[name], float) and new[name] > 0):
                    raise ControlParameterError(f"{name} must be > 0 s, got {new[name]!r}")
            if any(n in new for n in GAIN_PARAMS + LIMIT_PARAMS):
                # Try the whole new set on a scratch controller: all or nothing.
                cur = {n: self.get_parameter(n).value for n in GAIN_PARAMS + LIMIT_PARAMS}
                cur.update({n: v for n, v in new.items() if n in cur})
                check_actuator_limits(cur["u_clamp_min"], cur["u_clamp_max"])
                PID(cur["k"], cur["ti_s"], cur["td_s"], n=cur["n"],
                    u_clamp_max=cur["u_clamp_max"], u_clamp_min=cur["u_clamp_min"],
                    tracking_time_constant=cur["tracking_time_constant"])
        except (ControlParameterError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params) -> None:
        names = {p.name for p in params}
        g = self.get_parameter
        pid = self.hybrid.pid
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
        self.ff_timeout_s = float(g("feedforward_timeout_s").value)
        self.y_timeout_s = float(g("measurement_timeout_s").value)
        self.use_reference_rate = bool(g("use_reference_rate").value)
        self._sim_time = bool(g("use_sim_time").value)

    # -- inputs ---------------------------------------------------------------------------------
    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _on_reference(self, msg: PointStamped) -> None:
        if math.isfinite(msg.point.x):
            self._ref_mm = msg.point.x * 1e3
            if self._first_ref_ns is None:
                self._first_ref_ns = _stamp_ns(msg)
            self._maybe_run_pending()
            self._ref_rate = msg.point.y * 1e3 if math.isfinite(msg.point.y) else 0.0
            self._recent_refs[_stamp_ns(msg)] = (self._ref_mm, self._ref_rate)
            if len(self._recent_refs) > REFERENCE_MEMORY:
                self._recent_refs.popitem(last=False)

    def _on_feedforward(self, msg: Vector3Stamped) -> None:
        if math.isfinite(msg.vector.x):
            self._ff_v = float(msg.vector.x)
            self._ff_rx_s = self._now_s()
            self._ff_ref = self._recent_refs.get(_stamp_ns(msg))
            self._recent_ffs[_stamp_ns(msg)] = self._ff_v
            if len(self._recent_ffs) > REFERENCE_MEMORY:
                self._recent_ffs.popitem(last=False)
            self._maybe_run_pending()

    def _on_displacement(self, msg: PointStamped) -> None:
        if not math.isfinite(msg.point.x):
            return
        self._y_mm = msg.point.x * 1e3
        self._y_rx_s = self._now_s()
        if self.trigger == "measurement":
            if self._pending is not None:  # a step still waiting for its u_ff goes first
                self.unpaired_steps += 1
                self._run_pending()
            target_ns = _stamp_ns(msg) + int(round(1e9 / self.rate_hz))
            if self._missing_inputs(target_ns):
                # The reference sample this step aims at, or the feedforward answering it, is
                # on its way (from the reference node, from model_server): wait for it, at most
                # pair_wait_s of wall time, so the step pairs them as the in-process loop does.
                self._pending = (_stamp_s(msg), self._y_rx_s, target_ns, time.monotonic())
                return
            self._step(_stamp_s(msg), self._y_rx_s, target_ns)

    def _missing_inputs(self, target_ns: int) -> bool:
        if self._first_ref_ns is None:
            # Wait for the first sample if someone publishes, and on the very first step even
            # before its publisher is seen: discovery can lag under load, and a controller that
            # idled there let a lock-step plant run on before the reference began (CI, once).
            return not self._stepped or self.count_publishers("/ipmc/reference") > 0
        if target_ns < self._first_ref_ns:
            return False   # before the reference starts: the step idles, nothing to wait for
        if target_ns not in self._recent_refs:
            return True
        # Wait for the feedforward even before its publisher is seen (discovery can lag under
        # load); without model_server the first step waits pair_wait_s and falls back.
        return (self.hybrid.mode != "pid" and not self._fallback
                and target_ns not in self._recent_ffs)

    def _maybe_run_pending(self) -> None:
        if self._pending is not None and not self._missing_inputs(self._pending[2]):
            self._run_pending()

    def _run_pending(self) -> None:
        if self._pending is not None:
            t_s, now, target_ns, _ = self._pending
            self._pending = None
            self._step(t_s, now, target_ns)

    def _on_pair_wait(self) -> None:
        if self._pending is not None and time.monotonic() - self._pending[3] > self.pair_wait_s:
            self.unpaired_steps += 1
            self._run_pending()

    # -- the loop -------------------------------------------------------------------------------
    def _on_tick(self) -> None:
        now = self._now_s()
        self._step(now, now)

    def _publish_command(self, u_v: float) -> None:
        self.pub_command.publish(Float64(data=u_v))
        if self.pub_command_stamped is None:
            return
        msg = Vector3Stamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(self._answer_ns, 1_000_000_000)
        msg.vector.x = u_v
        self.pub_command_stamped.publish(msg)

    def _step(self, t_s: float, now: float, target_ns: int | None = None) -> None:
        """One control step at sample time ``t_s`` (s); ``now`` is the node clock (s);
        ``target_ns``: stamp of the reference sample this command aims at, if known."""
        self._stepped = True
        self._answer_ns = (target_ns - int(round(1e9 / self.rate_hz)) if target_ns is not None
                           else int(round(t_s * 1e9)))
        wall = time.perf_counter()
        self._count_deadline(wall)
        dt = (1.0 / self.rate_hz) if self._last_t_s is None else t_s - self._last_t_s
        self._last_t_s = t_s
        if not (0.0 < dt <= 10.0 / self.rate_hz):
            # Clock jumped (sim time reset, pause): hold the command, restart timing.
            self.skipped_steps += 1
            self._publish_command(self.hybrid.command)
            return
        ff_fresh = self._ff_v is not None and now - self._ff_rx_s <= self.ff_timeout_s
        if target_ns is not None and target_ns in self._recent_ffs:
            # The feedforward answering this very sample is here: fresh whatever the receive
            # time says (under use_sim_time it may have come before the /clock that dates it).
            ff_fresh = True
        y_fresh = self._y_mm is not None and now - self._y_rx_s <= self.y_timeout_s
        mode = self.hybrid.mode
        needs_y = mode != "inverse" or not ff_fresh
        before_start = (target_ns is not None and self._first_ref_ns is not None
                        and target_ns < self._first_ref_ns)
        if self._ref_mm is None or before_start or (needs_y and not y_fresh):
            self._go_idle("no reference yet" if self._ref_mm is None or before_start
                          else "no fresh displacement")
            return
        self._idle_reason = ""
        ref_mm = self._ref_mm
        rate = self._ref_rate
        ff_v = self._ff_v if ff_fresh else None
        if ff_fresh and mode != "pid" and self._ff_ref is not None:
            ref_mm, rate = self._ff_ref
        if target_ns is not None and target_ns in self._recent_refs:
            ref_mm, rate = self._recent_refs[target_ns]
            if ff_fresh and target_ns in self._recent_ffs:
                ff_v = self._recent_ffs[target_ns]
            # The PID compares the measurement with the reference of its own instant; only the
            # feedforward looks ahead (ipmc_control.experiment: e_{k-1} = r_{k-1} - y_{k-1}).
            ref_mm, rate = self._recent_refs.get(self._answer_ns, (ref_mm, rate))
        y_mm = self._y_mm if self._y_mm is not None else ref_mm
        u = self.hybrid.compute_command(ref_mm, y_mm, dt, ff_v,
                                        rate if self.use_reference_rate else None)
        self._publish_command(u)
        self.step_us.append((time.perf_counter() - wall) * 1e6)
        self._saturated.append(self.hybrid.saturated)
        self.ticks += 1
        fallback = mode != "pid" and not ff_fresh
        if fallback != self._fallback:
            self._fallback = fallback
            if fallback:
                last = ("none received yet" if self._ff_v is None
                        else f"last received {now - self._ff_rx_s:.3f} s before")
                at = f" at sample {t_s:.3f} s" if target_ns is not None else ""
                self.get_logger().warn(
                    f"feedforward stale (> {self.ff_timeout_s} s){at}: {last}, "
                    f"{self.count_publishers('/ipmc/feedforward')} publisher(s), "
                    f"{self.unpaired_steps} unpaired step(s); PID alone until it returns")
            else:
                self.get_logger().info(f"feedforward back: mode {mode}")
            self.publish_diagnostics()

    def _go_idle(self, reason: str) -> None:
        if reason != self._idle_reason:
            self.get_logger().warn(f"{reason}: command 0 V")
            self._idle_reason = reason
            self.hybrid.reset()
        self._publish_command(0.0)

    def _count_deadline(self, wall: float) -> None:
        if self._last_wall is not None and self.trigger == "timer" and not self._sim_time:
            if wall - self._last_wall > MISS_FACTOR / self.rate_hz:
                self.deadline_misses += 1
        self._last_wall = wall

    # -- diagnostics ----------------------------------------------------------------------------
    def publish_diagnostics(self) -> None:
        """Publish one DiagnosticArray: feedforward, measurement, saturation, loop."""
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [self._diag_feedforward(), self._diag_measurement(),
                      self._diag_saturation(), self._diag_loop()]
        self.pub_diag.publish(arr)

    def _status(self, name: str, level: bytes, message: str, **values) -> DiagnosticStatus:
        return DiagnosticStatus(
            level=level, name=f"controller: {name}", message=message, hardware_id=HARDWARE_ID,
            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])

    def _diag_feedforward(self) -> DiagnosticStatus:
        age = self._now_s() - self._ff_rx_s
        age_txt = f"{age:.3f}" if math.isfinite(age) else "never"
        mode = self.hybrid.mode
        if mode == "pid":
            return self._status("feedforward", DiagnosticStatus.OK, "not used in mode pid",
                                mode=mode, age_s=age_txt)
        if self._fallback:
            return self._status("feedforward", DiagnosticStatus.WARN,
                                f"stale: PID alone instead of {mode}", mode=mode,
                                active_mode="pid", age_s=age_txt,
                                timeout_s=self.ff_timeout_s)
        return self._status("feedforward", DiagnosticStatus.OK, f"fresh, mode {mode}",
                            mode=mode, active_mode=self.hybrid.active_mode, age_s=age_txt,
                            feedforward_v=f"{self.hybrid.feedforward_v:.4f}",
                            paired_with_reference=self._ff_ref is not None)

    def _diag_measurement(self) -> DiagnosticStatus:
        if self._idle_reason:
            return self._status("measurement", DiagnosticStatus.ERROR,
                                f"{self._idle_reason}: command 0 V")
        age = self._now_s() - self._y_rx_s
        return self._status("measurement", DiagnosticStatus.OK, "fresh",
                            age_s=f"{age:.3f}" if math.isfinite(age) else "never")

    def _diag_saturation(self) -> DiagnosticStatus:
        frac = sum(self._saturated) / len(self._saturated) if self._saturated else 0.0
        pid = self.hybrid.pid
        level = DiagnosticStatus.WARN if frac > 0.5 else DiagnosticStatus.OK
        return self._status("saturation", level, f"{100 * frac:.0f} % of recent commands "
                            "at the limit", fraction=f"{frac:.3f}",
                            u_clamp_max_v=pid.u_clamp_max, u_clamp_min_v=pid.u_clamp_min,
                            command_v=f"{pid.command:.4f}", i_term_v=f"{pid.i_term:.4f}")

    def _diag_loop(self) -> DiagnosticStatus:
        us = sorted(self.step_us)
        p50 = us[len(us) // 2] if us else math.nan
        p99 = us[min(len(us) - 1, int(0.99 * len(us)))] if us else math.nan
        miss = self.deadline_misses / self.ticks if self.ticks else 0.0
        level = DiagnosticStatus.WARN if miss > 1e-3 else DiagnosticStatus.OK
        return self._status("loop", level, f"{self.ticks} steps, {miss:.2%} deadline misses",
                            rate_hz=self.rate_hz, trigger=self.trigger, ticks=self.ticks,
                            deadline_misses=self.deadline_misses,
                            skipped_steps=self.skipped_steps,
                            unpaired_steps=self.unpaired_steps,
                            rejected_steps=self.hybrid.pid.rejected_steps,
                            step_p50_us=f"{p50:.1f}", step_p99_us=f"{p99:.1f}")

    def destroy_node(self) -> None:
        # Leave the actuator at rest if the graph still carries messages (best effort: after an
        # external shutdown the context is gone; the driver's own command timeout covers that).
        try:
            self._publish_command(0.0)
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
