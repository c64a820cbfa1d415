"""Crash-tolerant rosbag2 writing on ``rosbags`` and ``ipmc bag-recover``.

Pure core (``rosbags`` only, never ``rclpy``): the recorder node hands it serialised CDR.

Layout of a bag ``run/`` written by :class:`BagWriter`::

    run/metadata.yaml     rewritten (atomically) each time a split is complete
    run/run_0.mcap        complete splits
    run/run_1.mcap
    run/run_2/run_2.mcap  the split being written (a rosbags Writer's own folder)

Why this layout: it is the one ``ros2 bag record --max-bag-duration`` itself produces (one
folder, ``<name>_<i>.<ext>`` files, one metadata.yaml whose ``relative_file_paths`` and ``files``
list every split), so ``ros2 bag info/play`` of a full ROS install and rosbags' own Reader read it
as one split bag. Sub-folder paths in ``relative_file_paths`` are not an option: rosbag2 never
writes them and rosbags' Reader keeps only the file name. Each split is written by its own
``rosbags.rosbag2.Writer`` in a sub-folder named like the file, so the finished file is moved up
under the same name its embedded metadata gives.

What a SIGKILL costs: the complete splits are listed in metadata.yaml already; the split being
written is torn (an MCAP file without its summary and footer, a sqlite3 file with an uncommitted
transaction). :func:`recover_bag` rebuilds metadata.yaml from the complete files and salvages what
the torn one holds. :meth:`BagWriter.flush` (every ``flush_s``) pushes what the current split has
buffered to the file (a complete MCAP chunk / a sqlite3 commit), so the salvage loses at most
``flush_s`` of data, and without the salvage at most ``split_s``.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import sqlite3
import struct
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from rosbags.interfaces import Qos
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.errors import ReaderError, WriterError
from rosbags.rosbag2.metadata import dump_qos_v9
from rosbags.typesys import Stores, get_typestore

__all__ = ["BagError", "BagWriter", "FileInfo", "RecoveryReport", "recover_bag", "recover_main"]

#: rosbag2 metadata version written by ROS 2 Jazzy (rosbag2 0.26).
BAG_VERSION = 9
STORAGES = {"mcap": (".mcap", StoragePlugin.MCAP), "sqlite3": (".db3", StoragePlugin.SQLITE3)}
_MCAP_MAGIC = b"\x89MCAP0\r\n"
_SPLIT_RE = re.compile(r"^(?P<name>.+)_(?P<index>\d+)$")


class BagError(OSError):
    """A bag cannot be written or recovered; the message says why."""


def default_typestore():
    """The rosbags typestore of ROS 2 Jazzy (message definitions and type hashes)."""
    return get_typestore(Stores.ROS2_JAZZY)


@dataclass
class FileInfo:
    """What one complete storage file of a bag holds (``files`` entry of metadata.yaml)."""

    name: str
    start_ns: int
    end_ns: int
    message_count: int
    #: (topic, msgtype) -> {"count", "qos", "digest"}
    topics: dict = field(default_factory=dict)


def read_file_info(path: Path, typestore=None) -> FileInfo:
    """Open one storage file (``.mcap`` / ``.db3``) with rosbags' Reader and summarise it.

    Raises ``ReaderError`` (or ``OSError``) when the file is torn or not a bag file.
    """
    typestore = typestore or default_typestore()
    with Reader(path) as reader:
        count = reader.message_count
        topics = {}
        for c in reader.connections:
            digest = c.digest
            if not digest and c.msgtype in typestore.fielddefs:
                # rosbags' MCAP files do not carry the type hash; the typestore knows it.
                digest = typestore.hash_rihs01(c.msgtype)
            entry = topics.setdefault((c.topic, c.msgtype), {
                "count": 0, "qos": list(c.ext.offered_qos_profiles), "digest": digest})
            entry["count"] += c.msgcount
        start = reader.start_time if count else 0
        end = reader.end_time - 1 if count else 0
    return FileInfo(path.name, start, end, count, topics)


def write_metadata(bag: Path, storage: str, infos: list[FileInfo]) -> Path:
    """Write ``bag/metadata.yaml`` listing ``infos`` (in that order), atomically."""
    from ruamel.yaml import YAML  # a rosbags dependency; it writes the layout rosbags reads

    counted = [i for i in infos if i.message_count]
    start = min((i.start_ns for i in counted), default=0)
    end = max((i.end_ns for i in counted), default=0)
    topics: dict = {}
    for info in infos:
        for key, entry in info.topics.items():
            merged = topics.setdefault(key, {"count": 0, "qos": entry["qos"], "digest": ""})
            merged["count"] += entry["count"]
            merged["digest"] = merged["digest"] or entry["digest"]
    meta = {
        "rosbag2_bagfile_information": {
            "version": BAG_VERSION,
            "storage_identifier": storage,
            "relative_file_paths": [i.name for i in infos],
            "duration": {"nanoseconds": max(0, end - start)},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": sum(i.message_count for i in infos),
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": topic,
                        "type": msgtype,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": dump_qos_v9(entry["qos"]),
                        "type_description_hash": entry["digest"],
                    },
                    "message_count": entry["count"],
                }
                for (topic, msgtype), entry in topics.items()
            ],
            "compression_format": "",
            "compression_mode": "",
            "files": [
                {
                    "path": i.name,
                    "starting_time": {"nanoseconds_since_epoch": i.start_ns},
                    "duration": {"nanoseconds": max(0, i.end_ns - i.start_ns)},
                    "message_count": i.message_count,
                }
                for i in infos
            ],
            "custom_data": None,
            "ros_distro": "rosbags",
        }
    }
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    path = bag / "metadata.yaml"
    tmp = bag / "metadata.yaml.tmp"
    with tmp.open("w", encoding="utf-8") as fh:
        yaml.dump(meta, fh)
        fh.flush()
        os.fsync(fh.fileno())
    tmp.replace(path)
    return path


class BagWriter:
    """Write a rosbag2 folder in splits of ``split_s`` seconds (wall clock) with rosbags.

    Parameters
    ----------
    path : str or os.PathLike
        The bag folder; must not exist yet.
    storage : {'mcap', 'sqlite3'}
        Storage plugin.
    split_s : float
        Recording time per split file, s. A SIGKILL loses at most the current split (at most
        ``flush_s`` of it after :func:`recover_bag`).
    flush_s : float
        Period at which buffered messages are pushed to the current split's file, s.
    typestore : rosbags Typestore, optional
        Where message definitions and type hashes come from (default: ROS 2 Jazzy).
    clock : callable, optional
        Monotonic clock in seconds (default ``time.monotonic``); tests pass their own.

    Use as a context manager, or call :meth:`close`. ``add_topic`` then ``write(topic,
    timestamp_ns, cdr_bytes)``; :meth:`tick` (from a timer) splits and flushes when no messages
    arrive.
    """

    def __init__(self, path, *, storage: str = "mcap", split_s: float = 60.0,
                 flush_s: float = 1.0, typestore=None, clock=time.monotonic):
        if storage not in STORAGES:
            raise ValueError(f"storage must be one of {sorted(STORAGES)}, got {storage!r}")
        if not split_s > 0:
            raise ValueError(f"split_s must be > 0 s, got {split_s!r}")
        if not flush_s > 0:
            raise ValueError(f"flush_s must be > 0 s, got {flush_s!r}")
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f"{self.path} exists already; a bag is never written over.")
        self.storage = storage
        self.split_s = float(split_s)
        self.flush_s = float(flush_s)
        self.typestore = typestore or default_typestore()
        self._clock = clock
        self._ext, self._plugin = STORAGES[storage]
        self._topics: dict[str, tuple[str, str, str, list[Qos]]] = {}
        self._infos: list[FileInfo] = []
        self._writer: Writer | None = None
        self._conns: dict = {}
        self._index = 0
        self._split_count = 0
        self._split_t0 = 0.0
        self._flush_t0 = 0.0
        self._unflushed = 0
        self.message_count = 0
        self.closed = False
        self.path.mkdir(parents=True)

    # -- public API -------------------------------------------------------------------------
    def add_topic(self, topic: str, msgtype: str, *, msgdef: str | None = None,
                  rihs01: str | None = None, offered_qos_profiles=()) -> None:
        """Register ``topic`` of ``msgtype`` (e.g. ``'std_msgs/msg/Float64'``).

        ``msgdef`` and ``rihs01`` default to the typestore's; a type it does not know needs
        both (``ValueError`` otherwise).
        """
        if topic in self._topics:
            raise ValueError(f"topic {topic} is already registered")
        if msgdef is None or rihs01 is None:
            if msgtype not in self.typestore.fielddefs:
                raise ValueError(f"message type {msgtype} of {topic} is unknown to the typestore;"
                                 " pass msgdef and rihs01")
            msgdef, _ = self.typestore.generate_msgdef(msgtype, ros_version=2)
            rihs01 = self.typestore.hash_rihs01(msgtype)
        self._topics[topic] = (msgtype, msgdef, rihs01, list(offered_qos_profiles))
        if self._writer is not None:
            self._add_connection(topic)

    @property
    def topics(self) -> dict[str, str]:
        """Registered topics: name -> message type."""
        return {t: v[0] for t, v in self._topics.items()}

    @property
    def files(self) -> list[str]:
        """Names of the complete split files so far."""
        return [i.name for i in self._infos]

    def write(self, topic: str, timestamp_ns: int, data: bytes) -> None:
        """Write one serialised (CDR) message of a registered topic at ``timestamp_ns``."""
        if self.closed:
            raise BagError(f"{self.path} is closed.")
        if topic not in self._topics:
            raise ValueError(f"topic {topic} is not registered; call add_topic first")
        self.tick()
        if self._writer is None:
            self._open_split()
        self._writer.write(self._conns[topic], int(timestamp_ns), data)
        self._split_count += 1
        self._unflushed += 1
        self.message_count += 1

    def tick(self) -> None:
        """Split and flush when due; call it periodically (a timer) as well as on writes."""
        if self.closed or self._writer is None:
            return
        now = self._clock()
        if self._split_count and now - self._split_t0 >= self.split_s:
            self._finish_split()
            self._open_split()
        elif self._unflushed and now - self._flush_t0 >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        """Push the current split's buffered messages to its file.

        Workaround: rosbags 0.11 has no public flush; its MCAP writer keeps a chunk of up to
        1 MiB in memory and its sqlite3 writer one open transaction until ``close``. This calls
        their ``close_chunk`` / ``commit`` when present and does nothing otherwise.
        """
        self._flush_t0 = self._clock()
        storage = getattr(self._writer, "storage", None)
        if storage is None or not self._unflushed:
            return
        chunk = getattr(storage, "chunk", None)
        if hasattr(storage, "close_chunk") and chunk is not None and chunk.bio.tell():
            storage.close_chunk()
            storage.bio.flush()
        elif hasattr(storage, "conn") and hasattr(storage.conn, "commit"):
            storage.conn.commit()
        self._unflushed = 0

    def close(self) -> None:
        """Finish the current split and write the final metadata.yaml (idempotent)."""
        if self.closed:
            return
        if self._writer is None or (self._split_count == 0 and self._infos):
            self._discard_split()
            if not self._infos:
                # No message at all: still leave a valid, empty bag.
                self._open_split()
                self._finish_split()
        else:
            self._finish_split()
        self.closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    # -- splits -----------------------------------------------------------------------------
    def _stage(self, index: int) -> Path:
        return self.path / f"{self.path.name}_{index}"

    def _open_split(self) -> None:
        stage = self._stage(self._index)
        self._writer = Writer(stage, version=BAG_VERSION, storage_plugin=self._plugin)
        self._writer.open()
        self._conns = {}
        for topic in self._topics:
            self._add_connection(topic)
        self._split_t0 = self._flush_t0 = self._clock()
        self._split_count = 0
        self._unflushed = 0

    def _add_connection(self, topic: str) -> None:
        msgtype, msgdef, rihs01, qos = self._topics[topic]
        self._conns[topic] = self._writer.add_connection(
            topic, msgtype, msgdef=msgdef, rihs01=rihs01, offered_qos_profiles=qos)

    def _finish_split(self) -> None:
        writer, self._writer = self._writer, None
        writer.close()
        self._infos.append(_promote(self.path, self._stage(self._index), self._ext,
                                    self.typestore))
        self._index += 1
        write_metadata(self.path, self.storage, self._infos)

    def _discard_split(self) -> None:
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.abort()
            shutil.rmtree(self._stage(self._index), ignore_errors=True)


def _promote(bag: Path, stage: Path, ext: str, typestore) -> FileInfo:
    """Move a closed split's file from its stage folder into the bag and summarise it."""
    name = stage.name + ext
    dst = bag / name
    os.replace(stage / name, dst)
    (stage / "metadata.yaml").unlink(missing_ok=True)
    shutil.rmtree(stage, ignore_errors=True)
    return read_file_info(dst, typestore)


# -- recovery -------------------------------------------------------------------------------
@dataclass
class RecoveryReport:
    """What :func:`recover_bag` did."""

    bag: Path
    storage: str
    kept: list[FileInfo]
    salvaged: dict[str, int]  # torn file -> messages salvaged from it
    dropped: list[str]  # files set aside as <name>.torn

    @property
    def message_count(self) -> int:
        return sum(i.message_count for i in self.kept)

    def summary(self) -> str:
        lines = [f"{self.bag}: kept {len(self.kept)} file(s), {self.message_count} messages "
                 f"({self.storage})."]
        for i in self.kept:
            lines.append(f"  {i.name}: {i.message_count} messages, "
                         f"{(i.end_ns - i.start_ns) * 1e-9:.3f} s")
        for name, n in self.salvaged.items():
            lines.append(f"  salvaged {n} messages from torn {name}")
        for name in self.dropped:
            lines.append(f"  set aside {name}.torn (unreadable)")
        return "\n".join(lines)


def _split_key(path: Path):
    m = _SPLIT_RE.match(path.name.split(".")[0])
    return (int(m.group("index")) if m else -1, path.name)


def recover_bag(path, *, typestore=None) -> RecoveryReport:
    """Make a bag whose writer was killed readable again.

    Complete split files are kept; a split whose writer closed it but did not move it is moved
    into place; a torn split (the one being written) is salvaged: its complete MCAP chunks or
    committed sqlite3 rows are rewritten as a new split file, and the torn file is kept beside
    it as ``<file>.torn``. metadata.yaml is then rebuilt from the files. Running it on a
    healthy bag rewrites the same metadata.

    Raises
    ------
    BagError
        ``path`` is not a folder or holds no storage file with a message.
    """
    bag = Path(path)
    typestore = typestore or default_typestore()
    if not bag.is_dir():
        raise BagError(f"{bag} is not a folder; give the rosbag2 folder to recover.")
    found = [p for p in bag.iterdir() if p.is_file() and p.suffix in (".mcap", ".db3")]
    stages = [(d, f) for d in bag.iterdir() if d.is_dir()
              for f in d.iterdir() if f.suffix in (".mcap", ".db3") and f.stem == d.name]
    exts = {p.suffix for p in found} | {f.suffix for _, f in stages}
    if not exts:
        raise BagError(f"{bag} holds no .mcap or .db3 file; nothing to recover.")
    if len(exts) > 1:
        raise BagError(f"{bag} mixes .mcap and .db3 files; recover them separately.")
    ext = exts.pop()
    storage = "mcap" if ext == ".mcap" else "sqlite3"
    kept: list[FileInfo] = []
    salvaged: dict[str, int] = {}
    dropped: list[str] = []

    def set_aside(f: Path) -> None:
        f.replace(bag / f"{f.name}.torn")

    for f in sorted(found, key=_split_key):
        try:
            kept.append(read_file_info(f, typestore))
        except (ReaderError, OSError, struct.error, AssertionError, KeyError):
            torn = bag / f.stem
            torn.mkdir()
            f.replace(torn / f.name)
            stages.append((torn, torn / f.name))
    for stage, f in sorted(stages, key=lambda s: _split_key(s[1])):
        if (stage / "metadata.yaml").exists():
            try:  # closed but not yet moved up when the writer died
                kept.append(_promote(bag, stage, ext, typestore))
                continue
            except (ReaderError, OSError, struct.error, AssertionError, KeyError):
                pass
        conns, messages = _salvage(f)
        set_aside(f)
        shutil.rmtree(stage, ignore_errors=True)
        n = _rewrite(stage, ext, conns, messages, typestore) if messages else 0
        if n:
            kept.append(_promote(bag, stage, ext, typestore))
            salvaged[f.name] = n
        else:
            dropped.append(f.name)
    kept.sort(key=lambda i: _split_key(Path(i.name)))
    if not any(i.message_count for i in kept):
        raise BagError(f"{bag} holds no complete or salvageable message.")
    write_metadata(bag, storage, kept)
    return RecoveryReport(bag, storage, kept, salvaged, dropped)


def _salvage(path: Path):
    """Connections {id: (topic, msgtype, msgdef, qos)} and messages [(id, t_ns, data)]."""
    try:
        if path.suffix == ".mcap":
            return _salvage_mcap(path.read_bytes())
        return _salvage_sqlite(path)
    except (OSError, sqlite3.Error, struct.error, UnicodeDecodeError, IndexError):
        return {}, []


def _salvage_mcap(data: bytes):
    schemas: dict[int, tuple[str, str]] = {}
    channels: dict[int, tuple[int, str, bytes]] = {}
    messages: list[tuple[int, int, bytes]] = []
    if not data.startswith(_MCAP_MAGIC):
        return {}, []

    def records(buf: bytes, pos: int):
        # MCAP record: opcode u8, length u64, body. A record cut short ends the scan.
        while pos + 9 <= len(buf):
            op, n = buf[pos], struct.unpack_from("<Q", buf, pos + 1)[0]
            start, pos = pos + 9, pos + 9 + n
            if pos > len(buf):
                return
            yield op, buf[start:pos]

    def string(buf: bytes, pos: int):
        (n,) = struct.unpack_from("<I", buf, pos)
        return buf[pos + 4:pos + 4 + n], pos + 4 + n

    def parse(op: int, body: bytes) -> None:
        if op == 0x03:  # schema: id, name, encoding, data
            (sid,) = struct.unpack_from("<H", body, 0)
            name, p = string(body, 2)
            _enc, p = string(body, p)
            text, _ = string(body, p)
            schemas[sid] = (name.decode(), text.decode())
        elif op == 0x04:  # channel: id, schema id, topic, encoding, metadata map
            cid, sid = struct.unpack_from("<HH", body, 0)
            topic, p = string(body, 4)
            _enc, p = string(body, p)
            meta, _ = string(body, p)
            channels[cid] = (sid, topic.decode(), meta)
        elif op == 0x05:  # message: channel, sequence, log time, publish time, data
            cid, _seq, log_time, _pub = struct.unpack_from("<HIQQ", body, 0)
            messages.append((cid, log_time, body[22:]))

    for op, body in records(data, len(_MCAP_MAGIC)):
        if op == 0x06:  # chunk: start, end, size, crc, compression, compressed size, records
            comp, p = string(body, 28)
            if comp:
                continue  # BagWriter never compresses
            (size,) = struct.unpack_from("<Q", body, p)
            for inner_op, inner in records(body[p + 8:p + 8 + size], 0):
                parse(inner_op, inner)
        else:
            parse(op, body)
    conns = {}
    for cid, (sid, topic, meta) in channels.items():
        if sid in schemas:
            conns[cid] = (topic, schemas[sid][0], schemas[sid][1], _mcap_qos(meta))
    return conns, [m for m in messages if m[0] in conns]


def _mcap_qos(meta: bytes) -> list[Qos]:
    try:
        from rosbags.rosbag2.storage_mcap import get_qos
        return get_qos(meta)
    except Exception:  # noqa: BLE001 - QoS is optional; a salvage must not fail on it
        return []


def _salvage_sqlite(path: Path):
    # A normal (not immutable) connection rolls a hot journal back to the last commit.
    db = sqlite3.connect(f"file:{path}", uri=True)
    try:
        defs = dict(db.execute(
            "SELECT topic_type, encoded_message_definition FROM message_definitions"))
        conns = {}
        for cid, topic, msgtype, _qos in db.execute(
                "SELECT id, name, type, offered_qos_profiles FROM topics"):
            conns[cid] = (topic, msgtype, defs.get(msgtype), [])
        messages = list(db.execute(
            "SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp"))
    finally:
        db.close()
    return conns, messages


def _rewrite(stage: Path, ext: str, conns: dict, messages: list, typestore) -> int:
    plugin = STORAGES["mcap" if ext == ".mcap" else "sqlite3"][1]
    written = 0
    with Writer(stage, version=BAG_VERSION, storage_plugin=plugin) as writer:
        out = {}
        for cid, (topic, msgtype, msgdef, qos) in conns.items():
            if msgtype in typestore.fielddefs:
                msgdef, _ = typestore.generate_msgdef(msgtype, ros_version=2)
                rihs01 = typestore.hash_rihs01(msgtype)
            else:
                # Not in the typestore: keep the file's definition; rosbag2 accepts an
                # unset hash (it is only used to match types on playback).
                rihs01 = "RIHS01_" + "0" * 64
            if msgdef:
                with _suppress_writer_error():
                    out[cid] = writer.add_connection(topic, msgtype, msgdef=msgdef,
                                                     rihs01=rihs01, offered_qos_profiles=qos)
        for cid, t_ns, data in sorted(messages, key=lambda m: m[1]):
            if cid in out:
                writer.write(out[cid], int(t_ns), bytes(data))
                written += 1
    return written


class _suppress_writer_error:
    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        return exc_type is not None and issubclass(exc_type, WriterError)


def recover_main(argv: list[str] | None = None) -> int:
    """``ipmc bag-recover DIR``: make a bag whose recorder was killed readable again."""
    parser = argparse.ArgumentParser(
        prog="ipmc bag-recover",
        description="Rebuild metadata.yaml of a rosbag2 folder whose writer was killed: keep "
                    "the complete split files, salvage what the torn last one holds (it is "
                    "kept as <file>.torn), and report what was kept.")
    parser.add_argument("bag", help="rosbag2 folder")
    args = parser.parse_args(argv)
    try:
        report = recover_bag(args.bag)
    except BagError as exc:
        print(f"ipmc bag-recover: error: {exc}", file=sys.stderr)
        return 1
    print(report.summary())
    return 0


if __name__ == "__main__":
    sys.exit(recover_main())
