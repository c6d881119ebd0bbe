"""The append-only journal: framing, replay, torn tails, rotation, failed writes."""

import errno
import os

import numpy as np
import pytest

from reloc_service.core.errors import StorageError
from reloc_service.storage import journal as J
from reloc_service.storage.journal import Journal, scan_segment, segment_name


def records(n: int, seed: int = 0) -> list[bytes]:
    rng = np.random.default_rng(seed)
    return [rng.bytes(int(rng.integers(0, 3000))) for _ in range(n)]


def test_append_then_replay_in_order(tmp_path):
    j = Journal(tmp_path)
    assert j.open() == 1
    data = records(20)
    for r in data:
        j.append(r)
    j.close()
    assert list(Journal(tmp_path).replay()) == data


def test_reopen_continues_the_last_segment(tmp_path):
    j = Journal(tmp_path)
    j.open()
    j.append(b"a")
    j.close()
    j = Journal(tmp_path)
    assert j.open() == 1
    j.append(b"b")
    j.close()
    assert list(Journal(tmp_path).replay()) == [b"a", b"b"]


@pytest.mark.parametrize("missing", [1, 5, 12, 19])
def test_torn_last_record_is_dropped_and_truncated(tmp_path, caplog, missing):
    j = Journal(tmp_path)
    j.open()
    for r in (b"first", b"second", b"third-record"):
        j.append(r)
    j.close()
    path = tmp_path / segment_name(1)
    size = path.stat().st_size
    with open(path, "r+b") as f:      # a crash part-way through the last (20-byte) record
        f.truncate(size - missing)
    with caplog.at_level("WARNING"):
        assert list(Journal(tmp_path).replay()) == [b"first", b"second"]
    assert "torn" in caplog.text
    j = Journal(tmp_path)
    j.open()                           # truncates the tail, then appends after the good part
    j.append(b"fourth")
    j.close()
    assert list(Journal(tmp_path).replay()) == [b"first", b"second", b"fourth"]
    assert scan_segment(path).dropped_bytes == 0


def test_corrupt_record_stops_replay(tmp_path):
    j = Journal(tmp_path)
    j.open()
    j.append(b"good")
    j.append(b"will be flipped")
    j.close()
    path = tmp_path / segment_name(1)
    data = bytearray(path.read_bytes())
    data[-3] ^= 0xFF
    path.write_bytes(bytes(data))
    assert list(Journal(tmp_path).replay()) == [b"good"]


def test_rotate_and_delete_before(tmp_path):
    j = Journal(tmp_path)
    j.open()
    j.append(b"old")
    new = j.rotate()
    assert new == 2
    j.append(b"new")
    assert list(j.replay(from_segment=2)) == [b"new"]
    assert list(j.replay()) == [b"old", b"new"]
    j.delete_before(2)
    assert j.segments() == [2]
    j.close()


def test_bad_header_is_a_storage_error(tmp_path):
    (tmp_path / segment_name(1)).write_bytes(b"NOTAJOURNALxxxxxxxxxxxxx")
    with pytest.raises(StorageError, match="bad header"):
        list(Journal(tmp_path).replay())


def test_failed_write_leaves_the_journal_usable(tmp_path, monkeypatch):
    j = Journal(tmp_path)
    j.open()
    j.append(b"before")
    real_write = os.write
    calls = {"n": 0}

    def full_disk(fd, data):  # write half, then fail like a full disk
        calls["n"] += 1
        if calls["n"] == 1:
            real_write(fd, bytes(data[: len(data) // 2]))
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(J.os, "write", full_disk)
    with pytest.raises(StorageError, match="No space left"):
        j.append(b"lost-record-xxxxxxxxxxxxxxxxxxxx")
    monkeypatch.setattr(J.os, "write", real_write)
    j.append(b"after")
    j.close()
    assert list(Journal(tmp_path).replay()) == [b"before", b"after"]


def test_unwritable_directory_is_a_storage_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_bytes(b"")
    with pytest.raises(StorageError, match="cannot create journal directory"):
        Journal(blocker / "journal").open()


# -- damage: skip one record, resynchronise, quarantine its bytes (docs/reliability.md, fault case 3)

def _offsets(path) -> list[int]:
    """Byte offset of every record of a clean segment (from its own framing)."""
    scan, out, pos = scan_segment(path), [], J._HEADER.size
    for r in scan.records:
        out.append(pos)
        pos += J._FRAME.size + len(r)
    return out


def _written(tmp_path, data: list[bytes]):
    j = Journal(tmp_path)
    j.open()
    for r in data:
        j.append(r)
    j.close()
    return tmp_path / segment_name(1)


def _flip(path, offset: int, mask: int = 0x01) -> bytes:
    data = bytearray(path.read_bytes())
    data[offset] ^= mask
    path.write_bytes(bytes(data))
    return bytes(data)


@pytest.mark.parametrize("k", range(11))
@pytest.mark.parametrize("where", ["payload", "length", "sync"])
def test_one_damaged_record_loses_only_that_record(tmp_path, k, where):
    data = records(11, seed=k)
    data = [r or b"x" for r in data]
    path = _written(tmp_path, data)
    start = _offsets(path)[k]
    end = start + J._FRAME.size + len(data[k])
    at = {"payload": end - 1, "length": start + 5, "sync": start}[where]
    damaged = _flip(path, at)
    j = Journal(tmp_path)
    assert list(j.replay()) == data[:k] + data[k + 1:]
    [skip] = j.report.skipped
    assert (skip.offset, skip.size) == (start, end - start)
    [kept] = j.report.quarantined
    assert kept.read_bytes() == damaged[start:end]           # the bytes, as found
    assert path.read_bytes() == damaged                      # the segment is not rewritten
    j.open()                                                 # appending goes on elsewhere
    j.append(b"after")
    j.close()
    assert path.read_bytes()[:len(damaged)] == damaged   # appended to, never rewritten
    assert list(Journal(tmp_path).replay()) == data[:k] + data[k + 1:] + [b"after"]


def test_a_damaged_length_claiming_more_than_the_file_is_not_a_torn_tail(tmp_path):
    data = [b"a" * 100, b"b" * 100, b"c" * 100]
    path = _written(tmp_path, data)
    start = _offsets(path)[1]
    raw = bytearray(path.read_bytes())
    raw[start + 4:start + 8] = (10**6).to_bytes(4, "little")   # far past the end of the file
    path.write_bytes(bytes(raw))
    j = Journal(tmp_path)
    assert list(j.replay()) == [data[0], data[2]]
    assert j.report.torn_bytes == 0 and len(j.report.skipped) == 1


def test_replay_twice_quarantines_once(tmp_path):
    path = _written(tmp_path, [b"one", b"two", b"three"])
    _flip(path, _offsets(path)[1] + J._FRAME.size)
    assert list(Journal(tmp_path).replay()) == [b"one", b"three"]
    assert list(Journal(tmp_path).replay()) == [b"one", b"three"]
    assert len(list((tmp_path / J.QUARANTINE_DIR).iterdir())) == 1


def test_a_segment_ending_in_damage_is_left_as_it_is(tmp_path):
    path = _written(tmp_path, [b"one", b"two"])
    damaged = _flip(path, len(path.read_bytes()) - 1)
    j = Journal(tmp_path)
    assert list(j.replay()) == [b"one"]
    assert j.open() == 2
    j.append(b"three")
    j.close()
    assert path.read_bytes() == damaged
    assert list(Journal(tmp_path).replay()) == [b"one", b"three"]


def test_first_format_segments_are_still_read(tmp_path):
    old = [b"old-1", b"old-2"]
    body = b"".join(J._FRAME_V1.pack(len(r), J.zlib.crc32(r)) + r for r in old)
    (tmp_path / segment_name(1)).write_bytes(J._HEADER.pack(J.MAGIC_V1, 1) + body)
    j = Journal(tmp_path)
    assert list(j.replay()) == old
    assert j.open() == 2                      # never appends to a first-format segment
    j.append(b"new")
    j.close()
    assert list(Journal(tmp_path).replay()) == [*old, b"new"]


# -- the third format: map identity and sequence numbers in the segment header ------------------

def test_segments_of_a_journal_with_an_identity_carry_it_and_chain_by_sequence_number(tmp_path):
    import uuid

    j = Journal(tmp_path)
    j.identity = uuid.UUID(int=7)
    assert j.open() == 1
    for r in records(3):
        j.append(r)
    assert j.next_seq == 4
    assert j.rotate() == 2
    j.append(b"after the rotation")
    j.close()
    first, second = scan_segment(tmp_path / segment_name(1)), scan_segment(tmp_path / segment_name(2))
    assert (first.version, first.map_id, first.first_seq) == (3, uuid.UUID(int=7).hex, 1)
    assert (second.version, second.first_seq, second.records) == (3, 4, [b"after the rotation"])
    assert list(Journal(tmp_path).replay()) == [*records(3), b"after the rotation"]
    assert not list(tmp_path.glob("*.new"))          # created whole, then renamed


def test_a_third_format_segment_shorter_than_its_header_is_kept_not_reused(tmp_path):
    """Such a segment is never what a crash leaves (segments are created whole): it is kept as
    the evidence of a loss and appending continues in a new segment."""
    import uuid

    j = Journal(tmp_path)
    j.identity = uuid.UUID(int=7)
    j.open()
    j.append(b"lost")
    j.close()
    (tmp_path / segment_name(1)).write_bytes(b"")
    j = Journal(tmp_path)
    j.identity = uuid.UUID(int=7)
    assert j.open() == 2
    j.close()
    assert (tmp_path / segment_name(1)).read_bytes() == b""
    assert scan_segment(tmp_path / segment_name(1)).version == 0


def test_a_journal_with_an_identity_does_not_continue_a_second_format_segment(tmp_path):
    import uuid

    j = Journal(tmp_path)
    j.open()
    j.append(b"legacy")
    j.close()
    j = Journal(tmp_path)
    j.identity = uuid.UUID(int=7)
    assert j.open() == 2
    j.append(b"numbered")
    j.close()
    assert scan_segment(tmp_path / segment_name(1)).version == 2
    assert list(Journal(tmp_path).replay()) == [b"legacy", b"numbered"]
