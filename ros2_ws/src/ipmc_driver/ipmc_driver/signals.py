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
          band_hz: tuple[float, float] = (0.02, 0.8), seed: int | None = 0
          ) -> tuple[np.ndarray, np.ndarray]:
    """Identification input that covers the operating range in amplitude AND frequency.

    Three parts, one after the other: a random sine over ``band_hz`` (half the time), a random
    sine over the band's slow quarter ``(low, high / 4)`` (a quarter), then random levels held
    0.5-5 s (a quarter), all with peak ``amplitude`` (V). Why: a nonlinear model fitted on a
    fast random sine alone rarely sees large voltages held long (its peaks are brief), so it
    extrapolates on a slow full-range sine; the slow part and the held levels put data there
    (the amplitude-modulated PRBS habit of nonlinear identification).
    """
    lo, hi = band_hz
    if not 0 <= lo < hi / 4:
        raise ValueError(f"band_hz must satisfy 0 <= low < high / 4, got {band_hz}")
    n = time_axis(seconds, rate_hz).size
    if n < 4:
        raise ValueError(f"seconds * rate_hz must give at least 4 samples, got {n}")
    seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=3)
    n_fast, n_slow = n // 2, n // 4
    n_steps = n - n_fast - n_slow
    fast = random_sine(n_fast / rate_hz, rate_hz, amplitude, (lo, hi), seed=int(seeds[0]))[1]
    slow = random_sine(n_slow / rate_hz, rate_hz, amplitude, (lo, hi / 4), seed=int(seeds[1]))[1]
    held = random_steps(n_steps / rate_hz, rate_hz, amplitude, seed=int(seeds[2]))[1]
    x = np.concatenate([fast[:n_fast], slow[:n_slow], held[:n_steps]])
    return np.arange(n) / float(rate_hz), x
