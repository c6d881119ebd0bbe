"""What a ground crew watches: each map node's status as a diagnostic_msgs/DiagnosticStatus
on ``/diagnostics`` (DiagnosticArray, as ROS's diagnostic_updater publishes it: every
``diagnostics_period_s`` and at once on a change), and the events behind it in the log.

:class:`NodeStatus` keeps one node's counters and last events (thread-safe): each Trigger
answer, each keyframe added or refused (INFO / WARNING log line and a counter), each failure
of the lost-mode relocalization (WARNING). :func:`level_and_summary` turns them and the map's
state into OK / WARN / ERROR and a one-line message; :class:`DiagnosticsLoop` publishes.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from reloc_client import protocol as wire

from . import types as ros

log = logging.getLogger(__name__)

DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
#: Keyframes put and not yet added or refused by the map (their events name them).
PENDING_KEYFRAMES = 1024
OK, WARN, ERROR = 0, 1, 2   # diagnostic_msgs/DiagnosticStatus levels


@dataclass
class LastEvent:
    """What happened last: when (Unix seconds), whether it went well, and what."""

    time_s: float
    ok: bool
    text: str
    image: str = ""          # the image stamp it was about ("" when none)


@dataclass
class NodeStatus:
    """One map node's counters and last events (see module docstring)."""

    map_name: str
    on_change: Callable[[], None] = lambda: None
    counters: collections.Counter[str] = field(default_factory=collections.Counter)
    last_answer: LastEvent | None = None
    last_keyframe: LastEvent | None = None
    last_lost_mode: LastEvent | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] += n

    def answered(self, success: bool, message: str, image: str) -> None:
        """A Trigger call was answered (``image``: the stamp it answered for, or "")."""
        with self._lock:
            self.counters["answers_ok" if success else "answers_failed"] += 1
            self.last_answer = LastEvent(time.time(), success, message, image)
        self.on_change()

    def keyframe_added(self, kf_id: int, image: str, keyframes: int | None) -> None:
        with self._lock:
            self.counters["keyframes_added"] += 1
            self.last_keyframe = LastEvent(time.time(), True, f"keyframe {kf_id} added", image)
        log.info("map %s: keyframe %d added (%s; the map has %s keyframes)", self.map_name,
                 kf_id, image or "no image stamp", "?" if keyframes is None else keyframes)
        self.on_change()

    def keyframe_refused(self, kf_id: int | None, image: str, reason: str) -> None:
        what = "a keyframe" if kf_id is None else f"keyframe {kf_id}"
        with self._lock:
            self.counters["keyframes_refused"] += 1
            self.last_keyframe = LastEvent(time.time(), False, f"{what} refused: {reason}",
                                           image)
        log.warning("map %s: %s refused (%s): %s", self.map_name, what, image or "no image",
                    reason)
        self.on_change()

    def lost_mode(self, success: bool, message: str, image: str) -> None:
        """A relocalization of the lost mode (every Nth image while ``lost``)."""
        with self._lock:
            self.counters["lost_mode_ok" if success else "lost_mode_failed"] += 1
            self.last_lost_mode = LastEvent(time.time(), success, message, image)
        if not success:
            log.warning("map %s: lost-mode relocalization of %s failed: %s", self.map_name,
                        image, message)
        self.on_change()

    def localized(self, success: bool, message: str, image: str) -> None:
        """A localization of the tracking mode (every Nth image with the odometry's prior);
        a failure is routine (the service fell back to its full method and could not verify
        either) and logged at debug level."""
        with self._lock:
            self.counters["localize_ok" if success else "localize_failed"] += 1
        log.debug("map %s: localization of %s with a prior: %s", self.map_name, image, message)
        self.on_change()

    def snapshot(self) -> tuple[dict[str, int], dict[str, LastEvent | None]]:
        with self._lock:
            return dict(self.counters), {"answer": self.last_answer,
                                         "keyframe": self.last_keyframe,
                                         "lost_mode": self.last_lost_mode}


class KeyframeReports:
    """The keyframes a node puts, reported added or refused when the map's event about each
    arrives (the map's writer decides: a put can still be refused, e.g. over a quota)."""

    def __init__(self, status: NodeStatus, instance: str,
                 keyframes: Callable[[], int | None]) -> None:
        self.status = status
        self.instance = instance
        self._keyframes = keyframes
        self._images: dict[int, str] = {}   # put, not yet added or refused: its image stamp

    def put(self, kf_id: int, image: str) -> None:
        if len(self._images) >= PENDING_KEYFRAMES:   # events lost: forget the oldest
            self._images.pop(next(iter(self._images)))
        self._images[kf_id] = image

    def event(self, payload: bytes) -> None:
        """An event of the map (``<prefix>/<map>/events``); those about our puts reported."""
        try:
            event = wire.Event.decode(payload)
        except Exception as exc:
            log.debug("map %s: an event that does not decode: %s", self.status.map_name, exc)
            return
        fields = event.fields
        if event.kind not in (wire.EventKind.KEYFRAME_ADDED, wire.EventKind.KEYFRAME_REJECTED):
            return
        if fields.get("instance", self.instance) != self.instance:
            return   # another replica's acknowledgement
        kf_id = fields.get("id")
        if not isinstance(kf_id, int) or kf_id not in self._images:
            return
        image = self._images.pop(kf_id)
        if event.kind is wire.EventKind.KEYFRAME_ADDED:
            self.status.keyframe_added(kf_id, image, self._keyframes())
        else:
            self.status.keyframe_refused(kf_id, image, f"{fields.get('code', '?')}: "
                                                       f"{fields.get('message', '')}")


@dataclass(frozen=True)
class MapState:
    """What the bridge knows of the map and its inputs, for the summary."""

    served: bool
    keyframes: int = 0
    map_version: int = 0
    camera_known: bool = False
    lost: bool = False
    mismatches: int = 0


def map_keyframes(rt: Any) -> int | None:
    """The keyframes of a map runtime (None: not served)."""
    return None if rt is None else int(rt.engine.status()["keyframes"])


def map_state(rt: Any, *, camera_known: bool, lost: bool, mismatches: int) -> MapState:
    """The state of map runtime ``rt`` (None: not served) and of the node's inputs."""
    if rt is None:
        return MapState(served=False, mismatches=mismatches)
    engine = rt.engine.status()
    return MapState(served=True, keyframes=int(engine["keyframes"]),
                    map_version=int(engine["map_version"]), camera_known=camera_known,
                    lost=lost, mismatches=mismatches)


def node_status(status: NodeStatus, state: MapState, hardware_id: str,
                counters: dict[str, int], extra: dict[str, str]) -> Any:
    """A node's DiagnosticStatus: its level, summary and key-values."""
    own, last = status.snapshot()
    level, summary = level_and_summary(state, last)
    return status_message(f"reloc: {status.map_name}", hardware_id, level, summary,
                          values(state, {**own, **counters}, last, extra))


def level_and_summary(state: MapState, last: dict[str, LastEvent | None]) -> tuple[int, str]:
    """OK / WARN / ERROR and why: ERROR when nothing can work (the map is not served, or a
    node speaks another type on one of our topics, so rmw_zenoh never delivers); WARN when
    an answer cannot be given yet or the last one failed; else OK."""
    if not state.served:
        return ERROR, "the map is not served (see the service log)"
    if state.mismatches:
        return ERROR, "ROS 2 type mismatch on a topic (see the ROS 2 TYPE MISMATCH log line)"
    if not state.camera_known:
        return WARN, "no camera_info received yet"
    if state.keyframes == 0:
        return WARN, "the map has no keyframes yet"
    answer = last["answer"]
    if answer is not None and not answer.ok:
        return WARN, f"last answer failed: {answer.text}"
    if state.lost:
        lost = last["lost_mode"]
        return WARN, ("lost: relocalizing every Nth image" if lost is None else
                      f"lost: last relocalization {'succeeded' if lost.ok else 'failed'}")
    return OK, "ready" if answer is None else "last answer succeeded"


def values(state: MapState, counters: dict[str, int], last: dict[str, LastEvent | None],
           extra: dict[str, str]) -> list[tuple[str, str]]:
    """The status's key-values: the map, its inputs, the last events, the counters and
    ``extra`` (e.g. the map frame's)."""
    out = [("map keyframes", str(state.keyframes)), ("map version", str(state.map_version)),
           ("camera_info", "received" if state.camera_known else "none yet"),
           ("lost", str(state.lost).lower())]
    for name, event in last.items():
        if event is None:
            out.append((f"last {name}", "none"))
            continue
        out += [(f"last {name}", "ok" if event.ok else "failed"),
                (f"last {name} reason", event.text),
                (f"last {name} image stamp", event.image or "none"),
                (f"last {name} age s", f"{max(time.time() - event.time_s, 0.0):.1f}")]
    out += sorted((k, str(v)) for k, v in counters.items())
    out += sorted(extra.items())
    return out


def status_message(name: str, hardware_id: str, level: int, message: str,
                   key_values: Iterable[tuple[str, str]]) -> Any:
    """A diagnostic_msgs/DiagnosticStatus."""
    m = ros.message
    return m("diagnostic_msgs/msg/DiagnosticStatus", level=level, name=name, message=message,
             hardware_id=hardware_id,
             values=[m("diagnostic_msgs/msg/KeyValue", key=k, value=v) for k, v in key_values])


def array_message(statuses: list[Any], now_s: float | None = None) -> Any:
    """A diagnostic_msgs/DiagnosticArray stamped ``now_s`` (Unix seconds; now by default)."""
    m = ros.message
    t = time.time() if now_s is None else now_s
    stamp = m("builtin_interfaces/msg/Time", sec=int(t), nanosec=int((t - int(t)) * 1e9))
    return m(DIAGNOSTIC_ARRAY, header=m("std_msgs/msg/Header", stamp=stamp, frame_id=""),
             status=statuses)


class DiagnosticsLoop:
    """Calls ``publish()`` every ``period_s`` and soon after :meth:`changed` (changes within
    a tenth of the period are published together)."""

    def __init__(self, publish: Callable[[], None], period_s: float) -> None:
        self._publish = publish
        self.period_s = period_s
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="ros2-diagnostics",
                                        daemon=True)
        self._thread.start()

    def changed(self) -> None:
        self._wake.set()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=5.0)

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(timeout=self.period_s)
            if self._stop.is_set():
                return
            if self._wake.is_set():
                self._stop.wait(self.period_s / 10)   # gather a burst of changes
                self._wake.clear()
            try:
                self._publish()
            except Exception:   # a failed publication never stops the loop
                log.exception("publishing /diagnostics failed")
