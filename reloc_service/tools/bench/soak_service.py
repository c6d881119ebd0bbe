"""The ``reloc serve`` child process of the soak run (:mod:`.soak`): one port and one storage
folder, started and stopped many times, by ``kill -9`` or SIGTERM."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Protocol

from .loopback import free_port, service_doc, toml_text

MAP_NAME = "soak"


class ServiceConf(Protocol):
    """What the service's configuration takes from the soak run's ``SoakConf``."""

    @property
    def method(self) -> str: ...
    @property
    def workers(self) -> int: ...
    @property
    def queue_size(self) -> int: ...
    @property
    def snapshot_every(self) -> int: ...
    @property
    def fsync(self) -> bool: ...


class ServiceRunner:
    """``reloc serve`` on one port and one storage folder, started and stopped many times."""

    def __init__(self, conf: ServiceConf, folder: Path) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.folder = folder
        doc = service_doc(self.endpoint, folder / "storage", [conf.method], {},
                          map_name=MAP_NAME, workers=conf.workers, queue_size=conf.queue_size)
        doc["service"].update(snapshot_every=conf.snapshot_every, fsync=conf.fsync,
                              allow_new_maps=False, instance="soak")
        self.config = folder / "service.toml"
        self.config.write_text(toml_text(doc))
        self.proc: subprocess.Popen[bytes] | None = None
        self.started_at = math.nan
        self.runs = 0

    @property
    def pid(self) -> int | None:
        proc = self.proc
        return proc.pid if proc is not None and proc.poll() is None else None

    def start(self) -> None:
        self.runs += 1
        log = open(self.folder / f"service-{self.runs:02d}.log", "wb")  # noqa: SIM115
        self.started_at = time.monotonic()
        self.proc = subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", "serve",
                                      "--config", str(self.config)],
                                     stdout=log, stderr=subprocess.STDOUT)
        log.close()  # the child holds its own descriptor

    def stop(self, kind: str, timeout_s: float) -> dict[str, Any]:
        """Stop by ``kind`` (``kill9`` or ``sigterm``; a SIGTERM that takes longer than
        ``timeout_s`` is followed by kill -9). Returns how it went."""
        assert self.proc is not None
        start = time.monotonic()
        self.proc.send_signal(signal.SIGKILL if kind == "kill9" else signal.SIGTERM)
        escalated = False
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            escalated = True
            self.proc.kill()
            self.proc.wait()
        return {"kind": kind, "stop_s": time.monotonic() - start,
                "exit_code": self.proc.returncode, "killed_after_timeout": escalated}

    def exited(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def log_tail(self, chars: int = 2000) -> str:
        path = self.folder / f"service-{self.runs:02d}.log"
        return path.read_text(errors="replace")[-chars:] if path.exists() else ""
