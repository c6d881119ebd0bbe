"""Deployment set-ups: every TOML in config/ serves behind a Zenoh router, ``reloc router`` as a
process (from flags and from config/router.json5), and ``reloc serve`` exiting on SIGINT."""
# ruff: noqa: E402

from __future__ import annotations

# reloc_client lives in clients/ (importable once the distribution is installed).
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh
from reloc_client.client import NoReplyError, RelocClient
from service_support import ROOT, Events, endpoint, free_port, wait_until

from reloc_service.core.cameras import PinholeCamera
from reloc_service.service.app import Service
from reloc_service.service.config import load_config, with_overrides

CAMERA = PinholeCamera(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5)
CONFIGS = sorted((ROOT / "config").glob("*.toml"))


def open_router(port: int) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([endpoint(port)]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def connected_client(port: int, map_name: str) -> RelocClient:
    return wait_until(lambda: _try_client(port, map_name), timeout=30, interval=0.2)


def _try_client(port: int, map_name: str) -> RelocClient | None:
    try:
        return RelocClient(endpoint(port), map=map_name, timeout=10)
    except ConnectionError:
        return None


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_every_config_serves_behind_a_router(path: Path, tmp_path):
    router_port = free_port()
    conf = with_overrides(load_config(path), listen=[], connect=[endpoint(router_port)],
                          storage=str(tmp_path), instance="smoke")
    with open_router(router_port), Service(conf) as service:
        name = sorted(conf.maps)[0] if conf.maps else "smoke"
        with RelocClient(endpoint(router_port), map=name, timeout=10) as client:
            events = Events(client)
            client.set_camera("c", CAMERA)
            events.wait("camera_added", id="c")
            status = wait_until(lambda: _status(client))
            assert status.instance == "smoke" and status.cameras == ("c",)
            assert status.methods == service.methods
            events.close()


def _status(client: RelocClient):
    try:
        return client.status(timeout=2)
    except NoReplyError:
        return None


def _spawn(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", *args], cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)},
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


# the router from config/router.json5 is a second process start (about 5 s): slow; the
# router from flags runs by default
@pytest.mark.parametrize("with_file", [False, pytest.param(True, marks=pytest.mark.slow)],
                         ids=["flags", "router.json5"])
def test_reloc_router_process_connects_service_and_client(with_file, tmp_path):
    port = free_port()
    args = ["router", "--listen", endpoint(port)]
    if with_file:
        args += ["--config", str(ROOT / "config" / "router.json5")]
    router = _spawn(*args)
    try:
        client = connected_client(port, "viaroute")
        conf = with_overrides(load_config(None), mode="client", listen=[],
                              connect=[endpoint(port)], storage="", instance="behind")
        with Service(conf), client:
            events = Events(client)
            client.set_camera("c", CAMERA)
            events.wait("camera_added", id="c")
            assert ("behind", "viaroute") in client.maps()
            events.close()
        router.send_signal(signal.SIGINT)
        assert router.wait(20) == 0
    finally:
        if router.poll() is None:
            router.kill()
            router.wait()


@pytest.mark.slow   # a reloc serve process started and stopped: about 8 s
def test_reloc_serve_exits_cleanly_on_sigint(tmp_path):
    port = free_port()
    serve = _spawn("serve", "--listen", endpoint(port), "--storage", str(tmp_path),
                   "--instance", "sig")
    try:
        client = connected_client(port, "m")
        with client:
            events = Events(client)
            client.set_camera("c", CAMERA)
            events.wait("camera_added", id="c")
            assert ("sig", "m") in client.maps()
        serve.send_signal(signal.SIGINT)
        assert serve.wait(30) == 0
        log = serve.stdout.read().decode()
        assert "signal SIGINT: shutting down" in log and "stopped" in log
    finally:
        if serve.poll() is None:
            serve.kill()
            serve.wait()
    assert (tmp_path / "m" / "service.json").is_file()   # final snapshot


def test_bad_config_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[service]\nworkres = 2\n")
    proc = subprocess.run([sys.executable, "-m", "reloc_service.cli.main", "serve", "--config",
                           str(bad)], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert "workres" in proc.stderr and "workers" in proc.stderr
