"""Replicas that cannot diverge, on loopback behind a router: a replica follows only a peer
serving its map's identity (a different map under the same name is refused, loudly, and the
replica keeps its own), a new replica takes its peer's identity, and replicas compare map
version and content hash and report divergence (``replica_diverged``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from reloc_client import protocol as wire
from reloc_client.client import RelocClient, ServiceError, to_wire_image
from service_support import Events, endpoint, free_port, ground_conf, open_router, stream_keyframes

from reloc_service.service.app import Service
from reloc_service.service.divergence import DivergenceWatch
from reloc_service.service.runtime import MapRuntime


def _shifted(scene, kf_id: int, dx: float) -> np.ndarray:
    pose = np.array(scene.keyframe_poses[kf_id % len(scene.keyframe_poses)], dtype=float)
    pose[0, 3] += dx
    return pose


def _put(rt: MapRuntime, scene, kf_id: int, world_from_cam: np.ndarray) -> None:
    """Put a keyframe on ``rt`` directly (as its writer would), not through Zenoh."""
    i = kf_id % len(scene.keyframe_images)
    put = wire.KeyframePut(id=kf_id, image=to_wire_image(scene.keyframe_images[i]),
                           world_from_cam=wire.WirePose.from_matrix(world_from_cam),
                           camera_id="cam0", timestamp=float(kf_id))
    rt.put_keyframe(kf_id, put.encode())


def _replica(port: int, storage: Path, **service) -> Service:
    return Service(ground_conf("service-replica", port, storage, **service)).start()


#: Keyframes of the replica's own drone1 (the other one has 2).
OWN = 4


def test_replica_refuses_a_peer_serving_another_map_under_the_same_name(synthetic_scene,
                                                                        tmp_path, caplog):
    """The replica holds a 4-keyframe drone1; a peer then serves another drone1 (2
    keyframes, keyframe 0 elsewhere). The replica keeps its 4 and keyframe 0's pose, at its
    start and at the next, says why (ERROR naming both identities, replica_diverged event,
    status ``diverged``) and serves its own map. (4 keyframes: a map that differs from the
    peer's in its ids and poses; each mapped keyframe costs a fraction of a second.)"""
    scene = synthetic_scene
    port = free_port()
    with open_router(port):
        replica = _replica(port, tmp_path / "a2")          # alone: its own map of 4
        try:
            with RelocClient(endpoint(port), map="drone1", timeout=20) as client:
                events = Events(client)
                client.set_camera("cam0", scene.camera)
                events.wait("camera_added", id="cam0")
                stream_keyframes(client, scene, range(OWN), 0.0)
                events.wait("keyframe_added", id=OWN - 1, timeout=60)
                events.close()
            assert replica.wait_idle(60)
            own_id = replica.maps["drone1"].map_id
            pose0 = replica.maps["drone1"].map_state().keyframes[0].world_from_cam.copy()
        finally:
            replica.stop()
        with Service(ground_conf("service-a", port, tmp_path / "a")) as other, \
                RelocClient(endpoint(port), map="drone1", timeout=20) as client:
            other_rt = other.maps["drone1"]
            other_rt.put_camera("cam0", wire.CameraPut(
                "cam0", wire.WireCamera.from_dict(scene.camera.to_dict())).encode())
            for kf_id in range(2):                           # another drone1: 2 keyframes
                _put(other_rt, scene, kf_id, _shifted(scene, kf_id, 0.5))
            other_id = other_rt.map_id
            assert other_id and own_id and other_id != own_id
            events = Events(client)
            for _restart in range(2):
                caplog.clear()
                replica = _replica(port, tmp_path / "a2")
                try:
                    rt = replica.maps["drone1"]
                    assert rt.map_state().keyframe_ids() == list(range(OWN))
                    assert np.array_equal(rt.map_state().keyframes[0].world_from_cam, pose0)
                    assert rt.map_id == own_id
                    status = rt.status()
                    assert status.map_id == own_id and other_id in status.diverged
                    errors = [r.getMessage() for r in caplog.records
                              if r.levelname == "ERROR" and "not following" in r.getMessage()]
                    assert errors and own_id in errors[0] and other_id in errors[0], errors
                    event = events.wait("replica_diverged", reason="identity",
                                        peer="ground-a", timeout=10)
                    assert event.fields["map_id"] == own_id
                    assert event.fields["peer_map_id"] == other_id
                    events.seen.clear()
                finally:
                    replica.stop()
            assert other_rt.map_state().keyframe_ids() == [0, 1]   # the peer is untouched
            events.close()


def test_new_replica_takes_its_peers_identity_and_keeps_it(synthetic_scene, tmp_path):
    scene = synthetic_scene
    port = free_port()
    with open_router(port), \
            Service(ground_conf("service-a", port, tmp_path / "a")) as first, \
            RelocClient(endpoint(port), map="drone1", timeout=20) as client:
        events = Events(client)
        client.set_camera("cam0", scene.camera)
        events.wait("camera_added", id="cam0")
        stream_keyframes(client, scene, range(3), 0.0)
        events.wait("keyframe_added", id=2, timeout=60)
        assert first.wait_idle(60)
        first_id = first.maps["drone1"].map_id
        for _restart in range(2):   # its first start adopts the identity, the next keeps it
            replica = _replica(port, tmp_path / "a2", replica_check_s=0.0)
            try:
                rt = replica.maps["drone1"]
                assert rt.map_id == first_id and rt.status().map_id == first_id
                assert rt.map_state().keyframe_ids() == [0, 1, 2]
                assert rt.camera("cam0") is not None
                assert rt.status().diverged == ""
                # the map "lab" has no keyframes on either: it adopts the peer's identity too
                assert replica.maps["lab"].map_id == first.maps["lab"].map_id
            finally:
                replica.stop()
        events.close()


def test_replicas_report_other_content_at_the_same_version_and_a_lag(synthetic_scene,
                                                                     tmp_path):
    scene = synthetic_scene
    port = free_port()
    with open_router(port), \
            Service(ground_conf("service-a", port, tmp_path / "a")) as first, \
            RelocClient(endpoint(port), map="drone1", timeout=20) as client:
        rt1 = first.maps["drone1"]
        rt1.put_camera("cam0", wire.CameraPut(
            "cam0", wire.WireCamera.from_dict(scene.camera.to_dict())).encode())
        for kf_id in range(2):
            _put(rt1, scene, kf_id, _shifted(scene, kf_id, 0.0))
        replica = _replica(port, tmp_path / "a2", replica_check_s=0.0)
        try:
            rt2 = replica.maps["drone1"]
            watch = DivergenceWatch(replica.session, replica.prefix, replica.instance,
                                    replica.maps, interval_s=1.0, lag_s=0.0)
            s1, s2 = rt1.status(content_hash=True), rt2.status(content_hash=True)
            assert (s1.map_version, s1.content_hash) == (s2.map_version, s2.content_hash)
            assert watch.check_once()["drone1"] == ""
            events = Events(client)
            # keyframe 1 moved by 20 µm apart on each: same version (same landmarks), other content
            _put(rt1, scene, 1, _shifted(scene, 1, 1e-5))
            _put(rt2, scene, 1, _shifted(scene, 1, -1e-5))
            assert rt1.status().map_version == rt2.status().map_version
            assert watch.check_once()["drone1"] == ""      # once could be a put in flight
            found = watch.check_once()["drone1"]
            assert "other content" in found and "ground-a" in found, found
            assert rt2.status().diverged == found
            event = events.wait("replica_diverged", reason="content", timeout=10)
            assert event.fields["peer_content_hash"] == rt1.status(content_hash=True).content_hash
            # the same change on both: they agree again, the status says so
            _put(rt1, scene, 1, _shifted(scene, 1, 0.02))
            _put(rt2, scene, 1, _shifted(scene, 1, 0.02))
            assert watch.check_once()["drone1"] == "" == rt2.status().diverged
            # a keyframe the replica missed: it lags (lag_s = 0: at once)
            _put(rt1, scene, 2, _shifted(scene, 2, 0.0))
            found = watch.check_once()["drone1"]
            assert "lags peer ground-a" in found, found
            events.wait("replica_diverged", reason="lagging", timeout=10)
            events.close()
        finally:
            replica.stop()


def test_status_map_id_and_content_hash_round_trip():
    status = wire.StatusReply("lab", "drone1", 1, 2, True, 3, map_id="ab" * 16,
                              content_hash="cd" * 32, diverged="peer x: other content")
    assert wire.StatusReply.decode(status.encode()) == status
    bare = wire.StatusReply("lab", "drone1", 1, 2, True, 3)
    assert "map_id" not in bare.to_wire() and "content_hash" not in bare.to_wire()
    bad = dataclasses.replace(status, map_id="not-hex")
    try:
        wire.StatusReply.decode(bad.encode())
    except wire.ProtocolError as exc:
        assert exc.code is wire.ErrorCode.BAD_VALUE and "hex" in exc.message
    else:
        raise AssertionError("a map_id that is not hex decoded")


def test_a_lagging_replica_catches_up_from_its_peer(synthetic_scene, tmp_path):
    """Changes that reached one replica only (its peer's disk was full, say): keyframe 2
    added, keyframe 1 moved. The other replica is reported lagging and copies them; then
    both hold the same content, and nothing more is reported."""
    scene = synthetic_scene
    port = free_port()
    with open_router(port), \
            Service(ground_conf("service-a", port, tmp_path / "a")) as first:
        rt1 = first.maps["drone1"]
        rt1.put_camera("cam0", wire.CameraPut(
            "cam0", wire.WireCamera.from_dict(scene.camera.to_dict())).encode())
        for kf_id in range(2):
            _put(rt1, scene, kf_id, _shifted(scene, kf_id, 0.0))
        replica = _replica(port, tmp_path / "a2", replica_check_s=0.0)
        try:
            rt2 = replica.maps["drone1"]
            watch = DivergenceWatch(replica.session, replica.prefix, replica.instance,
                                    replica.maps, interval_s=1.0, lag_s=0.0,
                                    writer_for=replica.writes.writer_for)
            _put(rt1, scene, 2, _shifted(scene, 2, 0.0))       # only on the first
            _put(rt1, scene, 1, _shifted(scene, 1, 0.05))
            assert "lags peer ground-a" in watch.check_once()["drone1"]
            assert replica.wait_idle(60)
            assert rt2.map_state().keyframe_ids() == [0, 1, 2]
            assert np.allclose(rt2.map_state().keyframes[1].world_from_cam,
                               _shifted(scene, 1, 0.05), atol=1e-9)
            assert rt2.status().counters.get("catch_up_keyframes") == 2
            assert (rt2.status(content_hash=True).content_hash
                    == rt1.status(content_hash=True).content_hash)
            assert watch.check_once()["drone1"] == "" == rt2.status().diverged
        finally:
            replica.stop()


def test_an_acknowledgement_names_the_replicas_that_stored_the_keyframe(synthetic_scene,
                                                                        tmp_path):
    """Two replicas; the second refuses every keyframe after its first (its quota, standing
    in for a full disk). add_keyframe(wait=True, replicas=N) says which stored it: N=1
    succeeds with the one that did, N=2 raises naming who stored it and who refused."""
    scene = synthetic_scene
    port = free_port()
    full = ground_conf("service-replica", port, tmp_path / "a2", replica_check_s=0.0)
    full = dataclasses.replace(full, quotas=dataclasses.replace(full.quotas,
                                                                max_keyframes_per_map=1))
    with open_router(port), \
            Service(ground_conf("service-a", port, tmp_path / "a")) as first, \
            Service(full) as second, \
            RelocClient(endpoint(port), map="drone1", timeout=20) as client:
        client.set_camera("cam0", scene.camera, wait=True)
        assert first.wait_idle(30) and second.wait_idle(30)
        stored = client.add_keyframe(0, scene.keyframe_images[0], scene.keyframe_poses[0],
                                     camera_id="cam0", wait=True, replicas=2)
        assert stored == ("ground-a", "ground-a2")
        stored = client.add_keyframe(1, scene.keyframe_images[1], scene.keyframe_poses[1],
                                     camera_id="cam0", wait=True, replicas=1)
        assert "ground-a" in stored
        try:
            client.add_keyframe(2, scene.keyframe_images[2], scene.keyframe_poses[2],
                                camera_id="cam0", wait=True, replicas=2)
        except ServiceError as exc:
            assert exc.code is wire.ErrorCode.QUOTA_EXCEEDED, exc
            assert "1 of 2 replicas" in str(exc) and "['ground-a']" in str(exc), exc
            assert "refused by ground-a2" in str(exc), exc
        else:
            raise AssertionError("a keyframe one replica refused was acknowledged by two")
        assert first.wait_idle(30)
        assert first.maps["drone1"].map_state().keyframe_ids() == [0, 1, 2]
        assert second.maps["drone1"].map_state().keyframe_ids() == [0]
