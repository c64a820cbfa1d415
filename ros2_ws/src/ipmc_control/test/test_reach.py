"""Tests of the reference checks (ipmc_control.reach, bringup's reference options)."""

from __future__ import annotations

import numpy as np
import pytest

from ipmc_control.bringup import check_reference, reference_params
from ipmc_control.reach import ReachError, build_reference, plant_reach_mm, reference_span_mm


def test_3_v_settles_short_of_the_swing_and_below_4_mm():
    low_held, high_held = plant_reach_mm(held=True)
    low, high = plant_reach_mm(held=False)
    assert low < low_held < 0.0 < high_held < high
    assert high_held < 4.0 and high < 4.0     # +4 mm is out of reach of +3 V


@pytest.mark.parametrize("kind,given,span", [
    ("constant", {"value_mm": 1.5}, (1.5, 1.5)),
    ("sine", {"amplitude_mm": 2.0, "frequency_hz": 0.5}, (-2.0, 2.0)),
    ("steps", {"levels_mm": [-3.0, 0.0, 2.0], "hold_s": 2.0}, (-3.0, 2.0)),
    ("random", {}, (-9.0, 4.0)),
])
def test_span_is_what_the_reference_asks_for(kind, given, span):
    got = reference_span_mm(build_reference(kind, given), kind)
    np.testing.assert_allclose(got, span, atol=1e-3)


def test_a_level_beyond_3_v_is_refused_in_one_sentence():
    with pytest.raises(ReachError) as info:
        check_reference("constant", {"value_mm": 4.0}, sim=True, model=None)
    text = str(info.value)
    assert "4.00 mm" in text and "settles between" in text and text.count(". ") == 0
    assert check_reference("constant", {"value_mm": 2.0}, sim=True, model=None) == (2.0, 2.0)
    # the rig: its reach is not the simulated IPMC's; only the model's range applies
    assert check_reference("constant", {"value_mm": 4.0}, sim=False, model=None) == (4.0, 4.0)


def test_options_of_another_kind_and_bad_text_are_refused():
    with pytest.raises(ReachError, match="value_mm sets a constant reference, not a sine"):
        check_reference("sine", {"value_mm": 1.0}, sim=True, model=None)
    with pytest.raises(ValueError, match="levels_mm '1,x' is not a number list"):
        reference_params({"levels_mm": "1,x"})
    assert reference_params({"levels_mm": "-2, 0,2", "hold_s": "3", "amplitude_mm": ""}) == {
        "levels_mm": [-2.0, 0.0, 2.0], "hold_s": 3.0}


def test_a_reference_beyond_the_models_range_is_refused(tmp_path):
    """An inverse identified on +-1.5 mm of motion may not be asked for 2.5 mm."""
    from ipmc_driver.plant import IpmcPlant
    from ipmc_driver.signals import random_sine
    from ipmc_model.lssvm import FixedSizeLSSVMRegressor
    from ipmc_model.narx import InverseNarxModel
    from ipmc_model.persistence import save_model

    _, u = random_sine(30.0, 100.0, amplitude=0.8, seed=1)
    run = IpmcPlant(seed=1).run(u)
    model = InverseNarxModel(FixedSizeLSSVMRegressor(C=1e3, sigma=2.0, n_prototypes=60,
                                                     seed=0), input_lags=0, output_lags=2)
    path = save_model(model.fit(run.u_v, run.y_mm), tmp_path / "inv.json")
    lo, hi = model.identified_range_mm
    assert hi < 2.5
    with pytest.raises(ReachError, match=r"beyond the .* mm the model was identified on \("):
        check_reference("sine", {"amplitude_mm": 2.5}, sim=True, model=str(path))
    small = 0.5 * min(-lo, hi)
    assert check_reference("sine", {"amplitude_mm": small}, sim=True, model=str(path))


def test_voltage_reach_takes_the_settled_ends_for_holds_and_the_swing_otherwise():
    """A response that overshoots to 1.5 x its gain and relaxes back to 1 x (back-relaxation):
    a hold reaches the settled 3 mm per 3 V, a moving reference up to the 4.5 mm peak."""
    from ipmc_control.reach import voltage_reach_mm

    def simulate(u):
        t = np.arange(u.size) * 0.01
        return u * (1.0 + 0.5 * (1.0 - np.exp(-t / 0.2)) * np.exp(-t / 2.0) * 2.5)

    low, high = voltage_reach_mm(simulate, 100.0, held=True)
    assert low == pytest.approx(-3.0, abs=1e-3) and high == pytest.approx(3.0, abs=1e-3)
    low, high = voltage_reach_mm(simulate, 100.0, held=False)
    assert high > 4.0 and low == pytest.approx(-high)
