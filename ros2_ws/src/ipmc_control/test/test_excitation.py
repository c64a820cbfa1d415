"""Tests of the open-loop excitations (ipmc_control.excitation). Plain pytest, no ROS."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from numpy.testing import assert_allclose

from ipmc_control.excitation import (
    KINDS,
    ExcitationError,
    load_excitation,
    make_excitation,
    save_csv,
)
from ipmc_model.residuals import find_holds


def test_importing_the_core_leaves_rclpy_out():
    code = ("import sys, ipmc_control.excitation, ipmc_control.reach, ipmc_control.console; "
            "assert 'rclpy' not in sys.modules, 'rclpy imported'")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_stays_within_3_v_and_is_seeded(kind):
    a = make_excitation(kind, seconds=60.0, hold_s=5.0, seed=3)
    b = make_excitation(kind, seconds=60.0, hold_s=5.0, seed=3)
    assert a.u_v.size == 6000 and a.rate_hz == 100.0
    assert np.max(np.abs(a.u_v)) <= 3.0
    assert_allclose(a.u_v, b.u_v, rtol=0, atol=0)


@pytest.mark.parametrize("kind", ["mixed", "steps"])
def test_default_excitations_hold_levels_spanning_the_range_on_both_sides_of_the_split(kind):
    """What identification and diagnosis need: holds of several seconds (creep) at levels
    spanning +-amplitude, in the fit part (first 70 %) and the held-out part (last 30 %)."""
    exc = make_excitation(kind)       # the defaults: 240 s, holds of 8 s, 3 V
    holds = find_holds(exc.u_v, 0.01, 3.0)
    cut = int(0.7 * exc.u_v.size)
    assert sum(b <= cut for _, b in holds) >= 4 and sum(a >= cut for a, _ in holds) >= 2
    levels = sorted({round(float(exc.u_v[a]), 2) for a, _ in holds})
    assert levels[0] <= -2.9 and levels[-1] >= 2.9 and any(abs(v) < 1.6 for v in levels)
    assert exc.u_v.min() == pytest.approx(-3.0) and exc.u_v.max() == pytest.approx(3.0)
    # steps: a level change at every hold's end (the delay shows there)
    assert np.count_nonzero(np.abs(np.diff(exc.u_v)) > 0.5) >= 20


def test_random_sine_has_no_holds_and_a_bad_amplitude_is_refused():
    assert make_excitation("random-sine", seconds=60.0).holds() == []
    with pytest.raises(ExcitationError, match="<= 3 V"):
        make_excitation("mixed", amplitude_v=3.5)
    with pytest.raises(ExcitationError, match="too short for two holds of 8 s"):
        make_excitation("mixed", seconds=20.0)
    with pytest.raises(ExcitationError, match="choose one of"):
        make_excitation("chirp")


def test_a_csv_plays_back_exactly_and_is_checked(tmp_path):
    exc = make_excitation("steps", seconds=20.0, hold_s=2.0, seed=1)
    back = load_excitation(save_csv(exc, tmp_path / "u.csv"), 100.0)
    assert_allclose(back.u_v, exc.u_v, atol=1e-6)
    assert load_excitation(tmp_path / "u.csv", 100.0, seconds=5.0).u_v.size == 500
    with pytest.raises(ExcitationError, match="sampled at 100 Hz but the plant at 50 Hz"):
        load_excitation(tmp_path / "u.csv", 50.0)
    (tmp_path / "hot.csv").write_text("t,u\n0,0\n0.01,3.5\n0.02,0\n")
    with pytest.raises(ExcitationError, match="asks for 3.5 V, beyond"):
        load_excitation(tmp_path / "hot.csv", 100.0)
    (tmp_path / "ty.csv").write_text("t,y\n0,0\n0.01,1\n0.02,0\n")
    with pytest.raises(ExcitationError, match="columns t and u"):
        load_excitation(tmp_path / "ty.csv", 100.0)
    (tmp_path / "u.txt").write_text("t,u\n")
    with pytest.raises(ExcitationError, match=r"\.csv \(t,u\) or an ipmc diagnose"):
        load_excitation(tmp_path / "u.txt", 100.0)


def test_an_experiment_of_ipmc_diagnose_plays_its_voltages(tmp_path):
    from ipmc_model.diagnosis.experiment import EXPERIMENT_FORMAT, Experiment, holds

    u = np.concatenate([holds([2.0, -2.0], 4.0, 100.0), np.zeros(100)])
    doc = Experiment(100.0, 0.7, u, ()).as_dict()
    assert doc["format"] == EXPERIMENT_FORMAT
    (tmp_path / "next_experiment.json").write_text(json.dumps(doc))
    exc = load_excitation(tmp_path / "next_experiment.json", 100.0)
    assert_allclose(exc.u_v, u)
    assert len(exc.holds()) == 2
    (tmp_path / "other.json").write_text(json.dumps({**doc, "format": "ipmc-ros-model"}))
    with pytest.raises(ExcitationError, match="not an experiment of ipmc diagnose"):
        load_excitation(tmp_path / "other.json", 100.0)
    (tmp_path / "fast.json").write_text(json.dumps({**doc, "rate_hz": 200.0}))
    with pytest.raises(ExcitationError, match="200 Hz but the plant at 100 Hz"):
        load_excitation(tmp_path / "fast.json", 100.0)
    (tmp_path / "newer.json").write_text(json.dumps({**doc, "format_version": 99}))
    with pytest.raises(ExcitationError, match="format version 99; this ipmc-ros reads"):
        load_excitation(tmp_path / "newer.json", 100.0)


@pytest.mark.parametrize("lockstep,record", [(False, "bag"), (True, "bag"), (True, None)])
def test_open_loop_graph_has_no_controller_and_waits_for_its_listeners(lockstep, record):
    from ipmc_control.bringup import excite_specs

    specs = {s.name: s.params for s in excite_specs(
        rig_port=None, lockstep=lockstep, excitation={"kind": "steps"}, plant_effects=[],
        record=record)}
    assert set(specs) == {"excitation", "sim_plant"} | ({"recorder"} if record else set())
    listeners = 1 + bool(record)
    assert specs["excitation"]["min_subscribers"] == listeners
    assert specs["excitation"]["exit_at_end"] is not lockstep
    if record:
        assert specs["recorder"]["topics"] == ["/ipmc/command", "/ipmc/voltage",
                                               "/ipmc/displacement"]
    if lockstep:
        assert specs["sim_plant"]["lockstep_min_subscribers"] == listeners
        assert specs["sim_plant"]["lockstep_min_command_publishers"] == 1
    rig = {s.name for s in excite_specs(rig_port="/dev/ttyX", lockstep=lockstep,
                                        excitation={"kind": "mixed"}, plant_effects=[],
                                        record=record)}
    assert "driver" in rig and "sim_plant" not in rig


@pytest.mark.parametrize("sim_time", [False, True])
def test_before_its_listeners_match_a_lockstep_excitation_holds_the_sample_unanswered(
        sim_time, monkeypatch):
    """In real time a sample before the start is answered with 0 V; on sim time (a lock-step
    plant waits for the answer) it is held and answered with the first voltage once the
    listeners have matched, so the record carries no 0 V lead-in of the graph's discovery."""
    import os

    rclpy = pytest.importorskip("rclpy")
    from geometry_msgs.msg import PointStamped
    from rclpy.parameter import Parameter

    from ipmc_control.nodes.excitation import ExcitationNode

    monkeypatch.setenv("ROS_DOMAIN_ID", str(150 + os.getpid() % 50))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = ExcitationNode(context=context, parameter_overrides=[
            Parameter("kind", value="steps"), Parameter("duration_s", value=6.0),
            Parameter("hold_s", value=2.0), Parameter("min_subscribers", value=1),
            Parameter("use_sim_time", value=sim_time)])
        sent: list[float] = []
        monkeypatch.setattr(node, "_command", lambda u_v, sample: sent.append(u_v))
        first_v = float(node.excitation.u_v[0])
        node._on_sample(PointStamped())          # nobody listens yet: the gate is shut
        assert sent == ([] if sim_time else [0.0])
        monkeypatch.setattr(node, "_gate", type("Open", (), {"ready": lambda self: True})())
        node._answer_held()
        assert sent == ([first_v] if sim_time else [0.0])
        if sim_time:   # started: the poll for a held sample stops
            node._answer_held()
            assert node._hold_timer.is_canceled() and sent == [first_v]
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_leaving_the_node_sends_0_v_that_a_reliable_reader_receives_last(monkeypatch):
    """Every exit goes through ``destroy_node``: it publishes 0 V and waits (at most
    ``ZERO_ACK_S``) for the reliable readers' acknowledgement. A matched reader gets the 0 V
    last, right after nonzero commands; with no reader the wait returns at once. (A writer
    gone before delivery loses the sample on a loaded machine only; in one idle process the
    delivery is quicker than the destruction.)"""
    import os
    import threading
    import time

    rclpy = pytest.importorskip("rclpy")
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from std_msgs.msg import Float64

    from ipmc_control.nodes.excitation import ZERO_ACK_S, ExcitationNode
    from ipmc_driver.qos import COMMAND_QOS

    monkeypatch.setenv("ROS_DOMAIN_ID", str(200 + os.getpid() % 30))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.Context()
    rclpy.init(context=context)
    params = [Parameter("kind", value="steps"), Parameter("duration_s", value=6.0),
              Parameter("hold_s", value=2.0)]
    try:
        alone = ExcitationNode(context=context, parameter_overrides=params)
        t0 = time.perf_counter()
        alone.destroy_node()
        assert time.perf_counter() - t0 < 0.5 * ZERO_ACK_S
        reader = rclpy.create_node("reader", context=context)
        got: list[float] = []
        reader.create_subscription(Float64, "/ipmc/command", lambda m: got.append(m.data),
                                   COMMAND_QOS)
        node = ExcitationNode(context=context, parameter_overrides=params)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(reader)
        spin = threading.Thread(target=executor.spin, daemon=True)
        spin.start()
        deadline = time.monotonic() + 10.0
        while node.pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert node.pub.get_subscription_count() == 1, "the reader never matched"
        for v in (1.5, 2.0, 2.5):
            node.pub.publish(Float64(data=v))
        node.destroy_node()
        deadline = time.monotonic() + 5.0
        while (not got or got[-1] != 0.0) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert got[-4:] == [1.5, 2.0, 2.5, 0.0]
        executor.shutdown()
        reader.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_a_bag_recorded_with_an_experiment_keeps_it(tmp_path):
    """``ipmc bringup --experiment FILE --record BAG`` copies FILE into the bag, where ``ipmc
    diagnose --data BAG`` finds it; nothing is written without a bag folder or experiment."""
    from ipmc_control.bringup import keep_experiment
    from ipmc_model.diagnosis.experiment import BAG_EXPERIMENT, Experiment

    exp = tmp_path / "next_experiment.json"
    exp.write_text(json.dumps(Experiment(100.0, 0.7, np.zeros(300), ()).as_dict()))
    bag = tmp_path / "day2"
    keep_experiment(str(exp), str(bag))          # the recording never started: no folder
    assert not bag.exists()
    bag.mkdir()
    keep_experiment(None, str(bag))
    assert not (bag / BAG_EXPERIMENT).exists()
    keep_experiment(str(exp), str(bag))
    assert (bag / BAG_EXPERIMENT).read_text() == exp.read_text()
