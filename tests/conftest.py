"""Fixtures for tests that cross packages and processes.

Every test session gets its own DDS domain (ROS_DOMAIN_ID from the pid) on loopback only, and
every process a test starts is stopped: SIGINT first, SIGKILL after a grace period, and the test
learns whether the grace was enough.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest

VENV_BIN = Path(sys.executable).parent
GRACE_S = 2.0
# Domain IDs 1..100 are safe on Linux; the pid spreads concurrent sessions apart.
SESSION_DOMAIN_ID = str(1 + os.getpid() % 100)


@pytest.fixture(scope="session")
def ros_env() -> dict:
    """Environment for child processes (and this one): a private domain on localhost."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = SESSION_DOMAIN_ID
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONUNBUFFERED"] = "1"
    saved = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    os.environ.update({k: env[k] for k in saved})
    yield env
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


class Processes:
    """The processes one test started; :meth:`stop` reports how long each took to exit."""

    def __init__(self, env: dict, log_dir: Path):
        self.env = env
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen] = {}
        self.returncodes: dict[str, int] = {}  # of the processes stop() ended

    def start(self, name: str, argv: list[str], **popen) -> subprocess.Popen:
        log = open(self.log_dir / f"{name}.log", "w")  # noqa: SIM115 - closed with the process
        proc = subprocess.Popen(argv, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                **popen)
        proc._log = log  # type: ignore[attr-defined]
        self.procs[name] = proc
        return proc

    def start_node(self, name: str, executable: str, params: dict | None = None
                   ) -> subprocess.Popen:
        argv = [str(VENV_BIN / executable), "--ros-args"]
        for key, value in (params or {}).items():
            argv += ["-p", f"{key}:={value}"]
        return self.start(name, argv)

    def log(self, name: str) -> str:
        return (self.log_dir / f"{name}.log").read_text()

    def stop(self, name: str, sig: int = signal.SIGINT) -> float:
        """Send ``sig``; return seconds until exit (inf if SIGKILL was needed)."""
        proc = self.procs.pop(name)
        t0 = time.monotonic()
        if proc.poll() is None:
            proc.send_signal(sig)
            try:
                proc.wait(timeout=GRACE_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
                proc._log.close()
                self.returncodes[name] = proc.returncode
                return float("inf")
        proc._log.close()
        self.returncodes[name] = proc.returncode
        return time.monotonic() - t0

    def stop_all(self) -> dict[str, float]:
        return {name: self.stop(name) for name in list(self.procs)}


def _domain_processes() -> dict[int, str]:
    """Processes other than this one whose environment is this session's domain: pid -> argv."""
    want = {f"ROS_DOMAIN_ID={SESSION_DOMAIN_ID}".encode(),
            b"ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST"}
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if want <= set((entry / "environ").read_bytes().split(b"\0")):
                found[int(entry.name)] = (entry / "cmdline").read_bytes().replace(
                    b"\0", b" ").decode(errors="replace").strip()
        except OSError:   # gone meanwhile, or another user's
            continue
    return {pid: argv for pid, argv in found.items() if argv}


@pytest.fixture(autouse=True)
def no_stray_nodes(request):
    """A test leaves no process on the session's domain behind: a node left running (a
    grandchild of a launcher, say) would publish into every later test's graph."""
    yield
    deadline = time.monotonic() + GRACE_S
    while (stray := _domain_processes()) and time.monotonic() < deadline:
        time.sleep(0.1)
    for pid in stray:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
    assert not stray, f"{request.node.name} left processes running: {stray}"


@pytest.fixture
def processes(ros_env, tmp_path):
    procs = Processes(ros_env, tmp_path)
    yield procs
    procs.stop_all()


@pytest.fixture
def rig_emulator(processes, tmp_path):
    """The rig emulator on a pty (``python -m ipmc_driver.emulator --link``): yields the process
    (its stdin takes the emulator's commands, e.g. ``unplug 1.0``) and the pty's path; stopped
    with SIGINT at the end, killed if it does not exit within 5 s."""
    emu = subprocess.Popen([sys.executable, "-m", "ipmc_driver.emulator", "--link",
                            str(tmp_path / "ttyRIG")], env=processes.env,
                           stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1)
    try:
        yield emu, emu.stdout.readline().strip()
    finally:
        emu.send_signal(signal.SIGINT)
        try:
            emu.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            emu.kill()
            emu.wait()


@pytest.fixture(scope="session")
def rclpy_context(ros_env):
    """An rclpy context of this test process, in the session's domain."""
    rclpy = pytest.importorskip("rclpy")
    context = rclpy.Context()
    rclpy.init(context=context)
    yield context
    rclpy.try_shutdown(context=context)


def spin_until(node, predicate, timeout_s: float, context=None) -> bool:
    """Spin ``node`` until ``predicate()`` is true or ``timeout_s`` passes; return the result."""
    from rclpy.executors import SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=context or node.context)
    executor.add_node(node)
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            if predicate():
                return True
            executor.spin_once(timeout_sec=0.02)
        return bool(predicate())
    finally:
        executor.remove_node(node)


def call_service(node, client, request, timeout_s: float = 10.0, retry_s: float = 2.0,
                 server_log=None):
    """Call ``client`` with ``request`` and return the response; repeat the call when no answer
    comes within ``retry_s`` seconds, until ``timeout_s`` seconds have passed.

    ``wait_for_service`` is true once the server's request reader is matched, but the server's
    response writer may not yet have matched this client's reader; rmw_fastrtps then waits
    100 ms and drops the response (ros2/ros2#1253). On a loaded machine that loses a first call.
    Only idempotent requests (parameter sets, reloads) are called this way. ``server_log``, a
    callable, adds the server's log to the failure message."""
    deadline = time.monotonic() + timeout_s
    assert client.wait_for_service(timeout_sec=timeout_s), f"no service {client.srv_name}"
    while True:
        future = client.call_async(request)
        left = deadline - time.monotonic()
        if spin_until(node, future.done, min(retry_s, max(left, 0.0))):
            return future.result()
        client.remove_pending_request(future)
        if time.monotonic() >= deadline:
            raise AssertionError(f"{client.srv_name} did not answer within {timeout_s} s"
                                 + (f"; the server's log:\n{server_log()}" if server_log else ""))
        # Shown in pytest's warning summary, so a CI log says how often the race struck.
        warnings.warn(f"{client.srv_name}: no answer within {retry_s} s, calling again",
                      stacklevel=2)


@pytest.fixture
def spin():
    """The :func:`spin_until` helper, as a fixture."""
    return spin_until


@pytest.fixture
def call():
    """The :func:`call_service` helper, as a fixture."""
    return call_service


def bag_commands_v(bag) -> list[float]:
    """The ``/ipmc/command`` voltages of a rosbag2 folder, in the order recorded."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == "/ipmc/command"]
        return [store.deserialize_cdr(raw, c.msgtype).data
                for c, _, raw in reader.messages(connections=conns)]


@pytest.fixture
def commands_v():
    """:func:`bag_commands_v`, as a fixture (test modules cannot import this conftest by
    name: the package test folders have conftest modules of their own)."""
    return bag_commands_v
