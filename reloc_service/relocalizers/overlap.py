"""Running one step of a query beside another: a small pool of helper threads that a query
borrows when one is idle (the multi relocalizer extracts the query's features there while
the place finder ranks keyframes). OpenCV's feature extraction releases the GIL, so the two
steps use two cores; a query that finds every helper busy runs the step itself, in order,
so concurrent queries never wait for each other's helpers."""

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


def run_beside(step: Callable[[], T], *, enabled: bool = True) -> Beside[T]:
    """Start ``step`` on an idle helper thread and return at once; without one (every helper
    busy, or ``enabled`` False) ``step`` runs when :meth:`Beside.result` is called. The
    caller must call :meth:`Beside.result` (also when its own work fails), so no step
    outlives its query."""
    pool = _HELPERS.borrow() if enabled else None
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
