"""LSSVM-NARX models augmented with physical effect blocks: the model, its inverse, its files.

An :class:`AugmentedModel` wraps a fitted :class:`~ipmc_model.narx.NarxModel` (the baseline)
between *input effects*, applied to the voltage before the baseline, and *output effects*,
applied to the baseline's output z (mm) to give the displacement y (mm)::

    u --[delay, dead_zone, asymmetry, rate_dependence]--> v --[NARX]--> z --[creep, drift,
    saturation]--> y

Each effect is a small physical block with parameters in physical units (seconds, volts, mm,
per minute), not a bigger black box:

============== ======== ==================================================================
effect         side     block (k: sample, dt: sample period, t: time since record start)
============== ======== ==================================================================
creep          output   y = z + c, c_k = a c_{k-1} + (1 - a) g u_{k-1}, a = exp(-dt / tau_s);
                        slow first-order relaxation driven by the input, g (mm/V) of either
                        sign (g < 0 relaxes back against the bending)
drift          output   y = (1 - gain_loss_per_min t/60) z + offset_mm_per_min t/60
saturation     output   y = limit_mm tanh(z / limit_mm)
delay          input    v_k = u_{k - d}, d = delay_s / dt (transport delay)
dead_zone      input    v = sign(u) max(|u| - width_v, 0)
asymmetry      input    v = u for u >= 0, negative_gain_ratio u for u < 0
asymmetry      output   (with negative_bending_ratio: fitted around a given model beside the
                        input form, the better kept) y = z for z >= 0, negative_bending_ratio z
                        for z < 0: the negative bending scaled (one electrode face cracked), as
                        the plant has it
rate_dependence input   an extra input channel, the voltage rate du/dt (V/s) low-passed with
                        tau_s, one lag: the bending depends on how fast the voltage changes
rate_dependence output  (with gain_mm_per_v_per_s: the block around a given model) y = z + g rho,
                        rho_k = a rho_{k-1} + (1 - a) (u_{k-1} - u_{k-2}) / dt: a bending that
                        follows the ionic current (the low-passed voltage rate), g mm per V/s
memory         input    an extra input channel, the voltage low-passed with tau_s (V): the
                        polymer's back-relaxation remembers the input beyond the NARX's lag
                        window. A block of the baseline (``diagnose(memory_taus_s=...)``),
                        never a candidate effect
============== ======== ==================================================================

The channel blocks (rate_dependence, memory) act after the other input effects, whatever the
order they were added in: they read the transformed voltage (the first channel).

These files (format ``ipmc-ros-augmented-model``) were written by earlier versions of
``ipmc diagnose`` around LSSVM-NARX baselines; they still load, run, serve and invert here. The
diagnosis itself now adds its effects as stages of a GPI model (:mod:`ipmc_model.diagnosis`),
whose files are ordinary GPI model files.

Inversion (feedforward control): :meth:`AugmentedModel.inverse_stepper` wraps an inverse NARX
fitted in the baseline's space (:meth:`AugmentedModel.fit_inverse`). For creep, at each step
the creep state c_k (known from the voltages already applied) is subtracted from the desired
displacement, the baseline inverse gives the voltage for the rest, and the applied voltage
then advances the creep state. Drift and saturation are inverted the same way, dead zone and
asymmetry (either form) by their inverse static maps, the output form of rate dependence like
creep (its state is known from the voltages already applied); delay and the rate and memory
channels are not invertible step by step (a delay needs reference preview) and raise
``ValueError``. :class:`AugmentedInverse` is that feedforward as a model file (``ipmc identify
--inverse --effects-from``, served by ``ipmc track`` and model_server): it keeps the effects a
later run can undo and leaves out, with the reason, drift (its time origin is the
identification record's), delay and the channels (:data:`FEEDFORWARD_LEAVES_OUT`).
"""

from __future__ import annotations

import copy
import json
import math
from collections import deque
from pathlib import Path

import numpy as np
from scipy.signal import lfilter

from ipmc_driver.dataio import write_atomic
from ipmc_driver.validation import as_signal, same_length

from .errors import ModelFileError
from .narx import (
    FreeRunCache,
    InverseNarxModel,
    NarxCommittee,
    NarxModel,
    members_of,
    samples_to_settle,
)
from .persistence import (
    DOCUMENT_CHECKSUM,
    document_sha256,
    load_model,
    read_model_document,
    save_model,
)

EFFECT_NAMES = ("creep", "drift", "delay", "rate_dependence", "asymmetry", "dead_zone",
                "saturation")
#: Blocks of a baseline that are not candidate effects (never in ``effects_found``).
BASELINE_BLOCKS = ("memory",)
#: Input blocks that append a channel (they act after the other input effects).
CHANNEL_BLOCKS = ("rate_dependence", "memory")
OUTPUT_EFFECTS = ("creep", "drift", "saturation")
INPUT_EFFECTS = ("delay", "dead_zone", "asymmetry", "rate_dependence")
#: Effects whose fit refits the baseline NARX (the others keep it fixed).
REFIT_EFFECTS = ("delay", "dead_zone", "asymmetry", "rate_dependence", "saturation")
#: Blocks that can also be fitted around a model kept as it is (a model given to the
#: diagnosis, fitted on other data): :func:`fit_frozen_effect`.
FROZEN_EFFECTS = ("drift", "delay", "dead_zone", "asymmetry", "saturation", "rate_dependence")
#: Points of the frozen fits' parameter grids (then refined between the best one's neighbours).
FROZEN_GRID_POINTS = 25

#: Units of each effect parameter (for reports).
PARAM_UNITS = {
    "tau_s": "s", "gain_mm_per_v": "mm/V", "gain_loss_per_min": "1/min",
    "offset_mm_per_min": "mm/min", "delay_s": "s", "width_v": "V",
    "negative_gain_ratio": "1", "negative_bending_ratio": "1", "limit_mm": "mm",
    "gain_mm_per_v_per_s": "mm/(V/s)",
}

#: What each fitted parameter means on the bench, by (effect, parameter), for reports.
PARAM_MEANING = {
    ("creep", "tau_s"): "time constant of the slow relaxation under a held voltage",
    ("creep", "gain_mm_per_v"): "creep's final displacement per volt held (< 0: relaxes back "
                                "against the bending)",
    ("drift", "gain_loss_per_min"): "share of the gain lost per minute of the record",
    ("drift", "offset_mm_per_min"): "offset gained per minute of the record",
    ("delay", "delay_s"): "transport delay from the voltage to the tip",
    ("dead_zone", "width_v"): "voltage magnitude below which the tip does not move",
    ("asymmetry", "negative_gain_ratio"): "negative voltages act this share as strongly as "
                                          "before",
    ("asymmetry", "negative_bending_ratio"): "the negative bending is this share of the "
                                             "model's (one electrode face weaker)",
    ("saturation", "limit_mm"): "displacement the tip approaches but cannot pass",
    ("rate_dependence", "tau_s"): "low-pass of the voltage rate (the ionic current's lag)",
    ("rate_dependence", "gain_mm_per_v_per_s"): "extra bending per V/s of voltage rate",
    ("memory", "tau_s"): "low-pass of the voltage kept as a slow memory channel",
}

AUGMENTED_FORMAT = "ipmc-ros-augmented-model"
#: 2 adds the document checksum (as model files of format 5); files of version 1 still load.
AUGMENTED_FORMAT_VERSION = 2
#: ``kind`` of an augmented model file that also holds a feedforward (:class:`AugmentedInverse`).
AUGMENTED_INVERSE_KIND = "augmented-lssvm-narx-inverse"

#: Effects an augmented model's feedforward leaves out, and why (:class:`AugmentedInverse`).
FEEDFORWARD_LEAVES_OUT = {
    "drift": "a trend over the identification record's time: a later run starts at a point of "
             "it the feedforward cannot know (the PID takes out a slow offset)",
    "delay": "a transport delay cannot be undone without the reference ahead of time",
    "rate_dependence": "its rate channel is an input of the baseline, which the inverse does "
                       "not give",
    "memory": "its channel is an input of the baseline, which the inverse does not give",
}


# -- the effects --
class Effect:
    """One physical effect with fixed parameters (physical units); see the module table.

    Parameters
    ----------
    name : str
        One of :data:`EFFECT_NAMES` or :data:`BASELINE_BLOCKS`.
    **params : float
        The effect's parameters (keys as in the module table).
    """

    _KEYS = {
        "creep": ("tau_s", "gain_mm_per_v"),
        "drift": ("gain_loss_per_min", "offset_mm_per_min"),
        "saturation": ("limit_mm",),
        "delay": ("delay_s",),
        "dead_zone": ("width_v",),
        "asymmetry": ("negative_gain_ratio",),
        "rate_dependence": ("tau_s",),
        "memory": ("tau_s",),
    }
    # a second parameter set: the output form of a block, fitted around a given model
    _OUTPUT_KEYS = {"rate_dependence": ("tau_s", "gain_mm_per_v_per_s"),
                    "asymmetry": ("negative_bending_ratio",)}

    def __init__(self, name: str, **params):
        if name not in EFFECT_NAMES + BASELINE_BLOCKS:
            raise ValueError(f"unknown effect {name!r}; known: "
                             f"{', '.join(EFFECT_NAMES + BASELINE_BLOCKS)}")
        keys = self._KEYS[name]
        alt = self._OUTPUT_KEYS.get(name)
        if alt is not None and set(params) == set(alt):
            keys = alt
        elif set(params) != set(keys):
            need = f"{list(keys)}" + (f" or {list(alt)}" if alt else "")
            raise ValueError(f"effect {name!r} needs parameters {need}, got {sorted(params)}")
        self.name = name
        self.params = {k: float(params[k]) for k in keys}
        for k, v in self.params.items():
            if not math.isfinite(v):
                raise ValueError(f"effect {name!r}: parameter {k} must be finite, got {v}")
        if name in ("creep", *CHANNEL_BLOCKS) and self.params["tau_s"] <= 0:
            raise ValueError(f"effect {name!r}: tau_s must be > 0, got {self.params['tau_s']}")
        if name == "saturation" and self.params["limit_mm"] <= 0:
            raise ValueError(f"saturation: limit_mm must be > 0, got {self.params['limit_mm']}")
        if name == "asymmetry" and list(self.params.values())[0] <= 0:
            raise ValueError(f"asymmetry: {keys[0]} must be > 0")
        if name in ("delay", "dead_zone") and list(self.params.values())[0] < 0:
            raise ValueError(f"effect {name!r}: parameter must be >= 0, got {self.params}")

    @property
    def side(self) -> str:
        """``"input"`` or ``"output"``."""
        return "output" if self.name in OUTPUT_EFFECTS or self.is_output_form else "input"

    @property
    def is_output_form(self) -> bool:
        """The output form of a block that also has an input form (its second parameter set:
        rate dependence with ``gain_mm_per_v_per_s``, asymmetry with
        ``negative_bending_ratio``)."""
        return tuple(self.params) == self._OUTPUT_KEYS.get(self.name)

    @property
    def is_rate_output(self) -> bool:
        """Rate dependence as an output block (``gain_mm_per_v_per_s`` given), not a channel."""
        return self.name == "rate_dependence" and self.is_output_form

    @property
    def is_channel(self) -> bool:
        """An extra input channel of the baseline (the rate or memory channel)."""
        return self.name in CHANNEL_BLOCKS and not self.is_rate_output

    def describe(self) -> str:
        """Parameters with units, e.g. ``tau_s = 31.2 s, gain_mm_per_v = -0.29 mm/V``."""
        return ", ".join(f"{k} = {v:.4g} {PARAM_UNITS[k]}" for k, v in self.params.items())

    def __repr__(self) -> str:
        return f"Effect({self.name!r}, {self.describe()})"

    def as_dict(self) -> dict:
        return {"name": self.name, "params": dict(self.params)}

    # -- batch (whole records; ``u`` includes the past, ``t_s`` aligned with it) --
    def apply_input(self, v: np.ndarray, dt_s: float) -> np.ndarray:
        """Input effect on a whole record (N,) or (N, c) -> (N,) or (N, c + 1)."""
        p = self.params
        if self.name == "delay":
            d = int(round(p["delay_s"] / dt_s))
            if d == 0:
                return v
            out = np.empty_like(v)
            out[:d] = 0.0
            out[d:] = v[:-d]
            return out
        if self.name == "dead_zone":
            return np.sign(v) * np.maximum(np.abs(v) - p["width_v"], 0.0)
        if self.name == "asymmetry":
            return np.where(v >= 0.0, v, p["negative_gain_ratio"] * v)
        # channel blocks: append the low-passed voltage rate (rate_dependence) or the
        # low-passed voltage (memory) of the first channel
        u0 = v if v.ndim == 1 else v[:, 0]
        x = np.diff(u0, prepend=u0[:1]) / dt_s if self.name == "rate_dependence" else u0
        a = math.exp(-dt_s / p["tau_s"])
        return np.column_stack([v, lfilter([1.0 - a], [1.0, -a], x)])

    def creep_state(self, u: np.ndarray, dt_s: float) -> np.ndarray:
        """Creep c_k for every k from the input (N,) (causal: c_k uses u up to k - 1)."""
        return _late_low_pass(u, dt_s, self.params["tau_s"], self.params["gain_mm_per_v"])

    def rate_state(self, u: np.ndarray, dt_s: float) -> np.ndarray:
        """Rate output block g rho_k (mm) for every k from the input (N,) (causal: rho_k uses
        u up to k - 1; the rate before the record is 0)."""
        du = np.diff(u, prepend=u[:1]) / dt_s
        return _late_low_pass(du, dt_s, self.params["tau_s"], self.params["gain_mm_per_v_per_s"])

    def forward(self, z, u, t_s, dt_s):
        """Output effect: baseline output z (mm) -> displacement y (mm), whole record."""
        p = self.params
        if self.name == "creep":
            return z + self.creep_state(u, dt_s)
        if self.name == "rate_dependence":
            return z + self.rate_state(u, dt_s)
        if self.name == "asymmetry":
            return np.where(z >= 0.0, z, p["negative_bending_ratio"] * z)
        if self.name == "drift":
            m = t_s / 60.0
            return (1.0 - p["gain_loss_per_min"] * m) * z + p["offset_mm_per_min"] * m
        lim = p["limit_mm"]
        return lim * np.tanh(z / lim)

    def backward(self, y, u, t_s, dt_s):
        """Inverse of :meth:`forward`: displacement y (mm) -> baseline output z (mm)."""
        p = self.params
        if self.name == "creep":
            return y - self.creep_state(u, dt_s)
        if self.name == "rate_dependence":
            return y - self.rate_state(u, dt_s)
        if self.name == "asymmetry":
            return np.where(y >= 0.0, y, y / p["negative_bending_ratio"])
        if self.name == "drift":
            m = t_s / 60.0
            g = np.maximum(1.0 - p["gain_loss_per_min"] * m, 0.05)
            return (y - p["offset_mm_per_min"] * m) / g
        lim = p["limit_mm"]
        return lim * np.arctanh(np.clip(y / lim, -0.999, 0.999))

    # -- streaming --
    def runner(self, dt_s: float) -> _Runner:
        """A per-sample state machine of this effect (used by the steppers)."""
        return _Runner(self, dt_s)


class _Runner:
    """Per-sample state of one effect. Input effects: ``apply(u_k)`` records u_k and returns the
    transformed input; ``invert(v_k)`` gives u_k without recording. Output effects:
    ``forward(z_k, t_k)``, ``backward(y_k, t_k)`` use the state known before u_k is chosen;
    ``push(u_k)`` then advances it."""

    def __init__(self, effect: Effect, dt_s: float):
        self.e = effect
        self.dt_s = float(dt_s)
        p = effect.params
        self.c = 0.0  # creep state, mm
        self.rho = 0.0  # low-passed rate, V/s
        self.u_prev = 0.0
        self.pushed = False  # the output rate block: no voltage applied yet (rate 0 before)
        if effect.name == "delay":
            self.line = deque([0.0] * int(round(p["delay_s"] / dt_s)))
        if effect.name in ("creep", *CHANNEL_BLOCKS):
            self.a = math.exp(-dt_s / p["tau_s"])

    def apply(self, u_k):
        name, p = self.e.name, self.e.params
        if name == "delay":
            if not self.line:
                return u_k
            self.line.append(u_k)
            return self.line.popleft()
        if name == "dead_zone":
            return math.copysign(max(abs(u_k) - p["width_v"], 0.0), u_k)
        if name == "asymmetry":
            return u_k if u_k >= 0 else p["negative_gain_ratio"] * u_k
        # channel blocks: u_k is the voltage or the channels so far (the voltage first)
        chans = u_k if isinstance(u_k, tuple) else (u_k,)
        x = chans[0]
        if name == "rate_dependence":
            x = (chans[0] - self.u_prev) / self.dt_s
            self.u_prev = chans[0]
        self.rho = self.a * self.rho + (1.0 - self.a) * x
        return (*chans, self.rho)

    def invert(self, v_k):
        name, p = self.e.name, self.e.params
        if name == "dead_zone":
            return 0.0 if v_k == 0.0 else math.copysign(abs(v_k) + p["width_v"], v_k)
        if name == "asymmetry":
            return v_k if v_k >= 0 else v_k / p["negative_gain_ratio"]
        raise ValueError(f"the {name} effect cannot be inverted step by step"
                         + (" (a transport delay needs reference preview)" if name == "delay"
                            else ""))

    def forward(self, z_k, t_k):
        p = self.e.params
        if self.e.name == "creep":
            return z_k + self.c
        if self.e.name == "rate_dependence":
            return z_k + p["gain_mm_per_v_per_s"] * self.rho
        if self.e.name == "asymmetry":
            return z_k if z_k >= 0 else p["negative_bending_ratio"] * z_k
        if self.e.name == "drift":
            m = t_k / 60.0
            return (1.0 - p["gain_loss_per_min"] * m) * z_k + p["offset_mm_per_min"] * m
        return p["limit_mm"] * math.tanh(z_k / p["limit_mm"])

    def backward(self, y_k, t_k):
        p = self.e.params
        if self.e.name == "creep":
            return y_k - self.c
        if self.e.name == "rate_dependence":
            return y_k - p["gain_mm_per_v_per_s"] * self.rho
        if self.e.name == "asymmetry":
            return y_k if y_k >= 0 else y_k / p["negative_bending_ratio"]
        if self.e.name == "drift":
            m = t_k / 60.0
            g = max(1.0 - p["gain_loss_per_min"] * m, 0.05)
            return (y_k - p["offset_mm_per_min"] * m) / g
        lim = p["limit_mm"]
        return lim * math.atanh(min(max(y_k / lim, -0.999), 0.999))

    def push(self, u_k):
        if self.e.name == "creep":
            self.c = self.a * self.c + (1.0 - self.a) * self.e.params["gain_mm_per_v"] * u_k
        elif self.e.name == "rate_dependence":
            x = (u_k - self.u_prev) / self.dt_s if self.pushed else 0.0
            self.u_prev, self.pushed = u_k, True
            self.rho = self.a * self.rho + (1.0 - self.a) * x


def _late_low_pass(x: np.ndarray, dt_s: float, tau_s: float, gain: float) -> np.ndarray:
    """s_k = a s_{k-1} + (1 - a) gain x_{k-1}, a = exp(-dt / tau): the creep and rate states,
    one sample late so that the state is known before u_k is chosen (inverse steppers)."""
    a = math.exp(-dt_s / tau_s)
    return lfilter([0.0, (1.0 - a) * gain], [1.0, -a], x)


# -- the augmented model --
def _channel_lags(lags, n_ch: int, chans) -> tuple[int, ...]:
    """Per-channel input lags of a template refitted on ``n_ch`` channels: the voltage and the
    channels ``chans`` (block names, in order) the input blocks add. The lags the template
    gives per channel name the channels it knew (the voltage, memory channels); the rate
    channel gets one lag: the rate now is the effect, and 12 lags of it were a second copy of
    the voltage's window (a bigger model, not a physical block: docs/diagnose.md, "Rate
    dependence: one lag")."""
    per = [lags] * n_ch if np.isscalar(lags) else list(lags) + [lags[0]] * (n_ch - len(lags))
    for i, name in enumerate(chans, start=1):
        if name == "rate_dependence":
            per[i] = 1
    return tuple(per)


class AugmentedModel:
    """A fitted baseline NARX model with physical effects around it (see the module docstring).

    Parameters
    ----------
    baseline : NarxModel or NarxCommittee (fitted)
        Fitted on the data seen through ``effects`` (transformed input, effect-free output).
    effects : sequence of Effect
        In the order they were added; input effects act in this order on u, output effects in
        this order on z (the last added is outermost).
    dt_s : float
        Sample period (s) of the data the model was fitted on (creep, delay, rate, drift time).

    Notes
    -----
    Time ``t_s`` (drift) counts from the start of the record the model was identified on;
    :meth:`simulate` takes ``t0_s`` for a later start and ``u_past`` for the input history
    (creep state, delay line) before the first sample.
    """

    def __init__(self, baseline: NarxModel | NarxCommittee, effects=(), dt_s: float = 0.01):
        if not isinstance(baseline, (NarxModel, NarxCommittee)):
            raise ValueError("baseline must be a NarxModel or NarxCommittee, got "
                             f"{type(baseline).__name__}")
        if not dt_s > 0:
            raise ValueError(f"dt_s must be > 0, got {dt_s}")
        self.baseline = baseline
        self.effects = list(effects)
        self.dt_s = float(dt_s)

    @property
    def max_lag_(self) -> int:
        return int(getattr(self.baseline, "max_lag_", 0))

    @property
    def effect_names(self) -> list[str]:
        return [e.name for e in self.effects]

    def _inputs(self):
        # channel blocks last: they read the voltage the other input effects give
        ins = [e for e in self.effects if e.side == "input"]
        return ([e for e in ins if e.name not in CHANNEL_BLOCKS]
                + [e for e in ins if e.name in CHANNEL_BLOCKS])

    def _outputs(self):
        return [e for e in self.effects if e.side == "output"]

    def _context(self, u, u_past, t0_s):
        u = as_signal("u", u, min_length=self.max_lag_ + 1)
        past = np.zeros(0) if u_past is None else as_signal("u_past", u_past)
        ua = np.concatenate([past, u])
        ta = float(t0_s) + (np.arange(ua.size) - past.size) * self.dt_s
        return u, ua, ta, past.size

    def to_baseline_space(self, u, y=None, *, u_past=None, t0_s: float = 0.0):
        """The data as the baseline sees it: (v, z) with v (N,) or (N, c) and z (N,) or None."""
        u, ua, ta, n0 = self._context(u, u_past, t0_s)
        v = ua
        for e in self._inputs():
            v = e.apply_input(v, self.dt_s)
        z = None
        if y is not None:
            y = as_signal("y", y)
            same_length(u=u, y=y)
            za = np.concatenate([np.zeros(n0), y])
            for e in reversed(self._outputs()):
                za = e.backward(za, ua, ta, self.dt_s)
            z = za[n0:]
        return v[n0:], z

    def _from_baseline_space(self, z, u, u_past, t0_s):
        u, ua, ta, n0 = self._context(u, u_past, t0_s)
        ya = np.concatenate([np.zeros(n0), z])
        for e in self._outputs():
            ya = e.forward(ya, ua, ta, self.dt_s)
        return ya[n0:]

    def simulate(self, u, y_init=None, *, u_past=None, t0_s: float = 0.0,
                 cache: FreeRunCache | None = None) -> np.ndarray:
        """Free-run simulation (mm) from the input ``u`` (N,) (V).

        Parameters
        ----------
        u : array_like, shape (N,)
            Input (V).
        y_init : array_like, shape (max_lag_,), optional
            Measured first outputs (mm), as :meth:`NarxModel.simulate`; default rest.
        u_past : array_like, optional
            Input before ``u`` (V), oldest first: warms the creep state and delay line.
        t0_s : float
            Time of ``u[0]`` since the start of the identification record (drift).
        cache : FreeRunCache, optional
            Of this model's baseline: a baseline input run before is looked up, not run again
            (for fits that score many blocks around one baseline kept as it is).
        """
        if cache is not None and cache.model is not self.baseline:
            raise ValueError("cache must be a FreeRunCache of this model's baseline")
        v, _ = self.to_baseline_space(u, u_past=u_past, t0_s=t0_s)
        z_init = None
        L = self.max_lag_
        if y_init is not None and L:
            yi = np.atleast_1d(np.asarray(y_init, dtype=float))
            if yi.shape != (L,) or not np.all(np.isfinite(yi)):
                raise ValueError(f"y_init must be {L} finite values (max lag), got {yi.shape}")
            uu, ua, ta, n0 = self._context(u, u_past, t0_s)
            za = np.concatenate([np.zeros(n0), yi, np.zeros(uu.size - L)])
            for e in reversed(self._outputs()):
                za = e.backward(za, ua, ta, self.dt_s)
            z_init = za[n0 : n0 + L]
        z = (self.baseline if cache is None else cache).simulate(v, z_init)
        return self._from_baseline_space(z, u, u_past, t0_s)

    def predict(self, u, y, *, u_past=None, t0_s: float = 0.0) -> np.ndarray:
        """One-step-ahead prediction (mm) from input ``u`` and measured output ``y``."""
        v, z = self.to_baseline_space(u, y, u_past=u_past, t0_s=t0_s)
        zh = self.baseline.predict(v, z)
        return self._from_baseline_space(zh, u, u_past, t0_s)

    @classmethod
    def identify(cls, narx: NarxModel, u, y, effects=(), dt_s: float = 0.01) -> AugmentedModel:
        """Fit ``narx`` (unfitted template) with fixed ``effects`` on a record (u V, y mm)
        starting at t = 0; returns the fitted model."""
        return cls(narx, effects, dt_s).refit(narx, u, y)

    def refit(self, narx: NarxModel, u, y, effects=None) -> AugmentedModel:
        """A new model: ``effects`` (default these) and ``narx`` (unfitted) fitted on (u, y)
        seen through them. The record starts at t = 0."""
        m = AugmentedModel(self.baseline, self.effects if effects is None else effects,
                           self.dt_s)
        v, z = m.to_baseline_space(u, y)
        nx = copy.deepcopy(narx)
        n_ch = 1 if v.ndim == 1 else v.shape[1]
        if n_ch > 1:
            chans = [e.name for e in m._inputs() if e.name in CHANNEL_BLOCKS]
            for one in members_of(nx):
                one.input_lags = _channel_lags(one.input_lags, n_ch, chans)
        m.baseline = nx.fit(v, z)
        return m

    # -- step by step --
    def stepper(self, t0_s: float = 0.0) -> AugmentedStepper:
        """Sample-by-sample free-run predictor from rest; see :class:`AugmentedStepper`."""
        return AugmentedStepper(self, t0_s)

    def fit_inverse(self, u, y, inverse: InverseNarxModel | None = None) -> InverseNarxModel:
        """Fit an inverse NARX (Eq. 19) of the baseline in its own space (v, z) from the
        record (u V, y mm) the model was identified on; for :meth:`inverse_stepper`."""
        if any(e.name == "delay" or e.is_channel for e in self.effects):
            raise ValueError("a model with delay, rate_dependence or memory cannot be inverted "
                             "step by step")
        v, z = self.to_baseline_space(u, y)
        inv = InverseNarxModel() if inverse is None else copy.deepcopy(inverse)
        return inv.fit(v, z)

    def inverse_stepper(self, inverse: InverseNarxModel, t0_s: float = 0.0, *,
                        y_history=None, u_history=None) -> AugmentedInverseStepper:
        """Feedforward compensator ``step(y_desired_mm) -> u_v``; see
        :class:`AugmentedInverseStepper`."""
        return AugmentedInverseStepper(self, inverse, t0_s, y_history=y_history,
                                       u_history=u_history)

    def feedforward_part(self) -> tuple[AugmentedModel, dict[str, str]]:
        """The model with the effects a feedforward can undo step by step, and the others
        with why each is left out (:data:`FEEDFORWARD_LEAVES_OUT`)."""
        kept, left = [], {}
        for e in self.effects:
            if e.name in ("drift", "delay") or e.is_channel:
                left[e.name] = FEEDFORWARD_LEAVES_OUT[e.name]
            else:
                kept.append(e)
        return AugmentedModel(self.baseline, kept, self.dt_s), left


class AugmentedStepper:
    """The augmented model one sample at a time: ``step(u_k) -> y_k`` (V -> mm), free run."""

    def __init__(self, model: AugmentedModel, t0_s: float = 0.0):
        self._m = model
        self._in = [e.runner(model.dt_s) for e in model._inputs()]
        self._out = [e.runner(model.dt_s) for e in model._outputs()]
        self._base = model.baseline.stepper()
        self._k = 0
        self._t0 = float(t0_s)

    def step(self, u_k: float) -> float:
        t_k = self._t0 + self._k * self._m.dt_s
        v = float(u_k)
        for r in self._in:
            v = r.apply(v)
        y = self._base.step(np.asarray(v, dtype=float))
        for r in self._out:
            y = r.forward(y, t_k)
        for r in self._out:
            r.push(float(u_k))
        self._k += 1
        return y


class AugmentedInverseStepper:
    """Feedforward voltage from the inverse of an augmented model, one sample at a time.

    ``step(y_desired_mm) -> u_v``: the output effects are removed from the desired displacement
    with the state known before u_k (creep: z_d = y_d - c_k), the baseline inverse gives the
    baseline-space input, the input effects' inverse maps give u_k. Unless told otherwise
    (``record_applied``), u_k is taken as applied when the next step starts, which advances the
    creep state.

    Parameters
    ----------
    model : AugmentedModel
    inverse : InverseNarxModel
        Fitted by :meth:`AugmentedModel.fit_inverse` (baseline space).
    t0_s : float
        Time of the first step since the identification record's start (drift).
    y_history, u_history : array_like, optional
        Past desired displacements (mm) and applied voltages (V), oldest first, of equal
        length: the stepper goes on from them (a model server's reload) instead of from rest.
        The effects' states are run through them, and the inverse is given them in the
        baseline's space. A creep state older than the history is not known
        (:attr:`AugmentedInverse.history_samples` says how much is enough).
    """

    def __init__(self, model: AugmentedModel, inverse: InverseNarxModel, t0_s: float = 0.0,
                 *, y_history=None, u_history=None):
        for e in model.effects:
            if e.name == "delay" or e.is_channel:
                raise ValueError(f"the {e.name} effect cannot be inverted step by step")
        self._m = model
        self._in = [e.runner(model.dt_s) for e in model._inputs()]
        self._out = [e.runner(model.dt_s) for e in model._outputs()]
        self._k = 0
        self._t0 = float(t0_s)
        self._pending: tuple[float, float] | None = None  # (u applied, v returned)
        if y_history is None and u_history is None:
            self._inv = inverse.stepper()
            return
        yh, uh = as_signal("y_history", y_history), as_signal("u_history", u_history)
        same_length(y_history=yh, u_history=uh)
        n = yh.size
        self._t0 -= n * model.dt_s  # the history ends where t0_s starts
        # What step() and _commit() do to each sample, without the inverse's kernel rows: the
        # inverse's own state comes from its history at once (a creep of minutes needs
        # tens of thousands of samples).
        z, v = np.empty(n), np.empty(n)
        for k, (y_k, u_k) in enumerate(zip(yh, uh, strict=True)):
            z[k] = self._baseline_target(y_k, self._t0 + k * model.dt_s)
            v[k] = self._baseline_input(u_k)
            if k < n - 1:
                self._push(u_k)
        # the last sample stays pending, as a live step's: record_applied may still correct it
        self._k = n - 1
        self._pending = (float(uh[-1]), float(v[-1]))
        self._inv = inverse.stepper(z, v)

    def _baseline_target(self, y_mm: float, t_k: float) -> float:
        """The displacement the baseline must give (mm): the output effects removed, with
        their state known before this sample's voltage."""
        for r in reversed(self._out):
            y_mm = r.backward(y_mm, t_k)
        return y_mm

    def _baseline_input(self, u_v: float) -> float:
        """The baseline's input (V) for an applied voltage: the input effects' maps."""
        for r in self._in:
            u_v = r.apply(u_v)
        return u_v

    def _push(self, u_v: float) -> None:
        """Advance the output effects' states by an applied voltage (V)."""
        for r in self._out:
            r.push(u_v)

    def _commit(self) -> None:
        if self._pending is None:
            return
        u, v_returned = self._pending
        v = self._baseline_input(u)
        if v != v_returned:
            self._inv.record_applied(v)
        self._push(u)
        self._k += 1
        self._pending = None

    def step(self, y_desired_mm: float) -> float:
        """Desired displacement (mm) -> feedforward voltage (V)."""
        self._commit()
        z = self._baseline_target(float(y_desired_mm), self._t0 + self._k * self._m.dt_s)
        v = self._inv.step(z)
        u = v
        for r in reversed(self._in):
            u = r.invert(u)
        self._pending = (u, v)
        return u

    def record_applied(self, u_applied_v: float) -> None:
        """The voltage that really reached the actuator at the last step (V)."""
        if self._pending is not None:
            self._pending = (float(u_applied_v), self._pending[1])


class AugmentedInverse:
    """The feedforward of an augmented model: the baseline's inverse NARX, fitted in the
    baseline's space, with the model's effects undone around it step by step.

    What ``ipmc identify --inverse --effects-from MODEL`` writes, and ``ipmc track`` and
    model_server serve as an inverse model: ``stepper(y_history, u_history)`` gives
    ``step(y_desired_mm) -> u_v`` and ``record_applied(u_v)``. Effects that cannot be undone
    step by step (drift, delay, the channel blocks) are left out (``left_out``), the others
    kept (``feedforward_model``): creep and the output form of rate dependence subtract their
    state, dead zone, asymmetry and saturation invert their static maps.

    Parameters
    ----------
    model : AugmentedModel
        The whole augmented model (``ipmc diagnose``'s ``model_after.json``).
    inverse : InverseNarxModel
        Fitted on ``feedforward_model.to_baseline_space(u, y)`` (voltages from displacements in
        the baseline's space).
    """

    def __init__(self, model: AugmentedModel, inverse: InverseNarxModel):
        if not isinstance(inverse, InverseNarxModel):
            raise ValueError(f"inverse must be an InverseNarxModel, got {type(inverse).__name__}")
        self.model, self.inverse = model, inverse
        self.feedforward_model, self.left_out = model.feedforward_part()

    @property
    def dt_s(self) -> float:
        return self.model.dt_s

    @property
    def max_lag_(self) -> int:
        return self.inverse.max_lag_

    @property
    def history_samples(self) -> int:
        """Past samples a stepper going on from a history needs (a model server keeps as
        many): the inverse's, and :data:`~ipmc_model.narx.HISTORY_TAUS` of the longest time
        constant among the effects it undoes (a creep's)."""
        taus = [e.params["tau_s"] for e in self.feedforward_model.effects if "tau_s" in e.params]
        return samples_to_settle(self.inverse.history_samples, taus, self.dt_s)

    @property
    def effect_names(self) -> list[str]:
        """The effects the feedforward undoes."""
        return self.feedforward_model.effect_names

    def stepper(self, y_history=None, u_history=None, t0_s: float = 0.0
                ) -> AugmentedInverseStepper:
        """Sample-by-sample compensator from rest, or going on from a history (desired mm,
        applied V, oldest first); see :class:`AugmentedInverseStepper`."""
        return self.feedforward_model.inverse_stepper(self.inverse, t0_s, y_history=y_history,
                                                      u_history=u_history)

    def _run(self, y, u_known) -> np.ndarray:
        """Step through ``y`` (mm); the first ``len(u_known)`` voltages applied are those (V)."""
        s, out = self.stepper(), np.empty(y.size)
        for k, y_k in enumerate(y):
            out[k] = s.step(y_k)
            if k < u_known.size:
                s.record_applied(u_known[k])
        return out

    def simulate(self, y_desired, u_init=None) -> np.ndarray:
        """Free-run compensator: voltages (V) for a desired trajectory (mm), from rest. As the
        inverse NARX's, entries ``[:max_lag_]`` are ``u_init`` (V, default zeros): the voltages
        applied first."""
        L = self.max_lag_
        y = as_signal("y_desired", y_desired, min_length=L + 1)
        u0 = np.zeros(L) if u_init is None else as_signal("u_init", u_init, min_length=0)
        if u0.size != L:
            raise ValueError(f"u_init must be {L} values (max lag), got {u0.size}")
        out = self._run(y, u0)
        out[:L] = u0
        return out

    def predict(self, y, u) -> np.ndarray:
        """One-step compensator: the voltage (V) for each displacement ``y`` (mm), the measured
        voltages ``u`` (V) taken as applied before it (the effects' states and the history)."""
        y, u = as_signal("y", y), as_signal("u", u)
        same_length(y=y, u=u)
        return self._run(y, u)


# -- persistence --
def save_augmented(model: AugmentedModel | AugmentedInverse, path, *,
                   metadata: dict | None = None) -> Path:
    """Save an augmented model: ``path`` (JSON: effects, dt_s) and its baseline as a plain
    model file beside it (``<stem>.baseline.json`` + ``.npz``, readable by ``load_model``).

    An :class:`AugmentedInverse` is saved as its whole model, plus its inverse as a plain
    model file (``<stem>.inverse.json`` + ``.npz``) and the effects it leaves out
    (``kind`` ``augmented-lssvm-narx-inverse``; :func:`load_augmented` still reads the
    forward model from it).

    Returns the JSON path written.
    """
    ff = model if isinstance(model, AugmentedInverse) else None
    model = ff.model if ff is not None else model
    path = Path(path)
    if path.suffix != ".json":
        path = path.with_name(path.name + ".json")
    base_path = save_model(model.baseline, path.with_name(path.stem + ".baseline.json"),
                           metadata={"role": "baseline of an augmented model"})
    doc = {
        "format": AUGMENTED_FORMAT,
        "format_version": AUGMENTED_FORMAT_VERSION,
        "kind": "augmented-lssvm-narx" if ff is None else AUGMENTED_INVERSE_KIND,
        "units": {"input": "V", "output": "mm", "time": "s"},
        "dt_s": model.dt_s,
        "baseline_file": base_path.name,
        "effects": [e.as_dict() for e in model.effects],
        "metadata": metadata or {},
    }
    if ff is not None:
        inv_path = save_model(ff.inverse, path.with_name(path.stem + ".inverse.json"),
                              metadata={"role": "inverse of an augmented model's baseline, in "
                                                "its baseline space"})
        doc["inverse_file"] = inv_path.name
        doc["feedforward_left_out"] = dict(ff.left_out)
    doc[DOCUMENT_CHECKSUM] = document_sha256(json.loads(json.dumps(doc)))
    write_atomic({path: json.dumps(doc, indent=2) + "\n"})
    return path


def _read_json(path: Path):
    """The JSON document of a model file; ``ModelFileError`` if there is none."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise ModelFileError(f"{path}: no such model file.") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        raise ModelFileError(f"{path}: not a model file (not readable JSON).") from None


def _augmented_from(path: Path, doc: dict) -> AugmentedModel:
    """The augmented model of the document ``doc`` read from ``path``."""
    if not isinstance(doc.get("format_version"), int) or \
            doc["format_version"] > AUGMENTED_FORMAT_VERSION:
        raise ModelFileError(f"{path}: unsupported augmented format version "
                             f"{doc.get('format_version')!r}.")
    if (doc["format_version"] >= 2 or DOCUMENT_CHECKSUM in doc) \
            and doc.get(DOCUMENT_CHECKSUM) != document_sha256(doc):
        raise ModelFileError(f"{path}: the model file was changed or corrupted after it was "
                             "written (the checksum of its JSON document differs).")
    try:
        base = load_model(path.parent / doc["baseline_file"])
        effects = [Effect(e["name"], **e["params"]) for e in doc["effects"]]
        m = AugmentedModel(base, effects, float(doc["dt_s"]))
    except (KeyError, TypeError) as exc:
        raise ModelFileError(f"{path}: corrupt augmented model ({exc!r}).") from None
    m.metadata_ = doc.get("metadata", {})
    return m


def load_augmented(path, dt_s: float | None = None) -> AugmentedModel:
    """Load a model file as an :class:`AugmentedModel`.

    An augmented model file gives its baseline and effects; a plain ``lssvm-narx`` file
    (``ipmc identify``) gives a model without effects (``dt_s`` from the argument, its
    metadata's ``rate_hz``, or 0.01 s). Anything else raises ``ModelFileError``.
    """
    path = Path(path)
    doc = _read_json(path)
    if isinstance(doc, dict) and doc.get("format") == AUGMENTED_FORMAT:
        return _augmented_from(path, doc)
    read_model_document(path)  # raises ModelFileError with the reason if not a model file
    base = load_model(path)
    if not isinstance(base, (NarxModel, NarxCommittee)):
        raise ModelFileError(f"{path}: a {type(base).__name__} cannot be a baseline here; "
                             "give an lssvm-narx forward model.")
    if dt_s is None:
        rate = base.metadata_.get("rate_hz")
        dt_s = 1.0 / float(rate) if rate else 0.01
    m = AugmentedModel(base, (), dt_s)
    m.metadata_ = base.metadata_
    return m


def check_rate(model: AugmentedModel, dt_s: float) -> AugmentedModel:
    """``model``, if its sample period is the record's ``dt_s`` (s) within 1 %; a ValueError
    naming both rates otherwise (the effects' states and the lags count samples)."""
    if abs(model.dt_s - dt_s) > 0.01 * dt_s:
        raise ValueError(f"the model was identified at {1 / model.dt_s:.4g} Hz, the data are "
                         f"at {1 / dt_s:.4g} Hz")
    return model


def load_augmented_inverse(path, doc: dict | None = None) -> AugmentedInverse:
    """Load the feedforward of an augmented model (``ipmc identify --inverse --effects-from``;
    ``doc``: its JSON document, if already read); ``ModelFileError`` naming the file if it
    holds none."""
    path = Path(path)
    doc = _read_json(path) if doc is None else doc
    if not isinstance(doc, dict) or doc.get("format") != AUGMENTED_FORMAT:
        raise ModelFileError(f"{path}: not an augmented model file.")
    if doc.get("kind") != AUGMENTED_INVERSE_KIND:
        raise ModelFileError(f"{path}: an augmented model without a feedforward; make one "
                             "with 'ipmc identify --model lssvm-narx --inverse "
                             f"--effects-from {path.name} --data RECORD'.")
    model = _augmented_from(path, doc)
    try:
        inverse = load_model(path.parent / doc["inverse_file"])
    except (KeyError, TypeError) as exc:
        raise ModelFileError(f"{path}: corrupt augmented inverse ({exc!r}).") from None
    if not isinstance(inverse, InverseNarxModel):
        raise ModelFileError(f"{path}: its inverse_file holds a {type(inverse).__name__}, not "
                             "an inverse model.")
    ff = AugmentedInverse(model, inverse)
    ff.metadata_ = model.metadata_
    return ff


def load_any_model(path, dt_s: float | None = None):
    """Any model file this package writes, for a record sampled every ``dt_s`` (s): an
    augmented one (``ipmc diagnose``'s ``model_after.json``) as :class:`AugmentedModel`, and
    one with a feedforward as :class:`AugmentedInverse`, checked against the rate
    (:func:`check_rate`, unless ``dt_s`` is None); any other as
    :func:`~ipmc_model.persistence.load_model` gives it (NARX, inverse, Prandtl-Ishlinskii)."""
    path = Path(path)
    try:
        doc = _read_json(path)
    except ModelFileError:
        doc = None  # load_model names what is wrong with the file
    if not isinstance(doc, dict) or doc.get("format") != AUGMENTED_FORMAT:
        return load_model(path)
    if doc.get("kind") == AUGMENTED_INVERSE_KIND:
        ff = load_augmented_inverse(path, doc)
        if dt_s is not None:
            check_rate(ff.model, dt_s)
        return ff
    model = _augmented_from(path, doc)
    return model if dt_s is None else check_rate(model, dt_s)
