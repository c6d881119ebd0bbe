"""Relocalize workers as processes (``service.worker_mode = "process"``), the service's
side (the worker's own loop is :mod:`.worker_process`): each holds a read-only replica of
every served map, kept in the parent's journal order.

Why processes: a worker thread holds the GIL outside OpenCV (decoding the request, matching
bookkeeping, RANSAC set-up), so 8 clients on 2 threads got 1.28x one client on 2 cores.

How a replica stays current (the parent's :class:`~.runtime.MapRuntime` is the only writer):

- **Base**: the parent saves the map's engine (``Engine.save``: map and trained models) into
  a private directory and each worker loads it (``Engine.load``). This happens when a worker
  starts (for every served map), when a map is first served, and after every training job
  (the new models replace the old ones in one step; a trained model is not a journal record,
  and retraining in every worker would cost N times the training).
- **Changes**: every keyframe put/delete and camera put the parent *applies* is forwarded,
  in the order applied, to every worker, which applies the same input to its engine (the
  keyframe's features and landmarks are recomputed there: forwarding the decoded input is
  a few hundred KB, while forwarding the resulting map delta would tie the IPC to the map's
  internals). A put thus costs its mapping time once per worker, off the query path of the
  other workers.
- **Ordering**: each worker has one pipe, read in order. Changes are sent under the map's
  apply lock before the parent publishes ``keyframe_added``; a query is sent later on the
  same pipe, so a query dispatched after a change was applied is answered on a replica that
  includes it. Bases are sent under the same lock, so no change is lost or applied twice.

Queries go through the service's bounded :class:`~.workers.WorkerPool` (same busy reply);
each pool thread borrows one idle process, sends the request bytes as received (compressed
image: decoded in the worker) and gets back the reply bytes. Until the workers hold a map
(:meth:`ProcessWorkers.replica_ready`: after the service's start, a cold load, a worker's
replacement) the service answers its queries on its own map, the same answers, rather than
waiting seconds for their start and load. A worker that dies (kill -9)
gives the query it held an INTERNAL error reply and is replaced (new process, fresh bases).

Processes are forked from a ``forkserver`` (a clean single-threaded server started by exec,
with this module preloaded): never a fork of the service with Zenoh threads running, and a
new worker costs a fork rather than a fresh interpreter importing OpenCV (~2 s CPU). Each
worker uses one OpenCV thread (the processes are the parallelism). Workers start when
``reloc serve`` has restored its maps (:meth:`ProcessWorkers.start`), or with the first
relocalize query (a :class:`~.app.Service` used as a library).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode

from ..storage.keyframe_parts import EVERYTHING
from ..storage.snapshot_link import link_snapshot
from . import worker_process
from .map_dirs import map_dirname
from .memory import descendants
from .replica_scratch import SCRATCH_PREFIX, remove_stale_scratch
from .served import WriteOp
from .worker_handle import WorkerHandle, terminate
from .worker_process import EngineSpec, ReplicaMap, wait_ready, worker_main

if TYPE_CHECKING:
    from .runtime import MapRuntime
    from .runtime_state import RuntimeState

log = logging.getLogger(__name__)

#: Seconds a worker gets to exit after "stop" before it is terminated, then killed.
STOP_GRACE_S = 3.0

__all__ = ["EngineSpec", "ProcessWorkers", "RemoteAnswer", "ReplicaMap"]


@dataclass
class _Base:
    """A saved engine that workers load; deleted once every worker it was sent to loaded it
    (or died)."""

    path: Path
    waiting: set[int]
    name: str = ""   # the map it holds


@dataclass(frozen=True)
class RemoteAnswer:
    """A worker's answer: the reply bytes (``error`` False) or an error reply's bytes."""

    payload: bytes
    error: bool
    ok: bool = False
    total_s: float = 0.0


class ProcessWorkers:
    """``count`` worker processes holding replicas of the maps :meth:`attach`-ed to them."""

    def __init__(self, count: int, spec: EngineSpec) -> None:
        if count < 1:
            raise ValueError(f"expected count >= 1 worker processes, got {count}")
        self.count = count
        self.spec = spec
        self._ctx = multiprocessing.get_context("forkserver")
        self._ctx.set_forkserver_preload([worker_process.__name__])
        self._lock = threading.Lock()                 # handles, idle list, bases, maps
        self._start_lock = threading.Lock()           # the first start of the workers
        self._handles: list[WorkerHandle] = []
        self._idle: list[WorkerHandle] = []
        self._idle_ready = threading.Condition(self._lock)
        self._maps: dict[str, MapRuntime] = {}
        self._bases: dict[int, _Base] = {}            # id -> base (several may be in flight)
        self._started = False
        self._starting = False                        # a start_in_background thread runs
        self._closed = False
        self._reviver: threading.Thread | None = None   # start_in_background's thread
        self._token = 0
        self._in_flight = 0
        #: Told the pids of the forkserver and the workers once they first start (the
        #: residency counts their own memory against the service's budget).
        self.on_started: Callable[[list[int]], None] | None = None
        remove_stale_scratch(Path(tempfile.gettempdir()))
        self._scratch = Path(tempfile.mkdtemp(prefix=f"{SCRATCH_PREFIX}{os.getpid()}-"))

    # -- maps ------------------------------------------------------------------------------------
    def attach(self, rt: MapRuntime) -> None:
        """Serve map ``rt`` from the workers too: its changes are forwarded from now on, and
        the running workers load its current state."""
        with rt.apply_lock():   # no change between the first forward and the first base
            rt.replicas = self
            with self._lock:
                self._maps[rt.name] = rt
                handles = [h for h in self._handles if not h.dead]
            if handles:
                self.rebase(rt, handles)

    def detach(self, rt: MapRuntime) -> None:
        """Stop serving map ``rt`` from the workers (the parent closes it): its changes are
        no longer forwarded and every worker drops its replica (after the queries already
        sent to it, in pipe order)."""
        with rt.apply_lock():
            rt.replicas = None
            with self._lock:
                self._maps.pop(rt.name, None)
                handles = list(self._handles)
                for handle in handles:
                    handle.holds.discard(rt.name)
        for handle in handles:
            handle.send(("drop", rt.name))

    def forward(self, name: str, op: WriteOp, *args: Any) -> None:
        """Send a change the parent just applied to every worker (called under the map's
        apply lock, so in journal order). The op travels as its string, like the other
        message kinds ("load", "query", "stop")."""
        with self._lock:
            handles = list(self._handles)
        msg = (op.value, name, *args)
        for handle in handles:
            handle.send(msg)

    def rebase(self, rt: RuntimeState, handles: list[WorkerHandle] | None = None) -> None:
        """Save ``rt``'s engine and have ``handles`` (default: every worker) load it. Under
        the map's apply lock: no change is applied between the save and the sends."""
        with rt.apply_lock():
            with self._lock:
                targets = [h for h in (handles if handles is not None else self._handles)
                           if not h.dead]
            if not targets:
                return
            # named like the map's storage directory, cut short: mkdtemp adds to it, and the
            # name must fit NAME_MAX whatever the map's name
            path = Path(tempfile.mkdtemp(prefix=f"{map_dirname(rt.name)[:120]}-", dir=self._scratch))
            # pending from now on: a query that finds it pending is answered here, not sent
            # to a worker that will load the base before it reads the query
            base = _Base(path, {id(h) for h in targets}, rt.name)
            with self._lock:
                self._bases[id(base)] = base
            try:
                # unchanged since it was loaded: the snapshot it was loaded from, linked;
                # else float64 geometry as the map holds it (a worker answers bit for bit as
                # this map does) and every image and depth map it holds (a copy, not a
                # compact snapshot)
                loaded = rt.engine.loaded_snapshot()
                if loaded is None or not link_snapshot(loaded, path):
                    rt.engine.save(path, exact_geometry=True, parts=EVERYTHING)
            except BaseException:
                with self._lock:
                    self._bases.pop(id(base), None)
                shutil.rmtree(path, ignore_errors=True)
                raise
            msg = ("load", rt.name, path, self.spec, rt.cameras())
            for handle in targets:
                if not handle.send(msg):
                    self._base_done(str(path), handle)

    # -- queries ---------------------------------------------------------------------------------
    def relocalize(self, name: str, payload: bytes, queued_s: float) -> RemoteAnswer:
        """Answer a RelocalizeRequest on a worker (blocks the calling pool thread). A worker
        found dead before it got the query is replaced and the query sent to the new one; a
        worker dying while it holds the query gives it an INTERNAL error reply."""
        for _ in range(2):
            handle = self._borrow()
            try:
                with self._lock:
                    self._token += 1
                    token = self._token
                    self._in_flight += 1
                try:
                    if not handle.send(("query", token, name, payload, queued_s)):
                        continue   # gone before the query reached it: not held, send it again
                    answer = self._receive(handle, token)
                finally:
                    with self._lock:
                        self._in_flight -= 1
                if answer is not None:
                    return answer
                why = handle.exit_description()
                log.error("relocalize worker process %d %s while answering a query on map %s; "
                          "it is replaced", handle.process.pid, why, name)
                return _internal(f"the worker process answering this query {why}; it is being "
                                 "replaced: retry")
            finally:
                self._give_back(handle)
        return _internal("two worker processes in a row were gone before they got this query; "
                         "retry")

    def replica_ready(self, name: str) -> bool:
        """Whether the workers hold map ``name`` now: every live worker has loaded a base of
        it and none is pending (sent, or being saved to be sent). Until then the service
        answers its queries itself (:meth:`.app.Service.relocalize_payload`): the same
        answers, without waiting for the workers' start and their load of the map (a query
        sent to a worker that is still warming up, or that has a base to load before it,
        waits for both: seconds)."""
        self._read_acks()
        with self._lock:
            if not self._started or self._closed or name not in self._maps:
                return False
            live = [h for h in self._handles if not h.dead]
            if not live or any(base.name == name for base in self._bases.values()):
                return False
            return all(name in h.holds for h in live)

    def _read_acks(self) -> None:
        """Read the "loaded" acknowledgements the idle workers sent (an idle worker holds
        no query, so its pipe holds nothing else), without blocking."""
        with self._idle_ready:
            idle, self._idle = self._idle, []
        done: list[tuple[str, WorkerHandle]] = []
        try:
            for handle in idle:
                try:
                    while not handle.dead and handle.conn.poll(0):
                        msg = handle.conn.recv()
                        if msg[0] == "loaded":
                            done.append((msg[1], handle))
                        else:
                            log.error("idle worker %d sent %r", handle.process.pid, msg[0])
                except (EOFError, OSError):
                    handle.dead = True
        finally:
            with self._idle_ready:
                self._idle.extend(idle)
                self._idle_ready.notify_all()
        for path, handle in done:
            self._base_done(path, handle)

    def start_in_background(self) -> None:
        """On a thread of its own: :meth:`start` the workers, or replace the idle ones found
        dead (each with fresh bases); nothing if neither is needed or one such thread runs."""
        with self._lock:
            if self._closed or self._starting:
                return
            if self._started and all(not h.dead for h in self._handles):
                return
            self._starting = True
            self._reviver = threading.Thread(target=self._start_or_revive, name="revive-workers",
                                             daemon=True)
            self._reviver.start()

    def _start_or_revive(self) -> None:
        try:
            self._ensure_started()
            with self._idle_ready:
                dead = [h for h in self._idle if h.dead or not h.process.is_alive()]
                for handle in dead:
                    self._idle.remove(handle)
            for handle in dead:
                try:
                    handle = self._replace(handle)
                finally:
                    self._give_back(handle)
        except Exception as exc:   # the next query tries again
            if self._closed:   # the service stopped meanwhile: its maps' files went with it
                log.debug("worker processes not started, the service is stopping: %s", exc)
            else:
                log.error("starting the relocalize worker processes failed: %s", exc)
        finally:
            with self._lock:
                self._starting = False

    @property
    def in_flight(self) -> int:
        """Queries sent to a worker and not answered yet."""
        with self._lock:
            return self._in_flight

    def _receive(self, handle: WorkerHandle, token: int) -> RemoteAnswer | None:
        """The answer to query ``token`` (load acknowledgements read on the way); None if the
        worker died."""
        while True:
            try:
                msg = handle.conn.recv()
            except (EOFError, OSError):
                handle.dead = True
                return None
            if msg[0] == "loaded":
                self._base_done(msg[1], handle)
            elif msg[1] != token:
                log.error("worker %d answered query %s, expected %s", handle.process.pid,
                          msg[1], token)
            elif msg[0] == "result":
                return RemoteAnswer(msg[2], error=False, ok=msg[3], total_s=msg[4])
            else:
                return RemoteAnswer(msg[2], error=True)

    def _borrow(self) -> WorkerHandle:
        """An idle worker, live: one found dead is replaced first (an exception here, a
        worker that does not start, becomes the query's error reply)."""
        self._ensure_started()
        with self._idle_ready:
            while not self._idle:
                self._idle_ready.wait()
            handle = self._idle.pop(0)   # round robin: every worker takes its turn
        if not handle.dead and handle.process.is_alive():
            return handle
        try:
            return self._replace(handle)
        except BaseException:
            self._give_back(handle)   # still dead: the next query tries again
            raise

    def _give_back(self, handle: WorkerHandle) -> None:
        with self._idle_ready:
            self._idle.append(handle)
            self._idle_ready.notify()

    # -- life cycle ------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the workers now (``reloc serve`` does once its maps are restored, so the
        first query does not wait for them); else the first query starts them. Idempotent;
        nothing happens once :meth:`close` was called."""
        self._ensure_started()

    def _ensure_started(self) -> None:
        with self._start_lock:   # one start; close() waits for it (no worker left behind)
            with self._lock:
                if self._started or self._closed:
                    return
                self._started = True
            handles = [self._start_process() for _ in range(self.count)]   # warm in parallel
            with self._lock:   # listed at once (pids, changes forwarded: read once warm)
                self._handles.extend(handles)
            try:
                for handle in handles:
                    wait_ready(handle.process, handle.conn)
            except BaseException:
                with self._lock:
                    self._started = False   # the next query tries again
                    for handle in handles:
                        self._handles.remove(handle)
                for handle in handles:
                    terminate(handle)
                raise
        if self.on_started is not None:   # warmed up, before any replica: no map in them
            self.on_started(descendants())
        for rt in self._attached():
            self.rebase(rt, handles)
        with self._idle_ready:
            self._idle.extend(handles)
            self._idle_ready.notify_all()

    def _replace(self, dead: WorkerHandle) -> WorkerHandle:
        """A new worker (with fresh bases of every map) in place of ``dead``."""
        self._drop(dead)
        if self._closed:
            raise RuntimeError("the service is stopping")
        return self._spawn_one()

    def _spawn_one(self) -> WorkerHandle:
        handle = self._new_process()
        with self._lock:
            closed = self._closed
            if not closed:
                self._handles.append(handle)
        if closed:   # close() has stopped the workers it listed: this one is not among them
            terminate(handle)
            raise RuntimeError("the service is stopping")
        for rt in self._attached():
            self.rebase(rt, [handle])
        return handle

    def _attached(self) -> list[MapRuntime]:
        with self._lock:
            return list(self._maps.values())

    def _new_process(self) -> WorkerHandle:
        """A new worker process, warmed up (:func:`.worker_process.wait_ready`)."""
        handle = self._start_process()
        try:
            wait_ready(handle.process, handle.conn)
        except BaseException:
            terminate(handle)
            raise
        return handle

    def _start_process(self) -> WorkerHandle:
        parent_end, child_end = self._ctx.Pipe()
        with self._lock:
            index = len(self._handles)
        process = self._ctx.Process(target=worker_main, args=(child_end, index),
                                    name=f"reloc-relocalize-{index}", daemon=True)
        process.start()
        child_end.close()   # the worker's end lives in the worker only: its death means EOF
        return WorkerHandle(process, parent_end)

    def _drop(self, handle: WorkerHandle) -> None:
        handle.dead = True
        with self._lock:
            if handle in self._handles:
                self._handles.remove(handle)
            bases = list(self._bases.values())
        for base in bases:
            self._base_done(str(base.path), handle)
        terminate(handle)

    def _base_done(self, path: str, handle: WorkerHandle) -> None:
        """Worker ``handle`` loaded the base at ``path`` (or died: it waits for it no more)."""
        with self._lock:
            for key, base in list(self._bases.items()):
                if str(base.path) == path:
                    if not handle.dead:
                        handle.holds.add(base.name)
                    base.waiting.discard(id(handle))
                    if not base.waiting:
                        del self._bases[key]
                        shutil.rmtree(base.path, ignore_errors=True)

    def pids(self) -> list[int]:
        """Process ids of the live workers (empty before the first query)."""
        with self._lock:
            return [h.process.pid for h in self._handles if not h.dead]

    def close(self) -> None:
        """Stop every worker (asked, then terminated, then killed) and delete the bases."""
        with self._start_lock, self._lock:
            self._closed = True
            handles = list(self._handles)
            self._handles.clear()
            reviver = self._reviver
        for handle in handles:
            handle.send(("stop",))
        deadline = time.monotonic() + STOP_GRACE_S
        for handle in handles:
            handle.process.join(max(0.0, deadline - time.monotonic()))
            terminate(handle)
        if reviver is not None:   # a replacement it is starting is terminated by itself
            reviver.join(max(0.0, deadline - time.monotonic()) + STOP_GRACE_S)
        shutil.rmtree(self._scratch, ignore_errors=True)


def _internal(message: str) -> RemoteAnswer:
    return RemoteAnswer(wire.encode_error(ErrorCode.INTERNAL, message), error=True)
