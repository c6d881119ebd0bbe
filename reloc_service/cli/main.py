"""``reloc``: the command line. Only wires subcommands: each lives in its own module of this
package (``add_arguments(parser)``, ``run(args) -> int``), imported only when it is chosen, so
``reloc --help`` loads neither NumPy nor OpenCV."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from ._delegate import TOOLS_EXTRA_HINT, UNAVAILABLE, missing_tools_extra

#: Subcommand -> (module in this package, one-line help). Order is the order in ``--help``.
COMMANDS: dict[str, tuple[str, str]] = {
    "synth": ("synth", "render a photoreal synthetic dataset with exact ground truth"),
    "dataset": ("dataset", "convert (TUM RGB-D, EuRoC) and check reloc datasets"),
    "eval": ("eval", "evaluate relocalization methods on a dataset"),
    "serve": ("serve", "run the Zenoh relocalization service"),
    "bench": ("bench", "run the benchmark suite"),
    "demo": ("demo", "render desk, serve it over Zenoh and relocalize every query"),
    "router": ("router", "run a Zenoh router (ground-station set-up)"),
    "map": ("map", "inspect map storage: `reloc map check DIR` (exit 1 if damaged)"),
}

#: Subcommands of the tools (reloc_service.tools), which need the ``tools`` extra installed.
TOOL_COMMANDS = frozenset({"synth", "dataset", "eval", "bench", "demo"})


def _version() -> str:
    from .. import __version__

    return __version__


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``reloc`` parser; only ``command``'s module is imported to fill its arguments."""
    parser = argparse.ArgumentParser(
        prog="reloc", description="Fast vision-based 6-DoF camera relocalization for MAVs: "
        "synthetic data, evaluation and a Zenoh service.")
    parser.add_argument("--version", action="version", version=f"reloc {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        sub_parser = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            module = importlib.import_module(f"{__package__}.{module_name}")
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
    if command in TOOL_COMMANDS and _refuse_without_tools_extra(command):
        return UNAVAILABLE
    parser = build_parser(command)
    args, extra = parser.parse_known_args(argv)
    if getattr(args, "_any_arguments", False):
        args.args = extra
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def _refuse_without_tools_extra(command: str) -> bool:
    """Say so and return True if the ``tools`` extra is missing: checked before the tool's
    module is imported, so its absence is one line rather than a traceback from deep inside
    a render or a plot."""
    missing = missing_tools_extra()
    if missing:
        print(f"reloc {command} {TOOLS_EXTRA_HINT} (not installed: {', '.join(missing)})",
              file=sys.stderr)
    return bool(missing)


if __name__ == "__main__":
    sys.exit(main())
