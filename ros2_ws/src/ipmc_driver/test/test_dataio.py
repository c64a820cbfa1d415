"""Tests of ipmc_driver.dataio: CSV and rosbag2 loading, CSV saving, ``ipmc export``."""

import re
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from ipmc_driver.dataio import (
    DataError,
    ImplausibleDataWarning,
    LostSamplesWarning,
    Record,
    check_plausibility,
    export_main,
    fill_gaps,
    load_record,
    save_csv,
    write_atomic,
)

TS = get_typestore(Stores.ROS2_JAZZY)
T0_NS = 1_700_000_000_123_000_000


def _record(n=50, dt=0.01, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    return Record(t, rng.uniform(-3, 3, n), rng.normal(0, 2, n))


def _write_csv(path, text):
    path.write_text(text)
    return path


def _header(stamp_ns, frame="ipmc_clamp"):
    Time = TS.types["builtin_interfaces/msg/Time"]
    Header = TS.types["std_msgs/msg/Header"]
    return Header(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=frame)


def write_bag(path, stamps_v, volts, stamps_y, metres, *, storage="mcap", extra_topic=None):
    """Write a bag with /ipmc/voltage and /ipmc/displacement (receive time = stamp)."""
    V3S = TS.types["geometry_msgs/msg/Vector3Stamped"]
    V3 = TS.types["geometry_msgs/msg/Vector3"]
    PS = TS.types["geometry_msgs/msg/PointStamped"]
    P = TS.types["geometry_msgs/msg/Point"]
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        cv = w.add_connection("/ipmc/voltage", V3S.__msgtype__, typestore=TS)
        cy = w.add_connection("/ipmc/displacement", PS.__msgtype__, typestore=TS)
        for s, v in zip(stamps_v, volts, strict=True):
            msg = V3S(header=_header(int(s)), vector=V3(x=float(v), y=float(v), z=0.0))
            w.write(cv, int(s), TS.serialize_cdr(msg, V3S.__msgtype__))
        for s, y in zip(stamps_y, metres, strict=True):
            msg = PS(header=_header(int(s)), point=P(x=float(y), y=0.0, z=0.0))
            w.write(cy, int(s), TS.serialize_cdr(msg, PS.__msgtype__))
        if extra_topic:
            Float64 = TS.types["std_msgs/msg/Float64"]
            ce = w.add_connection(extra_topic, "std_msgs/msg/Float64", typestore=TS)
            w.write(ce, T0_NS, TS.serialize_cdr(Float64(data=1.0), "std_msgs/msg/Float64"))
    return path


def test_save_csv_round_trip_preserves_values(tmp_path):
    rec = _record()
    out = save_csv(rec, tmp_path / "sub" / "r.csv")
    assert out.read_text().splitlines()[0] == "t,u,y"
    back = load_record(out)
    assert_allclose(back.t_s, rec.t_s, atol=1e-9)
    assert_allclose(back.u_v, rec.u_v, rtol=1e-9)
    assert_allclose(back.y_mm, rec.y_mm, rtol=1e-9)
    assert len(back) == 50
    assert back.rate_hz == pytest.approx(100.0)
    assert not list(tmp_path.glob("sub/.*tmp*"))


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.floats(-3, 3), st.floats(-20, 20)), min_size=10, max_size=60),
       st.sampled_from([0.001, 0.01, 0.05]))
def test_save_csv_round_trip_any_values(tmp_path_factory, samples, dt):
    u, y = np.array(samples).T
    rec = Record(np.arange(len(u)) * dt, u, y)
    back = load_record(save_csv(rec, tmp_path_factory.mktemp("h") / "r.csv"))
    assert_allclose(back.u_v, rec.u_v, rtol=1e-9, atol=1e-12)
    assert_allclose(back.y_mm, rec.y_mm, rtol=1e-9, atol=1e-12)


def test_load_csv_accepts_extra_columns_and_blank_lines(tmp_path):
    lines = ["y, t ,extra,u"] + [f"{k * 0.1},{k * 0.01},x,{k * 0.2}" for k in range(12)]
    rec = load_record(_write_csv(tmp_path / "a.csv", "\n".join(lines + ["", ""])))
    assert_allclose(rec.t_s, np.arange(12) * 0.01, atol=1e-12)
    assert_allclose(rec.u_v, np.arange(12) * 0.2)
    assert_allclose(rec.y_mm, np.arange(12) * 0.1)


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ("t,u,y\n" + "".join(f"{k * 0.01},1,2\n" for k in range(5)) + "0.05,nan,1\n"
         + "".join(f"{k * 0.01},1,2\n" for k in range(6, 12)),
         r"non-finite .* in u_v \(V\), the first at sample 5"),
        ("t,u,y\n" + "".join(f"{k * 0.01},1,2\n" for k in (0, 1, 2, 4, 3, 5, 6, 7, 8, 9, 10)),
         r"unsorted or repeated time: t\[4\] = 0.03 s does not follow t\[3\] = 0.04 s"),
        ("t,u,y\n" + "".join(f"{k * 0.01},1,2\n" for k in (0, 1, 2, 3, 5, 6, 7, 8, 9, 10, 11)),
         r"irregular time: a gap of 0.02 s between t = 0.03 s and 0.05 s"),
        ("t,u,y\n" + "".join(f"{k * 0.01 + (0.003 if k == 4 else 0)},1,2\n" for k in range(12)),
         r"irregular time: an irregular interval"),
        ("t,u,y\n" + "".join(f"{k * 0.01},1,2\n" for k in range(3)),
         r"too few samples: 3, need at least 10"),
        ("time,u,y\n0,1,2\n", r"lacks column\(s\) t in its header 'time,u,y'"),
        ("0,1,2\n0.01,1,2\n", r"lacks column\(s\) t, u, y"),
        ("", r"is empty; expected a header line 't,u,y'"),
        ("t,u,y\n0,1,2\n0.01,1\n", r"line 3 has 2 field\(s\), fewer than the header's 3"),
        ("t,u,y\n0,1,2\n0.01,one,2\n", r"line 3 has a non-numeric value"),
    ],
    ids=["nan", "unsorted", "gap", "jitter", "too-few", "bad-header", "no-header", "empty",
         "short-row", "non-numeric"],
)
def test_load_csv_bad_input_raises_clear_error(tmp_path, body, match):
    path = _write_csv(tmp_path / "bad.csv", body)
    with pytest.raises(DataError, match=match) as info:
        load_record(path)
    msg = str(info.value)
    assert str(path) in msg and msg.endswith(".") and "\n" not in msg
    assert isinstance(info.value, ValueError)


def test_load_record_missing_path_raises(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        load_record(tmp_path / "nope.csv")


def test_load_csv_min_samples_and_jitter_are_tunable(tmp_path):
    body = "t,u,y\n" + "".join(f"{k * 0.01 + (0.003 if k == 1 else 0)},1,2\n" for k in range(3))
    rec = load_record(_write_csv(tmp_path / "a.csv", body), min_samples=3, max_jitter=0.5)
    assert len(rec) == 3


def test_record_rejects_unequal_lengths():
    with pytest.raises(DataError, match="one length: t_s has 3, u_v has 2, y_mm has 3"):
        Record([0, 1, 2], [0, 1], [0, 1, 2])


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_load_bag_pairs_by_stamp_and_converts_to_mm(tmp_path, storage):
    n = 40
    stamps = T0_NS + np.arange(n) * 10_000_000
    volts = np.sin(np.arange(n) * 0.3)
    metres = 1e-3 * np.cos(np.arange(n) * 0.3)
    # The recording caught the voltage of the first instant and the displacement of one more.
    stamps_y = np.append(stamps[1:], stamps[-1] + 10_000_000)
    metres_y = np.append(metres[1:], 9.9)
    bag = write_bag(tmp_path / "bag", stamps, volts, stamps_y, metres_y, storage=storage)
    rec = load_record(bag)
    assert len(rec) == n - 1
    assert_allclose(rec.t_s, np.arange(n - 1) * 0.01, atol=1e-12)
    assert_allclose(rec.u_v, volts[1:], rtol=1e-12)
    assert_allclose(rec.y_mm, 1e3 * metres[1:], rtol=1e-12)


def test_load_bag_single_storage_file(tmp_path):
    stamps = T0_NS + np.arange(20) * 10_000_000
    bag = write_bag(tmp_path / "bag", stamps, np.zeros(20), stamps, np.zeros(20))
    rec = load_record(bag / "bag.mcap")
    assert len(rec) == 20


def test_load_bag_missing_topic_raises(tmp_path):
    stamps = T0_NS + np.arange(20) * 10_000_000
    bag = write_bag(tmp_path / "bag", stamps, np.zeros(20), [], [])
    with pytest.raises(DataError, match="has no messages on /ipmc/displacement"):
        load_record(bag)
    with pytest.raises(DataError, match=r"lacks topic\(s\) /rig/y; it has /ipmc/displacement, "):
        load_record(bag, displacement_topic="/rig/y")


def test_load_bag_wrong_type_raises(tmp_path):
    stamps = T0_NS + np.arange(20) * 10_000_000
    bag = write_bag(tmp_path / "bag", stamps, np.zeros(20), stamps, np.zeros(20),
                    extra_topic="/ipmc/command")
    with pytest.raises(DataError, match="topic /ipmc/command has type std_msgs/msg/Float64, "
                                        "expected geometry_msgs/msg/PointStamped"):
        load_record(bag, displacement_topic="/ipmc/command")


def test_load_bag_lost_message_inside_raises(tmp_path):
    stamps = T0_NS + np.arange(20) * 10_000_000
    keep = np.delete(np.arange(20), 7)
    bag = write_bag(tmp_path / "bag", stamps, np.zeros(20), stamps[keep], np.zeros(19))
    with pytest.raises(DataError, match=r"1 /ipmc/voltage sample\(s\) with no /ipmc/displacement"
                                        r" sample of the same stamp, the first at t = 0.07 s"):
        load_record(bag)


def test_load_bag_gap_raises(tmp_path):
    stamps = T0_NS + np.delete(np.arange(21), 7) * 10_000_000
    bag = write_bag(tmp_path / "bag", stamps, np.zeros(20), stamps, np.zeros(20))
    with pytest.raises(DataError, match="irregular time: a gap"):
        load_record(bag)


def test_a_bag_that_lost_samples_loads_with_them_as_rows_not_measured(tmp_path):
    # samples 7-9 lost on both topics, the displacement of 14 and the voltage of 17 alone
    k = np.delete(np.arange(30), [7, 8, 9])
    stamps = T0_NS + k * 10_000_000
    volts, metres = k * 0.1, k * 1e-4
    v_keep, d_keep = k != 17, k != 14
    bag = write_bag(tmp_path / "bag", stamps[v_keep], volts[v_keep], stamps[d_keep],
                    metres[d_keep])
    notes: list[str] = []
    rec = load_record(bag, gaps=True, notes=notes)
    assert_allclose(rec.t_s, np.arange(30) * 0.01, atol=1e-9)
    # a sample whose voltage was lost is not measured either: its input is not known
    lost = [7, 8, 9, 14, 17]
    assert np.flatnonzero(np.isnan(rec.y_mm)).tolist() == lost
    measured = np.delete(np.arange(30), lost)
    assert_allclose(rec.y_mm[measured], measured * 0.1)
    # the voltage is held through a loss; a sample's own voltage is kept where it came
    assert_allclose(rec.u_v[[7, 8, 9]], 0.6) and rec.u_v[14] == pytest.approx(1.4)
    assert rec.u_v[17] == pytest.approx(1.6)
    assert len(notes) == 1 and "5 of 30 samples were not measured" in notes[0]
    assert "the longest 0.03 s after t = 0.06 s" in notes[0]
    with pytest.warns(LostSamplesWarning, match="5 of 30 samples were not measured"):
        load_record(bag, gaps=True)
    with pytest.raises(DataError, match="no /ipmc/displacement"):
        load_record(bag)


def test_fill_gaps_refuses_an_interval_that_is_no_whole_number_of_samples():
    t = np.r_[np.arange(10) * 0.01, 0.09 + 0.015 + np.arange(10) * 0.01]
    rec = Record(t, np.ones(20), np.ones(20))
    with pytest.raises(DataError, match="no whole number of the median interval"):
        fill_gaps(rec, source="r.csv")
    regular = _record()
    same, note = fill_gaps(regular)
    assert note is None
    assert_allclose(same.t_s, regular.t_s, atol=1e-12)
    assert_allclose(np.c_[same.u_v, same.y_mm], np.c_[regular.u_v, regular.y_mm])


def test_load_bag_without_metadata_points_to_recover(tmp_path):
    (tmp_path / "bag").mkdir()
    with pytest.raises(DataError, match="no metadata.yaml .*ipmc bag-recover"):
        load_record(tmp_path / "bag")


def test_load_bag_corrupt_storage_raises_data_error(tmp_path):
    stamps = T0_NS + np.arange(20) * 10_000_000
    bag = write_bag(tmp_path / "bag", stamps, np.zeros(20), stamps, np.zeros(20))
    (bag / "bag.mcap").write_bytes(b"\x89MCAP0\r\ngarbage")
    with pytest.raises(DataError, match="cannot be read as a rosbag2 bag"):
        load_record(bag)


def test_export_main_writes_csv(tmp_path, capsys):
    n = 30
    stamps = T0_NS + np.arange(n) * 10_000_000
    volts = np.linspace(-3, 3, n)
    bag = write_bag(tmp_path / "bag", stamps, volts, stamps, volts * 1e-3, storage="sqlite3")
    out = tmp_path / "out.csv"
    assert export_main([str(bag), "--out", str(out)]) == 0
    assert "wrote 30 samples" in capsys.readouterr().out
    rec = load_record(out)
    assert_allclose(rec.u_v, volts, rtol=1e-9)
    assert_allclose(rec.y_mm, volts, rtol=1e-9)


def test_export_main_bad_bag_returns_1_with_message(tmp_path, capsys):
    (tmp_path / "bag").mkdir()
    assert export_main([str(tmp_path / "bag"), "--out", str(tmp_path / "o.csv")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("ipmc export: error: ") and "metadata.yaml" in err
    assert not (tmp_path / "o.csv").exists()


def test_write_atomic_writes_the_files_whole_and_leaves_no_temporary(tmp_path):
    a, b = tmp_path / "sub" / "m.npz", tmp_path / "sub" / "m.json"
    assert write_atomic({a: b"\x00\x01", b: "{}\n"}) == [a, b]
    assert a.read_bytes() == b"\x00\x01" and b.read_text() == "{}\n"
    assert sorted(p.name for p in a.parent.iterdir()) == ["m.json", "m.npz"]


def test_write_atomic_failing_part_way_touches_no_final_name(tmp_path, monkeypatch):
    import ipmc_driver.dataio as dataio

    old = tmp_path / "m.json"
    old.write_text("old")
    calls = []

    def fsync(fd):  # the disk fails on the second file
        calls.append(fd)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(dataio.os, "fsync", fsync)
    with pytest.raises(OSError, match="No space left"):
        write_atomic({tmp_path / "m.npz": b"new", old: "new"})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json"]
    assert old.read_text() == "old"


def test_export_main_refuses_a_bad_out_before_reading(tmp_path, capsys):
    (tmp_path / "dir").mkdir()
    for out, why in ((tmp_path / "dir", "is a folder"), (tmp_path / "o.mcap", "expected a .csv")):
        assert export_main([str(tmp_path / "no_bag"), "--out", str(out)]) == 1
        err = capsys.readouterr().err.strip()
        assert err.startswith("ipmc export: error: --out ") and why in err and "\n" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir"]
    assert list((tmp_path / "dir").iterdir()) == []


def _plausible(n=200, dt=0.01):
    t = np.arange(n) * dt
    u = 2.5 * np.sin(2 * np.pi * 0.5 * t)
    return t, u, 3.0 * np.sin(2 * np.pi * 0.5 * t - 0.3)


def test_plausibility_passes_an_ipmc_record_silently():
    assert check_plausibility(Record(*_plausible())) == []


@pytest.mark.parametrize(("scale", "match"), [
    ((1, 100, 1), r"r\.csv: u reaches 250 V, far beyond the H-bridge's 3 V \(looks like "
                  r"millivolts; ipmc expects V\); --allow-implausible accepts it\.$"),
    ((1, 1e4, 1), r"u reaches 2\.5e\+04 V, .*\(no IPMC is driven at that\)"),
    ((1, 1, 1000), r"r\.csv: y reaches 3000, beyond 1 m .*\(looks like micrometres; ipmc "
                   r"expects mm\)"),
])
def test_plausibility_refuses_what_no_ipmc_record_has(scale, match):
    t, u, y = _plausible()
    rec = Record(t * scale[0], u * scale[1], y * scale[2])
    with pytest.raises(DataError, match=match) as info:
        check_plausibility(rec, source="r.csv")
    assert "\n" not in str(info.value)
    allowed = check_plausibility(rec, source="r.csv", allow_implausible=True)
    assert len(allowed) == 1 and allowed[0].startswith("r.csv: ") and allowed[0].endswith(".")


@pytest.mark.parametrize(("scale", "match"), [
    ((1, 1, 1e-3), r"r\.csv: y spans 0\.006 - looks like metres; ipmc expects mm"),
    ((1000, 1, 1), r"r\.csv: t steps by 10 - looks like milliseconds; ipmc expects s"),
    ((1, 1.6, 1), r"r\.csv: u reaches 4 V, beyond the H-bridge's 3 V"),
    ((1, 1, 50), r"r\.csv: y reaches 150 mm, further than an IPMC strip is long"),
])
def test_plausibility_warns_of_a_likely_unit_mistake(scale, match):
    t, u, y = _plausible()
    notes = check_plausibility(Record(t * scale[0], u * scale[1], y * scale[2]),
                               source="r.csv")
    assert len(notes) == 1 and re.match(match, notes[0]) and notes[0].endswith(".")


def test_load_record_applies_the_plausibility_check(tmp_path):
    t, u, y = _plausible()
    volts = save_csv(Record(t, 100 * u, y), tmp_path / "volts.csv")
    with pytest.raises(DataError, match=r"volts\.csv: u reaches 250 V"):
        load_record(volts)
    notes = []
    assert len(load_record(volts, allow_implausible=True, notes=notes)) == 200
    assert len(notes) == 1 and "250 V" in notes[0]
    metres = save_csv(Record(t, u, y * 1e-3), tmp_path / "metres.csv")
    with pytest.warns(ImplausibleDataWarning, match="looks like metres"):
        load_record(metres)
    notes = []
    load_record(metres, notes=notes)
    assert len(notes) == 1 and "looks like metres" in notes[0]


def test_load_record_checks_a_bag_in_mm_after_conversion(tmp_path):
    # a bag's displacement is in metres on the topic: converted, it is plausible
    n = 40
    stamps = T0_NS + np.arange(n) * 10_000_000
    bag = write_bag(tmp_path / "bag", stamps, np.sin(np.arange(n) * 0.3), stamps,
                    2e-3 * np.cos(np.arange(n) * 0.3))
    notes = []
    load_record(bag, notes=notes)
    assert notes == []
    bag = write_bag(tmp_path / "bag_v", stamps, 300 * np.sin(np.arange(n) * 0.3), stamps,
                    2e-3 * np.cos(np.arange(n) * 0.3))
    with pytest.raises(DataError, match=r"bag_v: u reaches .* V, far beyond"):
        load_record(bag)


def test_export_main_refuses_an_implausible_bag_unless_allowed(tmp_path, capsys):
    n = 30
    stamps = T0_NS + np.arange(n) * 10_000_000
    bag = write_bag(tmp_path / "bag", stamps, np.linspace(-300, 300, n), stamps,
                    np.linspace(-1, 1, n) * 1e-3)
    out = tmp_path / "out.csv"
    assert export_main([str(bag), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("ipmc export: error: ") and "far beyond the H-bridge" in err
    assert not out.exists()
    assert export_main([str(bag), "--out", str(out), "--allow-implausible"]) == 0
    assert "ipmc export: warning: " in capsys.readouterr().err and out.exists()


def test_import_dataio_leaves_rclpy_out():
    code = ("import sys, ipmc_driver.dataio as d; d.load_record; "
            "assert 'rclpy' not in sys.modules, 'rclpy imported'")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=30)
