"""Candidate effects: one small class each, one interface, one registry.

A candidate names a physical effect, says whether the record's excitation can show it (and
what to record instead), and fits the block that adds it to a :class:`GeneralizedPI`:

* ``refit``: the diagnosis's own model, refitted on the fit rows with the block's stage
  switched on (its physical parameter from a structural scan, within bounds);
* ``around``: a given model (another day's), frozen; only the block's own parameters are
  fitted on the fit rows.

Either way the result is again a :class:`GeneralizedPI`, so its file, its inverse (the
feedforward undoes the block too) and the model server need nothing new. To add an effect,
write one subclass and decorate it with :func:`register`.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.optimize import brentq, minimize_scalar
from scipy.stats import chi2

from ..hysteresis import (
    DEFAULT_MEMORY_TAUS_S,
    MIN_SPANS_PER_TAU,
    GeneralizedPI,
    dead_zone,
    estimate_delay,
    lowpass_bank,
)
from ..metrics import effective_samples
from .experiment import Probe, crossings, holds, probe_level_v, sweep
from .parallel import fan_out
from .record import DiagnosisRecord


@dataclass(frozen=True)
class Fitted:
    """A candidate's model (fitted on the fit rows), its physical parameters and the
    structural scan that set them."""

    model: GeneralizedPI
    params: dict
    scan: str = ""


@dataclass(frozen=True)
class Refined:
    """An accepted effect's costlier estimate: its parameters with 95 % intervals (they
    replace the round's) and, if it replaces the accepted model, the model they describe.
    ``outside``: why the estimate lies outside the effect's physical range, if it does: the
    block then took up something the effect does not describe, and the effect is rejected."""

    params: dict
    model: GeneralizedPI | None = None
    outside: str | None = None


class Candidate:
    """One physical effect the model may lack."""

    name: ClassVar[str] = ""
    #: The effect in one line of physics.
    meaning: ClassVar[str] = ""
    #: Parameters the block adds (the degrees of freedom of its fit-part screen).
    n_params: ClassVar[int] = 1
    #: Its fit's run time in refits of the whole model (a scan costs several): the costliest
    #: fits of a round start first on the workers.
    refits: ClassVar[float] = 1.0

    def not_testable(self, rec: DiagnosisRecord, model: GeneralizedPI, given: bool
                     ) -> str | None:
        """Why the record cannot decide this effect and what to record instead; None if it
        can."""
        return None

    def probe(self, rec: DiagnosisRecord, model: GeneralizedPI, result
              ) -> Probe | None:
        """The input that would make this effect testable (``result``: this round's result,
        its evidence when the candidate was fitted as a rival); None if no record can (a
        given model is what it needs)."""
        return None

    def poorly_determined(self, result, rec: DiagnosisRecord) -> str | None:
        """Why an accepted effect is not pinned down by the record (a 95 % interval the
        record leaves open), so that the probe is worth recording; None if it is."""
        return None

    def refit(self, model: GeneralizedPI, rec: DiagnosisRecord) -> Fitted | str:
        """The own model with this block, refitted on the fit rows (or why none fits)."""
        return "fitted only around a given model"

    def around(self, model: GeneralizedPI, rec: DiagnosisRecord) -> Fitted | str:
        """The given model with this block fitted around it, the rest frozen."""
        raise NotImplementedError

    def fit(self, model: GeneralizedPI, rec: DiagnosisRecord, given: bool) -> Fitted | str:
        return self.around(model, rec) if given else self.refit(model, rec)

    def refine(self, before: GeneralizedPI, after: GeneralizedPI, rec: DiagnosisRecord,
               given: bool) -> Refined | None:
        """A costlier estimate once the effect is accepted (``before``: the model without
        it, ``after``: the accepted one); none by default."""
        return None


CANDIDATES: dict[str, Candidate] = {}


def register(cls: type[Candidate]) -> type[Candidate]:
    """Class decorator: add the candidate to :data:`CANDIDATES` under its ``name``."""
    if not cls.name or cls.name in CANDIDATES:
        raise ValueError(f"a candidate needs a new, non-empty name (got {cls.name!r})")
    CANDIDATES[cls.name] = cls()
    return cls


# -- shared fitting helpers -----------------------------------------------------------------
def refit_with(model: GeneralizedPI, rec: DiagnosisRecord, start: dict,
               warm: GeneralizedPI | None = None, **changes) -> GeneralizedPI:
    """``model``'s hyperparameters with ``changes``, fitted on the fit rows twice: from a
    fresh start (its ridge weight chosen again by the blocked free-run CV), and warm from
    ``model`` with the block added at ``start`` (:func:`warm_refit`; a block at zero
    reproduces ``model``, so that fit can only descend from its error); the lower fit-rows
    error is kept. Either alone fails somewhere: a fresh fit of a few dozen iterations can
    stop above the model it extends, a warm one in the model's basin. ``warm``: that warm
    refit when a scan has already made it."""
    fresh = GeneralizedPI(**{**model.get_params(), **changes}).fit(rec.u_fit, rec.y_fit)
    warm = warm if warm is not None else warm_refit(model, rec, **start)
    return min((fresh, warm), key=lambda m: fit_sse(m, rec))


#: Trust-region iterations of the quick fits of the dead-zone scan (the final fit at
#: the best value has the model's own). Warm refits there, as the delay's, fit widths to the
#: core's misfit beside other effects (a false dead zone beside a drift), which the decision's
#: noise-floor margin does not discount.
SCAN_NFEV = 10


def scan_error(model: GeneralizedPI, rec: DiagnosisRecord, **changes) -> float:
    """Fit-part RMSE of a quick refit of ``model`` with ``changes`` (ridge weight kept)."""
    params = {**model.get_params(), **changes, "alphas": (model.cv_.alpha,),
              "max_nfev": SCAN_NFEV}
    return GeneralizedPI(**params).fit(rec.u_fit, rec.y_fit).train_rmse_


def descend_delay(model: GeneralizedPI, rec: DiagnosisRecord, start: int, lo: int, hi: int
                  ) -> tuple[int, str, GeneralizedPI]:
    """The delay (samples, in [lo, hi]) that refits prefer, by discrete descent from
    ``start`` (the linear scan's); the scan's text; the refit there. Each refit starts warm
    from ``model`` (:func:`warm_refit`): a core without a delay takes one up as slower
    charging, and a short fit from a fresh start stops several times above that core's
    error, so a scan of such fits would compare how far each got, not the delays."""
    dt = rec.dt_s
    cache = {}

    def err(d: int) -> float:
        if d not in cache:
            cache[d] = warm_refit(model, rec, delay_samples_=d, delay_s=d * dt)
        return cache[d].train_rmse_

    d = min(max(start, lo), hi)
    while True:
        nbrs = [n for n in (d - 1, d + 1) if lo <= n <= hi]
        better = [n for n in nbrs if err(n) < err(d)]
        if not better:
            break
        d = min(better, key=err)
    tried = ", ".join(f"{k}: {cache[k].train_rmse_:.4f}" for k in sorted(cache))
    return d, f"linear scan {start} samples; warm refits (samples: fit RMSE mm) {tried}", cache[d]


def fit_residual(model: GeneralizedPI, rec: DiagnosisRecord) -> np.ndarray:
    """Free-run error of ``model`` on the fit rows."""
    return (model.simulate(rec.u_fit) - rec.y_fit)[rec.fit_obs]


def fit_sse(model: GeneralizedPI, rec: DiagnosisRecord) -> float:
    """Free-run squared error of ``model`` on the fit rows."""
    e = fit_residual(model, rec)
    return float(e @ e)


def scalar_around(model: GeneralizedPI, rec: DiagnosisRecord, attr: str, lo: float,
                  hi: float) -> tuple[GeneralizedPI, float]:
    """A copy of ``model`` with the scalar ``attr`` set by bounded minimisation of the fit
    rows' free-run error over [lo, hi]."""
    m = copy.deepcopy(model)

    def sse(x: float) -> float:
        setattr(m, attr, float(x))
        return fit_sse(m, rec)

    res = minimize_scalar(sse, bounds=(lo, hi), method="bounded",
                          options={"xatol": 1e-3 * (hi - lo)})
    setattr(m, attr, float(res.x))
    return m, float(res.x)


def fast_input_reason(rec: DiagnosisRecord, model: GeneralizedPI, what: str) -> str | None:
    """None when the input has steps or power above the charging corner; else why a
    ``what`` cannot be told from the charging lag, and what to record."""
    c, ex = rec.config, rec.excitation
    tau = max(model.charge_tau_s_, rec.dt_s)
    f_corner = 1.0 / (2.0 * math.pi * tau)
    share = rec.power_share_above(f_corner)
    if ex.steps_fit >= c.min_steps or share >= c.delay_power_share:
        return None
    return (f"{ex.steps_fit} steps in the fit part and {100 * share:.0f} % of the input's "
            f"power above the charging corner ({f_corner:.2g} Hz): there a {what} looks like "
            f"the charging lag; record steps (at least {c.min_steps}) or faster input")


def unresolved_charging(rec: DiagnosisRecord, model: GeneralizedPI) -> str | None:
    """None when the model's charging lags the input over enough samples that its current is
    a signal of its own (:attr:`DiagnosisConfig.rate_min_lagged_share`); else why not, and
    the sampling rate that would resolve it."""
    tau, share = model.charge_tau_s_, rec.config.rate_min_lagged_share
    if not tau > 0:
        return ("the model has no charging stage: its charge is the input, whose current is "
                "the input's sample difference, not a charging current")
    if math.exp(-2.0 * rec.dt_s / tau) >= share:
        return None
    need_hz = 2.0 / (tau * math.log(1.0 / share))
    return (f"the model's charging settles within {tau / rec.dt_s:.1f} sample periods (tau "
            f"{1e3 * tau:.0f} ms): a step's current falls mostly in the step's own sample, "
            f"where it is the input's sample difference, not a charging current; if the "
            f"actuator charges at all, sample at {need_hz:.0f} Hz or faster to resolve it")


# -- the effects ----------------------------------------------------------------------------
def creep_taus(model: GeneralizedPI, rec: DiagnosisRecord, given: bool = False
               ) -> tuple[float, ...]:
    """Creep time constants the fit part can identify and the model does not have. Around a
    given (frozen) model a relaxation of the output may share a time constant with the
    model's input memory: the model's weights stay as another day fitted them, so the block
    takes up only what has changed; in a refit the two channels would be the same regressor."""
    c = rec.config
    have = set(model.output_taus_s) | (set() if given else set(model.memory_taus_s_))
    return tuple(t for t in DEFAULT_MEMORY_TAUS_S
                 if t >= c.creep_min_tau_s and t * MIN_SPANS_PER_TAU <= rec.excitation.fit_span_s
                 and t not in have)


def too_few_holds(rec: DiagnosisRecord) -> str | None:
    """How few input holds the record has, when it has fewer than ``min_holds`` in the fit
    part or the held-out part; None when both have enough. While the input holds, the memory
    of the path stands still, so what still moves is a relaxation or a drift; on a moving
    input, whatever the model misfits of that memory moves as well."""
    c, ex = rec.config, rec.excitation
    if ex.holds_fit >= c.min_holds and ex.holds_held >= c.min_holds:
        return None
    return (f"{ex.holds_fit} input holds of {c.hold_min_s:g} s or more in the fit part, "
            f"{ex.holds_held} in the held-out part")


#: Holds proposed for creep last this many of its time constants (86 % settled).
HOLD_TAUS = 2.0
#: Levels of the proposed holds, as shares of the probe level: both signs, two sizes, each
#: hold a step from the last. The loss differential's samples are correlated over about a
#: time constant, so the test's effective sample size grows with the number of settlings,
#: not their length: four holds of two time constants give twice the settlings of two of
#: three, in 4/3 of the time.
HOLD_LEVELS = (1.0, -1.0, 0.5, -0.5)
#: Steps proposed for a delay: this many, each held this long (s; > 5 charging time
#: constants of an IPMC, ~0.3 s, so that each onset starts from a settled charge).
PROBE_STEPS, PROBE_STEP_S = 8, 1.5
#: Slow crossings of 0 V proposed for a dead zone: period (s, far slower than the charging)
#: and cycles.
CROSSING_PERIOD_S, CROSSING_CYCLES = 20.0, 2
#: Levels of a drift's probe, as shares of the probe level, each held ``hold_min_s`` (the
#: charging and the back-relaxation settled): the held levels show the gain, 0 V the offset.
DRIFT_LEVELS = (1.0, -1.0, 0.5, -0.5, 0.0)
#: A rate dependence's sweep runs an octave either side of the charging corner; each octave
#: lasts this many periods of its lowest frequency (logarithmic: the same time in each).
SWEEP_OCTAVE_PERIODS = 2


@register
class Creep(Candidate):
    name = "creep"
    n_params = 2    # one relaxation: its time constant and gain
    meaning = ("slow relaxation under a sustained voltage (time constants of "
               "tens of seconds to minutes): the tip keeps moving while the input holds")

    def not_testable(self, rec, model, given):
        c, ex = rec.config, rec.excitation
        if ex.fit_span_s < MIN_SPANS_PER_TAU * c.creep_min_tau_s:
            return (f"the fit part spans {ex.fit_span_s:.0f} s: a relaxation slower than "
                    f"{c.creep_min_tau_s:g} s must be seen settling over "
                    f"{MIN_SPANS_PER_TAU:g} of its time constants; record longer")
        few = too_few_holds(rec)
        if few:
            return (f"{few}: on a moving input a slow relaxation cannot be told from the "
                    f"memory of the path; record holds of at least {c.hold_min_s:g} s at "
                    f"several levels in both parts")
        return None

    def probe(self, rec, model, result):
        ev = result.evidence
        # the upper end of the creep's 95 % interval: the holds decide every tau it allows
        upper = ev.params.get("tau_ci_s", [0.0, 0.0])[1] if ev is not None else 0.0
        tau = max(float(upper), rec.config.creep_min_tau_s)
        hold_s = max(HOLD_TAUS * tau, rec.config.hold_min_s)
        a = probe_level_v(rec)
        return Probe(self.name, holds(np.array(HOLD_LEVELS) * a, hold_s, 1.0 / rec.dt_s),
                     f"{len(HOLD_LEVELS)} holds of {hold_s:.0f} s ({HOLD_TAUS:g} x the creep's "
                     f"time constant {tau:.3g} s) at +-{a:.2f} and +-{a / 2:.2f} V: a "
                     f"relaxation settles while the input holds still, the path memory does "
                     f"not move",
                     also=("drift",))   # in both copies: the same levels held at two times

    def poorly_determined(self, result, rec):
        p = result.evidence.params if result.evidence is not None else {}
        low, high = p.get("tau_ci_open", (False, False))
        if not (low or high):
            return None
        lo, hi = p["tau_ci_s"]
        side = "longest" if high else "shortest"
        return (f"the creep's time constant is not pinned down: its 95 % interval "
                f"[{lo:.3g}, {hi:.3g}] s runs to the {side} one the record can show")

    def refit(self, model, rec):
        taus = creep_taus(model, rec)
        if not taus:
            return "no creep time constant the fit part can identify"
        taus_s = tuple(model.output_taus_s) + taus
        m = refit_with(model, rec, {"output_taus_s": taus_s, "output_coef_": np.append(
            model.output_coef_, np.zeros(len(taus)))}, output_taus_s=taus_s)
        return Fitted(m, _creep_params(m, taus, rec))

    def around(self, model, rec):
        # one relaxation, its time constant and gain fitted to what the frozen model leaves:
        # a bank of free gains would also take up the slow part of that model's misfit
        if not creep_taus(model, rec, given=True):
            return "no creep time constant the fit part can identify"
        est = creep_estimate(model, rec)
        m = copy.deepcopy(model)
        m.output_taus_s = (*m.output_taus_s, est["tau_s"])
        m.output_coef_ = np.append(m.output_coef_, est["gain_mm_per_v"])
        return Fitted(m, {"taus_s": [est["tau_s"]], "gains_mm_per_v": [est["gain_mm_per_v"]],
                          **est})

    def refine(self, before, after, rec, given):
        # the held-out rows have decided; the relaxation is then estimated on every row (the
        # held-out part's holds show it settling too). Around a given model that is a profile
        # over tau with a linear gain; the own model moves with tau, so it is refitted. The
        # bank of fixed time constants is the test's device (a refit without a search over
        # tau); the creep the diagnosis reports is one relaxation, and the model after it is
        # that relaxation at the estimated tau (three free gains would also take up the slow
        # part of the model's misfit). Its likelihood is traced below the creep's range too,
        # so that its interval can close there: a best fit below it is a faster relaxation
        # (the charging and the memory the core holds) the test's bank took up, not a creep
        if given:
            params = {**creep_estimate(before, rec.whole()), "interval": "whole record"}
            single = None
        else:
            # the profile starts from the accepted model's core (its bank taken out): the
            # core fitted beside the creep. Started from the core fitted without it (which
            # took up what it could of the creep), the refits can stay in that core's basin,
            # at several times the accepted model's error on both parts. The output gains
            # kept: the charging current's (first, when the model has one) and the model's
            # own relaxations'
            k = len(before.output_taus_s)
            core = copy_with(after, output_taus_s=tuple(after.output_taus_s[:k]),
                             output_coef_=after.output_coef_[:int(after.output_rate) + k])
            params, single = creep_profile(core, rec)
            params = {**params, "taus_s": [float(single.output_taus_s[-1])],
                      "gains_mm_per_v": [float(single.output_coef_[-1])]}
        return Refined(params, single, creep_outside(params, rec))


def warm_refit(model: GeneralizedPI, rec: DiagnosisRecord, **attrs) -> GeneralizedPI:
    """A copy of ``model`` with ``attrs`` set, fitted on the fit rows from ``model``'s
    learned parameters (warm start, its ridge weight kept).
    It starts where ``model`` is, so it converges in a third of a fit's iterations; a short
    fit from a fresh start stops several times above the converged error, and a profile
    over a parameter would then measure how far each fit got."""
    m = copy_with(model, **attrs)
    m.warm_start, m.alphas, m.progress = True, (model.cv_.alpha,), None   # the ridge weight kept
    m.fit(rec.u_fit, rec.y_fit)
    m.warm_start, m.alphas, m.progress = model.warm_start, model.alphas, model.progress
    return m


#: A further refit that raises the fit rows' likelihood ratio by less than chi2(1)'s median
#: leaves the model converged: a one-parameter block needs chi2(1) at 0.95 (3.84), so what
#: iterating could still gain is too small to pass for a block.
CONVERGED_LR = float(chi2.ppf(0.5, 1))
#: Warm refits tried at most (each a third of a fit's iterations).
MAX_POLISH = 6


def converged(model: GeneralizedPI, rec: DiagnosisRecord) -> GeneralizedPI:
    """``model`` warm refitted (at its ridge weight) while a refit lowers the fit rows' error,
    until one gains less than :data:`CONVERGED_LR`. A short fit can stop short of its optimum,
    and a candidate refitted from it would win the remainder as if its block had explained
    it. A refit that does not lower the error ends it: at a fixed ridge weight a refit may
    trade fit error for smaller weights."""
    r = fit_residual(model, rec)
    for _ in range(MAX_POLISH):
        nxt = warm_refit(model, rec)
        r_new = fit_residual(nxt, rec)
        sse, new = float(r @ r), float(r_new @ r_new)
        if not new < sse:
            break
        lr = effective_samples(r) * math.log(sse / new)
        model, r = nxt, r_new
        if lr < CONVERGED_LR:
            break
    return model


def copy_with(model: GeneralizedPI, **attrs) -> GeneralizedPI:
    """A copy of ``model`` with ``attrs`` set, the rest as learned."""
    m = copy.deepcopy(model)
    for name, value in attrs.items():
        setattr(m, name, value)
    return m


def with_relaxation(model: GeneralizedPI, rec: DiagnosisRecord, tau_s: float
                    ) -> GeneralizedPI:
    """``model`` with one more output relaxation (``tau_s``, its gain from zero), warm
    refitted (:func:`warm_refit`)."""
    return warm_refit(model, rec, output_taus_s=(*model.output_taus_s, float(tau_s)),
                      output_coef_=np.append(model.output_coef_, 0.0))


@dataclass(frozen=True)
class Profile:
    """Fits of a model over a grid ``x`` of one parameter (on the scale its interval is
    interpolated on), their fit rows' free-run sums of squares, and the best fit's
    residual in effective samples (:func:`effective_samples`)."""

    x: np.ndarray
    fits: list
    sse: np.ndarray
    n_eff: float
    #: The parameter's finest step: a value between two grid points at this step shows as
    #: the nearer one, so no interval is narrower than a step about the best point.
    resolution: float = 0.0

    @classmethod
    def of(cls, x, fits: list, rec: DiagnosisRecord, resolution: float = 0.0) -> Profile:
        sse = np.array([fit_sse(m, rec) for m in fits])
        best = fits[int(np.argmin(sse))]
        n_eff = effective_samples(fit_residual(best, rec))
        return cls(np.asarray(x, float), list(fits), sse, n_eff, resolution)

    @classmethod
    def traced(cls, x, fit_at, rec: DiagnosisRecord, resolution: float) -> Profile:
        """The profile of ``fit_at(value)`` over the grid ``x``; when the interval lies within
        the best point's neighbours (a grid too coarse to trace it), traced again with points
        between them, on multiples of ``resolution`` (the finest step the parameter has)."""
        x = np.asarray(x, float)
        prof = cls.of(x, fan_out(fit_at, x.tolist()), rec, resolution)
        k = int(np.argmin(prof.sse))
        if not prof._within_neighbours(k):
            return prof
        fine = np.unique(np.round(np.linspace(x[k - 1], x[k + 1], 2 * PROFILE_HALF_POINTS + 1)
                                  / resolution) * resolution)
        # new points only, within the grid's range: a near twin of a point is a refit's noise
        fine = fine[(np.min(np.abs(fine[:, None] - x), axis=1) > resolution / 2)
                    & (fine >= x[0]) & (fine <= x[-1])]
        if fine.size == 0:
            return prof
        merged = np.r_[x, fine]
        order = np.argsort(merged)
        fits = prof.fits + fan_out(fit_at, fine.tolist())
        return cls.of(merged[order], [fits[i] for i in order], rec, resolution)

    @property
    def best(self) -> GeneralizedPI:
        return self.fits[int(np.argmin(self.sse))]

    def _excess(self) -> tuple[np.ndarray, np.ndarray]:
        """n_eff ln(SSE / SSE_min) at each point, and its excess over chi2(1)'s 0.95."""
        dev = self.n_eff * np.log(self.sse / self.sse.min())
        return dev, dev - chi2.ppf(0.95, 1)

    def _within_neighbours(self, k: int) -> bool:
        excess = self._excess()[1]
        return 0 < k < self.x.size - 1 and min(excess[k - 1], excess[k + 1]) > 0

    def interval(self) -> tuple[float, tuple[float, float], tuple[bool, bool]]:
        """The parameter's estimate and profile-likelihood 95 % interval: where the sum of
        squares stays within chi2(1) 0.95 of its minimum, n_eff ln(SSE / SSE_min) (the
        other parameters refitted at each point carry what they can take up), and at least
        half a ``resolution`` either side of the best point; ends cut by the grid's edge,
        not the data, are open."""
        centre, (lo, hi), open_ends = self._interval()
        best, half = float(self.x[int(np.argmin(self.sse))]), self.resolution / 2.0
        return centre, (min(lo, best - half), max(hi, best + half)), open_ends

    def _interval(self) -> tuple[float, tuple[float, float], tuple[bool, bool]]:
        x, n = self.x, self.x.size
        k = int(np.argmin(self.sse))
        dev, excess = self._excess()
        if self._within_neighbours(k):
            # the interval lies within the neighbours: the parabola through the three points
            a, b, c = dev[k - 1:k + 2]
            h_l, h_r = x[k] - x[k - 1], x[k + 1] - x[k]
            slope_l, slope_r = (b - a) / h_l, (c - b) / h_r
            curv = 2.0 * (slope_r - slope_l) / (h_l + h_r)
            centre = float(x[k] - (slope_l * h_r + slope_r * h_l) / (h_l + h_r) / curv)
            half = math.sqrt(2.0 * chi2.ppf(0.95, 1) / curv)
            return centre, (centre - half, centre + half), (False, False)
        ends, open_ends = [], []
        for side in (range(k, -1, -1), range(k, n)):   # an end at the grid's edge: open
            idx = list(side)
            end, crossed = float(x[idx[-1]]), False
            for i, j in zip(idx, idx[1:], strict=False):
                if excess[j] > 0:   # crossed between the two: interpolate
                    end = float(x[i] + (x[j] - x[i]) * -excess[i] / (excess[j] - excess[i]))
                    crossed = True
                    break
            ends.append(end)
            open_ends.append(not crossed)
        return float(x[k]), (ends[0], ends[1]), (open_ends[0], open_ends[1])


def better_fit(model: GeneralizedPI, than: GeneralizedPI, rec: DiagnosisRecord
               ) -> GeneralizedPI | None:
    """``model`` (of ``than``'s structure, another value of one parameter) if it fits the fit
    rows better than ``than``, else None."""
    return model if fit_sse(model, rec) < fit_sse(than, rec) else None


def judged_on_profile(prof: Profile, after: GeneralizedPI, rec: DiagnosisRecord, own: float,
                      value: Callable[[GeneralizedPI], float], min_added: float,
                      keys: tuple[str, str, str], why: Callable[[float], str]) -> Refined:
    """An accepted block judged on its profile over one parameter (``value`` of a model, in
    the unit of the profile's grid): outside the effect's physical range when the profile's
    best fit adds less than ``min_added`` to the model's ``own`` value (``why(added)`` says
    so), else the best point kept where it fits better than ``after``. ``keys``: the names of
    the estimate, its 95 % interval (from ``own`` up) and which ends are open. Outside, the
    estimate reported is the profile's, beside its interval."""
    _, ends, open_ends = prof.interval()
    best = prof.best
    added = float(value(best)) - own
    inside = added >= min_added
    kept = better_fit(best, after, rec) if inside else None
    shown = (kept or after) if inside else best
    estimate, interval, is_open = keys
    return Refined({estimate: float(value(shown)), interval: [max(ends[0], own), ends[1]],
                    is_open: list(open_ends)}, kept, None if inside else why(added))


def creep_outside(params: dict, rec: DiagnosisRecord) -> str | None:
    """Why a creep estimated on every row is no creep, or None: a relaxation faster than a
    creep, a time constant the record bounds on neither side (a relaxation is defined by
    its time constant; a block that fits as well at every one the record can show took up a
    slow misfit, which any slow block fits), or a gain whose interval holds zero (as a
    delay or a dead zone whose profile adds less than its resolution: no size shown)."""
    low = rec.config.creep_min_tau_s
    lo, hi = params["tau_ci_s"]
    if params["tau_s"] < low:
        return (f"estimated on every row its relaxation is faster than a creep (tau "
                f"{params['tau_s']:.3g} s < {low:g} s): the block took up a fast misfit of "
                f"the model, not a creep")
    if all(params.get("tau_ci_open", (False, False))):
        return (f"estimated on every row its time constant is bounded on neither side (95 % "
                f"interval {lo:.3g}-{hi:.3g} s, every one the record can show): the block "
                f"took up a slow misfit of the model, not a relaxation")
    g_lo, g_hi = params["gain_ci_mm_per_v"]
    if g_lo <= 0.0 <= g_hi:
        return (f"estimated on every row its gain's 95 % interval ({g_lo:.3g} to "
                f"{g_hi:.3g} mm/V) holds zero: the fit rows do not tell it from no creep")
    return None


#: The creep profile's finest step in ln tau (1 %: far inside any interval a record gives).
CREEP_LOG_TAU_RESOLUTION = 0.01


def creep_profile(before: GeneralizedPI, rec: DiagnosisRecord, n_taus: int = 9
                  ) -> tuple[dict, GeneralizedPI]:
    """One creep relaxation added to ``before`` and refitted with it (warm refits,
    :func:`with_relaxation`) on a log grid of tau: tau and its gain with 95 % intervals
    (:meth:`Profile.interval`), and the model refitted at the estimated tau."""
    lo, hi = rec.config.creep_min_tau_s / 3.0, rec.excitation.fit_span_s / MIN_SPANS_PER_TAU
    prof = Profile.traced(np.linspace(math.log(lo), math.log(hi), n_taus),
                          lambda lt: with_relaxation(before, rec, math.exp(lt)), rec,
                          CREEP_LOG_TAU_RESOLUTION)
    grid = np.exp(prof.x)
    u, obs = rec.u_fit, rec.fit_obs
    # the gain's Wald half-width at each tau: its channel's energy against the residual
    # variance per effective sample
    energy = np.array([np.sum(lowpass_bank(m._charge(u, m._theta), (t,), rec.dt_s)[0][obs] ** 2)
                       for m, t in zip(prof.fits, grid, strict=True)])
    halves = 1.96 * np.sqrt(prof.sse / prof.n_eff / energy)
    centre, ends, open_ends = prof.interval()
    params = _tau_and_gain(prof.x, prof.fits, halves, centre, ends, open_ends)
    if np.isclose(centre, prof.x).any():   # the estimate is a grid point: its fit is there
        return params, prof.best
    at_centre = with_relaxation(before, rec, params["tau_s"])
    return params, min((at_centre, prof.best), key=lambda m: fit_sse(m, rec))


def _tau_and_gain(log_grid: np.ndarray, fits: list, halves: np.ndarray, centre: float,
                  ends: tuple, open_ends: tuple) -> dict:
    """tau (s) at ``centre`` with the interval ``ends`` (log s; ``open_ends``: which end the
    grid cut, not the data), and the refits' creep gain (mm/V) there with its interval: each
    gain's Wald interval (``halves``), joined over tau's interval."""
    gains = np.array([m.output_coef_[-1] for m in fits])
    at = np.linspace(ends[0], ends[1], 25)
    g, h = np.interp(at, log_grid, gains), np.interp(at, log_grid, halves)
    return {"tau_s": float(np.exp(centre)),
            "tau_ci_s": [float(np.exp(ends[0])), float(np.exp(ends[1]))],
            "gain_mm_per_v": float(np.interp(centre, log_grid, gains)),
            "gain_ci_mm_per_v": [float((g - h).min()), float((g + h).max())],
            "tau_ci_open": [bool(e) for e in open_ends], "interval": "profile of refits"}


def _creep_params(m: GeneralizedPI, taus, rec: DiagnosisRecord) -> dict:
    """The creep's bank (time constants, gain on each in mm per V of charge) and one
    relaxation's time constant and gain with their 95 % intervals (:func:`creep_estimate`)."""
    n = len(taus)
    base = copy.deepcopy(m)
    base.output_coef_ = np.concatenate([m.output_coef_[:-n], np.zeros(n)])
    est = creep_estimate(base, rec)
    return {"taus_s": list(taus), "gains_mm_per_v": [float(g) for g in m.output_coef_[-n:]],
            **est}


def creep_estimate(base: GeneralizedPI, rec: DiagnosisRecord) -> dict:
    """One relaxation ``g * lowpass(v, tau)`` fitted, over the fit rows, to what ``base``
    leaves: ``tau_s`` and ``gain_mm_per_v``
    with 95 % intervals. tau's is the profile-likelihood interval (the sum of squares within
    chi2(1) 0.95 of its minimum) and the gain's the Wald one at that tau, both with the
    residual's effective sample size (:func:`effective_samples`): the residual of a free run
    is far from white, and n alone would make the intervals too narrow."""
    u, obs = rec.u_fit, rec.fit_obs
    r = (rec.y_fit - base.simulate(u))[obs]
    v = base._charge(u, base._theta)
    lo, hi = rec.config.creep_min_tau_s / 3.0, rec.excitation.fit_span_s / MIN_SPANS_PER_TAU

    def fit(tau: float) -> tuple[float, float, np.ndarray]:
        x = lowpass_bank(v, (tau,), rec.dt_s)[0][obs, 0]
        g = float(x @ r / (x @ x))
        return float(np.sum((r - g * x) ** 2)), g, x

    grid = np.geomspace(lo, hi, 40)
    k = int(np.argmin([fit(t)[0] for t in grid]))
    res = minimize_scalar(lambda lt: fit(math.exp(lt))[0],
                          bounds=(math.log(grid[max(k - 1, 0)]),
                                  math.log(grid[min(k + 1, grid.size - 1)])), method="bounded")
    tau = math.exp(res.x)
    sse, g, x = fit(tau)
    n_eff = effective_samples(r - g * x)
    limit = chi2.ppf(0.95, 1) / n_eff   # ln(SSE / SSE_min) at the interval's ends

    def excess(t: float) -> float:
        return math.log(fit(t)[0] / sse) - limit

    closed = [excess(a) * excess(b) < 0 for a, b in ((lo, tau), (hi, tau))]
    ends = [brentq(excess, a, b, xtol=1e-3 * tau) if c else a
            for (a, b), c in zip(((lo, tau), (hi, tau)), closed, strict=True)]
    half = 1.96 * math.sqrt(sse / n_eff / float(x @ x))
    return {"tau_s": tau, "tau_ci_s": [float(ends[0]), float(ends[1])],
            "gain_mm_per_v": g, "gain_ci_mm_per_v": [g - half, g + half],
            "tau_ci_open": [not c for c in closed]}


def fit_drift(model: GeneralizedPI, rec: DiagnosisRecord) -> GeneralizedPI:
    """A copy of ``model`` whose output gain and offset change linearly with time, the two
    rates fitted by least squares on the fit rows (the rest frozen)."""
    m = copy.deepcopy(model)
    m.drift_gain_per_s_ = m.drift_offset_mm_per_s_ = 0.0
    lim = m.limit_mm_
    m.limit_mm_ = math.inf
    obs = rec.fit_obs
    y0 = m.simulate(rec.u_fit)
    t = (np.arange(y0.size) * rec.dt_s)[obs]
    y0, y = y0[obs], rec.y_fit[obs]
    if math.isfinite(lim):  # fit where the limit is undone
        y = lim * np.arctanh(np.clip(y / lim, -0.999, 0.999))
    g, o = np.linalg.lstsq(np.column_stack([y0 * t, t]), y - y0, rcond=None)[0]
    m.drift_gain_per_s_, m.drift_offset_mm_per_s_, m.limit_mm_ = float(g), float(o), lim
    m.drift = True
    return m


def _drift_params(m: GeneralizedPI) -> dict:
    return {"gain_change_per_min": 60.0 * m.drift_gain_per_s_,
            "offset_mm_per_min": 60.0 * m.drift_offset_mm_per_s_}


@register
class Drift(Candidate):
    name = "drift"
    n_params = 2    # the gain's and the offset's rates
    meaning = ("an offset and a gain that change steadily over the record (dehydration, "
               "temperature)")

    def probe(self, rec, model, result):
        a, hold_s = probe_level_v(rec), rec.config.hold_min_s
        return Probe(self.name, holds(np.array(DRIFT_LEVELS) * a, hold_s, 1.0 / rec.dt_s),
                     f"{len(DRIFT_LEVELS)} levels held {hold_s:g} s each (+-{a:.2f}, "
                     f"+-{a / 2:.2f} and 0 V) at the experiment's start and again at its end: "
                     f"a drift bends the same levels less or more at the end (its gain) and "
                     f"moves where 0 V rests (its offset); the actuator's memory of the path "
                     f"does not", ends=True)

    def not_testable(self, rec, model, given):
        few = too_few_holds(rec)
        if few is None:
            return None
        return (f"{few}: on a moving input a trend in the error is also what a misfit of the "
                f"memory of a path that never repeats leaves; record the same levels held at "
                f"the start and the end (its probe)")

    def refit(self, model, rec):
        # the two rates fitted jointly with the rest
        m = refit_with(model, rec, {"drift": True, "drift_gain_per_s_": 0.0,
                                    "drift_offset_mm_per_s_": 0.0}, drift=True)
        return Fitted(m, _drift_params(m))

    def around(self, model, rec):
        m = fit_drift(model, rec)
        return Fitted(m, _drift_params(m))


#: The shortest delay a record can show: the drive's zero-order hold and the sensor's sampling
#: each shift the response by up to half a sample, so one sample is within the sampling itself.
MIN_DELAY_SAMPLES = 2


@register
class Delay(Candidate):
    name = "delay"
    meaning = "a transport delay between the command and the bending (drive, bus, sensor)"
    refits = 1.5    # a descent over whole samples of quick refits, then the refit

    def not_testable(self, rec, model, given):
        return fast_input_reason(rec, model, "delay")

    def probe(self, rec, model, result):
        a = probe_level_v(rec)
        levels = np.array([1.0, 0.0, -1.0, 0.5, -0.5, 0.0, 1.0, -1.0])[:PROBE_STEPS] * a
        return Probe(self.name, holds(levels, PROBE_STEP_S, 1.0 / rec.dt_s),
                     f"{PROBE_STEPS} steps held {PROBE_STEP_S:g} s each: a delay shifts each "
                     f"onset, the charging lag only rounds it")

    def refit(self, model, rec):
        c = rec.config
        u = dead_zone(rec.u_fit, model.dead_zone_v)
        d = estimate_delay(u, rec.y_fit, rec.dt_s, model.memory_taus_s_,
                           int(round(c.max_delay_s / rec.dt_s)))
        lo, hi = model.delay_samples_ + MIN_DELAY_SAMPLES, int(round(c.max_delay_s / rec.dt_s))
        d, scan, warm = descend_delay(model, rec, max(d, lo), lo, hi)
        m = refit_with(model, rec, {"delay_samples_": d, "delay_s": d * rec.dt_s}, warm,
                       delay_s=d * rec.dt_s)
        return Fitted(m, {"delay_s": d * rec.dt_s}, scan)

    def refine(self, before, after, rec, given):
        # the profile over whole samples around the accepted delay, each refitted (own
        # model) or the frozen rest kept (given): the delay's 95 % interval in seconds
        d, dt = int(after.delay_samples_), rec.dt_s
        step = max(1, d // (2 * PROFILE_HALF_POINTS))
        top = int(before.delay_samples_) + int(round(rec.config.max_delay_s / dt))
        grid = np.arange(max(int(before.delay_samples_), d - PROFILE_HALF_POINTS * step),
                         min(d + PROFILE_HALF_POINTS * step, top) + 1, step)
        prof = Profile.traced(grid * dt, lambda v: at_values(
            after, rec, given, delay_samples_=int(round(v / dt)), delay_s=v), rec, dt)
        # whole samples, compared in seconds: MIN_DELAY_SAMPLES or more added is more than
        # MIN_DELAY_SAMPLES - 0.5 (clear of the rounding of a product with dt)
        return judged_on_profile(
            prof, after, rec, int(before.delay_samples_) * dt, lambda m: m.delay_samples_ * dt,
            (MIN_DELAY_SAMPLES - 0.5) * dt, ("delay_s", "delay_ci_s", "delay_ci_open"),
            lambda added: f"its profile's best fit adds {round(added / dt)} sample(s) of delay, "
                          f"within the sampling itself (fewer than {MIN_DELAY_SAMPLES}): the "
                          f"block took up a misfit of the model, not a transport delay")

    def around(self, model, rec):
        best, best_sse = 0, fit_sse(model, rec)
        m = copy.deepcopy(model)
        for d in range(MIN_DELAY_SAMPLES, int(round(rec.config.max_delay_s / rec.dt_s)) + 1):
            m.delay_samples_ = model.delay_samples_ + d
            s = fit_sse(m, rec)
            if s < best_sse:
                best, best_sse = d, s
        if best == 0:
            return "no added delay lowers the fit part's free-run error"
        m.delay_samples_ = model.delay_samples_ + best
        m.delay_s = m.delay_samples_ * rec.dt_s
        return Fitted(m, {"delay_s": m.delay_samples_ * rec.dt_s},
                      f"free-run scan: {best} samples added")


def at_values(model: GeneralizedPI, rec: DiagnosisRecord, frozen: bool, **attrs
              ) -> GeneralizedPI:
    """``model`` with ``attrs`` set: the rest frozen (a given model), or warm refitted (the
    own model, :func:`warm_refit`)."""
    return copy_with(model, **attrs) if frozen else warm_refit(model, rec, **attrs)


#: Grid points of a parameter's profile on each side of its estimate.
PROFILE_HALF_POINTS = 4


#: Resolution of the dead zone's scan (V): below the sensor's reach at IPMC gains (~1 mm/V).
DEAD_ZONE_TOL_V = 0.01


@register
class DeadZone(Candidate):
    name = "dead_zone"
    meaning = "voltages below a threshold move no ions (a contact or electrode threshold)"
    refits = 4.0    # a bounded scan of about ten quick refits, then the refit

    def not_testable(self, rec, model, given):
        # both parts: the fit rows set the width, and the judged rows decide only if they
        # dwell near 0 V too
        c, ex = rec.config, rec.excitation
        if min(ex.near_zero_share, ex.near_zero_held_share) >= c.dead_zone_min_share:
            return None
        return (f"{100 * ex.near_zero_share:.1f} % of the fit part and "
                f"{100 * ex.near_zero_held_share:.1f} % of the judged held-out rows within "
                f"+-{c.dead_zone_max_v:g} V: a dead zone shows in slow crossings of 0 V; "
                f"record small, slow ones in both parts (at least "
                f"{100 * c.dead_zone_min_share:.0f} % of the time)")

    def probe(self, rec, model, result):
        a = min(rec.config.dead_zone_max_v, probe_level_v(rec))
        return Probe(self.name, crossings(a, CROSSING_PERIOD_S, CROSSING_CYCLES, 1.0 / rec.dt_s),
                     f"{CROSSING_CYCLES} slow triangles of +-{a:.2f} V ({CROSSING_PERIOD_S:g} s "
                     f"period): the charge follows them, and a dead zone flattens the bending "
                     f"at each crossing of 0 V")

    def refit(self, model, rec):
        hi = rec.config.dead_zone_max_v
        res = minimize_scalar(lambda w: scan_error(model, rec, dead_zone_v=float(w)),
                              bounds=(model.dead_zone_v, model.dead_zone_v + hi),
                              method="bounded", options={"xatol": DEAD_ZONE_TOL_V})
        w = float(res.x)
        m = refit_with(model, rec, {"dead_zone_v": w}, dead_zone_v=w)
        return Fitted(m, {"width_v": w}, f"bounded scan of quick refits: {w:.3f} V "
                                         f"({res.nfev} refits)")

    def refine(self, before, after, rec, given):
        # the profile over widths around the accepted one, within the scan's bounds
        lo = before.dead_zone_v
        hi = lo + rec.config.dead_zone_max_v
        step = rec.config.dead_zone_max_v / (2 * PROFILE_HALF_POINTS)
        grid = np.unique(np.clip(after.dead_zone_v + step * np.arange(
            -PROFILE_HALF_POINTS, PROFILE_HALF_POINTS + 1), lo, hi))
        prof = Profile.traced(grid, lambda w: at_values(after, rec, given, dead_zone_v=w),
                              rec, DEAD_ZONE_TOL_V)
        return judged_on_profile(
            prof, after, rec, lo, lambda m: m.dead_zone_v, DEAD_ZONE_TOL_V,
            ("width_v", "width_ci_v", "width_ci_open"),
            lambda added: f"its profile's best fit adds {1000 * added:.1f} mV of dead zone, "
                          f"below the scan's resolution ({1000 * DEAD_ZONE_TOL_V:g} mV, a "
                          f"bending below the sensor's reach): the block took up a misfit of "
                          f"the model, not a dead zone")

    def around(self, model, rec):
        m, w = scalar_around(model, rec, "dead_zone_v", model.dead_zone_v,
                             model.dead_zone_v + rec.config.dead_zone_max_v)
        return Fitted(m, {"width_v": w})


@register
class RateDependence(Candidate):
    name = "rate_dependence"
    meaning = ("bending that follows the charging current, not the charge (water dragged "
               "with the migrating cations): loops widen with frequency")

    def not_testable(self, rec, model, given):
        return unresolved_charging(rec, model) or fast_input_reason(
            rec, model, "rate-dependent bending")

    def probe(self, rec, model, result):
        if unresolved_charging(rec, model):
            return None   # a faster sampling rate decides it, not an input
        f_c = 1.0 / (2.0 * math.pi * model.charge_tau_s_)
        f0, f1 = f_c / 2.0, min(2.0 * f_c, 0.125 / rec.dt_s)   # eight samples a period
        if not f1 > f0:
            return None
        seconds = SWEEP_OCTAVE_PERIODS / f0 * math.log2(f1 / f0)
        a = probe_level_v(rec)
        return Probe(self.name, sweep(a, f0, f1, seconds, 1.0 / rec.dt_s),
                     f"a sine of +-{a:.2f} V swept from {f0:.2g} to {f1:.2g} Hz in "
                     f"{seconds:.0f} s, an octave either side of the charging corner "
                     f"({f_c:.2g} Hz): the bending that follows the charging current grows "
                     f"along the sweep while the charge's falls, so the loops widen with "
                     f"frequency")

    # the water dragged with the cations bends the strip on top of the charge's bending: a
    # charging-current channel added after the output map, one gain (mm per V/s). Inside the
    # map, a current is only the difference of the charge and its fastest relaxation, a
    # weight the ridge penalty keeps small
    def refit(self, model, rec):
        if model.output_rate:
            return "the model already has a charging-current channel"
        m = refit_with(model, rec, {"output_rate": True,
                                    "output_coef_": np.r_[0.0, model.output_coef_]},
                       output_rate=True)
        return Fitted(m, {"gain_mm_per_v_per_s": float(m.output_coef_[0])})

    def refine(self, before, after, rec, given):
        # what the channel itself bends on the judged rows: adding it alone lowers their mean
        # squared error by at most its own mean square, so one below the materiality margin
        # passed on what the refit moved in the rest of the model, not on a rate dependence
        v = after._charge(rec.u_v, after._theta)
        bend = after.output_coef_[0] * after._charging_current(v)[rec.judged_for(self.name)]
        ms, margin = float(np.mean(bend ** 2)), rec.margin_mm2
        if ms >= margin:
            return None
        return Refined({"gain_mm_per_v_per_s": float(after.output_coef_[0])}, outside=(
            f"the channel itself bends {math.sqrt(ms):.2g} mm RMS on the judged rows, a mean "
            f"square below the materiality margin ({margin:.3g} mm^2): the gain came from "
            f"refitting the rest of the model, not from a rate-dependent bending"))

    def around(self, model, rec):
        # one gain, fitted by least squares to what the frozen model leaves
        if model.output_rate:
            return "the model already has a charging-current channel"
        obs = rec.fit_obs
        x = model._charging_current(model._charge(rec.u_fit, model._theta))[obs]
        if not x @ x > 0:
            return "the model's charge does not move on the fit part"
        g = float(x @ (rec.y_fit - model.simulate(rec.u_fit))[obs] / (x @ x))
        m = copy.deepcopy(model)
        m.output_rate, m.output_coef_ = True, np.r_[g, model.output_coef_]
        return Fitted(m, {"gain_mm_per_v_per_s": g})


OWN_MAP_REASON = ("without a given model the output map is fitted to this record and carries "
                  "any {what}; give another day's model (--model) to see it change")


@register
class Asymmetry(Candidate):
    name = "asymmetry"
    meaning = "the bending towards one side weakened or strengthened (a cracked electrode face)"

    def not_testable(self, rec, model, given):
        return None if given else OWN_MAP_REASON.format(what="asymmetry")

    def around(self, model, rec):
        m = copy.deepcopy(model)
        m.negative_gain_ = 1.0
        y0 = m.simulate(rec.u_fit)[rec.fit_obs]
        neg = y0 < 0
        if neg.sum() < 10:
            return "the model's output is hardly ever negative on the fit part"
        y = rec.y_fit[rec.fit_obs]
        m.negative_gain_ = float(np.clip((y0[neg] @ y[neg]) / (y0[neg] @ y0[neg]), 0.05, 20))
        return Fitted(m, {"negative_gain_ratio": m.negative_gain_ / model.negative_gain_})


@register
class Saturation(Candidate):
    name = "saturation"
    meaning = "a soft limit of the tip (a stop, a stiffening) beyond the model's output map"

    def not_testable(self, rec, model, given):
        return None if given else OWN_MAP_REASON.format(what="soft limit")

    def around(self, model, rec):
        peak = float(np.max(np.abs(model.simulate(rec.u_fit)[rec.fit_obs])))
        m, lim = scalar_around(model, rec, "limit_mm_", 0.3 * peak, 10.0 * peak)
        return Fitted(m, {"limit_mm": lim})
