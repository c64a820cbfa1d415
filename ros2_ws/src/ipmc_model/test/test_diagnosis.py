"""Tests of ipmc_model.diagnosis: the decision rule, the candidates, the search, the report."""

from __future__ import annotations

import copy
import json
import os
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from ipmc_driver.dataio import Record, save_csv
from ipmc_driver.plant import IpmcPlant
from ipmc_driver.signals import random_sine, random_steps
from ipmc_model.diagnose_cli import main
from ipmc_model.diagnosis import CANDIDATES, Candidate, DiagnosisConfig, Fitted, Outcome
from ipmc_model.diagnosis import diagnose as run_diagnosis
from ipmc_model.diagnosis.decision import holm, loss_differential_test
from ipmc_model.diagnosis.record import DiagnosisRecord
from ipmc_model.diagnosis.search import core_model
from ipmc_model.persistence import load_model

RATE = 50.0


def plant_record(effects, seconds: float, seed: int, holds: bool = False) -> Record:
    """A random sine on random steps (the sine off during every other step with ``holds``)."""
    _, us = random_sine(seconds, RATE, 2.5, (0.05, 1.0), 8, seed=seed + 2)
    _, st = random_steps(seconds, RATE, 1.5, (3.0, 10.0), seed=seed + 3)
    if holds:
        us = us * (np.cumsum(np.r_[0, np.diff(st) != 0]) % 2 == 0)
    u = np.clip(0.6 * us + st, -3, 3)
    run = IpmcPlant(effects=effects, seed=seed, dt_s=1 / RATE).run(u)
    return Record(run.t_s, u, run.y_mm)


def diagnose(rec: Record, **kw):
    return run_diagnosis(rec.t_s, rec.u_v, rec.y_mm, **kw)


def test_loss_differential_test_tells_a_better_model_from_an_equal_one():
    rng = np.random.default_rng(0)
    slow = np.convolve(rng.normal(size=4000), np.ones(50) / 50, mode="same")
    e_cur = slow + 0.01 * rng.normal(size=4000)
    better = loss_differential_test(e_cur, 0.3 * slow + 0.01 * rng.normal(size=4000), 0.0)
    other = np.convolve(rng.normal(size=4000), np.ones(50) / 50, mode="same")
    same = loss_differential_test(e_cur, other + 0.01 * rng.normal(size=4000), 0.0)
    assert better.p_value < 1e-3 and better.mean_gain_mm2 > 0
    assert same.p_value > 0.05
    # the bandwidth follows the differential's autocorrelation (a 50-sample moving average)
    assert better.bandwidth_samples >= 20


def test_loss_differential_test_is_not_significant_on_autocorrelated_noise_too_often():
    """Under the null (two models equally good, slow errors) the 5 % test rejects about 5 %."""
    rng = np.random.default_rng(1)
    rejected = 0
    for _ in range(200):
        a = np.convolve(rng.normal(size=2000), np.ones(30) / 30, mode="same")
        b = np.convolve(rng.normal(size=2000), np.ones(30) / 30, mode="same")
        rejected += loss_differential_test(a, b, 0.0).p_value < 0.05
    assert rejected <= 25  # 12.5 %: a naive i.i.d. t test rejects far more on these


def test_a_held_out_offset_counts_as_one_draw_per_record_not_as_many():
    """A block that only moves the level of each record's held-out error (an offset the
    model's slow misfit leaves there) is neither significant nor material however many rows
    carry it; one that follows the error's course but moves its level away is significant
    and not material."""
    rng = np.random.default_rng(3)
    slow = np.convolve(rng.normal(size=4000), np.ones(50) / 50, mode="same")
    records = np.repeat([0, 1], 2000)
    offset = np.where(records == 0, 0.05, -0.03)
    noise = 0.005 * rng.normal(size=4000)
    level = loss_differential_test(slow + offset, slow + noise, 1e-4, records)
    assert level.mean_gain_mm2 > 1e-3 and not level.material
    assert level.p_value > 0.05
    # taken as one record, the step between the two offsets is a course the block explains
    assert loss_differential_test(slow + offset, slow + noise, 1e-4).p_value < 0.01
    course = loss_differential_test(slow, 0.3 * slow + 0.3, 1e-4, records)
    assert course.p_value < 1e-3 and course.centred_gain_mm2 > 0
    assert course.mean_gain_mm2 < 0 and not course.material


def test_a_tested_gain_below_the_margin_is_not_material_beside_a_large_offset_gain():
    """Materiality is judged on what the test found significant: a block that removes each
    record's held-out offset and a sliver of the error's course is significant on that sliver
    (many rows carry it), and its gain as the errors are is far above the margin, but its
    gain about the held-out means is below it: not material. The same sliver's gain above
    the margin is."""
    rng = np.random.default_rng(4)
    slow = np.convolve(rng.normal(size=8000), np.ones(40) / 40, mode="same")
    records = np.repeat([0, 1], 4000)
    offset = np.where(records == 0, 0.2, -0.1)
    margin = 0.1 * float(np.mean(slow ** 2))
    sliver = loss_differential_test(slow + offset, 0.97 * slow, margin, records)
    assert sliver.p_value < 0.01 and sliver.mean_gain_mm2 > 5 * margin
    assert 0 < sliver.centred_gain_mm2 < margin and not sliver.material
    course = loss_differential_test(slow + offset, 0.5 * slow, margin, records)
    assert course.centred_gain_mm2 > margin and course.material


def test_a_rejection_for_materiality_names_the_gain_that_fell_short():
    from ipmc_model.diagnosis.results import Evidence, FitScreen, LossTest, Outcome
    from ipmc_model.diagnosis.search import _verdict

    def verdict(gain, centred):
        test = LossTest(gain, 4.0, 1e-4, 10, 1e-4, 1e-5, centred)
        ev = Evidence(0.02, 0.01, test, {}, p_holm=1e-4,
                      screen=FitScreen(50.0, 3.84, 300.0, 1, 2e-4))
        return _verdict("drift", ev, None, [], 0.05, {})

    outcome, reason = verdict(5e-4, 5e-5)   # a level gain beside a tiny tested one
    assert outcome is Outcome.REJECTED
    assert reason.endswith("below the margin: its gain about the held-out mean")
    assert verdict(5e-5, 5e-4)[1].endswith("below the margin: its gain of the errors as they are")
    assert verdict(5e-5, 5e-5)[1].endswith(
        "below the margin: its gain about the held-out mean and its gain of the errors as they "
        "are")


def test_the_power_of_the_held_out_test_follows_its_standard_error():
    from ipmc_model.diagnosis.decision import power

    rng = np.random.default_rng(2)
    slow = np.convolve(rng.normal(size=3000), np.ones(40) / 40, mode="same")
    test = loss_differential_test(1.2 * slow, slow, 0.0)
    n = slow.size   # the standard error is the one the statistic divides by
    assert test.centred_gain_mm2 / test.standard_error_mm2 * np.sqrt((n - 1) / n) == \
        pytest.approx(test.statistic)
    assert power(test, 0.0, 0.05) == pytest.approx(0.05)
    assert power(test, 4.0 * test.standard_error_mm2, 0.05) > 0.9
    assert power(test, 1.0 * test.standard_error_mm2, 0.05) < 0.3


def test_holm_adjusts_as_the_step_down_defines():
    adj = holm({"a": 0.01, "b": 0.04, "c": 0.03})
    assert adj == pytest.approx({"a": 0.03, "c": 0.06, "b": 0.06})
    assert holm({"a": 0.01, "b": 0.04, "c": 0.03}, {"a": 2.0, "b": 2.0, "c": 2.0}) == adj
    # weighted: order by p / w, each step's level w / (the weights left) x alpha
    adj = holm({"a": 0.013, "b": 0.01, "c": 0.5}, {"a": 8.0, "b": 1.0, "c": 1.0})
    assert adj == pytest.approx({"a": 10 * 0.013 / 8, "b": 0.02, "c": 0.5})
    with pytest.raises(ValueError, match="positive"):
        holm({"a": 0.01}, {"a": 0.0})


def test_weighted_holm_holds_the_family_wise_error():
    """Weights fixed before the p-values are drawn: under the null (uniform p-values) the
    chance that any hypothesis is rejected at 0.05 stays within 0.05."""
    rng = np.random.default_rng(3)
    weights = {"a": 25.0, "b": 2.0, "c": 2.0, "d": 1.0}
    hits = sum(min(holm(dict(zip(weights, rng.uniform(size=4), strict=True)),
                        weights).values()) <= 0.05 for _ in range(4000))
    assert 0.03 < hits / 4000 <= 0.05 + 2 * np.sqrt(0.05 * 0.95 / 4000)


def test_config_refuses_thresholds_out_of_range():
    with pytest.raises(ValueError, match="family_alpha"):
        DiagnosisConfig(family_alpha=0.7)
    with pytest.raises(ValueError, match="hold_min_s"):
        DiagnosisConfig(hold_min_s=0.0)
    with pytest.raises(ValueError, match="core_direction_channels"):
        DiagnosisConfig(core_direction_channels=7)
    with pytest.raises(ValueError, match="core_map must be one of"):
        DiagnosisConfig(core_map="cubic")


def test_the_core_carries_direction_memory_on_the_channels_the_config_asks():
    # default none; with N channels the identify default's travels on the N fastest, and the
    # fit gives them weights; the config the report writes names the choice
    from ipmc_model.diagnosis.search import core_model
    from ipmc_model.hysteresis import DEFAULT_DIRECTION_MEMORY_V

    r = plant_record({}, 60.0, 4)
    plain = core_model(DiagnosisRecord(r.t_s, r.u_v, r.y_mm, DiagnosisConfig()))
    assert plain.direction_memory_v == () and plain.n_direction_channels == 0
    assert plain.map_basis == "linear"   # DiagnosisConfig.core_map
    spline = DiagnosisRecord(r.t_s, r.u_v, r.y_mm, DiagnosisConfig(core_map="quadratic"))
    assert core_model(spline).map_basis == "quadratic"
    rec = DiagnosisRecord(r.t_s, r.u_v, r.y_mm, DiagnosisConfig(core_direction_channels=1))
    core = core_model(rec)
    assert core.direction_memory_v == DEFAULT_DIRECTION_MEMORY_V
    assert core.n_direction_channels == 1
    assert core.weights_.size == plain.weights_.size + len(DEFAULT_DIRECTION_MEMORY_V)
    from ipmc_model.diagnosis.report import summary_of
    from ipmc_model.diagnosis.results import Diagnosis

    d = Diagnosis(rec.t_s, rec.u_v, rec.y_mm, rec.held_rows, rec.segments, rec.config, False,
                  core, core)
    assert summary_of(d, {})["config"]["core_direction_channels"] == 1


def test_a_clean_record_has_nothing_and_a_dead_zone_is_found_with_its_width():
    # 240 s: the length of the benchmark's records
    clean = diagnose(plant_record({}, 240.0, 0))
    assert clean.effects_found == []
    dz = diagnose(plant_record({"dead_zone": {"width_v": 0.4}}, 240.0, 0))
    assert dz.effects_found == ["dead_zone"]
    width = dz.model_after.dead_zone_v
    assert abs(width - 0.4) < 0.03
    # its 95 % interval, from the profile of refits around the accepted width, holds the
    # model's width and reaches within the estimate's error of the plant's: the profile
    # carries the record's noise, not the core's misfit of the plant's structure (0.38 V,
    # 95 % 0.377-0.398 on this record)
    p = next(r for r in dz.candidates if r.name == "dead_zone").evidence.params
    lo, hi = p["width_ci_v"]
    assert lo <= p["width_v"] == width <= hi and hi - lo < 0.2
    assert lo - 0.03 < 0.4 < hi + 0.03
    assert p["width_ci_open"] == [False, False]
    assert dz.rmse_after_mm < 0.5 * dz.rmse_before_mm
    assert dz.rmse_after_mm < 2.0 * clean.rmse_after_mm


def test_the_model_a_round_starts_from_is_converged_on_the_fit_rows():
    # a fit stopped after 3 iterations is far from its optimum; converged() refits it warm
    # until another refit gains less than chi2(1)'s median in the fit rows' likelihood ratio
    from ipmc_model.diagnosis.candidates import (
        CONVERGED_LR,
        converged,
        effective_samples,
        fit_sse,
        warm_refit,
    )
    from ipmc_model.hysteresis import GeneralizedPI

    r = plant_record({}, 120.0, 3, holds=True)
    rec = DiagnosisRecord(r.t_s, r.u_v, r.y_mm, DiagnosisConfig())
    short = GeneralizedPI(memory_taus_s=(0.05, 0.15, 0.5), delay_s=0.0, dt_s=1 / RATE,
                          direction_memory_v=(), max_nfev=3, start_tau_factors=(1.0,)
                          ).fit(rec.u_fit, rec.y_fit)
    done = converged(short, rec)
    assert fit_sse(done, rec) < 0.8 * fit_sse(short, rec)
    e = (done.simulate(rec.u_fit) - rec.y_fit)[rec.fit_obs]
    again = fit_sse(warm_refit(done, rec), rec)
    assert effective_samples(e) * np.log(fit_sse(done, rec) / again) < 2 * CONVERGED_LR


def test_a_known_effect_this_record_cannot_test_is_carried_and_one_it_can_is_judged_again():
    # an earlier record decided a creep (this one has no holds) and a dead zone (this one
    # dwells near 0 V): the creep is in the starting model, the dead zone is judged again
    from ipmc_model.diagnosis.search import diagnose_records

    fx = {"creep": {"tau_s": 12.0, "gain_mm_per_v": -0.6}, "dead_zone": {"width_v": 0.4}}
    r = plant_record(fx, 240.0, 0)
    d = diagnose_records([("record", r.t_s, r.u_v, r.y_mm)], known=("creep", "dead_zone"),
                         candidates=["creep", "dead_zone"])
    assert d.known == ("creep",) and d.model_before.output_taus_s
    assert [c.name for c in d.candidates] == ["dead_zone"] and d.effects_found == ["dead_zone"]
    plain = diagnose_records([("record", r.t_s, r.u_v, r.y_mm)], candidates=["dead_zone"])
    assert d.rmse_before_mm < 0.8 * plain.rmse_before_mm


def test_a_profile_interval_is_where_the_deviance_stays_within_chi2():
    """A deviance n_eff ln(SSE / SSE_min) = ((x - c) / s)^2 has the 95 % interval
    c -+ 1.96 s: interpolated on a grid that traces it, from the parabola when it lies
    within the best point's neighbours, open where the grid's edge cuts it."""
    from ipmc_model.diagnosis.candidates import Profile

    def profile(x, c, s):
        return Profile(x, [None] * x.size, np.exp(((x - c) / s) ** 2 / 100.0), 100.0)

    x = np.linspace(-1.0, 1.0, 41)
    est, (lo, hi), opened = profile(x, 0.13, 0.3).interval()
    assert est == pytest.approx(0.15) and opened == (False, False)
    assert lo == pytest.approx(0.13 - 1.96 * 0.3, abs=0.01)
    assert hi == pytest.approx(0.13 + 1.96 * 0.3, abs=0.01)
    est, (lo, hi), opened = profile(np.linspace(-1.0, 1.0, 9), 0.26, 0.05).interval()
    assert est == pytest.approx(0.26) and opened == (False, False)
    assert (lo, hi) == pytest.approx((0.26 - 1.96 * 0.05, 0.26 + 1.96 * 0.05), rel=1e-4)
    # no narrower than the parameter's resolution about the best point
    g = np.linspace(0.0, 0.3, 7)
    sharp = Profile(g, [None] * g.size, np.exp(((g - 0.13) / 0.002) ** 2 / 100.0), 100.0, 0.05)
    assert sharp.interval()[1] == pytest.approx((0.15 - 0.025, 0.15 + 0.025))
    est, (lo, hi), opened = profile(np.linspace(0.0, 1.0, 11), -0.2, 0.3).interval()
    assert opened == (True, False) and lo == 0.0 and est == 0.0
    # relative to the grid's best point (the deviance there is (0.2 / 0.3)^2 above its own)
    assert hi == pytest.approx(-0.2 + 0.3 * np.sqrt(1.96 ** 2 + (0.2 / 0.3) ** 2), abs=0.01)


def test_creep_needs_holds_and_is_found_on_them():
    fx = {"creep": {"tau_s": 12.0, "gain_mm_per_v": -0.6}}
    moving = diagnose(plant_record(fx, 150.0, 1))
    creep = next(r for r in moving.candidates if r.name == "creep")
    assert creep.outcome is Outcome.NOT_TESTABLE and "holds" in creep.reason
    assert "creep" not in moving.effects_found
    held = diagnose(plant_record(fx, 150.0, 1, holds=True))
    assert held.effects_found[:1] == ["creep"]
    assert held.rmse_after_mm < 0.3 * held.rmse_before_mm
    # one relaxation's time constant with its 95 % interval, around the plant's 12 s
    p = next(r for r in held.candidates if r.name == "creep").evidence.params
    lo, hi = p["tau_ci_s"]
    assert lo < 12.0 < hi and lo <= p["tau_s"] <= hi and hi - lo < 6.0
    assert p["tau_ci_open"] == [False, False]   # both ends set by the data
    assert held.next_experiment is None or "creep" not in held.next_experiment.decides
    assert p["gain_ci_mm_per_v"][0] < p["gain_mm_per_v"] < p["gain_ci_mm_per_v"][1] < 0
    # the model after it is that one relaxation, not the test's bank of fixed time constants
    assert held.model_after.output_taus_s[-1:] == (pytest.approx(p["tau_s"]),)
    assert p["taus_s"] == [p["tau_s"]]


def test_the_model_an_accepted_creep_leaves_generalises_as_the_one_that_passed():
    """The creep's costlier estimate (one relaxation, profiled over tau) must not leave a
    model that predicts the held-out rows worse than the one the rule accepted: the next
    round would find a drift in what it lost. On this record the core fitted without the
    creep is a poor start for the profile (its refits stay in that core's basin)."""
    fx = {"creep": {"tau_s": 12.0, "gain_mm_per_v": -0.6}}
    d = diagnose(plant_record(fx, 150.0, 1, holds=True))
    assert d.effects_found == ["creep"]
    passed = next(r for r in d.rounds[0].results if r.name == "creep").evidence
    assert d.rounds[1].rmse_start_mm <= 1.2 * passed.rmse_candidate_mm


def test_a_creep_accepted_beside_a_charging_current_channel_is_profiled_with_it():
    """The creep's profile starts from the accepted model less its bank; the charging-current
    channel, first among the output channels, stays with its gain."""
    fx = {"creep": {"tau_s": 20.0, "gain_mm_per_v": -0.3},
          "rate_dependence": {"gain_mm_per_v_per_s": 0.15}}
    rec_ = plant_record(fx, 150.0, 1, holds=True)
    rec = DiagnosisRecord(rec_.t_s, rec_.u_v, rec_.y_mm, DiagnosisConfig())
    before = CANDIDATES["rate_dependence"].refit(core_model(rec), rec).model
    after = CANDIDATES["creep"].refit(before, rec).model
    refined = CANDIDATES["creep"].refine(before, after, rec, False)
    m = refined.model
    assert m.output_rate and len(m.output_taus_s) == 1
    assert m.output_coef_.size == m.n_output_channels == 2
    assert 10.0 <= refined.params["tau_s"] and refined.params["gain_mm_per_v"] < 0


def test_samples_lost_on_the_link_are_rows_the_models_run_through_not_fitted_or_judged():
    """A record that lost stretches of samples (y NaN, the voltage held: dataio.fill_gaps)
    is diagnosed on its measured rows: the creep is found as on the whole record."""
    fx = {"creep": {"tau_s": 12.0, "gain_mm_per_v": -0.6}}
    whole = plant_record(fx, 150.0, 1, holds=True)
    y = whole.y_mm.copy()
    lost = np.r_[1000:1042, 4100:4150, 6000:6010]    # in the fit part and the held-out part
    y[lost] = np.nan
    rec = DiagnosisRecord(whole.t_s, whole.u_v, y, DiagnosisConfig())
    assert not np.any((rec.fit_rows | rec.held_rows | rec.judged)[lost])
    assert rec.fit_rows.sum() + rec.held_rows.sum() == whole.u_v.size - lost.size
    assert np.isfinite(rec.excitation.noise_floor_mm)
    held = diagnose(Record(whole.t_s, whole.u_v, y))
    assert held.effects_found[:1] == ["creep"]
    assert held.rmse_after_mm < 0.3 * held.rmse_before_mm
    assert all(np.isfinite(v) for v in held.record_rmse(held.model_after).values())
    for measured_from_s, match in ((147.0, "measured samples are too few"),
                                   (140.0, "its fit part has no measured sample")):
        with pytest.raises(ValueError, match=match):
            DiagnosisRecord(whole.t_s, whole.u_v, np.where(whole.t_s < measured_from_s,
                                                           np.nan, y), DiagnosisConfig())


def test_fan_out_keeps_order_runs_closures_and_does_not_nest():
    from ipmc_model.diagnosis.parallel import fan_out, using

    offset = 10

    def inner(x):    # a closure; inside a worker a fan-out runs in that worker
        return fan_out(lambda k: (k + offset, os.getpid()), [x, x])

    with using(2) as jobs:
        out = fan_out(inner, [1, 2, 3])
    assert jobs == 2 and [[v for v, _ in pair] for pair in out] == [[11, 11], [12, 12], [13, 13]]
    assert all(pair[0][1] == pair[1][1] != os.getpid() for pair in out)
    with using(1):
        assert {pid for _, pid in fan_out(lambda k: (k, os.getpid()), [1, 2])} == {os.getpid()}
    with pytest.raises(ValueError, match="jobs must be >= 1"), using(0):
        pass


@pytest.mark.timeout(30)   # a hang is the failure: the pool waited forever for its workers
def test_fan_out_ends_its_workers_while_a_ros_context_is_live():
    """rclpy's SIGTERM handler, which a fork inherits, kept a pool's idle worker from ending
    when the pool was torn down; the pool must end its workers after the work and after a
    failing item."""
    import rclpy

    from ipmc_model.diagnosis.parallel import fan_out, using

    def fails_on_one(k):
        if k == 1:
            raise RuntimeError("fit failed")
        return k

    owned = not rclpy.ok()   # the default context: the one whose init installs the handlers
    if owned:
        rclpy.init()
    try:
        with using(2):
            for _ in range(10):   # the hang was a race between a worker's end and the signal
                assert fan_out(lambda k: k * 2, [1, 2, 3]) == [2, 4, 6]
            with pytest.raises(RuntimeError, match="fit failed"):
                fan_out(fails_on_one, [0, 1, 2, 3])
    finally:
        if owned:
            rclpy.shutdown()


def test_a_diagnosis_on_two_workers_is_the_one_in_process():
    rec = plant_record({"dead_zone": {"width_v": 0.4}}, 100.0, 2)
    names = ["drift", "dead_zone"]
    one, two = (diagnose(rec, candidates=names, jobs=j) for j in (1, 2))
    assert one.effects_found == two.effects_found == ["dead_zone"]
    assert two.rmse_after_mm == pytest.approx(one.rmse_after_mm, rel=1e-6)
    for a, b in zip(one.candidates, two.candidates, strict=True):
        assert (a.name, a.outcome) == (b.name, b.outcome)
        assert b.evidence.test.p_value == pytest.approx(a.evidence.test.p_value, rel=1e-4,
                                                         abs=1e-12)


def test_a_creep_the_held_out_rows_are_too_few_to_decide_is_undecided_with_its_probe():
    """A 20 s creep of -0.08 mm/V on 3-10 s holds: the fit rows support the block, but 72 s
    of held-out rows cannot make the test pass at the gain they show; undecided, not
    rejected, and the next experiment holds for it (at -0.1 mm/V these rows accept it)."""
    fx = {"creep": {"tau_s": 20.0, "gain_mm_per_v": -0.08}}
    d = diagnose(plant_record(fx, 240.0, 29, holds=True), candidates=["creep", "drift"])
    creep = next(r for r in d.candidates if r.name == "creep")
    assert creep.outcome is Outcome.NOT_TESTABLE and "too few to decide" in creep.reason
    ev = creep.evidence
    assert ev.screen.passed and ev.test.mean_gain_mm2 > 0 and ev.p_holm > 0.05
    assert "creep" in d.next_experiment.decides
    assert d.effects_found == []


def test_a_given_model_gets_the_block_of_what_changed_fitted_around_it():
    day1 = plant_record({}, 150.0, 2)
    rec1 = DiagnosisRecord(day1.t_s, day1.u_v, day1.y_mm, DiagnosisConfig())
    model = core_model(rec1)
    before = copy.deepcopy(model)
    day2 = plant_record({"asymmetry": {"negative_gain_ratio": 0.7}}, 150.0, 3)
    d = diagnose(day2, model=model)
    assert d.effects_found[:1] == ["asymmetry"]
    assert d.model_after.negative_gain_ == pytest.approx(0.7, abs=0.12)
    # the given model itself is not changed, and the held-out error drops
    assert np.array_equal(before.weights_, model.weights_)
    assert d.rmse_after_mm < 0.5 * d.rmse_before_mm


def test_rate_dependence_is_a_charging_current_channel_found_with_its_gain():
    """The plant's bending on top of the charge, 0.1 mm per V/s of its charging current: the
    own model and a clean day's given model each get one gain for it."""
    fx = {"rate_dependence": {"gain_mm_per_v_per_s": 0.1}}
    day1 = plant_record({}, 150.0, 4)
    given = core_model(DiagnosisRecord(day1.t_s, day1.u_v, day1.y_mm, DiagnosisConfig()))
    rec = plant_record(fx, 150.0, 7)
    for model in (None, given):
        d = diagnose(rec, model=model)
        assert d.effects_found[:1] == ["rate_dependence"]
        p = next(r for r in d.candidates if r.name == "rate_dependence").evidence.params
        assert p["gain_mm_per_v_per_s"] == pytest.approx(0.1, abs=0.025)
        assert d.rmse_after_mm < 0.5 * d.rmse_before_mm


def test_a_delay_the_core_took_up_as_slower_charging_is_scanned_to_its_length():
    """Without a delay the core model takes a 0.2 s one up as slower charging. The delay's
    scan refits it at each delay from where it is and lands on the plant's 10 samples (short
    refits from a fresh start stop far above the core's error, and a scan of them does not)."""
    from ipmc_model.diagnosis.candidates import fit_sse

    r = plant_record({"delay": {"delay_s": 0.2}}, 240.0, 0)
    rec = DiagnosisRecord(r.t_s, r.u_v, r.y_mm, DiagnosisConfig())
    core = core_model(rec)
    fitted = CANDIDATES["delay"].refit(core, rec)
    assert abs(fitted.params["delay_s"] - 0.2) <= 1.0 / RATE + 1e-9
    assert fit_sse(fitted.model, rec) < 0.5 * fit_sse(core, rec)


def test_rate_dependence_needs_a_charging_the_sampling_resolves():
    """On the Duhem plant, which has no charging lag, the core's charging settles within a
    sample or two, so a charging current would be the input's sample difference: not
    testable, with the rate that would resolve one. The IPMC's charging spans many samples."""
    from duhem_plant import duhem_plant

    ipmc = plant_record({}, 150.0, 4)
    rate = CANDIDATES["rate_dependence"]
    reasons = {}
    for name, y in (("ipmc", ipmc.y_mm), ("duhem", duhem_plant(ipmc.u_v, 4, 1 / RATE))):
        rec = DiagnosisRecord(ipmc.t_s, ipmc.u_v, y, DiagnosisConfig())
        model = core_model(rec)
        reasons[name] = rate.not_testable(rec, model, given=False)
    assert reasons["ipmc"] is None
    assert "sample difference" in reasons["duhem"] and "Hz or faster" in reasons["duhem"]
    model.rate_limit, model.charge_tau_s_ = False, 0.0   # a model without a charging stage
    assert "no charging stage" in rate.not_testable(rec, model, given=True)


def test_creep_around_a_given_model_with_slow_input_memory_is_one_relaxation():
    """Another day's model of ipmc identify's default family (input memory up to 36 s):
    creep that came since is still testable around it, fitted as one relaxation, and its
    parameters, estimated on the whole record once the held-out rows decided, hold the
    plant's; the clean twin names nothing."""
    from ipmc_model.hysteresis import GeneralizedPI

    day1 = plant_record({}, 240.0, 4, holds=True)
    model = GeneralizedPI(dt_s=1 / RATE).fit(day1.u_v, day1.y_mm)
    assert max(model.memory_taus_s_) >= 30.0
    fx = {"creep": {"tau_s": 20.0, "gain_mm_per_v": -0.3}}
    d = diagnose(plant_record(fx, 240.0, 5, holds=True), model=model)
    assert d.effects_found[:1] == ["creep"]
    p = next(r for r in d.candidates if r.name == "creep").evidence.params
    assert len(p["taus_s"]) == 1 and p["interval"] == "whole record"
    assert p["tau_ci_s"][0] < 20.0 < p["tau_ci_s"][1]
    assert p["gain_ci_mm_per_v"][0] < -0.3 < p["gain_ci_mm_per_v"][1]
    # Holm's family is the testable candidates the fit rows support, each weighted by its z
    # there (sqrt of the likelihood ratio): creep's p (the first step) is multiplied by the
    # family's weights over its own
    ev = next(r for r in d.rounds[0].results if r.name == "creep").evidence
    family = {r.name: r.evidence for r in d.rounds[0].results if r.evidence is not None
              and r.outcome is not Outcome.NOT_TESTABLE and r.evidence.screen.passed}
    assert ev.screen.passed and len(family) < len(d.rounds[0].results)
    w = {n: np.sqrt(e.screen.likelihood_ratio) for n, e in family.items()}
    assert min(family, key=lambda n: family[n].test.p_value / w[n]) == "creep"
    assert ev.p_holm == pytest.approx(min(1.0, sum(w.values()) * ev.test.p_value / w["creep"]))
    clean = diagnose(plant_record({}, 240.0, 5, holds=True), model=model)
    assert clean.effects_found == []


class GainChange(Candidate):
    """A toy effect: the whole bending scaled, fitted around a given model."""

    name = "gain_change"
    meaning = "the bending scaled by a constant (a toy effect for this test)"

    def around(self, model, rec):
        m = copy.deepcopy(model)
        y0 = m.simulate(rec.u_fit)[rec.fit_obs]
        k = float(y0 @ rec.y_fit[rec.fit_obs] / (y0 @ y0))
        m.map_coef_ = m.map_coef_ * k
        return Fitted(m, {"gain": k})


@contextmanager
def toy_effect(cls):
    """``cls`` registered for the block's duration, and a clean day's core model and a later
    day's record (its displacement to be scaled by the test)."""
    from ipmc_model.diagnosis import register

    register(cls)
    try:
        day1 = plant_record({}, 120.0, 4)
        yield (core_model(DiagnosisRecord(day1.t_s, day1.u_v, day1.y_mm, DiagnosisConfig())),
               plant_record({}, 120.0, 5))
    finally:
        CANDIDATES.pop(cls.name)


def test_a_new_effect_is_one_class_and_one_registry_line():
    with toy_effect(GainChange) as (model, day2):
        day2 = Record(day2.t_s, day2.u_v, 0.8 * day2.y_mm)
        d = diagnose(day2, model=model, candidates=["gain_change", "drift", "delay"])
        assert d.effects_found[:1] == ["gain_change"]
        found = next(r for r in d.candidates if r.name == "gain_change")
        assert found.evidence.params["gain"] == pytest.approx(0.8, abs=0.05)


class Weakening(GainChange):
    """A toy effect whose physical range is a bending that weakened (a gain below 1)."""

    name = "weakening"

    def refine(self, before, after, rec, given):
        from ipmc_model.diagnosis.candidates import Refined

        p = self.around(before, rec.whole()).params
        return Refined(p, outside=None if p["gain"] < 1.0 else "the bending grew")


def test_an_accepted_effect_estimated_outside_its_range_is_rejected_and_the_rest_judged():
    with toy_effect(Weakening) as (model, day2):
        grown = diagnose(Record(day2.t_s, day2.u_v, 1.25 * day2.y_mm), model=model,
                         candidates=["weakening", "drift"])
        first = next(r for r in grown.rounds[0].results if r.name == "weakening")
        assert first.outcome is Outcome.REJECTED and "the bending grew" in first.reason
        assert first.evidence.params["gain"] == pytest.approx(1.25, abs=0.05)
        assert "weakening" not in grown.effects_found and grown.rounds[0].accepted is None
        # the rest are judged again around the model the round started from
        assert [r.name for r in grown.rounds[1].results] == ["drift"]
        assert grown.rounds[1].rmse_start_mm == grown.rounds[0].rmse_start_mm
        weak = diagnose(Record(day2.t_s, day2.u_v, 0.8 * day2.y_mm), model=model,
                        candidates=["weakening", "drift"])
        assert weak.effects_found[:1] == ["weakening"]


def test_a_charging_current_channel_that_bends_below_the_margin_is_outside_its_range():
    """Adding a block lowers the judged rows' mean squared error by at most its own mean
    square: a rate dependence whose channel bends less than the materiality margin passed on
    what its refit moved in the rest of the model, and is rejected; a real one is kept."""
    rec_ = plant_record({}, 60.0, 1)
    rec = DiagnosisRecord(rec_.t_s, rec_.u_v, rec_.y_mm, DiagnosisConfig())
    model = core_model(rec)
    cand = CANDIDATES["rate_dependence"]
    for gain, outside in ((1e-5, True), (0.1, False)):
        after = copy.deepcopy(model)
        after.output_rate, after.output_coef_ = True, np.r_[gain, model.output_coef_]
        refined = cand.refine(model, after, rec, False)
        assert (refined is not None and "below the materiality margin" in refined.outside) \
            is outside


def test_a_creep_whose_relaxation_is_faster_than_a_creep_is_outside_its_range():
    """The creep's time constant is estimated below the creep's range too: a relaxation
    faster than ``creep_min_tau_s`` that the test's bank took up is not named creep."""
    from ipmc_model.hysteresis import GeneralizedPI

    day1 = plant_record({}, 240.0, 4, holds=True)
    model = GeneralizedPI(dt_s=1 / RATE).fit(day1.u_v, day1.y_mm)
    creep = CANDIDATES["creep"]
    found = {}
    for tau_s in (4.0, 20.0):
        day2 = plant_record({"creep": {"tau_s": tau_s, "gain_mm_per_v": -0.4}}, 240.0, 5,
                            holds=True)
        rec = DiagnosisRecord(day2.t_s, day2.u_v, day2.y_mm, DiagnosisConfig())
        found[tau_s] = creep.refine(model, model, rec, given=True)
    assert found[4.0].params["tau_s"] < 10.0 and "faster than a creep" in found[4.0].outside
    assert found[20.0].outside is None and found[20.0].params["tau_s"] > 10.0


def test_a_dead_zone_narrower_than_its_scan_resolves_is_outside_its_range():
    """A width below the dead-zone scan's resolution bends the tip less than the sensor
    resolves: a block that small took up a misfit of the model, and is not named."""
    from ipmc_model.diagnosis.candidates import DEAD_ZONE_TOL_V, copy_with
    from ipmc_model.hysteresis import GeneralizedPI

    day1 = plant_record({}, 150.0, 4)
    model = GeneralizedPI(dt_s=1 / RATE).fit(day1.u_v, day1.y_mm)
    dz = CANDIDATES["dead_zone"]
    found = {}
    for plant_v, after_v in ((0.0, 0.4 * DEAD_ZONE_TOL_V), (0.3, 0.3)):
        day2 = plant_record({"dead_zone": {"width_v": plant_v}} if plant_v else {}, 150.0, 5)
        rec = DiagnosisRecord(day2.t_s, day2.u_v, day2.y_mm, DiagnosisConfig())
        found[plant_v] = dz.refine(model, copy_with(model, dead_zone_v=after_v), rec, True)
    assert found[0.0].params["width_v"] < DEAD_ZONE_TOL_V
    assert "below the scan's resolution" in found[0.0].outside
    assert found[0.3].outside is None
    assert found[0.3].params["width_v"] == pytest.approx(0.3, abs=0.05)


def test_a_delay_whose_profile_adds_less_than_the_sampling_is_outside_its_range():
    """A delay whose profile's best fit adds fewer than ``MIN_DELAY_SAMPLES`` is within the
    sampling itself (zero-order hold, sensor): the block took up a misfit, and is not named;
    on a delayed plant the same profile keeps the delay."""
    from ipmc_model.diagnosis.candidates import MIN_DELAY_SAMPLES, copy_with
    from ipmc_model.hysteresis import GeneralizedPI

    day1 = plant_record({}, 150.0, 4)
    model = GeneralizedPI(dt_s=1 / RATE).fit(day1.u_v, day1.y_mm)
    delay = CANDIDATES["delay"]
    found = {}
    # accepted 3 samples above the model's own on the plant without a delay (the profile
    # then reaches down to none added), and at the plant's delay on the delayed one
    for plant_s, added in ((0.0, 3), (0.2, int(round(0.2 * RATE)))):
        day2 = plant_record({"delay": {"delay_s": plant_s}} if plant_s else {}, 150.0, 5)
        rec = DiagnosisRecord(day2.t_s, day2.u_v, day2.y_mm, DiagnosisConfig())
        d = int(model.delay_samples_) + added
        found[plant_s] = delay.refine(model, copy_with(model, delay_samples_=d,
                                                       delay_s=d / RATE), rec, True)
    assert "within the sampling itself" in found[0.0].outside
    own_s = model.delay_samples_ / RATE
    lo, hi = found[0.0].params["delay_ci_s"]
    assert lo < own_s + MIN_DELAY_SAMPLES / RATE
    assert lo <= found[0.0].params["delay_s"] <= hi   # the estimate reported is the profile's
    assert found[0.2].outside is None
    assert found[0.2].params["delay_s"] - own_s == pytest.approx(0.2, abs=2 / RATE)


def test_a_dead_zone_whose_profile_is_best_without_one_is_outside_its_range():
    """A dead zone whose profile's best width adds less than the scan's resolution is not a
    dead zone (the block took up a misfit), whatever width was accepted; on a plant with a
    dead zone the same profile keeps its width."""
    from ipmc_model.diagnosis.candidates import DEAD_ZONE_TOL_V, copy_with
    from ipmc_model.hysteresis import GeneralizedPI

    day1 = plant_record({}, 150.0, 4)
    model = GeneralizedPI(dt_s=1 / RATE).fit(day1.u_v, day1.y_mm)
    found = {}
    # accepted 0.1 V on the plant without a dead zone (the profile then reaches down to none),
    # and at the plant's width on the one with a dead zone
    for plant_v, accepted_v in ((0.0, 0.1), (0.3, 0.3)):
        day2 = plant_record({"dead_zone": {"width_v": plant_v}} if plant_v else {}, 150.0, 5)
        rec = DiagnosisRecord(day2.t_s, day2.u_v, day2.y_mm, DiagnosisConfig())
        found[plant_v] = CANDIDATES["dead_zone"].refine(
            model, copy_with(model, dead_zone_v=accepted_v), rec, True)
    assert "below the scan's resolution" in found[0.0].outside
    lo, hi = found[0.0].params["width_ci_v"]
    assert lo < DEAD_ZONE_TOL_V
    assert lo <= found[0.0].params["width_v"] <= hi   # the estimate reported is the profile's
    assert found[0.3].outside is None
    assert found[0.3].params["width_v"] == pytest.approx(0.3, abs=0.03)


def test_cli_writes_the_report_and_a_model_that_runs(tmp_path, capsys):
    data = save_csv(plant_record({"delay": {"delay_s": 0.2}}, 150.0, 6), tmp_path / "d.csv")
    out = tmp_path / "report"
    assert main(["--data", str(data), "--report", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert {"effects_found", "rmse_before_mm", "rmse_after_mm", "metric", "candidates",
            "model_before", "model_after", "rule", "config"} <= set(s)
    assert s["effects_found"][:1] == ["delay"]
    after = load_model(s["model_after"])
    assert abs(after.delay_samples_ * after.dt_s - 0.2) <= 0.04
    report = (out / "report.md").read_text()
    assert "Diebold-Mariano" in report and "| delay | accepted |" in report
    assert "effects found: delay" in capsys.readouterr().out
    # creep was not testable (no holds): the report proposes the record that decides it
    x = json.loads(Path(s["next_experiment"]).read_text())
    # the held-out part is the probes' last copies: the record is split where they start
    held_s = min(p["start_s"] for p in x["parts"] if p["held_out"])
    assert "creep" in x["decides"] and x["fit_share"] == pytest.approx(held_s / x["duration_s"])
    assert max(abs(v) for v in x["u_v"]) <= 3.0 and "## The next experiment" in report
    # a drift needs holds too; the creep's, played in both copies, decide it without its own
    assert "drift" in x["decides"] and all(p["effect"] != "drift" for p in x["parts"])
    assert all("also decides drift" in p["reason"] and p["also"] == ["drift"]
               for p in x["parts"] if p["effect"] == "creep")


def test_cli_refuses_a_report_path_that_is_a_file_before_any_work(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["--data", str(tmp_path / "missing.csv"), "--report", str(f)]) == 1
    assert "is a file" in capsys.readouterr().err


def test_cli_refuses_a_given_model_that_is_not_gpi(tmp_path, capsys):
    from ipmc_model.persistence import save_model
    from ipmc_model.play import PrandtlIshlinskii

    rec = plant_record({}, 60.0, 7)
    data = save_csv(rec, tmp_path / "d.csv")
    pi = save_model(PrandtlIshlinskii(n_operators=4).fit(rec.u_v, rec.y_mm), tmp_path / "pi")
    assert main(["--data", str(data), "--model", str(pi), "--report", str(tmp_path / "r")]) == 1
    assert "GPI model" in capsys.readouterr().err


def test_cli_refuses_millivolts_and_warns_of_metres_before_any_work(tmp_path, capsys):
    from dataclasses import replace

    rec = plant_record({}, 60.0, 7)
    mv = save_csv(replace(rec, u_v=rec.u_v * 1000.0), tmp_path / "mv.csv")
    assert main(["--data", str(mv), "--report", str(tmp_path / "r")]) == 1
    err = capsys.readouterr().err
    assert "H-bridge" in err and "--allow-implausible" in err
    assert not (tmp_path / "r" / "summary.json").exists()


def test_the_next_experiment_makes_each_effect_testable():
    """Probes assembled after a record that could test none of them: the new record's
    excitation lets each be tested, and the deciding part is the held-out part; the rate
    dependence's sweep alone has the fast input it needs, and a drift's probe opens and
    closes the experiment."""
    from ipmc_model.diagnosis.candidates import CANDIDATES as C
    from ipmc_model.diagnosis.candidates import fast_input_reason
    from ipmc_model.diagnosis.config import DiagnosisConfig
    from ipmc_model.diagnosis.experiment import assemble
    from ipmc_model.diagnosis.record import DiagnosisRecord
    from ipmc_model.diagnosis.results import CandidateResult
    from ipmc_model.diagnosis.search import core_model

    # slow and smooth (no holds, no steps, little power above the charging corner), far from
    # 0 V
    _, u = random_sine(80.0, RATE, 1.0, (0.02, 0.2), 4, seed=3)
    u = 2.0 + 0.8 * u / np.max(np.abs(u))
    run = IpmcPlant(seed=3, dt_s=1 / RATE).run(u)
    cfg = DiagnosisConfig()
    rec = DiagnosisRecord(run.t_s, u, run.y_mm, cfg)
    model = core_model(rec)
    names = ("creep", "delay", "dead_zone", "rate_dependence")
    assert all(C[n].not_testable(rec, model, False) for n in names)
    probes = [C[n].probe(rec, model, CandidateResult(n, Outcome.NOT_TESTABLE, "", 1))
              for n in (*names, "drift")]
    sweep = IpmcPlant(seed=5, dt_s=1 / RATE).run(probes[3].u_v)
    alone = DiagnosisRecord(sweep.t_s, probes[3].u_v, sweep.y_mm, cfg)
    assert fast_input_reason(alone, model, "rate-dependent bending") is None
    x = assemble(probes, rec)
    assert np.max(np.abs(x.u_v)) <= 3.0 and x.decides == sorted((*names, "drift"))
    # a wipe, then the drift's probe opens; it closes the experiment, after a wipe too
    assert [p.name for p in x.parts[:2]] == ["memory wipe", "drift probe, at the start"]
    assert x.parts[-2].name == "memory wipe" and x.parts[-1].effect == "drift"
    n, k = probes[4].u_v.size, int(round(x.parts[1].start_s * RATE))
    assert np.array_equal(x.u_v[k:k + n], x.u_v[-n:]) and np.ptp(x.u_v[-n:]) > 2.0
    new = IpmcPlant(seed=4, dt_s=1 / RATE).run(x.u_v)
    rec2 = DiagnosisRecord(new.t_s, x.u_v, new.y_mm, cfg, parts=x.parts)
    model2 = core_model(rec2)
    assert [C[n].not_testable(rec2, model2, False) for n in names] == [None] * len(names)
    held = [p for p in x.parts if p.start_s >= rec2.segments[0].cut * rec2.dt_s - 1e-9]
    assert {p.effect for p in held if p.held_out} == {*names, "drift"}
    assert all(p.held_out or p.name == "memory wipe" for p in held)


def test_a_record_of_an_experiment_judges_each_effect_on_its_own_probe():
    """The held-out part of an experiment's record is its probes; an effect with a probe is
    judged on that probe's rows, any other effect on every judged row."""
    from ipmc_model.diagnosis.experiment import Probe, assemble, holds

    first = plant_record({}, 60.0, 1, holds=True)
    cfg = DiagnosisConfig()
    rec0 = DiagnosisRecord(first.t_s, first.u_v, first.y_mm, cfg)
    x = assemble([Probe("creep", holds((1.5, -1.5), 20.0, RATE), "holds"),
                  Probe("delay", holds((1.0, 0.0, -1.0), 1.5, RATE), "steps")], rec0)
    run = IpmcPlant(seed=2, dt_s=1 / RATE).run(x.u_v)
    rec = DiagnosisRecord(run.t_s, x.u_v, run.y_mm, cfg, parts=x.parts)
    held = {p.effect: p for p in x.parts if "held-out" in p.name}
    for effect in ("creep", "delay"):
        rows = np.flatnonzero(rec.judged_for(effect))
        part = held[effect]
        assert rows.size > 0 and np.all(rec.judged[rows])
        assert rows[0] * rec.dt_s >= part.start_s - 1e-9
        assert rows[-1] * rec.dt_s < part.start_s + part.duration_s
    both = rec.judged_for("creep") | rec.judged_for("delay")
    assert not np.any(rec.judged_for("creep") & rec.judged_for("delay"))
    # the record is split where the probes' last copies start: its held-out part is them
    first_probe_s = min(p.start_s for p in held.values())
    assert rec.segments[0].cut * rec.dt_s == pytest.approx(first_probe_s)
    assert np.array_equal(both, rec.judged)
    assert np.array_equal(rec.judged_for("drift"), rec.judged)
    plain = DiagnosisRecord(run.t_s, x.u_v, run.y_mm, cfg)   # no parts: every judged row
    assert np.array_equal(plain.judged_for("delay"), plain.judged)


def test_both_copies_of_an_experiments_probes_start_from_the_same_state():
    """A memory wipe before each copy of the probes: the simulated IPMC (without sensor
    noise) and the core model fitted on the first record each bend alike in both copies,
    though the inputs before them differ (a rest there instead leaves the core's plays and
    path memory where the input left them: its copies then differ by 0.03-0.2 mm RMS)."""
    from ipmc_driver.plant import load_plant_params
    from ipmc_model.diagnosis.experiment import Probe, assemble, holds

    exact = {**load_plant_params(), "noise_std_mm": 0.0, "resolution_mm": 0.0}
    _, u = random_sine(120.0, RATE, 3.0, seed=1)
    first = IpmcPlant(exact, seed=1, dt_s=1 / RATE).run(u)
    rec0 = DiagnosisRecord(first.t_s, u, first.y_mm, DiagnosisConfig())
    x = assemble([Probe("creep", holds((2.4, -2.4, 1.2, -1.2), 30.0, RATE), "holds"),
                  Probe("delay", holds((1.0, 0.0, -1.0, 0.5), 1.5, RATE), "steps")], rec0)
    plant = IpmcPlant(exact, seed=2, dt_s=1 / RATE).run(x.u_v).y_mm
    core = core_model(rec0).simulate(x.u_v)
    fit = [p for p in x.parts if p.effect and not p.held_out]
    held = [p for p in x.parts if p.held_out]
    assert [p.effect for p in fit] == [p.effect for p in held] == ["creep", "delay"]
    for a, b in zip(fit, held, strict=True):
        i, j, n = (int(round(v * RATE)) for v in (a.start_s, b.start_s, a.duration_s))
        assert np.array_equal(x.u_v[i - 1:i + n], x.u_v[j - 1:j + n])  # the wipe's end too
        for y, most_mm in ((plant, 1e-3), (core, 0.01)):   # the sensor's noise: 0.005 mm
            assert np.sqrt(np.mean((y[i:i + n] - y[j:j + n]) ** 2)) < most_mm
    assert x.fit_share == pytest.approx(held[0].start_s / x.duration_s)


def test_a_drift_is_judged_on_its_probe_at_the_two_ends_of_an_experiment():
    """A drift's probe opens and closes the experiment: on an actuator whose gain fades,
    the diagnosis of the experiment's record names the drift on that probe's held-out rows
    (the same levels bend less at the end than at the start), and nothing on a steady one."""
    from ipmc_model.diagnosis.experiment import assemble
    from ipmc_model.diagnosis.search import diagnose_records

    first = plant_record({}, 60.0, 1)
    rec0 = DiagnosisRecord(first.t_s, first.u_v, first.y_mm, DiagnosisConfig())
    probe = CANDIDATES["drift"].probe(rec0, core_model(rec0), None)
    x = assemble([probe], rec0)
    fading = {"drift": {"gain_loss_per_min": 0.05, "offset_mm_per_min": 0.0}}
    found = {}
    for name, fx in (("fading", fading), ("steady", {})):
        run = IpmcPlant(effects=fx, seed=2, dt_s=1 / RATE).run(x.u_v)
        rec = DiagnosisRecord(run.t_s, x.u_v, run.y_mm, DiagnosisConfig(), parts=x.parts)
        rows = np.flatnonzero(rec.judged_for("drift"))   # the last copy, none of the first
        assert rows.size == probe.u_v.size and rows[0] == x.u_v.size - probe.u_v.size
        d = diagnose_records([(name, run.t_s, x.u_v, run.y_mm, x.parts)],
                             candidates=["drift"])
        found[name] = d.effects_found
        res = next(r for r in d.candidates if r.name == "drift")
        assert "its probe's" in res.evidence.judged_on
    assert found == {"fading": ["drift"], "steady": []}


def test_cli_judges_the_experiment_a_record_played_on_its_probes(tmp_path, capsys):
    """``--experiment``: the record (begun 3 s before the experiment, as a recorder that
    started first) has its parts found by its voltages; the delay is judged on its probe."""
    from ipmc_model.diagnosis.experiment import (
        Experiment,
        Probe,
        assemble,
        holds,
        played_parts,
    )

    delay_steps = holds((1.0, 0.0, -1.0, 0.5, -0.5, 0.0, 1.0, -1.0), 1.5, RATE)   # its probe's
    first = plant_record({}, 60.0, 1, holds=True)
    rec0 = DiagnosisRecord(first.t_s, first.u_v, first.y_mm, DiagnosisConfig())
    x = assemble([Probe("creep", holds((1.5, -1.5), 20.0, RATE), "holds"),
                  Probe("delay", delay_steps, "steps")], rec0)
    exp = tmp_path / "next_experiment.json"
    exp.write_text(json.dumps(Experiment(RATE, 0.7, x.u_v, x.parts).as_dict()))
    lead = int(3.0 * RATE)
    u = np.r_[np.zeros(lead), x.u_v]
    run = IpmcPlant(effects={"delay": {"delay_s": 0.1}}, seed=3, dt_s=1 / RATE).run(u)
    data = save_csv(Record(run.t_s, u, run.y_mm), tmp_path / "day2.csv")
    moved = played_parts(x.parts, x.u_v, u, 1 / RATE)
    assert all(abs(m.start_s - p.start_s - 3.0) < 1e-9
               for m, p in zip(moved, x.parts, strict=True))
    out = tmp_path / "report"
    assert main(["--data", str(data), "--experiment", str(exp), "--report", str(out),
                 "--effects", "delay", "drift"]) == 0
    s = json.loads((out / "summary.json").read_text())
    ev = {r["name"]: r["evidence"] for r in s["candidates"]}
    probe = next(p for p in x.parts if p.effect == "delay" and "held-out" in p.name)
    rows = int(round(probe.duration_s * RATE))
    assert ev["delay"]["judged_on"] == f"its probe's {rows} held-out rows"
    assert ev["drift"]["judged_on"] == ""
    # named first, on its probe (the core model's misfit of the creep probe's holds leaves
    # slow residual that a drift may take up in the next round)
    assert s["effects_found"][:1] == ["delay"]
    # an experiment the record did not play: refused in one sentence
    short = save_csv(Record(run.t_s[:500], u[:500], run.y_mm[:500]), tmp_path / "short.csv")
    assert main(["--data", str(short), "--experiment", str(exp), "--report",
                 str(tmp_path / "r2")]) == 1
    assert "did not play all of" in capsys.readouterr().err


def test_a_bag_recorded_with_an_experiment_carries_it_to_the_diagnosis(tmp_path):
    """``ipmc diagnose --data BAG`` finds the experiment ``ipmc bringup --experiment FILE
    --record BAG`` keeps in the bag (``--experiment`` names it for the last record) and
    splits there; a version-1 experiment, without held-out parts, splits at the share."""
    from ipmc_model.diagnose_cli import experiment_of
    from ipmc_model.diagnosis.experiment import (
        BAG_EXPERIMENT,
        Probe,
        assemble,
        holds,
        read_experiment,
    )

    first = plant_record({}, 60.0, 1)
    rec0 = DiagnosisRecord(first.t_s, first.u_v, first.y_mm, DiagnosisConfig())
    x = assemble([Probe("delay", holds((1.0, -1.0) * 4, 1.5, RATE), "steps")], rec0)
    exp, bag = tmp_path / "next_experiment.json", tmp_path / "day2"
    exp.write_text(json.dumps(x.as_dict()))
    bag.mkdir()
    assert experiment_of(str(bag), None) is None
    (bag / BAG_EXPERIMENT).write_text(exp.read_text())
    assert experiment_of(str(bag), None) == str(bag / BAG_EXPERIMENT)
    assert experiment_of(str(bag), "other.json") == "other.json"
    run = IpmcPlant(seed=2, dt_s=1 / RATE).run(x.u_v)
    cut = DiagnosisRecord(run.t_s, x.u_v, run.y_mm, DiagnosisConfig(), parts=x.parts)
    held_s = next(p.start_s for p in x.parts if p.held_out)
    assert cut.segments[0].cut == round(held_s * RATE)
    old = {**x.as_dict(), "format_version": 1,
           "parts": [{k: v for k, v in vars(p).items() if k != "held_out"} for p in x.parts]}
    exp.write_text(json.dumps(old))
    parts = read_experiment(exp)[0]
    plain = DiagnosisRecord(run.t_s, x.u_v, run.y_mm, DiagnosisConfig(), parts=parts)
    assert plain.segments[0].cut == round(0.7 * x.u_v.size)


def test_records_are_joined_by_unmeasured_rests_and_each_split_the_same_way():
    a, b = plant_record({}, 60.0, 1), plant_record({}, 90.0, 2, holds=True)
    cfg = DiagnosisConfig()
    rec = DiagnosisRecord.joined([("a", a.t_s, a.u_v, a.y_mm), ("b", b.t_s, b.u_v, b.y_mm)],
                                 cfg)
    sa, sb = rec.segments
    assert (sa.start, sa.cut, sa.stop) == (0, 2100, 3000)
    assert sb.start > sa.stop and sb.cut - sb.start == 3150 and sb.stop == rec.u_v.size
    rest = slice(sa.stop, sb.start)
    assert np.all(rec.u_v[rest] == 0.0) and np.all(np.isnan(rec.y_mm[rest]))
    np.testing.assert_array_equal(rec.y_mm[sb.start:sb.stop], b.y_mm)
    # fits run up to the last fit row and see only the fit rows; judging sees held rows only
    assert rec.fit_end == sb.cut and rec.fit_obs.sum() == 2100 + 3150
    assert np.all(np.isnan(rec.y_fit[~rec.fit_obs]))
    assert not np.any(rec.judged & ~rec.held_rows) and rec.held_rows.sum() == 900 + 1350
    # the holds of the record that has them count, each in its own part
    alone = DiagnosisRecord(b.t_s, b.u_v, b.y_mm, cfg).excitation
    assert (rec.excitation.holds_fit, rec.excitation.holds_held) == \
        (alone.holds_fit, alone.holds_held)
    fast = plant_record({}, 10.0, 3)
    with pytest.raises(ValueError, match="Hz"):
        DiagnosisRecord.joined([("a", a.t_s, a.u_v, a.y_mm),
                                ("c", fast.t_s / 2, fast.u_v, fast.y_mm)], cfg)


def test_cli_diagnoses_records_together_and_says_which_decided(tmp_path, capsys):
    """Creep is not testable on a record without holds; with a second record that has them,
    both are fitted and judged together and creep is named."""
    fx = {"creep": {"tau_s": 12.0, "gain_mm_per_v": -0.6}}
    moving = save_csv(plant_record(fx, 150.0, 1), tmp_path / "moving.csv")
    held = save_csv(plant_record(fx, 150.0, 4, holds=True), tmp_path / "held.csv")
    out = tmp_path / "report"
    assert main(["--data", str(moving), "--data", str(held), "--report", str(out),
                 "--effects", "creep", "drift"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["effects_found"][:1] == ["creep"]
    assert [r["name"] for r in s["records"]] == [str(moving), str(held)]
    assert all(r["rmse_after_mm"] < r["rmse_before_mm"] for r in s["records"])
    creep = next(r for r in s["candidates"] if r["name"] == "creep")["evidence"]
    assert [r["record"] for r in creep["records"]] == [str(moving), str(held)]
    report = (out / "report.md").read_text()
    assert "Which record decided creep" in report and "joined in this order" in report
    assert "effects found: creep" in capsys.readouterr().out


def test_an_accepted_creep_whose_time_constant_is_left_open_gets_deciding_holds():
    from ipmc_model.diagnosis import design_experiment
    from ipmc_model.diagnosis.results import CandidateResult, Diagnosis, Evidence, LossTest, Round

    data = plant_record({}, 120.0, 1, holds=True)
    cfg = DiagnosisConfig()
    rec = DiagnosisRecord(data.t_s, data.u_v, data.y_mm, cfg)
    model = core_model(rec)

    def proposal(open_ends):
        params = {"tau_s": 28.0, "tau_ci_s": [9.0, 28.0], "tau_ci_open": open_ends,
                  "gain_mm_per_v": 0.05, "gain_ci_mm_per_v": [0.01, 0.09]}
        ev = Evidence(0.05, 0.03, LossTest(1e-3, 3.0, 0.001, 10, 1e-5), params)
        res = CandidateResult("creep", Outcome.ACCEPTED, "accepted", 1, ev)
        d = Diagnosis(rec.t_s, rec.u_v, rec.y_mm, rec.held_rows, rec.segments, cfg, False,
                      model, model, rounds=[Round(1, 0.05, (res,), "creep")])
        return design_experiment(d, rec)

    assert proposal([False, False]) is None
    x = proposal([False, True])
    assert x.decides == ["creep"]
    probe = next(p for p in x.parts if p.effect == "creep")
    from ipmc_model.diagnosis.candidates import HOLD_LEVELS, HOLD_TAUS

    assert "not pinned down" in probe.reason
    assert probe.duration_s >= len(HOLD_LEVELS) * HOLD_TAUS * 28.0 - 1e-6


def test_a_drift_on_a_moving_input_is_not_testable_and_its_probe_is_proposed():
    """On an input that never holds still, a misfit of the path memory trends as a drift
    would: there a drift is not testable, and the next experiment plays its probe (the same
    levels held at the two ends); on a record with holds in both parts it is judged."""
    fading = {"drift": {"gain_loss_per_min": 0.05, "offset_mm_per_min": 0.15}}
    moving = diagnose(plant_record(fading, 120.0, 1), candidates=["drift"])
    drift = next(r for r in moving.candidates if r.name == "drift")
    assert drift.outcome is Outcome.NOT_TESTABLE and "0 input holds" in drift.reason
    assert moving.effects_found == [] and moving.next_experiment.decides == ["drift"]
    x = moving.next_experiment
    ends = [p for p in x.parts if p.effect == "drift"]
    assert len(ends) == 2 and x.parts[0].name == "memory wipe"   # each copy after a wipe
    assert ends[0].start_s == pytest.approx(x.parts[0].duration_s)
    assert ends[-1].start_s + ends[-1].duration_s == pytest.approx(x.duration_s)
    held = diagnose(plant_record(fading, 120.0, 1, holds=True), candidates=["drift"])
    assert next(r for r in held.candidates if r.name == "drift").outcome is not \
        Outcome.NOT_TESTABLE
    assert held.next_experiment is None or "drift" not in held.next_experiment.decides


def test_a_probe_that_gives_another_effect_its_excitation_replaces_that_ones_probe():
    """A probe naming an effect the record lacked the excitation for stands in for that
    effect's probe, which is left out, and the effect is judged on its held-out copy; one
    undecided for too few rows keeps its own; a probe that is itself left out covers
    nothing (a chain), and two naming each other both stay (a cycle)."""
    from ipmc_model.diagnosis.experiment import Probe, assemble, covering

    def probe(effect, *also, level=1.0):
        return Probe(effect, np.full(int(10 * RATE), level), f"{effect} input", also=also)

    a, b, c = probe("creep", "drift"), probe("drift", level=-1.0), probe("delay", level=0.5)
    kept = covering([a, b, c], lacking={"drift"})
    assert [p.effect for p in kept] == ["creep", "delay"]
    assert kept[0].also == ("drift",) and kept[0].reason.endswith("it also decides drift")
    assert [p.effect for p in covering([a, b], lacking=set())] == ["creep", "drift"]
    chain = covering([probe("x", "y"), probe("y", "z"), probe("z")], lacking={"y", "z"})
    assert [p.effect for p in chain] == ["x", "z"] and chain[0].also == ("y",)
    cycle = covering([probe("x", "y"), probe("y", "x")], lacking={"x", "y"})
    assert [(p.effect, p.also) for p in cycle] == [("x", ()), ("y", ())]
    # the covered effect is judged on the covering probe's held-out copy
    data = plant_record({}, 120.0, 1)
    rec = DiagnosisRecord(data.t_s, data.u_v, data.y_mm, DiagnosisConfig())
    x = assemble(kept, rec)
    assert x.decides == ["creep", "delay", "drift"]
    run = IpmcPlant(seed=2, dt_s=1 / RATE).run(x.u_v)
    rec2 = DiagnosisRecord(run.t_s, x.u_v, run.y_mm, DiagnosisConfig(), parts=x.parts)
    assert np.array_equal(rec2.judged_for("drift"), rec2.judged_for("creep"))
    assert rec2.judged_for("drift").any() and not (rec2.judged_for("drift")
                                                   & rec2.judged_for("delay")).any()


def test_a_creep_the_record_does_not_bound_or_size_is_outside_its_range():
    """A relaxation is its time constant: a creep whose profile stays within the 95 % bound
    at every time constant the record can show took up a slow misfit, and is rejected; one
    open end only asks for longer holds, and a closed interval is a creep, unless its gain's
    interval holds zero (the fit rows do not tell it from none)."""
    from ipmc_model.diagnosis.candidates import creep_outside

    data = plant_record({}, 60.0, 1, holds=True)
    rec = DiagnosisRecord(data.t_s, data.u_v, data.y_mm, DiagnosisConfig())

    def outside(tau_s, ci, open_ends, gain_ci=(-0.3, -0.1)):
        return creep_outside({"tau_s": tau_s, "tau_ci_s": ci, "tau_ci_open": open_ends,
                              "gain_ci_mm_per_v": list(gain_ci)}, rec)

    assert "holds zero" in outside(348.0, [78.0, 350.0], [False, True], (-0.003, 0.042))
    assert "holds zero" in outside(20.0, [15.0, 35.0], [False, False], (-0.2, 0.0))
    assert outside(40.0, [12.0, 80.0], [False, True], (0.02, 0.09)) is None

    assert "bounded on neither side" in outside(360.0, [3.3, 362.0], [True, True])
    assert outside(40.0, [12.0, 80.0], [False, True]) is None
    assert outside(20.0, [15.0, 35.0], [False, False]) is None
    assert "faster than a creep" in outside(4.0, [3.3, 6.0], [True, False])
