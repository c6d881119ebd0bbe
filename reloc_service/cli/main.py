"""``reloc``: the command line. Only wires subcommands: each is a module of this package with
the same interface (``HELP``, ``add_arguments(parser)``, ``run(args) -> int``) whose imports
of the implementation are inside its functions, so ``reloc --help`` loads neither NumPy nor
OpenCV."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from types import ModuleType

from .tools_extra import UNAVAILABLE, refuse_without_tools_extra

#: The subcommands, each implemented by the module of this package of the same name. Order is
#: the order in ``--help``.
COMMANDS = ("synth", "dataset", "eval", "serve", "bench", "demo", "router", "map")

DESCRIPTION = ("Fast vision-based 6-DoF camera relocalization for MAVs: synthetic data, "
               "evaluation and a Zenoh service.")


def _version() -> str:
    from .. import __version__

    return __version__


def command_module(command: str) -> ModuleType:
    """The module of subcommand ``command``: light to import (its help text and two functions
    that import the implementation when called)."""
    return importlib.import_module(f"{__package__}.{command}")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``reloc`` parser; only ``command``'s arguments are filled in (and only its
    implementation imported)."""
    parser = argparse.ArgumentParser(prog="reloc", description=DESCRIPTION)
    parser.add_argument("--version", action="version", version=f"reloc {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        module = command_module(name)
        sub_parser = sub.add_parser(name, help=module.HELP, description=module.HELP)
        if name == command:
            module.add_arguments(sub_parser)
            sub_parser.set_defaults(_run=module.run)
    return parser


def _chosen_command(argv: Sequence[str]) -> str | None:
    """The subcommand word: the first argument not starting with ``-`` (``reloc`` itself has
    only flags without values)."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``reloc`` with ``argv`` (default: ``sys.argv[1:]``); returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    command = _chosen_command(argv)
    if command is not None and refuse_without_tools_extra(command):
        return UNAVAILABLE
    parser = build_parser(command)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
