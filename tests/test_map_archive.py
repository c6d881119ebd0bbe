"""The export file itself (:mod:`reloc_service.storage.map_archive`): a snapshot file equal to
an earlier one is written once and lands as a hard link to it; an export without such a file
keeps format version 1; a link that names no equal earlier snapshot part is refused. Real
files and real tar files."""

from __future__ import annotations

import hashlib
import io
import json
import tarfile
from pathlib import Path

import pytest

from reloc_service.storage.map_archive import (
    MANIFEST,
    MANIFEST_DIGEST,
    SAME_AS,
    ArchiveError,
    Part,
    bytes_part,
    extract_archive,
    write_archive,
)

SNAP = "map/snapshots/000001"
IDENTITY = {"map_id": "0" * 32, "last_seq": 3, "map_name": "lab"}


def _file_part(root: Path, rel: str, data: bytes) -> Part:
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return Part(rel, len(data), hashlib.sha256(data).hexdigest(), path)


def _parts(root: Path) -> list[Part]:
    model = b"a trained model" * 10000
    return [bytes_part("service.json", b"{}"),
            _file_part(root, f"{SNAP}/models/a/place_bow.msgpack.zlib", model),
            _file_part(root, f"{SNAP}/models/b/place_bow.msgpack.zlib", model),
            _file_part(root, f"{SNAP}/features/orb.descriptors.npy", b"other bytes"),
            # an empty journal equals no other part's bytes by link: it is appended to
            _file_part(root, "journal/00000001.journal", b""),
            _file_part(root, "journal/00000002.journal", b"")]


def test_an_equal_snapshot_file_is_written_once_and_imported_as_a_link(tmp_path):
    parts = _parts(tmp_path / "src")
    manifest, size = write_archive(tmp_path / "x.relocmap", IDENTITY, parts)
    assert manifest["format_version"] == 2
    with tarfile.open(tmp_path / "x.relocmap") as tar:
        members = tar.getnames()
    assert members.count(f"{SNAP}/models/a/place_bow.msgpack.zlib") == 1
    assert f"{SNAP}/models/b/place_bow.msgpack.zlib" not in members
    assert members.count("journal/00000002.journal") == 1
    assert size < 1.5 * 150_000   # the model's 150 kB once, not twice
    dest = tmp_path / "dest"
    extract_archive(tmp_path / "x.relocmap", dest)
    a, b = (dest / SNAP / "models" / m / "place_bow.msgpack.zlib" for m in "ab")
    assert a.read_bytes() == b.read_bytes() == parts[1].source.read_bytes()
    assert a.stat().st_ino == b.stat().st_ino
    j1, j2 = dest / "journal/00000001.journal", dest / "journal/00000002.journal"
    assert j1.stat().st_ino != j2.stat().st_ino


def test_an_export_without_an_equal_file_stays_version_1(tmp_path):
    parts = [p for p in _parts(tmp_path / "src") if "/b/" not in p.path]
    manifest, _ = write_archive(tmp_path / "x.relocmap", IDENTITY, parts)
    assert manifest["format_version"] == 1
    assert not any(SAME_AS in p for p in manifest["parts"])
    assert extract_archive(tmp_path / "x.relocmap", tmp_path / "dest")["format_version"] == 1


def _relinked(src: Path, dst: Path, target: str) -> None:
    """``src`` with its linked part's ``same_as`` pointing at ``target`` (digest refreshed)."""
    with tarfile.open(src) as tin, tarfile.open(dst, "w", format=tarfile.PAX_FORMAT) as tout:
        text = b""
        for member in tin:
            data = tin.extractfile(member).read()
            if member.name == MANIFEST:
                manifest = json.loads(data)
                for p in manifest["parts"]:
                    if SAME_AS in p:
                        p[SAME_AS] = target
                data = text = json.dumps(manifest).encode()
            elif member.name == MANIFEST_DIGEST:
                data = hashlib.sha256(text).hexdigest().encode()
            member.size = len(data)
            tout.addfile(member, io.BytesIO(data))


@pytest.mark.parametrize("target", ["journal/00000001.journal",
                                    f"{SNAP}/features/orb.descriptors.npy",
                                    f"{SNAP}/models/b/place_bow.msgpack.zlib", "nowhere"])
def test_a_link_to_no_equal_snapshot_part_is_refused_by_name(tmp_path, target):
    write_archive(tmp_path / "x.relocmap", IDENTITY, _parts(tmp_path / "src"))
    _relinked(tmp_path / "x.relocmap", tmp_path / "bad.relocmap", target)
    with pytest.raises(ArchiveError, match=f"manifest lacks or has a malformed {SAME_AS}"):
        extract_archive(tmp_path / "bad.relocmap", tmp_path / "dest")
