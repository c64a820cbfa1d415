"""The sample grid of a simulated rig that runs on a wall clock (pure core, no ROS).

A timer cannot promise its period: under load it fires late and skips the periods it missed.
Counting the timer's ticks then puts the sample stamps further and further behind the clock
(a plant that stamps ``start + n x period`` was 33 s behind after 14 minutes of a loaded
machine). :class:`SampleClock` derives the samples due from the clock instead: sample ``k`` is
stamped ``t0 + k x period`` and is due once the clock has passed the end of its period, so a
late tick produces the samples it missed (a catch-up burst, at most ``max_burst``) and the
stamps stay with the clock. Samples beyond the burst are skipped (a gap) and counted.
:class:`RateReport` says whether the rate was held over a diagnostics period.
"""

from __future__ import annotations

from dataclasses import dataclass

# A catch-up burst stays below the subscribers' queue depth (100, ipmc_driver.qos.SAMPLE_QOS).
MAX_BURST = 90
# The achieved tick rate below this fraction of the requested rate: the rate is not held.
HELD_FRACTION = 0.95


@dataclass(frozen=True)
class RateReport:
    """One diagnostics period of a :class:`SampleClock`: requested and achieved rates (Hz),
    samples published late in catch-up bursts and samples skipped (gaps)."""

    requested_hz: float
    tick_hz: float
    sample_hz: float
    caught_up: int
    skipped: int

    @property
    def held(self) -> bool:
        """The timer kept the requested rate and no sample came late or was skipped."""
        return (self.tick_hz >= HELD_FRACTION * self.requested_hz and not self.caught_up
                and not self.skipped)

    @property
    def message(self) -> str:
        if self.held:
            return f"rate held: {self.sample_hz:.1f} Hz"
        return (f"rate not held: timer at {self.tick_hz:.1f} Hz of {self.requested_hz:g} Hz "
                f"requested; {self.caught_up} samples published late (stamped on time), "
                f"{self.skipped} skipped")


class SampleClock:
    """Which samples are due at a clock reading, on the grid ``t0_ns + k * period_ns``.

    Parameters
    ----------
    rate_hz : float
        Sample rate, Hz (> 0).
    max_burst : int
        Most samples one tick produces; older ones due are skipped.
    """

    def __init__(self, rate_hz: float, max_burst: int = MAX_BURST) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        self.rate_hz = float(rate_hz)
        self.period_ns = int(round(1e9 / rate_hz))
        self.max_burst = int(max_burst)
        self.t0_ns: int | None = None
        self.next_k = 0
        self.ticks = self.samples = self.caught_up = self.skipped = 0
        self._last = (0, 0, 0, 0)   # ticks, samples, caught_up, skipped at the last report
        self._last_report_ns: int | None = None

    def start(self, now_ns: int) -> None:
        """Time starts: sample 0 is the period that begins at ``now_ns``."""
        self.t0_ns = int(now_ns)
        self._last_report_ns = self.t0_ns

    def due(self, now_ns: int) -> tuple[range, int]:
        """The sample indices to produce at ``now_ns``, and how many older ones are skipped.

        Sample ``k`` covers the period ending at ``t0 + (k + 1) * period``; it is due when the
        clock is within half a period of that end (a timer fires a little early or late).
        """
        if self.t0_ns is None:
            self.start(now_ns)
        self.ticks += 1
        last_k = round((now_ns - self.t0_ns) / self.period_ns) - 1
        skipped = max(0, last_k + 1 - self.next_k - self.max_burst)
        first_k = self.next_k + skipped
        if last_k - first_k >= 1:
            self.caught_up += last_k - first_k
        self.skipped += skipped
        ks = range(first_k, max(first_k, last_k + 1))
        self.samples += len(ks)
        self.next_k = max(self.next_k, last_k + 1)
        return ks, skipped

    def stamp_ns(self, k: int) -> int:
        """The stamp of sample ``k``, ns."""
        return self.t0_ns + k * self.period_ns

    def report(self, now_ns: int) -> RateReport:
        """Rates and counts since the previous report (rates 0 before any time passed)."""
        dt_s = (now_ns - self._last_report_ns) * 1e-9 if self._last_report_ns is not None else 0
        counts = (self.ticks, self.samples, self.caught_up, self.skipped)
        d = [a - b for a, b in zip(counts, self._last, strict=True)]
        self._last, self._last_report_ns = counts, now_ns
        rate = (lambda n: n / dt_s) if dt_s > 0 else (lambda n: 0.0)
        return RateReport(self.rate_hz, rate(d[0]), rate(d[1]), d[2], d[3])
