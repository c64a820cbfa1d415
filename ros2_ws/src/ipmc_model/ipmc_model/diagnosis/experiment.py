"""The next experiment: an excitation designed to decide what a record could not.

When the record cannot test a candidate (creep or drift without input holds, a delay without
steps, a dead zone without slow crossings of 0 V), or an accepted effect's parameters are
left open by it (a creep whose time constant's interval runs to the longest the record can
show), the candidate's class proposes a probe: the short input that shows its effect. The
experiment plays the probes after an identification input that covers the record's range,
and then plays them again as the held-out part, so that the diagnosis of the new record
judges each effect on exactly the excitation that shows it, and the fit part has seen that
excitation too (the judged rows stay within its range).

Layout: ``[wipe] [end probes] [base] [wipe] [probes] [wipe] | [probes] [wipe] [end
probes]``: the held-out part is the probes' last copies, marked ``held_out`` in the parts, and
a record that comes with the parts is split where they start (``fit_share`` is that point's
share of the whole). The base, the identification input, covers the record's range; the
probes of the fit part excite the core as well, at the levels they are judged at. The wipe,
a slow sine whose amplitude falls to 0 V, erases the memory of the path (each reversal
smaller than the last) before each copy of the probes: both copies start from the same
state, so a steady actuator bends alike in both, and so does the core model. After different
inputs, or after a rest (which keeps the core's plays and path memory where the input left
them), the copies differ by tenths of a millimetre: a history the core misfits differently in
each, which a drift or a slow creep could take up. An end probe (a drift's) opens and closes
the experiment: what the same input bends differently at the two ends is what changed over
the record.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ipmc_driver.signals import mixed

from ..hysteresis import DEFAULT_PATH_MEMORY_V
from .record import DiagnosisRecord
from .results import Diagnosis, Outcome

EXPERIMENT_FORMAT = "ipmc-ros-experiment"
EXPERIMENT_FORMAT_VERSION = 2
#: The copy of the experiment a bag recorded by ``ipmc bringup --experiment`` keeps.
BAG_EXPERIMENT = "experiment.json"
#: The H-bridge's limit (V): no proposed voltage goes beyond it.
ACTUATOR_LIMIT_V = 3.0
#: Probe levels as a share of the record's largest |u|: inside the range the model was
#: identified on, with room for the identification input around them.
LEVEL_SHARE = 0.8
#: The identification input's length (s): a minute of the mixed input (fast and slow random
#: sines and held levels over the record's range).
BASE_S = 60.0
#: The memory wipe's period (s): far slower than the charging (IPMC corners 0.5-1.5 Hz), so
#: the charge, where the memory is, follows the sine.
WIPE_PERIOD_S = 5.0
#: The wipe's travel (V): 1.8 times the longest path memory of the core model (32 V); 12
#: periods from 2.4 V travel it. The core's two copies of the probes then differ by about the
#: sensor's noise (the module's test: under 0.01 mm RMS on the simulated IPMC), which cannot
#: show as an effect. Lower levels take more periods.
WIPE_TRAVEL_V = 1.8 * max(DEFAULT_PATH_MEMORY_V)


@dataclass(frozen=True)
class Probe:
    """A candidate's deciding input: voltages at the record's rate and why they decide."""

    effect: str
    u_v: np.ndarray
    reason: str
    #: Played at the experiment's start as well as in its held-out part, which it closes.
    ends: bool = False
    #: Effects whose own probe this one makes unnecessary when the record lacked the
    #: excitation they need: played in both copies, it gives it (a creep's holds are the same
    #: levels at two times, what tells a drift from the memory of the path).
    also: tuple[str, ...] = ()


@dataclass(frozen=True)
class ExperimentPart:
    name: str
    effect: str
    start_s: float
    duration_s: float
    reason: str
    #: Part of the held-out part (a probe's last copy); the record is split where the first
    #: such part starts.
    held_out: bool = False
    #: Effects judged on this probe too (:attr:`Probe.also`): their own probe was left out.
    also: tuple[str, ...] = ()


@dataclass(frozen=True)
class Experiment:
    """The proposed excitation: voltages ``u_v`` at ``rate_hz``, and its parts."""

    rate_hz: float
    fit_share: float
    u_v: np.ndarray
    parts: tuple[ExperimentPart, ...]

    @property
    def duration_s(self) -> float:
        return self.u_v.size / self.rate_hz

    @property
    def decides(self) -> list[str]:
        return sorted({e for p in self.parts for e in (p.effect, *p.also) if e})

    def as_dict(self) -> dict:
        return {"format": EXPERIMENT_FORMAT, "format_version": EXPERIMENT_FORMAT_VERSION,
                "rate_hz": self.rate_hz, "fit_share": self.fit_share,
                "u_max_v": ACTUATOR_LIMIT_V, "duration_s": self.duration_s,
                "decides": self.decides,
                "parts": [{**vars(p), "also": list(p.also)} for p in self.parts],
                "u_v": [round(float(v), 4) for v in self.u_v]}


def probe_level_v(rec: DiagnosisRecord) -> float:
    """The probes' largest level (V): a share of the record's range, within the H-bridge."""
    u_abs = max(abs(rec.excitation.u_min_v), abs(rec.excitation.u_max_v))
    return LEVEL_SHARE * min(u_abs, ACTUATOR_LIMIT_V)


def design_experiment(d: Diagnosis, rec: DiagnosisRecord) -> Experiment | None:
    """The experiment that decides the diagnosis's not-testable candidates and pins down the
    accepted ones the record left open; None if none of them has a probe
    (the ones that need a given model instead of a record). A probe another one makes
    unnecessary (:func:`covering`) is left out."""
    from .candidates import CANDIDATES

    probes, lacking = [], set()
    for res in d.candidates:
        cand = CANDIDATES.get(res.name)
        why = (cand.poorly_determined(res, rec) if cand is not None and res.accepted else None)
        if cand is None or not (res.outcome is Outcome.NOT_TESTABLE or why):
            continue
        probe = cand.probe(rec, d.model_before, res)
        if probe is None:
            continue
        probes.append(probe if why is None else replace(probe, reason=f"{why}; "
                                                                      f"{probe.reason}"))
        if cand.not_testable(rec, d.model_before, d.given_model) is not None:
            lacking.add(res.name)
    return assemble(covering(probes, lacking), rec, seed=0) if probes else None


def covering(probes: list[Probe], lacking: set[str]) -> list[Probe]:
    """``probes`` without those another one makes unnecessary: an effect the record lacked
    the excitation for (``lacking``; one undecided for too few rows or left open needs its
    own probe's lever) is covered by a probe naming it in :attr:`Probe.also` that is itself
    not covered; the covering probe says so and is judged for it too."""
    named = {e for p in probes for e in p.also if e != p.effect}
    own = {p.effect for p in probes}
    kept = []
    for p in probes:
        if p.effect in lacking and any(p.effect in q.also and q.effect not in named
                                       for q in probes if q is not p):
            continue
        also = () if p.effect in named else tuple(
            e for e in p.also if e in own and e in lacking and e != p.effect)
        kept.append(replace(p, also=also, reason=p.reason + (
            f"; played in both copies, it also decides {', '.join(also)}" if also else "")))
    return kept


def assemble(probes: list[Probe], rec: DiagnosisRecord, seed: int = 0) -> Experiment:
    """Probes and the identification input in the layout of the module's docstring."""
    rate, level = 1.0 / rec.dt_s, probe_level_v(rec)
    amp = min(max(abs(rec.excitation.u_min_v), abs(rec.excitation.u_max_v)), ACTUATOR_LIMIT_V)
    _, base = mixed(BASE_S, rate, amp, seed=seed)
    cycles = math.ceil(WIPE_TRAVEL_V / (2.0 * level))   # 2 x the amplitude a period on average
    clear = ("memory wipe", "", wipe(level, WIPE_PERIOD_S, cycles, rate),
             f"a sine decaying from +-{level:.2f} V to 0 V over {cycles} periods of "
             f"{WIPE_PERIOD_S:g} s: it erases the memory of the path, so each copy of the "
             f"probes after it starts from the same state", False)
    inner, ends = [p for p in probes if not p.ends], [p for p in probes if p.ends]

    def copies(group: list[Probe], held: bool, where: str) -> list[tuple]:
        return [(f"{p.effect} probe{where}", p.effect, p.u_v, p.reason, held, p.also)
                for p in group]

    # at the start too: an actuator at rest keeps the memory of how it got there
    pieces = [clear, *copies(ends, False, ", at the start")] if ends else []
    pieces.append(("identification input", "", base, "covers the record's range in "
                   "amplitude and frequency for the core model", False))
    if inner:
        pieces += [clear, *copies(inner, False, "")]
    pieces += [clear, *copies(inner, True, ", repeated as the held-out part")]
    if inner and ends:
        pieces.append(clear)
    pieces += copies(ends, True, ", repeated as the held-out part")
    parts, start = [], 0
    for name, effect, u, reason, held, *also in pieces:
        parts.append(ExperimentPart(name, effect, start / rate, u.size / rate, reason, held,
                                    *also))
        start += u.size
    u_all = np.clip(np.concatenate([piece[2] for piece in pieces]), -ACTUATOR_LIMIT_V,
                    ACTUATOR_LIMIT_V)
    share = min(p.start_s for p in parts if p.held_out) * rate / u_all.size
    return Experiment(rate, share, u_all, tuple(parts))


def read_experiment(path) -> tuple[tuple[ExperimentPart, ...], np.ndarray, float]:
    """The parts, voltages and rate (Hz) of a ``next_experiment.json``; ``ValueError`` in one
    sentence if the file is not one."""
    import json
    from pathlib import Path

    try:
        doc = json.loads(Path(path).read_text())
    except OSError as exc:
        raise ValueError(f"cannot read the experiment {path}: {exc.strerror}") from None
    except ValueError as exc:
        raise ValueError(f"{path} cannot be read as JSON: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != EXPERIMENT_FORMAT:
        raise ValueError(f"{path} is not an experiment of ipmc diagnose (format "
                         f"{EXPERIMENT_FORMAT!r})")
    version = doc.get("format_version", 1)
    if not isinstance(version, int) or not 1 <= version <= EXPERIMENT_FORMAT_VERSION:
        raise ValueError(f"{path} is an experiment of format version {version!r}; this "
                         f"ipmc-ros reads versions 1 to {EXPERIMENT_FORMAT_VERSION}")
    try:
        # format 1 had no held-out flag: its records split by the diagnosis's share
        parts = tuple(ExperimentPart(str(p["name"]), str(p["effect"]), float(p["start_s"]),
                                     float(p["duration_s"]), str(p["reason"]),
                                     _flag(p, "held_out", required=version >= 2),
                                     tuple(str(e) for e in p.get("also", ())))
                      for p in doc["parts"])
        return parts, np.asarray(doc["u_v"], dtype=float).reshape(-1), float(doc["rate_hz"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path} lacks readable parts, u_v or rate_hz: {exc!r}") from None


def _flag(part: dict, key: str, required: bool) -> bool:
    """A part's boolean ``key`` (False where it may be missing)."""
    value = part[key] if required else part.get(key, False)
    if not isinstance(value, bool):
        raise TypeError(f"{key} is {value!r}, not true or false")
    return value


def played_parts(parts, u_experiment_v: np.ndarray, u_record_v: np.ndarray, dt_s: float
                 ) -> tuple[ExperimentPart, ...]:
    """``parts`` moved to where the record played them: the record can start before the
    experiment (a recorder that started first), so the start is the lag that best matches
    the record's voltages to the experiment's (least squares over every lag)."""
    from scipy.signal import correlate

    n, m = u_experiment_v.size, u_record_v.size
    if m < n:
        raise ValueError(f"the record ({m} samples) is shorter than the experiment it played "
                         f"({n} samples)")
    # sum over the window of (r - e)^2 = sum r^2 - 2 r.e + sum e^2, for every lag
    cross = correlate(u_record_v, u_experiment_v, mode="valid", method="fft")
    energy = np.convolve(u_record_v ** 2, np.ones(n), mode="valid")
    lag = int(np.argmin(energy - 2.0 * cross))
    return tuple(replace(p, start_s=p.start_s + lag * dt_s) for p in parts)


def holds(levels_v, hold_s: float, rate_hz: float) -> np.ndarray:
    """Voltages held at each of ``levels_v`` for ``hold_s``, one after the other."""
    n = int(round(hold_s * rate_hz))
    return np.concatenate([np.full(n, float(v)) for v in levels_v])


def crossings(amplitude_v: float, period_s: float, cycles: int, rate_hz: float) -> np.ndarray:
    """A triangle wave of ``amplitude_v`` around 0 V: slow, even crossings of 0 V."""
    t = np.arange(int(round(cycles * period_s * rate_hz))) / rate_hz
    phase = (t / period_s) % 1.0
    return amplitude_v * (4.0 * np.abs(phase - 0.5) - 1.0)


def sweep(amplitude_v: float, f0_hz: float, f1_hz: float, seconds: float, rate_hz: float
          ) -> np.ndarray:
    """A sine of ``amplitude_v`` whose frequency rises from ``f0_hz`` to ``f1_hz`` over
    ``seconds``, logarithmically (the same time in each octave)."""
    from scipy.signal import chirp

    t = np.arange(int(round(seconds * rate_hz))) / rate_hz
    return amplitude_v * chirp(t, f0_hz, seconds, f1_hz, method="logarithmic", phi=-90.0)


def wipe(amplitude_v: float, period_s: float, cycles: int, rate_hz: float) -> np.ndarray:
    """A sine of ``period_s`` whose amplitude falls linearly from ``amplitude_v`` to 0 over
    ``cycles`` periods: each reversal smaller than the last, it erases a hysteretic memory."""
    t = np.arange(int(round(cycles * period_s * rate_hz))) / rate_hz
    return amplitude_v * (1.0 - t / t[-1]) * np.sin(2.0 * np.pi * t / period_s)
