"""One served map: its engine, camera registry, journal, snapshots, training jobs and counters.

Durability (per map directory ``<storage>/<map>/``)::

    journal/NNNNNNNNNNNN.journal   every accepted put/delete, fsynced before it is applied
    map/                           engine snapshots (``reloc_service.storage``: map + models)
    service.json                   cameras, keyframe camera ids, first journal segment to replay

A snapshot rotates the journal, saves the engine in a background thread (puts arriving
meanwhile are journaled at once and applied after the save, so queries are never held up by
it), writes ``service.json`` atomically and only then deletes the older journal segments.
Restoring loads the last snapshot and replays the journal from there, keeping what it can
prove: a damaged journal record is skipped (its bytes quarantined, see :mod:`.journal`), a
missing ``map/CURRENT`` is restored only to the snapshot ``service.json`` names (verified), and
anything else that does not read is a StorageError for this map alone. What was skipped is
logged, counted in the map's status counters (``restore_*``) and published as a
``storage_damaged`` event.
"""

from __future__ import annotations

import collections
import json
import logging
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode, EventKind, ProtocolError

from ..cameras import Camera, camera_from_dict
from ..engine import Engine, EngineConf
from ..errors import CameraError, MapError, StorageError
from ..fileio import atomic_write
from ..frame import Frame
from ..map import MapState
from ..relocalizers.base import Prior, RelocResult
from ..storage import CURRENT_FILE, restore_current, snapshot_dirs
from . import handlers
from .journal import Journal, JournalReport

log = logging.getLogger(__name__)

SERVICE_FILE = "service.json"
#: Limits when replaying the journal: what was accepted once is accepted again.
REPLAY_LIMITS = wire.Limits(max_payload_bytes=2**40, max_image_pixels=2**40,
                            max_features=2**40, max_hypotheses=2**20, max_list_len=2**40)

Publish = Callable[[str, EventKind, dict[str, Any]], None]


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


class RestoreInterrupted(Exception):
    """The service stopped while a map was being restored (nothing was written)."""


@dataclass
class RestoreReport:
    """What restoring a map found: journal records applied, records read that did not apply,
    damaged journal bytes skipped (quarantined), and a snapshot ``CURRENT`` was restored to."""

    replayed: int = 0
    not_applied: int = 0
    journal: JournalReport = field(default_factory=JournalReport)
    recovered_snapshot: str | None = None

    @property
    def damaged(self) -> bool:
        return bool(self.journal.damage or self.not_applied or self.recovered_snapshot)

    def counters(self) -> dict[str, int]:
        """Status counters (a StatusReply carries them without a protocol change)."""
        return {"restore_records_replayed": self.replayed,
                "restore_records_not_applied": self.not_applied,
                "restore_journal_skipped": len(self.journal.skipped),
                "restore_journal_torn_bytes": self.journal.torn_bytes,
                "restore_quarantine_files": len(self.journal.quarantined),
                "restore_snapshot_recovered": int(self.recovered_snapshot is not None)}

    def event_fields(self) -> dict[str, Any]:
        """Fields of the ``storage_damaged`` event published when :attr:`damaged`."""
        return {"failed": False, "records_replayed": self.replayed,
                "records_not_applied": self.not_applied,
                "journal_skipped": [[d.segment, d.offset, d.size] for d in self.journal.skipped],
                "journal_torn_bytes": self.journal.torn_bytes,
                "quarantined": [str(p) for p in self.journal.quarantined],
                "recovered_snapshot": self.recovered_snapshot}


@dataclass
class TrainingJob:
    """A training run in the background."""

    job_id: str
    methods: tuple[str, ...]
    thread: threading.Thread | None = None
    started: float = 0.0


class MapRuntime:
    """Everything the service holds for map ``name`` (see module docstring).

    Map changes (:meth:`apply_keyframe_put` etc.) come from the map's writer
    thread; queries (:meth:`relocalize`) from any worker thread."""

    def __init__(self, name: str, engine: Engine, *, instance: str, limits: wire.Limits,
                 methods: tuple[str, ...], default_method: str, directory: Path | None,
                 publish: Publish, snapshot_every: int = 200, fsync: bool = True) -> None:
        self.name = name
        self.engine = engine
        self.instance = instance
        self.limits = limits
        self.methods = methods
        self.default_method = default_method
        self.directory = directory
        self.stats = Stats()
        self.started_at = time.monotonic()
        self.snapshot_every = snapshot_every
        self._publish = publish
        self._cameras: dict[str, Camera] = {}
        self._kf_camera_ids: dict[int, str] = {}
        self.journal = None if directory is None else Journal(directory / "journal", fsync=fsync)
        self._apply_lock = threading.RLock()          # one map change at a time, in order
        self._maintenance = threading.Lock()          # training and snapshots do not overlap
        self._job_lock = threading.Lock()
        self._job: TrainingJob | None = None
        self._deferred: list[tuple[str, Any]] = []    # applied after the running snapshot
        self._snapshotting = False
        self._snapshot_thread: threading.Thread | None = None
        self._since_snapshot = 0
        self.restore_report = RestoreReport()
        #: Keyframes journaled at shutdown without being applied, and whether any record was.
        self._unapplied: set[int] = set()
        self._journal_ahead = False
        self._closed = False

    # -- reading -------------------------------------------------------------------------------
    def camera(self, camera_id: str) -> Camera | None:
        return self._cameras.get(camera_id)

    def camera_ids(self) -> list[str]:
        return sorted(self._cameras)

    def cameras(self) -> dict[str, Camera]:
        return dict(self._cameras)

    def keyframe_camera_id(self, kf_id: int) -> str | None:
        return self._kf_camera_ids.get(kf_id)

    def map_state(self) -> MapState:
        """The map as the relocalizers currently see it."""
        return self.engine.map.snapshot()

    def check_method(self, method: str | None) -> str:
        """``method`` (default: the map's default) if served; UNKNOWN_METHOD otherwise."""
        if method is None:
            return self.default_method
        method = ",".join(p.strip() for p in method.split(","))
        if method not in self.methods:
            raise ProtocolError(ErrorCode.UNKNOWN_METHOD,
                                f"method {method!r} is not served on map {self.name!r}; "
                                f"served: {list(self.methods)}")
        return method

    def relocalize(self, frame: Frame, *, method: str, prior: Prior | None,
                   hypotheses: int) -> RelocResult:
        return self.engine.relocalize(frame, method=method, prior=prior, hypotheses=hypotheses)

    def status(self) -> wire.StatusReply:
        st = self.engine.status()
        counters, latency = self.stats.snapshot()
        with self._job_lock:
            training = self._job is not None
        return wire.StatusReply(
            map=self.name, instance=self.instance, keyframes=st["keyframes"],
            landmarks=st["landmarks"],
            trained=all(m["trained"] for m in st["methods"].values()),
            map_version=st["map_version"], methods=self.methods,
            default_method=self.default_method, cameras=tuple(self.camera_ids()),
            training=training, uptime_s=time.monotonic() - self.started_at,
            counters=counters, latency_s=latency)

    # -- events ----------------------------------------------------------------------------------
    def publish(self, kind: EventKind, **fields: Any) -> None:
        self._publish(self.name, kind, fields)

    def reject(self, kind: EventKind, exc: BaseException, **fields: Any) -> None:
        """Publish a ``*_rejected`` event for ``exc`` and count it."""
        code, message = handlers.error_of(exc)
        self.stats.count("rejected")
        log.info("map %s: %s %s: %s %s", self.name, kind.value, fields, code.value, message)
        self.publish(kind, **fields, code=code.value, message=message)

    # -- map changes (writer thread) -------------------------------------------------------------
    def put_keyframe(self, kf_id: int, payload: bytes) -> None:
        """Validate, journal, apply (or defer during a snapshot) a KeyframePut."""
        try:
            kf = handlers.decode_keyframe_put(self, kf_id, payload)
            with self._apply_lock:
                self._journal_record({"op": "kf", "id": kf_id, "payload": payload})
                self.publish(EventKind.KEYFRAME_ACCEPTED, id=kf_id)
                self._apply_or_defer("kf", kf)
        except Exception as exc:
            self.reject(EventKind.KEYFRAME_REJECTED, exc, id=kf_id)

    def delete_keyframe(self, kf_id: int) -> None:
        """Journal and apply the removal of keyframe ``kf_id``."""
        try:
            with self._apply_lock:
                if kf_id not in self.engine.map and not self._deferred_has(kf_id):
                    raise MapError(f"cannot remove keyframe {kf_id}: not in map {self.name!r}")
                self._journal_record({"op": "del", "id": kf_id})
                self.publish(EventKind.KEYFRAME_ACCEPTED, id=kf_id, removed=True)
                self._apply_or_defer("del", kf_id)
        except Exception as exc:
            self.reject(EventKind.KEYFRAME_REJECTED, exc, id=kf_id)

    def put_camera(self, camera_id: str, payload: bytes) -> None:
        """Validate, journal and register a CameraPut."""
        try:
            camera = handlers.decode_camera_put(camera_id, payload, self.limits)
            with self._apply_lock:
                self._journal_record({"op": "cam", "id": camera_id, "payload": payload})
                previous = self._cameras.get(camera_id)
                self._cameras[camera_id] = camera
            self.stats.count("cameras_put")
            if previous is None or previous.to_dict() == camera.to_dict():
                self.publish(EventKind.CAMERA_ADDED, id=camera_id)
                return
            # Never rewritten: the keyframes already built keep the intrinsics they were built
            # with (a replica copies them so, see bootstrap.Bootstrap); only new puts use these.
            kept = sum(1 for c in self._kf_camera_ids.values() if c == camera_id)
            log.warning("map %s: camera %s changed; %d keyframes built with it keep their "
                        "intrinsics", self.name, camera_id, kept)
            self.publish(EventKind.CAMERA_ADDED, id=camera_id, changed=True,
                         keyframes_kept=kept)
        except Exception as exc:
            self.reject(EventKind.CAMERA_REJECTED, exc, id=camera_id)

    def _journal_record(self, record: dict[str, Any]) -> None:
        if self.journal is not None:
            self.journal.append(msgpack.packb(record, use_bin_type=True))
            self._since_snapshot += 1

    def _deferred_has(self, kf_id: int) -> bool:
        return any(op == "kf" and item.kf_id == kf_id for op, item in self._deferred)

    def _apply_or_defer(self, op: str, item: Any) -> None:
        if self._snapshotting:
            self._deferred.append((op, item))
        else:
            self._apply(op, item)

    def _apply(self, op: str, item: Any, *, replay: bool = False) -> None:
        if op == "kf":
            kf: handlers.KeyframeInput = item
            self.engine.add_keyframe(kf.kf_id, kf.image, kf.camera, kf.world_from_cam,
                                     **kf.engine_kwargs())
            if kf.camera_id is not None:
                self._kf_camera_ids[kf.kf_id] = kf.camera_id
            else:
                self._kf_camera_ids.pop(kf.kf_id, None)
            if not replay:
                self.stats.count("keyframes_put")
                self.publish(EventKind.KEYFRAME_ADDED, id=kf.kf_id,
                             map_version=self.engine.map.version)
        elif op == "del":
            self.engine.remove_keyframe(item)
            self._kf_camera_ids.pop(item, None)
            if not replay:
                self.stats.count("keyframes_deleted")
                self.publish(EventKind.KEYFRAME_REMOVED, id=item,
                             map_version=self.engine.map.version)

    def wants_snapshot(self) -> bool:
        return (self.journal is not None and self.snapshot_every > 0
                and self._since_snapshot >= self.snapshot_every)

    # -- restore ---------------------------------------------------------------------------------
    def restore(self, stop: threading.Event | None = None) -> int:
        """Replay the journal after the snapshot the engine was loaded from (see
        :func:`open_engine`), then open it for appending. Returns the records replayed; what
        was skipped is in :attr:`restore_report` and the status counters. StorageError if
        ``service.json`` or a journal segment header does not read (nothing is changed);
        RestoreInterrupted if ``stop`` is set meanwhile (the journal is left as it was)."""
        if self.journal is None or self.directory is None:
            return 0
        meta = read_service_file(self.directory)
        self._restore_cameras(meta)
        report = self.restore_report
        for raw in self.journal.replay(from_segment=int(meta.get("next_segment", 0))):
            if stop is not None and stop.is_set():
                raise RestoreInterrupted(f"map {self.name}: restore interrupted after "
                                         f"{report.replayed} journal records (shutting down)")
            if self._replay_record(raw):
                report.replayed += 1
            else:
                report.not_applied += 1
        report.journal = self.journal.report
        self.journal.open()
        self._since_snapshot = report.replayed
        for name, n in report.counters().items():
            if n:
                self.stats.count(name, n)
        return report.replayed

    def _restore_cameras(self, meta: dict[str, Any]) -> None:
        assert self.directory is not None
        try:
            for cid, d in meta.get("cameras", {}).items():
                self._cameras[cid] = camera_from_dict(d)
            self._kf_camera_ids.update({int(k): str(v) for k, v in
                                        meta.get("keyframe_camera_ids", {}).items()})
            int(meta.get("next_segment", 0))
        except (AttributeError, KeyError, TypeError, ValueError, CameraError) as exc:
            raise StorageError(f"{self.directory / SERVICE_FILE}: {exc}; expected cameras, "
                               f"keyframe_camera_ids and next_segment as written by the "
                               f"service") from exc

    def _replay_record(self, raw: bytes) -> int:
        """1 if the record was applied again, 0 if it was skipped (logged)."""
        try:
            record = msgpack.unpackb(raw, raw=False)
            op = record["op"]
            if op == "kf":
                kf = handlers.decode_keyframe_put(_ReplayView(self), record["id"],
                                                  record["payload"])
                self._apply("kf", kf, replay=True)
            elif op == "del":
                if record["id"] in self.engine.map:
                    self._apply("del", record["id"], replay=True)
            elif op == "cam":
                self._cameras[record["id"]] = handlers.decode_camera_put(
                    record["id"], record["payload"], REPLAY_LIMITS)
            else:
                raise ValueError(f"unknown journal op {op!r}")
            return 1
        except Exception as exc:  # a record that cannot be applied again is skipped, loudly
            log.error("map %s: skipping a journal record that does not replay: %s", self.name,
                      exc)
            return 0

    # -- snapshots -------------------------------------------------------------------------------
    def start_snapshot(self, *, wait: bool = False) -> bool:
        """Save the map in the background (one at a time); with ``wait``, block until it is
        durable. False if there is no storage or a snapshot is already running."""
        if self.journal is None:
            return False
        with self._job_lock:
            if self._journal_ahead or self._closed:
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
        assert self.journal is not None and self.directory is not None
        with self._maintenance:
            with self._apply_lock:
                if self._journal_ahead:   # waited past a shutdown that journaled unapplied puts
                    return
                try:
                    segment = self.journal.rotate()
                except StorageError as exc:
                    log.error("map %s: snapshot not taken: %s", self.name, exc)
                    return
                cameras = {cid: cam.to_dict() for cid, cam in self._cameras.items()}
                kf_cams = {str(k): v for k, v in self._kf_camera_ids.items()}
                self._snapshotting = True
                self._since_snapshot = 0
            try:
                path = self.engine.save(self.directory / "map")
                write_service_file(self.directory, {
                    "snapshot": path.name, "next_segment": segment, "cameras": cameras,
                    "keyframe_camera_ids": kf_cams, "map_version": self.map_state().version,
                    "time": time.time()})
                self.journal.delete_before(segment)
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
                                id=item.kf_id if op == "kf" else item)

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
                self.publish(EventKind.TRAIN_PROGRESS, job_id=job.job_id, fraction=1.0,
                             stage="done")
        except Exception as exc:
            code, message = handlers.error_of(exc)
            self.publish(EventKind.TRAIN_FAILED, job_id=job.job_id, code=code.value,
                         message=message)
            with self._job_lock:
                self._job = None
            return
        with self._job_lock:
            self._job = None
        self.publish(EventKind.TRAIN_DONE, job_id=job.job_id,
                     duration_s=time.perf_counter() - start, map_version=self.map_state().version)
        self.start_snapshot()   # the trained models survive a restart

    def wait_snapshot(self, timeout: float = 60.0) -> None:
        """Wait for a running snapshot (its deferred puts are applied when it ends)."""
        thread = self._snapshot_thread
        if thread is not None and thread.is_alive():
            thread.join(timeout)

    def training_thread(self) -> threading.Thread | None:
        with self._job_lock:
            return None if self._job is None else self._job.thread

    # -- shutdown --------------------------------------------------------------------------------
    def journal_only(self, op: str, ident: Any, payload: bytes | None) -> bool:
        """At shutdown: validate and journal a queued keyframe put or delete without applying
        it (applying runs SIFT and triangulation, ~0.3 s a keyframe); the journal replay at
        the next start applies it. False without storage (nothing would survive anyway)."""
        if self.journal is None:
            return False
        try:
            with self._apply_lock:
                if op == "kf":
                    assert payload is not None
                    handlers.decode_keyframe_put(self, ident, payload)   # refused as usual
                    self._journal_record({"op": "kf", "id": ident, "payload": payload})
                    self._unapplied.add(ident)
                else:
                    if (ident not in self.engine.map and ident not in self._unapplied
                            and not self._deferred_has(ident)):
                        raise MapError(f"cannot remove keyframe {ident}: not in map "
                                       f"{self.name!r}")
                    self._journal_record({"op": "del", "id": ident})
                    self._unapplied.discard(ident)
                self._journal_ahead = True
            self.publish(EventKind.KEYFRAME_ACCEPTED, id=ident, **({"removed": True}
                                                                   if op == "del" else {}))
        except Exception as exc:
            self.reject(EventKind.KEYFRAME_REJECTED, exc, id=ident)
        return True

    def close(self, *, final_snapshot: bool = True, timeout: float = 60.0) -> None:
        """Final snapshot within ``timeout`` s (when something changed since the last one and
        no record was journaled without being applied: the snapshot would drop it from the
        journal), then close the journal. A running training job is not waited for beyond
        the same ``timeout``: its models are lost, the map is not."""
        deadline = time.monotonic() + timeout
        if (final_snapshot and self.journal is not None and self._since_snapshot > 0
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
        if self.journal is not None:
            self.journal.close()

    def _start_final_snapshot(self) -> threading.Thread | None:
        self.start_snapshot()
        return self._snapshot_thread


class _ReplayView:
    """A MapRuntime as seen by decoding during replay: no payload limits."""

    def __init__(self, rt: MapRuntime) -> None:
        self._rt = rt
        self.limits = REPLAY_LIMITS
        self.name = rt.name

    def camera(self, camera_id: str) -> Camera | None:
        return self._rt.camera(camera_id)

    def camera_ids(self) -> list[str]:
        return self._rt.camera_ids()


# -- the service.json file ---------------------------------------------------------------------

def read_service_file(directory: Path) -> dict[str, Any]:
    """``service.json`` of a map directory ({} if absent); StorageError if damaged."""
    path = directory / SERVICE_FILE
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise StorageError(f"{path}: cannot read ({exc}); expected the service's map "
                           f"metadata") from exc
    if not isinstance(data, dict):
        raise StorageError(f"{path}: expected a JSON object")
    return data


def write_service_file(directory: Path, data: dict[str, Any]) -> None:
    """Write ``service.json`` atomically (temporary file, fsync, rename, fsync directory)."""
    atomic_write(directory / SERVICE_FILE, json.dumps(data, indent=1))


def open_engine(directory: Path | None, conf: EngineConf) -> Engine:
    """The engine of a map: loaded from its last snapshot if there is one, else empty.
    Call :func:`recover_current` first so a missing ``CURRENT`` is not taken for a new map."""
    if directory is not None and (directory / "map" / CURRENT_FILE).is_file():
        return Engine.load(directory / "map", conf)
    return Engine(conf)


def recover_current(directory: Path) -> str | None:
    """Restore a missing ``map/CURRENT`` of map directory ``directory``; the snapshot name
    if it was restored, None if nothing was missing (or the map is new).

    Only the snapshot ``service.json`` names is a valid target: the journal continues from
    it (``next_segment``), so any other snapshot would silently lose or repeat records. It is
    used only if every file of it verifies against its manifest; otherwise StorageError (the
    map is failed, nothing is deleted or rewritten)."""
    map_dir = directory / "map"
    if (map_dir / CURRENT_FILE).is_file():
        return None
    present = [p.name for p in snapshot_dirs(map_dir)]
    named = read_service_file(directory).get("snapshot")
    if not present and named is None:
        return None
    if not isinstance(named, str) or named not in present:
        raise StorageError(
            f"{map_dir / CURRENT_FILE}: missing; snapshot(s) {present or 'none'} present, "
            f"{directory / SERVICE_FILE} names {named!r}: cannot tell which snapshot the "
            f"journal continues from, so the map is not restored (nothing was deleted); "
            f"inspect it with `reloc map check {directory}`, then write CURRENT "
            f"('snapshots/<n>') by hand")
    restore_current(map_dir, named)
    log.warning("map directory %s: %s was missing; restored it to snapshots/%s, the snapshot "
                "service.json names (every file verified)", directory, CURRENT_FILE, named)
    return named


def check_storage(directory: Path) -> None:
    """Create ``directory`` (StorageError with the reason if impossible)."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StorageError(f"cannot create the storage directory {directory}: "
                           f"{exc.strerror or exc}") from exc

