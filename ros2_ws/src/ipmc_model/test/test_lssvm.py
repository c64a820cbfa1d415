import numpy as np
import pytest
from numpy.testing import assert_allclose

from ipmc_model.errors import NotFittedError
from ipmc_model.lssvm import (
    FixedSizeLSSVMRegressor,
    FixedSizeStatistics,
    LSSVMRegressor,
    rbf_kernel,
    select_prototypes,
)


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(0)
    X = rng.uniform(-2, 2, (300, 3))
    y = np.sin(X[:, 0]) + 0.5 * X[:, 1] * X[:, 2] + 0.01 * rng.standard_normal(300)
    return X, y


def test_lssvm_matches_dense_bordered_system(data):
    X, y = data
    C, sigma = 50.0, 0.9
    m = LSSVMRegressor(C=C, sigma=sigma).fit(X, y)
    n = len(y)
    A = np.zeros((n + 1, n + 1))
    A[0, 1:] = A[1:, 0] = 1.0
    A[1:, 1:] = rbf_kernel(X, X, sigma) + np.eye(n) / C
    sol = np.linalg.solve(A, np.concatenate([[0.0], y]))
    assert_allclose(m.intercept_, sol[0], rtol=1e-8, atol=1e-10)
    assert_allclose(m.coef_, sol[1:], rtol=1e-6, atol=1e-8)
    assert_allclose(m.coef_.sum(), 0.0, atol=1e-8)  # Eq. 12: sum alpha = 0


def test_predict_one_equals_predict(data):
    X, y = data
    m = LSSVMRegressor(C=10.0, sigma=1.0).fit(X, y)
    batch = m.predict(X[:20])
    single = [m.predict_one(x) for x in X[:20]]
    assert_allclose(single, batch, rtol=1e-10, atol=1e-12)
    # in blocks of rows that do not divide the record, the same
    assert_allclose(m.predict(X[:20], chunk_size=7), batch, rtol=1e-12, atol=1e-14)
    assert_allclose(m.predict(X), rbf_kernel(X, m.centers_, 1.0) @ m.coef_ + m.intercept_,
                    rtol=1e-9, atol=1e-12)


def test_fixed_size_with_all_points_equals_exact(data):
    X, y = data
    exact = LSSVMRegressor(C=20.0, sigma=0.7).fit(X, y)
    fs = FixedSizeLSSVMRegressor(C=20.0, sigma=0.7, n_prototypes=len(y), chunk_size=64)
    fs.fit(X, y)
    assert_allclose(fs.predict(X[:50]), exact.predict(X[:50]), atol=1e-5)


def test_fixed_size_approximates_with_fewer_prototypes(data):
    X, y = data
    fs = FixedSizeLSSVMRegressor(C=100.0, sigma=1.0, n_prototypes=80, seed=1).fit(X, y)
    assert fs.n_centers_ == 80
    assert np.sqrt(np.mean((fs.predict(X) - y) ** 2)) < 0.05


def test_prototype_selection_reproducible_and_distinct(data):
    X, _ = data
    a = select_prototypes(X, 40, "kmeans++", seed=3)
    b = select_prototypes(X, 40, "kmeans++", seed=3)
    np.testing.assert_array_equal(a, b)
    assert np.unique(a).size == 40
    with pytest.raises(ValueError, match="kmeans"):
        select_prototypes(X, 4, "renyi")


@pytest.mark.parametrize("sigma", [0.0, -1.0, np.nan])
def test_lssvm_rejects_nonpositive_sigma(data, sigma):
    X, y = data
    with pytest.raises(ValueError, match="sigma must be a finite number > 0"):
        LSSVMRegressor(C=1.0, sigma=sigma).fit(X, y)
    with pytest.raises(ValueError, match="sigma must be a finite number > 0"):
        FixedSizeLSSVMRegressor(C=1.0, sigma=sigma).fit(X, y)


def test_lssvm_rejects_nonpositive_c(data):
    X, y = data
    with pytest.raises(ValueError, match="C must be"):
        LSSVMRegressor(C=0.0, sigma=1.0).fit(X, y)


def test_lssvm_rejects_nan_and_mismatch(data):
    X, y = data
    Xn = X.copy()
    Xn[3, 1] = np.nan
    with pytest.raises(ValueError, match="finite"):
        LSSVMRegressor().fit(Xn, y)
    with pytest.raises(ValueError, match="same length"):
        LSSVMRegressor().fit(X, y[:-1])


def test_lssvm_unfitted_raises():
    with pytest.raises(NotFittedError):
        LSSVMRegressor().predict(np.zeros((2, 3)))


def test_fixed_size_statistics_solve_equals_fit_for_each_c(data):
    X, y = data
    idx = select_prototypes(X, 40, seed=3)
    stats = FixedSizeStatistics(X, y, idx, sigma=1.5)
    for C in (1.0, 100.0, 1e5):
        ref = FixedSizeLSSVMRegressor(C=C, sigma=1.5, n_prototypes=40, seed=3).fit(X, y)
        got = stats.solve(C)
        assert_allclose(got.predict(X), ref.predict(X), rtol=0, atol=1e-9)
        assert got.C_ == C and got.n_centers_ == 40
