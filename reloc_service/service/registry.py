"""The maps a service serves, and how each comes to be served: restored from its storage at
start (the cheapest first, each declared as soon as its snapshot is loaded, then served from it
while its journal backlog replays; its puts wait for the replay), created by its first put, or
failed (its storage did not restore: its queries and puts get STORAGE_ERROR with the reason,
its files are left as they are).

The registry knows nothing of Zenoh: the service gives it the callables that declare a map
(queryables, liveliness token, ROS 2 node) and publish its events.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode, EventKind

from ..core.errors import ConfigError, StorageError
from ..engine import Engine, EngineConf, MappingConf
from ..storage.lock import DirectoryLock
from .config import ServiceConf
from .durability import RestoreInterrupted, check_storage, journal_bytes, open_engine, recover_current
from .map_dirs import map_dirname, record_map_name, stored_map_names
from .quotas import MapUsage, Quotas
from .residency import Residency, resident_copies
from .restore_verdict import judge
from .runtime import MapRuntime, Publish
from .workers import seconds_left

if TYPE_CHECKING:
    from .processes import ProcessWorkers

log = logging.getLogger(__name__)


class MapRegistry:
    """The served maps by name (:attr:`maps`), the failed ones (:attr:`failed`) and those
    still being restored.

    :attr:`maps` and :attr:`failed` are read from any thread without a lock; ``_lock``
    orders their changes (a map restored or created once, never both served and failed).
    It is taken inside no other lock of the service; under it a map created by a put is
    opened and attached to the worker processes (whose locks thus come after it)."""

    def __init__(self, conf: ServiceConf, engine_conf: EngineConf, methods: tuple[str, ...],
                 *, limits: wire.Limits, stopped: threading.Event, publish: Publish,
                 declare: Callable[[str], None], declare_created: Callable[[str], None],
                 declare_failed: Callable[[str, str], None]) -> None:
        """``declare`` makes a restored map reachable, ``declare_created`` one its first put
        created, ``declare_failed`` a failed one (with the reason); ``publish`` sends a
        map's events; ``stopped`` is set when the service stops (restoring stops too)."""
        self.conf = conf
        self.storage = conf.storage_path
        self.engine_conf = engine_conf
        #: The engine configuration of each map whose ``[maps.NAME]`` table sets its own
        #: calibration accuracy (the others have ``engine_conf``'s).
        self.map_engine_confs = {
            name: dataclasses.replace(engine_conf, mapping=MappingConf.from_options(
                conf.mapping_for(name)))
            for name, map_conf in conf.maps.items() if map_conf.mapping_overrides()}
        self.methods = methods
        self.limits = limits
        self._stopped = stopped
        self._publish = publish
        self._declare = declare
        self._declare_created = declare_created
        self._declare_failed = declare_failed
        self.maps: dict[str, MapRuntime] = {}
        #: Maps whose storage did not restore: map -> why (queries get STORAGE_ERROR with it).
        self.failed: dict[str, str] = {}
        #: The worker processes (worker_mode "process"): every map opened is attached to them.
        self.processes: ProcessWorkers | None = None
        #: The quotas every map's puts are checked against (their use is each map's).
        self.quotas = Quotas(conf.quotas, self._usages)
        #: Which maps are in memory, when ``service.max_resident_mb`` > 0 (None: every map
        #: is restored at start and stays resident).
        self.residency: Residency | None = None
        if conf.service.max_resident_mb > 0:
            self.residency = Residency(self, budget_mb=conf.service.max_resident_mb,
                                       stop_timeout_s=conf.service.stop_timeout_s,
                                       copies=resident_copies(conf.service.worker_mode,
                                                              conf.service.workers),
                                       workers=conf.service.workers,
                                       max_image_pixels=conf.limits.max_image_pixels)
        self._lock = threading.Lock()
        self._loading: set[str] = set()      # being restored: not declared yet
        self._ready = threading.Event()      # every stored and configured map is up (or failed)
        self._loader: threading.Thread | None = None
        #: The storage's lock and each opened map's, held while the service runs: no other
        #: service or writing tool changes these files meanwhile.
        self._storage_lock: DirectoryLock | None = None
        self._map_locks: dict[str, DirectoryLock] = {}

    # -- start -----------------------------------------------------------------------------------
    def check_methods(self) -> None:
        """Build every method once on an empty map: bad names or options fail at start."""
        try:
            Engine(self.engine_conf)
        except ConfigError as exc:
            raise ConfigError(f"service.methods / [options]: {exc}") from exc

    def maps_to_restore(self) -> list[str]:
        """Check the storage root, then the stored and configured maps, each once, the
        cheapest restore first (fewest journal bytes to replay)."""
        start = time.perf_counter()
        if self.storage is not None:
            check_storage(self.storage)
            self.lock_storage()
        stored = [] if self.storage is None else stored_map_names(self.storage)
        names = self._restore_order(stored + sorted(self.conf.maps))
        log.info("%d maps found in %.2f s (%d stored in %s)", len(names),
                 time.perf_counter() - start, len(stored), self.storage)
        return names

    def lock_storage(self) -> None:
        """Own the storage directory for this process's lifetime (before any map is opened);
        LockHeld naming the holder if another service (or tool) owns it."""
        assert self.storage is not None
        if self._storage_lock is None:
            self._storage_lock = DirectoryLock(self.storage, what="storage").acquire(
                "reloc serve")

    def _restore_order(self, names: list[str]) -> list[str]:
        def cost(name: str) -> int:
            return 0 if self.storage is None else journal_bytes(self.storage / map_dirname(name))

        unique = list(dict.fromkeys(names))
        return sorted(unique, key=lambda n: (cost(n), n))

    def _usages(self) -> list[MapUsage]:
        if self.residency is not None:
            return self.residency.usages()
        return [rt.usage for rt in list(self.maps.values())]

    def _served_count(self) -> int:
        if self.residency is not None:
            return self.residency.served_count()
        return len(self.maps)

    def register_lazily(self, names: list[str], *, warm_up_growth: int = 0) -> None:
        """Declare ``names`` served without loading them (each loads on first use); the
        service's own memory is counted first, with ``warm_up_growth`` (bytes) for the
        warm-up still to come (:meth:`.residency.Residency.count_service_baseline`)."""
        assert self.residency is not None
        self.residency.count_service_baseline(warm_up_growth)   # before any map is loaded
        start = time.perf_counter()
        self.residency.register(names, self._declare)
        log.info("%d maps declared in %.2f s, each loaded on its first use", len(names),
                 time.perf_counter() - start)
        self._ready.set()

    def known(self, name: str) -> bool:
        """Served here (resident or not)."""
        return name in self.maps or (self.residency is not None and self.residency.known(name))

    def pin(self, name: str) -> MapRuntime | None:
        """The runtime of served map ``name``, kept resident until :meth:`unpin` (loaded
        first if it is not: the caller waits); None if it is not served here."""
        if self.residency is None:
            return self.maps.get(name)
        return self.residency.acquire(name, None)

    def unpin(self, name: str) -> None:
        if self.residency is not None:
            self.residency.release(name)

    def load_resident(self, name: str) -> None:
        """Restore stored map ``name`` on demand (snapshot and journal backlog), then add it
        to the served maps; failed as at start if it does not restore."""
        start = time.perf_counter()
        try:
            rt = self._open_map(name)
        except Exception as exc:
            self._fail_map(name, exc)
            return
        self._replay(rt, declared=True, start=start)
        if name in self.failed or self._stopped.is_set() or rt.replaying:
            if self.processes is not None:
                self.processes.detach(rt)
        if name in self.failed:
            return
        if self._stopped.is_set() or rt.replaying:   # interrupted: the journal is untouched
            rt.close(final_snapshot=False, timeout=0.0)
            self._unlock_map(name)
            return
        self.maps[name] = rt

    def close_resident(self, name: str, *, timeout: float) -> None:
        """Close resident map ``name`` (final snapshot within ``timeout``, journal, lock):
        its files are released; it is loaded again on its next use."""
        rt = self.maps.pop(name)
        rt.engine.close()   # its pools still to be made are not
        if self.processes is not None:   # the worker processes drop their replicas
            self.processes.detach(rt)
        try:
            rt.close(final_snapshot=True, timeout=timeout)
            while rt.maintenance_running():   # a snapshot past the budget may still rotate
                rt.wait_snapshot(timeout)
        finally:
            self._unlock_map(name)

    def expect(self, names: list[str]) -> None:
        """``names`` are about to be restored: their puts get BUSY until they are served."""
        self._loading = set(names)

    def load_in_background(self, names: list[str]) -> None:
        """:meth:`load` ``names`` on a thread, declaring each map once it is up."""
        self._loader = threading.Thread(target=self.load, args=(names,),
                                        name="restore-maps", daemon=True)
        self._loader.start()

    def load(self, names: list[str], *, declare: bool = True) -> None:
        """Restore ``names`` in order; declare each one ready (``declare``) or failed at once."""
        try:
            for name in names:
                if self._stopped.is_set():
                    break
                self._bring_up(name, declare=declare)
        finally:
            self._loading.clear()
            self._ready.set()

    def wait_ready(self, timeout: float | None = None) -> bool:
        """Wait until every map found at start is served (or failed); False on timeout."""
        return self._ready.wait(timeout)

    @property
    def ready(self) -> bool:
        return self._ready.is_set()

    def reserve(self, name: str) -> None:
        """Hold ``name`` for a map about to be added to the storage (an import): its puts get
        BUSY until :meth:`serve_added` (or :meth:`release`); StorageError if it is served."""
        with self._lock:
            if self.known(name) or name in self._loading:
                raise StorageError(f"map {name!r} is served (or being restored) here; an "
                                   f"import does not replace a served map: import it under "
                                   f"another name, or stop the service and use `reloc map "
                                   f"import --replace`")
            self.failed.pop(name, None)
            self._loading.add(name)

    def release(self, name: str) -> None:
        with self._lock:
            self._loading.discard(name)

    def serve_added(self, name: str) -> None:
        """Restore and declare map ``name``, added to the storage after :meth:`reserve`;
        StorageError if it does not restore (it is failed then, as at start)."""
        self._bring_up(name, declare=True)
        if name in self.failed:
            raise StorageError(self.failed[name])

    def _bring_up(self, name: str, *, declare: bool) -> None:
        """Load ``name``'s snapshot, serve it (``declare``), then replay its journal
        backlog behind it (queries answer from what is replayed so far)."""
        start = time.perf_counter()
        try:
            rt = self._open_map(name)
        except Exception as exc:   # one map's damage never takes down the others
            self._fail_map(name, exc)
            return
        with self._lock:
            self._loading.discard(name)
            if self._stopped.is_set():
                rt.close(final_snapshot=False, timeout=0.0)
                self._unlock_map(name)
                return
            self.maps[name] = rt
        if declare:
            self._declare(name)
        self._replay(rt, declared=declare, start=start)

    def _replay(self, rt: MapRuntime, *, declared: bool, start: float) -> None:
        """Replay the journal backlog of served map ``rt``; publish what the restore skipped
        (a declared map: the declaration came before the replay found it) and start the
        training a restored map needs. A replay that fails fails the map."""
        if rt.replaying:
            log.info("map %s: served from its snapshot (%d keyframes) while %d journal "
                     "records replay", rt.name, len(rt.map_state().keyframes),
                     rt.status().counters.get("replay_records_total", 0))
        try:
            replayed = rt.replay_backlog(self._stopped)
        except RestoreInterrupted as exc:
            log.info("%s", exc)
            return
        except Exception as exc:
            with self._lock:
                self.maps.pop(rt.name, None)
            rt.close(final_snapshot=False, timeout=0.0)
            self._unlock_map(rt.name)
            self._fail_map(rt.name, exc)
            return
        if rt.store is None:   # a map without storage: nothing was restored
            return
        state = rt.map_state()
        log.info("map %s: %d keyframes restored (%d journal records replayed) in %.1f s",
                 rt.name, len(state.keyframes), replayed, time.perf_counter() - start)
        if declared and rt.restore_report.damaged:
            self._publish(rt.name, EventKind.STORAGE_DAMAGED,
                          rt.restore_report.event_fields())
        trained = all(m["trained"] for m in rt.engine.status()["methods"].values())
        if len(state.keyframes) and not trained and self.conf.service.train_on_load:
            rt.start_training(None)

    def _fail_map(self, name: str, exc: BaseException) -> None:
        """Mark ``name`` failed: its queries and puts get STORAGE_ERROR with the reason; its
        files stay as they are."""
        where = ("" if self.storage is None
                 else f" (see `reloc map check {self.storage / map_dirname(name)}`)")
        message = (f"map {name!r} is not served: its storage did not restore: {exc}; its "
                   f"files are left untouched{where}")
        log.error("%s", message, exc_info=not isinstance(exc, StorageError))
        with self._lock:
            self._loading.discard(name)
            self.failed[name] = message
        self._declare_failed(name, message)

    # -- serving ---------------------------------------------------------------------------------
    def check_restored(self, name: str) -> None:
        """STORAGE_ERROR if ``name`` failed to restore, BUSY while it is being restored."""
        if name in self.failed:
            raise StorageError(self.failed[name])
        if name in self._loading:
            raise wire.ProtocolError(ErrorCode.BUSY,
                                     f"map {name!r} is being restored from storage; put again "
                                     f"once it is served (its liveliness token appears)")

    def create(self, name: str) -> MapRuntime:
        """The runtime of ``name``, created (and declared) unless another put did it first;
        for a first put already validated. STORAGE_ERROR or BUSY as :meth:`check_restored`,
        QUOTA_EXCEEDED when ``quotas.max_maps`` are served already."""
        with self._lock:
            self.check_restored(name)
            if name not in self.maps:
                if self.residency is not None and self.residency.known(name):
                    raise wire.ProtocolError(ErrorCode.BUSY, f"map {name!r} is being loaded "
                                             "or closed; put again")
                self.quotas.check_new_map(name, self._served_count())
                rt = self._open_map(name)
                try:
                    rt.replay_backlog(self._stopped)   # a new map: opens its journal
                except BaseException:
                    self._unlock_map(name)
                    raise
                self.maps[name] = rt
                self._declare_created(name)
                log.info("map %s created by its first put", name)
            return self.maps[name]

    def _open_map(self, name: str) -> MapRuntime:
        """The runtime of map ``name``, restored from its storage (StorageError naming the
        file if that is damaged beyond what restoring skips). Its directory is locked and
        its name recorded in it first; the lock is held until the map is closed, or given
        back at once if the map does not open (a failed map is left to the operator's
        tools)."""
        directory = None if self.storage is None else self.storage / map_dirname(name)
        if directory is not None:
            check_storage(directory)
            self._map_locks[name] = DirectoryLock(directory, what=f"map {name!r}").acquire(
                "reloc serve")
        try:
            if directory is not None:
                record_map_name(directory, name)
            return self._restore_map(name, directory)
        except BaseException:
            self._unlock_map(name)
            raise

    def _unlock_map(self, name: str) -> None:
        lock = self._map_locks.pop(name, None)
        if lock is not None:
            lock.release()

    def _restore_map(self, name: str, directory: Path | None) -> MapRuntime:
        """The runtime of ``name`` with its snapshot loaded and its restore begun
        (:meth:`.MapRuntime.begin_restore`); its journal replay is the caller's."""
        verdict = None if directory is None else judge(directory)
        if verdict is not None and verdict.refusal is not None:
            raise StorageError(verdict.refusal)   # nothing loaded, nothing written
        recovered = None if directory is None else recover_current(directory)
        s = self.conf.service
        # with worker processes the queries run on their replicas, which make their own pools
        engine_conf = self.map_engine_confs.get(name, self.engine_conf)
        engine = open_engine(directory, engine_conf, pools=s.worker_mode != "process")
        rt = MapRuntime(name, engine, instance=self.conf.instance, limits=self.limits,
                        methods=self.methods, default_method=self.methods[0],
                        directory=directory, publish=self._publish,
                        snapshot_every=s.snapshot_every, fsync=s.fsync, quotas=self.quotas,
                        calibration_sigma=self.calibration_sigma(name))
        if directory is not None:
            check_storage(directory)
            rt.begin_restore(verdict)
            if recovered is not None:   # counted once the replay ends, with the others
                rt.restore_report.recovered_snapshot = recovered
        if self.processes is not None:
            self.processes.attach(rt)
        return rt

    def calibration_sigma(self, name: str) -> dict[str, float]:
        """The calibration accuracy map ``name`` states, as its status shows it, when its
        ``[maps.NAME]`` table sets its own; empty: the service-wide ``[mapping]`` values."""
        engine_conf = self.map_engine_confs.get(name)
        if engine_conf is None:
            return {}
        return {"focal_rel": engine_conf.mapping.calibration_focal_sigma_rel,
                "radial_px": engine_conf.mapping.calibration_radial_sigma_px}

    # -- stop ------------------------------------------------------------------------------------
    def close(self, *, final_snapshot: bool, deadline: float) -> None:
        """Close every served map (final snapshots with the time left until ``deadline``)."""
        if self.residency is not None:
            self.residency.close()
        for rt in list(self.maps.values()):
            try:
                rt.close(final_snapshot=final_snapshot, timeout=seconds_left(deadline))
            except Exception as exc:
                log.error("map %s: closing failed: %s", rt.name, exc)
            self._unlock_map(rt.name)
        for name in list(self._map_locks):
            self._unlock_map(name)
        if self._storage_lock is not None:
            self._storage_lock.release()
