"""The one ``main()`` of every ipmc-ros node: help, init, spin, and a safe exit on any signal.

- ``-h``/``--help`` prints the node's docstring and usage without starting ROS (a ROS user's
  first question, and what the colcon test asks of an installed executable).
- SIGINT and SIGTERM (``bringup``/``launch`` stop children with it) both leave ``spin()`` as an
  exception while the ROS context is still up, so ``destroy_node()`` always runs AND can still
  publish: that is where a node makes hardware safe (the controller's last 0 V command, the
  driver's 0 V frame) and closes files. rclpy's own handlers are off on purpose: they shut the
  context down under the executor, after which the last command cannot be sent and a message
  being taken raises RuntimeError (ros/joint_state_publisher#117).
- The signal handlers only note the signal; a 0.1 s wall-clock timer raises it inside the
  executor, between callbacks. Raising from the handler itself could land inside rclpy's C++
  message conversion, which then fails with "RuntimeError: Unable to convert call argument"
  and exits 1 with a traceback (seen on model_server under lock-step load). The timer also
  wakes the executor when a node's own timers follow a simulated clock that has stopped.
- A node that cannot start (bad parameter, missing port) prints one line and exits 1.
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

WAKE_PERIOD_S = 0.1


class Terminated(Exception):
    """Raised inside the executor after SIGINT or SIGTERM, to leave ``spin()``."""


_signalled: list[int] = []


def _on_signal(signum, frame) -> None:
    _signalled.append(signum)


def _wake() -> None:
    """Leave ``spin()`` if a signal came (raised here, between callbacks, not in the handler)."""
    if _signalled:
        raise Terminated()


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
    _signalled.clear()
    previous_int = signal.signal(signal.SIGINT, _on_signal)
    previous = signal.signal(signal.SIGTERM, _on_signal)
    node = None
    try:
        node = factory()
        node.create_timer(WAKE_PERIOD_S, _wake, clock=Clock(clock_type=ClockType.STEADY_TIME))
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
        # A second signal must not cut the cleanup short.
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            if node is not None:
                node.destroy_node()
        finally:
            signal.signal(signal.SIGTERM, previous)
            signal.signal(signal.SIGINT, previous_int)
            rclpy.try_shutdown()
