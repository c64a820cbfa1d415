"""Tip arc compensation of the laser reading (paper Eq. 1, section 2.1).

The IPMC tip moves on an arc about the clamp, while the laser measures along a fixed line at
distance ``L2`` from the clamp. With ``x`` the laser reading and ``d`` its reading at rest, the
beam meets the actuator at the angle ``a = arctan((d - x) / L2)``, so the tip displacement is::

    y = L1 * sin(arctan((d - x) / L2))                                   (Eq. 1)

valid while the beam still hits the actuator (``L2 / cos(a) <= L1``)::

    d - L1 * sin(arccos(L2 / L1)) < x <= L1 * sin(arccos(L2 / L1)) + d

Readings outside that range are not numbers of the tip position: ``compensate`` returns NaN for
them and ``in_range`` flags them, so callers never publish them. Lengths in mm.

Pure core: NumPy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["ArcGeometry", "ArcRangeError", "L1_MM", "L2_MM", "D_MM"]

L1_MM = 27.0  # actuator length (27 mm x 6 mm x 0.2 mm samples of the paper)
L2_MM = 20.0  # clamp to laser line, mm (rig-specific; set from the rig's drawing)
D_MM = 150.0  # laser reading at rest, mm (rig-specific; LE250 range 100-400 mm)


class ArcRangeError(ValueError):
    """A reading or displacement outside the range where Eq. 1 is valid."""


@dataclass(frozen=True)
class ArcGeometry:
    """Geometry of the arc compensation (paper Eq. 1).

    Parameters
    ----------
    l1_mm : float
        Actuator length L1 (clamp to tip), mm. Default 27 mm.
    l2_mm : float
        Distance L2 from the clamp to the laser line, mm; ``0 < l2_mm < l1_mm``.
    d_mm : float
        Laser reading d with the actuator at rest, mm.
    """

    l1_mm: float = L1_MM
    l2_mm: float = L2_MM
    d_mm: float = D_MM

    def __post_init__(self) -> None:
        for name in ("l1_mm", "l2_mm", "d_mm"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        if self.l1_mm <= 0:
            raise ValueError(f"l1_mm must be > 0, got {self.l1_mm}")
        if not 0 < self.l2_mm < self.l1_mm:
            raise ValueError(
                f"l2_mm must be in (0, l1_mm={self.l1_mm}), got {self.l2_mm}: the laser line "
                "must cross the actuator"
            )

    @property
    def half_span_mm(self) -> float:
        """``L1 sin(arccos(L2/L1)) = sqrt(L1^2 - L2^2)``: half width of the valid ranges, mm."""
        return self.l1_mm * math.sin(math.acos(self.l2_mm / self.l1_mm))

    @property
    def reading_range_mm(self) -> tuple[float, float]:
        """Valid laser readings ``(lo, hi)``: ``lo < x <= hi`` (Eq. 1), mm."""
        s = self.half_span_mm
        return self.d_mm - s, self.d_mm + s

    @property
    def displacement_range_mm(self) -> tuple[float, float]:
        """Tip displacements reachable inside the valid range ``(lo, hi)``: ``lo <= y < hi``."""
        s = self.half_span_mm
        return -s, s

    def in_range(self, x_mm):
        """True where the laser reading ``x_mm`` (mm, scalar or array) is inside Eq. 1's range.

        Non-finite readings are out of range.
        """
        x = np.asarray(x_mm, dtype=float)
        lo, hi = self.reading_range_mm
        with np.errstate(invalid="ignore"):
            ok = (x > lo) & (x <= hi) & np.isfinite(x)
        return bool(ok) if ok.ndim == 0 else ok

    def compensate(self, x_mm):
        """Tip displacement y (mm) from the laser reading x (mm), Eq. 1.

        Parameters
        ----------
        x_mm : float or array_like, shape (N,)
            Laser readings, mm.

        Returns
        -------
        float or ndarray, shape (N,)
            ``y = L1 sin(arctan((d - x)/L2))``, mm; NaN where ``x`` is outside the valid range
            (see ``in_range``). Positive y: the tip moved towards the sensor.
        """
        x = np.asarray(x_mm, dtype=float)
        ok = np.asarray(self.in_range(x))
        with np.errstate(invalid="ignore"):
            y = self.l1_mm * np.sin(np.arctan((self.d_mm - x) / self.l2_mm))
        y = np.where(ok, y, np.nan)
        return float(y) if y.ndim == 0 else y

    def compensate_scalar(self, x_mm: float) -> float:
        """Like ``compensate`` for one reading, but raise ``ArcRangeError`` when out of range."""
        if not self.in_range(x_mm):
            lo, hi = self.reading_range_mm
            raise ArcRangeError(
                f"laser reading {x_mm} mm outside the valid range ({lo:.3f}, {hi:.3f}] mm"
            )
        return self.l1_mm * math.sin(math.atan((self.d_mm - x_mm) / self.l2_mm))

    def reading(self, y_mm):
        """Inverse of Eq. 1: the laser reading x (mm) for a tip displacement y (mm).

        ``x = d - L2 tan(arcsin(y / L1))``; NaN where ``y`` is outside
        ``displacement_range_mm`` (the beam would miss the actuator).
        """
        y = np.asarray(y_mm, dtype=float)
        lo, hi = self.displacement_range_mm
        with np.errstate(invalid="ignore"):
            ok = (y >= lo) & (y < hi) & np.isfinite(y)
            x = self.d_mm - self.l2_mm * np.tan(np.arcsin(np.clip(y / self.l1_mm, -1.0, 1.0)))
        x = np.where(ok, x, np.nan)
        return float(x) if x.ndim == 0 else x

    def reading_scalar(self, y_mm: float) -> float | None:
        """Inverse of Eq. 1 for one displacement (mm); ``None`` where the beam misses the tip.

        A fast path (no NumPy) for per-sample loops such as the rig emulator.
        """
        s = self.half_span_mm
        if not -s <= y_mm < s:  # also False for NaN
            return None
        return self.d_mm - self.l2_mm * math.tan(math.asin(y_mm / self.l1_mm))
