"""One file that carries a map directory: a plain (uncompressed) tar whose first member is a
JSON manifest, the second the manifest's SHA-256, then every part of the map directory.

Layout of an export file (format version 2; one without a linked part is written as version
1, which it then is)::

    manifest.json        format, format version, the map's name and identity (map UUID, last
                         sequence number), keyframe ids, and per part: path, size, SHA-256
    manifest.sha256      SHA-256 of manifest.json (so a damaged manifest is named as such)
    service.json, map_name, map/CURRENT, map/snapshots/<n>/..., journal/<n>.journal

A snapshot file equal to an earlier one (the same trained model under two methods, which the
snapshot holds as one file hard-linked: :mod:`.snapshot_save`) is not a member a second
time: its manifest entry names the earlier part (``same_as``), and the import hard-links it
to that part (a copy where a link cannot be made), so its bytes travel and land once. Only
snapshot files are linked: they are never written again, whereas a journal segment is
appended to.

A tar because the standard library reads and writes it, ``tar tvf`` lists it, it streams
(written and verified part by part, never held in memory) and it adds nothing to compress:
the images are JPEG/PNG already and the arrays are narrow. SHA-256 because every snapshot
file is listed with its SHA-256 in the snapshot manifest already, so an export checks each
file against it while copying it (one read per file) instead of hashing twice.

Reading (:func:`extract_archive`) checks everything before it returns: the container, the
format and version, the manifest's own checksum, that every member is a listed part at a
safe relative path, and each part's size and checksum as it is extracted. Any failure is an
:class:`ArchiveError` naming what is wrong (which part, truncated, which version).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import tarfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import IO, Any

from ..core.errors import StorageError
from ..core.fileio import fsync_path

FORMAT = "reloc map export"
FORMAT_VERSION = 2
#: What an export without a linked part (``same_as``) is written as: nothing in it needs a
#: later version, so a reloc that reads version 1 still imports it.
UNLINKED_FORMAT_VERSION = 1
#: Export format versions this reloc reads.
READABLE_VERSIONS = (1, 2)
#: Manifest key of a part stored once under another path (version 2).
SAME_AS = "same_as"
#: Parts that may be linked to an equal earlier part: files of a snapshot, never rewritten.
LINKABLE_PREFIX = "map/snapshots/"
MANIFEST = "manifest.json"
MANIFEST_DIGEST = "manifest.sha256"
#: Largest manifest read (a 10000-keyframe map's manifest is about 1 MB).
MAX_MANIFEST_BYTES = 64 * 1024 * 1024
CHUNK = 1 << 20
#: Part kinds by the first directory of a snapshot file (sizes are reported per kind).
SNAPSHOT_KINDS = ("images", "features", "depth", "models", "landmarks", "thumbnails")


class ArchiveError(StorageError):
    """An export file that is refused: damaged, truncated, of an unknown version."""


class PartChanged(StorageError):
    """A part's source changed or vanished while it was written (the export retries)."""


@dataclass(frozen=True)
class Part:
    """One file of a map directory in an export: its path in the map directory, its size
    and SHA-256, and where its bytes are at export (a file, or the bytes themselves)."""

    path: str
    size: int
    sha256: str
    source: Path | bytes

    def entry(self) -> dict[str, Any]:
        return {"path": self.path, "size": self.size, "sha256": self.sha256,
                "kind": part_kind(self.path)}

    @property
    def linkable(self) -> bool:
        return not isinstance(self.source, bytes) and self.path.startswith(LINKABLE_PREFIX)


def same_as(parts: list[Part]) -> dict[str, str]:
    """Path of each linkable part -> the first earlier linkable part of the same size and
    SHA-256 (its bytes are written once)."""
    first: dict[tuple[int, str], str] = {}
    links = {}
    for part in parts:
        if part.linkable:
            key = (part.size, part.sha256)
            if key in first:
                links[part.path] = first[key]
            else:
                first[key] = part.path
    return links


def bytes_part(path: str, data: bytes) -> Part:
    return Part(path, len(data), hashlib.sha256(data).hexdigest(), data)


def part_kind(path: str) -> str:
    """``images``, ``features``, ``depth``, ``models``, ``landmarks``, ``thumbnails``,
    ``journal`` or ``meta`` (service.json, the snapshot manifest, CURRENT, map_name)."""
    parts = PurePosixPath(path).parts
    if parts[0] == "journal":
        return "journal"
    if parts[:2] == ("map", "snapshots") and len(parts) > 4 and parts[3] in SNAPSHOT_KINDS:
        return parts[3]
    return "meta"


# -- writing ----------------------------------------------------------------------------------

def write_archive(out: Path, manifest: dict[str, Any], parts: Iterable[Part]
                  ) -> tuple[dict[str, Any], int]:
    """Write the export file ``out`` atomically (``<out>.partial``, fsync, rename); the
    manifest written (``manifest`` with the format and the parts) and the file's size.
    A file part is checked against its SHA-256 while copied: PartChanged if it differs or is
    gone (nothing is left at ``out`` then)."""
    parts = list(parts)
    links = same_as(parts)
    manifest = {**manifest, "format": FORMAT,
                "format_version": FORMAT_VERSION if links else UNLINKED_FORMAT_VERSION,
                "parts": [p.entry() | ({SAME_AS: links[p.path]} if p.path in links else {})
                          for p in parts]}
    text = json.dumps(manifest, indent=1).encode("utf-8")
    tmp = out.with_name(out.name + ".partial")
    try:
        with tarfile.open(tmp, "w", format=tarfile.PAX_FORMAT) as tar:
            _add_bytes(tar, MANIFEST, text)
            _add_bytes(tar, MANIFEST_DIGEST, hashlib.sha256(text).hexdigest().encode())
            for part in parts:
                if part.path not in links:
                    _add_part(tar, part)
        fsync_path(tmp)
        os.replace(tmp, out)
        fsync_path(out.parent)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return manifest, out.stat().st_size


def _add_bytes(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size = len(data)
    info.mode = 0o644
    tar.addfile(info, io.BytesIO(data))


def _add_part(tar: tarfile.TarFile, part: Part) -> None:
    if isinstance(part.source, bytes):
        _add_bytes(tar, part.path, part.source)
        return
    try:
        fh = open(part.source, "rb")
    except FileNotFoundError:
        raise PartChanged(f"{part.source}: removed while exporting") from None
    with fh:
        if os.fstat(fh.fileno()).st_size != part.size:
            raise PartChanged(f"{part.source}: {os.fstat(fh.fileno()).st_size} bytes, "
                              f"expected {part.size}")
        info = tarfile.TarInfo(part.path)
        info.size = part.size
        info.mode = 0o644
        reader = _HashingReader(fh)
        tar.addfile(info, reader)   # type: ignore[arg-type]
    if reader.digest.hexdigest() != part.sha256:
        raise StorageError(f"{part.source}: its SHA-256 does not match the one recorded for "
                           f"it; the map is damaged (see `reloc map check`), not exported")


class _HashingReader:
    """A file object that hashes what is read from it."""

    def __init__(self, fh: IO[bytes]) -> None:
        self.fh = fh
        self.digest = hashlib.sha256()

    def read(self, size: int = -1) -> bytes:
        data = self.fh.read(size)
        self.digest.update(data)
        return data


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


# -- reading ----------------------------------------------------------------------------------

def extract_archive(path: Path, dest: Path) -> dict[str, Any]:
    """Check export file ``path`` and extract its parts into the empty directory ``dest``;
    its manifest. ArchiveError naming what is wrong (the caller removes ``dest`` then)."""
    try:
        tar = tarfile.open(path, "r:")
    except FileNotFoundError:
        raise ArchiveError(f"{path}: no such file") from None
    except (tarfile.TarError, OSError, EOFError) as exc:
        raise ArchiveError(f"{path}: not a reloc map export (not an uncompressed tar: "
                           f"{exc}); expected a file written by `reloc map export`") from exc
    with tar:
        manifest = _read_manifest(path, tar)
        expected = {p["path"]: p for p in manifest["parts"] if SAME_AS not in p}
        done: set[str] = set()
        while True:
            member = _next(path, tar, sorted(set(expected) - done))
            if member is None:
                break
            entry = expected.get(member.name)
            if entry is None or member.name in done or not member.isfile():
                raise ArchiveError(f"{path}: member {member.name!r} is not a part its manifest "
                                   f"lists (or is listed twice); the file was altered")
            _extract_part(path, tar, member, entry, dest)
            done.add(member.name)
    missing = [name for name in expected if name not in done]
    if missing:
        raise ArchiveError(f"{path}: truncated: {len(missing)} of {len(expected)} parts missing "
                           f"(first: {missing[0]}); the file ends early or a tar header is "
                           f"damaged")
    for entry in manifest["parts"]:
        if SAME_AS in entry:
            _link_part(dest / entry["path"], dest / entry[SAME_AS])
    return manifest


def _link_part(target: Path, source: Path) -> None:
    """``target`` as a hard link to the extracted part ``source`` (a copy where the file
    system cannot link)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(source, target)
    except OSError:
        shutil.copyfile(source, target)


def _next(path: Path, tar: tarfile.TarFile, pending: list[str]) -> tarfile.TarInfo | None:
    try:
        return tar.next()
    except (tarfile.TarError, OSError, EOFError) as exc:
        where = pending[0] if pending else "the end"
        raise ArchiveError(f"{path}: truncated or damaged before part {where} ({exc})") from exc


def _member_bytes(path: Path, tar: tarfile.TarFile, name: str, limit: int) -> bytes:
    member = _next(path, tar, [name])
    if member is None or member.name != name or not member.isfile() or member.size > limit:
        raise ArchiveError(f"{path}: expected {name} as the "
                           f"{'first' if name == MANIFEST else 'second'} member of a reloc map "
                           f"export, found {None if member is None else member.name!r}")
    fh = tar.extractfile(member)
    assert fh is not None
    try:
        return fh.read()
    except (tarfile.TarError, OSError, EOFError) as exc:
        raise ArchiveError(f"{path}: truncated inside {name} ({exc})") from exc


def _read_manifest(path: Path, tar: tarfile.TarFile) -> dict[str, Any]:
    """The manifest, checked: its own checksum, format, a known version, identity, parts."""
    text = _member_bytes(path, tar, MANIFEST, MAX_MANIFEST_BYTES)
    digest = _member_bytes(path, tar, MANIFEST_DIGEST, 1024).decode("ascii", "replace").strip()
    if hashlib.sha256(text).hexdigest() != digest:
        raise ArchiveError(f"{path}: part {MANIFEST}: checksum mismatch (SHA-256 "
                           f"{hashlib.sha256(text).hexdigest()[:16]}..., recorded "
                           f"{digest[:16]}...); the file is damaged")
    try:
        manifest = json.loads(text)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ArchiveError(f"{path}: {MANIFEST} is not valid JSON ({exc})") from exc
    got = manifest.get("format") if isinstance(manifest, dict) else None
    if got != FORMAT:
        raise ArchiveError(f"{path}: format {got!r}, expected {FORMAT!r}")
    version = manifest.get("format_version")
    if version not in READABLE_VERSIONS:
        raise ArchiveError(f"{path}: unknown export format version {version!r}; this reloc "
                           f"reads version(s) {', '.join(map(str, READABLE_VERSIONS))}"
                           + ("; upgrade reloc to import it" if isinstance(version, int)
                              and version > FORMAT_VERSION else ""))
    _check_fields(path, manifest)
    return manifest


def _check_fields(path: Path, manifest: dict[str, Any]) -> None:
    """The identity and the part list are present and well formed."""
    problems = []
    if not isinstance(manifest.get("map_id"), str) or len(manifest["map_id"]) != 32:
        problems.append("map_id (a UUID's 32 hex digits)")
    if not isinstance(manifest.get("last_seq"), int) or manifest["last_seq"] < 0:
        problems.append("last_seq (a sequence number)")
    if not isinstance(manifest.get("map_name"), str):
        problems.append("map_name")
    parts = manifest.get("parts")
    if not isinstance(parts, list) or not all(
            isinstance(p, dict) and isinstance(p.get("path"), str) and _safe(p["path"])
            and isinstance(p.get("size"), int) and isinstance(p.get("sha256"), str)
            for p in parts):
        problems.append("parts (relative paths with size and sha256)")
    elif not _links_resolve(parts):
        problems.append(f"{SAME_AS} (an earlier snapshot part of the same size and sha256)")
    if problems:
        raise ArchiveError(f"{path}: manifest lacks or has a malformed "
                           + ", ".join(problems))


def _links_resolve(parts: list[dict[str, Any]]) -> bool:
    """Every ``same_as`` names an earlier stored (not itself linked) snapshot part of the
    same size and SHA-256, and only snapshot parts are linked."""
    stored: dict[str, dict[str, Any]] = {}
    for p in parts:
        if SAME_AS not in p:
            stored[p["path"]] = p
            continue
        first = stored.get(p[SAME_AS]) if isinstance(p[SAME_AS], str) else None
        if first is None or p["path"] in stored or not all(
                q.startswith(LINKABLE_PREFIX) for q in (p["path"], first["path"])) or (
                first["size"], first["sha256"]) != (p["size"], p["sha256"]):
            return False
    return True


def _safe(rel: str) -> bool:
    """A relative path inside the map directory (no absolute path, no ``..``)."""
    p = PurePosixPath(rel)
    return bool(rel) and not p.is_absolute() and ".." not in p.parts and \
        rel not in (MANIFEST, MANIFEST_DIGEST)


def _extract_part(path: Path, tar: tarfile.TarFile, member: tarfile.TarInfo,
                  entry: dict[str, Any], dest: Path) -> None:
    """Copy one part to ``dest`` checking its size and SHA-256."""
    if member.size != entry["size"]:
        raise ArchiveError(f"{path}: part {member.name}: {member.size} bytes, its manifest "
                           f"says {entry['size']}; the file is damaged")
    target = dest / member.name
    target.parent.mkdir(parents=True, exist_ok=True)
    src = tar.extractfile(member)
    assert src is not None
    digest = hashlib.sha256()
    try:
        with open(target, "wb") as out:
            while chunk := src.read(CHUNK):
                digest.update(chunk)
                out.write(chunk)
    except (tarfile.TarError, EOFError) as exc:
        raise ArchiveError(f"{path}: truncated inside part {member.name} ({exc})") from exc
    if digest.hexdigest() != entry["sha256"]:
        raise ArchiveError(f"{path}: part {member.name}: checksum mismatch (SHA-256 "
                           f"{digest.hexdigest()[:16]}..., recorded {entry['sha256'][:16]}...); "
                           f"the file is damaged")
