"""Subcommands implemented elsewhere (``serve``, ``bench``, ``demo``, ``router``): their module
is imported only when the subcommand is chosen; a missing module, or a missing ``tools`` extra
for a tool subcommand, is a clear exit status 2."""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys
from types import ModuleType

#: Exit status when the module behind a subcommand is not installed.
UNAVAILABLE = 2

#: Import names of the third-party packages of pyproject's ``tools`` extra (scikit-image,
#: matplotlib): the tool subcommands need them, the service does not.
TOOLS_EXTRA_MODULES = ("skimage", "matplotlib")
TOOLS_EXTRA_HINT = "needs the tools extra: pip install 'reloc[tools]'"


def missing_tools_extra() -> list[str]:
    """The modules of :data:`TOOLS_EXTRA_MODULES` that are not installed. ``find_spec`` locates
    a top-level module without importing it, so asking costs no import time."""
    return [name for name in TOOLS_EXTRA_MODULES if importlib.util.find_spec(name) is None]


def import_optional(module_name: str) -> ModuleType | None:
    """``module_name`` imported, or None if it (or a package above it) does not exist; an
    import error *inside* an existing module is raised, not hidden."""
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        missing = exc.name or ""
        if missing and (module_name == missing or module_name.startswith(missing + ".")):
            return None
        raise


def accept_any_arguments(parser: argparse.ArgumentParser, help_text: str) -> None:
    """Let ``parser`` take any further words (flags too); ``reloc``'s main puts them in
    ``args.args`` (argparse's REMAINDER does not take a leading flag in a subparser)."""
    parser.usage = f"%(prog)s [-h] ARGS ...  ({help_text})"
    parser.set_defaults(_any_arguments=True)


class Delegate:
    """A subcommand whose ``add_arguments(parser)`` (optional) and ``main(args) -> int`` live in
    ``module_name``. Without ``add_arguments``, every further word is passed on as ``args.args``."""

    def __init__(self, command: str, module_name: str) -> None:
        self.command = command
        self.module_name = module_name
        self.module: ModuleType | None = None

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        self.module = import_optional(self.module_name)
        add = getattr(self.module, "add_arguments", None)
        if add is not None:
            add(parser)
        else:
            accept_any_arguments(parser, f"arguments for {self.module_name}.main")

    def run(self, args: argparse.Namespace) -> int:
        if self.module is None:
            self.module = import_optional(self.module_name)
        if self.module is None or not hasattr(self.module, "main"):
            what = "is not installed" if self.module is None else "has no main(args)"
            print(f"reloc {self.command}: not available in this installation "
                  f"({self.module_name} {what})", file=sys.stderr)
            return UNAVAILABLE
        return int(self.module.main(args) or 0)
