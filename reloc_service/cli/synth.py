"""``reloc synth``: render a photoreal synthetic reloc dataset.

The glue (``add_synth_arguments``, ``main_synth``) is in ``reloc_service.tools.synth.cli``, imported
only when the subcommand is chosen.
"""

from __future__ import annotations

import argparse
import sys

from ._delegate import UNAVAILABLE, accept_any_arguments, import_optional

HELP = "render a photoreal synthetic dataset with exact ground truth"
GLUE = "reloc_service.tools.synth.cli"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    glue = import_optional(GLUE)
    if glue is None:
        accept_any_arguments(parser, f"{GLUE} is not installed")
    else:
        glue.add_synth_arguments(parser)


def run(args: argparse.Namespace) -> int:
    glue = import_optional(GLUE)
    if glue is None:
        print(f"reloc synth: not available in this installation ({GLUE} is not installed)",
              file=sys.stderr)
        return UNAVAILABLE
    return int(glue.main_synth(args) or 0)
