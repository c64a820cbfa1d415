"""excitation: drives the IPMC open loop, one voltage per sample, for an identification record.

Publishes ``/ipmc/command`` (std_msgs/Float64, V) and ``/ipmc/command_stamped``
(Vector3Stamped, x in V, stamped with the sample it answers: a lock-step sim_plant applies it
to that sample), one voltage per ``/ipmc/displacement`` sample, so the excitation runs at the
plant's (or the rig's) own rate, in real time or lock-step alike. The voltages come from
``ipmc_control.excitation``: ``kind`` ``mixed`` | ``steps`` | ``random-sine`` (with
``amplitude_v``, ``hold_s``, ``duration_s``, ``seed``) or ``file`` (``path``: a ``t,u`` CSV or
an ``ipmc diagnose`` next_experiment.json at ``rate_hz``); never beyond 3 V.

The excitation starts with the first sample after ``/ipmc/command`` has matched
``min_subscribers`` subscriptions (the plant and a recorder), so a recorder holds every
command. Until then, in real time each sample is answered with 0 V; on sim time (a lock-step
plant, which waits for its answer) the sample is held unanswered and answered with the first
voltage once the gate opens, so the plant does not run ahead through 0 V samples the graph's
discovery happened to take. After the last voltage it logs
"excitation: finished" and commands 0 V; then it exits (code 0) ``linger_s`` later, or, with
``exit_at_end:=false``, answers no further sample and runs until stopped: a lock-step plant
then waits instead of running on alone (``ipmc bringup --lockstep --excite`` stops the plant
when it reads the line, so the record ends with the excitation).
"""

from __future__ import annotations

from geometry_msgs.msg import PointStamped, Vector3Stamped
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.node import Node
from std_msgs.msg import Float64

from ipmc_control.excitation import KINDS, ExcitationError, load_excitation, make_excitation
from ipmc_driver.matching import MatchGate
from ipmc_driver.node_runtime import (
    ParameterSpec,
    Terminated,
    declare_checked,
    non_negative,
    one_of,
    positive,
    run_node,
)
from ipmc_driver.qos import COMMAND_WRITER_QOS, SAMPLE_QOS

PARAMETERS = {
    "kind": ParameterSpec("mixed", " | ".join((*KINDS, "file")), True,
                          one_of(*KINDS, "file")),
    "path": ParameterSpec("", "file: CSV (t, u in s, V) or next_experiment.json", True),
    "amplitude_v": ParameterSpec(3.0, "largest |voltage|, V (<= 3)", True, positive),
    "hold_s": ParameterSpec(8.0, "mixed/steps: length of each held level, s", True, positive),
    "duration_s": ParameterSpec(240.0, "length, s (a file: at most this long; 0 = all of it)",
                                True, non_negative),
    "seed": ParameterSpec(0, "seed of the random parts (>= 0)", True, non_negative),
    "rate_hz": ParameterSpec(100.0, "the plant's sampling rate, Hz", True, positive),
    "min_subscribers": ParameterSpec(
        1, "start once /ipmc/command has matched this many subscriptions", True, non_negative),
    "linger_s": ParameterSpec(0.5, "wall time between the last command and the exit, s", True,
                              non_negative),
    "exit_at_end": ParameterSpec(
        True, "exit linger_s after the end; false: answer no further sample (a lock-step "
        "plant then waits) and run until stopped", True),
}


#: Longest wait (s) for the readers to acknowledge the final 0 V: well inside the grace
#: ``ipmc bringup`` gives a node between SIGINT and SIGKILL (2 s).
ZERO_ACK_S = 0.5


class ExcitationNode(Node):
    def __init__(self, **node_kwargs) -> None:
        super().__init__("excitation", **node_kwargs)
        p = declare_checked(self, PARAMETERS)
        try:
            if p["kind"] == "file":
                self.excitation = load_excitation(p["path"], p["rate_hz"],
                                                  p["duration_s"] or None)
            else:
                self.excitation = make_excitation(
                    p["kind"], amplitude_v=p["amplitude_v"], hold_s=p["hold_s"],
                    seconds=p["duration_s"], rate_hz=p["rate_hz"], seed=p["seed"])
        except ExcitationError as exc:
            raise ValueError(str(exc)) from None
        self._k = -1        # index of the next voltage; -1 until the start
        self._linger_s, self._exit_at_end = p["linger_s"], p["exit_at_end"]
        self._quiet = False
        self._held: PointStamped | None = None   # sim time: the sample waiting for the start
        self.pub = self.create_publisher(Float64, "/ipmc/command", COMMAND_WRITER_QOS)
        self.pub_stamped = self.create_publisher(Vector3Stamped, "/ipmc/command_stamped",
                                                 COMMAND_WRITER_QOS)
        self._gate = MatchGate(self.count_subscribers,
                               [(self.pub, "/ipmc/command", p["min_subscribers"])],
                               warn=self.get_logger().warn)
        self.create_subscription(PointStamped, "/ipmc/displacement", self._on_sample,
                                 SAMPLE_QOS)
        self._sim_time = bool(self.get_parameter("use_sim_time").value)
        if self._sim_time:   # polls the gate for a held sample until the excitation starts
            self._hold_timer = self.create_timer(0.01, self._answer_held,
                                                 clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f"excitation: {self.excitation.describe()}")

    def _answer_held(self) -> None:
        if self._k >= 0:
            self._hold_timer.cancel()   # started: nothing is held any more
            return
        if self._held is not None and self._gate.ready():
            held, self._held = self._held, None
            self._on_sample(held)

    def _on_sample(self, msg: PointStamped) -> None:
        u = self.excitation.u_v
        if self._k < 0 and self._gate.ready():
            self._k = 0
            self.get_logger().info("excitation: started")
        elif self._k < 0 and self._sim_time:
            self._held = msg     # answered by _answer_held once the gate opens
            return
        if 0 <= self._k < u.size:
            self._command(float(u[self._k]), msg)
            self._k += 1
            if self._k == u.size:
                self._finish()
        elif self._k < 0 or self._exit_at_end or not self._quiet:
            self._command(0.0, msg)
            # after the end, without exit_at_end: this 0 V, then no further answer
            self._quiet = self._k >= u.size

    def _finish(self) -> None:
        self.get_logger().info(f"excitation: finished, {self.excitation.u_v.size} samples "
                               f"({self.excitation.duration_s:g} s)")
        if self._exit_at_end:
            self.create_timer(max(self._linger_s, 1e-3), self._exit,
                              clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _command(self, u_v: float, sample: PointStamped) -> None:
        self.pub.publish(Float64(data=u_v))
        stamped = Vector3Stamped()
        stamped.header = sample.header
        stamped.vector.x = u_v
        self.pub_stamped.publish(stamped)

    def _exit(self) -> None:
        raise Terminated()

    def destroy_node(self) -> None:
        """Leave the actuator at 0 V on every exit path, and wait (at most
        :data:`ZERO_ACK_S`) until the reliable readers (driver, recorder) have it: a writer
        destroyed right after its last sample can take it along undelivered, and a recorded
        run would then end on its last nonzero voltage."""
        try:
            self.pub.publish(Float64(data=0.0))
            self.pub.wait_for_all_acked(Duration(seconds=ZERO_ACK_S))
        finally:
            super().destroy_node()


def main(args: list[str] | None = None) -> None:
    run_node(ExcitationNode, args, name="excitation", doc=__doc__,
             usage="excitation [--ros-args -p kind:=mixed|steps|random-sine|file "
                   "-p path:=next_experiment.json -p amplitude_v:=3.0 -p hold_s:=8.0 "
                   "-p duration_s:=240.0 -p rate_hz:=100.0 -p min_subscribers:=2]")


if __name__ == "__main__":
    main()
