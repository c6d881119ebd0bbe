"""A dependency-free progress bar on stderr for long work (training, rendering, evaluation)."""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")


def _enabled() -> bool:
    return os.environ.get("RELOC_PROGRESS", "1") != "0"


def progress(items: Iterable[T], *, total: int | None = None, desc: str = "") -> Iterator[T]:
    """Yield ``items`` while drawing ``desc [####....] i/total elapsed`` on stderr.

    On a terminal the bar redraws in place; otherwise (CI logs) it prints about ten lines in
    all. ``RELOC_PROGRESS=0`` silences it."""
    if total is None:
        total = len(items) if hasattr(items, "__len__") else None  # type: ignore[arg-type]
    if not _enabled():
        yield from items
        return
    tty = sys.stderr.isatty()
    start = time.perf_counter()
    step = max(1, (total or 10) // 10)
    i = 0
    for i, item in enumerate(items, 1):
        yield item
        if tty or i % step == 0 or i == total:
            _draw(desc, i, total, time.perf_counter() - start, tty)
    if tty and i:
        sys.stderr.write("\n")
        sys.stderr.flush()


def _draw(desc: str, i: int, total: int | None, elapsed: float, tty: bool) -> None:
    if total:
        filled = int(30 * i / total)
        bar = "#" * filled + "." * (30 - filled)
        eta = elapsed / i * (total - i)
        line = f"{desc} [{bar}] {i}/{total} {elapsed:5.1f}s (eta {eta:4.1f}s)"
    else:
        line = f"{desc} {i} {elapsed:5.1f}s"
    sys.stderr.write(("\r" + line) if tty else (line + "\n"))
    sys.stderr.flush()
