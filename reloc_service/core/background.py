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
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)

#: How long exit waits for each background thread after asking it to stop: work that checks
#: its cancel event between units of a few hundred milliseconds ends well within it.
EXIT_WAIT_S = 30.0

_lock = threading.Lock()
_running: dict[threading.Thread, threading.Event | None] = {}


def start_background(target: Callable[[], None], name: str,
                     cancel: threading.Event | None = None) -> threading.Thread:
    """Run ``target`` on a daemon thread named ``name`` that exit waits for; ``cancel``: the
    event ``target`` checks to stop early, set at exit."""

    def run() -> None:
        try:
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


atexit.register(stop_background)
