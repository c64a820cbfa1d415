"""Tests of ipmc_model.effects: blocks, augmented model, streaming, inverse, save/load."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from ipmc_driver.plant import IpmcPlant
from ipmc_driver.signals import mixed, random_sine, random_steps
from ipmc_model.effects import (
    EFFECT_NAMES,
    PARAM_MEANING,
    PARAM_UNITS,
    AugmentedInverse,
    AugmentedModel,
    Effect,
    dead_time_test,
    dead_zone_test,
    drift_removed,
    fit_creep_on_holds,
    fit_effect,
    fit_frozen_creep,
    fit_frozen_effect,
    load_any_model,
    load_augmented,
    load_augmented_inverse,
    mask_model_settling,
    refit_frozen_pair,
    saturation_test,
    save_augmented,
)
from ipmc_model.errors import ModelFileError
from ipmc_model.lssvm import LSSVMRegressor
from ipmc_model.narx import FreeRunCache, InverseNarxModel, NarxModel

RATE = 50.0


def _narx(rows=400):
    # the structure ipmc diagnose identifies (diagnose.BASELINE_INPUT_LAGS / _OUTPUT_LAGS)
    return NarxModel(LSSVMRegressor(C=1000.0, sigma=3.0), input_lags=12, output_lags=0,
                     lag_step=5, max_rows=rows)


@pytest.fixture(scope="module")
def record():
    _, us = random_sine(60, RATE, 2.5, (0.05, 1.0), 8, seed=2)
    _, st = random_steps(60, RATE, 1.5, (3.0, 10.0), seed=1)
    u = np.clip(0.6 * us + st, -3, 3)
    run = IpmcPlant(seed=0, dt_s=1 / RATE).run(u)
    return u, run.y_mm


@pytest.fixture(scope="module")
def base(record):
    u, y = record
    return AugmentedModel.identify(_narx(), u, y, (), 1 / RATE)


def test_every_parameter_has_a_unit_and_a_meaning():
    # the report's Fitted effects table reads both for every parameter of every form
    for name, keys in list(Effect._KEYS.items()) + list(Effect._OUTPUT_KEYS.items()):
        for k in keys:
            assert k in PARAM_UNITS and PARAM_MEANING[(name, k)]


def test_effect_validates_parameters():
    with pytest.raises(ValueError, match="unknown effect"):
        Effect("hysteresis", a=1.0)
    with pytest.raises(ValueError, match="needs parameters"):
        Effect("creep", tau_s=1.0)
    with pytest.raises(ValueError, match="tau_s must be > 0"):
        Effect("creep", tau_s=0.0, gain_mm_per_v=1.0)
    assert "mm/V" in Effect("creep", tau_s=3.0, gain_mm_per_v=-0.2).describe()


def test_creep_state_is_first_order_step_response():
    e = Effect("creep", tau_s=2.0, gain_mm_per_v=-0.5)
    u = np.ones(1001)
    c = e.creep_state(u, 0.01)
    assert c[0] == 0.0
    assert_allclose(c[200], -0.5 * (1 - np.exp(-2.0 / 2.0)), rtol=1e-9)


@pytest.mark.parametrize("name,params", [
    ("creep", {"tau_s": 5.0, "gain_mm_per_v": -0.3}),
    ("drift", {"gain_loss_per_min": 0.05, "offset_mm_per_min": 0.1}),
    ("saturation", {"limit_mm": 4.0}),
    ("rate_dependence", {"tau_s": 0.3, "gain_mm_per_v_per_s": 0.1}),
    ("asymmetry", {"negative_bending_ratio": 0.7}),
])
def test_output_effect_backward_inverts_forward(name, params):
    e = Effect(name, **params)
    rng = np.random.default_rng(0)
    u = rng.uniform(-3, 3, 500)
    z = rng.uniform(-3, 3, 500)
    t = np.arange(500) * 0.02
    assert_allclose(e.backward(e.forward(z, u, t, 0.02), u, t, 0.02), z, atol=1e-9)


def test_the_rate_channel_is_the_voltage_and_its_low_pass_linearly():
    """The premise of the diagnosis' control for the rate channel: lp(du/dt) = (u - lp(u)) / tau
    (discrete: factor (1 - a) / (a dt)), up to the filters' start transient, which decays as
    a^k. Beside the voltage, the rate channel carries no linear information the voltage's own
    low-pass does not."""
    dt = 0.02
    u = np.cumsum(np.random.default_rng(0).standard_normal(500)) * 0.1
    k = np.arange(u.size)
    for tau in (0.04, 0.2, 1.0):
        rate = Effect("rate_dependence", tau_s=tau).apply_input(u, dt)
        low = Effect("memory", tau_s=tau).apply_input(u, dt)
        a = np.exp(-dt / tau)
        assert_allclose(rate[:, 0], u)
        assert_allclose(low[:, 0], u)
        d = rate[:, 1] - (u - low[:, 1]) * (1 - a) / (a * dt)
        assert_allclose(d, d[0] * a ** k, atol=1e-9)
        assert abs(d[0]) > 1e-3  # the start transient is there, and is all there is


def test_rate_output_block_is_the_low_passed_voltage_rate_one_sample_late():
    e = Effect("rate_dependence", tau_s=0.3, gain_mm_per_v_per_s=0.1)
    assert e.side == "output" and not e.is_channel
    assert Effect("rate_dependence", tau_s=0.3).is_channel  # the refit form: a channel
    assert "mm/(V/s)" in e.describe()
    with pytest.raises(ValueError, match=r"or \['tau_s', 'gain_mm_per_v_per_s'\]"):
        Effect("rate_dependence", gain_mm_per_v_per_s=0.1)
    dt = 0.02
    u = np.r_[np.zeros(10), np.linspace(0.0, 2.0, 51), np.full(400, 2.0)]  # a 2 V ramp in 1 s
    g = e.rate_state(u, dt)
    assert_allclose(g[:12], 0.0, atol=1e-15)  # nothing before the rate reaches it
    a = np.exp(-dt / 0.3)
    assert g[12] == pytest.approx(0.1 * (1 - a) * 2.0)  # first ramp step (2 V/s), a sample late
    assert g[61] == pytest.approx(0.2 * (1 - a ** 50), rel=1e-9)  # 50 ramp steps: towards g du/dt
    assert abs(g[-1]) < 1e-6  # held: no current, no bending
    assert np.sum(g) * dt == pytest.approx(0.1 * 2.0, rel=1e-6)  # integral: g times the step


def test_asymmetry_output_form_scales_the_negative_bending(base, tmp_path):
    """Asymmetry's output form, one of the two fitted around a given model: the negative
    bending scaled, as a cracked electrode face scales it (the plant's form)."""
    e = Effect("asymmetry", negative_bending_ratio=0.7)
    assert e.side == "output" and e.is_output_form and not e.is_channel
    assert Effect("asymmetry", negative_gain_ratio=0.7).side == "input"  # the refit form
    assert "negative_bending_ratio = 0.7 1" in e.describe()
    with pytest.raises(ValueError, match="negative_bending_ratio must be > 0"):
        Effect("asymmetry", negative_bending_ratio=0.0)
    z = np.array([-2.0, -0.5, 0.0, 0.5, 2.0])
    assert_allclose(e.forward(z, z, z, 0.02), [-1.4, -0.35, 0.0, 0.5, 2.0])
    m = AugmentedModel(base.baseline, [e], base.dt_s)
    u = random_sine(10, RATE, 2.0, (0.1, 1.0), 4, seed=5)[1]
    zb = base.baseline.simulate(u)
    assert_allclose(m.simulate(u), np.where(zb >= 0, zb, 0.7 * zb), atol=1e-12)
    st, bs = m.stepper(), base.baseline.stepper()
    zs = np.array([bs.step(x) for x in u])
    assert_allclose([st.step(x) for x in u], np.where(zs >= 0, zs, 0.7 * zs), atol=1e-9)
    # the feedforward divides a negative reference by the ratio before the baseline inverse
    inv = m.inverse_stepper(_IdentityInverse())
    ref = np.r_[np.linspace(0, 1.0, 20), np.linspace(1.0, -1.4, 40)]
    u_ff = np.array([inv.step(r) for r in ref])
    assert_allclose(np.where(u_ff >= 0, u_ff, 0.7 * u_ff), ref, atol=1e-12)
    assert u_ff[-1] == pytest.approx(-2.0)
    # a model file keeps the form (the voltage form's round trip: test_save_load_round_trip)
    m2 = load_augmented(save_augmented(m, tmp_path / "asym.json"))
    assert m2.effects[0].params == {"negative_bending_ratio": 0.7}
    assert m2.effects[0].side == "output"
    assert_allclose(m2.simulate(u), m.simulate(u), atol=1e-12)


def test_stepper_matches_batch_simulation(base):
    effects = [Effect("dead_zone", width_v=0.2), Effect("creep", tau_s=4.0, gain_mm_per_v=-0.3),
               Effect("drift", gain_loss_per_min=0.02, offset_mm_per_min=0.05)]
    m = AugmentedModel(base.baseline, effects, base.dt_s)
    u = random_sine(10, RATE, 2.0, (0.1, 1.0), 4, seed=5)[1]
    st = m.stepper()
    stream = np.array([st.step(v) for v in u])
    # the same chain by hand: dead zone -> baseline stepper (from rest) -> creep -> drift
    v = effects[0].apply_input(u, m.dt_s)
    bs = base.baseline.stepper()
    z = np.array([bs.step(x) for x in v])
    t = np.arange(u.size) * m.dt_s
    expected = effects[2].forward(effects[1].forward(z, u, t, m.dt_s), u, t, m.dt_s)
    assert_allclose(stream, expected, atol=1e-9)
    # the rate output block: batch and stream agree, and it is invertible step by step
    rate = AugmentedModel(base.baseline, [Effect("rate_dependence", tau_s=0.3,
                                                 gain_mm_per_v_per_s=0.1)], base.dt_s)
    st = rate.stepper()
    bs = base.baseline.stepper()
    z = np.array([bs.step(x) for x in u])
    assert_allclose([st.step(v) for v in u], rate.effects[0].forward(z, u, t, m.dt_s),
                    atol=1e-9)
    inv = rate.inverse_stepper(_IdentityInverse())
    u_ff = np.array([inv.step(r) for r in u])
    # identity baseline: y = u_ff + g rho(u_ff) must equal the reference exactly
    assert_allclose(u_ff + rate.effects[0].rate_state(u_ff, rate.dt_s), u, atol=1e-12)


class _IdentityInverse:
    """Stands in for a fitted InverseNarxModel whose baseline is the identity (z = v)."""

    def stepper(self):
        return self

    def step(self, z):
        return z

    def record_applied(self, v):
        pass


def test_inverse_stepper_subtracts_creep_before_the_baseline_inverse(base):
    creep = Effect("creep", tau_s=5.0, gain_mm_per_v=-0.3)
    m = AugmentedModel(base.baseline, [creep], base.dt_s)
    ref = np.full(int(20 * RATE), 1.0)
    st = m.inverse_stepper(_IdentityInverse())
    u_ff = np.array([st.step(r) for r in ref])
    # with an identity baseline, y = u + c(u): the feedforward must make u + c = ref exactly
    c = creep.creep_state(u_ff, m.dt_s)
    assert_allclose(u_ff + c, ref, atol=1e-12)
    assert c[-1] < -0.2  # the creep built up and was compensated (u rose above 1 V)
    assert u_ff[-1] > 1.2
    # an applied voltage other than the returned one (limit, PID) advances the creep state
    st2 = m.inverse_stepper(_IdentityInverse())
    st2.step(1.0)
    st2.record_applied(0.0)
    assert st2.step(1.0) == 1.0  # no creep built from 0 V


def test_inverse_fits_in_baseline_space(record, base):
    u, y = record
    m = AugmentedModel(base.baseline, [Effect("creep", tau_s=5.0, gain_mm_per_v=-0.3)],
                       base.dt_s)
    inv = m.fit_inverse(u, y, InverseNarxModel(LSSVMRegressor(C=5000.0, sigma=2.0),
                                               lag_step=4, max_rows=300))
    st = m.inverse_stepper(inv)
    assert np.isfinite(st.step(0.5))


def test_delay_is_not_invertible(base):
    m = AugmentedModel(base.baseline, [Effect("delay", delay_s=0.1)], base.dt_s)
    with pytest.raises(ValueError, match="delay"):
        m.fit_inverse(np.zeros(10), np.zeros(10))


def test_save_load_round_trip(tmp_path, base):
    effects = [Effect("creep", tau_s=12.0, gain_mm_per_v=-0.25), Effect("asymmetry",
                                                                       negative_gain_ratio=1.3),
               Effect("rate_dependence", tau_s=0.3, gain_mm_per_v_per_s=0.1)]
    m = AugmentedModel(base.baseline, effects, base.dt_s)
    p = save_augmented(m, tmp_path / "aug.json")
    m2 = load_augmented(p)
    assert m2.effect_names == ["creep", "asymmetry", "rate_dependence"]
    assert m2.effects[2].side == "output"
    u = random_sine(8, RATE, 2.0, (0.1, 1.0), 4, seed=7)[1]
    assert_allclose(m2.simulate(u), m.simulate(u), atol=1e-12)
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ModelFileError, match="bad.json"):
        load_augmented(tmp_path / "bad.json")


@pytest.fixture(scope="module")
def feedforward(record, base):
    """An augmented model's feedforward: creep, dead zone and drift around the baseline; the
    inverse fitted in the baseline space of the part it keeps."""
    u, y = record
    m = AugmentedModel(base.baseline, [Effect("creep", tau_s=5.0, gain_mm_per_v=-0.3),
                                       Effect("dead_zone", width_v=0.1),
                                       Effect("drift", gain_loss_per_min=0.01,
                                              offset_mm_per_min=0.0)], base.dt_s)
    part, _ = m.feedforward_part()
    inv = part.fit_inverse(u, y, InverseNarxModel(LSSVMRegressor(C=5000.0, sigma=2.0),
                                                  output_lags=4, lag_step=4, max_rows=300))
    return AugmentedInverse(m, inv)


def test_feedforward_keeps_what_it_can_undo_and_says_why_it_leaves_the_rest(base):
    effects = [Effect("creep", tau_s=5.0, gain_mm_per_v=-0.3), Effect("drift",
               gain_loss_per_min=0.01, offset_mm_per_min=0.0), Effect("delay", delay_s=0.1),
               Effect("rate_dependence", tau_s=0.3), Effect("saturation", limit_mm=5.0),
               Effect("rate_dependence", tau_s=0.3, gain_mm_per_v_per_s=0.1)]
    part, left = AugmentedModel(base.baseline, effects, base.dt_s).feedforward_part()
    # the output form of rate dependence has a state known from the applied voltages
    assert part.effect_names == ["creep", "saturation", "rate_dependence"]
    assert part.effects[2].is_rate_output
    assert set(left) == {"drift", "delay", "rate_dependence"}
    assert "time" in left["drift"] and "ahead" in left["delay"]


def test_feedforward_stepper_goes_on_from_its_history(feedforward, record):
    """A stepper given the past (desired mm, applied V) from rest gives what the stepper that
    lived through it gives (a model server's reload)."""
    u, y = record
    ref, n, m = y[:600], 600, 400
    s = feedforward.stepper()
    out, applied = np.empty(n), np.empty(n)
    for k in range(n):
        out[k] = s.step(ref[k])
        applied[k] = np.clip(out[k], -1.5, 1.5)  # a limit: the applied voltage differs
        s.record_applied(applied[k])
    assert np.any(applied != out)
    s2 = feedforward.stepper(ref[:m], applied[:m])
    later = []
    for k in range(m, n):
        later.append(s2.step(ref[k]))
        s2.record_applied(applied[k])
    assert_allclose(later, out[m:], atol=1e-9)
    # the history's last voltage may still be corrected, as a live step's (model_server with
    # history_voltage:=applied, when the applied voltage comes after a reload)
    wrong = applied[:m].copy()
    wrong[-1] += 0.5
    s4 = feedforward.stepper(ref[:m], wrong)
    s4.record_applied(applied[m - 1])
    assert s4.step(ref[m]) == pytest.approx(out[m], abs=1e-9)
    assert abs(feedforward.stepper(ref[:m], wrong).step(ref[m]) - out[m]) > 1e-4
    # from rest instead, the creep state of the first 4 s is missing
    s3 = feedforward.stepper()
    assert abs(s3.step(ref[m]) - out[m]) > 1e-3
    with pytest.raises(ValueError, match="same length"):
        feedforward.stepper(ref[:5], applied[:4])


def test_feedforward_history_spans_its_slowest_effect(feedforward, record):
    """history_samples (what model_server keeps for a reload) spans five of the creep's time
    constants: going on from that many past samples lands near the stepper that lived through
    the whole record; from 256 (model_server's depth before) the creep state is short."""
    u, y = record
    n = y.size
    s, out, applied = feedforward.stepper(), np.empty(n), np.empty(n)
    for k in range(n):
        out[k] = s.step(y[k])
        applied[k] = np.clip(out[k], -1.5, 1.5)
        s.record_applied(applied[k])
    h = feedforward.history_samples
    assert h == math.ceil(5 * 5.0 * RATE) > feedforward.inverse.history_samples
    m = n - 200

    def going_on_from(depth):
        st, got = feedforward.stepper(y[m - depth:m], applied[m - depth:m]), []
        for k in range(m, n):
            got.append(st.step(y[k]))
            st.record_applied(applied[k])
        return np.max(np.abs(np.array(got) - out[m:]))

    err = {depth: going_on_from(depth) for depth in (h, 256)}
    assert err[h] < 0.02 * err[256], err


def test_feedforward_free_run_and_one_step(feedforward, record):
    u, y = record
    L = feedforward.max_lag_
    free = feedforward.simulate(y, u[:L])
    assert_allclose(free[:L], u[:L])
    # a one-step run fed its own free-run voltages is the free run
    assert_allclose(feedforward.predict(y, free)[L:], free[L:], atol=1e-9)
    one = feedforward.predict(y, u)
    assert np.sqrt(np.mean((one - u) ** 2)) < np.sqrt(np.mean(u ** 2))
    # the creep is undone: the voltages differ from the baseline inverse's alone
    bare = AugmentedInverse(AugmentedModel(feedforward.model.baseline, [], feedforward.dt_s),
                            feedforward.inverse).simulate(y, u[:L])
    assert np.max(np.abs(bare - free)) > 0.05


def test_feedforward_file_round_trip(feedforward, record, tmp_path):
    u, y = record
    p = save_augmented(feedforward, tmp_path / "ff.json", metadata={"data": "x.csv"})
    assert (tmp_path / "ff.inverse.json").exists() and (tmp_path / "ff.baseline.json").exists()
    ff = load_any_model(p, feedforward.dt_s)
    assert isinstance(ff, AugmentedInverse)
    assert ff.effect_names == ["creep", "dead_zone"] and set(ff.left_out) == {"drift"}
    assert ff.metadata_ == {"data": "x.csv"}
    assert_allclose(ff.simulate(y[:300]), feedforward.simulate(y[:300]), atol=1e-12)
    # the same file is the whole forward model for what reads a forward model
    fwd = load_augmented(p)
    assert fwd.effect_names == ["creep", "dead_zone", "drift"]
    with pytest.raises(ValueError, match="identified at 50 Hz, the data are at 100 Hz"):
        load_any_model(p, 0.01)
    # a model without a feedforward, a missing or wrong inverse file
    plain = save_augmented(feedforward.model, tmp_path / "after.json")
    with pytest.raises(ModelFileError, match="--effects-from after.json"):
        load_augmented_inverse(plain)
    (tmp_path / "ff.inverse.json").unlink()
    with pytest.raises(ModelFileError, match="ff.inverse.json"):
        load_any_model(p)
    (tmp_path / "ff.inverse.json").write_text((tmp_path / "ff.baseline.json").read_text())
    with pytest.raises(ModelFileError, match="not an inverse model"):
        load_any_model(p)


def test_channel_blocks_act_after_the_other_input_effects(record, tmp_path):
    """memory and rate_dependence append channels computed from the voltage the other input
    effects give, whatever the order the effects were added in; stepper = batch; save/load."""
    u, y = record
    dz = Effect("dead_zone", width_v=0.3)
    effects = [Effect("rate_dependence", tau_s=0.2), dz, Effect("memory", tau_s=1.0),
               Effect("memory", tau_s=3.0)]
    m = AugmentedModel.identify(_narx(300), u, y, effects, 1 / RATE)
    v, _ = m.to_baseline_space(u)
    assert v.shape == (u.size, 4)
    w = dz.apply_input(u, m.dt_s)
    assert_allclose(v[:, 0], w)
    a = np.exp(-m.dt_s / 3.0)
    lp = np.zeros_like(w)
    for k in range(w.size):  # the 3 s memory channel, from rest, of the dead-zone output
        lp[k] = a * (lp[k - 1] if k else 0.0) + (1 - a) * w[k]
    assert_allclose(v[:, 3], lp, atol=1e-12)
    b = np.exp(-m.dt_s / 0.2)  # the rate channel: du/dt of the dead-zone output, low-passed
    rho, prev = np.zeros_like(w), 0.0
    for k in range(w.size):
        prev = b * prev + (1 - b) * (w[k] - w[max(k - 1, 0)]) / m.dt_s
        rho[k] = prev
    assert_allclose(v[:, 1], rho, atol=1e-9)
    uu = random_sine(10, RATE, 2.0, (0.1, 1.0), 4, seed=5)[1]
    st = m.stepper()
    L = m.max_lag_  # the batch free run starts from L measured samples, the stepper from rest
    assert_allclose(np.array([st.step(x) for x in uu])[L:], m.simulate(uu)[L:], atol=1e-9)
    m2 = load_augmented(save_augmented(m, tmp_path / "mem.json"))
    assert m2.effect_names == ["rate_dependence", "dead_zone", "memory", "memory"]
    assert_allclose(m2.simulate(uu), m.simulate(uu), atol=1e-12)
    with pytest.raises(ValueError, match="memory"):
        AugmentedModel(m.baseline, [Effect("memory", tau_s=1.0)], m.dt_s).fit_inverse(u, y)
    with pytest.raises(ValueError, match="tau_s must be > 0"):
        Effect("memory", tau_s=0.0)
    # per-channel lags name the template's channels; the rate channel gets one lag (its value
    # now is the effect; a window of it would double the voltage's window)
    nx = NarxModel(LSSVMRegressor(C=1000.0, sigma=3.0), input_lags=(12, 1), output_lags=0,
                   lag_step=5, max_rows=300)
    base = AugmentedModel.identify(nx, u, y, [Effect("memory", tau_s=1.0)], 1 / RATE)
    assert base.baseline.input_lags_ == (12, 1)
    m3 = base.refit(nx, u, y, base.effects + [Effect("rate_dependence", tau_s=0.2)])
    assert m3.baseline.input_lags_ == (12, 1, 1)
    nx.input_lags = 12
    m4 = AugmentedModel.identify(nx, u, y, [Effect("rate_dependence", tau_s=0.2)], 1 / RATE)
    assert m4.baseline.input_lags_ == (12, 1)


def test_fit_creep_recovers_parameters_on_baseline_plus_creep():
    # 180 s: the creep is estimated from a cross-fitted residual, each half (90 s) predicted by
    # a baseline fitted on the other; on 60 s records tau is poorly determined (docs/diagnose.md)
    _, us = random_sine(180, RATE, 2.5, (0.05, 1.0), 8, seed=2)
    _, st = random_steps(180, RATE, 1.5, (3.0, 10.0), seed=1)
    u = np.clip(0.6 * us + st, -3, 3)
    base = AugmentedModel.identify(_narx(), u, IpmcPlant(seed=0, dt_s=1 / RATE).run(u).y_mm,
                                   (), 1 / RATE)
    true = Effect("creep", tau_s=8.0, gain_mm_per_v=-0.4)
    y = AugmentedModel(base.baseline, [true], base.dt_s).simulate(u)
    m, eff = fit_effect("creep", AugmentedModel(base.baseline, [], base.dt_s), _narx(), u, y)
    assert_allclose(eff.params["gain_mm_per_v"], -0.4, rtol=0.15)
    assert_allclose(eff.params["tau_s"], 8.0, rtol=0.3)
    assert m.effect_names == ["creep"]


def _lowpass(u, tau_s, dt_s):
    from scipy.signal import lfilter

    a = np.exp(-dt_s / tau_s)
    return lfilter([0.0, 1 - a], [1.0, -a], u)


def _hold_residual(seed: int, seconds: float = 240.0, noise_mm: float = 0.005,
                   dt: float = 0.02):
    """Synthetic residual (mm) of a finite-window baseline on random 2.5 V steps (holds
    0.5-6 s): a per-hold offset (path memory), a 0.4 s transient after each step, a shared
    slower settling (the input low-passed at 1.2 s, +0.03 mm/V) and white noise; (u, r)."""
    _, u = random_steps(seconds, 1 / dt, 2.5, (0.5, 6.0), seed=seed)
    rng = np.random.default_rng(seed)
    jumps = np.r_[0, np.flatnonzero(np.diff(u)) + 1, u.size]
    r = np.zeros_like(u)
    prev = 0.0
    for s, e in zip(jumps[:-1], jumps[1:], strict=True):
        step = u[s] - prev
        r[s:e] = 0.1 * np.sign(step) + 0.3 * step * np.exp(-np.arange(e - s) * dt / 0.4)
        prev = u[s]
    return u, r + 0.03 * _lowpass(u, 1.2, dt) + noise_mm * rng.standard_normal(u.size)


def test_fit_creep_on_holds_recovers_tau_and_gain_beside_the_settling():
    # the synthetic residual with a creep of tau 15 s, +0.2 mm/V (sizes not used to design
    # the fit)
    dt = 0.02
    u, r = _hold_residual(11)
    true = Effect("creep", tau_s=15.0, gain_mm_per_v=0.2)
    taus = np.geomspace(3.6, 480, 40)
    fit = fit_creep_on_holds(r + true.creep_state(u, dt), u, dt, taus, nuisance_tau_s=1.2)
    assert fit["holds"] >= 10 and not fit["at_edge"]
    assert 15.0 / 1.3 <= fit["tau_s"] <= 15.0 * 1.3
    assert_allclose(fit["gain_mm_per_v"], 0.2, rtol=0.2)
    assert_allclose(fit["nuisance_mm_per_v"], 0.03, atol=0.02)
    # the leave-one-hold-out prediction is there on every used hold, and only there
    own = np.isfinite(fit["oof_state"])
    assert own.sum() == sum(e - s for s, e in fit["segments"])
    # without the creep the fitted gain is small (the settling is taken by the nuisances)
    fit0 = fit_creep_on_holds(r, u, dt, taus, nuisance_tau_s=1.2)
    assert abs(fit0["gain_mm_per_v"]) < 0.05 or fit0["at_edge"]
    # too few holds: no fit
    assert "tau_s" not in fit_creep_on_holds(r[:600], u[:600], dt, taus)


def test_creep_hold_intervals_cover_the_truth_and_widen_with_the_noise():
    # the bootstrap over holds: 95 % intervals of tau and gain on 20 synthetic records (seeds
    # not used elsewhere; measured: 20 of 20 cover both, median hi / lo of tau 1.65, 4.24 with
    # 4 x the noise)
    dt, taus = 0.02, np.geomspace(3.6, 480, 40)
    true = Effect("creep", tau_s=15.0, gain_mm_per_v=0.2)

    def fit(seed, noise_mm):
        u, r = _hold_residual(seed, noise_mm=noise_mm)
        return fit_creep_on_holds(r + true.creep_state(u, dt), u, dt, taus, nuisance_tau_s=1.2)

    quiet = [fit(seed, 0.005) for seed in range(20, 40)]
    covered = [f["tau_interval_s"][0] <= 15.0 <= f["tau_interval_s"][1]
               and f["gain_interval_mm_per_v"][0] <= 0.2 <= f["gain_interval_mm_per_v"][1]
               for f in quiet]
    assert sum(covered) >= 18
    assert all(f["tau_interval_s"][0] <= f["tau_s"] <= f["tau_interval_s"][1] for f in quiet)

    def width(fits):
        return float(np.median([f["tau_interval_s"][1] / f["tau_interval_s"][0] for f in fits]))

    noisy = [fit(seed, 0.02) for seed in range(20, 40)]
    assert width(noisy) > 2.0 * width(quiet)
    # no noise: every resample picks the same tau; the interval is still a grid step each way
    exact = fit(20, 0.0)
    lo, hi = exact["tau_interval_s"]
    assert lo < exact["tau_s"] < hi and exact["tau_bounded"]
    assert fit(20, 0.0)["gain_interval_mm_per_v"] == exact["gain_interval_mm_per_v"]  # seeded
    u, r = _hold_residual(20)
    with pytest.raises(ValueError, match="n_boot must be at least 1"):
        fit_creep_on_holds(r, u, dt, taus, n_boot=0)


def _plant_creep_fit(seed: int, tau_s: float, gain: float):
    """240 s of random 2.5 V steps (holds 0.5-5 s: the demo's kind of record) at 50 Hz on the
    plant with a creep; the baseline identified, then the creep fitted: (model, effect)."""
    _, u = random_steps(240, RATE, 2.5, seed=seed)
    fx = {"creep": {"tau_s": tau_s, "gain_mm_per_v": gain}}
    y = IpmcPlant(effects=fx, seed=seed, dt_s=1 / RATE).run(u).y_mm
    base = AugmentedModel.identify(_narx(), u, y, (), 1 / RATE)
    return fit_effect("creep", base, _narx(), u, y)


@pytest.mark.parametrize("seed, tau_s, gain, bounded", [
    (6, 15.0, -0.2, True), (9, 12.0, 0.1, True), (10, 12.0, 0.1, True), (9, 15.0, 0.2, True),
    # the two whose point fit misses (the xfails below): the interval holds the truth and the
    # record is said not to bound tau
    (8, 12.0, 0.1, False), (7, 30.0, -0.15, False),
])
def test_creep_hold_intervals_hold_the_plants_creep(seed, tau_s, gain, bounded):
    _, eff = _plant_creep_fit(seed, tau_s, gain)
    fit = eff.hold_fit_
    lo, hi = fit["tau_interval_s"]
    g_lo, g_hi = fit["gain_interval_mm_per_v"]
    assert lo <= tau_s <= hi and g_lo <= gain <= g_hi
    assert fit["tau_bounded"] is bounded


@pytest.mark.parametrize("seed, tau_s, gain", [
    (6, 15.0, -0.2),
    # forward creeps (the tip keeps going the input's way), not used to design; the
    # diagnosis still refuses them (docs/diagnose.md, "Forward creep (session 8)")
    (9, 12.0, 0.1), (10, 12.0, 0.1), (9, 15.0, 0.2),
    # the first forward case run: 18.4 s, +0.139 mm/V (1.53x, +39 %), the slow side again
    pytest.param(8, 12.0, 0.1, marks=pytest.mark.xfail(
        strict=True, reason="tau 12 s fitted 18.4 s (1.53x): docs/diagnose.md")),
    # a slow creep on a short record: the fit's profile is flat over tau 14-27 s, it gives
    # tau 20.8 s (within 1.5x) but -0.091 mm/V (-40 %; the drift rate g / tau is within 12 %)
    pytest.param(7, 30.0, -0.15, marks=pytest.mark.xfail(
        strict=True, reason="tau 30 s on 240 s: tau and gain trade off (docs/diagnose.md)")),
])
def test_creep_fit_on_plant_holds_is_near_the_truth(seed, tau_s, gain):
    # the plant with a creep of sizes and seeds not used to design the hold fit; before it the
    # fit landed at tau 3.6 s (the grid's end) with twice the gain on the demo's record
    m, eff = _plant_creep_fit(seed, tau_s, gain)
    assert eff.hold_fit_["holds"] >= 10
    assert tau_s / 1.5 <= eff.params["tau_s"] <= 1.5 * tau_s
    assert_allclose(eff.params["gain_mm_per_v"], gain, rtol=0.35)
    assert m.effect_names == ["creep"]


def test_frozen_creep_is_fitted_on_the_hold_drift_around_a_fixed_model():
    # a model identified on the clean plant's step record (the demo's kind: holds 0.5-5 s),
    # then a later record of the plant with a creep: around the model kept as it is, the creep
    # comes from the residual's drift during the holds (session 34)
    _, u1 = random_steps(240, RATE, 2.5, seed=6)
    base = AugmentedModel.identify(_narx(), u1, IpmcPlant(seed=6, dt_s=1 / RATE).run(u1).y_mm,
                                   (), 1 / RATE)
    fx = {"creep": {"tau_s": 15.0, "gain_mm_per_v": -0.2}}
    _, u = random_steps(240, RATE, 2.5, seed=7)
    y = IpmcPlant(effects=fx, seed=7, dt_s=1 / RATE).run(u).y_mm
    m, eff = fit_frozen_creep(base, u, y)
    assert m.baseline is base.baseline and m.effect_names == ["creep"]
    assert eff.hold_fit_["holds"] >= 10
    assert 15.0 / 1.5 <= eff.params["tau_s"] <= 1.5 * 15.0
    assert_allclose(eff.params["gain_mm_per_v"], -0.2, rtol=0.35)
    assert eff.frozen_["fit_rmse_mm"] < 0.95 * eff.frozen_["fit_rmse_before_mm"]
    # the clean plant on the same input: the hold fit finds no creep of that size
    y0 = IpmcPlant(seed=7, dt_s=1 / RATE).run(u).y_mm
    _, eff0 = fit_frozen_creep(base, u, y0)
    assert abs(eff0.params["gain_mm_per_v"]) < 0.25 * 0.2
    # without input holds (a random sine) it is not fitted (the diagnosis then refits), nor
    # around a model that has a creep already
    _, us = random_sine(120, RATE, 2.5, (0.05, 1.0), 8, seed=7)
    with pytest.raises(ValueError, match="usable input hold"):
        fit_frozen_creep(base, us, IpmcPlant(effects=fx, seed=7, dt_s=1 / RATE).run(us).y_mm)
    with pytest.raises(ValueError, match="already has the creep"):
        fit_frozen_creep(m, u, y)


def test_mask_model_settling_blanks_where_the_model_still_moves():
    dt = 0.01
    u = np.r_[np.zeros(100), np.full(500, 2.0), np.full(500, -1.0)]
    r = 0.1 * np.sin(np.arange(u.size) * 0.05)
    # a model that keeps moving for 2.5 s after each jump (a rate channel), then is constant
    pred = np.zeros(u.size)
    pred[100:350] = np.linspace(1.0, 0.0, 250)
    pred[600:850] = np.linspace(-1.0, 0.0, 250)
    out = mask_model_settling(r, pred, u, dt)
    assert np.all(np.isnan(out[100:349])) and np.all(np.isnan(out[600:849]))
    assert_allclose(out[350:600], r[350:600])
    assert_allclose(out[850:], r[850:])
    assert_allclose(out[:100], r[:100])  # 1 s at rest is no usable hold
    # a model constant in every hold leaves the residual as it is
    assert_allclose(mask_model_settling(r, np.zeros(u.size), u, dt), r)


def test_drift_removed_lets_a_drifting_model_settle_in_holds(base):
    # a model with a drift moves through every input hold (here 0.3 mm/min and a gain loss of
    # 0.1 /min: 0.02 mm in 4 s), so the settling mask blanked the whole hold and a creep
    # beside the drift went untested; without the drift the model is constant in each hold
    dt = 1 / RATE
    u = np.r_[np.zeros(100), np.full(500, 2.0), np.full(500, -1.0), np.full(500, 1.5)]
    t = np.arange(u.size) * dt
    z = 0.8 * u  # the input-driven part, constant in each hold
    drift = Effect("drift", gain_loss_per_min=0.1, offset_mm_per_min=0.3)
    m = AugmentedModel(base.baseline, [drift], dt)
    pred = drift.forward(z, u, t, dt)
    assert_allclose(drift_removed(m, pred, t), z, atol=1e-12)
    r = 0.01 * np.sin(np.arange(u.size) * 0.05)
    blanked = mask_model_settling(r, pred, u, dt)
    kept = mask_model_settling(r, drift_removed(m, pred, t), u, dt)
    assert np.isnan(blanked[100:1500]).mean() > 0.9  # the hold tests saw almost no hold
    assert_allclose(kept, r)
    # a model without a drift: the prediction as it is
    assert_allclose(drift_removed(base, pred, t), pred)


def test_every_candidate_fits(record, base):
    u, y = record
    for name in EFFECT_NAMES:
        if name == "delay":  # its dead time comes from the ARX scan: none on the clean plant
            with pytest.raises(ValueError, match="no dead time"):
                fit_effect(name, base, _narx(), u, y, screen_narx=_narx(200))
            continue
        m, eff = fit_effect(name, base, _narx(), u, y, screen_narx=_narx(200))
        assert m.effect_names == [name] and eff.name == name
        assert np.all(np.isfinite(m.simulate(u[:200])))


@pytest.mark.parametrize("name, params", [
    ("dead_zone", {"width_v": 0.35}), ("saturation", {"limit_mm": 1.2}),
    ("asymmetry", {"negative_bending_ratio": 0.7}), ("asymmetry", {"negative_gain_ratio": 0.7}),
    ("delay", {"delay_s": 0.1}),
    ("drift", {"gain_loss_per_min": 0.2, "offset_mm_per_min": -0.3}),
    ("rate_dependence", {"tau_s": 0.25, "gain_mm_per_v_per_s": 0.08}),
])
def test_frozen_fit_recovers_the_block_around_a_fixed_model(record, base, name, params):
    # data = the fixed model seen through the block (+ laser-like noise): the fit must find
    # the block and leave the model's baseline untouched (asymmetry: in the form it has)
    u, _ = record
    truth = AugmentedModel(base.baseline, [Effect(name, **params)], base.dt_s)
    y = truth.simulate(u) + 0.005 * np.random.default_rng(0).standard_normal(u.size)
    m, eff = fit_frozen_effect(name, base, u, y)
    assert m.baseline is base.baseline and m.effect_names == [name]
    assert set(eff.params) == set(params)
    for k, v in params.items():
        assert eff.params[k] == pytest.approx(v, rel=0.05)
    assert eff.frozen_["fit_rmse_mm"] < 0.02 < eff.frozen_["fit_rmse_before_mm"]


def test_frozen_fit_finds_a_dead_zone_narrower_than_its_grid_step(record, base):
    # the grid's first width is 1/25 of half the input range; a narrower dead zone (here
    # 0.6 of it: the first width still beats no block) lies between it and 0, and the
    # refinement must look there (it stopped at the first width, 67 % too wide)
    u, _ = record
    width = 0.6 * 0.5 * np.max(np.abs(u)) / 25
    truth = AugmentedModel(base.baseline, [Effect("dead_zone", width_v=width)], base.dt_s)
    y = truth.simulate(u) + 0.005 * np.random.default_rng(2).standard_normal(u.size)
    _, eff = fit_frozen_effect("dead_zone", base, u, y)
    assert eff.params["width_v"] == pytest.approx(width, rel=0.1)


def test_frozen_fit_on_a_window_sees_only_that_window(record, base):
    # the diagnosis's split-half check: a dead zone that sets in half way through the record
    # is found on the second half alone, at its width, and refused on the first half alone
    u, _ = record
    h = u.size // 2
    truth = AugmentedModel(base.baseline, [Effect("dead_zone", width_v=0.35)], base.dt_s)
    y = np.concatenate([base.simulate(u)[:h], truth.simulate(u)[h:]])
    y = y + 0.005 * np.random.default_rng(4).standard_normal(u.size)
    _, late = fit_frozen_effect("dead_zone", base, u, y, window=(h, u.size))
    assert late.params["width_v"] == pytest.approx(0.35, rel=0.05)
    assert late.frozen_["fit_rmse_mm"] < 0.02 < late.frozen_["fit_rmse_before_mm"]
    with pytest.raises(ValueError, match="best without it"):
        fit_frozen_effect("dead_zone", base, u, y, window=(0, h))
    # the whole record as a window is no window; a window with no samples is refused
    _, whole = fit_frozen_effect("dead_zone", base, u, y)
    _, same = fit_frozen_effect("dead_zone", base, u, y, window=(0, u.size))
    assert same.params == whole.params and same.frozen_ == whole.frozen_
    for bad in ((h, h), (-1, h), (0, u.size + 1)):
        with pytest.raises(ValueError, match="leaves no samples"):
            fit_frozen_effect("dead_zone", base, u, y, window=bad)


def test_a_pair_refit_undoes_what_one_block_took_in(record, base):
    # a dead zone fitted alone takes in an asymmetry that maps the input alike; refitted jointly
    # with the asymmetry it comes back to its width (the diagnosis's backfit, session 29)
    u, _ = record
    truth = AugmentedModel(base.baseline, [Effect("dead_zone", width_v=0.3),
                                           Effect("asymmetry", negative_gain_ratio=0.8)],
                           base.dt_s)
    y = truth.simulate(u) + 0.005 * np.random.default_rng(6).standard_normal(u.size)
    alone, dz = fit_frozen_effect("dead_zone", base, u, y)
    assert abs(dz.params["width_v"] - 0.3) > 0.02  # the asymmetry taken in
    _, asym = fit_frozen_effect("asymmetry", alone, u, y)
    joint, dz2 = refit_frozen_pair(alone, 0, asym, u, y)
    assert dz2.params["width_v"] == pytest.approx(0.3, rel=0.05)
    assert joint.effect_names == ["dead_zone"] and joint.effects[0] is dz2
    assert dz2.frozen_["pair_with"] == "asymmetry"
    _, asym2 = fit_frozen_effect("asymmetry", joint, u, y)
    assert asym2.params["negative_gain_ratio"] == pytest.approx(0.8, rel=0.05)
    with pytest.raises(ValueError, match="joint refits are for"):
        refit_frozen_pair(alone, 0, Effect("delay", delay_s=0.02), u, y)


def test_a_free_run_is_causal_so_a_window_is_scored_on_the_whole_run(record, base):
    # the frozen fits score a window on the run over the whole fit part (kept in a cache):
    # that is exact only if no block looks ahead, so the run of a prefix must be the prefix
    # of the run, to the bit, with every block there is
    u, y = record
    fx = [Effect("delay", delay_s=0.1), Effect("dead_zone", width_v=0.2),
          Effect("asymmetry", negative_gain_ratio=0.8), Effect("creep", tau_s=5.0,
                                                                gain_mm_per_v=-0.2),
          Effect("rate_dependence", tau_s=0.2, gain_mm_per_v_per_s=0.05),
          Effect("asymmetry", negative_bending_ratio=0.9),
          Effect("drift", gain_loss_per_min=0.1, offset_mm_per_min=0.2),
          Effect("saturation", limit_mm=3.0)]
    L = base.max_lag_
    for effects in ([], fx[:3], fx[3:5], fx[5:]):
        m = AugmentedModel(base.baseline, effects, base.dt_s)
        whole = m.simulate(u, y[:L])
        for stop in (L + 1, u.size // 2, u.size - 1):
            assert np.array_equal(m.simulate(u[:stop], y[:L]), whole[:stop])
        cache = FreeRunCache(base.baseline)
        assert np.array_equal(m.simulate(u, y[:L], cache=cache), whole)
    with pytest.raises(ValueError, match="this model's baseline"):
        base.simulate(u, cache=FreeRunCache(_narx().fit(u[:600], y[:600])))


@pytest.mark.parametrize("name", ["dead_zone", "asymmetry", "saturation", "drift"])
def test_frozen_fits_through_one_cache_are_the_fits_without_it(record, base, name):
    # the diagnosis fits a block on the whole fit part and on each half, around one model,
    # through one cache: the fits must be those of separate calls, and the halves must find
    # the grid's runs there
    u, _ = record
    truth = AugmentedModel(base.baseline, [Effect("dead_zone", width_v=0.25),
                                           Effect("saturation", limit_mm=2.5)], base.dt_s)
    y = truth.simulate(u) + 0.005 * np.random.default_rng(3).standard_normal(u.size)
    h = u.size // 2
    cache = FreeRunCache(base.baseline)
    for window in (None, (0, h), (h, u.size)):
        _, shared = fit_frozen_effect(name, base, u, y, window=window, cache=cache)
        _, alone = fit_frozen_effect(name, base, u, y, window=window)
        assert shared.params == alone.params and shared.frozen_ == alone.frozen_
        if name in ("saturation", "drift"):  # output blocks: the baseline's input never changes
            assert cache.misses == 1
    if name in ("dead_zone", "asymmetry"):
        assert cache.hits > 40  # the halves' grids (24-25 values each, and per form)


def test_frozen_fit_refuses_a_block_the_data_do_not_need(record, base):
    u, _ = record
    y = base.simulate(u) + 0.005 * np.random.default_rng(1).standard_normal(u.size)
    for name in ("dead_zone", "saturation", "asymmetry", "delay"):
        with pytest.raises(ValueError, match="best without it"):
            fit_frozen_effect(name, base, u, y)
    with pytest.raises(ValueError, match="cannot be fitted around a frozen model"):
        fit_frozen_effect("creep", base, u, y)
    # the rate block's gain is fitted by least squares, so it rarely is refused outright; on
    # the model's own output it must change next to nothing
    m, eff = fit_frozen_effect("rate_dependence", base, u, y)
    assert abs(eff.params["gain_mm_per_v_per_s"]) < 0.005
    assert eff.frozen_["fit_rmse_mm"] > 0.99 * eff.frozen_["fit_rmse_before_mm"]


@pytest.mark.parametrize("delay_s, seed", [(None, 0), (None, 3), (0.05, 0), (0.1, 3), (0.2, 5)])
def test_dead_time_test_finds_the_plant_delay(delay_s, seed):
    # the plant rounds its delay to whole samples (0.05 s at 50 Hz -> 2 samples); seeds 3 and 5
    # were not used to set anything
    _, us = random_sine(60, RATE, 2.5, (0.05, 1.0), 8, seed=seed + 2)
    _, st = random_steps(60, RATE, 1.5, (3.0, 10.0), seed=seed + 3)
    u = np.clip(0.6 * us + st, -3, 3)
    fx = {} if delay_s is None else {"delay": {"delay_s": delay_s}}
    y = IpmcPlant(effects=fx, seed=seed, dt_s=1 / RATE).run(u).y_mm
    t = dead_time_test(u, y, 1 / RATE)
    expected = 0 if delay_s is None else int(round(delay_s * RATE))
    assert t["delay_samples"] == expected
    if expected:
        assert t["p_value"] < 1e-3 and not t["at_edge"]
        # a dead time: the input lags before it add nothing (0.03-0.14 on these records)
        assert t["p_before"] >= 1e-3
    else:
        assert t["p_value"] == 1.0 and t["p_before"] == 1.0


@pytest.mark.parametrize("seed", [5, 6, 7])  # not used to design the p_before check (0-4 were)
def test_dead_time_scan_on_a_smooth_input_is_no_dead_time(seed):
    # the clean plant on a 1 V random sine: the scan puts the response 6 samples late (the
    # charging lag looks like a delay through a smooth input), but it starts at lag 0
    _, u = random_sine(60, RATE, 1.0, (0.05, 0.8), 8, seed=seed)
    y = IpmcPlant(seed=seed, dt_s=1 / RATE).run(u).y_mm
    t = dead_time_test(u, y, 1 / RATE)
    assert t["delay_samples"] > 0 and t["p_value"] < 1e-3
    assert t["p_before"] < 1e-3


@pytest.mark.parametrize("seed", [6, 7])  # seeds 6, 7 and the 0.5 V width not used to design
def test_dead_zone_test_finds_the_plant_width(seed):
    # 120 s of `ipmc simulate --input mixed --amplitude 1.5` at 50 Hz, the fit part (70 %)
    _, u = mixed(120.0, RATE, 1.5, band_hz=(0.02, 0.8), seed=seed)
    cut = int(0.7 * u.size)
    for fx, width in (({}, None), ({"saturation": {}}, None), ({"dead_zone": {}}, 0.3),
                      ({"dead_zone": {"width_v": 0.5}}, 0.5)):
        y = IpmcPlant(effects=fx, seed=seed, dt_s=1 / RATE).run(u).y_mm
        t = dead_zone_test(u[:cut], y[:cut], 1 / RATE)
        assert not t["refused"] and t["moving_share"] > 0.7
        if width is None:  # the clean plant's own smooth nonlinearity is no dead zone
            assert t["p_value"] > 1e-3, (fx, t)
        else:
            assert t["p_value"] < 1e-3 and not t["at_edge"], (fx, t)
            assert t["width_v"] == pytest.approx(width, abs=0.04)


@pytest.mark.parametrize("seed", [8, 9])  # seeds 8, 9 not used to design the scan
def test_saturation_test_finds_an_output_limit_and_no_other_effect(seed):
    # 120 s of `ipmc simulate --input mixed --amplitude 3` at 50 Hz, the fit part (70 %): the
    # clean plant's own soft positive saturation (8 mm) and negative stiffening are no limit,
    # nor are the other static or slow effects
    _, u = mixed(120.0, RATE, 3.0, band_hz=(0.02, 0.8), seed=seed)
    cut = int(0.7 * u.size)
    for fx, limit in (({}, None), ({"asymmetry": {}}, None), ({"dead_zone": {}}, None),
                      ({"drift": {}}, None), ({"creep": {}}, None),
                      ({"saturation": {"limit_mm": 2.0}}, 2.0),
                      ({"saturation": {"limit_mm": 1.5}}, 1.5)):
        y = IpmcPlant(effects=fx, seed=seed, dt_s=1 / RATE).run(u).y_mm
        t = saturation_test(u[:cut], y[:cut], 1 / RATE)
        assert not t["refused"] and t["limits_tested"] == 25
        if limit is None:
            assert t["p_value"] > 1e-3 or t["at_edge"], (fx, t)
        else:
            assert t["p_value"] < 1e-3 and not t["at_edge"], (fx, t)
            # every excursion to the limit bends: without the one that gains most it holds
            assert t["p_without_top"] < 1e-3 and t["excursions"] > 20, (fx, t)
            # the scan's limit lies above the peak the data reach, near the plant's
            assert t["peak_mm"] < t["limit_mm"] < 1.3 * limit, (fx, t)


@pytest.mark.parametrize("kind, amplitude_v, effect, seed", [
    ("random-sine", 1.0, None, 6), ("mixed", 0.5, "asymmetry", 7), ("mixed", 1.0, "dead_zone", 7)])
def test_saturation_test_needs_more_than_one_excursion(kind, amplitude_v, effect, seed):
    # 120 s of `ipmc simulate` at 0.5-1 V, 50 Hz, the fit part, no limit: the scan's p falls
    # below 1e-3 (2.7e-5, 2.2e-5, 1.1e-4) on the bend of one large peak; without that
    # excursion nothing is left (design records: 13 of 224 such at 0.5-1 V, docs/diagnose.md)
    gen = random_sine if kind == "random-sine" else mixed
    _, u = gen(120.0, RATE, amplitude_v, band_hz=(0.02, 0.8), seed=seed)
    cut = int(0.7 * u.size)
    y = IpmcPlant(effects=[effect] if effect else [], seed=seed, dt_s=1 / RATE).run(u).y_mm
    t = saturation_test(u[:cut], y[:cut], 1 / RATE)
    assert t["p_value"] < 1e-3 and not t["at_edge"] and not t["refused"], t
    assert t["p_without_top"] >= 1e-3, t


@pytest.mark.parametrize("effect", ["dead_zone", "asymmetry"])
def test_saturation_test_takes_no_other_static_map_for_a_limit(effect):
    # random sine 1.5 V, seed 0 (used to design the scan): without the cube among the output
    # nuisance terms, both records passed as saturated (1.34 mm, p 3e-13; 1.83 mm, p 4e-17)
    _, u = random_sine(120.0, RATE, 1.5, (0.02, 0.8), seed=0)
    cut = int(0.7 * u.size)
    y = IpmcPlant(effects={effect: {}}, seed=0, dt_s=1 / RATE).run(u).y_mm
    t = saturation_test(u[:cut], y[:cut], 1 / RATE)
    assert t["p_value"] > 1e-3 or t["at_edge"], t


def test_saturation_test_refuses_a_step_input():
    _, u = random_steps(120.0, RATE, 2.5, seed=6)
    y = IpmcPlant(effects={"saturation": {"limit_mm": 2.0}}, seed=6, dt_s=1 / RATE).run(u).y_mm
    t = saturation_test(u, y, 1 / RATE)
    assert t["refused"] and t["p_value"] == 1.0


def test_dead_zone_test_refuses_a_step_input():
    # random steps visit a few dozen levels: a kink between them would always "fit"
    _, u = random_steps(120.0, RATE, 1.5, seed=6)
    y = IpmcPlant(effects={"dead_zone": {}}, seed=6, dt_s=1 / RATE).run(u).y_mm
    t = dead_zone_test(u, y, 1 / RATE)
    assert t["refused"] and t["moving_share"] < 0.5
