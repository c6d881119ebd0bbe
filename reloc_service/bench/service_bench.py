"""Benchmarks of the Zenoh service on loopback: what the service layer adds to a query's
latency, throughput with concurrent clients, whether worker threads use several cores, and
``reloc eval --remote`` next to the in-process evaluation.

Every ``bench_*`` function returns a plain dict (milliseconds, queries per second) for
``reloc bench``. The service runs in this process (a Zenoh peer on a free loopback port,
multicast scouting off, memory-only storage); clients are threads of this process with their
own Zenoh sessions. Queries alternate between in-process and remote so that machine load
affects both sides alike.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ..cameras import Camera
from ..engine import Engine, EngineConf
from ..frame import Frame, Keyframe
from ..map import KeyframeMap
from ..relocalizers.base import RELOCALIZERS, Prior, Relocalizer, RelocResult, RelocStatus
from ..service import ensure_client_importable

ensure_client_importable()

from reloc_client import protocol as wire  # noqa: E402
from reloc_client.client import RelocClient, ServiceBusy  # noqa: E402

Array = npt.NDArray[np.float64]

#: A relocalizer that answers at once: isolates what the service layer costs.
ECHO = "bench-echo"


class EchoRelocalizer(Relocalizer):
    """Answers every query with the first keyframe's pose, without looking at the image."""

    @classmethod
    def from_options(cls, spec: str, kmap: KeyframeMap, options: Any, *,
                     evaluation: bool = False) -> EchoRelocalizer:
        return cls(kmap)

    @property
    def method(self) -> str:
        return ECHO

    def add_keyframe(self, keyframe: Keyframe) -> None:
        pass

    def remove_keyframe(self, keyframe: Keyframe) -> None:
        pass

    def relocalize(self, query: Frame, *, prior: Prior | None = None, hypotheses: int = 1
                   ) -> RelocResult:
        state = self.map.snapshot()
        ids = state.keyframe_ids()
        if not ids:
            return RelocResult.failure(ECHO, "empty map")
        return RelocResult(RelocStatus.OK, ECHO,
                           world_from_cam=state.keyframes[ids[0]].world_from_cam,
                           confidence=1.0, inliers=100, num_matches=100,
                           matched_keyframe_ids=[ids[0]], map_version=state.version)


#: The echo relocalizer after an idle wait as long as a real query: tells the service's own
#: cost apart from the effects of a CPU busy with the query (threads waking up on a loaded
#: machine).
SLEEP = "bench-sleep"
SLEEP_S = 0.25


class SleepRelocalizer(EchoRelocalizer):
    """The echo answer after sleeping :data:`SLEEP_S` seconds (no CPU used)."""

    @property
    def method(self) -> str:
        return SLEEP

    def relocalize(self, query: Frame, *, prior: Prior | None = None, hypotheses: int = 1
                   ) -> RelocResult:
        time.sleep(SLEEP_S)
        result = super().relocalize(query, prior=prior, hypotheses=hypotheses)
        result.method = SLEEP
        return result


def _register_echo() -> None:
    if ECHO not in RELOCALIZERS:
        RELOCALIZERS.register(ECHO)(EchoRelocalizer)
    if SLEEP not in RELOCALIZERS:
        RELOCALIZERS.register(SLEEP)(SleepRelocalizer)


# -- data ------------------------------------------------------------------------------------------

@dataclass(eq=False)
class BenchData:
    """Keyframes and queries of one camera: images (H, W) uint8 and ``world_from_cam``."""

    camera: Camera
    keyframes: list[tuple[npt.NDArray[np.uint8], Array]]
    queries: list[tuple[npt.NDArray[np.uint8], Array]]


def load_bench_data(dataset_root: str | Path) -> BenchData:
    """The map and query frames of a reloc dataset (first camera)."""
    from ..data.dataset import read_dataset

    ds = read_dataset(dataset_root)
    camera = ds.camera(ds.map_entries[0])
    return BenchData(camera,
                     [(ds.load_image(e), np.array(e.world_from_cam)) for e in ds.map_entries],
                     [(ds.load_image(e), np.array(e.world_from_cam)) for e in ds.query_entries])


def render_bench_data(preset: str = "desk", *, scale: float = 0.5,
                      directory: str | Path | None = None) -> BenchData:
    """Render ``preset`` at ``scale`` (into ``directory`` or a temporary folder) and load it."""
    from ..synth import render_dataset

    if directory is not None:
        return load_bench_data(render_dataset(preset, Path(directory), scale=scale,
                                              progress=False))
    with tempfile.TemporaryDirectory(prefix="reloc-bench-") as tmp:
        return load_bench_data(render_dataset(preset, Path(tmp) / preset, scale=scale,
                                              progress=False))


# -- a service on loopback -------------------------------------------------------------------------

def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def running_service(methods: Sequence[str], *, workers: int = 2, queue_size: int = 16,
                    process: bool = True) -> Iterator[str]:
    """A service serving ``methods`` (memory only) and map ``bench``; yields its endpoint.
    ``process``: in a child process (as deployed: no GIL shared with the clients), else in
    this one."""
    _register_echo()
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    doc = {"zenoh": {"mode": "peer", "listen": [endpoint], "multicast_scouting": False},
           "service": {"instance": "bench", "storage": "", "methods": list(methods),
                       "default_method": methods[0], "workers": workers,
                       "queue_size": queue_size},
           "maps": {"bench": {}}}
    if not process:
        from ..service.app import Service
        from ..service.config import parse_config

        service = Service(parse_config(doc)).start()
        try:
            yield endpoint
        finally:
            service.stop()
        return
    with tempfile.TemporaryDirectory(prefix="reloc-bench-service-") as tmp, service_process(
            doc, Path(tmp), module="reloc_service.bench.service_bench", map_name="bench"):
        yield endpoint


@contextmanager
def service_process(doc: Mapping[str, Any], folder: Path, *,
                    module: str = "reloc_service.cli.main", map_name: str) -> Iterator[None]:
    """``python -m MODULE serve --config`` of the service config ``doc`` in a child process,
    until it answers on ``map_name``; SIGTERM on exit. Its config and log are kept in
    ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    config, log_path = folder / "service.toml", folder / "service.log"
    config.write_text(toml_text(doc))
    with open(log_path, "wb") as log:
        child = subprocess.Popen([sys.executable, "-m", module, "serve", "--config", str(config)],
                                 stdout=log, stderr=subprocess.STDOUT)
        try:
            wait_ready(child, doc["zenoh"]["listen"][0], map_name=map_name, log=log_path)
            yield
        finally:
            child.send_signal(signal.SIGTERM)
            try:
                child.wait(60)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()


def toml_text(doc: Mapping[str, Any], prefix: str = "") -> str:
    """A TOML document from nested dicts of strings, numbers, booleans and lists of them
    (JSON's spelling of those is valid TOML); nested dicts become ``[a.b]`` tables."""
    import json

    scalars = [f"{k} = {json.dumps(v)}" for k, v in doc.items() if not isinstance(v, Mapping)]
    lines = ([f"[{prefix}]"] if prefix else []) + scalars
    text = "\n".join(lines) + "\n" if lines else ""
    for k, v in doc.items():
        if isinstance(v, Mapping):
            text += toml_text(v, f"{prefix}.{k}" if prefix else k)
    return text


def wait_ready(child: subprocess.Popen[bytes], endpoint: str, timeout: float = 120.0, *,
               map_name: str = "bench", log: Path | None = None) -> None:
    """Wait until the service ``child`` answers a status query on ``map_name``; RuntimeError
    with the end of its stderr (or of ``log``) if it exits first."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if child.poll() is not None:
            if child.stderr is not None:
                err = child.stderr.read().decode(errors="replace")
            else:
                err = log.read_text(errors="replace") if log is not None and log.exists() else ""
            raise RuntimeError(f"the bench service exited with {child.returncode}: {err[-2000:]}")
        try:
            with RelocClient(endpoint, map=map_name, timeout=2) as client:
                client.status(timeout=1)
                return
        except (ConnectionError, TimeoutError):
            time.sleep(0.2)
    raise TimeoutError(f"the bench service did not answer on {endpoint} within {timeout} s")


def upload(client: RelocClient, data: BenchData, *, train: bool = True) -> None:
    """Put the camera and every keyframe, wait until applied, then train."""
    done = threading.Event()
    target = len(data.keyframes)
    added: set[int] = set()

    def on_event(event: wire.Event) -> None:
        if event.kind is wire.EventKind.KEYFRAME_ADDED:
            added.add(int(event.fields["id"]))
            if len(added) >= target:
                done.set()

    sub = client.subscribe_events(on_event)
    time.sleep(0.2)
    client.set_camera("cam0", data.camera)
    time.sleep(0.1)
    for kf_id, (image, pose) in enumerate(data.keyframes):
        client.add_keyframe(kf_id, image, pose, camera_id="cam0")
    if not done.wait(600):
        raise TimeoutError(f"only {len(added)} of {target} keyframes applied")
    sub.undeclare()
    if train:
        client.train(wait=True, timeout=3600)


def in_process_engine(data: BenchData, methods: Sequence[str]) -> Engine:
    """An engine with ``data``'s keyframes, trained."""
    _register_echo()
    engine = Engine(EngineConf(methods=tuple(methods)))
    for kf_id, (image, pose) in enumerate(data.keyframes):
        engine.add_keyframe(kf_id, image, data.camera, pose)
    engine.train()
    return engine


def _pct(values: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(values) * 1e3, q)) if len(values) else math.nan


# -- benchmarks ------------------------------------------------------------------------------------

def bench_latency(data: BenchData, method: str = "sbi+p3p", *, repeats: int = 5,
                  process: bool = True) -> dict[str, Any]:
    """Query latency in-process (``Engine.relocalize`` on a new Frame, as the service does)
    vs over Zenoh (client round trip, mono8 image), for ``method`` and for the echo
    relocalizer that isolates the service layer, and the echo after a 250 ms idle wait. p50/p90
    in ms. ``added_p50_ms`` is the
    median of the paired differences (remote - in-process) of the same query;
    ``service_overhead_p50_ms`` the median of (round trip - the engine's own time in the
    service) per query: everything the service and Zenoh add, free of the noise between two
    separate runs of the method."""
    methods = [method, ECHO, SLEEP]
    engine = in_process_engine(data, methods)
    out: dict[str, Any] = {"method": method, "queries": len(data.queries) * repeats,
                           "image": f"{data.camera.width}x{data.camera.height}",
                           "load_before": _load()}
    with running_service(methods, process=process) as endpoint, \
            RelocClient(endpoint, map="bench", timeout=60) as client:
        upload(client, data)
        for m in methods:
            local, remote, server, engine_s = [], [], [], []
            for _ in range(repeats):
                for image, _pose in data.queries:
                    t = time.perf_counter()
                    engine.relocalize(Frame(image, data.camera), method=m)
                    local.append(time.perf_counter() - t)
                    r = client.relocalize(image, camera_id="cam0", method=m)
                    remote.append(r.round_trip_s or math.nan)
                    server.append(r.timings.get("total", math.nan))
                    engine_s.append(r.timings.get("engine_total", math.nan))
            key = {ECHO: "echo", SLEEP: "sleep"}.get(m, "method")
            paired = [b - a for a, b in zip(local, remote, strict=True)]
            out[key] = {
                "in_process_p50_ms": _pct(local, 50), "in_process_p90_ms": _pct(local, 90),
                "zenoh_p50_ms": _pct(remote, 50), "zenoh_p90_ms": _pct(remote, 90),
                "server_total_p50_ms": _pct(server, 50),
                "added_p50_ms": _pct(paired, 50),
                "service_overhead_p50_ms": _pct([b - e for b, e in zip(remote, engine_s,
                                                                       strict=True)], 50),
                "transport_p50_ms": _pct([b - s for b, s in zip(remote, server, strict=True)],
                                         50)}
    out["load_after"] = _load()
    return out


def bench_throughput(data: BenchData, method: str = "sbi+p3p", *,
                     clients: Sequence[int] = (1, 2, 4, 8), duration_s: float = 10.0,
                     workers: int = 2, queue_size: int = 8, rounds: int = 2,
                     process: bool = True) -> dict[str, Any]:
    """Queries per second answered with 1, 2, 4, 8 concurrent clients (each its own Zenoh
    session, querying back to back for ``duration_s``); busy replies are counted apart. The
    sequence of client counts is run ``rounds`` times (machine load drifts) and averaged."""
    raw: dict[int, list[dict[str, Any]]] = {n: [] for n in clients}
    load_before = _load()
    with running_service([method], workers=workers, queue_size=queue_size,
                         process=process) as endpoint:
        with RelocClient(endpoint, map="bench", timeout=60) as client:
            upload(client, data)
        for _ in range(rounds):
            for n in clients:
                raw[n].append(_throughput_run(endpoint, data, method, n, duration_s))
    rows = [{"clients": n,
             "queries_per_s": float(np.mean([r["queries_per_s"] for r in runs])),
             "queries_per_s_each_round": [round(r["queries_per_s"], 2) for r in runs],
             **{k: sum(r[k] for r in runs) for k in ("ok", "not_relocalized", "busy")},
             "p50_ms": float(np.median([r["p50_ms"] for r in runs])),
             "p99_ms": float(np.max([r["p99_ms"] for r in runs]))}
            for n, runs in raw.items()]
    return {"method": method, "workers": workers, "queue_size": queue_size,
            "duration_s": duration_s, "rounds": rounds, "runs": rows,
            "load_before": load_before, "load_after": _load()}


def _throughput_run(endpoint: str, data: BenchData, method: str, n: int,
                    duration_s: float) -> dict[str, Any]:
    counts = {"ok": 0, "not_relocalized": 0, "busy": 0}
    latencies: list[float] = []
    lock = threading.Lock()
    barrier = threading.Barrier(n + 1)

    def worker(index: int) -> None:
        with RelocClient(endpoint, map="bench", timeout=120) as c:
            barrier.wait()
            deadline = time.perf_counter() + duration_s
            i = index
            while time.perf_counter() < deadline:
                image = data.queries[i % len(data.queries)][0]
                i += 1
                try:
                    r = c.relocalize(image, camera_id="cam0", method=method)
                    outcome = "ok" if r.ok else "not_relocalized"
                except ServiceBusy:
                    outcome = "busy"
                    time.sleep(0.005)
                with lock:
                    counts[outcome] += 1
                    if outcome != "busy":
                        latencies.append(r.round_trip_s or math.nan)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    barrier.wait()
    start = time.perf_counter()
    for t in threads:
        t.join()
    elapsed = time.perf_counter() - start
    answered = counts["ok"] + counts["not_relocalized"]
    return {"clients": n, "queries_per_s": answered / elapsed, **counts,
            "p50_ms": _pct(latencies, 50), "p99_ms": _pct(latencies, 99)}


def bench_thread_scaling(data: BenchData, method: str = "sbi+p3p", *,
                         threads: Sequence[int] = (1, 2), duration_s: float = 8.0,
                         opencv_threads: Sequence[int | None] = (None, 1)) -> dict[str, Any]:
    """In-process queries per second with 1 and 2 threads on one engine: whether OpenCV,
    NumPy and PoseLib release the GIL enough for worker threads to use several cores. Run
    with OpenCV's own thread pool (None: its default) and with it limited to 1 thread."""
    import cv2

    engine = in_process_engine(data, [method])
    default_cv = cv2.getNumThreads()

    def work(k: int, deadline: float, done: list[int]) -> None:
        i = k
        while time.perf_counter() < deadline:
            engine.relocalize(Frame(data.queries[i % len(data.queries)][0], data.camera))
            done[k] += 1
            i += 1

    rows = []
    try:
        for cv_threads in opencv_threads:
            cv2.setNumThreads(default_cv if cv_threads is None else cv_threads)
            for n in threads:
                done = [0] * n
                deadline = time.perf_counter() + duration_s
                start = time.perf_counter()
                pool = [threading.Thread(target=work, args=(k, deadline, done))
                        for k in range(n)]
                for t in pool:
                    t.start()
                for t in pool:
                    t.join()
                rows.append({"threads": n, "opencv_threads": cv2.getNumThreads(),
                             "queries_per_s": sum(done) / (time.perf_counter() - start)})
    finally:
        cv2.setNumThreads(default_cv)
    return {"method": method, "cores": os.cpu_count(), "runs": rows, "load_after": _load()}


def bench_remote_eval(dataset_root: str | Path, methods: Sequence[str] = ("sbi+p3p",), *,
                      progress: bool = False) -> dict[str, Any]:
    """``reloc eval`` in-process and ``--remote`` (through a service on loopback) on the same
    dataset: both tables and their summaries."""
    from ..eval import report
    from ..eval.evaluate import RemoteSpec, evaluate

    local = evaluate(dataset_root, list(methods), progress=progress)
    with running_service(methods) as endpoint:
        remote = evaluate(dataset_root, list(methods), progress=progress,
                          remote=RemoteSpec(endpoint, "bench-eval"))
    return {"dataset": str(dataset_root),
            "in_process": {"table": report.format_table(local),
                           "summaries": {m.method: vars(m.summary) for m in local.methods},
                           "build_s": local.map.build_time_s, "train_s": local.map.train_time_s},
            "remote": {"table": report.format_table(remote),
                       "summaries": {m.method: vars(m.summary) for m in remote.methods},
                       "build_s": remote.map.build_time_s, "train_s": remote.map.train_time_s}}


def run(*, quick: bool = False, data: BenchData | None = None,
        eval_dataset: str | Path | None = None) -> dict[str, Any]:
    """Every service benchmark (``quick``: fewer repeats, shorter runs; the remote evaluation
    only when ``eval_dataset`` is given)."""
    data = data or render_bench_data("desk", scale=0.5)
    out: dict[str, Any] = {
        "latency": bench_latency(data, repeats=2 if quick else 5),
        "throughput": bench_throughput(data, duration_s=4.0 if quick else 10.0),
        "thread_scaling": bench_thread_scaling(data, duration_s=3.0 if quick else 8.0)}
    if eval_dataset is not None:
        out["remote_eval"] = bench_remote_eval(eval_dataset)
    return out


def _load() -> list[float]:
    """The 1, 5 and 15 minute load averages (the machine may be shared)."""
    return [round(x, 2) for x in os.getloadavg()]


def _serve_main(config: str) -> int:
    """``python -m reloc_service.bench.service_bench serve --config CONFIG``: the service of
    :func:`running_service` (with the echo relocalizer registered)."""
    import logging

    from ..service.app import serve
    from ..service.config import load_config

    logging.basicConfig(level=logging.WARNING)
    _register_echo()
    return serve(load_config(config))


if __name__ == "__main__":
    if len(sys.argv) != 4 or sys.argv[1:3] != ["serve", "--config"]:
        sys.exit("usage: python -m reloc_service.bench.service_bench serve --config CONFIG.toml")
    sys.exit(_serve_main(sys.argv[3]))
