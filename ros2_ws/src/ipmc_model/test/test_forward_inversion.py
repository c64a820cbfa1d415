"""ForwardInversionFeedforward: inverts a known forward system, respects the voltage limit,
refuses bad input."""

import numpy as np
import pytest

from ipmc_model.errors import NotFittedError
from ipmc_model.forward_inversion import ForwardInversionFeedforward, voltage_channels
from ipmc_model.lssvm import LSSVMRegressor
from ipmc_model.narx import NarxModel

DT_S = 0.01
TAUS_S = (0.3, 0.5)


class LinearRegressor:
    """Least squares with intercept: the model of a linear system is then exact."""

    def fit(self, X, y):
        A = np.column_stack([X, np.ones(len(X))])
        self.w_ = np.linalg.lstsq(A, y, rcond=None)[0]
        return self

    def predict(self, X):
        return np.column_stack([X, np.ones(len(X))]) @ self.w_


def linear_plant(u_v):
    """Synthetic tip (mm): a charging state minus a relaxation state, 1.2 mm/V at DC."""
    ch = voltage_channels(u_v, TAUS_S, DT_S, include_voltage=False)
    return 2.0 * ch[:, 0] - 0.8 * ch[:, 1]


def smooth_voltage(n, seed, amplitude_v=2.0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT_S
    u = sum(rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
            for f in rng.uniform(0.05, 0.7, 6))
    return amplitude_v * u / np.abs(u).max()


def fit_forward(regressor, plant, n=3000, seed=1):
    u = smooth_voltage(n, seed)
    model = NarxModel(regressor, input_lags=[0, 0], output_lags=0)
    return model.fit(voltage_channels(u, TAUS_S, DT_S, include_voltage=False), plant(u))


def run(ff, r_mm):
    st = ff.stepper()
    return np.array([st.step(r) for r in r_mm])


@pytest.fixture(scope="module")
def linear_ff():
    model = fit_forward(LinearRegressor(), linear_plant)
    return ForwardInversionFeedforward(model, input_memory_taus_s=TAUS_S, include_voltage=False)


def test_reproduces_a_reachable_target_of_a_linear_system(linear_ff):
    u_true = smooth_voltage(1500, seed=7, amplitude_v=1.5)  # not the training signal
    target = linear_plant(u_true)
    u = run(linear_ff, target)
    # The voltage found makes the system follow the target; a grid + parabola leaves < 1e-3 V.
    assert np.sqrt(np.mean((linear_plant(u) - target) ** 2)) < 2e-4
    assert np.max(np.abs(u - u_true)) < 5e-3


def test_reproduces_a_reachable_target_of_a_nonlinear_system_with_an_lssvm():
    def plant(u_v):  # asymmetric, saturating bend of the same two states
        ch = voltage_channels(u_v, TAUS_S, DT_S, include_voltage=False)
        s = ch[:, 0] - 0.4 * ch[:, 1]
        return np.where(s > 0, 3.0 * np.tanh(s), 1.2 * s * (1 - 0.2 * s))

    model = fit_forward(LSSVMRegressor(C=1e6, sigma=2.0), plant, n=2000)
    ff = ForwardInversionFeedforward(model, input_memory_taus_s=TAUS_S, include_voltage=False)
    target = plant(smooth_voltage(1500, seed=9, amplitude_v=1.5))
    st = ff.stepper()
    u = np.empty(target.size)
    predicted = np.empty(target.size)
    for k, r in enumerate(target):
        u[k] = st.step(r)
        predicted[k] = st.predicted_mm
    assert np.sqrt(np.mean((predicted - target) ** 2)) < 1e-3  # the model follows exactly
    assert np.sqrt(np.mean((plant(u) - target) ** 2)) < 0.02   # the system within its fit


def test_voltage_is_clipped_to_the_limit(linear_ff):
    up = run(linear_ff, np.full(50, 100.0))
    down = run(linear_ff, np.full(50, -100.0))
    assert np.all(up == 3.0) and np.all(down == -3.0)
    ff = ForwardInversionFeedforward(linear_ff.forward_model, input_memory_taus_s=TAUS_S,
                                     include_voltage=False, u_limit_v=1.0)
    assert np.all(np.abs(run(ff, np.linspace(-50, 50, 200))) <= 1.0)


def test_record_applied_changes_what_the_model_remembers(linear_ff):
    a, b = linear_ff.stepper(), linear_ff.stepper()
    ua, ub = a.step(0.02), b.step(0.02)  # 0.02 mm: reachable in one sample (about 0.4 V)
    assert ua == ub
    a.record_applied(ua)  # the same voltage: nothing changes
    b.record_applied(0.0)  # b's model never received ub
    assert a.predicted_mm == pytest.approx(linear_plant(np.array([ua]))[0], abs=1e-9)
    assert b.predicted_mm == pytest.approx(0.0, abs=1e-9)
    assert abs(ua) < 3.0
    assert b.step(0.02) > a.step(0.02)  # b is further from the target and pushes harder


def test_smoothness_penalty_slows_the_voltage(linear_ff):
    target = np.r_[np.zeros(5), np.full(30, 1.0)]
    ff = ForwardInversionFeedforward(linear_ff.forward_model, input_memory_taus_s=TAUS_S,
                                     include_voltage=False, smoothness_mm2_per_v2=1.0)
    assert np.max(np.abs(np.diff(run(ff, target)))) < np.max(np.abs(np.diff(run(linear_ff,
                                                                                target))))


def test_bad_input_raises_clear_errors(linear_ff):
    model = linear_ff.forward_model
    st = linear_ff.stepper()
    with pytest.raises(ValueError, match="r_mm must be a finite"):
        st.step(float("nan"))
    with pytest.raises(ValueError, match="before any step"):
        st.record_applied(1.0)
    with pytest.raises(ValueError, match="2 input channel"):
        ForwardInversionFeedforward(model, input_memory_taus_s=TAUS_S, include_voltage=True)
    with pytest.raises(ValueError, match="u_limit_v"):
        ForwardInversionFeedforward(model, input_memory_taus_s=TAUS_S, include_voltage=False,
                                    u_limit_v=0.0)
    with pytest.raises(ValueError, match="horizon_samples"):
        ForwardInversionFeedforward(model, input_memory_taus_s=TAUS_S, include_voltage=False,
                                    horizon_samples=0)
    with pytest.raises(NotFittedError):
        ForwardInversionFeedforward(NarxModel(LinearRegressor()), input_memory_taus_s=TAUS_S)
    with pytest.raises(ValueError, match="no channel"):
        voltage_channels(np.zeros(10), (), DT_S, include_voltage=False)


def test_a_model_with_its_own_voltage_channels_needs_no_repeated_taus(linear_ff):
    u = smooth_voltage(3000, seed=1)
    own = NarxModel(LinearRegressor(), input_lags=0, output_lags=0, input_memory_taus_s=TAUS_S,
                    include_voltage=False, dt_s=DT_S).fit(u, linear_plant(u))
    ff = ForwardInversionFeedforward(own)
    assert ff.get_params()["input_memory_taus_s"] == list(TAUS_S)
    assert ff.include_voltage is False and ff.dt_s == DT_S
    target = linear_plant(smooth_voltage(500, seed=7, amplitude_v=1.5))
    np.testing.assert_allclose(run(ff, target), run(linear_ff, target), rtol=0, atol=1e-9)
    # Repeating the model's own values is accepted; contradicting them is not.
    ForwardInversionFeedforward(own, input_memory_taus_s=list(TAUS_S), dt_s=DT_S)
    # dt from a record's time stamps is not exactly 0.01 s: still the same channels.
    own.dt_s = DT_S * (1 - 1e-12)
    ForwardInversionFeedforward(own, dt_s=DT_S)
    own.dt_s = DT_S
    with pytest.raises(ValueError, match="dt_s=0.02 disagrees"):
        ForwardInversionFeedforward(own, dt_s=0.02)
    with pytest.raises(ValueError, match="include_voltage=True disagrees"):
        ForwardInversionFeedforward(own, include_voltage=True)


def _run_applied(ff, target_mm):
    """A stepper run over ``target_mm`` with each voltage recorded as applied; (stepper, V)."""
    st, u = ff.stepper(), []
    for r in target_mm:
        u.append(st.step(r))
        st.record_applied(u[-1])
    return st, u


def test_stepper_seeded_with_past_voltages_continues_the_run(linear_ff):
    target = linear_plant(smooth_voltage(400, seed=3, amplitude_v=1.5))
    a, u = _run_applied(linear_ff, target[:200])
    b = linear_ff.stepper(u_history=u[:-1] + [0.0])
    b.record_applied(u[-1])  # replaces the last voltage of the history
    assert b.predicted_mm == pytest.approx(a.predicted_mm, abs=1e-12)
    for r in target[200:260]:
        assert b.step(r) == pytest.approx(a.step(r), abs=1e-9)
    with pytest.raises(ValueError, match="finite voltages"):
        linear_ff.stepper(u_history=[0.0, float("nan")])


def test_history_samples_of_past_voltages_are_enough_to_go_on(linear_ff):
    """history_samples: five of the slowest channel's time constants (what model_server hands
    a new stepper); the last that many voltages continue the run within 0.01 V (0.005 V
    measured), a tenth of them 2.7 V off."""
    assert linear_ff.history_samples == 250   # 5 x 0.5 s at 100 Hz
    target = linear_plant(smooth_voltage(900, seed=3, amplitude_v=1.5))
    a, u = _run_applied(linear_ff, target[:800])
    ahead = [a.step(r) for r in target[800:]]

    def off(n):
        b = linear_ff.stepper(u_history=u[-n:])
        return max(abs(b.step(r) - v) for r, v in zip(target[800:], ahead, strict=True))

    assert off(linear_ff.history_samples) < 0.01 < 1.0 < off(linear_ff.history_samples // 10)


@pytest.fixture(scope="module")
def lssvm_nfir():
    """A forward LSSVM on the two low-passed voltages (the structure model_server inverts)."""
    def plant(u_v):
        ch = voltage_channels(u_v, TAUS_S, DT_S, include_voltage=False)
        s = ch[:, 0] - 0.4 * ch[:, 1]
        return np.where(s > 0, 3.0 * np.tanh(s), 1.2 * s * (1 - 0.2 * s))

    u = smooth_voltage(2000, seed=1)
    model = NarxModel(LSSVMRegressor(C=1e6, sigma=1.0), input_lags=0, output_lags=0,
                      input_memory_taus_s=TAUS_S, include_voltage=False, dt_s=DT_S)
    return model.fit(u, plant(u)), plant


def test_auto_series_agrees_with_the_grid_and_with_the_model(lssvm_nfir):
    model, plant = lssvm_nfir
    target = plant(smooth_voltage(1500, seed=9, amplitude_v=1.5))
    auto = ForwardInversionFeedforward(model).stepper()
    grid = ForwardInversionFeedforward(model, method="grid").stepper()
    u_auto, predicted = np.empty(target.size), np.empty(target.size)
    for k, r in enumerate(target):
        u_auto[k] = auto.step(r)
        predicted[k] = auto.predicted_mm
    u_grid = np.array([grid.step(r) for r in target])
    assert auto.series_steps == target.size and grid.series_steps == 0
    assert auto.series_error_bound_mm <= 1e-6
    # The series' prediction (the model's advanced state) is the model's own free run.
    np.testing.assert_allclose(predicted, model.simulate(u_auto), rtol=0, atol=1e-8)
    # The smoothness penalty (mm^2/V^2) weighs the same in both.
    smooth = {m: ForwardInversionFeedforward(model, smoothness_mm2_per_v2=0.05, method=m)
              for m in ("auto", "grid")}
    u_smooth = {m: run(ff, target[:300]) for m, ff in smooth.items()}
    assert np.max(np.abs(u_smooth["auto"] - u_smooth["grid"])) < 1e-3
    assert np.max(np.abs(u_smooth["auto"] - u_auto[:300])) > 1e-2   # and it does something
    # An applied voltage other than the returned one (the hybrid adds the PID's): the state
    # still follows the model's free run on what was applied.
    st, applied, predicted = ForwardInversionFeedforward(model).stepper(), [], []
    for k, r in enumerate(target[:400]):
        applied.append(float(np.clip(st.step(r) + 0.3 * np.sin(0.05 * k), -3.0, 3.0)))
        st.record_applied(applied[-1])
        predicted.append(st.predicted_mm)
    np.testing.assert_allclose(predicted, model.simulate(np.array(applied)), rtol=0, atol=1e-8)
    # Both minimise the same cost, the grid to about 1e-3 V: measured 1e-5 V apart.
    assert np.max(np.abs(u_auto - u_grid)) < 1e-3
    assert np.sqrt(np.mean((plant(u_auto) - target) ** 2)) < 0.02


def test_auto_takes_the_grid_where_the_series_bound_is_too_large(lssvm_nfir):
    model, plant = lssvm_nfir
    u = smooth_voltage(2000, seed=1)
    raw = NarxModel(LSSVMRegressor(C=1e3, sigma=0.3), input_lags=0, output_lags=0,
                    input_memory_taus_s=TAUS_S, include_voltage=True, dt_s=DT_S).fit(u, plant(u))
    st = ForwardInversionFeedforward(raw).stepper()
    target = plant(smooth_voltage(50, seed=9, amplitude_v=1.5))
    u_auto = np.array([st.step(r) for r in target])
    # The raw voltage channel moves the row several kernel widths over +-3 V: the grid.
    assert st.series_steps == 0
    grid = ForwardInversionFeedforward(raw, method="grid").stepper()
    np.testing.assert_array_equal(u_auto, [grid.step(r) for r in target])


def test_method_is_checked(lssvm_nfir):
    with pytest.raises(ValueError, match="method must be one of"):
        ForwardInversionFeedforward(lssvm_nfir[0], method="newton")
