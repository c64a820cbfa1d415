"""The one ``main()`` of every ipmc-ros node: help, init, spin, and a safe exit on any signal.

- ``-h``/``--help`` prints the node's docstring and usage without starting ROS (a ROS user's
  first question, and what the colcon test asks of an installed executable).
- SIGINT and SIGTERM (``bringup``/``launch`` stop children with it) both leave ``spin()`` as an
  exception while the ROS context is still up, so ``destroy_node()`` always runs AND can still
  publish: that is where a node makes hardware safe (the controller's last 0 V command, the
  driver's 0 V frame) and closes files. rclpy's own handlers are off on purpose: they shut the
  context down under the executor, after which the last command cannot be sent and a message
  being taken raises RuntimeError (ros/joint_state_publisher#117).
- The signal handlers only note the signal (``StopSignals``); a 0.1 s wall-clock timer raises
  it inside the executor, between callbacks. Raising from the handler itself could land inside
  rclpy's C++ message conversion, which then fails with "RuntimeError: Unable to convert call
  argument" and exits 1 with a traceback (seen on model_server under lock-step load). The timer
  also wakes the executor when a node's own timers follow a simulated clock that has stopped.
- A node that cannot start (bad parameter, missing port) prints one line and exits 1.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

WAKE_PERIOD_S = 0.1


class Terminated(Exception):
    """Raised inside the executor after SIGINT or SIGTERM, to leave ``spin()``."""


class StopSignals:
    """SIGINT (Ctrl-C) and SIGTERM (``bringup``, a launcher, a scheduler or a test runner),
    noted by their handlers and raised later by the owner, between callbacks: raised from the
    handler itself, a signal can land inside rclpy's C++ message conversion ("RuntimeError:
    Unable to convert call argument") or in rclpy's ``Future.__del__``, where it is only
    printed and the process runs on. Off the main thread no handler can be set: nothing is
    noted. Used by every node (``run_node``) and by ``ipmc track --graph``'s wait loop."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.signalled: list[int] = []
        self._previous: dict[int, object] = {}
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._note) for s in self.SIGNALS}

    def _note(self, signum: int, frame) -> None:
        self.signalled.append(signum)

    def raise_if_signalled(self) -> None:
        """KeyboardInterrupt after SIGINT, SystemExit(143) after SIGTERM; nothing otherwise."""
        if not self.signalled:
            return
        if self.signalled[0] == signal.SIGINT:
            raise KeyboardInterrupt
        raise SystemExit(128 + self.signalled[0])

    def ignore(self) -> None:
        """Ignore both from now on (a second signal must not cut a cleanup short)."""
        for signum in self._previous:
            signal.signal(signum, signal.SIG_IGN)

    def restore(self) -> None:
        """Put the handlers back that were there before."""
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous = {}


def run_node(factory: Callable[[], Node], args: list[str] | None = None, *, name: str,
             doc: str = "", usage: str = "", executor=None) -> None:
    """Run the node built by ``factory`` until SIGINT/SIGTERM; always destroy it.

    Parameters
    ----------
    factory : callable
        Builds the node (called after ``rclpy.init``).
    args : list of str, optional
        Command-line arguments (default ``sys.argv``).
    name : str
        Executable name, for messages.
    doc, usage : str
        Printed by ``--help``.
    executor : rclpy executor, optional
        Default: the global single-threaded executor of ``rclpy.spin``.
    """
    argv = sys.argv if args is None else args
    if "-h" in argv or "--help" in argv:
        print(doc.strip())
        if usage:
            print(f"\nusage: {usage}")
        return
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = StopSignals()

    def wake() -> None:
        # leave spin() if a signal came: raised here, between callbacks, not in the handler
        if stop.signalled:
            raise Terminated()

    node = None
    try:
        node = factory()
        node.create_timer(WAKE_PERIOD_S, wake, clock=Clock(clock_type=ClockType.STEADY_TIME))
        if executor is None:
            rclpy.spin(node)
        else:
            executor.add_node(node)
            executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException, Terminated):
        pass
    except (ValueError, OSError) as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        raise SystemExit(1) from None
    finally:
        stop.ignore()
        try:
            if node is not None:
                node.destroy_node()
        finally:
            stop.restore()
            rclpy.try_shutdown()
