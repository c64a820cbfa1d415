"""A second simulated actuator of another structure than the shipped IPMC plant, for judging
model families on a plant none was designed on: a Duhem hysteresis (Coleman-Hodgdon) on the
voltage, a relaxation with two real poles (0.8 s back-relaxation, 8 s creep in the same
direction), a polynomial asymmetric output with a soft limit, and a 4-sample transport delay.
No ion-current limit and no play operator: the GPI family's stages are not this plant's.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

NOISE_STD_MM = 0.008
RESOLUTION_MM = 0.01
#: The sensor's noise floor: Gaussian noise and the quantisation's uniform error.
NOISE_FLOOR_MM = float(np.hypot(NOISE_STD_MM, RESOLUTION_MM / np.sqrt(12.0)))


def duhem_plant(u_v, seed: int = 0, dt_s: float = 0.01, delay_samples: int = 4,
                creep_share: float = 0.15) -> np.ndarray:
    """Measured displacement (mm) of the Duhem actuator for the voltage ``u_v`` (V), its drive
    delayed by ``delay_samples``, its 8 s relaxation (a creep) of ``creep_share``."""
    u = np.concatenate([np.zeros(delay_samples), np.asarray(u_v, float)])[:len(u_v)]
    h, out = 0.0, np.empty(u.size)
    prev = 0.0
    for k, uk in enumerate(u):  # dh = a |du| (c u - h) + b du along the path, in 0.01 V steps
        n = max(1, int(np.ceil(abs(uk - prev) / 0.01)))
        for x in np.linspace(prev, uk, n + 1)[1:]:
            du = x - prev
            h += 0.9 * abs(du) * (0.8 * x - h) + 0.35 * du
            prev = x
        out[k] = h
    a1, a2 = np.exp(-dt_s / 0.8), np.exp(-dt_s / 8.0)
    x = (out - 0.4 * lfilter([1 - a1], [1, -a1], out)
         + creep_share * lfilter([1 - a2], [1, -a2], out))
    y = 1.6 * x + 0.22 * x * np.abs(x) - 0.05 * x ** 3
    y = 6.0 * np.tanh(y / 6.0)
    rng = np.random.default_rng(seed)
    y = y + rng.normal(0.0, NOISE_STD_MM, y.size)
    return np.round(y / RESOLUTION_MM) * RESOLUTION_MM
