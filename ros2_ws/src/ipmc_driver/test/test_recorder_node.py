"""The recorder as a real process over real DDS: what is published is what the bag holds."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from ipmc_driver.bagio import read_file_info
from ipmc_driver.dataio import load_record

rclpy = pytest.importorskip("rclpy")
from geometry_msgs.msg import PointStamped, Vector3Stamped  # noqa: E402
from rclpy.qos import QoSProfile, QoSReliabilityPolicy  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402

GRACE_S = 2.0
SAMPLE_QOS = QoSProfile(depth=100, reliability=QoSReliabilityPolicy.RELIABLE)
T0_NS = 1_000_000_000_000


@pytest.fixture(scope="module")
def ros_env():
    """A private DDS domain on loopback for this module, and an rclpy context in this process."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(100 + os.getpid() % 100)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    old = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    os.environ.update({k: env[k] for k in old})
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("recorder_test_source", context=context)
    try:
        yield env, node
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class Source:
    """Publishers of the rig's topics in the test process."""

    def __init__(self, node):
        self.voltage = node.create_publisher(Vector3Stamped, "/ipmc/voltage", SAMPLE_QOS)
        self.displacement = node.create_publisher(PointStamped, "/ipmc/displacement", SAMPLE_QOS)
        self.command = node.create_publisher(Float64, "/ipmc/command", 10)

    def wait_matched(self, timeout_s=10.0):
        deadline = time.monotonic() + timeout_s
        pubs = (self.voltage, self.displacement, self.command)
        while min(p.get_subscription_count() for p in pubs) < 1:
            assert time.monotonic() < deadline, "recorder did not subscribe in time"
            time.sleep(0.02)
        # Our side has matched; give the recorder's side time to match our writers too, or a
        # volatile reader may start after the first samples.
        time.sleep(1.0)

    def publish(self, k):
        ns = T0_NS + k * 10_000_000
        v = Vector3Stamped()
        v.header.stamp.sec, v.header.stamp.nanosec = divmod(ns, 1_000_000_000)
        v.vector.x = k * 1e-3
        y = PointStamped()
        y.header = v.header
        y.point.x = k * 1e-6
        self.command.publish(Float64(data=k * 1e-3))
        self.voltage.publish(v)
        self.displacement.publish(y)


def _start(env, bag, *params):
    args = [sys.executable, "-m", "ipmc_driver.nodes.recorder", "--ros-args",
            "-p", f"output:={bag}"]
    for p in params:
        args += ["-p", p]
    return subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def _stop(proc, sig=signal.SIGINT):
    """Send ``sig``; SIGKILL after the grace period. Returns the seconds it took to exit."""
    t0 = time.monotonic()
    proc.send_signal(sig)
    try:
        proc.wait(timeout=GRACE_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5)
    return time.monotonic() - t0


@pytest.mark.parametrize(("storage", "sig"), [("mcap", signal.SIGINT),
                                              ("sqlite3", signal.SIGTERM)])
def test_recorder_records_every_sample_and_stops_cleanly(ros_env, tmp_path, storage, sig):
    env, node = ros_env
    bag = tmp_path / "bag"
    proc = _start(env, bag, f"storage:={storage}")
    try:
        src = Source(node)
        src.wait_matched()
        n = 300
        for k in range(n):
            src.publish(k)
            time.sleep(0.001)
        time.sleep(1.0)  # let the last samples arrive, also on a loaded machine
    finally:
        took = _stop(proc, sig)
        out = proc.stdout.read()
    assert took < GRACE_S, f"recorder took {took:.2f} s to stop:\n{out}"
    assert proc.returncode == 0, out
    assert "closed" in out
    rec = load_record(bag, max_jitter=1e-6)
    assert len(rec) == n
    assert_allclose(rec.t_s, np.arange(n) * 0.01, atol=1e-9)
    assert_allclose(rec.u_v, np.arange(n) * 1e-3, rtol=1e-12)
    assert_allclose(rec.y_mm, np.arange(n) * 1e-3, rtol=1e-9)


def test_recorder_sigkill_then_bag_recover_keeps_completed_splits(ros_env, tmp_path):
    env, node = ros_env
    bag = tmp_path / "bag"
    proc = _start(env, bag, "split_s:=0.4", "flush_s:=0.1")
    try:
        src = Source(node)
        src.wait_matched()
        k = 0
        t_end = time.monotonic() + 2.0
        while time.monotonic() < t_end:
            src.publish(k)
            k += 1
            time.sleep(0.005)
        time.sleep(0.3)
    finally:
        _stop(proc, signal.SIGKILL)
        proc.stdout.read()
    assert proc.returncode == -signal.SIGKILL
    complete = sorted(bag.glob("bag_*.mcap"))
    assert complete, "no split was completed before the kill"
    in_complete = sum(read_file_info(f).message_count for f in complete)
    ipmc = Path(sys.executable).with_name("ipmc")
    cmd = [str(ipmc)] if ipmc.exists() else [sys.executable, "-m", "ipmc_driver.cli"]
    done = subprocess.run([*cmd, "bag-recover", str(bag)], capture_output=True, text=True,
                          timeout=30)
    assert done.returncode == 0, done.stderr
    assert "kept" in done.stdout
    rec = load_record(bag, max_jitter=1e-6)
    # Contiguous from the first sample (load_record refuses gaps and unpaired samples), holding
    # every completed split and what the torn one had flushed.
    assert_allclose(rec.u_v, np.arange(len(rec)) * 1e-3, rtol=1e-12)
    assert len(rec) >= in_complete // 3 - 1  # 3 topics a sample: command, voltage, y
    assert len(rec) >= k // 2, (len(rec), k)
