"""Rate-dependent generalised Prandtl-Ishlinskii model (GPI): a structured hysteresis model
whose free run cannot diverge, for IPMC and piezo actuators.

The voltage u (V) passes through four stages, each an actuator mechanism:

0. **A transport delay** of whole samples (drive electronics, a bus): the one the linear part
   prefers over 0 .. ``max_delay_s`` is fitted beside none, and the free-run CV keeps one
   (``delay_s`` fixes it). An optional **dead zone** ``dead_zone_v`` comes before it (voltages
   below it move no ions: a contact or electrode threshold).
1. **Ion-current-limited charging** (the double layer of an IPMC, a piezo's amplifier):
   ``v_k = v_{k-1} + dt S tanh((u_k - v_{k-1}) / (tau S))``, a first-order lag of time constant
   ``tau`` whose rate saturates at ``S`` V/s. Two parameters, fitted.
2. **A bank of linear relaxations** spanning the actuator's time scales (tens of ms to
   minutes: charging, back-relaxation, creep): ``x_j = a_j x_j + (1 - a_j) v``,
   ``a_j = exp(-dt / tau_j)``, the time constants fixed on a geometric grid (orthonormal-basis
   identification, where the slow poles are fixed and only their weights are fitted).
3. **Play operators** (the paper's PI hysteresis, Eq. 2) on the charge and the faster
   relaxations, thresholds a share of the largest voltage; beside them **smooth memory**: the
   charge low-passed over its own travel (path memory) and, on the charge and the fastest
   relaxations, the direction of motion low-passed over its travel (direction memory).
   Together these are the exact basis of a Duhem (Bouc-Wen, n = 1) element, whose loop rounds
   off exponentially after each reversal where a play's corners are sharp.
4. **An output map** ``y = g(z)``, ``z = w . phi`` the weighted sum of the channels and plays;
   ``g`` is piecewise linear (hinges at quantiles of z): the asymmetric, saturating bending
   of the generalised PI (Al Janaideh, Rakheja & Su).

An optional channel beside the plays: the charging current ``dv/dt`` (``rate_channel``:
bending that follows the migrating ions, not their charge). After the map, optional output
channels are added to the tip linearly: the charging current (``output_rate``: water dragged
with the migrating cations bends the strip on top of the charge's bending, so it adds after
the bending's nonlinearity, not inside it) and slow relaxations of the charge
(``output_taus_s``: creep). Then an output stage
scales the negative side (``negative_gain_``: an electrode face that cracked), lets gain and
offset change linearly with the time since the start (``drift_gain_per_s_``,
``drift_offset_mm_per_s_``: an IPMC dehydrating) and softly limits the tip (``limit_mm_``: a
stop); :meth:`GeneralizedPI.fit` leaves it neutral, the residual diagnosis fits it.

Every parameter but ``tau``, ``S`` enters linearly or bilinearly, and there is no output
feedback: the free run is the one-step prediction, bounded for any bounded input. The joint
fit is SciPy's ``least_squares`` (trust region, analytic Jacobian for the weights and the map,
finite differences for the two charging parameters); the ridge weight on ``w`` is chosen by
blocked K-fold cross-validation of the free-run error (each held-out block is scored on the
output the model simulates from the record's input alone).

:class:`GpiInverse` is its numerical inverse: at each sample the voltage whose model output
equals the desired displacement, found on the monotone scalar map u_k -> y_k (grid search
then bracket refinement), from the model's own state; so it is exact to the model wherever the
actuator's limits allow.
"""

from __future__ import annotations

import copy
import math
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline
from scipy.optimize import least_squares
from scipy.signal import lfilter

from ipmc_driver.validation import as_signal, same_length

from .errors import check_fitted
from .metrics import effective_samples, independent_samples

#: Relaxation time constants (s), spaced by 3: charging (tens of ms) to creep (minutes).
DEFAULT_MEMORY_TAUS_S = (0.05, 0.15, 0.45, 1.35, 4.0, 12.0, 36.0, 108.0)
#: Travels (V of charge) of the path-memory channels: smooth rate-independent memory.
DEFAULT_PATH_MEMORY_V = (0.5, 2.0, 8.0, 32.0)
#: Travels (V) of the direction-memory channels: smooth plays.
DEFAULT_DIRECTION_MEMORY_V = (0.5, 2.0, 8.0, 32.0)
#: Charging time constants tried as the joint fit's start, as multiples of the first guess:
#: the fit's only non-convex parameters, started where a linear fit of the rest explains most.
INITIAL_TAU_FACTORS = (1 / 30, 0.1, 1 / 3, 1.0, 3.0)
#: Play thresholds as shares of the largest |u| of the identification record.
DEFAULT_THRESHOLD_SHARES = (0.1, 0.25, 0.5, 0.75)
#: Ridge weights tried by the cross-validation (on standardised features, per sample).
DEFAULT_ALPHAS = tuple(float(a) for a in np.logspace(-9, -2, 8))
#: A time constant is kept only if the record spans this many of it: slower ones are not
#: identifiable from it (a relaxation must be seen settling to be told from an offset).
MIN_SPANS_PER_TAU = 3.0
#: The charging stage starts at this many samples' time constant (0.3 s at 100 Hz).
INITIAL_TAU_SAMPLES = 30
#: Independent samples of the fit's residual with z beyond a hinge of the output map for the
#: map to go on at its slope past the fit range: one fixes the slope, a second checks it.
EDGE_INDEPENDENT_SAMPLES = 2


def rate_limited_charge(u_v, tau_s: float, slew_v_per_s: float, dt_s: float,
                        v0: float = 0.0) -> np.ndarray:
    """Ion-current-limited first-order charging of ``u_v`` (V): the stage-1 state, shape (N,).

    Written as a loop: a nonlinear recursion, which no SciPy filter runs.
    """
    u = np.asarray(u_v, dtype=float)
    step, gain, tanh = dt_s * slew_v_per_s, 1.0 / (tau_s * slew_v_per_s), math.tanh
    v, out = float(v0), []
    put = out.append   # a list and one conversion: a sixth faster than item assignment
    for uk in u.tolist():
        v += step * tanh((uk - v) * gain)
        put(v)
    return np.array(out, dtype=float).reshape(u.shape)


def lowpass_bank(v, taus_s, dt_s: float, state=None) -> tuple[np.ndarray, np.ndarray]:
    """First-order low-passes of ``v`` with unit DC gain, ``x_k = a x_{k-1} + (1 - a) v_k``:
    the (N, J) outputs and the last outputs (J,), from ``state`` (J,) before sample 0 or rest."""
    a = np.exp(-dt_s / np.asarray(taus_s, dtype=float))
    x0 = np.zeros(a.size) if state is None else np.asarray(state, dtype=float)
    out = np.empty((np.size(v), a.size))
    for j, aj in enumerate(a):
        out[:, j] = lfilter([1.0 - aj], [1.0, -aj], v, zi=[aj * x0[j]])[0]
    return out, (out[-1].copy() if len(out) else x0.copy())


def travel_bank(v, travels_v, v_prev: float = 0.0, state=None) -> tuple[np.ndarray, np.ndarray]:
    """Low-passes of ``v`` in its own travel, not in time: ``x_k = a_k x_{k-1} + (1 - a_k) v_k``
    with ``a_k = exp(-|v_k - v_{k-1}| / T_j)``. Rate-independent smooth path memory (a Duhem or
    Bouc-Wen element forgets its turning point over a travel, not a time); still while the
    input holds. The (N, J) outputs and the last (J,), from ``state`` and ``v_prev`` or rest."""
    v = np.asarray(v, dtype=float)
    T = np.asarray(travels_v, dtype=float)
    x0 = np.zeros(T.size) if state is None else np.asarray(state, dtype=float)
    A = np.exp(-np.abs(np.diff(v, prepend=v_prev))[:, None] / T)
    out = _affine_scan(A, (1.0 - A) * v[:, None], x0)
    return out, (out[-1].copy() if len(out) else x0.copy())


def direction_bank(X, travels_v, x_prev=None, state=None) -> tuple[np.ndarray, np.ndarray]:
    """Low-passes, over each channel's own travel, of its direction of motion:
    ``d_k = a_k d_{k-1} + (1 - a_k) sign(x_k - x_{k-1})``, ``a_k = exp(-|x_k - x_{k-1}| / T_j)``.
    The solution of a Duhem (Bouc-Wen, n = 1) element is a travel low-pass of the input plus
    one of its direction, so these are its basis: a smooth play that saturates exponentially
    after each reversal. Still while the channel holds.

    X : (N, C) channels; travels_v : (J,); x_prev : (C,) before sample 0 (rest: 0);
    state : (C, J). Returns the (N, C * J) outputs and the last (C, J)."""
    X = np.asarray(X, dtype=float)
    T = np.asarray(travels_v, dtype=float)
    n, c = X.shape
    x0 = np.zeros((c, T.size)) if state is None else np.asarray(state, dtype=float)
    prev = np.zeros(c) if x_prev is None else np.asarray(x_prev, dtype=float)
    d = np.diff(X, axis=0, prepend=prev[None, :])
    A = np.exp(-np.abs(d)[:, :, None] / T)
    out = _affine_scan(A, (1.0 - A) * np.sign(d)[:, :, None], x0)
    return out.reshape(n, -1), (out[-1].copy() if n else x0.copy())


def _affine_scan(A: np.ndarray, B: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """``x_k = A_k x_{k-1} + B_k`` along axis 0 from ``x0``, elementwise: a first-order
    recursion with varying coefficients is a prefix scan of affine maps
    (``(a2, b2) o (a1, b1) = (a2 a1, a2 b1 + b2)``), log2(N) vectorised passes."""
    A, B = A.copy(), B.copy()
    shift = 1
    while shift < A.shape[0]:
        B[shift:] = A[shift:] * B[:-shift] + B[shift:]
        A[shift:] = A[shift:] * A[:-shift]
        shift *= 2
    return A * x0 + B


#: Samples per block of the play scan: log2(64) passes inside the blocks, then one scan over
#: the blocks' composites, instead of log2(N) passes over the whole record.
PLAY_SCAN_BLOCK = 64


def _clip_scan(lo: np.ndarray, hi: np.ndarray) -> None:
    """In place along axis 0: clip ``k`` becomes the composite of clips 0..k (Hillis-Steele)."""
    a, b = np.empty_like(lo), np.empty_like(lo)
    shift, n = 1, lo.shape[0]
    while shift < n:
        m = n - shift
        np.minimum(np.maximum(lo[:m], lo[shift:], out=a[:m]), hi[shift:], out=a[:m])
        np.minimum(np.maximum(hi[:m], lo[shift:], out=b[:m]), hi[shift:], out=b[:m])
        lo[shift:], hi[shift:] = a[:m], b[:m]
        shift *= 2


def play_bank(X, thresholds, state=None) -> tuple[np.ndarray, np.ndarray]:
    """Play operators (paper Eq. 2) on several channels at once.

    X : (N, C) inputs; thresholds : (C, M) half-widths >= 0; state : (C, M) before sample 0.
    Returns the (N, C * M) outputs and the final (C, M) state.

    A play step is a clip, ``w_k = clip(w_{k-1}, x_k - r, x_k + r)``, and clips compose into
    clips (``clip(clip(w, a1, b1), a2, b2) = clip(w, clip(a1, a2, b2), clip(b1, a2, b2))``),
    so the whole run is a prefix scan of vectorised passes instead of N Python steps: within
    blocks of :data:`PLAY_SCAN_BLOCK` samples, then over the blocks. Only min and max: the
    result is exactly the step-by-step one.
    """
    X = np.asarray(X, dtype=float)
    r = np.asarray(thresholds, dtype=float)
    w0 = np.zeros_like(r) if state is None else np.array(state, dtype=float)
    n = X.shape[0]
    if n == 0:
        return np.zeros((0, r.size)), w0
    nb = -(-n // PLAY_SCAN_BLOCK)
    Xp = np.concatenate([X, np.repeat(X[-1:], nb * PLAY_SCAN_BLOCK - n, axis=0)])

    def blocks(edge):  # (block position, block, C, M)
        return edge.reshape(nb, PLAY_SCAN_BLOCK, *r.shape).swapaxes(0, 1).copy()

    lo, hi = blocks(Xp[:, :, None] - r), blocks(Xp[:, :, None] + r)
    _clip_scan(lo, hi)                         # from each block's start
    block_lo, block_hi = lo[-1].copy(), hi[-1].copy()
    _clip_scan(block_lo, block_hi)             # from sample 0 to each block's end
    starts = np.concatenate([w0[None], np.minimum(np.maximum(w0, block_lo[:-1]),
                                                  block_hi[:-1])])
    out = np.minimum(np.maximum(starts[None], lo), hi).swapaxes(0, 1)
    out = out.reshape(nb * PLAY_SCAN_BLOCK, *r.shape)[:n]
    return out.reshape(n, -1), out[-1].copy()


def place_knots(z: np.ndarray, n: int) -> np.ndarray:
    """Hinges of the output map at ``n`` quantiles of z (as many samples between any two)."""
    return np.quantile(z, np.linspace(0, 1, n + 2)[1:-1])


def hinge_basis(z: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """Columns z, max(z - k_j, 0): a continuous piecewise-linear map's basis."""
    return np.column_stack([z, np.maximum(z[:, None] - knots[None, :], 0.0)])


def hinge_slope(z: np.ndarray, knots: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """dg/dz of the piecewise-linear map at ``z``."""
    return coef[0] + (z[:, None] > knots[None, :]).astype(float) @ coef[1:]


def _beyond_counts(z: np.ndarray, rows: np.ndarray, knots: np.ndarray, block_rows: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Independent samples (:func:`independent_samples`) of z above and below each knot."""
    def count(beyond: np.ndarray) -> np.ndarray:
        return np.array([independent_samples(rows[b], block_rows) for b in beyond.T])

    return count(z[:, None] > knots[None, :]), count(z[:, None] < knots[None, :])


def determined_edge_slopes(z: np.ndarray, rows: np.ndarray, knots: np.ndarray,
                           coef: np.ndarray, block_rows: float, min_samples: int
                           ) -> tuple[float, float]:
    """The slopes the map goes on at below and above the range of ``z`` (its inputs on the
    fit's ``rows``): at each end, that of the outermost segment whose hinge has z beyond it
    in at least ``min_samples`` independent samples (:func:`independent_samples`, for a
    residual correlated over ``block_rows``). A hinge beyond which z goes on one visit only
    (the joint fit moves z after the hinges are placed, and one can end just inside the
    range's end) has a slope change fitted to that visit, hundreds of mm per unit on a
    handful of rows, which a run beyond the range would follow."""
    above, below = _beyond_counts(z, rows, knots, block_rows)
    upper = float(coef[0] + coef[1:][above >= min_samples].sum())
    lower = float(coef[0] + coef[1:][below < min_samples].sum())
    return lower, upper


class HingeMap:
    """The output map as a continuous piecewise-linear function of z (hinges at the knots)."""

    name = "linear"
    basis = staticmethod(hinge_basis)
    slope = staticmethod(hinge_slope)
    edge_slopes = staticmethod(determined_edge_slopes)
    knots = staticmethod(place_knots)

    @staticmethod
    def identity(knots: np.ndarray) -> np.ndarray:
        """The coefficients of ``g(z) = z``: the joint fit's start."""
        return np.r_[1.0, np.zeros(knots.size)]


class QuadraticSplineMap:
    """The output map as a quadratic spline of z: B-splines of degree 2 (SciPy's) on the
    knots, the outer two the ends of z's range at the fit's start, continued straight beyond
    them; its slope is continuous. An IPMC's bending stiffens smoothly with the strain (the
    negative side of the simulated strip by 3 per V); hinges approximate that curvature with
    kinks, and near 0 V a kink trades with a dead zone's width. B-splines, each nonzero over
    three knot spans only, stay well conditioned where the knots crowd (a record that dwells
    at rest): truncated powers ``max(z - k, 0)^2`` there are nearly collinear, and their
    fits converge several times slower."""

    name = "quadratic"

    @staticmethod
    def _vector(knots: np.ndarray) -> np.ndarray:
        """The B-splines' knot vector: the end knots repeated to degree + 1."""
        return np.r_[[knots[0]] * 2, knots, [knots[-1]] * 2]

    @classmethod
    def _slopes(cls, x: np.ndarray, knots: np.ndarray) -> np.ndarray:
        """Each B-spline's derivative at ``x`` (within the end knots), (x.size, knots + 1)."""
        return BSpline(cls._vector(knots), np.eye(knots.size + 1), 2).derivative()(x)

    @classmethod
    def basis(cls, z: np.ndarray, knots: np.ndarray) -> np.ndarray:
        lo, hi = knots[0], knots[-1]
        zc = np.clip(z, lo, hi)
        B = BSpline.design_matrix(zc, cls._vector(knots), 2).toarray()
        out = zc != z
        if out.any():   # straight on beyond the end knots
            ends = cls._slopes(np.array([lo, hi]), knots)
            B[out] += (z[out] - zc[out])[:, None] * np.where((z[out] < lo)[:, None],
                                                              ends[0], ends[1])
        return B

    @classmethod
    def slope(cls, z: np.ndarray, knots: np.ndarray, coef: np.ndarray) -> np.ndarray:
        return cls._slopes(np.clip(z, knots[0], knots[-1]), knots) @ coef

    @classmethod
    def edge_slopes(cls, z: np.ndarray, rows: np.ndarray, knots: np.ndarray, coef: np.ndarray,
                    block_rows: float, min_samples: int) -> tuple[float, float]:
        """The slopes beyond the range of ``z``: the spline's slope at the range's ends, or,
        as :func:`determined_edge_slopes`, at the outermost inner knot beyond which z goes in
        fewer than ``min_samples`` independent samples (its curvature there is fitted to a
        visit or two)."""
        inner = knots[1:-1]
        above, below = _beyond_counts(z, rows, inner, block_rows)
        hi = min([float(z.max())] + list(inner[above < min_samples]))
        lo = max([float(z.min())] + list(inner[below < min_samples]))
        s = cls.slope(np.array([lo, hi]), knots, coef)
        return float(s[0]), float(s[1])

    @staticmethod
    def knots(z: np.ndarray, n: int) -> np.ndarray:
        """Up to ``n`` inner knots at quantiles of z (:func:`place_knots`) between its ends,
        each once: where z rests at one value for a tenth of the rows, quantiles coincide, and
        a B-spline over a repeated knot would be zero on every row."""
        return np.unique(np.r_[z.min(), place_knots(z, n), z.max()])

    @classmethod
    def identity(cls, knots: np.ndarray) -> np.ndarray:
        """The coefficients of ``g(z) = z`` (the Greville abscissae): the joint fit's start."""
        t = cls._vector(knots)
        return (t[1:-2] + t[2:-1]) / 2.0


#: The output maps by name (``GeneralizedPI(map_basis=...)``).
MAP_BASES = {m.name: m for m in (HingeMap, QuadraticSplineMap)}


def hinge_map(z: np.ndarray, knots: np.ndarray, coef: np.ndarray,
              z_range: tuple[float, float] = (-math.inf, math.inf),
              edge_slopes: tuple[float, float] | None = None, basis=HingeMap) -> np.ndarray:
    """The map ``g(z)`` of ``basis`` (:data:`MAP_BASES`), continued beyond ``z_range`` (the
    range of z it was fitted on) straight at ``edge_slopes`` (below, above; None: its slope
    at that range's edge): no data fixes the slope change at a hinge beyond it, so its
    coefficient is whatever the optimiser left there, and a free run that leaves the range
    would follow it."""
    lo, hi = z_range
    if lo == -math.inf and hi == math.inf:
        return basis.basis(z, knots) @ coef
    zc = np.clip(z, lo, hi)
    g = basis.basis(zc, knots) @ coef
    out = zc != z   # the slopes only where the run left the range (a free run's hot path)
    if edge_slopes is None:
        slope = basis.slope(zc[out], knots, coef)
    else:
        slope = np.where(z[out] < lo, edge_slopes[0], edge_slopes[1])
    g[out] += slope * (z[out] - zc[out])
    return g


def delayed(u: np.ndarray, samples: int, history=None) -> np.ndarray:
    """``u`` delayed by whole ``samples``, the first ones from ``history`` (oldest first) or 0."""
    if samples <= 0:
        return u
    past = np.zeros(samples) if history is None else np.asarray(history, float)[-samples:]
    past = np.concatenate([np.zeros(samples - past.size), past])
    return np.concatenate([past, u])[:u.size]


def estimate_delay(u: np.ndarray, y: np.ndarray, dt_s: float, taus_s, max_samples: int) -> int:
    """Transport delay (samples) whose delayed input best explains ``y`` by least squares
    through the relaxation bank (a linear model: the delay shows in its phase); rows where
    ``y`` is NaN (not measured) are left out."""
    best, best_sse = 0, math.inf
    obs = np.isfinite(y)
    for d in range(max(0, int(max_samples)) + 1):
        ud = delayed(u, d)
        X = np.column_stack([ud, lowpass_bank(ud, taus_s, dt_s)[0], np.ones(u.size)])[obs]
        coef = np.linalg.lstsq(X, y[obs], rcond=None)[0]
        # lstsq gives no residual when rank-deficient
        sse = float(np.sum((X @ coef - y[obs]) ** 2))
        if sse < best_sse:
            best, best_sse = d, sse
    return best


def dead_zone(u: np.ndarray, width_v: float) -> np.ndarray:
    """``u`` with magnitudes below ``width_v`` removed: sign(u) max(|u| - w, 0)."""
    if width_v <= 0:
        return u
    return np.sign(u) * np.maximum(np.abs(u) - width_v, 0.0)


@dataclass(frozen=True)
class GpiState:
    """The model's state after a sample: charge v (V), relaxations (J,), plays (C, M), the
    samples run so far (the drift's clock), path memory (T,), output relaxations (O,) and
    direction memory (C, D)."""

    v: float
    relax: np.ndarray
    plays: np.ndarray
    k: int = 0
    travel: np.ndarray | None = None
    out_relax: np.ndarray | None = None
    direction: np.ndarray | None = None


@dataclass(frozen=True)
class CvResult:
    """Blocked cross-validation of the ridge weight: free-run RMSE (output units) per alpha."""

    alphas: tuple[float, ...]
    rmse: tuple[float, ...]
    alpha: float
    n_folds: int

    def as_dict(self) -> dict:
        return {"alphas": list(self.alphas), "rmse": list(self.rmse), "alpha": self.alpha,
                "n_folds": self.n_folds}


class GeneralizedPI:
    """Rate-dependent generalised Prandtl-Ishlinskii model, input u (V) -> output y (mm).

    Parameters
    ----------
    memory_taus_s : sequence of float
        Time constants of the relaxation bank (s); those longer than the record / 3 are
        dropped at fit (``memory_taus_s_`` keeps the rest).
    play_channels : int
        Plays act on the charge and the ``play_channels - 1`` fastest relaxations.
    threshold_shares : sequence of float
        Play thresholds as shares of max |u| of the identification record (of half each
        play channel's swing with ``channel_thresholds``).
    channel_thresholds : bool
        Each play channel's thresholds from its own swing on the identification record
        (:meth:`_play_thresholds`) instead of all from max |u|.
    n_knots : int
        Knots of the output map.
    map_basis : str
        The output map between knots (:data:`MAP_BASES`): ``"linear"`` (hinges) or
        ``"quadratic"`` (a quadratic spline, slope continuous: a bending that stiffens
        smoothly).
    rate_limit : bool
        Fit the ion-current limit of stage 1 (False: v = u, no charging stage).
    alphas : sequence of float
        Ridge weights tried by blocked cross-validation (free-run error).
    n_folds : int
        Blocks of the cross-validation.
    row_step : int
        Fit on every ``row_step``-th sample (the states run at the full rate).
    max_nfev : int
        Trust-region iterations of each joint fit (at most; it stops earlier once converged).
        With the direction memory's sharper features the fit needs several tens.
    max_delay_s : float
        Longest transport delay searched (s; 0: none). The delay the linear part prefers is
        fitted beside no delay, and the blocked free-run CV keeps the better: a least-squares
        delay estimate alone takes a charging lag for a delay (3 samples on the simulated
        IPMC, which has none).
    dt_s : float
        Sample period (s) of the data the model is fitted on and run at.
    path_memory_v, direction_memory_v : sequence of float
        Travels (V) of the path-memory channels (on the charge) and of the direction-memory
        channels; () leaves them out.
    start_tau_factors : sequence of float
        Charging time constants tried as the joint fit's start, as multiples of the first
        guess (30 samples); the one whose linear fit of the rest explains most is kept.
    direction_channels : int
        Direction memory acts on the charge and the ``direction_channels - 1`` fastest
        relaxations (the strain that drives the polymer's hysteresis). Slower channels seldom
        reverse, so their direction memory is a long-lived state a record pins down poorly.
    output_taus_s : sequence of float
        Relaxations of the charge added after the map (creep); () by default.
    output_rate : bool
        The charging current ``dv/dt`` added after the map with a fitted gain
        (``output_coef_[0]``, mm per V/s): rate-dependent bending.
    warm_start : bool
        A fitted model's ``fit`` keeps its learned structure (relaxations kept, thresholds,
        delay, feature scaling, map knots) and fits the continuous parameters on from where
        they are, with a third of ``max_nfev``: a refit on a longer record of the same rig
        (the whole record after a comparison on its first part).
    progress : callable, optional
        ``progress(text)`` after each stage of the fit.

    Attributes
    ----------
    delay_samples_ : int
        Transport delay, samples.
    delay_scores_ : tuple of (int, float)
        The delays fitted and their CV free-run RMSE.
    charge_tau_s_, slew_v_per_s_ : float
        Stage 1 (``slew_v_per_s_`` inf without ``rate_limit``).
    memory_taus_s_ : tuple of float
    thresholds_ : ndarray, shape (play_channels, n_thresholds), V
    feature_mean_, feature_scale_ : ndarray, shape (p,)
    weights_ : ndarray, shape (p + 1,)
        Weights of the standardised features, the last one a constant.
    knots_ : ndarray, shape (n_knots,)
    map_coef_ : ndarray, shape (n_knots + 1,)
    map_range_ : tuple of float
        The map input's range on the fit's rows; beyond it the map goes on at its edge slope.
    cv_ : CvResult
    train_rmse_ : float
    """

    def __init__(self, memory_taus_s=DEFAULT_MEMORY_TAUS_S, play_channels: int = 5,
                 threshold_shares=DEFAULT_THRESHOLD_SHARES, n_knots: int = 10,
                 rate_limit: bool = True, alphas=DEFAULT_ALPHAS, n_folds: int = 5,
                 row_step: int = 2, max_nfev: int = 60, max_delay_s: float = 0.3,
                 dt_s: float = 0.01, delay_s: float | None = None, dead_zone_v: float = 0.0,
                 rate_channel: bool = False, drift: bool = False,
                 path_memory_v=DEFAULT_PATH_MEMORY_V, output_taus_s=(),
                 direction_memory_v=DEFAULT_DIRECTION_MEMORY_V, direction_channels: int = 3,
                 start_tau_factors=INITIAL_TAU_FACTORS, warm_start: bool = False,
                 output_rate: bool = False, channel_thresholds: bool = False,
                 map_basis: str = "linear", progress=None):
        self.memory_taus_s = tuple(float(t) for t in memory_taus_s)
        self.play_channels = play_channels
        self.threshold_shares = tuple(float(s) for s in threshold_shares)
        self.n_knots = n_knots
        self.rate_limit = rate_limit
        self.alphas = tuple(float(a) for a in alphas)
        self.n_folds = n_folds
        self.row_step = row_step
        self.max_nfev = max_nfev
        self.max_delay_s = float(max_delay_s)
        self.dt_s = float(dt_s)
        self.delay_s = None if delay_s is None else float(delay_s)
        self.dead_zone_v = float(dead_zone_v)
        self.rate_channel = bool(rate_channel)
        self.drift = bool(drift)
        self.path_memory_v = tuple(float(t) for t in path_memory_v)
        self.output_taus_s = tuple(float(t) for t in output_taus_s)
        self.direction_memory_v = tuple(float(t) for t in direction_memory_v)
        self.direction_channels = int(direction_channels)
        self.start_tau_factors = tuple(float(f) for f in start_tau_factors)
        self.warm_start = bool(warm_start)
        self.output_rate = bool(output_rate)
        self.channel_thresholds = bool(channel_thresholds)
        self.map_basis = str(map_basis)
        self.progress = progress
        self.weights_ = None
        self.map_range_ = (-math.inf, math.inf)
        self.map_edge_slopes_ = None
        self.neutral_output_stage()

    def neutral_output_stage(self) -> None:
        """Output stage off: negative-side gain 1, no drift, no limit."""
        self.negative_gain_, self.limit_mm_ = 1.0, math.inf
        self.drift_gain_per_s_, self.drift_offset_mm_per_s_ = 0.0, 0.0
        self.output_coef_ = np.zeros(self.n_output_channels)

    @property
    def _map(self):
        """The output map's basis (:data:`MAP_BASES`)."""
        return MAP_BASES[self.map_basis]

    @property
    def n_output_channels(self) -> int:
        """Channels added after the map: the charging current (first, with ``output_rate``),
        then one per output relaxation."""
        return int(self.output_rate) + len(self.output_taus_s)

    def _outputs_of(self, v: np.ndarray) -> np.ndarray:
        """The channels added to the bending after the map, (N, n_output_channels), of the
        charge ``v``: the charging current (rate-dependent bending) and the charge's slow
        relaxations (creep), each linear in the charge."""
        relax = lowpass_bank(v, self.output_taus_s, self.dt_s)[0]
        if not self.output_rate:
            return relax
        return np.column_stack([self._charging_current(v), relax])

    # -- features ----------------------------------------------------------------------------
    def _charge(self, u: np.ndarray, theta) -> np.ndarray:
        u = delayed(dead_zone(u, self.dead_zone_v), self.delay_samples_)
        if not self.rate_limit:
            return u
        return rate_limited_charge(u, math.exp(theta[0]), math.exp(theta[1]), self.dt_s)

    def _raw_features(self, u: np.ndarray, theta) -> np.ndarray:
        return self._features_of(self._charge(u, theta))

    def _features_of(self, v: np.ndarray) -> np.ndarray:
        """:meth:`_raw_features` of the charge ``v``."""
        relax, _ = lowpass_bank(v, self.memory_taus_s_, self.dt_s)
        ch = np.column_stack([v, relax])
        plays, _ = play_bank(ch[:, :self.thresholds_.shape[0]], self.thresholds_)
        travel, _ = travel_bank(v, self.path_memory_v)
        direction, _ = direction_bank(ch[:, :self.n_direction_channels],
                                      self.direction_memory_v)
        return np.hstack([ch, plays, travel, direction, self._extra_channels(v)])

    def _charging_current(self, v: np.ndarray, v_prev=None) -> np.ndarray:
        """dv/dt (V/s) of charges ``v``, shape (N,); ``v_prev``: each one's previous charge
        (None: ``v`` is a run from rest)."""
        prev = np.concatenate([[0.0], v[:-1]]) if v_prev is None else v_prev
        return (v - prev) / self.dt_s

    def _extra_channels(self, v: np.ndarray, v_prev=None) -> np.ndarray:
        """The charging current as a channel inside the map, shape (N, 0 or 1)."""
        if not self.rate_channel:
            return np.zeros((v.size, 0))
        return self._charging_current(v, v_prev)[:, None]

    @property
    def n_direction_channels(self) -> int:
        """Channels the direction memory acts on (the charge first), 0 without it."""
        if not self.direction_memory_v:
            return 0
        return max(0, min(self.direction_channels, 1 + len(self.memory_taus_s_)))

    @property
    def n_extra_channels(self) -> int:
        """Channels beside the charge, relaxations and plays."""
        return int(self.rate_channel)

    def output_stage(self, y: np.ndarray, t_s, added=0.0) -> np.ndarray:
        """The map's output ``y`` (mm) at times ``t_s`` (s since the start) through the
        negative-side gain, the drift, the ``added`` output relaxations and the soft limit."""
        if self.negative_gain_ != 1.0:
            y = np.where(y < 0, self.negative_gain_ * y, y)
        if self.drift_gain_per_s_ != 0.0 or self.drift_offset_mm_per_s_ != 0.0:
            y = y * (1.0 + self.drift_gain_per_s_ * t_s) + self.drift_offset_mm_per_s_ * t_s
        y = y + added
        if math.isfinite(self.limit_mm_):
            y = self.limit_mm_ * np.tanh(y / self.limit_mm_)
        return y

    def _design_of(self, v: np.ndarray) -> np.ndarray:
        F = (self._features_of(v) - self.feature_mean_) / self.feature_scale_
        return np.column_stack([F, np.ones(len(F))])

    def _design_and_outputs(self, u: np.ndarray, theta) -> tuple[np.ndarray, np.ndarray]:
        """The map's design matrix and the output channels (:meth:`_outputs_of`) from one
        run of the charging recursion (the fit's costliest step)."""
        v = self._charge(u, theta)
        return self._design_of(v), self._outputs_of(v)

    @property
    def _theta(self) -> np.ndarray:
        if not self.rate_limit:
            return np.zeros(2)
        return np.log([self.charge_tau_s_, self.slew_v_per_s_])

    def _check_params(self, n: int) -> None:
        if int(self.play_channels) < 1 or int(self.n_knots) < 0 or int(self.n_folds) < 2:
            raise ValueError("play_channels must be >= 1, n_knots >= 0 and n_folds >= 2")
        if self.map_basis not in MAP_BASES:
            raise ValueError(f"map_basis must be one of {sorted(MAP_BASES)}, got "
                             f"{self.map_basis!r}")
        if not self.threshold_shares or min(self.threshold_shares) <= 0:
            raise ValueError("threshold_shares must be positive shares of max |u|")
        if not (self.dt_s > 0 and math.isfinite(self.dt_s)):
            raise ValueError(f"dt_s must be a positive sample period (s), got {self.dt_s}")
        if n < 20 * self.n_folds:
            raise ValueError(f"{n} samples are too few to identify and cross-validate a "
                             f"GPI model (at least {20 * self.n_folds})")

    # -- fitting -----------------------------------------------------------------------------
    def fit(self, u, y) -> GeneralizedPI:
        """Fit to input ``u`` (V) and output ``y`` (mm), both shape (N,); returns self.

        A NaN in ``y`` marks a row whose output was not measured (a gap between records, a
        row kept for judging): the model runs through it and is fitted on the others."""
        u, y = as_signal("u", u), as_signal("y", y, allow_nan=True)
        same_length(u=u, y=y)
        if np.any(np.isinf(y)):
            raise ValueError("y has infinite values; mark rows not measured with NaN")
        self._check_params(int(np.isfinite(y).sum()))
        if np.ptp(u) == 0.0:
            raise ValueError("u is constant; a hysteresis model needs a varying input")
        t0 = time.perf_counter()
        span_s = u.size * self.dt_s
        if self.warm_start and self.weights_ is not None:
            return self._fit_on(u, y, span_s, t0)
        self.memory_taus_s_ = tuple(t for t in self.memory_taus_s
                                    if t * MIN_SPANS_PER_TAU <= span_s and t > self.dt_s)
        n_play = min(int(self.play_channels), 1 + len(self.memory_taus_s_))
        self.thresholds_ = self._play_thresholds(u, n_play)
        # a delay is a candidate when the linear part prefers one; the whole model's blocked
        # free-run CV decides (a charging lag also looks like a delay to a linear model)
        if self.delay_s is None:
            d_lin = estimate_delay(dead_zone(u, self.dead_zone_v), y, self.dt_s,
                                   self.memory_taus_s_, int(round(self.max_delay_s / self.dt_s)))
            delays = sorted({0, d_lin})
        else:
            delays = [int(round(self.delay_s / self.dt_s))]
        self.neutral_output_stage()
        x = self._fit_delays(u, y, span_s, delays, t0)
        if self.cv_.alpha != self.alphas[0]:
            _, bounds = self._initial_theta(u, span_s)
            x = self._joint_fit(u, y, x, bounds, self.cv_.alpha, max(5, self.max_nfev // 3))
        self._unpack(x)
        self._learned_on(u, y)
        self.fit_seconds_ = time.perf_counter() - t0
        return self

    def _play_thresholds(self, u: np.ndarray, n_play: int) -> np.ndarray:
        """The plays' thresholds, (n_play, shares): ``threshold_shares`` of max |u| on every
        channel, or with ``channel_thresholds`` of half each channel's swing (the input
        through the dead zone, and its relaxations). A play reverses only where its channel
        travels more than twice its threshold; a slower channel swings less, and its plays
        above half the swing move once and stay: a step in time whose weight no loop fixes,
        which takes up a slow trend of the record and moves again (far off) where a run drives
        beyond the record's range."""
        shares = np.array(self.threshold_shares)
        if not self.channel_thresholds:
            return np.tile(shares * float(np.max(np.abs(u))), (n_play, 1))
        v = dead_zone(u, self.dead_zone_v)
        relax, _ = lowpass_bank(v, self.memory_taus_s_[:n_play - 1], self.dt_s)
        half_swing = 0.5 * np.ptp(np.column_stack([v, relax])[:, :n_play], axis=0)
        return half_swing[:, None] * shares[None, :]

    def _fit_on(self, u, y, span_s: float, t0: float) -> GeneralizedPI:
        """Warm start: the continuous parameters fitted on from the learned ones, the ridge
        weight kept unless the blocked CV on this record prefers another."""
        _, bounds = self._initial_theta(u, span_s)
        nfev = max(5, self.max_nfev // 3)
        alpha = self.cv_.alpha
        x = self._joint_fit(u, y, self._packed(), bounds, alpha, nfev)
        self.cv_ = self._cross_validate(u, y, x)
        if self.cv_.alpha != alpha:
            x = self._joint_fit(u, y, x, bounds, self.cv_.alpha, nfev)
        self._unpack(x)
        self._say(f"refitted on this record from the parameters learned before: CV free-run RMSE "
                  f"{min(self.cv_.rmse):.4g} ({time.perf_counter() - t0:.1f} s)")
        self._learned_on(u, y)
        self.fit_seconds_ = time.perf_counter() - t0
        return self

    def _packed(self) -> np.ndarray:
        """The learned parameters as the joint fit's vector (the inverse of ``_unpack``)."""
        drift = ([self.drift_gain_per_s_, self.drift_offset_mm_per_s_] if self.drift else [])
        return np.concatenate([self._theta, self.weights_, self.map_coef_, drift,
                               self.output_coef_])

    def _fit_delays(self, u, y, span_s: float, delays: list[int], t0: float) -> np.ndarray:
        """The joint fit at the delay of lowest blocked-CV free-run error. The first delay
        (no delay, when the linear part proposes one) is fitted in full; each other starts
        from that fit, its feature scaling and knots kept, and gets a third of the iterations:
        the delays differ in the input's timing, which those iterations settle. Fits stopped
        early at the same budget would favour the one that converges faster, not the better
        model."""
        self.delay_samples_ = delays[0]
        x, cv = self._fit_at_delay(u, y, span_s, self.max_nfev)
        fits = [(min(cv.rmse), delays[0], x, cv)]
        self._say(f"delay {delays[0]} samples: CV free-run RMSE {min(cv.rmse):.4g} "
                  f"({time.perf_counter() - t0:.1f} s)")
        _, bounds = self._initial_theta(u, span_s)
        for d in delays[1:]:
            self.delay_samples_ = d
            xd = self._joint_fit(u, y, fits[0][2], bounds, self.alphas[0],
                                 max(5, self.max_nfev // 3))
            cvd = self._cross_validate(u, y, xd)
            fits.append((min(cvd.rmse), d, xd, cvd))
            self._say(f"delay {d} samples, from the fit at {delays[0]}: CV free-run RMSE "
                      f"{min(cvd.rmse):.4g} ({time.perf_counter() - t0:.1f} s)")
        self.delay_scores_ = tuple((f[1], f[0]) for f in fits)
        _, self.delay_samples_, x, self.cv_ = min(fits, key=lambda f: f[0])
        return x

    def _fit_at_delay(self, u, y, span_s: float, max_nfev: int):
        """The joint fit at ``delay_samples_`` and the smallest ridge weight (at most
        ``max_nfev`` iterations), and the blocked CV of the ridge weight around it; sets the
        feature scaling and the map's knots."""
        theta0, bounds = self._initial_theta(u, span_s)
        _, theta0, self.feature_mean_, self.feature_scale_, w0, self.knots_ = \
            self._best_start(u, y, theta0, bounds)
        coef0 = np.zeros(self.knots_.size + 1 + (2 if self.drift else 0)
                         + self.n_output_channels)
        coef0[:self.knots_.size + 1] = self._map.identity(self.knots_)
        x = self._joint_fit(u, y, np.concatenate([theta0, w0, coef0]), bounds,
                            self.alphas[0], max_nfev)
        return x, self._cross_validate(u, y, x)

    def _best_start(self, u, y, theta0: np.ndarray, bounds):
        """The joint fit's start: of the charging time constants ``start_tau_factors`` x the
        first guess (the slew limit scaled inversely: the same voltage swing), the one whose
        linear fit of the rest explains most; a (variance, theta, ...) as ``_linear_start``."""
        if not self.rate_limit:
            return self._linear_start(u, y, theta0)
        lo, hi = np.asarray(bounds[0]) + 1e-9, np.asarray(bounds[1]) - 1e-9
        starts = [self._linear_start(u, y, np.clip(theta0 + math.log(f) * np.array([1.0, -1.0]),
                                                   lo, hi))
                  for f in self.start_tau_factors or (1.0,)]
        return min(starts, key=lambda st: st[0])

    def _linear_start(self, u, y, theta):
        """The weights and map a linear fit gives at ``theta``, and its residual variance:
        features, then the map's knots at quantiles of the linear z and its hinges by least
        squares. Returns (variance, theta, feature mean, feature scale, w, knots)."""
        obs = np.isfinite(y)
        F = self._raw_features(u, theta)[obs]
        y = y[obs]
        mean, std = F.mean(axis=0), F.std(axis=0)
        scale = np.where(std > 0, std, 1.0)
        A = np.column_stack([(F - mean) / scale, np.ones(y.size)])
        w = np.linalg.lstsq(A, y, rcond=None)[0]
        z = A @ w
        knots = self._map.knots(z, int(self.n_knots))
        B = np.column_stack([self._map.basis(z, knots), np.ones(y.size)])
        resid = y - B @ np.linalg.lstsq(B, y, rcond=None)[0]
        return float(np.var(resid)), theta, mean, scale, w, knots

    def _say(self, text: str) -> None:
        if self.progress is not None:
            self.progress(text)

    def _initial_theta(self, u: np.ndarray, span_s: float):
        tau0 = min(INITIAL_TAU_SAMPLES * self.dt_s, span_s / 10)
        u_max = float(np.max(np.abs(u)))
        slew0 = u_max / tau0
        lo = [math.log(self.dt_s), math.log(0.01 * slew0)]
        hi = [math.log(span_s / 10), math.log(1e4 * u_max / self.dt_s)]
        return np.log([tau0, slew0]), (lo, hi)

    def _unpack(self, x: np.ndarray) -> None:
        p = self.feature_mean_.size + 1
        if self.rate_limit:
            self.charge_tau_s_, self.slew_v_per_s_ = (float(v) for v in np.exp(x[:2]))
        else:
            self.charge_tau_s_, self.slew_v_per_s_ = 0.0, math.inf
        k = self.knots_.size + 1
        self.weights_ = np.array(x[2:2 + p])
        self.map_coef_ = np.array(x[2 + p:2 + p + k])
        if self.drift:
            self.drift_gain_per_s_, self.drift_offset_mm_per_s_ = (float(v) for v in
                                                                   x[2 + p + k:4 + p + k])
        self.output_coef_ = np.array(x[x.size - self.n_output_channels:])

    def _learned_on(self, u: np.ndarray, y: np.ndarray) -> None:
        """The map input's range on the rows of ``u`` the fit measured (``y`` finite), the
        slopes beyond it (:func:`determined_edge_slopes`, a hinge determined by z beyond it
        in :data:`EDGE_INDEPENDENT_SAMPLES` independent samples of the fit's residual), and
        the fit's RMSE there, from one free run."""
        A, X = self._design_and_outputs(u, self._theta)
        z = A @ self.weights_
        seen = np.isfinite(y)
        self.map_range_ = (float(z[seen].min()), float(z[seen].max()))
        e = (self._output_of(z, X) - y)[seen]
        self.train_rmse_ = float(np.sqrt(np.mean(e ** 2)))
        block_rows = e.size / effective_samples(e) if np.ptp(e) > 0 else 1.0
        self.map_edge_slopes_ = self._map.edge_slopes(
            z[seen], np.flatnonzero(seen), self.knots_, self.map_coef_, block_rows,
            EDGE_INDEPENDENT_SAMPLES)

    def _joint_fit(self, u, y, x0, bounds, alpha: float, max_nfev: int | None = None
                   ) -> np.ndarray:
        """theta, w and the map's coefficients by trust-region least squares, ridge ``alpha``
        on the feature weights (not on the constant)."""
        rows = np.arange(0, u.size, max(1, int(self.row_step)))
        rows = rows[np.isfinite(y[rows])]
        p, kn, basis = self.feature_mean_.size + 1, self.knots_, self._map
        k = kn.size + 1
        t = rows * self.dt_s
        ridge = math.sqrt(alpha * rows.size)
        n_theta = 2 if self.rate_limit else 0
        n_out = self.n_output_channels
        cache: dict = {}

        def design(theta):
            key = tuple(np.round(theta, 12))
            if key not in cache:
                cache.clear()
                A, X = self._design_and_outputs(u, theta)
                cache[key] = (A[rows], X[rows])
            return cache[key]

        def split(x):
            g, o = x[2 + p + k:4 + p + k] if self.drift else (0.0, 0.0)
            return x[:2], x[2:2 + p], x[2 + p:2 + p + k], g, o, x[x.size - n_out:]

        def output(A, X, w, c, g, o, e):
            return (basis.basis(A @ w, kn) @ c) * (1.0 + g * t) + o * t + X @ e

        def residual(x):
            th, w, c, g, o, e = split(x)
            return np.concatenate([output(*design(th), w, c, g, o, e) - y[rows], ridge * w[:-1]])

        def jacobian(x):
            th, w, c, g, o, e = split(x)
            A, X = design(th)
            z = A @ w
            base = basis.basis(z, kn) @ c
            scale = (1.0 + g * t)[:, None]
            now = output(A, X, w, c, g, o, e)
            cols = []
            for i in range(n_theta):  # finite differences through the charging recursion
                t2 = th.copy()
                t2[i] += 1e-4
                A2, X2 = (m[rows] for m in self._design_and_outputs(u, t2))
                cols.append((output(A2, X2, w, c, g, o, e) - now) / 1e-4)
            cols += [np.zeros(rows.size)] * (2 - n_theta)
            drift = [np.column_stack([base * t, t])] if self.drift else []
            top = np.hstack([np.column_stack(cols), A * basis.slope(z, kn, c)[:, None] * scale,
                             basis.basis(z, kn) * scale] + drift + [X])
            bottom = np.zeros((p - 1, top.shape[1]))
            bottom[:, 2:p + 1] = ridge * np.eye(p - 1)
            return np.vstack([top, bottom])

        lo = np.full(x0.size, -np.inf)
        hi = np.full(x0.size, np.inf)
        if self.rate_limit:
            lo[:2], hi[:2] = bounds
        else:
            lo[:2], hi[:2] = -1.0, 1.0  # unused: no charging stage
        x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)
        res = least_squares(residual, x0, jac=jacobian, bounds=(lo, hi), method="trf",
                            x_scale="jac", max_nfev=int(max_nfev or self.max_nfev))
        return res.x

    def _cross_validate(self, u, y, x) -> CvResult:
        """Ridge weight by blocked K-fold CV: the map linearised at the joint fit (one
        Gauss-Newton step in w per alpha and fold), scored on the held-out block's free run."""
        p, k = self.feature_mean_.size + 1, self.knots_.size + 1
        A, X = self._design_and_outputs(u, x[:2])
        w, c = x[2:2 + p], x[2 + p:2 + p + k]
        n_out = self.n_output_channels
        if n_out:  # judged on the record with the fitted output stage undone
            y = y - X @ x[x.size - n_out:]
        if self.drift:
            g, o = x[2 + p + k:4 + p + k]
            t = np.arange(u.size) * self.dt_s
            y = (y - o * t) / np.maximum(1.0 + g * t, 1e-3)
        z = A @ w
        slope = self._map.slope(z, self.knots_, c)
        target = y - self._map.basis(z, self.knots_) @ c + slope * z
        obs = np.isfinite(y)
        # folds of equal measured rows, each contiguous in time
        at = np.flatnonzero(obs)
        cuts = np.linspace(0, at.size, int(self.n_folds) + 1).round().astype(int)
        edges = np.append(at[cuts[:-1]], u.size)
        sse = np.zeros(len(self.alphas))
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            train = obs.copy()
            train[a:b] = False
            D = A[train] * slope[train, None]
            U, s, Vt = np.linalg.svd(D, full_matrices=False)
            proj = U.T @ target[train]
            held = obs[a:b]
            for i, alpha in enumerate(self.alphas):
                # the constant is penalised too, lightly: alpha * n is tiny beside its s^2
                wa = Vt.T @ (s / (s ** 2 + alpha * train.sum()) * proj)
                sse[i] += np.sum((self._map.basis(A[a:b][held] @ wa, self.knots_) @ c
                                  - y[a:b][held]) ** 2)
        rmse = np.sqrt(sse / at.size)
        best = int(np.argmin(rmse))
        return CvResult(self.alphas, tuple(float(v) for v in rmse), self.alphas[best],
                        int(self.n_folds))

    # -- use ---------------------------------------------------------------------------------
    def simulate(self, u) -> np.ndarray:
        """Free-run output (mm), shape (N,), from input ``u`` (V), every state from rest."""
        check_fitted(self, "weights_")
        u = as_signal("u", u)
        A, X = self._design_and_outputs(u, self._theta)
        return self._output_of(A @ self.weights_, X)

    def _output_of(self, z: np.ndarray, X: np.ndarray) -> np.ndarray:
        """The free run's output (mm) from the map's input ``z`` and the output channels."""
        added = X @ self.output_coef_ if self.n_output_channels else 0.0
        return self.output_stage(hinge_map(z, self.knots_, self.map_coef_, self.map_range_,
                                           self.map_edge_slopes_, self._map),
                                 np.arange(z.size) * self.dt_s, added)

    def predict(self, u, y=None) -> np.ndarray:
        """One-step prediction; the model has no output feedback, so this equals simulate."""
        return self.simulate(u)

    @property
    def max_lag_(self) -> int:
        """Measured samples a free run needs to start: none."""
        return 0

    @property
    def history_samples(self) -> int:
        """Past samples a stepper going on from a history needs: the delay and five of its
        slowest time constants (its relaxations then within 0.7 % of those of an uninterrupted
        run; the plays keep what the history shows of their reversal points)."""
        check_fitted(self, "weights_")
        slow = max(self.memory_taus_s_ + (self.charge_tau_s_,))
        return max(1, math.ceil(5.0 * slow / self.dt_s)) + int(self.delay_samples_)

    def stepper(self, u_history=None) -> GpiStepper:
        """Sample-by-sample model, going on from ``u_history`` (V, oldest first) or from rest."""
        check_fitted(self, "weights_")
        return GpiStepper(self, u_history)

    def inverse(self, u_max_v: float = 3.0) -> GpiInverse:
        """The numerical inverse (feedforward): desired y (mm) -> u (V), |u| <= ``u_max_v``."""
        check_fitted(self, "weights_")
        return GpiInverse(self, u_max_v)

    def get_params(self) -> dict:
        """Constructor hyperparameters (for persistence)."""
        return {"memory_taus_s": list(self.memory_taus_s), "play_channels": self.play_channels,
                "threshold_shares": list(self.threshold_shares), "n_knots": self.n_knots,
                "rate_limit": self.rate_limit, "alphas": list(self.alphas),
                "n_folds": self.n_folds, "row_step": self.row_step,
                "max_nfev": self.max_nfev, "max_delay_s": self.max_delay_s, "dt_s": self.dt_s,
                "delay_s": self.delay_s, "dead_zone_v": self.dead_zone_v,
                "rate_channel": self.rate_channel, "drift": self.drift,
                "path_memory_v": list(self.path_memory_v),
                "output_taus_s": list(self.output_taus_s),
                "direction_memory_v": list(self.direction_memory_v),
                "direction_channels": self.direction_channels,
                "start_tau_factors": list(self.start_tau_factors),
                "warm_start": self.warm_start, "output_rate": self.output_rate,
                "channel_thresholds": self.channel_thresholds, "map_basis": self.map_basis}


class GpiStepper:
    """A :class:`GeneralizedPI` one sample at a time: ``step(u_v) -> y_mm``.

    ``outputs(x)`` evaluates candidate voltages reaching the charging stage now (after the
    transport delay) without advancing; ``advance(x)`` applies one. The numerical inverse works
    on that delay-free core: its voltages reach the charge ``delay_samples_`` later.
    """

    def __init__(self, model: GeneralizedPI, u_history=None):
        self._m = model
        self._a = np.exp(-model.dt_s / np.asarray(model.memory_taus_s_, dtype=float))
        self._travels = np.asarray(model.path_memory_v, dtype=float)
        self._directions = np.asarray(model.direction_memory_v, dtype=float)
        self._a_out = np.exp(-model.dt_s / np.asarray(model.output_taus_s, dtype=float))
        self.reset(u_history)

    def reset(self, u_history=None) -> None:
        """Go on from ``u_history`` (V, oldest first), or from rest."""
        m = self._m
        d = int(m.delay_samples_)
        if u_history is None or len(u_history) == 0:
            self._queue = deque([0.0] * d)
            self.state = GpiState(0.0, np.zeros(self._a.size), np.zeros(m.thresholds_.shape),
                                  0, np.zeros(self._travels.size), np.zeros(self._a_out.size),
                                  np.zeros((m.n_direction_channels, self._directions.size)))
            return
        u = as_signal("u_history", u_history)
        past = dead_zone(u, m.dead_zone_v).tolist()[-d:] if d else []
        self._queue = deque([0.0] * (d - len(past)) + past)
        v = m._charge(u, m._theta)
        relax, zf = lowpass_bank(v, m.memory_taus_s_, m.dt_s)
        ch = np.column_stack([v, relax])
        _, plays = play_bank(ch[:, :m.thresholds_.shape[0]], m.thresholds_)
        _, travel = travel_bank(v, m.path_memory_v)
        _, out_relax = lowpass_bank(v, m.output_taus_s, m.dt_s)
        _, direction = direction_bank(ch[:, :m.n_direction_channels], m.direction_memory_v)
        self.state = GpiState(float(v[-1]), zf, plays, int(u.size), travel, out_relax,
                              direction)

    def _channels(self, x: np.ndarray) -> GpiState:
        """The states (each with a leading axis G) after charge inputs ``x`` (G,)."""
        m, s = self._m, self.state
        if m.rate_limit:
            v = s.v + m.dt_s * m.slew_v_per_s_ * np.tanh(
                (x - s.v) / (m.charge_tau_s_ * m.slew_v_per_s_))
        else:
            v = x
        relax = self._a * s.relax + (1.0 - self._a) * v[:, None]
        ch = np.column_stack([v, relax])
        c, nd = m.thresholds_.shape[0], m.n_direction_channels
        plays = np.maximum(ch[:, :c, None] - m.thresholds_,
                           np.minimum(ch[:, :c, None] + m.thresholds_, s.plays))
        a = np.exp(-np.abs(v - s.v)[:, None] / self._travels)
        travel = a * s.travel + (1.0 - a) * v[:, None]
        out_relax = self._a_out * s.out_relax + (1.0 - self._a_out) * v[:, None]
        step = ch[:, :nd] - np.concatenate([[s.v], s.relax])[:nd]
        a = np.exp(-np.abs(step)[:, :, None] / self._directions)
        direction = a * s.direction + (1.0 - a) * np.sign(step)[:, :, None]
        return GpiState(v, relax, plays, s.k + 1, travel, out_relax, direction)

    def _output(self, n: GpiState) -> np.ndarray:
        m, g = self._m, np.size(n.v)
        extra = m._extra_channels(n.v, np.full(g, self.state.v))
        phi = np.column_stack([n.v, n.relax, n.plays.reshape(g, -1), n.travel,
                               n.direction.reshape(g, -1), extra])
        z = ((phi - m.feature_mean_) / m.feature_scale_) @ m.weights_[:-1] + m.weights_[-1]
        r = int(m.output_rate)
        added = n.out_relax @ m.output_coef_[r:]
        if r:
            added = added + m.output_coef_[0] * m._charging_current(n.v, self.state.v)
        return m.output_stage(hinge_map(z, m.knots_, m.map_coef_, m.map_range_,
                                        m.map_edge_slopes_, m._map),
                              self.state.k * m.dt_s, added)

    def outputs(self, x_candidates) -> np.ndarray:
        """Model outputs (mm) for candidate charge inputs (V) of this sample; state unchanged."""
        return self._output(self._channels(np.atleast_1d(np.asarray(x_candidates, float))))

    def advance(self, x_v: float) -> float:
        """One sample with ``x_v`` (V) reaching the charging stage; returns the output (mm)."""
        n = self._channels(np.array([float(x_v)]))
        y = float(self._output(n)[0])
        self.state = GpiState(float(n.v[0]), n.relax[0], n.plays[0], n.k, n.travel[0],
                              n.out_relax[0], n.direction[0])
        return y

    def step(self, u_v: float) -> float:
        """Apply ``u_v`` (V) for one sample, through the delay; returns the output (mm)."""
        x = float(dead_zone(np.array([float(u_v)]), self._m.dead_zone_v)[0])
        if self._queue:
            self._queue.append(x)
            x = self._queue.popleft()
        return self.advance(x)


#: Voltage grid of the inverse's search per sample, then refinement rounds (9 points each).
INVERSE_GRID_POINTS = 49
INVERSE_REFINE_ROUNDS = 3


class GpiInverse:
    """Numerical inverse of a :class:`GeneralizedPI`: desired y (mm) -> voltage (V).

    Each sample it searches the voltage in [-u_max_v, u_max_v] whose model output equals the
    desired displacement, from the model's state (grid, then bracket refinement and a linear
    interpolation on the last bracket); beyond the actuator's reach it returns the voltage
    that comes closest. The voltage is the one the charging stage needs now: with a transport
    delay the feedforward lags by it (no preview of the reference), and the PID of the hybrid
    loop takes up the rest. The served interface of an inverse model: ``stepper(y_history,
    u_history)``, ``simulate(y_desired)``, ``history_samples``, ``max_lag_``.
    """

    def __init__(self, model: GeneralizedPI, u_max_v: float = 3.0):
        check_fitted(model, "weights_")
        if not u_max_v > 0:
            raise ValueError(f"u_max_v must be > 0, got {u_max_v}")
        self.model = model
        self.u_max_v = float(u_max_v)

    @property
    def max_lag_(self) -> int:
        return 0

    @property
    def history_samples(self) -> int:
        return self.model.history_samples

    @property
    def dt_s(self) -> float:
        return self.model.dt_s

    def stepper(self, y_history=None, u_history=None) -> GpiInverseStepper:
        """Sample-by-sample feedforward; the state goes on from ``u_history`` (V)."""
        return GpiInverseStepper(self, u_history)

    def simulate(self, y_desired, u_init=None) -> np.ndarray:
        """Voltages (V) for a desired trajectory (mm), from rest."""
        y = as_signal("y_desired", y_desired)
        s = self.stepper()
        return np.array([s.step(v) for v in y.tolist()])

    def predict(self, y, u) -> np.ndarray:
        """One-step inverse: each voltage from the state the measured voltages ``u`` left."""
        y, u = as_signal("y", y), as_signal("u", u)
        s, out = self.stepper(), np.empty(y.size)
        for k in range(y.size):
            out[k] = s.step(y[k])
            s.record_applied(u[k])
        return out


class GpiInverseStepper:
    """One feedforward step: ``step(y_desired_mm) -> u_v``; ``record_applied(u_v)`` replaces
    the returned voltage by the one that reached the actuator (PID added, limits)."""

    def __init__(self, inverse: GpiInverse, u_history=None):
        self._inv = inverse
        self._fwd = GpiStepper(inverse.model, u_history)
        self._before = None

    def _arrival(self) -> GpiStepper:
        """The model as it will be when a voltage sent now reaches the charge: the voltages
        already in the transport delay applied first (without this the search answers the
        lag of its own earlier voltages, and the loop through the delay oscillates)."""
        if not self._fwd._queue:
            return self._fwd
        ahead = copy.copy(self._fwd)
        for x in list(self._fwd._queue):
            ahead.advance(x)
        return ahead

    def step(self, y_desired_mm: float) -> float:
        """Desired displacement (mm) -> feedforward voltage (V); advances the model."""
        lim = self._inv.u_max_v
        grid = np.linspace(-lim, lim, INVERSE_GRID_POINTS)
        y_target = float(y_desired_mm)
        ahead = self._arrival()
        for _ in range(INVERSE_REFINE_ROUNDS + 1):
            err = ahead.outputs(grid) - y_target
            i, j = _bracket(err)
            lo, hi, e_lo, e_hi = grid[i], grid[j], err[i], err[j]
            if i == j:
                break
            grid = np.linspace(lo, hi, 9)
        x = lo if i == j or e_hi == e_lo else lo - e_lo * (hi - lo) / (e_hi - e_lo)
        x = float(np.clip(x, -lim, lim))
        # the voltage whose dead-zoned value is x (the dead zone's edge for x = 0)
        w = self._inv.model.dead_zone_v
        u = float(np.clip(x + math.copysign(w, x) if x != 0.0 else 0.0, -lim, lim))
        self._before = (self._fwd.state, deque(self._fwd._queue))
        self._fwd.step(u)
        return u

    def record_applied(self, u_applied_v: float) -> None:
        """Advance the model's state by the applied voltage instead of the returned one."""
        if self._before is not None:
            # the applied voltage reaches the charge after the transport delay, as in reset()
            self._fwd.state, self._fwd._queue = self._before[0], deque(self._before[1])
            self._fwd.step(float(u_applied_v))


def _bracket(err: np.ndarray) -> tuple[int, int]:
    """Indices (i, i + 1) of the cell where ``err`` changes sign nearest its smallest |err|;
    (i, i) at that smallest |err| where it never does (the target is out of reach)."""
    best = int(np.argmin(np.abs(err)))
    cross = np.flatnonzero(np.sign(err[:-1]) * np.sign(err[1:]) <= 0)
    if not cross.size:
        return best, best
    i = int(cross[np.argmin(np.abs(cross - best))])
    return i, i + 1


__all__ = ["CvResult", "GeneralizedPI", "GpiInverse", "GpiInverseStepper", "GpiState",
           "GpiStepper", "hinge_basis", "hinge_map", "lowpass_bank", "play_bank",
           "rate_limited_charge"]
