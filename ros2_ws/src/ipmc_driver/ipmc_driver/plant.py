"""A physically plausible model of a Pt-electrode IPMC bender in water (pure core, no ROS).

Signal chain, one sample period ``dt_s`` integrated in ``substeps`` explicit steps:

1. H-bridge: the command is hard-limited to ``|u| <= u_max_v`` (3 V in the paper).
2. Optional ``delay`` (transport delay) and ``dead_zone`` on the applied voltage.
3. Electrical charging of the electrode double layer: ``v_c`` follows ``u`` with time constant
   ``tau_charge_s``, but the ionic current is limited, so ``dv_c/dt`` saturates at
   ``slew_v_per_s`` (large, fast voltages cannot be followed: the high-frequency loss of Table 1).
4. Back-relaxation: water diffuses back against the cation-driven swelling; a state ``r``
   follows ``v_c`` with ``tau_relax_s`` and a fraction ``relax_fraction`` of it is subtracted
   (the low-frequency loss of Table 1). The back-diffusion grows with the swelling pressure,
   so the relaxed share grows with charge:
   ``s = v_c - relax_fraction * r * (1 + relax_growth_per_v * |r|)``.
5. Hysteresis of the polymer: a Bouc-Wen element (n = 1) driven by ``s``; its output ``h``
   is mixed with ``s`` (``hyst_weight``).
6. Asymmetric bending: ``z > 0`` bends with gain ``gain_pos_mm_per_v`` and soft saturation at
   ``sat_pos_mm``; ``z < 0`` bends with ``gain_neg_mm_per_v * (1 + stiffen_neg_per_v |z|)``
   (negative voltages bend further, as in Table 1). Optional ``asymmetry`` scales the negative
   bending by ``negative_gain_ratio`` (the electrode on one face cracked or thinner).
7. Optional ``rate_dependence``: a bending that follows the ionic current, not the charge
   (water dragged with the migrating cations): ``gain_mm_per_v_per_s * dv_c/dt``. The loop
   widens with frequency and a step overshoots while the double layer charges.
8. Optional ``creep`` (slow relaxation with ``tau_s`` of seconds to a minute), ``drift`` (gain
   loss and offset over minutes: dehydration), ``saturation`` (symmetric soft limit).
9. Laser sensor: Gaussian noise ``noise_std_mm`` and quantisation ``resolution_mm``.

The default parameters (``data/plant_default.yaml``) were found by ``scripts/calibrate_plant.py``
so that the paper's nine sine conditions reproduce its Table 1 within 20 %.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import yaml

from .validation import as_signal

EFFECTS = ("creep", "drift", "delay", "dead_zone", "saturation", "asymmetry",
           "rate_dependence")

# Parameters every plant file must define; values are floats in the unit of the suffix.
_REQUIRED = (
    "u_max_v", "tau_charge_s", "slew_v_per_s", "tau_relax_s", "relax_fraction",
    "relax_growth_per_v",
    "bw_alpha", "bw_beta_per_v", "bw_gamma_per_v", "hyst_weight", "gain_pos_mm_per_v",
    "sat_pos_mm", "gain_neg_mm_per_v", "stiffen_neg_per_v", "noise_std_mm", "resolution_mm",
)


def default_params_path() -> Path:
    """Path of the shipped default plant parameter file."""
    return Path(str(resources.files("ipmc_driver") / "data" / "plant_default.yaml"))


def load_plant_params(path: str | Path | None = None) -> dict:
    """Load plant parameters from YAML (default: the shipped calibrated file).

    Returns a dict with the keys of ``_REQUIRED`` (floats) and ``effects`` (name -> dict of
    floats). Raises ``ValueError`` naming the file and the missing or bad key.
    """
    path = Path(path) if path is not None else default_params_path()
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"cannot read plant parameters from {path}: {exc}") from None
    if not isinstance(doc, dict) or "plant" not in doc:
        raise ValueError(f"{path} is not a plant parameter file (no 'plant' section)")
    params = {}
    for key in _REQUIRED:
        if key not in doc["plant"]:
            raise ValueError(f"{path}: plant parameter '{key}' is missing")
        params[key] = float(doc["plant"][key])
    params["effects"] = {k: {kk: float(vv) for kk, vv in v.items()}
                         for k, v in (doc.get("effects") or {}).items()}
    unknown = set(params["effects"]) - set(EFFECTS)
    if unknown:
        raise ValueError(f"{path}: unknown effects {sorted(unknown)}; known: {list(EFFECTS)}")
    return params


@dataclass
class PlantRun:
    """Result of :meth:`IpmcPlant.run`: time (s), applied voltage (V), measured and true
    displacement (mm), all shape (N,)."""

    t_s: np.ndarray
    u_v: np.ndarray
    y_mm: np.ndarray
    y_true_mm: np.ndarray


class IpmcPlant:
    """Simulated IPMC actuator sampled at ``1 / dt_s``.

    Parameters
    ----------
    params : dict, optional
        As returned by :func:`load_plant_params`; default: the shipped calibrated file.
    effects : iterable of str or dict, optional
        Optional physical effects to switch on, names from ``EFFECTS``; a dict maps a name to
        overrides of that effect's parameters (e.g. ``{"creep": {"tau_s": 40.0}}``).
    seed : int, optional
        Seed of the sensor noise.
    dt_s : float
        Sample period in seconds (default 0.01: 100 Hz).
    substeps : int
        Integration steps per sample (explicit Euler on the fast states).
    """

    def __init__(self, params: dict | None = None, effects=(), seed: int | None = 0,
                 dt_s: float = 0.01, substeps: int = 5):
        if dt_s <= 0 or not math.isfinite(dt_s):
            raise ValueError(f"dt_s must be a positive number of seconds, got {dt_s}")
        self.params = dict(params if params is not None else load_plant_params())
        self.dt_s = float(dt_s)
        self.substeps = int(substeps)
        self.seed = seed
        self.effects = self._resolve_effects(effects)
        self.reset()

    def _resolve_effects(self, effects) -> dict:
        if isinstance(effects, str):
            effects = [effects]
        overrides = dict(effects) if isinstance(effects, dict) else {e: {} for e in effects}
        out = {}
        for name, extra in overrides.items():
            if name not in EFFECTS:
                raise ValueError(f"unknown effect '{name}'; known effects: {', '.join(EFFECTS)}")
            base = dict(self.params.get("effects", {}).get(name, {}))
            bad = set(extra or {}) - set(base)
            if bad:
                raise ValueError(f"effect '{name}' has no parameter(s) {sorted(bad)}; "
                                 f"it has {sorted(base)}")
            base.update({k: float(v) for k, v in (extra or {}).items()})
            out[name] = base
        return out

    def reset(self) -> None:
        """Return to rest: all states zero, time zero, noise generator re-seeded."""
        self._k = 0
        self._v = 0.0  # double-layer voltage, V
        self._r = 0.0  # back-relaxation state, V
        self._s_prev = 0.0
        self._h = 0.0  # Bouc-Wen hysteretic state, V
        self._creep = 0.0  # mm
        self._rng = np.random.default_rng(self.seed)
        delay = self.effects.get("delay")
        n_delay = int(round(delay["delay_s"] / self.dt_s)) if delay else 0
        self._delay_line = deque([0.0] * n_delay)

    @property
    def t_s(self) -> float:
        """Time of the next sample, seconds."""
        return self._k * self.dt_s

    def _bend_mm(self, z: float) -> float:
        p = self.params
        if z >= 0.0:
            sat = p["sat_pos_mm"]
            return sat * math.tanh(p["gain_pos_mm_per_v"] * z / sat)
        y = p["gain_neg_mm_per_v"] * z * (1.0 + p["stiffen_neg_per_v"] * -z)
        if "asymmetry" in self.effects:
            y *= self.effects["asymmetry"]["negative_gain_ratio"]
        return y

    def step(self, u_v: float) -> tuple[float, float]:
        """Apply ``u_v`` for one sample period; return (applied voltage V, measured tip mm)."""
        u_applied, y_true = self._advance(u_v)
        return u_applied, self._measure(y_true)

    def _advance(self, u_v: float) -> tuple[float, float]:
        p = self.params
        fx = self.effects
        u = float(u_v)
        if not math.isfinite(u):
            u = 0.0  # a NaN command must never reach the H-bridge
        u_max = p["u_max_v"]
        u_applied = min(max(u, -u_max), u_max)
        u_eff = u_applied
        if self._delay_line:
            self._delay_line.append(u_eff)
            u_eff = self._delay_line.popleft()
        if "dead_zone" in fx:
            w = fx["dead_zone"]["width_v"]
            u_eff = math.copysign(max(abs(u_eff) - w, 0.0), u_eff)

        h_dt = self.dt_s / self.substeps
        tau_c, slew = p["tau_charge_s"], p["slew_v_per_s"]
        tau_r, beta_r, grow = p["tau_relax_s"], p["relax_fraction"], p["relax_growth_per_v"]
        a, b, g = p["bw_alpha"], p["bw_beta_per_v"], p["bw_gamma_per_v"]
        v, r, h, s_prev = self._v, self._r, self._h, self._s_prev
        v_start = v
        for _ in range(self.substeps):
            # Current-limited charging: linear for small errors, slew-limited for large ones.
            v += h_dt * slew * math.tanh((u_eff - v) / (tau_c * slew))
            r += h_dt * (v - r) / tau_r
            s = v - beta_r * r * (1.0 + grow * abs(r))
            ds = s - s_prev
            h += a * ds - b * abs(ds) * h - g * ds * abs(h)
            s_prev = s
        self._v, self._r, self._h, self._s_prev = v, r, h, s_prev
        w = p["hyst_weight"]
        y = self._bend_mm((1.0 - w) * s_prev + w * h)
        if "rate_dependence" in fx:
            # the charging current over this sample, as the mean rate of the double layer
            y += fx["rate_dependence"]["gain_mm_per_v_per_s"] * (v - v_start) / self.dt_s

        t = self.t_s
        if "creep" in fx:
            c = fx["creep"]
            # Slow relaxation driven by the sustained charge; sign of gain sets the direction.
            target = c["gain_mm_per_v"] * v
            self._creep += (target - self._creep) * (1.0 - math.exp(-self.dt_s / c["tau_s"]))
            y += self._creep
        if "drift" in fx:
            d = fx["drift"]
            minutes = t / 60.0
            y = y * max(0.0, 1.0 - d["gain_loss_per_min"] * minutes)
            y += d["offset_mm_per_min"] * minutes
        if "saturation" in fx:
            lim = fx["saturation"]["limit_mm"]
            y = lim * math.tanh(y / lim)
        self._k += 1
        return u_applied, y

    def _measure(self, y_true_mm: float) -> float:
        p = self.params
        y = y_true_mm + p["noise_std_mm"] * self._rng.standard_normal()
        q = p["resolution_mm"]
        return round(y / q) * q if q > 0 else y

    def run(self, u_v) -> PlantRun:
        """Drive the plant with the voltage sequence ``u_v`` (V, one value per sample) from its
        current state; return time, applied voltage and measured/true displacement."""
        u_v = as_signal("u_v", u_v)
        t0 = self._k
        n = u_v.size
        u_out = np.empty(n)
        y_true = np.empty(n)
        for i in range(n):
            u_out[i], y_true[i] = self._advance(u_v[i])
        noise = self.params["noise_std_mm"] * self._rng.standard_normal(n)
        q = self.params["resolution_mm"]
        y_meas = y_true + noise
        if q > 0:
            y_meas = np.round(y_meas / q) * q
        t = (t0 + np.arange(n)) * self.dt_s
        return PlantRun(t_s=t, u_v=u_out, y_mm=y_meas, y_true_mm=y_true)
