"""Queries being answered, counted per process, so that background work that only prepares
for later queries (a loaded map's later pools) steps aside while they run.

A lower nice value (:data:`.background.LOWER_PRIORITY`) is not enough on its own: with one
query on one core, the background thread has the other core to itself and still slows the
query down, through the interpreter lock it takes between its numpy calls and the memory
bandwidth and caches the two share. In the fleet bench a warm query sent right after its
map's cold load took a median 1.17x the round trip of the same image on a map resident
from the start (40 picks, 30 ms more CPU in the service per query); sent once the map's
pools were made, 0.90x.

So background work checks :func:`step_aside` between its units (through a cancel check made
by :func:`yielding`): it waits while a query that began after the work did is being
answered, and for :data:`GRACE_S` after the last query ended, unless some query is waiting
for background work itself (a pool being made that its next step reads). Then the
background work is what the queries need, and it goes on at once: a query never waits for
work that waits for queries. The queries that began before it (the cold query whose map is
being loaded) do not hold it: it went on beside their first steps before, and their later
steps may need it (stepping aside for them too, a cold query answered by SIFT waited about
0.1 s longer for the SIFT pool its first steps used to leave made).
"""

from __future__ import annotations

import contextlib
import itertools
import math
import threading
import time
from collections.abc import Callable, Iterator

#: How often a background thread that steps aside checks its own stop condition (a map
#: closed meanwhile stops its pools within this).
POLL_S = 0.05

#: How long after the last query ended background work still waits. A client that sends
#: its next query on the answer (the next image of a stream at 10 Hz or more, a retry, the
#: fleet bench's warm query) sends it within this; resuming at once, the background work
#: was in the middle of a unit of 10-30 ms of CPU when that query arrived.
GRACE_S = 0.1

_changed = threading.Condition()
#: Start times (monotonic seconds) of the queries being answered, by a token of each.
_started: dict[int, float] = {}
_tokens = itertools.count()
_waiting = 0
_last_end = -math.inf


@contextlib.contextmanager
def answering() -> Iterator[None]:
    """Count the calling thread as answering a query while the block runs (blocks may
    nest: a service's request around the engine's query)."""
    global _last_end
    token = next(_tokens)
    with _changed:
        _started[token] = time.monotonic()
    try:
        yield
    finally:
        with _changed:
            del _started[token]
            _last_end = time.monotonic()


@contextlib.contextmanager
def waiting_for_background() -> Iterator[None]:
    """Count the calling thread as waiting for background work while the block runs:
    background work that steps aside goes on meanwhile."""
    global _waiting
    with _changed:
        _waiting += 1
        _changed.notify_all()
    try:
        yield
    finally:
        with _changed:
            _waiting -= 1


def queries_running(since: float = -math.inf) -> bool:
    """Whether some query that began at ``since`` or later (monotonic seconds) is being
    answered and no query waits for background work."""
    with _changed:
        return _waiting == 0 and _begun_since(since)


def _begun_since(since: float) -> bool:
    """Under the lock: whether a query being answered began at ``since`` or later."""
    return any(t >= since for t in _started.values())


def _wait_needed(since: float) -> float:
    """Under the lock: how long background work begun at ``since`` should still wait (0: go
    on)."""
    if _waiting > 0:
        return 0.0
    if _begun_since(since):
        return POLL_S
    return max(0.0, min(POLL_S, _last_end + GRACE_S - time.monotonic()))


def step_aside(stop: Callable[[], bool] | None = None, since: float = -math.inf) -> None:
    """Wait while :func:`queries_running` (queries begun at ``since`` or later) and
    :data:`GRACE_S` after the last query ended, or until ``stop()`` is true (checked at
    least every :data:`POLL_S`)."""
    while not (stop is not None and stop()):   # outside the lock: the caller's code
        with _changed:
            wait = _wait_needed(since)
            if wait <= 0.0:
                return
            _changed.wait(wait)


def yielding(stop: Callable[[], bool]) -> Callable[[], bool]:
    """A cancel check for background work begun now (called between its units): it first
    steps aside for the queries begun since (:func:`step_aside`), then says whether
    ``stop()``."""
    since = time.monotonic()

    def check() -> bool:
        step_aside(stop, since)
        return stop()

    return check
