"""What model_server serves, as a pure core (no ROS): models, steppers, histories, pairing.

The node (``ipmc_model.nodes.model_server``) maps topics, parameters and timers onto this:

- :func:`load_served_models` loads a model set all or nothing (:class:`ModelSet`), with the
  feedforward source :func:`choose_feedforward` picks.
- :class:`ReferenceQueue` holds the references waiting for their feedforward and decides what
  an overloaded server does: a reference that has waited longer than ``max_delay_s`` while a
  newer one waits is skipped (a feedforward that late is of no use to a controller, and
  answering it would make every later one later still), the newest is always answered, and
  every reference left unanswered is counted, also those that never reached the server (gaps
  in the publisher's sequence numbers).
- :class:`ModelService` steps the feedforward per reference, the forward model per applied
  voltage, pairs predictions and measurements by stamp into residuals for the staleness
  monitor, keeps the histories that re-seed new steppers after a reload or a skip, and renders
  the ``/diagnostics`` statuses as :class:`Status` values.
"""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from dataclasses import dataclass, field

import numpy as np

from ipmc_model.effects import AugmentedInverse, AugmentedModel, load_any_model
from ipmc_model.forward_inversion import ForwardInversionFeedforward
from ipmc_model.hysteresis import GpiInverse
from ipmc_model.narx import (
    InverseNarxModel,
    NarxCommittee,
    NarxModel,
    out_of_reach,
    reach_mm,
)
from ipmc_model.residuals import ResidualMonitor

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


def load_model_set(model_file: str, inverse_model_file: str = "") -> tuple:
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


def describe(model) -> str:
    """What /diagnostics and the log say a served model is (one line)."""
    if model is None:
        return "none"
    if isinstance(model, AugmentedInverse):
        effects = ", ".join(model.effect_names)
        return f"{describe(model.inverse)} with the effects undone around it: {effects}"
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
OK, WARN, ERROR = 0, 1, 2   # diagnostic_msgs/DiagnosticStatus levels


@dataclass(frozen=True)
class ModelSet:
    """A model set as loaded from the node's parameters: the forward and inverse models, the
    feedforward source (``inverse``, ``forward-inversion`` or ``none``) and, for
    ``forward-inversion``, the inversion of the forward model."""

    model_file: str = ""
    inverse_model_file: str = ""
    feedforward: str = "auto"
    forward: object = None
    inverse: object = None
    source: str = "none"
    inversion: ForwardInversionFeedforward | None = None

    @property
    def files(self) -> str:
        return " + ".join(f for f in (self.model_file, self.inverse_model_file) if f)

    @property
    def empty(self) -> bool:
        return self.forward is None and self.inverse is None

    def summary(self) -> str:
        return (f"forward {describe(self.forward)}, inverse {describe(self.inverse)}, "
                f"feedforward {FEEDFORWARD_NAMES[self.source]}")


def load_served_models(model_file: str, inverse_model_file: str = "",
                       feedforward: str = "auto") -> ModelSet:
    """Load the model set of the three parameters, all or nothing.

    Raises
    ------
    ValueError
        (``ModelSetError``, ``ModelFileError``) one sentence naming the file and the problem.
    """
    if not model_file and not inverse_model_file:
        raise ModelSetError("no model file given (parameters model_file, inverse_model_file)")
    try:
        forward, inverse = load_model_set(model_file, inverse_model_file)
        source = choose_feedforward(feedforward, forward, inverse)
        inversion = (ForwardInversionFeedforward(forward, u_limit_v=U_LIMIT_V)
                     if source == "forward-inversion" else None)
    except OSError as exc:
        raise ModelSetError(str(exc)) from None
    return ModelSet(model_file, inverse_model_file, feedforward, forward, inverse, source,
                    inversion)


def build_monitor(p: dict) -> ResidualMonitor:
    """The ResidualMonitor of the ``monitor_*`` parameters (name -> value); ValueError names
    the bad one."""
    residual, test = p["monitor_residual"], p["monitor_test"]
    if residual not in MONITOR_RESIDUALS:
        raise ValueError(f"monitor_residual must be one of {MONITOR_RESIDUALS}, got {residual!r}")
    if test not in MONITOR_TESTS:
        raise ValueError(f"monitor_test must be one of {MONITOR_TESTS}, got {test!r}")
    if test == "auto":
        test = AUTO_TEST[residual]
    growth = float(p["monitor_growth"])
    if growth != 0.0 and not growth > 1.0:
        raise ValueError(f"monitor_growth must be > 1 (or 0 = off), got {growth}")
    try:
        return ResidualMonitor(
            window=int(p["monitor_window"]) or AUTO_WINDOW[test], lags=p["monitor_lags"],
            check_every=p["monitor_check_every"], patience=p["monitor_patience"],
            decimate=p["monitor_decimate"], test=test, reference=p["monitor_reference"],
            bias_factor=p["monitor_bias_factor"], growth=growth or None, unit="mm")
    except ValueError as exc:
        raise ValueError(f"monitor_* parameters: {exc}") from None


@dataclass(frozen=True)
class Reference:
    """A reference sample waiting for its feedforward: stamp (ns), displacement (mm) and when
    it was received (ns, the same clock as ``now_ns`` of :meth:`ReferenceQueue.take`)."""

    stamp_ns: int
    y_mm: float
    received_ns: int
    frame_id: str = ""


class ReferenceQueue:
    """References received and not yet answered, and what an overloaded server leaves out.

    Parameters
    ----------
    max_delay_s : float
        A reference that has waited longer than this (s) while a newer one waits is skipped;
        the newest is always answered. 0: answer every reference however late.
    """

    def __init__(self, max_delay_s: float = 0.2) -> None:
        self.max_delay_s = float(max_delay_s)
        self._pending: deque[Reference] = deque()
        self._last_sequence: int | None = None
        self.lost = 0    # never reached the server: gaps in the publisher's sequence numbers
        self.stale = 0   # skipped: waited longer than max_delay_s while a newer one waited

    def __len__(self) -> int:
        return len(self._pending)

    def offer(self, ref: Reference, sequence: int | None = None,
              one_publisher: bool = True) -> None:
        """Queue ``ref``; ``sequence``, the publisher's sequence number, counts the references
        lost on the way (only with ``one_publisher``: the numbers are per publisher)."""
        if sequence is not None:
            last = self._last_sequence
            if one_publisher and last is not None and sequence > last + 1:
                self.lost += sequence - last - 1
            self._last_sequence = sequence   # lower: another publisher, or one restarted
        self._pending.append(ref)

    def take(self, now_ns: int) -> tuple[list[Reference], list[Reference]]:
        """Empty the queue: (the references to answer, oldest first; those skipped as late)."""
        refs = list(self._pending)
        self._pending.clear()
        if len(refs) < 2 or self.max_delay_s <= 0:
            return refs, []
        limit_ns = self.max_delay_s * 1e9
        stale = [r for r in refs[:-1] if now_ns - r.received_ns > limit_ns]
        due = [r for r in refs[:-1] if now_ns - r.received_ns <= limit_ns] + refs[-1:]
        self.stale += len(stale)
        return due, stale


@dataclass(frozen=True)
class Status:
    """One ``/diagnostics`` status of the server: level (OK, WARN, ERROR), message, values."""

    level: int
    message: str
    values: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Feedforward:
    """One answered reference: the published voltage (V, within ``u_max_v``) and whether the
    limit acted."""

    u_v: float
    clamped: bool


class ModelService:
    """Feedforward, prediction and residual of a served model set, message by message.

    Parameters
    ----------
    monitor : ResidualMonitor
        The staleness monitor (:func:`build_monitor`); reset on every (re)load.
    monitor_residual : {"free_run", "one_step"}
        The residual fed to it.
    u_max_v : float
        Feedforward limit, V (0 < u_max_v <= 3).
    history_voltage : {"applied", "clamped", "model"}
        The voltage history the feedforward stepper sees (``ipmc_model.narx``).
    max_delay_s : float
        :class:`ReferenceQueue`'s lateness limit, s.

    Attributes
    ----------
    notes : list of (str, str)
        (kind, sentence) the node logs and empties: ``beyond`` (a reference beyond the
        displacements the inverse was identified on), ``diverged`` (a stepper restarted).
    """

    def __init__(self, monitor: ResidualMonitor, monitor_residual: str = "free_run",
                 u_max_v: float = U_LIMIT_V, history_voltage: str = "applied",
                 max_delay_s: float = 0.2) -> None:
        self.monitor, self.monitor_residual = monitor, monitor_residual
        self.u_max_v, self.history_voltage = float(u_max_v), history_voltage
        self.queue = ReferenceQueue(max_delay_s)
        self.models = ModelSet()
        self.reach: tuple[float, float] | None = None
        window = monitor.window * monitor.decimate
        self._e_free: deque[float] = deque(maxlen=window)   # residuals (mm) for the RMS
        self._e_one: deque[float] = deque(maxlen=window)
        self._free = self._one = self._ff = None
        self._one_stamp: int | None = None    # stamp of the one-step stepper's last step
        self._sample_hist = PairHistory(HISTORY_MAX)   # (u applied V, y measured mm)
        self._ff_hist = PairHistory(HISTORY_MAX)       # (y desired mm, u V)
        self._pred: OrderedDict[int, tuple] = OrderedDict()   # stamp -> (u, y free, y one)
        self._meas: OrderedDict[int, float] = OrderedDict()   # stamp -> y measured mm
        self._u_applied_v: float | None = None
        self._u_applied_new = False
        self.notes: list[tuple[str, str]] = []
        self.load_error = ""
        self.loaded_at = "never"
        self.reloads = self.failed_reloads = 0
        self.ff_count = self.ff_clamped = self.ff_invalid = self.ff_beyond = 0
        self.pred_count = self.residual_count = self.free_resets = 0
        self.ff_last_v = math.nan
        self.ff_rate_hz = 0.0
        self._period_start: tuple = (None, 0, 0, 0)   # (t_s, count, beyond, unanswered)
        self._period: tuple = (0, 0)                  # beyond, unanswered in the last period

    # -- models ---------------------------------------------------------------------------------
    def install(self, models: ModelSet, loaded_at: str = "") -> str:
        """Serve ``models``; new steppers go on from the histories kept. Returns the summary."""
        self.models = models
        self.reach = reach_mm(models.inverse) if models.source == "inverse" else None
        self.restart_steppers()
        self.monitor.reset()
        self._e_free.clear()
        self._e_one.clear()
        self.load_error = ""
        self.loaded_at = loaded_at or self.loaded_at
        return models.summary()

    def reload(self, loaded_at: str = "") -> tuple[bool, str]:
        """Load the current files anew, all or nothing. Returns (success, message)."""
        m = self.models
        try:
            models = load_served_models(m.model_file, m.inverse_model_file, m.feedforward)
        except ValueError as exc:  # ModelFileError and ModelSetError are ValueErrors
            if m.model_file or m.inverse_model_file:
                self.load_error = str(exc)
            return False, str(exc)
        return True, self.install(models, loaded_at)

    def restart_steppers(self) -> None:
        """New steppers seeded with the recent samples, so a reload does not restart from rest."""
        self._free = self._one = None
        self._one_stamp = None
        self._pred.clear()
        if self.models.forward is not None:
            self._free = self._new_forward()
            self._one = self._new_forward()
        self._ff = self._new_feedforward()

    def _new_forward(self):
        """A forward stepper going on from the recent (u applied V, y measured mm) pairs."""
        forward = self.models.forward
        return forward.stepper(*self._sample_hist.tail(history_depth(forward)))

    def _new_feedforward(self):
        """A feedforward stepper of the chosen source, going on from the recent
        (y desired mm, u V) pairs."""
        m = self.models
        if m.source == "inverse":
            return m.inverse.stepper(*self._ff_hist.tail(history_depth(m.inverse)))
        if m.source == "forward-inversion":
            return m.inversion.stepper(self._ff_hist.tail(history_depth(m.inversion))[1])
        return None

    @property
    def serves_feedforward(self) -> bool:
        return self._ff is not None

    @property
    def serves_prediction(self) -> bool:
        return self._free is not None

    # -- feedforward ----------------------------------------------------------------------------
    def answer(self, y_mm: float) -> Feedforward | None:
        """One feedforward step for the reference ``y_mm`` (mm); None when it is not answered
        (no feedforward served, a non-finite reference, a diverged stepper: restarted)."""
        if self._ff is None:
            return None
        if not math.isfinite(y_mm):
            self.ff_invalid += 1
            return None
        if self.history_voltage == "applied" and self._u_applied_new and len(self._ff_hist):
            # The voltage that really reached the actuator replaces the last feedforward.
            self._ff.record_applied(self._u_applied_v)
            self._ff_hist.set_last(self._ff_hist.last()[0], self._u_applied_v)
        self._u_applied_new = False
        if out_of_reach(y_mm, self.reach):
            self.ff_beyond += 1
            lo, hi = self.reach
            self.notes.append(("beyond", f"reference {y_mm:.2f} mm lies beyond the "
                               f"displacements the inverse model was identified on ({lo:.2f} "
                               f"to {hi:.2f} mm), where it extrapolates"))
        u = self._ff.step(y_mm)
        if not math.isfinite(u):
            self.ff_invalid += 1
            self.notes.append(("diverged", "inverse model diverged: restarted it from rest"))
            self._ff_hist.clear()
            self._ff = self._new_feedforward()
            return None
        u_ff = min(self.u_max_v, max(-self.u_max_v, u))
        self.ff_clamped += u_ff != u
        if self.history_voltage != "model":
            self._ff.record_applied(u_ff)
        self._ff_hist.append(y_mm, u_ff if self.history_voltage != "model" else u)
        self.ff_count += 1
        self.ff_last_v = u_ff
        return Feedforward(u_ff, u_ff != u)

    def skip(self, refs: list[Reference]) -> None:
        """References left unanswered (late): they enter the history with the last voltage
        held, and the stepper goes on from there, so the next answer keeps its time base."""
        if not refs or self._ff is None:
            return
        u_held = self.ff_last_v if math.isfinite(self.ff_last_v) else 0.0
        for ref in refs:
            if math.isfinite(ref.y_mm):
                self._ff_hist.append(ref.y_mm, u_held)
        self._ff = self._new_feedforward()

    @property
    def unanswered(self) -> int:
        """References left unanswered since the start: late, lost on the way, or invalid."""
        return self.queue.stale + self.queue.lost + self.ff_invalid

    # -- prediction and residual ----------------------------------------------------------------
    def predict(self, stamp_ns: int, u_v: float) -> tuple[float | None, float | None]:
        """One free-run step on the applied voltage ``u_v`` (V) of the sample ``stamp_ns``:
        (prediction mm to publish or None, residual mm when its measurement was here)."""
        if not math.isfinite(u_v):
            return None, None
        self._u_applied_v, self._u_applied_new = u_v, True
        if self._free is None:
            return None, None
        y_free = self._free.step(u_v)
        if not abs(y_free) < DIVERGED_MM:
            self.free_resets += 1
            self.notes.append(("diverged", "free-run prediction diverged: restarted from the "
                               "measured history"))
            self._free = self._new_forward()
            y_free = self._free.step(u_v)
            if not abs(y_free) < DIVERGED_MM:
                return None, None
        y_one = self._one.step(u_v)
        if not abs(y_one) < DIVERGED_MM:
            self._one = self._new_forward()
            y_one = self._one.step(u_v)
        self._one_stamp = stamp_ns
        self.pred_count += 1
        y_meas = self._meas.pop(stamp_ns, None)
        if y_meas is None:
            _remember(self._pred, stamp_ns, (u_v, y_free, y_one))
            return y_free, None
        return y_free, self._complete(stamp_ns, u_v, y_free, y_one, y_meas)

    def measure(self, stamp_ns: int, y_mm: float) -> float | None:
        """The measured displacement (mm) of the sample ``stamp_ns``: its residual (mm) when
        its prediction was here."""
        if not math.isfinite(y_mm) or self._free is None:
            return None
        pred = self._pred.pop(stamp_ns, None)
        if pred is None:
            _remember(self._meas, stamp_ns, y_mm)
            return None
        return self._complete(stamp_ns, *pred, y_mm)

    def _complete(self, stamp_ns: int, u_v: float, y_free: float, y_one: float,
                  y_meas: float) -> float:
        e_free = y_meas - y_free
        self.residual_count += 1
        self._e_free.append(e_free)
        self._sample_hist.append(u_v, y_meas)
        if stamp_ns == self._one_stamp:
            # One-step-ahead: the next prediction starts from this measurement.
            self._one.correct_output(y_meas)
            e_one = y_meas - y_one
            self._e_one.append(e_one)
        else:
            e_one = math.nan  # its partner came after a newer voltage: no one-step residual
        was_stale = self.monitor.status.level == 2
        self.monitor.update(e_one if self.monitor_residual == "one_step" else e_free)
        if self.monitor.status.level == 2 and not was_stale:
            self.notes.append(("stale", stale_advice(
                self.monitor.status.message,
                self.models.model_file or self.models.inverse_model_file)))
        return e_free


def stale_advice(message: str, model_file: str) -> str:
    """The staleness monitor's verdict and the commands that find what changed: diagnose the
    recorded run with the served model given, then play the experiment it proposes."""
    model = model_file or "MODEL"
    return (f"{message}. Find what changed: ipmc diagnose --data BAG --model {model} "
            f"--report DIR on this run's record (ipmc bringup --record BAG), then ipmc bringup "
            f"--experiment DIR/next_experiment.json --record BAG2 if it proposes one, or ipmc "
            f"investigate --rig PORT --report DIR to run the whole loop")


def _remember(memory: OrderedDict, key, value) -> None:
    """Keep ``value`` under ``key`` while waiting for its partner; the oldest go first."""
    memory[key] = value
    while len(memory) > PAIR_MEMORY:
        memory.popitem(last=False)


# -- /diagnostics ---------------------------------------------------------------------------------
def model_status(s: ModelService) -> Status:
    """``model_server: model``: what is loaded, from which files, the last load error."""
    m = s.models
    info = dict(model_file=m.model_file, inverse_model_file=m.inverse_model_file,
                forward=describe(m.forward), inverse=describe(m.inverse),
                feedforward=m.feedforward, feedforward_source=m.source,
                loaded_at=s.loaded_at, reloads=s.reloads, failed_reloads=s.failed_reloads,
                last_error=s.load_error)
    if m.empty:
        return Status(ERROR, f"no model loaded: {s.load_error}", info)
    kinds = ", ".join(k for k, x in (("forward", m.forward), ("inverse", m.inverse))
                      if x is not None)
    if s.load_error:
        return Status(WARN, f"last reload failed, serving the previous {kinds} model", info)
    return Status(OK, f"loaded ({kinds})", info)


def feedforward_status(s: ModelService, now_s: float) -> Status:
    """``model_server: feedforward`` over the period since the previous call (``now_s``: a
    monotonic clock, s): rate, clamping, references beyond the identified range, and every
    reference left unanswered (late under overload, lost on the way, invalid)."""
    t_s, count0, beyond0, unanswered0 = s._period_start
    if t_s is not None and now_s > t_s:
        s.ff_rate_hz = (s.ff_count - count0) / (now_s - t_s)
    beyond, unanswered = s.ff_beyond - beyond0, s.unanswered - unanswered0
    s._period_start = (now_s, s.ff_count, s.ff_beyond, s.unanswered)
    m = s.models
    if not s.serves_feedforward:
        return Status(OK, "not served (no inverse model, and no forward model with voltage "
                      "channels to invert)", dict(source="none", feedforward=m.feedforward))
    frac = s.ff_clamped / s.ff_count if s.ff_count else 0.0
    name = FEEDFORWARD_NAMES[m.source]
    msg = (f"{name}: {s.ff_rate_hz:.1f} Hz, {100 * frac:.0f} % clamped" if s.ff_count
           else f"{name}: waiting for /ipmc/reference")
    if beyond:
        msg += f", {beyond} references beyond the identified range (the inverse extrapolates)"
    if unanswered:
        msg += (f", {unanswered} references unanswered (overloaded: the newest answered, "
                "late ones skipped)")
    level = WARN if frac > 0.5 or beyond or unanswered else OK
    reach = "" if s.reach is None else f"{s.reach[0]:.3f} {s.reach[1]:.3f}"
    return Status(level, msg, dict(
        source=m.source, feedforward=m.feedforward, rate_hz=f"{s.ff_rate_hz:.2f}",
        count=s.ff_count, clamped=s.ff_clamped, skipped=s.unanswered,
        skipped_late=s.queue.stale, lost=s.queue.lost, skipped_invalid=s.ff_invalid,
        max_delay_s=s.queue.max_delay_s, last_v=f"{s.ff_last_v:.4f}", u_max_v=s.u_max_v,
        history_voltage=s.history_voltage, identified_range_mm=reach,
        beyond_range=s.ff_beyond))


def residual_status(s: ModelService) -> Status:
    """``model_server: residual``: the staleness monitor and the residuals' RMS."""
    if not s.serves_prediction:
        return Status(OK, "not served (no forward model)")

    def rms(e) -> str:
        return f"{math.sqrt(sum(x * x for x in e) / len(e)):.5f}" if e else "nan"

    def num(x: float) -> str:
        return f"{x:.4g}"

    mon = s.monitor
    st = mon.status
    # A stale model is a warning (the loop still runs; refit and reload); one failed check is
    # not yet one.
    return Status(WARN if st.level == 2 else OK, st.message, dict(
        stale=st.level == 2, monitor_residual=s.monitor_residual, monitor_test=mon.test,
        failed_checks=st.failed, patience=mon.patience,
        reference_samples=f"{st.reference_samples}/{mon.reference}",
        reference_mean_mm=num(st.reference_mean), reference_spread_mm=num(st.reference_spread),
        mean_shift_mm=num(st.shift), mean_shift_limit_mm=num(st.shift_limit),
        window_spread_mm=num(st.spread), spread_limit_mm=num(st.spread_limit),
        white=st.white, ljung_box_q=num(st.q), ljung_box_limit=num(st.q_limit),
        ljung_box_p=f"{st.p_value:.4g}", window_rms_mm=num(st.rms), window_mean_mm=num(st.mean),
        free_run_rms_mm=rms(s._e_free), one_step_rms_mm=rms(s._e_one),
        predictions=s.pred_count, residuals=s.residual_count,
        free_run_restarts=s.free_resets))
