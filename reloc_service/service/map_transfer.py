"""Maps that travel: a served map directory exported as one file, an export file imported
into a storage (verified in full before anything is written there), and what a map holds.

An export is the map as a restart at one instant would restore it, taken without stopping
the service that serves it: the snapshot ``service.json`` names (immutable; each file is
checked against the SHA-256 its snapshot manifest records while it is copied) and the
journal segments from the one ``service.json`` says follows it, each cut after its last
complete record (a record being written is left out, as a crash would leave it). Records
are appended only to the last segment and segments are deleted only after a newer snapshot
is named, so those segments read in order are a prefix of the journal; a snapshot or
segment removed meanwhile (a newer snapshot was taken) restarts the export from a fresh
``service.json``.

An import extracts and checks the file in a temporary directory outside the storage
(:func:`.map_archive.extract_archive`), judges it as a service's restore would
(:func:`.restore_verdict.judge`: identity, sequence numbers, no loss), loads its snapshot
with the service's snapshot reader (:func:`..storage.snapshot.load_map`, every checksum)
and compares the keyframe ids and the last sequence number with the manifest. Only then is
it copied next to the storage's maps under a hidden name and renamed into place. The map
keeps its identity (UUID and sequence numbers), so replicas of it recognise it.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
from reloc_client import protocol as wire

from ..core.errors import StorageError
from ..core.fileio import atomic_write, fsync_path
from ..storage.journal import Journal, scan_segment, segment_name
from ..storage.lock import holder_if_locked
from ..storage.map_archive import (
    ArchiveError,
    Part,
    PartChanged,
    bytes_part,
    extract_archive,
    file_sha256,
    part_kind,
    same_as,
    write_archive,
)
from ..storage.snapshot import load_map
from ..storage.snapshot_files import MANIFEST_FILE, fsync_tree
from ..storage.snapshot_link import copy_tree_keeping_links
from .durability import SERVICE_FILE, read_service_file
from .map_dirs import MAP_NAME_FILE, map_dirname, map_name_of, stored_map_name
from .restore_verdict import judge

log = logging.getLogger(__name__)

#: Fresh views tried before an export gives up on a map that keeps changing under it.
EXPORT_ATTEMPTS = 5


@dataclass
class MapView:
    """A consistent view of a map directory: the parts to export and what they hold."""

    map_name: str
    map_id: str
    parts: list[Part] = field(default_factory=list)
    snapshot: str | None = None
    snapshot_seq: int = 0
    snapshot_keyframe_ids: list[int] = field(default_factory=list)
    keyframe_ids: list[int] = field(default_factory=list)
    landmarks: int | None = None
    last_seq: int = 0
    journal_records: int = 0
    last_change: float | None = None

    def manifest(self) -> dict[str, Any]:
        return {"map_name": self.map_name, "map_id": self.map_id, "last_seq": self.last_seq,
                "snapshot": self.snapshot, "snapshot_seq": self.snapshot_seq,
                "snapshot_keyframe_ids": self.snapshot_keyframe_ids,
                "keyframe_ids": self.keyframe_ids, "keyframes": len(self.keyframe_ids),
                "landmarks": self.landmarks, "journal_records": self.journal_records,
                "last_change": self.last_change, "exported_at": time.time()}


# -- export -----------------------------------------------------------------------------------

def export_map(map_dir: Path, out: Path) -> tuple[dict[str, Any], int]:
    """Write map directory ``map_dir`` as the export file ``out`` (atomically); its
    manifest and size in bytes. StorageError if it is not a served map directory, is
    damaged, or keeps changing under :data:`EXPORT_ATTEMPTS` views."""
    for attempt in range(EXPORT_ATTEMPTS):
        with tempfile.TemporaryDirectory(prefix="reloc-export-") as tmp:
            try:
                view = take_view(map_dir, Path(tmp))
                return write_archive(out, view.manifest(), view.parts)
            except PartChanged as exc:
                log.info("export of %s: %s; taking a fresh view (attempt %d)", map_dir, exc,
                         attempt + 2)
    raise StorageError(f"{map_dir}: changed under {EXPORT_ATTEMPTS} export attempts (a new "
                       f"snapshot each time); try again when the map is less busy")


def take_view(map_dir: Path, tmp: Path) -> MapView:
    """The parts of ``map_dir`` a restore would read now (see module docstring); journal
    segments are copied into ``tmp`` (cut after their last complete record)."""
    try:
        meta_bytes = (map_dir / SERVICE_FILE).read_bytes()
    except FileNotFoundError:
        raise StorageError(f"{map_dir}: no {SERVICE_FILE}; expected a map directory of a "
                           f"`reloc serve --storage` storage") from None
    meta = json.loads(meta_bytes)
    if not isinstance(meta.get("map_id"), str):
        raise StorageError(f"{map_dir / SERVICE_FILE}: no map identity recorded; serve the "
                           f"map once (it is assigned then) before exporting it")
    view = MapView(stored_map_name(map_dir) or map_name_of(map_dir.name), meta["map_id"],
                   last_change=meta.get("time"))
    view.parts.append(bytes_part(SERVICE_FILE, meta_bytes))
    if isinstance(meta.get("snapshot"), str):
        _snapshot_parts(view, map_dir, meta["snapshot"])
    _journal_parts(view, map_dir, meta_bytes, int(meta.get("next_segment", 0)), tmp)
    view.last_seq = max(view.last_seq, view.snapshot_seq)
    return view


def _snapshot_parts(view: MapView, map_dir: Path, name: str) -> None:
    snap_dir = map_dir / "map" / "snapshots" / name
    try:
        text = (snap_dir / MANIFEST_FILE).read_bytes()
    except FileNotFoundError:
        raise PartChanged(f"snapshot {name} removed") from None
    manifest = json.loads(text)
    rel = f"map/snapshots/{name}"
    view.parts.append(bytes_part("map/CURRENT", f"snapshots/{name}\n".encode()))
    view.parts.append(bytes_part(f"{rel}/{MANIFEST_FILE}", text))
    for path, entry in manifest["files"].items():
        view.parts.append(Part(f"{rel}/{path}", int(entry["size"]), str(entry["sha256"]),
                               snap_dir / path))
    view.snapshot = name
    view.snapshot_seq = int(manifest.get("store", {}).get("last_seq", 0))
    view.snapshot_keyframe_ids = [int(kf["id"]) for kf in manifest["keyframes"]]
    view.keyframe_ids = list(view.snapshot_keyframe_ids)
    count = manifest.get("landmarks", {}).get("count")
    ids = manifest["files"].get("landmarks/ids.npy")
    if isinstance(count, int):   # format 7 names it (its ids may be stored compressed)
        view.landmarks = count
    elif ids is not None:   # the .npy header is 128 bytes: 8-byte ids after it (int32 or int64)
        view.landmarks = _npy_length(snap_dir / "landmarks" / "ids.npy")


def _npy_length(path: Path) -> int | None:
    import numpy as np

    try:
        return int(np.load(path, mmap_mode="r").shape[0])
    except FileNotFoundError:
        raise PartChanged(f"{path} removed") from None
    except (OSError, ValueError):
        return None


def _journal_parts(view: MapView, map_dir: Path, meta_bytes: bytes, first: int,
                   tmp: Path) -> None:
    """Segments from ``first`` on, each copied to ``tmp`` and cut after its last complete
    record; the keyframe ids and last sequence number they lead to."""
    numbers = [n for n in Journal(map_dir / "journal").segments() if n >= first]
    if (map_dir / SERVICE_FILE).read_bytes() != meta_bytes:
        # segments are deleted only after service.json names a newer snapshot: unchanged
        # after the listing, the listing holds every segment from ``first`` on
        raise PartChanged(f"{SERVICE_FILE} changed (a new snapshot)")
    ids = set(view.keyframe_ids)
    for number in numbers:
        copy = tmp / segment_name(number)
        try:
            data = (map_dir / "journal" / segment_name(number)).read_bytes()
        except FileNotFoundError:
            raise PartChanged(f"journal segment {segment_name(number)} removed") from None
        copy.write_bytes(data)
        scan = scan_segment(copy)
        if any(d.kind == "corrupt" for d in scan.damage):
            raise StorageError(f"{map_dir / 'journal' / segment_name(number)}: damaged "
                               f"records; see `reloc map check {map_dir}` before exporting")
        if scan.version == 0:
            continue
        os.truncate(copy, scan.valid_bytes)
        view.parts.append(Part(f"journal/{segment_name(number)}", scan.valid_bytes,
                               file_sha256(copy), copy))
        if scan.records:
            view.last_change = max(view.last_change or 0.0, copy_mtime(map_dir, number))
        for raw in scan.records:
            _apply_record(view, ids, raw)
    view.keyframe_ids = sorted(ids)


def _apply_record(view: MapView, ids: set[int], raw: bytes) -> None:
    record = msgpack.unpackb(raw, raw=False)
    seq = record.get("seq")
    if isinstance(seq, int) and seq <= view.snapshot_seq:
        return   # already in the snapshot
    view.journal_records += 1
    view.last_seq = max(view.last_seq, seq if isinstance(seq, int) else 0)
    if record.get("op") == "kf":
        ids.add(int(record["id"]))
    elif record.get("op") == "del":
        ids.discard(int(record["id"]))


def copy_mtime(map_dir: Path, number: int) -> float:
    """When segment ``number`` was last written (0 if it is gone meanwhile)."""
    try:
        return (map_dir / "journal" / segment_name(number)).stat().st_mtime
    except FileNotFoundError:
        return 0.0


# -- import -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Imported:
    """An imported map: its name, directory, identity, keyframes and last sequence number."""

    name: str
    directory: Path
    map_id: str
    keyframes: int
    last_seq: int


def import_map(file: Path, storage: Path, *, name: str | None = None, replace: bool = False,
               owner_checked: bool = False) -> Imported:
    """Import export file ``file`` into ``storage`` as ``name`` (default: the name it was
    exported under), replacing a map of that name only with ``replace``. Everything is
    checked before the storage is written (ArchiveError / StorageError naming what is
    wrong, nothing written). ``owner_checked``: the caller owns the storage (the service
    itself); else a storage a running process holds is refused."""
    if not owner_checked:
        holder = holder_if_locked(storage)
        if holder is not None:
            raise StorageError(f"storage {storage} is in use by {holder.describe()}; import "
                               f"through that service (`reloc-client import`), or stop it first")
    with tempfile.TemporaryDirectory(prefix="reloc-import-") as tmp:
        staged = Path(tmp) / "map"
        manifest = extract_archive(file, staged)
        name = _check_target(storage, name or manifest["map_name"], replace)
        verify_restorable(staged, manifest, file)
        atomic_write(staged / MAP_NAME_FILE, name)
        target = _place(staged, storage, map_dirname(name), replace)
    return Imported(name, target, manifest["map_id"], len(manifest["keyframe_ids"]),
                    manifest["last_seq"])


def _check_target(storage: Path, name: str, replace: bool) -> str:
    try:
        wire.check_name(name)
    except wire.ProtocolError as exc:
        raise ArchiveError(f"map name {name!r}: {exc.message}") from exc
    if (storage / map_dirname(name)).exists() and not replace:
        raise StorageError(f"map {name!r} is already present in {storage}; import it under "
                           f"another name (--name) or replace it (--replace)")
    return name


def verify_restorable(staged: Path, manifest: dict[str, Any], file: Path) -> None:
    """The staged map directory restores complete, as the manifest says (ArchiveError)."""
    verdict = judge(staged)
    if verdict.refusal is not None:
        raise ArchiveError(f"{file}: the map does not restore: {verdict.refusal}")
    if verdict.losses:
        raise ArchiveError(f"{file}: the map would restore degraded: "
                           + "; ".join(loss.describe() for loss in verdict.losses))
    if verdict.map_id != manifest["map_id"] or verdict.next_seq - 1 != manifest["last_seq"]:
        raise ArchiveError(f"{file}: identity {verdict.map_id} up to sequence number "
                           f"{verdict.next_seq - 1} restored; the manifest says "
                           f"{manifest['map_id']} up to {manifest['last_seq']}")
    snapshot_ids: list[int] = []
    if (staged / "map" / "CURRENT").is_file():
        try:
            state, _ = load_map(staged / "map")
        except StorageError as exc:
            raise ArchiveError(f"{file}: the snapshot does not load: {exc}") from exc
        snapshot_ids = sorted(state.keyframes)
    if snapshot_ids != sorted(manifest.get("snapshot_keyframe_ids", [])):
        raise ArchiveError(f"{file}: the snapshot holds {len(snapshot_ids)} keyframes, the "
                           f"manifest lists {len(manifest.get('snapshot_keyframe_ids', []))}")
    view = MapView("", "", keyframe_ids=snapshot_ids, snapshot_seq=verdict.snapshot_seq)
    ids = set(snapshot_ids)
    for number in Journal(staged / "journal").segments():
        for raw in scan_segment(staged / "journal" / segment_name(number)).records:
            _apply_record(view, ids, raw)
    if sorted(ids) != sorted(manifest["keyframe_ids"]):
        raise ArchiveError(f"{file}: snapshot and journal give {len(ids)} keyframes, the "
                           f"manifest lists {len(manifest['keyframe_ids'])}")


def _place(staged: Path, storage: Path, dirname: str, replace: bool) -> Path:
    """Copy ``staged`` next to the storage's maps under a hidden name, fsync it, rename it
    into place (the map it replaces, with ``replace``, is moved aside first, then removed)."""
    storage.mkdir(parents=True, exist_ok=True)
    target = storage / dirname
    hidden = storage / f".import-{uuid.uuid4().hex}"
    aside = storage / f".replaced-{uuid.uuid4().hex}"
    try:
        copy_tree_keeping_links(staged, hidden)   # an export's linked parts stay one file
        for path in hidden.rglob("*"):
            if path.is_file():
                fsync_path(path)
        fsync_tree(hidden)
        if target.exists():
            if not replace:
                raise StorageError(f"{target}: appeared while importing; not replaced")
            os.rename(target, aside)
        os.rename(hidden, target)
        fsync_path(storage)
    finally:
        shutil.rmtree(hidden, ignore_errors=True)
        shutil.rmtree(aside, ignore_errors=True)
    return target


# -- describing -------------------------------------------------------------------------------

def map_info(map_dir: Path) -> dict[str, Any]:
    """What ``map_dir`` holds (read only): name, identity, keyframes, landmarks, snapshot
    format version, bytes on disk per part kind, last change, restore outcome."""
    meta = read_service_file(map_dir)
    with tempfile.TemporaryDirectory(prefix="reloc-info-") as tmp:
        view = take_view(map_dir, Path(tmp)) if meta.get("map_id") else None
    sizes: dict[str, int] = {}
    parts = view.parts if view is not None else []
    linked = same_as(parts)   # a file two methods share is on disk once
    for p in parts:
        if p.path not in linked:
            sizes[part_kind(p.path)] = sizes.get(part_kind(p.path), 0) + p.size
    version = None
    if view is not None and view.snapshot is not None:
        manifest = json.loads((map_dir / "map" / "snapshots" / view.snapshot /
                               MANIFEST_FILE).read_text())
        version = manifest.get("format_version")
    return {"name": stored_map_name(map_dir) or map_name_of(map_dir.name),
            "directory": str(map_dir), "map_id": meta.get("map_id"),
            "keyframes": None if view is None else len(view.keyframe_ids),
            "landmarks": None if view is None else view.landmarks,
            "format_version": version, "last_seq": None if view is None else view.last_seq,
            "bytes": sizes, "total_bytes": sum(sizes.values()),
            "last_change": None if view is None else view.last_change,
            "restore": judge(map_dir).outcome.value}
