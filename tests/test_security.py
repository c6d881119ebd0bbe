"""Security of the ground-station set-up with Zenoh's own mechanisms, on loopback: the router
of deploy/ground (user/password authentication or mutual TLS, access control rules) in this
process, the two service shards of deploy/ground behind it, drones and a ground tool as
clients. Every refusal of the access matrix is shown; so is every allowed operation, so a
refusal cannot be an accident of a broken set-up."""
# ruff: noqa: E402

from __future__ import annotations

import importlib.util
import json
import time
from contextlib import ExitStack
from pathlib import Path

import pytest
import zenoh
from reloc_client.client import NoReplyError, RelocClient, ServiceError
from service_support import (
    CREDENTIALS,
    GROUND,
    ROOT,
    Events,
    ground_station,
    user_client,
    wait_until,
)


def _gen_certs():
    spec = importlib.util.spec_from_file_location("gen_certs", ROOT / "scripts" / "gen_certs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    """A CA, a server certificate for localhost and client certificates by common name."""
    out = tmp_path_factory.mktemp("certs")
    _gen_certs().generate(out, clients=("reloc-service", "ground", "drone1", "drone2"))
    return out


def tls_client(endpoint: str, map_name: str, certs: Path, name: str | None, **kw
               ) -> RelocClient:
    """A mutual-TLS client presenting ``certs/<name>.pem`` (None: no client certificate)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    tls = {"root_ca_certificate": str(certs / "ca.pem")}
    if name is not None:
        tls.update(connect_private_key=str(certs / f"{name}.key"),
                   connect_certificate=str(certs / f"{name}.pem"), enable_mtls=True)
    conf.insert_json5("transport/link/tls", json.dumps(tls))
    return RelocClient(endpoint, map=map_name, config=conf, **kw)


def _status(client: RelocClient):
    try:
        return client.status(timeout=2)
    except NoReplyError:
        return None


def check_access_matrix(scene, ground: RelocClient, drone1: RelocClient,
                        drone1_on_2: RelocClient, ground_on_2: RelocClient) -> None:
    """The refusal matrix: drone1 may put on its own map, relocalize and read status; its
    keyframe put to drone2's map, its train query, its keyframe delete and its map copy never
    reach a service; the ground tool may train and delete."""
    events = Events(ground)                       # ground follows map drone1's events
    events2 = Events(ground_on_2)                 # ... and map drone2's
    wait_until(lambda: _status(ground) and _status(ground_on_2), timeout=20)
    ground.set_camera("cam0", scene.camera)       # ground: camera put allowed
    events.wait("camera_added", id="cam0")
    drone1.set_camera("cam1", scene.camera)       # drone1: camera put on its own map allowed
    events.wait("camera_added", id="cam1")
    # drone1 writes to map drone2 first, then to its own map: once its own put has arrived,
    # the earlier one would have too (one ordered link), had the router forwarded it.
    drone1_on_2.set_camera("cam0", scene.camera)
    drone1_on_2.add_keyframe(7, scene.keyframe_images[0], scene.keyframe_poses[0],
                             camera=scene.camera)
    for kf_id in range(3):
        drone1.add_keyframe(kf_id, scene.keyframe_images[kf_id], scene.keyframe_poses[kf_id],
                            camera_id="cam1")
    events.wait("keyframe_added", id=2)
    assert drone1.status().keyframes == 3         # drone1: status query allowed
    status2 = ground_on_2.status()
    assert status2.keyframes == 0 and status2.cameras == ()
    assert not [e for e in events2.drain() if e.kind.value != "map_saved"], \
        "drone1's puts on map drone2 reached the service"
    # drone1: relocalize answered (a pose, or an error reply such as not trained: a reply);
    # the first query builds and trains the default method, seconds on a loaded machine
    try:
        drone1.relocalize(scene.query_images[0], camera_id="cam1", timeout=30.0)
    except ServiceError:
        pass
    # drone1: train, delete and map copy are dropped by the router
    with pytest.raises(NoReplyError):
        drone1.train()
    drone1.remove_keyframe(0)
    with pytest.raises(NoReplyError):
        drone1.keyframes()
    time.sleep(0.5)
    status = ground.status()
    assert status.keyframes == 3 and not status.training
    assert not [e for e in events.drain() if e.kind.value in ("train_started",
                                                              "keyframe_removed")]
    # ground: delete and train allowed
    ground.remove_keyframe(0)
    events.wait("keyframe_removed", id=0)
    assert ground.train().accepted
    events.wait("train_started")
    events.close()
    events2.close()


def test_user_password_authentication_and_access_rules(synthetic_scene, tmp_path):
    with ground_station(tmp_path) as ep, ExitStack() as stack:
        # refused at connection time
        with pytest.raises(ConnectionError):
            user_client(ep, "drone1", None)
        with pytest.raises(ConnectionError):
            user_client(ep, "drone1", "drone1", "not-the-password")
        with pytest.raises(ConnectionError):
            user_client(ep, "drone1", "intruder", CREDENTIALS["drone1"])
        # the drone's own config file (deploy/ground/drone-client.json5) with the endpoint
        drone_conf = zenoh.Config.from_file(str(GROUND / "drone-client.json5"))
        drone1 = stack.enter_context(RelocClient(ep, map="drone1", config=drone_conf,
                                                 timeout=3))
        drone1_on_2 = stack.enter_context(
            user_client(ep, "drone2", "drone1", CREDENTIALS["drone1"], timeout=3))
        ground = stack.enter_context(user_client(ep, "drone1", "ground", CREDENTIALS["ground"]))
        ground_on_2 = stack.enter_context(
            user_client(ep, "drone2", "ground", CREDENTIALS["ground"]))
        check_access_matrix(synthetic_scene, ground, drone1, drone1_on_2, ground_on_2)


def test_mutual_tls_and_access_rules_by_certificate_name(synthetic_scene, certs, tmp_path):
    other_ca = tmp_path / "other-ca"
    _gen_certs().generate(other_ca, clients=("drone1",))
    with ground_station(tmp_path, tls=certs) as ep, ExitStack() as stack:
        with pytest.raises(ConnectionError):           # no client certificate
            tls_client(ep, "drone1", certs, None)
        with pytest.raises(ConnectionError):           # a certificate from another CA
            conf = zenoh.Config()
            conf.insert_json5("mode", '"client"')
            conf.insert_json5("transport/link/tls", json.dumps({
                "root_ca_certificate": str(certs / "ca.pem"),
                "connect_private_key": str(other_ca / "drone1.key"),
                "connect_certificate": str(other_ca / "drone1.pem"), "enable_mtls": True}))
            RelocClient(ep, map="drone1", config=conf)
        with pytest.raises(ConnectionError):           # plain TCP to a TLS port
            user_client(ep.replace("tls/localhost", "tcp/127.0.0.1"), "drone1", None)
        drone1 = stack.enter_context(tls_client(ep, "drone1", certs, "drone1", timeout=3))
        drone1_on_2 = stack.enter_context(tls_client(ep, "drone2", certs, "drone1", timeout=3))
        ground = stack.enter_context(tls_client(ep, "drone1", certs, "ground"))
        ground_on_2 = stack.enter_context(tls_client(ep, "drone2", certs, "ground"))
        check_access_matrix(synthetic_scene, ground, drone1, drone1_on_2, ground_on_2)


def test_gen_certs_names_the_clients(certs):
    import subprocess

    for name in ("server", "reloc-service", "drone1"):
        out = subprocess.run(["openssl", "x509", "-in", str(certs / f"{name}.pem"), "-noout",
                              "-subject", "-issuer"], capture_output=True, text=True, check=True)
        cn = "localhost" if name == "server" else name
        assert f"CN = {cn}" in out.stdout and "CN = reloc-test-ca" in out.stdout
    verify = subprocess.run(["openssl", "verify", "-CAfile", str(certs / "ca.pem"),
                             str(certs / "drone1.pem")], capture_output=True, text=True)
    assert verify.returncode == 0, verify.stderr
    assert (certs / "drone1.key").stat().st_mode & 0o077 == 0
