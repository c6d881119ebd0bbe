"""atomic_write: a file is replaced whole or not at all."""

from __future__ import annotations

import json

import numpy as np
import pytest

from reloc_service.core.fileio import atomic_write


def test_atomic_write_replaces_text_bytes_and_writer_output(tmp_path):
    path = tmp_path / "service.json"
    atomic_write(path, json.dumps({"a": 1}))
    assert json.loads(path.read_text()) == {"a": 1}
    atomic_write(path, b"\x00\x01")
    assert path.read_bytes() == b"\x00\x01"
    arrays = tmp_path / "model.npz"
    atomic_write(arrays, lambda f: np.savez(f, x=np.arange(3)))
    assert np.load(arrays)["x"].tolist() == [0, 1, 2]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.npz", "service.json"]


def test_atomic_write_leaves_the_old_file_when_writing_fails(tmp_path):
    path = tmp_path / "CURRENT"
    atomic_write(path, "snapshots/1\n")

    def half_then_fail(f):
        f.write(b"snapsh")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(path, half_then_fail)
    assert path.read_text() == "snapshots/1\n"
    assert [p.name for p in tmp_path.iterdir()] == ["CURRENT"]  # no temporary file left


def test_atomic_write_without_fsync_still_replaces(tmp_path):
    path = tmp_path / "quarantine.bin"
    atomic_write(path, b"old", fsync=False)
    atomic_write(path, b"new", fsync=False)
    assert path.read_bytes() == b"new"


def test_atomic_write_into_a_missing_directory_raises(tmp_path):
    with pytest.raises(FileNotFoundError):
        atomic_write(tmp_path / "missing" / "f", "x")
