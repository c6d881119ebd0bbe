"""The service over real Zenoh on loopback (free ports, multicast scouting off): every key
expression, several maps, liveliness discovery, a raw-zenoh client written from
docs/protocol.md, concurrency with keyframes streaming in, and a full disk (the malformed
inputs: test_service_malformed.py). The relocalizer is the real ``sbi+p3p`` on the synthetic
room of conftest.py."""
# ruff: noqa: E402

from __future__ import annotations

# reloc_client lives in clients/ (importable once the distribution is installed).
import threading
import time

import cv2
import msgpack
import numpy as np
import pytest
import zenoh
from reloc_client import protocol as wire
from reloc_client.client import RelocClient, ServiceBusy, ServiceError
from service_api_support import MAP, METHOD, assert_pose, served_api, upload
from service_support import Events, endpoint, free_port, raw_session, service_conf, wait_until

from reloc_service.service.app import Service
from reloc_service.storage import journal as journal_module


@pytest.fixture(scope="module")
def served(synthetic_scene, tmp_path_factory):
    """A service (2 workers, 2 queue slots, small limits) with map ``lab`` uploaded."""
    yield from served_api(synthetic_scene, tmp_path_factory)


# -- every key expression ------------------------------------------------------------------------

def test_relocalize_gives_the_right_pose(served, synthetic_scene):
    _, _, client, _ = served
    for image, gt in zip(synthetic_scene.query_images, synthetic_scene.query_poses, strict=True):
        result = client.relocalize(image, camera_id="cam0", request_id="q1", timestamp=12.5)
        assert result.ok, result.reason
        assert_pose(result.world_from_cam, gt)
        assert result.method == METHOD and result.request_id == "q1" and result.timestamp == 12.5
        assert result.inliers >= 20 and 0 < result.confidence <= 1
        assert result.matched_keyframe_ids and result.map_version > 0
        assert {"decode", "queue", "total"} <= set(result.timings)
        assert result.covariance is None or result.covariance.shape == (6, 6)


def test_relocalize_with_inline_camera_prior_and_hypotheses(served, synthetic_scene):
    _, _, client, _ = served
    gt = synthetic_scene.query_poses[0]
    result = client.relocalize(synthetic_scene.query_images[0], camera=synthetic_scene.camera,
                               prior=(gt, 1.0), hypotheses=2, image_format="png")
    assert result.ok
    assert_pose(result.world_from_cam, gt)
    far = gt.copy()
    far[:3, 3] += [20.0, 0.0, 0.0]
    result = client.relocalize(synthetic_scene.query_images[0], camera_id="cam0",
                               prior=(far, 0.5))
    assert not result.ok and result.reason          # no keyframe within the prior's radius


def test_relocalize_tracks_a_prior_with_a_covariance(served, synthetic_scene):
    _, _, client, _ = served
    gt = synthetic_scene.query_poses[1]
    covariance = np.diag([0.05**2] * 3 + [np.deg2rad(2.0) ** 2] * 3)
    result = client.relocalize(synthetic_scene.query_images[1], camera_id="cam0",
                               prior=(gt, None, covariance))
    assert result.ok and result.method == "track"      # tracked from the prior
    assert_pose(result.world_from_cam, gt)
    far = gt.copy()
    far[:3, 3] += [2.0, 0.0, 0.0]
    result = client.relocalize(synthetic_scene.query_images[1], camera_id="cam0",
                               prior=(far, None, covariance))
    assert result.method != "track"                    # the method answers a wrong prior
    assert not result.ok or np.linalg.norm(result.world_from_cam[:3, 3] - gt[:3, 3]) < 0.05


def test_keyframes_get_copies_the_map(served, synthetic_scene):
    _, port, client, _ = served
    infos = client.keyframes()
    ids = [i.id for i in infos]
    assert ids[:6] == list(range(6))
    first = infos[0]
    assert first.camera_id == "cam0" and first.timestamp == 0.0 and first.image is None
    assert first.num_landmarks > 0
    np.testing.assert_allclose(first.world_from_cam.matrix(), synthetic_scene.keyframe_poses[0],
                               atol=1e-6)
    with_images = client.keyframes(images=True)
    png = with_images[0].image
    grey = cv2.imdecode(np.frombuffer(png.data, np.uint8), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(grey, synthetic_scene.keyframe_images[0])
    # A get on one keyframe's key returns only that one.
    with raw_session(port) as session:
        replies = list(session.get(wire.keys.keyframe("reloc", MAP, 3), timeout=10))
    assert [wire.KeyframeInfo.decode(r.ok.payload.to_bytes()).id for r in replies] == [3]


def test_cameras_get(served, synthetic_scene):
    _, _, client, _ = served
    cams = client.cameras()
    assert list(cams) == ["cam0"]
    assert cams["cam0"].to_dict() == synthetic_scene.camera.to_dict()


def test_put_replace_and_delete_keyframe(served, synthetic_scene):
    _, _, client, events = served
    client.add_keyframe(50, synthetic_scene.keyframe_images[1], synthetic_scene.keyframe_poses[1],
                        camera_id="cam0")
    added = events.wait("keyframe_added", id=50)
    pose = synthetic_scene.keyframe_poses[2]
    client.add_keyframe(50, synthetic_scene.keyframe_images[2], pose, camera_id="cam0")
    wait_until(lambda: any(e.kind.value == "keyframe_added" and e.fields["id"] == 50
                           and e.fields["map_version"] > added.fields["map_version"]
                           for e in events.drain()))
    (info,) = [i for i in client.keyframes() if i.id == 50]
    np.testing.assert_allclose(info.world_from_cam.matrix(), pose, atol=1e-6)
    client.remove_keyframe(50)
    events.wait("keyframe_removed", id=50)
    assert 50 not in [i.id for i in client.keyframes()]
    client.remove_keyframe(50)                      # unknown now: rejected, nothing else
    events.wait("keyframe_rejected", id=50, code="UNKNOWN_KEYFRAME")


def test_train_answers_at_once_and_publishes_progress(served):
    _, _, client, events = served
    start = time.perf_counter()
    reply = client.train()
    assert time.perf_counter() - start < 2.0
    assert reply.accepted and reply.job_id
    done = events.wait("train_done", job_id=reply.job_id, timeout=120)
    assert done.fields["duration_s"] >= 0 and done.fields["map_version"] > 0
    kinds = [e.kind.value for e in events.seen if e.fields.get("job_id") == reply.job_id]
    assert kinds[0] == "train_started" and "train_progress" in kinds
    status = client.status()
    assert status.trained and not status.training


def test_status_reports_map_methods_counters_latency(served):
    _, _, client, _ = served
    client.relocalize(np.zeros((240, 320), np.uint8), camera_id="cam0")
    status = client.status()
    assert status.map == MAP and status.instance == "test"
    assert status.keyframes >= 6 and status.landmarks > 100 and status.map_version > 0
    assert status.methods == (METHOD, "bow+p3p") and status.default_method == METHOD
    assert status.cameras == ("cam0",)
    assert status.counters["keyframes_put"] >= 6 and status.counters["cameras_put"] == 1
    assert status.counters.get("relocalize_ok", 0) + status.counters["relocalize_failed"] >= 1
    assert {"p50", "p90", "p99", "max"} <= set(status.latency_s)
    assert status.uptime_s > 0


# -- several maps, discovery -------------------------------------------------------------------

def test_several_maps_and_map_created_by_first_put(served, synthetic_scene):
    _, port, _, _ = served
    with RelocClient(endpoint(port), map="second", timeout=30) as other:
        ev = Events(other)
        other.set_camera("c", synthetic_scene.camera)
        ev.wait("camera_added", id="c")
        other.add_keyframe(7, synthetic_scene.keyframe_images[0],
                           synthetic_scene.keyframe_poses[0], camera_id="c")
        ev.wait("keyframe_added", id=7)
        status = other.status()
        assert status.keyframes == 1 and status.cameras == ("c",)
        assert ("test", "second") in other.maps() and ("test", MAP) in other.maps()
        assert ("test", "empty") in other.maps()      # configured, no keyframe yet
        # every map is in memory (no max_resident_mb), the one a put created too
        assert {("test", "second"), ("test", MAP), ("test", "empty")} <= set(
            other.resident_maps())
        ev.close()
    with RelocClient(endpoint(port), map="empty", timeout=30) as empty:
        assert empty.status().keyframes == 0
        result = empty.relocalize(synthetic_scene.query_images[0],
                                  camera=synthetic_scene.camera)
        assert not result.ok and result.reason


def test_not_trained_method_is_reported(served, synthetic_scene):
    _, port, _, _ = served
    with RelocClient(endpoint(port), map="untrained", timeout=30) as c:
        ev = Events(c)
        upload(c, synthetic_scene, ev, ids=[0, 1])
        with pytest.raises(ServiceError) as info:
            c.relocalize(synthetic_scene.query_images[0], camera_id="cam0", method="bow+p3p")
        assert info.value.code is wire.ErrorCode.NOT_TRAINED
        ev.close()


def test_liveliness_discovery_and_an_instance_going_away(served):
    _, port, client, _ = served
    port2 = free_port()
    conf2 = service_conf(port2, maps=("far",), instance="second",
                         zenoh={"connect": [endpoint(port)]})
    changes: list[tuple[str, str]] = []
    with raw_session(port) as session:
        sub = session.liveliness().declare_subscriber(
            "reloc/@live/**", lambda s: changes.append((str(s.key_expr), str(s.kind))))
        second = Service(conf2).start()
        wait_until(lambda: ("second", "far") in client.maps(timeout=2))
        second.stop()
        wait_until(lambda: ("reloc/@live/second/far", str(zenoh.SampleKind.DELETE)) in changes)
        assert ("second", "far") not in client.maps(timeout=2)
        assert ("test", MAP) in client.maps(timeout=2)
        sub.undeclare()


def test_allow_new_maps_false_rejects_unknown_maps(synthetic_scene):
    port = free_port()
    with Service(service_conf(port, maps=("only",), allow_new_maps=False)):
        with RelocClient(endpoint(port), map="other", timeout=5) as c:
            ev = Events(c)
            c.set_camera("cam0", synthetic_scene.camera)
            ev.wait("camera_rejected", id="cam0", code="UNKNOWN_MAP")
            assert c.maps() == [("test", "only")]
            ev.close()


# -- a client written from docs/protocol.md alone ----------------------------------------------

def test_raw_zenoh_get_from_the_protocol_document(served, synthetic_scene):
    _, port, _, _ = served
    ok, png = cv2.imencode(".png", synthetic_scene.query_images[1])
    height, width = synthetic_scene.query_images[1].shape
    request = {"v": 1, "camera_id": "cam0", "request_id": "raw-1",
               "image": {"format": "png", "width": width, "height": height,
                         "data": png.tobytes()}}
    with raw_session(port) as session:
        replies = list(session.get("reloc/lab/relocalize",
                                   payload=msgpack.packb(request, use_bin_type=True),
                                   timeout=30))
    assert len(replies) == 1 and replies[0].ok is not None
    assert str(replies[0].ok.key_expr) == "reloc/lab/relocalize"
    answer = msgpack.unpackb(replies[0].ok.payload.to_bytes(), raw=False)
    assert answer["v"] == 1 and answer["status"] == "ok" and answer["request_id"] == "raw-1"
    tx, ty, tz = answer["world_from_cam"]["t"]
    qx, qy, qz, qw = answer["world_from_cam"]["q"]
    # Hamilton quaternion (x y z w) to a rotation matrix, written out as in the docs.
    rotation = np.array([
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
        [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
        [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)]])
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3], world_from_cam[:3, 3] = rotation, (tx, ty, tz)
    assert_pose(world_from_cam, synthetic_scene.query_poses[1])
    assert len(answer["covariance"]) == 36 if "covariance" in answer else True
    assert set(answer["timings"]) >= {"total"}


# -- malformed inputs: each gets its code, the service keeps answering -------------------------



def test_keyframe_with_svo_features_registers_their_landmarks(served, synthetic_scene):
    _, _, client, events = served
    scene = synthetic_scene
    depth = scene.keyframe_depths[2]
    kp = np.array([[100.0, 80.0], [200.0, 150.0], [60.0, 200.0]])
    z = depth[kp[:, 1].astype(int), kp[:, 0].astype(int)]
    bearings = scene.camera.unproject(kp)
    points_cam = bearings / bearings[:, 2:3] * z[:, None]
    pose = scene.keyframe_poses[2]
    points_world = points_cam @ pose[:3, :3].T + pose[:3, 3]
    client.add_keyframe(60, scene.keyframe_images[2], pose, camera_id="cam0",
                        features={"keypoints_px": kp, "landmark_ids": [900001, 900002, -1],
                                  "points_world": np.vstack([points_world[:2],
                                                             [np.nan] * 3])})
    events.wait("keyframe_added", id=60)
    (info,) = [i for i in client.keyframes() if i.id == 60]
    assert info.num_landmarks >= 2
    client.remove_keyframe(60)
    events.wait("keyframe_removed", id=60)


# -- concurrency ---------------------------------------------------------------------------------

@pytest.mark.slow
def test_eight_clients_query_while_keyframes_stream_in(served, synthetic_scene):
    """Every reply is a correct pose or an explicit busy; none is wrong, none is lost."""
    _, port, client, events = served
    scene = synthetic_scene
    outcomes: list[str] = []
    errors: list[BaseException] = []
    lock = threading.Lock()

    def query(worker: int) -> None:
        with RelocClient(endpoint(port), map=MAP, timeout=60) as c:
            for i in range(3):
                q = (worker + i) % len(scene.query_images)
                try:
                    result = c.relocalize(scene.query_images[q], camera_id="cam0")
                    assert result.ok, result.reason
                    assert_pose(result.world_from_cam, scene.query_poses[q])
                    outcome = "ok"
                except ServiceBusy:
                    outcome = "busy"
                except BaseException as exc:  # noqa: BLE001 - reported below
                    with lock:
                        errors.append(exc)
                    return
                with lock:
                    outcomes.append(outcome)

    threads = [threading.Thread(target=query, args=(w,)) for w in range(8)]
    for t in threads:
        t.start()
    stream_ids = [200 + i for i in range(len(scene.keyframe_images))]
    for kf_id, image, pose in zip(stream_ids, scene.keyframe_images, scene.keyframe_poses,
                                  strict=True):
        client.add_keyframe(kf_id, image, pose, camera_id="cam0")
    for t in threads:
        t.join(120)
    assert not errors, errors
    assert len(outcomes) == 24 and outcomes.count("ok") >= 1, outcomes
    for kf_id in stream_ids:
        events.wait("keyframe_added", id=kf_id)
    assert client.status().counters.get("busy", 0) == outcomes.count("busy")


# -- storage errors ------------------------------------------------------------------------------

def test_full_disk_is_a_storage_error_not_a_crash(synthetic_scene, tmp_path, monkeypatch):
    port = free_port()
    with Service(service_conf(port, tmp_path)), \
            RelocClient(endpoint(port), map="disk", timeout=30) as client:
        events = Events(client)
        upload(client, synthetic_scene, events, ids=[0, 1, 2])

        def disk_full(fd, data):
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(journal_module, "_write_all", disk_full)
        client.add_keyframe(3, synthetic_scene.keyframe_images[3],
                            synthetic_scene.keyframe_poses[3], camera_id="cam0")
        rejected = events.wait("keyframe_rejected", id=3)
        assert rejected.fields["code"] == "STORAGE_ERROR"
        assert "No space left" in rejected.fields["message"]
        assert client.relocalize(synthetic_scene.query_images[0], camera_id="cam0").ok
        monkeypatch.undo()
        client.add_keyframe(3, synthetic_scene.keyframe_images[3],
                            synthetic_scene.keyframe_poses[3], camera_id="cam0")
        events.wait("keyframe_added", id=3)
        assert client.status().keyframes == 4
        events.close()


# -- copying a map, prefixes ---------------------------------------------------------------------

def test_copy_a_map_to_another_instance_through_keyframes_get(served, synthetic_scene):
    """A tool reads every keyframe (with images) from one service and puts them into another."""
    _, port, source, _ = served
    port2 = free_port()
    with Service(service_conf(port2, instance="copy", prefix="fleet/reloc")), \
            RelocClient(endpoint(port2), map="copied", prefix="fleet/reloc", timeout=30) as dest:
        events = Events(dest)
        for info in source.keyframes(images=True):
            if info.id >= 6:
                continue
            dest.add_keyframe(info.id, info.image, info.world_from_cam.matrix(),
                              camera=info.camera, timestamp=info.timestamp)
        for kf_id in range(6):
            events.wait("keyframe_added", id=kf_id)
        assert dest.maps() == [("copy", "copied")]        # only under its own prefix
        result = dest.relocalize(synthetic_scene.query_images[2], camera=synthetic_scene.camera)
        assert result.ok, result.reason
        assert_pose(result.world_from_cam, synthetic_scene.query_poses[2])
        events.close()
