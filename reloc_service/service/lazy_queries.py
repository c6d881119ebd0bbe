"""The queries of a service with a memory budget (``[service] max_resident_mb``), whose maps
may be dormant (on disk only) or resident (:class:`LazyQueries`): a relocalize query holds its
map resident while it runs, a status of a dormant map answers from its storage, any other
query loads its map first."""

from __future__ import annotations

from collections.abc import Callable

from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode

from . import handlers
from .codec import error_reply
from .config import ServiceConf
from .registry import MapRegistry
from .residency import dormant_status
from .runtime import MapRuntime
from .workers import WorkerPool
from .zenoh_io import PendingQuery, QueryKind


class LazyQueries:
    """What the service does first with a query on a map of its memory budget (:meth:`take`):
    ``relocalize`` answers a relocalize query on a resident map, ``on_query`` dispatches any
    other query on a resident map (the service's own ways)."""

    def __init__(self, conf: ServiceConf, registry: MapRegistry, *,
                 relocalize_pool: WorkerPool, control_pool: WorkerPool,
                 relocalize: Callable[[MapRuntime, PendingQuery, float], None],
                 on_query: Callable[[str, QueryKind, PendingQuery], None]) -> None:
        if registry.residency is None:
            raise ValueError("expected the registry of a service with a memory budget "
                             "([service] max_resident_mb > 0)")
        self.conf = conf
        self.registry = registry
        self.residency = registry.residency
        self.maps = registry.maps
        self.relocalize_pool = relocalize_pool
        self.control_pool = control_pool
        self._relocalize = relocalize
        self.on_query = on_query

    def take(self, map_name: str, kind: QueryKind, query: PendingQuery) -> bool:
        """A query on a map that may not be resident (``max_resident_mb``): the status of a
        dormant map answers from its storage; a relocalize query holds its map resident
        while it runs, waiting ``cold_load_wait_s`` for a load (then "busy" with a retry
        hint); any other query on a dormant map loads it, then goes its usual way. False
        when the query goes its usual way now."""
        residency = self.registry.residency
        assert residency is not None
        if not residency.known(map_name):
            return False
        if kind is QueryKind.RELOCALIZE:
            if not self.relocalize_pool.submit(
                    lambda queued: self._relocalize_held(map_name, query, queued)):
                query.reply(handlers.busy_reply(
                    f"all {self.conf.service.workers} workers busy and "
                    f"{self.conf.service.queue_size} queries waiting; retry later"))
                query.finish()
            return True
        if map_name in self.maps:
            return False
        job = (self._dormant_status if kind is QueryKind.STATUS
               else self._load_then_dispatch)
        if not self.control_pool.submit(lambda _queued: job(map_name, kind, query)):
            query.reply_err(wire.encode_error(ErrorCode.BUSY, "control queue full; retry"))
        return True

    def _cold_busy(self, map_name: str) -> str:
        wait = self.conf.service.cold_load_wait_s
        return (f"map {map_name!r} is being loaded from storage (not resident; waited "
                f"{wait:g} s); retry in a few seconds")

    def _relocalize_held(self, map_name: str, query: PendingQuery, queued_s: float) -> None:
        residency = self.registry.residency
        assert residency is not None
        try:
            rt = residency.acquire(map_name, self.conf.service.cold_load_wait_s)
        except Exception as exc:   # its load failed: STORAGE_ERROR with the reason
            query.reply_err(error_reply(exc))
            query.finish()
            return
        if rt is None:
            query.reply(handlers.busy_reply(self._cold_busy(map_name)))
            query.finish()
            return
        try:
            self._relocalize(rt, query, queued_s)
        finally:
            residency.release(map_name)

    def _dormant_status(self, map_name: str, kind: QueryKind, query: PendingQuery) -> None:
        try:
            rt = self.maps.get(map_name)   # loaded meanwhile: its own status
            reply = rt.status() if rt is not None else dormant_status(self.registry, map_name)
            query.reply(handlers.with_counters(reply, self.residency.memory_counters()).encode())
        except Exception as exc:
            query.reply_err(error_reply(exc))
        finally:
            query.finish()

    def _load_then_dispatch(self, map_name: str, kind: QueryKind, query: PendingQuery) -> None:
        residency = self.registry.residency
        assert residency is not None
        try:
            rt = residency.acquire(map_name, self.conf.service.cold_load_wait_s)
        except Exception as exc:
            query.reply_err(error_reply(exc))
            query.finish()
            return
        if rt is None:
            query.reply_err(wire.encode_error(ErrorCode.BUSY, self._cold_busy(map_name)))
            query.finish()
            return
        residency.release(map_name)
        self.on_query(map_name, kind, query)   # resident now: its usual way
