"""Hybrid inverse-feedforward + PID law of the paper, Eq. 20-22 (pure core, no ROS).

``u = clip(u_ff + u_pid)``: ``u_ff`` is the inverse LSSVM-NARX model's voltage for the desired
displacement (computed by the caller, e.g. received on ``/ipmc/feedforward``), ``u_pid`` the PID
on the tracking error. The limit applies to the total and the PID's back-calculation anti-windup
sees that total saturation.

Modes
-----
``"pid"``      feedback alone, the feedforward is ignored.
``"inverse"``  open loop: ``u = clip(u_ff)``; the PID only tracks the applied command so that
               switching to ``"hybrid"`` or ``"pid"`` later does not bump.
``"hybrid"``   ``u = clip(u_ff + u_pid)``.

When the feedforward is missing (None or not finite: model server gone, stale topic) the
controller falls back to PID alone for that step, whatever the mode, and ``active_mode`` says
``"pid"``. Every switch between "feedforward in the sum" and "not in the sum" (mode change,
fallback, recovery) moves the last feedforward value into or out of the integral term, so the
command does not jump.
"""

from __future__ import annotations

import math

from .pid import PID, ControlParameterError

MODES = ("pid", "inverse", "hybrid")


def check_mode(mode: str) -> str:
    """Return ``mode`` if it is one of :data:`MODES`, else raise ``ControlParameterError``."""
    if mode not in MODES:
        raise ControlParameterError(f"mode must be one of {MODES}, got {mode!r}")
    return mode


class HybridController:
    """Hybrid inverse-feedforward + PID controller (paper Eq. 22: ``u_l = u + u_i``).

    Parameters
    ----------
    pid : PID, optional
        The feedback part; default ``PID()`` (K = 1.2 V/mm, TI = 0.87 s, TD = 0.13 s,
        |u| <= 3 V). Its output limits are the limits of the total command.
    mode : {"pid", "inverse", "hybrid"}
        Control law, see the module docstring. Can be changed at any time through ``mode``.

    Attributes
    ----------
    active_mode : str
        Law used by the last step: ``mode``, or ``"pid"`` during a feedforward fallback.
    feedforward_v : float
        Feedforward included in the last command, V (0 when none was).
    """

    def __init__(self, pid: PID | None = None, mode: str = "hybrid") -> None:
        self.pid = PID() if pid is None else pid
        self._mode = check_mode(mode)
        self.active_mode = self._mode
        self.feedforward_v = 0.0
        # Whether the last accepted step had the feedforward in the sum, and its value (V).
        self._ff_in_sum = False
        self._ff_last = 0.0
        self._started = False

    @property
    def mode(self) -> str:
        """Requested control law, one of :data:`MODES`."""
        return self._mode

    @mode.setter
    def mode(self, value: str) -> None:
        self._mode = check_mode(value)

    @property
    def command(self) -> float:
        """Last command, V."""
        return self.pid.command

    @property
    def saturated(self) -> bool:
        """True when the last command was clipped."""
        return self.pid.saturated

    def reset(self) -> None:
        """Clear the PID state and forget the feedforward."""
        self.pid.reset()
        self._ff_in_sum = False
        self._ff_last = 0.0
        self._started = False
        self.feedforward_v = 0.0
        self.active_mode = self._mode

    def compute_command(self, reference_mm: float, measurement_mm: float, dt_s: float,
                        feedforward_v: float | None = None,
                        reference_rate_mm_s: float | None = None) -> float:
        """Advance one sample and return the command, V (clipped, never NaN).

        Parameters
        ----------
        reference_mm : float
            Desired tip displacement, mm.
        measurement_mm : float
            Measured tip displacement, mm.
        dt_s : float
            Time since the previous call, s (caller's clock). Bad values (<= 0, NaN) return the
            previous command without changing the state, as :meth:`PID.compute_command`.
        feedforward_v : float or None
            Inverse-model voltage for ``reference_mm``, V; None or NaN when unavailable.
        reference_rate_mm_s : float or None
            Rate of a smooth reference, mm/s: the derivative acts on the error (paper Eq. 21);
            None: on the measurement (see :meth:`PID.compute_command`).

        Returns
        -------
        float
            The command, V, within the PID's limits.
        """
        ff_ok = feedforward_v is not None and math.isfinite(feedforward_v)
        mode = self._mode if (ff_ok or self._mode == "pid") else "pid"
        rate = reference_rate_mm_s
        if rate is not None and not math.isfinite(rate):
            rate = None  # an unknown rate must not stop the loop: derivative on measurement
        if not (dt_s > 0.0 and math.isfinite(dt_s)
                and math.isfinite(reference_mm) and math.isfinite(measurement_mm)):
            # Let the PID reject and count the step; nothing else changes.
            return self.pid.compute_command(reference_mm, measurement_mm, dt_s)
        use_ff = mode != "pid"
        ff = float(feedforward_v) if use_ff else 0.0
        self._transfer(use_ff, ff)
        if mode == "inverse":
            u = self.pid.compute_command(reference_mm, measurement_mm, dt_s, feedforward=ff,
                                         u_applied=ff, reference_rate=rate)
        else:
            u = self.pid.compute_command(reference_mm, measurement_mm, dt_s, feedforward=ff,
                                         reference_rate=rate)
        self.active_mode = mode
        self.feedforward_v = ff
        return u

    def _transfer(self, use_ff: bool, ff: float) -> None:
        # Bumpless switch: when the feedforward leaves the sum, the integral takes over its last
        # value; when it enters, the integral gives the new value back. Not on the first step:
        # there is no previous command to be continuous with.
        if not self._started:
            self._started = True
        elif use_ff and not self._ff_in_sum:
            self.pid.add_to_integral(-ff)
        elif not use_ff and self._ff_in_sum:
            self.pid.add_to_integral(self._ff_last)
        self._ff_in_sum = use_ff
        self._ff_last = ff if use_ff else 0.0
