"""``reloc router``: a Zenoh router in this process (implemented in :mod:`.cli`)."""

from __future__ import annotations

from .cli import add_router_arguments as add_arguments
from .cli import run_router as main

run = main

__all__ = ["add_arguments", "main", "run"]
