"""What ``ipmc bringup`` prints while the graph runs, and at its end (no ROS import).

- :class:`LogTail` reads the lines a node has added to its log file since the last read;
  :func:`alarm_line` picks the warnings and errors among them (rclpy's ``[WARN]``,
  ``[ERROR]``, ``[FATAL]`` lines and a node's one-sentence ``<node>: error: ...``) and prefixes
  the node's name, so they reach the console as they happen.
- :class:`RunStats` counts the displacement samples, keeps the reference and the
  displacement by stamp (the tracking error), the driver's link state and faults, and the
  warnings; it renders the progress line and the end-of-run summary. ``bringup`` feeds it from
  an in-process subscriber; at the end, from the bag when one was recorded (every sample, not
  only those a console subscriber kept up with).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

_ALARM = re.compile(r"^\[(WARN|ERROR|FATAL)\]|^\S+: error: ")
#: The start of a tracking run (the loop closing, the feedforward's history filling) left out
#: of the tracking RMSE, s.
SKIP_S = 2.0


class LogTail:
    """The complete lines appended to a text file since the previous :meth:`read`."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._offset = 0
        self._partial = ""

    def read(self) -> list[str]:
        try:
            with self.path.open("r", errors="replace") as f:
                f.seek(self._offset)
                text = f.read()
                self._offset = f.tell()
        except OSError:
            return []
        lines = (self._partial + text).split("\n")
        self._partial = lines.pop()
        return lines


def alarm_line(node: str, line: str) -> str | None:
    """``"[node] line"`` for a warning or an error line of a node's log, else None."""
    return f"[{node}] {line.rstrip()}" if _ALARM.search(line) else None


def is_error(line: str) -> bool:
    return "[ERROR]" in line or "[FATAL]" in line or ": error: " in line


@dataclass
class RunStats:
    """Counts and series of one run; times in seconds of the console's monotonic clock."""

    started_s: float
    samples: int = 0
    first_sample_s: float | None = None
    displacement_mm: dict[int, float] = field(default_factory=dict)
    reference_mm: dict[int, float] = field(default_factory=dict)
    link_state: str | None = None
    link_faults: int = 0
    link_values: dict[str, str] = field(default_factory=dict)
    warnings: int = 0
    errors: int = 0

    def on_sample(self, stamp_ns: int, y_mm: float, now_s: float) -> None:
        self.samples += 1
        if self.first_sample_s is None:
            self.first_sample_s = now_s
        self.displacement_mm[stamp_ns] = y_mm

    def on_reference(self, stamp_ns: int, r_mm: float) -> None:
        self.reference_mm[stamp_ns] = r_mm

    def on_link(self, values: dict[str, str]) -> None:
        """The driver's ``link`` diagnostics values (``state``, ``connections``, ...): a
        fault is a connected link that was lost, seen here or counted by reconnections."""
        state = values.get("state")
        if self.link_state == "connected" and state != "connected":
            self.link_faults += 1
        self.link_state = state
        self.link_values = dict(values)
        try:
            reconnections = int(values.get("connections", "0")) - 1
        except ValueError:
            reconnections = 0
        self.link_faults = max(self.link_faults, reconnections)

    def on_alarm(self, line: str) -> None:
        if is_error(line):
            self.errors += 1
        else:
            self.warnings += 1

    def rate_hz(self, now_s: float) -> float:
        """Samples per wall second since the first one."""
        if self.first_sample_s is None or now_s <= self.first_sample_s:
            return 0.0
        return self.samples / (now_s - self.first_sample_s)

    def progress_line(self, now_s: float, total_samples: int | None = None) -> str:
        """``"12.0 s: 1187 samples, 99.8 per s, link connected"`` (samples per wall second: a
        lock-step plant runs faster than real time), and the share of
        ``total_samples`` (an excitation's length) seen so far."""
        elapsed_s = now_s - self.started_s
        text = f"{elapsed_s:6.1f} s: {self.samples} samples, {self.rate_hz(now_s):.1f} per s"
        if self.link_state is not None:
            text += f", link {self.link_state}"
        if total_samples:
            text += f", {min(100.0, 100.0 * self.samples / total_samples):.0f} % played"
        rmse = self.tracking_rmse_mm()
        if rmse is not None:
            text += f", tracking RMSE {rmse[0]:.4f} mm"
        if self.warnings or self.errors:
            text += f", {self.warnings} warnings, {self.errors} errors"
        return text

    def tracking_rmse_mm(self, skip_s: float = SKIP_S) -> tuple[float, int] | None:
        """RMSE (mm) of displacement minus reference, and the samples it covers: the reference
        interpolated at each displacement stamp within its span, the first ``skip_s`` after
        the reference's start left out; None without a reference."""
        return tracking_rmse_mm(self.reference_mm, self.displacement_mm, skip_s)


def tracking_rmse_mm(reference_mm: dict[int, float], displacement_mm: dict[int, float],
                     skip_s: float = SKIP_S) -> tuple[float, int] | None:
    """See :meth:`RunStats.tracking_rmse_mm`; both map a stamp (ns) to a value (mm)."""
    if len(reference_mm) < 2 or not displacement_mm:
        return None
    t_r = np.array(sorted(reference_mm), dtype=np.int64)
    r = np.array([reference_mm[k] for k in t_r])
    t_y = np.array(sorted(displacement_mm), dtype=np.int64)
    y = np.array([displacement_mm[k] for k in t_y])
    keep = (t_y >= t_r[0] + int(skip_s * 1e9)) & (t_y <= t_r[-1])
    if not keep.any():
        return None
    err = y[keep] - np.interp((t_y[keep] - t_r[0]) * 1e-9, (t_r - t_r[0]) * 1e-9, r)
    return float(math.sqrt(np.mean(err * err))), int(keep.sum())


def summary_lines(stats: RunStats, *, elapsed_s: float, log_dir: Path, bag: Path | None,
                  samples: int | None = None, sample_rate_hz: float | None = None,
                  rmse: tuple[float, int] | None = None, rig: bool = False) -> list[str]:
    """The end-of-run summary; ``samples``, ``sample_rate_hz`` and ``rmse`` from the bag
    when one was recorded, else from ``stats``."""
    n = stats.samples if samples is None else samples
    rate = stats.rate_hz(stats.started_s + elapsed_s) if sample_rate_hz is None \
        else sample_rate_hz
    lines = [f"summary: {elapsed_s:.1f} s, {n} samples"
             + (f" recorded in {bag}" if bag else "") + f", {rate:.1f} Hz"]
    if rig:
        v = stats.link_values
        lines.append(f"link: {stats.link_faults} faults, state {stats.link_state or 'unknown'}, "
                     f"{v.get('dropped', '?')} frames dropped, {v.get('rig_errors', '?')} rig "
                     "errors")
    if rmse is not None:
        lines.append(f"tracking RMSE {rmse[0]:.4f} mm over {rmse[1]} samples (the first "
                     f"{SKIP_S:g} s left out)")
    lines.append(f"{stats.warnings} warnings, {stats.errors} errors; logs in {log_dir}")
    return lines


def bag_figures(bag: str | Path, *, with_reference: bool, until_ns: int | None = None
                ) -> dict:
    """``samples``, ``sample_rate_hz`` (from the stamps) and ``rmse`` (with the reference)
    of a bag's ``/ipmc/displacement`` (and ``/ipmc/reference``), as :func:`summary_lines`
    takes them; the RMSE covers the samples stamped up to ``until_ns`` (the loop's last
    sample before the nodes were stopped: a plant that outlives its controller holds the
    last command). Raises ``ValueError`` for a bag that cannot be read."""
    from ipmc_driver.dataio import read_stamped_series

    point = "geometry_msgs/msg/PointStamped"
    wanted = {"/ipmc/displacement": point}
    if with_reference:
        wanted["/ipmc/reference"] = point
    series = read_stamped_series(bag, wanted)
    y = {k: v * 1e3 for k, v in series["/ipmc/displacement"].items()}
    span_s = (max(y) - min(y)) * 1e-9 if len(y) > 1 else 0.0
    rmse = None
    if with_reference:
        closed = {k: v for k, v in y.items() if until_ns is None or k <= until_ns}
        rmse = tracking_rmse_mm({k: v * 1e3 for k, v in series["/ipmc/reference"].items()},
                                closed)
    return {"samples": len(y), "sample_rate_hz": (len(y) - 1) / span_s if span_s else 0.0,
            "rmse": rmse}
