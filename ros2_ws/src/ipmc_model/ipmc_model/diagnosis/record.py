"""The record under diagnosis: its fit / held-out split and what its excitation can show."""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass, replace

import numpy as np

from ipmc_driver.validation import as_signal, same_length

from ..residuals import find_holds, noise_floor
from .config import DiagnosisConfig


@dataclass(frozen=True)
class Excitation:
    """What the input of the record can show: holds (creep), steps (delay), time near 0 V
    (dead zone), its range and the sensor's noise floor."""

    span_s: float
    fit_span_s: float
    holds_fit: int
    holds_held: int
    steps_fit: int
    near_zero_share: float
    u_min_v: float
    u_max_v: float
    noise_floor_mm: float
    judged_share: float

    def as_dict(self) -> dict:
        return asdict(self)


class DiagnosisRecord:
    """Time (s), voltage (V) and tip (mm) of one record, split at ``cut``: the model and every
    block are fitted on ``[:cut]`` and judged on the free run over ``[cut:]``."""

    def __init__(self, t_s, u_v, y_mm, config: DiagnosisConfig):
        self.t_s, self.u_v, self.y_mm = (as_signal(n, v) for n, v in
                                         (("t_s", t_s), ("u_v", u_v), ("y_mm", y_mm)))
        same_length(t_s=self.t_s, u_v=self.u_v, y_mm=self.y_mm)
        if self.u_v.size < 200:
            raise ValueError(f"{self.u_v.size} samples are too few to diagnose (at least 200)")
        dt = np.diff(self.t_s)
        if not np.all(dt > 0):
            raise ValueError("the time stamps must increase")
        self.dt_s = float(np.median(dt))
        if np.ptp(self.u_v) == 0.0:
            raise ValueError("the input is constant: nothing can be identified from it")
        self.config = config
        self.cut = int(round(config.fit_share * self.u_v.size))
        self.judged = self._judged()
        self.excitation = self._excitation()

    def whole(self) -> DiagnosisRecord:
        """This record with every row in the fit part: where a parameter is estimated once
        the held-out rows have decided."""
        out = copy.copy(self)
        out.cut = self.u_v.size
        out.excitation = replace(self.excitation, fit_span_s=self.excitation.span_s)
        return out

    @property
    def fit(self) -> slice:
        return slice(0, self.cut)

    @property
    def held(self) -> slice:
        return slice(self.cut, None)

    def _excitation(self) -> Excitation:
        c, u = self.config, self.u_v
        holds = find_holds(u, self.dt_s, c.hold_min_s)
        jumps = np.abs(np.diff(u[:self.cut])) >= c.step_share * np.ptp(u)
        return Excitation(
            span_s=u.size * self.dt_s, fit_span_s=self.cut * self.dt_s,
            holds_fit=sum(1 for a, b in holds if b <= self.cut),
            holds_held=sum(1 for a, b in holds if a >= self.cut),
            steps_fit=int(np.sum(jumps[1:] & ~jumps[:-1]) + (jumps[0] if jumps.size else 0)),
            near_zero_share=float(np.mean(np.abs(u[:self.cut]) < c.dead_zone_max_v)),
            u_min_v=float(u.min()), u_max_v=float(u.max()),
            noise_floor_mm=noise_floor(self.y_mm), judged_share=float(self.judged.mean()))

    def _judged(self) -> np.ndarray:
        """Held-out rows the decision uses: those whose voltage stayed within the fit part's
        range for the last ``settle_s`` (beyond it every model extrapolates, and a block can
        win there by extrapolating differently, not by being the effect)."""
        lo, hi = self.u_v[:self.cut].min(), self.u_v[:self.cut].max()
        out = ((self.u_v < lo) | (self.u_v > hi)).astype(float)
        n = max(1, int(round(self.config.settle_s / self.dt_s)))
        recent = np.convolve(out, np.ones(n), mode="full")[:out.size] > 0
        judged = ~recent[self.cut:]
        return judged if judged.mean() >= 0.5 else np.ones_like(judged)

    def power_share_above(self, f_hz: float) -> float:
        """Share of the fit part's input power (mean removed) above ``f_hz``."""
        x = self.u_v[:self.cut] - self.u_v[:self.cut].mean()
        p = np.abs(np.fft.rfft(x)) ** 2
        f = np.fft.rfftfreq(x.size, self.dt_s)
        total = float(p[1:].sum())
        return float(p[f > f_hz].sum() / total) if total > 0 else 0.0
