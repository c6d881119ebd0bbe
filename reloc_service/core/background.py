"""Background work that ends before the interpreter does.

A daemon thread still running numpy, OpenCV or numba code while the interpreter finalizes
can crash the process at exit (a segmentation fault after the program's last line: the
modules it calls into are being torn down under it). So every background thread reloc starts
for work of its own (a loaded map's pools, the compiled kernels' warm-up) is started here: at
exit each one is asked to stop (its cancel event set, which the work checks between its
units) and waited for before finalization begins.
"""

from __future__ import annotations

import atexit
import logging
import os
import threading
from collections.abc import Callable

from .errors import Cancelled

log = logging.getLogger(__name__)

#: How long exit waits for each background thread after asking it to stop: work that checks
#: its cancel event between units of a few hundred milliseconds ends well within it.
EXIT_WAIT_S = 30.0

#: How much lower a background thread's CPU priority is than the queries' when it asks to be
#: (``nice``): Linux's scheduler weighs a thread at nice +10 at 110 against 1024 at nice 0,
#: so next to a query's thread on the same core it gets about a tenth of it, and all of it
#: when no query runs. A loaded map's pools take 1-3 s of CPU per 1000 keyframes (fleet
#: bench), which the queries on the maps already resident otherwise share a core with.
#: Threads it starts inherit the value (the pools' work starts none: numpy and single-
#: threaded kernels).
LOWER_PRIORITY = 10

_lock = threading.Lock()
_running: dict[threading.Thread, threading.Event | None] = {}


def stop_if(cancelled: Callable[[], bool] | None) -> None:
    """Raise :class:`~.errors.Cancelled` when ``cancelled`` (a work's cancel check, such as
    an event's ``is_set``) is given and true: called between a long work's units."""
    if cancelled is not None and cancelled():
        raise Cancelled("cancelled by its caller")


def start_background(target: Callable[[], None], name: str,
                     cancel: threading.Event | None = None, *,
                     yield_to_queries: bool = False) -> threading.Thread:
    """Run ``target`` on a daemon thread named ``name`` that exit waits for; ``cancel``: the
    event ``target`` checks to stop early, set at exit. With ``yield_to_queries``, the
    thread runs :data:`LOWER_PRIORITY` nice levels below the process's other threads."""

    def run() -> None:
        try:
            if yield_to_queries:
                lower_priority(LOWER_PRIORITY)
            target()
        finally:
            with _lock:
                _running.pop(threading.current_thread(), None)

    thread = threading.Thread(target=run, name=name, daemon=True)
    with _lock:
        _running[thread] = cancel
    thread.start()
    return thread


def stop_background(timeout_s: float = EXIT_WAIT_S) -> list[str]:
    """Ask every running background thread to stop and wait for each up to ``timeout_s``;
    the names of those still running after it (none when all ended)."""
    with _lock:
        running = list(_running.items())
    for _, cancel in running:
        if cancel is not None:
            cancel.set()
    late = []
    for thread, _ in running:
        if thread is not threading.current_thread():
            thread.join(timeout_s)
            if thread.is_alive():
                late.append(thread.name)
    if late:
        log.warning("background work still running at exit: %s", ", ".join(late))
    return late


def lower_priority(levels: int) -> bool:
    """Raise the calling thread's nice value by ``levels`` (Linux schedules threads one by
    one: the process's other threads keep theirs); False where that is not possible."""
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + levels)
    except (AttributeError, OSError) as exc:   # not Linux, or not allowed
        log.debug("background thread priority not lowered: %s", exc)
        return False
    return True


atexit.register(stop_background)
