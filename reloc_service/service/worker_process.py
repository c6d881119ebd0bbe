"""The worker process of ``service.worker_mode = "process"`` (:mod:`.processes` is the
service's side): it holds a read-only replica of every map the service sends it, applies the
changes forwarded in the order received, and answers relocalize queries on them.

Everything it gets arrives on one pipe, read in order: "load" (a saved engine to load as a
map's replica), a change ("put"/"delete"/camera, the :class:`~.served.WriteOp` values),
"query", "drop" (the service closed the map) and "stop". It runs forked from the service's
forkserver, which preloads this module (OpenCV and the engine imported once, not per worker).
"""

from __future__ import annotations

import logging
import os
import signal
from collections.abc import Mapping
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

from reloc_client import protocol as wire
from reloc_client.protocol import ErrorCode

from ..core.cameras import Camera
from ..core.numeric import limit_blas_threads
from ..engine import Engine, EngineConf, MappingConf
from . import handlers
from .codec import error_reply
from .memory import release_memory
from .served import ServedMap, WriteOp
from .warm import warm_kernels

log = logging.getLogger(__name__)

#: Seconds a worker waits, when it drops a replica, for the whole-map pool being made to
#: stop (its map is freed then); the queries queued behind wait too, but meanwhile the
#: service answers them itself (the map they go to next is not loaded here yet).
DROP_WAIT_S = 30.0

@dataclass(frozen=True)
class EngineSpec:
    """What a worker needs to build the engine of a replica (plain data: it is pickled)."""

    methods: tuple[str, ...]
    options: dict[str, dict[str, Any]]
    mapping: dict[str, Any]
    limits: wire.Limits
    #: Map name -> its own map-building options, for the maps that set some (``[maps.NAME]``
    #: calibration accuracy); the others use ``mapping``.
    map_mapping: dict[str, dict[str, Any]] = field(default_factory=dict)

    @classmethod
    def of(cls, methods: tuple[str, ...], options: Mapping[str, Mapping[str, Any]],
           mapping: Mapping[str, Any], limits: wire.Limits,
           map_mapping: Mapping[str, Mapping[str, Any]] | None = None) -> EngineSpec:
        return cls(tuple(methods), {k: dict(v) for k, v in options.items()}, dict(mapping),
                   limits, {k: dict(v) for k, v in (map_mapping or {}).items()})

    def engine_conf(self, name: str | None = None) -> EngineConf:
        """The engine configuration of map ``name``'s replica (None: the service-wide)."""
        mapping = self.map_mapping.get(name, self.mapping) if name is not None else self.mapping
        return EngineConf(methods=self.methods, options=self.options,
                          mapping=MappingConf.from_options(mapping))


class ReplicaMap(ServedMap):
    """A map as a worker sees it: what :func:`handlers.relocalize_reply` needs of a runtime
    (the :class:`~.served.ServedMap` the parent's map shares), read-only except for the
    changes forwarded (:meth:`~.served.ServedMap.apply_change`: same input, same order)."""

    def __init__(self, name: str, engine: Engine, spec: EngineSpec,
                 cameras: dict[str, Camera]) -> None:
        super().__init__(name, engine, limits=spec.limits, methods=spec.methods,
                         default_method=spec.methods[0], cameras=cameras)


def worker_main(conn: Connection, index: int) -> None:
    """A worker process: apply bases and changes, answer queries, in pipe order, until "stop"
    or the parent is gone (EOF). A change that does not apply exits the process (status 3):
    its replica would differ from the parent's map, and the replacement starts from a fresh
    base."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # Ctrl-C stops the parent, which stops us
    import cv2

    cv2.setNumThreads(1)
    limit_blas_threads(1)
    warm_kernels()   # with the worker, not within its first query's answer time
    conn.send(("ready", os.getpid()))   # warmed up, no replica yet: its baseline memory
    replicas: dict[str, ReplicaMap] = {}
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return                                 # the parent is gone
        kind = msg[0]
        if kind == "stop":
            return
        if kind == "query":
            conn.send(_answer(replicas, *msg[1:]))
        elif kind == "drop":   # the parent closed the map: its replica goes too
            dropped = replicas.pop(msg[1], None)
            if dropped is not None:
                dropped.engine.close()   # with the pools it still had to make
                # the pool being made holds the map until it ends; then the pages go back
                # to the system, as the service's do when it closes a map (residency)
                dropped.engine.prepared.wait(DROP_WAIT_S)
                del dropped
                release_memory()   # its objects are in reference cycles: collected now
        elif kind == "load":
            _, name, base, spec, cameras = msg
            try:
                engine = Engine.load(base, spec.engine_conf(name), train=False)   # as saved
                previous = replicas.pop(name, None)
                if previous is not None:
                    previous.engine.close()
                replicas[name] = ReplicaMap(name, engine, spec, cameras)
            except Exception:
                log.exception("worker %d: the replica of map %s did not load from %s", index,
                              name, base)
                os._exit(3)
            conn.send(("loaded", str(base)))
        else:
            _, name, *args = msg
            replica = replicas.get(name)
            if replica is None:
                continue   # its base comes later and includes this change
            try:
                replica.apply_change(WriteOp(kind), *args)
            except Exception:
                log.exception("worker %d: change %s on map %s did not apply", index, kind, name)
                os._exit(3)


def _answer(replicas: dict[str, ReplicaMap], token: int, name: str, payload: bytes,
            queued_s: float) -> tuple[Any, ...]:
    """("result", token, reply bytes, ok, total seconds) or ("error", token, error bytes)."""
    replica = replicas.get(name)
    try:
        if replica is None:
            raise wire.ProtocolError(ErrorCode.INTERNAL,
                                     f"map {name!r} has no replica in worker process "
                                     f"{os.getpid()}; retry")
        reply, ok, total = handlers.relocalize_reply(replica, payload, queued_s=queued_s)
        return ("result", token, reply, ok, total)
    except Exception as exc:
        return ("error", token, error_reply(exc))

def wait_ready(process: Any, conn: Connection) -> None:
    """Wait for a new worker's "ready" (its imports and kernels loaded, no replica yet: what
    it holds then is its baseline memory); RuntimeError if it exits first. No time limit: a
    first start on an installation compiles the kernels, about a minute."""
    while not conn.poll(1.0):
        if not process.is_alive():
            raise RuntimeError(f"worker process {process.pid} exited with status "
                               f"{process.exitcode} before it was ready")
    try:
        msg = conn.recv()
    except (EOFError, OSError) as exc:
        raise RuntimeError(f"worker process {process.pid} exited before it was ready") from exc
    if msg[0] != "ready":
        raise RuntimeError(f"worker process {process.pid}: expected 'ready' first, got "
                           f"{msg[0]!r}")
