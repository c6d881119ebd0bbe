"""Which image a std_srvs/Trigger call answers for.

A call answers for the newest image received no longer than ``max_image_age_s`` ago that no
call has answered for yet. When there is none, the call waits up to ``trigger_wait_s`` for
the next image: a drone that publishes an image and calls right away expects the answer for
that image, but Zenoh does not order samples of different key expressions (the image topic
and the service), so the call may arrive first. Every call waiting when an image arrives
answers for it. A call that finds nothing in time answers why (no image yet, none newer than
the last answered, the newest too old). A rejected image (not a PNG or JPEG, cut short, not
the camera's size, a message that does not decode) is answered for like any other: with
``success=False`` and the reason, never with an older image's pose.

Images are checked when they arrive, cheaply (header, size, the end marker of the file),
not decoded: a full decode costs 1.6 ms for a VGA JPEG and 8.7 ms for a PNG on the bridge's
one ordered worker, for every frame of a 30 Hz camera, most never asked about; the image
asked about is decoded once, by its relocalization, whose failure is answered the same way.

The waiting calls never block a thread: they wait in a list, answered by the image that
arrives or by one timer thread when their time is up.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from reloc_client import protocol as wire

log = logging.getLogger(__name__)


def stamp_text(stamp: Any) -> str:
    """builtin_interfaces/Time as ``<sec>.<nanosec, 9 digits>``."""
    return f"{int(stamp.sec)}.{int(stamp.nanosec):09d}"


@dataclass(frozen=True)
class ReceivedImage:
    """An image message as received: its stamp (None when the message did not decode), the
    image (None when rejected, ``problem`` then says why) and when it arrived (monotonic)."""

    seq: int
    received_s: float
    stamp: Any | None
    image: wire.WireImage | None
    problem: str | None = None

    def label(self) -> str:
        """How replies and logs name it."""
        if self.stamp is None:
            return "the image message that did not decode"
        return f"image stamped {stamp_text(self.stamp)}"


def image_problem(image: wire.WireImage, camera_size: tuple[int, int] | None) -> str | None:
    """Why ``image`` cannot be relocalized, from its header and end (no decoding), or None:
    another size than the camera's, or a PNG / JPEG file cut short."""
    if camera_size is not None and (image.width, image.height) != camera_size:
        return (f"its size {image.width}x{image.height} is not the camera's "
                f"{camera_size[0]}x{camera_size[1]} (camera_info)")
    data = image.data
    if image.format is wire.ImageFormat.PNG and data[-8:-4] != b"IEND":
        return "the PNG file is cut short (it does not end with the IEND chunk)"
    if image.format is wire.ImageFormat.JPEG and not data.rstrip(b"\0").endswith(b"\xff\xd9"):
        return "the JPEG file is cut short (it does not end with the EOI marker)"
    return None


#: ``answer(calls, image, reason)``: the calls answer for ``image``, or (``image`` None) fail
#: with ``reason``. Called outside the desk's lock, never in a waiting state.
Answer = Callable[[list[Any], ReceivedImage | None, str], None]


class TriggerDesk:
    """The calls waiting for their image and the images they answer for (module docstring)."""

    def __init__(self, answer: Answer, *, max_age_s: float, wait_s: float, topic: str,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._answer = answer
        self.max_age_s = max_age_s
        self.wait_s = wait_s
        self.topic = topic
        self._clock = clock
        self._cond = threading.Condition()
        self._newest: ReceivedImage | None = None
        self._answered_seq = -1
        self._waiting: list[tuple[float, Any]] = []   # (deadline, call)
        self._closed = False
        self._seq = 0
        self.waited = 0   # calls that arrived before an image to answer for
        self._timer = threading.Thread(target=self._expire_loop, name="ros2-trigger",
                                       daemon=True)
        self._timer.start()

    def received(self, stamp: Any | None, image: wire.WireImage | None,
                 problem: str | None = None) -> ReceivedImage:
        """A new image (numbered in arrival order); every waiting call answers for it."""
        with self._cond:
            self._seq += 1
            entry = ReceivedImage(self._seq, self._clock(), stamp, image, problem)
            self._newest = entry
            waiting = [call for _deadline, call in self._waiting]
            self._waiting = []
            if waiting:
                self._answered_seq = entry.seq
        if waiting:
            self._deliver(waiting, entry, "")
        return entry

    def call(self, call: Any) -> None:
        """A Trigger call: answered now for an unanswered fresh image, else when one arrives
        or ``wait_s`` is up."""
        with self._cond:
            if self._closed:
                chosen, reason = None, "reloc is shutting down"
            else:
                chosen, reason = self._unanswered(), ""
                if chosen is not None:
                    self._answered_seq = chosen.seq
                elif self.wait_s > 0:
                    self.waited += 1
                    self._waiting.append((self._clock() + self.wait_s, call))
                    self._cond.notify()
                    return
                else:
                    reason = self._why_none()
        self._deliver([call], chosen, reason)

    def close(self) -> None:
        """Answer every waiting call (shutting down) and stop the timer."""
        with self._cond:
            self._closed = True
            waiting = [call for _deadline, call in self._waiting]
            self._waiting = []
            self._cond.notify()
        if waiting:
            self._deliver(waiting, None, "reloc is shutting down")
        self._timer.join(timeout=5.0)

    def _deliver(self, calls: list[Any], image: ReceivedImage | None, reason: str) -> None:
        try:
            self._answer(calls, image, reason)
        except Exception:   # the timer and the bridge's worker go on
            log.exception("answering %d Trigger call(s) failed", len(calls))

    def _unanswered(self) -> ReceivedImage | None:
        newest = self._newest
        if newest is None or newest.seq <= self._answered_seq:
            return None
        return newest if self._clock() - newest.received_s <= self.max_age_s else None

    def _why_none(self) -> str:
        newest = self._newest
        if newest is None:
            return f"no image received on {self.topic} yet (waited {self.wait_s:.2f} s)"
        if newest.seq <= self._answered_seq:
            return (f"no image newer than {newest.label()} (answered already) arrived on "
                    f"{self.topic} within {self.wait_s:.2f} s")
        age = self._clock() - newest.received_s
        return (f"the newest image, {newest.label()}, arrived {age:.2f} s ago; expected one "
                f"at most {self.max_age_s:.2f} s old (max_image_age_s): is the camera "
                "publishing?")

    def _expire_loop(self) -> None:
        while True:
            with self._cond:
                if self._closed:
                    return
                now = self._clock()
                due = [call for deadline, call in self._waiting if deadline <= now]
                if not due:
                    timeout = min((d for d, _c in self._waiting), default=now + 3600) - now
                    self._cond.wait(timeout=max(timeout, 0.001))
                    continue
                self._waiting = [(d, c) for d, c in self._waiting if d > now]
                reason = self._why_none()
            self._deliver(due, None, reason)
