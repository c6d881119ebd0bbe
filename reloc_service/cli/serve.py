"""``reloc serve``: implemented in :mod:`reloc_service.service.cli`, imported only when the
subcommand is chosen."""

from __future__ import annotations

import argparse

HELP = "run the Zenoh relocalization service"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..service.cli import add_arguments as add_serve_arguments

    add_serve_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ..service.cli import run as run_serve

    return run_serve(args)
