"""Tests of ipmc_driver.bagio: split rosbag2 writing with rosbags, and ``ipmc bag-recover``."""

import os
import shutil
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from numpy.testing import assert_allclose
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

from ipmc_driver.bagio import BagError, BagWriter, recover_bag, recover_main
from ipmc_driver.dataio import DataError, load_record

TS = get_typestore(Stores.ROS2_JAZZY)
T0_NS = 1_700_000_000_000_000_000
DT_NS = 10_000_000


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def _samples(k):
    """CDR of /ipmc/voltage and /ipmc/displacement at sample k (u = k mV, y = k um)."""
    ns = T0_NS + k * DT_NS
    header = TS.types["std_msgs/msg/Header"](
        stamp=TS.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
        frame_id="ipmc_clamp")
    v = TS.types["geometry_msgs/msg/Vector3Stamped"](
        header=header, vector=TS.types["geometry_msgs/msg/Vector3"](x=k * 1e-3, y=0.0, z=0.0))
    y = TS.types["geometry_msgs/msg/PointStamped"](
        header=header, point=TS.types["geometry_msgs/msg/Point"](x=k * 1e-6, y=0.0, z=0.0))
    return ns, TS.serialize_cdr(v, v.__msgtype__), TS.serialize_cdr(y, y.__msgtype__)


def _writer(path, storage, clock, **kw):
    w = BagWriter(path, storage=storage, clock=clock, **kw)
    w.add_topic("/ipmc/voltage", "geometry_msgs/msg/Vector3Stamped")
    w.add_topic("/ipmc/displacement", "geometry_msgs/msg/PointStamped")
    w.add_topic("/ipmc/command", "std_msgs/msg/Float64")
    return w


def _feed(w, clock, ks):
    for k in ks:
        clock.t = k * DT_NS * 1e-9
        ns, v, y = _samples(k)
        w.write("/ipmc/voltage", ns, v)
        w.write("/ipmc/displacement", ns, y)


def _metadata(bag):
    text = (bag / "metadata.yaml").read_text()
    return YAML(typ="safe").load(text)["rosbag2_bagfile_information"]


@pytest.mark.parametrize(("storage", "ext"), [("mcap", ".mcap"), ("sqlite3", ".db3")])
def test_writer_splits_and_reads_back_whole(tmp_path, storage, ext):
    clock = FakeClock()
    bag = tmp_path / "run"
    with _writer(bag, storage, clock, split_s=1.0) as w:
        _feed(w, clock, range(250))
    assert w.files == [f"run_{i}{ext}" for i in range(3)]
    assert sorted(p.name for p in bag.iterdir()) == sorted([*w.files, "metadata.yaml"])
    meta = _metadata(bag)
    assert meta["version"] == 9 and meta["storage_identifier"] == storage
    assert meta["relative_file_paths"] == w.files
    assert [f["message_count"] for f in meta["files"]] == [200, 200, 100]
    assert meta["message_count"] == 500
    assert meta["starting_time"]["nanoseconds_since_epoch"] == T0_NS
    assert meta["duration"]["nanoseconds"] == 249 * DT_NS
    topics = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    assert topics["/ipmc/voltage"]["message_count"] == 250
    assert topics["/ipmc/command"]["message_count"] == 0
    assert topics["/ipmc/voltage"]["topic_metadata"]["type_description_hash"] == \
        TS.hash_rihs01("geometry_msgs/msg/Vector3Stamped")
    with Reader(bag) as reader:
        assert reader.message_count == 500
        stamps = [t for _, t, _ in reader.messages()]
        assert stamps == sorted(stamps) and len(stamps) == 500
    rec = load_record(bag)
    assert len(rec) == 250
    assert_allclose(rec.u_v, np.arange(250) * 1e-3, rtol=1e-12)
    assert_allclose(rec.y_mm, np.arange(250) * 1e-3, rtol=1e-9)


def test_writer_tick_splits_without_messages_and_close_drops_empty_split(tmp_path):
    clock = FakeClock()
    w = _writer(tmp_path / "run", "mcap", clock, split_s=1.0)
    _feed(w, clock, range(10))
    clock.t = 5.0
    w.tick()  # due: the split with 20 messages is finished, an empty one opened
    assert w.files == ["run_0.mcap"]
    with pytest.raises(DataError, match="unfinished split run_1.mcap .*still running"):
        load_record(tmp_path / "run")
    w.close()
    w.close()
    assert w.files == ["run_0.mcap"]
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["metadata.yaml", "run_0.mcap"]
    assert load_record(tmp_path / "run").t_s[-1] == pytest.approx(0.09)


def test_writer_without_messages_leaves_valid_empty_bag(tmp_path):
    with _writer(tmp_path / "run", "sqlite3", FakeClock()):
        pass
    with Reader(tmp_path / "run") as reader:
        assert reader.message_count == 0
        assert {c.topic for c in reader.connections} == {
            "/ipmc/voltage", "/ipmc/displacement", "/ipmc/command"}


def test_writer_refuses_bad_use(tmp_path):
    (tmp_path / "exists").mkdir()
    with pytest.raises(BagError, match="exists already"):
        BagWriter(tmp_path / "exists")
    with pytest.raises(ValueError, match="storage must be one of"):
        BagWriter(tmp_path / "a", storage="rosbag1")
    with pytest.raises(ValueError, match="split_s must be > 0"):
        BagWriter(tmp_path / "b", split_s=0)
    w = BagWriter(tmp_path / "c")
    with pytest.raises(ValueError, match="unknown to the typestore"):
        w.add_topic("/x", "my_msgs/msg/Nope")
    with pytest.raises(ValueError, match="not registered"):
        w.write("/x", 0, b"")
    w.close()
    with pytest.raises(BagError, match="is closed"):
        w.write("/x", 0, b"")


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_recover_after_crash_keeps_splits_and_salvages_flushed_part(tmp_path, storage):
    clock = FakeClock()
    bag = tmp_path / "run"
    w = _writer(bag, storage, clock, split_s=1.0, flush_s=0.1)
    _feed(w, clock, range(250))  # splits 0 and 1 complete; 0.5 s of split 2, flushed to 2.4 s
    crashed = tmp_path / "crashed"
    shutil.copytree(bag, crashed)  # the files as a SIGKILL would leave them
    w.close()
    with pytest.raises(DataError, match="unfinished split run_2.*ipmc bag-recover"):
        load_record(crashed)
    report = recover_bag(crashed)
    assert [i.message_count for i in report.kept][:2] == [200, 200]
    salvaged = report.salvaged["run_2" + (".mcap" if storage == "mcap" else ".db3")]
    assert 80 <= salvaged < 100
    rec = load_record(crashed)
    assert len(rec) == 200 + salvaged // 2
    assert_allclose(rec.u_v, np.arange(len(rec)) * 1e-3, rtol=1e-12)
    assert any(p.name.endswith(".torn") for p in crashed.iterdir())
    # Idempotent on a healthy bag.
    again = recover_bag(crashed)
    assert [i.message_count for i in again.kept] == [i.message_count for i in report.kept]


def test_recover_drops_torn_split_with_nothing_flushed(tmp_path):
    clock = FakeClock()
    bag = tmp_path / "run"
    w = _writer(bag, "mcap", clock, split_s=1.0, flush_s=100.0)
    _feed(w, clock, range(150))
    crashed = tmp_path / "crashed"
    shutil.copytree(bag, crashed)
    w.close()
    report = recover_bag(crashed)
    assert report.dropped == ["run_1.mcap"] and report.salvaged == {}
    assert "set aside run_1.mcap.torn" in report.summary()
    assert len(load_record(crashed)) == 100


def test_recover_main_reports_and_fails_clearly(tmp_path, capsys):
    clock = FakeClock()
    bag = tmp_path / "run"
    with _writer(bag, "mcap", clock, split_s=1.0) as w:
        _feed(w, clock, range(120))
    (bag / "metadata.yaml").unlink()
    assert recover_main([str(bag)]) == 0
    out = capsys.readouterr().out
    assert "kept 2 file(s), 240 messages (mcap)" in out and "run_1.mcap: 40 messages" in out
    assert len(load_record(bag)) == 120
    (tmp_path / "empty").mkdir()
    assert recover_main([str(tmp_path / "empty")]) == 1
    assert "holds no .mcap or .db3 file" in capsys.readouterr().err
    assert recover_main([str(tmp_path / "nope")]) == 1
    assert "is not a folder" in capsys.readouterr().err


WRITER_SCRIPT = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {testdir!r})
    from test_bagio import _samples
    from ipmc_driver.bagio import BagWriter
    w = BagWriter({bag!r}, storage={storage!r}, split_s=0.5, flush_s=0.1)
    w.add_topic("/ipmc/voltage", "geometry_msgs/msg/Vector3Stamped")
    w.add_topic("/ipmc/displacement", "geometry_msgs/msg/PointStamped")
    k = 0
    while True:
        ns, v, y = _samples(k)
        w.write("/ipmc/voltage", ns, v)
        w.write("/ipmc/displacement", ns, y)
        if k == 100:
            print("running", flush=True)
        if k == 250:
            print("written", flush=True)
        k += 1
        time.sleep(0.005)
""")


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_sigkill_mid_recording_then_recover_keeps_all_but_last_flush(tmp_path, storage):
    bag = tmp_path / "run"
    script = WRITER_SCRIPT.format(testdir=os.path.dirname(__file__), bag=str(bag),
                                  storage=storage)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "running"
        # killed once 250 samples are written, however slowly the machine runs the loop
        assert proc.stdout.readline().strip() == "written"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=5)
    assert proc.returncode == -signal.SIGKILL
    report = recover_bag(bag)
    assert len(report.kept) >= 2
    rec = load_record(bag, max_jitter=1e-6)
    # No hole: every sample from 0 to the last one kept is there (load_record checks gaps).
    assert_allclose(rec.u_v, np.arange(len(rec)) * 1e-3, rtol=1e-12)
    assert len(rec) >= 150


def test_import_bagio_leaves_rclpy_out():
    code = ("import sys, ipmc_driver.bagio; "
            "assert 'rclpy' not in sys.modules, 'rclpy imported'")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=30)
