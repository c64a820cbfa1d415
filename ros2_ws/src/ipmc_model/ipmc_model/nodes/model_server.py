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

Each message costs one kernel row per model (two for a voltage: free-run and one-step; a
reference served by forward inversion: 25 + 21 rows in two batched calls, plus one or two); the
node keeps no timers on the ROS clock, so it runs as well under ``use_sim_time:=true`` with
``sim_plant`` in lock-step.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict, deque

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped, Vector3Stamped
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_srvs.srv import Trigger

from ipmc_driver.dataio import stamp_ns
from ipmc_driver.node_runtime import run_node
from ipmc_driver.qos import DIAGNOSTICS_QOS, PAIRED_SAMPLE_QOS, SAMPLE_QOS
from ipmc_model.effects import AugmentedInverse, AugmentedModel, load_any_model
from ipmc_model.forward_inversion import ForwardInversionFeedforward
from ipmc_model.hysteresis import GpiInverse
from ipmc_model.narx import (
    HISTORY_VOLTAGES,
    InverseNarxModel,
    NarxCommittee,
    NarxModel,
    out_of_reach,
    reach_mm,
)
from ipmc_model.residuals import ResidualMonitor

# A sample topic like the others (docs/interfaces.md: reliable, depth 100): at depth 10 a busy
# lock-step run lost feedforwards, and the controller waiting for one fell back to PID.
# Transient local (ipmc_driver.qos): a controller that matches late still gets the first
# feedforwards, which a lock-step controller waits for.
FEEDFORWARD_QOS = PAIRED_SAMPLE_QOS
HARDWARE_ID = "ipmc"
U_LIMIT_V = 3.0  # the actuators' safe limit (paper section 2.1); u_max_v may only be lower
FEEDFORWARDS = ("auto", "inverse", "forward-inversion")
MONITOR_RESIDUALS = ("one_step", "free_run")
MONITOR_TESTS = ("auto", "drift", "whiteness", "both")
# monitor_test auto: the test that works on each residual (docs/diagnose.md, "Online monitor").
AUTO_TEST = {"free_run": "drift", "one_step": "whiteness"}
# monitor_window 0: measured per test, samples after decimation (10 Hz at the defaults).
AUTO_WINDOW = {"drift": 600, "both": 600, "whiteness": 300}
# Unpaired predictions / measurements kept while waiting for their partner (stamps).
PAIR_MEMORY = 256
# Samples of history handed to new steppers after a reload: at least this many (more than any
# sane lag depth), or as many as the model's state needs (its history_samples: a creep undone
# around an inverse, tau 20 s, needs 100 s), up to HISTORY_MAX (10 min at 100 Hz). Both
# histories always keep HISTORY_MAX, so a reload to a model of longer memory has its history.
HISTORY_DEPTH = 256
HISTORY_MAX = 60_000
# A free-run output beyond this (mm) is a diverged model, not a displacement.
DIVERGED_MM = 1e3


# What the model server serves as an inverse model (feedforward:=inverse).
INVERSES = (InverseNarxModel, AugmentedInverse, GpiInverse)


class PairHistory:
    """The last ``maxlen`` pairs of samples (two floats each), oldest first, in a ring buffer
    (a deque of 60 000 tuples would hold about 6 MB)."""

    def __init__(self, maxlen: int):
        self.maxlen = int(maxlen)
        self._buf = np.empty((self.maxlen, 2))
        self._n = 0       # pairs written since the last clear

    def __len__(self) -> int:
        return min(self._n, self.maxlen)

    def append(self, a: float, b: float) -> None:
        self._buf[self._n % self.maxlen] = a, b
        self._n += 1

    def set_last(self, a: float, b: float) -> None:
        """Replace the newest pair."""
        if not self._n:
            raise IndexError("the history is empty")
        self._buf[(self._n - 1) % self.maxlen] = a, b

    def last(self) -> tuple[float, float]:
        if not self._n:
            raise IndexError("the history is empty")
        a, b = self._buf[(self._n - 1) % self.maxlen]
        return float(a), float(b)

    def clear(self) -> None:
        self._n = 0

    def tail(self, n: int) -> tuple:
        """The newest ``n`` pairs (fewer if fewer were kept) as two arrays, oldest first;
        (None, None) when empty: a stepper's history arguments."""
        n = min(int(n), len(self))
        if n <= 0:
            return None, None
        idx = np.arange(self._n - n, self._n) % self.maxlen
        pairs = self._buf[idx]
        return pairs[:, 0].copy(), pairs[:, 1].copy()


def history_depth(model) -> int:
    """Samples of history a new stepper of ``model`` (any model served: forward, inverse,
    forward inversion) is given: its ``history_samples`` within HISTORY_DEPTH .. HISTORY_MAX."""
    return min(max(HISTORY_DEPTH, int(model.history_samples)), HISTORY_MAX)


class ModelSetError(ValueError):
    """A model file cannot be served (unreadable, or of the wrong kind for its parameter)."""


def load_model_set(model_file: str, inverse_model_file: str = ""):
    """Load the forward and inverse models from the two parameters' files.

    Returns
    -------
    (forward, inverse) : (NarxModel, NarxCommittee or None; InverseNarxModel,
        AugmentedInverse or None)

    Raises
    ------
    ModelSetError, ModelFileError
        One sentence naming the file and the problem.
    """
    forward = inverse = None
    if model_file:
        m = load_any_model(model_file)
        if isinstance(m, INVERSES):
            inverse = m
        elif isinstance(m, (NarxModel, NarxCommittee)):
            forward = m
        else:
            raise ModelSetError(f"{model_file}: {_not_served(m)}")
    if inverse_model_file:
        m = load_any_model(inverse_model_file)
        if isinstance(m, AugmentedModel):
            raise ModelSetError(f"{inverse_model_file}: {_not_served(m)}")
        if not isinstance(m, INVERSES):
            hint = (" A forward model with voltage channels goes in model_file: "
                    "feedforward:=auto inverts it." if isinstance(m, NarxModel)
                    and m.uses_voltage_channels else "")
            raise ModelSetError(f"{inverse_model_file}: inverse_model_file holds a "
                                f"{type(m).__name__}, not an inverse model "
                                f"(ipmc identify --inverse).{hint}")
        if inverse is not None:
            raise ModelSetError(f"{model_file} and {inverse_model_file} are both inverse models; "
                                "model_file should be the forward one.")
        inverse = m
    if forward is not None and forward.n_inputs_ != 1 and not forward.uses_voltage_channels:
        raise ModelSetError(f"{model_file}: the forward model takes {forward.n_inputs_} input "
                            "channels; the model server has only the voltage.")
    return forward, inverse


def _not_served(model) -> str:
    """Why the model server cannot serve ``model`` (one sentence)."""
    if isinstance(model, AugmentedModel):
        return ("an augmented model (ipmc diagnose) is not served as it is; serve its "
                "feedforward, made by 'ipmc identify --model lssvm-narx --inverse "
                "--effects-from MODEL --data RECORD', as inverse_model_file.")
    return (f"a {type(model).__name__} has no step-wise API; the model server serves "
            "lssvm-narx (also a committee) and lssvm-narx-inverse models, and augmented "
            "models' feedforwards.")


def choose_feedforward(feedforward: str, forward, inverse) -> str:
    """The feedforward source for a ``feedforward`` parameter and the loaded models.

    Returns
    -------
    str
        ``"inverse"``, ``"forward-inversion"`` or ``"none"`` (auto without a usable model).

    Raises
    ------
    ModelSetError
        An explicit choice the models cannot serve, in one sentence.
    """
    invertible = forward is not None and forward.uses_voltage_channels
    if feedforward == "inverse":
        if inverse is None:
            raise ModelSetError("feedforward:=inverse needs an inverse model "
                                "(inverse_model_file, from ipmc identify --inverse).")
        return "inverse"
    if feedforward == "forward-inversion":
        if forward is None:
            raise ModelSetError("feedforward:=forward-inversion needs a forward model in "
                                "model_file.")
        if not invertible:
            raise ModelSetError("feedforward:=forward-inversion needs a forward model with "
                                "voltage channels (ipmc identify --input-memory-taus 0.3 0.5 "
                                "--no-raw-voltage --output-lags 0); this one takes the "
                                "voltage itself.")
        return "forward-inversion"
    if feedforward != "auto":
        raise ModelSetError(f"feedforward must be one of {FEEDFORWARDS}, got {feedforward!r}.")
    if inverse is not None:
        return "inverse"
    return "forward-inversion" if invertible else "none"


def _stamp_ns(msg) -> int:
    return stamp_ns(msg.header.stamp)


def _describe(model) -> str:
    if model is None:
        return "none"
    if isinstance(model, AugmentedInverse):
        effects = ", ".join(model.effect_names)
        return f"{_describe(model.inverse)} with the effects undone around it: {effects}"
    if isinstance(model, GpiInverse):
        m = model.model
        return (f"gpi-inverse (numerical inverse of a GPI model: charging tau "
                f"{m.charge_tau_s_:.3g} s, {len(m.memory_taus_s_)} relaxations, "
                f"{m.thresholds_.size} plays)")
    if isinstance(model, NarxCommittee):
        centres = sum(m.regressor_.centers_.shape[0] for m in model.members)
        return (f"lssvm-narx-committee ({len(model.members)} models, {centres} centres, max lag "
                f"{model.max_lag_})")
    narx = model.narx_ if isinstance(model, InverseNarxModel) else model
    kind = "lssvm-narx-inverse" if isinstance(model, InverseNarxModel) else "lssvm-narx"
    channels = ""
    if narx.uses_voltage_channels:
        taus = ", ".join(f"{float(t):g}" for t in narx.input_memory_taus_s)
        channels = (f", voltage channels: low-passed {taus} s"
                    f"{' and the voltage' if narx.include_voltage else ''}")
    return (f"{kind} ({narx.regressor_.centers_.shape[0]} centres, max lag {narx.max_lag_}"
            f"{channels})")


# The parameters that make the model set: setting any of them loads the set anew.
MODEL_SET = frozenset({"model_file", "inverse_model_file", "feedforward"})

# What /diagnostics calls each feedforward source.
FEEDFORWARD_NAMES = {"inverse": "inverse model", "forward-inversion":
                     "forward-model inversion", "none": "none"}


class ModelServer(Node):
    def __init__(self) -> None:
        super().__init__("model_server")
        d = ParameterDescriptor
        # The model set (model_file, inverse_model_file, feedforward) may be set at run time:
        # the new set is loaded all or nothing, and a set that does not load is refused.
        self.declare_parameter("model_file", "", d(
            description="model file (JSON) from 'ipmc identify --out': forward -> predictions "
                        "and residual; inverse -> feedforward; '' = none"))
        self.declare_parameter("inverse_model_file", "", d(
            description="inverse model file for the feedforward ('' = none)"))
        self.declare_parameter("u_max_v", U_LIMIT_V, d(
            description=f"feedforward limit |u| <= u_max_v, V (0 < u_max_v <= {U_LIMIT_V})"))
        self.declare_parameter("history_voltage", "applied", d(
            description="voltage history of the inverse model: applied (latest /ipmc/voltage) "
                        "| clamped (own output, limited) | model (own output)"))
        self.declare_parameter("feedforward", "auto", d(
            description="feedforward source: auto (the inverse model if given, else the "
                        "forward model inverted if it has voltage channels) | inverse | "
                        "forward-inversion (about 0.1 ms per sample)"))
        # The staleness monitor (all read-only: it is built once; a reload restarts it).
        self.declare_parameter("monitor_residual", "free_run", d(
            description="residual fed to the staleness monitor: free_run (measured - free-run "
                        "prediction, default) | one_step (measured - one-step prediction)",
            read_only=True))
        self.declare_parameter("monitor_test", "auto", d(
            description="staleness test: drift (window mean/spread against the reference "
                        "measured after each load) | whiteness (Ljung-Box + bias) | both | "
                        "auto (drift on free_run, whiteness on one_step)", read_only=True))
        # Measured on the simulated plant at 100 Hz (docs/diagnose.md, "Online monitor"): the
        # drift test on the free-run residual flagged a drifting plant 3-10 min after the fit
        # and no clean one in 30 min; the whiteness test on the one-step residual flagged the
        # clean plant at decimate 1 and 5 most of the time, at 10 x 300 2 % of the time.
        self.declare_parameter("monitor_window", 0, d(
            description="monitor window, samples after decimation (0: 600 for drift/both, "
                        "300 for whiteness)", read_only=True))
        self.declare_parameter("monitor_reference", 1200, d(
            description="drift test: samples after decimation, from each (re)load, that "
                        "define the normal residual (mean m0, spread s0)", read_only=True))
        self.declare_parameter("monitor_bias_factor", 1.5, d(
            description="drift test: a check fails when |window mean - m0| > this x s0",
            read_only=True))
        self.declare_parameter("monitor_growth", 0.0, d(
            description="drift test: a check fails when the window spread > this x s0 "
                        "(> 1; 0 = off)", read_only=True))
        self.declare_parameter("monitor_lags", 20, d(
            description="whiteness test: Ljung-Box lags", read_only=True))
        self.declare_parameter("monitor_decimate", 10, d(
            description="monitor keeps every n-th residual sample", read_only=True))
        self.declare_parameter("monitor_check_every", 50, d(
            description="monitor: samples (after decimation) between checks", read_only=True))
        self.declare_parameter("monitor_patience", 3, d(
            description="monitor: failed checks in a row before 'model stale' (WARN)",
            read_only=True))
        self.declare_parameter("diagnostics_period_s", 1.0, d(
            description="wall-clock period of /diagnostics, s", read_only=True))
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        g = self.get_parameter
        self.model_file = g("model_file").value
        self.inverse_model_file = g("inverse_model_file").value
        self.u_max_v = float(g("u_max_v").value)
        self.history_voltage = g("history_voltage").value
        self.feedforward = g("feedforward").value
        self.monitor_residual = g("monitor_residual").value
        problem = self._check(u_max_v=self.u_max_v, history_voltage=self.history_voltage)
        if self.feedforward not in FEEDFORWARDS:
            problem = f"feedforward must be one of {FEEDFORWARDS}, got {self.feedforward!r}"
        if self.monitor_residual not in MONITOR_RESIDUALS:
            problem = (f"monitor_residual must be one of {MONITOR_RESIDUALS}, "
                       f"got {self.monitor_residual!r}")
        if problem:
            raise ValueError(problem)
        self.monitor = self._build_monitor()
        window = self.monitor.window * self.monitor.decimate
        self._e_free = deque(maxlen=window)   # residuals (mm) for the RMS on /diagnostics
        self._e_one = deque(maxlen=window)

        # Models and their steppers; the histories re-seed the steppers after a reload.
        self.forward = self.inverse = None
        self.ff_source = "none"   # what serves /ipmc/feedforward: inverse | forward-inversion
        self._inversion: ForwardInversionFeedforward | None = None
        self._free = self._one = self._ff = None
        self._one_stamp: int | None = None    # stamp of the one-step stepper's last step
        self._sample_hist = PairHistory(HISTORY_MAX)   # (u applied V, y measured mm)
        self._ff_hist = PairHistory(HISTORY_MAX)       # (y desired mm, u V)
        self._pred: OrderedDict[int, tuple] = OrderedDict()     # stamp -> (u, y free, y one)
        self._meas: OrderedDict[int, float] = OrderedDict()     # stamp -> y measured mm
        self._u_applied_v: float | None = None
        self._u_applied_new = False
        self.loaded_at: str = "never"
        self.load_error = ""
        self._pending = None   # a model set loaded by _validate_parameters, to be installed
        self.reloads = self.failed_reloads = 0
        # Counters for /diagnostics.
        self.ff_count = self.ff_clamped = self.ff_skipped = 0
        # References beyond the displacements the inverse was identified on (it extrapolates).
        self.ff_reach: tuple[float, float] | None = None
        self.ff_beyond = 0
        self._ff_beyond_last = self._ff_beyond_period = 0
        self.pred_count = self.residual_count = self.free_resets = 0
        self._ff_count_last = 0
        self._diag_wall_last = time.monotonic()
        self.ff_rate_hz = 0.0
        self.ff_last_v = math.nan
        ok, why = self.reload()
        if not ok:
            self.get_logger().error(f"no model served: {why}")

        self.pub_ff = self.create_publisher(Vector3Stamped, "/ipmc/feedforward", FEEDFORWARD_QOS)
        self.pub_pred = self.create_publisher(PointStamped, "/ipmc/predicted", SAMPLE_QOS)
        self.pub_res = self.create_publisher(PointStamped, "/ipmc/residual", SAMPLE_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", DIAGNOSTICS_QOS)
        # Volatile: a transient-local subscription would refuse a volatile reference publisher
        # (a user's, ros2 topic pub).
        self.create_subscription(PointStamped, "/ipmc/reference", self._on_reference, SAMPLE_QOS)
        self.create_subscription(Vector3Stamped, "/ipmc/voltage", self._on_voltage, SAMPLE_QOS)
        self.create_subscription(PointStamped, "/ipmc/displacement", self._on_displacement,
                                 SAMPLE_QOS)
        self.create_service(Trigger, "~/reload", self._on_reload)
        # Diagnostics on the wall clock: they keep coming when a simulated clock stalls.
        self.create_timer(float(g("diagnostics_period_s").value), self.publish_diagnostics,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))

    # -- parameters -----------------------------------------------------------------------------
    def _build_monitor(self) -> ResidualMonitor:
        """The ResidualMonitor of the monitor_* parameters; ValueError names the bad one."""
        g = self.get_parameter
        test = g("monitor_test").value
        if test not in MONITOR_TESTS:
            raise ValueError(f"monitor_test must be one of {MONITOR_TESTS}, got {test!r}")
        if test == "auto":
            test = AUTO_TEST[self.monitor_residual]
        window = int(g("monitor_window").value) or AUTO_WINDOW[test]
        growth = float(g("monitor_growth").value)
        if growth != 0.0 and not growth > 1.0:
            raise ValueError(f"monitor_growth must be > 1 (or 0 = off), got {growth}")
        try:
            return ResidualMonitor(
                window=window, lags=g("monitor_lags").value,
                check_every=g("monitor_check_every").value,
                patience=g("monitor_patience").value, decimate=g("monitor_decimate").value,
                test=test, reference=g("monitor_reference").value,
                bias_factor=g("monitor_bias_factor").value, growth=growth or None, unit="mm")
        except ValueError as exc:
            raise ValueError(f"monitor_* parameters: {exc}") from None

    @staticmethod
    def _check(**new) -> str:
        if "u_max_v" in new:
            u = new["u_max_v"]
            if not (isinstance(u, float) and 0.0 < u <= U_LIMIT_V):
                return f"u_max_v must be a float in (0, {U_LIMIT_V}] V, got {u!r}"
        if "history_voltage" in new and new["history_voltage"] not in HISTORY_VOLTAGES:
            return (f"history_voltage must be one of {HISTORY_VOLTAGES}, "
                    f"got {new['history_voltage']!r}")
        return ""

    def _validate_parameters(self, params) -> SetParametersResult:
        new = {p.name: p.value for p in params}
        problem = self._check(**new)
        if problem:
            return SetParametersResult(successful=False, reason=problem)
        self._pending = None
        if MODEL_SET.intersection(new):
            names = {k: new.get(k, self.get_parameter(k).value) for k in MODEL_SET}
            try:
                self._pending = (names, self._load(**names))
            except ValueError as exc:
                self.get_logger().error(f"parameters refused: {exc}")
                return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params) -> None:
        self.u_max_v = float(self.get_parameter("u_max_v").value)
        self.history_voltage = self.get_parameter("history_voltage").value
        if self._pending is not None:
            names, loaded = self._pending
            self._pending = None
            self.model_file, self.inverse_model_file = (names["model_file"],
                                                        names["inverse_model_file"])
            self.feedforward = names["feedforward"]
            self._install(*loaded)

    # -- models ---------------------------------------------------------------------------------
    @staticmethod
    def _load(model_file: str, inverse_model_file: str, feedforward: str) -> tuple:
        """(forward, inverse, feedforward source, forward inversion) of a model set; ValueError
        with one sentence when it cannot be served."""
        if not model_file and not inverse_model_file:
            raise ValueError("no model file given (parameters model_file, inverse_model_file)")
        try:
            forward, inverse = load_model_set(model_file, inverse_model_file)
            source = choose_feedforward(feedforward, forward, inverse)
            inversion = (ForwardInversionFeedforward(forward, u_limit_v=U_LIMIT_V)
                         if source == "forward-inversion" else None)
        except OSError as exc:
            raise ValueError(str(exc)) from None
        return forward, inverse, source, inversion

    def reload(self) -> tuple[bool, str]:
        """(Re)load the model file(s); all or nothing. Returns (success, message)."""
        try:
            loaded = self._load(self.model_file, self.inverse_model_file, self.feedforward)
        except ValueError as exc:  # ModelFileError and ModelSetError are ValueErrors
            if self.model_file or self.inverse_model_file:
                self.load_error = str(exc)
            return False, str(exc)
        return True, self._install(*loaded)

    def _install(self, forward, inverse, source: str, inversion) -> str:
        """Serve a loaded model set; new steppers go on from the histories kept."""
        self.forward, self.inverse = forward, inverse
        self.ff_source, self._inversion = source, inversion
        self.ff_reach = reach_mm(inverse) if source == "inverse" else None
        self._restart_steppers()
        self.monitor.reset()
        self._e_free.clear()
        self._e_one.clear()
        self.load_error = ""
        self.loaded_at = time.strftime("%Y-%m-%d %H:%M:%S")
        msg = (f"forward {_describe(forward)}, inverse {_describe(inverse)}, feedforward "
               f"{FEEDFORWARD_NAMES[source]}")
        self.get_logger().info(f"loaded {self._files()}: {msg}")
        return msg

    def _files(self) -> str:
        return " + ".join(f for f in (self.model_file, self.inverse_model_file) if f)

    def _restart_steppers(self) -> None:
        """New steppers seeded with the recent samples, so a reload does not restart from rest."""
        self._free = self._one = self._ff = None
        self._one_stamp = None
        self._pred.clear()
        if self.forward is not None:
            self._free = self._new_forward()
            self._one = self._new_forward()
        self._ff = self._new_feedforward()

    def _new_forward(self):
        """A forward stepper going on from the recent (u applied V, y measured mm) pairs."""
        return self.forward.stepper(*self._sample_hist.tail(history_depth(self.forward)))

    def _new_feedforward(self):
        """A feedforward stepper of the chosen source, going on from the recent
        (y desired mm, u V) pairs."""
        if self.ff_source == "inverse":
            return self.inverse.stepper(*self._ff_hist.tail(history_depth(self.inverse)))
        if self.ff_source == "forward-inversion":
            return self._inversion.stepper(
                self._ff_hist.tail(history_depth(self._inversion))[1])
        return None

    def _on_reload(self, request, response):
        ok, msg = self.reload()
        self.reloads += 1
        response.success = ok
        if ok:
            response.message = f"reloaded {self._files()}: {msg}"
        else:
            self.failed_reloads += 1
            kept = ("kept the models in use" if self.forward is not None
                    or self.inverse is not None else "no model served")
            response.message = f"reload failed, {kept}: {msg}"
            self.get_logger().error(response.message)
        return response

    # -- feedforward ----------------------------------------------------------------------------
    def _on_reference(self, msg: PointStamped) -> None:
        if self._ff is None:
            return
        y_mm = msg.point.x * 1e3
        if not math.isfinite(y_mm):
            self.ff_skipped += 1
            return
        if self.history_voltage == "applied" and self._u_applied_new and len(self._ff_hist):
            # The voltage that really reached the actuator replaces the last feedforward.
            self._ff.record_applied(self._u_applied_v)
            self._ff_hist.set_last(self._ff_hist.last()[0], self._u_applied_v)
        self._u_applied_new = False
        if out_of_reach(y_mm, self.ff_reach):
            self.ff_beyond += 1
            lo, hi = self.ff_reach
            self.get_logger().warn(
                f"reference {y_mm:.2f} mm lies beyond the displacements the inverse model was "
                f"identified on ({lo:.2f} to {hi:.2f} mm), where it extrapolates",
                throttle_duration_sec=5.0)
        u = self._ff.step(y_mm)
        if not math.isfinite(u):
            self.ff_skipped += 1
            self.get_logger().warn("inverse model diverged: restarted it from rest",
                                   throttle_duration_sec=1.0)
            self._ff_hist.clear()
            self._ff = self._new_feedforward()
            return
        u_ff = min(self.u_max_v, max(-self.u_max_v, u))
        if u_ff != u:
            self.ff_clamped += 1
        if self.history_voltage != "model":
            self._ff.record_applied(u_ff)
        self._ff_hist.append(y_mm, u_ff if self.history_voltage != "model" else u)
        out = Vector3Stamped()
        out.header = msg.header
        out.vector.x = u_ff
        self.pub_ff.publish(out)
        self.ff_count += 1
        self.ff_last_v = u_ff

    # -- prediction and residual ----------------------------------------------------------------
    def _on_voltage(self, msg: Vector3Stamped) -> None:
        u = float(msg.vector.x)
        if not math.isfinite(u):
            return
        self._u_applied_v, self._u_applied_new = u, True
        if self._free is None:
            return
        y_free = self._free.step(u)
        if not abs(y_free) < DIVERGED_MM:
            self.free_resets += 1
            self.get_logger().warn("free-run prediction diverged: restarted from the measured "
                                   "history", throttle_duration_sec=1.0)
            self._free = self._new_forward()
            y_free = self._free.step(u)
            if not abs(y_free) < DIVERGED_MM:
                return
        y_one = self._one.step(u)
        if not abs(y_one) < DIVERGED_MM:
            self._one = self._new_forward()
            y_one = self._one.step(u)
        stamp = _stamp_ns(msg)
        self._one_stamp = stamp
        out = PointStamped()
        out.header = msg.header
        out.point.x = y_free * 1e-3
        self.pub_pred.publish(out)
        self.pred_count += 1
        y_meas = self._meas.pop(stamp, None)
        if y_meas is not None:
            self._complete(stamp, msg.header.frame_id, u, y_free, y_one, y_meas)
        else:
            self._remember(self._pred, stamp, (u, y_free, y_one))

    def _on_displacement(self, msg: PointStamped) -> None:
        y_mm = msg.point.x * 1e3
        if not math.isfinite(y_mm) or self._free is None:
            return
        stamp = _stamp_ns(msg)
        pred = self._pred.pop(stamp, None)
        if pred is not None:
            self._complete(stamp, msg.header.frame_id, *pred, y_mm)
        else:
            self._remember(self._meas, stamp, y_mm)

    @staticmethod
    def _remember(memory: OrderedDict, key, value) -> None:
        memory[key] = value
        while len(memory) > PAIR_MEMORY:
            memory.popitem(last=False)

    def _complete(self, stamp: int, frame_id: str, u: float, y_free: float, y_one: float,
                  y_meas: float) -> None:
        e_free = y_meas - y_free
        out = PointStamped()
        out.header.stamp.sec, out.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        out.header.frame_id = frame_id
        out.point.x = e_free * 1e-3
        self.pub_res.publish(out)
        self.residual_count += 1
        self._e_free.append(e_free)
        self._sample_hist.append(u, y_meas)
        if stamp == self._one_stamp:
            # One-step-ahead: the next prediction starts from this measurement.
            self._one.correct_output(y_meas)
            e_one = y_meas - y_one
            self._e_one.append(e_one)
        else:
            e_one = math.nan  # its partner came after a newer voltage: no one-step residual
        self.monitor.update(e_one if self.monitor_residual == "one_step" else e_free)

    # -- diagnostics ----------------------------------------------------------------------------
    def publish_diagnostics(self) -> None:
        """Publish one DiagnosticArray: model, feedforward, residual."""
        now = time.monotonic()
        dt = now - self._diag_wall_last
        if dt > 0:
            self.ff_rate_hz = (self.ff_count - self._ff_count_last) / dt
        self._diag_wall_last, self._ff_count_last = now, self.ff_count
        self._ff_beyond_period = self.ff_beyond - self._ff_beyond_last
        self._ff_beyond_last = self.ff_beyond
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [self._diag_model(), self._diag_feedforward(), self._diag_residual()]
        self.pub_diag.publish(arr)

    def _status(self, name: str, level: bytes, message: str, **values) -> DiagnosticStatus:
        return DiagnosticStatus(
            level=level, name=f"model_server: {name}", message=message, hardware_id=HARDWARE_ID,
            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])

    def _diag_model(self) -> DiagnosticStatus:
        info = dict(model_file=self.model_file, inverse_model_file=self.inverse_model_file,
                    forward=_describe(self.forward), inverse=_describe(self.inverse),
                    feedforward=self.feedforward, feedforward_source=self.ff_source,
                    loaded_at=self.loaded_at, reloads=self.reloads,
                    failed_reloads=self.failed_reloads, last_error=self.load_error)
        if self.forward is None and self.inverse is None:
            return self._status("model", DiagnosticStatus.ERROR,
                                f"no model loaded: {self.load_error}", **info)
        kinds = ", ".join(k for k, m in (("forward", self.forward), ("inverse", self.inverse))
                          if m is not None)
        if self.load_error:
            return self._status("model", DiagnosticStatus.WARN,
                                f"last reload failed, serving the previous {kinds} model",
                                **info)
        return self._status("model", DiagnosticStatus.OK, f"loaded ({kinds})", **info)

    def _diag_feedforward(self) -> DiagnosticStatus:
        if self._ff is None:
            return self._status("feedforward", DiagnosticStatus.OK,
                                "not served (no inverse model, and no forward model with "
                                "voltage channels to invert)", source="none",
                                feedforward=self.feedforward)
        frac = self.ff_clamped / self.ff_count if self.ff_count else 0.0
        level = (DiagnosticStatus.WARN if frac > 0.5 or self._ff_beyond_period
                 else DiagnosticStatus.OK)
        name = FEEDFORWARD_NAMES[self.ff_source]
        msg = (f"{name}: {self.ff_rate_hz:.1f} Hz, {100 * frac:.0f} % clamped" if self.ff_count
               else f"{name}: waiting for /ipmc/reference")
        if self._ff_beyond_period:
            msg += (f", {self._ff_beyond_period} references beyond the identified range "
                    "(the inverse extrapolates)")
        reach = ("" if self.ff_reach is None
                 else f"{self.ff_reach[0]:.3f} {self.ff_reach[1]:.3f}")
        return self._status("feedforward", level, msg, source=self.ff_source,
                            feedforward=self.feedforward, rate_hz=f"{self.ff_rate_hz:.2f}",
                            count=self.ff_count, clamped=self.ff_clamped,
                            skipped=self.ff_skipped, last_v=f"{self.ff_last_v:.4f}",
                            u_max_v=self.u_max_v, history_voltage=self.history_voltage,
                            identified_range_mm=reach, beyond_range=self.ff_beyond)

    def _diag_residual(self) -> DiagnosticStatus:
        if self._free is None:
            return self._status("residual", DiagnosticStatus.OK,
                                "not served (no forward model)")

        def rms(e) -> str:
            return f"{math.sqrt(sum(x * x for x in e) / len(e)):.5f}" if e else "nan"

        def num(x: float) -> str:
            return f"{x:.4g}"

        mon = self.monitor
        s = mon.status
        # A stale model is a warning (the loop still runs; refit and reload); one failed check
        # is not yet one.
        level = DiagnosticStatus.WARN if s.level == 2 else DiagnosticStatus.OK
        return self._status(
            "residual", level, s.message,
            stale=s.level == 2, monitor_residual=self.monitor_residual, monitor_test=mon.test,
            failed_checks=s.failed, patience=mon.patience,
            reference_samples=f"{s.reference_samples}/{mon.reference}",
            reference_mean_mm=num(s.reference_mean), reference_spread_mm=num(s.reference_spread),
            mean_shift_mm=num(s.shift), mean_shift_limit_mm=num(s.shift_limit),
            window_spread_mm=num(s.spread), spread_limit_mm=num(s.spread_limit),
            white=s.white, ljung_box_q=num(s.q), ljung_box_limit=num(s.q_limit),
            ljung_box_p=f"{s.p_value:.4g}",
            window_rms_mm=num(s.rms), window_mean_mm=num(s.mean),
            free_run_rms_mm=rms(self._e_free), one_step_rms_mm=rms(self._e_one),
            predictions=self.pred_count, residuals=self.residual_count,
            free_run_restarts=self.free_resets)


def main(args: list[str] | None = None) -> None:
    run_node(ModelServer, args, name="model_server", doc=__doc__,
             usage="model_server [--ros-args -p model_file:=MODEL.json "
                   "-p inverse_model_file:=INVERSE.json -p u_max_v:=3.0 "
                   "-p history_voltage:=applied|clamped|model "
                   "-p feedforward:=auto|inverse|forward-inversion "
                   "-p monitor_residual:=free_run|one_step "
                   "-p monitor_test:=auto|drift|whiteness|both -p use_sim_time:=true]\n"
                   "service: /model_server/reload (std_srvs/srv/Trigger)")


if __name__ == "__main__":
    main()
