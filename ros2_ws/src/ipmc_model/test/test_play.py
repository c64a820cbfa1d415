import numpy as np
import pytest
from numpy.testing import assert_allclose

from ipmc_model.errors import NotFittedError
from ipmc_model.play import PrandtlIshlinskii, play_operators


def test_play_operator_backlash_response():
    u = np.array([0.0, 1.0, 2.0, 1.5, 1.0, 0.5, 2.0])
    out = play_operators(u, [0.5])[:, 0]
    # up: follows u - r; reversal: holds until u has fallen 2r; then follows u + r
    assert_allclose(out, [0.0, 0.5, 1.5, 1.5, 1.5, 1.0, 1.5])


def test_play_zero_threshold_is_identity():
    u = np.sin(np.linspace(0, 10, 50))
    assert_allclose(play_operators(u, [0.0])[:, 0], u)


def test_play_rejects_negative_threshold():
    with pytest.raises(ValueError, match=">= 0"):
        play_operators([0.0, 1.0], [-0.1])


def test_nnls_recovers_pi_model_on_grid():
    rng = np.random.default_rng(1)
    u = np.cumsum(rng.standard_normal(800)) * 0.1
    u = 3 * u / np.abs(u).max()
    r = np.arange(5) * (3.0 / 5)
    a = np.array([0.8, 0.5, 0.0, 0.3, 0.2])
    y = play_operators(u, r) @ a + 0.4
    pi = PrandtlIshlinskii(n_operators=5, method="nnls", r_max=3.0).fit(u, y)
    assert_allclose(pi.thresholds_, r, atol=1e-12)
    assert_allclose(pi.weights_, a, atol=1e-6)
    assert_allclose(pi.offset_, 0.4, atol=1e-6)
    assert np.all(pi.thresholds_ >= 0)


def test_inverse_pi_compensates_forward_model(hyst_data):
    u, y = hyst_data
    pi = PrandtlIshlinskii(n_operators=8).fit(u, y)
    inv = pi.inverse()
    y_des = 0.8 * y
    u_ff = inv.simulate(y_des)
    assert_allclose(pi.simulate(u_ff), y_des, atol=1e-9)
    inv.reset()
    steps = np.array([inv.step(v) for v in y_des[:100]])
    assert_allclose(steps, u_ff[:100], atol=1e-12)


def test_pso_fit_reproducible_and_thresholds_nonnegative(hyst_data):
    u, y = hyst_data
    kw = {"n_operators": 4, "method": "pso", "n_particles": 12, "n_iter": 8, "seed": 3}
    a = PrandtlIshlinskii(**kw).fit(u[:300], y[:300])
    b = PrandtlIshlinskii(**kw).fit(u[:300], y[:300])
    assert_allclose(a.weights_, b.weights_)
    assert np.all(a.thresholds_ >= 0)
    assert a.train_rmse_ < np.std(y[:300])


def test_inverse_needs_positive_weights():
    pi = PrandtlIshlinskii(n_operators=2)
    pi.thresholds_, pi.weights_, pi.offset_ = np.array([0.0, 1.0]), np.array([1.0, -0.5]), 0.0
    with pytest.raises(ValueError, match="non-negative weights"):
        pi.inverse()


def test_pi_unfitted_raises():
    with pytest.raises(NotFittedError, match="not fitted"):
        PrandtlIshlinskii().simulate([0.0, 1.0])


def test_pi_rejects_constant_input():
    with pytest.raises(ValueError, match="constant"):
        PrandtlIshlinskii().fit(np.ones(100), np.arange(100.0))
