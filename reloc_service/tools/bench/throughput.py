"""``reloc bench`` section ``throughput``: 1, 2, 4, 8 concurrent Zenoh clients against
``reloc serve`` with the default method, per worker mode (process, thread) the service knows,
and the same queries from threads in one process (the in-process reference)."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from typing import Any

from ...algorithms.relocalizers.factory import DEFAULT_METHOD
from ...core.progress import progress
from .samples import (
    QuerySet,
    pct_ms,
    relocalize_jpeg,
)
from .workspace import (
    CAMERA_ID,
    MAP_NAME,
    Workspace,
    group_client,
    group_service,
)


def bench_throughput(ws: Workspace, method: str = DEFAULT_METHOD) -> dict[str, Any]:
    """Queries per second and latency with 1, 2, 4, 8 concurrent clients (each its own Zenoh
    session, querying back to back with the JPEG queries) against ``reloc serve`` in its own
    process with ``service_workers`` workers, once per worker mode the service knows
    (``service.worker_mode``, process then thread); "busy" replies are counted apart and a
    query that gets no reply at all is counted as lost."""
    from .loopback import worker_modes_supported

    conf = ws.conf
    known = worker_modes_supported()
    modes: list[str | None] = [m for m in conf.worker_modes if m in known] or [None]
    by_mode = {}
    for mode in modes:
        by_mode[mode or "thread"] = _throughput_mode(ws, method, mode)
    first = next(iter(by_mode))
    return {"method": method, "workers": conf.service_workers, "queue_size": conf.service_queue,
            "duration_s": conf.throughput_seconds, "reply_timeout_s": conf.reply_timeout_s,
            "mode": first, "runs": by_mode[first], "modes": by_mode,
            "worker_mode_key": bool(known),
            "in_process_threads": _in_process_threads(ws, method, conf.throughput_seconds),
            "note": "clients are threads of the benchmark process, each with its own Zenoh "
                    "session; the service is `reloc serve` in its own process, as deployed"
                    + ("" if known else "; this service has no `service.worker_mode` key: "
                       "its workers are threads")}


def _throughput_mode(ws: Workspace, method: str, mode: str | None) -> list[dict[str, Any]]:
    """The client-count sweep against one ``reloc serve`` in worker mode ``mode``."""
    conf, q = ws.conf, ws.queries
    runs = []
    with group_service(ws, "default", process=True, worker_mode=mode) as endpoint:
        with group_client(endpoint, q.camera) as client:
            _until_workers_answer(client, q, method, conf.reply_timeout_s)
            for _ in range(conf.service_workers):  # warm-up: every worker's first query
                client.relocalize(q.jpegs[0], camera_id=CAMERA_ID, method=method)
        for n in progress(list(conf.throughput_clients),
                          desc=f"throughput, {mode or 'thread'} workers (client counts)"):
            runs.append(_throughput_run(endpoint, q, method, n, conf.throughput_seconds,
                                        conf.reply_timeout_s))
    base = runs[0]["queries_per_s"]
    for row in runs:
        row["speedup_over_first"] = row["queries_per_s"] / base if base else math.nan
    return runs


def _until_workers_answer(client: Any, q: QuerySet, method: str, timeout_s: float) -> None:
    """Query until the service's worker processes answer (until they hold the map the service
    answers itself, counted as ``relocalize_in_service``): the runs measure the workers, not
    their start. One query where the service has no worker processes."""
    deadline = time.monotonic() + timeout_s
    while True:
        before = client.status().counters.get("relocalize_in_service", 0)
        client.relocalize(q.jpegs[0], camera_id=CAMERA_ID, method=method)
        if client.status().counters.get("relocalize_in_service", 0) == before:
            return
        if time.monotonic() > deadline:
            raise RuntimeError(f"the service's worker processes did not take queries within "
                               f"{timeout_s:.0f} s")
        time.sleep(0.2)


def _in_process_threads(ws: Workspace, method: str, duration_s: float,
                        threads: Sequence[int] = (1, 2)) -> list[dict[str, Any]]:
    """Queries per second of 1 and 2 threads querying one engine back to back, no Zenoh:
    how far the work itself lets two workers use two cores (OpenCV, NumPy and PoseLib
    release the GIL; the Python between them does not)."""
    q, engine = ws.queries, ws.engines["default"]
    rows = []
    for n in threads:
        done = [0] * n
        deadline = time.perf_counter() + duration_s

        def work(k: int, done: list[int] = done, deadline: float = deadline) -> None:
            i = k
            while time.perf_counter() < deadline:
                relocalize_jpeg(engine, q.jpegs[i % len(q)], q.camera, method)
                done[k] += 1
                i += 1

        start = time.perf_counter()
        pool = [threading.Thread(target=work, args=(k,)) for k in range(n)]
        for t in pool:
            t.start()
        for t in pool:
            t.join()
        rows.append({"threads": n, "queries_per_s": sum(done) / (time.perf_counter() - start)})
    return rows


def _throughput_run(endpoint: str, q: QuerySet, method: str, n: int, duration_s: float,
                    reply_timeout_s: float = 60.0) -> dict[str, Any]:
    """``n`` clients querying back to back for ``duration_s``: answers (ok or not
    relocalized), busy replies (retried after 5 ms) and lost queries (no reply within
    ``reply_timeout_s``; the client goes on with the next query)."""
    from reloc_client.client import NoReplyError, RelocClient, ServiceBusy

    counts = {"ok": 0, "not_relocalized": 0, "busy": 0, "lost": 0, "sent": 0}
    latencies: list[float] = []
    lock = threading.Lock()
    barrier = threading.Barrier(n + 1)
    errors: list[str] = []

    def client_loop(index: int) -> None:
        with RelocClient(endpoint, map=MAP_NAME, timeout=reply_timeout_s) as c:
            barrier.wait()
            deadline = time.perf_counter() + duration_s
            i = index
            while time.perf_counter() < deadline:
                with lock:
                    counts["sent"] += 1
                try:
                    r = c.relocalize(q.jpegs[i % len(q)], camera_id=CAMERA_ID, method=method)
                except ServiceBusy:
                    with lock:
                        counts["busy"] += 1
                    time.sleep(0.005)
                    continue
                except NoReplyError:  # no reply at all: lost, which must never happen
                    with lock:
                        counts["lost"] += 1
                    i += 1
                    continue
                except Exception as exc:  # reported, not hidden
                    errors.append(f"{type(exc).__name__}: {exc}")
                    return
                i += 1
                with lock:
                    counts["ok" if r.ok else "not_relocalized"] += 1
                    latencies.append(r.round_trip_s or math.nan)

    threads = [threading.Thread(target=client_loop, args=(k,)) for k in range(n)]
    for t in threads:
        t.start()
    barrier.wait()
    start = time.perf_counter()
    for t in threads:
        t.join()
    elapsed = time.perf_counter() - start
    if errors:
        raise RuntimeError(f"throughput with {n} clients: {errors[0]}")
    answered = counts["ok"] + counts["not_relocalized"]
    return {"clients": n, "queries_per_s": answered / elapsed, "answered": answered, **counts,
            "p50_ms": pct_ms(latencies, 50), "p99_ms": pct_ms(latencies, 99)}
