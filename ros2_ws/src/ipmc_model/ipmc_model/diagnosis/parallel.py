"""Independent fits on several cores: a round's candidates are each fitted around the same
model, and a profile's grid points each refit it; none depends on another's result, so they
run in forked worker processes and come back in order, the same models as one after the
other.

Written by hand over ``multiprocessing``: the fits are closures over the record and the model
(no pickling of the work, only of the fitted models that come back), which a fork carries and
``concurrent.futures`` would have to pickle.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import TypeVar

from threadpoolctl import threadpool_limits

T = TypeVar("T")
R = TypeVar("R")

#: Worker processes the fits of the running diagnosis may use (1: in this process).
_JOBS: ContextVar[int] = ContextVar("diagnosis_jobs", default=1)
#: The work of the running :func:`fan_out`, read by the forked workers.
_WORK: tuple[Callable, list] | None = None


def cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@contextmanager
def using(jobs: int | None) -> Iterator[int]:
    """Let the fits inside use ``jobs`` worker processes (None: :func:`cores`); one where
    this process cannot fork, or is itself a daemonic worker (which may not have children)."""
    n = cores() if jobs is None else int(jobs)
    if n < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    if ("fork" not in multiprocessing.get_all_start_methods()
            or multiprocessing.current_process().daemon):
        n = 1
    token = _JOBS.set(n)
    try:
        yield n
    finally:
        _JOBS.reset(token)


def fan_out(fn: Callable[[T], R], items: Iterable[T], costs=None) -> list[R]:
    """``[fn(x) for x in items]``, on the worker processes :func:`using` allows, each held
    to one BLAS thread (the workers share the cores). ``costs``: each item's expected run
    time (any unit); the costliest start first, so that the last to finish is short."""
    global _WORK
    items = list(items)
    jobs = min(_JOBS.get(), len(items))
    if jobs <= 1 or _WORK is not None:   # one core, or already inside a fan-out
        return [fn(x) for x in items]
    order = (sorted(range(len(items)), key=lambda i: -costs[i]) if costs is not None
             else list(range(len(items))))
    _WORK = (fn, items)
    try:
        pool = multiprocessing.get_context("fork").Pool(jobs, initializer=_worker_start)
        try:
            done = pool.map(_run, order, chunksize=1)
            pool.close()     # idle workers leave on the end-of-work message, not on a signal
        except BaseException:
            pool.terminate()
            raise
        finally:
            pool.join()
    finally:
        _WORK = None
    out: list = [None] * len(items)
    for i, r in zip(order, done, strict=True):
        out[i] = r
    return out


def _worker_start() -> None:
    """One BLAS thread; the default end on SIGTERM and Ctrl-C left to the parent. A fork
    inherits the parent's signal handlers: a live ROS context's SIGTERM handler would keep
    the worker alive when the pool ends it, and the parent would wait for it forever."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threadpool_limits(1)


def _run(i: int):
    fn, items = _WORK
    return fn(items[i])
