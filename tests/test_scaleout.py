"""Scale-out behind one Zenoh router, on loopback: shards (each instance serves its own maps,
clients only name a map), replicas (two instances serve one map; both receive every keyframe
put, queries reach both and the client keeps the first answer), a replica that starts late
copies the map from a running one (``bootstrap_from_peers``) without gaps or duplicates, and
queries go on when a replica process is killed."""
# ruff: noqa: E402

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from reloc_client.client import NoReplyError, RelocClient, ServiceError
from service_support import (
    GROUND,
    ROOT,
    Events,
    endpoint,
    free_port,
    ground_conf,
    open_router,
    stop_process,
    stream_keyframes,
    streamed_pose_covariance,
    wait_until,
)

from reloc_service.service.app import Service


def test_shards_serve_their_own_maps_and_clients_are_unaware(synthetic_scene, tmp_path):
    scene = synthetic_scene
    port = free_port()
    with open_router(port), \
            Service(ground_conf("service-a", port, tmp_path / "a")) as shard_a, \
            Service(ground_conf("service-b", port, tmp_path / "b")) as shard_b, \
            RelocClient(endpoint(port), map="drone1", timeout=10) as c1, \
            RelocClient(endpoint(port), map="drone2", timeout=10) as c2:
        ev1, ev2 = Events(c1), Events(c2)
        assert sorted(c1.maps()) == [("ground-a", "drone1"), ("ground-a", "lab"),
                                     ("ground-b", "drone2")]
        for client, ev in ((c1, ev1), (c2, ev2)):
            client.set_camera("cam0", scene.camera)
            ev.wait("camera_added", id="cam0")
            for kf_id in range(2):
                client.add_keyframe(kf_id, scene.keyframe_images[kf_id],
                                    scene.keyframe_poses[kf_id], camera_id="cam0")
            ev.wait("keyframe_added", id=1)
        assert c1.status().instance == "ground-a" and c2.status().instance == "ground-b"
        assert [k.id for k in c1.keyframes()] == [0, 1] == [k.id for k in c2.keyframes()]
        assert sorted(shard_a.maps) == ["drone1", "lab"] and sorted(shard_b.maps) == ["drone2"]
        time.sleep(0.5)
        # the shard that does not serve a map stays silent: no spurious rejection
        for ev in (ev1, ev2):
            assert not [e for e in ev.drain() if e.kind.value.endswith("_rejected")], ev.seen
        ev1.close()
        ev2.close()


def _same_pose_covariances(state, ids) -> bool:
    for kf_id in ids:
        got, put = state.keyframes[kf_id].pose_covariance, streamed_pose_covariance(kf_id)
        if (got is None) != (put is None) or (put is not None and not np.array_equal(got, put)):
            return False
    return True


@pytest.mark.slow
def test_late_replica_bootstraps_then_follows_the_stream(synthetic_scene, tmp_path):
    scene = synthetic_scene
    port = free_port()
    n = 12
    with open_router(port), \
            Service(ground_conf("service-a", port, tmp_path / "a")) as first, \
            RelocClient(endpoint(port), map="drone1", timeout=20) as client:
        events = Events(client)
        client.set_camera("cam0", scene.camera)
        events.wait("camera_added", id="cam0")
        stream_keyframes(client, scene, range(6), 0.0)                # the first replica has a map
        events.wait("keyframe_added", id=5, timeout=60)
        # the second replica starts while keyframes keep coming (during and after its copy)
        started: list[Service] = []
        starter = threading.Thread(target=lambda: started.append(Service(
            ground_conf("service-replica", port, tmp_path / "a2")).start()))
        starter.start()
        stream_keyframes(client, scene, range(6, n - 3), 0.1)
        starter.join(60)
        second = started[0]
        try:
            stream_keyframes(client, scene, range(n - 3, n), 0.05)     # after the copy: live only
            assert first.wait_idle(60) and second.wait_idle(60)
            rt1, rt2 = first.maps["drone1"], second.maps["drone1"]
            wait_until(lambda: len(rt2.map_state().keyframes) == n, timeout=30)
            s1, s2 = rt1.status(), rt2.status()
            # no gap: every keyframe on both; no duplicate: each applied once (one version each)
            assert rt1.map_state().keyframe_ids() == rt2.map_state().keyframe_ids() \
                == list(range(n))
            assert s1.map_version == s2.map_version > n, (s1.map_version, s2.map_version)
            copied = s2.counters.get("bootstrap_keyframes", 0)
            assert 6 <= copied <= n - 3 and s2.counters.get("keyframes_put") == n, s2.counters
            print(f"\nbootstrap: {copied} keyframes copied, {n - copied} from the live stream, "
                  f"{s2.counters.get('bootstrap_duplicates', 0)} buffered duplicates skipped")
            assert s2.cameras == ("cam0",)
            for kf_id in (0, n - 1):     # the same keyframe (pose) in both replicas
                k1 = rt1.map_state().keyframes[kf_id]
                k2 = rt2.map_state().keyframes[kf_id]
                assert abs(k1.world_from_cam - k2.world_from_cam).max() < 1e-9
                assert (k1.image == k2.image).all()
            # both replicas answer the same map; the client gets one answer
            assert {i for i, m in client.maps() if m == "drone1"} == {"ground-a", "ground-a2"}
        finally:
            second.stop()
        events.close()


# -- real processes ---------------------------------------------------------------------------

def _spawn(args: list[str], log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", *args], cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)},
                            stdout=open(log, "ab"), stderr=subprocess.STDOUT)


def _write_toml(tmp: Path, name: str, port: int, **service) -> Path:
    text = (GROUND / f"{name}.toml").read_text().replace(
        'config_file = "service-zenoh.json5"', "").replace(
        "tcp/127.0.0.1:7447", endpoint(port))
    for key, value in service.items():
        line = f"{key} = {json.dumps(value)}"
        text, n = re.subn(rf"^{key} = .*$", line, text, flags=re.M)
        if n == 0:
            text = text.replace("[service]\n", f"[service]\n{line}\n")
    path = tmp / f"{name}-{len(list(tmp.glob('*.toml')))}.toml"
    path.write_text(text)
    return path


@pytest.mark.slow
def test_processes_router_replicas_and_clients_survive_a_killed_replica(synthetic_scene,
                                                                         tmp_path):
    scene = synthetic_scene
    port = free_port()
    procs = [_spawn(["router", "--listen", endpoint(port)], tmp_path / "router.log")]
    try:
        client = wait_until(lambda: _try_client(port), timeout=30, interval=0.2)
        a = _write_toml(tmp_path, "service-a", port, instance="rep-1",
                        storage=str(tmp_path / "s1"))
        procs.append(_spawn(["serve", "--config", str(a)], tmp_path / "rep1.log"))
        wait_until(lambda: ("rep-1", "drone1") in client.maps(timeout=1), timeout=60)
        events = Events(client)
        client.set_camera("cam0", scene.camera)
        for kf_id in range(len(scene.keyframe_images)):
            client.add_keyframe(kf_id, scene.keyframe_images[kf_id],
                                scene.keyframe_poses[kf_id], camera_id="cam0")
        events.wait("keyframe_added", id=len(scene.keyframe_images) - 1, timeout=60)
        b = _write_toml(tmp_path, "service-replica", port, instance="rep-2",
                        storage=str(tmp_path / "s2"))
        procs.append(_spawn(["serve", "--config", str(b)], tmp_path / "rep2.log"))
        wait_until(lambda: ("rep-2", "drone1") in client.maps(timeout=1), timeout=90)
        # several clients query while a replica dies
        results: list[tuple[float, str]] = []
        stop = threading.Event()

        def worker() -> None:
            with RelocClient(endpoint(port), map="drone1", timeout=20) as c:
                i = 0
                while not stop.is_set():
                    try:
                        r = c.relocalize(scene.query_images[i % 3], camera_id="cam0")
                        results.append((time.monotonic(), "ok" if r.ok else "not"))
                    except (ServiceError, NoReplyError) as exc:
                        results.append((time.monotonic(), type(exc).__name__))
                    i += 1

        threads = [threading.Thread(target=worker) for _ in range(3)]
        for t in threads:
            t.start()
        wait_until(lambda: len(results) >= 6, timeout=120)
        killed_at = time.monotonic()
        procs[1].send_signal(signal.SIGKILL)
        procs[1].wait(10)
        wait_until(lambda: sum(t > killed_at + 1 for t, _ in results) >= 6, timeout=120)
        stop.set()
        for t in threads:
            t.join(60)
        after = [s for t, s in results if t > killed_at]
        assert after and all(s in ("ok", "ServiceBusy") for s in after), after
        assert all(s in ("ok", "ServiceBusy") for _, s in results), results
        assert [i for i, m in client.maps() if m == "drone1"] == ["rep-2"]
        print(f"\nreplicas: {len(results)} queries by 3 clients, {len(after)} after the kill, "
              f"outcomes {sorted(set(s for _, s in results))}")
        events.close()
        client.close()
    finally:
        for p in reversed(procs):
            stop_process(p, signal.SIGINT)


def _try_client(port: int) -> RelocClient | None:
    try:
        return RelocClient(endpoint(port), map="drone1", timeout=20)
    except ConnectionError:
        return None


def _answer(rt, scene, q: int, camera_id: str):
    """The pose ``rt`` gives for query ``q`` (through the wire handler), a 4x4 or None."""
    from reloc_client.client import to_wire_image
    from reloc_client.protocol import RelocalizeReply, RelocalizeRequest

    from reloc_service.service import handlers

    request = RelocalizeRequest(image=to_wire_image(scene.query_images[q]), camera_id=camera_id)
    reply = RelocalizeReply.decode(handlers.relocalize(rt, request.encode()), rt.limits)
    return None if reply.world_from_cam is None else reply.world_from_cam.matrix()


def test_bootstrapped_replica_keeps_the_intrinsics_keyframes_were_built_with(synthetic_scene,
                                                                              tmp_path):
    """Camera cam0 re-put with other intrinsics after keyframes 0-4 were built with the first
    ones (fault case 2 of docs/reliability.md). A replica that copies the map must replay the
    same history (each keyframe with the intrinsics it was built with, the camera change after
    them), end at the same map version and answer like the original (here within 1 mm)."""
    scene = synthetic_scene
    true_cam = scene.camera.to_dict()
    port = free_port()
    with open_router(port), \
            Service(ground_conf("service-a", port, tmp_path / "a")) as first, \
            RelocClient(endpoint(port), map="drone1", timeout=20) as client:
        events = Events(client)
        client.set_camera("cam0", true_cam)
        client.set_camera("truth", true_cam)     # queries name the true camera on both
        events.wait("camera_added", id="truth")
        stream_keyframes(client, scene, range(5), 0.0)
        events.wait("keyframe_added", id=4, timeout=60)
        client.set_camera("cam0", {**true_cam, "fx": true_cam["fx"] * 0.65})   # re-put
        # said, not silent: the keyframes built with cam0 keep their intrinsics
        events.wait("camera_added", id="cam0", changed=True, keyframes_kept=5)
        assert first.wait_idle(60)
        second = Service(ground_conf("service-replica", port, tmp_path / "a2")).start()
        try:
            rt1, rt2 = first.maps["drone1"], second.maps["drone1"]
            assert rt2.map_state().keyframe_ids() == list(range(5))
            for kf_id in range(5):     # the keyframes kept the intrinsics they were built with
                assert rt2.map_state().keyframes[kf_id].camera.to_dict() == true_cam
            assert _same_pose_covariances(rt2.map_state(), range(5))   # and their covariances
            assert rt2.camera("cam0").to_dict() == rt1.camera("cam0").to_dict()
            assert rt1.status().map_version == rt2.status().map_version
            for q in range(len(scene.query_images)):
                p1, p2 = _answer(rt1, scene, q, "truth"), _answer(rt2, scene, q, "truth")
                assert (p1 is None) == (p2 is None), q
                if p1 is not None:
                    assert abs(p1[:3, 3] - p2[:3, 3]).max() < 1e-3, (q, p1, p2)
            # same for a restart: the replica restores its own storage, copies nothing twice
            version = rt2.status().map_version
            second.stop()
            second = Service(ground_conf("service-replica", port, tmp_path / "a2")).start()
            rt2 = second.maps["drone1"]
            assert rt2.status().map_version == version == rt1.status().map_version
            assert rt2.status().counters.get("bootstrap_already_held") == 5
            assert all(rt2.map_state().keyframes[k].camera.to_dict() == true_cam
                       for k in range(5))
            assert _same_pose_covariances(rt2.map_state(), range(5))
        finally:
            second.stop()
        events.close()
