"""Running one step of a query beside another: a small pool of helper threads that a query
borrows when a core is idle (the multi relocalizer runs the place finder there while the
query's thread extracts its features; OpenCV's extraction releases the GIL, so the two steps
use two cores). A query that finds no idle core (other queries, other processes: counted by
the kernel, :func:`idle_core`) or every helper busy runs the step itself, in order: a
second thread on a busy machine would only take time from the first, and concurrent queries
never wait for each other's helpers."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Generic, TypeVar

T = TypeVar("T")

#: Helper threads of the process: one per core beyond the first (a query's own thread
#: keeps one core), at least one.
MAX_HELPERS = max(1, (os.cpu_count() or 2) - 1)


class Beside(Generic[T]):
    """A step started by :func:`run_beside`: :meth:`result` waits for it and returns its
    value, or raises the exception it raised (the same object, in the caller's thread)."""

    def __init__(self, future: Future[T] | None = None, call: Callable[[], T] | None = None
                 ) -> None:
        self._future = future
        self._call = call

    @property
    def overlapped(self) -> bool:
        """True when the step runs on a helper thread (False: it runs in :meth:`result`)."""
        return self._future is not None

    def result(self) -> T:
        if self._future is not None:
            return self._future.result()
        assert self._call is not None
        call, self._call = self._call, None
        return call()


class _Helpers:
    """The process's helper threads and how many are lent out (created on first use)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pool: ThreadPoolExecutor | None = None
        self._busy = 0

    def borrow(self) -> ThreadPoolExecutor | None:
        """The pool with one helper reserved for the caller, or None when all are lent."""
        with self._lock:
            if self._busy >= MAX_HELPERS:
                return None
            if self._pool is None:
                self._pool = ThreadPoolExecutor(MAX_HELPERS, thread_name_prefix="reloc-beside")
            self._busy += 1
            return self._pool

    def give_back(self) -> None:
        with self._lock:
            self._busy -= 1

    def reset_after_fork(self) -> None:
        """A forked child has none of its parent's threads: start afresh."""
        self._lock = threading.Lock()
        self._pool = None
        self._busy = 0


_HELPERS = _Helpers()
os.register_at_fork(after_in_child=_HELPERS.reset_after_fork)

#: The kernel's instant count of running and runnable threads (4th field, "running/total").
LOADAVG = "/proc/loadavg"


class _RunQueue:
    """:data:`LOADAVG` kept open (one ``pread``, under a microsecond), per process."""

    def __init__(self, path: str = LOADAVG, cores: int | None = None) -> None:
        self.path = path
        self._fd: int | None = None
        self._pid = -1
        self.cores = cores or _usable_cores()

    def running(self) -> int | None:
        """Threads running or waiting for a core on this machine now (the caller's
        included); None where the kernel does not say."""
        try:
            if self._pid != os.getpid():
                self._fd, self._pid = os.open(self.path, os.O_RDONLY), os.getpid()
            assert self._fd is not None
            return running_threads(os.pread(self._fd, 128, 0).decode("ascii"))
        except (OSError, ValueError, UnicodeDecodeError):
            return None


def running_threads(loadavg: str) -> int:
    """The running count of a ``/proc/loadavg`` line (``"0.5 0.4 0.3 2/180 4242"``: 2)."""
    fields = loadavg.split()
    if len(fields) < 4 or "/" not in fields[3]:
        raise ValueError(f"expected a /proc/loadavg line, got {loadavg!r}")
    return int(fields[3].split("/")[0])


def _usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


_RUN_QUEUE = _RunQueue()


def idle_core() -> bool:
    """Whether a core this process may use is idle now: fewer threads running or runnable
    on the machine (the caller included) than those cores. True where the kernel does not
    say (no ``/proc``), as on a machine the service has to itself."""
    running = _RUN_QUEUE.running()
    return running is None or running < _RUN_QUEUE.cores


def run_beside(step: Callable[[], T], *, enabled: bool = True) -> Beside[T]:
    """Start ``step`` on a helper thread and return at once, when a core is idle
    (:func:`idle_core`) and a helper free; else (or with ``enabled`` False) ``step`` runs
    when :meth:`Beside.result` is called. The caller must call :meth:`Beside.result` (also
    when its own work fails), so no step outlives its query."""
    pool = _HELPERS.borrow() if enabled and idle_core() else None
    if pool is None:
        return Beside(call=step)
    try:
        future = pool.submit(_then_give_back, step)
    except BaseException:
        _HELPERS.give_back()
        raise
    return Beside(future=future)


def _then_give_back(step: Callable[[], T]) -> T:
    """``step()`` on a helper, which is free again before its caller sees the result."""
    try:
        return step()
    finally:
        _HELPERS.give_back()
