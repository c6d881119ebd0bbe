"""A map with a journal backlog is served from its snapshot while the backlog replays behind
it (status says how far, queries answer from what is replayed, puts wait and apply after it),
and a replay stopped by the service's stop resumes at the next start where it stopped.

Real services on loopback (in-process, or ``reloc serve`` processes for the slow ones), real
journal files written as the service writes them (identity, sequence numbers)."""

from __future__ import annotations

import json
import re
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import msgpack
import pytest
from reloc_client import protocol as wire
from reloc_client.client import (
    RelocClient,
    ServiceBusy,
    ServiceError,
    to_wire_camera,
    to_wire_image,
    to_wire_pose,
)
from reloc_client.protocol import ErrorCode
from reloc_client.result import RelocStatus
from service_support import Events, endpoint, free_port, service_conf, wait_until
from storage_support import answers, connect, serve, write_config

from reloc_service.service.app import Service
from reloc_service.service.config import ServiceConf
from reloc_service.service.durability import MapStore
from reloc_service.service.runtime import MapRuntime
from reloc_service.storage.journal import Journal

MAP = "backlog"


def numbered_journal(map_dir: Path, scene, n: int) -> None:
    """A map directory whose journal (with an identity and sequence numbers, as the service
    writes it) holds camera cam0 and ``n`` keyframe puts, no snapshot: a start replays
    ``n + 1`` records."""
    store = MapStore(MAP, map_dir)
    store.journal.identity = uuid.uuid4()
    store.journal.open()
    camera = wire.CameraPut("cam0", to_wire_camera(scene.camera)).encode()
    store.append({"op": "cam", "id": "cam0", "payload": camera})
    for kf_id in range(n):
        i = kf_id % len(scene.keyframe_images)
        put = wire.KeyframePut(id=kf_id, image=to_wire_image(scene.keyframe_images[i]),
                               world_from_cam=to_wire_pose(scene.keyframe_poses[i]),
                               camera_id="cam0").encode()
        store.append({"op": "kf", "id": kf_id, "payload": put})
    store.close()


def camera_last_journal(map_dir: Path, scene, n: int) -> None:
    """A map directory whose journal holds ``n`` keyframe puts, each with its camera inline,
    then the put of camera cam1 as its last record (no snapshot)."""
    store = MapStore(MAP, map_dir)
    store.journal.identity = uuid.uuid4()
    store.journal.open()
    camera = to_wire_camera(scene.camera)
    for kf_id in range(n):
        i = kf_id % len(scene.keyframe_images)
        put = wire.KeyframePut(id=kf_id, image=to_wire_image(scene.keyframe_images[i]),
                               world_from_cam=to_wire_pose(scene.keyframe_poses[i]),
                               camera=camera).encode()
        store.append({"op": "kf", "id": kf_id, "payload": put})
    store.append({"op": "cam", "id": "cam1",
                  "payload": wire.CameraPut("cam1", camera).encode()})
    store.close()


def journal_seqs(map_dir: Path) -> dict[int, int]:
    """Keyframe id -> sequence number of its (last) put in the journal."""
    out = {}
    for raw in Journal(map_dir / "journal").replay():
        record = msgpack.unpackb(raw, raw=False)
        if record["op"] == "kf":
            out[record["id"]] = record["seq"]
    return out


def progress(client: RelocClient) -> tuple[bool, int, int]:
    """(replaying, records replayed, records to replay) from the map's status."""
    st = client.status(timeout=5)
    return (st.replaying, st.counters.get("replay_records_done", -1),
            st.counters.get("replay_records_total", -1))


def backlog_conf(storage: Path, scene, write_journal: Callable[[Path, object, int], None],
                 n: int) -> tuple[ServiceConf, int]:
    """The configuration of an in-process service (worker threads, no training, no
    snapshots) over ``storage`` on a free port, and that port, once ``write_journal`` has
    written map ``MAP``'s backlog of ``n`` keyframes."""
    write_journal(storage / MAP, scene, n)
    port = free_port()
    return service_conf(port, storage, train_on_load=False, snapshot_every=0,
                        worker_mode="thread"), port


@contextmanager
def replay_held_after(rt: MapRuntime, records: int) -> Iterator[None]:
    """Map ``rt``'s journal replay held between two records (its apply lock taken) once at
    least ``records`` are replayed: what the test does meanwhile happens during the replay,
    however fast or slow the machine replays."""
    lock = rt.apply_lock()
    while True:
        lock.acquire()
        if rt.restore_report.replayed >= records or not rt.replaying:
            break
        lock.release()
        time.sleep(0.002)
    try:
        assert rt.replaying, "replayed too fast to hold the replay during it"
        yield
    finally:
        lock.release()


def test_a_map_is_served_while_its_backlog_replays_and_a_put_applies_after_it(
        synthetic_scene, tmp_path):
    n = 8
    storage = tmp_path / "storage"
    conf, port = backlog_conf(storage, synthetic_scene, numbered_journal, n)
    service = Service(conf)
    started = time.monotonic()
    service.start(wait_ready=False)
    try:
        wait_until(lambda: MAP in service.maps, timeout=60, interval=0.01)
        rt = service.maps[MAP]
        with RelocClient(endpoint(port), map=MAP, timeout=30) as client:
            with replay_held_after(rt, 2):   # cam0 and a keyframe replayed, 7 to come
                wait_until(lambda: answers(client), timeout=60, interval=0.05)
                replaying, done, total = progress(client)
                assert replaying, "the map should be served while its journal replays"
                assert total == n + 1 and 1 <= done < total
                events = Events(client)
                # a put meanwhile waits for the backlog, then is journaled and applied after it
                client.add_keyframe(100, synthetic_scene.keyframe_images[0],
                                    synthetic_scene.keyframe_poses[0], camera_id="cam0")
                result = client.relocalize(synthetic_scene.query_images[0], camera_id="cam0")
                assert result.status in (RelocStatus.OK, RelocStatus.NOT_RELOCALIZED)
            events.wait("keyframe_added", id=100, timeout=120)
            st = client.status()
            assert not st.replaying and "replay_records_done" not in st.counters
            assert st.keyframes == n + 1
            assert st.counters["restore_records_replayed"] == n + 1
            events.close()
        print(f"backlog of {n + 1} records replayed in {time.monotonic() - started:.1f} s")
    finally:
        service.stop(final_snapshot=False)
    seqs = journal_seqs(storage / MAP)
    assert seqs[100] == n + 2 and max(v for k, v in seqs.items() if k != 100) == n + 1


def test_a_camera_not_replayed_yet_is_busy_with_the_replay_progress_not_unknown(
        synthetic_scene, tmp_path):
    n = 8
    storage = tmp_path / "storage"
    conf, port = backlog_conf(storage, synthetic_scene, camera_last_journal, n)
    service = Service(conf)
    service.start(wait_ready=False)
    query = synthetic_scene.query_images[0]
    try:
        wait_until(lambda: MAP in service.maps, timeout=60, interval=0.01)
        rt = service.maps[MAP]
        with RelocClient(endpoint(port), map=MAP, timeout=30) as client:
            with rt.apply_lock():   # the replay waits before its next record: cam1 is last
                assert rt.replaying, "replayed too fast to query during it"
                wait_until(lambda: answers(client), timeout=30, interval=0.05)
                with pytest.raises(ServiceBusy) as busy:
                    client.relocalize(query, camera_id="cam1")
                done = progress(client)[1]
            assert busy.value.code is ErrorCode.BUSY
            message = busy.value.message
            assert "'cam1' is not on map 'backlog' yet" in message
            assert f"replaying its journal ({done} of {n + 1} records replayed)" in message
            assert "not replayed yet; retry" in message and "never put" not in message
            wait_until(lambda: not progress(client)[0], timeout=120, interval=0.1)
            result = client.relocalize(query, camera_id="cam1")
            assert result.status in (RelocStatus.OK, RelocStatus.NOT_RELOCALIZED)
            # once replayed, a camera the map does not hold is final again
            with pytest.raises(ServiceError) as unknown:
                client.relocalize(query, camera_id="cam9")
            assert unknown.value.code is ErrorCode.UNKNOWN_CAMERA
            assert not isinstance(unknown.value, ServiceBusy)
            assert "never put" in unknown.value.message
    finally:
        service.stop(final_snapshot=False)


@pytest.mark.slow
def test_a_replay_stopped_midway_resumes_where_it_stopped(synthetic_scene, tmp_path):
    n = 8
    storage = tmp_path / "storage"
    conf, port = backlog_conf(storage, synthetic_scene, numbered_journal, n)
    service = Service(conf)
    service.start(wait_ready=False)
    try:
        with RelocClient(endpoint(port), map=MAP, timeout=30) as client:
            wait_until(lambda: answers(client) and progress(client)[1] >= 3, timeout=60,
                       interval=0.05)
            assert progress(client)[0]
    finally:
        service.stop()
    meta = json.loads((storage / MAP / "service.json").read_text())
    resumed_after = meta["last_seq"]
    assert 3 <= resumed_after < n + 1, "the stop should have saved what was replayed"
    service = Service(conf).start()
    try:
        with RelocClient(endpoint(port), map=MAP, timeout=30) as client:
            st = client.status()
            assert st.keyframes == n and not st.replaying
            # only the records after the stop snapshot were replayed the second time
            assert st.counters["restore_records_replayed"] == n + 1 - resumed_after
            assert {info.id for info in client.keyframes()} == set(range(n))
    finally:
        service.stop(final_snapshot=False)


# -- real processes ----------------------------------------------------------------------------

def replayed_counts(log: Path) -> list[int]:
    """The "N journal records replayed" counts ``reloc serve`` logged, in order."""
    return [int(m) for m in re.findall(r"\((\d+) journal records replayed\)", log.read_text())]


@pytest.mark.slow
def test_sigterm_during_a_served_replay_resumes_and_keeps_every_acknowledged_put(
        synthetic_scene, tmp_path):
    n = 60
    storage = tmp_path / "storage"
    numbered_journal(storage / MAP, synthetic_scene, n)
    config = write_config(tmp_path, port := free_port(), storage, ())
    first_log, second_log = tmp_path / "serve1.log", tmp_path / "serve2.log"
    start = time.monotonic()
    proc = serve(config, first_log)
    try:
        with connect(proc, port, MAP) as client:
            wait_until(lambda: answers(client), timeout=120, interval=0.1)
            first_answer = time.monotonic() - start
            replaying, done, total = progress(client)
            assert replaying and total == n + 1
            # the query names cam0, the journal's first record: before it is replayed, the
            # map knows no camera yet (BUSY: it may be in the records not replayed)
            wait_until(lambda: progress(client)[1] >= 1, timeout=120, interval=0.1)
            # process mode: the first query starts the worker processes (slow under load)
            client.relocalize(synthetic_scene.query_images[0], camera_id="cam0", timeout=120)
            wait_until(lambda: progress(client)[1] >= 10, timeout=300, interval=0.5)
        stopping = time.monotonic()
        proc.terminate()
        assert proc.wait(60) == 0
        stop_s = time.monotonic() - stopping
    finally:
        if proc.poll() is None:
            proc.kill()
    resumed_after = json.loads((storage / MAP / "service.json").read_text())["last_seq"]
    assert resumed_after >= 11
    proc = serve(config, second_log)
    try:
        with connect(proc, port, MAP) as client:
            wait_until(lambda: answers(client), timeout=120, interval=0.1)
            events = Events(client)
            client.add_keyframe(100, synthetic_scene.keyframe_images[1],
                                synthetic_scene.keyframe_poses[1], camera_id="cam0")
            events.wait("keyframe_added", id=100, timeout=300)
            st = client.status()
            assert st.keyframes == n + 1 and not st.replaying
            assert {info.id for info in client.keyframes()} == set(range(n)) | {100}
            events.close()
        proc.terminate()
        assert proc.wait(120) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    assert replayed_counts(second_log) == [n + 1 - resumed_after]
    print(f"first answer after {first_answer:.1f} s; SIGTERM at record {resumed_after} of "
          f"{n + 1} stopped in {stop_s:.1f} s; the restart replayed "
          f"{n + 1 - resumed_after} records")
