"""Discrete PID in the paper's standard form (pure core, no ROS).

The paper (Eq. 21) writes the controller in the standard (ISA) form

    u = K (e + 1/TI * integral(e) + TD * de/dt),        e = r - y

with K = 1.2 V/mm, TI = 0.87 s, TD = 0.13 s. This module discretises it as Astrom and
Hagglund, *Advanced PID Control* (2006), ch. 3 and 13, do for a practical controller:

- derivative on the measurement (no derivative kick when the reference steps), low-pass
  filtered with time constant ``TD / N`` (backward difference, stable for any ``dt``); when the
  caller knows the rate of a smooth reference (``reference_rate``) it is added, so the
  derivative acts on the error as Eq. 21 writes it, still without a kick on steps (a step
  train's rate is 0);
- integral by forward Euler, stored in volts, so a change of TI alone leaves the output alone;
- output limit ``u_clamp_min <= u <= u_clamp_max`` (the H-bridge's 3 V);
- back-calculation anti-windup with tracking time constant ``Tt`` (default ``sqrt(TI * TD)``,
  Astrom-Hagglund's rule, which is also control_toolbox's default ``sqrt(d / i)``);
- bumpless gain changes: the integral absorbs the jump of the proportional and derivative
  terms, so the output continues without a step;
- the sample time ``dt_s`` is the caller's (measured from its clock), never assumed.

Names follow ros-controls/control_toolbox (``Pid``/``PidROS``) where they mean the same thing:
``p``, ``i``, ``d`` (the equivalent parallel gains), ``u_clamp_max``, ``u_clamp_min``,
``antiwindup_strategy`` (``"back_calculation"`` or ``"none"``), ``tracking_time_constant``
(``trk_tc`` in control_toolbox's first anti-windup release, renamed since), ``i_term``,
``reset(save_i_term)``. The paper's K, TI, TD are ``k``, ``ti_s``, ``td_s``.

Bad samples: a ``dt_s`` that is zero, negative or not finite, or a non-finite reference,
measurement or feedforward, returns the previous command and leaves every state untouched
(control_toolbox does the same for ``dt == 0``; it throws on negative ``dt`` and returns NaN on a
non-finite error, which here would reach the actuator or kill the node on a backward clock jump
of simulated time). Such calls are counted in ``rejected_steps``.
"""

from __future__ import annotations

import math

ANTIWINDUP_STRATEGIES = ("back_calculation", "none")

#: Paper defaults (Section 4.3): K in V/mm, TI and TD in s.
DEFAULT_K = 1.2
DEFAULT_TI_S = 0.87
DEFAULT_TD_S = 0.13
# N = 3, not the textbooks' 10: with the laser's 0.01 mm noise, TD = 0.13 s and N = 10 put a
# 0.12 V (std) ripple on the command; near the 3 V limit its peaks clip, back-calculation then
# bleeds the integrator and a hold kept a -0.023 mm offset (-4 mm hold after the rise: 0.14 mm).
# N = 3: 0.04 V ripple; every tracking cell of docs/control.md improved.
DEFAULT_N = 3.0
#: Output limit of the rig's H-bridge, V.
DEFAULT_U_LIMIT_V = 3.0


class ControlParameterError(ValueError):
    """A controller or reference parameter is out of its domain."""


def check_actuator_limits(u_clamp_min, u_clamp_max, limit_v: float = DEFAULT_U_LIMIT_V
                          ) -> tuple[float, float]:
    """The command limits (V) a node may put on the actuator: finite, within the H-bridge's
    +-``limit_v``, and with 0 V between them (a pair that excludes 0 V holds the actuator away
    from rest whatever the loop asks). Raises :class:`ControlParameterError` otherwise."""
    lo = check_parameter("u_clamp_min", u_clamp_min)
    hi = check_parameter("u_clamp_max", u_clamp_max)
    if not (-limit_v <= lo <= 0.0 <= hi <= limit_v and lo < hi):
        raise ControlParameterError(
            f"u_clamp_min and u_clamp_max must satisfy -{limit_v:g} <= u_clamp_min <= 0 <= "
            f"u_clamp_max <= {limit_v:g} V (the H-bridge's limit, with 0 V allowed), got "
            f"{lo:g} and {hi:g}")
    return lo, hi


def check_parameter(name: str, value, *, low: float | None = None, low_open: bool = False,
                    allow_inf: bool = False) -> float:
    """Return ``value`` as a float, or raise :class:`ControlParameterError` naming ``name``.

    Parameters
    ----------
    name : str
        Parameter name for the message.
    value : float-like
        The value.
    low : float, optional
        Lower bound (inclusive, or exclusive with ``low_open``).
    allow_inf : bool
        Accept infinite values (NaN is always refused).
    """
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ControlParameterError(
            f"{name} must be a number, got {type(value).__name__} {value!r}") from None
    if math.isnan(x) or (math.isinf(x) and not allow_inf):
        raise ControlParameterError(f"{name} must be finite, got {x}")
    if low is not None:
        if low_open and not x > low:
            raise ControlParameterError(f"{name} must be > {low}, got {x}")
        if not low_open and not x >= low:
            raise ControlParameterError(f"{name} must be >= {low}, got {x}")
    return x


class PID:
    """Discrete PID controller in the standard form of the paper's Eq. 21.

    Parameters
    ----------
    k : float
        Proportional gain K, V/mm (>= 0).
    ti_s : float
        Integral time TI, s (> 0; ``math.inf`` disables the integral action).
    td_s : float
        Derivative time TD, s (>= 0; 0 disables the derivative action).
    n : float
        Derivative filter ratio N (> 0): the derivative is low-passed with time constant
        ``td_s / n`` s. Textbooks say 8 to 20; the default is 3 (see DEFAULT_N).
    u_clamp_max, u_clamp_min : float
        Output limits, V (``u_clamp_min < u_clamp_max``; infinite values are allowed).
    antiwindup_strategy : {"back_calculation", "none"}
        ``"back_calculation"`` feeds ``(u - v) / Tt`` back into the integrator, where ``v`` is the
        unsaturated and ``u`` the applied command.
    tracking_time_constant : float or None
        Tt, s (> 0). None or 0 (control_toolbox's convention): ``sqrt(ti_s * td_s)``, or
        ``ti_s`` when ``td_s`` is 0.

    Notes
    -----
    One call of :meth:`compute_command` with error ``e = r - y`` and sample time ``h`` computes::

        P = K e
        D = a D_prev - K TD (y - y_prev) / (Tf + h),   Tf = TD / N,  a = Tf / (Tf + h)
        v = u_ff + P + I + D                 (unsaturated total, V)
        u = clip(v, u_clamp_min, u_clamp_max)
        I <- I + K h / TI * e + h / Tt * (u - v)

    The first call after construction or :meth:`reset` has no previous measurement, so D = 0.
    Values in mm and V; any consistent units work.

    Examples
    --------
    >>> pid = PID()
    >>> round(pid.compute_command(reference=1.0, measurement=0.0, dt_s=0.01), 6)
    1.2
    """

    def __init__(self, k: float = DEFAULT_K, ti_s: float = DEFAULT_TI_S,
                 td_s: float = DEFAULT_TD_S, *, n: float = DEFAULT_N,
                 u_clamp_max: float = DEFAULT_U_LIMIT_V, u_clamp_min: float = -DEFAULT_U_LIMIT_V,
                 antiwindup_strategy: str = "back_calculation",
                 tracking_time_constant: float | None = None) -> None:
        self._apply(*self._validated(k, ti_s, td_s, n, u_clamp_max, u_clamp_min,
                                     antiwindup_strategy, tracking_time_constant))
        self.rejected_steps = 0
        self.reset()

    # -- construction helpers -------------------------------------------------------------------
    @classmethod
    def from_parallel(cls, p: float, i: float, d: float, **kwargs) -> PID:
        """Build from parallel gains ``u = p e + i int(e) + d de/dt`` (control_toolbox form).

        Parameters
        ----------
        p : float
            Proportional gain, V/mm (> 0).
        i : float
            Integral gain, V/(mm s) (>= 0; 0 disables the integral).
        d : float
            Derivative gain, V s/mm (>= 0).
        **kwargs
            Other keyword arguments of :class:`PID`.
        """
        p = check_parameter("p", p, low=0.0, low_open=True)
        i = check_parameter("i", i, low=0.0)
        d = check_parameter("d", d, low=0.0)
        return cls(p, p / i if i > 0 else math.inf, d / p, **kwargs)

    @staticmethod
    def _validated(k, ti_s, td_s, n, u_max, u_min, strategy, tt):
        k = check_parameter("k", k, low=0.0)
        ti_s = check_parameter("ti_s", ti_s, low=0.0, low_open=True, allow_inf=True)
        td_s = check_parameter("td_s", td_s, low=0.0)
        n = check_parameter("n", n, low=0.0, low_open=True)
        u_max = check_parameter("u_clamp_max", u_max, allow_inf=True)
        u_min = check_parameter("u_clamp_min", u_min, allow_inf=True)
        if not u_min < u_max:
            raise ControlParameterError(
                f"u_clamp_min must be < u_clamp_max, got {u_min} >= {u_max}")
        if strategy not in ANTIWINDUP_STRATEGIES:
            raise ControlParameterError(
                f"antiwindup_strategy must be one of {ANTIWINDUP_STRATEGIES}, got {strategy!r}")
        if tt is None or tt == 0.0:  # 0: control_toolbox's "use the default rule"
            tt_eff = math.sqrt(ti_s * td_s) if td_s > 0 else ti_s
            tt = None
        else:
            tt = tt_eff = check_parameter("tracking_time_constant", tt, low=0.0, low_open=True)
        return k, ti_s, td_s, n, u_max, u_min, strategy, tt, tt_eff

    def _apply(self, k, ti_s, td_s, n, u_max, u_min, strategy, tt, tt_eff) -> None:
        self._k, self._ti, self._td, self._n = k, ti_s, td_s, n
        self._u_max, self._u_min = u_max, u_min
        self._strategy = strategy
        self._tt_param, self._tt = tt, tt_eff
        # Integral gain K/TI, V/(mm s); 0 when TI is infinite.
        self._ki = k / ti_s if math.isfinite(ti_s) else 0.0
        # Back-calculation gain 1/Tt, 1/s. Without integral action there is nothing to track
        # (control_toolbox skips it too when i == 0).
        use_tracking = strategy == "back_calculation" and self._ki > 0 and math.isfinite(tt_eff)
        self._kt = 1.0 / tt_eff if use_tracking else 0.0

    # -- hyperparameters (read-only: change them with set_gains / set_limits) -------------------
    @property
    def k(self) -> float:
        """Proportional gain K, V/mm."""
        return self._k

    @property
    def ti_s(self) -> float:
        """Integral time TI, s (inf: no integral action)."""
        return self._ti

    @property
    def td_s(self) -> float:
        """Derivative time TD, s."""
        return self._td

    @property
    def n(self) -> float:
        """Derivative filter ratio N."""
        return self._n

    @property
    def u_clamp_max(self) -> float:
        """Upper output limit, V."""
        return self._u_max

    @property
    def u_clamp_min(self) -> float:
        """Lower output limit, V."""
        return self._u_min

    @property
    def antiwindup_strategy(self) -> str:
        """``"back_calculation"`` or ``"none"``."""
        return self._strategy

    @property
    def tracking_time_constant(self) -> float | None:
        """Tt as set, s; None when it follows the default rule."""
        return self._tt_param

    # -- control_toolbox-style views ------------------------------------------------------------
    @property
    def p(self) -> float:
        """Equivalent parallel proportional gain ``K``, V/mm."""
        return self._k

    @property
    def i(self) -> float:
        """Equivalent parallel integral gain ``K / TI``, V/(mm s)."""
        return self._ki

    @property
    def d(self) -> float:
        """Equivalent parallel derivative gain ``K TD``, V s/mm."""
        return self._k * self._td

    @property
    def tracking_time_constant_s(self) -> float:
        """Effective back-calculation tracking time constant Tt, s."""
        return self._tt

    @property
    def i_term(self) -> float:
        """Integral contribution to the output, V."""
        return self._i

    @property
    def d_term(self) -> float:
        """Derivative contribution of the last step, V."""
        return self._d

    @property
    def p_term(self) -> float:
        """Proportional contribution of the last step, V."""
        return self._p

    @property
    def command(self) -> float:
        """Last (saturated) command, V; 0 after :meth:`reset`."""
        return self._u

    @property
    def command_unsaturated(self) -> float:
        """Last unsaturated total ``u_ff + P + I + D``, V."""
        return self._v

    @property
    def saturated(self) -> bool:
        """True when the last command was clipped."""
        return self._v != self._u

    # -- state ----------------------------------------------------------------------------------
    def reset(self, save_i_term: bool = False) -> None:
        """Clear the state (previous measurement, derivative, command); keep I if asked.

        Parameters
        ----------
        save_i_term : bool
            Keep the integral term (control_toolbox's ``save_i_term``).
        """
        if not save_i_term:
            self._i = 0.0
        self._y_prev = None
        self._e = 0.0
        self._p = 0.0
        self._d = 0.0
        self._u = 0.0
        self._v = 0.0

    def add_to_integral(self, delta_v: float) -> None:
        """Shift the integral term by ``delta_v`` V (bumpless transfer when a feedforward
        appears or disappears). Non-finite values are ignored."""
        if math.isfinite(delta_v):
            self._i += float(delta_v)

    def set_gains(self, k: float | None = None, ti_s: float | None = None,
                  td_s: float | None = None, *, n: float | None = None,
                  tracking_time_constant: float | None = None) -> None:
        """Change gains without a jump of the output (bumpless).

        The integral term absorbs the change of the proportional and derivative terms at the
        last error and derivative state, so the next step gives what it would have given with
        the old gains (the new gains act on what changes from then on).
        Arguments left at None keep their value. Invalid values raise
        :class:`ControlParameterError` and change nothing.

        Parameters
        ----------
        k : float, optional
            Proportional gain K, V/mm.
        ti_s : float, optional
            Integral time TI, s.
        td_s : float, optional
            Derivative time TD, s.
        n : float, optional
            Derivative filter ratio N.
        tracking_time_constant : float, optional
            Tt, s; 0 returns to the default rule ``sqrt(TI TD)``. Not given: unchanged (an
            explicit Tt stays, the default rule follows the new TI and TD).
        """
        k = self._k if k is None else k
        ti_s = self._ti if ti_s is None else ti_s
        td_s = self._td if td_s is None else td_s
        n = self._n if n is None else n
        tt = self._tt_param if tracking_time_constant is None else tracking_time_constant
        checked = self._validated(k, ti_s, td_s, n, self._u_max, self._u_min,
                                  self._strategy, tt)
        # P + D before the change, at the last error and derivative state (V).
        pd_old = self._k * self._e + self._d
        kd_old = self._k * self._td
        self._apply(*checked)
        # D is a filtered derivative times K TD: rescale it to the new K TD.
        self._d = self._d * (self._k * self._td) / kd_old if kd_old > 0 else 0.0
        self._p = self._k * self._e
        self._i += pd_old - (self._p + self._d)

    def set_limits(self, u_clamp_min: float, u_clamp_max: float) -> None:
        """Change the output limits, V (``u_clamp_min < u_clamp_max``)."""
        self._apply(*self._validated(self._k, self._ti, self._td, self._n, u_clamp_max,
                                     u_clamp_min, self._strategy, self._tt_param))

    # -- the step -------------------------------------------------------------------------------
    def compute_command(self, reference: float, measurement: float, dt_s: float,
                        feedforward: float = 0.0, u_applied: float | None = None,
                        reference_rate: float | None = None) -> float:
        """Advance one sample and return the saturated command, V.

        Parameters
        ----------
        reference : float
            Desired displacement r, mm.
        measurement : float
            Measured displacement y, mm.
        dt_s : float
            Time since the previous call, s, from the caller's clock. ``dt_s <= 0`` or not
            finite: the previous command is returned and no state changes.
        feedforward : float
            Voltage added before the limit, V (the inverse model's ``u_ff`` in the hybrid law);
            the anti-windup then sees the saturation of the total.
        u_applied : float, optional
            Command actually applied when the loop is open (feedforward only, manual), V. The
            integrator then only tracks it, ``I <- I + h / Tt * (u - v)``, so ``v`` converges
            to it with time constant Tt and closing the loop later does not bump (with
            ``antiwindup_strategy="none"`` the integrator is frozen instead). It is clipped to
            the limits and returned.
        reference_rate : float, optional
            dr/dt of a smooth reference, mm/s (e.g. ``Reference.rate``). The derivative then
            acts on the error, ``TD d(r - y)/dt`` as in the paper's Eq. 21, through the same
            filter, with r's rate given rather than differenced: a tracked trajectory does not
            see ``-K TD dy/dt`` fight the feedforward, and a step (rate 0 on both sides) still
            gives no kick. None (default): derivative on the measurement alone.

        Returns
        -------
        float
            ``clip(feedforward + P + I + D)`` (or clipped ``u_applied``), V. Never NaN.
        """
        h = dt_s
        if not (h > 0.0 and math.isfinite(h) and math.isfinite(reference)
                and math.isfinite(measurement) and math.isfinite(feedforward)
                and (u_applied is None or math.isfinite(u_applied))
                and (reference_rate is None or math.isfinite(reference_rate))):
            self.rejected_steps += 1
            return self._u
        e = reference - measurement
        p = self._k * e
        if self._y_prev is None:
            d = 0.0
        else:
            tf = self._td / self._n
            change = measurement - self._y_prev
            if reference_rate is not None:
                change -= reference_rate * h
            d = (tf * self._d - self._k * self._td * change) / (tf + h)
        v = feedforward + p + self._i + d
        u = v if u_applied is None else u_applied
        u = self._u_max if u > self._u_max else (self._u_min if u < self._u_min else u)
        if u_applied is None:
            self._i += h * (self._ki * e + self._kt * (u - v))
        else:
            # Tracking (manual) mode: the integrator follows the applied command only, so that
            # v converges to it exactly and closing the loop does not bump (Astrom-Hagglund).
            self._i += h * self._kt * (u - v)
        self._e, self._p, self._d, self._v, self._u = e, p, d, v, u
        self._y_prev = measurement
        return u
