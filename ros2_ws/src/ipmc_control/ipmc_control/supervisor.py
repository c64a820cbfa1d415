"""The controller's safety rules as a pure core (no ROS): what the loop commands, and when 0 V.

The ``controller`` node maps its topics, parameters and timers onto :class:`Supervisor`; each
input method returns the commands to publish. The rules:

- No reference yet, or a step aiming before the first reference sample: 0 V, the controller
  state reset (the loop starts on the reference's first sample).
- No displacement younger than ``measurement_timeout_s`` (node clock) when feedback is needed
  (any mode but ``inverse`` with a fresh feedforward): 0 V, state reset.
- Hybrid or inverse mode, before the first feedforward: PID alone; the first feedforward
  starts the loop afresh (PID state cleared), not bumplessly: the integral the PID wound up
  alone would otherwise be kept against the feedforward and unwind for seconds.
- A feedforward older than ``feedforward_timeout_s``: PID alone (bumpless) until one comes
  back; a feedforward answering the very reference sample a step aims at is fresh whatever its
  receive time says (under ``use_sim_time`` it may come before the ``/clock`` that dates it).
- A clock jump (``dt`` not in (0, 10 periods]): the last command held, the timing restarted.
- Every command within ``u_clamp_min``..``u_clamp_max`` (``ipmc_control.pid``, checked by
  ``check_actuator_limits``: 0 V allowed, within the H-bridge's 3 V).
- ``trigger="measurement"``: a step aims at the reference stamped one period after its sample
  and waits for that reference and its feedforward at most ``pair_wait_s`` of wall time; steps
  run without them are counted (``unpaired_steps``).
"""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field

from .hybrid import HybridController

# Recent reference samples kept to pair a feedforward with the reference it answers.
REFERENCE_MEMORY = 64
OK, WARN, ERROR = 0, 1, 2   # diagnostic_msgs/DiagnosticStatus levels


@dataclass(frozen=True)
class Command:
    """A command to publish: voltage (V) and the stamp (ns) of the sample it answers."""

    u_v: float
    answer_ns: int


@dataclass(frozen=True)
class Status:
    """One ``/diagnostics`` status: level (OK, WARN, ERROR), message, values."""

    level: int
    message: str
    values: dict = field(default_factory=dict)


@dataclass
class _Pending:
    """A ``trigger="measurement"`` step waiting for its reference or feedforward."""

    t_s: float
    now_s: float
    target_ns: int
    wall_s: float


class Supervisor:
    """The loop's inputs, timeouts and fallbacks around a :class:`HybridController`.

    Parameters
    ----------
    hybrid : HybridController
        The control law and its limits.
    rate_hz : float
        Sample rate, Hz (> 0): the nominal ``dt`` and the look-ahead of one period.
    trigger : {"timer", "measurement"}
        What steps the loop (:meth:`on_tick` or :meth:`on_measurement`).
    feedforward_timeout_s, measurement_timeout_s : float
        Input ages (node clock, s) beyond which the feedforward is stale / the loop idles.
    pair_wait_s : float
        ``trigger="measurement"``: longest wall-time wait for a step's reference and
        feedforward, s.
    use_reference_rate : bool
        Derivative on the error with the reference's rate (else on the measurement).
    reference_publishers : callable, optional
        Number of publishers of the reference (a step before the first reference sample waits
        for it only when someone publishes one).

    Attributes
    ----------
    notes : list of (str, str)
        (kind, sentence) for the node's log: ``idle``, ``stale``, ``back``.
    """

    def __init__(self, hybrid: HybridController, rate_hz: float, *, trigger: str = "timer",
                 feedforward_timeout_s: float = 0.2, measurement_timeout_s: float = 0.5,
                 pair_wait_s: float = 0.05, use_reference_rate: bool = True,
                 reference_publishers: Callable[[], int] = lambda: 0) -> None:
        self.hybrid = hybrid
        self.rate_hz = float(rate_hz)
        self.period_ns = int(round(1e9 / self.rate_hz))
        self.trigger = trigger
        self.ff_timeout_s = feedforward_timeout_s
        self.y_timeout_s = measurement_timeout_s
        self.pair_wait_s = pair_wait_s
        self.use_reference_rate = use_reference_rate
        self._reference_publishers = reference_publishers
        self._ref: tuple[float, float] | None = None   # latest (mm, rate mm/s)
        self._first_ref_ns: int | None = None   # a step aiming before it has no reference
        self._ff_started = False   # the loop has run with a feedforward
        self._recent_refs: OrderedDict[int, tuple[float, float]] = OrderedDict()
        self._ff_ref: tuple[float, float] | None = None  # the one the last feedforward answers
        self._recent_ffs: OrderedDict[int, float] = OrderedDict()
        self._y_mm: float | None = None
        self.y_rx_s = -math.inf
        self._ff_v: float | None = None
        self.ff_rx_s = -math.inf
        self._last_t_s: float | None = None
        self.fallback = False
        self.idle_reason = "starting"
        self._pending: _Pending | None = None
        self._stepped = False   # a step has run (the first one waits for the reference)
        self.ticks = self.skipped_steps = self.unpaired_steps = 0
        self._saturated: deque[bool] = deque(maxlen=200)
        self.notes: list[tuple[str, str]] = []

    # -- inputs ---------------------------------------------------------------------------------
    def on_reference(self, stamp_ns: int, y_mm: float, rate_mm_s: float) -> list[Command]:
        """A reference sample (mm, its rate mm/s; a non-finite rate counts as 0)."""
        if not math.isfinite(y_mm):
            return []
        self._ref = (y_mm, rate_mm_s if math.isfinite(rate_mm_s) else 0.0)
        if self._first_ref_ns is None:
            self._first_ref_ns = stamp_ns
        _remember(self._recent_refs, stamp_ns, self._ref)
        return self._maybe_run_pending()

    def on_feedforward(self, stamp_ns: int, u_v: float, now_s: float) -> list[Command]:
        """A feedforward (V) answering the reference stamped ``stamp_ns``, received at
        ``now_s`` (node clock)."""
        if not math.isfinite(u_v):
            return []
        self._ff_v, self.ff_rx_s = float(u_v), now_s
        self._ff_ref = self._recent_refs.get(stamp_ns)
        _remember(self._recent_ffs, stamp_ns, self._ff_v)
        return self._maybe_run_pending()

    def on_measurement(self, stamp_ns: int, y_mm: float, now_s: float, wall_s: float
                       ) -> list[Command]:
        """A displacement sample (mm) received at ``now_s`` (node clock), ``wall_s`` (wall
        clock); with ``trigger="measurement"`` it steps the loop (now or once its inputs are
        here)."""
        if not math.isfinite(y_mm):
            return []
        self._y_mm, self.y_rx_s = y_mm, now_s
        if self.trigger != "measurement":
            return []
        out = []
        if self._pending is not None:  # a step still waiting for its u_ff goes first
            self.unpaired_steps += 1
            out += self._run_pending()
        target_ns = stamp_ns + self.period_ns
        if self._missing_inputs(target_ns):
            # The reference sample this step aims at, or the feedforward answering it, is on
            # its way: wait for it, at most pair_wait_s of wall time, so the step pairs them as
            # the in-process loop does.
            self._pending = _Pending(stamp_ns * 1e-9, now_s, target_ns, wall_s)
            return out
        return out + [self.step(stamp_ns * 1e-9, now_s, target_ns)]

    def on_pair_wait(self, wall_s: float) -> list[Command]:
        """The wall clock: a step that has waited ``pair_wait_s`` runs without its inputs."""
        if self._pending is not None and wall_s - self._pending.wall_s > self.pair_wait_s:
            self.unpaired_steps += 1
            return self._run_pending()
        return []

    def on_tick(self, now_s: float) -> Command:
        """``trigger="timer"``: one step at the node clock's ``now_s``."""
        return self.step(now_s, now_s)

    def _missing_inputs(self, target_ns: int) -> bool:
        if self._first_ref_ns is None:
            # Wait for the first sample if someone publishes, and on the very first step even
            # before its publisher is seen: discovery can lag under load, and a controller that
            # idled there let a lock-step plant run on before the reference began.
            return not self._stepped or self._reference_publishers() > 0
        if target_ns < self._first_ref_ns:
            return False   # before the reference starts: the step idles, nothing to wait for
        if target_ns not in self._recent_refs:
            return True
        # Wait for the feedforward even before its publisher is seen (discovery can lag under
        # load); without model_server the first step waits pair_wait_s and falls back.
        return (self.hybrid.mode != "pid" and not self.fallback
                and target_ns not in self._recent_ffs)

    def _maybe_run_pending(self) -> list[Command]:
        if self._pending is not None and not self._missing_inputs(self._pending.target_ns):
            return self._run_pending()
        return []

    def _run_pending(self) -> list[Command]:
        p, self._pending = self._pending, None
        return [self.step(p.t_s, p.now_s, p.target_ns)] if p is not None else []

    # -- the loop -------------------------------------------------------------------------------
    def step(self, t_s: float, now_s: float, target_ns: int | None = None) -> Command:
        """One control step at sample time ``t_s`` (s); ``now_s`` is the node clock (s);
        ``target_ns``: stamp of the reference sample this command aims at, if known."""
        self._stepped = True
        answer_ns = (target_ns - self.period_ns if target_ns is not None
                     else int(round(t_s * 1e9)))
        dt = (1.0 / self.rate_hz) if self._last_t_s is None else t_s - self._last_t_s
        self._last_t_s = t_s
        if not (0.0 < dt <= 10.0 / self.rate_hz):
            # Clock jumped (sim time reset, pause): hold the command, restart timing.
            self.skipped_steps += 1
            return Command(self.hybrid.command, answer_ns)
        ff_fresh = self._ff_v is not None and now_s - self.ff_rx_s <= self.ff_timeout_s
        if target_ns is not None and target_ns in self._recent_ffs:
            ff_fresh = True   # the feedforward answering this very sample is here
        y_fresh = self._y_mm is not None and now_s - self.y_rx_s <= self.y_timeout_s
        needs_y = self.hybrid.mode != "inverse" or not ff_fresh
        before_start = (target_ns is not None and self._first_ref_ns is not None
                        and target_ns < self._first_ref_ns)
        if self._ref is None or before_start:
            return self._go_idle("no reference yet", answer_ns)
        if needs_y and not y_fresh:
            return self._go_idle("no fresh displacement", answer_ns)
        if not self._ff_started and (ff_fresh or self.hybrid.mode == "pid"):
            # the first feedforward of a loop started in hybrid or inverse mode: a fresh start,
            # not a bumpless one (a loop started in pid mode switches bumplessly later)
            self._ff_started = True
            if self.hybrid.mode != "pid":
                self.hybrid.reset()
        self.idle_reason = ""
        ref_mm, rate, ff_v = self._inputs(target_ns, answer_ns, ff_fresh)
        y_mm = self._y_mm if self._y_mm is not None else ref_mm
        u = self.hybrid.compute_command(ref_mm, y_mm, dt, ff_v,
                                        rate if self.use_reference_rate else None)
        self._saturated.append(self.hybrid.saturated)
        self.ticks += 1
        self._note_fallback(self.hybrid.mode != "pid" and not ff_fresh, now_s, t_s, target_ns)
        return Command(u, answer_ns)

    def _inputs(self, target_ns: int | None, answer_ns: int, ff_fresh: bool
                ) -> tuple[float, float, float | None]:
        """(reference mm, its rate mm/s, feedforward V or None) of a step."""
        ref_mm, rate = self._ref
        ff_v = self._ff_v if ff_fresh else None
        if ff_fresh and self.hybrid.mode != "pid" and self._ff_ref is not None:
            ref_mm, rate = self._ff_ref   # the reference the latest feedforward answers
        if target_ns is not None and target_ns in self._recent_refs:
            ref_mm, rate = self._recent_refs[target_ns]
            if ff_fresh and target_ns in self._recent_ffs:
                ff_v = self._recent_ffs[target_ns]
            # The PID compares the measurement with the reference of its own instant; only the
            # feedforward looks ahead (ipmc_control.experiment: e_{k-1} = r_{k-1} - y_{k-1}).
            ref_mm, rate = self._recent_refs.get(answer_ns, (ref_mm, rate))
        return ref_mm, rate, ff_v

    def _note_fallback(self, fallback: bool, now_s: float, t_s: float,
                       target_ns: int | None) -> None:
        if fallback == self.fallback:
            return
        self.fallback = fallback
        if fallback:
            last = ("none received yet" if self._ff_v is None
                    else f"last received {now_s - self.ff_rx_s:.3f} s before")
            at = f" at sample {t_s:.3f} s" if target_ns is not None else ""
            if self._ff_v is None:   # the start: model_server has not answered yet
                self.notes.append(("waiting", f"no feedforward yet{at}: PID alone until it "
                                              "comes"))
            else:
                self.notes.append(("stale", f"feedforward stale (> {self.ff_timeout_s} s){at}: "
                                            f"{last}, {self.unpaired_steps} unpaired step(s); "
                                            "PID alone until it returns"))
        else:
            self.notes.append(("back", f"feedforward back: mode {self.hybrid.mode}"))

    def _go_idle(self, reason: str, answer_ns: int) -> Command:
        if reason != self.idle_reason:
            # before the input ever came it is the start, not a fault
            never = (self._ref if reason == "no reference yet" else self._y_mm) is None
            self.notes.append(("waiting" if never else "idle", f"{reason}: command 0 V"))
            self.idle_reason = reason
            self.hybrid.reset()
        return Command(0.0, answer_ns)

    @property
    def saturated_fraction(self) -> float:
        """Fraction of the last 200 commands at a limit."""
        return sum(self._saturated) / len(self._saturated) if self._saturated else 0.0

    @property
    def paired_with_reference(self) -> bool:
        """The last feedforward's reference sample is known."""
        return self._ff_ref is not None


def _remember(memory: OrderedDict, key: int, value) -> None:
    memory[key] = value
    if len(memory) > REFERENCE_MEMORY:
        memory.popitem(last=False)


# -- /diagnostics ---------------------------------------------------------------------------------
def _age(now_s: float, rx_s: float) -> str:
    age = now_s - rx_s
    return f"{age:.3f}" if math.isfinite(age) else "never"


def feedforward_status(s: Supervisor, now_s: float) -> Status:
    """``controller: feedforward``: fresh, stale (PID alone), or not used."""
    mode, age = s.hybrid.mode, _age(now_s, s.ff_rx_s)
    if mode == "pid":
        return Status(OK, "not used in mode pid", dict(mode=mode, age_s=age))
    if s.fallback:
        return Status(WARN, f"stale: PID alone instead of {mode}", dict(
            mode=mode, active_mode="pid", age_s=age, timeout_s=s.ff_timeout_s))
    return Status(OK, f"fresh, mode {mode}", dict(
        mode=mode, active_mode=s.hybrid.active_mode, age_s=age,
        feedforward_v=f"{s.hybrid.feedforward_v:.4f}",
        paired_with_reference=s.paired_with_reference))


def measurement_status(s: Supervisor, now_s: float) -> Status:
    """``controller: measurement``: ERROR while the loop idles at 0 V."""
    if s.idle_reason:
        return Status(ERROR, f"{s.idle_reason}: command 0 V")
    return Status(OK, "fresh", dict(age_s=_age(now_s, s.y_rx_s)))


def saturation_status(s: Supervisor) -> Status:
    """``controller: saturation``: WARN when most recent commands were at a limit."""
    frac, pid = s.saturated_fraction, s.hybrid.pid
    return Status(WARN if frac > 0.5 else OK,
                  f"{100 * frac:.0f} % of recent commands at the limit", dict(
                      fraction=f"{frac:.3f}", u_clamp_max_v=pid.u_clamp_max,
                      u_clamp_min_v=pid.u_clamp_min, command_v=f"{pid.command:.4f}",
                      i_term_v=f"{pid.i_term:.4f}"))
