"""``reloc bench``: implemented in :mod:`reloc_service.tools.bench.cli`, imported only when the
subcommand is chosen."""

from __future__ import annotations

import argparse

HELP = "run the benchmark suite"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..tools.bench.cli import add_arguments as add_bench_arguments

    add_bench_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ..tools.bench.cli import main as run_bench

    return run_bench(args)
