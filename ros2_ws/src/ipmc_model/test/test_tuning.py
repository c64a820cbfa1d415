import numpy as np
import pytest

from ipmc_model.narx import InverseNarxModel, NarxModel
from ipmc_model.tuning import (
    free_run_rmse_objective,
    identify_lssvm_narx,
    one_step_rmse_objective,
    tune_lssvm_narx,
)

SMALL = {"n_sources": 4, "n_cycles": 2, "max_train_rows": 300, "max_val_samples": 300}


def test_tuning_reproducible_and_in_bounds(hyst_data):
    u, y = hyst_data
    a = tune_lssvm_narx(u, y, seed=5, **SMALL)
    b = tune_lssvm_narx(u, y, seed=5, **SMALL)
    assert (a.C, a.sigma, a.score_mm) == (b.C, b.sigma, b.score_mm)
    assert 1.0 <= a.C <= 1e7 and 0.1 <= a.sigma <= 10**1.5
    assert a.objective == "free_run" and np.isfinite(a.score_mm)
    assert a.nfev >= 4 * (2 * 2 + 1)


def test_one_step_objective_is_named_and_smaller(hyst_data):
    u, y = hyst_data
    res = tune_lssvm_narx(u, y, objective="one_step", seed=0, **SMALL)
    assert res.objective == "one_step"
    free = tune_lssvm_narx(u, y, objective="free_run", seed=0, **SMALL)
    assert res.score_mm < free.score_mm


def test_objectives_on_fitted_model(hyst_data):
    u, y = hyst_data
    m = NarxModel().fit(u[:600], y[:600])
    assert one_step_rmse_objective(m, u[600:], y[600:]) <= \
        free_run_rmse_objective(m, u[600:], y[600:]) + 1e-12


def test_identify_with_given_hyperparameters_and_inverse(hyst_data):
    u, y = hyst_data
    model, tuning = identify_lssvm_narx(u, y, C=100.0, sigma=2.0)
    assert tuning is None and isinstance(model, NarxModel)
    inv, tuning = identify_lssvm_narx(u, y, inverse=True, seed=1, **SMALL)
    assert isinstance(inv, InverseNarxModel) and tuning is not None


def test_tuning_rejects_bad_objective(hyst_data):
    u, y = hyst_data
    with pytest.raises(ValueError, match="objective must be"):
        tune_lssvm_narx(u, y, objective="training")


def test_tuning_rejects_bad_data(hyst_data):
    u, y = hyst_data
    with pytest.raises(ValueError, match="u is constant"):
        tune_lssvm_narx(np.zeros(u.size), y, **SMALL)
    with pytest.raises(ValueError, match="same length"):
        tune_lssvm_narx(u, y[:-5], **SMALL)
