"""Helpers shared by the service integration tests (not a test module): free ports, service
configurations on loopback with multicast scouting off, event collection, raw Zenoh sessions,
a router of config/router.json5, a ``reloc serve`` process and its durable keyframes, the
ground station of deploy/ground with its authenticated clients, its services' configurations
and a stream of keyframes put into them."""

from __future__ import annotations

import dataclasses
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zenoh
from reloc_client import protocol as wire
from reloc_client.client import NoReplyError, RelocClient, ServiceBusy

from reloc_service.service.app import Service
from reloc_service.service.config import ServiceConf, load_config, parse_config, with_overrides
from reloc_service.service.residency import MB
from reloc_service.storage.journal import Journal

ROOT = Path(__file__).resolve().parents[1]
GROUND = ROOT / "deploy" / "ground"
CREDENTIALS = {line.split(":")[0]: line.split(":", 1)[1]
               for line in (GROUND / "credentials.example.txt").read_text().split()}
#: The map a :func:`write_config` service serves.
MAP = "lab"
# Tests put with this where a put Zenoh drops under congestion would read as a service fault.
BLOCK = zenoh.CongestionControl.BLOCK


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


#: A budget no test process's own memory reaches: a service starts with it, then the test
#: gives its maps their share of the baseline it measured (:func:`limit_maps`).
AMPLE_MB = 1_000_000


def limit_maps(service: Service, maps_bytes: float) -> None:
    """Give ``service``'s maps ``maps_bytes``: its budget made the baseline it measured (its
    process's once warmed up; its worker processes', started here, once they are) plus
    ``maps_bytes``, as if configured so. In the test's process the baseline is the whole
    pytest process, which grows by more than a map between two starts: a budget configured
    from a probe's measure would not leave the maps what the test asks."""
    residency = service.registry.residency
    assert residency is not None and residency.baseline_settled.wait(60)
    if service.processes is not None:
        service.processes.start()
    residency.set_total_budget((residency.baseline + maps_bytes) / MB)
    assert residency.budget == int(residency.total_budget - residency.baseline)


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


# -- a router, a service process --------------------------------------------------------------

def open_router(port: int) -> zenoh.Session:
    conf = zenoh.Config.from_file(str(ROOT / "config" / "router.json5"))
    conf.insert_json5("listen/endpoints", json.dumps([endpoint(port)]))
    return zenoh.open(conf)


def write_config(tmp: Path, port: int, *, instance: str = "durable",
                 options: dict[str, dict[str, object]] | None = None,
                 **service: object) -> Path:
    """A ``reloc serve`` config: a peer on ``port``, storage under ``tmp``, map ``lab``,
    ``[service]`` keys from ``service`` and ``[options.<name>]`` tables from ``options``."""
    lines = ["[zenoh]", 'mode = "peer"', f'listen = ["{endpoint(port)}"]',
             "multicast_scouting = false", "[service]", f'instance = "{instance}"',
             f'storage = "{tmp / "storage"}"']
    lines += [f"{k} = {json.dumps(v)}" for k, v in service.items()]
    for name, values in (options or {}).items():
        lines += [f"[options.{name}]", *[f"{k} = {json.dumps(v)}" for k, v in values.items()]]
    lines += [f"[maps.{MAP}]"]
    path = tmp / "service.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def durable_keyframe_ids(map_dir: Path) -> set[int]:
    """Keyframe ids on disk after a crash: the snapshot's, then the journal's puts and deletes
    from the segment the snapshot's service.json names."""
    ids: set[int] = set()
    first_segment = 0
    if (map_dir / "service.json").is_file():
        meta = json.loads((map_dir / "service.json").read_text())
        first_segment = meta["next_segment"]
        if "snapshot" in meta:   # (a map's identity is recorded before its first snapshot)
            manifest = map_dir / "map" / "snapshots" / meta["snapshot"] / "manifest.json"
            ids = {kf["id"] for kf in json.loads(manifest.read_text())["keyframes"]}
    for raw in Journal(map_dir / "journal").replay(first_segment):
        record = msgpack.unpackb(raw)
        if record["op"] == "kf":
            ids.add(record["id"])
        elif record["op"] == "del":
            ids.discard(record["id"])
    return ids


class ServiceProcess:
    """``reloc serve --config FILE`` in a subprocess, ready once its map answers and its
    journal has replayed (within ``ready_s``: a restart replaying hundreds of journal records
    needs minutes under load)."""

    def __init__(self, config: Path, port: int, log: Path, ready_s: float = 60.0) -> None:
        self.log_path = log
        self.log = open(log, "ab")
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "reloc_service.cli.main", "serve", "--config", str(config)],
            cwd=ROOT, stdout=self.log, stderr=self.log, env=env)
        self.port = port
        self.client: RelocClient | None = None
        wait_until(self._ready, timeout=ready_s, interval=0.2)

    def _ready(self) -> bool:
        if self.proc.poll() is not None:
            raise AssertionError(f"service exited with {self.proc.returncode}: "
                                 f"{self.log_path.read_text()[-2000:]}")
        try:
            if self.client is None:  # a client-mode session needs the service listening
                self.client = RelocClient(endpoint(self.port), map=MAP, timeout=30)
            return not self.client.status(timeout=1).replaying
        except (ConnectionError, NoReplyError, ServiceBusy):   # busy: retry, as it asks
            return False

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)
        self.close()

    def terminate(self) -> int:
        self.proc.send_signal(signal.SIGTERM)
        code = self.proc.wait(30)
        self.close()
        return code

    def close(self) -> None:
        """Kill the process if it still runs; close the client and the log."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        if self.client is not None:
            self.client.close()
        self.log.close()


# -- the ground station of deploy/ground ------------------------------------------------------

def _json5_copy(src: Path, dst: Path, replace: dict[str, str]) -> Path:
    """``src`` with its absolute /etc/reloc paths pointed at the test's files."""
    text = src.read_text()
    for old, new in replace.items():
        assert old in text, f"{src.name} no longer mentions {old}"
        text = text.replace(old, new)
    dst.write_text(text)
    return dst


def _listen_on(conf: zenoh.Config, endpoint: str) -> zenoh.Config:
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    return conf


@contextmanager
def ground_station(tmp: Path, *, tls: Path | None = None) -> Iterator[str]:
    """deploy/ground's router (router.json5, or router-tls.json5 with ``tls`` certificates)
    and services service-a (maps drone1, lab) and service-b (map drone2); the endpoint."""
    port = free_port()
    if tls is None:
        creds = tmp / "credentials.txt"
        creds.write_text((GROUND / "credentials.example.txt").read_text())
        router_file = _json5_copy(GROUND / "router.json5", tmp / "router.json5",
                                  {"/etc/reloc/credentials.txt": str(creds)})
        endpoint, service_zenoh = f"tcp/127.0.0.1:{port}", GROUND / "service-zenoh.json5"
    else:
        paths = {"/etc/reloc/certs": str(tls)}
        router_file = _json5_copy(GROUND / "router-tls.json5", tmp / "router.json5", paths)
        service_zenoh = _json5_copy(GROUND / "service-zenoh-tls.json5",
                                    tmp / "service-zenoh.json5", paths)
        endpoint = f"tls/localhost:{port}"
    router_conf = _listen_on(zenoh.Config.from_file(str(router_file)), endpoint)
    with ExitStack() as stack:
        router = zenoh.open(router_conf)
        stack.callback(router.close)
        for name in ("service-a", "service-b"):
            conf = with_overrides(load_config(GROUND / f"{name}.toml"), connect=[endpoint],
                                  storage=str(tmp / name))
            conf = dataclasses.replace(conf, zenoh=dataclasses.replace(
                conf.zenoh, config_file=str(service_zenoh)))
            stack.enter_context(Service(conf))
        yield endpoint


def user_client(endpoint: str, map_name: str, user: str | None, password: str | None = None,
                **kw) -> RelocClient:
    """A client in mode client, authenticated as ``user`` (None: no credentials)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    if user is not None:
        conf.insert_json5("transport/auth/usrpwd",
                          json.dumps({"user": user, "password": password}))
    return RelocClient(endpoint, map=map_name, config=conf, **kw)


def ground_conf(name: str, port: int, storage: Path, **service) -> ServiceConf:
    """deploy/ground/<name>.toml joining the router on ``port`` without credentials."""
    conf = with_overrides(load_config(GROUND / f"{name}.toml"), connect=[endpoint(port)],
                          storage=str(storage))
    return dataclasses.replace(conf, zenoh=dataclasses.replace(conf.zenoh, config_file=""),
                               service=dataclasses.replace(conf.service, workers=1,
                                                           **service))


def streamed_pose_covariance(kf_id: int) -> np.ndarray | None:
    """Even keyframes are put with a pose covariance of their own, odd ones without."""
    return None if kf_id % 2 else np.diag([1e-4, 4e-4, 9e-4, 1e-5, 2e-5, 3e-5]) * (1 + kf_id)


def stream_keyframes(client: RelocClient, scene, ids: range, pause: float) -> None:
    """Keyframes ``ids`` (the scene's, in turn) put one by one, ``pause`` seconds apart, with
    :func:`streamed_pose_covariance`."""
    for kf_id in ids:
        i = kf_id % len(scene.keyframe_images)
        client.add_keyframe(kf_id, scene.keyframe_images[i], scene.keyframe_poses[i],
                            camera_id="cam0", timestamp=float(kf_id),
                            pose_covariance=streamed_pose_covariance(kf_id))
        time.sleep(pause)
