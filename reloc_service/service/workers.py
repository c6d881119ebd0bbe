"""Worker threads behind bounded queues: Zenoh callbacks only enqueue, the work runs here.

A :class:`WorkerPool` never blocks its caller: :meth:`WorkerPool.submit` returns False at once
when the queue is full, and the caller answers "busy". With ``workers=1`` it is the service's
single writer, which applies keyframe puts in arrival order. Relocalize queries run on these
threads only with ``service.worker_mode = "thread"``; by default each relocalize thread hands
its query to a worker process (:mod:`.processes`), since the Python around OpenCV holds the
GIL (two threads querying one engine: about 1.25x one thread on 2 cores).
"""

from __future__ import annotations

import logging
import queue
import signal
import threading
import time
from collections.abc import Callable
from types import FrameType

log = logging.getLogger(__name__)

#: A job receives the seconds it waited in the queue.
Job = Callable[[float], None]

_STOP = object()


class WorkerPool:
    """``workers`` daemon threads serving a queue of at most ``queue_size`` waiting jobs and,
    if ``max_bytes`` is set, at most ``max_bytes`` of payload held by queued and running jobs
    (a count alone lets 512 puts of 30 MiB hold 15 GiB)."""

    def __init__(self, name: str, *, workers: int, queue_size: int,
                 max_bytes: int | None = None) -> None:
        if workers < 1 or queue_size < 1 or (max_bytes is not None and max_bytes < 1):
            raise ValueError(f"{name}: expected workers >= 1, queue_size >= 1 and max_bytes "
                             f">= 1 or None, got {workers}, {queue_size}, {max_bytes}")
        self.name = name
        self.max_bytes = max_bytes
        self._held_bytes = 0
        self._queue: queue.Queue[object] = queue.Queue(maxsize=queue_size)
        self._threads = [threading.Thread(target=self._serve, name=f"{name}-{i}", daemon=True)
                         for i in range(workers)]
        self._closed = False
        self._lock = threading.Lock()
        self._busy = 0
        self._idle = threading.Condition(self._lock)
        for t in self._threads:
            t.start()

    def submit(self, job: Job, size: int = 0) -> bool:
        """Queue ``job`` holding ``size`` bytes (its payload) until it has run; False (without
        waiting) if the queue is full, the bytes would exceed ``max_bytes`` or the pool is
        closed. One job is always admitted into an empty pool, whatever its size (the payload
        limit bounds it), so no single put is refused forever."""
        if self._closed:
            return False
        size = max(0, int(size))
        with self._lock:
            if (self.max_bytes is not None and self._held_bytes
                    and self._held_bytes + size > self.max_bytes):
                return False
            self._held_bytes += size
        try:
            self._queue.put_nowait((job, time.perf_counter(), size))
        except queue.Full:
            self._release(size)
            return False
        return True

    @property
    def held_bytes(self) -> int:
        """Payload bytes of the jobs queued or running."""
        with self._lock:
            return self._held_bytes

    def _release(self, size: int) -> None:
        with self._lock:
            self._held_bytes -= size

    @property
    def pending(self) -> int:
        """Jobs waiting (not counting those running)."""
        return self._queue.qsize()

    def join(self, timeout: float | None = None) -> bool:
        """Wait until every queued job has finished; False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._idle:
            while self._queue.qsize() or self._busy:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return False
                self._idle.wait(0.05 if remaining is None else min(0.05, remaining))
        return True

    def take_queued(self) -> list[Job]:
        """Hand back the queued jobs, in order, without running them (shutdown: the service
        journals queued puts instead of applying them). A job submitted afterwards still runs
        before :meth:`close` returns."""
        jobs: list[Job] = []
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return jobs
            if item is not _STOP:
                jobs.append(item[0])  # type: ignore[index]

    def close(self, timeout: float = 10.0) -> None:
        """Finish the queued jobs, then stop the threads (waiting up to ``timeout`` s)."""
        if self._closed:
            return
        self._closed = True
        deadline = time.monotonic() + timeout
        for _ in self._threads:
            while True:  # the queue may be full: wait for room for each stop marker
                try:
                    self._queue.put(_STOP, timeout=max(0.01, deadline - time.monotonic()))
                    break
                except queue.Full:
                    if time.monotonic() > deadline:
                        log.warning("%s: queue still full at shutdown", self.name)
                        break
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))

    def _serve(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            job: Job
            queued_at: float
            size: int
            job, queued_at, size = item  # type: ignore[misc]
            with self._lock:
                self._busy += 1
            try:
                job(time.perf_counter() - queued_at)
            except Exception:  # a job reports its own errors; this is the last resort
                log.exception("%s: job failed", self.name)
            finally:
                with self._idle:
                    self._busy -= 1
                    self._held_bytes -= size
                    self._idle.notify_all()


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM (call from the main thread)."""
    stop = threading.Event()

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        log.info("signal %s: shutting down", signal.Signals(signum).name)
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    return stop


def seconds_left(deadline: float, share: float = 1.0) -> float:
    """``share`` of the seconds left until ``deadline`` (a ``time.monotonic()`` time; 0 when
    past): how long a stop may wait for one more pool, writer or map."""
    return max(0.0, deadline - time.monotonic()) * share
