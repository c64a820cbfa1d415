"""The GPI model (ipmc_model.hysteresis): free run, stepper, numerical inverse, model files,
and ``ipmc identify``'s default comparison of families."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from ipmc_driver.dataio import Record, save_csv
from ipmc_driver.plant import IpmcPlant
from ipmc_driver.signals import mixed, random_sine, sine
from ipmc_model.errors import ModelFileError
from ipmc_model.hysteresis import (
    GeneralizedPI,
    GpiInverse,
    delayed,
    determined_edge_slopes,
    hinge_map,
    rate_limited_charge,
)
from ipmc_model.identify_cli import evaluate_main, identify_main
from ipmc_model.persistence import load_model, save_model
from ipmc_model.selection import LinearArx, record_limits


def _rmse(a, b) -> float:
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


@pytest.fixture(scope="module")
def rig_model():
    _, u = mixed(180.0, 100.0, 3.0, (0.02, 0.8), seed=1)
    y = IpmcPlant(seed=1).run(u).y_mm
    return GeneralizedPI().fit(u, y)


def test_fit_finds_the_plants_ion_current_limit_and_charging(rig_model):
    # the simulated IPMC charges with tau 0.2967 s under a 11.94 V/s ion-current limit
    assert rig_model.charge_tau_s_ == pytest.approx(0.2967, rel=0.2)
    assert rig_model.slew_v_per_s_ == pytest.approx(11.94, rel=0.2)
    assert rig_model.cv_.alpha in rig_model.alphas and len(rig_model.cv_.rmse) == 8


def test_a_transport_delay_is_kept_only_where_the_free_run_cv_wants_it(rig_model):
    assert rig_model.delay_samples_ == 0  # the simulated IPMC has none (a charging lag only)
    assert len(rig_model.delay_scores_) == 2  # yet the linear part proposed one
    from duhem_plant import duhem_plant  # 4 samples of delay before a hysteresis that acts
    # at once: there the delay is the lag a charging stage cannot take up

    _, u = mixed(120.0, 100.0, 3.0, (0.02, 0.8), seed=6)
    assert GeneralizedPI().fit(u, duhem_plant(u, 6)).delay_samples_ == 4


def test_warm_start_keeps_the_structure_and_fits_on_over_the_longer_record():
    """The comparison's refit: a model fitted on the first 70 % goes on over the whole
    record with its delay, scaling and knots, and fits the whole at least as well."""
    _, u = mixed(120.0, 100.0, 3.0, (0.02, 0.8), seed=3)
    y = IpmcPlant(seed=3).run(u).y_mm
    cut = int(0.7 * u.size)
    m = GeneralizedPI(max_nfev=20).fit(u[:cut], y[:cut])
    first = _rmse(m.simulate(u), y), m.delay_samples_, m.knots_.copy(), m.weights_.copy()
    m.warm_start = True
    m.fit(u, y)
    assert m.delay_samples_ == first[1] and np.array_equal(m.knots_, first[2])
    assert not np.array_equal(m.weights_, first[3])   # fitted on, not kept
    assert _rmse(m.simulate(u), y) <= 1.01 * first[0]


def test_free_run_on_another_input_is_near_the_noise_floor(rig_model):
    _, u = random_sine(60.0, 100.0, 3.0, band_hz=(0.02, 0.8), seed=2)
    y = IpmcPlant(seed=2).run(u).y_mm
    e = _rmse(rig_model.simulate(u), y)
    arx = _rmse(LinearArx().fit(*_train_pair()).simulate(u), y)
    assert e < 0.05 and e < arx / 5


def _train_pair():
    _, u = mixed(180.0, 100.0, 3.0, (0.02, 0.8), seed=1)
    return u, IpmcPlant(seed=1).run(u).y_mm


def test_stepper_is_the_free_run_and_goes_on_from_a_history(rig_model):
    _, u = random_sine(20.0, 100.0, 3.0, seed=5)
    ys = rig_model.simulate(u)
    s = rig_model.stepper()
    np.testing.assert_allclose([s.step(v) for v in u], ys, atol=1e-10)
    s2 = rig_model.stepper(u[:1200])
    np.testing.assert_allclose([s2.step(v) for v in u[1200:]], ys[1200:], atol=1e-9)


def test_inverse_is_exact_to_the_model_within_reach(rig_model):
    _, u = sine(1.5, 0.3, 20.0)
    y_desired = rig_model.simulate(u)
    u_inv = rig_model.inverse().simulate(y_desired)
    np.testing.assert_allclose(rig_model.simulate(u_inv), y_desired, atol=1e-6)
    assert np.max(np.abs(u_inv)) <= 3.0


def test_inverse_beyond_reach_holds_the_limit(rig_model):
    u = rig_model.inverse().simulate(np.full(300, 50.0))
    assert np.all(u == 3.0)


def test_record_applied_replaces_the_returned_voltage(rig_model):
    inv = rig_model.inverse()
    a, b = inv.stepper(), inv.stepper()
    u_a = a.step(0.005)
    assert abs(u_a) < 3.0  # within reach: the replaced voltage matters
    a.record_applied(0.0)
    b.step(0.005)
    assert a.step(0.006) != pytest.approx(b.step(0.006), abs=1e-3)


def test_charge_and_delay_stages():
    u = np.r_[np.zeros(5), np.full(200, 3.0)]
    v = rate_limited_charge(u, 0.3, 5.0, 0.01)
    assert np.max(np.diff(v)) <= 5.0 * 0.01 + 1e-12  # the ion-current limit
    assert v[-1] == pytest.approx(3.0 * (1 - 1e-3), rel=5e-3) or v[-1] < 3.0
    np.testing.assert_array_equal(delayed(np.arange(5.0), 2), [0, 0, 0, 1, 2])


def test_model_files_round_trip_and_refuse_a_changed_array(rig_model, tmp_path):
    _, u = random_sine(10.0, 100.0, 3.0, seed=3)
    path = save_model(rig_model, tmp_path / "gpi")
    np.testing.assert_array_equal(load_model(path).simulate(u), rig_model.simulate(u))
    ipath = save_model(rig_model.inverse(), tmp_path / "inv")
    inv = load_model(ipath)
    assert isinstance(inv, GpiInverse)
    np.testing.assert_array_equal(inv.simulate(u), rig_model.inverse().simulate(u))
    npz = path.with_suffix(".npz")
    npz.write_bytes(npz.read_bytes()[:-3] + b"xyz")
    with pytest.raises(ModelFileError, match="checksum"):
        load_model(path)


def test_a_hinge_beyond_the_fitted_range_does_not_move_the_free_run(tmp_path):
    """Fitted within +-1.5 V and run to +-3 V: the map's input leaves the range it was fitted
    on, where it goes on at its edge slope, so a hinge placed beyond that range (any
    coefficient: no data fixes it) changes nothing, and the range survives the file."""
    _, u = random_sine(60.0, 100.0, 1.5, seed=4)
    m = GeneralizedPI(max_nfev=10).fit(u, IpmcPlant(seed=4).run(u).y_mm)
    z_fit = m._design_and_outputs(u, m._theta)[0] @ m.weights_
    assert m.map_range_ == (z_fit.min(), z_fit.max())
    _, wide = random_sine(30.0, 100.0, 3.0, seed=5)
    z = m._design_and_outputs(wide, m._theta)[0] @ m.weights_
    assert z.max() > m.map_range_[1] + 0.1   # the run goes past the hinge added below
    before = m.simulate(wide)
    hinged = copy.deepcopy(m)
    hinged.knots_ = np.r_[m.knots_, m.map_range_[1] + 0.05]
    hinged.map_coef_ = np.r_[m.map_coef_, 1000.0]
    np.testing.assert_allclose(hinged.simulate(wide), before, atol=1e-9)
    hinged.map_range_ = (-np.inf, np.inf)   # without the range the hinge takes over
    assert _rmse(hinged.simulate(wide), before) > 1.0
    assert load_model(save_model(m, tmp_path / "gpi")).map_range_ == m.map_range_


def test_a_hinge_with_one_row_beyond_it_does_not_steer_the_run_past_the_range(
        tmp_path):
    """A hinge left just inside the top of the fit's range, one row beyond it and a slope
    change no data checks (1000 mm per unit): past the range the map goes on at the slope
    below that hinge, as it would without it, and that slope survives the file."""
    _, u = random_sine(60.0, 100.0, 1.5, seed=4)
    y = IpmcPlant(seed=4).run(u).y_mm
    m = GeneralizedPI(max_nfev=10).fit(u, y)
    z_fit = m._design_and_outputs(u, m._theta)[0] @ m.weights_
    _, wide = random_sine(30.0, 100.0, 3.0, seed=5)
    before = m.simulate(wide)
    hinged = copy.deepcopy(m)
    hinged.knots_ = np.r_[m.knots_, np.mean(np.sort(z_fit)[-2:])]
    hinged.map_coef_ = np.r_[m.map_coef_, 1000.0]
    hinged._learned_on(u, y)
    assert hinged.map_edge_slopes_[1] == pytest.approx(m.map_edge_slopes_[1])
    loaded = load_model(save_model(hinged, tmp_path / "gpi"))
    assert loaded.map_edge_slopes_ == hinged.map_edge_slopes_
    np.testing.assert_allclose(loaded.simulate(wide), hinged.simulate(wide), atol=1e-9)
    hinged.map_edge_slopes_ = None   # at the slope at the range's edge: the hinge's
    assert _rmse(hinged.simulate(wide), before) > 1.0


def test_each_edge_slope_is_that_of_the_outermost_segment_visited_twice_beyond_its_hinge():
    rows = np.arange(1000)
    z = np.linspace(0.0, 1.0, 1000)   # in time order: one sweep up
    knots, coef = np.array([0.2, 0.5, 0.999]), np.array([1.0, 1.0, -1.0, 500.0])
    # one row above the top hinge: its 500 is not followed; 200 below the lowest are
    assert determined_edge_slopes(z, rows, knots, coef, 10.0, 2) == (1.0, 1.0)
    # correlated over 150 rows, the 200 below the lowest hinge are two samples: needing
    # three, the lowest segment is not followed either, the next one is
    assert determined_edge_slopes(z, rows, knots, coef, 150.0, 3) == (2.0, 1.0)
    # two peaks, each a few rows above the top hinge: it is followed
    twice = 0.5 + 0.5 * np.sin(2 * np.pi * 2 * rows / 1000)
    assert determined_edge_slopes(twice, rows, knots, coef, 50.0, 2)[1] == 501.0
    beyond = np.array([-1.0, 2.0])
    np.testing.assert_allclose(hinge_map(beyond, knots, coef, (0.0, 1.0), (2.0, 1.0)),
                               hinge_map(np.array([0.0, 1.0]), knots, coef) + [-2.0, 1.0])


def _csv(tmp_path, name, u, y, rate_hz=100.0):
    t = np.arange(u.size) / rate_hz
    return str(save_csv(Record(t_s=t, u_v=u, y_mm=y), tmp_path / name))


def test_identify_with_no_flag_compares_families_and_keeps_the_table(tmp_path, capsys):
    _, u = mixed(120.0, 100.0, 3.0, (0.02, 0.8), seed=4)
    data = _csv(tmp_path, "rec.csv", u, IpmcPlant(seed=4).run(u).y_mm)
    assert identify_main(["--data", data, "--out", str(tmp_path / "m.json")]) == 0
    out = capsys.readouterr().out
    assert "held-out free-run RMSE" in out and "<- chosen" in out
    # the GPI runs on the input alone: one free-run line, no one-step line that repeats it
    assert "training free-run: RMSE" in out and "training one-step" not in out
    assert "its one-step prediction is its free run" in out
    doc = json.loads((tmp_path / "m.json").read_text())
    sel = doc["metadata"]["selection"]
    rows = {r["family"]: r for r in sel["families"]}
    assert set(rows) == {"gpi", "pi"} and sel["chosen"] == doc["kind"] == "gpi"
    assert rows["gpi"]["held_out_free_run_rmse_mm"] < rows["pi"]["held_out_free_run_rmse_mm"]


def test_one_periodic_sine_gets_the_warning_and_the_model_does_not_collapse(tmp_path, capsys):
    _, u = sine(2.5, 0.25, 120.0)
    y = IpmcPlant(seed=8).run(u).y_mm
    data = _csv(tmp_path, "sine.csv", u, y)
    assert identify_main(["--data", data, "--out", str(tmp_path / "m.json")]) == 0
    assert "one periodic excitation" in capsys.readouterr().err
    model = load_model(tmp_path / "m.json")
    _, uv = random_sine(60.0, 100.0, 3.0, band_hz=(0.02, 0.8), seed=9)
    yv = IpmcPlant(seed=9).run(uv).y_mm
    arx = LinearArx(6, 6).fit(u, y)
    assert _rmse(model.simulate(uv), yv) <= _rmse(arx.simulate(uv), yv)


def test_record_limits_are_silent_on_a_rich_record():
    _, u = mixed(600.0, 100.0, 3.0, (0.02, 0.8), seed=1)
    assert record_limits(u, 100.0) == []


def test_identify_refuses_bad_input_in_one_sentence(tmp_path, capsys):
    out = tmp_path / "m.json"
    assert identify_main(["--data", str(tmp_path / "none.csv"), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("ipmc identify: error:") and "\n" not in err
    assert not out.exists() and not out.with_suffix(".npz").exists()
    _, u = mixed(60.0, 100.0, 3.0, (0.02, 0.8), seed=4)
    data = _csv(tmp_path, "rec.csv", u, IpmcPlant(seed=4).run(u).y_mm)
    assert identify_main(["--data", data, "--model", "gpi", "--memory-taus", "1",
                          "--out", str(out)]) == 1
    assert "lssvm-narx" in capsys.readouterr().err and not out.exists()
    assert identify_main(["--data", data, "--C", "10", "--out", str(out)]) == 1
    assert "--C belong to one model family" in capsys.readouterr().err and not out.exists()


def test_evaluate_says_when_a_record_is_unlike_the_identification_record(tmp_path, capsys):
    _, u = sine(2.0, 0.16, 40.0)
    data = _csv(tmp_path, "sine.csv", u, IpmcPlant(seed=3).run(u).y_mm)
    assert identify_main(["--data", data, "--model", "pi", "--out", str(tmp_path / "m")]) == 0
    _, uv = random_sine(40.0, 100.0, 3.0, band_hz=(0.02, 0.8), seed=4)
    other = _csv(tmp_path, "rs.csv", uv, IpmcPlant(seed=4).run(uv).y_mm)
    capsys.readouterr()
    assert evaluate_main(["--model", str(tmp_path / "m.json"), "--data", data]) == 0
    assert "unlike" not in capsys.readouterr().err
    js = tmp_path / "e.json"
    assert evaluate_main(["--model", str(tmp_path / "m.json"), "--data", other,
                          "--json", str(js)]) == 0
    err = capsys.readouterr().err
    assert "beyond the identified -2 .. 2 V" in err and "another kind" in err
    assert len(json.loads(js.read_text())["unlike_identification"]) == 2


def test_inverse_with_a_delay_goes_on_from_a_history_as_from_its_own_steps():
    from duhem_plant import duhem_plant

    _, u = mixed(90.0, 100.0, 3.0, (0.02, 0.8), seed=7)
    model = GeneralizedPI().fit(u, duhem_plant(u, 7))
    assert model.delay_samples_ > 0
    _, y_ref = sine(1.0, 0.2, 6.0)
    inv = model.inverse()
    a = inv.stepper()
    applied = []
    for r in y_ref[:300]:
        applied.append(a.step(r))
        a.record_applied(applied[-1])
    b = inv.stepper(u_history=applied)
    np.testing.assert_allclose([a.step(r) for r in y_ref[300:320]],
                               [b.step(r) for r in y_ref[300:320]], atol=1e-6)


def test_travel_bank_is_the_recursion_and_still_while_the_input_holds():
    from ipmc_model.hysteresis import travel_bank

    rng = np.random.default_rng(0)
    v = np.concatenate([np.cumsum(rng.normal(0, 0.1, 300)), np.full(100, 1.0)])
    out, last = travel_bank(v, (0.5, 4.0))
    x = np.zeros(2)
    prev = 0.0
    for k, vk in enumerate(v):
        a = np.exp(-abs(vk - prev) / np.array([0.5, 4.0]))
        x = a * x + (1 - a) * vk
        prev = vk
        assert np.allclose(out[k], x, atol=1e-12)
    assert np.allclose(last, x)
    assert np.allclose(out[301:], out[301])  # a hold: no travel, no change


@pytest.mark.parametrize("n", [1, 63, 64, 65, 1000])
def test_play_bank_is_the_step_by_step_play_from_a_state(n):
    """The blocked scan gives exactly what N clip steps give, across block edges."""
    from ipmc_model.hysteresis import play_bank

    rng = np.random.default_rng(n)
    X = np.cumsum(rng.normal(0, 0.2, (n, 3)), axis=0)
    r = np.tile([0.0, 0.3, 1.0], (3, 1))
    w = rng.normal(0, 0.5, r.shape)
    out, last = play_bank(X, r, state=w)
    for k in range(n):
        w = np.clip(w, X[k][:, None] - r, X[k][:, None] + r)
        assert np.array_equal(out[k], w.ravel()), k
    assert np.array_equal(last, w)


def test_direction_bank_is_the_recursion_per_channel_and_still_while_they_hold():
    from ipmc_model.hysteresis import direction_bank

    rng = np.random.default_rng(1)
    X = np.vstack([np.cumsum(rng.normal(0, 0.1, (300, 2)), axis=0), np.ones((100, 2))])
    T = np.array([0.5, 4.0])
    out, last = direction_bank(X, T)
    d, prev = np.zeros((2, 2)), np.zeros(2)
    for k, xk in enumerate(X):
        a = np.exp(-np.abs(xk - prev)[:, None] / T)
        d = a * d + (1 - a) * np.sign(xk - prev)[:, None]
        prev = xk
        assert np.allclose(out[k], d.ravel(), atol=1e-12)
    assert np.allclose(last, d)
    assert np.allclose(out[301:], out[301])  # a hold: no travel, no change
    # from a state: the second half goes on from the first half's end
    half, state = direction_bank(X[:150], T)
    rest, _ = direction_bank(X[150:], T, x_prev=X[149], state=state)
    assert np.allclose(np.vstack([half, rest]), out)


def test_a_duhem_element_is_in_the_span_of_the_travel_and_direction_memories():
    """A Duhem element, dh = |du| (c u - h) / T + b du, is a travel low-pass of c u plus one
    of the direction b T sign(du): exactly the channels the GPI carries (at that travel)."""
    from ipmc_model.hysteresis import direction_bank, lowpass_bank, travel_bank

    _, u = mixed(60.0, 100.0, 3.0, band_hz=(0.02, 0.8), seed=2)
    u = lowpass_bank(u, [0.1], 0.01)[0][:, 0]  # a charge: small steps per sample
    travel_v, c, b = 1.5, 0.8, 0.35
    h, prev, out = 0.0, 0.0, np.empty(u.size)
    for k, uk in enumerate(u):  # integrated along the path in 0.005 V steps
        for x in np.linspace(prev, uk, 1 + max(1, int(abs(uk - prev) / 0.005)))[1:]:
            h += abs(x - prev) * (c * x - h) / travel_v + b * (x - prev)
            prev = x
        out[k] = h
    F = np.column_stack([travel_bank(u, [travel_v])[0],
                         direction_bank(u[:, None], [travel_v])[0]])
    w = np.linalg.lstsq(F, out, rcond=None)[0]
    # a sample's ramp of the input against the memories' one step: second order in its travel
    assert np.sqrt(np.mean((F @ w - out) ** 2)) < 0.02 * np.std(out)
    assert w == pytest.approx([c, b * travel_v], rel=0.1)


def test_optional_stages_step_as_they_simulate_and_survive_the_file(tmp_path):
    """Dead zone, fixed delay, drift, creep relaxations after the map and the output stage:
    the stepper equals the free run (also going on from a history), the inverse is exact to
    the model, and the model file keeps them all."""
    _, u = mixed(120.0, 50.0, 3.0, band_hz=(0.02, 0.8), seed=4)
    y = IpmcPlant(effects={"dead_zone": {}, "creep": {}}, seed=4, dt_s=0.02).run(u).y_mm
    m = GeneralizedPI(dt_s=0.02, memory_taus_s=(0.05, 0.45, 4.0), dead_zone_v=0.3,
                      delay_s=0.0, drift=True, output_taus_s=(12.0,),
                      max_nfev=8).fit(u[:4000], y[:4000])
    m.negative_gain_, m.limit_mm_ = 0.9, 9.0
    ys = m.simulate(u)
    st = m.stepper()
    assert np.allclose([st.step(v) for v in u], ys, atol=1e-9)
    st = m.stepper(u[:3000])
    assert np.allclose([st.step(v) for v in u[3000:]], ys[3000:], atol=1e-9)
    target = 0.8 * ys[:600]
    assert np.sqrt(np.mean((m.simulate(m.inverse().simulate(target)) - target) ** 2)) < 1e-6
    loaded = load_model(save_model(m, tmp_path / "m.json"))
    assert np.allclose(loaded.simulate(u), ys)
    assert (loaded.dead_zone_v, loaded.output_taus_s, loaded.limit_mm_) == (0.3, (12.0,), 9.0)


def test_the_charging_current_bending_after_the_map_is_recovered_and_runs_everywhere(tmp_path):
    """Bending that follows the charging current adds to the tip after the bending map: the
    output-side term recovers the plant's gain and its free run generalises; stepper, inverse
    and file give the same output as simulate, beside a creep relaxation."""
    _, u = mixed(160.0, 50.0, 3.0, band_hz=(0.02, 0.8), seed=5)
    y = IpmcPlant(effects={"rate_dependence": {"gain_mm_per_v_per_s": 0.1}}, seed=5,
                  dt_s=0.02).run(u).y_mm
    kw = dict(dt_s=0.02, memory_taus_s=(0.05, 0.15, 0.45, 1.35), delay_s=0.0, max_nfev=20)
    fit, held = slice(0, 5600), slice(5600, None)
    plain = GeneralizedPI(**kw).fit(u[fit], y[fit])
    rate = GeneralizedPI(**kw, output_rate=True).fit(u[fit], y[fit])
    assert rate.output_coef_[0] == pytest.approx(0.1, abs=0.02)
    e_plain = _rmse(plain.simulate(u)[held], y[held])
    assert _rmse(rate.simulate(u)[held], y[held]) < 0.6 * e_plain
    m = GeneralizedPI(**{**kw, "max_nfev": 6}, output_rate=True, output_taus_s=(12.0,)
                      ).fit(u[fit], y[fit])
    assert m.output_coef_.size == 2
    ys = m.simulate(u)
    st = m.stepper()
    assert np.allclose([st.step(v) for v in u[:3000]], ys[:3000], atol=1e-9)
    st = m.stepper(u[:3000])
    assert np.allclose([st.step(v) for v in u[3000:4000]], ys[3000:4000], atol=1e-9)
    target = 0.8 * ys[:600]
    assert np.sqrt(np.mean((m.simulate(m.inverse().simulate(target)) - target) ** 2)) < 1e-3
    loaded = load_model(save_model(m, tmp_path / "m.json"))
    assert loaded.output_rate and np.allclose(loaded.simulate(u), ys)


def test_the_charging_current_channel_steps_as_it_simulates():
    _, u = mixed(60.0, 50.0, 3.0, band_hz=(0.02, 0.8), seed=5)
    y = IpmcPlant(effects={"rate_dependence": {}}, seed=5, dt_s=0.02).run(u).y_mm
    m = GeneralizedPI(dt_s=0.02, memory_taus_s=(0.05, 0.45), rate_channel=True,
                      max_nfev=8).fit(u, y)
    st = m.stepper()
    assert np.allclose([st.step(v) for v in u], m.simulate(u), atol=1e-9)



def test_rows_not_measured_are_run_through_and_left_out_of_the_fit():
    """NaN in y marks rows without a measurement: the model runs over them (its state goes
    on) and is fitted on the rest; a spoiled stretch marked NaN does not spoil the fit."""
    _, u = random_sine(80.0, 50.0, 2.5, (0.05, 1.0), 8, seed=3)
    y = IpmcPlant(seed=3, dt_s=0.02).run(u).y_mm
    gap = slice(1500, 2500)
    spoiled = y.copy()
    spoiled[gap] += 20.0
    kw = dict(dt_s=0.02, delay_s=0.0, max_nfev=15, start_tau_factors=(1.0,))
    marked = spoiled.copy()
    marked[gap] = np.nan
    clean_rows = np.ones(u.size, dtype=bool)
    clean_rows[gap] = False
    with_nan = GeneralizedPI(**kw).fit(u, marked)
    with_spoil = GeneralizedPI(**kw).fit(u, spoiled)
    e_nan = _rmse(with_nan.simulate(u)[clean_rows], y[clean_rows])
    e_spoil = _rmse(with_spoil.simulate(u)[clean_rows], y[clean_rows])
    assert np.isfinite(with_nan.train_rmse_) and e_nan < 0.1 < e_spoil
    assert with_nan.train_rmse_ == pytest.approx(e_nan, rel=1e-9)
    with pytest.raises(ValueError, match="NaN"):
        GeneralizedPI(**kw).fit(u, np.where(clean_rows, y, np.inf))


def test_channel_thresholds_let_every_play_reverse_and_survive_the_file(tmp_path):
    """With ``channel_thresholds`` each play channel's thresholds follow its own swing, so every
    play reverses on the record it was fitted on; with max |u| on every channel the slow
    channel's upper plays only move once (a step in time). Kept by the model file and by a
    refit from its hyperparameters (``--effects-from``)."""
    from ipmc_model.hysteresis import lowpass_bank, play_bank

    _, u = mixed(120.0, 50.0, 3.0, band_hz=(0.02, 0.8), seed=4)
    y = IpmcPlant(seed=4, dt_s=0.02).run(u).y_mm
    kw = dict(dt_s=0.02, memory_taus_s=(0.05, 0.45, 4.0), max_nfev=8)
    m = GeneralizedPI(channel_thresholds=True, **kw).fit(u[:4000], y[:4000])
    default = GeneralizedPI(**kw).fit(u[:4000], y[:4000])
    ch = np.column_stack([u[:4000], lowpass_bank(u[:4000], m.memory_taus_s_, 0.02)[0]])

    def reversing(thresholds):
        d = np.diff(play_bank(ch[:, :thresholds.shape[0]], thresholds)[0], axis=0)
        return (d > 1e-12).any(axis=0) & (d < -1e-12).any(axis=0)

    assert reversing(m.thresholds_).all()
    assert not reversing(default.thresholds_).all()
    assert m.thresholds_[-1, -1] < 0.5 * m.thresholds_[0, -1]   # the 4 s channel swings less
    loaded = load_model(save_model(m, tmp_path / "m.json"))
    assert loaded.channel_thresholds and np.allclose(loaded.simulate(u), m.simulate(u))
    again = GeneralizedPI(**loaded.get_params()).fit(u[:4000], y[:4000])
    assert np.allclose(again.thresholds_, m.thresholds_)


def test_the_quadratic_spline_holds_a_stiffening_bend_the_hinges_meet_with_kinks():
    """A bending that stiffens on one side (y = z + 3 z^2 below 0, as the simulated strip's
    negative side) is in the quadratic spline's span (its curvature changes at each knot; a
    knot at the lowest z gives it curvature from there on) and not in the hinges' with the
    same knots; the spline's slope is its basis's derivative."""
    from ipmc_model.hysteresis import MAP_BASES

    z = np.linspace(-1.0, 1.0, 2001)
    y = z + 3.0 * np.minimum(z, 0.0) ** 2
    knots = np.array([-1.0, -0.5, 0.0, 0.5])

    def residual(basis):
        B = np.column_stack([basis.basis(z, knots), np.ones(z.size)])
        return y - B @ np.linalg.lstsq(B, y, rcond=None)[0]

    quad, hinge = MAP_BASES["quadratic"], MAP_BASES["linear"]
    assert np.abs(residual(quad)).max() < 1e-9
    assert np.abs(residual(hinge)).max() > 0.03   # the chord of 3 z^2 over half-volt spans
    coef = np.array([0.7, -1.0, 2.0, 0.5, 0.1])
    zs = np.linspace(-1.5, 1.5, 3000)   # no sample on a knot, some beyond the end knots
    g = quad.basis(zs, knots) @ coef
    # the central difference errs by a curvature jump x the step next to a knot (< 0.02); a
    # kink (a jump of the slope itself) would show as the jump
    np.testing.assert_allclose(quad.slope(zs[1:-1], knots, coef),
                               np.gradient(g, zs)[1:-1], atol=0.02)


def test_the_quadratic_maps_knots_are_each_once_where_z_rests_at_one_value():
    """A record that rests (z at one value for a third of its rows) puts several quantile
    knots on that value; the spline keeps each knot once, so every B-spline is nonzero on
    some row."""
    from ipmc_model.hysteresis import QuadraticSplineMap as Q

    z = np.r_[np.zeros(3000), np.linspace(0.0, 2.0, 6000)]
    knots = Q.knots(z, 10)
    assert np.all(np.diff(knots) > 0) and knots[0] == 0.0 and knots[-1] == 2.0
    B = Q.basis(z, knots)
    assert B.shape[1] == knots.size + 1 and np.all(np.abs(B).max(axis=0) > 0)


def test_the_quadratic_map_goes_on_straight_at_its_determined_edge_slopes():
    """Beyond its fitted range the quadratic map goes on straight (no parabola past the data),
    at its slope at the range's end, or at the last inner knot beyond which z went in fewer
    than two independent samples (a curvature fitted to one visit is not followed)."""
    from ipmc_model.hysteresis import QuadraticSplineMap as Q

    rows = np.arange(1000)
    z = np.linspace(0.0, 1.0, 1000)   # one sweep up: 100 rows below 0.1, 100 above 0.9
    knots, coef = np.array([0.0, 0.1, 0.9, 1.0]), np.array([0.0, 0.2, 0.3, 1.5, 5.0])
    at = Q.slope(np.array([0.0, 0.1, 0.9, 1.0]), knots, coef)
    assert abs(at[3] - at[2]) > 1.0 and abs(at[1] - at[0]) > 1.0   # the outer spans curve
    assert Q.edge_slopes(z, rows, knots, coef, 10.0, 2) == (at[0], at[3])
    # correlated over 500 rows, 100 rows are one sample: the slopes at those knots are kept
    assert Q.edge_slopes(z, rows, knots, coef, 500.0, 2) == (at[1], at[2])
    beyond = np.array([-1.0, 2.0])
    np.testing.assert_allclose(
        hinge_map(beyond, knots, coef, (0.0, 1.0), (at[1], at[2]), Q),
        hinge_map(np.array([0.0, 1.0]), knots, coef, basis=Q) + [-at[1], at[2]])
    # the basis itself goes on straight past its end knots: the fit's z may leave them
    B = Q.basis(np.array([1.0, 1.5, 2.0]), knots) @ coef
    assert B[2] - B[1] == pytest.approx(B[1] - B[0]) and B[1] - B[0] == pytest.approx(0.5 * at[3])


def test_a_quadratic_map_model_fits_runs_steps_and_survives_the_file(tmp_path):
    """``map_basis='quadratic'`` through fit, free run, stepper and the model file; a file
    written without the key loads with hinges; an unknown basis is refused by name."""
    _, u = mixed(60.0, 50.0, 3.0, band_hz=(0.02, 0.8), seed=5)
    y = IpmcPlant(seed=5, dt_s=0.02).run(u).y_mm
    kw = dict(dt_s=0.02, memory_taus_s=(0.05, 0.45), max_nfev=8)
    m = GeneralizedPI(map_basis="quadratic", **kw).fit(u, y)
    assert _rmse(m.simulate(u), y) < 0.1 * np.std(y)
    st = m.stepper()
    np.testing.assert_allclose([st.step(v) for v in u[:300]], m.simulate(u[:300]), atol=1e-9)
    path = save_model(m, tmp_path / "q.json")
    loaded = load_model(path)
    assert loaded.map_basis == "quadratic"
    np.testing.assert_allclose(loaded.simulate(u), m.simulate(u), atol=1e-12)
    # a file written before the map had a choice: no key, its document checksum re-made
    from ipmc_model.persistence import DOCUMENT_CHECKSUM, document_sha256

    hinge = GeneralizedPI(**kw).fit(u, y)
    old = save_model(hinge, tmp_path / "h.json")
    doc = json.loads(old.read_text())
    del doc["model"]["params"]["map_basis"]
    doc[DOCUMENT_CHECKSUM] = document_sha256(doc)
    old.write_text(json.dumps(doc))
    loaded = load_model(old)
    assert loaded.map_basis == "linear"
    np.testing.assert_allclose(loaded.simulate(u), hinge.simulate(u), atol=1e-12)
    doc["model"]["params"]["map_basis"] = "cubic"   # a newer version's map
    doc[DOCUMENT_CHECKSUM] = document_sha256(doc)
    old.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match="its output map is 'cubic'"):
        load_model(old)
    with pytest.raises(ValueError, match="map_basis must be one of"):
        GeneralizedPI(map_basis="cubic", **kw).fit(u, y)
