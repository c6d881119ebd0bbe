"""Snapshot directories: numbered, immutable directories of checksummed files, one of them
named by an atomically replaced ``CURRENT`` file.

This module knows files, not maps: :class:`SnapshotWriter` writes and fsyncs files into a new
snapshot recording each one's size and SHA-256, :class:`SnapshotReader` reads or memory-maps
them back after checking both, and the functions here number, switch to and prune snapshot
directories. What a map's snapshot holds (the manifest and its arrays) is :mod:`.storage`'s.
"""

from __future__ import annotations

import hashlib
import io
import os
import re
import shutil
from collections.abc import Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core.errors import StorageError
from ..core.file_mapping import map_file
from ..core.fileio import atomic_write, fsync_path

CURRENT_FILE = "CURRENT"
SNAPSHOTS_DIR = "snapshots"
MANIFEST_FILE = "manifest.json"
#: Snapshots kept after a save (:func:`prune_snapshots`): the new one and the one it replaced.
KEEP_SNAPSHOTS = 2

#: Bytes of a .npy header read at most (numpy writes a few hundred).
NPY_HEADER_MAX = 1 << 16


class SnapshotWriter:
    """Writes files into a new snapshot directory, fsynced, recording their checksums."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.files: dict[str, dict[str, Any]] = {}

    def write(self, relpath: str, data: bytes) -> str:
        path = self.root / relpath
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        self.files[relpath] = {"sha256": hashlib.sha256(data).hexdigest(), "size": len(data)}
        return relpath

    def record_tree(self, relroot: str) -> None:
        """Checksum (and fsync) every file written by someone else under ``relroot``."""
        for path in sorted((self.root / relroot).rglob("*")):
            if path.is_file():
                data = path.read_bytes()
                fsync_path(path)
                rel = path.relative_to(self.root).as_posix()
                self.files[rel] = {"sha256": hashlib.sha256(data).hexdigest(), "size": len(data)}


def fsync_tree(root: Path) -> None:
    """fsync every directory under ``root`` (and ``root``), so new entries are durable."""
    for path in [root, *sorted(p for p in root.rglob("*") if p.is_dir())]:
        fsync_path(path)



def new_snapshot_dir(directory: Path) -> Path:
    """Create ``snapshots/<n>`` with n above every existing snapshot (atomic mkdir)."""
    snaps = directory / SNAPSHOTS_DIR
    snaps.mkdir(parents=True, exist_ok=True)
    numbers = [int(p.name) for p in snaps.iterdir() if p.name.isdigit()]
    n = max(numbers, default=0) + 1
    while True:
        path = snaps / f"{n:06d}"
        try:
            path.mkdir()
            return path
        except FileExistsError:
            n += 1


def switch_current(directory: Path, snapshot: Path) -> None:
    """Atomically point ``CURRENT`` at ``snapshot`` (write, fsync, rename, fsync directory)."""
    atomic_write(directory / CURRENT_FILE, snapshot.relative_to(directory).as_posix() + "\n")


def prune_snapshots(directory: Path, keep: Path, previous: Path | None) -> None:
    """Remove the snapshots the new one ``keep`` was built from, except ``previous`` (kept as
    a fallback): those numbered below ``previous``, and debris of crashed saves between the
    two (no manifest). Without a ``previous`` (``CURRENT`` was missing) nothing is removed:
    the new state was not built from the snapshots present, so they may hold what it lacks."""
    if previous is None:
        return
    floor = int(previous.name)
    for path in snapshot_dirs(directory):
        number = int(path.name)
        if path in (keep, previous) or number > int(keep.name):
            continue
        if number < floor or not (path / MANIFEST_FILE).is_file():
            shutil.rmtree(path, ignore_errors=True)


def snapshot_dirs(directory: str | Path) -> list[Path]:
    """The numbered snapshot directories of map directory ``directory``, oldest first."""
    snaps = Path(directory) / SNAPSHOTS_DIR
    if not snaps.is_dir():
        return []
    return sorted((p for p in snaps.iterdir() if p.name.isdigit() and p.is_dir()),
                  key=lambda p: int(p.name))



def current_or_none(directory: Path) -> Path | None:
    """The snapshot ``CURRENT`` names, or None when there is none (or it is damaged)."""
    try:
        return current_snapshot(directory)
    except StorageError:
        return None


def current_snapshot(directory: str | Path) -> Path:
    """The snapshot directory ``CURRENT`` names; StorageError if there is none."""
    directory = Path(directory)
    current = directory / CURRENT_FILE
    if not current.is_file():
        raise StorageError(f"{directory}: no saved map (missing {CURRENT_FILE}); expected a "
                           f"directory written by save_map")
    text = current.read_text(encoding="utf-8", errors="replace").strip()
    if not re.fullmatch(rf"{SNAPSHOTS_DIR}/\d+", text):
        raise StorageError(f"{current}: expected '{SNAPSHOTS_DIR}/<number>', got {text[:80]!r}")
    snapshot = directory / text
    if not snapshot.is_dir():
        raise StorageError(f"{current}: names {text!r}, which does not exist")
    return snapshot


class SnapshotReader:
    """Reads files of a snapshot, checking size and SHA-256 against the manifest."""

    def __init__(self, root: Path, files: Mapping[str, Any]) -> None:
        self.root = root
        self.files = files
        self._pending: dict[str, Future[npt.NDArray[np.uint8]]] = {}

    def prefetch(self, pool: ThreadPoolExecutor, relpaths: list[str]) -> None:
        """Start mapping and checking ``relpaths`` on ``pool``: hashlib hashes without the
        GIL, so the 1000 images of a big map hash on the other cores while this thread builds
        keyframes; ``map``/``check`` wait for a file's own check (and raise its error)."""
        for rel in relpaths:
            self._pending[rel] = pool.submit(self._map, rel)

    def wait_all(self) -> None:
        """Every prefetched file checked (the first damaged one in order raises)."""
        for future in self._pending.values():
            future.result()

    def read(self, relpath: str) -> bytes:
        path = self.root / relpath
        expected = self.files.get(relpath)
        if not isinstance(expected, dict) or "sha256" not in expected:
            raise StorageError(f"{path}: not listed with a checksum in {MANIFEST_FILE}")
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise StorageError(f"{path}: cannot read ({exc.strerror}); the map is damaged") from exc
        if len(data) != expected.get("size", len(data)):
            raise StorageError(f"{path}: {len(data)} bytes, expected {expected['size']} "
                               f"(truncated or damaged)")
        digest = hashlib.sha256(data).hexdigest()
        if digest != expected["sha256"]:
            raise StorageError(f"{path}: checksum mismatch (sha256 {digest[:12]}..., expected "
                               f"{str(expected['sha256'])[:12]}...); the file is damaged")
        return data

    def check(self, relpath: str) -> Path:
        """``relpath``'s path after checking its size and SHA-256 (hashed from a memory map,
        nothing copied or kept)."""
        self.map(relpath)
        return self.root / relpath

    def map(self, relpath: str) -> npt.NDArray[np.uint8]:
        """``relpath``'s bytes memory-mapped read-only after checking them (see ``_map``)."""
        future = self._pending.get(relpath)
        return self._map(relpath) if future is None else future.result()

    def _map(self, relpath: str) -> npt.NDArray[np.uint8]:
        """``relpath``'s bytes memory-mapped read-only after checking their size and SHA-256
        (:func:`..core.file_mapping.map_file`: the file is closed once mapped). One open and
        no copy: hashing the mapping instead of read() chunks halves the load
        time of a big map (reads copied every byte once more before hashing it)."""
        path = self.root / relpath
        expected = self.files.get(relpath)
        if not isinstance(expected, dict) or "sha256" not in expected:
            raise StorageError(f"{path}: not listed with a checksum in {MANIFEST_FILE}")
        try:
            with open(path, "rb") as fh:
                size = os.fstat(fh.fileno()).st_size
                # no descriptor stays open per mapped file: a map keeps every keyframe's
                # image mapped, more files than a process may hold open
                mapped = map_file(fh, size) if size else None
        except OSError as exc:
            raise StorageError(f"{path}: cannot read ({exc.strerror}); the map is damaged") from exc
        if size != expected.get("size", size):
            raise StorageError(f"{path}: {size} bytes, expected {expected['size']} "
                               f"(truncated or damaged)")
        digest = hashlib.sha256(mapped.array.data if mapped is not None else b"").hexdigest()
        if mapped is not None:
            # hashing touched every page: drop them from this process (they stay in the page
            # cache) so a kept mapping costs resident memory only once its bytes are used
            mapped.drop_pages()
        data = mapped.array if mapped is not None else np.zeros(0, np.uint8)
        if digest != expected["sha256"]:
            raise StorageError(f"{path}: checksum mismatch (sha256 {digest[:12]}..., "
                               f"expected {str(expected['sha256'])[:12]}...); the file is damaged")
        return data

    def npy(self, relpath: str) -> np.ndarray:
        """The checked array of ``relpath``, viewing its read-only memory map (``map``: no
        open file kept, where ``np.load(mmap_mode=...)`` keeps one per array); a plain array
        when it has no element (an empty region cannot be mapped)."""
        raw = self.map(relpath)
        path = self.root / relpath
        try:
            shape, dtype, fortran, offset = _npy_header(raw)
        except (ValueError, OSError, EOFError) as exc:
            raise StorageError(f"{path}: not a readable .npy ({exc})") from exc
        if dtype.hasobject:
            raise StorageError(f"{path}: a .npy of Python objects; expected numbers")
        count = int(np.prod(shape, dtype=np.int64))
        if offset + count * dtype.itemsize > len(raw):
            raise StorageError(f"{path}: {len(raw)} bytes hold less than its header's "
                               f"{shape} x {dtype}")
        if count == 0:
            return np.zeros(shape, dtype)
        return np.ndarray(shape, dtype, buffer=raw, offset=offset,
                          order="F" if fortran else "C")

    def npz(self, relpath: str, fields: tuple[str, ...], *, optional: tuple[str, ...] = ()
            ) -> dict[str, np.ndarray]:
        """The arrays ``fields`` (all required) and those of ``optional`` that are present."""
        try:
            with np.load(io.BytesIO(self.read(relpath)), allow_pickle=False) as data:
                missing = [f for f in fields if f not in data.files]
                if missing:
                    raise StorageError(f"{self.root / relpath}: missing array(s) {missing}; "
                                       f"expected {list(fields)}")
                return {f: data[f] for f in (*fields, *optional) if f in data.files}
        except (ValueError, OSError, EOFError) as exc:
            raise StorageError(f"{self.root / relpath}: not a readable .npz ({exc})") from exc

    def verify_tree(self, relroot: str) -> None:
        for rel in self.files:
            if rel.startswith(relroot + "/"):
                self.read(rel)


def _npy_header(raw: npt.NDArray[np.uint8]) -> tuple[tuple[int, ...], np.dtype, bool, int]:
    """(shape, dtype, Fortran order, data offset) of the .npy bytes ``raw`` (format versions
    1 and 2; ValueError otherwise)."""
    head = io.BytesIO(raw[:NPY_HEADER_MAX].tobytes())
    version = np.lib.format.read_magic(head)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(head)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(head)
    else:
        raise ValueError(f".npy format version {version}, expected 1.0 or 2.0")
    return tuple(shape), np.dtype(dtype), bool(fortran), head.tell()
