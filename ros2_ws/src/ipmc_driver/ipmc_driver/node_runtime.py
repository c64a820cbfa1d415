"""The one ``main()`` of every ipmc-ros node: help, init, spin, and a safe exit on any signal.

- ``-h``/``--help`` prints the node's docstring and usage without starting ROS (a ROS user's
  first question, and what the colcon test asks of an installed executable).
- SIGINT (rclpy's handler) and SIGTERM (ours, as ``bringup``/``launch`` stop children with it)
  both leave ``spin()`` the same way, so ``destroy_node()`` always runs: that is where a node
  makes hardware safe (0 V) and closes files.
- A node that cannot start (bad parameter, missing port) prints one line and exits 1.
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions


class Terminated(Exception):
    """Raised from the SIGTERM handler to leave ``spin()`` like SIGINT does."""


def _on_sigterm(signum, frame) -> None:
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
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.SIGINT)
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    node = None
    try:
        node = factory()
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
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second TERM must not skip cleanup
        try:
            if node is not None:
                node.destroy_node()
        finally:
            signal.signal(signal.SIGTERM, previous)
            rclpy.try_shutdown()
