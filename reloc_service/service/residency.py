"""Which stored maps are in memory (``[service] max_resident_mb`` > 0): every map on disk is
declared at start without being loaded, opened on first use (a cold load: snapshot, then its
journal backlog), and closed again when the resident maps count more than the budget, least
recently used first. A cold load first makes room for the map it brings (what the map counted
when it was last closed, else the largest of the maps known so far), so the count stays under the
budget through the load; if no map is idle within :data:`MAKE_ROOM_WAIT_S` it loads anyway and
the idle ones are closed once they are.

What a map counts is what the quotas count for it (:class:`~.quotas.MapUsage`: its keyframes'
images as held, depth and features) and what its relocalizers hold beside the map (the
whole-map landmark pools, :meth:`~reloc_service.engine.Engine.held_bytes`, about 80 MB per
1000 keyframes); until its pools are made, what they will hold and what making them holds
at its peak, estimated from its keyframes (:mod:`.pool_reserve`), so the evictor makes room
for them before they are built (:meth:`Residency.counted`). A 1000-keyframe map
counts 343 MB; its resident memory is 258 MB once its pools are made, 272 MB after queries,
at most 350 MB while the pools are made (docs/performance.md). With ``worker_mode =
"process"`` every worker process holds a replica of each resident map (its own engine, pools
included), so a resident map counts once per copy: ``1 + workers`` times.

The processes' own memory counts too, and what their workers' queries hold while they run
(:mod:`.memory_baseline`): the maps get ``max_resident_mb`` minus that baseline.

A map is never closed while it is in use: a query or a write holds it (:meth:`Residency.acquire`
... :meth:`Residency.release`), puts wait in its writer lane, a training job, snapshot or
journal replay runs, or it journaled puts it has not applied. Closing takes its final
snapshot, closes its journal and gives back its directory lock, so an idle map holds no file
(with ``worker_mode = "process"`` each worker process drops its replica too);
its usage is kept, so quotas on the total still count it. A map whose load fails is failed as
at start (its queries get STORAGE_ERROR with the reason).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from reloc_client import protocol as wire

from ..core.errors import StorageError
from .config import LimitsConf
from .durability import read_service_file
from .map_dirs import map_dirname
from .memory import release_memory, rss_bytes, trim_now
from .memory_baseline import ProcessBaseline, query_working_bytes
from .pool_reserve import PoolReserve
from .quotas import MapUsage

if TYPE_CHECKING:
    from .config import ServiceConf
    from .runtime import MapRuntime

log = logging.getLogger(__name__)

#: Seconds a cold load waits for a resident map to become idle so it can close it first.
MAKE_ROOM_WAIT_S = 5.0

MB = 1024 * 1024


class MapRegistry(Protocol):
    """What :class:`Residency` uses of the service's :class:`~.registry.MapRegistry`."""

    conf: ServiceConf
    storage: Path | None
    methods: tuple[str, ...]
    maps: dict[str, MapRuntime]
    failed: dict[str, str]

    def load_resident(self, name: str) -> None: ...

    def close_resident(self, name: str, *, timeout: float) -> None: ...

    def calibration_sigma(self, name: str) -> dict[str, float]: ...


class Residency(ProcessBaseline):
    """The resident and dormant maps of a :class:`~.registry.MapRegistry` (see module
    docstring). Its lock is taken inside no other; the registry's maps table is changed
    under it only by single dict operations."""

    registry: MapRegistry

    def __init__(self, registry: MapRegistry, *, budget_mb: float, stop_timeout_s: float,
                 copies: int = 1, workers: int = 0,
                 max_image_pixels: int = LimitsConf.max_image_pixels,
                 pending_writes: Callable[[str], int] | None = None) -> None:
        if copies < 1:
            raise ValueError(f"expected copies >= 1 of each resident map, got {copies}")
        self.registry = registry
        #: ``max_resident_mb``: the whole service's budget (processes and maps), bytes.
        self.total_budget = int(budget_mb * MB)
        #: The resident memory of the service's process with no map, and of its worker
        #: processes and their forkserver once they start (bytes; 0 until measured).
        self.baseline_service = 0
        self.baseline_workers = 0
        #: What the ``workers`` queries answered at once, each of at most
        #: ``max_image_pixels``, hold while they run (bytes).
        self.baseline_queries = max(0, workers) * query_working_bytes(max_image_pixels)
        #: What the resident maps may count: the total budget minus the baseline.
        self.budget = max(1, self.total_budget - self.baseline_queries)
        #: How many processes hold each resident map: the service's, and one replica per
        #: worker process (worker_mode "process"); each copy counts against the budget.
        self.copies = copies
        self.stop_timeout_s = stop_timeout_s
        #: Jobs queued in a map's writer lane (the service sets it once its writers exist).
        self.pending_writes = pending_writes
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)   # a load or close ended
        self.dormant: set[str] = set()                   # on disk, declared, not loaded
        self._loading: set[str] = set()
        self._closing: set[str] = set()
        self._lru: collections.OrderedDict[str, None] = collections.OrderedDict()
        self._pins: collections.Counter[str] = collections.Counter()
        #: The usage of each closed map (quotas on the total still count it).
        self.kept_usage: dict[str, MapUsage] = {}
        #: What each closed map's relocalizers held beside it (its next load's estimate).
        self.kept_held: dict[str, int] = {}
        #: What each resident map was expected to count (one copy) when its load began: it
        #: counts at least that until its pools are made (:meth:`counted`); a map leaves
        #: this table once its pools are seen made (:meth:`note_prepared`).
        self._expected: dict[str, int] = {}
        #: What pools not made yet count, per keyframe (:mod:`.pool_reserve`).
        self.pool_reserve = PoolReserve()
        self._load_slot = threading.Semaphore(1)   # one cold load at a time: bounded memory
        #: Set once the service's warm-up has ended (its baseline measured, or estimated
        #: when a map was resident then); loads do not wait for it.
        self.baseline_settled = threading.Event()
        self._declared = False   # count_service_baseline ran (the maps are declared)
        self._warmed = False     # settle_service_baseline ran (the warm-up ended)
        #: The service's resident memory when the maps were declared (before its warm-up).
        self.declared_rss = 0
        #: What the service's warm-up was expected to add to its memory at declaration (bytes).
        self.growth_estimate = 0
        self._wake = threading.Event()
        self._stopped = threading.Event()
        self._evictor = threading.Thread(target=self._evict_loop, name="map-evictor",
                                         daemon=True)
        self.loads = 0
        self.evictions = 0
        #: The largest count of the resident maps seen after a load (bytes).
        self.peak_bytes = 0
        #: Told ``(name, True)`` when a map is loaded, ``(name, False)`` when it is closed
        #: (the service's residency tokens); called outside this object's lock.
        self.on_change: Callable[[str, bool], None] | None = None

    # -- start / stop ----------------------------------------------------------------------------
    def register(self, names: list[str], declare: Callable[[str], None]) -> None:
        """Declare ``names`` (stored or configured maps) as served, without loading them."""
        with self._lock:
            self.dormant.update(names)
        for name in names:
            declare(name)
        self._evictor.start()

    def close(self) -> None:
        """Stop closing maps (the registry closes the resident ones)."""
        self._stopped.set()
        self._wake.set()
        with self._lock:
            self._changed.notify_all()

    # -- reading ---------------------------------------------------------------------------------
    def known(self, name: str) -> bool:
        """Served here: resident, loading, closing or dormant."""
        return (name in self.registry.maps or name in self.dormant or name in self._loading
                or name in self._closing)

    def served_count(self) -> int:
        """Maps served here, resident or not."""
        with self._lock:
            return len(set(self.registry.maps) | self.dormant | self._loading | self._closing)

    def resident_bytes(self) -> int:
        """What the resident maps count: their usage totals and what their relocalizers
        hold beside them, once per process holding them (:attr:`copies`)."""
        return self.copies * sum(self.counted(n, rt)
                                 for n, rt in list(self.registry.maps.items()))

    def counted(self, name: str, rt: MapRuntime) -> int:
        """What one copy of resident map ``name`` counts: :func:`counted_bytes`, and while
        its pools are being made, its keyframes and the reserve of its pools
        (:meth:`.pool_reserve.PoolReserve.reserve`, or what they hold if more), at least
        what its load expected it to count. A loaded map's pools come a few seconds after
        its load: counted only once made, they let the next loads in over the budget (the
        fleet bench had three 1000-keyframe maps counted without their pools, each load
        expecting what the previous map counted before its pools were made)."""
        if rt.engine.prepared.is_set():
            return counted_bytes(rt)
        usage = rt.usage
        pools = max(rt.engine.held_bytes(), self.pool_reserve.reserve(usage.keyframes))
        return max(int(usage.total) + pools, self._expected.get(name, 0))

    def usages(self) -> list[MapUsage]:
        """The usage of every served map: resident ones' and closed ones' (as kept)."""
        with self._lock:
            kept = [u for n, u in self.kept_usage.items() if n not in self.registry.maps]
        return [rt.usage for rt in list(self.registry.maps.values())] + kept

    # -- use -------------------------------------------------------------------------------------
    def acquire(self, name: str, timeout: float | None) -> MapRuntime | None:
        """The runtime of served map ``name``, held resident until :meth:`release`; loaded
        first if it is not resident (waiting at most ``timeout`` s, None: as long as it
        takes). None when the wait timed out (the load goes on) or the map is not served
        here; StorageError if its load failed."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._lock:
            while True:
                rt = self.registry.maps.get(name)
                if rt is not None and name not in self._closing:
                    self._pins[name] += 1
                    self._lru[name] = None
                    self._lru.move_to_end(name)
                    return rt
                failure = self.registry.failed.get(name)
                if failure is not None:
                    raise StorageError(failure)
                if name not in self.dormant and name not in self._loading \
                        and name not in self._closing:
                    return None
                if self._stopped.is_set():
                    return None
                if name in self.dormant:
                    self.dormant.discard(name)
                    self._loading.add(name)
                    threading.Thread(target=self._load, args=(name,), name=f"load-{name}",
                                     daemon=True).start()
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return None
                self._changed.wait(left if left is not None else 1.0)

    def release(self, name: str) -> None:
        """``name`` is no longer used by the caller of :meth:`acquire`."""
        with self._lock:
            self._pins[name] -= 1
            if self._pins[name] <= 0:
                del self._pins[name]
                self._changed.notify_all()   # a cold load may be waiting to close it
        # the evictor closes what is over the budget and gives back what the query freed
        self._wake.set()

    def loading(self, name: str) -> bool:
        return name in self._loading

    # -- loading ---------------------------------------------------------------------------------
    def _load(self, name: str) -> None:
        start = time.perf_counter()
        try:
            with self._load_slot:
                if not self._stopped.is_set():
                    expected = self.expected_bytes(name)
                    if self.budget and expected > self.budget:
                        log.warning("map %s alone counts %.1f MB (%d copies), over the budget "
                                    "of %.1f MB: it is closed whenever it is idle", name,
                                    expected / MB, self.copies, self.budget / MB)
                    self.make_room(expected)
                    log.info("map %s: loading, %.1f MB expected (%.1f MB resident of %.1f MB: "
                             "%s)", name, expected / MB, self.resident_bytes() / MB,
                             self.budget / MB, self.accounting())
                    self._expected[name] = expected // self.copies
                    self.registry.load_resident(name)
                    # what the load read and decoded on its way (snapshot files, buffers)
                    # is freed now, but stays in the heap's arenas unless given back
                    trim_now()
        finally:
            with self._lock:
                self._loading.discard(name)
                if name in self.registry.maps:
                    self._lru[name] = None
                    self.loads += 1
                    self.peak_bytes = max(self.peak_bytes, self.resident_bytes())
                elif name not in self.registry.failed:
                    self.dormant.add(name)   # stopped meanwhile
                self._changed.notify_all()
            log.info("map %s: loaded on demand in %.2f s (%.1f MB resident of %.1f MB)", name,
                     time.perf_counter() - start, self.resident_bytes() / MB, self.budget / MB)
            self._tell(name, name in self.registry.maps)
            self._wake.set()

    def expected_bytes(self, name: str) -> int:
        """What map ``name`` will count while its pools are made (all its :attr:`copies`):
        its keyframes and pools when it was last closed, else the largest of the maps known
        here (0 when none is), and what making its pools holds at the peak
        (:mod:`.pool_reserve`). The largest, not the mean: the maps differ in size, and
        the mean let a third 1000-keyframe map into a share that holds two."""
        kept = self.kept_usage.get(name)
        if kept is not None:
            return self.copies * self._while_made(kept, self.kept_held.get(name, 0))
        known = [self._while_made(rt.usage, self._pools_made(rt))
                 for rt in list(self.registry.maps.values())]
        known += [self._while_made(u, self.kept_held.get(n, 0))
                  for n, u in list(self.kept_usage.items()) if n not in self.registry.maps]
        return self.copies * max(known) if known else 0

    def _pools_made(self, rt: MapRuntime) -> int:
        """What resident map ``rt``'s pools hold, or will once made (estimated)."""
        held = rt.engine.held_bytes()
        if rt.engine.prepared.is_set():
            return held
        return max(held, self.pool_reserve.pools(rt.usage.keyframes))

    def _while_made(self, usage: MapUsage, pools: int) -> int:
        """What one copy of a map with ``usage`` and ``pools`` (bytes, once made) counts
        while its pools are made."""
        return int(usage.total) + pools + self.pool_reserve.making(usage.keyframes)

    def note_prepared(self) -> None:
        """Measure the pools of every map whose pools were made since the last call (the
        pool rate of :attr:`pool_reserve`); their count is now what those hold."""
        with self._lock:
            preparing = [(n, self.registry.maps.get(n)) for n in list(self._expected)]
        for name, rt in preparing:
            if rt is None or not rt.engine.prepared.is_set():
                continue
            held = rt.engine.held_bytes()
            self.pool_reserve.learn(rt.usage.keyframes, held)
            self._expected.pop(name, None)
            log.info("map %s: pools made, %.1f MB for %d keyframes (%.1f MB resident of "
                     "%.1f MB: %s)", name, held / MB, rt.usage.keyframes,
                     self.resident_bytes() / MB, self.budget / MB, self.accounting())

    def accounting(self) -> str:
        """What each resident map counts (one copy), MB, for the log: ``name count
        (pools held or reserved)``."""
        parts = []
        for name, rt in list(self.registry.maps.items()):
            state = "pools made" if rt.engine.prepared.is_set() else "pools reserved"
            parts.append(f"{name} {self.counted(name, rt) / MB:.1f} ({state})")
        return ", ".join(parts) or "none"

    # -- eviction --------------------------------------------------------------------------------
    def make_room(self, incoming: int) -> int:
        """Close idle maps, least recently used first, until ``incoming`` more bytes fit the
        budget; a map in use is waited for (at most :data:`MAKE_ROOM_WAIT_S` in all). The
        number closed."""
        closed = 0
        deadline = time.monotonic() + MAKE_ROOM_WAIT_S
        while (self.budget and not self._stopped.is_set()
               and self.resident_bytes() + incoming > self.budget and self.registry.maps):
            name = self._take_idle()
            if name is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    log.warning("loading a map over the budget: no resident map became idle "
                                "within %.1f s", MAKE_ROOM_WAIT_S)
                    break
                with self._lock:
                    self._changed.wait(min(left, 0.2))
                continue
            self._close(name)
            closed += 1
        return closed

    def _evict_loop(self) -> None:
        while not self._stopped.is_set():
            self._wake.wait(1.0)
            self._wake.clear()
            try:
                self.note_prepared()
                self.enforce_budget()
                self.trim_excess()
            except Exception as exc:   # never stops evicting for one map's failure
                log.error("closing idle maps failed: %s", exc)

    def trim_excess(self) -> bool:
        """Give the free heap pages back when this process holds more than it counts (its
        baseline and one copy of each resident map); whether it trimmed. Making a map's
        pools frees about 90 MB per 1000 keyframes and queries free more, all kept in the
        C heap's arenas otherwise: the fleet bench's service held 1040 MB with two maps
        resident, which count 687 MB with its 210 MB baseline."""
        counted = self.baseline_service + self.resident_bytes() // self.copies
        if rss_bytes() <= counted:
            return False
        return trim_now()

    def enforce_budget(self) -> int:
        """Close idle maps, least recently used first, until the resident ones fit the
        budget (or none left is idle); the number closed."""
        closed = 0
        while not self._stopped.is_set() and self.resident_bytes() > self.budget:
            name = self._take_idle()
            if name is None:
                break
            self._close(name)
            closed += 1
        return closed

    def idle(self, rt: MapRuntime) -> bool:
        """Whether ``rt`` may be closed: nothing uses or changes it (see module docstring)."""
        name = rt.name
        return (self._pins[name] <= 0
                and not (self.pending_writes is not None and self.pending_writes(name))
                and rt.training_thread() is None and not rt.replaying
                and not rt.maintenance_running() and not rt.journal_ahead)

    def _take_idle(self) -> str | None:
        """The least recently used idle resident map, taken out of the maps table (queries
        and puts arriving now wait for its close, then load it again)."""
        with self._lock:
            for name in list(self.registry.maps):   # served without a use yet (an import)
                if name not in self._lru and name not in self._closing:
                    self._lru[name] = None
                    self._lru.move_to_end(name, last=False)
            for name in list(self._lru):
                rt = self.registry.maps.get(name)
                if rt is None:
                    self._lru.pop(name, None)
                    continue
                if self.idle(rt):
                    self._closing.add(name)
                    self._lru.pop(name, None)
                    return name
        return None

    def _close(self, name: str) -> None:
        """Take the final snapshot of resident map ``name``, close its journal and lock."""
        rt = self.registry.maps[name]
        try:
            self.kept_usage[name] = rt.usage
            prepared = rt.engine.prepared
            held = rt.engine.held_bytes()
            if not prepared.is_set():   # closed before its pools were made: as estimated
                held = max(held, self.pool_reserve.pools(rt.usage.keyframes))
            self.kept_held[name] = held
            self._expected.pop(name, None)
            self.registry.close_resident(name, timeout=self.stop_timeout_s)
            del rt   # this frame's reference: the map is freed below, not when _close returns
            # a pool being made holds the map until it stops (at its next keyframe or chunk)
            prepared.wait(self.stop_timeout_s)
            # the map's objects are in reference cycles, and its arrays' freed pages stay in
            # the C heap's arenas unless given back (memory.release_memory)
            release_memory()
            self.evictions += 1
            log.info("map %s: closed (idle; %.1f MB resident of %.1f MB)", name,
                     self.resident_bytes() / MB, self.budget / MB)
        finally:
            with self._lock:
                self._closing.discard(name)
                if name not in self.registry.failed:
                    self.dormant.add(name)
                self._changed.notify_all()
            self._tell(name, False)

    def _tell(self, name: str, resident: bool) -> None:
        if self.on_change is None:
            return
        try:
            self.on_change(name, resident)
        except Exception as exc:   # a token not declared never stops loading or closing
            log.warning("map %s: residency token not updated: %s", name, exc)


def resident_copies(worker_mode: str, workers: int) -> int:
    """How many processes hold each resident map: the service's own, plus one replica in each
    worker process with ``worker_mode = "process"`` (:mod:`.processes`)."""
    return 1 + workers if worker_mode == "process" else 1


def counted_bytes(rt: MapRuntime) -> int:
    """What resident map ``rt`` counts against the budget: its usage (what the quotas count)
    and its relocalizers' pools (:meth:`~reloc_service.engine.Engine.held_bytes`)."""
    return int(rt.usage.total) + rt.engine.held_bytes()


def dormant_status(registry: MapRegistry, name: str) -> wire.StatusReply:
    """The status of a map that is not resident, from what its ``service.json`` records
    (keyframes, version, cameras, identity) without loading it; its landmarks and training
    state are known once it is loaded (0 and false until then)."""
    assert registry.storage is not None
    meta: dict[str, Any] = read_service_file(registry.storage / map_dirname(name))
    methods = registry.methods
    return wire.StatusReply(
        map=name, instance=registry.conf.instance, keyframes=len(meta.get("keyframe_ids", [])),
        landmarks=0, trained=False, map_version=int(meta.get("map_version", 0)),
        methods=methods, default_method=methods[0],
        cameras=tuple(sorted(meta.get("cameras", {}))), map_id=str(meta.get("map_id") or ""),
        resident=False, calibration_sigma=registry.calibration_sigma(name))
