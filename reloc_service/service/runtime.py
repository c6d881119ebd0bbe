"""One served map: its engine front, camera registry, change ordering (deferral during a
snapshot), training jobs, counters and events.

What is written to disk and how it is restored is :mod:`.durability`'s (a :class:`MapStore`
per map directory); this module decides when: every accepted put is journaled before it is
applied, a snapshot runs in the background while the puts arriving meanwhile are journaled
at once and applied after the save (so queries are never held up by it), and training and
snapshots never overlap.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from reloc_client import protocol as wire
from reloc_client.protocol import EventKind

from ..core.errors import MapError, StorageError
from ..engine import Engine
from .codec import KeyframeInput, WithLimits, decode_camera_put, decode_keyframe_put, error_of
from .durability import REPLAY_LIMITS, MapStore, RestoreInterrupted, RestoreReport, ServiceMeta
from .map_digest import ContentDigest
from .quotas import MapUsage, Quotas, keyframe_bytes
from .restore_verdict import Loss, Verdict, judge, record_losses, unaccepted
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

    def rebase(self, rt: MapRuntime) -> None: ...


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


class MapRuntime(ServedMap):
    """Everything the service holds for map ``name`` (see module docstring); its query face
    (engine, cameras, methods) is the :class:`~.served.ServedMap` a worker's replica shares.

    Map changes (:meth:`put_keyframe` etc.) come from the map's writer thread; queries
    (:meth:`relocalize`, :meth:`map_state`, :meth:`status`) from any worker thread.

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
        #: The journal replay after the snapshot (see :meth:`begin_restore`): where it
        #: continues from, whether it started, ended (however) and completed; the writers
        #: hold this map's changes until it completes.
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

    def status(self, *, content_hash: bool = False) -> wire.StatusReply:
        """The map's status; with ``content_hash``, its content hash too (computed on demand:
        the first time, each keyframe's pixels are read)."""
        st = self.engine.status()
        counters, latency = self.stats.snapshot()
        counters["quota_bytes"] = self.usage.total   # what the map counts against [quotas]
        with self._job_lock:
            training = self._job is not None
        return wire.StatusReply(
            map=self.name, instance=self.instance, keyframes=st["keyframes"],
            landmarks=st["landmarks"],
            trained=all(m["trained"] for m in st["methods"].values()),
            map_version=st["map_version"], methods=self.methods,
            default_method=self.default_method, cameras=tuple(self.camera_ids()),
            training=training, uptime_s=time.monotonic() - self.started_at,
            counters={**counters, **self._replay_progress()}, latency_s=latency,
            degraded=self.degraded(), replaying=self.replaying, map_id=self.map_id or "",
            content_hash=self.content.of(self.map_state()) if content_hash else "",
            diverged=self.diverged, calibration_sigma=self.calibration_sigma,
            keyframe_pose_sigma=st["keyframe_pose_sigma"] or {})

    @property
    def map_id(self) -> str | None:
        """The map's identity (None without storage, or before its restore assigned it)."""
        return None if self.store is None else self.store.map_id

    @property
    def replaying(self) -> bool:
        """The map is served from its snapshot while its journal backlog replays."""
        return not self._replay_complete

    def _replay_progress(self) -> dict[str, int]:
        """While the journal replays: the records replayed (or skipped as not applying) and
        how many there are (status counters)."""
        if self._replay_complete or self._verdict is None:
            return {}
        report = self.restore_report
        return {"replay_records_done": report.replayed + report.not_applied,
                "replay_records_total": self._verdict.to_replay}

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

    # -- map changes (writer thread) -------------------------------------------------------------
    def put_keyframe(self, kf_id: int, payload: bytes) -> None:
        """Validate, journal, apply (or defer during a snapshot) a KeyframePut."""
        try:
            kf = decode_keyframe_put(self, kf_id, payload)
            with self._apply_lock:
                self._admit(kf_id, len(payload))   # QUOTA_EXCEEDED: nothing journaled
                try:
                    self._journal_record(WriteOp.KEYFRAME, kf_id, payload)
                    self.publish(EventKind.KEYFRAME_ACCEPTED, id=kf_id)
                    self._apply_or_defer(WriteOp.KEYFRAME, kf)
                except Exception:
                    self._recount(kf_id)
                    raise
        except Exception as exc:
            self.reject(EventKind.KEYFRAME_REJECTED, exc, id=kf_id)

    def _admit(self, kf_id: int, size: int) -> None:
        """Count a put against the quotas (QUOTA_EXCEEDED beyond them)."""
        if self.quotas is not None:
            self.quotas.admit(self.name, self.usage, kf_id, size)

    def _recount(self, kf_id: int) -> None:
        """Count keyframe ``kf_id`` as the map now holds it (a put that failed on the way
        counts what stayed: the old keyframe, or nothing)."""
        keyframe = self.engine.map.snapshot().keyframes.get(kf_id)
        size = None if keyframe is None else keyframe_bytes(keyframe)
        if self.quotas is not None:
            self.quotas.count(self.usage, kf_id, size)
        else:
            self.usage.set_bytes(kf_id, size)

    def delete_keyframe(self, kf_id: int) -> None:
        """Journal and apply the removal of keyframe ``kf_id``."""
        try:
            with self._apply_lock:
                if kf_id not in self.engine.map and not self._deferred_has(kf_id):
                    raise MapError(f"cannot remove keyframe {kf_id}: not in map {self.name!r}")
                self._journal_record(WriteOp.DELETE, kf_id)
                self.publish(EventKind.KEYFRAME_ACCEPTED, id=kf_id, removed=True)
                self._apply_or_defer(WriteOp.DELETE, kf_id)
                self._recount(kf_id)   # frees its quota (once applied)
        except Exception as exc:
            self.reject(EventKind.KEYFRAME_REJECTED, exc, id=kf_id)

    def put_camera(self, camera_id: str, payload: bytes) -> None:
        """Validate, journal and register a CameraPut."""
        try:
            camera = decode_camera_put(camera_id, payload, self.limits)
            with self._apply_lock:
                self._journal_record(WriteOp.CAMERA, camera_id, payload)
                previous = self._cameras.get(camera_id)
                self.apply_change(WriteOp.CAMERA, camera_id, camera)
                if self.replicas is not None:
                    self.replicas.forward(self.name, WriteOp.CAMERA, camera_id, camera)
            self.stats.count("cameras_put")
            if previous is None or previous.to_dict() == camera.to_dict():
                self.publish(EventKind.CAMERA_ADDED, id=camera_id)
                return
            # Never rewritten: the keyframes already built keep the intrinsics they were built
            # with (a replica copies them so, see replication.Bootstrap); only new puts use these.
            kept = sum(1 for c in self._kf_camera_ids.values() if c == camera_id)
            log.warning("map %s: camera %s changed; %d keyframes built with it keep their "
                        "intrinsics", self.name, camera_id, kept)
            self.publish(EventKind.CAMERA_ADDED, id=camera_id, changed=True,
                         keyframes_kept=kept)
        except Exception as exc:
            self.reject(EventKind.CAMERA_REJECTED, exc, id=camera_id)

    def _journal_record(self, op: WriteOp, ident: Any, payload: bytes | None = None) -> None:
        """Append a change as the journal stores it: the op's string, the id, and the put as
        it was sent (a delete has none)."""
        if self.store is not None:
            record: dict[str, Any] = {"op": op.value, "id": ident}
            if payload is not None:
                record["payload"] = payload
            self.store.append(record)

    def _deferred_has(self, kf_id: int) -> bool:
        return any(op is WriteOp.KEYFRAME and item.kf_id == kf_id for op, item in self._deferred)

    def _apply_or_defer(self, op: WriteOp, item: Any) -> None:
        if self._snapshotting:
            self._deferred.append((op, item))
        else:
            self._apply(op, item)

    def _apply(self, op: WriteOp, item: Any, *, replay: bool = False) -> None:
        if op is WriteOp.KEYFRAME:
            kf: KeyframeInput = item
            self.apply_change(WriteOp.KEYFRAME, kf)
            self._recount(kf.kf_id)   # its features are known now
            if self.replicas is not None:   # before keyframe_added: a query after it sees it
                self.replicas.forward(self.name, WriteOp.KEYFRAME, kf)
            if kf.camera_id is not None:
                self._kf_camera_ids[kf.kf_id] = kf.camera_id
            else:
                self._kf_camera_ids.pop(kf.kf_id, None)
            if not replay:
                self.stats.count("keyframes_put")
                self.publish(EventKind.KEYFRAME_ADDED, id=kf.kf_id,
                             map_version=self.engine.map.version)
        elif op is WriteOp.DELETE:
            self.apply_change(WriteOp.DELETE, item)
            self._recount(item)
            if self.replicas is not None:
                self.replicas.forward(self.name, WriteOp.DELETE, item)
            self._kf_camera_ids.pop(item, None)
            if not replay:
                self.stats.count("keyframes_deleted")
                self.publish(EventKind.KEYFRAME_REMOVED, id=item,
                             map_version=self.engine.map.version)

    def wants_snapshot(self) -> bool:
        return self.store is not None and self.store.wants_snapshot()

    # -- restore ---------------------------------------------------------------------------------
    def restore(self, stop: threading.Event | None = None, verdict: Verdict | None = None
                ) -> int:
        """:meth:`begin_restore`, then :meth:`replay_backlog`: the records replayed."""
        self.begin_restore(verdict)
        return self.replay_backlog(stop)

    def begin_restore(self, verdict: Verdict | None = None) -> None:
        """Take the cameras of ``service.json`` and what the restore lacks (``verdict``,
        judged on the map directory before it was loaded: :func:`.restore_verdict.judge`):
        the map can be served from the snapshot the engine was loaded from (see
        :func:`.durability.open_engine`) while :meth:`replay_backlog` applies the journal
        after it; its changes wait for that. StorageError if the verdict refuses the map
        or ``service.json`` does not read (nothing is changed)."""
        if self.store is None:
            return
        if verdict is None:
            verdict = judge(self.store.directory)
        if verdict.refusal is not None:
            raise StorageError(verdict.refusal)
        meta = self.store.read_meta()
        self._cameras.update(meta.cameras)
        self._kf_camera_ids.update(meta.keyframe_camera_ids)
        self._note_losses(verdict)
        self._verdict = verdict
        self._replay_complete = False
        self._replay_ended.clear()

    def replay_backlog(self, stop: threading.Event | None = None) -> int:
        """Replay the journal after the snapshot (each record under the apply lock, so
        queries see the map grow and replicas get the records in order), then open it for
        appending; the records replayed. What was skipped is in :attr:`restore_report` and
        the status counters. StorageError if a journal segment header does not read;
        RestoreInterrupted if ``stop`` is set meanwhile or the map was closed (the journal
        is left as it was; :meth:`close` saves what was replayed)."""
        if self._replay_complete or self._verdict is None or self.store is None:
            return 0
        with self._job_lock:
            if self._closed:
                raise RestoreInterrupted(f"map {self.name}: closed before its journal replay")
            self._replay_started = True
        report = self.restore_report
        try:
            self.store.replay(self._verdict, self._replay_locked, report, stop)
        except BaseException as exc:
            self._replay_failed = not isinstance(exc, RestoreInterrupted)
            self._replay_ended.set()
            raise
        for name, n in report.counters().items():
            if n:
                self.stats.count(name, n)
        self._replay_complete = True
        self._replay_ended.set()
        return report.replayed

    def wait_replayed(self, stop: threading.Event) -> bool:
        """Wait until the journal replay ends (the writers hold this map's changes until
        then): True once it completed, False if it did not (stopped, or failed) or ``stop``
        is set first."""
        while not self._replay_ended.wait(0.2):
            if stop.is_set():
                return False
        return self._replay_complete

    def _replay_locked(self, record: dict[str, Any]) -> None:
        with self._apply_lock:
            self._replay_record(record)

    def _note_losses(self, verdict: Verdict) -> None:
        """Record what the restore lacks (so a restart still knows it) and say so."""
        assert self.store is not None
        for note in verdict.notes:
            log.warning("map %s: %s", self.name, note)
        if not verdict.losses:
            return
        try:
            record_losses(self.store.directory, verdict.losses)
        except (OSError, StorageError) as exc:   # still served degraded; found again next time
            log.error("map %s: could not record the losses found: %s", self.name, exc)
        self._losses = list(verdict.losses)
        report = self.restore_report
        report.losses = [loss.to_dict() for loss in verdict.losses]
        report.missing_keyframe_ids = verdict.missing_keyframe_ids
        report.degraded = verdict.describe()
        log.error("map %s: served degraded: %s", self.name, report.degraded)

    def degraded(self) -> str:
        """Why the map is served degraded ("" once every loss is accepted, or if none)."""
        if not self._losses or self.store is None:
            return ""
        self._losses = unaccepted(self.store.directory, self._losses)
        return self.restore_report.degraded if self._losses else ""

    def _replay_record(self, record: dict[str, Any]) -> None:
        """Apply a journal record again (raises if it does not apply: it is skipped)."""
        op = record["op"]
        if op == WriteOp.KEYFRAME:
            kf = decode_keyframe_put(WithLimits(self, REPLAY_LIMITS), record["id"],
                                     record["payload"])
            self._apply(WriteOp.KEYFRAME, kf, replay=True)
        elif op == WriteOp.DELETE:
            if record["id"] in self.engine.map:
                self._apply(WriteOp.DELETE, record["id"], replay=True)
        elif op == WriteOp.CAMERA:
            self.apply_change(WriteOp.CAMERA, record["id"],
                              decode_camera_put(record["id"], record["payload"], REPLAY_LIMITS))
        else:
            raise ValueError(f"unknown journal op {op!r}")

    # -- snapshots -------------------------------------------------------------------------------
    def start_snapshot(self, *, wait: bool = False) -> bool:
        """Save the map in the background (one at a time); with ``wait``, block until it is
        durable. False if there is no storage or a snapshot is already running."""
        if self.store is None:
            return False
        with self._job_lock:
            if self._journal_ahead or self._closed or not self._replay_complete:
                return False   # it would drop the records journaled (not applied) at shutdown
            running = self._snapshot_thread is not None and self._snapshot_thread.is_alive()
            if not running:
                self._snapshot_thread = threading.Thread(
                    target=self._snapshot, name=f"snapshot-{self.name}", daemon=True)
                self._snapshot_thread.start()
            thread = self._snapshot_thread
        if wait and thread is not None:
            thread.join()
        return not running

    def _snapshot(self) -> None:
        assert self.store is not None
        with self._maintenance:
            with self._apply_lock:   # no put between the rotation and the cameras it saves
                if self._journal_ahead:   # waited past a shutdown that journaled unapplied puts
                    return
                try:
                    segment = self.store.rotate()
                except StorageError as exc:
                    log.error("map %s: snapshot not taken: %s", self.name, exc)
                    return
                meta = ServiceMeta(cameras=dict(self._cameras),
                                   keyframe_camera_ids=dict(self._kf_camera_ids),
                                   next_segment=segment)
                self._snapshotting = True
            try:
                path = self.store.save(self.engine, meta)
                self.publish(EventKind.MAP_SAVED, map_version=self.map_state().version,
                             path=str(path))
            except Exception as exc:
                log.error("map %s: snapshot failed (the journal still has everything): %s",
                          self.name, exc)
            finally:
                self._finish_snapshot()

    def _finish_snapshot(self) -> None:
        """Apply the puts that arrived during the save, in order."""
        with self._apply_lock:
            deferred, self._deferred = self._deferred, []
            self._snapshotting = False
            for op, item in deferred:
                try:
                    self._apply(op, item)
                except Exception as exc:
                    self.reject(EventKind.KEYFRAME_REJECTED, exc,
                                id=item.kf_id if op is WriteOp.KEYFRAME else item)

    # -- training --------------------------------------------------------------------------------
    def start_training(self, method: str | None) -> tuple[str, bool]:
        """Start a training job (``method`` or every served method); (job id, started). A job
        already running is reported with its id and started=False."""
        with self._job_lock:
            if self._job is not None:
                return self._job.job_id, False
            methods = (method,) if method is not None else self.methods
            job = TrainingJob(uuid.uuid4().hex[:12], methods, started=time.time())
            job.thread = threading.Thread(target=self._train, args=(job,),
                                          name=f"train-{self.name}", daemon=True)
            self._job = job
            job.thread.start()
            return job.job_id, True

    def _train(self, job: TrainingJob) -> None:
        start = time.perf_counter()
        try:
            with self._maintenance:
                self.publish(EventKind.TRAIN_STARTED, job_id=job.job_id, instance=self.instance,
                             method=",".join(job.methods) if len(job.methods) == 1
                             else " ".join(job.methods))
                for i, method in enumerate(job.methods):
                    self.publish(EventKind.TRAIN_PROGRESS, job_id=job.job_id,
                                 fraction=i / len(job.methods), stage=f"training {method}")
                    self.engine.train([method])
                if self.replicas is not None:   # the new models, before train_done
                    self.replicas.rebase(self)
                self.publish(EventKind.TRAIN_PROGRESS, job_id=job.job_id, fraction=1.0,
                             stage="done")
        except Exception as exc:
            code, message = error_of(exc)
            self.publish(EventKind.TRAIN_FAILED, job_id=job.job_id, code=code.value,
                         message=message)
            with self._job_lock:
                self._job = None
            return
        # The snapshot starts before the job ends: a map with neither running may be closed
        # as idle (max_resident_mb), and its models must be on disk by then.
        self.start_snapshot()   # the trained models survive a restart
        with self._job_lock:
            self._job = None
        self.publish(EventKind.TRAIN_DONE, job_id=job.job_id,
                     duration_s=time.perf_counter() - start, map_version=self.map_state().version)

    def wait_snapshot(self, timeout: float = 60.0) -> None:
        """Wait for a running snapshot (its deferred puts are applied when it ends)."""
        thread = self._snapshot_thread
        if thread is not None and thread.is_alive():
            thread.join(timeout)

    def maintenance_running(self) -> bool:
        """A snapshot or training job holds the map's files or models now."""
        thread = self._snapshot_thread
        return (thread is not None and thread.is_alive()) or self._maintenance.locked()

    @property
    def journal_ahead(self) -> bool:
        """Records were journaled at shutdown without being applied (no snapshot may drop
        them before a restart replays them)."""
        return self._journal_ahead

    def training_thread(self) -> threading.Thread | None:
        with self._job_lock:
            return None if self._job is None else self._job.thread

    # -- shutdown --------------------------------------------------------------------------------
    def journal_only(self, op: WriteOp, ident: Any, payload: bytes | None) -> bool:
        """At shutdown: validate and journal a queued keyframe put or delete without applying
        it (applying runs SIFT and triangulation, ~0.3 s a keyframe); the journal replay at
        the next start applies it. False without storage (nothing would survive anyway)."""
        if self.store is None:
            return False
        if not self._replay_complete:   # the journal was never opened for appending
            self.reject(EventKind.KEYFRAME_REJECTED, wire.ProtocolError(
                wire.ErrorCode.BUSY, f"the service stopped while map {self.name!r} was "
                "replaying its journal; put again once it is back"), id=ident)
            return False
        try:
            with self._apply_lock:
                if op is WriteOp.KEYFRAME:
                    assert payload is not None
                    decode_keyframe_put(self, ident, payload)   # refused as usual
                    self._admit(ident, len(payload))
                    self._journal_record(WriteOp.KEYFRAME, ident, payload)
                    self._unapplied.add(ident)
                else:
                    if (ident not in self.engine.map and ident not in self._unapplied
                            and not self._deferred_has(ident)):
                        raise MapError(f"cannot remove keyframe {ident}: not in map "
                                       f"{self.name!r}")
                    self._journal_record(WriteOp.DELETE, ident)
                    self._unapplied.discard(ident)
                self._journal_ahead = True
            self.publish(EventKind.KEYFRAME_ACCEPTED, id=ident, **({"removed": True}
                                                                   if op is WriteOp.DELETE
                                                                   else {}))
        except Exception as exc:
            self.reject(EventKind.KEYFRAME_REJECTED, exc, id=ident)
        return True

    def close(self, *, final_snapshot: bool = True, timeout: float = 60.0) -> None:
        """Final snapshot within ``timeout`` s (when something changed since the last one and
        no record was journaled without being applied: the snapshot would drop it from the
        journal), then close the journal. A running training job is not waited for beyond
        the same ``timeout``: its models are lost, the map is not. A map closed while its
        journal replays saves what was replayed instead (:meth:`_close_mid_replay`)."""
        deadline = time.monotonic() + timeout
        if not self._replay_complete:
            self._close_mid_replay(deadline)
            return
        if (final_snapshot and self.store is not None and self.store.since_snapshot > 0
                and not self._journal_ahead):
            if self._maintenance.acquire(timeout=max(0.0, timeout)):
                self._maintenance.release()
                thread = self._start_final_snapshot()
                if thread is not None:
                    thread.join(max(0.0, deadline - time.monotonic()))
        snapshot_thread = self._snapshot_thread
        if snapshot_thread is not None:
            snapshot_thread.join(max(0.0, deadline - time.monotonic()))
        with self._job_lock:
            self._closed = True   # a training job ending later takes no snapshot
        if snapshot_thread is not None and snapshot_thread.is_alive():
            log.warning("map %s: the final snapshot did not finish within the stop budget; "
                        "the journal still holds every change", self.name)
            return   # it may still rotate the journal: leave that open (the process exits)
        if self.store is not None:
            self.store.close()

    def _close_mid_replay(self, deadline: float) -> None:
        """Once the replay has stopped (at its next record: the service's stop event is
        set), save what it replayed as a snapshot within the time left, so that the next
        start resumes after it; if that does not fit, the next start replays the same
        records again (nothing is lost: the journal is untouched)."""
        with self._job_lock:
            self._closed = True
            started = self._replay_started
        if not started or self._replay_failed:
            if self.store is not None:
                self.store.close()
            return
        if not self._replay_ended.wait(max(0.0, deadline - time.monotonic())):
            log.warning("map %s: the journal replay did not stop within the stop budget; "
                        "the next start replays it again", self.name)
            return
        if self._replay_complete:   # it completed meanwhile: the journal is open
            assert self.store is not None
            self.store.close()
            return
        thread = threading.Thread(target=self._save_replayed, args=(deadline,),
                                  name=f"snapshot-{self.name}", daemon=True)
        thread.start()
        thread.join(max(0.0, deadline - time.monotonic()))
        if thread.is_alive():
            log.warning("map %s: what the stopped replay applied was not saved within the "
                        "stop budget; the next start replays those records again (nothing "
                        "is lost)", self.name)

    def _save_replayed(self, deadline: float) -> None:
        """Save the state the stopped replay reached (see :meth:`.MapStore.save_replayed`)."""
        assert self.store is not None and self._verdict is not None
        if self._verdict.map_id is None:   # a journal written before sequence numbers
            log.info("map %s: journal replay stopped; the next start replays it from the "
                     "start (it has no sequence numbers to resume by)", self.name)
            return
        if not self._maintenance.acquire(timeout=max(0.0, deadline - time.monotonic())):
            return
        try:
            meta = ServiceMeta(cameras=dict(self._cameras),
                               keyframe_camera_ids=dict(self._kf_camera_ids))
            path = self.store.save_replayed(self.engine, meta, self._verdict.map_id,
                                            self._verdict.snapshot_seq)
            report = self.restore_report
            if path is None:
                log.info("map %s: journal replay stopped before a numbered record past the "
                         "snapshot; nothing to save", self.name)
            else:
                log.info("map %s: journal replay stopped after %d of %d records; saved as "
                         "snapshot %s, the next start resumes after sequence number %s",
                         self.name, report.replayed + report.not_applied,
                         self._verdict.to_replay, path.name,
                         None if self.store.replayed_to is None else self.store.replayed_to[0])
        except Exception as exc:
            log.error("map %s: saving what the stopped replay applied failed (the next "
                      "start replays those records again): %s", self.name, exc)
        finally:
            self._maintenance.release()

    def _start_final_snapshot(self) -> threading.Thread | None:
        self.start_snapshot()
        return self._snapshot_thread
