"""A served map's shared state (:class:`RuntimeState`): what its write path, journal replay,
snapshots and training jobs, each a layer of :class:`~.runtime.MapRuntime` in a module of its
own, guard with its locks; its request counters (:class:`Stats`) and the events it publishes.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from reloc_client import protocol as wire
from reloc_client.protocol import EventKind

from ..engine import Engine
from .codec import error_of
from .durability import MapStore, RestoreReport
from .map_digest import ContentDigest
from .quotas import MapUsage, Quotas
from .restore_verdict import Loss, Verdict
from .served import ServedMap, WriteOp

log = logging.getLogger(__name__)

Publish = Callable[[str, EventKind, dict[str, Any]], None]

#: The events acknowledging a put or delete: they name the instance that sends them.
ACK_KINDS = frozenset({EventKind.KEYFRAME_ACCEPTED, EventKind.KEYFRAME_ADDED,
                       EventKind.KEYFRAME_REMOVED, EventKind.KEYFRAME_REJECTED,
                       EventKind.CAMERA_ADDED, EventKind.CAMERA_REJECTED})


class Replicas(Protocol):
    """Where a map's applied changes go besides its engine (:class:`.processes.ProcessWorkers`)."""

    def forward(self, name: str, op: WriteOp, *args: Any) -> None: ...

    def rebase(self, rt: RuntimeState) -> None: ...


class Stats:
    """Request counters and a window of relocalize latencies (thread-safe)."""

    def __init__(self, window: int = 4096) -> None:
        self._lock = threading.Lock()
        self.counters: collections.Counter[str] = collections.Counter()
        self._latency: collections.deque[float] = collections.deque(maxlen=window)

    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] += n

    def record_relocalize(self, ok: bool, seconds: float) -> None:
        with self._lock:
            self.counters["relocalize_ok" if ok else "relocalize_failed"] += 1
            self._latency.append(seconds)

    def snapshot(self) -> tuple[dict[str, int], dict[str, float]]:
        """(counters, latency percentiles p50/p90/p99/max in seconds)."""
        with self._lock:
            counters = dict(self.counters)
            lat = np.array(self._latency)
        if len(lat) == 0:
            return counters, {}
        p50, p90, p99 = np.percentile(lat, [50, 90, 99])
        return counters, {"p50": float(p50), "p90": float(p90), "p99": float(p99),
                          "max": float(lat.max()), "mean": float(lat.mean())}


@dataclass
class TrainingJob:
    """A training run in the background."""

    job_id: str
    methods: tuple[str, ...]
    thread: threading.Thread | None = None
    started: float = 0.0


class RuntimeState(ServedMap):
    """The state of a served map that its layers share (see module docstring).

    Locks: the engine's state is the engine's to guard (one mapping thread, many querying
    threads, see :mod:`reloc_service.engine`), so queries take no lock here. The locks below
    order what only this runtime knows: ``_apply_lock`` keeps the journal order, the
    deferred puts and the cameras consistent with what is applied; ``_maintenance`` keeps
    training and snapshots apart (one of them at a time per map); ``_job_lock`` guards the
    training job and the snapshot thread."""

    def __init__(self, name: str, engine: Engine, *, instance: str, limits: wire.Limits,
                 methods: tuple[str, ...], default_method: str, directory: Path | None,
                 publish: Publish, snapshot_every: int = 200, fsync: bool = True,
                 quotas: Quotas | None = None,
                 calibration_sigma: Mapping[str, float] | None = None) -> None:
        super().__init__(name, engine, limits=limits, methods=methods,
                         default_method=default_method)
        self.instance = instance
        #: The calibration accuracy the map states when it sets its own (``[maps.NAME]``),
        #: as its status says it; empty: the service-wide ``[mapping]`` values.
        self.calibration_sigma = dict(calibration_sigma or {})
        self.stats = Stats()
        self.started_at = time.monotonic()
        self._publish = publish
        self._kf_camera_ids: dict[int, str] = {}
        #: The map's journal, snapshots and service.json; None without storage.
        self.store = None if directory is None else MapStore(
            name, directory, fsync=fsync, snapshot_every=snapshot_every)
        self._apply_lock = threading.RLock()          # one map change at a time, in order
        self._maintenance = threading.Lock()          # training and snapshots do not overlap
        self._job_lock = threading.Lock()
        self._job: TrainingJob | None = None
        self._deferred: list[tuple[WriteOp, Any]] = []    # applied after the running snapshot
        self._snapshotting = False
        self._snapshot_thread: threading.Thread | None = None
        self.restore_report = RestoreReport()
        self._losses: list[Loss] = []       # what the restore lacks, until accepted
        #: The journal replay after the snapshot (see :meth:`.JournalReplay.begin_restore`):
        #: where it continues from, whether it started, ended (however) and completed; the
        #: writers hold this map's changes until it completes.
        self._verdict: Verdict | None = None
        self._replay_started = False
        self._replay_ended = threading.Event()
        self._replay_ended.set()
        self._replay_complete = True
        self._replay_failed = False
        #: Keyframes journaled at shutdown without being applied, and whether any record was.
        self._unapplied: set[int] = set()
        self._journal_ahead = False
        self._closed = False
        #: The worker processes holding replicas of this map (worker_mode "process"): every
        #: change applied here is forwarded to them, in order (see :mod:`.processes`).
        self.replicas: Replicas | None = None
        #: What the map's keyframes count against the quotas (None: no quota checked).
        self.quotas = quotas
        self.usage = MapUsage.of(engine.map.snapshot())
        #: The map's content hash (status ``content_hash``; replicas compare it).
        self.content = ContentDigest()
        #: Why this replica disagrees with a peer (status ``diverged``; set by
        #: :class:`.divergence.DivergenceWatch`), "" when it does not.
        self.diverged = ""

    # -- reading -------------------------------------------------------------------------------
    def keyframe_camera_id(self, kf_id: int) -> str | None:
        return self._kf_camera_ids.get(kf_id)

    def apply_lock(self) -> threading.RLock:
        """The lock under which changes are journaled and applied, in order (held, no change
        is applied: the replica processes save a base under it)."""
        return self._apply_lock

    @property
    def map_id(self) -> str | None:
        """The map's identity (None without storage, or before its restore assigned it)."""
        return None if self.store is None else self.store.map_id

    @property
    def replaying(self) -> bool:
        """The map is served from its snapshot while its journal backlog replays."""
        return not self._replay_complete

    @property
    def journal_ahead(self) -> bool:
        """Records were journaled at shutdown without being applied (no snapshot may drop
        them before a restart replays them)."""
        return self._journal_ahead

    # -- events ----------------------------------------------------------------------------------
    def publish(self, kind: EventKind, **fields: Any) -> None:
        if kind in ACK_KINDS:   # a client waiting for several replicas tells them apart
            fields.setdefault("instance", self.instance)
        self._publish(self.name, kind, fields)

    def reject(self, kind: EventKind, exc: BaseException, **fields: Any) -> None:
        """Publish a ``*_rejected`` event for ``exc`` and count it."""
        code, message = error_of(exc)
        self.stats.count("rejected")
        log.info("map %s: %s %s: %s %s", self.name, kind.value, fields, code.value, message)
        self.publish(kind, **fields, code=code.value, message=message)
