"""Which model a record supports: the model families ``ipmc identify`` tries, the held-out
free-run comparison that picks one, and what a record can and cannot show about how a model
generalises (pure core, no ROS).

A family is a small class behind one interface (``name``, ``describe()``, ``fit(u, y, dt_s)``)
in :data:`FAMILIES`; adding one is a class and a registry line. The comparison fits each
family on the first :data:`FIT_SHARE` of the record and scores the free run of the whole
record, from rest, on the rest: the error a user meets on data the model has not seen, with
the states the record's own past leaves.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
from scipy.signal import lfilter

from ipmc_driver.validation import as_signal, same_length

from .hysteresis import GeneralizedPI
from .play import PrandtlIshlinskii

#: Share of the record the families are fitted on for the comparison; the rest is held out.
FIT_SHARE = 0.7


class Family:
    """A model family ``ipmc identify`` can try: fitted on (u V, y mm) at ``dt_s``."""

    name = ""

    def describe(self) -> str:
        raise NotImplementedError

    def fit(self, u: np.ndarray, y: np.ndarray, dt_s: float, progress=None):
        raise NotImplementedError

    def refit(self, model, u: np.ndarray, y: np.ndarray, dt_s: float, progress=None):
        """The whole record's model, given ``model`` fitted on its first part: a fresh fit
        unless the family can go on from ``model``."""
        return self.fit(u, y, dt_s, progress)


class GpiFamily(Family):
    name = "gpi"

    def describe(self) -> str:
        return ("rate-dependent generalised Prandtl-Ishlinskii: ion-current-limited charging, "
                "relaxations 0.05-108 s, plays, an asymmetric output map")

    def fit(self, u, y, dt_s, progress=None):
        return GeneralizedPI(dt_s=dt_s, progress=progress).fit(u, y)

    def refit(self, model, u, y, dt_s, progress=None):
        # The structure the first part chose (delay, scaling, knots) is kept; the parameters
        # go on from the first part's: a third of the iterations of a fresh fit.
        model.progress, model.warm_start = progress, True
        model.fit(u, y)
        model.warm_start = False
        return model


class PiFamily(Family):
    name = "pi"

    def describe(self) -> str:
        return "Prandtl-Ishlinskii, 10 play operators, NNLS (the paper's rate-independent model)"

    def fit(self, u, y, dt_s, progress=None):
        return PrandtlIshlinskii(n_operators=10, method="nnls").fit(u, y)


#: The families ``ipmc identify`` tries by default, in the order of the table.
FAMILIES: dict[str, Family] = {f.name: f for f in (GpiFamily(), PiFamily())}


@dataclass(frozen=True)
class FamilyScore:
    """One row of the comparison: free-run RMSE (mm) held out first, then on the fit part."""

    name: str
    description: str
    held_out_rmse_mm: float
    fit_rmse_mm: float
    seconds: float
    error: str = ""
    model: object = field(default=None, repr=False, compare=False)

    def as_dict(self) -> dict:
        return {"family": self.name, "description": self.description,
                "held_out_free_run_rmse_mm": _finite_or_none(self.held_out_rmse_mm),
                "fit_free_run_rmse_mm": _finite_or_none(self.fit_rmse_mm),
                "seconds": round(self.seconds, 2), "error": self.error or None}


@dataclass(frozen=True)
class Selection:
    """The comparison's rows and the family it picks (lowest held-out free-run RMSE)."""

    rows: tuple[FamilyScore, ...]
    fit_samples: int
    held_out_samples: int
    chosen: str = field(default="")

    def refit(self, u, y, dt_s: float, progress=None):
        """The chosen family's model on the whole record (u V, y mm)."""
        row = next(r for r in self.rows if r.name == self.chosen)
        return FAMILIES[self.chosen].refit(row.model, u, y, dt_s, progress)

    def as_dict(self) -> dict:
        return {"chosen": self.chosen, "fit_samples": self.fit_samples,
                "held_out_samples": self.held_out_samples,
                "rule": "lowest held-out free-run RMSE",
                "families": [r.as_dict() for r in self.rows]}

    def table(self) -> str:
        lines = [f"{'family':<6} {'held-out free-run RMSE':>23} {'fit-part free-run':>18} "
                 f"{'time':>7}"]
        for r in self.rows:
            mark = "  <- chosen" if r.name == self.chosen else ""
            if r.error:
                lines.append(f"{r.name:<6} {'failed: ' + r.error}")
                continue
            lines.append(f"{r.name:<6} {r.held_out_rmse_mm:>20.4f} mm {r.fit_rmse_mm:>15.4f} mm "
                         f"{r.seconds:>6.1f}s{mark}")
        return "\n".join(lines)


def _finite_or_none(v: float):
    return float(v) if math.isfinite(v) else None


def compare_families(u, y, dt_s: float, names=None, progress=None) -> Selection:
    """Fit each family on the first :data:`FIT_SHARE` of (u V, y mm); score the free run of
    the whole record on the rest. ``names`` defaults to all of :data:`FAMILIES`."""
    u, y = as_signal("u", u), as_signal("y", y)
    same_length(u=u, y=y)
    cut = int(round(FIT_SHARE * u.size))
    rows = []
    for name in names or FAMILIES:
        fam = FAMILIES[name]
        t0 = time.perf_counter()
        m = None
        try:
            m = fam.fit(u[:cut], y[:cut], dt_s, progress)
            ys = m.simulate(u)
            held = float(np.sqrt(np.mean((ys[cut:] - y[cut:]) ** 2)))
            fit = float(np.sqrt(np.mean((ys[:cut] - y[:cut]) ** 2)))
            err = "" if math.isfinite(held) else "free run not finite"
        except ValueError as exc:
            held = fit = math.inf
            err = str(exc)
        rows.append(FamilyScore(name, fam.describe(), held if not err else math.inf, fit,
                                time.perf_counter() - t0, err, m))
    ok = [r for r in rows if not r.error]
    if not ok:
        raise ValueError("no model family could be fitted on this record: "
                         + "; ".join(f"{r.name}: {r.error}" for r in rows))
    best = min(ok, key=lambda r: r.held_out_rmse_mm)
    return Selection(tuple(rows), cut, u.size - cut, best.name)


class LinearArx:
    """Linear ARX y_k = sum a_i y_{k-i} + sum b_j u_{k-j} (j = 0..m), by least squares: the
    reference a nonlinear model must beat. ``simulate`` runs it free (``scipy.signal.lfilter``)
    from rest; ``predict`` is one step ahead from the measured outputs."""

    def __init__(self, output_lags: int = 6, input_lags: int = 6):
        self.output_lags = output_lags
        self.input_lags = input_lags
        self.a_ = None

    def _rows(self, u, y):
        n, m = int(self.output_lags), int(self.input_lags)
        L = max(n, m)
        cols = [y[L - i:y.size - i] for i in range(1, n + 1)]
        cols += [u[L - j:u.size - j] for j in range(0, m + 1)]
        return np.column_stack(cols + [np.ones(y.size - L)]), L

    def fit(self, u, y) -> LinearArx:
        u, y = as_signal("u", u), as_signal("y", y)
        same_length(u=u, y=y)
        X, L = self._rows(u, y)
        theta = np.linalg.lstsq(X, y[L:], rcond=None)[0]
        n = int(self.output_lags)
        self.a_, self.b_, self.c_ = theta[:n], theta[n:-1], float(theta[-1])
        return self

    def simulate(self, u) -> np.ndarray:
        den = np.concatenate([[1.0], -self.a_])
        # the constant enters as an input of 1 through the same denominator
        return lfilter(self.b_, den, as_signal("u", u)) + lfilter([self.c_], den,
                                                                   np.ones(np.size(u)))

    def predict(self, u, y) -> np.ndarray:
        u, y = as_signal("u", u), as_signal("y", y)
        X, L = self._rows(u, y)
        out = y.copy()
        out[L:] = X @ np.concatenate([self.a_, self.b_, [self.c_]])
        return out


# -- what a record can show --------------------------------------------------------------------
#: A record whose input spectrum holds this share of its power within +-2 bins of one peak
#: and its harmonics is one periodic excitation.
PERIODIC_POWER_SHARE = 0.9
#: Fewer independent stretches than this (duration x 95 % bandwidth) cannot separate fit
#: from held-out data.
MIN_INDEPENDENT_CYCLES = 20
#: Relative spread of the input's local peak amplitudes below which it has one amplitude.
ONE_AMPLITUDE_SPREAD = 0.05


def record_limits(u, rate_hz: float) -> list[str]:
    """What the record cannot show about how a model generalises, one sentence each (with
    what to record instead); empty when it can show it."""
    from .excitation import input_kind

    u = as_signal("u", u)
    out = []
    kind = input_kind(u, rate_hz)
    f, p = np.fft.rfftfreq(u.size, 1.0 / rate_hz)[1:], np.abs(np.fft.rfft(u - u.mean()))[1:] ** 2
    if p.sum() > 0:
        k = int(np.argmax(p))
        near = np.zeros(p.size, dtype=bool)
        for h in range(1, 6):  # the peak's bin index is k + 1 (the DC bin was dropped)
            c = h * (k + 1) - 1
            near[max(0, c - 2):c + 3] = True
        share = p[near].sum() / p.sum()
        if share >= PERIODIC_POWER_SHARE:
            out.append(f"the input is one periodic excitation ({f[k]:.3g} Hz holds "
                       f"{100 * share:.0f} % of its power): a model fitted on it is not shown "
                       "other frequencies or waveforms; record a random sine or ipmc simulate "
                       "--input mixed (random sines, slow sweeps and held levels)")
    cycles = u.size / rate_hz * kind["bandwidth_hz"]
    if cycles < MIN_INDEPENDENT_CYCLES:
        out.append(f"about {cycles:.0f} independent cycles (duration x {kind['bandwidth_hz']:.3g} "
                   f"Hz bandwidth): too few to hold some out; record at least "
                   f"{math.ceil(MIN_INDEPENDENT_CYCLES / kind['bandwidth_hz'])} s")
    peaks = _local_peaks(np.abs(u))
    if peaks.size >= 4 and np.std(peaks) < ONE_AMPLITUDE_SPREAD * np.mean(peaks):
        out.append(f"every cycle peaks at one amplitude ({np.mean(peaks):.3g}): minor loops and "
                   "other amplitudes are not shown; vary the amplitude")
    if kind["hold_share"] == 0.0:
        out.append("no input holds of 3 s or more: creep and slow relaxation are not shown "
                   "apart from the hysteresis; add held levels")
    return out


#: A record reaching beyond the identified voltages by more than this share of their span
#: asks the model to extrapolate.
RANGE_SHARE = 0.05


def unlike_identification(metadata: dict, u, rate_hz: float) -> list[str]:
    """How a record (u V at ``rate_hz``) differs from the one a model was identified on, as
    its file's ``metadata`` keeps it (rate, input range, bandwidth and holds), one sentence
    each; empty when it does not differ, or when the file does not say."""
    from .excitation import input_kind, kind_text, kinds_differ, model_input_kind

    u = as_signal("u", u)
    out = []
    rate = metadata.get("rate_hz") if isinstance(metadata, dict) else None
    if isinstance(rate, int | float) and abs(rate - rate_hz) > 1e-6 * rate:
        out.append(f"the record is sampled at {rate_hz:g} Hz, the model was identified at "
                   f"{rate:g} Hz")
    span = metadata.get("input_range_v") if isinstance(metadata, dict) else None
    if isinstance(span, list) and len(span) == 2:
        lo, hi = float(span[0]), float(span[1])
        beyond = max(float(u.max()) - hi, lo - float(u.min()), 0.0)
        if beyond > RANGE_SHARE * (hi - lo):
            out.append(f"the input reaches {float(u.min()):.3g} .. {float(u.max()):.3g} V, beyond "
                       f"the identified {lo:.3g} .. {hi:.3g} V: the model extrapolates there")
    kind = model_input_kind(SimpleNamespace(metadata_=metadata))
    if kind is not None:
        now = input_kind(u, rate_hz)
        if kinds_differ(kind, now):
            out.append(f"the input is of another kind ({kind_text(now)}) than the "
                       f"identification record's ({kind_text(kind)}): the error measures "
                       "generalisation to it")
    return out


def _local_peaks(x: np.ndarray) -> np.ndarray:
    i = np.flatnonzero((x[1:-1] > x[:-2]) & (x[1:-1] >= x[2:])) + 1
    return x[i][x[i] > 0.2 * x.max()] if i.size else i.astype(float)


__all__ = ["FAMILIES", "FIT_SHARE", "Family", "FamilyScore", "LinearArx", "Selection",
           "compare_families", "record_limits", "unlike_identification"]
