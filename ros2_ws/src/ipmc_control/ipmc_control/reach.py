"""Whether a reference can be tracked: within what 3 V reaches and what the model knows.

Two limits, checked before a closed-loop run starts:

- **3 V reaches** (the simulated IPMC): a held voltage of +-3 V (the H-bridge's limit)
  settles at :func:`plant_reach_mm` ``held=True`` (back-relaxation pulls the tip back after
  its first swing, so a hold reaches less than a passing peak); a moving reference can go as
  far as the peaks of that swing (``held=False``). A reference beyond them saturates the
  drive: no controller can follow it.
- **The model's range**: an inverse feedforward extrapolates beyond the displacements it was
  identified on (``ipmc_model.narx.reach_mm``: its settled range for a hold, its whole range
  for a moving reference); the reference must stay within them.

A reference holds (``constant``, ``steps``) or moves (``sine``, ``random``, ``file``). No ROS
import.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from ipmc_control.pid import ControlParameterError
from ipmc_control.references import KIND_PARAMS, KINDS, Reference, make_reference

HELD_KINDS = ("constant", "steps")
#: What sets the span of each kind, as a user would change it.
SETTING = {"constant": "value_mm", "sine": "amplitude_mm", "random": "range_mm",
           "steps": "levels_mm", "file": "the file's y column"}
LIMIT_V = 3.0
#: Length of the hold that gives the settled reach, s.
SETTLE_S = 30.0


class ReachError(ValueError):
    """A reference that cannot be tracked: one sentence saying why and what to change."""


def build_reference(kind: str, given: dict) -> Reference:
    """The reference ``kind`` with the parameters ``given`` (the others at their defaults);
    a parameter of another kind, or a bad value, raises :class:`ReachError`."""
    if kind not in KINDS:
        raise ReachError(f"reference kind must be one of {', '.join(KINDS)}, got {kind!r}")
    stray = [name for name in given if name not in KIND_PARAMS[kind]]
    if stray:
        users = [k for k in KINDS if stray[0] in KIND_PARAMS[k]]
        raise ReachError(f"{stray[0]} sets a {' or '.join(users)} reference, not a {kind} one")
    if kind == "file" and not given.get("path"):
        raise ReachError("a file reference needs a path (a CSV with columns t, y in s, mm)")
    try:
        return make_reference(kind, **given)
    except ControlParameterError as exc:
        raise ReachError(str(exc)) from None


def reference_span_mm(ref: Reference, kind: str, rate_hz: float = 100.0) -> tuple[float, float]:
    """The lowest and highest displacement (mm) ``ref`` asks for over one period (or its
    span, for a file)."""
    if kind == "sine":
        length_s = 1.0 / ref.frequency_hz
    elif kind == "random":
        length_s = ref.period_s
    elif kind == "steps":
        length_s = ref.levels_mm.size * ref.hold_s
    elif kind == "file":
        length_s = ref.duration_s + 1.0 / rate_hz
    else:
        length_s = 1.0 / rate_hz
    _, y = ref.sample(max(length_s, 1.0 / rate_hz), max(rate_hz, 20.0 / length_s))
    return float(np.min(y)), float(np.max(y))


@lru_cache(maxsize=4)
def plant_reach_mm(held: bool, rate_hz: float = 100.0) -> tuple[float, float]:
    """What +-3 V reaches on the simulated IPMC (default plant parameters), mm
    (:func:`voltage_reach_mm`)."""
    from ipmc_driver.plant import IpmcPlant

    return voltage_reach_mm(lambda u: IpmcPlant(seed=0, dt_s=1.0 / rate_hz).run(u).y_mm,
                            rate_hz, held)


def model_reach_mm(model_path: str | Path, held: bool
                   ) -> tuple[tuple[float, float], str] | None:
    """What the feedforward in ``model_path`` can be asked for (mm), and how the range was
    found: an inverse LSSVM-NARX's displacements it was identified on (settled ones for a
    hold); an inverse of a hysteresis model (GPI), what its forward model says +-3 V reach
    (:func:`voltage_reach_mm`). None when the file does not tell (a forward model's
    inversion, an unreadable file: model_server says why)."""
    from ipmc_model.effects import load_any_model
    from ipmc_model.narx import reach_mm

    try:
        feedforward = load_any_model(model_path)
    except (ValueError, OSError):
        return None
    span = reach_mm(feedforward, held=held)
    if span is not None:
        return span, "the model was identified on"
    forward = getattr(getattr(feedforward, "inverse", feedforward), "model", None)
    if forward is not None and hasattr(forward, "simulate") and hasattr(forward, "dt_s"):
        return voltage_reach_mm(forward.simulate, 1.0 / forward.dt_s, held), \
            f"the model reaches at +-{LIMIT_V:g} V"
    return None


def voltage_reach_mm(simulate, rate_hz: float, held: bool) -> tuple[float, float]:
    """Where +-3 V held ``SETTLE_S`` take the output of ``simulate`` (V -> mm, from rest):
    the settled ends (``held``; the median of the last second) or the extreme swing."""
    ends = []
    for v in (-LIMIT_V, LIMIT_V):
        y = np.asarray(simulate(np.full(int(SETTLE_S * rate_hz), v)), dtype=float)
        ends.append(float(np.median(y[-int(rate_hz):])) if held
                    else float(np.min(y) if v < 0 else np.max(y)))
    return ends[0], ends[1]


def check_reach(span_mm: tuple[float, float], kind: str, *, plant: bool,
                model: str | Path | None, rate_hz: float = 100.0) -> None:
    """Raise :class:`ReachError` when the span (mm) lies beyond what 3 V reaches on the
    simulated IPMC (``plant``) or beyond the model's identified range (``model``)."""
    from ipmc_model.narx import out_of_reach

    held = kind in HELD_KINDS
    lo, hi = span_mm
    asks = f"{lo:.2f} mm" if lo == hi else f"{lo:.2f}..{hi:.2f} mm"
    if plant:
        low, high = plant_reach_mm(held, rate_hz)
        if not (low <= lo and hi <= high):
            how = "settles between" if held else "swings between"
            raise ReachError(
                f"the reference asks for {asks}, but the simulated IPMC {how} {low:.2f} and "
                f"{high:.2f} mm at +-{LIMIT_V:g} V; set {SETTING[kind]} within that")
    found = model_reach_mm(model, held) if model else None
    if found is not None and (out_of_reach(lo, found[0]) or out_of_reach(hi, found[0])):
        (low, high), how = found
        raise ReachError(
            f"the reference asks for {asks}, beyond the {low:.2f}..{high:.2f} mm "
            f"{'held ' if held else ''}{how} ({model}); record an excitation that covers it, "
            f"or set {SETTING[kind]} within it")
