"""Running one step of a query beside another: a small pool of helper threads that a query
borrows when a core is idle (the multi relocalizer runs the place finder there while the
query's thread extracts its features; OpenCV's extraction releases the GIL, so the two steps
use two cores). A query that finds no idle core (other queries, other processes: counted by
the kernel, :func:`idle_core`) or every helper busy runs the step itself, in order: a
second thread on a busy machine would only take time from the first, and concurrent queries
never wait for each other's helpers.

:func:`run_beside` is for work the query needs now (it waits for it); :func:`run_ahead` for
work it may need later, or not at all (a fallback chain's next step's features, started when
the current step begins to fail), which nobody has to wait for.

The module owns its helpers: :func:`close_helpers` lets the steps under way finish (a bounded
wait), stops the threads and joins them, and runs at interpreter exit too (``atexit``). A
helper must not be inside OpenCV when the interpreter finalizes: the interpreter ends a daemon
thread that returns to it then with ``pthread_exit``, whose unwinding through OpenCV's
``catch (...)`` aborts the process ("FATAL: exception not rethrown", exit 134), as a step
started ahead for the last query of ``reloc eval`` could."""

from __future__ import annotations

import atexit
import os
import queue
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, Generic, TypeVar

T = TypeVar("T")

#: Helper threads of the process: one per core beyond the first (a query's own thread
#: keeps one core), at least one.
MAX_HELPERS = max(1, (os.cpu_count() or 2) - 1)


#: Seconds :func:`close_helpers` waits at interpreter exit for the steps under way (one
#: query's feature extraction or place finding takes well under a second).
EXIT_WAIT_S = 10.0

#: Name of the helper threads.
THREAD_NAME = "reloc-beside"


class _Helper:
    """One daemon thread running the tasks put in its inbox until it finds ``None`` there; a
    task delivers its own outcome (:class:`Beside` into the helper's outbox, :class:`Ahead`
    into itself). Queues, not a ``concurrent.futures`` pool: a hand-off is two C-level queue
    operations (a pool's submit took 0.13 ms of Python per query). Daemon, so that a step
    stuck past :func:`close_helpers`'s wait cannot hold the process forever; joined by
    :func:`close_helpers` otherwise."""

    def __init__(self) -> None:
        self.inbox: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self.outbox: queue.SimpleQueue[tuple[bool, Any]] = queue.SimpleQueue()
        #: Set (under the pool's lock) once the helper is told to stop: never lent again.
        self.retired = False
        self.thread = threading.Thread(target=self._serve, name=THREAD_NAME, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while True:
            task = self.inbox.get()
            if task is None:
                return
            task()
            del task


def _outcome(step: Callable[[], T]) -> tuple[bool, Any]:
    """(True, value) or (False, the exception ``step`` raised)."""
    try:
        return True, step()
    except BaseException as exc:  # noqa: BLE001 (handed to the caller as it is)
        return False, exc


class Beside(Generic[T]):
    """A step started by :func:`run_beside`: :meth:`result` waits for it and returns its
    value, or raises the exception it raised (the same object, in the caller's thread)."""

    def __init__(self, helper: _Helper | None = None, call: Callable[[], T] | None = None
                 ) -> None:
        self._helper = helper
        self._call = call

    @property
    def overlapped(self) -> bool:
        """True when the step runs on a helper thread (False: it runs in :meth:`result`)."""
        return self._helper is not None

    def result(self) -> T:
        """The step's value (waiting for its helper, which is then free for the next)."""
        if self._helper is None:
            assert self._call is not None
            call, self._call = self._call, None
            return call()
        helper, self._helper = self._helper, None
        ok, value = helper.outbox.get()
        _HELPERS.give_back(helper)
        if not ok:
            raise value
        return value  # type: ignore[no-any-return]


class _Helpers:
    """The process's helper threads, the free ones in a queue (created on first use). A task
    is put in a helper's inbox under the lock that :meth:`close` takes, so no task lands
    behind a helper's stop and waits forever."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._free: queue.SimpleQueue[_Helper] = queue.SimpleQueue()
        self._started: list[_Helper] = []
        self._closed = False

    def lend(self, task_for: Callable[[_Helper], Callable[[], None]]) -> _Helper | None:
        """A free helper (started if fewer than :data:`MAX_HELPERS` are) running
        ``task_for(helper)``; None, nothing started, when all are lent or the pool is
        closed."""
        with self._lock:
            if self._closed:
                return None
            try:
                helper = self._free.get_nowait()
            except queue.Empty:
                if len(self._started) >= MAX_HELPERS:
                    return None
                helper = _Helper()
                self._started.append(helper)
            helper.inbox.put(task_for(helper))
            return helper

    def give_back(self, helper: _Helper) -> None:
        with self._lock:
            if not helper.retired:
                self._free.put(helper)

    def close(self, timeout: float, *, final: bool = False) -> list[threading.Thread]:
        """Stop every helper once the task it runs (if any) ends, and join them within
        ``timeout`` seconds; the threads still running then. Later steps start new helpers,
        unless ``final`` (interpreter exit: they run in the caller's thread)."""
        with self._lock:
            self._closed = True
            helpers, self._started = self._started, []
            self._free = queue.SimpleQueue()
            for helper in helpers:
                helper.retired = True
                helper.inbox.put(None)
        deadline = time.monotonic() + timeout
        for helper in helpers:
            helper.thread.join(max(0.0, deadline - time.monotonic()))
        with self._lock:
            self._closed = final
        return [h.thread for h in helpers if h.thread.is_alive()]

    def reset_after_fork(self) -> None:
        """A forked child has none of its parent's threads: start afresh."""
        self.__init__()  # type: ignore[misc]


_HELPERS = _Helpers()
os.register_at_fork(after_in_child=_HELPERS.reset_after_fork)


def close_helpers(timeout: float = EXIT_WAIT_S) -> bool:
    """Let the steps under way finish, stop the helper threads and join them (within
    ``timeout`` seconds); True when none is left running. Steps started later start new
    helpers. For whoever ends the work of a process (a command, a service stopping)."""
    return not _HELPERS.close(timeout)


def _close_at_exit() -> None:
    """Interpreter exit: :func:`close_helpers`, and no helper after it (a step started by
    another exit handler runs in its caller's thread). A step still running after
    :data:`EXIT_WAIT_S` is named on stderr: the interpreter may abort when it returns."""
    left = _HELPERS.close(EXIT_WAIT_S, final=True)
    if left:
        print(f"reloc: {len(left)} helper thread(s) still running a step after "
              f"{EXIT_WAIT_S:g} s at exit", file=sys.stderr)


atexit.register(_close_at_exit)

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


#: Seconds a reading of the run queue answers :func:`idle_core` for: a read right after
#: other work costs about 0.05 ms (against 4 us warm), so queries in quick succession
#: share one, and a machine's load changes more slowly than that.
IDLE_READING_S = 0.02

_last_reading: tuple[float, bool] = (-1.0, True)


def idle_core() -> bool:
    """Whether a core this process may use is idle: fewer threads running or runnable on
    the machine (the caller included) than those cores, read at most every
    :data:`IDLE_READING_S`. True where the kernel does not say (no ``/proc``), as on a
    machine the service has to itself."""
    global _last_reading
    now = time.monotonic()
    if now - _last_reading[0] < IDLE_READING_S:
        return _last_reading[1]
    running = _RUN_QUEUE.running()
    idle = running is None or running < _RUN_QUEUE.cores
    _last_reading = (now, idle)
    return idle


def run_beside(step: Callable[[], T], *, enabled: bool = True) -> Beside[T]:
    """Start ``step`` on a helper thread and return at once, when a core is idle
    (:func:`idle_core`) and a helper free; else (or with ``enabled`` False) ``step`` runs
    when :meth:`Beside.result` is called. The caller must call :meth:`Beside.result` (also
    when its own work fails), so no step outlives its query."""
    if not (enabled and idle_core()):
        return Beside(call=step)

    def task_for(helper: _Helper) -> Callable[[], None]:
        outbox = helper.outbox
        return lambda: outbox.put(_outcome(step))

    helper = _HELPERS.lend(task_for)
    return Beside(call=step) if helper is None else Beside(helper=helper)


class Ahead(Generic[T]):
    """A step started by :func:`run_ahead`, which nobody has to wait for: its helper goes
    back to the pool when the step ends. :meth:`result` waits for it and returns its value,
    or raises the exception it raised."""

    def __init__(self) -> None:
        self._done = threading.Event()
        self._outcome: tuple[bool, Any] = (False, None)

    def _finish(self, outcome: tuple[bool, Any]) -> None:
        self._outcome = outcome
        self._done.set()

    @property
    def done(self) -> bool:
        return self._done.is_set()

    def result(self) -> T:
        self._done.wait()
        ok, value = self._outcome
        if not ok:
            raise value
        return value  # type: ignore[no-any-return]


def run_ahead(step: Callable[[], T]) -> Ahead[T] | None:
    """Start ``step`` on a helper thread, when a core is idle (:func:`idle_core`) and a
    helper free, and return at once; None (``step`` not run) otherwise. For work a query may
    not need (features of a later fallback step): unlike :func:`run_beside`, the step may
    outlive its query, and its helper serves other queries only once it ends."""
    if not idle_core():
        return None
    ahead: Ahead[T] = Ahead()

    def task_for(helper: _Helper) -> Callable[[], None]:
        def task() -> None:
            outcome = _outcome(step)
            _HELPERS.give_back(helper)  # first: whoever saw the step end finds it free
            ahead._finish(outcome)
        return task

    return ahead if _HELPERS.lend(task_for) is not None else None
