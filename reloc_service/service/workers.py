"""Worker threads behind bounded queues: Zenoh callbacks only enqueue, the work runs here.

A :class:`WorkerPool` never blocks its caller: :meth:`WorkerPool.submit` returns False at once
when the queue is full, and the caller answers "busy". With ``workers=1`` it is the service's
single writer, which applies keyframe puts in arrival order. Relocalize queries run on these
threads only with ``service.worker_mode = "thread"``; by default each relocalize thread hands
its query to a worker process (:mod:`.processes`), since the Python around OpenCV holds the
GIL (two threads querying one engine: about 1.25x one thread on 2 cores).
"""

from __future__ import annotations

import collections
import logging
import queue
import signal
import threading
import time
from collections.abc import Callable, Hashable
from types import FrameType

log = logging.getLogger(__name__)

#: A job receives the seconds it waited in the queue.
Job = Callable[[float], None]

_STOP = object()



def _check_bounds(name: str, workers: int, queue_size: int, max_bytes: int | None) -> None:
    """ValueError unless a pool's bounds are usable (both pools take the same ones)."""
    if workers < 1 or queue_size < 1 or (max_bytes is not None and max_bytes < 1):
        raise ValueError(f"{name}: expected workers >= 1, queue_size >= 1 and max_bytes "
                         f">= 1 or None, got {workers}, {queue_size}, {max_bytes}")

class WorkerPool:
    """``workers`` daemon threads serving a queue of at most ``queue_size`` waiting jobs and,
    if ``max_bytes`` is set, at most ``max_bytes`` of payload held by queued and running jobs
    (a count alone lets 512 puts of 30 MiB hold 15 GiB)."""

    def __init__(self, name: str, *, workers: int, queue_size: int,
                 max_bytes: int | None = None) -> None:
        _check_bounds(name, workers, queue_size, max_bytes)
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


class KeyedPool:
    """Jobs queued per key (a map name) and run by ``workers`` threads shared by every key:
    the jobs of one key run one at a time, in the order submitted; different keys run in
    parallel, at most ``workers`` at once. A key with no job holds nothing (no thread, no
    queue), so the threads are bounded whatever the number of keys. A key whose job ran goes
    to the back of the line of ready keys: a busy key does not starve the others.

    Bounded as :class:`WorkerPool`: at most ``queue_size`` jobs waiting per key, and (if
    ``max_bytes`` is set) at most ``max_bytes`` of payload held by the queued and running
    jobs of all keys together (the memory the writers may hold)."""

    def __init__(self, name: str, *, workers: int, queue_size: int,
                 max_bytes: int | None = None) -> None:
        _check_bounds(name, workers, queue_size, max_bytes)
        self.name = name
        self.queue_size = queue_size
        self.max_bytes = max_bytes
        self._lock = threading.Lock()
        self._work = threading.Condition(self._lock)    # a key became ready, or stopping
        self._idle = threading.Condition(self._lock)    # a job finished
        #: key -> its waiting jobs (job, queued at, size); absent when it has none.
        self._lanes: dict[Hashable, collections.deque[tuple[Job, float, int]]] = {}
        #: Keys with waiting jobs and no thread on them, in the order they are served.
        self._ready: collections.deque[Hashable] = collections.deque()
        self._running: set[Hashable] = set()
        self._held_bytes = 0
        self._closed = False
        self._stopping = False
        self._threads = [threading.Thread(target=self._serve, name=f"{name}-{i}", daemon=True)
                         for i in range(workers)]
        for t in self._threads:
            t.start()

    def submit(self, key: Hashable, job: Job, size: int = 0) -> bool:
        """Queue ``job`` after the jobs of ``key``, holding ``size`` bytes until it has run;
        False (without waiting) if ``key`` already has ``queue_size`` jobs waiting, the bytes
        would exceed ``max_bytes`` or the pool is closed. One job is always admitted into an
        empty pool, whatever its size (the payload limit bounds it)."""
        size = max(0, int(size))
        with self._lock:
            lane = self._lanes.get(key)
            if self._closed or (lane is not None and len(lane) >= self.queue_size):
                return False
            if (self.max_bytes is not None and self._held_bytes
                    and self._held_bytes + size > self.max_bytes):
                return False
            if lane is None:
                lane = self._lanes[key] = collections.deque()
            lane.append((job, time.perf_counter(), size))
            self._held_bytes += size
            if len(lane) == 1 and key not in self._running:
                self._ready.append(key)
                self._work.notify()
        return True

    @property
    def held_bytes(self) -> int:
        """Payload bytes of the jobs queued or running, all keys."""
        with self._lock:
            return self._held_bytes

    def pending(self, key: Hashable | None = None) -> int:
        """Jobs waiting (not counting those running): of ``key``, or of every key."""
        with self._lock:
            if key is not None:
                return len(self._lanes.get(key, ()))
            return sum(len(lane) for lane in self._lanes.values())

    @property
    def threads(self) -> int:
        """The pool's threads (fixed)."""
        return len(self._threads)

    def join(self, timeout: float | None = None) -> bool:
        """Wait until every queued job has finished; False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._idle:
            while self._lanes or self._running:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return False
                self._idle.wait(0.05 if remaining is None else min(0.05, remaining))
        return True

    def take_queued(self) -> list[Job]:
        """Hand back the waiting jobs without running them (shutdown: the service journals
        queued puts instead of applying them), each key's in its order. A job submitted
        afterwards still runs before :meth:`close` returns."""
        with self._lock:
            lanes, self._lanes = self._lanes, {}
            self._ready.clear()
            jobs = [item for lane in lanes.values() for item in lane]
            self._held_bytes -= sum(size for _job, _at, size in jobs)
            self._idle.notify_all()
        return [job for job, _at, _size in jobs]

    def close(self, timeout: float = 10.0) -> None:
        """Refuse new jobs, finish the queued ones, then stop the threads (waiting up to
        ``timeout`` s for both)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._stopping = True
            self._work.notify_all()
        deadline = time.monotonic() + timeout
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        if any(t.is_alive() for t in self._threads):
            log.warning("%s: still busy at shutdown", self.name)

    def _next(self) -> tuple[Hashable, Job, float, int] | None:
        """The next job to run (its key marked running), waiting for one; None once
        stopping with nothing left."""
        with self._lock:
            while not self._ready:
                if self._stopping:
                    return None
                self._work.wait()
            key = self._ready.popleft()
            job, queued_at, size = self._lanes[key].popleft()
            self._running.add(key)
            return key, job, queued_at, size

    def _done(self, key: Hashable, size: int) -> None:
        with self._lock:
            self._running.discard(key)
            self._held_bytes -= size
            lane = self._lanes.get(key)
            if lane:
                self._ready.append(key)
                self._work.notify()
            elif lane is not None:
                del self._lanes[key]
            self._idle.notify_all()

    def _serve(self) -> None:
        while (item := self._next()) is not None:
            key, job, queued_at, size = item
            try:
                job(time.perf_counter() - queued_at)
            except Exception:  # a job reports its own errors; this is the last resort
                log.exception("%s: job of %r failed", self.name, key)
            finally:
                self._done(key, size)


class Lane:
    """The jobs of one key of a :class:`KeyedPool`, submitted like a :class:`WorkerPool`'s
    (a map's writer, as the code that queues a map's writes sees it)."""

    def __init__(self, pool: KeyedPool, key: Hashable) -> None:
        self.pool = pool
        self.key = key
        self.name = f"{pool.name}[{key}]"

    def submit(self, job: Job, size: int = 0) -> bool:
        return self.pool.submit(self.key, job, size)

    @property
    def held_bytes(self) -> int:
        """Payload bytes held by the whole pool (its byte budget is shared by every key)."""
        return self.pool.held_bytes

    @property
    def pending(self) -> int:
        return self.pool.pending(self.key)


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
