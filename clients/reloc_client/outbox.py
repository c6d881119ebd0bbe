"""An outbox of map changes (keyframe puts and removals, camera puts) that must reach the
service: kept in memory and sent in order, each resent until the service acknowledges it."""

from __future__ import annotations

import atexit
import collections
import logging
import threading
import weakref
from collections.abc import Callable
from typing import Any

from . import protocol as wire
from .client import (
    CameraLike,
    ImageLike,
    NoReplyError,
    PoseLike,
    RelocClient,
    ServiceBusy,
    ServiceError,
    _check_timeout,
    keyframe_put_bytes,
    to_wire_camera,
)

log = logging.getLogger(__name__)

#: Outboxes not closed yet: closed at interpreter exit if their owner forgot, so that no
#: sending thread is inside Zenoh's native code when the interpreter finalizes.
_OPEN: weakref.WeakSet[Outbox] = weakref.WeakSet()


class Outbox:
    """Map changes that must reach the service, kept in memory and sent in order by a
    background thread: each waits for its acknowledgement (journaled) before the next is
    sent, and is sent again while none comes (service down, restarting, unreachable).

    A resend cannot duplicate anything: a keyframe put replaces the keyframe of the same id.
    A change the service refuses is dropped and listed in :attr:`rejected`; "busy" is retried.
    Nothing survives this process: :meth:`flush` before exiting.

    >>> with Outbox(client) as outbox:
    ...     outbox.add_keyframe(0, image, world_from_cam, camera_id="cam0")  # returns at once
    ...     outbox.flush(timeout=600)                                    # True once all stored
    """

    def __init__(self, client: RelocClient, *, ack_timeout: float = 10.0,
                 retry_s: float = 1.0, max_pending: int = 10_000) -> None:
        self.client = client
        self.ack_timeout = _check_timeout(ack_timeout, ack_timeout)
        self.retry_s = float(retry_s)
        self.max_pending = int(max_pending)
        self.rejected: list[tuple[str, ServiceError]] = []
        #: Sends that got no acknowledgement (each was sent again).
        self.retries = 0
        self._items: collections.deque[tuple[str, Callable[[], object]]] = collections.deque()
        self._cond = threading.Condition()
        self._sending = False
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="reloc-outbox", daemon=True)
        self._thread.start()
        _OPEN.add(self)

    def add_keyframe(self, kf_id: int, image: ImageLike, world_from_cam: PoseLike,
                     **kwargs: Any) -> None:
        """Queue a keyframe put (arguments as :meth:`RelocClient.add_keyframe`; encoded now,
        so a bad argument raises here)."""
        payload = keyframe_put_bytes(kf_id, image, world_from_cam, **kwargs)
        c = self.client
        key = wire.keys.keyframe(c.prefix, c.map, kf_id)
        self._enqueue(f"keyframe {kf_id}", lambda: c._send(
            ("kf", kf_id), lambda: c._put(key, payload), wait=True, timeout=self.ack_timeout,
            what=f"keyframe {kf_id}"))

    def remove_keyframe(self, kf_id: int) -> None:
        """Queue the removal of keyframe ``kf_id``."""
        self._enqueue(f"removal of keyframe {kf_id}", lambda: self.client.remove_keyframe(
            kf_id, wait=True, timeout=self.ack_timeout))

    def set_camera(self, camera_id: str, camera: CameraLike) -> None:
        """Queue a camera put."""
        to_wire_camera(camera)   # a bad camera raises here
        self._enqueue(f"camera {camera_id!r}", lambda: self.client.set_camera(
            camera_id, camera, wait=True, timeout=self.ack_timeout))

    @property
    def pending(self) -> int:
        """Changes not acknowledged yet (including the one being sent)."""
        with self._cond:
            return len(self._items)

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every queued change is acknowledged or refused; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._items, timeout)

    def close(self) -> int:
        """Stop sending; the number of changes dropped unacknowledged."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._thread.join(self.ack_timeout + 1.0)
        _OPEN.discard(self)
        return self.pending

    def __enter__(self) -> Outbox:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _enqueue(self, what: str, send: Callable[[], object]) -> None:
        with self._cond:
            if self._closed:
                raise RuntimeError("outbox closed; expected changes before close()")
            if len(self._items) >= self.max_pending:
                raise RuntimeError(f"outbox full: {len(self._items)} changes wait for the "
                                   f"service (max_pending = {self.max_pending}); flush() first")
            self._items.append((what, send))
            self._cond.notify_all()

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._items or self._closed)
                if self._closed:
                    return
                what, send = self._items[0]
            if self._send_one(what, send):
                with self._cond:
                    self._items.popleft()
                    self._cond.notify_all()
            else:
                with self._cond:
                    self._cond.wait_for(lambda: self._closed, self.retry_s)

    def _send_one(self, what: str, send: Callable[[], object]) -> bool:
        """Send one change; True once it is done with (acknowledged or refused)."""
        try:
            send()
        except ServiceBusy:
            return False
        except ServiceError as exc:
            log.warning("outbox: %s refused: %s", what, exc)
            self.rejected.append((what, exc))
        except NoReplyError:
            self.retries += 1
            return False
        except Exception:   # a closed session, ...: keep the change, try again
            log.exception("outbox: sending %s failed", what)
            return False
        return True


def _close_at_exit() -> None:
    """Close the outboxes left open (their unacknowledged changes are lost with the process
    anyway), joining their threads before the interpreter finalizes."""
    for outbox in list(_OPEN):
        dropped = outbox.close()
        if dropped:
            log.warning("outbox closed at exit with %d changes unacknowledged", dropped)


atexit.register(_close_at_exit)
