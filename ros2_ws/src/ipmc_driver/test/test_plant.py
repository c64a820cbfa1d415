import subprocess
import sys

import numpy as np
import pytest

from ipmc_driver.plant import EFFECTS, IpmcPlant, load_plant_params
from ipmc_driver.signals import random_sine, sine


def test_core_does_not_import_rclpy():
    code = ("import sys, ipmc_driver.plant, ipmc_driver.characterize, ipmc_driver.signals; "
            "print('rclpy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_voltage_is_hard_limited_to_3_v():
    plant = IpmcPlant()
    run = plant.run(np.array([5.0, -7.0, 2.5, 3.2]))
    np.testing.assert_allclose(run.u_v, [3.0, -3.0, 2.5, 3.0])


def test_nan_command_applies_zero_volts():
    plant = IpmcPlant()
    u_applied, _ = plant.step(float("nan"))
    assert u_applied == 0.0


def test_same_seed_same_record_and_different_seed_different_noise():
    _, u = random_sine(10.0, 100.0, 2.5, seed=3)
    a = IpmcPlant(seed=1).run(u)
    b = IpmcPlant(seed=1).run(u)
    c = IpmcPlant(seed=2).run(u)
    np.testing.assert_array_equal(a.y_mm, b.y_mm)
    np.testing.assert_array_equal(a.y_true_mm, c.y_true_mm)
    assert np.any(a.y_mm != c.y_mm)


def test_sensor_noise_and_resolution_are_as_configured():
    params = load_plant_params()
    _, u = sine(2.0, 0.3, 20.0)
    run = IpmcPlant(seed=0).run(u)
    q = params["resolution_mm"]
    np.testing.assert_allclose(run.y_mm / q, np.round(run.y_mm / q), atol=1e-6)
    err = run.y_mm - run.y_true_mm
    expected = np.sqrt(params["noise_std_mm"] ** 2 + q ** 2 / 12)
    assert 0.7 * expected < err.std() < 1.3 * expected


def test_negative_voltage_bends_further_than_positive():
    plus = IpmcPlant().run(np.full(300, 2.0)).y_true_mm.max()
    minus = IpmcPlant().run(np.full(300, -2.0)).y_true_mm.min()
    assert plus > 0 > minus
    assert -minus > 1.2 * plus


def test_response_lags_the_voltage_like_a_charging_double_layer():
    # A step does not appear in full at once: charging takes tens of milliseconds.
    y = IpmcPlant().run(np.full(100, -2.0)).y_true_mm
    peak = y.min()
    assert y[0] > 0.3 * peak  # first sample well short of the peak (both negative)
    assert np.argmin(y) > 5


def test_unknown_effect_is_refused_with_the_known_list():
    with pytest.raises(ValueError, match="unknown effect 'humidity'.*creep"):
        IpmcPlant(effects=["humidity"])
    with pytest.raises(ValueError, match="effect 'creep' has no parameter"):
        IpmcPlant(effects={"creep": {"speed": 1.0}})


def test_all_effects_are_off_by_default():
    # The shipped file defines every effect's parameters; none may act unless switched on.
    assert IpmcPlant().effects == {}
    bare = load_plant_params()
    bare["effects"] = {}
    u = np.full(3000, -2.0)
    np.testing.assert_array_equal(IpmcPlant().run(u).y_true_mm,
                                  IpmcPlant(bare).run(u).y_true_mm)


def hold(effects, u_v=-2.0, seconds=60.0):
    return IpmcPlant(effects=effects).run(np.full(int(seconds * 100), u_v)).y_true_mm


def test_creep_moves_a_sustained_response_slowly_in_either_direction():
    base = hold(())
    back = hold({"creep": {"gain_mm_per_v": -0.4, "tau_s": 20.0}})
    forward = hold({"creep": {"gain_mm_per_v": 0.4, "tau_s": 20.0}})
    d_back, d_fwd = back - base, forward - base
    # At 1 s little has happened; by 60 s most of 0.8 mm (0.4 mm/V x 2 V) has.
    assert abs(d_back[100]) < 0.1 and abs(d_back[-1]) > 0.6
    assert d_back[-1] > 0 > d_fwd[-1]  # negative bend: back-relaxation moves towards zero


def test_drift_loses_gain_over_minutes():
    _, u = sine(2.0, 0.5, 600.0)
    base = IpmcPlant().run(u).y_true_mm
    drift = IpmcPlant(effects={"drift": {"gain_loss_per_min": 0.05,
                                         "offset_mm_per_min": 0.0}}).run(u).y_true_mm
    first, last = slice(0, 3000), slice(-3000, None)
    assert np.ptp(drift[first]) > 0.95 * np.ptp(base[first])
    ratio = np.ptp(drift[last]) / np.ptp(base[last])
    assert 0.45 < ratio < 0.6  # 1 - 0.05/min x ~9.75 min


def test_delay_shifts_the_response_by_the_configured_time():
    _, u = random_sine(20.0, 100.0, 2.0, seed=1)
    base = IpmcPlant().run(u).y_true_mm
    late = IpmcPlant(effects={"delay": {"delay_s": 0.12}}).run(u).y_true_mm
    np.testing.assert_allclose(late[12:], base[:-12], atol=1e-9)


def test_dead_zone_ignores_small_voltages():
    small = IpmcPlant(effects={"dead_zone": {"width_v": 0.5}}).run(np.full(200, 0.4))
    assert np.all(small.y_true_mm == 0.0)
    assert np.abs(IpmcPlant().run(np.full(200, 0.4)).y_true_mm).max() > 0.2


def test_saturation_bounds_the_tip():
    y = hold({"saturation": {"limit_mm": 2.0}}, u_v=-3.0, seconds=5.0)
    assert np.abs(y).max() < 2.0
    assert np.abs(hold((), u_v=-3.0, seconds=5.0)).max() > 3.0


def test_asymmetry_weakens_only_the_negative_bending():
    base_neg, base_pos = hold(()), hold((), u_v=2.0)
    weak_neg = hold({"asymmetry": {"negative_gain_ratio": 0.6}})
    weak_pos = hold({"asymmetry": {"negative_gain_ratio": 0.6}}, u_v=2.0)
    assert base_neg.min() < -1.0
    np.testing.assert_allclose(weak_neg, 0.6 * base_neg, atol=1e-12)
    np.testing.assert_array_equal(weak_pos, base_pos)


def test_rate_dependence_follows_the_charging_current_and_vanishes_at_rest():
    k = 0.1  # mm per V/s
    u = np.r_[np.zeros(100), np.full(1500, 2.0)]  # a 2 V step at 1 s, held 15 s
    base = IpmcPlant().run(u).y_true_mm
    fast = IpmcPlant(effects={"rate_dependence": {"gain_mm_per_v_per_s": k}}).run(u).y_true_mm
    extra = fast - base
    # the extra bending is k dv_c/dt: its time integral is k times the charged voltage (2 V)
    assert np.sum(extra) * 0.01 == pytest.approx(k * 2.0, rel=1e-3)
    assert extra[100:140].max() > 0.5  # the step overshoots while the double layer charges
    assert abs(extra[-100:]).max() < 1e-3  # charged: no current, no extra bending
    # the loop widens with frequency: the extra bending grows with the input's rate
    _, slow = sine(1.0, 0.1, 20.0)
    _, quick = sine(1.0, 1.0, 20.0)
    fx = {"rate_dependence": {"gain_mm_per_v_per_s": k}}
    gap = [np.std(IpmcPlant(effects=fx).run(x).y_true_mm - IpmcPlant().run(x).y_true_mm)
           for x in (slow, quick)]
    assert gap[1] > 3 * gap[0]  # 10 x the rate, less the charging lag at 1 Hz


def test_effect_names_are_the_documented_ones():
    assert EFFECTS == ("creep", "drift", "delay", "dead_zone", "saturation", "asymmetry",
                       "rate_dependence")
    assert set(load_plant_params()["effects"]) == set(EFFECTS)


def test_bad_parameter_file_fails_with_a_clear_message(tmp_path):
    bad = tmp_path / "p.yaml"
    bad.write_text("plant:\n  u_max_v: 3.0\n")
    with pytest.raises(ValueError, match="'tau_charge_s' is missing"):
        load_plant_params(bad)
    bad.write_text("[1, 2")
    with pytest.raises(ValueError, match="cannot read plant parameters"):
        load_plant_params(bad)


def test_sample_stamps_never_repeat_or_overflow_nanoseconds():
    pytest.importorskip("rclpy")
    from ipmc_driver.nodes.sim_plant import to_time_msg

    # The node computes (k + 1) * dt - dt: 31.01 - 0.01 = 30.999999999999996, whose fraction
    # rounds to 1e9 ns.
    stamps = [to_time_msg((k + 1) * 0.01 - 0.01) for k in range(20000)]
    ns = [s.sec * 1_000_000_000 + s.nanosec for s in stamps]
    assert all(0 <= s.nanosec < 1_000_000_000 for s in stamps)
    assert ns == [k * 10_000_000 for k in range(20000)]
