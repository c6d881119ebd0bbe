"""A ``reloc serve`` of a fleet's storage in a child process (:mod:`.fleet`): its
configuration, its life, and the time from its start to its first answer."""

from __future__ import annotations

import contextlib
import dataclasses
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol

from .loopback import free_port, toml_text
from .stored_map import CAMERA_ID


class FleetConf(Protocol):
    """What the service's configuration takes of :class:`.fleet.FleetConf`."""

    @property
    def maps(self) -> int: ...
    @property
    def method(self) -> str: ...
    @property
    def workers(self) -> int: ...
    @property
    def worker_mode(self) -> str: ...
    @property
    def cold_load_wait_s(self) -> float: ...


def compile_bytecode() -> float:
    """Compile reloc_service's and reloc_client's modules to bytecode in their
    ``__pycache__`` folders, as ``pip install`` leaves an installed package (the deployments'
    way: deploy/); the seconds it took (nothing to do: a few milliseconds). An editable
    install where PYTHONDONTWRITEBYTECODE is set (this machine) otherwise compiles its
    1.6 MB of source at every start of a service, 0.3 s of CPU that a deployed service does
    not spend. The bytecode stays (gitignored)."""
    import compileall

    import reloc_client

    import reloc_service

    start = time.perf_counter()
    for package in (reloc_service, reloc_client):
        for folder in package.__path__:
            compileall.compile_dir(folder, quiet=1)
    return time.perf_counter() - start


def service_doc(conf: FleetConf, storage: Path, endpoint: str, budget_mb: float,
                max_image_pixels: int) -> dict[str, Any]:
    """``reloc serve``'s configuration for ``storage`` with ``max_resident_mb = budget_mb``,
    accepting query images of at most ``max_image_pixels`` (the fleet's camera: the budget
    keeps what a query of that size may hold for each worker)."""
    return {"zenoh": {"mode": "peer", "listen": [endpoint], "multicast_scouting": False},
            "service": {"instance": f"fleet-{endpoint.rsplit(':', 1)[1]}",
                        "storage": str(storage), "methods": [conf.method],
                        "default_method": conf.method, "workers": conf.workers,
                        "worker_mode": conf.worker_mode, "opencv_threads": 1,
                        "allow_new_maps": False, "snapshot_every": 0, "fsync": False,
                        "max_resident_mb": budget_mb, "cold_load_wait_s": conf.cold_load_wait_s},
            "limits": {"max_image_pixels": max_image_pixels},
            "quotas": {"max_maps": max(16, conf.maps), "max_total_bytes": 2**50}}


@dataclasses.dataclass(eq=False)
class Served:
    """A running ``reloc serve``: its process, endpoint, start time and log."""

    process: subprocess.Popen[bytes]
    endpoint: str
    started: float
    log: Path


@contextlib.contextmanager
def serve(conf: FleetConf, storage: Path, budget_mb: float, folder: Path,
          max_image_pixels: int) -> Iterator[Served]:
    """``reloc serve`` of ``storage`` in a child process (config and log in ``folder``), see
    :func:`service_doc`; SIGTERM on exit (kill after 60 s)."""
    from ...service.config import parse_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    doc = service_doc(conf, storage, endpoint, budget_mb, max_image_pixels)
    parse_config(doc)   # a ConfigError here, not in the child's log
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "service.toml").write_text(toml_text(doc))
    log_path = folder / "service.log"
    with open(log_path, "wb") as log:
        started = time.monotonic()
        child = subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", "serve",
                                  "--config", str(folder / "service.toml")],
                                 stdout=log, stderr=subprocess.STDOUT)
        try:
            yield Served(child, endpoint, started, log_path)
        finally:
            child.terminate()
            try:
                child.wait(60)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()


def first_answer(served: Served, name: str, jpeg: bytes, timeout_s: float) -> float:
    """Seconds from the service's process start to its first answer (relocalized or not)
    to a relocalize query on ``name``; RuntimeError if it exits, TimeoutError after
    ``timeout_s``."""
    from reloc_client.client import NoReplyError, RelocClient, ServiceBusy

    while time.monotonic() - served.started < timeout_s:
        if served.process.poll() is not None:
            tail = served.log.read_text(errors="replace")[-2000:]
            raise RuntimeError(f"reloc serve exited with {served.process.returncode}: {tail}")
        try:
            with RelocClient(served.endpoint, map=name, timeout=timeout_s) as client:
                client.relocalize(jpeg, camera_id=CAMERA_ID)
                return time.monotonic() - served.started
        except (ConnectionError, NoReplyError, ServiceBusy):
            time.sleep(0.02)
    raise TimeoutError(f"reloc serve gave no answer on {served.endpoint} within {timeout_s} s")
