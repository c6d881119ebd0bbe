"""Read-only memory mappings of files that hold no file descriptor.

Python's :class:`mmap.mmap` duplicates the descriptor it maps and keeps it open as long as the
mapping lives. A map keeps every keyframe image mapped (read in place, resident only when
used), so with :class:`mmap.mmap` a map of a thousand keyframes held a thousand open files:
past the usual soft limit of 1024 (systemd's default, ``ulimit -n``) a map failed to load
with "Too many open files" and worker processes failed to start. POSIX lets a mapping outlive
its descriptor (``mmap(2)``: closing the file does not unmap the region), so here the region
is mapped through the C library, the file is closed at once, and the region is unmapped when
the last array viewing it is collected. Where the C library's ``mmap`` cannot be reached (not
a POSIX system), :class:`mmap.mmap` is used as before.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import mmap
import os
import weakref
from typing import IO

import numpy as np
import numpy.typing as npt


class _Libc:
    """``mmap``, ``munmap`` and ``madvise`` of the C library, typed for ctypes."""

    def __init__(self, lib: ctypes.CDLL) -> None:
        self.mmap = lib.mmap
        self.mmap.restype = ctypes.c_void_p
        self.mmap.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int,
                              ctypes.c_int, ctypes.c_int64)
        self.munmap = lib.munmap
        self.munmap.restype = ctypes.c_int
        self.munmap.argtypes = (ctypes.c_void_p, ctypes.c_size_t)
        self.madvise = lib.madvise
        self.madvise.restype = ctypes.c_int
        self.madvise.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)


def _load_libc() -> _Libc | None:
    if os.name != "posix" or ctypes.sizeof(ctypes.c_void_p) != 8:
        return None
    try:
        return _Libc(ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True))
    except (OSError, AttributeError):
        return None


_LIBC = _load_libc()
#: What the C library's ``mmap`` returns on failure: ``(void *) -1``.
_MAP_FAILED = ctypes.c_void_p(-1).value


class MappedFile:
    """A read-only mapping of a whole file: :attr:`array` (uint8, not writeable) views it.
    The region stays mapped while any array viewing it lives; no descriptor stays open
    unless the fallback :class:`mmap.mmap` is in use (:attr:`holds_descriptor`)."""

    def __init__(self, array: npt.NDArray[np.uint8], address: int | None,
                 fallback: mmap.mmap | None) -> None:
        self.array = array
        self._address = address
        self._fallback = fallback

    @property
    def holds_descriptor(self) -> bool:
        return self._fallback is not None

    def drop_pages(self) -> None:
        """Give the mapping's resident pages back (they stay in the page cache): after a pass
        over every byte (a checksum), a kept mapping then costs memory only where used."""
        if self._fallback is not None:
            self._fallback.madvise(mmap.MADV_DONTNEED)
        elif self._address is not None and _LIBC is not None:
            _LIBC.madvise(self._address, len(self.array), mmap.MADV_DONTNEED)


def map_file(fh: IO[bytes], size: int) -> MappedFile:
    """Map the first ``size`` bytes of the open file ``fh`` read-only (``size`` > 0: the
    caller's ``fstat``); the mapping does not need ``fh`` once this returns. OSError as
    ``mmap(2)`` gives it."""
    if size <= 0:
        raise ValueError(f"expected a file of at least one byte to map, got {size} bytes")
    if _LIBC is None:
        mapped = mmap.mmap(fh.fileno(), size, access=mmap.ACCESS_READ)
        return MappedFile(np.frombuffer(mapped, np.uint8), None, mapped)
    address = _LIBC.mmap(None, size, mmap.PROT_READ, mmap.MAP_PRIVATE, fh.fileno(), 0)
    if address is None or address == _MAP_FAILED:
        errno = ctypes.get_errno()
        raise OSError(errno, os.strerror(errno))
    region = (ctypes.c_ubyte * size).from_address(address)
    # Unmapped once nothing views the region: every array made from it keeps ``region``.
    # Not at exit: weakref's exit hook runs finalizers still pending, and a thread still
    # reading the map then (a pool being made) would fault on the unmapped pages; the
    # process's end unmaps everything anyway.
    weakref.finalize(region, _LIBC.munmap, address, size).atexit = False
    array = np.frombuffer(memoryview(region).cast("B"), np.uint8)
    array.flags.writeable = False  # the pages are PROT_READ: a write would fault
    return MappedFile(array, address, None)


def is_mapped(array: np.ndarray) -> bool:
    """Whether ``array`` views a region :func:`map_file` mapped (not a copy in memory)."""
    base: object = array
    while isinstance(base, np.ndarray):
        base = base.base
    while isinstance(base, memoryview):
        base = base.obj
    return isinstance(base, mmap.mmap | ctypes.Array)
