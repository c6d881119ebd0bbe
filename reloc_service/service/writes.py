"""The write path: keyframe and camera puts (from the Zenoh subscriber or the ROS 2 bridge)
queued per map in a pool of writer threads shared by every map, which journal then apply each
map's puts in arrival order, and the rejected events that answer a put refused on the way (the
accepted and added events are the runtime's, :class:`~.runtime.MapRuntime`).

The maps' writes go to one :class:`~.workers.KeyedPool` of ``service.writer_threads``
threads: one map's puts run one at a time and in order, different maps' in parallel, so one
map's slow write (a snapshot's wait, a big keyframe) holds up at most one thread, and the
service's threads do not grow with its maps (a map with nothing queued holds no thread). A
shared writer (one thread) takes the puts of maps this instance does not serve (rejected, or
ignored when another instance serves them, in order) and the bootstrap's copy. At shutdown
the queued puts are journaled without being applied (:meth:`Writes.flush`); the replay at the
next start applies them.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode, EventKind, ProtocolError

from .codec import decode_camera_put, decode_keyframe_put, error_of
from .config import ServiceConf
from .registry import MapRegistry
from .replication import Bootstrap, Peers
from .runtime import MapRuntime, Publish
from .served import WriteOp
from .workers import KeyedPool, Lane, WorkerPool, seconds_left

log = logging.getLogger(__name__)

#: Distinct malformed keys remembered so that each is logged once (a flood of keys is bounded).
WARNED_KEYS = 1024


@dataclass(frozen=True)
class WriteJob:
    """A queued keyframe or camera write: applied by its map's writer, or (at shutdown)
    journaled without being applied."""

    writes: Writes
    map_name: str
    op: WriteOp
    ident: Any
    apply: Callable[[MapRuntime], None]
    payload: bytes | None

    @property
    def rejected(self) -> EventKind:
        """The event that refuses this write."""
        return (EventKind.CAMERA_REJECTED if self.op is WriteOp.CAMERA
                else EventKind.KEYFRAME_REJECTED)

    def __call__(self, _queued: float) -> None:
        self.writes.run(self)


class Writes:
    """The writers of one service and the puts queued in them (see module docstring)."""

    def __init__(self, conf: ServiceConf, registry: MapRegistry, *, prefix: str,
                 limits: wire.Limits, stopped: threading.Event, publish: Publish) -> None:
        self.conf = conf.service
        self.registry = registry
        self.prefix = prefix
        self.limits = limits
        self._stopped = stopped
        self._publish = publish
        #: Writes of maps this instance does not serve (rejected or ignored, in order) and the
        #: bootstrap's copy (created by :meth:`open`).
        self.writer: WorkerPool | None = None
        #: The served maps' writes (and those of maps their put may create), one lane per map.
        self.pool: KeyedPool | None = None
        #: The other instances under the prefix: a put on a map one of them serves is theirs.
        self.peers: Peers | None = None
        #: The copy of peers' maps at start (bootstrap_from_peers): while it runs, live
        #: keyframe puts skip what it copied.
        self.bootstrap: Bootstrap | None = None
        self._warned_keys: dict[str, None] = {}   # malformed keys already logged (bounded)

    def open(self) -> None:
        """Start the shared writer and the maps' writer pool."""
        self.writer = WorkerPool("writer", workers=1, queue_size=self.conf.writer_queue_size,
                                 max_bytes=self.conf.writer_queue_bytes)
        self.pool = KeyedPool("map-writer", workers=self.conf.writer_threads,
                              queue_size=self.conf.writer_queue_size,
                              max_bytes=self.conf.writer_queue_bytes)

    # -- samples (called in Zenoh threads: enqueue only) -----------------------------------------
    def keyframe_sample(self, map_name: str, kf_id: int, payload: bytes | None) -> None:
        """Queue a keyframe put (``payload``) or delete (None)."""
        if payload is None:
            self._enqueue(map_name, WriteOp.DELETE, kf_id, lambda rt: rt.delete_keyframe(kf_id))
        elif self.bootstrap is not None and self.bootstrap.active:
            copy = self.bootstrap
            self._enqueue(map_name, WriteOp.KEYFRAME, kf_id,
                          lambda rt: copy.put_unless_copied(rt, kf_id, payload), payload)
        else:
            self._enqueue(map_name, WriteOp.KEYFRAME, kf_id,
                          lambda rt: rt.put_keyframe(kf_id, payload), payload)

    def camera_sample(self, map_name: str, camera_id: str, payload: bytes | None) -> None:
        """Queue a camera put; a delete (None) is rejected at once."""
        if payload is None:
            self.reject(map_name, EventKind.CAMERA_REJECTED, camera_id, ErrorCode.BAD_VALUE,
                        "cameras cannot be deleted; put the camera again to change it")
            return
        self._enqueue(map_name, WriteOp.CAMERA, camera_id,
                      lambda rt: rt.put_camera(camera_id, payload), payload)

    def refuse_sample(self, key: str, problem: str, code: ErrorCode) -> None:
        """A refused sample: a rejected event on its map's events key if this instance serves
        that map (the sender listens there), else one WARNING per key naming the rule."""
        target = self._rejection_target(key)
        if target is not None:
            self.reject(*target, code, problem)
            return
        if key in self._warned_keys:
            return
        if len(self._warned_keys) >= WARNED_KEYS:
            self._warned_keys.pop(next(iter(self._warned_keys)))
        self._warned_keys[key] = None
        log.warning("ignoring a sample on %s (%s): %s (logged once per key)", key, code.value,
                    problem)

    def _rejection_target(self, key: str) -> tuple[str, EventKind, Any] | None:
        """(map, event kind, id) for a sample on ``<prefix>/<served map>/keyframes|cameras/
        <id>``; None when the map is not one this instance serves."""
        head = f"{self.prefix}/"
        parts = key[len(head):].split("/") if key.startswith(head) else []
        if len(parts) != 3 or not self.registry.known(parts[0]):
            return None
        leaf = parts[2]
        if parts[1] == "keyframes":
            canonical = (leaf.isdigit() and (leaf == "0" or not leaf.startswith("0"))
                         and int(leaf) < 2**63)
            return parts[0], EventKind.KEYFRAME_REJECTED, int(leaf) if canonical else leaf
        if parts[1] == "cameras":
            return parts[0], EventKind.CAMERA_REJECTED, leaf
        return None

    def _enqueue(self, map_name: str, op: WriteOp, ident: Any,
                 apply: Callable[[MapRuntime], None], payload: bytes | None = None) -> None:
        """Queue a write in its map's writer; BUSY at once if stopping or the queue is full."""
        job = WriteJob(self, map_name, op, ident, apply, payload)
        if self._stopped.is_set():
            self.reject(map_name, job.rejected, ident, ErrorCode.BUSY,
                        "the service is stopping; put again once it is back (or to a replica)")
        elif not self._submit(map_name, job, size=len(payload or b"")):
            self.reject(map_name, job.rejected, ident, ErrorCode.BUSY,
                        f"writer queue full ({self.conf.writer_queue_size} puts or "
                        f"{self.conf.writer_queue_bytes} bytes waiting); put again later")
        else:
            # Counted once queued: a publisher can tell from the map's status that its puts
            # reached the service (a status reply says nothing about samples still in flight,
            # Zenoh orders no query after a put).
            rt = self.registry.maps.get(map_name)
            if rt is not None:
                rt.stats.count(f"{op.name.lower()}_writes_queued")

    def reject(self, map_name: str, kind: EventKind, ident: Any, code: ErrorCode,
               message: str) -> None:
        """Publish a rejected event (``kind``) for put ``ident`` and count it on its map."""
        rt = self.registry.maps.get(map_name)
        if rt is not None:
            rt.stats.count("rejected")
        self._publish(map_name, kind, {"id": ident, "code": code.value, "message": message})

    # -- writers ---------------------------------------------------------------------------------
    def writer_for(self, map_name: str) -> Lane | WorkerPool:
        """Where the writes of ``map_name`` queue: its lane of the maps' pool if the map is
        served or may be created by this put, else the shared writer (which rejects or
        ignores, in order)."""
        assert self.writer is not None and self.pool is not None
        if not self.registry.known(map_name) and not self.conf.allow_new_maps:
            return self.writer
        return Lane(self.pool, map_name)

    def _submit(self, map_name: str, job: WriteJob, *, size: int = 0) -> bool:
        return self.writer_for(map_name).submit(job, size=size)

    def _pools(self) -> list[KeyedPool | WorkerPool]:
        return [pool for pool in (self.pool, self.writer) if pool is not None]

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Wait until the queued puts are applied."""
        deadline = time.monotonic() + timeout
        return all(pool.join(seconds_left(deadline)) for pool in self._pools())

    def flush(self, deadline: float) -> int:
        """Take the queued writes out of every writer, let each finish the write it is
        running (so the journal keeps arrival order), then journal the queued ones without
        applying them; the number journaled. Queued map copies get no reply (their gets end
        empty); the writer threads stop."""
        pools = self._pools()
        queued = [job for pool in pools for job in pool.take_queued()]
        for pool in pools:   # a running put ends within a second; a map copy may not
            if not pool.join(min(seconds_left(deadline, share=0.25), 5.0)):
                log.warning("%s: still busy at shutdown", pool.name)
        journaled = sum(self._journal_unapplied(job) for job in queued
                        if isinstance(job, WriteJob))
        for pool in pools:
            pool.close(timeout=seconds_left(deadline, share=0.25))
        return journaled

    # -- jobs (writer threads) -------------------------------------------------------------------
    def run(self, job: WriteJob) -> None:
        """A queued write, in its map's writer thread."""
        try:
            rt = self._map_for_put(job)
        except Exception as exc:
            code, message = error_of(exc)
            self.reject(job.map_name, job.rejected, job.ident, code, message)
            return
        try:
            self._apply(job, rt)
        finally:
            if rt is not None:   # the map may be closed while idle again
                self.registry.unpin(rt.name)

    def _apply(self, job: WriteJob, rt: MapRuntime | None) -> None:
        if rt is None and self.peers is not None and self.peers.serves(job.map_name):
            log.debug("put on map %s ignored: another instance serves it", job.map_name)
        elif rt is None:
            self.reject(job.map_name, job.rejected, job.ident, ErrorCode.UNKNOWN_MAP,
                        f"map {job.map_name!r} is not served and this service does not create "
                        "maps (service.allow_new_maps = false)")
        elif self._replayed(rt, job):
            job.apply(rt)
            if rt.wants_snapshot():
                rt.start_snapshot()

    def _replayed(self, rt: MapRuntime, job: WriteJob) -> bool:
        """Hold the job (and the map's later ones, queued behind it in its lane) until the
        map's journal backlog is replayed, so they apply after it, in order; False (the job
        rejected) if the replay did not complete: the service stopped, or the map failed."""
        if rt.wait_replayed(self._stopped):
            return True
        failure = self.registry.failed.get(job.map_name)
        self.reject(job.map_name, job.rejected, job.ident,
                    ErrorCode.STORAGE_ERROR if failure else ErrorCode.BUSY,
                    failure or f"the service stopped while map {job.map_name!r} was "
                    "replaying its journal; put again once it is back")
        return False

    def _map_for_put(self, job: WriteJob) -> MapRuntime | None:
        """The runtime of the job's map; created (and served) if new maps are allowed and the
        put decodes and validates (ProtocolError otherwise: garbage on a new name leaves
        nothing on disk). A delete never creates a map. A map being restored refuses puts
        (BUSY), a failed one too (STORAGE_ERROR)."""
        name = job.map_name
        rt = self.registry.pin(name)   # loaded first if it is stored but not resident
        if rt is not None:
            return rt
        self.registry.check_restored(name)
        if not self.conf.allow_new_maps or self._stopped.is_set():
            return None
        if job.payload is None:
            raise ProtocolError(ErrorCode.UNKNOWN_MAP,
                                f"map {name!r} does not exist; a delete does not create it")
        self._validate_first_put(job, job.payload)
        self.registry.create(name)
        return self.registry.pin(name)

    def _validate_first_put(self, job: WriteJob, payload: bytes) -> None:
        """Decode a put on a map that does not exist yet, as the new map would (no camera
        registered: a keyframe needs an inline camera); ProtocolError if it would fail."""
        wire.check_name(job.map_name)
        if job.op is WriteOp.CAMERA:
            decode_camera_put(job.ident, payload, self.limits)
        else:
            decode_keyframe_put(_NoCameras(job.map_name, self.limits), job.ident, payload)

    def _journal_unapplied(self, job: WriteJob) -> bool:
        """At shutdown: journal a queued write without applying it (cameras are cheap and
        keyframes need them: applied). True if journaled."""
        rt = self.registry.maps.get(job.map_name)
        if rt is None:   # a put that would have created or loaded its map: refused, not lost
            doing = "loading" if self.registry.known(job.map_name) else "creating"
            self.reject(job.map_name, job.rejected, job.ident, ErrorCode.BUSY,
                        f"the service stopped before {doing} map {job.map_name!r}; put "
                        "again once it is back")
            return False
        if job.op is WriteOp.CAMERA:
            job.apply(rt)
            return False
        return rt.journal_only(job.op, job.ident, job.payload)


class _NoCameras:
    """The camera registry of a map that does not exist yet (validating its first put)."""

    def __init__(self, name: str, limits: wire.Limits) -> None:
        self.name = name
        self.limits = limits

    def camera(self, camera_id: str) -> None:
        return None

    def camera_ids(self) -> list[str]:
        return []
