"""Every threshold of the residual diagnosis, in one frozen object written into its report."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from ..hysteresis import DEFAULT_MEMORY_TAUS_S, MAP_BASES


@dataclass(frozen=True)
class DiagnosisConfig:
    """The diagnosis's thresholds; each has its one-line reason beside it."""

    #: The first share of the record fits, the rest judges (free run from the record's start).
    fit_share: float = 0.7
    #: Family-wise error of one round's tests, held by Holm's weighted step-down over its
    #: candidates.
    family_alpha: float = 0.05
    #: A block is material when it cuts the held-out mean squared error, both about each
    #: record's held-out mean and as it is, by at least this share of the sensor's noise
    #: variance: a smaller cut is below what the record can show.
    material_noise_share: float = 0.25
    #: Relaxations slower than this are creep; faster ones are the actuator's charging and
    #: back-relaxation (an IPMC in water settles within a few seconds), in the core model.
    creep_min_tau_s: float = 10.0
    #: A hold is the input still for this long: five times the back-relaxation (about 0.5 s),
    #: so that the fast dynamics have settled and what still moves is slow memory.
    hold_min_s: float = 3.0
    #: Holds needed in each of the fit and held-out parts to tell creep from path memory.
    min_holds: int = 1
    #: A step is a one-sample input change of at least this share of the input's range.
    step_share: float = 0.1
    #: Steps needed in the fit part to tell a transport delay from the charging lag.
    min_steps: int = 3
    #: Share of the input's power above the charging corner (1 / (2 pi tau)) that also tells a
    #: delay from that lag (there the lag's phase levels off and a delay's keeps growing).
    delay_power_share: float = 0.1
    #: Widest dead zone searched (V), and the share of fit samples with |u| below it needed.
    dead_zone_max_v: float = 1.0
    dead_zone_min_share: float = 0.05
    #: A charging current is told from the input's sample difference when at least this share
    #: of a step's current energy comes after the step's own sample (exp(-2 dt / tau) for the
    #: first-order charging); below it, the current is mostly that one sample.
    rate_min_lagged_share: float = 0.5
    #: Longest transport delay searched (s).
    max_delay_s: float = 0.5
    #: Held-out samples within this time after the voltage left the fit part's range are not
    #: judged: the charge and the back-relaxation (time constants <= 0.5 s) carry the
    #: excursion for a few of their time constants.
    settle_s: float = 2.0
    #: Power the held-out test needs at the gain the fit rows show to reject a block the fit
    #: rows support (the conventional 80 % of a study's design); below it, undecided.
    min_power: float = 0.8
    #: Rounds of the forward search (one effect accepted per round).
    max_rounds: int = 4
    #: Channels (the charge, then the fastest relaxations) whose direction memory the core
    #: model carries; 0 leaves it out: on a fit part of a few thousand samples its weights
    #: are poorly determined, and which records a core with it misfits (a held-out error
    #: twice the core's without it on some) changes with the seed, not with the plant.
    core_direction_channels: int = 0
    #: The core model's output map between its knots (``GeneralizedPI.map_basis``): hinges.
    #: A quadratic spline follows the bending's smooth stiffening without kinks and brings
    #: the clean records and the held-out error after an effect closer to their goals, but
    #: names one effect right less often on the set no design choice read (docs/diagnose.md).
    core_map: str = "linear"

    def __post_init__(self) -> None:
        if not 0.3 <= self.fit_share <= 0.9:
            raise ValueError(f"fit_share must be in [0.3, 0.9], got {self.fit_share}")
        if not 0 < self.min_power < 1:
            raise ValueError(f"min_power must be in (0, 1), got {self.min_power}")
        if not 0 < self.rate_min_lagged_share < 1:
            raise ValueError(f"rate_min_lagged_share must be in (0, 1), got "
                             f"{self.rate_min_lagged_share}")
        if not 0 < self.family_alpha < 0.5:
            raise ValueError(f"family_alpha must be in (0, 0.5), got {self.family_alpha}")
        positive = ("material_noise_share", "creep_min_tau_s", "hold_min_s", "step_share",
                    "dead_zone_max_v", "max_delay_s")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.max_rounds < 1 or self.min_holds < 1 or self.min_steps < 1:
            raise ValueError("max_rounds, min_holds and min_steps must be >= 1")
        channels = 1 + len(self.core_memory_taus_s)
        if not 0 <= self.core_direction_channels <= channels:
            raise ValueError(f"core_direction_channels must be in [0, {channels}] (the "
                             f"charge and its relaxations below creep_min_tau_s), got "
                             f"{self.core_direction_channels}")

        if self.core_map not in MAP_BASES:
            raise ValueError(f"core_map must be one of {sorted(MAP_BASES)}, got "
                             f"{self.core_map!r}")

    @property
    def core_memory_taus_s(self) -> tuple[float, ...]:
        """The core model's relaxations (s): the model's default bank below creep_min_tau_s."""
        return tuple(t for t in DEFAULT_MEMORY_TAUS_S if t < self.creep_min_tau_s)

    def as_dict(self) -> dict:
        return asdict(self)
