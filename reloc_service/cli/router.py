"""``reloc router``: implemented in :mod:`reloc_service.service.cli` (beside ``reloc serve``,
with which it shares the Zenoh flags), imported only when the subcommand is chosen."""

from __future__ import annotations

import argparse

HELP = "run a Zenoh router (ground-station set-up)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..service.cli import add_router_arguments

    add_router_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ..service.cli import run_router

    return run_router(args)
