"""A restore proves it is complete, or says what it lacks: each storage corruption restores
completely, is served *degraded* with what it lacks named (status, a ``storage_damaged``
event, ``reloc map check`` exit 1) until an operator accepts the loss, or is refused by name;
``reloc serve`` and ``reloc map check`` reach the same verdict. A snapshot that fails on a full
disk leaves nothing behind.

Real services on loopback (multicast scouting off), real keyframes of the synthetic room, real
files damaged on disk; the disk-full snapshot is an injected ENOSPC (the snapshot's file write
raises after writing part of its bytes)."""
# ruff: noqa: E402

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import msgpack
import pytest
from reloc_client import protocol as wire
from reloc_client.client import NoReplyError, RelocClient, ServiceError
from service_support import Events, endpoint, free_port, service_conf, wait_until
from storage_support import (
    ORB_AND_SIFT,
    Peer,
    files_of,
    journal_of_keyframes,
    journal_segment,
    kf_ids,
)

from reloc_service.cli.main import main
from reloc_service.service.app import Service
from reloc_service.storage import journal as J
from reloc_service.storage import snapshot_files

MAP, OTHER = "m", "other"
FIRST, SECOND, JOURNALED = (0, 1, 2), (3, 4, 5), (6, 7)
EVERY = (*FIRST, *SECOND, *JOURNALED)


def conf(port: int, storage: Path, **service):
    """Maps ``m`` and ``other``, snapshots on demand only; ORB and SIFT maps
    (``ORB_AND_SIFT``: an edited format version is refused for the ORB angles it expects)."""
    return service_conf(port, storage, maps=(MAP, OTHER), train_on_load=False,
                        snapshot_every=0, **ORB_AND_SIFT, **service)


def put(client: RelocClient, scene, events: Events, ids) -> None:
    for kf_id in ids:
        client.add_keyframe(kf_id, scene.keyframe_images[kf_id % len(scene.keyframe_images)],
                            scene.keyframe_poses[kf_id % len(scene.keyframe_poses)],
                            camera_id="cam0")
    for kf_id in ids:
        events.wait("keyframe_added", id=kf_id)


@pytest.fixture(scope="module")
def template(synthetic_scene, tmp_path_factory) -> Path:
    """Map ``m``: keyframes 0-2 in snapshot A, 3-5 added in snapshot B (CURRENT; A kept as
    the previous one), 6-7 in the journal after B (10 acknowledged changes with the camera).
    Map ``other``: keyframes 0-1 in a snapshot."""
    storage = tmp_path_factory.mktemp("verdict") / "storage"
    port = free_port()
    service = Service(conf(port, storage)).start()
    try:
        for name, batches in ((MAP, (FIRST, SECOND, JOURNALED)), (OTHER, ((0, 1),))):
            with RelocClient(endpoint(port), map=name, timeout=30) as client:
                events = Events(client)
                client.set_camera("cam0", synthetic_scene.camera)
                events.wait("camera_added", id="cam0")
                for i, ids in enumerate(batches):
                    put(client, synthetic_scene, events, ids)
                    if i < 2:
                        service.maps[name].start_snapshot(wait=True)
                events.close()
    finally:
        service.stop(final_snapshot=False)
    return storage


@pytest.fixture
def storage(template, tmp_path) -> Path:
    target = tmp_path / "storage"
    shutil.copytree(template, target)
    return target


def check(map_dir: Path, capsys) -> tuple[int, dict]:
    """``reloc map check --json`` of ``map_dir``: its exit status and report."""
    code = main(["map", "check", "--json", str(map_dir)])
    [report] = json.loads(capsys.readouterr().out)
    return code, report


def served(storage: Path, map_name: str = MAP):
    """Start a service on ``storage``; (service, peer client of ``map_name`` whose event
    subscription exists before the restore)."""
    port, peer_port = free_port(), free_port()
    peer = Peer(peer_port, map_name)
    service = Service(conf(port, storage, zenoh={"connect": [endpoint(peer_port)]})).start()
    wait_until(lambda: reachable(peer.client), timeout=30, interval=0.2)
    return service, peer


def reachable(client: RelocClient) -> bool:
    """The service answers ``client`` (a refusal is an answer): the peer has its routes."""
    try:
        client.status(timeout=1)
    except ServiceError:
        pass
    except NoReplyError:
        return False
    return True


# -- the corruptions -----------------------------------------------------------------------------

def _delete_segment(map_dir: Path) -> None:
    journal_segment(map_dir).unlink()


def _empty_segment(map_dir: Path) -> None:
    journal_segment(map_dir).write_bytes(b"")


def _current_rolled_back(map_dir: Path) -> None:
    snaps = sorted((map_dir / "map" / "snapshots").iterdir())
    assert len(snaps) == 2
    (map_dir / "map" / "CURRENT").write_text(f"snapshots/{snaps[0].name}\n")


DEGRADED = {
    # corruption: (keyframes served, missing keyframe ids named, loss kind)
    "segment_deleted": (_delete_segment, {*FIRST, *SECOND}, [], "missing_segment"),
    "segment_emptied": (_empty_segment, {*FIRST, *SECOND}, [], "empty_segment"),
    "current_rolled_back": (_current_rolled_back, {*FIRST, *JOURNALED}, list(SECOND),
                            "older_snapshot"),
}


@pytest.mark.parametrize("case", sorted(DEGRADED))
def test_a_restore_that_lacks_changes_is_served_degraded_until_the_loss_is_accepted(
        storage, capsys, case):
    damage, held, missing_ids, kind = DEGRADED[case]
    map_dir = storage / MAP
    damage(map_dir)
    code, report = check(map_dir, capsys)
    assert code == 1 and report["verdict"]["outcome"] == "degraded", report
    assert [loss["kind"] for loss in report["verdict"]["losses"]] == [kind]
    assert report["verdict"]["missing_keyframe_ids"] == missing_ids
    service, peer = served(storage)
    try:
        assert kf_ids(peer.client) == held
        status = peer.client.status()
        assert status.degraded.startswith("degraded: " + kind), status.degraded
        assert status.counters["restore_degraded"] == 1
        if missing_ids:
            assert f"keyframe ids {missing_ids}" in status.degraded
        else:
            assert "keyframe ids unknown (only the sequence range can be known)" in \
                status.degraded
        event = peer.events.wait("storage_damaged")
        assert event.fields["degraded"] is True and not event.fields["failed"]
        assert event.fields["missing_keyframe_ids"] == missing_ids
        assert [loss["kind"] for loss in event.fields["losses"]] == [kind]
    finally:
        service.stop(final_snapshot=False)
        peer.close()
    # The same verdict after the restore moved past the evidence (a new segment, ...).
    code, again = check(map_dir, capsys)
    assert code == 1 and again["verdict"]["losses"] == report["verdict"]["losses"]
    # Still degraded after a restart; an operator accepts the loss while it is served: its
    # status says so at once, map check exits 0, and a restart serves the map normally.
    service, peer = served(storage)
    try:
        assert peer.client.status().degraded.startswith("degraded: " + kind)
        assert main(["map", "check", "--accept-loss", str(map_dir)]) == 0
        capsys.readouterr()
        assert peer.client.status().degraded == ""
    finally:
        service.stop(final_snapshot=False)
        peer.close()
    code, accepted = check(map_dir, capsys)
    assert code == 0 and accepted["verdict"]["outcome"] == "complete"
    assert [loss["kind"] for loss in accepted["verdict"]["accepted"]] == [kind]
    service, peer = served(storage)
    try:
        assert kf_ids(peer.client) == held
        status = peer.client.status()
        assert status.degraded == "" and "restore_degraded" not in status.counters
    finally:
        service.stop(final_snapshot=False)
        peer.close()


@pytest.mark.parametrize("shift", [1, -1])
def test_an_edited_next_segment_loses_nothing_and_is_noted(storage, capsys, shift):
    """The sequence numbers, not ``next_segment``, decide what a restore replays."""
    map_dir = storage / MAP
    meta = json.loads((map_dir / "service.json").read_text())
    meta["next_segment"] += shift
    (map_dir / "service.json").write_text(json.dumps(meta))
    code, report = check(map_dir, capsys)
    assert code == 0 and report["verdict"]["outcome"] == "complete", report
    if shift > 0:
        assert "replayed by sequence number" in report["verdict"]["notes"][0]
    service, peer = served(storage)
    try:
        assert kf_ids(peer.client) == set(EVERY)
        assert peer.client.status().degraded == ""
    finally:
        service.stop(final_snapshot=False)
        peer.close()


# -- refused by name -------------------------------------------------------------------------------

def _other_snapshot(storage: Path) -> str:
    """Map ``other``'s current snapshot copied over map ``m``'s current one."""
    current = (storage / MAP / "map" / "CURRENT").read_text().strip()
    theirs = (storage / OTHER / "map" / "CURRENT").read_text().strip()
    shutil.rmtree(storage / MAP / "map" / current)
    shutil.copytree(storage / OTHER / "map" / theirs, storage / MAP / "map" / current)
    return "another map's content is never served"


def _other_snapshot_dir(storage: Path) -> str:
    """Map ``other``'s whole snapshot directory (``map/``) in place of map ``m``'s."""
    shutil.rmtree(storage / MAP / "map")
    shutil.copytree(storage / OTHER / "map", storage / MAP / "map")
    return "another map's content is never served"


def _format_version(storage: Path) -> str:
    """The current manifest's ``format_version`` edited to an older, readable one."""
    current = (storage / MAP / "map" / "CURRENT").read_text().strip()
    path = storage / MAP / "map" / current / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["format_version"] = 3
    path.write_text(json.dumps(manifest))
    return "not listed with a checksum"


def _unwritable_quarantine(storage: Path) -> str:
    """A torn last record (kept in the quarantine before it is cut) and a quarantine that
    is a file, not a directory."""
    with journal_segment(storage / MAP).open("ab") as fh:
        fh.write(J.frame(b"cut short")[:-4])
    (storage / MAP / "journal" / J.QUARANTINE_DIR).write_text("not a directory")
    return "not a writable directory"


def _service_field_edited(storage: Path) -> str:
    """``service.json``'s ``last_seq`` edited to something that is not a number."""
    path = storage / MAP / "service.json"
    meta = json.loads(path.read_text())
    meta["last_seq"] = "many"
    path.write_text(json.dumps(meta))
    return "expected service.json and the manifests as the service writes them"


REFUSED = {"service_json_field_edited": _service_field_edited,
           "other_maps_snapshot": _other_snapshot, "other_maps_snapshot_dir": _other_snapshot_dir,
           "format_version_edited": _format_version,
           "unwritable_quarantine": _unwritable_quarantine}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_another_maps_content_or_an_unreadable_map_is_refused_by_name(storage, capsys, case):
    why = REFUSED[case](storage)
    map_dir = storage / MAP
    before = files_of(map_dir)
    code, report = check(map_dir, capsys)
    assert code == 1 and report["verdict"]["outcome"] == "refused", report
    assert why in report["verdict"]["refusal"]
    service, peer = served(storage)
    try:
        with pytest.raises(ServiceError) as err:
            peer.client.status()
        assert err.value.code is wire.ErrorCode.STORAGE_ERROR
        assert report["verdict"]["refusal"] in err.value.message       # the same words
        event = peer.events.wait("storage_damaged")
        assert event.fields["failed"] is True
    finally:
        service.stop(final_snapshot=False)
        peer.close()
    assert files_of(map_dir) == before


# -- a map written before identities and sequence numbers ------------------------------------------

def test_a_map_written_by_the_previous_format_restores_and_gets_an_identity(
        synthetic_scene, tmp_path, capsys):
    """A journal of second-format segments whose records carry no sequence number (what the
    previous reloc wrote): restored completely, given an identity at its first open, and
    checked by sequence number from then on."""
    storage = tmp_path / "storage"
    journal_of_keyframes(storage / MAP, synthetic_scene, 3)
    assert (storage / MAP / "journal" / J.segment_name(1)).read_bytes()[:8] == J.MAGIC
    code, report = check(storage / MAP, capsys)
    assert code == 0 and report["verdict"]["legacy"] and report["verdict"]["map_id"] is None
    service, peer = served(storage)
    try:
        assert kf_ids(peer.client) == {0, 1, 2}
        put(peer.client, synthetic_scene, peer.events, (3,))
    finally:
        service.stop(final_snapshot=False)
        peer.close()
    meta = json.loads((storage / MAP / "service.json").read_text())
    code, report = check(storage / MAP, capsys)
    assert code == 0 and report["verdict"]["map_id"] == meta["map_id"]
    assert not report["verdict"]["legacy"] and report["verdict"]["next_seq"] == 2
    segment = storage / MAP / "journal" / J.segment_name(2)
    [record] = J.scan_segment(segment).records
    assert msgpack.unpackb(record, raw=False)["seq"] == 1
    service, peer = served(storage)
    try:
        assert kf_ids(peer.client) == {0, 1, 2, 3}
        assert peer.client.status().degraded == ""
    finally:
        service.stop(final_snapshot=False)
        peer.close()


# -- a disk-full snapshot ---------------------------------------------------------------------------

@pytest.mark.slow
def test_a_snapshot_failing_on_a_full_disk_leaves_nothing_and_puts_go_on(
        storage, synthetic_scene, monkeypatch):
    """Injected: the snapshot's write of a feature column (a part every snapshot writes)
    writes half its bytes, then raises ENOSPC (what a full disk does). The partial snapshot
    directory is removed, CURRENT still names the previous snapshot, and later puts are
    journaled and acknowledged."""
    map_dir = storage / MAP
    snapshots = sorted(p.name for p in (map_dir / "map" / "snapshots").iterdir())
    current = (map_dir / "map" / "CURRENT").read_text()
    real_write = snapshot_files.SnapshotWriter.write

    def full_disk(self, relpath, data):
        if relpath.startswith("features/"):
            (self.root / relpath).parent.mkdir(parents=True, exist_ok=True)
            with open(self.root / relpath, "wb") as fh:
                fh.write(data[: len(data) // 2])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_write(self, relpath, data)

    port = free_port()
    service = Service(conf(port, storage)).start()
    try:
        with RelocClient(endpoint(port), map=MAP, timeout=30) as client:
            events = Events(client)
            monkeypatch.setattr(snapshot_files.SnapshotWriter, "write", full_disk)
            service.maps[MAP].start_snapshot(wait=True)
            assert sorted(p.name for p in (map_dir / "map" / "snapshots").iterdir()) == snapshots
            assert (map_dir / "map" / "CURRENT").read_text() == current
            assert not list((map_dir / "map").glob(".models-*"))
            put(client, synthetic_scene, events, (8, 9))
            monkeypatch.undo()
            events.close()
    finally:
        service.stop(final_snapshot=False)
    service, peer = served(storage)
    try:
        assert kf_ids(peer.client) == {*EVERY, 8, 9}
        assert peer.client.status().degraded == ""
    finally:
        service.stop(final_snapshot=False)
        peer.close()


# -- a snapshot the process never finished ------------------------------------------------------

def _partial_snapshot(map_dir: Path) -> None:
    """What a kill -9 in the middle of a map's first snapshot leaves: a numbered snapshot
    directory holding part of a file and no manifest, no CURRENT, and a service.json (if
    any) naming no snapshot."""
    snapshot = snapshot_files.new_snapshot_dir(map_dir / "map")
    (snapshot / "keyframes").mkdir()
    (snapshot / "keyframes" / "000000.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 100)


def _empty_snapshot_dir(map_dir: Path) -> None:
    """Killed right after the snapshot directory was made."""
    snapshot_files.new_snapshot_dir(map_dir / "map")


@pytest.mark.parametrize("leftover", [_partial_snapshot, _empty_snapshot_dir])
def test_a_first_snapshot_killed_midway_is_removed_and_the_journal_restores_everything(
        synthetic_scene, tmp_path, capsys, leftover):
    """A map whose first snapshot was interrupted still has every change in its journal
    (segments are deleted only after service.json names a snapshot): the map restores
    completely, ``reloc map check`` agrees (exit 0), and the unfinished directory is gone."""
    storage = tmp_path / "storage"
    journal_of_keyframes(storage / MAP, synthetic_scene, 3)
    leftover(storage / MAP)
    code, report = check(storage / MAP, capsys)
    assert code == 0, report["problems"]
    service, peer = served(storage)
    try:
        assert kf_ids(peer.client) == {0, 1, 2}
        assert peer.client.status().degraded == ""
    finally:
        service.stop(final_snapshot=False)
        peer.close()
    assert snapshot_files.snapshot_dirs(storage / MAP / "map") == []
