"""The Zenoh relocalization service (``reloc serve``): pure ``bytes -> bytes`` handlers behind a
thin Zenoh layer, worker threads, a journal and background snapshots.

The wire format comes from ``reloc_client.protocol`` (one definition for both ends). In a
source checkout where the distribution is not installed, ``clients/`` is put on ``sys.path``
so that package is found.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path


def ensure_client_importable() -> None:
    """Make ``import reloc_client`` work from a source checkout (``clients/`` next to
    ``reloc_service/``); nothing to do when the distribution is installed."""
    if importlib.util.find_spec("reloc_client") is not None:
        return
    clients = Path(__file__).resolve().parents[2] / "clients"
    if (clients / "reloc_client" / "__init__.py").is_file():
        sys.path.insert(0, str(clients))


ensure_client_importable()

_LAZY = {"Service": "app", "serve": "app", "ServiceConf": "config", "load_config": "config",
         "parse_config": "config", "with_overrides": "config"}

__all__ = ["ensure_client_importable", *sorted(_LAZY)]


def __getattr__(name: str) -> object:
    """``Service``, ``ServiceConf``, ``load_config``... imported on first use (Zenoh, OpenCV
    load only then)."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
