import time

import numpy as np
import pytest
from numpy.testing import assert_allclose

from ipmc_model.errors import NotFittedError
from ipmc_model.lssvm import FixedSizeLSSVMRegressor, LSSVMRegressor
from ipmc_model.metrics import rmse
from ipmc_model.narx import FreeRunCache, InverseNarxModel, NarxCommittee, NarxModel


@pytest.fixture(scope="module")
def fitted(hyst_data):
    u, y = hyst_data
    return NarxModel(LSSVMRegressor(C=1e4, sigma=3.0)).fit(u[:800], y[:800])


def test_narx_one_step_and_free_run_accurate(hyst_data, fitted):
    u, y = hyst_data
    uv, yv = u[800:], y[800:]
    L = fitted.max_lag_
    assert L == 3
    one = fitted.predict(uv, yv)
    free = fitted.simulate(uv, yv[:L])
    assert_allclose(one[:L], yv[:L])
    assert_allclose(free[:L], yv[:L])
    assert rmse(yv, one, L) < 0.03 * np.std(yv)
    assert rmse(yv, free, L) < 0.2 * np.std(yv)


def test_stepper_reproduces_simulate(hyst_data, fitted):
    u, y = hyst_data
    free = fitted.simulate(u[800:900], y[800:803])
    st = fitted.stepper(u_history=u[800:803], y_history=y[800:803])
    steps = [st.step(v) for v in u[803:900]]
    assert_allclose(steps, free[3:], rtol=1e-9, atol=1e-9)


def test_stepper_with_measured_output_is_one_step(hyst_data, fitted):
    u, y = hyst_data
    one = fitted.predict(u[800:900], y[800:900])
    st = fitted.stepper(u_history=u[800:803], y_history=y[800:803])
    out = []
    for k in range(803, 900):
        out.append(st.step(u[k]))
        st.correct_output(y[k])
    assert_allclose(out, one[3:], rtol=1e-9, atol=1e-9)


def test_a_model_without_output_lags_runs_free_as_its_stepper(hyst_data):
    """Without output lags (the diagnosis's baseline) the free run is computed in blocks of
    rows; it must be the step-by-step run, and the one-step prediction."""
    u, y = hyst_data
    m = NarxModel(LSSVMRegressor(C=1e3, sigma=3.0), input_lags=6, output_lags=0,
                  lag_step=2).fit(u[:800], y[:800])
    L = m.max_lag_
    assert L == 12 and m.out_delays_.size == 0
    free = m.simulate(u[800:], y[800 : 800 + L])
    st = m.stepper(u_history=u[800 : 800 + L], y_history=y[800 : 800 + L])
    assert_allclose([st.step(v) for v in u[800 + L :]], free[L:], rtol=1e-9, atol=1e-9)
    assert_allclose(m.predict(u[800:], y[800:]), free, rtol=1e-12, atol=1e-12)
    assert rmse(y[800:], free, L) < 0.2 * np.std(y[800:])


class _Blows:
    """A regressor whose output leaves any range where its first regressor exceeds 1."""

    def fit(self, X, y):
        return self

    def predict(self, X):
        return np.where(X[:, 0] > 1.0, 1e7, 0.5)


def test_a_free_run_without_output_lags_is_nan_from_where_it_diverges():
    u = np.r_[np.zeros(30), 2.0, np.zeros(29)] + np.linspace(0, 0.01, 60)
    m = NarxModel(_Blows(), input_lags=2, output_lags=0, standardize=False).fit(u, u)
    z = m.simulate(u)
    k = 30  # the first row whose current input is above 1
    assert np.all(np.isfinite(z[:k])) and np.all(np.isnan(z[k:]))


def test_lag_step_and_extra_exogenous_input(hyst_data):
    u, y = hyst_data
    slow = np.convolve(u, np.ones(50) / 50, mode="full")[: u.size]  # e.g. a creep regressor
    U = np.column_stack([u, slow])
    m = NarxModel(LSSVMRegressor(C=1e3, sigma=3.0), input_lags=(2, 0), output_lags=2,
                  lag_step=4).fit(U[:800], y[:800])
    assert m.max_lag_ == 8 and m.n_features_ == 3 + 1 + 2
    free = m.simulate(U[800:], y[800:808])
    st = m.stepper(U[792:800], y[792:800])
    assert_allclose([st.step(U[k]) for k in range(800, 830)],
                    m.simulate(U[792:830], y[792:800])[8:], rtol=1e-9, atol=1e-9)
    assert np.all(np.isfinite(free))
    with pytest.raises(ValueError, match="2 channel"):
        m.simulate(u[:100])


def test_inverse_model_stepper_and_compensation(hyst_data):
    u, y = hyst_data
    inv = InverseNarxModel(LSSVMRegressor(C=1e4, sigma=3.0)).fit(u[:800], y[:800])
    u_one = inv.predict(y[800:], u[800:])
    assert rmse(u[800:], u_one, inv.max_lag_) < 0.1 * np.std(u)
    u_free = inv.simulate(y[800:900], u[800:803])
    st = inv.stepper(y_history=y[800:803], u_history=u[800:803])
    assert_allclose([st.step(v) for v in y[803:900]], u_free[3:], rtol=1e-9, atol=1e-9)
    st.record_applied(0.0)  # the loop applied something else: accepted without error


def test_inverse_step_is_fast():
    rng = np.random.default_rng(0)
    u = rng.standard_normal(6000)
    y = np.convolve(u, [0.5, 0.3, 0.2])[:6000]
    inv = InverseNarxModel(FixedSizeLSSVMRegressor(C=100.0, sigma=2.0, n_prototypes=1000))
    inv.fit(u, y)
    st = inv.stepper()
    times = []
    for v in y[:300]:
        t0 = time.perf_counter()
        st.step(v)
        times.append(time.perf_counter() - t0)
    # target 200 us at 100 Hz; the bound is loose because the test machine is shared
    assert np.median(times) < 600e-6, f"median step {np.median(times) * 1e6:.0f} us"


def test_narx_rejects_nan(hyst_data):
    u, y = hyst_data
    y = y.copy()
    y[10] = np.nan
    with pytest.raises(ValueError, match="y must be finite; first non-finite value at index 10"):
        NarxModel().fit(u, y)


def test_narx_rejects_constant_input(hyst_data):
    _, y = hyst_data
    with pytest.raises(ValueError, match="u is constant"):
        NarxModel().fit(np.full(y.size, 1.5), y)
    with pytest.raises(ValueError, match="u is constant"):
        InverseNarxModel().fit(np.full(y.size, 1.5), y)


def test_narx_rejects_too_few_samples():
    with pytest.raises(ValueError, match="too few samples for the lags"):
        NarxModel().fit(np.arange(12.0), np.sin(np.arange(12.0)))


def test_narx_rejects_mismatched_lengths(hyst_data):
    u, y = hyst_data
    with pytest.raises(ValueError, match="same length: u has 100, y has 99"):
        NarxModel().fit(u[:100], y[:99])


def test_narx_rejects_nonpositive_sigma(hyst_data):
    u, y = hyst_data
    with pytest.raises(ValueError, match="sigma must be a finite number > 0"):
        NarxModel(LSSVMRegressor(C=10.0, sigma=0.0)).fit(u[:200], y[:200])


def test_narx_unfitted_raises():
    with pytest.raises(NotFittedError, match="not fitted"):
        NarxModel().simulate(np.zeros(20))
    with pytest.raises(NotFittedError, match="not fitted"):
        InverseNarxModel().stepper()


def _relaxing_plant(u, dt=0.01, tau=0.46, share=0.56):
    """Bending with back-relaxation: y = u - share * lowpass(u, tau) (the IPMC's water
    back-diffusion); its inverse has a pole at tau / (1 - share), about 1 s."""
    a = np.exp(-dt / tau)
    r = np.zeros_like(u)
    for k in range(1, u.size):
        r[k] = a * r[k - 1] + (1 - a) * u[k]
    return u - share * r


def test_inverse_memory_channel_undoes_back_relaxation():
    rng = np.random.default_rng(3)
    t = np.arange(4000) * 0.01
    u = sum(rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * f * t + rng.uniform(0, 6))
            for f in rng.uniform(0.02, 0.5, 8))
    y = _relaxing_plant(u)
    fit = slice(0, 3000)
    plain = InverseNarxModel(LSSVMRegressor(C=1e4, sigma=3.0), output_lags=3, input_lags=0,
                             lag_step=5).fit(u[fit], y[fit])
    memory = InverseNarxModel(LSSVMRegressor(C=1e4, sigma=3.0), output_lags=3, input_lags=0,
                              lag_step=5, memory_taus_s=[1.0]).fit(u[fit], y[fit])
    # Free runs over the whole record from rest; scored on the held-out last 1000 samples.
    e_plain = rmse(u, plain.simulate(y), 3000)
    e_memory = rmse(u, memory.simulate(y), 3000)
    print(f"inverse free-run RMSE: plain {e_plain:.4f}, with memory {e_memory:.4f}")
    assert e_memory < 0.3 * e_plain, (e_plain, e_memory)
    assert memory.get_params()["memory_taus_s"] == [1.0]


def test_inverse_memory_stepper_matches_simulate_and_history(hyst_data):
    u, y = hyst_data
    inv = InverseNarxModel(LSSVMRegressor(C=1e3, sigma=3.0), output_lags=3, input_lags=1,
                           memory_taus_s=[0.3, 2.0]).fit(u[:800], y[:800])
    u_free = inv.simulate(y[:900], u[:inv.max_lag_])
    st = inv.stepper()
    # From rest: the stepper's first outputs are the model's, whatever the initial lags say.
    st.reset(y_history=y[:inv.max_lag_], u_history=u[:inv.max_lag_])
    got = [st.step(v) for v in y[inv.max_lag_:900]]
    assert_allclose(got, u_free[inv.max_lag_:], rtol=1e-9, atol=1e-9)
    # A stepper seeded mid-record continues exactly as one that ran through it.
    st2 = inv.stepper(y_history=y[:850], u_history=u_free[:850])
    assert_allclose([st2.step(v) for v in y[850:900]], u_free[850:900], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("taus, dt", [([0.0], 0.01), ([-1.0], 0.01), ([float("nan")], 0.01),
                                      ([1.0], 0.0)])
def test_inverse_memory_rejects_bad_time_constants(hyst_data, taus, dt):
    u, y = hyst_data
    with pytest.raises(ValueError, match="memory_taus_s|dt_s"):
        InverseNarxModel(LSSVMRegressor(), memory_taus_s=taus, dt_s=dt).fit(u, y)


def _two_state_plant(u, dt=0.01):
    """Tip (mm) from a charging and a relaxation state of the voltage (taus 0.3, 0.5 s)."""
    from ipmc_model.narx import voltage_channels

    ch = voltage_channels(u, (0.3, 0.5), dt, include_voltage=False)
    s = 2.0 * ch[:, 0] - 0.8 * ch[:, 1]
    return np.where(s > 0, 2.5 * np.tanh(s), s)


def test_voltage_channel_model_builds_its_channels_from_the_voltage(hyst_data):
    from ipmc_model.narx import voltage_channels

    u, _ = hyst_data
    y = _two_state_plant(u)
    m = NarxModel(LSSVMRegressor(C=1e5, sigma=2.0), input_lags=0, output_lags=0,
                  input_memory_taus_s=(0.3, 0.5), include_voltage=False).fit(u[:800], y[:800])
    assert m.uses_voltage_channels and m.n_inputs_ == 2 and m.max_lag_ == 0
    assert not NarxModel().uses_voltage_channels
    # The same as a plain model fitted on channels the caller built.
    ch = voltage_channels(u, (0.3, 0.5), 0.01, include_voltage=False)
    plain = NarxModel(LSSVMRegressor(C=1e5, sigma=2.0), input_lags=[0, 0],
                      output_lags=0).fit(ch[:800], y[:800])
    assert_allclose(m.simulate(u), plain.simulate(ch), rtol=0, atol=1e-12)
    assert_allclose(m.predict(u, y), plain.predict(ch, y), rtol=0, atol=1e-12)
    assert rmse(y[:800], m.simulate(u[:800])) < 0.05 * np.std(y)
    assert rmse(y[800:], m.simulate(u)[800:]) < 0.25 * np.std(y)   # held out, extrapolating
    # Stepper from rest, and seeded with a voltage history, follow the free run.
    free = m.simulate(u)
    st = m.stepper()
    assert_allclose([st.step(v) for v in u[:300]], free[:300], rtol=0, atol=1e-9)
    st = m.stepper(u_history=u[:600], y_history=y[:600])
    assert_allclose([st.step(v) for v in u[600:700]], free[600:700], rtol=0, atol=1e-9)


def test_history_samples_are_enough_for_a_stepper_to_go_on(hyst_data):
    """history_samples (what model_server hands a stepper after a reload): five of the slowest
    voltage channel's time constants; that much history puts a stepper within 0.2 % of the
    span of the free run that lived through everything, a tenth of it 9 % off."""
    u, _ = hyst_data
    y = _two_state_plant(u)
    m = NarxModel(LSSVMRegressor(C=1e5, sigma=2.0), input_lags=0, output_lags=0,
                  input_memory_taus_s=(0.3, 0.5), include_voltage=False).fit(u[:800], y[:800])
    h = m.history_samples
    assert h == 250  # 5 x 0.5 s at 100 Hz
    free = m.simulate(u)

    def off(n):
        st = m.stepper(u_history=u[800 - n:800], y_history=y[800 - n:800])
        return np.max(np.abs([st.step(v) - f for v, f in zip(u[800:900], free[800:900],
                                                             strict=True)]))

    assert off(h) < 0.002 * np.ptp(y) < 0.02 * np.ptp(y) < off(h // 10)
    # without memory channels, the lags; a committee, its longest member's
    plain = NarxModel(LSSVMRegressor(C=1e3, sigma=3.0), input_lags=4, output_lags=2,
                      lag_step=3).fit(u[:800], y[:800])
    assert plain.history_samples == plain.max_lag_ == 12
    members = [NarxModel(LSSVMRegressor(C=1e3, sigma=3.0), input_lags=k, output_lags=0,
                         max_rows=400) for k in (4, 9)]
    assert NarxCommittee(members).fit(u[:800], y[:800]).history_samples == 9


def test_reach_is_the_displacements_the_inverse_was_identified_on(hyst_data):
    from types import SimpleNamespace

    from ipmc_model.narx import REACH_TOLERANCE_SHARE, out_of_reach, reach_mm

    u, y = hyst_data
    inv = InverseNarxModel(LSSVMRegressor(C=1e3, sigma=3.0), output_lags=3, input_lags=1,
                           memory_taus_s=[2.0]).fit(u[:800], y[:800])
    rows = y[inv.max_lag_:800]          # every row of a plain LS-SVM is a centre
    assert inv.identified_range_mm == pytest.approx((rows.min(), rows.max()), abs=1e-9)
    lo, hi = inv.settled_range_mm       # the displacement low-passed over 2 s: narrower
    assert rows.min() < lo < hi < rows.max()
    assert reach_mm(inv) == inv.identified_range_mm
    assert reach_mm(inv, held=True) == inv.settled_range_mm
    # an augmented model's feedforward by its inverse; a forward model does not tell
    assert reach_mm(SimpleNamespace(inverse=inv), held=True) == (lo, hi)
    assert reach_mm(NarxModel()) is None and not out_of_reach(99.0, None)
    tol = REACH_TOLERANCE_SHARE * (hi - lo)
    assert not out_of_reach(lo - 0.9 * tol, (lo, hi)) and not out_of_reach(hi + 0.9 * tol,
                                                                           (lo, hi))
    assert out_of_reach(lo - 1.1 * tol, (lo, hi)) and out_of_reach(hi + 1.1 * tol, (lo, hi))


def test_voltage_channel_model_with_the_raw_voltage_and_output_lags(hyst_data):
    u, y = hyst_data
    m = NarxModel(LSSVMRegressor(C=1e3, sigma=3.0), input_lags=1, output_lags=2,
                  input_memory_taus_s=[0.5], dt_s=0.01).fit(u[:800], y[:800])
    assert m.n_inputs_ == 2 and m.max_lag_ == 2
    free = m.simulate(u[:900], y[:2])
    st = m.stepper(u_history=u[:2], y_history=y[:2])
    assert_allclose([st.step(v) for v in u[2:900]], free[2:], rtol=1e-9, atol=1e-9)
    assert m.get_params()["input_memory_taus_s"] == [0.5]


def test_voltage_channel_model_refuses_bad_channels(hyst_data):
    u, y = hyst_data
    with pytest.raises(ValueError, match="no channel"):
        NarxModel(LSSVMRegressor(), include_voltage=False).fit(u, y)
    with pytest.raises(ValueError, match="memory_taus_s"):
        NarxModel(LSSVMRegressor(), input_memory_taus_s=[0.0]).fit(u, y)
    m = NarxModel(LSSVMRegressor(C=10.0, sigma=2.0), input_lags=0, output_lags=0,
                  input_memory_taus_s=(0.3,)).fit(u[:300], y[:300])
    with pytest.raises(ValueError, match="1-D voltage record"):
        m.simulate(np.column_stack([u, u]))


def test_free_run_cache_gives_the_model_s_free_run_exactly(hyst_data, fitted):
    u, y = hyst_data
    fir = NarxModel(LSSVMRegressor(C=1e3, sigma=3.0), input_lags=12, output_lags=0,
                    lag_step=2).fit(u[:800], y[:800])
    uv, yv = u[800:], y[800:]
    for model, L in ((fir, 24), (fitted, 3)):
        assert model.max_lag_ == L
        cache = FreeRunCache(model)
        first = cache.simulate(uv, yv[:L])
        assert np.array_equal(first, model.simulate(uv, yv[:L]))
        assert (cache.hits, cache.misses) == (0, 1)
        assert np.array_equal(cache.simulate(uv, yv[:L]), first)  # looked up, not run
        assert (cache.hits, cache.misses) == (1, 1)
        # other initial outputs (a strided view, as a slice may be): without output lags they
        # are only the first L entries (a hit); with them they change the run (a miss);
        # either way the model's own run
        other = (yv[: 2 * L] + 0.5)[::2]
        assert np.array_equal(cache.simulate(uv, other), model.simulate(uv, other))
        assert np.array_equal(cache.simulate(uv), model.simulate(uv))
        assert cache.misses == (1 if model.out_delays_.size == 0 else 3)
        # another input is another run; the returned runs are copies
        assert np.array_equal(cache.simulate(0.5 * uv), model.simulate(0.5 * uv))
        first[:] = 0.0
        assert np.array_equal(cache.simulate(uv, yv[:L]), model.simulate(uv, yv[:L]))


def test_free_run_cache_forgets_a_refitted_model_and_keeps_its_byte_budget(hyst_data):
    u, y = hyst_data
    model = NarxModel(LSSVMRegressor(C=1e3, sigma=3.0)).fit(u[:600], y[:600])
    uv = u[800:]
    with pytest.raises(NotFittedError):
        FreeRunCache(NarxModel())
    with pytest.raises(ValueError, match="max_bytes"):
        FreeRunCache(model, max_bytes=0)
    cache = FreeRunCache(model, max_bytes=2 * uv.nbytes)  # room for two runs
    old = cache.simulate(uv)
    model.fit(u[200:800], y[200:800])  # refitted in place: the kept run is stale
    new = cache.simulate(uv)
    assert not np.array_equal(new, old) and np.array_equal(new, model.simulate(uv))
    assert cache.misses == 2
    for gain in (0.9, 0.8, 0.7):  # three more runs: the oldest two are dropped
        cache.simulate(gain * uv)
    assert cache.misses == 5
    cache.simulate(0.7 * uv)
    cache.simulate(0.8 * uv)
    assert (cache.hits, cache.misses) == (2, 5)
    cache.simulate(uv)
    assert cache.misses == 6


def test_committee_is_the_mean_of_its_members(hyst_data):
    u, y = hyst_data
    u2 = np.column_stack([u, np.sin(np.arange(u.size) / 50.0)])  # an extra channel, as blocks add

    def members():
        return [NarxModel(LSSVMRegressor(C=1e3, sigma=3.0), input_lags=k, output_lags=n,
                          lag_step=2, max_rows=400) for k, n in ((4, 0), (8, 0), (6, 2))]

    alone = [m.fit(u2[:800], y[:800]) for m in members()]
    c = NarxCommittee(members()).fit(u2[:800], y[:800])
    L = c.max_lag_
    assert L == 16 and c.out_delays_.tolist() == [1, 3]
    uv, yv = u2[800:], y[800:]
    # free run: the members' mean after the longest window; its first L outputs are y_init
    free = c.simulate(uv, yv[:L])
    want = np.mean([m.simulate(uv, yv[: m.max_lag_]) for m in alone], axis=0)
    assert_allclose(free[L:], want[L:], rtol=1e-12, atol=1e-12)
    assert np.array_equal(free[:L], yv[:L])
    assert rmse(yv[L:], free[L:]) < 0.5 * np.std(yv)
    one = c.predict(uv, yv)
    assert_allclose(one[L:], np.mean([m.predict(uv, yv) for m in alone], axis=0)[L:],
                    rtol=1e-12, atol=1e-12)
    # step by step: with the measurements fed back, the one-step prediction
    st = c.stepper()
    steps = []
    for uk, yk in zip(uv[:300], yv[:300], strict=True):
        steps.append(st.step(uk))
        st.correct_output(yk)
    assert_allclose(steps[L:], one[L:300], rtol=1e-9, atol=1e-12)
    # and free from rest (members without output lags), the free run from rest
    fir = NarxCommittee(alone[:2])._set_fitted()
    st = fir.stepper()
    assert_allclose([st.step(x) for x in uv[:300]][L:], fir.simulate(uv[:300])[L:],
                    rtol=1e-9, atol=1e-12)
    # the cache runs the committee as it is
    cache = FreeRunCache(c)
    assert np.array_equal(cache.simulate(uv, yv[:L]), free)
    assert np.array_equal(cache.simulate(uv, yv[:L]), free) and cache.hits == 1
    with pytest.raises(ValueError, match="at least 2 members"):
        NarxCommittee(members()[:1]).fit(u2, y)
    with pytest.raises(ValueError, match="voltage channels"):
        NarxCommittee([members()[0], NarxModel(input_memory_taus_s=(1.0,))]).fit(u, y)
    with pytest.raises(NotFittedError):
        NarxCommittee(members()).simulate(uv)
