"""An append-only journal of opaque records, in numbered segment files, for crash safety.

A segment starts with a 16-byte header (magic and segment number); each record is framed as
``sync (4 bytes) | length (uint32 LE) | crc32(payload) | crc32(sync, length, payload crc) |
payload`` and is written, flushed and fsynced before :meth:`Journal.append` returns.
:meth:`Journal.rotate` starts a new segment, so a snapshot taken at that moment covers every
earlier segment, which :meth:`Journal.delete_before` then removes.

Reading keeps every record it can prove: a record whose header or payload fails its CRC is
skipped and reading resynchronises at the next sync marker whose header checks out, so one
damaged record (even a damaged length field) costs that record only. Its bytes are copied
to ``quarantine/`` next to the segments, never rewritten. Only a *torn tail* (an incomplete
last record, what a crash mid-write leaves) is truncated when the journal is opened for
writing, after its bytes are quarantined too; a segment ending in damaged (complete) bytes is
left as it is and appending continues in a new segment. Segments of the first format
(``RELOCJ01``, no sync markers) are still read; appending never continues one.

A journal given a map identity (:attr:`Journal.identity`) writes segments of the third format
(``RELOCJ03``): the header also holds the map's 16-byte UUID and the sequence number the
segment starts at (the number its first record carries, one more than the previous segment's
last), so segments chain and a segment of another map is recognised. Such a segment is
created whole (header written to a temporary file, fsynced, renamed), so a segment shorter
than its header is never what a crash leaves: it is kept as evidence of a loss and appending
continues in a new segment. Without an identity the second format (``RELOCJ02``) is written,
as before; both are read.
"""

from __future__ import annotations

import logging
import os
import re
import struct
import threading
import uuid
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from ..core.errors import StorageError
from ..core.fileio import atomic_write

log = logging.getLogger(__name__)

MAGIC = b"RELOCJ02"
#: The third format: the header also holds the map identity and the first sequence number.
MAGIC_V3 = b"RELOCJ03"
#: The first format: ``length | crc32 | payload`` frames without sync markers (read only).
MAGIC_V1 = b"RELOCJ01"
_HEADER = struct.Struct("<8sQ")       # magic, segment number
_HEADER_V3 = struct.Struct("<8sQ16sQ")  # magic, segment number, map UUID, first sequence number
SYNC = b"\xd3RJ\x0c"
_FRAME = struct.Struct("<4sIII")      # sync, payload length, crc32(payload), header crc32
_FRAME_V1 = struct.Struct("<II")      # payload length, crc32(payload)
#: Largest record accepted (a keyframe with its image is a few MB).
MAX_RECORD_BYTES = 256 * 1024 * 1024
_SEGMENT_RE = re.compile(r"^(\d{12})\.journal$")
QUARANTINE_DIR = "quarantine"
#: The number of a journal's first segment (later ones count up; older ones are deleted
#: once a snapshot holds their records).
FIRST_SEGMENT = 1


def segment_name(number: int) -> str:
    return f"{number:012d}.journal"


@dataclass(frozen=True)
class Damage:
    """Bytes of segment ``segment`` at ``offset`` that hold no provable record: ``kind`` is
    ``"corrupt"`` (skipped; reading resynchronised after it) or ``"torn"`` (an incomplete
    last record)."""

    segment: int
    offset: int
    size: int
    kind: str

    def quarantine_name(self) -> str:
        return f"{segment_name(self.segment)}.at{self.offset:010d}.{self.kind}"


@dataclass(frozen=True)
class SegmentScan:
    """What reading one segment found: its records, where appending could continue
    (``valid_bytes``: the end of the last record, before a torn tail), the damaged byte
    ranges, and the format version."""

    number: int
    records: list[bytes]
    valid_bytes: int
    damage: tuple[Damage, ...] = ()
    #: 1, 2 or 3; 0 for a file shorter than any header (nothing provable in it).
    version: int = 2
    #: Format 3: the map's identity (a UUID's hex) and the segment's first sequence number.
    map_id: str | None = None
    first_seq: int | None = None

    @property
    def header_bytes(self) -> int:
        return _HEADER_V3.size if self.version == 3 else _HEADER.size

    @property
    def dropped_bytes(self) -> int:
        return sum(d.size for d in self.damage)

    @property
    def torn_bytes(self) -> int:
        return sum(d.size for d in self.damage if d.kind == "torn")

    @property
    def ends_damaged(self) -> bool:
        """The segment ends in complete but corrupt bytes (appending must not continue it)."""
        return bool(self.damage) and self.damage[-1].kind == "corrupt" and (
            self.damage[-1].offset + self.damage[-1].size >= self.valid_bytes)


@dataclass
class JournalReport:
    """What :meth:`Journal.replay` found: records read, byte ranges skipped, torn tails,
    and the quarantine files holding their bytes."""

    records: int = 0
    damage: list[Damage] = field(default_factory=list)
    quarantined: list[Path] = field(default_factory=list)

    @property
    def skipped(self) -> list[Damage]:
        return [d for d in self.damage if d.kind == "corrupt"]

    @property
    def torn_bytes(self) -> int:
        return sum(d.size for d in self.damage if d.kind == "torn")


def frame(payload: bytes) -> bytes:
    """One framed record: sync marker, length, payload CRC32, header CRC32, payload."""
    head = SYNC + struct.pack("<II", len(payload), zlib.crc32(payload))
    return head + struct.pack("<I", zlib.crc32(head)) + payload


def _frame_at(data: bytes, pos: int) -> tuple[str, int]:
    """("ok", end) for a valid record at ``pos``; ("torn", len) for a valid header whose
    record runs past the end (or a header cut short); ("bad", pos) otherwise."""
    if len(data) - pos < _FRAME.size:
        return ("torn", len(data)) if SYNC.startswith(data[pos:pos + 4]) else ("bad", pos)
    sync, length, crc, head_crc = _FRAME.unpack_from(data, pos)
    if sync != SYNC or zlib.crc32(data[pos:pos + 12]) != head_crc or length > MAX_RECORD_BYTES:
        return "bad", pos
    end = pos + _FRAME.size + length
    if end > len(data):
        return "torn", len(data)
    if zlib.crc32(data[pos + _FRAME.size:end]) != crc:
        return "bad", pos
    return "ok", end


def _resync(data: bytes, start: int) -> int | None:
    """The next position from ``start`` where a record (complete or torn) provably begins."""
    pos = data.find(SYNC, start)
    while pos != -1:
        if _frame_at(data, pos)[0] != "bad":
            return pos
        pos = data.find(SYNC, pos + 1)
    return None


def scan_segment(path: Path) -> SegmentScan:
    """Every provable record of segment ``path``, skipping damaged ones (see module doc).
    StorageError if the header is not a reloc journal segment header."""
    data = path.read_bytes()
    number = _segment_number(path)
    if len(data) < _HEADER.size or (data[:8] == MAGIC_V3 and len(data) < _HEADER_V3.size):
        cut = (Damage(number, 0, len(data), "torn"),) if data else ()
        return SegmentScan(number, [], 0, cut, version=0)
    magic, stored = _HEADER.unpack_from(data)
    if magic not in (MAGIC, MAGIC_V1, MAGIC_V3) or stored != number:
        raise StorageError(f"{path}: not a reloc journal segment {number} (bad header: "
                           f"expected {MAGIC_V3!r} or {MAGIC!r} and segment number {number})")
    if magic == MAGIC_V1:
        return _scan_v1(data, number)
    map_id, first_seq = None, None
    if magic == MAGIC_V3:
        _, _, raw_id, first_seq = _HEADER_V3.unpack_from(data)
        map_id = raw_id.hex()
    start = _HEADER_V3.size if magic == MAGIC_V3 else _HEADER.size
    records, damage, pos = _scan_frames(data, number, start)
    return SegmentScan(number, records, pos, damage, version=3 if magic == MAGIC_V3 else 2,
                       map_id=map_id, first_seq=first_seq)


def _scan_frames(data: bytes, number: int, pos: int
                 ) -> tuple[list[bytes], tuple[Damage, ...], int]:
    """The records framed in ``data`` from ``pos``, the damaged ranges, and where appending
    could continue (after the last record, before a torn tail; the end after damage)."""
    records, damage = [], list[Damage]()
    while pos < len(data):
        status, end = _frame_at(data, pos)
        if status == "ok":
            records.append(data[pos + _FRAME.size:end])
            pos = end
            continue
        if status == "torn":
            damage.append(Damage(number, pos, len(data) - pos, "torn"))
            break
        nxt = _resync(data, pos + 1)
        damage.append(Damage(number, pos, (len(data) if nxt is None else nxt) - pos, "corrupt"))
        if nxt is None:
            return records, tuple(damage), len(data)
        pos = nxt
    return records, tuple(damage), pos


def _scan_v1(data: bytes, number: int) -> SegmentScan:
    """A first-format segment: records up to the first torn or corrupt one (no sync marker
    to resynchronise on); the rest is reported as one damaged range."""
    pos, records = _HEADER.size, []
    while pos + _FRAME_V1.size <= len(data):
        length, crc = _FRAME_V1.unpack_from(data, pos)
        end = pos + _FRAME_V1.size + length
        if length > MAX_RECORD_BYTES or end > len(data):
            break
        payload = data[pos + _FRAME_V1.size:end]
        if zlib.crc32(payload) != crc:
            break
        records.append(payload)
        pos = end
    damage = (Damage(number, pos, len(data) - pos, "corrupt"),) if pos < len(data) else ()
    return SegmentScan(number, records, len(data), damage, version=1)


def _segment_number(path: Path) -> int:
    m = _SEGMENT_RE.match(path.name)
    if not m:
        raise StorageError(f"{path}: not a journal segment name (expected NNNNNNNNNNNN.journal)")
    return int(m.group(1))


class Journal:
    """The journal in ``directory``: replay what is there, then append durably.

    Thread-safe; one writer at a time is expected (the map's writer). Damaged bytes found by
    :meth:`replay` are copied to ``quarantine`` (default ``directory/quarantine``) and listed
    in :attr:`report`."""

    def __init__(self, directory: str | Path, *, fsync: bool = True,
                 quarantine: str | Path | None = None) -> None:
        #: The map's UUID: set, new segments are of the third format and carry it.
        self.identity: uuid.UUID | None = None
        #: The sequence number the next record carries (its owner numbers the records; a
        #: new segment's header records it as its first).
        self.next_seq = 1
        self.directory = Path(directory)
        self.quarantine = (self.directory / QUARANTINE_DIR if quarantine is None
                           else Path(quarantine))
        self.fsync = fsync
        self.report = JournalReport()
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
        found = (_SEGMENT_RE.match(p.name) for p in self.directory.iterdir() if p.is_file())
        return sorted(int(m.group(1)) for m in found if m)

    def replay(self, from_segment: int = 0) -> Iterator[bytes]:
        """Every provable record of segments >= ``from_segment``, in order. Damaged bytes are
        skipped with an ERROR (a torn tail with a WARNING), quarantined and counted in
        :attr:`report`."""
        for _, record in self.replay_numbered(from_segment):
            yield record

    def replay_numbered(self, from_segment: int = 0) -> Iterator[tuple[int, bytes]]:
        """As :meth:`replay`, each record with the number of the segment holding it."""
        for number in self.segments():
            if number < from_segment:
                continue
            path = self.directory / segment_name(number)
            scan = scan_segment(path)
            self._note_damage(path, scan)
            self.report.records += len(scan.records)
            for record in scan.records:
                yield number, record

    def _note_damage(self, path: Path, scan: SegmentScan) -> None:
        for d in scan.damage:
            kept = self._quarantine(path, d)
            self.report.damage.append(d)
            self.report.quarantined.append(kept)
            if d.kind == "torn":
                log.warning("journal %s: a torn last record (%d bytes at offset %d, a write "
                            "cut by a crash); its bytes are kept in %s", path, d.size,
                            d.offset, kept)
            else:
                log.error("journal %s: skipped %d damaged bytes at offset %d (CRC mismatch); "
                          "reading resumed at the next valid record; the bytes are kept in %s",
                          path, d.size, d.offset, kept)

    def _quarantine(self, path: Path, damage: Damage) -> Path:
        """Copy the damaged bytes to the quarantine directory (once; durable)."""
        target = self.quarantine / damage.quarantine_name()
        if target.exists():
            return target
        with open(path, "rb") as fh:
            fh.seek(damage.offset)
            data = fh.read(damage.size)
        try:
            self.quarantine.mkdir(parents=True, exist_ok=True)
            atomic_write(target, data, fsync=self.fsync)
        except OSError as exc:
            raise StorageError(f"cannot keep the damaged bytes of {path} in {target}: "
                               f"{exc.strerror or exc}") from exc
        return target

    # -- writing -------------------------------------------------------------------------------
    def open(self, *, min_segment: int = 0) -> int:
        """Open for appending: continue the last segment after truncating a torn tail (its
        bytes quarantined first), or start a new segment (numbered at least ``min_segment``)
        if the last one is of an older format than this journal writes, ends in damaged bytes
        (left untouched) or, in the third format, is shorter than its header (kept: such a
        segment is never what a crash leaves). Returns the current segment."""
        with self._lock:
            self._mkdir()
            numbers = self.segments()
            if not numbers:
                self._start_segment(max(FIRST_SEGMENT, min_segment))
                return self._segment
            last = self.directory / segment_name(numbers[-1])
            scan = scan_segment(last)
            for d in scan.damage:
                self._quarantine(last, d)
            if scan.version == 0 and self.identity is None:
                last.unlink()     # a second-format segment cut while its header was written
                self._start_segment(max(numbers[-1], min_segment))
                return self._segment
            if (scan.version != (3 if self.identity is not None else 2) or scan.ends_damaged
                    or min_segment > numbers[-1]
                    or (self.identity is not None and scan.map_id != self.identity.hex)):
                self._start_segment(max(numbers[-1] + 1, min_segment))
                return self._segment
            self._continue(last, scan)
            return self._segment

    def _continue(self, last: Path, scan: SegmentScan) -> None:
        try:
            self._fd = os.open(last, os.O_WRONLY)
            if scan.torn_bytes:
                log.warning("journal %s: truncating a torn last record of %d bytes", last,
                            scan.torn_bytes)
                os.ftruncate(self._fd, scan.valid_bytes)
                self._sync(self._fd)
            os.lseek(self._fd, scan.valid_bytes, os.SEEK_SET)
        except OSError as exc:
            raise StorageError(f"cannot open journal {last} for writing: {exc}") from exc
        self._segment, self._size = scan.number, scan.valid_bytes

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
            self.next_seq += 1

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
        """Open a fresh segment ``number`` with its header (fsynced with its directory); in
        the third format created whole under a temporary name, then renamed."""
        path = self.directory / segment_name(number)
        header = (_HEADER.pack(MAGIC, number) if self.identity is None else
                  _HEADER_V3.pack(MAGIC_V3, number, self.identity.bytes, self.next_seq))
        target = path if self.identity is None else path.with_name(path.name + ".new")
        try:
            fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                _write_all(fd, header)
                self._sync(fd)
                if target != path:
                    os.replace(target, path)
                _fsync_dir(self.directory)
            except OSError:
                os.close(fd)
                raise
        except OSError as exc:
            self._broken = True
            if target != path:
                target.unlink(missing_ok=True)
            raise StorageError(f"cannot start journal segment {path}: "
                               f"{exc.strerror or exc}") from exc
        self._close_fd()
        self._fd, self._segment, self._size, self._broken = fd, number, len(header), False

    def _undo_partial_write(self) -> None:
        assert self._fd is not None
        try:
            os.ftruncate(self._fd, self._size)
            os.lseek(self._fd, self._size, os.SEEK_SET)
        except OSError:
            # The segment may end with garbage; replay skips it, so continue elsewhere.
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
