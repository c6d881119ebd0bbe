"""A reloc service on loopback for the benchmarks: in this process or as ``reloc serve`` in a
child process (as deployed, no GIL shared with the clients), serving a map saved in a storage
folder, and clients that wait until the service has applied their camera.

The service is a Zenoh peer on a free loopback port with multicast scouting off, OpenCV on one
thread per worker (``service.opencv_threads = 1``), no fsync and no periodic snapshots.
"""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from ...core.cameras import Camera


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def worker_modes_supported() -> tuple[str, ...]:
    """The values ``service.worker_mode`` accepts in this build, or () when the service has
    no such key (its workers are threads)."""
    import dataclasses
    import typing

    from ...service.config import ServiceSection

    fields = {f.name: f for f in dataclasses.fields(ServiceSection)}
    if "worker_mode" not in fields:
        return ()
    hint = typing.get_type_hints(ServiceSection).get("worker_mode")
    values = typing.get_args(hint) if typing.get_origin(hint) is typing.Literal else ()
    return tuple(str(v) for v in values) or ("process", "thread")


def service_doc(endpoint: str, storage: Path, methods: Sequence[str],
                options: Mapping[str, Mapping[str, Any]], *, map_name: str, workers: int,
                queue_size: int, worker_mode: str | None = None) -> dict[str, Any]:
    """The service configuration (as parsed from TOML) of a benchmark service serving
    ``map_name`` (loaded from ``storage`` if saved there, else empty). ``worker_mode``
    (``service.worker_mode``) is set only when given: ValueError if the service has no such
    mode."""
    doc = _service_doc(endpoint, storage, methods, options, map_name=map_name,
                       workers=workers, queue_size=queue_size)
    if worker_mode is not None:
        known = worker_modes_supported()
        if worker_mode not in known:
            raise ValueError(f"service.worker_mode {worker_mode!r}: this service knows "
                             f"{list(known) or 'no worker_mode key (thread workers only)'}")
        doc["service"]["worker_mode"] = worker_mode
    return doc


def _service_doc(endpoint: str, storage: Path, methods: Sequence[str],
                 options: Mapping[str, Mapping[str, Any]], *, map_name: str, workers: int,
                 queue_size: int) -> dict[str, Any]:
    return {"zenoh": {"mode": "peer", "listen": [endpoint], "multicast_scouting": False},
            "service": {"instance": f"bench-{endpoint.rsplit(':', 1)[1]}",
                        "storage": str(storage), "methods": list(methods),
                        "default_method": methods[0], "workers": workers, "opencv_threads": 1,
                        "queue_size": queue_size, "allow_new_maps": False,
                        "snapshot_every": 0, "fsync": False, "train_on_load": True},
            "options": {k: dict(v) for k, v in options.items()},
            "maps": {map_name: {}}}


@contextlib.contextmanager
def loopback_service(storage: Path, methods: Sequence[str],
                     options: Mapping[str, Mapping[str, Any]], *, map_name: str,
                     workers: int = 2, queue_size: int = 8, process: bool = False,
                     worker_mode: str | None = None) -> Iterator[str]:
    """A service serving the maps saved in ``storage``; yields its endpoint once it answers
    on ``map_name``. ``process``: ``reloc serve`` in a child process (its config and log are
    kept next to ``storage``), else a :class:`~reloc_service.service.app.Service` here.
    ``worker_mode``: ``service.worker_mode`` (see :func:`service_doc`)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    doc = service_doc(endpoint, storage, methods, options, map_name=map_name, workers=workers,
                      queue_size=queue_size, worker_mode=worker_mode)
    if process:
        folder = storage.parent / f"service-{endpoint.rsplit(':', 1)[1]}"
        with service_process(doc, folder, map_name=map_name):
            yield endpoint
        return
    from ...service.app import Service
    from ...service.config import parse_config

    service = Service(parse_config(doc)).start()
    try:
        yield endpoint
    finally:
        service.stop(final_snapshot=False)


@contextlib.contextmanager
def service_process(doc: Mapping[str, Any], folder: Path, *, map_name: str) -> Iterator[None]:
    """``reloc serve --config`` of the service config ``doc`` in a child process, until it
    answers on ``map_name``; SIGTERM on exit. Its config and log are kept in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    config, log_path = folder / "service.toml", folder / "service.log"
    config.write_text(toml_text(doc))
    with open(log_path, "wb") as log:
        child = subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", "serve",
                                  "--config", str(config)], stdout=log, stderr=subprocess.STDOUT)
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
    scalars = [f"{k} = {json.dumps(v)}" for k, v in doc.items() if not isinstance(v, Mapping)]
    lines = ([f"[{prefix}]"] if prefix else []) + scalars
    text = "\n".join(lines) + "\n" if lines else ""
    for k, v in doc.items():
        if isinstance(v, Mapping):
            text += toml_text(v, f"{prefix}.{k}" if prefix else k)
    return text


def wait_ready(child: subprocess.Popen[bytes], endpoint: str, *, map_name: str,
               log: Path | None = None, timeout: float = 120.0) -> None:
    """Wait until the service ``child`` answers a status query on ``map_name``; RuntimeError
    with the end of ``log`` if it exits first, TimeoutError after ``timeout`` seconds."""
    from reloc_client.client import RelocClient

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if child.poll() is not None:
            err = log.read_text(errors="replace") if log is not None and log.exists() else ""
            raise RuntimeError(f"the bench service exited with {child.returncode}: {err[-2000:]}")
        try:
            with RelocClient(endpoint, map=map_name, timeout=2) as client:
                client.status(timeout=1)
                return
        except (ConnectionError, TimeoutError):
            time.sleep(0.2)
    raise TimeoutError(f"the bench service did not answer on {endpoint} within {timeout} s")


def camera_client(endpoint: str, map_name: str, camera_id: str, camera: Camera, *,
                  timeout: float = 120.0) -> Any:
    """A :class:`RelocClient` on ``map_name`` whose camera ``camera_id`` the service has
    applied (TimeoutError after 30 s)."""
    from reloc_client.client import NoReplyError, RelocClient

    client = RelocClient(endpoint, map=map_name, timeout=timeout)
    client.set_camera(camera_id, camera)
    deadline = time.perf_counter() + 30.0
    while True:
        with contextlib.suppress(NoReplyError):  # no reply at all while no camera is known
            if camera_id in client.cameras(timeout=1.0):
                return client
        if time.perf_counter() > deadline:
            client.close()
            raise TimeoutError(f"the service did not apply camera {camera_id!r} within 30 s")
        time.sleep(0.05)
