"""Typed results of the residual diagnosis: evidence, outcome, rounds, the whole diagnosis."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING

import numpy as np

from ..hysteresis import GeneralizedPI

if TYPE_CHECKING:
    from .experiment import Experiment
from .config import DiagnosisConfig


class Outcome(StrEnum):
    ACCEPTED = "accepted"
    REJECTED = "rejected"
    NOT_TESTABLE = "not testable"


@dataclass(frozen=True)
class LossTest:
    """The held-out free-run loss differential d_k = e_current_k^2 - e_candidate_k^2 (mm^2)
    and its Diebold-Mariano test (HAC variance, one-sided: the candidate has less loss)."""

    mean_gain_mm2: float
    statistic: float
    p_value: float
    bandwidth_samples: int
    margin_mm2: float
    #: The HAC standard error (mm^2) of the mean gain of the errors about their means,
    #: what the statistic divides: what the test's power follows.
    standard_error_mm2: float = float("nan")
    #: The mean gain of the errors about their means (mm^2), what the statistic tests.
    centred_gain_mm2: float = float("nan")

    @property
    def short_of_margin(self) -> tuple[str, ...]:
        """The gains below the margin: the one the statistic tests (the errors' course about
        their held-out means; not judged when the test was made without it, NaN) and the one
        of the errors as they are (a block must not move their level away)."""
        gains = (("about the held-out mean", self.centred_gain_mm2),
                 ("of the errors as they are", self.mean_gain_mm2))
        return tuple(w for w, g in gains if not math.isnan(g) and g < self.margin_mm2)

    @property
    def material(self) -> bool:
        """Both gains reach the margin (:attr:`short_of_margin` is empty)."""
        return not self.short_of_margin


@dataclass(frozen=True)
class FitScreen:
    """Whether the fit rows support a candidate's block: the likelihood ratio
    ``n_eff ln(SSE_current / SSE_candidate)`` of the fit rows' free-run errors, at the current
    model's effective sample size, against chi2(``n_params``) at the family's level."""

    likelihood_ratio: float
    needed: float
    effective_samples: float
    n_params: int
    #: The fit rows' mean squared error the block removes (mm^2): the held-out gain it
    #: predicts if the block is the effect.
    mean_gain_mm2: float = float("nan")

    @property
    def passed(self) -> bool:
        return self.likelihood_ratio >= self.needed


@dataclass(frozen=True)
class RecordShare:
    """One joined record's part in a candidate's test: its judged held-out RMSE with the
    current model and with the candidate, and the mean loss differential there (mm^2)."""

    record: str
    rmse_current_mm: float
    rmse_candidate_mm: float
    mean_gain_mm2: float


@dataclass(frozen=True)
class Evidence:
    """What one candidate showed in one round."""

    rmse_current_mm: float
    rmse_candidate_mm: float
    test: LossTest
    params: dict
    scan: str = ""
    p_holm: float = 1.0
    screen: FitScreen | None = None
    #: Each record's share when several are diagnosed at once (which record decided).
    records: tuple[RecordShare, ...] = ()
    #: Where the candidate was judged when not on every judged held-out row (its probe's).
    judged_on: str = ""

    def as_dict(self) -> dict:
        d = asdict(self)
        d["material"] = self.test.material
        if self.screen is not None:
            d["screen"]["passed"] = self.screen.passed
        return d


@dataclass(frozen=True)
class CandidateResult:
    """One candidate's outcome in one round, with the reason in one sentence."""

    name: str
    outcome: Outcome
    reason: str
    round: int
    evidence: Evidence | None = None

    @property
    def accepted(self) -> bool:
        return self.outcome is Outcome.ACCEPTED

    def as_dict(self) -> dict:
        return {"name": self.name, "outcome": self.outcome.value, "accepted": self.accepted,
                "reason": self.reason, "round": self.round,
                "evidence": None if self.evidence is None else self.evidence.as_dict()}


@dataclass(frozen=True)
class Round:
    """One round of the search: every candidate's result and the effect it accepted."""

    number: int
    rmse_start_mm: float
    results: tuple[CandidateResult, ...]
    accepted: str | None


@dataclass
class Diagnosis:
    """The whole diagnosis of one record, or of several joined (``segments``: where each
    is, rests at 0 V between them)."""

    t_s: np.ndarray
    u_v: np.ndarray
    y_mm: np.ndarray
    held_rows: np.ndarray
    segments: tuple
    config: DiagnosisConfig
    given_model: bool
    model_before: GeneralizedPI
    model_after: GeneralizedPI
    rounds: list[Round] = field(default_factory=list)
    noise_floor_mm: float = float("nan")
    seconds: float = 0.0
    excitation: dict = field(default_factory=dict)
    #: The experiment that would decide the not-testable candidates and pin down the accepted
    #: ones the record left open (None: nothing to run).
    next_experiment: Experiment | None = None
    #: Effects an earlier record decided: in ``model_before`` from the start, not judged here.
    known: tuple[str, ...] = ()

    @property
    def effects_found(self) -> list[str]:
        return [r.accepted for r in self.rounds if r.accepted]

    @property
    def candidates(self) -> list[CandidateResult]:
        """Each candidate's last result (accepted ones in the round that accepted them)."""
        last: dict[str, CandidateResult] = {}
        for rnd in self.rounds:
            for res in rnd.results:
                if res.name not in last or not last[res.name].accepted:
                    last[res.name] = res
        return list(last.values())

    def held_out_rmse(self, model: GeneralizedPI) -> float:
        """Free-run RMSE (mm) over every held-out row."""
        e = (model.simulate(self.u_v) - self.y_mm)[self.held_rows]
        return float(np.sqrt(np.mean(e ** 2)))

    def record_rmse(self, model: GeneralizedPI) -> dict[str, float]:
        """Free-run RMSE (mm) over each record's held-out rows."""
        e = np.where(self.held_rows, model.simulate(self.u_v) - self.y_mm, np.nan)
        return {s.name: float(np.sqrt(np.nanmean(e[s.cut:s.stop] ** 2)))
                for s in self.segments}

    @property
    def rmse_before_mm(self) -> float:
        return self.held_out_rmse(self.model_before)

    @property
    def rmse_after_mm(self) -> float:
        return self.held_out_rmse(self.model_after)
