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
- Parameters: each node lists its own in a table of :class:`ParameterSpec` (default, meaning,
  read-only, check) and declares them with :func:`declare_checked`: a value of the wrong type
  (``-p k:=2`` for a float, ``-p watchdog_s:=abc``) or out of its range stops the start with one
  sentence naming the parameter (rclpy raises a 19-line traceback for the type). The same
  checks refuse a run-time change (:func:`check_changes`, in the node's
  ``add_on_set_parameters_callback``) with the reason; rclpy itself refuses a value of another
  type and a read-only parameter.
"""

from __future__ import annotations

import math
import re
import signal
import sys
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import rclpy
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import InvalidParameterTypeException, ParameterException
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
    except (ValueError, OSError, ParameterException) as exc:
        # ParameterException: a wrong type for a parameter rclpy declares itself (use_sim_time)
        print(f"{name}: error: {describe_parameter_error(exc)}", file=sys.stderr)
        raise SystemExit(1) from None
    finally:
        stop.ignore()
        try:
            if node is not None:
                node.destroy_node()
        finally:
            stop.restore()
            rclpy.try_shutdown()


# -- parameters ---------------------------------------------------------------------------------
Check = Callable[[Any], str]


class ParameterError(ValueError):
    """A parameter value a node refuses: one sentence naming the parameter."""


@dataclass(frozen=True)
class ParameterSpec:
    """One node parameter: its default (which fixes its type), meaning, and the check of a value.

    ``check(value)`` returns ``""`` for a good value, else why it is refused, as the end of a
    sentence that starts with the parameter's name ("must be > 0, got -1.0").
    """

    default: Any
    description: str
    read_only: bool = False
    check: Check | None = None


# How a value of each rclpy type is written on the command line.
_TYPE_WORDS = {
    "DOUBLE": "a float", "INTEGER": "an integer", "BOOL": "true or false",
    "STRING": "a string", "DOUBLE_ARRAY": "a list of floats, e.g. [0.0, 0.7]",
    "INTEGER_ARRAY": "a list of integers, e.g. [1, 2]", "BOOL_ARRAY": "a list of true/false",
    "STRING_ARRAY": "a list of strings, e.g. [a, b]", "BYTE_ARRAY": "a list of bytes"}
_TYPE_ERROR = re.compile(r"Trying to set parameter '(?P<name>.*?)' to '(?P<value>.*)' of type "
                         r"'(?P<given>\w+)', expecting type '(?:Type\.)?(?P<expected>\w+)'")


def describe_parameter_error(exc: Exception) -> str:
    """One sentence for a refused parameter; rclpy's type error says what to write instead."""
    found = (_TYPE_ERROR.search(str(exc))
             if isinstance(exc, InvalidParameterTypeException) else None)
    if found is None:
        return str(exc)
    expected, given, value = found["expected"], found["given"], found["value"]
    words = _TYPE_WORDS.get(expected, expected.lower())
    if (expected, given) == ("DOUBLE", "INTEGER"):
        words += f" (write {value}.0, not {value})"
    return (f"parameter {found['name']} must be {words}, got {value} "
            f"({given.lower().replace('_', ' ')})")


def declare_checked(node: Node, specs: dict[str, ParameterSpec]) -> dict[str, Any]:
    """Declare every parameter of ``specs`` on ``node`` and check the values it starts with.

    Returns
    -------
    dict
        Parameter name -> value.

    Raises
    ------
    ParameterError
        One sentence naming the first parameter of the wrong type or out of its range.
    """
    for name, spec in specs.items():
        try:
            node.declare_parameter(name, spec.default, ParameterDescriptor(
                description=spec.description, read_only=spec.read_only))
        except InvalidParameterTypeException as exc:
            raise ParameterError(describe_parameter_error(exc)) from None
    values = {name: node.get_parameter(name).value for name in specs}
    problem = check_values(specs, values)
    if problem:
        raise ParameterError(problem)
    return values


def check_values(specs: dict[str, ParameterSpec], values: dict[str, Any]) -> str:
    """Why the first refused value of ``values`` is refused (``""``: all good)."""
    for name, value in values.items():
        spec = specs.get(name)
        why = spec.check(value) if spec is not None and spec.check is not None else ""
        if why:
            return f"parameter {name} {why}"
    return ""


def check_changes(specs: dict[str, ParameterSpec], params: Iterable) -> SetParametersResult:
    """The answer to a run-time change (``add_on_set_parameters_callback``): refused with the
    reason when a new value fails its check."""
    problem = check_values(specs, {p.name: p.value for p in params})
    return SetParametersResult(successful=not problem, reason=problem)


# Checks for ParameterSpec.check: each returns "" or why the value is refused.
def positive(value: Any) -> str:
    """A finite number > 0."""
    return "" if _finite(value) and value > 0 else f"must be > 0, got {value!r}"


def non_negative(value: Any) -> str:
    """A finite number >= 0."""
    return "" if _finite(value) and value >= 0 else f"must be >= 0, got {value!r}"


def one_of(*choices: str) -> Check:
    """One of ``choices``."""
    def check(value: Any) -> str:
        return "" if value in choices else f"must be one of {', '.join(choices)}, got {value!r}"
    return check


def within(low: float, high: float, *, low_open: bool = False) -> Check:
    """A finite number in [low, high] (or (low, high] with ``low_open``)."""
    def check(value: Any) -> str:
        ok = _finite(value) and (low < value if low_open else low <= value) and value <= high
        bracket = "(" if low_open else "["
        return "" if ok else f"must be in {bracket}{low:g}, {high:g}], got {value!r}"
    return check


def finite(value: Any) -> str:
    """A finite number."""
    return "" if _finite(value) else f"must be a finite number, got {value!r}"


def not_empty(value: Any) -> str:
    """A non-empty string."""
    return "" if isinstance(value, str) and value.strip() else "must not be empty"


def _finite(value: Any) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value))
