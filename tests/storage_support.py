"""Helpers shared by the storage tests (not a test module): a ``reloc serve`` process on a
storage directory and its clients, a listening peer whose event subscription exists before a
restore, a map's files and journal as the service leaves them, a journal written directly, and
a service filled with the scene's keyframes and the poses it gives to queries."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import msgpack
import numpy as np
from reloc_client import protocol as wire
from reloc_client.client import (
    NoReplyError,
    RelocClient,
    to_wire_camera,
    to_wire_image,
    to_wire_pose,
)
from service_support import MAP, ROOT, Events, endpoint, wait_until

from reloc_service.service.app import Service
from reloc_service.storage import journal as J
from reloc_service.storage.journal import Journal

#: The [service] keys of the damaged-storage tests' services: one method, SIFT features only.
#: What those tests check (restores, damaged files, verdicts, map check) does not depend on
#: the methods, and a map of one feature kind replays and loads in about half the time of
#: the default chain's (ORB and SIFT triangulated per keyframe, a bow vocabulary built at
#: every load).
ONE_METHOD = {"methods": ["sbi+p3p"], "default_method": "sbi+p3p"}
#: Two methods whose maps hold both feature kinds of the default chain (ORB, whose angles a
#: snapshot does not store, and SIFT), for the tests of what a snapshot holds per kind,
#: without the default chain's bow vocabulary built at every load.
ORB_AND_SIFT = {"methods": ["sbi+p3p:orb", "sbi+p3p"], "default_method": "sbi+p3p"}


def write_config(tmp: Path, port: int, storage: Path, maps: tuple[str, ...], *,
                 one_method: bool = False) -> Path:
    """A ``reloc serve`` config of ``storage`` serving ``maps``; with ``one_method``, the
    methods of :data:`ONE_METHOD`."""
    lines = ["[zenoh]", 'mode = "peer"', f'listen = ["{endpoint(port)}"]',
             "multicast_scouting = false", "[service]", 'instance = "faults"',
             f'storage = "{storage}"', "train_on_load = false", "snapshot_every = 0"]
    if one_method:
        lines += [f"{key} = {json.dumps(value)}" for key, value in ONE_METHOD.items()]
    lines += [f"[maps.{m}]" for m in maps]
    path = tmp / "service.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def serve(config: Path, log: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", "serve",
                             "--config", str(config)], cwd=ROOT, env=env,
                            stdout=log.open("ab"), stderr=subprocess.STDOUT)


def connect(proc: subprocess.Popen, port: int, map_name: str) -> RelocClient:
    """A client of the service in ``proc`` once it listens (it must not exit meanwhile)."""
    clients: list[RelocClient] = []

    def attempt() -> bool:
        assert proc.poll() is None, f"reloc serve exited with {proc.returncode}"
        try:
            clients.append(RelocClient(endpoint(port), map=map_name, timeout=30))
            return True
        except ConnectionError:
            return False

    wait_until(attempt, timeout=120, interval=0.1)
    return clients[0]


def answers(client: RelocClient) -> bool:
    try:
        client.status(timeout=1)
        return True
    except NoReplyError:
        return False


class Peer:
    """A client that listens (the service connects to it), so its event subscription exists
    before the service restores anything."""

    def __init__(self, port: int, map_name: str) -> None:
        import zenoh

        config = zenoh.Config()
        config.insert_json5("mode", '"peer"')
        config.insert_json5("listen/endpoints", json.dumps([endpoint(port)]))
        config.insert_json5("scouting/multicast/enabled", "false")
        self.client = RelocClient(map=map_name, config=config, timeout=30)
        self.events = Events(self.client)

    def close(self) -> None:
        self.events.close()
        self.client.close()


def kf_ids(client: RelocClient) -> set[int]:
    return {info.id for info in client.keyframes()}


def files_of(directory: Path) -> dict[str, bytes]:
    return {p.relative_to(directory).as_posix(): p.read_bytes()
            for p in sorted(directory.rglob("*")) if p.is_file()}


def journal_segment(map_dir: Path) -> Path:
    """The segment holding the records after the snapshot."""
    first = json.loads((map_dir / "service.json").read_text())["next_segment"]
    return map_dir / "journal" / J.segment_name(first)


def journal_of_keyframes(map_dir: Path, scene, n: int) -> None:
    """A map directory whose journal holds camera cam0 and ``n`` keyframe puts (no snapshot):
    a restart replays all of them."""
    journal = Journal(map_dir / "journal")
    journal.open()
    camera = wire.CameraPut("cam0", to_wire_camera(scene.camera)).encode()
    journal.append(msgpack.packb({"op": "cam", "id": "cam0", "payload": camera},
                                 use_bin_type=True))
    for kf_id in range(n):
        i = kf_id % len(scene.keyframe_images)
        put = wire.KeyframePut(id=kf_id, image=to_wire_image(scene.keyframe_images[i]),
                               world_from_cam=to_wire_pose(scene.keyframe_poses[i]),
                               camera_id="cam0").encode()
        journal.append(msgpack.packb({"op": "kf", "id": kf_id, "payload": put},
                                     use_bin_type=True))
    journal.close()


def camera_put(scene) -> bytes:
    return wire.CameraPut("cam0", wire.WireCamera.from_dict(scene.camera.to_dict())).encode()


def keyframe_put(scene, kf_id: int) -> bytes:
    i = kf_id % len(scene.keyframe_images)
    return wire.KeyframePut(id=kf_id, image=wire.WireImage.from_array(
        scene.keyframe_images[i]), world_from_cam=wire.WirePose.from_matrix(
        scene.keyframe_poses[i]), camera_id="cam0").encode()


def fill_map(service: Service, scene, ids: range) -> None:
    service.on_camera_sample(MAP, "cam0", camera_put(scene))
    for kf_id in ids:
        service.on_keyframe_sample(MAP, kf_id, keyframe_put(scene, kf_id))
    assert service.wait_idle(120)


def query_poses(port: int, scene, map_name: str = MAP) -> list[np.ndarray]:
    """The pose each query image gets (every query must be answered)."""
    out = []
    with RelocClient(endpoint(port), map=map_name, timeout=60) as client:
        for image in scene.query_images[:2]:
            result = client.relocalize(image, camera_id="cam0")
            assert result.ok, result.reason
            out.append(np.asarray(result.world_from_cam))
    return out


def listing(root: Path) -> list[tuple[str, int]]:
    return sorted((str(p.relative_to(root)), p.stat().st_size if p.is_file() else -1)
                  for p in root.rglob("*"))
