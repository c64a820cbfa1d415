"""Tests of ipmc_model.effects: blocks, augmented model, streaming, inverse, save/load."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from ipmc_driver.plant import IpmcPlant
from ipmc_driver.signals import random_sine, random_steps
from ipmc_model.effects import (
    PARAM_MEANING,
    PARAM_UNITS,
    AugmentedInverse,
    AugmentedModel,
    Effect,
    load_any_model,
    load_augmented,
    load_augmented_inverse,
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
    # an edited effect parameter is refused, as in any model file
    doc = json.loads(p.read_text())
    doc["effects"][0]["params"]["gain_mm_per_v"] = -2.5
    edited = tmp_path / "edited.json"
    edited.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match="edited.json.*changed or corrupted"):
        load_augmented(edited)


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




















