"""``reloc dataset``: implemented in :mod:`reloc_service.tools.data.cli`, imported only when the
subcommand is chosen."""

from __future__ import annotations

import argparse

HELP = "convert (TUM RGB-D, EuRoC, rosbag2) and check reloc datasets"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..tools.data.cli import add_dataset_arguments

    add_dataset_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ..tools.data.cli import main_dataset

    return main_dataset(args)
