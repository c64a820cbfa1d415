"""Physical effects that augment a baseline LSSVM-NARX model, and the augmented model itself.

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

Fitting (:func:`fit_effect`): creep and drift are additive/multiplicative terms on the output
of the current model; their parameters come from least squares on its free-run residual on the
fit data (creep: from the residual's drift during input holds, :func:`fit_creep_on_holds`, tau
on a log grid from seconds to minutes, gain in closed form; without holds from the whole
residual), and the baseline is then refitted on the data with the effect removed. The delay
and the dead-zone width come from linear ARX scans on the fit data (:func:`dead_time_test`,
:func:`dead_zone_test`), and the NARX is refitted once through them (a saturation's
:func:`saturation_test` is evidence only: the diagnosis names a limit it finds). The
other effects change what the NARX sees, so the baseline NARX is refitted on the data seen
through the effect (input transformed; saturation: output through artanh) for each value of a
one-dimensional parameter grid, scored by free-run RMSE on an internal validation slice (the
last quarter) of the fit data.

Around a model kept as it is (a model fitted on other data, given to the diagnosis),
:func:`fit_frozen_effect` fits drift, delay, dead zone, asymmetry, saturation or rate
dependence (its output form) as a block without refitting anything: the block is what changed
since the model was fitted. :func:`fit_frozen_creep` does the same for creep, on the drift of
the model's residual during input holds (a record without them cannot tell creep from path
memory, and falls back to :func:`fit_effect`).

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
from scipy.optimize import minimize, minimize_scalar
from scipy.signal import lfilter

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
from .persistence import load_model, read_model_document, save_model

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
AUGMENTED_FORMAT_VERSION = 1
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
    path.write_text(json.dumps(doc, indent=2) + "\n")
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


# -- fitting the effects --
def _free_run_rmse(model: AugmentedModel, u, y, u_past=None, t0_s=0.0) -> float:
    L = model.max_lag_
    return _rmse_after(model.simulate(u, y[:L], u_past=u_past, t0_s=t0_s), y, L)


def _rmse_after(ys: np.ndarray, y: np.ndarray, L: int) -> float:
    """RMSE (mm) of a free run ``ys`` against ``y`` after the first ``L`` samples (inf if the
    run is not finite)."""
    if not np.all(np.isfinite(ys)):
        return float("inf")
    return float(np.sqrt(np.mean((ys[L:] - y[L:]) ** 2)))


def _validate_on_slice(model_fn, effects, u, y, split: float):
    """Fit effects + baseline on the first ``split`` of (u, y), free-run RMSE on the rest."""
    cut = int(round(split * u.size))
    m = model_fn(effects, u[:cut], y[:cut])
    return _free_run_rmse(m, u[cut:], y[cut:], u_past=u[:cut], t0_s=cut * m.dt_s)


def _creep_basis(u, dt_s, tau_s):
    a = math.exp(-dt_s / tau_s)
    return lfilter([0.0, 1.0 - a], [1.0, -a], u)


def cross_fitted_residual(model: AugmentedModel, narx: NarxModel, u, y) -> np.ndarray:
    """Free-run residual (mm) of ``model``'s structure on (u, y), each half predicted by a model
    refitted on the other half (NaN on each half's first ``max_lag_`` samples).

    An in-sample residual hides what a flexible regressor has absorbed (the LSSVM follows part
    of a slow creep on the rows it was fitted on); out of fold it shows what the structure
    cannot explain.
    """
    h = u.size // 2
    dt = model.dt_s
    r = np.full(u.size, np.nan)
    for fit_sl, pred_sl in ((slice(0, h), slice(h, None)), (slice(h, None), slice(0, h))):
        m = model.refit(narx, u[fit_sl], y[fit_sl])
        L = m.max_lag_
        up, yp = u[pred_sl], y[pred_sl]
        t0 = (pred_sl.start or 0) * dt
        past = u[: pred_sl.start] if pred_sl.start else None
        ys = m.simulate(up, yp[:L], u_past=past, t0_s=t0)
        rr = yp - ys
        rr[:L] = np.nan
        r[pred_sl] = rr
    return r


def creep_taus(dt_s: float, duration_s: float, memory_s: float = 0.0, n: int = 20
               ) -> np.ndarray:
    """Creep time constants searched (s): ``n`` values on a log grid from 1 s (or 20 samples,
    or three times the baseline's memory ``memory_s``, whichever is longest) to 10 min, at most
    twice the record.

    Faster relaxation is inside the baseline's lag window, so the baseline models it (the
    plant's own back-relaxation, tau 0.46 s, would otherwise pass as creep)."""
    lo = max(1.0, 20 * dt_s, 3.0 * memory_s)
    return np.geomspace(lo, max(min(600.0, 2.0 * duration_s), 2.0 * lo), int(n))


#: Creep fit on input holds (:func:`fit_creep_on_holds`): each hold's segment starts
#: ``CREEP_HOLD_SKIP_S`` after the input jump. The plant's charging and back-relaxation
#: (tau 0.3 s, 0.46 s) still move the tip by up to 0.33 mm 2 s after a 3 V step and 0.04 mm
#: after 3 s, so each segment also gets its own fast exponential (time constant from
#: ``CREEP_FAST_TAUS_S``, amplitude free per hold) as a nuisance term; the creep is what
#: drifts beyond it, with one tau and gain over all holds.
CREEP_HOLD_SKIP_S = 2.0
#: Shortest usable segment after the skip (s).
CREEP_HOLD_MIN_USE_S = 1.0
#: Time constants (s) of the per-hold fast nuisance exponential (the best one is kept).
CREEP_FAST_TAUS_S = (0.3, 0.5, 0.8)
#: Fewest holds for the hold fit; with fewer the creep is fitted on the whole residual.
CREEP_HOLD_MIN_HOLDS = 3
#: Points of the creep tau grid of the hold fit (log spaced, :func:`creep_taus`).
CREEP_HOLD_TAU_POINTS = 40
#: Bootstrap resamples of the holds for the 95 % intervals of the creep's tau and gain.
CREEP_HOLD_BOOTSTRAP = 400


#: The current model counts as settled in a hold once its prediction stays within this share
#: of the residual's standard deviation of its value at the hold's end
#: (:func:`mask_model_settling`).
MODEL_SETTLED_SHARE = 0.01


def mask_model_settling(r, prediction, u, dt_s: float,
                        min_s: float = CREEP_HOLD_SKIP_S + CREEP_HOLD_MIN_USE_S,
                        share: float = MODEL_SETTLED_SHARE) -> np.ndarray:
    """``r`` with NaN in each input hold (>= ``min_s``) for as long as the model's own
    ``prediction`` still moves: until it stays within ``share`` x std(r) of its value at the
    hold's end.

    The hold fit and test of creep read the residual's movement during a hold as the creep's,
    which needs a model that is constant there. The plain nonlinear FIR is, 1.2 s after the
    jump; a model with the rate channel (``rate_dependence``) was not: its LSSVM answered the
    decaying low-passed rate with up to 0.12 mm of movement 2-3 s after a step, and the creep
    fitted on top of it came out 76 s, -0.37 mm/V (the demo's record; 13.8 s, -0.097 without)."""
    from .residuals import find_holds

    r = np.array(as_signal("r", r, allow_nan=True))
    pred = as_signal("prediction", prediction, allow_nan=True)
    u = as_signal("u", u)
    same_length(r=r, prediction=pred, u=u)
    tol = share * float(np.nanstd(r)) if np.any(np.isfinite(r)) else 0.0
    for s, e in find_holds(u, dt_s, min_s):
        seg = pred[s:e]
        moving = np.flatnonzero(~(np.abs(seg - seg[-1]) <= tol))
        if moving.size:
            r[s:s + moving[-1] + 1] = np.nan
    return r


def drift_removed(model: AugmentedModel, prediction, t_s) -> np.ndarray:
    """``prediction`` (mm) of ``model`` with the model's drift taken off (the drift's
    :meth:`Effect.backward` at the times ``t_s``, s from the start of the model's record): the
    part the input drives, which settles in an input hold. A drift moves the prediction through
    every hold (0.3 mm/min: 0.02 mm in 4 s), so :func:`mask_model_settling` masked nearly every
    hold once a drift was in the model, and a creep beside it went untested."""
    z = as_signal("prediction", prediction, allow_nan=True)
    for e in model.effects:  # a model has at most one drift (fit_effect refuses a second)
        if e.name == "drift":
            z = e.backward(z, None, np.asarray(t_s, dtype=float), model.dt_s)
    return z


def fit_creep_on_holds(r, u, dt_s: float, taus, *, nuisance_tau_s: float | None = None,
                       skip_s: float = CREEP_HOLD_SKIP_S,
                       min_use_s: float = CREEP_HOLD_MIN_USE_S,
                       fast_taus_s=CREEP_FAST_TAUS_S,
                       min_holds: int = CREEP_HOLD_MIN_HOLDS,
                       n_boot: int = CREEP_HOLD_BOOTSTRAP, boot_seed: int = 0) -> dict:
    """Creep tau and gain from the drift of a residual during input holds.

    During a hold of the input (:func:`~ipmc_model.residuals.find_holds`) a baseline with a
    finite input window (the diagnosis's nonlinear FIR) predicts a constant once its window
    has passed, whatever creep it absorbed, so the residual's movement there is the creep's,
    ``c_k - c_mean = g (x_k(tau) - x_mean(tau))`` with x the input low-passed at tau (the
    creep state of unit gain), plus what is left of the plant's own settling. Per hold i, from
    ``skip_s`` after its start, the residual r is projected off a constant and a fast
    exponential ``exp(-(t - t_i) / tau_f)`` (amplitude free per hold; tau_f from
    ``fast_taus_s``), and so are x and the nuisance (the input low-passed at
    ``nuisance_tau_s``, one gain over all holds: the settling slower than one exponential,
    on the plant a +0.01..+0.04 mm/V term at the baseline's 1.2 s memory, which biased tau
    20 s to 23-29 s without it); then the gains are least squares over all holds (closed form)
    for each tau of ``taus``, and (tau, tau_f) the pair of the smallest residual sum of squares.

    The hold levels themselves are not used: they carry path memory (hysteresis) as well.

    Parameters
    ----------
    r : array_like, shape (N,)
        Residual (mm) of the current model; NaN samples are skipped.
    u : array_like, shape (N,)
        Input (V); a hold reaching the end of ``u`` is not used (it continues beyond).
    dt_s : float
        Sample period (s).
    taus : array_like
        Creep time constants searched (s).
    nuisance_tau_s : float, optional
        Time constant (s) of the nuisance low-passed input (default none).

    Returns
    -------
    dict
        ``holds`` (usable G), ``skip_s``, and when G >= ``min_holds``: ``tau_s``,
        ``gain_mm_per_v``, ``at_edge`` (tau is the grid's longest: only g / tau is determined,
        the hold drift looks like a ramp), ``at_short_edge`` (tau is the grid's shortest: the
        drift is not told from the plant's own settling), ``fast_tau_s``, ``nuisance_tau_s``,
        ``nuisance_mm_per_v`` (its gain), ``tau_interval_s`` and ``gain_interval_mm_per_v``
        (95 % intervals from ``n_boot`` bootstrap resamples of the holds, seeded by
        ``boot_seed``; tau's widened by one grid step each way, the gain's to the fitted gains
        over tau's interval), ``tau_bounded`` (the tau interval reaches neither end of the
        grid: the record bounds tau),
        ``segments`` (list of (start, stop) samples), ``oof_state``, an (N,) array: in each
        used hold the creep state (mm) predicted by the fit on the *other* holds (leave one hold
        out; NaN elsewhere), for out-of-sample evidence, and ``profile`` (rows tau_s, gain,
        sse at the best tau_f).
    """
    from .residuals import find_holds, hold_basis

    r = as_signal("r", r, allow_nan=True)
    u = as_signal("u", u)
    same_length(r=r, u=u)
    taus = np.asarray(taus, dtype=float)
    if int(n_boot) < 1:
        raise ValueError(f"n_boot must be at least 1 (bootstrap resamples), got {n_boot}")
    skip = int(round(skip_s / dt_s))
    segs, idxs = [], []
    for s, e in find_holds(u, dt_s, skip_s + min_use_s):
        if e >= u.size:
            continue
        idx = np.arange(s + skip, e)
        idx = idx[np.isfinite(r[idx])]
        if idx.size * dt_s >= min_use_s:
            segs.append((s, e))
            idxs.append(idx)
    G = len(segs)
    out = {"holds": G, "skip_s": float(skip_s)}
    if G < min_holds:
        return out
    bases = [_creep_basis(u, dt_s, tau) for tau in taus]
    nuis = None if nuisance_tau_s is None else _creep_basis(u, dt_s, nuisance_tau_s)
    F, T = len(fast_taus_s), taus.size
    # per hold and tau_f: x'x, x'r (per tau), n'n, n'r, n'x (per tau), r'r after projection
    sxx, sxr, snx = np.zeros((G, F, T)), np.zeros((G, F, T)), np.zeros((G, F, T))
    srr, snn, snr = np.zeros((G, F)), np.zeros((G, F)), np.zeros((G, F))
    for i, ((s, _), idx) in enumerate(zip(segs, idxs, strict=True)):
        X0 = np.column_stack([b[idx] for b in bases])
        for f, tf in enumerate(fast_taus_s):
            Q = hold_basis((idx - s) * dt_s, tf)
            rr = r[idx] - Q @ (Q.T @ r[idx])
            X = X0 - Q @ (Q.T @ X0)
            srr[i, f] = rr @ rr
            sxx[i, f] = np.einsum("ij,ij->j", X, X)
            sxr[i, f] = X.T @ rr
            if nuis is not None:
                nn = nuis[idx] - Q @ (Q.T @ nuis[idx])
                snn[i, f], snr[i, f], snx[i, f] = nn @ nn, nn @ rr, X.T @ nn
    snn_raw = 0.0 if nuis is None else sum(float(nuis[i] @ nuis[i]) for i in idxs)

    def solve(w):
        """Gains (creep g, nuisance h) and SSE for every (tau_f, tau) from the holds weighted
        by ``w`` (G,): 0/1 to leave holds out, counts for a bootstrap resample."""
        a, b, c = (np.tensordot(w, x, axes=1) for x in (sxx, sxr, snx))
        d, e, rr = (np.tensordot(w, x, axes=1) for x in (snn, snr, srr))
        d, e = d[:, None], e[:, None]
        if nuis is None:
            g = np.where(a > 0, b / np.where(a > 0, a, 1.0), 0.0)
            h = np.zeros_like(g)
        else:
            det = a * d - c * c
            # a nuisance the per-hold exponential has taken (nearly) whole is left out
            ok = (d > 1e-9 * snn_raw) & (det > 1e-8 * np.maximum(a * d, 1e-300))
            g_alone = np.where(a > 0, b / np.where(a > 0, a, 1.0), 0.0)
            g = np.where(ok, (d * b - c * e) / np.where(ok, det, 1.0), g_alone)
            h = np.where(ok, (a * e - c * b) / np.where(ok, det, 1.0), 0.0)
        sse = rr[:, None] - g * b - h * e
        f, t = np.unravel_index(int(np.argmin(sse)), sse.shape)
        return f, t, g, h, sse

    f, t, g, h, sse = solve(np.ones(G))
    oof = np.full(u.size, np.nan)
    for i, (s, e) in enumerate(segs):
        keep = np.ones(G)
        keep[i] = 0.0
        fi, ti, gi, _, _ = solve(keep)
        oof[s:e] = gi[fi, ti] * bases[ti][s:e]
    # Holds resampled whole (a cluster bootstrap): samples within a hold are correlated, and
    # holds are what the record has few of. Each tau end moves out by one grid step: tau is
    # resolved to the grid, and every resample can land on one point.
    rng = np.random.default_rng(boot_seed)
    boot_t, boot_g = np.empty(int(n_boot), int), np.empty(int(n_boot))
    for j in range(int(n_boot)):
        fb, tb, gb, _, _ = solve(np.bincount(rng.integers(0, G, G), minlength=G).astype(float))
        boot_t[j], boot_g[j] = tb, gb[fb, tb]
    t_lo, t_hi = np.percentile(boot_t, [2.5, 97.5], method="inverted_cdf").astype(int)
    t_lo, t_hi = max(t_lo - 1, 0), min(t_hi + 1, T - 1)
    # the gain trades with tau: its interval also spans the fit's gains over tau's interval
    g_lo, g_hi = np.percentile(boot_g, [2.5, 97.5])
    g_prof = g[f, t_lo:t_hi + 1]
    out.update(tau_s=float(taus[t]), gain_mm_per_v=float(g[f, t]), at_edge=bool(t == T - 1),
               at_short_edge=bool(t == 0), fast_tau_s=float(fast_taus_s[f]),
               nuisance_tau_s=None if nuis is None else float(nuisance_tau_s),
               nuisance_mm_per_v=float(h[f, t]), segments=segs, oof_state=oof,
               tau_interval_s=[float(taus[t_lo]), float(taus[t_hi])],
               tau_bounded=bool(0 < t_lo and t_hi < T - 1),
               gain_interval_mm_per_v=[float(min(g_lo, g_prof.min())),
                                       float(max(g_hi, g_prof.max()))],
               profile=np.column_stack([taus, g[f], sse[f]]))
    return out


def _creep_on_hold_drift(model: AugmentedModel, r, prediction, u, t):
    """The creep fitted on the drift of the residual ``r`` (mm) during the input holds, where
    the model's ``prediction`` (mm) has stopped moving (a rate channel or a drift keeps it
    moving: :func:`mask_model_settling`, :func:`drift_removed`).

    Returns (the masked residual, the hold fit of :func:`fit_creep_on_holds`, the creep
    ``Effect`` with ``fit_residual_`` and ``hold_fit_``, or None with too few holds)."""
    dt = model.dt_s
    mem = max(model.max_lag_ * dt, 2 * dt)
    r = mask_model_settling(r, drift_removed(model, prediction, t), u, dt)
    hold = fit_creep_on_holds(r, u, dt, creep_taus(dt, u.size * dt, mem, CREEP_HOLD_TAU_POINTS),
                              nuisance_tau_s=mem)
    if "tau_s" not in hold:
        return r, hold, None
    eff = Effect("creep", tau_s=hold["tau_s"], gain_mm_per_v=hold["gain_mm_per_v"])
    eff.fit_residual_ = r
    eff.hold_fit_ = hold
    return r, hold, eff


def _fit_creep(model, narx, u, y, t, iterations):
    """Creep from the cross-fitted free-run residual r of the current structure (each half
    predicted by the structure refitted on the other half: the LSSVM has not absorbed the
    creep there), kept on the effect as ``fit_residual_`` for the time-behaviour evidence
    (:func:`~ipmc_model.residuals.hold_drift_test`).

    With at least :data:`CREEP_HOLD_MIN_HOLDS` input holds, tau and gain come from the drift
    of r during the holds (:func:`fit_creep_on_holds`), where the creep is the only thing still
    moving: on the whole residual the baseline's path memory (hysteresis), which a low-passed
    input imitates, led the fit (tau at the grid's end, gain 2-5 x the plant's). The fit is kept
    on the effect as ``hold_fit_`` (its ``oof_state`` gives the leave-one-hold-out prediction).

    Without holds (fallback, the previous method): ``iterations`` + 1 times, tau by a log grid
    from seconds to minutes and the gain by least squares on the whole r (an intercept and the
    input low-passed at the baseline's memory, its own misfit at that time scale, as nuisance
    terms), alternated with the baseline fitted on y minus the current creep.

    Either way the baseline is then refitted on the data with the creep removed."""
    from .residuals import find_holds

    dt = model.dt_s
    mem = max(model.max_lag_ * dt, 2 * dt)
    first_residual = cross_fitted_residual(model, narx, u, y)
    # The two halves' residuals come from two models, whose constant outputs in a hold differ:
    # a hold across the halves' boundary jumps within (0.1-0.3 mm, against a creep drift of
    # hundredths), and that one hold moved the fitted tau from 16 s to 67 s on a plant record.
    h = u.size // 2
    for s, e in find_holds(u, dt, CREEP_HOLD_SKIP_S + CREEP_HOLD_MIN_USE_S):
        if s < h < e:
            first_residual[s:e] = np.nan
    first_residual, hold, eff = _creep_on_hold_drift(model, first_residual,
                                                     y - first_residual, u, t)
    if eff is not None:
        return model.refit(narx, u, y, model.effects + [eff]), eff
    nuis = _creep_basis(u, dt, mem)
    taus = creep_taus(dt, u.size * dt, mem)
    bases = [_creep_basis(u, dt, tau) for tau in taus]
    cur = model
    eff = None
    for _ in range(int(iterations) + 1):
        if eff is None:
            r = first_residual
        else:  # y - out-of-fold baseline part
            r = cross_fitted_residual(cur, narx, u, y) + eff.creep_state(u, dt)
        ok = np.isfinite(r)
        best = None
        for tau, xb in zip(taus, bases, strict=True):
            A = np.column_stack([xb[ok], nuis[ok], np.ones(int(ok.sum()))])
            coef, *_ = np.linalg.lstsq(A, r[ok], rcond=None)
            sse = float(np.sum((r[ok] - A @ coef) ** 2))
            if best is None or sse < best[0]:
                best = (sse, tau, coef[0])
        eff = Effect("creep", tau_s=float(best[1]), gain_mm_per_v=float(best[2]))
        cur = AugmentedModel(model.baseline, model.effects + [eff], dt)
    eff.fit_residual_ = first_residual
    eff.hold_fit_ = hold
    return model.refit(narx, u, y, model.effects + [eff]), eff


def fit_frozen_creep(model: AugmentedModel, u, y, *,
                     cache: FreeRunCache | None = None) -> tuple[AugmentedModel, Effect]:
    """Creep around a model kept as it is (a model given to the diagnosis, fitted on other
    data), from the drift of its free-run residual during input holds.

    As :func:`_fit_creep` on holds, without its cross-fitting or refit: the given model was
    fitted elsewhere, so its free run on (u, y) is out of sample already. The residual is
    blanked where the model itself still moves in a hold (:func:`mask_model_settling`); tau and
    gain come from :func:`fit_creep_on_holds`, and the block is the creep output term
    ``y = z + c`` appended to ``model`` (same baseline object).

    Raises ``ValueError`` when the record has fewer usable holds than the hold fit needs
    (:data:`CREEP_HOLD_MIN_HOLDS`): without holds a creep is not told from path memory, and
    around a given model nothing else could fit it without a refit.

    Returns
    -------
    (AugmentedModel, Effect)
        As :func:`fit_frozen_effect`; the effect also carries ``fit_residual_`` (the masked
        residual, mm) and ``hold_fit_`` (the hold fit) for the diagnosis's hold test.
    """
    if "creep" in model.effect_names:
        raise ValueError("the model already has the creep effect")
    u = as_signal("u", u)
    y = as_signal("y", y)
    same_length(u=u, y=y)
    dt = model.dt_s
    L = model.max_lag_
    if cache is None:
        cache = FreeRunCache(model.baseline)
    z = model.simulate(u, y[:L], cache=cache)
    r = y - z
    r[:L] = np.nan
    _, hold, eff = _creep_on_hold_drift(model, r, z, u, np.arange(u.size) * dt)
    if eff is None:
        raise ValueError(f"no creep around the given model: {hold['holds']} usable input "
                         f"hold(s), the hold fit needs {CREEP_HOLD_MIN_HOLDS}")
    out = AugmentedModel(model.baseline, model.effects + [eff], dt)
    eff.frozen_ = {"fit_rmse_mm": _rmse_after(out.simulate(u, y[:L], cache=cache), y, L),
                   "fit_rmse_before_mm": _rmse_after(z, y, L)}
    return out, eff


def _fit_drift(model, narx, u, y, t, iterations):
    """Drift by backfitting on the in-sample residual: alternately (a) the baseline is fitted
    on the data with the current drift removed and simulated on the fit input (z), and
    (b) y - z is regressed on z t, t, z and an intercept (least squares; z and the intercept,
    the mean gain and offset the baseline takes up by itself, are not kept) to give gain loss
    and offset per minute.

    In sample is right here (unlike creep): a time trend is not a function of the input
    window, so the NARX cannot absorb it; a cross-fitted residual is wrong for drift, because
    each half's model has learned the other half's mean drift and the residual jumps between
    the halves. ``iterations`` + 2 passes (the first from the model as given)."""
    dt = model.dt_s
    mins = t / 60.0
    eff = None
    cur = model
    for _ in range(int(iterations) + 2):
        if eff is not None:
            cur = model.refit(narx, u, y, model.effects + [eff])
        L = cur.max_lag_
        yy = cur.simulate(u, y[:L])
        # z: the prediction without the drift being fitted (backward of this drift only)
        z = yy if eff is None else eff.backward(yy, u, t, dt)
        eff = _drift_on_residual(z, y, mins, L)
    return model.refit(narx, u, y, model.effects + [eff]), eff


def _drift_on_residual(z, y, mins, skip: int) -> Effect:
    """Drift from y - z regressed on z t, t, z and 1 (from sample ``skip``; t in minutes). z and
    1 are nuisance terms, not kept: a baseline fitted on drifting data has the record's mean
    gain and offset, and a model from another day can be off by a constant factor (a dead zone
    lowers the gain); only the change in time is drift."""
    z, y, mins = z[skip:], y[skip:], mins[skip:]
    A = np.column_stack([z * mins, mins, z, np.ones_like(z)])
    coef, *_ = np.linalg.lstsq(A, y - z, rcond=None)
    return Effect("drift", gain_loss_per_min=float(-coef[0]), offset_mm_per_min=float(coef[1]))


def dead_time_test(u, y, dt_s: float, *, max_delay_s: float = 0.5, output_lags: int = 4,
                   input_lags: int = 2) -> dict:
    """Dead time of the record from linear ARX one-step fits (refit-free delay evidence).

    For every candidate dead time nk = 0..K samples (K from ``max_delay_s``) an ARX
    y_k = sum a_i y_{k-i} + sum_j b_j u_{k-nk-j} + c (``output_lags`` a_i, ``input_lags`` b_j,
    least squares, the same rows for every nk) is fitted; the dead time d is the nk of the
    smallest residual sum of squares. A plant without delay answers within the sample
    (d = 0: the simulated IPMC's charging starts at once, so lag 0 carries information no
    later lag has). The evidence is an F test of the ARX with lags 0..d + input_lags - 1
    against the one without lags d..d + input_lags - 1 (i.e. nk = 0): the response after d
    explains the data significantly better than a response from lag 0. ``p_before`` tests the
    other side of a dead time, that nothing responds before it: the same full ARX against the
    one with lags d..d + input_lags - 1 only. A plant's own lag that a smooth input cannot
    tell from a delay (the clean IPMC on a 1 V random sine puts d at 4-8 samples) fails it:
    its response starts at lag 0, only weakly (p_before below 1e-15 on 84 s there).

    Returns
    -------
    dict
        ``delay_samples`` d, ``delay_s``, ``p_value`` (F test; 1.0 when d = 0),
        ``p_before`` (F test of lags 0..d - 1; 1.0 when d = 0), ``rss_ratio``
        RSS(nk = 0) / RSS(nk = d), ``at_edge`` (d = K: no interior minimum).
    """
    from scipy import stats

    u = as_signal("u", u)
    y = as_signal("y", y)
    same_length(u=u, y=y)
    na, nb = int(output_lags), int(input_lags)
    K = max(1, int(round(max_delay_s / dt_s)))
    rows = np.arange(max(na, nb + K), u.size)
    if rows.size < 10 * (na + nb + K):
        raise ValueError(f"too few samples ({u.size}) for a dead-time scan up to {K} samples")
    ys = [y[rows - i] for i in range(1, na + 1)]
    one = np.ones(rows.size)

    def rss(lags):
        X = np.column_stack(ys + [u[rows - j] for j in lags] + [one])
        coef, *_ = np.linalg.lstsq(X, y[rows], rcond=None)
        e = y[rows] - X @ coef
        return float(e @ e), X.shape[1]

    r = [rss(range(nk, nk + nb))[0] for nk in range(K + 1)]
    d = int(np.argmin(r))
    out = {"delay_samples": d, "delay_s": d * float(dt_s), "p_value": 1.0, "p_before": 1.0,
           "rss_ratio": r[0] / r[d] if r[d] > 0 else 1.0, "at_edge": d == K}
    if d > 0:
        r_full, p_full = rss(range(0, d + nb))
        dof = rows.size - p_full

        def p_dropped(r_without: float) -> float:
            # F test of the d input lags that the full ARX has and the other one lacks
            F = ((r_without - r_full) / d) / (r_full / dof) if r_full > 0 else 0.0
            return float(stats.f.sf(F, d, dof))

        out["p_value"] = p_dropped(r[0])
        out["p_before"] = p_dropped(r[d])
    return out


#: Dead-zone scan (:func:`dead_zone_test`): input holds of at least this long (s) are left out
#: of the regression, and the scan refuses a record with less than :data:`DZ_MIN_MOVING_SHARE`
#: of its samples outside such holds.
DZ_HOLD_S = 0.5
DZ_MIN_MOVING_SHARE = 0.5


def _scan_rows(u, y, dt_s: float, first: int, n_par: int):
    """The static-map scans' data: (u, y) checked, the regression rows from ``first`` on that
    lie outside input holds of >= :data:`DZ_HOLD_S` (there the response is the plant's
    settling, not its static map), their share of the record, and whether the scan must
    refuse (fewer than :data:`DZ_MIN_MOVING_SHARE` moving, or fewer than 20 rows per
    parameter of its ``n_par``)."""
    from .residuals import find_holds

    u = as_signal("u", u)
    y = as_signal("y", y)
    same_length(u=u, y=y)
    moving = np.ones(u.size, dtype=bool)
    for a, b in find_holds(u, dt_s, DZ_HOLD_S):
        moving[a:b] = False
    rows = np.arange(first, u.size)
    rows = rows[moving[rows]]
    share = rows.size / u.size
    return u, y, rows, share, bool(share < DZ_MIN_MOVING_SHARE or rows.size < 20 * n_par)


def _input_nuisance(lags_u: list) -> list:
    """The clean IPMC's smooth static input nonlinearities: |u|, u|u|, u^3 at each input lag."""
    return [f for uj in lags_u for f in (np.abs(uj), uj * np.abs(uj), uj ** 3)]


def dead_zone_test(u, y, dt_s: float, *, output_lags: int = 4, input_lags: int = 3,
                   n_widths: int = 25, max_width_share: float = 0.5) -> dict:
    """Dead-zone width of the record from Hammerstein ARX one-step fits (refit-free evidence).

    For every width w on a grid (``n_widths`` values up to ``max_width_share`` of max |u|) an ARX
    y_k = sum_i a_i y_{k-i} + sum_j b_j dz_w(u_{k-j}) + nuisance + c is fitted by least squares,
    dz_w(u) = sign(u) max(|u| - w, 0) (the plant's shift-type dead zone); the width is the w of
    the smallest residual sum of squares, against the same ARX with w = 0 (the raw input).
    The nuisance terms stand for the smooth static nonlinearities a clean IPMC has (its negative
    side stiffens, its positive side saturates softly, and the slopes differ at 0): |u|, u|u|,
    u^3 at each input lag and |y|, y|y| at output lag 1. A dead zone is the one thing they cannot
    make: a *flat* input range around 0 followed by a unit-slope shift.

    Rows inside input holds of >= :data:`DZ_HOLD_S` are left out (there the response is the
    plant's settling, not its static map), and the scan refuses a record with less than
    :data:`DZ_MIN_MOVING_SHARE` of moving samples: a piecewise-constant input (random steps)
    visits a few dozen levels, and any kink between them "fits" (measured: the clean plant's
    step records gave widths of 0.1-1.2 V at p < 1e-3 with all rows).

    Evidence: F test (1 dof) of the ARX at the scanned width against w = 0, Bonferroni-corrected
    for the ``n_widths`` widths tried.

    Returns
    -------
    dict
        ``width_v``, ``p_value`` (corrected; 1.0 when no width beats w = 0), ``rss_ratio``
        RSS(w = 0) / RSS(width), ``at_edge`` (the grid's largest width), ``moving_share``,
        ``refused`` (too few moving samples), ``widths_tested``.
    """
    from scipy import stats

    na, nb = int(output_lags), int(input_lags)
    u, y, rows, share, refuse = _scan_rows(u, y, dt_s, max(na, nb), na + 4 * nb + 3)
    umax = float(np.max(np.abs(u)))
    out = {"width_v": 0.0, "p_value": 1.0, "rss_ratio": 1.0, "at_edge": False,
           "moving_share": float(share), "refused": False, "widths_tested": int(n_widths)}
    if refuse or umax <= 0:
        out["refused"] = True
        return out
    lags_u = [u[rows - j] for j in range(nb)]
    lags_y = [y[rows - i] for i in range(1, na + 1)]
    y1 = y[rows - 1]
    nuisance = _input_nuisance(lags_u) + [np.abs(y1), y1 * np.abs(y1), np.ones(rows.size)]
    target = y[rows]

    def rss(w):
        X = np.column_stack(lags_y + [uj - np.clip(uj, -w, w) for uj in lags_u] + nuisance)
        coef, *_ = np.linalg.lstsq(X, target, rcond=None)
        e = target - X @ coef
        return float(e @ e), X.shape[1]

    r0, n_par = rss(0.0)
    widths = umax * float(max_width_share) * np.arange(1, n_widths + 1) / n_widths
    r = np.array([rss(w)[0] for w in widths])
    d = int(np.argmin(r))
    out.update(width_v=float(widths[d]), rss_ratio=float(r0 / r[d]) if r[d] > 0 else 1.0,
               at_edge=bool(d == n_widths - 1))
    if r[d] < r0:
        dof = rows.size - n_par - 1
        F = (r0 - r[d]) / (r[d] / dof)
        out["p_value"] = float(min(1.0, n_widths * stats.f.sf(F, 1, dof)))
    return out


#: Saturation scan (:func:`saturation_test`): limits tried, as multiples of the record's
#: largest |y| (from one the data nearly reach to one that hardly bends them).
SAT_SCAN_RANGE = (1.01, 3.0)


def saturation_test(u, y, dt_s: float, *, output_lags: int = 4, input_lags: int = 3,
                    n_limits: int = 25) -> dict:
    """Symmetric output limit of the record from Wiener ARX one-step fits (refit-free evidence).

    For every limit L on a log grid (:data:`SAT_SCAN_RANGE` x max |y|, ``n_limits`` values) the
    output is taken back through the plant's soft limit, x = L artanh(y / L), and an ARX
    x_k = sum_i a_i x_{k-i} + sum_j b_j u_{k-j} + nuisance + c is fitted by weighted least
    squares (weights (1 - (y/L)^2)^2: the residual in mm, to first order); its prediction is
    taken forward, L tanh(x / L), and scored in mm against the same ARX with no limit. The
    nuisance terms stand for the clean IPMC's smooth maps (its positive side saturates softly,
    its negative side stiffens): |u|, u|u|, u^3 at each input lag and |x|, x|x|, x^3 at each
    output lag. The cube is what tells a limit from a knee: a limit must flatten the output
    beyond what a cubic bends it (measured, docs/diagnose.md: without the cube, dead-zone,
    asymmetry and drift records at 1.5 V passed as saturated).

    Rows inside input holds and the refusal of a mostly held input: as :func:`dead_zone_test`.
    Evidence: F test (1 dof) of the ARX at the scanned limit against no limit,
    Bonferroni-corrected for the ``n_limits`` limits tried; a limit at either end of the grid is
    no finding (the smallest hugs the data's peak; the largest hardly bends them).

    A limit acts on every excursion that reaches it, so the scan is repeated without the
    *excursion* (a run of rows with one sign of y) whose rows gain the most from the limit:
    ``p_without_top``. On 0.5-1 V records without a limit the scan's p fell below 1e-3 on 13 of
    224, and on none of them without that excursion (docs/diagnose.md, "Saturation: more than
    one excursion").

    Returns
    -------
    dict
        ``limit_mm`` (the scan's limit: on a soft limit the data only reach the knee of, it
        overestimates), ``p_value`` (corrected; 1.0 when no limit beats none), ``rss_ratio``
        RSS(no limit) / RSS(limit), ``at_edge``, ``peak_mm`` (max |y|), ``moving_share``,
        ``refused``, ``limits_tested``, ``p_without_top`` (the scan again without the excursion
        that gains most: corrected p, 1.0 at the grid's edge or when no limit beats none),
        ``excursions`` (their number).
    """
    from scipy import stats

    na, nb = int(output_lags), int(input_lags)
    n_par = 4 * na + 4 * nb + 1
    u, y, rows, share, refuse = _scan_rows(u, y, dt_s, max(na, nb), n_par)
    peak = float(np.max(np.abs(y)))
    out = {"limit_mm": 0.0, "p_value": 1.0, "rss_ratio": 1.0, "at_edge": False,
           "peak_mm": peak, "moving_share": float(share), "refused": False,
           "limits_tested": int(n_limits), "p_without_top": 1.0, "excursions": 0}
    if refuse or peak <= 0:
        out["refused"] = True
        return out
    lags_u = [u[rows - j] for j in range(nb)]
    fixed = lags_u + _input_nuisance(lags_u) + [np.ones(rows.size)]
    target = y[rows]

    def residual(limit, keep):
        """One-step residual (mm) on all rows of the ARX at ``limit`` fitted on rows ``keep``."""
        if np.isfinite(limit):
            q = np.clip(y / limit, -0.999, 0.999)
            x = limit * np.arctanh(q)
            sw = 1.0 - q[rows] ** 2
        else:
            x, sw = y, np.ones(rows.size)
        lags_x = [x[rows - i] for i in range(1, na + 1)]
        X = np.column_stack(lags_x + fixed + [f for xi in lags_x
                                              for f in (np.abs(xi), xi * np.abs(xi), xi ** 3)])
        coef, *_ = np.linalg.lstsq((X * sw[:, None])[keep], (x[rows] * sw)[keep], rcond=None)
        x_hat = X @ coef
        return target - (limit * np.tanh(x_hat / limit) if np.isfinite(limit) else x_hat)

    limits = peak * np.geomspace(*SAT_SCAN_RANGE, n_limits)

    def scan(keep):
        """On rows ``keep``: index of the best limit, RSS without a limit and at it, p, and the
        squared residuals (all rows) without a limit minus at it."""
        e0 = residual(np.inf, keep)
        es = [residual(L, keep) for L in limits]
        r0 = float(e0[keep] @ e0[keep])
        r = np.array([float(e[keep] @ e[keep]) for e in es])
        d = int(np.argmin(r))
        p = 1.0
        if r[d] < r0:
            dof = int(keep.sum()) - n_par - 1
            p = float(min(1.0, n_limits * stats.f.sf((r0 - r[d]) / (r[d] / dof), 1, dof)))
        return d, r0, r[d], p, e0 ** 2 - es[d] ** 2

    d, r0, r_d, p, gain = scan(np.ones(rows.size, dtype=bool))
    out.update(limit_mm=float(limits[d]), rss_ratio=float(r0 / r_d) if r_d > 0 else 1.0,
               at_edge=bool(d in (0, n_limits - 1)), p_value=p)
    # excursions: runs of one sign of y, cut where a hold leaves rows out
    sign = np.sign(y[rows])
    excursion = np.cumsum(np.r_[True, (sign[1:] != sign[:-1]) | (np.diff(rows) > 1)]) - 1
    out["excursions"] = int(excursion[-1] + 1)
    keep = excursion != int(np.argmax(np.bincount(excursion, weights=gain)))
    if keep.sum() > 20 * n_par:
        d2, _, _, p2, _ = scan(keep)
        out["p_without_top"] = p2 if d2 not in (0, n_limits - 1) else 1.0
    return out


def _grid(name, u, y, dt, rate_tau_max_s=np.inf):
    # delay and dead_zone are not here: their value comes from an ARX scan (fit_effect)
    ymax = float(np.max(np.abs(y)))
    if name == "asymmetry":
        return [{"negative_gain_ratio": r} for r in (0.5, 0.67, 0.8, 1.25, 1.5, 2.0)]
    if name == "saturation":
        return [{"limit_mm": f * ymax} for f in (1.03, 1.08, 1.15, 1.3, 1.5, 2.0, 3.0)]
    if name == "rate_dependence":
        return [{"tau_s": ts} for ts in (2 * dt, 0.05, 0.2, 1.0) if ts <= rate_tau_max_s]
    raise ValueError(name)


def _frozen_grid(name: str, u, y, dt_s: float) -> list[float]:
    """Parameter values of a frozen fit (the block's one parameter, physical units)."""
    n = FROZEN_GRID_POINTS
    if name == "delay":  # whole samples up to 0.5 s, at most n of them
        d = np.unique(np.round(np.geomspace(1, max(1.0, 0.5 / dt_s), n)))
        return list(d * dt_s)
    if name == "dead_zone":
        return list(np.linspace(0.0, 0.5 * np.max(np.abs(u)), n + 1)[1:])
    if name == "asymmetry":
        r = np.geomspace(0.5, 2.0, n)
        return list(r[np.abs(np.log(r)) > 1e-3])
    # saturation: from a limit the record's largest displacement nearly reaches, to one that
    # hardly bends it (3 x: tanh(1/3) is 3.6 % below linear)
    return list(np.max(np.abs(y)) * np.geomspace(0.8, 3.0, n))


def fit_frozen_effect(name: str, model: AugmentedModel, u, y, *,
                      window: tuple[int, int] | None = None,
                      cache: FreeRunCache | None = None) -> tuple[AugmentedModel, Effect]:
    """Fit the block ``name`` around ``model`` kept as it is (nothing refitted).

    For a model fitted on other data (a model given to the diagnosis: yesterday's rig, before
    the electrode wore), the block is what changed since. A baseline fitted on this record
    has already absorbed a static input or output map (a nonlinear FIR represents
    dead_zone(u) or tanh(z) through its own inputs), so this fit is for given models.

    Drift (gain loss and offset per minute) is linear around a fixed model: least squares on
    the free-run residual, with a constant gain and offset as nuisance terms (kept out of the
    block: only the change in time is drift). The other blocks' one parameter (delay in whole
    samples up to 0.5 s, dead-zone width up to half of max |u|, negative-gain ratio 0.5-2,
    saturation limit 0.8-3 x max |y|) minimises the free-run RMSE of the augmented model on
    (u, y) (the fit part only) over a grid of :data:`FROZEN_GRID_POINTS` values, refined
    between the best value's neighbours (bounded Brent; not for the delay, in samples; below
    the first dead-zone width the neighbour is 0). A dead zone narrower than half the first
    width is refused: no grid value beats the model as given. Asymmetry is fitted in both its
    forms, the negative voltage scaled (``negative_gain_ratio``) and the negative bending
    scaled (``negative_bending_ratio``), and the form with the lower RMSE is kept: with a
    well-fitted model the bending form gives the plant's ratio, with a poor one the voltage
    form can absorb some of the model's error (docs/diagnose.md, session 27). Rate dependence
    is the output block ``z + g rho`` (the low-passed voltage rate): for each tau (log grid
    from 0.02 s to a third of the model's lag window, then Brent) g by least squares on the
    free-run residual, the model's output and a constant as nuisance terms.

    ``window`` = (start, stop): fit on those samples of (u, y) only; the model still runs over
    all of ``u`` from its start, so its states and the drift's time are those of the record
    (the diagnosis's split-half check, docs/diagnose.md, session 28).

    ``cache``: a :class:`~ipmc_model.narx.FreeRunCache` of ``model.baseline``, to share between
    calls around the same model (the full fit and its halves score the same grid); each call
    makes its own if not given. The static blocks' runs go over the whole of ``u`` through it
    and are scored on the window, which gives the window's own runs exactly (they are causal).

    Returns
    -------
    (AugmentedModel, Effect)
        The model with the effect appended (same baseline object), and the effect, whose
        ``frozen_`` attribute holds the fit (``{"fit_rmse_mm", "fit_rmse_before_mm"}``, on the
        window).
    """
    if name not in FROZEN_EFFECTS:
        raise ValueError(f"{name!r} cannot be fitted around a frozen model; frozen fits: "
                         f"{', '.join(FROZEN_EFFECTS)}")
    if name in model.effect_names:
        raise ValueError(f"the model already has the {name} effect")
    u = as_signal("u", u)
    y = as_signal("y", y)
    same_length(u=u, y=y)
    L = model.max_lag_
    start, stop = (0, u.size) if window is None else (int(window[0]), int(window[1]))
    if not 0 <= start < stop <= u.size or stop - max(start, L) < 2:
        raise ValueError(f"window {window} leaves no samples to fit on (N = {u.size}, "
                         f"max lag {L})")
    skip = max(start, L)
    grid = _frozen_grid(name, u, y, model.dt_s)  # the whole record's: a window changes no grid
    if cache is None:
        cache = FreeRunCache(model.baseline)

    def free_rmse(m: AugmentedModel) -> float:
        # the runs are causal: what follows the window changes nothing in it
        return _rmse_after(m.simulate(u, y[:L], cache=cache)[:stop], y[:stop], skip)

    z = model.simulate(u, y[:L], cache=cache)[:stop]  # the model's run: drift and rate use it
    uw, yw = u[:stop], y[:stop]
    rmse_model = _rmse_after(z, yw, skip)
    if name == "drift":
        # linear around a fixed model: the backfit's first pass, nothing refitted (without the
        # constant gain as nuisance a stale model passed a drift of +42 % on a dead-zone record)
        eff = _drift_on_residual(z, yw, np.arange(stop) * model.dt_s / 60.0, skip)
        out = AugmentedModel(model.baseline, model.effects + [eff], model.dt_s)
        eff.frozen_ = {"fit_rmse_mm": free_rmse(out), "fit_rmse_before_mm": rmse_model}
        return out, eff
    if name == "rate_dependence":
        return _fit_frozen_rate(model, uw, yw, z, rmse_model, skip)
    # asymmetry has two physical forms, the negative voltage or the negative bending scaled;
    # the one that fits the fit part better is kept (docs/diagnose.md, session 27)
    keys = ((Effect._KEYS[name][0], Effect._OUTPUT_KEYS[name][0]) if name == "asymmetry"
            else (Effect._KEYS[name][0],))
    fits = []
    for key in keys:
        def score(value: float, key=key) -> float:
            m = AugmentedModel(model.baseline, model.effects + [Effect(name, **{key: value})],
                               model.dt_s)
            with np.errstate(all="ignore"):
                return free_rmse(m)

        scores = [score(v) for v in grid]
        i = int(np.argmin(scores))
        best, best_score = float(grid[i]), float(scores[i])
        if best_score < rmse_model and name != "delay" and len(grid) > 2:
            lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
            if name == "dead_zone" and i == 0:  # below the first width lies 0, not the grid's end
                lo = 0.0
            res = minimize_scalar(score, bounds=(lo, hi), method="bounded",
                                  options={"xatol": 1e-3 * (hi - lo)})
            if res.success and res.fun < best_score:
                best, best_score = float(res.x), float(res.fun)
        fits.append((best_score, key, best))
    best_score, key, best = min(fits)
    if not best_score < rmse_model:
        raise ValueError(f"no {name}: the model as given fits the fit part best without it "
                         f"(free-run RMSE {rmse_model:.4g} mm; best {name} "
                         f"{best:.4g} {PARAM_UNITS[key]}: {best_score:.4g} mm)")
    eff = Effect(name, **{key: best})
    eff.frozen_ = {"fit_rmse_mm": best_score, "fit_rmse_before_mm": rmse_model}
    return AugmentedModel(model.baseline, model.effects + [eff], model.dt_s), eff


#: One-parameter static blocks that :func:`refit_frozen_pair` fits two at a time.
PAIR_REFIT_EFFECTS = ("dead_zone", "saturation", "asymmetry")

_NEUTRAL = {"dead_zone": lambda v: 0.0, "asymmetry": lambda v: 1.0,
            "saturation": lambda v: 2.0 * v}


def refit_frozen_pair(model: AugmentedModel, index: int, other: Effect, u, y, *,
                      cache: FreeRunCache | None = None) -> tuple[AugmentedModel, Effect]:
    """Refit the block ``model.effects[index]`` jointly with ``other`` (both one-parameter
    static blocks, :data:`PAIR_REFIT_EFFECTS`), around ``model`` kept as it is otherwise.

    A block fitted alone takes in part of another change that maps the input alike: around a
    stale model with an asymmetry 0.8 and a 0.3 V dead zone, the dead zone alone was fitted at
    0.40-0.54 V, and an asymmetry beside it then gained too little to be added. The two
    parameters minimise the free-run RMSE on (u, y) (the fit part) together: Nelder-Mead
    (SciPy) from the two blocks' values, and from the first moved half way to no effect.
    ``cache``: a :class:`~ipmc_model.narx.FreeRunCache` of ``model.baseline`` (a step that
    moves only an output block reruns no baseline).

    Returns
    -------
    (AugmentedModel, Effect)
        ``model`` with the block replaced by its joint refit (``other`` not added: the caller
        fits and tests it beside the refit), and the refitted block.
    """
    blk = model.effects[index]
    if blk.name not in PAIR_REFIT_EFFECTS or other.name not in PAIR_REFIT_EFFECTS:
        raise ValueError(f"joint refits are for {', '.join(PAIR_REFIT_EFFECTS)}; got "
                         f"{blk.name!r} and {other.name!r}")
    if other.name == blk.name:
        raise ValueError(f"the model already has the {blk.name} effect")
    u = as_signal("u", u)
    y = as_signal("y", y)
    same_length(u=u, y=y)
    (ka, a0), = blk.params.items()
    (kb, b0), = other.params.items()
    L = model.max_lag_

    def build(a: float, b: float) -> AugmentedModel:
        fx = list(model.effects)
        fx[index] = Effect(blk.name, **{ka: a})
        return AugmentedModel(model.baseline, fx + [Effect(other.name, **{kb: b})], model.dt_s)

    def score(p) -> float:
        a, b = float(p[0]), float(p[1])
        for name, v in ((blk.name, a), (other.name, b)):
            if (v < 0 or (name == "asymmetry" and not 0.5 <= v <= 2.0)
                    or (name == "saturation" and v <= 0)):
                return np.inf  # outside the block's physical range
        with np.errstate(all="ignore"):
            r = _rmse_after(build(a, b).simulate(u, y[:L], cache=cache), y, L)
        return r if np.isfinite(r) else np.inf

    best = None
    for start in ((a0, b0), (0.5 * (a0 + _NEUTRAL[blk.name](a0)), b0)):
        res = minimize(score, np.asarray(start, dtype=float), method="Nelder-Mead",
                       options={"xatol": 1e-3, "fatol": 1e-6, "maxiter": 120})
        if best is None or res.fun < best.fun:
            best = res
    if not np.isfinite(best.fun):
        raise ValueError(f"no joint refit of {blk.name} and {other.name}")
    fx = list(model.effects)
    fx[index] = eff = Effect(blk.name, **{ka: float(best.x[0])})
    eff.frozen_ = {"fit_rmse_mm": float(best.fun), "pair_with": other.name}
    return AugmentedModel(model.baseline, fx, model.dt_s), eff


FROZEN_RATE_TAU_MIN_S = 0.02  # the current's low-pass: from a sample or two ...
FROZEN_RATE_WINDOW_SHARE = 1.0 / 3.0  # ... to a third of the model's lag window, as the channel


def _fit_frozen_rate(model: AugmentedModel, u, y, z, rmse_model: float, skip: int
                     ) -> tuple[AugmentedModel, Effect]:
    # Linear in the gain for a given tau: least squares on the free-run residual, with the
    # model's own output and a constant as nuisance terms (a model from another day may be off
    # by a constant factor or offset: no rate dependence), tau on a log grid then Brent. The
    # block adds g rho to the model's free run (outermost), so each tau is scored on the
    # residual without simulating the model again (z: its free run on the fit part).
    L = model.max_lag_
    dt = model.dt_s
    r = (y - z)[skip:]
    nuis = np.column_stack([z[skip:], np.ones(r.size)])

    def fit(log_tau: float) -> tuple[float, float]:
        tau = float(np.exp(log_tau))
        rho = Effect("rate_dependence", tau_s=tau,
                     gain_mm_per_v_per_s=1.0).rate_state(u, dt)[skip:]
        coef, *_ = np.linalg.lstsq(np.column_stack([rho, nuis]), r, rcond=None)
        return float(coef[0]), float(np.sqrt(np.mean((r - coef[0] * rho) ** 2)))

    # A slower low-pass of du/dt is the voltage minus its slow average (u - LP(u)) / tau: memory
    # beyond the model's window, where a model from another day has its own error (with the
    # test's day-1 model the fit went to 1 s on clean and rate records alike, docs/diagnose.md).
    lo = max(FROZEN_RATE_TAU_MIN_S, 1.5 * dt)
    hi = max(FROZEN_RATE_WINDOW_SHARE * max(L, 1) * dt, 2.0 * lo)
    grid = np.linspace(np.log(lo), np.log(hi), FROZEN_GRID_POINTS)
    scores = [fit(v)[1] for v in grid]
    i = int(np.argmin(scores))
    best, best_score = float(grid[i]), float(scores[i])
    if not best_score < rmse_model:
        raise ValueError(f"no rate_dependence: the model as given fits the fit part best "
                         f"without it (free-run RMSE {rmse_model:.4g} mm)")
    res = minimize_scalar(lambda v: fit(v)[1], method="bounded", options={"xatol": 1e-3},
                          bounds=(grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]))
    if res.success and res.fun < best_score:
        best = float(res.x)
    eff = Effect("rate_dependence", tau_s=float(np.exp(best)), gain_mm_per_v_per_s=fit(best)[0])
    out = AugmentedModel(model.baseline, model.effects + [eff], dt)
    eff.frozen_ = {"fit_rmse_mm": _rmse_after(out.simulate(u, y[:L]), y, skip),
                   "fit_rmse_before_mm": rmse_model}
    return out, eff


def fit_effect(name: str, model: AugmentedModel, narx: NarxModel, u, y, *,
               screen_narx: NarxModel | None = None, iterations: int = 0,
               val_fraction: float = 0.25) -> tuple[AugmentedModel, Effect]:
    """Add the effect ``name`` to ``model`` and fit it, with the baseline, on (u, y).

    Parameters
    ----------
    name : str
        One of :data:`EFFECT_NAMES` not yet in ``model``.
    model : AugmentedModel
        The current model (fitted on the same record).
    narx : NarxModel
        Unfitted baseline template (hyperparameters, lags) refitted with the effect.
    u, y : array_like, shape (N,)
        The fit record (V, mm), starting at t = 0. The held-out part is never seen here.
    screen_narx : NarxModel, optional
        Cheaper template for the one-dimensional parameter searches (default ``narx``).
    iterations : int
        Extra alternations between the creep's least squares and the baseline refit (0: one
        pass; on the plant more alternations made the estimate wander, e.g. tau 3.6 s ->
        120 s on a 60 s record).
    val_fraction : float
        Share at the end of (u, y) scoring the parameter searches (free-run RMSE).

    Returns
    -------
    (AugmentedModel, Effect)
        The refitted model with the effect appended, and the fitted effect.
    """
    if name not in EFFECT_NAMES:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(EFFECT_NAMES)}")
    if name in model.effect_names:
        raise ValueError(f"the model already has the {name} effect")
    u = as_signal("u", u)
    y = as_signal("y", y)
    same_length(u=u, y=y)
    t = np.arange(u.size) * model.dt_s
    if name == "creep":
        return _fit_creep(model, narx, u, y, t, iterations)
    if name == "drift":
        return _fit_drift(model, narx, u, y, t, iterations)
    if name == "delay":
        # The dead time comes from the ARX scan (dead_time_test), not from a grid scored by
        # refits: the NARX's lag window absorbs a delay, so refit scores hardly tell delays
        # apart, while the one-step ARX sees where the response starts.
        dt_test = dead_time_test(u, y, model.dt_s)
        if dt_test["delay_samples"] == 0:
            raise ValueError("no dead time: the linear ARX scan puts the response at lag 0")
        eff = Effect("delay", delay_s=dt_test["delay_s"])
        eff.test_ = dt_test
        return model.refit(narx, u, y, model.effects + [eff]), eff
    if name == "dead_zone":
        # The width comes from the Hammerstein ARX scan (dead_zone_test), not from a grid scored
        # by refits: the LSSVM represents a static input nonlinearity about as well through the
        # raw input, so refit scores do not tell widths apart (docs/diagnose.md).
        # on the data as the current model's baseline sees it (after a delay found before)
        v, z = model.to_baseline_space(u, y)
        dz = dead_zone_test(v if v.ndim == 1 else v[:, 0], z, model.dt_s)
        if dz["refused"]:
            raise ValueError(f"the dead-zone scan needs a moving input: only "
                             f"{100 * dz['moving_share']:.0f} % of the samples are outside "
                             f"input holds of >= {DZ_HOLD_S:g} s (needs "
                             f"{100 * DZ_MIN_MOVING_SHARE:.0f} %)")
        eff = Effect("dead_zone", width_v=dz["width_v"])
        eff.test_ = dz
        return model.refit(narx, u, y, model.effects + [eff]), eff
    screen = narx if screen_narx is None else screen_narx

    def build(effects, uu, yy):
        return model.refit(screen, uu, yy, effects)

    best = None
    # The rate channel may not reach beyond a third of the baseline's lag window: a slower
    # low-pass of du/dt is u minus its slow average, i.e. memory longer than the window, and on
    # the clean plant that memory (its Bouc-Wen hysteresis, docs/diagnose.md) passed as a
    # "rate dependence" of 1 s (2 of 3 clean 90 s records).
    window_s = max(model.max_lag_, getattr(narx, "lag_step", 1) * 12) * model.dt_s
    for params in _grid(name, u, y, model.dt_s, rate_tau_max_s=window_s / 3.0):
        eff = Effect(name, **params)
        try:
            with np.errstate(all="ignore"):
                score = _validate_on_slice(build, model.effects + [eff], u, y, 1 - val_fraction)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError):
            continue
        if best is None or score < best[0]:
            best = (score, eff)
    if best is None:
        raise ValueError(f"no {name} parameter could be fitted on this record")
    eff = best[1]
    return model.refit(narx, u, y, model.effects + [eff]), eff


def signature(effect: Effect, before: AugmentedModel, after: AugmentedModel, u, *,
              u_past=None, t0_s: float = 0.0, y_init=None) -> np.ndarray:
    """What the fitted effect adds to the free-run prediction on a record (mm): the prediction
    of the augmented model minus the model's before it, both simulated from ``u``."""
    L = before.max_lag_
    y0 = None if y_init is None else np.asarray(y_init, dtype=float)[:L]
    a = after.simulate(u, y0, u_past=u_past, t0_s=t0_s)
    b = before.simulate(u, y0, u_past=u_past, t0_s=t0_s)
    return a - b
