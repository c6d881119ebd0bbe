"""Exclusive ownership of a directory: an ``flock`` on ``<directory>/.lock`` held while the
owner runs, with a record of who holds it so that a refusal can name the holder.

The kernel drops an ``flock`` when the last descriptor of its open file closes, so a holder
killed with SIGKILL leaves no lock behind: the next owner takes over at once. The record in
the file is only information (it says *who*, never *whether*): a clean release empties it, so
a record found by a new owner means the previous one ended without releasing (killed or
crashed), which is logged. The descriptor is not inherited by child processes (Python opens
it non-inheritable), so an orphaned worker cannot keep a dead service's lock.

``flock`` is advisory and local: it does not exclude processes on another machine reaching
the directory over NFS or most network filesystems (see docs/reliability.md).
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import socket
import sys
import time
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path

from ..core.errors import StorageError

log = logging.getLogger(__name__)

LOCK_FILE = ".lock"
#: How long a refused ``flock`` is retried: long enough to outlast a read-only probe
#: (:func:`holder_if_locked` holds a shared lock for microseconds), far shorter than a start.
RETRY_S = 0.3
#: Bytes of holder record read at most (the record is a few hundred bytes).
MAX_RECORD = 64 * 1024


@dataclass(frozen=True)
class Holder:
    """Who holds (or last held) a lock: process id, host, since when (UTC, ISO 8601), the
    command line, and what for (``serve``, or the name of a tool)."""

    pid: int
    host: str
    since: str
    command: str
    purpose: str

    def describe(self) -> str:
        """``pid 123 on host drone1 since 2026-...Z (reloc serve --config ...)``."""
        return (f"pid {self.pid} on host {self.host} since {self.since} "
                f"({self.purpose}: {self.command})")


class LockHeld(StorageError):
    """Another process holds the lock; :attr:`holder` names it when its record reads."""

    def __init__(self, message: str, holder: Holder | None) -> None:
        super().__init__(message)
        self.holder = holder


def current_holder(purpose: str) -> Holder:
    """The record this process writes into a lock it takes."""
    since = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    command = " ".join([os.path.basename(sys.argv[0]) if sys.argv else "python",
                        *sys.argv[1:]])[:1000]
    return Holder(os.getpid(), socket.gethostname(), since, command, purpose)


class DirectoryLock:
    """An exclusive ``flock`` on ``<directory>/.lock`` (:meth:`acquire`, :meth:`release`)."""

    def __init__(self, directory: Path, *, what: str) -> None:
        """``what`` names the directory in messages ("storage", "map 'lab'")."""
        self.directory = directory
        self.path = directory / LOCK_FILE
        self.what = what
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self, purpose: str) -> DirectoryLock:
        """Take the lock and write this process's record into it; LockHeld naming the holder
        if another process has it (nothing is written then), StorageError if the lock file
        cannot be opened. Logs a previous holder that ended without releasing."""
        assert self._fd is None, f"{self.path} is already held by this object"
        fd = self._open()
        try:
            self._lock(fd)
            previous = _read_record(fd)
            _write_record(fd, current_holder(purpose))
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        if previous is not None:
            log.warning("%s %s: the previous holder, %s, is gone without releasing its lock "
                        "(killed or crashed); taking over", self.what, self.directory,
                        previous.describe())
        return self

    def release(self) -> None:
        """Empty the record (a clean end) and drop the lock; no-op if not held."""
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
            os.ftruncate(fd, 0)
        except OSError as exc:   # the lock goes anyway; the next owner logs a stale record
            log.warning("%s: cannot clear the lock record: %s", self.path, exc)
        finally:
            os.close(fd)       # closing the last descriptor drops the flock

    def __enter__(self) -> DirectoryLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def _open(self) -> int:
        try:
            return os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise StorageError(f"cannot open the lock file {self.path}: "
                               f"{exc.strerror or exc}; expected a writable {self.what} "
                               f"directory") from exc

    def _lock(self, fd: int) -> None:
        deadline = time.monotonic() + RETRY_S
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except OSError as exc:
                if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                    raise StorageError(f"cannot lock {self.path}: {exc.strerror or exc}") \
                        from exc
                if time.monotonic() >= deadline:
                    raise self._refusal(_read_record(fd)) from None
            time.sleep(0.02)

    def _refusal(self, holder: Holder | None) -> LockHeld:
        who = holder.describe() if holder is not None else "another process (its record " \
            "does not read)"
        return LockHeld(f"{self.what} {self.directory} is in use by {who}; only one process "
                        f"may own it: stop that one first (or use another directory)", holder)


def holder_if_locked(directory: Path) -> Holder | None:
    """Who holds ``<directory>/.lock`` right now, None if nobody does (or there is no lock
    file). Read only: probes with a shared lock released at once, writes nothing. A holder
    whose record does not read is reported with pid 0."""
    path = directory / LOCK_FILE
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            return _read_record(fd) or Holder(0, "?", "?", "?", "unknown")
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def _read_record(fd: int) -> Holder | None:
    """The holder record in the lock file (None if empty or unreadable)."""
    try:
        data = json.loads(os.pread(fd, MAX_RECORD, 0).decode("utf-8"))
        return Holder(int(data["pid"]), str(data["host"]), str(data["since"]),
                      str(data["command"]), str(data["purpose"]))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def _write_record(fd: int, holder: Holder) -> None:
    """Replace the record with ``holder``'s (not fsynced: it is information, the lock
    itself is the kernel's)."""
    data = json.dumps(asdict(holder)).encode("utf-8")
    os.ftruncate(fd, 0)
    os.pwrite(fd, data, 0)
