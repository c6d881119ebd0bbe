"""Giving freed heap memory back to the system after a refused oversized payload (and
after a resident map is closed, :mod:`.residency`: :func:`release_memory`).

Zenoh reassembles a put or query in full before the service sees it (a 300 MiB put takes
300 MiB whatever the service then does). When that buffer is freed, glibc keeps the pages in
its arenas (its mmap threshold has grown past such sizes after the first big free), so the
resident memory never comes back down and each refused put can leave the process bigger.
``malloc_trim(0)`` returns the free pages of every arena to the system. It runs a moment
after the refusal, once Zenoh has dropped the sample (the callback that refuses it still
holds it), on a timer thread alive only until then; several refusals in a row share one trim.
Where the C library is not glibc, nothing is done.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import gc
import logging
import os
import threading
from collections.abc import Callable, Iterable
from pathlib import Path

log = logging.getLogger(__name__)

#: Seconds between a refusal and the trim (Zenoh frees the payload when its callback returns).
TRIM_DELAY_S = 0.5


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim``, or None without glibc."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim  # type: ignore[no-any-return]


def trim_now() -> bool:
    """Return the free heap pages to the system now; False where there is no glibc."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


def release_memory() -> None:
    """Free what nothing references any more, reference cycles included, and give the free
    heap pages back (:func:`trim_now`). A closed map's objects refer to each other (about
    6000 of them in cycles): on a 1000-keyframe map, 248 of the 272 MB it added stayed
    resident after it was closed and trimmed until the cyclic collector ran, which a service
    that allocates little may not do for minutes."""
    gc.collect()
    trim_now()


class Trimmer:
    """Trims the heap :data:`TRIM_DELAY_S` after :meth:`request` (requests meanwhile join
    the pending trim)."""

    def __init__(self, delay_s: float = TRIM_DELAY_S) -> None:
        self.delay_s = delay_s
        self._lock = threading.Lock()
        self._pending: threading.Timer | None = None

    def request(self) -> None:
        with self._lock:
            if self._pending is not None or _malloc_trim() is None:
                return
            self._pending = threading.Timer(self.delay_s, self._run)
            self._pending.name = "malloc-trim"
            self._pending.daemon = True
            self._pending.start()

    def _run(self) -> None:
        with self._lock:
            self._pending = None
        trim_now()
        log.debug("heap trimmed after a refused oversized payload")

    def cancel(self) -> None:
        """Drop a pending trim (the service is stopping)."""
        with self._lock:
            pending, self._pending = self._pending, None
        if pending is not None:
            pending.cancel()


def rss_bytes(pid: int | None = None) -> int:
    """The resident memory (``VmRSS`` of ``/proc/<pid>/status``) of process ``pid`` (None:
    this one) in bytes; 0 when it is gone or ``/proc`` is not there."""
    path = Path(f"/proc/{os.getpid() if pid is None else pid}/status")
    try:
        for line in path.read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024   # reported in kB
    except (OSError, ValueError, IndexError):
        return 0
    return 0


def descendants(pid: int | None = None) -> list[int]:
    """The process ids of every descendant of ``pid`` (None: this process): with worker
    processes, the forkserver and the workers it forked."""
    root = os.getpid() if pid is None else pid
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(stat.parent.name))
    found, todo = [], list(children.get(root, []))
    while todo:
        child = todo.pop()
        found.append(child)
        todo += children.get(child, [])
    return found


def total_rss_bytes(pids: Iterable[int]) -> int:
    """The sum of :func:`rss_bytes` over ``pids``."""
    return sum(rss_bytes(p) for p in pids)
