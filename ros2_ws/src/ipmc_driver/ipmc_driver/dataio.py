"""Load and save IPMC records: ``t,u,y`` CSV files (s, V, mm) and rosbag2 folders.

Pure core: NumPy and ``rosbags`` only, never ``rclpy``. Every refusal is a :class:`DataError`
with one sentence that names the file and what is wrong with it.
"""

from __future__ import annotations

import argparse
import csv
import io
import os
import secrets
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .validation import check_output_file

__all__ = ["DataError", "ImplausibleDataWarning", "LostSamplesWarning", "Record",
           "check_plausibility", "export_main", "fill_gaps", "load_record", "save_csv",
           "write_atomic"]

VOLTAGE_TOPIC = "/ipmc/voltage"
DISPLACEMENT_TOPIC = "/ipmc/displacement"
VOLTAGE_TYPE = "geometry_msgs/msg/Vector3Stamped"
DISPLACEMENT_TYPE = "geometry_msgs/msg/PointStamped"
CSV_COLUMNS = ("t", "u", "y")
MIN_SAMPLES = 10
MAX_JITTER = 0.05


class DataError(ValueError):
    """A data file or bag cannot be turned into a :class:`Record`; the message says why."""


@dataclass(frozen=True, eq=False)
class Record:
    """One experiment: input voltage and tip displacement sampled at common instants.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Sampling instants, s.
    u_v : ndarray, shape (N,)
        Applied voltage, V.
    y_mm : ndarray, shape (N,)
        Tip displacement, mm.
    """

    t_s: np.ndarray
    u_v: np.ndarray
    y_mm: np.ndarray

    def __post_init__(self):
        arrays = {}
        for name in ("t_s", "u_v", "y_mm"):
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.ndim != 1:
                raise DataError(f"Record.{name} must be 1-D, got shape {arr.shape}.")
            arrays[name] = arr
            object.__setattr__(self, name, arr)
        lengths = {len(a) for a in arrays.values()}
        if len(lengths) != 1:
            desc = ", ".join(f"{k} has {len(v)}" for k, v in arrays.items())
            raise DataError(f"Record arrays must have one length: {desc}.")

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def dt_s(self) -> float:
        """Median sampling interval, s (NaN with fewer than 2 samples)."""
        return float(np.median(np.diff(self.t_s))) if len(self) > 1 else float("nan")

    @property
    def rate_hz(self) -> float:
        """Sampling rate, Hz (1 / :attr:`dt_s`)."""
        return 1.0 / self.dt_s

    def __repr__(self) -> str:
        if len(self) > 1:
            return f"Record(n={len(self)}, duration_s={self.t_s[-1] - self.t_s[0]:.6g}, " \
                   f"rate_hz={self.rate_hz:.6g})"
        return f"Record(n={len(self)})"


def check_record(record: Record, *, source: str = "record", min_samples: int = MIN_SAMPLES,
                 max_jitter: float = MAX_JITTER, missing_y: bool = False) -> Record:
    """Raise :class:`DataError` unless ``record`` is finite, long enough and uniformly sampled.

    Parameters
    ----------
    record : Record
        The record to check.
    source : str
        What to call it in the message (a file name).
    min_samples : int
        Fewest samples accepted.
    max_jitter : float
        Largest accepted deviation of one sampling interval from the median interval, as a
        fraction of the median interval. A missing sample (a gap) is an interval of about twice
        the median: it is refused for any ``max_jitter`` below 1.
    missing_y : bool
        Accept NaN in ``y_mm`` (a sample not measured, :func:`fill_gaps`); ``min_samples``
        then counts the measured ones. Time and voltage must be finite regardless.

    Returns
    -------
    Record
        ``record`` itself.
    """
    n = int(np.isfinite(record.y_mm).sum()) if missing_y else len(record)
    if n < min_samples:
        measured = " measured" if missing_y else ""
        raise DataError(f"{source} has too few{measured} samples: {n}, need at least "
                        f"{min_samples}.")
    for name, unit in (("t_s", "s"), ("u_v", "V"), ("y_mm", "mm")):
        arr = getattr(record, name)
        # with missing_y, NaN in y is a sample not measured; inf is never a measurement
        bad = np.flatnonzero(np.isinf(arr) if missing_y and name == "y_mm"
                             else ~np.isfinite(arr))
        if bad.size:
            i = int(bad[0])
            raise DataError(
                f"{source} has {bad.size} non-finite (NaN or inf) value(s) in {name} ({unit}), "
                f"the first at sample {i} (t = {record.t_s[i]:.6g} s).")
    if len(record) < 2:
        return record
    dt = np.diff(record.t_s)
    if np.any(dt <= 0):
        i = int(np.flatnonzero(dt <= 0)[0])
        raise DataError(
            f"{source} has unsorted or repeated time: t[{i + 1}] = {record.t_s[i + 1]:.9g} s "
            f"does not follow t[{i}] = {record.t_s[i]:.9g} s.")
    med = float(np.median(dt))
    dev = np.abs(dt - med) / med
    if np.any(dev > max_jitter):
        i = int(np.argmax(dev > max_jitter))
        kind = "a gap" if dt[i] > 1.5 * med else "an irregular interval"
        raise DataError(
            f"{source} has irregular time: {kind} of {dt[i]:.6g} s between t = "
            f"{record.t_s[i]:.9g} s and {record.t_s[i + 1]:.9g} s, against a median interval "
            f"of {med:.6g} s (tolerance {max_jitter:.0%}).")
    return record


def fill_gaps(record: Record, *, source: str = "record",
              max_jitter: float = MAX_JITTER) -> tuple[Record, str | None]:
    """Put ``record`` on the regular grid of its median interval, its lost samples as rows
    that were not measured.

    An interval of about k median intervals (within ``max_jitter`` of one) lost k - 1
    samples: they become rows with ``y_mm`` NaN and ``u_v`` held at the last voltage (the
    rig's H-bridge holds its last command from one sample to the next). Where only the
    displacement of a sample was lost, its voltage is kept; where only the voltage, the last
    one is held. A model runs through such rows; a fit or an error uses the measured ones.

    Returns
    -------
    (Record, str or None)
        The regular record, and one sentence on what was lost (None when nothing was).

    Raises
    ------
    DataError
        An interval that is no whole number of median intervals, or time that does not
        increase.
    """
    t = record.t_s
    if len(record) < 2:
        return record, None
    dt = np.diff(t)
    if not np.all(np.isfinite(t)) or np.any(dt <= 0):  # check_record says which and where
        check_record(record, source=source, min_samples=0, max_jitter=max_jitter,
                     missing_y=True)
    med = float(np.median(dt))
    steps = np.maximum(1, np.round(dt / med)).astype(np.int64)
    dev = np.abs(dt - steps * med) / med
    if np.any(dev > max_jitter):
        i = int(np.argmax(dev > max_jitter))
        raise DataError(
            f"{source} has irregular time: an interval of {dt[i]:.6g} s between t = "
            f"{t[i]:.9g} s and {t[i + 1]:.9g} s is no whole number of the median interval "
            f"{med:.6g} s (tolerance {max_jitter:.0%}).")
    rows = np.concatenate([[0], np.cumsum(steps)])
    n = int(rows[-1]) + 1
    u, y = np.full(n, np.nan), np.full(n, np.nan)
    u[rows], y[rows] = record.u_v, record.y_mm
    y[np.isnan(u)] = np.nan   # its voltage lost: not a measurement the models can be fitted to
    held = np.maximum.accumulate(np.where(np.isfinite(u), np.arange(n), 0))
    filled = Record(t[0] + np.arange(n) * med, u[held], y)
    lost = int(np.sum(~np.isfinite(y)))
    if not lost:
        return filled, None
    gaps = steps[steps > 1]
    i = int(np.argmax(steps))
    where = (f" ({gaps.size} gap(s), the longest {(steps[i] - 1) * med:.3g} s after t = "
             f"{t[i]:.6g} s)" if gaps.size else "")
    note = (f"{source}: {lost} of {n} samples were not measured{where}; they are kept as "
            f"rows without a displacement, the voltage held")
    return filled, note


#: Plausibility of a record's values and units (:func:`check_plausibility`), with the reason
#: for each threshold. The H-bridge drives at most 3 V; 10 % over it is the voltage sensor's
#: error, beyond it the record was not driven through the H-bridge.
WARN_VOLTAGE_V = 3.3
#: An IPMC is driven at a few volts (its water electrolyses above that): a voltage beyond 10 V
#: never drove one; it is in another unit (mV) or of another device. Refused.
MAX_VOLTAGE_V = 10.0
#: An IPMC bender's tip moves well under 1 m (the strips are a few cm long): beyond it y is
#: not in mm (micrometres?). Refused.
MAX_DISPLACEMENT_MM = 1000.0
#: IPMC strips are at most about 100 mm long, so their tips do not move further: a warning.
WARN_DISPLACEMENT_MM = 100.0
#: A tip record in mm spans tenths of a millimetre or more; a span below the displacement
#: sensor's 0.04 mm resolution is a record in metres (20 mm of travel is 0.02 m): a warning.
MIN_SPAN_MM = 0.05
#: An IPMC responds within a second: a record sampled every 0.5 s or slower cannot show it;
#: such a time step is in milliseconds (10 ms at 100 Hz reads as 10): a warning.
MAX_STEP_S = 0.5


class LostSamplesWarning(UserWarning):
    """A record lost samples, kept as rows not measured (:func:`fill_gaps`)."""


class ImplausibleDataWarning(UserWarning):
    """A record's values look like another unit than s, V and mm (see
    :func:`check_plausibility`)."""


def check_plausibility(record: Record, *, source: str = "record",
                       allow_implausible: bool = False) -> list[str]:
    """Check that ``record``'s values can be an IPMC record in s, V and mm; pure.

    What cannot be one (|u| above :data:`MAX_VOLTAGE_V`, |y| above
    :data:`MAX_DISPLACEMENT_MM`) is refused unless ``allow_implausible``; what is unlikely
    (|u| beyond the H-bridge's 3 V, |y| above :data:`WARN_DISPLACEMENT_MM`, y spanning less
    than :data:`MIN_SPAN_MM`, time steps of :data:`MAX_STEP_S` or more) is returned as
    warnings. Non-finite values and time that does not increase are :func:`check_record`'s
    refusals, not lifted by ``allow_implausible``: no model runs on them.

    Parameters
    ----------
    record : Record
        A record that passed :func:`check_record`.
    source : str
        What to call it in the messages (a file name).
    allow_implausible : bool
        Return the refusals as warnings instead of raising.

    Returns
    -------
    list of str
        One sentence per warning, each naming the likely cause.

    Raises
    ------
    DataError
        The first refusal, one sentence naming ``source``.
    """
    u_peak_v = float(np.max(np.abs(record.u_v), initial=0.0))
    y_peak_mm = float(np.max(np.abs(record.y_mm), initial=0.0))
    y_span = float(np.ptp(record.y_mm)) if len(record) else 0.0
    refusals, notes = [], []
    if u_peak_v > MAX_VOLTAGE_V:
        unit = ("looks like millivolts; ipmc expects V" if u_peak_v / 1e3 <= WARN_VOLTAGE_V
                else "no IPMC is driven at that")
        refusals.append(f"{source}: u reaches {u_peak_v:.4g} V, far beyond the H-bridge's 3 V "
                        f"({unit})")
    elif u_peak_v > WARN_VOLTAGE_V:
        notes.append(f"{source}: u reaches {u_peak_v:.4g} V, beyond the H-bridge's 3 V: the "
                     "record was not driven through it, or its voltage is scaled.")
    if y_peak_mm > MAX_DISPLACEMENT_MM:
        refusals.append(f"{source}: y reaches {y_peak_mm:.4g}, beyond 1 m while an IPMC tip "
                        "moves well under it (looks like micrometres; ipmc expects mm)")
    elif y_peak_mm > WARN_DISPLACEMENT_MM:
        notes.append(f"{source}: y reaches {y_peak_mm:.4g} mm, further than an IPMC strip is "
                     "long: is it in another unit? ipmc expects mm.")
    if 0.0 < y_span < MIN_SPAN_MM:
        notes.append(f"{source}: y spans {y_span:.2g} - looks like metres; ipmc expects mm (a "
                     f"tip record in mm spans more than {MIN_SPAN_MM:g} mm).")
    if len(record) > 1 and record.dt_s >= MAX_STEP_S:
        notes.append(f"{source}: t steps by {record.dt_s:.4g} - looks like milliseconds; ipmc "
                     f"expects s (a record at {record.rate_hz:.3g} Hz cannot show an IPMC's "
                     "response).")
    if refusals and not allow_implausible:
        raise DataError(f"{refusals[0]}; --allow-implausible accepts it.")
    return [f"{r}." for r in refusals] + notes


def stamp_ns(stamp) -> int:
    """A ``builtin_interfaces/Time`` (anything with ``sec`` and ``nanosec``) as integer ns: the
    exact key samples, commands and references are paired by."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def load_record(path, *, voltage_topic: str = VOLTAGE_TOPIC,
                displacement_topic: str = DISPLACEMENT_TOPIC, min_samples: int = MIN_SAMPLES,
                max_jitter: float = MAX_JITTER, allow_implausible: bool = False,
                notes: list[str] | None = None, gaps: bool = False) -> Record:
    """Load a record from a ``t,u,y`` CSV file or a rosbag2 folder (MCAP or sqlite3).

    Parameters
    ----------
    path : str or os.PathLike
        A CSV file with header ``t,u,y`` (s, V, mm; more columns are ignored), or a rosbag2
        folder (or a single ``.mcap`` / ``.db3`` file) holding the two topics below.
    voltage_topic : str
        ``geometry_msgs/msg/Vector3Stamped`` topic; ``vector.x`` is the applied voltage, V.
    displacement_topic : str
        ``geometry_msgs/msg/PointStamped`` topic; ``point.x`` is the displacement, m (converted
        to mm here).
    min_samples : int
        Fewest samples accepted.
    max_jitter : float
        Accepted deviation of a sampling interval from the median, a fraction of it.
    allow_implausible : bool
        Accept values no IPMC record has (:func:`check_plausibility`), with a warning.
    notes : list of str, optional
        Receives :func:`check_plausibility`'s warnings (a command prints them); without it
        they are issued as :class:`ImplausibleDataWarning` (and the note on lost samples
        as :class:`LostSamplesWarning`).
    gaps : bool
        Keep a record that lost samples (a rig's link or a loaded recorder drops some): they
        are rows with ``y_mm`` NaN and the voltage held (:func:`fill_gaps`), and a note says
        how many. For a consumer that runs models through such rows (the diagnosis); without
        it a gap is refused.

    Returns
    -------
    Record
        For a bag, voltage and displacement samples are paired by header stamp and ``t_s``
        counts from the first pair (t_s[0] = 0).

    Raises
    ------
    DataError
        NaN, unsorted or irregular time, too few samples, missing columns or topics, values
        no IPMC record has, or an unreadable file; the message is one sentence naming the file.
    """
    p = Path(path)
    if not p.exists():
        raise DataError(f"{p} does not exist.")
    if p.is_dir() or p.suffix in (".mcap", ".db3"):
        record = _load_bag(p, voltage_topic, displacement_topic, keep_unpaired=gaps)
    else:
        record = _load_csv(p)
    lost = None
    if gaps:
        record, lost = fill_gaps(record, source=str(p), max_jitter=max_jitter)
    check_record(record, source=str(p), min_samples=min_samples, max_jitter=max_jitter,
                 missing_y=gaps)
    found = check_plausibility(record, source=str(p), allow_implausible=allow_implausible)
    if notes is None:
        if lost:
            warnings.warn(lost + ".", LostSamplesWarning, stacklevel=2)
        for note in found:
            warnings.warn(note, ImplausibleDataWarning, stacklevel=2)
    else:
        notes.extend(([lost + "."] if lost else []) + found)
    return record


def _load_csv(path: Path) -> Record:
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path} cannot be read as a CSV file: {exc}.") from None
    if not rows:
        raise DataError(f"{path} is empty; expected a header line 't,u,y' (s, V, mm).")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in CSV_COLUMNS if c not in header]
    if missing:
        raise DataError(
            f"{path} lacks column(s) {', '.join(missing)} in its header {','.join(header)!r}; "
            f"expected a header line 't,u,y' (s, V, mm).")
    cols = [header.index(c) for c in CSV_COLUMNS]
    data = np.empty((len(rows) - 1, 3))
    n = 0
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or all(not cell.strip() for cell in row):
            continue  # blank lines (a trailing newline) carry no sample
        try:
            data[n] = [float(row[c]) for c in cols]
        except IndexError:
            raise DataError(
                f"{path} line {lineno} has {len(row)} field(s), fewer than the header's "
                f"{len(header)}.") from None
        except ValueError:
            raise DataError(
                f"{path} line {lineno} has a non-numeric value in {row!r}.") from None
        n += 1
    data = data[:n]
    return Record(data[:, 0], data[:, 1], data[:, 2])


def _load_bag(path: Path, voltage_topic: str, displacement_topic: str,
              keep_unpaired: bool = False) -> Record:
    if path.is_dir() and not (path / "metadata.yaml").exists():
        raise DataError(
            f"{path} is not a readable rosbag2 folder: it has no metadata.yaml (if its recorder "
            f"was killed, run 'ipmc bag-recover {path}' first).")
    if path.is_dir():
        # ipmc_driver.bagio writes the split in progress in a sub-folder of the bag.
        torn = sorted(f.name for d in path.iterdir() if d.is_dir()
                      for f in d.iterdir() if f.suffix in (".mcap", ".db3"))
        if torn:
            raise DataError(
                f"{path} has an unfinished split {torn[0]} (its recorder is still running or "
                f"was killed; run 'ipmc bag-recover {path}' to keep what it holds).")
    wanted = {voltage_topic: VOLTAGE_TYPE, displacement_topic: DISPLACEMENT_TYPE}
    samples = read_stamped_series(path, wanted)
    samples[displacement_topic] = {k: v * 1e3 for k, v in samples[displacement_topic].items()}
    return _pair(path, samples[voltage_topic], samples[displacement_topic],
                 voltage_topic, displacement_topic, keep_unpaired)



# The scalar each stamped message type carries (SI units, as on the topic).
_SCALAR_FIELD = {
    VOLTAGE_TYPE: lambda msg: msg.vector.x,
    DISPLACEMENT_TYPE: lambda msg: msg.point.x,
}


def read_stamped_series(path, wanted: dict[str, str]) -> dict[str, dict[int, float]]:
    """Read stamped scalar topics of a rosbag2 folder: ``{topic: {stamp_ns: value}}``.

    ``wanted`` maps topic -> message type (``geometry_msgs/msg/Vector3Stamped``: ``vector.x``;
    ``geometry_msgs/msg/PointStamped``: ``point.x``, in the topic's SI unit). Raises
    ``DataError`` for a missing topic, a wrong type, a repeated stamp or an unreadable bag.
    """
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    typestore = get_typestore(Stores.ROS2_JAZZY)
    samples: dict[str, dict[int, float]] = {topic: {} for topic in wanted}
    try:
        with Reader(path) as reader:
            conns = [c for c in reader.connections if c.topic in wanted]
            found = {c.topic for c in conns}
            missing = [t for t in wanted if t not in found]
            if missing:
                have = sorted({c.topic for c in reader.connections}) or ["none"]
                raise DataError(
                    f"{path} lacks topic(s) {', '.join(missing)}; it has {', '.join(have)}.")
            for c in conns:
                if c.msgtype != wanted[c.topic]:
                    raise DataError(
                        f"{path} topic {c.topic} has type {c.msgtype}, expected "
                        f"{wanted[c.topic]}.")
            duplicates = 0
            for conn, _t_ns, raw in reader.messages(connections=conns):
                msg = typestore.deserialize_cdr(raw, conn.msgtype)
                stamp = stamp_ns(msg.header.stamp)
                store = samples[conn.topic]
                duplicates += stamp in store
                store[stamp] = float(_SCALAR_FIELD[conn.msgtype](msg))
    except DataError:
        raise
    except (ReaderError, OSError, KeyError, ValueError, AssertionError) as exc:
        raise DataError(f"{path} cannot be read as a rosbag2 bag: {exc}".rstrip(".") + ".") \
            from None
    if duplicates:
        raise DataError(f"{path} has {duplicates} message(s) repeating a header stamp already "
                        f"seen on the same topic.")
    return samples

def _pair(path: Path, volts: dict[int, float], metres_mm: dict[int, float],
          voltage_topic: str, displacement_topic: str, keep_unpaired: bool = False) -> Record:
    """Pair samples by stamp; unpaired samples are dropped at the ends only. Inside, one is
    refused, or with ``keep_unpaired`` kept with the other value NaN (:func:`fill_gaps`)."""
    for topic, store in ((voltage_topic, volts), (displacement_topic, metres_mm)):
        if not store:
            raise DataError(f"{path} has no messages on {topic}.")
    common = sorted(volts.keys() & metres_mm.keys())
    if not common:
        raise DataError(f"{path} has no {voltage_topic} and {displacement_topic} samples with "
                        f"the same header stamp.")
    first, last = common[0], common[-1]
    paired = set(common)
    if keep_unpaired:   # the other value NaN
        common = sorted(s for s in volts.keys() | metres_mm.keys() if first <= s <= last)
    # A recording starts and stops between the two messages of one sampling instant; an
    # unpaired sample inside the span means a message was lost.
    for topic, store in (() if keep_unpaired else ((voltage_topic, volts),
                                                   (displacement_topic, metres_mm))):
        inner = [s for s in store if first < s < last and s not in paired]
        if inner:
            other = displacement_topic if topic == voltage_topic else voltage_topic
            raise DataError(
                f"{path} has {len(inner)} {topic} sample(s) with no {other} sample of the same "
                f"stamp, the first at t = {(min(inner) - first) * 1e-9:.6g} s.")
    stamps = np.array(common, dtype=np.int64)
    t_s = (stamps - stamps[0]) * 1e-9
    return Record(t_s, np.array([volts.get(s, np.nan) for s in common]),
                  np.array([metres_mm.get(s, np.nan) for s in common]))


def write_atomic(files: dict[str | os.PathLike, bytes | str]) -> list[Path]:
    """Write files so that a crash never leaves a partly written one under its final name.

    Each file is written in full to a temporary file in its own folder (created if missing),
    flushed to disk, then renamed into place (``os.replace``) in the order given; if anything
    fails before the renames, no final name is touched and the temporary files are removed.
    For a pair read together, give last the file a reader opens first.

    Parameters
    ----------
    files : dict
        Destination path (str or os.PathLike) -> content (bytes, or str written as UTF-8).

    Returns
    -------
    list of pathlib.Path
        The destinations, in the order given.
    """
    staged: list[tuple[Path, Path]] = []
    try:
        for dest, content in files.items():
            dest = Path(dest)
            dest.parent.mkdir(parents=True, exist_ok=True)
            tmp = dest.with_name(f".{dest.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
            # os.open rather than tempfile.mkstemp: the file gets the umask's mode (0644 as a
            # rule) like any file the user writes, not mkstemp's owner-only 0600
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            staged.append((tmp, dest))
            with os.fdopen(fd, "wb") as fh:
                fh.write(content.encode("utf-8") if isinstance(content, str) else content)
                fh.flush()
                os.fsync(fh.fileno())
        for tmp, dest in staged:
            os.replace(tmp, dest)
    finally:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
    return [dest for _, dest in staged]


def save_csv(record: Record, path) -> Path:
    """Write ``record`` as a ``t,u,y`` CSV file (s, V, mm), atomically.

    The file is written beside its destination and renamed into place, so a crash leaves either
    the old file or the complete new one.

    Parameters
    ----------
    record : Record
        The record to write.
    path : str or os.PathLike
        Destination file; parent folders are created.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    buf = io.StringIO()
    buf.write(",".join(CSV_COLUMNS) + "\n")
    # 1 ns in time; 10 significant digits in V and mm is far below the sensor's 0.04 mm.
    np.savetxt(buf, np.column_stack([record.t_s, record.u_v, record.y_mm]),
               fmt=("%.9f", "%.10g", "%.10g"), delimiter=",")
    return write_atomic({path: buf.getvalue()})[0]


def add_allow_implausible(parser: argparse.ArgumentParser) -> None:
    """The ``--allow-implausible`` option of the commands that load a record."""
    parser.add_argument(
        "--allow-implausible", action="store_true",
        help=f"use a record whose values no IPMC record has (|u| above {MAX_VOLTAGE_V:g} V, "
             f"|y| above {MAX_DISPLACEMENT_MM:g} mm: most likely another unit), with a warning; "
             "non-finite values and time that does not increase are refused regardless")


def print_notes(prog: str, notes: list[str]) -> None:
    """Print :func:`check_plausibility`'s warnings of a command, one line each, to stderr."""
    for note in notes:
        print(f"{prog}: warning: {note}", file=sys.stderr)


def export_main(argv: list[str] | None = None) -> int:
    """``ipmc export BAG --out FILE.csv``: write a bag's voltage and displacement as ``t,u,y``."""
    parser = argparse.ArgumentParser(
        prog="ipmc export",
        description="Export a rosbag2 folder (MCAP or sqlite3) to a CSV file with columns "
                    "t,u,y (s, V, mm); voltage and displacement samples are paired by header "
                    "stamp and t counts from the first pair.")
    parser.add_argument("bag", help="rosbag2 folder (or .mcap/.db3 file)")
    parser.add_argument("--out", required=True, help="CSV file to write")
    parser.add_argument("--voltage-topic", default=VOLTAGE_TOPIC,
                        help=f"Vector3Stamped topic, vector.x in V (default {VOLTAGE_TOPIC})")
    parser.add_argument("--displacement-topic", default=DISPLACEMENT_TOPIC,
                        help=f"PointStamped topic, point.x in m (default {DISPLACEMENT_TOPIC})")
    parser.add_argument("--min-samples", type=int, default=MIN_SAMPLES,
                        help=f"fewest samples accepted (default {MIN_SAMPLES})")
    parser.add_argument("--max-jitter", type=float, default=MAX_JITTER,
                        help="accepted deviation of a sampling interval from the median, as a "
                             f"fraction (default {MAX_JITTER})")
    add_allow_implausible(parser)
    args = parser.parse_args(argv)
    notes: list[str] = []
    try:
        check_output_file(args.out, option="--out", suffixes=(".csv",))
        record = load_record(args.bag, voltage_topic=args.voltage_topic,
                             displacement_topic=args.displacement_topic,
                             min_samples=args.min_samples, max_jitter=args.max_jitter,
                             allow_implausible=args.allow_implausible, notes=notes)
        print_notes("ipmc export", notes)
        out = save_csv(record, args.out)
    except (ValueError, OSError) as exc:  # DataError and a refused --out are ValueErrors
        print(f"ipmc export: error: {exc}", file=sys.stderr)
        return 1
    print(f"ipmc export: wrote {len(record)} samples ({record.t_s[-1]:.3f} s at "
          f"{record.rate_hz:.6g} Hz) to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(export_main())
