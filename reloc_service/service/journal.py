"""An append-only journal of opaque records, in numbered segment files, for crash safety.

Each record is framed as ``length (uint32 LE) | crc32 (uint32 LE) | payload`` and is written,
flushed and fsynced before :meth:`Journal.append` returns. A segment starts with a 16-byte
header (magic and segment number). :meth:`Journal.rotate` starts a new segment, so a snapshot
taken at that moment covers every earlier segment, which :meth:`Journal.delete_before` then
removes. Reading stops at the first record that is incomplete or fails its CRC (a write torn by
a crash): it is dropped with a log line, and the segment is truncated to its valid part when
the journal is opened for writing.
"""

from __future__ import annotations

import logging
import os
import re
import struct
import threading
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from ..errors import StorageError

log = logging.getLogger(__name__)

MAGIC = b"RELOCJ01"
_HEADER = struct.Struct("<8sQ")       # magic, segment number
_FRAME = struct.Struct("<II")         # payload length, crc32(payload)
#: Largest record accepted (a keyframe with its image is a few MB).
MAX_RECORD_BYTES = 256 * 1024 * 1024
_SEGMENT_RE = re.compile(r"^(\d{12})\.journal$")


def segment_name(number: int) -> str:
    return f"{number:012d}.journal"


@dataclass(frozen=True)
class SegmentScan:
    """What reading one segment found: its records, the byte length of the valid prefix, and
    whether anything after it was dropped (torn or corrupt)."""

    number: int
    records: list[bytes]
    valid_bytes: int
    dropped_bytes: int


def frame(payload: bytes) -> bytes:
    """One framed record: length, CRC32, payload."""
    return _FRAME.pack(len(payload), zlib.crc32(payload)) + payload


def scan_segment(path: Path) -> SegmentScan:
    """Read every valid record of segment ``path``; stop at the first torn or corrupt one."""
    data = path.read_bytes()
    number = _segment_number(path)
    if len(data) < _HEADER.size:
        return SegmentScan(number, [], 0, len(data))
    magic, stored = _HEADER.unpack_from(data)
    if magic != MAGIC or stored != number:
        raise StorageError(f"{path}: not a reloc journal segment {number} (bad header)")
    pos, records = _HEADER.size, []
    while pos + _FRAME.size <= len(data):
        length, crc = _FRAME.unpack_from(data, pos)
        end = pos + _FRAME.size + length
        if length > MAX_RECORD_BYTES or end > len(data):
            break
        payload = data[pos + _FRAME.size:end]
        if zlib.crc32(payload) != crc:
            break
        records.append(payload)
        pos = end
    return SegmentScan(number, records, pos, len(data) - pos)


def _segment_number(path: Path) -> int:
    m = _SEGMENT_RE.match(path.name)
    if not m:
        raise StorageError(f"{path}: not a journal segment name (expected NNNNNNNNNNNN.journal)")
    return int(m.group(1))


class Journal:
    """The journal in ``directory``: replay what is there, then append durably.

    Thread-safe; one writer at a time is expected (the service's writer thread)."""

    def __init__(self, directory: str | Path, *, fsync: bool = True) -> None:
        self.directory = Path(directory)
        self.fsync = fsync
        self._lock = threading.Lock()
        self._fd: int | None = None
        self._segment = 0
        self._size = 0            # bytes of valid data in the open segment
        self._broken = False      # a failed write could not be undone: start a new segment

    # -- reading -------------------------------------------------------------------------------
    def segments(self) -> list[int]:
        """Numbers of the segment files present, ascending."""
        if not self.directory.is_dir():
            return []
        found = (_SEGMENT_RE.match(p.name) for p in self.directory.iterdir())
        return sorted(int(m.group(1)) for m in found if m)

    def replay(self, from_segment: int = 0) -> Iterator[bytes]:
        """Every valid record of segments >= ``from_segment``, in order. A torn or corrupt
        tail is dropped with a log line (a crash mid-write leaves one at most)."""
        for number in self.segments():
            if number < from_segment:
                continue
            scan = scan_segment(self.directory / segment_name(number))
            if scan.dropped_bytes:
                log.warning("journal %s: dropped a torn or corrupt record (%d bytes after %d "
                            "valid records)", self.directory / segment_name(number),
                            scan.dropped_bytes, len(scan.records))
            yield from scan.records

    # -- writing -------------------------------------------------------------------------------
    def open(self) -> int:
        """Open for appending: truncate a torn tail of the last segment and continue it (or
        start segment 1). Returns the current segment number."""
        with self._lock:
            self._mkdir()
            numbers = self.segments()
            if not numbers:
                self._start_segment(1)
                return self._segment
            last = self.directory / segment_name(numbers[-1])
            scan = scan_segment(last)
            if scan.valid_bytes < _HEADER.size:
                last.unlink()
                self._start_segment(numbers[-1])
                return self._segment
            try:
                self._fd = os.open(last, os.O_WRONLY)
                if scan.dropped_bytes:
                    log.warning("journal %s: truncating %d bytes of a torn record", last,
                                scan.dropped_bytes)
                    os.ftruncate(self._fd, scan.valid_bytes)
                    self._sync(self._fd)
                os.lseek(self._fd, scan.valid_bytes, os.SEEK_SET)
            except OSError as exc:
                raise StorageError(f"cannot open journal {last} for writing: {exc}") from exc
            self._segment, self._size = numbers[-1], scan.valid_bytes
            return self._segment

    @property
    def segment(self) -> int:
        """The segment records are appended to."""
        return self._segment

    def append(self, payload: bytes) -> None:
        """Write one record and make it durable (flush + fsync) before returning.
        StorageError (disk full, read-only, ...) leaves the journal as it was."""
        if len(payload) > MAX_RECORD_BYTES:
            raise StorageError(f"journal record of {len(payload)} bytes; expected at most "
                               f"{MAX_RECORD_BYTES}")
        record = frame(payload)
        with self._lock:
            if self._fd is None or self._broken:
                self._start_segment(self._segment + 1)
            assert self._fd is not None
            try:
                _write_all(self._fd, record)
                self._sync(self._fd)
            except OSError as exc:
                self._undo_partial_write()
                raise StorageError(f"cannot write the journal in {self.directory}: "
                                   f"{exc.strerror or exc}") from exc
            self._size += len(record)

    def rotate(self) -> int:
        """Close the current segment and start the next; returns the new segment's number.
        Every record appended before the call is in a segment with a smaller number."""
        with self._lock:
            self._start_segment(self._segment + 1)
            return self._segment

    def delete_before(self, segment: int) -> None:
        """Remove the segments numbered below ``segment`` (covered by a durable snapshot)."""
        for number in self.segments():
            if number < segment:
                try:
                    (self.directory / segment_name(number)).unlink()
                except FileNotFoundError:
                    pass
        _fsync_dir(self.directory)

    def close(self) -> None:
        with self._lock:
            self._close_fd()

    # -- internals -----------------------------------------------------------------------------
    def _mkdir(self) -> None:
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StorageError(f"cannot create journal directory {self.directory}: "
                               f"{exc.strerror or exc}") from exc

    def _start_segment(self, number: int) -> None:
        """Open a fresh segment ``number`` with its header (fsynced with its directory)."""
        path = self.directory / segment_name(number)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                _write_all(fd, _HEADER.pack(MAGIC, number))
                self._sync(fd)
                _fsync_dir(self.directory)
            except OSError:
                os.close(fd)
                raise
        except OSError as exc:
            self._broken = True
            raise StorageError(f"cannot start journal segment {path}: "
                               f"{exc.strerror or exc}") from exc
        self._close_fd()
        self._fd, self._segment, self._size, self._broken = fd, number, _HEADER.size, False

    def _undo_partial_write(self) -> None:
        assert self._fd is not None
        try:
            os.ftruncate(self._fd, self._size)
            os.lseek(self._fd, self._size, os.SEEK_SET)
        except OSError:
            # The segment may end with garbage; replay stops there, so continue elsewhere.
            self._broken = True

    def _sync(self, fd: int) -> None:
        if self.fsync:
            os.fsync(fd)

    def _close_fd(self) -> None:
        if self._fd is not None:
            try:
                os.close(self._fd)
            finally:
                self._fd = None


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _fsync_dir(directory: Path) -> None:
    """Make a file creation, rename or deletion in ``directory`` durable."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
