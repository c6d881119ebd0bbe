"""``reloc map export|import|ls|info``: a map exported from one service's storage and
imported into another's answers the same queries with the same poses; a damaged, truncated or
unknown export file is refused by name with nothing written; an export taken while the
service serves and takes puts is a consistent map. Real services on loopback, real files."""
# ruff: noqa: E402

from __future__ import annotations

import hashlib
import io
import json
import re
import shutil
import tarfile
import threading
from pathlib import Path

import numpy as np
import pytest
from reloc_client.client import RelocClient
from service_support import MAP, endpoint, free_port, service_conf
from storage_support import fill_map, keyframe_put, listing, query_poses

from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.cli.main import main as reloc
from reloc_service.service.app import Service
from reloc_service.service.map_transfer import export_map, import_map, map_info, take_view
from reloc_service.storage.map_archive import MANIFEST, MANIFEST_DIGEST, ArchiveError

KEYFRAMES = 6


@pytest.fixture(scope="module")
def built(synthetic_scene, tmp_path_factory):
    """A storage with map ``lab`` (snapshot plus a journal tail: snapshot every 4 records),
    stopped without a final snapshot, and the poses a service restoring it gives to the
    first query images (a restored map is what an imported one is compared with: the live
    map holds float64 landmark points its snapshot stores as float32 where far below their
    uncertainty, see storage.landmark_codec)."""
    storage = tmp_path_factory.mktemp("a") / "storage"
    # images kept (as a map served with ferns keeps them): an export carries every part kind
    service = Service(service_conf(free_port(), storage, maps=(MAP,), snapshot_every=4,
                                   keyframe_images="always"))
    service.start()
    try:
        fill_map(service, synthetic_scene, range(KEYFRAMES))
    finally:
        service.stop(final_snapshot=False)
    copy = storage.parent / "served"    # a served map takes a snapshot at stop: keep the tail
    shutil.copytree(storage, copy)
    return storage, _serve_poses(copy, synthetic_scene)


def _serve_poses(storage: Path, scene, map_name: str = MAP) -> list[np.ndarray]:
    """The poses a service restoring ``storage`` gives to the first query images (its
    queries run on threads: no worker processes to start for two queries; that they answer
    alike is test_processes')."""
    port = free_port()
    with Service(service_conf(port, storage, maps=(map_name,), worker_mode="thread")):
        return query_poses(port, scene, map_name)


def test_cli_export_import_gives_the_same_answers(built, synthetic_scene, tmp_path, capsys):
    storage, poses = built
    file = tmp_path / "lab.relocmap"
    assert reloc(["map", "export", "--storage", str(storage), MAP, str(file)]) == 0
    other = tmp_path / "b"
    assert reloc(["map", "import", str(file), "--storage", str(other)]) == 0
    assert reloc(["map", "ls", str(other)]) == 0
    listed = capsys.readouterr().out
    assert MAP in listed and f" {KEYFRAMES} " in listed
    assert reloc(["map", "info", "--json", str(other / MAP)]) == 0
    info = json.loads(capsys.readouterr().out)
    source = json.loads((storage / MAP / "service.json").read_text())
    assert info["map_id"] == source["map_id"] and info["keyframes"] == KEYFRAMES
    assert info["restore"] == "complete" and info["bytes"]["images"] > 0
    # every file the source restores from arrives byte for byte
    for part in json.loads(tarfile.open(file).extractfile(MANIFEST).read())["parts"]:
        assert _sha(other / MAP / part["path"]) == _sha(storage / MAP / part["path"]), \
            part["path"]
    # the journal tail is replayed (mapping again, in threads whose float summation order
    # varies): two restores of the same storage differ by ~1e-8, far below 1e-6
    for a, b in zip(poses, _serve_poses(other, synthetic_scene), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_import_under_another_name_keeps_the_identity(built, synthetic_scene, tmp_path):
    storage, poses = built
    file = tmp_path / "lab.relocmap"
    export_map(storage / MAP, file)
    done = import_map(file, tmp_path / "b", name="lab-copy")
    assert done.map_id == json.loads((storage / MAP / "service.json").read_text())["map_id"]
    assert (done.directory / "map_name").read_text() == "lab-copy"
    with pytest.raises(Exception, match="already present"):
        import_map(file, tmp_path / "b", name="lab-copy")
    assert import_map(file, tmp_path / "b", name="lab-copy", replace=True).keyframes == KEYFRAMES


def _rewrite(src: Path, dst: Path, change) -> None:
    """``src`` with its members rewritten by ``change(name, data) -> data``."""
    with tarfile.open(src) as tin, tarfile.open(dst, "w", format=tarfile.PAX_FORMAT) as tout:
        for member in tin:
            data = change(member.name, tin.extractfile(member).read())
            member.size = len(data)
            tout.addfile(member, io.BytesIO(data))


def _flip_in_part(src: Path, dst: Path, part: str) -> None:
    """Flip one byte in the middle of ``part``'s data, in place in the file."""
    with tarfile.open(src) as tar:
        member = tar.getmember(part)
    raw = bytearray(src.read_bytes())
    raw[member.offset_data + member.size // 2] ^= 0x01
    dst.write_bytes(bytes(raw))


def _new_version(name: str, data: bytes) -> bytes:
    if name == MANIFEST:
        return json.dumps({**json.loads(data), "format_version": 99}).encode()
    return data


def _fix_digest(src: Path, dst: Path) -> None:
    manifest = {}

    def change(name: str, data: bytes) -> bytes:
        if name == MANIFEST:
            manifest["text"] = _new_version(name, data)
            return manifest["text"]
        if name == MANIFEST_DIGEST:
            return hashlib.sha256(manifest["text"]).hexdigest().encode()
        return data
    _rewrite(src, dst, change)


@pytest.mark.parametrize("damage, expected", [
    ("flip-image", r"part map/snapshots/\d+/images/\S+: checksum mismatch"),
    ("flip-journal", r"part journal/\d+\.journal: checksum mismatch"),
    ("flip-manifest", r"part manifest.json: checksum mismatch"),
    ("truncate", r"truncated"),
    ("version", r"unknown export format version 99; this reloc reads version\(s\) 1, 2"),
])
def test_a_damaged_file_is_refused_by_name_and_nothing_is_written(built, tmp_path, damage,
                                                                  expected, capsys):
    storage, _ = built
    good = tmp_path / "good.relocmap"
    manifest, size = export_map(storage / MAP, good)
    bad = tmp_path / "bad.relocmap"
    if damage == "flip-image":
        image = next(p["path"] for p in manifest["parts"] if p["kind"] == "images")
        _flip_in_part(good, bad, image)
    elif damage == "flip-journal":
        journal = next(p["path"] for p in manifest["parts"] if p["kind"] == "journal"
                       and p["size"] > 64)
        _flip_in_part(good, bad, journal)
    elif damage == "flip-manifest":
        _flip_in_part(good, bad, MANIFEST)
    elif damage == "truncate":
        bad.write_bytes(good.read_bytes()[:size * 2 // 3])
    else:
        _fix_digest(good, bad)
    target = tmp_path / "b"
    target.mkdir()
    (target / "keep").write_text("an unrelated file")
    before = listing(target)
    assert reloc(["map", "import", str(bad), "--storage", str(target)]) == 1
    assert re.search(expected, capsys.readouterr().err)
    assert listing(target) == before
    with pytest.raises(ArchiveError, match=expected):
        import_map(bad, target)


@pytest.mark.slow
def test_an_export_while_serving_and_taking_puts_is_consistent(synthetic_scene, tmp_path):
    """Puts stream in (snapshot every 3 records, so snapshots are taken and pruned under the
    export) while three exports run; each export imports and restores to a prefix of the puts."""
    scene = synthetic_scene
    port = free_port()
    storage = tmp_path / "a"
    with Service(service_conf(port, storage, maps=(MAP,), snapshot_every=3)) as service:
        fill_map(service, scene, range(3))
        stop = threading.Event()

        def put_more() -> None:
            for kf_id in range(3, 3 + 8):
                if stop.is_set():
                    return
                service.on_keyframe_sample(MAP, kf_id, keyframe_put(scene, kf_id))
                service.wait_idle(60)

        writer = threading.Thread(target=put_more)
        writer.start()
        counts = []
        try:
            for i in range(3):
                file = tmp_path / f"live{i}.relocmap"
                manifest, _ = export_map(storage / MAP, file)
                done = import_map(file, tmp_path / f"b{i}")
                assert done.keyframes == manifest["keyframes"]
                # a prefix of the puts: keyframes 0..n-1, no gap
                assert manifest["keyframe_ids"] == list(range(manifest["keyframes"]))
                counts.append(manifest["keyframes"])
        finally:
            stop.set()
            writer.join()
    print(f"\nexports while serving: keyframes {counts}")
    assert counts == sorted(counts) and counts[0] >= 3
    port = free_port()
    last = tmp_path / f"b{len(counts) - 1}"
    with Service(service_conf(port, last, maps=(MAP,))), \
            RelocClient(endpoint(port), map=MAP, timeout=30) as client:
        assert sorted(i.id for i in client.keyframes()) == list(range(counts[-1]))


def test_export_refuses_a_directory_that_is_not_a_served_map(tmp_path, capsys):
    (tmp_path / "x").mkdir()
    assert reloc(["map", "export", str(tmp_path / "x"), str(tmp_path / "f")]) == 2
    assert "not a map directory" in capsys.readouterr().err
    (tmp_path / "x" / "journal").mkdir()
    with pytest.raises(Exception, match="no service.json"):
        take_view(tmp_path / "x", tmp_path)
    assert not (tmp_path / "f").exists()


def test_import_into_a_storage_a_service_holds_is_refused(built, tmp_path, capsys):
    from reloc_service.storage.lock import DirectoryLock

    storage, _ = built
    file = tmp_path / "lab.relocmap"
    export_map(storage / MAP, file)
    held = tmp_path / "held"
    held.mkdir()
    with DirectoryLock(held, what="storage").acquire("reloc serve"):
        assert reloc(["map", "import", str(file), "--storage", str(held), "--name", "x"]) == 1
    assert "is in use by" in capsys.readouterr().err and not (held / "x").exists()


def test_map_info_counts_the_landmarks_of_a_snapshot_with_packed_ids(built):
    """Format 7 may store the landmark ids compressed: the count comes from the manifest."""
    from reloc_service.service.map_transfer import map_info
    from reloc_service.storage.snapshot import load_map

    storage, _ = built
    map_dir = next(d for d in storage.iterdir() if (d / "service.json").is_file())
    state, _ = load_map(map_dir / "map")
    info = map_info(map_dir)
    assert info["format_version"] == 7   # nothing in it needs format 8 (shared descriptors)
    assert info["landmarks"] is not None and info["landmarks"] >= len(state.landmarks) > 0


def test_a_model_two_methods_share_travels_and_lands_once(synthetic_scene, tmp_path):
    """The default chain's bag-of-words step and ``bow+p3p`` train one model, which the
    snapshot holds once (hard-linked): the export carries its bytes once and the import
    lands it as one file again."""
    storage, port = tmp_path / "a", free_port()
    service = Service(service_conf(port, storage, maps=(MAP,),
                                   methods=[DEFAULT_METHOD, "bow+p3p"]))
    service.start()
    try:
        fill_map(service, synthetic_scene, range(KEYFRAMES))
        with RelocClient(endpoint(port), map=MAP, timeout=120) as client:
            client.train(wait=True, timeout=120)
    finally:
        service.stop()
    current = storage / MAP / "map" / (storage / MAP / "map" / "CURRENT").read_text().strip()
    files = [p for p in current.rglob("*") if p.is_file()]
    inodes = {p.stat().st_ino for p in files}
    linked = sorted(p for p in files if sum(q.stat().st_ino == p.stat().st_ino for q in files) > 1)
    assert any(p.name.startswith("place_bow") for p in linked), linked
    file = tmp_path / "lab.relocmap"
    manifest, _ = export_map(storage / MAP, file)
    assert manifest["format_version"] == 2
    names = set(tarfile.open(file).getnames())
    rel = [str(p.relative_to(storage / MAP)) for p in files]
    assert sum(r in names for r in rel) == len(inodes) < len(files)
    done = import_map(file, tmp_path / "b")
    landed = [done.directory / r for r in rel]
    for p, q in zip(files, landed, strict=True):
        assert q.read_bytes() == p.read_bytes()
    assert len({q.stat().st_ino for q in landed}) == len(inodes)
    # `reloc map info` counts the bytes on disk: a shared model once
    models = {p.stat().st_ino: p.stat().st_size for p in files if "models" in p.parts}
    assert map_info(storage / MAP)["bytes"]["models"] == sum(models.values())
