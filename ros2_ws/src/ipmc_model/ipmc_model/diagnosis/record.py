"""The records under diagnosis: their fit / held-out split and what their excitation can show.

One record or several (another day's, an experiment's) are joined into one: in that order,
each separated by a rest at 0 V whose output is not measured. Every model runs over the
whole, is fitted on the fit rows (the first share of each record, or up to the held-out part
of the experiment it played) and judged on the free run over the held-out rows (the rest of
each). A row whose
output was not measured (y NaN: a rest, a sample lost on the link) is in neither: models run
through it.

A record played from a proposed experiment (``next_experiment.json``) may come with the
experiment's parts: it is then split where they mark the held-out part (the probes' last
copies), and an effect with a probe there (its own, or one that decides it too) is judged on
that probe's rows alone (:meth:`DiagnosisRecord.judged_for`). The other probes show other
effects: a block's error on them measures how the refit moved the rest of the model, not the
effect.
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass, replace

import numpy as np

from ipmc_driver.validation import as_signal, same_length

from ..residuals import find_holds, noise_floor
from .config import DiagnosisConfig

#: The rest between joined records lasts this many of the shortest creep time constant: the
#: core's relaxations and a creep at that time constant have settled there (e^-5 < 1 %).
REST_TAUS = 5.0


@dataclass(frozen=True)
class Excitation:
    """What the input of the records can show: holds (creep), steps (delay), time near 0 V
    (dead zone), its range and the sensor's noise floor."""

    span_s: float
    fit_span_s: float
    holds_fit: int
    holds_held: int
    steps_fit: int
    near_zero_share: float
    near_zero_held_share: float
    u_min_v: float
    u_max_v: float
    noise_floor_mm: float
    judged_share: float

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Segment:
    """One record's rows in the joined record: [start, stop), held out from ``cut`` on."""

    name: str
    start: int
    stop: int
    cut: int


def _checked(name: str, t_s, u_v, y_mm) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    t, u = (as_signal(f"{name}: {k}", v) for k, v in (("t_s", t_s), ("u_v", u_v)))
    # y NaN: a sample not measured (lost on the link, ipmc_driver.dataio.fill_gaps)
    y = as_signal(f"{name}: y_mm", y_mm, allow_nan=True)
    same_length(t_s=t, u_v=u, y_mm=y)
    measured = int(np.isfinite(y).sum())
    if measured < 200:
        raise ValueError(f"{name}: {measured} measured samples are too few to diagnose (at "
                         "least 200)")
    dt = np.diff(t)
    if not np.all(dt > 0):
        raise ValueError(f"{name}: the time stamps must increase")
    return t, u, y, float(np.median(dt))


def _cut(record: tuple, n: int, config: DiagnosisConfig, dt_s: float) -> int:
    """Where a record's held-out part starts: at the first held-out part of the experiment
    it played (its probes' last copies), else after the config's ``fit_share``."""
    held = [p.start_s for p in (record[4] if len(record) > 4 else ())
            if p.held_out]
    cut = int(round(min(held) / dt_s)) if held else int(round(config.fit_share * n))
    if not 0 < cut < n:
        raise ValueError(f"{record[0]}: its experiment's held-out part starts at "
                         f"{min(held):.1f} s: the record ({n * dt_s:.1f} s) needs rows before "
                         f"it to fit on and rows from it on to judge")
    return cut


class DiagnosisRecord:
    """Time (s), voltage (V) and tip (mm) of one record, split at its segment's ``cut``: the
    model and every block are fitted on the rows before it and judged on the free run over
    the rows from it on. :meth:`joined` makes one of several records."""

    def __init__(self, t_s, u_v, y_mm, config: DiagnosisConfig, name: str = "record",
                 parts=()):
        self._build([(name, t_s, u_v, y_mm, parts)], config)

    @classmethod
    def joined(cls, records, config: DiagnosisConfig) -> DiagnosisRecord:
        """Several records ``(name, t_s, u_v, y_mm[, parts])``, in order, joined by rests at
        0 V; ``parts``: the :class:`ExperimentPart` s of the experiment a record played."""
        out = cls.__new__(cls)
        out._build(list(records), config)
        return out

    def _build(self, records: list, config: DiagnosisConfig) -> None:
        if not records:
            raise ValueError("no record to diagnose")
        checked = [(name, *_checked(name, *sig[:3])) for name, *sig in records]
        self.dt_s = checked[0][4]
        for name, *_, dt in checked[1:]:
            if abs(dt - self.dt_s) > 0.01 * self.dt_s:
                raise ValueError(f"{name} is sampled at {1 / dt:.4g} Hz and {checked[0][0]} at "
                                 f"{1 / self.dt_s:.4g} Hz; resample one to the other's rate")
        rest = int(round(REST_TAUS * config.creep_min_tau_s / self.dt_s))
        u, y, segs, start = [], [], [], 0
        for i, (name, _, ui, yi, _) in enumerate(checked):
            if i:
                u.append(np.zeros(rest))
                y.append(np.full(rest, np.nan))
                start += rest
            u.append(ui)
            y.append(yi)
            segs.append(Segment(name, start, start + ui.size,
                                start + _cut(records[i], ui.size, config, self.dt_s)))
            start += ui.size
        self.u_v, self.y_mm = np.concatenate(u), np.concatenate(y)
        # joined records: one clock from the first record's start, the rests included
        self.t_s = (checked[0][1] if len(checked) == 1 else
                    checked[0][1][0] + np.arange(self.u_v.size) * self.dt_s)
        if np.ptp(self.u_v) == 0.0:
            raise ValueError("the input is constant: nothing can be identified from it")
        self.config = config
        self._split(tuple(segs))
        self.judged = self._judged()
        self.probe_rows = self._probe_rows([r[4] if len(r) > 4 else () for r in records])
        self.excitation = self._excitation()

    # -- rows ----------------------------------------------------------------------------
    def _split(self, segments: tuple[Segment, ...]) -> None:
        """The rows of ``segments``' split, set once: ``fit_rows`` and ``held_rows`` (masks
        over every row); ``u_fit`` and ``y_fit``, what the fits run over (every row up to
        the last fit row; y NaN, not measured, where a row is not a fit row); ``fit_obs``,
        which rows of ``u_fit`` are fit rows."""
        self.segments = segments
        self.fit_rows = np.zeros(self.u_v.size, dtype=bool)
        self.held_rows = np.zeros(self.u_v.size, dtype=bool)
        for s in segments:
            self.fit_rows[s.start:s.cut] = True
            self.held_rows[s.cut:s.stop] = True
        measured = np.isfinite(self.y_mm)
        self.fit_rows &= measured
        self.held_rows &= measured
        for s in segments:   # (whole(): no held-out part)
            for part, rows, a, b in (("fit", self.fit_rows, s.start, s.cut),
                                     ("held-out", self.held_rows, s.cut, s.stop)):
                if b > a and not rows[a:b].any():
                    raise ValueError(f"{s.name}: its {part} part has no measured sample")
        self.fit_end = int(np.flatnonzero(self.fit_rows)[-1]) + 1
        self.u_fit = self.u_v[:self.fit_end]
        self.y_fit = np.where(self.fit_rows, self.y_mm, np.nan)[:self.fit_end]
        self.fit_obs = self.fit_rows[:self.fit_end]

    def whole(self) -> DiagnosisRecord:
        """These records with every measured row a fit row: where a parameter is estimated
        once the held-out rows have decided."""
        out = copy.copy(self)
        out._split(tuple(replace(s, cut=s.stop) for s in self.segments))
        out.excitation = replace(self.excitation, fit_span_s=self.excitation.span_s)
        return out

    def judged_error(self, y_model: np.ndarray, effect: str | None = None) -> np.ndarray:
        """``y_model - y`` over the judged held-out rows (``y_model`` over every row), those
        of ``effect``'s probes where the records have them."""
        return (y_model - self.y_mm)[self.judged_for(effect)]

    def judged_segments(self, effect: str | None = None) -> np.ndarray:
        """Which joined record (its index in ``segments``) each of ``effect``'s judged rows
        belongs to."""
        starts = np.array([s.start for s in self.segments])
        return np.searchsorted(starts, np.flatnonzero(self.judged_for(effect)), "right") - 1

    def judged_for(self, effect: str | None = None) -> np.ndarray:
        """The judged rows ``effect``'s test uses: its probes' held-out rows where a record
        played from an experiment has them, else every judged row."""
        return self.probe_rows.get(effect, self.judged)

    def _probe_rows(self, parts_per_record) -> dict[str, np.ndarray]:
        """Effect -> the judged rows of the held-out probes designed for it (or that decide it
        too, :attr:`ExperimentPart.also`)."""
        out: dict[str, np.ndarray] = {}
        for seg, parts in zip(self.segments, parts_per_record, strict=True):
            for p in parts:
                a = seg.start + int(round(p.start_s / self.dt_s))
                b = min(seg.stop, a + int(round(p.duration_s / self.dt_s)))
                if not p.effect or a < seg.cut:
                    continue
                for effect in (p.effect, *p.also):
                    out.setdefault(effect, np.zeros(self.u_v.size, dtype=bool))[a:b] = True
        return {k: v & self.judged for k, v in out.items() if (v & self.judged).any()}

    # -- what the excitation can show ------------------------------------------------------
    def _excitation(self) -> Excitation:
        c, u, dt = self.config, self.u_v, self.dt_s
        holds_fit = holds_held = steps = 0
        for s in self.segments:
            ui = u[s.start:s.stop]
            for a, b in find_holds(ui, dt, c.hold_min_s):
                holds_fit += b <= s.cut - s.start
                holds_held += a >= s.cut - s.start
            jumps = np.abs(np.diff(ui[:s.cut - s.start])) >= c.step_share * np.ptp(ui)
            steps += int(np.sum(jumps[1:] & ~jumps[:-1]) + (jumps[0] if jumps.size else 0))
        measured = self.fit_rows | self.held_rows
        fit_u = u[self.fit_rows]
        return Excitation(
            span_s=max(s.stop - s.start for s in self.segments) * dt,
            fit_span_s=max(s.cut - s.start for s in self.segments) * dt,
            holds_fit=holds_fit, holds_held=holds_held, steps_fit=steps,
            near_zero_share=float(np.mean(np.abs(fit_u) < c.dead_zone_max_v)),
            near_zero_held_share=float(np.mean(
                np.abs(u[self.judged_for("dead_zone")]) < c.dead_zone_max_v)),
            u_min_v=float(u[measured].min()), u_max_v=float(u[measured].max()),
            noise_floor_mm=noise_floor(self.y_mm[measured]),
            judged_share=float(self.judged.sum() / max(1, self.held_rows.sum())))

    def _judged(self) -> np.ndarray:
        """Held-out rows the decision uses: those whose voltage stayed within the fit rows'
        range for the last ``settle_s`` (beyond it every model extrapolates, and a block can
        win there by extrapolating differently, not by being the effect)."""
        fit_u = self.u_v[self.fit_rows]
        lo, hi = fit_u.min(), fit_u.max()
        out = ((self.u_v < lo) | (self.u_v > hi)).astype(float)
        n = max(1, int(round(self.config.settle_s / self.dt_s)))
        recent = np.convolve(out, np.ones(n), mode="full")[:out.size] > 0
        judged = self.held_rows & ~recent
        return judged if judged.sum() >= 0.5 * self.held_rows.sum() else self.held_rows.copy()

    @property
    def margin_mm2(self) -> float:
        """The materiality margin (mm^2): ``material_noise_share`` x the noise floor squared."""
        return self.config.material_noise_share * self.excitation.noise_floor_mm ** 2

    def power_share_above(self, f_hz: float) -> float:
        """Share of the fit parts' input power (each part's mean removed) above ``f_hz``."""
        above = total = 0.0
        for s in self.segments:
            x = self.u_v[s.start:s.cut] - self.u_v[s.start:s.cut].mean()
            p = np.abs(np.fft.rfft(x)) ** 2
            f = np.fft.rfftfreq(x.size, self.dt_s)
            above, total = above + float(p[f > f_hz].sum()), total + float(p[1:].sum())
        return above / total if total > 0 else 0.0
