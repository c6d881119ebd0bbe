"""The service: maps, worker pools, the per-map writers and the Zenoh layer, started and stopped
together.

Zenoh callbacks only enqueue (:class:`Service` is the :class:`~.zenoh_io.Dispatcher`):
relocalize queries go to a bounded pool of worker threads (full: "busy" at once), each
answering on the maps themselves (``service.worker_mode = "thread"``) or handing the request
to a worker process holding replicas of them (``"process"``, the default: :mod:`.processes`), status /
train / map-copy queries to a small control pool, and keyframe and camera puts to their map's
writer thread, which journals then applies them in arrival order (one writer per map, so one
map's snapshot or training never holds up another map's puts).

Stopping is bounded by ``service.stop_timeout_s``: puts still queued are validated and
journaled without being applied (the replay at the next start applies them), a final snapshot
is taken only within what is left of the budget, and the process exits without waiting for
threads that may still be inside native code (see :func:`serve`).
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode, EventKind, ProtocolError

from ..core.errors import ConfigError, StorageError
from ..core.numeric import limit_blas_threads
from ..engine import EngineConf, MappingConf
from . import handlers
from .codec import decode_camera_put, decode_keyframe_put, error_of, error_reply
from .config import ServiceConf
from .durability import (
    RestoreInterrupted,
    check_storage,
    journal_bytes,
    map_dirname,
    open_engine,
    recover_current,
    stored_map_names,
)
from .processes import EngineSpec, ProcessWorkers
from .replication import Bootstrap, Peers
from .runtime import MapRuntime
from .workers import WorkerPool, stop_on_signals
from .zenoh_io import PendingQuery, QueryKind, ZenohLayer, open_session

log = logging.getLogger(__name__)

#: Queue of the control pool (status, train, keyframes/cameras gets).
CONTROL_QUEUE = 64


class Service:
    """A reloc service for ``conf``: :meth:`start`, then :meth:`stop` (or ``with``)."""

    def __init__(self, conf: ServiceConf) -> None:
        self.conf = conf
        self.instance = conf.instance
        self.prefix = wire.check_prefix(conf.service.prefix)
        self.limits = conf.limits.to_wire()
        self.storage = conf.storage_path
        methods = conf.service.methods
        # The engine's default is its first method.
        self.methods = (conf.service.default_method,
                        *[m for m in methods if m != conf.service.default_method])
        self.engine_conf = EngineConf(methods=self.methods, options=conf.options,
                                      mapping=MappingConf.from_options(conf.mapping))
        self.maps: dict[str, MapRuntime] = {}
        self._maps_lock = threading.Lock()
        self.session: Any = None
        self.layer: ZenohLayer | None = None
        self.ros2: Any = None     # the ROS 2 bridge ([ros2] enabled)
        self.relocalize_pool: WorkerPool | None = None
        #: The worker processes (worker_mode "process"); they start with the first query.
        self.processes: ProcessWorkers | None = None
        self.control_pool: WorkerPool | None = None
        #: Writes of maps this instance does not serve (rejected or ignored, in order) and the
        #: bootstrap's copy; each served map has its own writer in ``writers``.
        self.writer: WorkerPool | None = None
        self.writers: dict[str, WorkerPool] = {}
        self._writers_lock = threading.Lock()
        self._stopped = threading.Event()
        self.started_at = time.monotonic()
        #: The copy of peers' maps at start (bootstrap_from_peers), and the other instances.
        self._bootstrap: Bootstrap | None = None
        self.peers: Peers | None = None
        #: Maps whose storage did not restore: map -> why (queries get STORAGE_ERROR with it).
        self.failed: dict[str, str] = {}
        self._loading: set[str] = set()      # being restored: not declared yet
        self._ready = threading.Event()      # every stored and configured map is up (or failed)
        self._loader: threading.Thread | None = None
        self._warned_keys: dict[str, None] = {}   # malformed keys already logged (bounded)

    # -- life cycle ------------------------------------------------------------------------------
    def start(self, *, wait_ready: bool = True) -> Service:
        """Open Zenoh, then restore stored maps and create configured ones one by one, the
        cheapest first, declaring each as soon as it is ready (a map being restored is not
        declared: no reply rather than a stale one). With ``wait_ready`` (the default), return
        once every map is up; ``reloc serve`` does not wait, so small maps are served while a
        big journal replays. A map whose storage does not restore is failed, not fatal."""
        self._check_methods()
        if self.conf.service.opencv_threads:
            import cv2

            cv2.setNumThreads(self.conf.service.opencv_threads)
        limit_blas_threads(self.conf.service.blas_threads)
        if self.storage is not None:
            check_storage(self.storage)
        names = self._restore_order(self._stored_map_names() + sorted(self.conf.maps))
        s = self.conf.service
        self.relocalize_pool = WorkerPool("relocalize", workers=s.workers,
                                          queue_size=s.queue_size)
        if s.worker_mode == "process":
            self.processes = ProcessWorkers(s.workers, EngineSpec.of(
                self.methods, self.conf.options, self.conf.mapping, self.limits))
        self.control_pool = WorkerPool("control", workers=1, queue_size=CONTROL_QUEUE)
        self.writer = WorkerPool("writer", workers=1, queue_size=s.writer_queue_size,
                                 max_bytes=s.writer_queue_bytes)
        self._loading = set(names)
        self.session = open_session(self.conf.zenoh)
        self.peers = Peers(self.session, self.prefix, self.instance, self.limits)
        self.layer = ZenohLayer(self.session, self.prefix, self.instance, self)
        if self.conf.ros2.enabled:   # imported here: rosbags and xxhash are the extra 'ros2'
            from .ros2.bridge import Ros2Bridge

            self.ros2 = Ros2Bridge(self, self.conf.ros2)
        if s.bootstrap_from_peers:   # a replica copies peers' maps once its own are restored
            self._load_maps(names, declare=False)
            # subscribed already: live puts buffer in the writer queues meanwhile
            self._bootstrap = Bootstrap(self.session, self.prefix, self.maps, gate=self.writer,
                                        writer_for=self._writer_for)
            self._bootstrap.run()
            for name in sorted(self.maps):
                self._declare(name)
        else:
            self._loader = threading.Thread(target=self._load_maps, args=(names,),
                                            name="restore-maps", daemon=True)
            self._loader.start()
            if wait_ready:
                self.wait_ready()
        log.info("reloc service %s under %r (zenoh %s, listen %s, connect %s): %s",
                 self.instance, self.prefix, self.conf.zenoh.mode,
                 list(self.conf.zenoh.listen), list(self.conf.zenoh.connect),
                 f"serving {sorted(self.maps) or 'no map yet'}" if self._ready.is_set()
                 else f"restoring {len(names)} maps, each served once ready")
        return self

    def wait_ready(self, timeout: float | None = None) -> bool:
        """Wait until every map found at start is served (or failed); False on timeout."""
        return self._ready.wait(timeout)

    def _restore_order(self, names: list[str]) -> list[str]:
        """Unique ``names``, cheapest restore first (fewest journal bytes to replay)."""
        def cost(name: str) -> int:
            return 0 if self.storage is None else journal_bytes(self.storage / map_dirname(name))

        unique = list(dict.fromkeys(names))
        return sorted(unique, key=lambda n: (cost(n), n))

    def _load_maps(self, names: list[str], *, declare: bool = True) -> None:
        """Restore ``names`` in order; declare each one ready (or failed) at once."""
        try:
            for name in names:
                if self._stopped.is_set():
                    break
                self._bring_up(name, declare=declare)
        finally:
            self._loading.clear()
            self._ready.set()

    def _bring_up(self, name: str, *, declare: bool) -> None:
        try:
            rt = self._open_map(name)
        except RestoreInterrupted as exc:
            log.info("%s", exc)
            return
        except Exception as exc:   # one map's damage never takes down the others
            self._fail_map(name, exc)
            return
        with self._maps_lock:
            self._loading.discard(name)
            if self._stopped.is_set():
                rt.close(final_snapshot=False)
                return
            self.maps[name] = rt
        if declare:
            self._declare(name)

    def _declare(self, name: str) -> None:
        """Declare map ``name`` (queryables, events, liveliness; ROS 2 nodes if enabled), then
        publish what its restore skipped, if anything."""
        if self.layer is None or self._stopped.is_set():
            return
        self.layer.serve_map(name)
        rt = self.maps.get(name)
        if rt is None:
            return
        if self.ros2 is not None:
            self.ros2.serve_map(name)
        if rt.restore_report.damaged:
            rt.publish(EventKind.STORAGE_DAMAGED, **rt.restore_report.event_fields())

    def _fail_map(self, name: str, exc: BaseException) -> None:
        """Mark ``name`` failed: its queries and puts get STORAGE_ERROR with the reason; its
        files stay as they are."""
        where = ("" if self.storage is None
                 else f" (see `reloc map check {self.storage / map_dirname(name)}`)")
        message = (f"map {name!r} is not served: its storage did not restore: {exc}; its "
                   f"files are left untouched{where}")
        log.error("%s", message, exc_info=not isinstance(exc, StorageError))
        with self._maps_lock:
            self._loading.discard(name)
            self.failed[name] = message
        self._publish_event(name, EventKind.STORAGE_DAMAGED, {"failed": True,
                                                              "message": message})
        if self.layer is not None and not self._stopped.is_set():
            self.layer.serve_map(name)

    def stop(self, *, final_snapshot: bool = True) -> None:
        """Within ``service.stop_timeout_s``: undeclare (clients see the liveliness tokens go,
        no more puts arrive), journal the queued puts without applying them, let queued
        queries finish, take final snapshots with the time left, close the session."""
        if self._stopped.is_set():
            return
        self._stopped.set()
        start = time.monotonic()
        deadline = start + self.conf.service.stop_timeout_s
        if self.ros2 is not None:
            self.ros2.close()              # ROS 2 tools see the nodes go
        if self.layer is not None:
            self.layer.withdraw()          # clients see the maps go; no more puts arrive
        journaled = self._flush_writers(deadline)
        for pool in (self.relocalize_pool, self.control_pool):
            if pool is not None:           # queued queries finish; new ones get "busy"
                pool.close(timeout=_left(deadline, share=0.5))
        if self.processes is not None:
            self.processes.close()
        for rt in list(self.maps.values()):
            try:
                rt.close(final_snapshot=final_snapshot, timeout=_left(deadline))
            except Exception as exc:
                log.error("map %s: closing failed: %s", rt.name, exc)
        if self.layer is not None:
            self.layer.close()
        if self.session is not None and not self.session.is_closed():
            self.session.close()
        log.info("reloc service %s stopped in %.1f s (%d queued puts journaled, applied at the "
                 "next start)", self.instance, time.monotonic() - start, journaled)

    def _flush_writers(self, deadline: float) -> int:
        """Take the queued writes out of every writer, let each finish the write it is
        running (so the journal keeps arrival order), then journal the queued ones without
        applying them; the number journaled. Queued map copies get no reply (their gets end
        empty); the writer threads stop."""
        with self._writers_lock:
            pools = [*self.writers.values(), *([self.writer] if self.writer else [])]
        queued = [job for pool in pools for job in pool.take_queued()]
        for pool in pools:   # a running put ends within a second; a map copy may not
            if not pool.join(min(_left(deadline, share=0.25), 5.0)):
                log.warning("%s: still busy at shutdown", pool.name)
        journaled = sum(job.journal_only() for job in queued if isinstance(job, _WriteJob))
        for pool in pools:
            pool.close(timeout=_left(deadline, share=0.25))
        return journaled

    def start_workers_in_background(self) -> None:
        """Start the relocalize worker processes (worker_mode "process") on a thread once
        every map is restored (each worker loads them all), so that the first query does not
        wait for them; without this they start with the first query. No-op in thread mode."""
        if self.processes is not None:
            threading.Thread(target=self._start_workers, name="start-workers",
                             daemon=True).start()

    def _start_workers(self) -> None:
        self.wait_ready()
        assert self.processes is not None
        try:
            self.processes.start()
        except Exception as exc:   # the first query tries again and reports it
            log.error("starting the relocalize worker processes failed: %s", exc)

    def __enter__(self) -> Service:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def run_forever(self, stop: threading.Event | None = None) -> None:
        """Serve until ``stop`` is set (default: until SIGINT or SIGTERM), then :meth:`stop`
        cleanly."""
        stop = stop or stop_on_signals()
        try:
            while not stop.wait(0.5):
                pass
        finally:
            self.stop()

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Wait until queued keyframe puts are applied (tests, demo)."""
        deadline = time.monotonic() + timeout
        with self._writers_lock:
            pools = [*([self.writer] if self.writer else []), *self.writers.values()]
        return all(pool.join(max(0.0, deadline - time.monotonic())) for pool in pools)

    def _writer_for(self, map_name: str) -> WorkerPool:
        """The writer of ``map_name``: its own if the map is served or may be created by this
        put, else the shared one (which rejects or ignores, in order)."""
        with self._writers_lock:
            return self._writer_locked(map_name)

    def _writer_locked(self, map_name: str) -> WorkerPool:
        pool = self.writers.get(map_name)
        if pool is not None:
            return pool
        if map_name not in self.maps and not self.conf.service.allow_new_maps:
            assert self.writer is not None
            return self.writer
        pool = WorkerPool(f"writer-{map_name}", workers=1,
                          queue_size=self.conf.service.writer_queue_size,
                          max_bytes=self.conf.service.writer_queue_bytes)
        self.writers[map_name] = pool
        return pool

    def _submit_write(self, map_name: str, job: Callable[[float], None], *,
                      size: int = 0) -> bool:
        with self._writers_lock:   # not interleaved with _retire_writer
            return self._writer_locked(map_name).submit(job, size=size)

    def _retire_writer(self, map_name: str) -> None:
        """Stop the writer of a map that its put did not create (no idle thread per junk
        name); called from that writer's own thread, so closed from another."""
        with self._writers_lock:
            pool = self.writers.get(map_name)
            if pool is None or map_name in self.maps or pool.pending or self._stopped.is_set():
                return
            del self.writers[map_name]
        threading.Thread(target=pool.close, name=f"retire-{map_name}", daemon=True).start()

    # -- maps ------------------------------------------------------------------------------------
    def _check_methods(self) -> None:
        """Build every method once on an empty map: bad names or options fail at start."""
        from ..engine import Engine

        try:
            Engine(self.engine_conf)
        except ConfigError as exc:
            raise ConfigError(f"service.methods / [options]: {exc}") from exc

    def _stored_map_names(self) -> list[str]:
        return [] if self.storage is None else stored_map_names(self.storage)

    def _open_map(self, name: str) -> MapRuntime:
        """The runtime of map ``name``, restored from its storage (StorageError naming the
        file if that is damaged beyond what restoring skips)."""
        directory = None if self.storage is None else self.storage / map_dirname(name)
        start = time.perf_counter()
        recovered = None if directory is None else recover_current(directory)
        engine = open_engine(directory, self.engine_conf)
        rt = MapRuntime(name, engine, instance=self.instance, limits=self.limits,
                        methods=self.methods, default_method=self.methods[0],
                        directory=directory, publish=self._publish_event,
                        snapshot_every=self.conf.service.snapshot_every,
                        fsync=self.conf.service.fsync)
        if directory is not None:
            check_storage(directory)
            replayed = rt.restore(self._stopped)
            if recovered is not None:
                rt.restore_report.recovered_snapshot = recovered
                rt.stats.count("restore_snapshot_recovered")
            state = rt.map_state()
            log.info("map %s: %d keyframes restored (%d journal records replayed) in %.1f s",
                     name, len(state.keyframes), replayed, time.perf_counter() - start)
            trained = all(m["trained"] for m in engine.status()["methods"].values())
            if len(state.keyframes) and not trained and self.conf.service.train_on_load:
                rt.start_training(None)
        if self.processes is not None:
            self.processes.attach(rt)
        return rt

    def _map_for_put(self, name: str, kind: EventKind, ident: Any,
                     payload: bytes | None) -> MapRuntime | None:
        """The runtime of ``name``; created (and served) if new maps are allowed and the put
        decodes and validates (ProtocolError otherwise: garbage on a new name leaves nothing
        on disk). A delete never creates a map. A map being restored refuses puts (BUSY), a
        failed one too (STORAGE_ERROR)."""
        rt = self.maps.get(name)
        if rt is not None:
            return rt
        self._check_restored(name)
        if not self.conf.service.allow_new_maps or self._stopped.is_set():
            return None
        if payload is None:
            raise ProtocolError(ErrorCode.UNKNOWN_MAP,
                                f"map {name!r} does not exist; a delete does not create it")
        self._validate_first_put(name, kind, ident, payload)
        with self._maps_lock:
            self._check_restored(name)
            if name not in self.maps:
                self.maps[name] = self._open_map(name)
                if self.layer is not None:
                    self.layer.serve_map(name)
                if self.ros2 is not None:
                    self.ros2.serve_map(name)
                log.info("map %s created by its first put", name)
            return self.maps[name]

    def _check_restored(self, name: str) -> None:
        if name in self.failed:
            raise StorageError(self.failed[name])
        if name in self._loading:
            raise wire.ProtocolError(ErrorCode.BUSY,
                                     f"map {name!r} is being restored from storage; put again "
                                     f"once it is served (its liveliness token appears)")

    def _validate_first_put(self, name: str, kind: EventKind, ident: Any,
                            payload: bytes) -> None:
        """Decode a put on a map that does not exist yet, as the new map would (no camera
        registered: a keyframe needs an inline camera); ProtocolError if it would fail."""
        wire.check_name(name)
        if kind is EventKind.CAMERA_REJECTED:
            decode_camera_put(ident, payload, self.limits)
        else:
            decode_keyframe_put(_NoCameras(name, self.limits), ident, payload)

    def _publish_event(self, map_name: str, kind: EventKind, fields: dict[str, Any]) -> None:
        payload = wire.Event(kind, map_name, time.time(), fields).encode()
        if self.layer is not None and map_name in self.maps:
            self.layer.publish_event(map_name, payload)
        elif self.session is not None and not self.session.is_closed():
            self.session.put(wire.keys.events(self.prefix, map_name), payload)

    # -- dispatcher (called in Zenoh threads: enqueue only) --------------------------------------
    def on_keyframe_sample(self, map_name: str, kf_id: int, payload: bytes | None) -> None:
        if payload is None:
            self._write(map_name, EventKind.KEYFRAME_REJECTED, kf_id,
                        lambda rt: rt.delete_keyframe(kf_id), op="del")
        elif self._bootstrap is not None and self._bootstrap.active:
            copy = self._bootstrap
            self._write(map_name, EventKind.KEYFRAME_REJECTED, kf_id,
                        lambda rt: copy.put_unless_copied(rt, kf_id, payload), op="kf",
                        payload=payload)
        else:
            self._write(map_name, EventKind.KEYFRAME_REJECTED, kf_id,
                        lambda rt: rt.put_keyframe(kf_id, payload), op="kf", payload=payload)

    def on_camera_sample(self, map_name: str, camera_id: str, payload: bytes | None) -> None:
        if payload is None:
            self._reject(map_name, EventKind.CAMERA_REJECTED, camera_id, ErrorCode.BAD_VALUE,
                         "cameras cannot be deleted; put the camera again to change it")
            return
        self._write(map_name, EventKind.CAMERA_REJECTED, camera_id,
                    lambda rt: rt.put_camera(camera_id, payload), payload=payload)

    def on_bad_key(self, key: str, problem: str, code: ErrorCode = ErrorCode.BAD_NAME) -> None:
        """A refused sample: a rejected event on its map's events key if this instance serves
        that map (the sender listens there), else one WARNING per key naming the rule."""
        target = self._rejection_target(key)
        if target is not None:
            self._reject(*target, code, problem)
            return
        if key in self._warned_keys:
            return
        if len(self._warned_keys) >= 1024:   # bounded: a flood of distinct keys
            self._warned_keys.pop(next(iter(self._warned_keys)))
        self._warned_keys[key] = None
        log.warning("ignoring a sample on %s (%s): %s (logged once per key)", key, code.value,
                    problem)

    def _rejection_target(self, key: str) -> tuple[str, EventKind, Any] | None:
        """(map, event kind, id) for a sample on ``<prefix>/<served map>/keyframes|cameras/
        <id>``; None when the map is not one this instance serves."""
        head = f"{self.prefix}/"
        parts = key[len(head):].split("/") if key.startswith(head) else []
        if len(parts) != 3 or parts[0] not in self.maps:
            return None
        leaf = parts[2]
        if parts[1] == "keyframes":
            canonical = (leaf.isdigit() and (leaf == "0" or not leaf.startswith("0"))
                         and int(leaf) < 2**63)
            return parts[0], EventKind.KEYFRAME_REJECTED, int(leaf) if canonical else leaf
        if parts[1] == "cameras":
            return parts[0], EventKind.CAMERA_REJECTED, leaf
        return None

    def on_query(self, map_name: str, kind: QueryKind, query: PendingQuery) -> None:
        rt = self.maps.get(map_name)
        if rt is None:  # undeclared meanwhile, or its storage did not restore
            failure = self.failed.get(map_name)
            query.reply_err(wire.encode_error(ErrorCode.STORAGE_ERROR, failure) if failure
                            else wire.encode_error(ErrorCode.UNKNOWN_MAP,
                                                   f"map {map_name!r} is not served"))
            return
        if kind is QueryKind.RELOCALIZE:
            assert self.relocalize_pool is not None
            if not self.relocalize_pool.submit(lambda queued: self._relocalize(rt, query,
                                                                               queued)):
                rt.stats.count("busy")
                query.reply(handlers.busy_reply(
                    f"all {self.conf.service.workers} workers busy and "
                    f"{self.conf.service.queue_size} queries waiting; retry later"))
                query.finish()
            return
        if kind is QueryKind.KEYFRAMES:
            # Answered by the writer after the puts already received, so a replica that
            # subscribed before asking (bootstrap_from_peers) misses none of them.
            if not self._writer_for(map_name).submit(
                    lambda _queued: self._copy_after_writes(rt, query)):
                rt.stats.count("busy")
                query.reply_err(wire.encode_error(ErrorCode.BUSY, "writer queue full; retry"))
            return
        assert self.control_pool is not None
        if not self.control_pool.submit(lambda _queued: self._control(rt, kind, query)):
            rt.stats.count("busy")
            query.reply_err(wire.encode_error(ErrorCode.BUSY, "control queue full; retry"))

    # -- jobs (worker threads) -------------------------------------------------------------------
    def _write(self, map_name: str, kind: EventKind, ident: Any,
               apply: Callable[[MapRuntime], None], *, op: str = "cam",
               payload: bytes | None = None) -> None:
        job = _WriteJob(self, map_name, kind, ident, apply, op, payload)
        if self._stopped.is_set():
            self._reject(map_name, kind, ident, ErrorCode.BUSY,
                         "the service is stopping; put again once it is back (or to a replica)")
        elif not self._submit_write(map_name, job, size=len(payload or b"")):
            s = self.conf.service
            self._reject(map_name, kind, ident, ErrorCode.BUSY,
                         f"writer queue full ({s.writer_queue_size} puts or "
                         f"{s.writer_queue_bytes} bytes waiting); put again later")

    def _run_write(self, job: _WriteJob) -> None:
        """A queued write, in its map's writer thread."""
        map_name, kind, ident = job.map_name, job.kind, job.ident
        try:
            rt = self._map_for_put(map_name, kind, ident, job.payload)
        except Exception as exc:
            code, message = error_of(exc)
            self._reject(map_name, kind, ident, code, message)
            self._retire_writer(map_name)
            return
        if rt is None and self.peers is not None and self.peers.serves(map_name):
            log.debug("put on map %s ignored: another instance serves it", map_name)
        elif rt is None:
            self._reject(map_name, kind, ident, ErrorCode.UNKNOWN_MAP,
                         f"map {map_name!r} is not served and this service does not create "
                         "maps (service.allow_new_maps = false)")
        else:
            job.apply(rt)
            if rt.wants_snapshot():
                rt.start_snapshot()
            return
        self._retire_writer(map_name)

    def _journal_write(self, job: _WriteJob) -> bool:
        """At shutdown: journal a queued write without applying it (cameras are cheap and
        keyframes need them: applied). True if journaled."""
        rt = self.maps.get(job.map_name)
        if rt is None:   # a put that would have created its map: refused, not lost silently
            self._reject(job.map_name, job.kind, job.ident, ErrorCode.BUSY,
                         f"the service stopped before creating map {job.map_name!r}; put "
                         "again once it is back")
            return False
        if job.op == "cam":
            job.apply(rt)
            return False
        return rt.journal_only(job.op, job.ident, job.payload)

    def _reject(self, map_name: str, kind: EventKind, ident: Any, code: ErrorCode,
                message: str) -> None:
        rt = self.maps.get(map_name)
        if rt is not None:
            rt.stats.count("rejected")
        self._publish_event(map_name, kind, {"id": ident, "code": code.value,
                                             "message": message})

    def relocalize_payload(self, rt: MapRuntime, payload: bytes, queued_s: float) -> bytes:
        """RelocalizeRequest bytes -> RelocalizeReply bytes, on a worker process (worker_mode
        "process") or in this thread; a failure raises as :func:`handlers.relocalize` does
        (ProtocolError with the worker's code). Called from a relocalize pool thread (Zenoh
        queries, the ROS 2 bridge)."""
        if self.processes is None:
            return handlers.relocalize(rt, payload, queued_s=queued_s)
        answer = self.processes.relocalize(rt.name, payload, queued_s)
        if answer.error:
            error = wire.decode_error_reply(answer.payload)
            raise ProtocolError(error.code, error.message)
        rt.stats.record_relocalize(answer.ok, answer.total_s)
        return answer.payload

    def _relocalize(self, rt: MapRuntime, query: PendingQuery, queued_s: float) -> None:
        try:
            query.reply(self.relocalize_payload(rt, query.payload, queued_s))
        except Exception as exc:
            rt.stats.count("errors")
            query.reply_err(error_reply(exc))
        finally:
            query.finish()

    def _copy_after_writes(self, rt: MapRuntime, query: PendingQuery) -> None:
        rt.wait_snapshot()
        self._control(rt, QueryKind.KEYFRAMES, query)

    def _control(self, rt: MapRuntime, kind: QueryKind, query: PendingQuery) -> None:
        try:
            if kind is QueryKind.STATUS:
                query.reply(handlers.status(rt, query.payload))
            elif kind is QueryKind.TRAIN:
                query.reply(handlers.train(rt, query.payload))
            elif kind is QueryKind.KEYFRAMES:
                images = query.parameters.get("image", "false").lower() in ("true", "1", "yes")
                for kf_id, payload in handlers.keyframe_infos(rt, images=images):
                    key = wire.keys.keyframe(self.prefix, rt.name, kf_id)
                    if query.wants(key):
                        query.reply(payload, key)
            elif kind is QueryKind.CAMERAS:
                for camera_id, payload in handlers.camera_puts(rt):
                    key = wire.keys.camera(self.prefix, rt.name, camera_id)
                    if query.wants(key):
                        query.reply(payload, key)
        except Exception as exc:
            rt.stats.count("errors")
            query.reply_err(error_reply(exc))
        finally:
            query.finish()


class _NoCameras:
    """The camera registry of a map that does not exist yet (validating its first put)."""

    def __init__(self, name: str, limits: wire.Limits) -> None:
        self.name = name
        self.limits = limits

    def camera(self, camera_id: str) -> None:
        return None

    def camera_ids(self) -> list[str]:
        return []


@dataclass(frozen=True)
class _WriteJob:
    """A queued keyframe or camera write: applied by its map's writer, or (at shutdown)
    journaled without being applied."""

    service: Service
    map_name: str
    kind: EventKind
    ident: Any
    apply: Callable[[MapRuntime], None]
    op: str                  # "kf", "del" or "cam"
    payload: bytes | None

    def __call__(self, _queued: float) -> None:
        self.service._run_write(self)

    def journal_only(self) -> bool:
        return self.service._journal_write(self)


def _left(deadline: float, share: float = 1.0) -> float:
    """``share`` of the seconds left until ``deadline`` (0 when past)."""
    return max(0.0, deadline - time.monotonic()) * share


def serve(conf: ServiceConf) -> int:
    """Run a service for ``conf`` until SIGINT/SIGTERM; the exit status. The signal handlers
    are installed first, so a signal during start-up (restoring maps) still stops cleanly.

    Once stopped (everything journaled and closed), a thread still running (a training job
    inside OpenCV, a snapshot past the budget) would be killed by the interpreter's exit in
    native code, which aborts the process ("exception not rethrown"): the process then
    leaves with ``os._exit`` instead."""
    stop = stop_on_signals()
    service = Service(conf)
    try:
        service.start(wait_ready=False)   # small maps are served while big ones replay
    except BaseException:
        service.stop(final_snapshot=False)
        raise
    service.start_workers_in_background()   # the first query does not wait for them
    service.run_forever(stop)
    # a restore stops at its next journal record; a snapshot load cannot: left to os._exit
    if not service.wait_ready(timeout=conf.service.stop_timeout_s):
        log.warning("a map restore was still running at exit")
    _exit_if_threads_linger(0)
    return 0


def _exit_if_threads_linger(code: int) -> None:
    """``os._exit(code)`` (after flushing logs and stdio) if a Python thread still runs (ours,
    or zenoh-python's callback threads, which block inside Rust)."""
    lingering = [t.name for t in threading.enumerate()
                 if t is not threading.current_thread() and t.is_alive()
                 and not isinstance(t, threading._DummyThread)]  # type: ignore[attr-defined]
    if not lingering:
        return
    ours = [name for name in lingering if "pyo3" not in name]
    log.log(logging.WARNING if ours else logging.DEBUG, "exiting without waiting for %s",
            ", ".join(sorted(lingering)))
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)

