"""Tests of ipmc_model.diagnose and ``ipmc diagnose``: contract, clean plant, bad input.

Short records (60 s at 50 Hz) and fixed LSSVM hyperparameters keep the file fast; the heavy
runs (every effect, several seeds, 30 000 samples, third-party data) are in
benchmarks/bench_diagnose.py and docs/diagnose.md.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import ipmc_model.diagnose as diagnose_module
from ipmc_driver.dataio import Record, save_csv
from ipmc_driver.plant import IpmcPlant
from ipmc_driver.signals import mixed, random_sine, random_steps
from ipmc_model.diagnose import (
    Candidate,
    block_direction,
    choose_lag_step,
    creep_rival,
    diagnose,
    hysteresis_memory,
    input_kind,
    input_shift,
    kinds_differ,
    model_coverage,
    model_input_kind,
    model_input_range,
    model_support,
    write_report,
)
from ipmc_model.diagnose_cli import main
from ipmc_model.effects import load_augmented

RATE = 50.0
FAST = {"C": 1000.0, "sigma": 3.0, "lag_step": 5, "max_rows": 800, "screen_rows": 300}
KEYS = {"effects_found", "rmse_before_mm", "rmse_after_mm", "metric", "candidates",
        "model_before", "model_after"}


def _input(seconds=60.0, seed=2, holds=False):
    """0.6 x random sine (0.05-1 Hz) + random steps (1.5 V, 3-10 s); with ``holds`` the sine is
    off during every other step, so those steps are true input holds (creep shows in time)."""
    _, us = random_sine(seconds, RATE, 2.5, (0.05, 1.0), 8, seed=seed)
    _, st = random_steps(seconds, RATE, 1.5, (3.0, 10.0), seed=seed + 1)
    if holds:
        step_no = np.cumsum(np.r_[0, np.diff(st) != 0])
        us = us * (step_no % 2 == 0)
    return np.clip(0.6 * us + st, -3, 3)


def _plant(effects, seed=0, seconds=60.0, holds=False):
    u = _input(seconds, seed=2 + seed, holds=holds)
    run = IpmcPlant(effects=effects, seed=seed, dt_s=1 / RATE).run(u)
    return run.t_s, u, run.y_mm


def test_import_leaves_rclpy_out():
    # In a fresh interpreter: other tests of the session may have imported rclpy already.
    code = ("import sys, ipmc_model.diagnose, ipmc_model.effects, ipmc_model.diagnose_cli; "
            "sys.exit('rclpy' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


@pytest.mark.parametrize("seed", [0, 2])  # seed 2 was not used to set anything
def test_no_effect_found_on_clean_plant(seed):
    t, u, y = _plant({}, seed=seed)
    d = diagnose(t, u, y, **FAST)
    assert d.effects_found == []
    assert d.rmse_after_mm == d.rmse_before_mm
    assert all(not c.accepted for c in d.candidates)


@pytest.mark.parametrize("seed", [
    1,  # accepted rate_dependence when the rate channel could low-pass over 1 s
    2,  # accepted creep (tau 3.6 s, -0.11 mm/V, +24 %): the case the hold-drift rule was
        # designed on (docs/diagnose.md, "Creep needs drift during holds")
    5,  # not used to design anything; the old rule accepted creep here too (+37 %)
])
def test_no_effect_found_on_clean_plant_with_full_tuning(seed):
    # the benchmark's clean 90 s records (docs/diagnose.md)
    t, u, y = _plant({}, seed=seed, seconds=90.0)
    d = diagnose(t, u, y)
    assert d.effects_found == []
    creep = next(c for c in d.candidates if c.effect == "creep")
    assert "hold" in creep.evidence["text"]


def test_no_creep_on_clean_plant_with_holds():
    # true input holds (the sine off during every other step): the hold-drift test is decided
    # on the drift, not on the lack of holds; seed 7 was not used to set the rule
    t, u, y = _plant({}, seed=7, seconds=90.0, holds=True)
    d = diagnose(t, u, y)
    assert "creep" not in d.effects_found
    creep = next(c for c in d.candidates if c.effect == "creep")
    assert creep.evidence["hold_drift"]["holds"] >= 3


@pytest.mark.parametrize("seed, creep", [
    (1, {"tau_s": 12.0, "gain_mm_per_v": -0.6}),
    # not tuned on: another seed, a faster and smaller creep (an xfail on 90 s of the mixed
    # input, 8.9 % gain; with holds and 120 s it gains 62 %)
    (4, {"tau_s": 8.0, "gain_mm_per_v": -0.4}),
])
def test_creep_found_with_undeclared_parameters(seed, creep, tmp_path, capsys):
    # creep needs input holds to show in time (the hold-drift evidence), and 120 s: on 90 s of
    # this input the seed-1 creep fit lands at tau 28 s, -2.7 mm/V and loses on held-out data
    t, u, y = _plant({"creep": creep}, seed=seed, seconds=120.0, holds=True)
    d = diagnose(t, u, y, candidates=("creep", "drift", "delay", "saturation"), **FAST)
    assert d.effects_found[:1] == ["creep"]
    assert d.rmse_after_mm < 0.9 * d.rmse_before_mm
    accepted = next(c for c in d.candidates if c.accepted and c.effect == "creep")
    assert accepted.evidence["hold_drift"]["significant"]
    # decided by the holds: not "undecided for lack of input holds"
    assert not accepted.evidence["undecided"] and d.undecided() == []
    # tau and gain from the drift during the holds: near the plant's (before the hold fit:
    # seed 1 gave tau 28 s, -2.7 mm/V on 90 s, and the demo's record tau 3.6 s, -0.24 mm/V)
    assert accepted.evidence["creep_fit"]["method"] == "holds"
    fitted = accepted.evidence["params"]
    assert creep["tau_s"] / 1.5 <= fitted["tau_s"] <= 1.5 * creep["tau_s"]
    assert fitted["gain_mm_per_v"] == pytest.approx(creep["gain_mm_per_v"], rel=0.35)
    # the 95 % intervals (bootstrap over the holds) hold the plant's creep, and the report
    # gives them beside the fitted values
    cf = accepted.evidence["creep_fit"]
    (lo, hi), (g_lo, g_hi) = cf["tau_interval_s"], cf["gain_interval_mm_per_v"]
    assert lo <= creep["tau_s"] <= hi and g_lo <= creep["gain_mm_per_v"] <= g_hi
    assert cf["tau_bounded"] and "95 % intervals over a bootstrap" in accepted.evidence["text"]
    from ipmc_model.diagnose import write_report

    write_report(d, tmp_path)
    report = (tmp_path / "report.md").read_text()
    assert (f"| creep | tau_s | {fitted['tau_s']:.4g} | {lo:.4g} to {hi:.4g} | s | "
            "time constant of the slow relaxation under a held voltage |") in report
    # the decision rule the report states is the one that accepted this creep: on the holds
    # it needed less than the other candidates' 10 % (the sentence said 10 % to session 41)
    need = accepted.evidence["threshold"]
    assert need < d.threshold and accepted.evidence["improvement"] >= need
    assert f"a creep shown on the input holds {100 * need:.0f} %" in report
    # the figure of the evidence: in the held-out input holds the residual before drifts the
    # way the creep predicts, and the creep in the model takes most of that drift out
    assert "creep_holds.png" in report and (tmp_path / "creep_holds.png").stat().st_size > 1000
    from ipmc_model.diagnose import binned_drift, hold_segments, shown_creep, shown_fast_tau_s

    shown, was_accepted = shown_creep(d)
    assert was_accepted and shown.params == pytest.approx(fitted)
    fast = shown_fast_tau_s(d)
    assert fast == cf["fast_tau_s"]
    segments = hold_segments(d, shown, fast)
    assert len(segments) >= 2
    for s in segments:
        before, predicted, after = s["before_mm"][-1], s["creep_mm"][-1], s["after_mm"][-1]
        assert np.sign(before) == np.sign(predicted) == -np.sign(s["u_v"])
        assert abs(after) < 0.5 * abs(before)
    # the figure's lower row, what the hold test compares: with the fast settling taken off,
    # the residual before follows the predicted drift and the residual after does not
    drift = {w: binned_drift(segments, w) for w in ("before", "after")}
    assert drift["before"]["slope"] > 0.5, drift
    assert abs(drift["after"]["slope"]) < 0.5 * drift["before"]["slope"], drift
    assert np.all(np.diff(drift["before"]["x_mm"]) > 0)
    # `ipmc evaluate` scores the model with its creep on a record, as it scores any model
    from ipmc_model.identify_cli import evaluate_main

    csv = save_csv(Record(t, u, y), tmp_path / "creep.csv")
    rmse = {}
    for name in ("model_before", "model_after"):
        assert evaluate_main(["--model", str(tmp_path / f"{name}.json"), "--data", str(csv),
                              "--json", str(tmp_path / f"{name}_eval.json")]) == 0
        rmse[name] = json.loads((tmp_path / f"{name}_eval.json").read_text())["free_run"]["rmse"]
    # the whole record: the fit part too, where the baseline after was refitted
    assert rmse["model_after"] < 0.8 * rmse["model_before"]
    slow = save_csv(Record(2.0 * t, u, y), tmp_path / "slow.csv")  # 25 Hz, not the model's 50
    assert evaluate_main(["--model", str(tmp_path / "model_after.json"), "--data",
                          str(slow)]) == 1
    assert "the model was identified at 50 Hz, the data are at 25 Hz" in capsys.readouterr().err


def test_no_creep_on_clean_step_record():
    # the demo's kind of identification record (300 s of random 2.5 V steps at 100 Hz, holds
    # 0.5-5 s) on the clean plant; seed 3 was not used to design the hold fit
    from ipmc_driver.signals import random_steps

    _, u = random_steps(300.0, 100.0, 2.5, seed=6)
    run = IpmcPlant(seed=3, dt_s=0.01).run(u)
    d = diagnose(run.t_s, u, run.y_mm, candidates=("creep",))
    assert d.effects_found == []
    creep = d.candidates[0]
    assert creep.evidence["creep_fit"]["holds"] >= 10
    assert not creep.evidence["hold_drift"]["significant"]
    assert d.in_data() == []


# A forward creep (the tip keeps going the input's way) is fitted right but refused: it partly
# cancels the baseline's path-memory error (docs/diagnose.md, "Forward creep"). Its hold test
# still names it in the data. 300 s of random 2.5 V steps (0.5-5 s) at 50 Hz; seeds 20-23 were
# run while writing this: 12.2 s, 17.6 s, 10.8 s on 20, 22, 23 and 32.4 s, 0.18 mm/V on 21
# (tau and gain trade on 0.5-5 s holds); 22 and 23 are asserted.
@pytest.mark.parametrize("seed", [22, 23])
def test_forward_creep_is_named_in_the_data_not_accepted(seed, tmp_path):
    from ipmc_model.diagnose import in_data_text, write_report

    creep = {"tau_s": 15.0, "gain_mm_per_v": 0.1}
    _, u = random_steps(300.0, RATE, 2.5, (0.5, 5.0), seed=seed + 3)
    run = IpmcPlant(effects={"creep": creep}, seed=seed, dt_s=1 / RATE).run(u)
    d = diagnose(run.t_s, u, run.y_mm, candidates=("creep",), **FAST)
    assert d.effects_found == []
    named = d.in_data()
    assert [c.effect for c in named] == ["creep"]
    p = named[0].evidence["params"]
    assert creep["tau_s"] / 1.5 <= p["tau_s"] <= 1.5 * creep["tau_s"]
    assert p["gain_mm_per_v"] == pytest.approx(creep["gain_mm_per_v"], rel=0.35)
    assert named[0].evidence["improvement"] < named[0].evidence["threshold"]
    assert "keeps drifting during input holds" in in_data_text(named[0])
    lo, hi = named[0].evidence["creep_fit"]["tau_interval_s"]
    assert lo <= creep["tau_s"] <= hi and "95 % intervals" in in_data_text(named[0])
    write_report(d, tmp_path)
    assert "In the data, not added: **creep**" in (tmp_path / "report.md").read_text()
    # the clean plant on the same input: no creep in the data
    run = IpmcPlant(seed=seed, dt_s=1 / RATE).run(u)
    d = diagnose(run.t_s, u, run.y_mm, candidates=("creep",), **FAST)
    assert d.effects_found == [] and d.in_data() == []


def _long_holds(seed):
    """600 s of random 2.5 V steps held 5-40 s at 50 Hz: the record a creep of minutes needs."""
    _, u = random_steps(600.0, RATE, 2.5, (5.0, 40.0), seed=seed + 3)
    return u


@pytest.mark.parametrize("seed", [4, 5])  # not used to set anything
def test_creep_of_minutes_found_on_long_holds(seed):
    # A slow creep leaves the baseline unstable under refits (spread 13-24 % here), so twice
    # the spread refused it (+20 %, +22 %); the paired rule compares refits on the same rows.
    creep = {"tau_s": 100.0, "gain_mm_per_v": -0.1}
    u = _long_holds(seed)
    run = IpmcPlant(effects={"creep": creep}, seed=seed, dt_s=1 / RATE).run(u)
    d = diagnose(run.t_s, u, run.y_mm, candidates=("creep",), **FAST)
    assert d.effects_found == ["creep"]
    ev = d.candidates[0].evidence
    assert creep["tau_s"] / 1.5 <= ev["params"]["tau_s"] <= 1.5 * creep["tau_s"]
    assert ev["params"]["gain_mm_per_v"] == pytest.approx(creep["gain_mm_per_v"], rel=0.35)
    assert len(ev["paired_improvements"]) == 2
    assert min(ev["paired_improvements"]) >= ev["threshold"]
    assert d.rmse_after_mm < 0.9 * d.rmse_before_mm


def test_no_creep_on_clean_long_holds():
    u = _long_holds(4)
    run = IpmcPlant(seed=4, dt_s=1 / RATE).run(u)
    d = diagnose(run.t_s, u, run.y_mm, candidates=("creep",), **FAST)
    assert d.effects_found == []
    assert not d.candidates[0].evidence["hold_drift"]["significant"]


def test_creep_without_holds_is_not_accepted():
    # the same creep on the mixed input (a sine rides on every step: no input holds): the
    # candidate gains +33 % but cannot be told from path memory, so it is not accepted
    creep = {"tau_s": 12.0, "gain_mm_per_v": -0.6}
    t, u, y = _plant({"creep": creep}, seed=1, seconds=90.0)
    d = diagnose(t, u, y, candidates=("creep",), **FAST)
    assert d.effects_found == []
    c = d.candidates[0]
    assert c.evidence["improvement"] >= 0.1 and c.evidence["hold_drift"]["holds"] == 0
    # but it gains with every row budget: the report says creep or path memory is missing,
    # undecided for lack of holds
    assert min(c.evidence["paired_improvements"]) >= 0.1
    assert c.evidence["undecided"] and d.undecided() == [c] and d.in_data() == []


@pytest.mark.parametrize("kind", ["random-sine", "steps"])
def test_report_says_creep_or_path_memory_undecided_without_holds(tmp_path, kind):
    """`ipmc simulate` 3 V, seed 4 (not used to design anything), 120 s at 50 Hz, the plant's
    default creep: on a random sine (no input holds) a slow term on the input gains but cannot
    be told from path memory, and the report says so and which record would decide; on random
    steps (holds) the hold test decides and nothing is undecided."""
    from ipmc_driver.simulate_cli import main as simulate

    csv = tmp_path / "data.csv"
    assert simulate(["--input", kind, "--amplitude", "3", "--seconds", "120", "--rate-hz",
                     "50", "--seed", "4", "--effect", "creep", "--out", str(csv)]) == 0
    out = tmp_path / "report"
    assert main(["--data", str(csv), "--report", str(out), "--seed", "0"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary) == KEYS
    report = (out / "report.md").read_text()
    undecided = [c for c in summary["candidates"] if c["evidence"].get("undecided")]
    if kind == "steps":
        assert undecided == [] and "Undecided" not in report
        return
    assert summary["effects_found"] == []
    assert [c["effect"] for c in undecided] == ["creep"]
    assert undecided[0]["evidence"]["hold_drift"]["holds"] < 3
    assert min(undecided[0]["evidence"]["paired_improvements"]) >= 0.1
    assert "Undecided for lack of input holds: **creep** or path memory" in report
    assert "Record input holds" in report


@pytest.mark.parametrize("seed, delay_s", [
    (0, 0.2),
    (1, 0.2),  # seed 1 and 0.1 s were not used to set the dead-time scan or the rule
    (0, 0.1),
])
def test_delay_found_with_undeclared_parameters(seed, delay_s):
    t, u, y = _plant({"delay": {"delay_s": delay_s}}, seed=seed, seconds=90.0)
    d = diagnose(t, u, y, candidates=("creep", "drift", "delay", "saturation"), **FAST)
    assert d.effects_found[:1] == ["delay"]
    delay = next(e for e in d.model_after.effects if e.name == "delay")
    assert delay.params["delay_s"] == pytest.approx(delay_s, abs=0.5 / RATE)
    assert d.rmse_after_mm < 0.9 * d.rmse_before_mm


@pytest.mark.parametrize("seed", [0, 1])  # seed 1 not used to set anything
def test_drift_found_with_undeclared_parameters(seed):
    drift = {"gain_loss_per_min": 0.1, "offset_mm_per_min": 0.3}
    t, u, y = _plant({"drift": drift}, seed=seed, seconds=90.0)
    d = diagnose(t, u, y, candidates=("creep", "drift", "delay", "saturation"), **FAST)
    assert d.effects_found[:1] == ["drift"]
    fitted = next(e for e in d.model_after.effects if e.name == "drift").params
    assert fitted["offset_mm_per_min"] == pytest.approx(0.3, rel=0.3)
    assert 0.0 < fitted["gain_loss_per_min"] < 0.2
    assert d.rmse_after_mm < 0.8 * d.rmse_before_mm
    # a trend in the fit part's residual too, not only a held-out gain
    ev = next(c for c in d.candidates if c.accepted and c.effect == "drift").evidence
    assert ev["drift_trend"]["lower"] > 0


def test_a_drift_must_trend_beside_the_hysteresis_memory():
    """Clean 3 V `mixed`, seed 11 (full tuning): a drift passed its signature, +16.1 % held
    out and the trend test (lower bound +0.26): it stood in for the plant's Bouc-Wen memory,
    which forgets with the input's travel (switched off in the plant, the drift gained 2.8 %).
    Beside the input low-passed over its travel the trend is within the scatter (session 33).
    The same record with a drift of 0.1 /min, 0.3 mm/min: found, beside the same memory."""
    d = diagnose(*_mixed_record({}, seed=11))
    assert "drift" not in d.effects_found
    ev = next(c for c in d.candidates if c.effect == "drift").evidence
    assert ev["drift_trend"]["hysteresis_travel_v"] in (5.0, 10.0, 20.0, 40.0, 80.0)
    assert ev["drift_trend"]["lower"] <= 0 < ev["drift_trend"]["coef"]
    assert "of its travel, the hysteresis's memory" in ev["text"]
    fx = {"drift": {"gain_loss_per_min": 0.1, "offset_mm_per_min": 0.3}}
    d = diagnose(*_mixed_record(fx, seed=11))
    assert d.effects_found[:1] == ["drift"]
    ev = next(c for c in d.candidates if c.accepted and c.effect == "drift").evidence
    assert ev["drift_trend"]["lower"] > 0 and ev["drift_trend"]["hysteresis_travel_v"]


def test_hysteresis_memory_picks_the_travel_that_explains_the_residual():
    from ipmc_model.residuals import travel_low_pass

    rng = np.random.default_rng(2)
    t = np.arange(4000) / RATE
    u = 1.5 * np.sin(2 * np.pi * 0.4 * t) + np.sin(2 * np.pi * 0.05 * t)
    assert np.abs(np.diff(u)).sum() > 4 * 40.0  # the grid up to 40 V is allowed
    e_true = 0.3 * travel_low_pass(u, 20.0)
    nuisance = np.ones((4000 - 10, 1))
    e = e_true[10:] + 0.01 * rng.standard_normal(3990)
    c, col = hysteresis_memory(u, e, nuisance, 10)
    assert c == 20.0 and np.array_equal(col, travel_low_pass(u, 20.0)[10:])
    # a run that diverged, or an input that hardly moves: no memory column
    assert hysteresis_memory(u, np.r_[e[:-1], np.nan], nuisance, 10) == (None, None)
    assert hysteresis_memory(np.full(4000, 1.0), e, nuisance, 10) == (None, None)


# -- a model from another day (given with --model): what changed since it was fitted --
def _mixed_record(effects, seed, seconds=120.0):
    """`ipmc simulate --input mixed --amplitude 3`: random sine, slow sine and held levels."""
    _, u = mixed(seconds, RATE, 3.0, band_hz=(0.02, 0.8), seed=seed)
    run = IpmcPlant(effects=effects, seed=seed, dt_s=1 / RATE).run(u)
    return run.t_s, run.u_v, run.y_mm


@pytest.fixture(scope="module")
def day1_model():
    """The rig's model fitted on a clean day (the diagnosis's own baseline, nothing added)."""
    return diagnose(*_mixed_record({}, seed=4), candidates=(), **FAST).model_after


# Designed on seeds 0, 1 (+100) with a 0.3 V dead zone and a 3 mm saturation, checked on seeds
# 2, 3 with 0.45 V / 2.5 mm (docs/diagnose.md, "A model from another day"); the seeds and sizes
# here were used for neither. (Drift
# around a given model: not here; this fast day-1 model's own error drifts with the input's
# cycles, -0.14 /min on the clean record, so a 0.15 /min drift is not told from it.)
# Asymmetry and rate dependence (session 13): designed on seeds 0, 1 (+100) with 0.7 / 0.8 and
# 0.1 / 0.05 mm/(V/s); the sizes here were used for neither. The plant's asymmetry scales its
# negative *bending*. The block around a given model has both forms and keeps the one that fits
# better (session 27): the bending form gives the plant's ratio, the voltage form a ratio
# nearer 1 (through the plant's stiffening bend 0.75 becomes 0.75..sqrt(0.75) = 0.87). This
# fast day-1 model fits better with the voltage form (0.855), so both are allowed here.
@pytest.mark.parametrize("effect, params", [
    ("dead_zone", {"width_v": 0.4}),
    ("saturation", {"limit_mm": 2.0}),
    ("asymmetry", {"negative_gain_ratio": 0.75}),
    ("rate_dependence", {"gain_mm_per_v_per_s": 0.08}),
    (None, {}),
])
def test_given_model_from_a_clean_day_names_what_changed(day1_model, effect, params):
    t, u, y = _mixed_record({effect: params} if effect else {}, seed=5)
    d = diagnose(t, u, y, model=day1_model, **FAST)
    if effect is None:
        assert d.effects_found == []
        assert d.rmse_after_mm == d.rmse_before_mm
        return
    assert d.effects_found[:1] == [effect]
    assert d.model_after.baseline is day1_model.baseline  # the block around it, not a refit
    fitted = d.model_after.effects[0].params
    rel = 0.25
    if effect == "asymmetry" and "negative_bending_ratio" in fitted:
        params, rel = {"negative_bending_ratio": params["negative_gain_ratio"]}, 0.1
    # the rate block's tau lands at its cap (0.4 s, a third of the model's window; the plant
    # charges in 0.3 s behind a slew limit), where gain and tau trade: measured 0.099 for 0.08
    if effect == "rate_dependence":
        rel = 0.35
    for k, v in params.items():
        assert fitted[k] == pytest.approx(v, rel=rel)
    # 0.6: dead zone and saturation take most of the error; asymmetry and rate dependence
    # (measured +11 % on this record with the fast day-1 model) less
    assert d.rmse_after_mm < (0.9 if effect == "rate_dependence" else 0.6) * d.rmse_before_mm



@pytest.mark.parametrize("seed, effects, found", [
    (7, {}, []),
    (0, {"drift": {"gain_loss_per_min": 0.1, "offset_mm_per_min": 0.3}}, ["drift"]),
])
def test_a_drift_around_a_given_model_must_show_as_a_trend(seed, effects, found):
    """`bench_diagnose.py stale` (full tuning): on seed 7 (not used to design) the clean later
    day got a drift around the clean day's model (0.034 /min, +24 %) and without the reach rule
    a 21.6 mm limit; both rules now hold around a given model (docs/diagnose.md, session 27).
    The plant's drift on seed 0 is still found."""
    day1 = _mixed_record({}, seed=seed)
    model = diagnose(*day1, candidates=()).model_before
    d = diagnose(*_mixed_record(effects, seed=seed + 100), model=model)
    assert d.effects_found[:1] == found
    drift = [c for c in d.candidates if c.effect == "drift" and "drift_trend" in c.evidence]
    assert drift, "the drift block around the model is tested for a trend"
    lower = drift[0].evidence["drift_trend"]["lower"]
    assert (lower > 0) == bool(found)


def test_a_static_block_around_a_given_model_must_fit_either_half():
    """`bench_diagnose.py stale 7 saturation` (full tuning; seed 7 was used to design nothing
    before session 27): after the plant's 2.5 mm limit an asymmetry 0.96 passed (+10.8 %) that
    the first half of the fit part is fitted best without; a block that does not change in time
    must gain on either half too (docs/diagnose.md, session 28). The limit keeps its gain on
    both halves."""
    model = diagnose(*_mixed_record({}, seed=7), candidates=()).model_before
    sat = {"saturation": {"limit_mm": 2.5}}
    d = diagnose(*_mixed_record(sat, seed=107), model=model)
    assert d.effects_found == ["saturation"]
    limit = [c for c in d.candidates if c.accepted][0].evidence
    assert limit["params"]["limit_mm"] == pytest.approx(2.5, rel=0.02)
    assert min(limit["half_improvements"]) >= limit["threshold"]
    asym = [c.evidence for c in d.candidates
            if c.effect == "asymmetry" and c.evidence["round"] == 2]
    assert asym[0]["improvement"] >= asym[0]["threshold"]  # what passed before
    assert min(asym[0]["half_improvements"]) < asym[0]["threshold"]
    assert "fitted on either half of the fit part no block" in asym[0]["text"]


def test_a_creep_around_a_given_model_is_a_block_fitted_on_the_holds():
    """`bench_diagnose.py creepmodel 0` (session 34): the baseline of a clean day's 120 s
    record with input holds, given to a later day's record on which the plant has its default
    creep (20 s, -0.12 mm/V). Before, the creep was fitted by refitting the given model and
    needed twice the refit spread (48 %): refused at +42 %. Now it is a block around the model,
    fitted on the hold drift, and accepted; on the clean later day nothing is."""
    model = diagnose(*_plant({}, seed=0, seconds=120.0, holds=True),
                     candidates=()).model_before
    d = diagnose(*_plant({"creep": {}}, seed=100, seconds=120.0, holds=True), model=model)
    assert d.effects_found == ["creep"]
    ev = [c for c in d.candidates if c.accepted][0].evidence
    assert ev["fit"] == "block around the given model, not refitted"
    assert ev["creep_fit"]["method"] == "holds" and ev["hold_drift"]["significant"]
    assert ev["improvement"] >= ev["threshold"] == pytest.approx(0.05)
    assert 20.0 / 1.5 <= ev["params"]["tau_s"] <= 1.5 * 20.0
    assert ev["params"]["gain_mm_per_v"] == pytest.approx(-0.12, rel=0.35)
    assert d.model_after.baseline is d.model_before.baseline
    clean = diagnose(*_plant({}, seed=100, seconds=120.0, holds=True), model=model)
    assert clean.effects_found == []
    creep = [c for c in clean.candidates if c.effect == "creep"][0].evidence
    assert creep["fit"] == "block around the given model, not refitted"
    assert not creep["hold_drift"]["significant"]


def test_a_creep_block_that_fails_around_a_given_model_is_refitted_as_before():
    """`bench_diagnose.py creepmodel 10` (session 34; seed 10 was used to design nothing
    before): a model from a day on which the plant creeps strongly (12 s, -0.6 mm/V), given
    to a later day of the same plant. The model holds a share of the creep's level, so the
    block around it, fitted right on the holds, loses on the held-out part; the refit (the
    rule before the block, twice the refit spread) passes and is kept."""
    strong = {"creep": {"tau_s": 12.0, "gain_mm_per_v": -0.6}}
    model = diagnose(*_plant(strong, seed=10, seconds=120.0, holds=True),
                     candidates=()).model_before
    d = diagnose(*_plant(strong, seed=110, seconds=120.0, holds=True), model=model)
    assert d.effects_found == ["creep"]
    ev = [c for c in d.candidates if c.accepted][0].evidence
    assert ev["fit"] == "baseline refitted with the effect"
    assert ev["improvement"] >= ev["threshold"] >= 2 * ev["refit_spread"]
    block = ev["block_around_model"]
    assert block["improvement"] < block["threshold"] and block["significant"]
    assert block["params"]["tau_s"] == pytest.approx(12.0, rel=0.2)
    assert "the block around the given model did not pass" in ev["text"]
    assert len([c for c in d.candidates if c.effect == "creep"]) == 1


def _fitted_on(u, rate=RATE):
    """An AugmentedModel whose baseline (12 input lags, step 5) is fitted on input ``u`` (V)
    and a smooth response of it (mm)."""
    from ipmc_model.effects import AugmentedModel
    from ipmc_model.lssvm import LSSVMRegressor
    from ipmc_model.narx import NarxModel

    y = np.convolve(np.tanh(u), np.full(10, 0.2), mode="full")[:u.size]
    narx = NarxModel(LSSVMRegressor(C=1000.0, sigma=3.0), input_lags=12, output_lags=0,
                     lag_step=5, max_rows=800)
    return AugmentedModel.identify(narx, u, y, (), 1 / rate)


def test_model_coverage_marks_the_samples_whose_window_leaves_the_models_voltages():
    rng = np.random.default_rng(0)
    u1 = np.clip(np.cumsum(rng.normal(0, 0.05, 3000)), -1.0, 2.0)
    u1[:200], u1[200:400] = -1.0, 2.0  # the range's ends are held, so the rows sample them
    model = _fitted_on(u1)
    lo, hi = model_input_range(model)
    assert lo == pytest.approx(-1.0, abs=1e-9) and hi == pytest.approx(2.0, abs=1e-9)
    u2 = np.clip(np.cumsum(rng.normal(0, 0.05, 1000)), -0.9, 1.9)
    u2[850:870] = -1.5  # beyond, in the held-out part
    cut, L = 700, model.max_lag_
    cov = model_coverage(model, u2, cut)
    assert cov["range_v"] == pytest.approx([-1.0, 2.0])
    out = np.flatnonzero(~cov["held_in"]) + cut + L  # record index of each uncovered sample
    # uncovered: from the first sample beyond to the last one's window end, nothing else
    assert out[0] == 850 and out[-1] == 869 + L and out.size == 20 + L
    assert cov["held_in_share"] == pytest.approx(1 - (20 + L) / (1000 - cut - L))
    assert "0.5 V beyond, and 67 % of the held-out part stays within" in cov["text"]
    inside = model_coverage(model, np.clip(u2, -0.9, 1.9), cut)
    assert inside["held_in"].all() and inside["held_in_share"] == 1.0


def test_a_block_that_gains_only_where_a_given_model_extrapolates_is_not_accepted():
    """`bench_diagnose.py creepmodel 6` (session 35): a clean day's model, identified on
    -1.80..2.45 V, given to a clean later day whose input reaches -2.39 V. A 5.1 mm saturation
    gained 20.2 % on the held-out part and was accepted; within the model's voltages, where it
    does not extrapolate, it gains 4.2 %. Now an effect must gain there too: nothing found."""
    model = diagnose(*_plant({}, seed=6, seconds=120.0, holds=True),
                     candidates=()).model_before
    d = diagnose(*_plant({}, seed=106, seconds=120.0, holds=True), model=model)
    assert d.effects_found == []
    assert any(n.startswith("WARNING: the given model was identified on") for n in d.notes)
    sat = [c.evidence for c in d.candidates if c.effect == "saturation"][0]
    assert sat["improvement"] >= sat["threshold"] > sat["improvement_in_model_range"]
    assert "where the given model has data" in sat["text"]


def test_model_support_marks_the_rows_the_model_saw_too_little_of_within_its_voltages():
    """A stretch of the held-out input that alternates between two voltages within the
    model's range, at a rate it never saw: its voltages are covered, its lag windows are not."""
    u1 = _input(120.0, seed=2)
    model = _fitted_on(u1)
    u2 = _input(40.0, seed=3)
    u2[1700:1740] = np.where(np.arange(40) % 2, u1.min() + 0.2, u1.max() - 0.2)
    y2 = np.convolve(np.tanh(u2), np.full(10, 0.2), mode="full")[:u2.size]
    cut, L = 1200, model.max_lag_
    assert model_coverage(model, u2, cut)["held_in_share"] == 1.0  # the voltages: all within
    sup = model_support(model, u2, y2, cut)
    at = np.arange(sup["supported"].size) + cut + L  # record index of each held-out sample
    # every window (13 lags, 5 samples apart) holding 4 or more alternating samples lies
    # outside the model's rows
    assert L == 60
    assert not sup["supported"][(at >= 1715) & (at < 1785)].any()
    # most of the ordinary input does not (5 % of the model's own rows would not either)
    assert sup["supported"][at < 1700].mean() > 0.8
    assert f"{100 * (1 - sup['supported_share']):.0f} % of the held-out part" in sup["text"]


def test_a_block_that_gains_only_where_a_given_model_saw_little_is_not_accepted():
    """`bench_diagnose.py creepmodel 13` (session 36): a clean day's model given to a clean
    later day within its voltages. An asymmetry 1.21 gained 14.4 % held out, both halves of
    the fit part passing, and was accepted; all of its gain was on the 1.3 % of the held-out
    samples where the model's rows are sparse (-8.5 % on the rest). Now nothing is found."""
    model = diagnose(*_plant({}, seed=13, seconds=120.0, holds=True),
                     candidates=()).model_before
    d = diagnose(*_plant({}, seed=113, seconds=120.0, holds=True), model=model)
    assert d.effects_found == []
    assert not any(n.startswith("WARNING") for n in d.notes)  # no voltage beyond the model's
    asym = [c.evidence for c in d.candidates if c.effect == "asymmetry"][0]
    assert asym["improvement"] >= asym["threshold"] > asym["improvement_in_model_range"]
    assert asym["half_improvements"] and min(asym["half_improvements"]) >= asym["threshold"]


def test_input_kind_tells_an_input_with_holds_from_the_mixed_input():
    """The mixed input holds its levels 0.5-5 s; the steps with holds hold them 3-10 s with
    the sine off. Two mixed records are of one kind, a mixed record and one with holds not."""
    def kind_of(u):
        return input_kind(u[:int(0.7 * u.size)], RATE)  # as a model's fit part

    k0, k1 = (kind_of(mixed(120.0, RATE, 3.0, band_hz=(0.02, 0.8), seed=s)[1]) for s in (0, 100))
    kh = kind_of(_input(120.0, seed=102, holds=True))
    assert k0["hold_share"] < 0.15 and kh["hold_share"] > 0.45
    assert not kinds_differ(k0, k1) and kinds_differ(k0, kh) and kinds_differ(kh, k1)
    # a bandwidth 4 times as wide differs too, holds alike
    assert kinds_differ(k0, dict(k0, bandwidth_hz=4 * k0["bandwidth_hz"]))
    assert not kinds_differ(k0, dict(k0, bandwidth_hz=2 * k0["bandwidth_hz"]))
    # a model file without a kind, or with a damaged one, has none: the record is not checked

    class Loaded:
        metadata_ = {"input_kind": k0}

    assert model_input_kind(Loaded()) == pytest.approx(k0)
    for bad in ({}, {"input_kind": None}, {"input_kind": {"bandwidth_hz": "fast"}},
                {"input_kind": dict(k0, hold_share=1.5)}):
        Loaded.metadata_ = bad
        assert model_input_kind(Loaded()) is None
    assert model_input_kind(object()) is None


def test_blocks_around_a_model_of_another_kind_of_input_are_undecided(tmp_path):
    """Session 37: a clean day's model from the mixed 3 V input (seed 0), given a clean later
    day with input holds (seed 100). An asymmetry 0.88 gained 37 % on the held-out part and
    passed every test, where the model has data too: the model's error on long holds, which it
    never saw. Now no block is accepted around a model of another kind of input; the
    asymmetry is named undecided, and the kind travels with the model's file."""
    model = diagnose(*_mixed_record({}, seed=0), candidates=()).model_before
    assert model_input_kind(model)["hold_share"] < 0.15
    d = diagnose(*_plant({}, seed=100, seconds=120.0, holds=True), model=model)
    assert d.effects_found == []
    assert any(n.startswith("WARNING: the record's input is not of the given model's kind")
               for n in d.notes)
    asym = [c for c in d.undecided() if c.effect == "asymmetry"][0].evidence
    assert asym["improvement"] >= asym["threshold"]  # it passes every test
    assert min(asym["half_improvements"]) >= asym["threshold"]
    kinds = asym["input_kinds"]
    assert kinds["record"]["hold_share"] > kinds["model"]["hold_share"] + 0.3
    write_report(d, tmp_path / "r")
    report = (tmp_path / "r" / "report.md").read_text()
    assert "Undecided for a model of another kind of input: **asymmetry**" in report
    given = load_augmented(tmp_path / "r" / "model_before.json")
    assert model_input_kind(given) == pytest.approx(model_input_kind(model))


def test_block_direction_is_the_side_or_the_sign():
    assert block_direction("asymmetry", {"negative_gain_ratio": 0.9}) == -1.0
    assert block_direction("asymmetry", {"negative_bending_ratio": 1.1}) == 1.0
    assert block_direction("rate_dependence", {"tau_s": 0.2, "gain_mm_per_v_per_s": -0.01}) == -1
    assert block_direction("dead_zone", {"width_v": 0.3}) == 0.0


def test_a_block_around_a_given_model_keeps_its_direction_beside_another():
    """`bench_diagnose.py stale 4 drift` (full tuning): fitted alone the asymmetry made the
    negative side weaker (0.94); after the drift it made it stronger (1.09, +15.1 %, both halves
    passing) and was accepted beside the drift. A change of the plant does not reverse when
    another block is added (docs/diagnose.md, session 28)."""
    model = diagnose(*_mixed_record({}, seed=4), candidates=()).model_before
    fx = {"drift": {"gain_loss_per_min": 0.1, "offset_mm_per_min": 0.3}}
    d = diagnose(*_mixed_record(fx, seed=104), model=model)
    assert d.effects_found == ["drift"]
    asym = {c.evidence["round"]: c.evidence for c in d.candidates
            if c.effect == "asymmetry" and "params" in c.evidence}
    assert block_direction("asymmetry", asym[1]["params"]) == -1.0
    assert block_direction("asymmetry", asym[2]["params"]) == 1.0
    assert asym[2]["improvement"] >= asym[2]["threshold"]  # what passed before
    assert not asym[2]["significant"]
    assert "pointed the other way" in asym[2]["text"]


def test_two_changes_that_hide_each_other_are_found_together():
    """`combos.py` (session 29; the `stale` bench with an asymmetry 1.25 and a drift at once,
    full tuning, seed 2): alone, the drift lost 21 % on the held-out part (the asymmetry pulls
    it) and the asymmetry 36 %, so nothing was found. Fitted beside each other in turn, both
    pass all their tests (docs/diagnose.md, session 29)."""
    model = diagnose(*_mixed_record({}, seed=2), candidates=()).model_before
    fx = {"asymmetry": {"negative_gain_ratio": 1.25},
          "drift": {"gain_loss_per_min": 0.1, "offset_mm_per_min": 0.3}}
    d = diagnose(*_mixed_record(fx, seed=102), model=model)
    assert sorted(d.effects_found) == ["asymmetry", "drift"]
    alone = [c.evidence for c in d.candidates if "beside" not in c.evidence
             and "params" in c.evidence]
    assert not any(e["significant"] and e["improvement"] >= e["threshold"] for e in alone)
    acc = {c.effect: c.evidence for c in d.candidates if c.accepted}
    assert acc["asymmetry"]["beside"] == "drift" and acc["drift"]["beside"] == "asymmetry"
    assert [e.name for e in d.model_after.effects] == d.effects_found
    fitted = {e.name: e.params for e in d.model_after.effects}
    assert fitted["drift"]["gain_loss_per_min"] == pytest.approx(0.1, rel=0.3)
    ratio = fitted["asymmetry"].get("negative_bending_ratio",
                                    fitted["asymmetry"].get("negative_gain_ratio"))
    assert 1.1 < ratio < 1.45
    assert d.rmse_after_mm < 0.7 * d.rmse_before_mm


def test_a_static_block_that_took_in_another_is_refitted_with_it():
    """`bench_diagnose.py combos 4` (session 29; full tuning): with an asymmetry 0.8 and a 0.3 V
    dead zone, the dead zone alone was fitted at 0.48 V and the asymmetry beside it gained
    2.6 %. Refitted jointly (docs/diagnose.md, session 29), both are found near the plant's."""
    model = diagnose(*_mixed_record({}, seed=4), candidates=()).model_before
    fx = {"asymmetry": {"negative_gain_ratio": 0.8}, "dead_zone": {"width_v": 0.3}}
    d = diagnose(*_mixed_record(fx, seed=104), model=model)
    assert sorted(d.effects_found) == ["asymmetry", "dead_zone"]
    assert [e.name for e in d.model_after.effects] == d.effects_found
    first = next(c for c in d.candidates if c.effect == "dead_zone" and "refitted" in c.evidence)
    assert not first.accepted and first.evidence["params"]["width_v"] > 0.4
    fitted = {e.name: e.params for e in d.model_after.effects}
    assert fitted["dead_zone"]["width_v"] == pytest.approx(0.3, rel=0.2)
    ratio = fitted["asymmetry"].get("negative_bending_ratio",
                                    fitted["asymmetry"].get("negative_gain_ratio"))
    assert 0.7 < ratio < 0.92
    acc = [c.evidence for c in d.candidates if c.accepted]
    assert all("beside" in e for e in acc)


# Memory channels (docs/diagnose.md, "Memory channels"): time constants 1 and 3 s chosen on an
# oracle on seeds 0, 1; seeds 6, 7 used for nothing. `mixed` 1.5 V, 120 s at 50 Hz. Measured
# with FAST: 0.3 V found on both seeds with memory, on seed 7 only without; 0.5 V found on
# seed 7, not on seed 6 (-2.4 %), so 0.5 V is not asserted.
@pytest.mark.parametrize("seed", [6, 7])
@pytest.mark.parametrize("effect", ["dead_zone", None])
def test_memory_channels_name_the_dead_zone_and_nothing_on_a_clean_record(seed, effect):
    _, u = mixed(120.0, RATE, 1.5, band_hz=(0.02, 0.8), seed=seed)
    fx = {"dead_zone": {"width_v": 0.3}} if effect else {}
    run = IpmcPlant(effects=fx, seed=seed, dt_s=1 / RATE).run(u)
    d = diagnose(run.t_s, run.u_v, run.y_mm, memory_taus_s=(1.0, 3.0), **FAST)
    assert [e.name for e in d.model_before.effects] == ["memory", "memory"]
    assert d.model_before.baseline.input_lags_ == (12, 1, 1)
    if effect is None:
        assert d.effects_found == []
        return
    assert d.effects_found[:1] == ["dead_zone"]
    fitted = [e for e in d.model_after.effects if e.name == "dead_zone"][0]
    assert fitted.params["width_v"] == pytest.approx(0.3, rel=0.1)
    assert d.rmse_after_mm < 0.9 * d.rmse_before_mm


def test_an_effect_below_the_noise_floor_is_not_material(tmp_path):
    """The record that motivated the rule (docs/diagnose.md, "Materiality"): `ipmc simulate`
    random sine 1.0 V, 0.3 V dead zone, seed 1, 120 s at 50 Hz; full tuning, memory 1 and 3 s.
    After the dead zone a drift passed every other rule (+13.0 %, r = 0.43) while changing the
    held-out prediction by 0.0038 mm RMS, below the record's noise floor (0.0061 mm)."""
    from ipmc_driver.simulate_cli import main as simulate

    csv = tmp_path / "rs.csv"
    assert simulate(["--input", "random-sine", "--amplitude", "1.0", "--seconds", "120",
                     "--rate-hz", "50", "--seed", "1", "--effect", "dead_zone",
                     "--out", str(csv)]) == 0
    t, u, y = np.loadtxt(csv, delimiter=",", skiprows=1).T
    d = diagnose(t, u, y, memory_taus_s=(1.0, 3.0))
    assert d.effects_found == ["dead_zone"]
    dz = next(c for c in d.candidates if c.accepted).evidence
    assert dz["material"] and dz["contribution_mm"] > dz["noise_floor_mm"]
    # noise 0.005 mm and 0.01 mm steps: 0.0058 mm (the noise alone is 14 % below)
    assert dz["noise_floor_mm"] == pytest.approx(0.0058, rel=0.10)
    drift = next(c for c in d.candidates
                 if c.effect == "drift" and c.evidence["round"] == 2).evidence
    # every other rule passes: only materiality refuses it
    assert drift["significant"] and drift["improvement"] >= drift["threshold"]
    assert not drift["material"] and drift["contribution_mm"] < drift["noise_floor_mm"]
    assert "not material" in drift["text"]


@pytest.mark.parametrize("effect", ["dead_zone", "none"])
def test_report_names_an_effect_in_the_data_that_the_baseline_already_represents(
        tmp_path, effect):
    """`ipmc simulate` mixed 1.5 V, seed 4 (not used to design the scan), 120 s at 50 Hz: the
    dead-zone scan names 0.3 V, the baseline refitted through it gains nothing, so nothing is
    accepted, and the report says the data carry a dead zone; the clean record says nothing."""
    from ipmc_driver.simulate_cli import main as simulate

    csv = tmp_path / "mixed.csv"
    assert simulate(["--input", "mixed", "--amplitude", "1.5", "--seconds", "120",
                     "--rate-hz", "50", "--seed", "4", "--out", str(csv)]
                    + (["--effect", effect] if effect != "none" else [])) == 0
    out = tmp_path / "report"
    assert main(["--data", str(csv), "--report", str(out), "--seed", "0"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary) == KEYS
    assert summary["effects_found"] == []
    report = (out / "report.md").read_text()
    in_data = [c for c in summary["candidates"] if c["evidence"].get("in_data")]
    if effect == "none":
        assert in_data == [] and "not missing from the model" not in report
        return
    assert {c["effect"] for c in in_data} == {"dead_zone"}
    assert in_data[0]["evidence"]["params"]["width_v"] == pytest.approx(0.3, abs=0.03)
    assert not in_data[0]["accepted"]
    assert "In the data but not missing from the model: **dead_zone**" in report


@pytest.mark.parametrize("case", ["mixed-delay", "random-sine-clean"])
def test_report_names_a_delay_in_the_data(tmp_path, case):
    """`ipmc simulate`, 120 s at 50 Hz, seeds not used to design the check (0-4 were): the
    plant's default delay (2 samples) on the mixed 3 V input (seed 9) is spanned by the
    baseline's input lags (nothing accepted), and the report says the data carry it; on a
    clean 1 V random sine (seed 5; on seed 9 the scan says lag 0) the dead-time scan alone
    puts the response 7 samples late (the plant's charging lag through a smooth input), but
    the input lags before it respond, and no delay is named."""
    from ipmc_driver.simulate_cli import main as simulate

    csv = tmp_path / "r.csv"
    args = (["--input", "mixed", "--amplitude", "3", "--effect", "delay"]
            if case == "mixed-delay" else ["--input", "random-sine", "--amplitude", "1"])
    seed = "9" if case == "mixed-delay" else "5"
    assert simulate(args + ["--seconds", "120", "--rate-hz", "50", "--seed", seed,
                            "--out", str(csv)]) == 0
    out = tmp_path / "report"
    assert main(["--data", str(csv), "--report", str(out), "--seed", "0"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    report = (out / "report.md").read_text()
    delay = [c for c in summary["candidates"] if c["effect"] == "delay"]
    assert "delay" not in summary["effects_found"]
    scan = delay[0]["evidence"]["test"]
    assert scan["p_value"] < 1e-3 and scan["delay_samples"] > 0
    if case == "random-sine-clean":
        assert scan["p_before"] < 1e-3
        assert not any(c["evidence"].get("in_data") for c in delay)
        assert "**delay**" not in report
        return
    assert scan["delay_samples"] == 2 and scan["p_before"] >= 1e-3
    assert delay[0]["evidence"]["in_data"]
    assert "In the data but not missing from the model: **delay**" in report
    assert "the input lags before it add nothing" in report


@pytest.mark.parametrize("seed", [7, 10, 11])  # seeds 0-5 set the RSS-ratio floor
def test_a_drift_on_a_smooth_input_is_no_dead_time(seed):
    """Random sine 1.5 V, 120 s at 50 Hz, drift 0.1 /min and 0.3 mm/min, the fit part: the
    scan puts the response late and nothing responds before it (the drift breaks the linear
    ARX), but the dead time explains little of the residual (ratio < 1.02); the plant's
    default delay on the mixed 3 V input explains far more (1.6-2.5 on seeds 5-9)."""
    from ipmc_model.diagnose import DELAY_MIN_RSS_RATIO, is_dead_time
    from ipmc_model.effects import dead_time_test

    cut = int(0.7 * 120 * RATE)
    _, u = random_sine(120.0, RATE, 1.5, (0.02, 0.8), seed=seed)
    fx = {"drift": {"gain_loss_per_min": 0.1, "offset_mm_per_min": 0.3}}
    y = IpmcPlant(effects=fx, seed=seed, dt_s=1 / RATE).run(u).y_mm
    t = dead_time_test(u[:cut], y[:cut], 1 / RATE)
    assert t["delay_samples"] > 0 and t["p_value"] < 1e-3 and t["p_before"] >= 1e-3
    assert t["rss_ratio"] < DELAY_MIN_RSS_RATIO and not is_dead_time(t)
    _, u = mixed(120.0, RATE, 3.0, band_hz=(0.02, 0.8), seed=seed)
    y = IpmcPlant(effects={"delay": {}}, seed=seed, dt_s=1 / RATE).run(u).y_mm
    t = dead_time_test(u[:cut], y[:cut], 1 / RATE)
    assert t["delay_samples"] == 2 and is_dead_time(t)


@pytest.mark.parametrize("effect", ["saturation", "none"])
def test_report_names_a_saturation_in_the_data(tmp_path, effect):
    """Mixed 3 V, seed 8 (not used to design the scan), 120 s at 50 Hz, a 2 mm limit: the
    baseline fitted on the record absorbs it (nothing accepted), the Wiener ARX scan finds it,
    and the report says so; the clean record says nothing."""
    from ipmc_model.diagnose import in_data_text, write_report

    t, u = mixed(120.0, RATE, 3.0, band_hz=(0.02, 0.8), seed=8)
    fx = {"saturation": {"limit_mm": 2.0}} if effect != "none" else {}
    y = IpmcPlant(effects=fx, seed=8, dt_s=1 / RATE).run(u).y_mm
    d = diagnose(t, u, y)
    sat = [c for c in d.candidates if c.effect == "saturation"]
    scan = sat[-1].evidence["saturation_scan"]
    write_report(d, tmp_path)
    report = (tmp_path / "report.md").read_text()
    if effect == "none":
        assert not scan["significant"] and d.in_data() == []
        assert "**saturation**" not in report
        return
    assert "saturation" not in d.effects_found
    assert [c.effect for c in d.in_data()] == ["saturation"]
    assert scan["significant"] and 2.0 < scan["limit_mm"] < 2.6
    assert "Wiener ARX scan" in in_data_text(d.in_data()[0])
    assert f"without the one of {scan['excursions']} excursions" in in_data_text(d.in_data()[0])
    assert "In the data but not missing from the model: **saturation**" in report


def test_one_large_peak_is_no_saturation_in_the_data():
    """Clean random sine 1 V, seed 6 (a design record), 120 s at 50 Hz: the scan's p is
    2.7e-5 (limit 1.38 mm, the output peaking at 1.31 mm), from the bend of one peak; the
    report names no saturation, because without that excursion the limit explains nothing."""
    t, u = random_sine(120.0, RATE, 1.0, (0.02, 0.8), seed=6)
    y = IpmcPlant(seed=6, dt_s=1 / RATE).run(u).y_mm
    d = diagnose(t, u, y)
    scan = [c for c in d.candidates if c.effect == "saturation"][-1].evidence["saturation_scan"]
    assert scan["p_value"] < 1e-3 and not scan["at_edge"]
    assert scan["p_without_top"] >= 1e-3
    assert not scan["significant"] and "saturation" not in [c.effect for c in d.in_data()]


def test_a_drift_found_is_no_saturation_in_the_data():
    """Random sine 1.5 V, seed 0 (used to design the scan), 120 s at 50 Hz, drift 0.1 /min and
    0.3 mm/min: on the raw record the gain loss passes the saturation scan (2.34 mm, p 2e-4);
    the scan asks the data as the final model sees them, drift taken out, and finds none."""
    t, u = random_sine(120.0, RATE, 1.5, (0.02, 0.8), seed=0)
    fx = {"drift": {"gain_loss_per_min": 0.1, "offset_mm_per_min": 0.3}}
    y = IpmcPlant(effects=fx, seed=0, dt_s=1 / RATE).run(u).y_mm
    d = diagnose(t, u, y)
    assert d.effects_found == ["drift"]
    scan = [c for c in d.candidates if c.effect == "saturation"][-1].evidence["saturation_scan"]
    assert not scan["significant"] and d.in_data() == []


# Creep and drift together: a soaked IPMC relaxes under a held voltage while it dehydrates.
# 120 s of random 1.5 V steps (holds 0.5-5 s) at 50 Hz, the plant's creep (20 s, -0.12 mm/V)
# and a drift of 0.1 /min, 0.3 mm/min. Once the drift was in the model its prediction moved
# through every hold, the settling mask blanked them, and the creep was tested on 1-6 holds
# instead of 16-21 (14 of 16 seeds): found on 1 of 16 (13, on 4 holds), 7 of 16 now. Seeds
# 0-7 were run while writing the fix, 8-15 after it (found on 3 of them); 5 and 13 asserted.
DRIFT = {"drift": {"gain_loss_per_min": 0.1, "offset_mm_per_min": 0.3}}
CREEP_12S = {"creep": {"tau_s": 12.0, "gain_mm_per_v": -0.6}}


def test_an_asymmetry_is_tested_only_around_a_given_model():
    """`bench_diagnose.py blind 66` (session 42; full tuning): without a model an asymmetry
    0.5 was accepted beside the plant's creep (0.2006 -> 0.1579 mm), and 0.8 on the clean
    record of that seed. A baseline fitted on the record represents the record's asymmetry;
    refitted through a scaled negative voltage it had found the plant's on none of 6 records.
    Around a model from a clean day it is found (test_given_model_from_a_clean_day_...)."""
    creep = {"tau_s": 15.0, "gain_mm_per_v": -0.35}
    d = diagnose(*_plant({"creep": creep}, seed=66, seconds=120.0, holds=True))
    assert d.effects_found == ["creep"]
    asym = [c for c in d.candidates if c.effect == "asymmetry"]
    assert asym and all(not c.accepted and "params" not in c.evidence for c in asym)
    assert asym[0].evidence["text"].startswith("not tested without a given model")


@pytest.mark.parametrize("seed", [5, 13])
def test_a_creep_beside_a_drift_is_found_on_the_holds(seed):
    _, u = random_steps(120.0, RATE, 1.5, seed=seed)
    run = IpmcPlant(effects={"creep": {}, **DRIFT}, seed=seed, dt_s=1 / RATE).run(u)
    d = diagnose(run.t_s, u, run.y_mm)
    assert d.effects_found[:2] == ["drift", "creep"]
    creeps = [c for c in d.candidates if c.effect == "creep"]
    # the hold test after the drift sees the holds it saw before
    assert creeps[1].evidence["hold_drift"]["holds"] == creeps[0].evidence["hold_drift"]["holds"]
    assert creeps[1].evidence["hold_drift"]["holds"] >= 15
    assert creeps[1].accepted and creeps[1].evidence["hold_drift"]["significant"]
    assert creeps[1].evidence["params"]["gain_mm_per_v"] < 0  # relaxes against the bending


def test_a_creep_the_drift_explains_is_not_named_in_the_data():
    """Mixed 0.5 V, seed 1, 120 s at 50 Hz, a drift and no creep: before the drift is taken
    out (round 1) the residual drifts during the 5 holds as a creep of 21 s would (lower bound
    0.28 > 0.25); after it (round 2, the final model) it does not, and the report speaks of
    the final model."""
    _, u = mixed(120.0, RATE, 0.5, band_hz=(0.02, 0.8), seed=1)
    y = IpmcPlant(effects=DRIFT, seed=1, dt_s=1 / RATE).run(u).y_mm
    d = diagnose(np.arange(u.size) / RATE, u, y)
    assert d.effects_found == ["drift"]
    first, last = [c for c in d.candidates if c.effect == "creep"]
    assert first.evidence["in_data"] and not last.evidence["in_data"]
    assert "creep" not in [c.effect for c in d.in_data()]


def test_a_limit_the_data_do_not_reach_is_not_accepted():
    """Seed 8 of the creep beside a drift: after the drift, a refit through an output limit
    at 2 x the data's peak (4.38 mm for 2.19 mm) gained 11.8 % (other rows +11.5, +11.2 %,
    signature r 0.41 > 0.21) and was accepted: it flattens the peaks the missing creep would
    have relaxed. There tanh bends the data by 7.6 % at most: a curvature, not a limit."""
    _, u = random_steps(120.0, RATE, 1.5, seed=8)
    run = IpmcPlant(effects={"creep": {}, **DRIFT}, seed=8, dt_s=1 / RATE).run(u)
    d = diagnose(run.t_s, u, run.y_mm)
    assert d.effects_found == ["drift"]
    sat = [c for c in d.candidates if c.effect == "saturation"][-1]
    assert sat.evidence["round"] == 2 and sat.evidence["improvement"] >= 0.1
    assert sat.evidence["params"]["limit_mm"] > 1.5 * np.max(np.abs(run.y_mm))
    assert not sat.evidence["significant"] and "not a limit they reach" in sat.evidence["text"]


def test_a_limit_the_data_reach_is_accepted_without_a_model():
    """Random sine 1.5 V, seed 10, 120 s at 50 Hz, a 1.5 mm limit the output peaks 0.17 mm
    below: the baseline fitted on the record does not represent it, and the limit, fitted at
    1.08 x the fit part's peak, is accepted (one of 3 of 40 saturation records)."""
    t, u = random_sine(120.0, RATE, 1.5, seed=10)
    y = IpmcPlant(effects={"saturation": {"limit_mm": 1.5}}, seed=10, dt_s=1 / RATE).run(u).y_mm
    d = diagnose(t, u, y)
    assert d.effects_found == ["saturation"]
    assert d.rmse_after_mm < 0.9 * d.rmse_before_mm
    limit = d.model_after.effects[0].params["limit_mm"]
    assert 1.3 < limit < 1.5 * np.max(np.abs(y))


def test_a_rate_channel_its_control_matches_is_not_accepted():
    """Clean plant, random 1.5 V steps, seed 4, 120 s at 50 Hz: the rate channel (tau 0.2 s)
    gained 15.2 % and was accepted, on a plant without a rate effect. The voltage low-passed
    with the same tau (one lag), which carries the same linear information, gains nearly as
    much (0.0811 mm against 0.0798 mm): the baseline's lags, 0.1 s apart, miss the fast response
    to a step, and either channel supplies it. A rate effect must gain 10 % over that control."""
    _, u = random_steps(120.0, RATE, 1.5, seed=4)
    run = IpmcPlant(seed=4, dt_s=1 / RATE).run(u)
    d = diagnose(run.t_s, u, run.y_mm)
    assert d.effects_found == []
    rate = [c for c in d.candidates if c.effect == "rate_dependence"][-1]
    ev = rate.evidence
    assert ev["improvement"] >= 0.1  # the gain that was accepted is still there
    assert ev["improvement_over_control"] < 0.1
    over = 1 - rate.rmse_mm / ev["control_rmse_mm"]
    assert ev["improvement_over_control"] == pytest.approx(over)
    assert not ev["significant"] and "not a rate effect" in ev["text"]


def test_a_drift_the_fit_part_does_not_trend_with_is_not_accepted():
    """Plant creep (default, no drift), random 1.5 V steps, seed 9, 120 s at 50 Hz: after the
    creep (right: tau 21 s, -0.14 mm/V) a drift was accepted at +18.2 % on the held-out part.
    The fit part's residual follows the fitted drift's trend 0.80 of the way, but within its
    slow scatter (jackknife lower bound -0.56): the held-out gain was a model error that differs
    between the parts. A drift must show as a trend where it was fitted."""
    _, u = random_steps(120.0, RATE, 1.5, seed=9)
    run = IpmcPlant(effects={"creep": {}}, seed=9, dt_s=1 / RATE).run(u)
    d = diagnose(run.t_s, u, run.y_mm)
    assert d.effects_found == ["creep"]
    drift = [c for c in d.candidates if c.effect == "drift"][-1].evidence
    assert drift["round"] == 2
    assert drift["improvement"] >= drift["threshold"]  # the gain that was accepted is there
    trend = drift["drift_trend"]
    assert trend["blocks"] == 20 and trend["coef"] > 0.5
    assert trend["lower"] == pytest.approx(trend["coef"] - 1.729 * trend["se"], abs=1e-3)
    assert trend["lower"] < 0
    assert not drift["significant"] and "not a drift" in drift["text"]


def _cand(effect, rmse_mm, passes):
    c = Candidate(effect, rmse_mm, False, {"round": 1}, model=object())
    c.passes = passes
    return c


def test_a_creep_is_a_rival_only_of_a_passing_drift_it_explains_as_well():
    creep = _cand("creep", 0.30, False)
    drift = _cand("drift", 0.32, True)
    assert creep_rival([creep, drift, _cand("delay", 0.2, True)]) == (drift, creep)
    assert creep_rival([_cand("creep", 0.33, False), drift]) is None  # the drift does better
    assert creep_rival([creep, _cand("drift", 0.25, False)]) is None  # the drift fails anyway
    assert creep_rival([_cand("creep", float("inf"), False), drift]) is None  # no creep fit
    assert creep_rival([drift]) is None
    # a creep that passes and does better is accepted before the drift anyway
    assert creep_rival([_cand("creep", 0.30, True), drift]) is None


# Clean 3 V mixed records without --model (the stale bench's day 1), full tuning: a drift passed
# on seeds 11 and 14 of 20 (session 29). On seed 14 the creep fitted in its place gained more
# (+20.3 % against +14.4 %, undecided for lack of holds) and the drift gains 0.5 % beside it.
# Creep (12 s, -0.6 mm/V) + drift on 1.5 V steps without holds, seed 2: the creep again explains
# the held-out part better than the drift (0.5327 against 0.5423 mm), but the drift beside it
# gains 17.5 %, a trend in time, and is kept (docs/diagnose.md, "A drift against a creep in its
# place"). Seed 11's false drift stayed (the creep gains 2 %) until session 33's trend test
# beside the hysteresis's memory, which now refuses seed 14's drift first: the creep rival is
# checked there with the trend test as it was (no memory column).
@pytest.mark.parametrize("case", ["clean-mixed-14", "creep-drift-steps-2"])
def test_a_drift_must_pass_beside_a_creep_that_explains_as_much(case, monkeypatch):
    rec = (_mixed_record({}, seed=14) if case == "clean-mixed-14"
           else _plant({**CREEP_12S, **DRIFT}, seed=2, seconds=120.0))
    if case == "clean-mixed-14":
        d = diagnose(*rec)
        drift = next(c for c in d.candidates if c.effect == "drift")
        assert d.effects_found == [] and drift.evidence["drift_trend"]["lower"] <= 0
        assert drift.evidence["drift_trend"]["hysteresis_travel_v"] is not None
        monkeypatch.setattr(diagnose_module, "DRIFT_TRAVEL_GRID_V", ())
    d = diagnose(*rec)
    drift = next(c for c in d.candidates if c.effect == "drift" and c.evidence["round"] == 1
                 and "beside" not in c.evidence)
    creep = next(c for c in d.candidates if c.effect == "creep" and c.evidence["round"] == 1)
    assert drift.evidence["improvement"] >= drift.evidence["threshold"]  # it gains alone
    assert drift.evidence["drift_trend"]["lower"] > 0  # and trends in the fit part
    assert creep.rmse_mm <= drift.rmse_mm and creep.evidence["undecided"]
    beside = drift.evidence["beside_creep"]
    assert beside["creep_rmse_mm"] == creep.rmse_mm
    gain_beside = 1 - beside["rmse_mm"] / creep.rmse_mm
    if case == "clean-mixed-14":
        assert d.effects_found == [] and gain_beside < 0.1 and not beside["passes"]
        assert not drift.accepted and "does not show a trend in time" in drift.evidence["text"]
        assert [c.effect for c in d.undecided()] == ["creep"]
    else:
        assert d.effects_found[:1] == ["drift"] and drift.accepted
        assert gain_beside >= 0.1 and beside["passes"]


# Creep 12 s, -0.6 mm/V + drift 0.1 /min, 0.3 mm/min, 120 s with holds: both found on 7 of 12
# seeds, nothing on 0, 1 and 7 before session 30. There the creep is fitted right on the holds
# and its hold test passes, but the held-out part, moved by the missing drift, gains -27.5 %
# and -0.3 % (seeds 0, 1); the drift alone is fitted wrong. Seeds 0 and 1 were used to write
# the pair (docs/diagnose.md, "A creep and a drift that hide each other").
@pytest.mark.parametrize("seed", [0, 1])
def test_a_creep_and_a_drift_that_hide_each_other_are_found_together(seed):
    d = diagnose(*_plant({**CREEP_12S, **DRIFT}, seed=seed, seconds=120.0, holds=True))
    first = [c for c in d.candidates if c.evidence["round"] == 1 and "beside" not in c.evidence]
    assert not any(c.accepted for c in first)
    creep = next(c for c in first if c.effect == "creep")
    assert creep.evidence["hold_drift"]["significant"]
    assert creep.evidence["improvement"] < creep.evidence["threshold"]  # refused alone
    assert sorted(d.effects_found) == ["creep", "drift"]
    acc = {c.effect: c.evidence for c in d.candidates if c.accepted}
    assert acc["drift"]["beside"] == "creep" and acc["creep"]["beside"] == "drift"
    assert 6.0 <= acc["creep"]["params"]["tau_s"] <= 18.0
    assert -0.75 <= acc["creep"]["params"]["gain_mm_per_v"] <= -0.45
    assert 0.15 <= acc["drift"]["params"]["offset_mm_per_min"] <= 0.45
    assert d.rmse_after_mm < 0.7 * d.rmse_before_mm
    if seed == 0:  # the pair adds two effects at once: not where only one may be added
        one = diagnose(*_plant({**CREEP_12S, **DRIFT}, seed=0, seconds=120.0, holds=True),
                       max_effects=1)
        assert one.effects_found == []


def test_memory_channels_are_not_for_a_given_model(day1_model):
    t, u, y = _mixed_record({}, seed=5, seconds=20.0)
    with pytest.raises(ValueError, match="memory channels"):
        diagnose(t, u, y, model=day1_model, memory_taus_s=(1.0,), **FAST)

def test_cli_writes_the_contract(tmp_path):
    t, u, y = _plant({}, seed=0, seconds=40.0)
    csv = save_csv(Record(t, u, y), tmp_path / "clean.csv")
    out = tmp_path / "report"
    assert main(["--data", str(csv), "--report", str(out), "--seed", "0"]) == 0

    def strict(constant):  # what jq and JSON.parse refuse
        raise AssertionError(f"summary.json is not strict JSON: {constant}")

    summary = json.loads((out / "summary.json").read_text(), parse_constant=strict)
    assert set(summary) == KEYS
    # a candidate not fitted or not tested has no RMSE: null (it was Infinity)
    assert any(c["rmse_mm"] is None for c in summary["candidates"])
    assert isinstance(summary["effects_found"], list)
    assert summary["rmse_before_mm"] > 0 and summary["rmse_after_mm"] > 0
    for c in summary["candidates"]:
        assert set(c) == {"effect", "rmse_mm", "accepted", "evidence"}
    report = (out / "report.md").read_text()
    assert "Before and after" in report and "acf_ccf.png" in report
    for f in ("residual_before_after.png", "acf_ccf.png", "residual_spectrum.png"):
        assert (out / f).stat().st_size > 1000
    assert not (out / "creep_holds.png").exists()  # no creep, found or named, on this record
    # the saved baseline can be given back as --model
    meta = json.loads(Path(summary["model_before"]).read_text())["metadata"]
    assert meta["held_out_free_run_rmse_mm"] == summary["rmse_before_mm"]
    out2 = tmp_path / "again"
    assert main(["--data", str(csv), "--model", summary["model_before"], "--report",
                 str(out2)]) == 0
    again = json.loads((out2 / "summary.json").read_text())["rmse_before_mm"]
    assert again == pytest.approx(summary["rmse_before_mm"], rel=1e-9)
    # beside the error it finds, the report gives the one the model had on its own record
    assert (f"Note: the given model erred {summary['rmse_before_mm']:.4f} mm (held-out "
            f"free-run RMSE) on its own record, {meta['data']}; here {again:.4f} mm before "
            "any block.") in (out2 / "report.md").read_text()



def test_cli_input_memory_taus_gives_the_baseline_memory_channels(tmp_path, capsys):
    t, u, y = _plant({}, seed=0, seconds=40.0)
    csv = save_csv(Record(t, u, y), tmp_path / "clean.csv")
    out = tmp_path / "report"
    assert main(["--data", str(csv), "--report", str(out), "--input-memory-taus", "1",
                 "3"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    doc = json.loads(Path(summary["model_before"]).read_text())
    assert [e["params"]["tau_s"] for e in doc["effects"] if e["name"] == "memory"] == [1, 3]
    assert "memory channels 1, 3 s" in (out / "report.md").read_text()
    assert main(["--data", str(csv), "--model", summary["model_before"], "--report",
                 str(tmp_path / "again"), "--input-memory-taus", "1"]) == 1
    assert "memory channels" in capsys.readouterr().err

def test_cli_bad_data_fails_with_one_sentence(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,u,y\n0,1,nan\n0.02,1,2\n")
    assert main(["--data", str(bad), "--report", str(tmp_path / "r")]) == 1
    assert "ipmc diagnose: error:" in capsys.readouterr().err


def test_bad_arguments_raise():
    t, u, y = _plant({}, seconds=10.0)
    with pytest.raises(ValueError, match="unknown candidate"):
        diagnose(t, u, y, candidates=["magic"], **FAST)
    with pytest.raises(ValueError, match="threshold"):
        diagnose(t, u, y, threshold=1.5, **FAST)


def test_lag_step_follows_input_bandwidth():
    u = _input(60.0)
    assert 1 <= choose_lag_step(u, RATE) <= 5
    fast = np.sin(2 * np.pi * 100 * np.arange(7500) / 750.0)
    assert choose_lag_step(fast, 750.0) == 1


def test_input_shift_flags_a_held_out_part_of_another_kind():
    # the CLI's 'mixed' input puts its held levels in the last quarter: a chronological split
    # then tests sines -> steps extrapolation (a clean plant got a dead zone that way)
    _, sine = random_sine(84.0, RATE, 2.5, (0.05, 1.0), 8, seed=9)
    _, steps = random_steps(36.0, RATE, 2.5, seed=9)
    shifted = input_shift(sine, steps, RATE)
    assert shifted["shifted"] and "WARNING" in shifted["text"]
    assert shifted["hold_share_fit"] == 0.0 and shifted["hold_share_held"] > 0.4
    u = _input(120.0, seed=9, holds=True)  # one kind throughout
    cut = int(0.7 * u.size)
    same = input_shift(u[:cut], u[cut:], RATE)
    assert not same["shifted"] and "WARNING" not in same["text"]
    assert same["beyond_range_share"] <= 0.2


def test_input_shift_flags_a_held_out_input_beyond_the_fit_range():
    # the bench's input on seed 4 (docs/diagnose.md, session 27): the held-out part reaches
    # -2.49 V, the fit part -1.49 V at most, and a dead-zone record got a false asymmetry; the
    # same kind of input otherwise (bandwidth, holds)
    _, us = random_sine(90.0, RATE, 2.5, (0.05, 1.0), 8, seed=6)
    _, st = random_steps(90.0, RATE, 1.5, (3.0, 10.0), seed=7)
    u = np.clip(0.6 * us + st, -3, 3)
    cut = int(0.7 * u.size)
    s = input_shift(u[:cut], u[cut:], RATE)
    assert s["range_fit_v"] == pytest.approx([-1.49, 2.39], abs=0.01)
    assert s["range_held_v"][0] == pytest.approx(-2.49, abs=0.01)
    assert s["beyond_range_share"] == pytest.approx(1.0 / 3.88, abs=0.01)
    assert s["shifted"] and "1 V beyond the fit part's range, 26 % of its span" in s["text"]
    # the same record split the other way round stays inside: no warning from the range
    inside = input_shift(u, u[:cut], RATE)
    assert inside["beyond_range_share"] == 0.0 and not inside["shifted"]


def test_a_committee_baseline_errs_less_on_new_input(tmp_path):
    """``--committee``: the baseline is the mean of three windows (12, 18, 24 lags), each tuned;
    on clean records it had less held-out error on 22 of 24 (docs/diagnose.md, session
    32). Seeds 1 and 14 here; saved and loaded as a committee; refused with --model."""
    from ipmc_model.effects import load_augmented
    from ipmc_model.narx import NarxCommittee, NarxModel

    for seed in (1, 14):
        rec = _mixed_record({}, seed=seed)
        one = diagnose(*rec, candidates=())
        com = diagnose(*rec, candidates=(), committee=True)
        assert isinstance(one.model_before.baseline, NarxModel)
        assert [m.input_lags for m in com.model_before.baseline.members] == [12, 18, 24]
        assert com.rmse_before_mm < 0.9 * one.rmse_before_mm
    csv = save_csv(Record(*rec), tmp_path / "clean.csv")
    assert main(["--data", str(csv), "--report", str(tmp_path / "rep"), "--committee"]) == 0
    s = json.loads((tmp_path / "rep" / "summary.json").read_text())
    assert "committee, the mean of 3 models" in (tmp_path / "rep" / "report.md").read_text()
    before = load_augmented(s["model_before"])
    assert isinstance(before.baseline, NarxCommittee)
    assert abs(diagnose(*rec, model=before, candidates=()).rmse_before_mm
               - s["rmse_before_mm"]) < 1e-9
    assert main(["--data", str(csv), "--report", str(tmp_path / "r2"), "--committee",
                 "--model", s["model_before"]]) == 1
