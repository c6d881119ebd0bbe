"""What a client follows while it waits: the liveliness tokens of the instances serving its
map (:class:`ServiceWatch`) and the acknowledgement events of its puts (:class:`Acks`)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import zenoh

from . import protocol as wire
from .protocol import ProtocolError


class ServiceWatch:
    """The liveliness tokens of the instances serving ``map_name`` under ``prefix``. ``gone`` names the
    token withdrawn when the followed instance's goes (see :meth:`follow`), or the last one
    when none is left; ``changed()`` is called then."""

    def __init__(self, session: zenoh.Session, prefix: str, map_name: str,
                 changed: Callable[[], None]) -> None:
        self.prefix, self.map = prefix, map_name
        self.live: set[str] = set()
        self.gone: str | None = None
        self._followed: str | None = None
        self._lock = threading.Lock()
        self._changed = changed
        key = f"{prefix}/@live/*/{map_name}"
        self._sub = session.liveliness().declare_subscriber(key, self._on_sample, history=True)

    def follow(self, instance: Any) -> None:
        """Watch only ``instance``'s token (the one running the job), if it is a valid name."""
        try:
            key = wire.keys.liveliness(self.prefix, instance, self.map)
        except (ProtocolError, TypeError):
            return   # an older service does not name itself: any instance will do
        with self._lock:
            self._followed = key

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.live.add(key)
                return
            self.live.discard(key)
            if key != self._followed and (self.live or self._followed is not None):
                return
            self.gone = key
        self._changed()

    def undeclare(self) -> None:
        self._sub.undeclare()


class Acks:
    """Acknowledgement events of this client's puts, by (``"kf"`` or ``"cam"``, id): only
    those being waited for are kept."""

    KINDS = {wire.EventKind.KEYFRAME_ACCEPTED: "kf", wire.EventKind.KEYFRAME_ADDED: "kf",
             wire.EventKind.KEYFRAME_REMOVED: "kf", wire.EventKind.KEYFRAME_REJECTED: "kf",
             wire.EventKind.CAMERA_ADDED: "cam", wire.EventKind.CAMERA_REJECTED: "cam"}

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._waiting: dict[tuple[str, Any], list[wire.Event]] = {}
        self.subscriber: zenoh.Subscriber | None = None

    def expect(self, ack: tuple[str, Any]) -> None:
        with self._cond:
            self._waiting[ack] = []

    def forget(self, ack: tuple[str, Any]) -> None:
        with self._cond:
            self._waiting.pop(ack, None)

    def on_event(self, event: wire.Event) -> None:
        ack = (self.KINDS[event.kind], event.fields.get("id"))
        with self._cond:
            if ack in self._waiting:
                self._waiting[ack].append(event)
                self._cond.notify_all()

    def wait(self, ack: tuple[str, Any], timeout: float,
             done: Callable[[list[wire.Event]], bool]) -> list[wire.Event]:
        """The events of ``ack`` so far, once ``done`` says they suffice or at ``timeout``."""
        with self._cond:
            self._cond.wait_for(lambda: done(self._waiting.get(ack, [])), timeout)
            return list(self._waiting.get(ack, []))


def stored_refused(events: list[wire.Event]) -> tuple[set[str], dict[str, wire.Event]]:
    """The instances that stored a put (accepted or applied it) and those that refused it
    (their first refusal), each instance counted by its first answer."""
    stored: set[str] = set()
    refused: dict[str, wire.Event] = {}
    for event in events:
        instance = str(event.fields.get("instance", ""))
        if instance in stored or instance in refused:
            continue
        if event.kind in (wire.EventKind.KEYFRAME_REJECTED, wire.EventKind.CAMERA_REJECTED):
            refused[instance] = event
        else:
            stored.add(instance)
    return stored, refused


def replica_answers(events: list[wire.Event], replicas: int, expected: int) -> bool:
    """Enough instances stored it, or every instance expected answered."""
    stored, refused = stored_refused(events)
    return len(stored) >= replicas or len(stored) + len(refused) >= expected
