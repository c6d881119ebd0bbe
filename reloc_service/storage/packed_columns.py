"""Snapshot columns of low entropy stored zlib-compressed, exactly (format 7).

Some columns of a map repeat themselves: landmark ids count up by one, the observation
offsets grow by a landmark's few observations, the observations' kinds and keyframes come in
runs, a pyramid level is shared by hundreds of consecutive keypoints, the depth sigmas of a
map made from exact depth are all zero. Such a column is written as the zlib of its ``.npy``
(``<stem>.npy.zlib``) or, for a 1-D integer column, of the ``.npy`` of its successive
differences (``<stem>.delta.npy.zlib``: wrapping differences in the column's own dtype, so
the running sum in that dtype restores every value exactly). A column is packed only when
that keeps at most :data:`PACK_RATIO` of its bytes: the others (descriptors, keypoints,
points) are close to random, gain little, and stay memory-mapped where they are stored raw.
A packed column is decompressed into memory at load, as the integer landmark columns were
widened there anyway.
"""

from __future__ import annotations

import io
import zlib
from collections.abc import Container

import numpy as np

from ..core.errors import StorageError
from .snapshot_files import SnapshotReader

RAW = ".npy"
PACKED = ".npy.zlib"
DELTA_PACKED = ".delta.npy.zlib"
SUFFIXES = (RAW, PACKED, DELTA_PACKED)
#: Largest fraction of its bytes a packed column may keep: below a quarter, decompressing at
#: load (one pass, no memory map) is worth it; above, the column stays a mapped ``.npy``.
PACK_RATIO = 0.25


def npy_bytes(array: np.ndarray) -> bytes:
    """``array`` as the bytes of a ``.npy`` file (no pickled objects)."""
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()


def deltas(column: np.ndarray) -> np.ndarray:
    """Wrapping successive differences of a 1-D integer column, in its dtype (first value
    kept): :func:`undelta` restores the column exactly."""
    out = column.copy()
    if len(column) > 1:
        out[1:] = np.subtract(column[1:], column[:-1], dtype=column.dtype)
    return out


def undelta(diffs: np.ndarray) -> np.ndarray:
    """The column whose :func:`deltas` are ``diffs`` (a running sum wrapping in its dtype)."""
    return np.cumsum(diffs, dtype=diffs.dtype)


def packed_file(stem: str, column: np.ndarray, *, ratio: float = PACK_RATIO
                ) -> tuple[str, bytes]:
    """(relative path, bytes) of ``column`` stored under ``stem``: the smallest of zlib of
    its ``.npy`` and (1-D integers) of its differences' ``.npy`` when that keeps at most
    ``ratio`` of the raw ``.npy``, else the raw ``.npy``."""
    raw = npy_bytes(column)
    options = [(stem + PACKED, zlib.compress(raw, 6))]
    if column.ndim == 1 and column.dtype.kind in "iu" and len(column):
        options.append((stem + DELTA_PACKED, zlib.compress(npy_bytes(deltas(column)), 6)))
    path, data = min(options, key=lambda option: len(option[1]))
    return (path, data) if len(data) <= ratio * len(raw) else (stem + RAW, raw)


def stored_as(files: Container[str], stem: str) -> str | None:
    """The path under which a snapshot's ``files`` hold the column ``stem``, None if none."""
    return next((stem + s for s in SUFFIXES if stem + s in files), None)


def read_column(reader: SnapshotReader, stem: str) -> np.ndarray:
    """The checked column ``stem`` as stored (raw: memory-mapped; packed: decompressed,
    read-only); StorageError naming the file when it is missing or not what it claims."""
    # A column the manifest lists under none of its forms is asked for raw: the reader then
    # names what is wrong as for any other file (not listed with a checksum, missing).
    relpath = stored_as(reader.files, stem) or stem + RAW
    if relpath.endswith(RAW) and not relpath.endswith(PACKED):
        return reader.npy(relpath)
    return unpack(reader.read(relpath), str(reader.root / relpath),
                  delta=relpath.endswith(DELTA_PACKED))


def unpack(data: bytes, where: str, *, delta: bool) -> np.ndarray:
    """The read-only array of a packed column's bytes; StorageError naming ``where`` when they
    are not the zlib of a ``.npy`` of numbers (1-D integers for a ``delta`` column)."""
    try:
        array = np.load(io.BytesIO(zlib.decompress(data)), allow_pickle=False)
    except (zlib.error, ValueError, OSError, EOFError) as exc:
        raise StorageError(f"{where}: expected the zlib of a .npy array ({exc})") from exc
    if not isinstance(array, np.ndarray) or array.dtype.kind not in "biuf":
        raise StorageError(f"{where}: expected a .npy of numbers")
    if delta:
        if array.ndim != 1 or array.dtype.kind not in "iu":
            raise StorageError(f"{where}: expected 1-D integer differences, got "
                               f"{array.shape} {array.dtype}")
        array = undelta(array)
    array.flags.writeable = False
    return array
