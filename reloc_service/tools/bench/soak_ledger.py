"""What the clients of ``reloc bench --only soak`` saw: keyframes sent, deleted and
acknowledged (:class:`Ledger`), query outcomes over time (:class:`Outcomes`), and whether the
service is up and how long clients took to be answered again after each restart
(:class:`Phase`). Thread-safe: Zenoh callbacks and client threads record into them."""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


class Ledger:
    """Keyframes sent, deleted and acknowledged (thread-safe; the event callback runs in a
    Zenoh thread and only records)."""

    def __init__(self) -> None:
        self.lock = threading.Condition()
        self.sent: list[int] = []
        self.delete_sent: list[int] = []
        self.added: set[int] = set()
        self.removed: set[int] = set()
        self.added_events: Counter[int] = Counter()
        self.removed_events: Counter[int] = Counter()
        self.rejected: Counter[str] = Counter()
        self.events: Counter[str] = Counter()

    def on_event(self, event: Any) -> None:
        kind, kf_id = event.kind.value, event.fields.get("id")
        with self.lock:
            self.events[kind] += 1
            if kind == "keyframe_added":
                self.added.add(kf_id)
                self.added_events[kf_id] += 1
            elif kind == "keyframe_removed":
                self.removed.add(kf_id)
                self.removed_events[kf_id] += 1
            elif kind == "keyframe_rejected":
                self.rejected[str(event.fields.get("code"))] += 1
            self.lock.notify_all()

    def wait_added(self, kf_id: int, timeout: float) -> bool:
        with self.lock:
            return self.lock.wait_for(lambda: kf_id in self.added, timeout)

    def deletable(self, keep: int) -> int | None:
        """The oldest acknowledged streamed keyframe not yet deleted, if more than ``keep``
        of them are in the map."""
        with self.lock:
            asked = set(self.delete_sent)
            alive = [k for k in self.sent if k in self.added and k not in asked]
            return alive[0] if len(alive) > keep else None


class Outcomes:
    """Query outcomes by kind, the latency of answered ones, and answered / failed queries
    per ``bucket_s`` of the run (thread-safe)."""

    ANSWERED = ("ok", "not_relocalized")

    def __init__(self, clock: Callable[[], float], bucket_s: float = 5.0) -> None:
        self.lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.latencies_s: list[float] = []
        self.sent = 0
        self.clock, self.bucket_s = clock, bucket_s
        self.buckets: dict[int, list[int]] = {}

    def record(self, kind: str, latency_s: float | None = None) -> None:
        with self.lock:
            self.sent += 1
            self.counts[kind] += 1
            if latency_s is not None:
                self.latencies_s.append(latency_s)
            row = self.buckets.setdefault(int(self.clock() // self.bucket_s), [0, 0])
            row[0 if kind in self.ANSWERED else 1] += 1

    def timeline(self) -> list[list[float]]:
        """``[start_s, answered, failed]`` per bucket, in time order."""
        with self.lock:
            return [[k * self.bucket_s, *v] for k, v in sorted(self.buckets.items())]


@dataclass
class Phase:
    """Whether the service is up (answered a fresh client's query since its last start), and
    how long each long-lived client took after that to be answered again (its Zenoh session
    reconnects on its own, with a back-off)."""

    up: threading.Event = field(default_factory=threading.Event)
    stop: threading.Event = field(default_factory=threading.Event)
    t0: float = field(default_factory=time.monotonic)
    #: Starts so far (0: the first) and when the current one began answering.
    generation: int = 0
    up_since: float = 0.0
    #: Seconds from "up" to each client's first answer, per restart (generation >= 1).
    resumed_s: dict[int, list[float]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def now(self) -> float:
        return time.monotonic() - self.t0

    def went_up(self) -> None:
        with self.lock:
            self.generation += 1
            self.up_since = self.now()
            self.up.set()

    def answered(self, seen: int) -> int:
        """A client that last saw generation ``seen`` was answered; returns the current."""
        with self.lock:
            if seen < self.generation and self.up.is_set():
                self.resumed_s.setdefault(self.generation, []).append(
                    self.now() - self.up_since)
            return self.generation


# -- the load ----------------------------------------------------------------------------------
