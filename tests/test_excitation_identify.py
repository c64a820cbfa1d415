"""ipmc identify's default model on ipmc bringup's open-loop excitation (packages ipmc_control
and ipmc_model together)."""

from __future__ import annotations

import numpy as np

from ipmc_control.excitation import make_excitation
from ipmc_driver.plant import IpmcPlant
from ipmc_model.hysteresis import GeneralizedPI


def test_a_delay_the_plant_does_not_have_is_not_chosen_on_the_bench_excitation():
    """ipmc bringup --excite mixed's input (steps, holds, sines) on the simulated IPMC: the
    linear part proposes a delay (the charging lag looks like one), and the fit compares it
    with none at convergence, so the step onsets are not missed by tens of ms."""
    exc = make_excitation("mixed", seconds=240.0, rate_hz=100.0, seed=4)
    run = IpmcPlant(seed=4, dt_s=0.01).run(exc.u_v)
    m = GeneralizedPI(dt_s=0.01).fit(run.u_v, run.y_mm)
    assert dict(m.delay_scores_).keys() > {0}          # a delay was proposed and compared
    assert m.delay_samples_ == 0, m.delay_scores_
    assert np.max(np.abs(m.simulate(run.u_v) - run.y_mm)) < 0.3
