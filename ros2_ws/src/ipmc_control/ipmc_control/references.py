"""Reference (desired tip displacement) generators, in mm and seconds (pure core, no ROS).

Each reference is a function of time: ``ref(t_s)`` takes a float (returns a float) or an array
(returns an array of the same shape), so a node can evaluate it at its clock's instants and an
offline run on a uniform grid (:meth:`Reference.sample`).

- :class:`ConstantReference` - a hold (the paper's 4 mm, Fig. 46).
- :class:`SineReference` - ``offset + A sin(2 pi f t + phase)`` (the paper's 2.5 mm at 1/2pi Hz).
- :class:`RandomSineReference` - a seeded sum of sines with frequencies in a band, scaled to a
  range (the paper's Fig. 50-52: 0-0.7 Hz, -9..4 mm).
- :class:`StepTrainReference` - levels held in turn.
- :class:`FileReference` - linear interpolation of a CSV file with columns ``t`` and ``y``.

:func:`make_reference` builds any of them from a kind name and keyword parameters (the
``reference`` node's and the ``track`` command's entry point).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from .pid import ControlParameterError, check_parameter

KINDS = ("constant", "sine", "random", "steps", "file")
#: Which parameters each kind takes (as the ``reference`` node and ``ipmc bringup`` name them).
KIND_PARAMS = {
    "constant": ("value_mm",),
    "sine": ("amplitude_mm", "frequency_hz", "offset_mm", "phase_rad"),
    "random": ("band_hz", "range_mm", "n_components", "period_s", "seed"),
    "steps": ("levels_mm", "hold_s", "repeat"),
    "file": ("path", "repeat"),
}


class Reference:
    """Base class: a desired displacement as a function of time, mm.

    Subclasses implement ``_eval(t_s: ndarray) -> ndarray``; scalars go through a fast path
    where a subclass defines ``_eval_scalar``.

    Attributes
    ----------
    duration_s : float or None
        Natural length of the reference, s (a file's span); None when unbounded.
    """

    duration_s: float | None = None

    def __call__(self, t_s):
        """Desired displacement at time(s) ``t_s`` (s), mm: float for a float, else array."""
        if np.ndim(t_s) == 0:
            return self._eval_scalar(float(t_s))
        return self._eval(np.asarray(t_s, dtype=float))

    def _eval_scalar(self, t: float) -> float:
        return float(self._eval(np.array([t]))[0])

    def _eval(self, t: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def rate(self, t_s):
        """Rate of change of the desired displacement at time(s) ``t_s`` (s), mm/s.

        Analytic where the reference is smooth; 0 on the flat parts of a step train (so a PID
        fed this rate has no derivative kick when the reference steps). The base class
        differentiates numerically (central difference over 1 ms).
        """
        if np.ndim(t_s) == 0:
            return float(self._rate(np.array([float(t_s)]))[0])
        return self._rate(np.asarray(t_s, dtype=float))

    def _rate(self, t: np.ndarray) -> np.ndarray:
        h = 0.5e-3
        return (self._eval(t + h) - self._eval(t - h)) / (2.0 * h)

    def sample(self, duration_s: float, rate_hz: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
        """Sample on a uniform grid.

        Parameters
        ----------
        duration_s : float
            Length, s (> 0).
        rate_hz : float
            Sampling rate, Hz (> 0).

        Returns
        -------
        t_s : ndarray, shape (N,)
            ``arange(N) / rate_hz`` with ``N = round(duration_s * rate_hz)``, s.
        y_mm : ndarray, shape (N,)
            Reference, mm.
        """
        duration_s = check_parameter("duration_s", duration_s, low=0.0, low_open=True)
        rate_hz = check_parameter("rate_hz", rate_hz, low=0.0, low_open=True)
        t = np.arange(int(round(duration_s * rate_hz))) / rate_hz
        return t, self._eval(t)


class ConstantReference(Reference):
    """A constant displacement ``value_mm``, mm."""

    def __init__(self, value_mm: float = 4.0) -> None:
        self.value_mm = check_parameter("value_mm", value_mm)

    def _eval_scalar(self, t: float) -> float:
        return self.value_mm

    def _eval(self, t: np.ndarray) -> np.ndarray:
        return np.full(t.shape, self.value_mm)

    def _rate(self, t: np.ndarray) -> np.ndarray:
        return np.zeros(t.shape)


class SineReference(Reference):
    """``offset_mm + amplitude_mm * sin(2 pi frequency_hz t + phase_rad)``, mm.

    Parameters
    ----------
    amplitude_mm : float
        Amplitude, mm (default 2.5 mm, the paper's Fig. 48).
    frequency_hz : float
        Frequency, Hz (> 0; default 1/(2 pi) Hz, the paper's Fig. 48).
    offset_mm : float
        Mean value, mm.
    phase_rad : float
        Phase at t = 0, rad.
    """

    def __init__(self, amplitude_mm: float = 2.5, frequency_hz: float = 1.0 / (2.0 * math.pi),
                 offset_mm: float = 0.0, phase_rad: float = 0.0) -> None:
        self.amplitude_mm = check_parameter("amplitude_mm", amplitude_mm)
        self.frequency_hz = check_parameter("frequency_hz", frequency_hz, low=0.0, low_open=True)
        self.offset_mm = check_parameter("offset_mm", offset_mm)
        self.phase_rad = check_parameter("phase_rad", phase_rad)
        self._w = 2.0 * math.pi * self.frequency_hz

    def _eval_scalar(self, t: float) -> float:
        return self.offset_mm + self.amplitude_mm * math.sin(self._w * t + self.phase_rad)

    def _eval(self, t: np.ndarray) -> np.ndarray:
        return self.offset_mm + self.amplitude_mm * np.sin(self._w * t + self.phase_rad)

    def _rate(self, t: np.ndarray) -> np.ndarray:
        return self.amplitude_mm * self._w * np.cos(self._w * t + self.phase_rad)


class RandomSineReference(Reference):
    """Seeded random sinusoid: a sum of sines in a band, scaled to a displacement range.

    The ``n_components`` frequencies are drawn without replacement from the multiples of
    ``1 / period_s`` inside ``band_hz`` (so the signal repeats every ``period_s``), with random
    amplitudes (uniform 0.3..1) and phases. The sum is then mapped affinely so that its minimum
    and maximum over one period are ``range_mm``; values are clipped to ``range_mm`` so the
    bound holds between grid points too.

    Parameters
    ----------
    band_hz : (float, float)
        Frequency band, Hz (``0 <= low < high``); default (0, 0.7) as in the paper's Fig. 52.
    range_mm : (float, float)
        Displacement range (min, max), mm; default (-9, 4) as in the paper's Fig. 52.
    n_components : int
        Number of sines (>= 1; fewer if the band holds fewer multiples of ``1 / period_s``).
    period_s : float
        Repetition period, s (> 0); sets the frequency grid.
    seed : int or None
        Seed of ``numpy.random.default_rng``; same seed, same signal.

    Attributes
    ----------
    frequencies_hz_, amplitudes_, phases_rad_ : ndarray, shape (n_components,)
        The drawn components (amplitudes before scaling, dimensionless).
    """

    def __init__(self, band_hz: tuple[float, float] = (0.0, 0.7),
                 range_mm: tuple[float, float] = (-9.0, 4.0), n_components: int = 20,
                 period_s: float = 100.0, seed: int | None = 0) -> None:
        lo, hi = _pair("band_hz", band_hz)
        if not 0.0 <= lo < hi:
            raise ControlParameterError(f"band_hz must satisfy 0 <= low < high, got {band_hz}")
        y_lo, y_hi = _pair("range_mm", range_mm)
        if not y_lo < y_hi:
            raise ControlParameterError(f"range_mm must satisfy min < max, got {range_mm}")
        if int(n_components) != n_components or n_components < 1:
            raise ControlParameterError(f"n_components must be an integer >= 1, "
                                        f"got {n_components!r}")
        period_s = check_parameter("period_s", period_s, low=0.0, low_open=True)
        grid = np.arange(max(1, math.ceil(lo * period_s)), math.floor(hi * period_s) + 1)
        grid = grid[(grid / period_s >= lo) & (grid / period_s <= hi)]
        if grid.size == 0:
            raise ControlParameterError(
                f"band_hz {band_hz} holds no multiple of 1/period_s = {1 / period_s} Hz; "
                "widen the band or lengthen period_s")
        self.band_hz, self.range_mm = (lo, hi), (y_lo, y_hi)
        self.n_components, self.period_s, self.seed = int(n_components), period_s, seed
        rng = np.random.default_rng(seed)
        k = np.sort(rng.choice(grid, size=min(self.n_components, grid.size), replace=False))
        self.frequencies_hz_ = k / period_s
        self.amplitudes_ = rng.uniform(0.3, 1.0, k.size)
        self.phases_rad_ = rng.uniform(0.0, 2.0 * np.pi, k.size)
        self._w = 2.0 * np.pi * self.frequencies_hz_
        # Extremes over one period on a grid of >= 200 points per period of the top frequency;
        # the clip in _eval covers the (relative 1e-4) miss between grid points.
        n = max(1000, int(math.ceil(200.0 * self.frequencies_hz_[-1] * period_s)))
        s = self._raw(np.arange(n) * (period_s / n))
        s_min, s_max = float(s.min()), float(s.max())
        if s_max - s_min <= 0.0:  # pragma: no cover - a sum of sines is never constant
            raise ControlParameterError("random sine degenerated to a constant")
        self._scale = (y_hi - y_lo) / (s_max - s_min)
        self._shift = y_lo - s_min * self._scale

    def _raw(self, t: np.ndarray) -> np.ndarray:
        flat = t.reshape(-1)
        out = np.zeros(flat.shape)
        for w, a, p in zip(self._w, self.amplitudes_, self.phases_rad_, strict=True):
            out += a * np.sin(w * flat + p)
        return out.reshape(t.shape)

    def _eval_scalar(self, t: float) -> float:
        s = 0.0
        for w, a, p in zip(self._w.tolist(), self.amplitudes_.tolist(),
                           self.phases_rad_.tolist(), strict=True):
            s += a * math.sin(w * t + p)
        y = self._shift + self._scale * s
        return min(max(y, self.range_mm[0]), self.range_mm[1])

    def _eval(self, t: np.ndarray) -> np.ndarray:
        return np.clip(self._shift + self._scale * self._raw(t), *self.range_mm)

    def _rate(self, t: np.ndarray) -> np.ndarray:
        flat = t.reshape(-1)
        out = np.zeros(flat.shape)
        for w, a, p in zip(self._w, self.amplitudes_, self.phases_rad_, strict=True):
            out += a * w * np.cos(w * flat + p)
        y = self._shift + self._scale * self._raw(flat)
        inside = (y > self.range_mm[0]) & (y < self.range_mm[1])  # clipped: flat
        return np.where(inside, self._scale * out, 0.0).reshape(t.shape)


class StepTrainReference(Reference):
    """Levels held in turn: ``levels_mm[j]`` for ``j * hold_s <= t < (j + 1) * hold_s``.

    Parameters
    ----------
    levels_mm : sequence of float
        The levels, mm (at least one).
    hold_s : float
        Time each level is held, s (> 0).
    repeat : bool
        Start again after the last level; otherwise hold the last level. Before t = 0 the first
        level holds.
    """

    def __init__(self, levels_mm=(0.0, 2.0, 0.0, -2.0), hold_s: float = 5.0,
                 repeat: bool = True) -> None:
        levels = np.asarray(levels_mm, dtype=float).reshape(-1)
        if levels.size < 1 or not np.all(np.isfinite(levels)):
            raise ControlParameterError(f"levels_mm must be one or more finite values, "
                                        f"got {levels_mm!r}")
        self.levels_mm = levels
        self.hold_s = check_parameter("hold_s", hold_s, low=0.0, low_open=True)
        self.repeat = bool(repeat)
        self.duration_s = None if self.repeat else levels.size * self.hold_s

    def _index(self, t: np.ndarray) -> np.ndarray:
        j = np.floor(t / self.hold_s).astype(np.int64)
        j = np.maximum(j, 0)
        if self.repeat:
            return j % self.levels_mm.size
        return np.minimum(j, self.levels_mm.size - 1)

    def _eval(self, t: np.ndarray) -> np.ndarray:
        return self.levels_mm[self._index(t)]

    def _rate(self, t: np.ndarray) -> np.ndarray:
        return np.zeros(t.shape)  # flat between the steps; the steps themselves are not rates


class FileReference(Reference):
    """Linear interpolation of a CSV file with a header naming columns ``t`` and ``y``.

    Accepted column names: ``t`` or ``t_s`` (s) and ``y`` or ``y_mm`` (mm), so both ``t,y``
    files and the project's ``t,u,y`` records work. Time must be finite and strictly increasing.

    Parameters
    ----------
    path : str or Path
        The CSV file.
    repeat : bool
        Play the file again after its end (period: its span plus one mean sample step);
        otherwise hold the last value. Before the first time stamp the first value holds.
    """

    def __init__(self, path: str | Path, repeat: bool = False) -> None:
        self.path = Path(path)
        self.repeat = bool(repeat)
        t, y = _read_ty(self.path)
        self.t_s, self.y_mm = t, y
        step = (t[-1] - t[0]) / (t.size - 1)
        self._period = t[-1] - t[0] + step
        self.duration_s = float(t[-1] - t[0])

    def _eval(self, t: np.ndarray) -> np.ndarray:
        if self.repeat:
            t = self.t_s[0] + np.mod(t - self.t_s[0], self._period)
        return np.interp(t, self.t_s, self.y_mm)


def _pair(name: str, value) -> tuple[float, float]:
    try:
        a, b = value
    except (TypeError, ValueError):
        raise ControlParameterError(f"{name} must be a pair (low, high), got {value!r}") from None
    return check_parameter(f"{name}[0]", a), check_parameter(f"{name}[1]", b)


def _read_ty(path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        with path.open(newline="") as f:
            rows = list(csv.reader(row for row in f if row.strip() and not row.startswith("#")))
    except OSError as exc:
        raise ControlParameterError(f"cannot read reference file {path}: {exc}") from None
    if len(rows) < 3:
        raise ControlParameterError(
            f"{path}: needs a header and at least 2 samples, got {len(rows)} rows")
    header = [h.strip().lower() for h in rows[0]]
    cols = {}
    for want, names in (("t", ("t", "t_s")), ("y", ("y", "y_mm"))):
        found = [header.index(n) for n in names if n in header]
        if not found:
            raise ControlParameterError(
                f"{path}: header {rows[0]} has no column {' or '.join(names)}")
        cols[want] = found[0]
    try:
        data = np.array([[float(r[cols["t"]]), float(r[cols["y"]])] for r in rows[1:]])
    except (ValueError, IndexError) as exc:
        raise ControlParameterError(f"{path}: bad row: {exc}") from None
    t, y = data[:, 0], data[:, 1]
    if not np.all(np.isfinite(data)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(data), axis=1))[0])
        raise ControlParameterError(f"{path}: non-finite value in data row {bad + 1}")
    if not np.all(np.diff(t) > 0):
        bad = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise ControlParameterError(
            f"{path}: time must increase strictly; row {bad + 2} has t = {t[bad + 1]} "
            f"after {t[bad]}")
    return t, y


def make_reference(kind: str, **params) -> Reference:
    """Build a reference from its kind name and keyword parameters.

    Parameters
    ----------
    kind : {"constant", "sine", "random", "steps", "file"}
        ``"constant"``: ``value_mm``. ``"sine"``: ``amplitude_mm``, ``frequency_hz``,
        ``offset_mm``, ``phase_rad``. ``"random"``: ``band_hz``, ``range_mm``,
        ``n_components``, ``period_s``, ``seed``. ``"steps"``: ``levels_mm``, ``hold_s``,
        ``repeat``. ``"file"``: ``path``, ``repeat``.
    **params
        The parameters of that kind (others raise).

    Returns
    -------
    Reference
    """
    classes = {"constant": ConstantReference, "sine": SineReference,
               "random": RandomSineReference, "steps": StepTrainReference,
               "file": FileReference}
    if kind not in classes:
        raise ControlParameterError(f"kind must be one of {KINDS}, got {kind!r}")
    try:
        return classes[kind](**params)
    except TypeError as exc:
        raise ControlParameterError(f"bad parameters for a {kind} reference: {exc}") from None
