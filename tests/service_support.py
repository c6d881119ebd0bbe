"""Helpers shared by the service integration tests (not a test module): free ports, service
configurations on loopback with multicast scouting off, event collection, raw Zenoh sessions."""

from __future__ import annotations

import json
import queue
import signal
import socket
import subprocess
import time
from pathlib import Path
from typing import Any

import zenoh
from reloc_client import protocol as wire

from reloc_service.service.config import ServiceConf, parse_config

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    """A loopback TCP port free right now (bound then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def service_conf(port: int, storage: Path | str = "", *, maps: tuple[str, ...] = (),
                 limits: dict[str, int] | None = None, zenoh: dict[str, Any] | None = None,
                 **service: Any) -> ServiceConf:
    """A peer service listening on ``port`` only (no scouting), storage ``storage`` (empty:
    in memory), serving ``maps`` from the start; ``service`` sets [service] keys, ``limits``
    and ``zenoh`` update those sections."""
    return parse_config({
        "zenoh": {"mode": "peer", "listen": [endpoint(port)], "multicast_scouting": False,
                  **(zenoh or {})},
        "service": {"instance": "test", "storage": str(storage), **service},
        "limits": limits or {}, "maps": {m: {} for m in maps}})


def raw_session(port: int, mode: str = "client") -> zenoh.Session:
    """A Zenoh session connected to ``port`` on loopback, multicast scouting off."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("connect/endpoints", json.dumps([endpoint(port)]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


class Events:
    """Collects a map's events from a client subscription."""

    def __init__(self, client: Any) -> None:
        self.queue: queue.Queue[wire.Event] = queue.Queue()
        self.seen: list[wire.Event] = []
        self.sub = client.subscribe_events(self.queue.put)
        time.sleep(0.2)  # the subscription reaches the service

    def wait(self, kind: str, timeout: float = 30.0, **fields: Any) -> wire.Event:
        """The first event of ``kind`` whose fields include ``fields`` (seen before or after)."""
        deadline = time.monotonic() + timeout
        while True:
            for e in self.seen:
                if e.kind.value == kind and all(e.fields.get(k) == v for k, v in fields.items()):
                    return e
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError(f"no {kind} event with {fields} within {timeout} s; seen "
                                     f"{[(e.kind.value, dict(e.fields)) for e in self.seen]}")
            try:
                self.seen.append(self.queue.get(timeout=remaining))
            except queue.Empty:
                pass

    def drain(self) -> list[wire.Event]:
        while True:
            try:
                self.seen.append(self.queue.get_nowait())
            except queue.Empty:
                return self.seen

    def close(self) -> None:
        self.sub.undeclare()


def stop_process(proc: subprocess.Popen, sig: int = signal.SIGTERM, timeout: float = 30.0
                 ) -> None:
    """Send ``sig`` to ``proc`` if it still runs and wait ``timeout`` s; kill it after that."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def wait_until(predicate: Any, timeout: float = 20.0, interval: float = 0.05) -> Any:
    """Poll ``predicate()`` until it is truthy; its value, or AssertionError on timeout."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout} s")
        time.sleep(interval)
