"""``reloc demo``: implemented in :mod:`reloc_service.tools.demo`, imported only when the
subcommand is chosen."""

from __future__ import annotations

import argparse

HELP = "render desk, serve it over Zenoh and relocalize every query"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..tools.demo import add_arguments as add_demo_arguments

    add_demo_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ..tools.demo import run as run_demo

    return run_demo(args)
