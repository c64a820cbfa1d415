"""model_server: serves a fitted IPMC model on the graph (feedforward, prediction, residual).

Loads ``model_file`` (forward ``lssvm-narx`` or inverse ``lssvm-narx-inverse``, as written by
``ipmc identify ... --out MODEL``) and optionally ``inverse_model_file`` (an inverse model, or
an augmented model's feedforward: ``ipmc identify --inverse --effects-from model_after.json``);
either may be empty, and what needs a missing model is simply not published.

- ``/ipmc/reference`` (PointStamped, x in m) -> ``/ipmc/feedforward`` (Vector3Stamped, x in V,
  |x| <= ``u_max_v``, the reference's header copied, so the controller pairs them by stamp):
  one feedforward step per reference sample, from the source ``feedforward`` chooses:
  ``inverse`` (the inverse model's stepper), ``forward-inversion`` (the forward model, if it
  has voltage channels (``ipmc identify --input-memory-taus``), inverted sample by sample:
  ``ipmc_model.forward_inversion``, about 0.1 ms a step) or ``auto`` (the inverse model if
  there is one, else the forward inversion if the forward model allows it, else none). The
  voltage history the feedforward sees is set by ``history_voltage``: ``applied`` (the latest
  ``/ipmc/voltage`` applied voltage when one arrived since the previous step, else the clamped
  feedforward), ``clamped`` or ``model`` (its own unclamped output; ``ipmc track`` runs
  ``clamped``, as its in-process loop).
- Under overload (references faster than the feedforward can answer them) the newest reference
  is always answered and one that has waited longer than ``reference_max_delay_s`` (wall
  time) while a newer one waits is skipped: a late feedforward is of no use to a controller,
  and answering every one would make each later still. The stepper goes on from the skipped
  references with the last voltage held. Every reference left unanswered is counted on
  ``/diagnostics`` (``skipped``: late ones, those lost before they reached the server, invalid
  ones), and the status is WARN while it happens. ``reference_max_delay_s:=0`` answers every
  reference however late.
- ``/ipmc/voltage`` (Vector3Stamped, x applied V) -> ``/ipmc/predicted`` (PointStamped, x in m,
  the voltage's header): one free-run step of the forward model per applied sample.
- ``/ipmc/displacement`` (PointStamped, x in m) paired with the prediction of the same header
  stamp -> ``/ipmc/residual`` (PointStamped, measured - predicted, m).
- ``~/reload`` (std_srvs/Trigger): reload the model file(s). All or nothing: a bad file keeps the
  models in use, and the response (success false) and the log say why. Setting
  ``model_file``, ``inverse_model_file`` or ``feedforward`` (``ros2 param set``) loads the new
  set the same way; a set that does not load is refused with the loader's sentence. Either
  way the new steppers go on from the samples kept, not from rest.
- ``/diagnostics`` (wall clock, every ``diagnostics_period_s``): model (loaded, kind, files),
  feedforward (rate, clamping, references beyond the displacements the inverse model was
  identified on, where it extrapolates), residual: the staleness monitor
  (``ipmc_model.residuals.ResidualMonitor``). By default it is fed the free-run residual and runs
  the drift test: the first ``monitor_reference`` samples after a (re)load are the residual of
  the freshly fitted model; the status turns WARN "model stale: ..." (with the statistic and its
  threshold) when the window's mean moves more than ``monitor_bias_factor`` reference spreads
  for ``monitor_patience`` checks in a row (drift, dehydration). ``monitor_residual:=one_step``
  gives the former Ljung-Box whiteness test on the one-step residual (``monitor_test:=auto``).

The work is done by the pure core ``ipmc_model.model_service``; this node maps topics,
parameters, the service and the diagnostics timer onto it.

Each message costs one kernel row per model (two for a voltage: free-run and one-step; a
reference served by forward inversion: 25 + 21 rows in two batched calls, plus one or two); the
node keeps no timers on the ROS clock, so it runs as well under ``use_sim_time:=true`` with
``sim_plant`` in lock-step.
"""


from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_srvs.srv import Trigger

from ipmc_driver.dataio import stamp_ns
from ipmc_driver.node_runtime import (
    ParameterSpec,
    check_changes,
    declare_checked,
    non_negative,
    one_of,
    positive,
    run_node,
    within,
)
from ipmc_driver.qos import DIAGNOSTICS_QOS, PAIRED_SAMPLE_QOS, SAMPLE_QOS
from ipmc_model.model_service import (  # noqa: F401 - the names tests and tools import here
    FEEDFORWARDS,
    MODEL_SET,
    MONITOR_RESIDUALS,
    MONITOR_TESTS,
    U_LIMIT_V,
    ModelService,
    ModelSet,
    ModelSetError,
    PairHistory,
    Reference,
    Status,
    build_monitor,
    choose_feedforward,
    describe,
    feedforward_status,
    history_depth,
    load_model_set,
    load_served_models,
    model_status,
    residual_status,
)
from ipmc_model.narx import HISTORY_VOLTAGES

_describe = describe   # the name this module gave it before the core existed

# A sample topic like the others (docs/interfaces.md: reliable, depth 100): at depth 10 a busy
# lock-step run lost feedforwards, and the controller waiting for one fell back to PID.
# Transient local (ipmc_driver.qos): a controller that matches late still gets the first
# feedforwards, which a lock-step controller waits for.
FEEDFORWARD_QOS = PAIRED_SAMPLE_QOS
HARDWARE_ID = "ipmc"
LEVELS = {0: DiagnosticStatus.OK, 1: DiagnosticStatus.WARN, 2: DiagnosticStatus.ERROR}


def _growth(value) -> str:
    ok = isinstance(value, float) and (value == 0.0 or value > 1.0)
    return "" if ok else f"must be > 1 (or 0 = off), got {value!r}"


def _monitor(description: str, default, check=positive) -> ParameterSpec:
    # The staleness monitor is built once (a reload restarts it): read-only.
    return ParameterSpec(default, description, True, check)


PARAMETERS = {
    # The model set (model_file, inverse_model_file, feedforward) may be set at run time: the
    # new set is loaded all or nothing, and a set that does not load is refused.
    "model_file": ParameterSpec(
        "", "model file (JSON) from 'ipmc identify --out': forward -> predictions and "
        "residual; inverse -> feedforward; '' = none"),
    "inverse_model_file": ParameterSpec("", "inverse model file for the feedforward ('' = none)"),
    "u_max_v": ParameterSpec(U_LIMIT_V, f"feedforward limit |u| <= u_max_v, V (0 < u_max_v <= "
                             f"{U_LIMIT_V})", check=within(0.0, U_LIMIT_V, low_open=True)),
    "history_voltage": ParameterSpec(
        "applied", "voltage history of the inverse model: applied (latest /ipmc/voltage) | "
        "clamped (own output, limited) | model (own output)", check=one_of(*HISTORY_VOLTAGES)),
    "feedforward": ParameterSpec(
        "auto", "feedforward source: auto (the inverse model if given, else the forward model "
        "inverted if it has voltage channels) | inverse | forward-inversion (about 0.1 ms per "
        "sample)", check=one_of(*FEEDFORWARDS)),
    "reference_max_delay_s": ParameterSpec(
        0.2, "overload: a reference that has waited longer than this (wall time, s) while a "
        "newer one waits is skipped and counted; the newest is always answered; 0 = answer "
        "every reference however late", check=non_negative),
    "monitor_residual": _monitor(
        "residual fed to the staleness monitor: free_run (measured - free-run prediction, "
        "default) | one_step (measured - one-step prediction)", "free_run",
        one_of(*MONITOR_RESIDUALS)),
    "monitor_test": _monitor(
        "staleness test: drift (window mean/spread against the reference measured after each "
        "load) | whiteness (Ljung-Box + bias) | both | auto (drift on free_run, whiteness on "
        "one_step)", "auto", one_of(*MONITOR_TESTS)),
    # Measured on the simulated plant at 100 Hz (docs/diagnose.md, "Online monitor"): the drift
    # test on the free-run residual flagged a drifting plant 3-10 min after the fit and no
    # clean one in 30 min; the whiteness test on the one-step residual flagged the clean plant
    # at decimate 1 and 5 most of the time, at 10 x 300 2 % of the time.
    "monitor_window": _monitor("monitor window, samples after decimation (0: 600 for "
                               "drift/both, 300 for whiteness)", 0, non_negative),
    "monitor_reference": _monitor("drift test: samples after decimation, from each (re)load, "
                                  "that define the normal residual (mean m0, spread s0)", 1200),
    "monitor_bias_factor": _monitor("drift test: a check fails when |window mean - m0| > this "
                                    "x s0", 1.5),
    "monitor_growth": _monitor("drift test: a check fails when the window spread > this x s0 "
                               "(> 1; 0 = off)", 0.0, _growth),
    "monitor_lags": _monitor("whiteness test: Ljung-Box lags", 20),
    "monitor_decimate": _monitor("monitor keeps every n-th residual sample", 10),
    "monitor_check_every": _monitor("monitor: samples (after decimation) between checks", 50),
    "monitor_patience": _monitor("monitor: failed checks in a row before 'model stale' (WARN)",
                                 3),
    "diagnostics_period_s": ParameterSpec(1.0, "wall-clock period of /diagnostics, s", True,
                                          positive),
}


def _stamped(cls, stamp: int, frame_id: str):
    out = cls()
    out.header.stamp.sec, out.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
    out.header.frame_id = frame_id
    return out


class ModelServer(Node):
    def __init__(self, **node_kwargs) -> None:
        super().__init__("model_server", **node_kwargs)
        p = declare_checked(self, PARAMETERS)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.service = ModelService(build_monitor(p), p["monitor_residual"], p["u_max_v"],
                                    p["history_voltage"], p["reference_max_delay_s"])
        self.service.models = ModelSet(p["model_file"], p["inverse_model_file"],
                                       p["feedforward"])
        self._pending = None   # a model set loaded by _validate_parameters, to be installed
        ok, why = self.reload()
        if not ok:
            self.get_logger().error(f"no model served: {why}")

        self.pub_ff = self.create_publisher(Vector3Stamped, "/ipmc/feedforward", FEEDFORWARD_QOS)
        self.pub_pred = self.create_publisher(PointStamped, "/ipmc/predicted", SAMPLE_QOS)
        self.pub_res = self.create_publisher(PointStamped, "/ipmc/residual", SAMPLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
        # Volatile: a transient-local subscription would refuse a volatile reference publisher
        # (a user's, ros2 topic pub).
        self._sub_ref = self.create_subscription(PointStamped, "/ipmc/reference",
                                                 self._on_reference, SAMPLE_QOS)
        self.create_subscription(Vector3Stamped, "/ipmc/voltage", self._on_voltage, SAMPLE_QOS)
        self.create_subscription(PointStamped, "/ipmc/displacement", self._on_displacement,
                                 SAMPLE_QOS)
        self.create_service(Trigger, "~/reload", self._on_reload)
        # Diagnostics on the wall clock: they keep coming when a simulated clock stalls.
        self.create_timer(p["diagnostics_period_s"], self.publish_diagnostics,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))

    # -- parameters and models ------------------------------------------------------------------
    def _validate_parameters(self, params) -> SetParametersResult:
        result = check_changes(PARAMETERS, params)
        new = {p.name: p.value for p in params}
        self._pending = None
        if result.successful and MODEL_SET.intersection(new):
            names = {k: new.get(k, self.get_parameter(k).value) for k in MODEL_SET}
            try:
                self._pending = load_served_models(**names)
            except ValueError as exc:
                self.get_logger().error(f"parameters refused: {exc}")
                return SetParametersResult(successful=False, reason=str(exc))
        return result

    def _apply_parameters(self, params) -> None:
        g = self.get_parameter
        self.service.u_max_v = g("u_max_v").value
        self.service.history_voltage = g("history_voltage").value
        self.service.queue.max_delay_s = g("reference_max_delay_s").value
        if self._pending is not None:
            models, self._pending = self._pending, None
            self._install_logged(models)

    def _install_logged(self, models) -> str:
        msg = self.service.install(models, time.strftime("%Y-%m-%d %H:%M:%S"))
        self.get_logger().info(f"loaded {models.files}: {msg}")
        return msg

    def reload(self) -> tuple[bool, str]:
        """(Re)load the model file(s); all or nothing. Returns (success, message)."""
        m = self.service.models
        try:
            models = load_served_models(m.model_file, m.inverse_model_file, m.feedforward)
        except ValueError as exc:  # ModelFileError and ModelSetError are ValueErrors
            if m.model_file or m.inverse_model_file:
                self.service.load_error = str(exc)
            return False, str(exc)
        return True, self._install_logged(models)

    def _on_reload(self, request, response):
        ok, msg = self.reload()
        self.service.reloads += 1
        response.success = ok
        files = self.service.models.files
        if ok:
            response.message = f"reloaded {files}: {msg}"
        else:
            self.service.failed_reloads += 1
            kept = "no model served" if self.service.models.empty else "kept the models in use"
            response.message = f"reload failed, {kept}: {msg}"
            self.get_logger().error(response.message)
        return response

    # -- messages -------------------------------------------------------------------------------
    def _on_reference(self, msg: PointStamped, info: dict) -> None:
        serving = self.service.serves_feedforward
        one_publisher = serving and self._sub_ref.get_publisher_count() == 1
        self._queue_reference(msg, info, one_publisher)
        # rclpy hands over one message per turn of the executor; under overload the others
        # wait in the subscription's queue (depth 100), whose oldest are then overwritten
        # without a word. Taking them all here shows the newest, and what is skipped is counted.
        with self._sub_ref.handle:
            while (taken := self._sub_ref.handle.take_message(PointStamped, False)) is not None:
                self._queue_reference(*taken, one_publisher)
        due, late = self.service.queue.take(time.time_ns())
        if not serving:
            return
        self.service.skip(late)
        for ref in due:
            ff = self.service.answer(ref.y_mm)
            if ff is not None:
                out = _stamped(Vector3Stamped, ref.stamp_ns, ref.frame_id)
                out.vector.x = ff.u_v
                self.pub_ff.publish(out)
        self._log_notes()

    def _queue_reference(self, msg: PointStamped, info: dict, one_publisher: bool) -> None:
        # received_timestamp: the middleware's reception time on the system clock (0 if the
        # middleware does not tell it: then now).
        received_ns = info.get("received_timestamp") or time.time_ns()
        self.service.queue.offer(
            Reference(stamp_ns(msg.header.stamp), msg.point.x * 1e3, received_ns,
                      msg.header.frame_id),
            info.get("publication_sequence_number"), one_publisher)

    def _on_voltage(self, msg: Vector3Stamped) -> None:
        stamp = stamp_ns(msg.header.stamp)
        y_free, e_free = self.service.predict(stamp, float(msg.vector.x))
        if y_free is not None:
            out = _stamped(PointStamped, stamp, msg.header.frame_id)
            out.point.x = y_free * 1e-3
            self.pub_pred.publish(out)
        self._publish_residual(stamp, msg.header.frame_id, e_free)

    def _on_displacement(self, msg: PointStamped) -> None:
        stamp = stamp_ns(msg.header.stamp)
        e_free = self.service.measure(stamp, msg.point.x * 1e3)
        self._publish_residual(stamp, msg.header.frame_id, e_free)

    def _publish_residual(self, stamp: int, frame_id: str, e_free_mm: float | None) -> None:
        if e_free_mm is not None:
            out = _stamped(PointStamped, stamp, frame_id)
            out.point.x = e_free_mm * 1e-3
            self.pub_res.publish(out)
        self._log_notes()

    def _log_notes(self) -> None:
        for kind, text in self.service.notes:
            self.get_logger().warn(text, throttle_duration_sec=5.0 if kind == "beyond" else 1.0)
        self.service.notes.clear()

    # -- diagnostics ----------------------------------------------------------------------------
    def publish_diagnostics(self) -> None:
        """Publish one DiagnosticArray: model, feedforward, residual."""
        s = self.service
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [self._status("model", model_status(s)),
                      self._status("feedforward", feedforward_status(s, time.monotonic())),
                      self._status("residual", residual_status(s))]
        self.pub_diag.publish(arr)

    @staticmethod
    def _status(name: str, status: Status) -> DiagnosticStatus:
        return DiagnosticStatus(
            level=LEVELS[status.level], name=f"model_server: {name}", message=status.message,
            hardware_id=HARDWARE_ID,
            values=[KeyValue(key=k, value=str(v)) for k, v in status.values.items()])


def main(args: list[str] | None = None) -> None:
    run_node(ModelServer, args, name="model_server", doc=__doc__,
             usage="model_server [--ros-args -p model_file:=MODEL.json "
                   "-p inverse_model_file:=INVERSE.json -p u_max_v:=3.0 "
                   "-p history_voltage:=applied|clamped|model "
                   "-p feedforward:=auto|inverse|forward-inversion "
                   "-p reference_max_delay_s:=0.2 "
                   "-p monitor_residual:=free_run|one_step "
                   "-p monitor_test:=auto|drift|whiteness|both -p use_sim_time:=true]\n"
                   "service: /model_server/reload (std_srvs/srv/Trigger)")


if __name__ == "__main__":
    main()
