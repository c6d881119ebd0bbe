"""Storage faults (fault cases 3, 4, 6 and 7 of docs/reliability.md): a damaged journal record
costs that record only, a deleted ``map/CURRENT`` is reported and deletes nothing, one damaged
file fails its map and leaves the others served, and maps come up one by one after the Zenoh
session opens.

Real services on loopback (multicast scouting off), real keyframes of the synthetic room, real
files damaged on disk, and ``reloc serve`` in a subprocess where the process must survive."""
# ruff: noqa: E402

from __future__ import annotations

# reloc_client lives in clients/ (importable once the distribution is installed).
import json
import shutil
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
from reloc_client import protocol as wire
from reloc_client.client import (
    NoReplyError,
    RelocClient,
    ServiceError,
)
from service_support import Events, endpoint, free_port, service_conf, wait_until
from storage_support import (
    ONE_METHOD,
    Peer,
    answers,
    connect,
    files_of,
    journal_of_keyframes,
    journal_segment,
    kf_ids,
    serve,
    write_config,
)

from reloc_service.service.app import Service
from reloc_service.storage import journal as J
from reloc_service.storage.journal import Journal, scan_segment

GOOD, BAD = "good", "bad"
SNAPSHOT_IDS, JOURNAL_IDS = (0, 1, 2), (3, 4, 5)


def conf(port: int, storage: Path, **service):
    """Snapshots keep the keyframe images (``keyframe_images = "always"``), so a damaged
    image file is among the faults a restore must name; one method (``ONE_METHOD``)."""
    return service_conf(port, storage, maps=(GOOD, BAD), train_on_load=False,
                        snapshot_every=0, keyframe_images="always", **ONE_METHOD, **service)


def pose_covariance(kf_id: int) -> np.ndarray | None:
    """The pose covariance keyframe ``kf_id`` is put with: one of its own for even ids
    (1-3 cm, 0.2-0.6 deg, x and yaw correlated), none (the map's default) for odd ids."""
    if kf_id % 2:
        return None
    cov = np.diag(np.square([0.01, 0.02, 0.03, 0.0035, 0.007, 0.0105]) * (1 + kf_id))
    cov[0, 5] = cov[5, 0] = 0.3 * np.sqrt(cov[0, 0] * cov[5, 5])
    return cov


def upload(client: RelocClient, scene, events: Events, ids) -> None:
    for kf_id in ids:
        client.add_keyframe(kf_id, scene.keyframe_images[kf_id], scene.keyframe_poses[kf_id],
                            camera_id="cam0", pose_covariance=pose_covariance(kf_id))
    for kf_id in ids:
        events.wait("keyframe_added", id=kf_id)


@pytest.fixture(scope="module")
def template(synthetic_scene, tmp_path_factory) -> Path:
    """A storage with maps ``good`` and ``bad``: camera cam0, keyframes 0-2 in a snapshot,
    keyframes 3-5 in the journal after it (three records)."""
    storage = tmp_path_factory.mktemp("template") / "storage"
    port = free_port()
    service = Service(conf(port, storage)).start()
    try:
        for name in (GOOD, BAD):
            with RelocClient(endpoint(port), map=name, timeout=30) as client:
                events = Events(client)
                client.set_camera("cam0", synthetic_scene.camera)
                events.wait("camera_added", id="cam0")
                upload(client, synthetic_scene, events, SNAPSHOT_IDS)
                service.maps[name].start_snapshot(wait=True)
                upload(client, synthetic_scene, events, JOURNAL_IDS)
                events.close()
    finally:
        service.stop(final_snapshot=False)
    return storage


@pytest.fixture
def storage(template, tmp_path) -> Path:
    target = tmp_path / "storage"
    shutil.copytree(template, target)
    return target


def record_offsets(path: Path) -> list[tuple[int, int]]:
    """(offset, framed size) of every record of a clean segment."""
    scan = scan_segment(path)
    out, pos = [], scan.header_bytes
    for r in scan.records:
        out.append((pos, J._FRAME.size + len(r)))
        pos += J._FRAME.size + len(r)
    return out


def flip(path: Path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x10
    path.write_bytes(bytes(data))


# -- case 3: a damaged journal record costs that record only ------------------------------------

@pytest.mark.parametrize("where", ["payload", "length"])
def test_a_damaged_journal_record_loses_only_that_keyframe(storage, where):
    map_dir = storage / BAD
    segment = journal_segment(map_dir)
    offset, size = record_offsets(segment)[1]            # keyframe 4
    flip(segment, offset + (size - 1 if where == "payload" else 5))
    damaged = segment.read_bytes()
    port, peer_port = free_port(), free_port()
    peer = Peer(peer_port, BAD)
    service = Service(conf(port, storage, zenoh={"connect": [endpoint(peer_port)]})).start()
    try:
        assert kf_ids(peer.client) == {0, 1, 2, 3, 5}
        status = peer.client.status()
        assert status.counters["restore_journal_skipped"] == 1
        assert status.counters["restore_quarantine_files"] == 1
        [kept] = (map_dir / "journal" / J.QUARANTINE_DIR).iterdir()
        assert kept.read_bytes() == damaged[offset:offset + size]
        assert segment.read_bytes()[:len(damaged)] == damaged      # never rewritten
        event = peer.events.wait("storage_damaged")
        assert event.fields["failed"] is False and event.fields["journal_skipped"] == [
            [int(segment.stem), offset, size]]
    finally:
        service.stop(final_snapshot=False)
        peer.close()


# -- case 4: CURRENT deleted ---------------------------------------------------------------------

def test_deleted_current_is_restored_to_the_verified_snapshot_and_reported(storage, caplog):
    map_dir = storage / BAD
    snapshot = json.loads((map_dir / "service.json").read_text())["snapshot"]
    (map_dir / "map" / "CURRENT").unlink()
    port = free_port()
    with caplog.at_level("WARNING"):
        service = Service(conf(port, storage)).start()
    try:
        with RelocClient(endpoint(port), map=BAD, timeout=30) as client:
            assert kf_ids(client) == {*SNAPSHOT_IDS, *JOURNAL_IDS}
            assert client.status().counters["restore_snapshot_recovered"] == 1
        assert "CURRENT was missing" in caplog.text
        service.maps[BAD].start_snapshot(wait=True)
        assert (map_dir / "map" / "snapshots" / snapshot).is_dir()   # the one it was built from
    finally:
        service.stop(final_snapshot=False)


def test_deleted_current_without_service_file_fails_the_map_and_deletes_nothing(storage):
    map_dir = storage / BAD
    (map_dir / "map" / "CURRENT").unlink()
    (map_dir / "service.json").unlink()
    before = files_of(map_dir)
    port = free_port()
    service = Service(conf(port, storage)).start()
    try:
        with RelocClient(endpoint(port), map=BAD, timeout=30) as client:
            with pytest.raises(ServiceError) as err:
                client.status()
            assert err.value.code is wire.ErrorCode.STORAGE_ERROR
            assert "CURRENT" in err.value.message
        with RelocClient(endpoint(port), map=GOOD, timeout=30) as client:
            assert client.status().keyframes == 6
    finally:
        service.stop()
    assert files_of(map_dir) == before


# -- case 6: one damaged file fails its map only -------------------------------------------------

def _segment_header_byte(map_dir: Path) -> Path:
    path = journal_segment(map_dir)
    flip(path, 3)
    return path


def _stray_segment(map_dir: Path) -> Path:
    path = map_dir / "journal" / J.segment_name(999)
    path.write_bytes(b"this is not a journal segment, but named like one")
    return path


def _half_service_file(map_dir: Path) -> Path:
    path = map_dir / "service.json"
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2])
    return path


def _snapshot_image_bit(map_dir: Path) -> Path:
    current = (map_dir / "map" / "CURRENT").read_text().strip()
    path = map_dir / "map" / current / "images" / "1.png"
    flip(path, len(path.read_bytes()) // 2)
    return path


def _truncated_manifest(map_dir: Path) -> Path:
    current = (map_dir / "map" / "CURRENT").read_text().strip()
    path = map_dir / "map" / current / "manifest.json"
    path.write_bytes(path.read_bytes()[:100])
    return path


DAMAGE = {"segment_header_byte": _segment_header_byte, "stray_segment": _stray_segment,
          "half_service_json": _half_service_file, "snapshot_image_bit": _snapshot_image_bit,
          "truncated_manifest": _truncated_manifest}


#: The damage whose case queries the good map through worker processes (the default, as
#: reloc serve runs): each damage fails the bad map at its restore alike, before any query, so
#: the other cases query through threads and start no worker process (seconds each under load).
PROCESS_WORKERS_DAMAGE = "snapshot_image_bit"


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_one_damaged_file_fails_its_map_and_the_others_are_served(storage, synthetic_scene,
                                                                  damage):
    map_dir = storage / BAD
    damaged = DAMAGE[damage](map_dir)
    before = files_of(map_dir)
    port = free_port()
    mode = "process" if damage == PROCESS_WORKERS_DAMAGE else "thread"
    service = Service(conf(port, storage, worker_mode=mode)).start()     # does not raise
    try:
        with RelocClient(endpoint(port), map=GOOD, timeout=30) as good:
            assert kf_ids(good) == {*SNAPSHOT_IDS, *JOURNAL_IDS}
            assert good.relocalize(synthetic_scene.query_images[0], camera_id="cam0").ok
        with RelocClient(endpoint(port), map=BAD, timeout=30) as bad:
            for ask in (bad.status, bad.keyframes,
                        lambda: bad.relocalize(synthetic_scene.query_images[0],
                                               camera_id="cam0")):
                with pytest.raises(ServiceError) as err:
                    ask()
                assert err.value.code is wire.ErrorCode.STORAGE_ERROR
                assert damaged.name in err.value.message and "reloc map check" in \
                    err.value.message
            events = Events(bad)
            bad.add_keyframe(9, synthetic_scene.keyframe_images[0],
                             synthetic_scene.keyframe_poses[0], camera_id="cam0")
            rejected = events.wait("keyframe_rejected", id=9)
            assert rejected.fields["code"] == "STORAGE_ERROR"
            events.close()
    finally:
        service.stop()
    assert files_of(map_dir) == before                 # nothing rewritten, deleted or added


def test_a_stray_file_in_the_journal_directory_is_ignored(storage):
    (storage / BAD / "journal" / "notes.txt").write_text("left here by someone")
    port = free_port()
    service = Service(conf(port, storage)).start()
    try:
        with RelocClient(endpoint(port), map=BAD, timeout=30) as client:
            assert client.status().keyframes == 6
    finally:
        service.stop(final_snapshot=False)


def restored(client: RelocClient) -> bool:
    """The map answers and its journal backlog has replayed."""
    try:
        return not client.status(timeout=1).replaying
    except NoReplyError:
        return False


@pytest.mark.slow   # a reloc serve process restoring two maps: about 10 s; the same damage
# in-process is test_one_damaged_file_fails_its_map_and_the_others_are_served
def test_reloc_serve_keeps_running_with_a_damaged_map(storage, tmp_path):
    _snapshot_image_bit(storage / BAD)
    port = free_port()
    proc = serve(write_config(tmp_path, port, storage, (GOOD, BAD), one_method=True),
                 tmp_path / "serve.log")
    try:
        with connect(proc, port, GOOD) as good:
            wait_until(lambda: proc.poll() is not None or restored(good), timeout=120)
            assert proc.poll() is None, (tmp_path / "serve.log").read_text()[-2000:]
            assert good.status().keyframes == 6
        with RelocClient(endpoint(port), map=BAD, timeout=30) as bad:
            with pytest.raises(ServiceError, match="STORAGE_ERROR.*1.png"):
                bad.status()
        proc.terminate()
        assert proc.wait(60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()


# -- case 7: maps come up one by one -------------------------------------------------------------


@pytest.mark.slow
def test_a_small_map_is_served_while_a_big_one_replays(synthetic_scene, tmp_path):
    storage = tmp_path / "storage"
    journal_of_keyframes(storage / "big", synthetic_scene, 60)
    journal_of_keyframes(storage / "small", synthetic_scene, 2)
    before = files_of(storage / "big")
    config = write_config(tmp_path, port := free_port(), storage, ())
    # SIGTERM in the middle of the big replay: a prompt clean exit, nothing written (a
    # journal without sequence numbers replays from its start again).
    proc = serve(config, tmp_path / "serve1.log")
    try:
        with connect(proc, port, "small") as small:
            wait_until(lambda: restored(small), timeout=120, interval=0.1)
        start = time.monotonic()
        proc.terminate()
        assert proc.wait(60) == 0
        assert time.monotonic() - start < 30
    finally:
        if proc.poll() is None:
            proc.kill()
    written = {"map_name", ".lock"}   # the map's recorded name and its lock, at its open
    assert {k: v for k, v in files_of(storage / "big").items() if k not in written} == before
    start = time.monotonic()
    proc = serve(config, tmp_path / "serve2.log")
    try:
        with connect(proc, port, "small") as small, \
                RelocClient(endpoint(port), map="big", timeout=30) as big:
            wait_until(lambda: restored(small), timeout=120, interval=0.1)
            small_at = time.monotonic() - start
            assert small.status().keyframes == 2
            # the big map is served while it replays; a put meanwhile is applied after it
            wait_until(lambda: answers(big), timeout=120, interval=0.1)
            assert big.status().replaying, "the big map should still be replaying"
            events = Events(big)
            big.add_keyframe(100, synthetic_scene.keyframe_images[0],
                             synthetic_scene.keyframe_poses[0], camera_id="cam0")
            events.wait("keyframe_added", id=100, timeout=300)
            big_at = time.monotonic() - start
            assert big.status().keyframes == 61 and not big.status().replaying
            events.close()
        print(f"small map served after {small_at:.1f} s, big map after {big_at:.1f} s")
        proc.terminate()
        assert proc.wait(120) == 0
    finally:
        if proc.poll() is None:
            proc.kill()


# -- reloc map check ------------------------------------------------------------------------------

def test_map_check_reports_a_clean_map_and_exits_0(storage, capsys):
    from reloc_service.cli.main import main

    assert main(["map", "check", str(storage / GOOD)]) == 0
    out = capsys.readouterr().out
    assert ": ok" in out and "[CURRENT] [service.json]: ok" in out
    assert "3 good records, 0 skipped, torn tail 0 bytes" in out


def test_map_check_reports_skipped_records_torn_tails_and_quarantine(storage, capsys):
    from reloc_service.cli.main import main

    segment = journal_segment(storage / BAD)
    offset, size = record_offsets(segment)[0]
    flip(segment, offset + size - 1)
    with segment.open("ab") as fh:              # and a torn tail after the last record
        fh.write(J.frame(b"cut short")[:-4])
    before = files_of(storage / BAD)
    assert main(["map", "check", str(storage)]) == 1        # the whole storage
    out = capsys.readouterr().out
    assert f"{storage / GOOD}: ok" in out and f"{storage / BAD}: DAMAGED" in out
    assert "2 good records, 1 skipped, torn tail 21 bytes" in out
    assert files_of(storage / BAD) == before                 # read only
    # After a restore the skipped bytes are in quarantine, and the report lists them.
    port = free_port()
    Service(conf(port, storage)).start().stop(final_snapshot=False)
    assert main(["map", "check", "--json", str(storage / BAD)]) == 1
    [report] = json.loads(capsys.readouterr().out)
    assert report["damaged"] and len(report["quarantine"]) == 2    # the skipped and the torn


def test_keyframe_pose_covariances_survive_snapshot_and_journal(storage):
    """Keyframes 0-2 come back from the snapshot, 3-5 from the journal: each with the pose
    covariance it was put with (bit for bit), or none; a get of the keyframes says so."""
    port = free_port()
    with Service(conf(port, storage)) as service, \
            RelocClient(endpoint(port), map=GOOD, timeout=30) as client:
        state = service.maps[GOOD].map_state()
        for kf_id in (*SNAPSHOT_IDS, *JOURNAL_IDS):
            got, put = state.keyframes[kf_id].pose_covariance, pose_covariance(kf_id)
            assert (got is None) == (put is None), kf_id
            if put is not None:
                np.testing.assert_array_equal(got, put)
        infos = {info.id: info for info in client.keyframes()}
        assert infos[2].pose_covariance == tuple(pose_covariance(2).ravel())
        assert infos[3].pose_covariance is None


def _bad_covariance_put(kf_id: int, scene) -> bytes:
    """A KeyframePut whose pose covariance is not one (written past the encoder's check, as
    a damaged or foreign writer could)."""
    good = wire.KeyframePut(kf_id, wire.WireImage.from_array(scene.keyframe_images[0]),
                            wire.WirePose.from_matrix(scene.keyframe_poses[0]),
                            camera_id="cam0").encode()
    fields = msgpack.unpackb(good, raw=False)
    fields["pose_covariance"] = np.diag([1e-4, 1e-4, 1e-4, 1e-6, 1e-6, -1e-6]).ravel().tolist()
    return msgpack.packb(fields, use_bin_type=True)


def test_map_check_names_a_journaled_pose_covariance_that_is_not_one(storage, synthetic_scene,
                                                                     capsys):
    """A journal record carrying a keyframe whose pose covariance is not positive
    semi-definite: map check says which and why; the service skips it and serves the rest."""
    from reloc_service.cli.main import main

    map_dir = storage / BAD
    journal = Journal(map_dir / "journal")
    journal.open()
    journal.append(msgpack.packb({"op": "kf", "id": 9, "payload": _bad_covariance_put(
        9, synthetic_scene)}, use_bin_type=True))
    journal.close()
    assert main(["map", "check", str(map_dir)]) == 1
    out = capsys.readouterr().out
    # (a writer without the map's identity appends in a segment of its own: record 0 there)
    assert "invalid record 0: kf 9: keyframe.pose_covariance" in out, out
    assert "not positive semi-definite" in out and "(a replay skips it)" in out
    port = free_port()
    with Service(conf(port, storage)) as service:
        state = service.maps[BAD].map_state()
        assert sorted(state.keyframes) == [*SNAPSHOT_IDS, *JOURNAL_IDS]   # 9 skipped, rest served


def test_map_check_names_a_snapshot_pose_covariance_that_is_not_one(storage, capsys):
    """A snapshot whose manifest gives a keyframe a covariance that is not symmetric: map
    check reports the current snapshot damaged, naming the keyframe and why."""
    from reloc_service.cli.main import main

    map_dir = storage / BAD
    snap = map_dir / "map" / (map_dir / "map" / "CURRENT").read_text().strip()
    manifest = json.loads((snap / "manifest.json").read_text())
    cov = np.eye(6) * 1e-4
    cov[0, 1] = 5e-5
    manifest["keyframes"][1]["pose_covariance"] = cov.tolist()
    (snap / "manifest.json").write_text(json.dumps(manifest))
    assert main(["map", "check", str(map_dir)]) == 1
    out = capsys.readouterr().out
    assert "the current snapshot is damaged" in out and "keyframe 1: pose_covariance" in out
    assert "not symmetric" in out


def test_map_check_reports_a_missing_current(storage, capsys):
    from reloc_service.cli.main import main

    (storage / BAD / "map" / "CURRENT").unlink()
    assert main(["map", "check", str(storage / BAD)]) == 1
    assert "CURRENT: missing although snapshot(s)" in capsys.readouterr().out
    assert main(["map", "check", str(storage / BAD / "journal" / "nothing")]) == 2
