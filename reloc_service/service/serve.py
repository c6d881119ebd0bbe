"""``reloc serve``'s process: run a :class:`~.app.Service` until SIGINT or SIGTERM, then
leave without letting the interpreter's exit abort on a thread still inside native code."""

from __future__ import annotations

import logging
import os
import sys
import threading

from ..storage.lock import LockHeld
from . import open_files
from .app import Service
from .config import ServiceConf
from .workers import stop_on_signals

log = logging.getLogger(__name__)


def serve(conf: ServiceConf) -> int:
    """Run a service for ``conf`` until SIGINT/SIGTERM; the exit status. The signal handlers
    are installed first, so a signal during start-up (restoring maps) still stops cleanly.

    Once stopped (everything journaled and closed), a thread still running (a training job
    inside OpenCV, a snapshot past the budget) would be killed by the interpreter's exit in
    native code, which aborts the process ("exception not rethrown"): the process then
    leaves with ``os._exit`` instead."""
    stop = stop_on_signals()
    # Two files per served map: systemd's soft limit of 1024 holds about 380 of them.
    open_files.raise_limit(max(conf.quotas.max_maps, len(conf.maps)))
    service = Service(conf)
    try:
        service.start(wait_ready=False)   # small maps are served while big ones replay
    except LockHeld:   # another process owns the storage: nothing was started or written
        raise
    except BaseException:
        service.stop(final_snapshot=False)
        raise
    service.start_workers_in_background()   # the first query does not wait for them
    service.run_forever(stop)
    # a restore stops at its next journal record; a snapshot load cannot: left to os._exit
    if not service.wait_ready(timeout=conf.service.stop_timeout_s):
        log.warning("a map restore was still running at exit")
    _exit_if_threads_linger(0)
    return 0


def _exit_if_threads_linger(code: int) -> None:
    """``os._exit(code)`` (after flushing logs and stdio) if a Python thread still runs (ours,
    or zenoh-python's callback threads, which block inside Rust)."""
    lingering = [t.name for t in threading.enumerate()
                 if t is not threading.current_thread() and t.is_alive()
                 and not isinstance(t, threading._DummyThread)]  # type: ignore[attr-defined]
    if not lingering:
        return
    ours = [name for name in lingering if "pyo3" not in name]
    log.log(logging.WARNING if ours else logging.DEBUG, "exiting without waiting for %s",
            ", ".join(sorted(lingering)))
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)

