import numpy as np
import pytest
from numpy.testing import assert_allclose

from ipmc_model.metrics import fit_percent, independent_samples, max_abs, nrmse, rmse, score


def test_metrics_known_values():
    y = np.array([0.0, 1.0, 2.0, 3.0])
    y_hat = np.array([0.0, 1.0, 2.0, 5.0])
    assert_allclose(rmse(y, y_hat), 1.0, rtol=1e-12)
    assert_allclose(nrmse(y, y_hat), 1.0 / 3.0, rtol=1e-12)
    assert_allclose(max_abs(y, y_hat), 2.0, rtol=1e-12)
    assert_allclose(fit_percent(y, y_hat), 100 * (1 - 2.0 / np.sqrt(5.0)), rtol=1e-12)
    assert_allclose(fit_percent(y, y), 100.0)


def test_metrics_skip_leading_samples():
    y = np.array([10.0, 0.0, 1.0, 2.0])
    y_hat = np.array([0.0, 0.0, 1.0, 2.0])
    assert rmse(y, y_hat, skip=1) == 0.0
    assert set(score(y, y_hat, skip=1)) == {"rmse", "nrmse", "fit_percent", "max_abs"}


def test_metrics_reject_mismatched_lengths():
    with pytest.raises(ValueError, match="same length"):
        rmse([1.0, 2.0], [1.0, 2.0, 3.0])


def test_metrics_reject_nan():
    with pytest.raises(ValueError, match="finite"):
        rmse([1.0, np.nan], [1.0, 2.0])


def test_metrics_reject_bad_skip():
    with pytest.raises(ValueError, match="skip"):
        rmse([1.0, 2.0], [1.0, 2.0], skip=2)


def test_independent_samples_count_visits_and_their_length():
    # runs joined across gaps up to 10 rows; one more sample per 10 rows a run lasts
    assert independent_samples(np.array([], dtype=int), 10.0) == 0
    assert independent_samples(np.array([5]), 10.0) == 1
    assert independent_samples(np.array([9, 10, 11]), 10.0) == 1   # across a block edge
    assert independent_samples(np.array([5, 12, 40]), 10.0) == 2
    assert independent_samples(np.arange(100, 125), 10.0) == 3
