"""The append-only journal: framing, replay, torn tails, rotation, failed writes."""

import errno
import os

import numpy as np
import pytest

from reloc_service.errors import StorageError
from reloc_service.service import journal as J
from reloc_service.service.journal import Journal, scan_segment, segment_name


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
