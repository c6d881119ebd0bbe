"""Maps whose names the protocol accepts are stored and restored under exactly those names,
however long their percent-encoding: 30 Hangul syllables, 64 emoji, 128 ``%`` characters
(each beyond NAME_MAX once encoded) are created by their first put and come back after a
restart; a directory written before names were recorded in it restores by its decoded name.

A real service on loopback (multicast scouting off), real keyframes and files on disk."""

from __future__ import annotations

from pathlib import Path

import pytest
from reloc_client.client import RelocClient
from service_support import endpoint, free_port, service_conf

from reloc_service.service.app import Service
from reloc_service.service.map_dirs import MAP_NAME_FILE, map_dirname

LONG_NAMES = ("\ud55c" * 30, "\U0001f681" * 64, "%" * 128)
OLD_STYLE = "caf\u00e9-1"


def put_keyframes(port: int, name: str, scene, ids: range) -> None:
    with RelocClient(endpoint(port), map=name, timeout=30) as client:
        client.set_camera("cam0", scene.camera, wait=True)
        for kf_id in ids:
            client.add_keyframe(kf_id, scene.keyframe_images[kf_id],
                                scene.keyframe_poses[kf_id], camera_id="cam0", wait=True)


def keyframe_ids(port: int, name: str) -> set[int]:
    with RelocClient(endpoint(port), map=name, timeout=30) as client:
        return {info.id for info in client.keyframes()}


def test_maps_with_names_beyond_name_max_are_created_and_restored_by_name(synthetic_scene,
                                                                          tmp_path):
    storage = tmp_path / "storage"
    port = free_port()
    conf = service_conf(port, storage, snapshot_every=0, train_on_load=False)
    service = Service(conf).start()
    try:
        for n, name in enumerate((*LONG_NAMES, OLD_STYLE)):
            put_keyframes(port, name, synthetic_scene, range(n % 2, n % 2 + 2))
        assert set(service.maps) == {*LONG_NAMES, OLD_STYLE}
    finally:
        service.stop()
    for name in LONG_NAMES:
        directory = storage / map_dirname(name)
        assert len(directory.name.encode()) <= 255
        assert (directory / MAP_NAME_FILE).read_text(encoding="utf-8") == name
    # a map directory as written before the name was recorded in it: decoded from its name
    (storage / map_dirname(OLD_STYLE) / MAP_NAME_FILE).unlink()
    service = Service(conf).start()
    try:
        assert set(service.maps) == {*LONG_NAMES, OLD_STYLE} and not service.registry.failed
        for n, name in enumerate((*LONG_NAMES, OLD_STYLE)):
            assert keyframe_ids(port, name) == set(range(n % 2, n % 2 + 2))
    finally:
        service.stop(final_snapshot=False)
    assert (storage / map_dirname(OLD_STYLE) / MAP_NAME_FILE).read_text() == OLD_STYLE


def test_storage_written_before_names_were_recorded_restores_unchanged(tmp_path: Path):
    storage = tmp_path / "storage"
    (storage / "lab%2B1" / "journal").mkdir(parents=True)     # "lab+1" as main encoded it
    service = Service(service_conf(free_port(), storage)).start()
    try:
        assert set(service.maps) == {"lab+1"} and not service.registry.failed
    finally:
        service.stop(final_snapshot=False)
    assert [p.name for p in storage.iterdir() if p.is_dir()] == ["lab%2B1"]   # no new map
    assert (storage / "lab%2B1" / MAP_NAME_FILE).read_text() == "lab+1"


@pytest.mark.slow
def test_worker_processes_relocalize_in_a_map_whose_name_is_beyond_name_max(synthetic_scene,
                                                                             tmp_path):
    port = free_port()
    service = Service(service_conf(port, tmp_path / "storage", worker_mode="process",
                                   train_on_load=False)).start()
    try:
        put_keyframes(port, LONG_NAMES[1], synthetic_scene, range(3))
        with RelocClient(endpoint(port), map=LONG_NAMES[1], timeout=60) as client:
            client.train(wait=True)
            # a worker process loads the map from a scratch copy named after it
            result = client.relocalize(synthetic_scene.query_images[0], camera_id="cam0")
            assert result.ok, result.reason
    finally:
        service.stop(final_snapshot=False)
