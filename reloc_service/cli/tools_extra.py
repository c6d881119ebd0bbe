"""The ``tools`` extra (scikit-image, matplotlib): which subcommands need it, and the one check
that refuses them, exit status 2 and one line naming the extra, when it is not installed."""

from __future__ import annotations

import importlib.util
import sys

#: Exit status of a subcommand refused because the extra is not installed.
UNAVAILABLE = 2

#: Import names of the third-party packages of pyproject's ``tools`` extra (scikit-image,
#: matplotlib): the tool subcommands need them, the service does not.
TOOLS_EXTRA_MODULES = ("skimage", "matplotlib")
TOOLS_EXTRA_HINT = "needs the tools extra: pip install 'reloc[tools]'"

#: Subcommands implemented in ``reloc_service.tools``, which need the extra.
TOOL_COMMANDS = frozenset({"synth", "dataset", "eval", "bench", "demo"})


def missing_tools_extra() -> list[str]:
    """The modules of :data:`TOOLS_EXTRA_MODULES` that are not installed. ``find_spec`` locates
    a top-level module without importing it, so asking costs no import time."""
    return [name for name in TOOLS_EXTRA_MODULES if importlib.util.find_spec(name) is None]


def refuse_without_tools_extra(command: str) -> bool:
    """True, after saying so on stderr, if ``command`` needs the extra and it is missing.
    Asked before the subcommand's implementation is imported, so a missing extra is one line
    rather than a traceback from deep inside a render or a plot."""
    if command not in TOOL_COMMANDS:
        return False
    missing = missing_tools_extra()
    if missing:
        print(f"reloc {command} {TOOLS_EXTRA_HINT} (not installed: {', '.join(missing)})",
              file=sys.stderr)
    return bool(missing)
