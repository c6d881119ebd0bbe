"""One relocalize worker process as the service sees it (:class:`WorkerHandle`): the process
and the parent's end of its pipe, sent to under a lock, how it exited, and its end
(:func:`terminate`)."""

from __future__ import annotations

import signal
import threading
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any


@dataclass
class WorkerHandle:
    """One worker process and the parent's end of its pipe."""

    process: Any
    conn: Connection
    send_lock: threading.Lock = field(default_factory=threading.Lock)
    dead: bool = False
    #: The maps whose replica this worker has loaded (it acknowledged one of their bases);
    #: changed under the owning :class:`~.processes.ProcessWorkers`' lock.
    holds: set[str] = field(default_factory=set)

    def send(self, msg: tuple[Any, ...]) -> bool:
        """Send ``msg``; False if the worker is gone (the pipe is closed)."""
        with self.send_lock:
            if self.dead:
                return False
            try:
                self.conn.send(msg)
                return True
            except (OSError, ValueError):
                self.dead = True
                return False

    def exit_description(self) -> str:
        self.process.join(1.0)
        code = self.process.exitcode
        if code is None:
            return "stopped answering"
        if code < 0:
            return f"was killed by signal {signal.Signals(-code).name}"
        return f"exited with status {code}"


def terminate(handle: WorkerHandle) -> None:
    """Make sure ``handle``'s process is gone (SIGTERM, then SIGKILL) and reaped."""
    process = handle.process
    if process.is_alive():
        process.terminate()
        process.join(1.0)
    if process.is_alive():
        process.kill()
        process.join(1.0)
    handle.conn.close()

