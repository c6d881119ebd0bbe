"""``reloc synth``: implemented in :mod:`reloc_service.tools.synth.cli`, imported only when the
subcommand is chosen."""

from __future__ import annotations

import argparse

HELP = "render a photoreal synthetic dataset with exact ground truth"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..tools.synth.cli import add_synth_arguments

    add_synth_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ..tools.synth.cli import main_synth

    return main_synth(args)
