"""The forward search: rounds of candidates around the current model, one decision each.

Round r fits every candidate not yet accepted around the current model (both fitted on the
same fit rows), judges them together by the rule of :mod:`.decision`, and accepts at most one;
the next round starts from the model with it. The search stops when a round accepts nothing.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
from scipy.stats import chi2

from ..hysteresis import DEFAULT_DIRECTION_MEMORY_V, GeneralizedPI
from .candidates import (
    CANDIDATES,
    Fitted,
    converged,
    effective_samples,
    fit_residual,
    fit_sse,
)
from .config import DiagnosisConfig
from .decision import holm, loss_differential_test, passes, power
from .experiment import design_experiment
from .parallel import fan_out, using
from .record import DiagnosisRecord
from .results import CandidateResult, Diagnosis, Evidence, FitScreen, Outcome, RecordShare, Round

#: Trust-region iterations of the core model's first fit and of its candidates' fresh refits
#: (with one start each): every round refits it many times, so the start grid's extra linear
#: fits would multiply the run time. The model a round starts from is then refitted warm
#: while that lowers its error (:func:`.candidates.converged`): 25 iterations can stop short
#: (a fresh fit of 150 reached half the fit error on some of the benchmark's records).
CORE_NFEV = 25


#: The charging time constant's starts of the core's joint fit, as multiples of its first
#: guess (30 samples): a fit of 25 iterations stays in the basin it starts in (on a smooth
#: input and a delayed plant one start ends at 18x the other's fit error), and at 50 Hz the
#: guess (0.6 s) lies above an IPMC's charging time (about 0.3 s). The lower blocked
#: free-run CV error wins: the lower fit error alone picked, on one record, a model whose
#: free run on another day's input was 9x the other's.
CORE_TAU_STARTS = (1.0 / 3.0, 1.0)


def core_model(rec: DiagnosisRecord) -> GeneralizedPI:
    """The diagnosis's own model: a GPI with the actuator's fast time scales only (charging,
    back-relaxation: below ``creep_min_tau_s``), no delay and no optional stage, fitted on the
    fit rows from each of :data:`CORE_TAU_STARTS` (side by side), the one with the lower
    blocked free-run CV error kept and converged there; the candidates are the stages it
    leaves out.

    By default it carries no direction memory (``core_direction_channels``): on a fit part of
    a few thousand samples the direction channels' weights are poorly determined, and refits
    with a candidate's block (a delay above all) overfit them (held-out error several times
    the blocked CV's), which would bias the loss differentials the decision rests on. Its
    plays' thresholds follow each channel's swing (``channel_thresholds``): a play its slower
    channel barely crosses moves once, a step in time that takes up a drift or a creep the
    candidates are there to name, and its free run leaves the fit range where the held-out
    part drives beyond it. Its output map is ``core_map`` (hinges by default)."""
    taus = rec.config.core_memory_taus_s
    channels = rec.config.core_direction_channels
    direction = ({"direction_memory_v": DEFAULT_DIRECTION_MEMORY_V,
                  "direction_channels": channels} if channels else {"direction_memory_v": ()})

    def fit_from(factor: float) -> GeneralizedPI:
        return GeneralizedPI(memory_taus_s=taus, delay_s=0.0, dt_s=rec.dt_s, **direction,
                             max_nfev=CORE_NFEV, map_basis=rec.config.core_map,
                             channel_thresholds=True,
                             start_tau_factors=(factor,)).fit(rec.u_fit, rec.y_fit)

    fits = fan_out(fit_from, CORE_TAU_STARTS)
    return converged(min(fits, key=lambda m: min(m.cv_.rmse)), rec)


def _given(model, rec: DiagnosisRecord) -> GeneralizedPI:
    from ..hysteresis import GpiInverse

    if isinstance(model, GpiInverse):
        model = model.model
    if not isinstance(model, GeneralizedPI):
        raise ValueError(f"a given model must be a GPI model (ipmc identify's default), not "
                         f"{type(model).__name__}; identify one with ipmc identify --data "
                         f"FILE --out MODEL")
    if abs(model.dt_s - rec.dt_s) > 0.01 * rec.dt_s:
        raise ValueError(f"the model runs at {1 / model.dt_s:.4g} Hz and the record at "
                         f"{1 / rec.dt_s:.4g} Hz; resample the record or identify a model at "
                         f"its rate")
    return model


def per_record(e_cur: np.ndarray, e_new: np.ndarray, rec: DiagnosisRecord,
               effect: str | None = None) -> tuple[RecordShare, ...]:
    """Each joined record's share of the judged held-out errors ``e_cur`` (current model)
    and ``e_new`` (with the candidate) over ``effect``'s judged rows; none for a single
    record (the round's figures are its own)."""
    if len(rec.segments) == 1:
        return ()
    at = np.flatnonzero(rec.judged_for(effect))
    out = []
    for s in rec.segments:
        k = (at >= s.start) & (at < s.stop)
        a, b = e_cur[k], e_new[k]
        gain = float(np.mean(a ** 2 - b ** 2)) if k.any() else float("nan")
        out.append(RecordShare(s.name, _rms(a) if k.any() else float("nan"),
                               _rms(b) if k.any() else float("nan"), gain))
    return tuple(out)


def _judged_on(rec: DiagnosisRecord, effect: str) -> str:
    """Where ``effect`` was judged, when not on every judged held-out row."""
    if effect not in rec.probe_rows:
        return ""
    return f"its probe's {int(rec.probe_rows[effect].sum())} held-out rows"


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e ** 2)))


def _try(name: str, current, rec, given) -> tuple[str | None, Fitted | str, str]:
    """(not-testable reason or None, fitted or why it could not be, a line of progress). A
    candidate the record cannot test is still fitted where it can be: as a rival, it keeps
    the round from naming another effect for a residual it would explain better."""
    cand = CANDIDATES[name]
    why = cand.not_testable(rec, current, given)
    t0 = time.perf_counter()
    out = cand.fit(current, rec, given)
    took = time.perf_counter() - t0
    if isinstance(out, str):
        return why, out, f"  {name}: {'not testable on this record: ' if why else ''}{out}"
    return why, out, (f"  {name}: fitted in {took:.1f} s"
                      + ("" if why is None else " (not testable on this record)"))


def fit_screen(current_sse: float, n_eff: float, candidate, model, rec, alpha: float
               ) -> FitScreen:
    """The fit rows' support for a candidate's block (:class:`FitScreen`)."""
    new_sse = fit_sse(model, rec)
    lr = n_eff * math.log(current_sse / new_sse) if new_sse > 0 else math.inf
    return FitScreen(float(lr), float(chi2.ppf(1.0 - alpha, candidate.n_params)),
                     float(n_eff), candidate.n_params,
                     float((current_sse - new_sse) / rec.fit_obs.sum()))


def run_round(number: int, current: GeneralizedPI, rec: DiagnosisRecord, names, given: bool,
              progress) -> tuple[Round, Fitted | None]:
    """One round: every candidate in ``names`` fitted around ``current`` and judged."""
    cfg = rec.config
    y_cur = current.simulate(rec.u_v)
    margin = rec.margin_mm2
    r_fit = fit_residual(current, rec)
    sse_fit, n_eff = float(r_fit @ r_fit), effective_samples(r_fit)
    results, tested, untestable = {}, {}, {}
    # each candidate is fitted around the same model: on as many cores as allowed
    fits = fan_out(lambda name: _try(name, current, rec, given), names,
                   costs=[CANDIDATES[n].refits for n in names])
    for name, (why, out, line) in zip(names, fits, strict=True):
        progress(line)
        if why is not None:
            untestable[name] = why
        if isinstance(out, str):
            results[name] = (CandidateResult(name, Outcome.NOT_TESTABLE, why, number)
                             if why is not None else
                             CandidateResult(name, Outcome.REJECTED, out, number))
            continue
        e_cur = rec.judged_error(y_cur, name)
        e_new = rec.judged_error(out.model.simulate(rec.u_v), name)
        test = loss_differential_test(e_cur, e_new, margin, rec.judged_segments(name))
        screen = fit_screen(sse_fit, n_eff, CANDIDATES[name], out.model, rec, cfg.family_alpha)
        tested[name] = (out, Evidence(_rms(e_cur), _rms(e_new), test, out.params, out.scan,
                                      screen=screen,
                                      records=per_record(e_cur, e_new, rec, name),
                                      judged_on=_judged_on(rec, name)))
    # the family is the candidates the round may accept and the fit rows support; rivals
    # (not testable) are tested beside it
    screened = {n: ev for n, (_, ev) in tested.items() if ev.screen.passed}
    # alpha spread over the family in proportion to each block's z on the fit rows
    # (sqrt of its likelihood ratio): fixed before the held-out rows are looked at
    weights = {n: math.sqrt(ev.screen.likelihood_ratio) for n, ev in screened.items()
               if n not in untestable}
    p_adj = holm({n: screened[n].test.p_value for n in weights}, weights)
    p_adj.update({n: ev.test.p_value for n, ev in screened.items() if n in untestable})
    passing = [n for n in screened if passes(tested[n][1].test, p_adj[n], cfg.family_alpha)]
    best = max(passing, key=lambda n: tested[n][1].test.mean_gain_mm2, default=None)
    # a candidate's share of the family's alpha at Holm's first step
    total = sum(weights.values())
    share = {n: w / total for n, w in weights.items()}
    for name, (_, ev) in tested.items():
        ev = replace(ev, p_holm=p_adj.get(name, 1.0))
        outcome, reason = _verdict(name, ev, best, passing, cfg.family_alpha, untestable)
        res = CandidateResult(name, outcome, reason, number, ev)
        short = (_too_few(res, cfg, share.get(name, 1.0), rec, current)
                 if outcome is Outcome.REJECTED and name not in passing else None)
        results[name] = (replace(res, outcome=Outcome.NOT_TESTABLE, reason=f"{short} ({reason})")
                         if short else res)
    accepted = best if best is not None and best not in untestable else None
    rnd = Round(number, _rms(rec.judged_error(y_cur)), tuple(results[n] for n in names),
                accepted)
    return rnd, (tested[accepted][0] if accepted else None)


def _too_few(res: CandidateResult, cfg: DiagnosisConfig, share: float, rec: DiagnosisRecord,
             current: GeneralizedPI) -> str | None:
    """Why the held-out rows cannot decide a block the fit rows support (the test's power
    at the gain they show is below ``min_power``), if they cannot and a probe can; None if
    the rejection stands."""
    sc, t = res.evidence.screen, res.evidence.test
    # a gain below the materiality margin is rejected however many rows there were
    if not (sc.passed and t.mean_gain_mm2 > 0 and sc.mean_gain_mm2 >= t.margin_mm2):
        return None
    level = cfg.family_alpha * share   # its level at Holm's first step
    pw = power(t, sc.mean_gain_mm2, level)
    if pw >= cfg.min_power or CANDIDATES[res.name].probe(rec, current, res) is None:
        return None
    return (f"undecided: the held-out rows are too few to decide it; at the gain the fit "
            f"rows show ({sc.mean_gain_mm2:.3g} mm^2) the test would pass with probability "
            f"{pw:.0%} (< {cfg.min_power:.0%}); record its probe")


def _verdict(name, ev: Evidence, best, passing, alpha, untestable) -> tuple[Outcome, str]:
    t, sc = ev.test, ev.screen
    on = f" on {ev.judged_on}" if ev.judged_on else ""
    text = (f"held-out RMSE{on} {ev.rmse_current_mm:.4f} -> {ev.rmse_candidate_mm:.4f} mm, mean "
            f"gain {t.mean_gain_mm2:.3g} mm^2 (margin {t.margin_mm2:.3g}; about the held-out "
            f"mean {t.centred_gain_mm2:.3g}), DM p = "
            f"{t.p_value:.2g}, Holm p = {ev.p_holm:.2g}; fit rows: likelihood ratio "
            f"{sc.likelihood_ratio:.3g} (needs {sc.needed:.3g})")
    if name in untestable:
        what = ("it would explain the residual best: undecided until such a record is made"
                if name == best else "as a rival only")
        return Outcome.NOT_TESTABLE, f"{untestable[name]} ({text}; {what})"
    if name == best:
        return Outcome.ACCEPTED, text
    if name in passing:
        rival = " (not testable on this record)" if best in untestable else ""
        return Outcome.REJECTED, f"{text}; passed, but {best}{rival} gained more this round"
    if not sc.passed:
        return Outcome.REJECTED, (f"{text}; the fit rows do not support the block "
                                  f"({sc.effective_samples:.0f} effective samples)")
    if ev.p_holm > alpha:
        return Outcome.REJECTED, f"{text}; not significant at {alpha:g} after Holm"
    gains = " and its gain ".join(t.short_of_margin)
    return Outcome.REJECTED, f"{text}; significant, but below the margin: its gain {gains}"


def _with_params(rnd: Round, params: dict) -> Round:
    """``rnd`` with its accepted candidate's parameters updated by ``params``."""
    def update(r: CandidateResult) -> CandidateResult:
        if r.name != rnd.accepted or r.evidence is None:
            return r
        return replace(r, evidence=replace(r.evidence, params={**r.evidence.params, **params}))
    return replace(rnd, results=tuple(update(r) for r in rnd.results))


def _withdrawn(rnd: Round, refined) -> Round:
    """``rnd`` with its accepted candidate rejected: its estimate on every row
    (``refined``) lies outside the effect's physical range."""
    def update(r: CandidateResult) -> CandidateResult:
        if r.name != rnd.accepted:
            return r
        ev = replace(r.evidence, params={**r.evidence.params, **refined.params})
        return replace(r, outcome=Outcome.REJECTED, evidence=ev,
                       reason=f"{r.reason}; {refined.outside}")
    return replace(rnd, results=tuple(update(r) for r in rnd.results),
                   accepted=None)


def with_known(current: GeneralizedPI, rec: DiagnosisRecord, known: list[str], given: bool,
               say) -> tuple[GeneralizedPI, tuple[str, ...]]:
    """``current`` with the blocks of the ``known`` effects fitted on the fit rows (each as its
    candidate fits it), and the effects that could be fitted."""
    done = []
    for name in known:
        out = CANDIDATES[name].fit(current, rec, given)
        if isinstance(out, str):
            say(f"known effect {name} not fitted on this record: {out}")
            continue
        current = out.model if given else converged(out.model, rec)
        done.append(name)
        say(f"known effect {name}: fitted into the starting model ({out.scan or 'refit'})")
    return current, tuple(done)


def diagnose(t_s, u_v, y_mm, *, model=None, config: DiagnosisConfig | None = None,
             candidates=None, progress=None, jobs: int | None = None) -> Diagnosis:
    """Diagnose one record: the missing effects of ``model`` (another day's GPI, frozen) or
    of the diagnosis's own core model, by rounds of the one decision rule.

    ``candidates``: names from :data:`CANDIDATES` (default all). ``progress(text)`` hears of
    each stage. ``jobs``: as :func:`diagnose_records`'.
    """
    return diagnose_records([("record", t_s, u_v, y_mm)], model=model, config=config,
                            candidates=candidates, progress=progress, jobs=jobs)


def diagnose_records(records, *, model=None, config: DiagnosisConfig | None = None,
                     candidates=None, progress=None, known=(), jobs: int | None = None
                     ) -> Diagnosis:
    """Diagnose several records ``(name, t_s, u_v, y_mm)`` at once, as :func:`diagnose` one:
    every model is fitted on the fit parts of all (joined by rests at 0 V,
    :class:`DiagnosisRecord`) and judged on the held-out parts of all.

    ``known``: effects an earlier record decided (``ipmc investigate``'s earlier rounds).
    Those these records cannot test are carried: their blocks are in the model the rounds
    start from, fitted on these fit rows, and not judged again (a record made to decide
    another effect need not be able to show them, and a model without them would carry their
    error into every other candidate's test). Those these records can test are judged again
    with the rest: the newer record, as a rule longer, decides them anew.

    ``jobs``: worker processes for a round's candidates and a profile's refits (None: the
    cores this process may use; the result is the same for any number)."""
    with using(jobs):
        return _diagnose_records(records, model, config, candidates, progress, known)


def _diagnose_records(records, model, config, candidates, progress, known) -> Diagnosis:
    say = progress or (lambda text: None)
    t0 = time.perf_counter()
    cfg = config or DiagnosisConfig()
    rec = DiagnosisRecord.joined(records, cfg)
    names = list(CANDIDATES if candidates is None else candidates)
    unknown = [n for n in names if n not in CANDIDATES]
    if unknown:
        raise ValueError(f"unknown candidate effects {unknown}; known: {list(CANDIDATES)}")
    given = model is not None
    if given:
        current = _given(model, rec)
    else:
        say(f"fitting the core model on {int(rec.fit_rows.sum())} samples "
            f"({', '.join(f'the first {s.cut - s.start} of {s.name}' for s in rec.segments)})")
        current = core_model(rec)
    carried = []
    for name in (n for n in known if n in names):
        if CANDIDATES[name].not_testable(rec, current, given) is None:
            say(f"known effect {name}: this record can test it; judged again")
        else:
            carried.append(name)
    current, known = with_known(current, rec, carried, given, say)
    names = [n for n in names if n not in known]
    d = Diagnosis(rec.t_s, rec.u_v, rec.y_mm, rec.held_rows, rec.segments, cfg, given,
                  current, current, known=known,
                  noise_floor_mm=rec.excitation.noise_floor_mm,
                  excitation=rec.excitation.as_dict())
    for number in range(1, cfg.max_rounds + 1):
        if not names:
            break
        say(f"round {number}: {', '.join(names)}")
        rnd, fitted = run_round(number, current, rec, names, given, say)
        d.rounds.append(rnd)
        if fitted is None:
            break
        say(f"round {number}: {rnd.accepted} passed; estimating it on every row")
        refined = CANDIDATES[rnd.accepted].refine(current, fitted.model, rec, given)
        names.remove(rnd.accepted)
        if refined is not None and refined.outside:
            say(f"round {number}: {rnd.accepted} rejected: {refined.outside}")
            d.rounds[-1] = _withdrawn(rnd, refined)
            continue   # the rest are judged again around the same model
        say(f"round {number}: accepted {rnd.accepted}")
        current = fitted.model
        if refined is not None:
            d.rounds[-1] = _with_params(rnd, refined.params)
            current = refined.model or current
        if not given:   # a given model stays frozen; the own model is the next start
            current = converged(current, rec)
    d.model_after = current
    d.next_experiment = design_experiment(d, rec)
    d.seconds = time.perf_counter() - t0
    return d
