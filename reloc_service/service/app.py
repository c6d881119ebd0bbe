"""The service: maps, worker pools, the maps' writers and the Zenoh layer, started and stopped
together. :class:`Service` holds the life cycle and the dispatch; the served maps and their
restore are its :class:`~.registry.MapRegistry`'s, the writers and puts its
:class:`~.writes.Writes`'.

Zenoh callbacks only enqueue (:class:`Service` is the :class:`~.zenoh_io.Dispatcher`):
relocalize queries go to a bounded pool of worker threads (full: "busy" at once), each
answering on the maps themselves (``service.worker_mode = "thread"``) or handing the request
to a worker process holding replicas of them (``"process"``, the default: :mod:`.processes`), status /
train / map-copy queries to a small control pool, and keyframe and camera puts to their map's
queue in the writer pool, which journals then applies each map's puts in arrival order (a
bounded pool shared by the maps, so one map's snapshot or training holds up at most one of
its threads and 300 maps need no more threads than one: :mod:`.writes`).

Stopping is bounded by ``service.stop_timeout_s``: puts still queued are validated and
journaled without being applied (the replay at the next start applies them), a final snapshot
is taken only within what is left of the budget, and the process exits without waiting for
threads that may still be inside native code (see :func:`.serve.serve`).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode, EventKind, ProtocolError

from ..algorithms.relocalizers.overlap import close_helpers
from ..core.errors import ConfigError
from ..core.numeric import limit_blas_threads
from ..engine import EngineConf, MappingConf
from . import handlers
from .codec import error_reply
from .config import ServiceConf
from .divergence import DivergenceWatch
from .lazy_queries import LazyQueries
from .processes import EngineSpec, ProcessWorkers
from .registry import MapRegistry
from .replication import Bootstrap, Peers
from .runtime import MapRuntime
from .transfer import Transfers
from .warm import expected_growth, warm_in_background
from .workers import Lane, WorkerPool, seconds_left, stop_on_signals
from .writes import Writes
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
                                      mapping=MappingConf.from_options(conf.mapping),
                                      stored=conf.service.stored_parts())
        self._stopped = threading.Event()
        self._starter: threading.Thread | None = None
        self.registry = MapRegistry(conf, self.engine_conf, self.methods, limits=self.limits,
                                    stopped=self._stopped, publish=self._publish_event,
                                    declare=self._declare,
                                    declare_created=self._declare_created,
                                    declare_failed=self._declare_failed)
        #: The served maps by name (the registry's table, read-only here).
        self.maps: dict[str, MapRuntime] = self.registry.maps
        self.writes = Writes(conf, self.registry, prefix=self.prefix, limits=self.limits,
                             stopped=self._stopped, publish=self._publish_event)
        self.session: Any = None
        self.layer: ZenohLayer | None = None
        self.ros2: Any = None     # the ROS 2 bridge ([ros2] enabled)
        self.relocalize_pool: WorkerPool | None = None
        #: The worker processes (worker_mode "process"); they start with the first query.
        self.processes: ProcessWorkers | None = None
        self.control_pool: WorkerPool | None = None
        #: The first way of every query under a memory budget (``max_resident_mb``).
        self.lazy: LazyQueries | None = None
        #: Compares the served maps with the peers serving them (a replica's).
        self.watch: DivergenceWatch | None = None
        self.started_at = time.monotonic()
        #: Maps exported and imported over Zenoh as one file (:mod:`.transfer`).
        self.transfers = Transfers(self.storage, self.registry, self.limits)

    # -- life cycle ------------------------------------------------------------------------------
    def start(self, *, wait_ready: bool = True) -> Service:
        """Open Zenoh, then restore stored maps and create configured ones one by one, the
        cheapest first, declaring each as soon as it is ready (a map being restored is not
        declared: no reply rather than a stale one). With ``wait_ready`` (the default), return
        once every map is up; ``reloc serve`` does not wait, so small maps are served while a
        big journal replays. A map whose storage does not restore is failed, not fatal."""
        self.registry.check_methods()
        if self.conf.service.opencv_threads:
            import cv2

            cv2.setNumThreads(self.conf.service.opencv_threads)
        limit_blas_threads(self.conf.service.blas_threads)
        names = self.registry.maps_to_restore()
        s = self.conf.service
        self.relocalize_pool = WorkerPool("relocalize", workers=s.workers,
                                          queue_size=s.queue_size)
        if s.worker_mode == "process":
            self.processes = ProcessWorkers(s.workers, EngineSpec.of(
                self.methods, self.conf.options, self.conf.mapping, self.limits,
                {name: self.conf.mapping_for(name) for name in self.registry.map_engine_confs}))
            self.registry.processes = self.processes
            if self.registry.residency is not None:   # their own memory counts too
                self.processes.on_started = self.registry.residency.count_workers_baseline
        # the queries run here (with worker processes, those before the workers hold their
        # map): their kernels load meanwhile, not in the first one; with a memory budget,
        # once the service's own memory before it is measured (:meth:`_start_lazily`)
        residency = self.registry.residency
        if residency is None:
            warm_in_background()
        self.control_pool = WorkerPool("control", workers=1, queue_size=CONTROL_QUEUE)
        if residency is not None:
            self.lazy = LazyQueries(self.conf, self.registry,
                                    relocalize_pool=self.relocalize_pool,
                                    control_pool=self.control_pool,
                                    relocalize=self._relocalize, on_query=self.on_query)
        self.writes.open()
        if self.registry.residency is not None:   # a map with puts queued stays resident
            pool = self.writes.pool
            assert pool is not None
            self.registry.residency.pending_writes = pool.pending
            self.registry.residency.on_change = self._resident_changed
        else:
            self.registry.expect(names)
        self.session = open_session(self.conf.zenoh)
        self.writes.peers = Peers(self.session, self.prefix, self.instance, self.limits)
        self.layer = ZenohLayer(self.session, self.prefix, self.instance, self)
        if self.storage is not None:
            self.layer.serve_imports()
        if self.conf.ros2.enabled:   # imported here: rosbags and xxhash are the extra 'ros2'
            from .ros2.bridge import Ros2Bridge

            self.ros2 = Ros2Bridge(self, self.conf.ros2)
        if s.bootstrap_from_peers:   # a replica copies peers' maps once its own are restored
            self._bootstrap(names)
            if s.replica_check_s > 0:
                self.watch = DivergenceWatch(self.session, self.prefix, self.instance,
                                             self.maps, interval_s=s.replica_check_s,
                                             writer_for=self.writes.writer_for)
                self.watch.start()
        elif residency is not None:   # each map loads on its first use
            self._start_lazily(names)
        else:
            self.registry.load_in_background(names)
            if wait_ready:
                self.wait_ready()
        log.info("reloc service %s under %r (zenoh %s, listen %s, connect %s): %s",
                 self.instance, self.prefix, self.conf.zenoh.mode,
                 list(self.conf.zenoh.listen), list(self.conf.zenoh.connect),
                 f"serving {sorted(self.maps) or 'no map yet'}" if self.registry.ready
                 else f"restoring {len(names)} maps, each served once ready")
        return self

    def _start_lazily(self, names: list[str]) -> None:
        """Declare ``names`` without loading them, counting the process's own memory before
        the warm-up and what the warm-up will add; then start the warm-up (measured again
        at its end: :meth:`.residency.Residency.settle_service_baseline`)."""
        residency = self.registry.residency
        assert residency is not None
        try:
            self.registry.register_lazily(names,
                                          warm_up_growth=expected_growth(self.storage))
        except ConfigError:
            self.stop(final_snapshot=False)   # the budget cannot hold this process
            raise
        warm_in_background(residency.settle_service_baseline)

    def _bootstrap(self, names: list[str]) -> None:
        """Restore ``names``, copy the peers' maps into them, then declare them. Subscribed
        already: live puts buffer in the writer queues meanwhile."""
        self.registry.load(names, declare=False)
        assert self.writes.writer is not None
        bootstrap = Bootstrap(self.session, self.prefix, self.maps, gate=self.writes.writer,
                              writer_for=self.writes.writer_for, instance=self.instance)
        self.writes.bootstrap = bootstrap
        bootstrap.run()
        for name in sorted(self.maps):
            self._declare(name)
        for rt, fields in bootstrap.refusals:   # said once the map's events are declared
            rt.publish(EventKind.REPLICA_DIVERGED, **fields)

    def wait_ready(self, timeout: float | None = None) -> bool:
        """Wait until every map found at start is served (or failed); False on timeout."""
        return self.registry.wait_ready(timeout)

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
        if self.watch is not None:
            self.watch.close()
        if self.layer is not None:
            self.layer.withdraw()          # clients see the maps go; no more puts arrive
        journaled = self.writes.flush(deadline)
        for pool in (self.relocalize_pool, self.control_pool):
            if pool is not None:           # queued queries finish; new ones get "busy"
                pool.close(timeout=seconds_left(deadline, share=0.5))
        if self.processes is not None:
            self.processes.close()   # a start after this returns at once
        if self._starter is not None:   # its last log line is written before serve's exit
            self._starter.join(timeout=seconds_left(deadline, share=0.25))
        # the queries are done: their helper threads (thread-mode workers) end here
        close_helpers(timeout=seconds_left(deadline, share=0.25))
        self.transfers.close()
        self.registry.close(final_snapshot=final_snapshot, deadline=deadline)
        if self.layer is not None:
            self.layer.close()
        if self.session is not None and not self.session.is_closed():
            self.session.close()
        log.info("reloc service %s stopped in %.1f s (%d queued puts journaled, applied at the "
                 "next start)", self.instance, time.monotonic() - start, journaled)

    def start_workers_in_background(self) -> None:
        """Start the relocalize worker processes (worker_mode "process") on a thread once
        every map is restored (each worker loads them all), so that the first query does not
        wait for them; without this they start after the first query's answer. No-op in
        thread mode, and with maps loaded on first use (``max_resident_mb``): no map is held
        at start then, and the workers' spawn and imports (seconds of CPU) would only slow
        the first query's cold load and answer, which the service makes itself anyway."""
        if self.processes is not None and self.registry.residency is None:
            self._starter = threading.Thread(target=self._start_workers, name="start-workers",
                                             daemon=True)
            self._starter.start()

    def _start_workers(self) -> None:
        while not self.wait_ready(timeout=0.2):   # a stop during the restore ends the wait
            if self._stopped.is_set():
                return
        assert self.processes is not None
        try:
            self.processes.start()
        except Exception as exc:   # the first query tries again and reports it
            if self._stopped.is_set():   # stopped meanwhile: its maps' files went with it
                log.debug("worker processes not started, the service is stopping: %s", exc)
            else:
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
        return self.writes.wait_idle(timeout)

    def _writer_for(self, map_name: str) -> Lane | WorkerPool:
        """Where the writes of ``map_name`` queue (tests hold it to fill its queue)."""
        return self.writes.writer_for(map_name)

    # -- declarations (the registry calls these as maps come and fail) ----------------------------
    def _declare(self, name: str) -> None:
        """Declare map ``name`` (queryables, events, liveliness; ROS 2 nodes if enabled), then
        publish what its restore skipped, if anything."""
        if self.layer is None or self._stopped.is_set():
            return
        self.layer.serve_map(name)
        rt = self.maps.get(name)
        if rt is None:   # dormant (loaded on first use) or failed
            return
        self.layer.set_resident(name, True)
        if self.ros2 is not None:
            self.ros2.serve_map(name)
        if rt.restore_report.damaged and not rt.replaying:   # else once it has replayed
            rt.publish(EventKind.STORAGE_DAMAGED, **rt.restore_report.event_fields())

    def _declare_created(self, name: str) -> None:
        """Declare a map its first put created (queryables, events, liveliness, ROS 2)."""
        if self.layer is not None:
            self.layer.serve_map(name)
            self.layer.set_resident(name, True)
        if self.ros2 is not None:
            self.ros2.serve_map(name)

    def _resident_changed(self, name: str, resident: bool) -> None:
        """A map was loaded into memory or closed (``[service] max_resident_mb``)."""
        if self.layer is not None and not self._stopped.is_set():
            self.layer.set_resident(name, resident)

    def _declare_failed(self, name: str, message: str) -> None:
        """Publish why map ``name`` failed, then declare its queryables: they answer
        STORAGE_ERROR with ``message``."""
        self._publish_event(name, EventKind.STORAGE_DAMAGED, {"failed": True,
                                                              "message": message})
        if self.layer is not None and not self._stopped.is_set():
            self.layer.serve_map(name)

    def _publish_event(self, map_name: str, kind: EventKind, fields: dict[str, Any]) -> None:
        payload = wire.Event(kind, map_name, time.time(), fields).encode()
        if self.layer is not None and map_name in self.maps:
            self.layer.publish_event(map_name, payload)
        elif self.session is not None and not self.session.is_closed():
            self.session.put(wire.keys.events(self.prefix, map_name), payload)

    # -- dispatcher (called in Zenoh threads: enqueue only) --------------------------------------
    def on_keyframe_sample(self, map_name: str, kf_id: int, payload: bytes | None) -> None:
        self.writes.keyframe_sample(map_name, kf_id, payload)

    def on_camera_sample(self, map_name: str, camera_id: str, payload: bytes | None) -> None:
        self.writes.camera_sample(map_name, camera_id, payload)

    def on_bad_key(self, key: str, problem: str, code: ErrorCode = ErrorCode.BAD_NAME) -> None:
        self.writes.refuse_sample(key, problem, code)

    def on_query(self, map_name: str, kind: QueryKind, query: PendingQuery) -> None:
        if kind is QueryKind.IMPORT:     # the map need not be served (yet)
            self.transfers.on_import(map_name, query)
            return
        if self.lazy is not None and self.lazy.take(map_name, kind, query):
            return
        if kind is QueryKind.EXPORT and map_name in self.maps:
            self.transfers.on_export(map_name, query)
            return
        rt = self.maps.get(map_name)
        if rt is None:  # undeclared meanwhile, or its storage did not restore
            failure = self.registry.failed.get(map_name)
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
            if rt.replaying:   # a copy holds the whole map or nothing
                query.reply_err(wire.encode_error(
                    ErrorCode.BUSY, f"{rt.replay_note()}; retry once its status no longer "
                    "says replaying"))
                return
            # Answered by the writer after the puts already received, so a replica that
            # subscribed before asking (bootstrap_from_peers) misses none of them.
            if not self.writes.writer_for(map_name).submit(
                    lambda _queued: self._copy_after_writes(rt, query)):
                rt.stats.count("busy")
                query.reply_err(wire.encode_error(ErrorCode.BUSY, "writer queue full; retry"))
            return
        assert self.control_pool is not None
        if not self.control_pool.submit(lambda _queued: self._control(rt, kind, query)):
            rt.stats.count("busy")
            query.reply_err(wire.encode_error(ErrorCode.BUSY, "control queue full; retry"))

    def _memory_counters(self) -> dict[str, int]:
        """The memory budget's figures every status carries (``max_resident_mb`` > 0)."""
        residency = self.registry.residency
        return {} if residency is None else residency.memory_counters()

    # -- query jobs (worker threads) -------------------------------------------------------------
    def relocalize_payload(self, rt: MapRuntime, payload: bytes, queued_s: float) -> bytes:
        """RelocalizeRequest bytes -> RelocalizeReply bytes, on a worker process (worker_mode
        "process") or in this thread; a failure raises as :func:`handlers.relocalize` does
        (ProtocolError with the worker's code), but a camera unknown while the map replays
        its journal is BUSY (:func:`handlers.camera_not_replayed`). Called from a relocalize
        pool thread (Zenoh queries, the ROS 2 bridge)."""
        replaying = rt.replaying   # read first: a replay ending meanwhile may put the camera
        try:
            return self._relocalize_payload(rt, payload, queued_s)
        except ProtocolError as exc:
            if replaying and exc.code is ErrorCode.UNKNOWN_CAMERA:
                raise handlers.camera_not_replayed(rt, payload) from exc
            raise

    def _relocalize_payload(self, rt: MapRuntime, payload: bytes, queued_s: float) -> bytes:
        if self.processes is None:
            return handlers.relocalize(rt, payload, queued_s=queued_s)
        if not self.processes.replica_ready(rt.name):
            # Answered here, as a worker's replica would answer it (:mod:`.served`), rather
            # than after the workers' start and their own load of the map: seconds after a
            # start or a cold load. Workers not started yet (or found dead) start once this
            # answer is made, not beside it: their spawn and imports would slow it down.
            rt.stats.count("relocalize_in_service")
            try:
                return handlers.relocalize(rt, payload, queued_s=queued_s)
            finally:
                self.processes.start_in_background()
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
        if not rt.wait_replayed(self._stopped):   # a copy holds the whole map, or nothing
            query.reply_err(wire.encode_error(ErrorCode.BUSY, f"map {rt.name!r} did not finish "
                                              "replaying its journal; retry"))
            query.finish()
            return
        rt.wait_snapshot()
        self._control(rt, QueryKind.KEYFRAMES, query)

    def _control(self, rt: MapRuntime, kind: QueryKind, query: PendingQuery) -> None:
        try:
            if kind is QueryKind.STATUS:
                query.reply(handlers.status(rt, query.payload, content_hash=_flag(
                    query.parameters, "content_hash"), counters=self._memory_counters()))
            elif kind is QueryKind.TRAIN:
                query.reply(handlers.train(rt, query.payload))
            elif kind is QueryKind.KEYFRAMES:
                images = _flag(query.parameters, "image")
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


def _flag(parameters: Any, name: str) -> bool:
    """Whether a query's selector parameter ``name`` is set (true, 1 or yes)."""
    return str(parameters.get(name, "false")).lower() in ("true", "1", "yes")
