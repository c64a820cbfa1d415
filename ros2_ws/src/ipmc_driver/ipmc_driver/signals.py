"""Test-signal generators for driving the IPMC (volts) or as references (any unit).

All generators return ``(t_s, x)`` with ``t_s = arange(n) / rate_hz``.
"""

from __future__ import annotations

import numpy as np


def time_axis(seconds: float, rate_hz: float) -> np.ndarray:
    """Sample instants in seconds, ``round(seconds * rate_hz)`` of them."""
    if seconds <= 0 or rate_hz <= 0:
        raise ValueError(f"seconds and rate_hz must be > 0, got {seconds} and {rate_hz}")
    return np.arange(int(round(seconds * rate_hz))) / float(rate_hz)


def sine(amplitude: float, frequency_hz: float, seconds: float, rate_hz: float = 100.0,
         phase: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``amplitude * sin(2 pi f t + phase)``."""
    t = time_axis(seconds, rate_hz)
    return t, amplitude * np.sin(2.0 * np.pi * frequency_hz * t + phase)


def random_sine(seconds: float, rate_hz: float = 100.0, amplitude: float = 3.0,
                band_hz: tuple[float, float] = (0.05, 0.8), n_components: int = 8,
                seed: int | None = 0) -> tuple[np.ndarray, np.ndarray]:
    """Random sinusoid: a sum of ``n_components`` sines with random frequencies in ``band_hz``,
    random amplitudes and phases, scaled so that its peak is ``amplitude``.

    This is the "random sinusoidal voltage" of the paper (section 3.4), used to excite the
    actuator over a band rather than at a single frequency.
    """
    lo, hi = band_hz
    if not 0 <= lo < hi:
        raise ValueError(f"band_hz must satisfy 0 <= low < high, got {band_hz}")
    rng = np.random.default_rng(seed)
    t = time_axis(seconds, rate_hz)
    freqs = rng.uniform(max(lo, 1e-3), hi, n_components)
    amps = rng.uniform(0.3, 1.0, n_components)
    phases = rng.uniform(0, 2 * np.pi, n_components)
    x = (amps[:, None] * np.sin(2 * np.pi * freqs[:, None] * t + phases[:, None])).sum(axis=0)
    return t, amplitude * x / np.max(np.abs(x))


def steps(levels: list[float] | np.ndarray, hold_s: float, rate_hz: float = 100.0
          ) -> tuple[np.ndarray, np.ndarray]:
    """A staircase: each of ``levels`` held for ``hold_s`` seconds."""
    n_hold = int(round(hold_s * rate_hz))
    if n_hold < 1:
        raise ValueError(f"hold_s * rate_hz must be >= 1 sample, got {hold_s} * {rate_hz}")
    x = np.repeat(np.asarray(levels, dtype=float), n_hold)
    return np.arange(x.size) / float(rate_hz), x


def random_steps(seconds: float, rate_hz: float = 100.0, amplitude: float = 3.0,
                 hold_s: tuple[float, float] = (0.5, 5.0), seed: int | None = 0
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Random levels in [-amplitude, amplitude] held for random times in ``hold_s``."""
    rng = np.random.default_rng(seed)
    t = time_axis(seconds, rate_hz)
    x = np.empty_like(t)
    i = 0
    while i < t.size:
        n = max(1, int(rng.uniform(*hold_s) * rate_hz))
        x[i:i + n] = rng.uniform(-amplitude, amplitude)
        i += n
    return t, x


def mixed(seconds: float, rate_hz: float = 100.0, amplitude: float = 3.0,
          band_hz: tuple[float, float] = (0.02, 0.8), seed: int | None = 0, cycles: int = 4
          ) -> tuple[np.ndarray, np.ndarray]:
    """Identification input that covers the operating range in amplitude AND frequency.

    ``cycles`` equal cycles, each of three parts one after the other: a random sine over
    ``band_hz`` (half the cycle), a random sine over the band's slow quarter ``(low, high / 4)``
    (a quarter), then random levels held 0.5-5 s (a quarter), all with peak ``amplitude`` (V).
    Why: a nonlinear model fitted on a fast random sine alone rarely sees large voltages held
    long (its peaks are brief), so it extrapolates on a slow full-range sine; the slow part and
    the held levels put data there (the amplitude-modulated PRBS habit of nonlinear
    identification). Why cycles: a chronological split (the last 30 % held out, as ``ipmc
    diagnose`` and the tuning do) then holds every kind of input on both sides.
    """
    lo, hi = band_hz
    if not 0 <= lo < hi / 4:
        raise ValueError(f"band_hz must satisfy 0 <= low < high / 4, got {band_hz}")
    if int(cycles) != cycles or cycles < 1:
        raise ValueError(f"cycles must be an integer >= 1, got {cycles!r}")
    n = time_axis(seconds, rate_hz).size
    if n < 4 * cycles:
        raise ValueError(f"seconds * rate_hz must give at least 4 samples per cycle, got {n}")
    seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=(int(cycles), 3))
    edges = np.linspace(0, n, int(cycles) + 1).round().astype(int)
    parts = []
    for (a, b), (s_fast, s_slow, s_held) in zip(zip(edges[:-1], edges[1:], strict=True), seeds,
                                                 strict=True):
        m = b - a
        n_fast, n_slow = m // 2, m // 4
        n_held = m - n_fast - n_slow
        parts += [random_sine(n_fast / rate_hz, rate_hz, amplitude, (lo, hi),
                              seed=int(s_fast))[1][:n_fast],
                  random_sine(n_slow / rate_hz, rate_hz, amplitude, (lo, hi / 4),
                              seed=int(s_slow))[1][:n_slow],
                  random_steps(n_held / rate_hz, rate_hz, amplitude,
                               seed=int(s_held))[1][:n_held]]
    return np.arange(n) / float(rate_hz), np.concatenate(parts)
