"""Issue 6, "back into control": the constant hold with the plant's creep, before and after the
diagnosis adds the creep it finds to the inverse (ipmc_model.diagnose.creep_hold_experiment,
which crosses ipmc_driver's plant, ipmc_model's diagnosis and ipmc_control's loop).

The plant's default creep (tau 20 s, -0.12 mm/V) is on and not told to the diagnosis; the
identification record is the demo's kind of rig data (300 s of random 2.5 V steps). Only the
creep candidate is tried, to keep the test short; docs/diagnose.md has the full runs
(scripts/creep_hold.py).
"""

import numpy as np
import pytest

from ipmc_model.diagnose import creep_hold_experiment

SETTLED_GOAL_MM = 0.05   # issue 6's hold goal, met after the rise from rest (t >= 2 s)


def _hold(identify_input: str) -> dict:
    return creep_hold_experiment(identify_s=300.0, duration_s=30.0,
                                 reference="constant-reachable", seed=0,
                                 identify_input=identify_input,
                                 diagnosis_kwargs={"candidates": ("creep",)})


@pytest.fixture(scope="module")
def steps_hold():
    return _hold("steps")


def test_creep_is_found_on_step_data(steps_hold):
    assert steps_hold["effects_found"] == ["creep"]
    # fitted on the drift during the input holds: near the plant's tau 20 s, -0.12 mm/V (the
    # joint fit gave tau 3.6 s, -0.24 mm/V: the hysteresis took the slow part)
    assert 20.0 / 1.5 <= steps_hold["creep_fitted"]["tau_s"] <= 20.0 * 1.5
    assert steps_hold["creep_fitted"]["gain_mm_per_v"] == pytest.approx(-0.12, rel=0.3)
    # the 95 % intervals over the holds hold the plant's creep, and 300 s bound its tau
    span = steps_hold["creep_intervals"]
    assert span["tau_s"][0] <= 20.0 <= span["tau_s"][1] and span["tau_bounded"]
    assert span["gain_mm_per_v"][0] <= -0.12 <= span["gain_mm_per_v"][1]
    assert steps_hold["identification_rmse_after_mm"] < steps_hold[
        "identification_rmse_before_mm"]


def test_the_hold_is_within_the_goal_after_the_rise(steps_hold):
    # Closed loop, plain and creep-augmented inverse: after the rise the -3 mm hold is within
    # 0.05 mm, and adding the creep does not make it worse by more than 10 %.
    assert steps_hold["settled_rmse_before_mm"] <= SETTLED_GOAL_MM
    assert steps_hold["settled_rmse_after_mm"] <= SETTLED_GOAL_MM
    assert steps_hold["settled_rmse_after_mm"] <= 1.1 * steps_hold["settled_rmse_before_mm"]
    assert set(steps_hold["results"]) == {"before", "after"}
    for res in steps_hold["results"].values():
        assert np.max(np.abs(res.u_v)) <= 3.0 + 1e-12
        assert res.reference_mm[0] == pytest.approx(-3.0)


def test_no_creep_without_input_holds():
    # A random sine riding on the steps leaves no input hold: the creep cannot show as drift
    # in time, so the diagnosis does not accept it and there is no "after".
    h = _hold("sine+steps")
    assert h["effects_found"] == []
    assert h["rmse_after_mm"] is None
    creep = next(c for c in h["diagnosis"].candidates if c.effect == "creep")
    assert not creep.accepted
    assert creep.evidence["hold_drift"]["holds"] < 3
    assert not creep.evidence["hold_drift"]["significant"]


def test_bad_identification_input_is_refused():
    with pytest.raises(ValueError, match="identify_input"):
        creep_hold_experiment(identify_s=10.0, identify_input="chirp")
