"""reference: publishes the desired tip displacement on ``/ipmc/reference``.

``/ipmc/reference`` is a PointStamped, ``point.x`` in metres and ``point.y`` its rate of change in
m/s (analytic for the smooth generators, 0 on a step train's levels; the controller's
derivative acts on the error with it) (frame ``ipmc_clamp``), published
every ``1/rate_hz`` s of the node's clock (ROS time: with ``use_sim_time:=true`` it follows
``/clock``, and also ticks on each ``/clock`` message, so that it starts with a lock-step
plant's first sample). Its time 0 waits until ``/ipmc/reference`` has matched at least
``min_subscribers`` subscriptions, and, at most 5 s of wall time, every one the graph shows: in
lock-step none then misses the first samples (the graph can list a subscription late), and in
real time the loop starts once every listener is up (a model_server that is still loading its
model would leave the first seconds to the PID alone). ``ipmc track`` and ``ipmc bringup`` set
``min_subscribers`` to the listeners they start. The
generator (``ipmc_control.references``) is chosen by ``kind``:

- ``constant``: ``value_mm``;
- ``sine``: ``amplitude_mm``, ``frequency_hz``, ``offset_mm``, ``phase_rad``;
- ``random``: ``band_hz`` [low, high], ``range_mm`` [min, max], ``n_components``, ``period_s``,
  ``seed`` (defaults: the paper's 0-0.7 Hz, -9..4 mm);
- ``steps``: ``levels_mm``, ``hold_s``, ``repeat``;
- ``file``: ``path`` (CSV with columns t, y in s, mm), ``repeat``.

The reference's time starts at 0 on the first tick. Samples lie on the grid
``t0 + k / rate_hz`` (t0: the first tick), stamped with their own time; each tick publishes every
sample not yet published up to ``now + preview_s``, so a late tick (under a lock-step
``/clock`` a timer skips the periods it missed) catches up instead of losing samples.
Generator parameters can be changed at run time: the new generator is built first and a failure
refuses the change with its reason; the time base continues.
"""

from __future__ import annotations

import math
from pathlib import Path

from geometry_msgs.msg import PointStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg

from ipmc_control.pid import ControlParameterError
from ipmc_control.references import KIND_PARAMS, KINDS, Reference, make_reference
from ipmc_driver.matching import MatchGate
from ipmc_driver.node_runtime import (
    ParameterSpec,
    check_changes,
    declare_checked,
    finite,
    non_negative,
    one_of,
    positive,
    run_node,
)
from ipmc_driver.qos import LATCHED_CLOCK_QOS, PAIRED_SAMPLE_QOS

# Longest catch-up burst, samples: below the subscribers' queue depth (100).
MAX_BURST = 90


def _pair(increasing: str, low_bound: float | None = None):
    """A [low, high] list of two finite numbers with low < high (and low >= low_bound)."""
    def check(value) -> str:
        ok = (len(value) == 2 and all(math.isfinite(v) for v in value) and value[0] < value[1]
              and (low_bound is None or value[0] >= low_bound))
        return "" if ok else f"must be {increasing}, got {list(value)!r}"
    return check


def _file(value) -> str:
    return "" if not value or Path(value).is_file() else f"names no file: {value!r}"


def _levels(value) -> str:
    ok = len(value) > 0 and all(math.isfinite(v) for v in value)
    return "" if ok else f"must be one or more finite values, got {list(value)!r}"


# The generators' parameters (ipmc_control.references), each checked on its own; a change is
# also tried on a new generator of the kind in use (band_hz against period_s, a file's rows).
GENERATOR_PARAMS = {
    "value_mm": ParameterSpec(4.0, "constant: displacement, mm", check=finite),
    "amplitude_mm": ParameterSpec(2.5, "sine: amplitude, mm", check=finite),
    "frequency_hz": ParameterSpec(1.0 / (2.0 * math.pi), "sine: frequency, Hz (> 0)",
                                  check=positive),
    "offset_mm": ParameterSpec(0.0, "sine: mean, mm", check=finite),
    "phase_rad": ParameterSpec(0.0, "sine: phase at t = 0, rad", check=finite),
    "band_hz": ParameterSpec([0.0, 0.7], "random: frequency band [low, high], Hz",
                             check=_pair("[low, high] with 0 <= low < high", 0.0)),
    "range_mm": ParameterSpec([-9.0, 4.0], "random: displacement range [min, max], mm",
                              check=_pair("[min, max] with min < max")),
    "n_components": ParameterSpec(20, "random: number of sines (>= 1)", check=positive),
    "period_s": ParameterSpec(100.0, "random: repetition period, s", check=positive),
    "seed": ParameterSpec(0, "random: seed (>= 0)", check=non_negative),
    "levels_mm": ParameterSpec([0.0, 2.0, 0.0, -2.0], "steps: levels, mm", check=_levels),
    "hold_s": ParameterSpec(5.0, "steps: time per level, s", check=positive),
    "repeat": ParameterSpec(True, "steps/file: start again after the end"),
    "path": ParameterSpec("", "file: CSV with columns t, y (s, mm)", check=_file),
}
PARAMETERS = {
    "rate_hz": ParameterSpec(100.0, "publication rate, Hz", True, positive),
    "frame_id": ParameterSpec("ipmc_clamp", "frame of the reference point", True),
    "preview_s": ParameterSpec(
        0.0, "publish the reference this far ahead of the clock, s (>= 0): a trajectory is "
        "known in advance, and feedforward needs the next sample", True, non_negative),
    "min_subscribers": ParameterSpec(
        0, "the reference's time 0 waits until /ipmc/reference has matched this many "
        "subscriptions (and every one the graph shows, at most 5 s)", True, non_negative),
    "kind": ParameterSpec("sine", " | ".join(KINDS), check=one_of(*KINDS)),
    **GENERATOR_PARAMS,
}


def build_reference(kind: str, values: dict) -> Reference:
    """Build the generator of ``kind`` from a name -> value dict of node parameters."""
    if kind not in KINDS:
        raise ControlParameterError(f"kind must be one of {KINDS}, got {kind!r}")
    params = {name: values[name] for name in KIND_PARAMS[kind]}
    for name in ("band_hz", "range_mm", "levels_mm"):
        if name in params:
            params[name] = [float(v) for v in params[name]]
    if kind == "file" and not params["path"]:
        raise ControlParameterError("kind 'file' needs the parameter path")
    return make_reference(kind, **params)


class ReferenceNode(Node):
    def __init__(self, **node_kwargs) -> None:
        super().__init__("reference", **node_kwargs)
        p = declare_checked(self, PARAMETERS)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self.rate_hz = p["rate_hz"]
        self.frame_id = p["frame_id"]
        self.preview_ns = int(round(p["preview_s"] * 1e9))
        self.generator = build_reference(p["kind"], self._values())
        self._pending: Reference | None = None
        self._t0_ns: int | None = None
        self._next_k = 0   # index of the next sample to publish, stamped t0 + k / rate_hz
        self._period_ns = int(round(1e9 / self.rate_hz))

        self.pub = self.create_publisher(PointStamped, "/ipmc/reference", PAIRED_SAMPLE_QOS)
        self.create_timer(1.0 / self.rate_hz, self._on_tick)
        if self.get_parameter("use_sim_time").value:
            # A timer on /clock first fires one period after the first /clock message. A
            # lock-step plant publishes its sample 0 and waits for the command, which waits for
            # this reference: tick on /clock itself, so the reference starts at the plant's t = 0.
            self.create_subscription(ClockMsg, "/clock", self._on_clock, LATCHED_CLOCK_QOS)
        # The first tick (in lock-step a burst up to preview_s ahead) is held until every
        # subscription the graph shows has matched, or a volatile one (model_server, a
        # recorder) loses it; while held, a wall timer retries (a simulated clock waits too).
        self._start_gate: MatchGate | None = MatchGate(
            self.count_subscribers, [(self.pub, "/ipmc/reference", p["min_subscribers"])],
            warn=self.get_logger().warn)
        self._held_ns: int | None = None
        self._hold_timer = None
        self.get_logger().info(
            f"reference: {self.get_parameter('kind').value} at {self.rate_hz:g} Hz")

    def _values(self, override: dict | None = None) -> dict:
        values = {name: self.get_parameter(name).value for name in GENERATOR_PARAMS}
        values.update(override or {})
        return values

    def _validate_parameters(self, params) -> SetParametersResult:
        result = check_changes(PARAMETERS, params)
        new = {p.name: p.value for p in params}
        if not result.successful or not (set(new) & (set(GENERATOR_PARAMS) | {"kind"})):
            return result
        kind = new.get("kind", self.get_parameter("kind").value)
        try:
            self._pending = build_reference(kind, self._values(new))
        except (ControlParameterError, TypeError, ValueError) as exc:
            self._pending = None
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params) -> None:
        if self._pending is not None:
            self.generator, self._pending = self._pending, None
            self.get_logger().info(f"reference: now {self.get_parameter('kind').value}")

    def _on_clock(self, msg: ClockMsg) -> None:
        self._publish_until(msg.clock.sec * 1_000_000_000 + msg.clock.nanosec)

    def _on_tick(self) -> None:
        self._publish_until(self.get_clock().now().nanoseconds)

    def _retry_held(self) -> None:
        if self._held_ns is not None:
            self._publish_until(self._held_ns)

    def _publish_until(self, now_ns: int) -> None:
        if self._start_gate is not None:
            if not self._start_gate.ready():
                self._held_ns = now_ns
                if self._hold_timer is None:
                    self._hold_timer = self.create_timer(
                        0.005, self._retry_held, clock=Clock(clock_type=ClockType.STEADY_TIME))
                return
            self._start_gate, self._held_ns = None, None
            if self._hold_timer is not None:
                self.destroy_timer(self._hold_timer)
        if self._t0_ns is None or now_ns < self._t0_ns:  # first tick, or the clock went back
            self._t0_ns, self._next_k = now_ns, 0
        # Every sample of the grid t0 + k / rate_hz up to now + preview, so that a late tick
        # (a timer on a lock-step /clock skips the periods it missed) loses no sample.
        last_k = (now_ns - self._t0_ns + self.preview_ns) // self._period_ns
        if last_k - self._next_k >= MAX_BURST:
            self.get_logger().warn(f"reference fell {last_k - self._next_k} samples behind: "
                                   "skipped them", throttle_duration_sec=1.0)
            self._next_k = last_k
        for k in range(self._next_k, last_k + 1):
            msg = PointStamped()
            stamp_ns = self._t0_ns + k * self._period_ns
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
            msg.header.frame_id = self.frame_id
            t_s = k * self._period_ns * 1e-9
            msg.point.x = self.generator(t_s) * 1e-3
            msg.point.y = self.generator.rate(t_s) * 1e-3
            self.pub.publish(msg)
        self._next_k = max(self._next_k, last_k + 1)


def main(args: list[str] | None = None) -> None:
    run_node(ReferenceNode, args, name="reference", doc=__doc__,
             usage="reference [--ros-args -p kind:=sine -p amplitude_mm:=2.5 "
                   "-p frequency_hz:=0.159 -p rate_hz:=100.0 -p preview_s:=0.0 "
                   "-p use_sim_time:=true]")


if __name__ == "__main__":
    main()
