"""Open-loop excitations: the drive voltage (V) played sample by sample to record a model's data.

An identification record has to contain what the model and its diagnosis are asked about:

- input holds of several seconds at levels spanning the range (creep and back-relaxation
  settle during a hold; a loop under feedback never holds the voltage still);
- steps (a delay shows as the lag between a voltage step and the first tip motion);
- the whole range of +-amplitude, fast and slow (the hysteresis loops a tracking loop will use).

Kinds (:data:`KINDS`):

- ``mixed`` (the default): ``cycles`` equal cycles, each an identification input
  (:func:`ipmc_driver.signals.mixed`: random sines over the band and its slow quarter, random
  short levels) followed by holds of ``hold_s`` at levels spanning +-amplitude; in cycles so
  that a chronological fit / held-out split has every kind of input on both sides;
- ``steps``: levels at 0, +-1/3, +-2/3 and +-1 of the amplitude in shuffled rounds, each held
  ``hold_s``;
- ``random-sine``: a random sum of sines up to 0.8 Hz (no holds: it cannot show creep);
- a file: a CSV with columns ``t`` (or ``t_s``, s) and ``u`` (or ``u_v``, V) as ``ipmc
  simulate`` writes, or a ``next_experiment.json`` of ``ipmc diagnose`` (format
  ``ipmc-ros-experiment``), at the plant's sampling rate.

No voltage beyond :data:`LIMIT_V` (the H-bridge's limit) is ever produced or accepted.
No ROS import: the ``excitation`` node and ``ipmc bringup`` use it, and tests call it directly.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ipmc_driver.signals import mixed, random_sine

KINDS = ("mixed", "steps", "random-sine")
#: The H-bridge's limit, V.
LIMIT_V = 3.0
#: Shortest input hold the diagnosis counts (creep needs holds), s.
HOLD_MIN_S = 3.0
#: Share of each ``mixed`` cycle spent on holds.
HOLD_SHARE = 0.5
#: The hold levels of ``mixed``, as fractions of the amplitude, taken in turn across cycles.
HOLD_FRACTIONS = (1.0, -1.0, 0.5, -0.5, 0.0, -0.75, 0.75, -0.25, 0.25)
#: The step levels of ``steps``, as fractions of the amplitude.
STEP_FRACTIONS = (-1.0, -2.0 / 3.0, -1.0 / 3.0, 0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0)
#: Relative mismatch of a file's sampling rate to the plant's that is still the same rate.
RATE_TOLERANCE = 1e-3


class ExcitationError(ValueError):
    """An excitation that cannot be built or played: one sentence saying why."""


@dataclass(frozen=True)
class Excitation:
    """Drive voltages ``u_v`` (V), one per sample at ``rate_hz``, and where they came from."""

    u_v: np.ndarray
    rate_hz: float
    source: str

    @property
    def duration_s(self) -> float:
        return self.u_v.size / self.rate_hz

    def holds(self, min_s: float = HOLD_MIN_S) -> list[tuple[int, int]]:
        """Runs [start, stop) (samples) of one constant voltage lasting ``min_s`` s or more."""
        n_min = max(1, int(math.ceil(min_s * self.rate_hz - 1e-9)))
        edges = np.flatnonzero(np.diff(self.u_v) != 0.0) + 1
        starts = np.concatenate([[0], edges])
        stops = np.concatenate([edges, [self.u_v.size]])
        return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True) if b - a >= n_min]

    def describe(self) -> str:
        """One line: source, length, range and holds."""
        return (f"{self.source}: {self.duration_s:g} s at {self.rate_hz:g} Hz, "
                f"{self.u_v.min():+.2f}..{self.u_v.max():+.2f} V, "
                f"{len(self.holds())} holds of {HOLD_MIN_S:g} s or more")


def _check_amplitude(amplitude_v: float) -> float:
    if not 0.0 < amplitude_v <= LIMIT_V:
        raise ExcitationError(f"the amplitude must be > 0 and <= {LIMIT_V:g} V (the H-bridge's "
                              f"limit), got {amplitude_v:g} V")
    return float(amplitude_v)


def _n_samples(seconds: float, rate_hz: float) -> int:
    if not (seconds > 0 and rate_hz > 0 and math.isfinite(seconds)):
        raise ExcitationError(f"the length must be > 0 s at a rate > 0 Hz, got {seconds:g} s "
                              f"at {rate_hz:g} Hz")
    return int(round(seconds * rate_hz))


def step_levels(amplitude_v: float, hold_s: float, seconds: float, rate_hz: float,
                seed: int = 0) -> np.ndarray:
    """Voltages (V) of ``steps``: shuffled rounds of :data:`STEP_FRACTIONS` times
    ``amplitude_v``, each held ``hold_s`` s, no level twice in a row; ``seconds`` long."""
    amplitude_v = _check_amplitude(amplitude_v)
    n, n_hold = _n_samples(seconds, rate_hz), int(round(hold_s * rate_hz))
    if n_hold < 1:
        raise ExcitationError(f"the hold must last at least one sample, got {hold_s:g} s")
    rng = np.random.default_rng(seed)
    levels: list[float] = []
    while len(levels) * n_hold < n:
        order = list(rng.permutation(STEP_FRACTIONS))
        if levels and order[0] == levels[-1]:
            order.append(order.pop(0))
        levels += order
    return np.repeat(amplitude_v * np.asarray(levels), n_hold)[:n]


def mixed_with_holds(amplitude_v: float, hold_s: float, seconds: float, rate_hz: float,
                     seed: int = 0, max_cycles: int = 4) -> np.ndarray:
    """Voltages (V) of ``mixed``: per cycle, an identification input then holds (module doc);
    as many cycles, up to ``max_cycles``, as leave room for two holds each."""
    amplitude_v = _check_amplitude(amplitude_v)
    n = _n_samples(seconds, rate_hz)
    cycles = max(1, min(max_cycles, int(HOLD_SHARE * seconds / (2.0 * hold_s))))
    cycle_s = seconds / cycles
    n_holds = min(len(HOLD_FRACTIONS), int(HOLD_SHARE * cycle_s / hold_s)) if hold_s > 0 else 0
    if n_holds < 2:
        need_s = 2.0 * hold_s / HOLD_SHARE
        raise ExcitationError(f"{seconds:g} s is too short for two holds of {hold_s:g} s "
                              f"beside the identification input: give at least {need_s:g} s "
                              "or shorter holds")
    n_hold = int(round(hold_s * rate_hz))
    seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=cycles)
    edges = np.linspace(0, n, cycles + 1).round().astype(int)
    parts, k = [], 0
    for j in range(cycles):
        m = int(edges[j + 1] - edges[j])
        n_ident = m - n_holds * n_hold
        parts.append(mixed(n_ident / rate_hz, rate_hz, amplitude_v, seed=int(seeds[j]),
                           cycles=1)[1][:n_ident])
        for _ in range(n_holds):
            parts.append(np.full(n_hold, amplitude_v * HOLD_FRACTIONS[k % len(HOLD_FRACTIONS)]))
            k += 1
    return np.concatenate(parts)[:n]


def make_excitation(kind: str, *, amplitude_v: float = LIMIT_V, hold_s: float = 8.0,
                    seconds: float = 240.0, rate_hz: float = 100.0, seed: int = 0
                    ) -> Excitation:
    """The excitation of ``kind`` (one of :data:`KINDS`).

    Parameters
    ----------
    kind : {"mixed", "steps", "random-sine"}
    amplitude_v : float
        Largest |voltage|, V (0 < amplitude_v <= 3).
    hold_s : float
        Length of each held level (``mixed``, ``steps``), s.
    seconds : float
        Length, s.
    rate_hz : float
        The plant's sampling rate, Hz: one voltage per sample.
    seed : int
        Seed of the random parts; same seed, same voltages.
    """
    if kind == "mixed":
        u = mixed_with_holds(amplitude_v, hold_s, seconds, rate_hz, seed)
    elif kind == "steps":
        u = step_levels(amplitude_v, hold_s, seconds, rate_hz, seed)
    elif kind == "random-sine":
        _n_samples(seconds, rate_hz)
        u = random_sine(seconds, rate_hz, _check_amplitude(amplitude_v), band_hz=(0.02, 0.8),
                        seed=seed)[1]
    else:
        raise ExcitationError(f"unknown excitation {kind!r}: choose one of {', '.join(KINDS)} "
                              "or give a file")
    return Excitation(np.clip(u, -LIMIT_V, LIMIT_V), float(rate_hz), kind)


def load_excitation(path: str | Path, rate_hz: float, seconds: float | None = None
                    ) -> Excitation:
    """The voltages of a CSV (``t``/``t_s``, ``u``/``u_v``) or a ``next_experiment.json``,
    checked: the plant's rate ``rate_hz``, finite, |u| <= 3 V; at most ``seconds`` long."""
    path = Path(path)
    if not path.is_file():
        raise ExcitationError(f"{path} is not a file")
    if path.suffix.lower() == ".json":
        u, file_rate_hz = _read_experiment(path)
    elif path.suffix.lower() == ".csv":
        u, file_rate_hz = _read_csv(path)
    else:
        raise ExcitationError(f"{path}: an excitation file is a .csv (t,u) or an ipmc diagnose "
                              "next_experiment.json")
    if abs(file_rate_hz - rate_hz) > RATE_TOLERANCE * rate_hz:
        raise ExcitationError(f"{path} is sampled at {file_rate_hz:g} Hz but the plant at "
                              f"{rate_hz:g} Hz: one voltage per sample needs the same rate")
    if not np.all(np.isfinite(u)):
        raise ExcitationError(f"{path} holds a non-finite voltage")
    worst = float(np.max(np.abs(u)))
    if worst > LIMIT_V + 1e-9:
        raise ExcitationError(f"{path} asks for {worst:g} V, beyond the H-bridge's "
                              f"{LIMIT_V:g} V")
    if seconds:
        u = u[:_n_samples(seconds, rate_hz)]
    return Excitation(u, float(rate_hz), str(path))


def _read_experiment(path: Path) -> tuple[np.ndarray, float]:
    from ipmc_model.diagnosis.experiment import read_experiment

    try:
        _, u, rate_hz = read_experiment(path)
    except ValueError as exc:
        raise ExcitationError(str(exc)) from None
    if u.size < 2:
        raise ExcitationError(f"{path} holds fewer than 2 voltages")
    return u, rate_hz


def _read_csv(path: Path) -> tuple[np.ndarray, float]:
    try:
        with path.open(newline="") as f:
            rows = list(csv.reader(r for r in f if r.strip() and not r.startswith("#")))
    except OSError as exc:
        raise ExcitationError(f"{path} cannot be read: {exc}") from None
    header = [h.strip().lower() for h in rows[0]] if rows else []
    cols = [next((header.index(n) for n in names if n in header), None)
            for names in (("t", "t_s"), ("u", "u_v"))]
    if None in cols or len(rows) < 3:
        raise ExcitationError(f"{path} needs a header with columns t and u (s, V) and at "
                              "least 2 rows")
    try:
        data = np.array([[float(r[cols[0]]), float(r[cols[1]])] for r in rows[1:]])
    except (ValueError, IndexError) as exc:
        raise ExcitationError(f"{path} has a bad row: {exc}") from None
    dt = np.diff(data[:, 0])
    if not np.all(dt > 0):
        raise ExcitationError(f"{path}: time must increase strictly")
    return data[:, 1], 1.0 / float(np.median(dt))


def save_csv(excitation: Excitation, path: str | Path) -> Path:
    """Write ``t,u`` (s, V) as a CSV that :func:`load_excitation` reads back."""
    path = Path(path)
    t = np.arange(excitation.u_v.size) / excitation.rate_hz
    lines = ["t,u"] + [f"{a:.6f},{b:.6f}" for a, b in zip(t, excitation.u_v, strict=True)]
    path.write_text("\n".join(lines) + "\n")
    return path
