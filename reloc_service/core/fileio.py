"""Atomic file replacement: the one way reloc writes a file that must never be seen half-written."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

#: What :func:`atomic_write` writes: bytes, text (UTF-8), or a function writing to the file.
Content = bytes | str | Callable[[BinaryIO], object]


def atomic_write(path: str | Path, data: Content, *, fsync: bool = True) -> None:
    """Replace ``path`` with ``data`` so that a crash leaves either the old or the new file.

    The data goes to ``<path>.tmp`` in the same directory (flushed and fsynced), which is then
    renamed over ``path`` with :func:`os.replace` and the directory fsynced, so the rename
    itself survives a power loss. On any error the temporary file is removed and ``path`` is
    left as it was. ``fsync=False`` skips both fsyncs (the journal's ``fsync`` option, for
    tests on slow disks); the rename stays atomic.
    """
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as fh:
            _write(fh, data)
            fh.flush()
            if fsync:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if fsync:
        fsync_path(path.parent)


def fsync_path(path: str | Path) -> None:
    """fsync a file (its data) or a directory (a creation, rename or deletion in it)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write(fh: BinaryIO, data: Content) -> None:
    if isinstance(data, bytes):
        fh.write(data)
    elif isinstance(data, str):
        fh.write(data.encode("utf-8"))
    else:
        data(fh)
