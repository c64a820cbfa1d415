"""Shared small data for the ipmc_model tests (kept small: the suite must stay fast)."""

import numpy as np
import pytest

from ipmc_model.play import play_operators


def hysteretic_system(n: int = 1200, seed: int = 0, noise_mm: float = 0.005):
    """A PI hysteresis followed by a first-order lag, driven by a random sum of sines."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.01
    u = sum(rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * f * t + rng.uniform(0, 6))
            for f in rng.uniform(0.1, 1.0, 5))
    u = 2.5 * u / np.max(np.abs(u))
    h = play_operators(u, np.array([0.0, 0.3, 0.8])) @ np.array([1.0, 0.6, 0.4])
    y = np.zeros(n)
    for k in range(1, n):
        y[k] = 0.85 * y[k - 1] + 0.15 * h[k]
    return u, y + noise_mm * rng.standard_normal(n)


@pytest.fixture(scope="session")
def hyst_data():
    return hysteretic_system()
