"""The single ``ipmc`` console script: subcommands are discovered from the ``ipmc.commands``
entry-point group, so each ipmc-ros package contributes its own without a central list."""

from __future__ import annotations

import sys
from importlib.metadata import entry_points


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
    func = commands[name].load()
    sys.argv = [f"ipmc {name}", *rest]
    result = func(rest)
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
