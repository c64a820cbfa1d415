"""Feedforward by inverting a FORWARD NARX model online, one sample at a time (pure core).

At each sample k the desired tip displacement r_k (mm) arrives and the feedforward picks the
voltage u_k in [-u_limit_v, u_limit_v] that makes the forward model's *free-run* prediction
follow it:

    u_k = argmin_u  mean_j (y_hat_{k+j}(u) - r_hat_{k+j})^2 + smoothness * (u - u_{k-1})^2,
          j = 0 .. horizon_samples - 1, u held over the horizon,

then advances the model one sample with u_k (its history holds its own predictions, never a
measurement, so the feedforward is a filter of the reference alone, like the inverse model it
replaces). ``r_hat`` is the reference extrapolated linearly from its last two samples (the
stepper sees r_k only).

Which forward model. The forward model's inputs are voltage channels: optionally the voltage
itself, then the voltage low-passed with each time constant of ``input_memory_taus_s`` (``m_j,k
= a_j m_j,k-1 + (1 - a_j) u_k``, ``a_j = exp(-dt_s / tau_j)``; build them for fitting with
:func:`voltage_channels`, or let the model build them: ``NarxModel(...,
input_memory_taus_s=..., include_voltage=...)``, which is what ``ipmc identify
--input-memory-taus`` writes and model_server and ``ipmc track`` invert). Why: the IPMC's tip
depends on the applied voltage through its double-layer charging (tau ~ 0.3 s) and
back-relaxation (tau ~ 0.46 s); low-passed voltages are those states, and they see *every* past
voltage. A NARX with voltage lags spaced s > 1 samples apart sees only every s-th voltage, so
its inversion is free to alternate the voltage between samples (it rang at the Nyquist
frequency, 3 V peak, in the experiment), and a raw-voltage channel lets the fit learn a
spurious direct u_k -> y_k gain that makes the one-step inversion ring as well.
``include_voltage=False`` with taus (0.3, 0.5) s and no output lags (an NFIR in the low-passed
voltages) is what worked: see scripts/forward_inversion_experiment.py.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .errors import check_fitted
from .lssvm import _KernelExpansion
from .narx import NarxModel, memory_poles, samples_to_settle, voltage_channels

__all__ = ["ForwardInversionFeedforward", "ForwardInversionStepper", "voltage_channels"]

METHODS = ("auto", "grid")
# method="auto": terms of the series along the line, points of the grid it is evaluated on
# (0.01 V at 3 V), and the largest truncation error accepted, mm (else the grid that step).
SERIES_TERMS = 17
SERIES_GRID_POINTS = 601
SERIES_TOLERANCE_MM = 1e-6


class ForwardInversionFeedforward:
    """Feedforward u_k (V) for a desired displacement r_k (mm) by inverting a forward model.

    Parameters
    ----------
    forward_model : fitted NarxModel
        y_k (mm) from its voltage channels (see :func:`voltage_channels`) and, optionally, its
        own past outputs; its regressor's ``predict(X)`` scores every candidate voltage in one
        batched call. A model with voltage channels of its own
        (``forward_model.uses_voltage_channels``) brings the next three parameters with it.
    input_memory_taus_s : sequence of float, optional
        The time constants (s) the model's low-passed voltage channels were built with.
        Default: the model's own, else none.
    include_voltage : bool, optional
        Whether the model's first channel is the voltage itself. Default: the model's own,
        else True.
    dt_s : float, optional
        Sample period, s (the model's and the loop's). Default: the model's own, else 0.01.
    Given for a model with voltage channels, these must agree with it.
    u_limit_v : float
        Voltages are searched in [-u_limit_v, u_limit_v], V (the H-bridge's 3 V).
    smoothness_mm2_per_v2 : float
        Weight of (u_k - u_{k-1})^2 against the squared tracking error, mm^2 / V^2 (0: none).
    horizon_samples : int
        Samples over which the held voltage is scored (1: one-step inversion).
    grid_points, refine_points : int
        The minimisation (``method="grid"``): a grid over the whole voltage range, then a finer
        grid across the best coarse cell and a parabolic step. Why a grid: the kernel model's
        cost can have several minima in u; a grid finds the global one at a fixed, predictable
        cost.
    method : {"auto", "grid"}
        ``auto``: for an RBF model on the channels themselves (no past lags, no output lags:
        the NFIR that inverts smoothly) and a one-sample horizon, the regressor row is affine
        in the voltage, z(u) = z0 + u w, so with A_j = ||z0 - c_j||^2, W = ||w||^2 and
        w.(z0 - c_j) = s - D_j (s = w.z0 - c_mid changes each step; D_j = w.c_j - c_mid,
        c_mid the middle of the w.c_j, does not) the prediction is

            f(u) = b + exp(-gamma (W u^2 + 2 s u)) sum_k (2 gamma u)^k / k! sum_j beta_j D_j^k,
            beta_j = alpha_j exp(-gamma A_j),

        a power series in u whose moments are one product of the kernel values with powers of
        D_j computed once. Over one sample the low-passed channels move little, so at most 17
        terms are exact to a bound computed each step (below 1e-6 mm, else that step takes
        the grid); the series is evaluated on a 601-point grid (0.01 V at 3 V) with the same
        parabolic step, so the global minimum is kept, and it gives the advanced model's
        prediction too. A raw-voltage channel moves the row too far for it (the grid). Other
        models and horizons: the grid.
        ``grid``: always the grid.

    Notes
    -----
    Cost per step: ``grid``: (grid_points + refine_points) * horizon_samples kernel rows,
    batched, plus one to advance the model; ``auto`` where the series applies: one kernel
    exponential per centre and one (SERIES_TERMS + 1) x centres matrix-vector product (on an
    800-centre model, step + record_applied 66 us against 105 us for a version with
    its powers of B_j formed each step, best of 5 x 3000 steps;
    the grid about 600 / 1100 us p50 / p99).
    """

    def __init__(self, forward_model: NarxModel, *,
                 input_memory_taus_s: Sequence[float] | None = None,
                 include_voltage: bool | None = None, dt_s: float | None = None,
                 u_limit_v: float = 3.0, smoothness_mm2_per_v2: float = 0.0,
                 horizon_samples: int = 1, grid_points: int = 25, refine_points: int = 21,
                 method: str = "auto"):
        if not isinstance(forward_model, NarxModel):
            raise ValueError(f"forward_model must be a fitted NarxModel, got "
                             f"{type(forward_model).__name__}")
        check_fitted(forward_model, "regressor_")
        self.forward_model = forward_model
        given = {"input_memory_taus_s": input_memory_taus_s, "include_voltage": include_voltage,
                 "dt_s": dt_s}
        if forward_model.uses_voltage_channels:
            own = {"input_memory_taus_s": tuple(float(t) for t in
                                                forward_model.input_memory_taus_s),
                   "include_voltage": bool(forward_model.include_voltage),
                   "dt_s": float(forward_model.dt_s)}
            for name, value in given.items():
                if value is None:
                    continue
                if name == "include_voltage":
                    same = bool(value) == own[name]
                else:  # times: dt_s comes from the data's time stamps (0.00999999999999 s)
                    theirs = np.atleast_1d(np.asarray(value, dtype=float))
                    mine = np.atleast_1d(np.asarray(own[name], dtype=float))
                    same = theirs.shape == mine.shape and np.allclose(theirs, mine, rtol=1e-6,
                                                                      atol=0.0)
                if not same:
                    raise ValueError(f"{name}={value!r} disagrees with the forward model's own "
                                     f"voltage channels ({name}={own[name]!r}); leave it out")
            given = own
        else:
            given = {"input_memory_taus_s": () if input_memory_taus_s is None
                     else input_memory_taus_s,
                     "include_voltage": True if include_voltage is None else include_voltage,
                     "dt_s": 0.01 if dt_s is None else dt_s}
        self.input_memory_taus_s = tuple(float(t) for t in given["input_memory_taus_s"])
        self.include_voltage = bool(given["include_voltage"])
        self.dt_s = float(given["dt_s"])
        self.poles_ = (memory_poles(self.input_memory_taus_s, self.dt_s)
                       if self.input_memory_taus_s else np.zeros(0))
        n_channels = int(self.include_voltage) + self.poles_.size
        if n_channels == 0:
            raise ValueError("no voltage channel: give input_memory_taus_s or "
                             "include_voltage=True")
        if forward_model.n_inputs_ != n_channels:
            raise ValueError(
                f"the forward model has {forward_model.n_inputs_} input channel(s) but "
                f"include_voltage={self.include_voltage} and {self.poles_.size} memory "
                f"time constant(s) make {n_channels}")
        if not (np.isfinite(u_limit_v) and u_limit_v > 0.0):
            raise ValueError(f"u_limit_v must be a positive voltage (V), got {u_limit_v!r}")
        self.u_limit_v = float(u_limit_v)
        if not (np.isfinite(smoothness_mm2_per_v2) and smoothness_mm2_per_v2 >= 0.0):
            raise ValueError(f"smoothness_mm2_per_v2 must be >= 0, got {smoothness_mm2_per_v2!r}")
        self.smoothness_mm2_per_v2 = float(smoothness_mm2_per_v2)
        for name, value, low in (("horizon_samples", horizon_samples, 1),
                                 ("grid_points", grid_points, 3),
                                 ("refine_points", refine_points, 3)):
            if int(value) != value or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        self.method = method
        self.horizon_samples = int(horizon_samples)
        self.grid_points = int(grid_points)
        self.refine_points = int(refine_points)

    def stepper(self, u_history=None) -> ForwardInversionStepper:
        """A fresh sample-by-sample feedforward; see :class:`ForwardInversionStepper`.

        ``u_history``: voltages (V, oldest first) it applied before, replayed from rest so that
        a restarted feedforward (model_server's reload) continues where the last one was
        (``record_applied`` then replaces the last of them); default none: from rest."""
        st = ForwardInversionStepper(self)
        if u_history is not None:
            for u in np.atleast_1d(np.asarray(u_history, dtype=float)):
                if not np.isfinite(u):
                    raise ValueError(f"u_history must hold finite voltages (V), got {u!r}")
                st._saved = (st._ub.copy(), st._yb.copy(), st._mem.copy(), st._u_prev)
                st._advance(min(self.u_limit_v, max(-self.u_limit_v, float(u))))
        return st

    @property
    def history_samples(self) -> int:
        """Past voltages a stepper going on from a history needs (see :meth:`stepper`): the
        forward model's lags, and five of its slowest voltage channel's time constants."""
        return samples_to_settle(self.forward_model.max_lag_, self.input_memory_taus_s,
                                 self.dt_s)

    def get_params(self) -> dict:
        return {
            "input_memory_taus_s": list(self.input_memory_taus_s),
            "include_voltage": self.include_voltage,
            "dt_s": self.dt_s,
            "u_limit_v": self.u_limit_v,
            "smoothness_mm2_per_v2": self.smoothness_mm2_per_v2,
            "horizon_samples": self.horizon_samples,
            "grid_points": self.grid_points,
            "refine_points": self.refine_points,
            "method": self.method,
        }


class ForwardInversionStepper:
    """The feedforward one sample at a time: ``step(r_mm) -> u_v``, from rest.

    State: the model's voltage-channel history, its low-pass filter states and its own past
    predicted outputs. ``record_applied(u_v)`` replaces the last voltage by the one really
    applied (e.g. limited elsewhere) and recomputes that sample's state.

    Attributes
    ----------
    predicted_mm : float
        The forward model's prediction of the tip for the last returned voltage, mm.
    series_steps : int
        Steps whose voltage ``method="auto"`` found by the series (the others: the grid).
    series_error_bound_mm : float
        The largest truncation bound of the series among those steps, mm.
    """

    def __init__(self, ff: ForwardInversionFeedforward):
        m = ff.forward_model
        self._ff = ff
        self._m = m
        self._a = ff.poles_
        self._raw = int(ff.include_voltage)
        self._u_mean = np.asarray(m.u_mean_, dtype=float)
        self._u_scale = np.asarray(m.u_scale_, dtype=float)
        self._u_delays = list(m.in_delays_)
        self._y_delays = m.out_delays_
        self._depth_u = 1 + max(int(d.max()) for d in self._u_delays)
        self._depth_y = int(self._y_delays.max()) if self._y_delays.size else 1
        self._y_rest = (0.0 - m.y_mean_) / m.y_scale_
        self._u_grid = np.linspace(-ff.u_limit_v, ff.u_limit_v, ff.grid_points)
        self._j = np.arange(ff.horizon_samples, dtype=float)
        # Newest first: _ub[i] = channels of u_{k-1-i} (V), _yb[i] = y_{k-1-i} (scaled).
        self._ub = np.zeros((self._depth_u, m.n_inputs_))
        self._yb = np.full(self._depth_y, self._y_rest)
        self._mem = np.zeros(self._a.size)
        self._one_minus_a = 1.0 - self._a
        self._r_prev: float | None = None
        self._u_prev = 0.0
        self._saved = None
        self.predicted_mm = 0.0
        self.series_steps = 0
        self.series_error_bound_mm = 0.0
        self._kernel = isinstance(m.regressor_, _KernelExpansion)   # RBF: exp(-gamma d^2)
        # The series needs the row affine in u with a constant slope: an RBF model on the
        # channels themselves (no past lags, no output lags), scored over one sample.
        self._series = (ff.method == "auto" and self._kernel and self._y_delays.size == 0
                        and ff.horizon_samples == 1
                        and all(list(ds) == [0] for ds in self._u_delays))
        if self._series:
            reg = m.regressor_
            g = self._gamma = float(reg._gamma)
            U = ff.u_limit_v
            self._fine_u = np.linspace(-U, U, SERIES_GRID_POINTS)
            k = np.arange(SERIES_TERMS)
            k_fact = np.cumprod(np.concatenate(([1.0], k[1:].astype(float))))       # k!
            # The row's change per volt w, and what depends on it alone.
            per_volt = np.concatenate((np.ones(self._raw), 1.0 - self._a))
            self._w = per_volt / self._u_scale                                 # (d,)
            self._W = float(self._w @ self._w)
            # w.c_j, centred on its mid-range: B_j = w.(z0 - c_j) = s - D_j with s changing
            # each step and D_j fixed, so the moments sum_j beta_j D_j^k use powers of D_j
            # computed once here (PT) and |2 gamma u D_j| <= x_max bounds the remainder for
            # every step.
            Cw = reg.centers_ @ self._w
            self._c_mid = 0.5 * (float(Cw.max()) + float(Cw.min()))
            D = Cw - self._c_mid
            PT = np.empty((SERIES_TERMS, D.size))
            PT[0] = 1.0
            for i in range(1, SERIES_TERMS):
                PT[i] = PT[i - 1] * D
            # One matrix-vector product per step gives every moment sum_j alpha_j E_j D_j^k
            # and, in its last row, sum_j |alpha_j| E_j (the bound's scale), with
            # E_j = exp(-gamma ||z0 - c_j||^2) from one more: [2 gamma c_j, -gamma ||c_j||^2, 1]
            # . [z0, 1, -gamma ||z0||^2].
            self._PTc = np.ascontiguousarray(
                np.vstack((PT * reg.coef_, np.abs(reg.coef_))))
            self._exponent = np.ascontiguousarray(np.column_stack(
                (reg._row_a, reg._row_c, np.ones(D.size))))  # predict_one's terms
            self._z_aug = np.zeros(self._exponent.shape[1])
            self._z_aug[-2] = 1.0
            x_max = 2.0 * g * U * float(np.abs(D).max())
            # Remainder of exp(x) after K terms, |x| <= x_max: e^x_max x_max^K / K!.
            self._remainder = [math.exp(x_max) * x_max ** K / (k_fact[K - 1] * K)
                               for K in range(1, SERIES_TERMS + 1)]
            # GT[k, g] = (2 gamma u_g)^k / k!; the prediction on the grid is intercept +
            # exp(-gamma W u_g^2 - 2 gamma s u_g) * (moments @ GT).
            self._GT = np.ascontiguousarray(((2.0 * g * self._fine_u[:, None]) ** k / k_fact).T)
            self._coef_scale = (2.0 * g) ** k / k_fact
            self._prefactor = np.ascontiguousarray(np.column_stack(
                (-2.0 * g * self._fine_u, -g * self._W * self._fine_u ** 2)))
            # Row at u = 0 from the filter states: z0 = mem * a / scale - mean / scale.
            self._z_mem = self._a / self._u_scale[self._raw:]
            self._z_rest = -self._u_mean / self._u_scale
        # The last step's series (its Horner coefficients in u, and s), while its state holds.
        self._series_coefs: list | None = None
        self._s = 0.0

    # -- the model -----------------------------------------------------------------------------
    def _f(self, X: np.ndarray) -> np.ndarray:
        """Scaled model output for scaled rows X (G, d): all candidates in one batched call."""
        return np.asarray(self._m.regressor_.predict(X), dtype=float)

    def _rows(self, ub: np.ndarray, yb: np.ndarray, o: int) -> np.ndarray:
        """Scaled regressor rows; column o + d of ub / yb holds the sample d steps back."""
        cols = [(ub[:, o + d, c] - self._u_mean[c]) / self._u_scale[c]
                for c, ds in enumerate(self._u_delays) for d in ds]
        if self._y_delays.size:
            cols.append(yb[:, o + self._y_delays])
        return np.column_stack(cols)

    def _channels(self, u: np.ndarray, steps: int) -> np.ndarray:
        """Channel values (G, c) after holding voltages u (G,) for ``steps`` samples."""
        out = np.empty((u.size, self._m.n_inputs_))
        if self._raw:
            out[:, 0] = u
        if self._a.size:
            an = self._a ** steps
            out[:, self._raw:] = an * self._mem + (1.0 - an) * u[:, None]
        return out

    def _simulate(self, u: np.ndarray) -> np.ndarray:
        """Predicted tips (G, horizon), mm, for candidate voltages u (G,) held over it."""
        H = self._ff.horizon_samples
        G = u.size
        ub = np.empty((G, H + self._depth_u, self._m.n_inputs_))
        ub[:, H:] = self._ub
        yb = np.empty((G, H + self._depth_y))
        yb[:, H:] = self._yb
        y = np.empty((G, H))
        for j in range(H):
            o = H - 1 - j  # sample k + j sits in column o
            ub[:, o] = self._channels(u, j + 1)
            zk = self._f(self._rows(ub, yb, o))
            yb[:, o] = zk
            y[:, j] = zk * self._m.y_scale_ + self._m.y_mean_
        return y

    def _series_minimise(self, r_mm: float) -> float | None:
        """The voltage whose one-sample prediction is nearest r_mm, by the series along the
        line (method="auto"), or None where its truncation bound exceeds
        SERIES_TOLERANCE_MM."""
        reg, g, U = self._m.regressor_, self._gamma, self._ff.u_limit_v
        z0 = self._z_rest.copy()                                     # the row at u = 0
        z0[self._raw:] += self._z_mem * self._mem
        za = self._z_aug
        za[:z0.size] = z0
        za[-1] = -g * float(z0 @ z0)
        E = self._exponent @ za                # -gamma ||z0 - c_j||^2 (this is the hot loop)
        np.exp(E, out=E)
        moments = self._PTc @ E
        s = float(self._w @ z0) - self._c_mid
        # The prefactor exp(-gamma W u^2 - 2 gamma s u) peaks at u = -s / W (within +-U).
        u_peak = min(U, max(-U, -s / self._W))
        log_e_max = -g * u_peak * (self._W * u_peak + 2.0 * s)
        if log_e_max > 600.0:   # a row far outside the centres: no series worth its terms
            return None
        e_max = math.exp(log_e_max)
        scale = float(moments[-1]) * e_max * abs(self._m.y_scale_)
        # The fewest terms that meet the tolerance.
        for K in range(4, SERIES_TERMS + 1):
            bound = scale * self._remainder[K - 1]
            if bound <= SERIES_TOLERANCE_MM:
                break
        else:
            return None
        moments = moments[:K]
        pred = moments @ self._GT[:K]
        e = self._prefactor @ (s, 1.0)
        np.exp(e, out=e)
        pred *= e
        # Prediction - target on the grid, in the model's scaled units (y_scale_ per mm).
        pred -= (r_mm - self._m.y_mean_) / self._m.y_scale_ - reg.intercept_
        J = pred * pred
        u_g = self._fine_u
        if self._ff.smoothness_mm2_per_v2:
            weight = self._ff.smoothness_mm2_per_v2 / self._m.y_scale_ ** 2   # scaled units
            J += weight * (u_g - self._u_prev) ** 2
        i = int(np.argmin(J))
        u = float(u_g[i])
        if 0 < i < J.size - 1:
            curv = J[i - 1] - 2.0 * J[i] + J[i + 1]
            if curv > 0.0:
                u += 0.5 * (J[i - 1] - J[i + 1]) / curv * (u_g[1] - u_g[0])
        u = min(U, max(-U, u))
        # Horner coefficients of the inner series in u, highest power first.
        coefs = moments * self._coef_scale[:K]
        self._series_coefs = coefs[::-1].tolist()
        self._s = s
        self.series_error_bound_mm = max(self.series_error_bound_mm, bound)
        return u

    def _series_at(self, u: float) -> float:
        """The scaled one-sample prediction at voltage u (|u| <= u_limit_v) by the last series."""
        inner = 0.0
        for c in self._series_coefs:
            inner = inner * u + c
        prefactor = math.exp(-self._gamma * u * (self._W * u + 2.0 * self._s))
        return self._m.regressor_.intercept_ + prefactor * inner

    def _cost(self, u: np.ndarray, target: np.ndarray) -> np.ndarray:
        err = self._simulate(u) - target
        du = u - self._u_prev
        return np.mean(err * err, axis=1) + self._ff.smoothness_mm2_per_v2 * du * du

    # -- the loop ------------------------------------------------------------------------------
    def step(self, r_mm: float) -> float:
        """Desired displacement r_k (mm) -> feedforward voltage u_k (V), within the limit."""
        r = float(r_mm)
        if not math.isfinite(r):
            raise ValueError(f"r_mm must be a finite displacement (mm), got {r_mm!r}")
        slope = 0.0 if self._r_prev is None else r - self._r_prev
        self._r_prev = r
        self._series_coefs = None
        u = self._series_minimise(r) if self._series else None
        if u is not None:
            self.series_steps += 1
        else:
            u = self._grid_minimise(r + slope * self._j)
        u = min(self._ff.u_limit_v, max(-self._ff.u_limit_v, u))
        self._saved = (self._ub.copy(), self._yb.copy(), self._mem.copy(), self._u_prev)
        self._advance(u, None if self._series_coefs is None else self._series_at(u))
        return u

    def _grid_minimise(self, target: np.ndarray) -> float:
        grid = self._u_grid
        i = int(np.argmin(self._cost(grid, target)))
        h = grid[1] - grid[0]
        fine = np.linspace(max(grid[0], grid[i] - h), min(grid[-1], grid[i] + h),
                           self._ff.refine_points)
        J = self._cost(fine, target)
        i = int(np.argmin(J))
        u = float(fine[i])
        if 0 < i < fine.size - 1:  # parabola through the best three points
            curv = J[i - 1] - 2.0 * J[i] + J[i + 1]
            if curv > 0.0:
                u += 0.5 * (J[i - 1] - J[i + 1]) / curv * (fine[1] - fine[0])
        return u

    def _advance(self, u: float, zk: float | None = None) -> None:
        """Advance the model one sample with voltage u (V); ``zk``: its scaled prediction if
        known (the series'), else computed here."""
        if self._a.size:
            self._mem = self._a * self._mem + self._one_minus_a * u
        if self._depth_u > 1:
            self._ub[1:] = self._ub[:-1]
        if self._raw:
            self._ub[0, 0] = u
        self._ub[0, self._raw:] = self._mem
        if zk is None:
            yb = np.concatenate(([0.0], self._yb))[None, :]  # column d = y_{k-d}
            row = self._rows(self._ub[None], yb, 0)
            zk = (self._m.regressor_.predict_one(row[0]) if self._kernel
                  else float(self._f(row)[0]))
        if self._depth_y > 1:
            self._yb[1:] = self._yb[:-1]
        self._yb[0] = zk
        self._u_prev = u
        self.predicted_mm = zk * self._m.y_scale_ + self._m.y_mean_

    def record_applied(self, u_applied_v: float) -> None:
        """Replace the last returned voltage in the history by the applied one (V)."""
        u = float(u_applied_v)
        if not np.isfinite(u):
            raise ValueError(f"u_applied_v must be a finite voltage (V), got {u_applied_v!r}")
        if self._saved is None:
            raise ValueError("record_applied before any step")
        if u == self._u_prev:
            return
        ub, yb, mem, u_prev = self._saved
        self._ub[:], self._yb[:], self._mem, self._u_prev = ub, yb, mem.copy(), u_prev
        # From the same state the last step's series holds for any voltage in the range.
        series = self._series_coefs is not None and abs(u) <= self._ff.u_limit_v
        self._advance(u, self._series_at(u) if series else None)
