"""The single ``ipmc`` console script: subcommands are discovered from the ``ipmc.commands``
entry-point group, so each ipmc-ros package contributes its own without a central list."""

from __future__ import annotations

import os
import sys
from importlib.metadata import entry_points

#: BLAS threads of an ``ipmc`` command unless the environment sets them. The fits' linear
#: algebra is on tall, narrow matrices, where a second thread gains little, and OpenBLAS
#: threads spin while another process holds the cores (the nodes of a running graph, a second
#: fit): a 60 000-sample ``ipmc identify`` took 107 s so, 45 s on one thread.
BLAS_THREADS = "1"


def limit_blas_threads(environ=os.environ) -> None:
    """Set ``OPENBLAS_NUM_THREADS`` to :data:`BLAS_THREADS` unless already set; before NumPy
    is imported (OpenBLAS reads it when it loads)."""
    environ.setdefault("OPENBLAS_NUM_THREADS", BLAS_THREADS)


def _commands() -> dict:
    return {ep.name: ep for ep in entry_points(group="ipmc.commands")}


def _usage(commands: dict) -> str:
    names = "\n".join(f"  {name}" for name in sorted(commands))
    return (
        "usage: ipmc COMMAND [ARGS...]\n\n"
        "IPMC actuator toolkit (ipmc-ros). Commands:\n"
        f"{names}\n\n"
        "Run 'ipmc COMMAND --help' for the options of one command."
    )


def main(argv: list[str] | None = None) -> int:
    """Dispatch ``ipmc COMMAND ARGS`` to the entry point registered under that name."""
    argv = list(sys.argv[1:] if argv is None else argv)
    commands = _commands()
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage(commands))
        return 0
    name, rest = argv[0], argv[1:]
    if name not in commands:
        print(f"ipmc: unknown command '{name}'.\n\n{_usage(commands)}", file=sys.stderr)
        return 2
    limit_blas_threads()
    func = commands[name].load()
    sys.argv = [f"ipmc {name}", *rest]
    result = func(rest)
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
