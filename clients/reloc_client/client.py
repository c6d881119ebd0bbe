"""RelocClient: talk to a reloc service over Zenoh (keyframes in, poses out).

Failures are exceptions: :class:`ServiceError` (the service refused, with an
:class:`ErrorCode`), :class:`ServiceBusy` (its queue is full: retry later; a subclass of
ServiceError), :class:`NoReplyError` (nothing answered in time; a ``TimeoutError``),
:class:`ServiceGone` (the service went away while a job was awaited; a NoReplyError), and
:class:`ProtocolError` for arguments that cannot be encoded or replies that do not decode.
Puts are acknowledged by events: ``wait=True`` waits for the acknowledgement, and an
:class:`~reloc_client.outbox.Outbox` resends until it comes.
"Not relocalized" is not a failure: it is a :class:`RelocResult` with status NOT_RELOCALIZED.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import zenoh

from . import protocol as wire
from .acks import Acks, ServiceWatch, replica_answers, stored_refused
from .convert import (
    CameraLike,
    ImageLike,
    PoseLike,
    keyframe_put_bytes,
    to_wire_camera,
    to_wire_depth,
    to_wire_features,
    to_wire_image,
    to_wire_pose,
)
from .errors import NoReplyError, ServiceBusy, ServiceError, ServiceGone
from .protocol import ErrorCode, ProtocolError
from .result import RelocResult, RelocStatus, result_from_reply

log = logging.getLogger(__name__)

__all__ = ["NoReplyError", "RelocClient", "ServiceBusy", "ServiceError", "ServiceGone",
           "make_config"]


# -- the client -------------------------------------------------------------------------------

def make_config(connect: str | Sequence[str] | None = None, *, mode: str | None = None,
                config: zenoh.Config | None = None) -> zenoh.Config:
    """A Zenoh config: ``config`` (or the default), in ``mode`` ("client" unless ``config``
    is given), connecting to ``connect``; multicast scouting is off when endpoints are given."""
    if mode not in (None, "client", "peer"):
        raise ValueError(f"mode: expected 'client' or 'peer', got {mode!r}")
    conf = config if config is not None else zenoh.Config()
    if mode is not None or config is None:
        conf.insert_json5("mode", json.dumps(mode or "client"))
    if connect:
        endpoints = [connect] if isinstance(connect, str) else list(connect)
        conf.insert_json5("connect/endpoints", json.dumps(endpoints))
        conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


class RelocClient:
    """A Zenoh session bound to one map of a reloc service (ConnectionError if the
    endpoints cannot be reached in client mode).

    >>> with RelocClient("tcp/192.168.1.10:7447", map="lab") as client:
    ...     result = client.relocalize(grey_image, camera_id="cam0")
    ...     if result.ok:
    ...         print(result.world_from_cam)

    ``timeout`` (seconds) is the default for every query. The session opens in the
    constructor; ``close()`` (or leaving the ``with`` block) closes it.
    """

    def __init__(self, connect: str | Sequence[str] | None = None, *, map: str,  # noqa: A002
                 prefix: str = wire.DEFAULT_PREFIX, mode: str | None = None,
                 config: zenoh.Config | None = None, timeout: float = 10.0,
                 limits: wire.Limits = wire.DEFAULT_LIMITS) -> None:
        self.map = wire.check_name(map)
        self.prefix = wire.check_prefix(prefix)
        self.timeout = _check_timeout(timeout, 10.0)
        self.limits = limits
        try:
            self.session = zenoh.open(make_config(connect, mode=mode, config=config))
        except zenoh.ZError as exc:
            raise ConnectionError(f"cannot open a Zenoh session (connect={connect!r}): "
                                  f"{str(exc).split(' at ')[0]}") from exc
        self._acks: Acks | None = None
        self._acks_lock = threading.Lock()

    # -- life cycle ------------------------------------------------------------------------
    def close(self) -> None:
        """Close the Zenoh session (undeclares every subscriber opened through it)."""
        self._acks = None
        if not self.session.is_closed():
            self.session.close()

    def __enter__(self) -> RelocClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"RelocClient(map={self.map!r}, prefix={self.prefix!r})"

    # -- map building (puts: acknowledged by events) ---------------------------------------
    def set_camera(self, camera_id: str, camera: CameraLike, *, wait: bool = False,
                   timeout: float | None = None) -> None:
        """Put camera ``camera_id`` (a camera dict or object with ``to_dict()``). With
        ``wait``, return once the service registered it (see :meth:`add_keyframe`)."""
        message = wire.CameraPut(wire.check_name(camera_id, "camera id"), to_wire_camera(camera))
        key = wire.keys.camera(self.prefix, self.map, camera_id)
        self._send(("cam", camera_id), lambda: self._put(key, message.encode()), wait=wait,
                   timeout=timeout, what=f"camera {camera_id!r}")

    def add_keyframe(self, kf_id: int, image: ImageLike, world_from_cam: PoseLike, *,
                     camera_id: str | None = None, camera: CameraLike | None = None,
                     timestamp: float | None = None,
                     features: wire.WireFeatures | Mapping[str, Any] | None = None,
                     depth: Any = None, image_format: str | None = None,
                     pose_covariance: Any = None,
                     wait: bool = False, timeout: float | None = None,
                     replicas: int | None = None) -> tuple[str, ...]:
        """Put keyframe ``kf_id`` (added, or replaced if it exists) with its image,
        ``world_from_cam`` ((4, 4) or (t, q)), and exactly one of ``camera_id`` / ``camera``.
        ``pose_covariance`` (6, 6): how well ``world_from_cam`` is known (twist (rho, omega),
        right perturbation ``world_from_cam @ exp(xi)``, m and rad); the relocalized poses
        the keyframe supports carry it. None: the map's configured default applies.

        A put has no reply. Without ``wait`` it returns at once, even if no service is
        there; a refused keyframe is then only reported as a ``keyframe_rejected`` event (see
        :meth:`subscribe_events`). With ``wait``, it returns once the service has journaled
        the keyframe (its ``keyframe_accepted`` event: it survives a crash from then on; it
        is applied to the map shortly after, ``keyframe_added``), and raises ServiceError
        (ServiceBusy) if the service refused it, NoReplyError if no acknowledgement came
        within ``timeout`` seconds (default: the client's): put it again later (or use an
        :class:`Outbox`).

        ``replicas`` (with ``wait``; several instances serving the map): wait until that many
        instances stored the keyframe, and return their names; ServiceError naming who
        stored it and who refused (and why) once every instance serving the map answered
        short of that, NoReplyError naming who stored it on timeout. Without ``replicas``
        the first answer decides (a refusal by one replica raises even if another stored
        it). Returns the instances known to have stored it (empty without ``wait``)."""
        payload = keyframe_put_bytes(kf_id, image, world_from_cam, camera_id=camera_id,
                                     camera=camera, timestamp=timestamp, features=features,
                                     depth=depth, image_format=image_format,
                                     pose_covariance=pose_covariance)
        key = wire.keys.keyframe(self.prefix, self.map, kf_id)
        if replicas is not None:
            return self._send_to_replicas(("kf", kf_id), lambda: self._put(key, payload),
                                          replicas=replicas, timeout=timeout,
                                          what=f"keyframe {kf_id}")
        return self._send(("kf", kf_id), lambda: self._put(key, payload), wait=wait,
                          timeout=timeout, what=f"keyframe {kf_id}")

    def remove_keyframe(self, kf_id: int, *, wait: bool = False,
                        timeout: float | None = None) -> None:
        """Delete keyframe ``kf_id``. Without ``wait`` there is no reply (an unknown id is
        reported as a ``keyframe_rejected`` event); with ``wait``, return once the removal
        is journaled, raise as :meth:`add_keyframe` does."""
        key = wire.keys.keyframe(self.prefix, self.map, kf_id)
        self._send(("kf", kf_id), lambda: self.session.delete(
            key, congestion_control=zenoh.CongestionControl.BLOCK), wait=wait, timeout=timeout,
            what=f"removal of keyframe {kf_id}")

    def _put(self, key: str, payload: bytes) -> None:
        # BLOCK, not the default DROP: a map upload must not lose keyframes under load.
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def _send(self, ack: tuple[str, Any], send: Callable[[], None], *, wait: bool,
              timeout: float | None, what: str) -> tuple[str, ...]:
        """``send()``; with ``wait``, block until the service acknowledges ``ack`` (the
        instance that did, when it says)."""
        if not wait:
            send()
            return ()
        timeout = _check_timeout(timeout, self.timeout)
        acks = self._ack_events()
        acks.expect(ack)
        try:
            send()
            events = acks.wait(ack, timeout, lambda evs: bool(evs))
        finally:
            acks.forget(ack)
        event = events[0] if events else None
        if event is None:
            raise NoReplyError(f"{what} on map {self.map!r} was not acknowledged within "
                               f"{timeout} s: is a reloc service serving it under prefix "
                               f"{self.prefix!r} reachable? It may not be stored: put it again")
        if event.kind in (wire.EventKind.KEYFRAME_REJECTED, wire.EventKind.CAMERA_REJECTED):
            code = _error_code(event.fields.get("code"))
            cls = ServiceBusy if code is ErrorCode.BUSY else ServiceError
            raise cls(code, f"{what}: {event.fields.get('message', 'refused')}")
        instance = event.fields.get("instance")
        return (instance,) if isinstance(instance, str) else ()

    def _send_to_replicas(self, ack: tuple[str, Any], send: Callable[[], None], *,
                          replicas: int, timeout: float | None, what: str) -> tuple[str, ...]:
        """``send()``, then wait until ``replicas`` instances stored ``ack`` (their names),
        or every instance serving the map answered (ServiceError), or ``timeout``."""
        if isinstance(replicas, bool) or not isinstance(replicas, int) or replicas < 1:
            raise ValueError(f"replicas: expected an integer >= 1, got {replicas!r}")
        timeout = _check_timeout(timeout, self.timeout)
        serving = {i for i, m in self.maps(timeout=min(timeout, 2.0)) if m == self.map}
        expected = max(len(serving), replicas)
        acks = self._ack_events()
        acks.expect(ack)
        try:
            send()
            events = acks.wait(ack, timeout, lambda evs: replica_answers(evs, replicas,
                                                                          expected))
        finally:
            acks.forget(ack)
        stored, refused = stored_refused(events)
        if len(stored) >= replicas:
            return tuple(sorted(stored))
        said = (f"stored by {sorted(stored) or 'none'}; refused by "
                + (", ".join(f"{i or '?'} ({e.fields.get('code')}: "
                             f"{e.fields.get('message', 'refused')})"
                             for i, e in sorted(refused.items())) or "none"))
        if not refused:
            raise NoReplyError(f"{what} on map {self.map!r}: {len(stored)} of {replicas} "
                               f"replicas acknowledged within {timeout} s ({said})")
        first = refused[sorted(refused)[0]]
        raise ServiceError(_error_code(first.fields.get("code")),
                           f"{what}: {len(stored)} of {replicas} replicas stored it ({said})")

    def _ack_events(self) -> Acks:
        """The map's acknowledgement events, subscribed once per client."""
        with self._acks_lock:
            if self._acks is None:
                acks = Acks()
                acks.subscriber = self.subscribe_events(acks.on_event, kinds=Acks.KINDS)
                self._acks = acks
            return self._acks

    # -- queries ---------------------------------------------------------------------------
    def relocalize(self, image: ImageLike, *, camera_id: str | None = None,
                   camera: CameraLike | None = None, method: str | None = None,
                   prior: tuple[PoseLike, float] | tuple[PoseLike, float | None, Any]
                   | wire.Prior | None = None,
                   hypotheses: int = 1, timeout: float | None = None,
                   request_id: str | None = None, timestamp: float | None = None,
                   image_format: str | None = None) -> RelocResult:
        """Where was ``image`` taken? ``prior`` is (world_from_cam, radius_m), (world_from_cam,
        radius_m or None, 6x6 covariance: twist (rho, omega), m and rad) or a Prior; with a
        covariance the service tracks from the prior first.

        Returns a RelocResult (OK or NOT_RELOCALIZED); raises ServiceBusy, ServiceError,
        NoReplyError; ValueError for ``timeout`` <= 0 (None: the client's default)."""
        timeout = _check_timeout(timeout, self.timeout)
        if prior is not None and not isinstance(prior, wire.Prior):
            prior_pose, radius_m, *rest = prior
            covariance = None if not rest or rest[0] is None else tuple(
                float(v) for v in np.asarray(rest[0], np.float64).reshape(-1))
            prior = wire.Prior(to_wire_pose(prior_pose, "prior.world_from_cam"),
                               None if radius_m is None else float(radius_m), covariance)
        request = wire.RelocalizeRequest(
            image=to_wire_image(image, image_format=image_format), camera_id=camera_id,
            camera=None if camera is None else to_wire_camera(camera), method=method,
            prior=prior, hypotheses=hypotheses, request_id=request_id, timestamp=timestamp)
        start = time.perf_counter()
        payload = self._query_one(wire.keys.relocalize(self.prefix, self.map), request.encode(),
                                  timeout)
        reply = wire.RelocalizeReply.decode(payload, self.limits)
        if reply.status is wire.ReplyStatus.BUSY:
            raise ServiceBusy(ErrorCode.BUSY, reply.reason or "service busy; retry later")
        return result_from_reply(reply, round_trip_s=time.perf_counter() - start)

    def train(self, *, method: str | None = None, wait: bool = False,
              timeout: float | None = 600.0,
              on_event: Callable[[wire.Event], None] | None = None) -> wire.TrainReply:
        """Start training (the service answers at once). With ``wait``, block until the job's
        ``train_done`` event (``on_event`` sees every event of the job meanwhile); raise
        ServiceError on ``train_failed``, TimeoutError after ``timeout`` seconds, and
        ServiceGone (a TimeoutError) as soon as no instance serves the map any more (its
        liveliness tokens went away: the service died or stopped, the job is lost)."""
        events: queue.Queue[wire.Event | None] = queue.Queue()
        # Subscribe before asking, so a fast job's train_done cannot be missed.
        sub = self.subscribe_events(events.put) if wait else None
        watch = (ServiceWatch(self.session, self.prefix, self.map, lambda: events.put(None))
                 if wait else None)
        try:
            payload = self._query_one(wire.keys.train(self.prefix, self.map),
                                      wire.TrainRequest(method=method).encode(), None)
            reply = wire.TrainReply.decode(payload, self.limits)
            if wait and reply.accepted:
                self._wait_for_job(events, reply.job_id, timeout, on_event, watch)
            return reply
        finally:
            for entity in (sub, watch):
                if entity is not None:
                    entity.undeclare()

    def _wait_for_job(self, events: queue.Queue[wire.Event | None], job_id: str | None,
                      timeout: float | None,
                      on_event: Callable[[wire.Event], None] | None,
                      watch: ServiceWatch | None = None) -> wire.Event:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                raise TimeoutError(f"training job {job_id} of map {self.map!r} did not finish "
                                   f"within {timeout} s")
            try:
                event = events.get(timeout=remaining)
            except queue.Empty:
                continue
            if event is None:   # a liveliness change
                if watch is not None and watch.gone is not None:
                    raise ServiceGone(f"training job {job_id} of map {self.map!r} is lost: "
                                      f"the service serving it went away ({watch.gone} "
                                      "withdrew or died); train again once a service is back")
                continue
            if event.fields.get("job_id") != job_id:
                continue
            if watch is not None and event.kind is wire.EventKind.TRAIN_STARTED:
                watch.follow(event.fields.get("instance"))
            if on_event is not None:
                on_event(event)
            if event.kind is wire.EventKind.TRAIN_DONE:
                return event
            if event.kind is wire.EventKind.TRAIN_FAILED:
                raise ServiceError(_error_code(event.fields.get("code")),
                                   str(event.fields.get("message", "training failed")))

    def status(self, *, timeout: float | None = None) -> wire.StatusReply:
        """The service's status for this map (size, training state, counters, latency)."""
        payload = self._query_one(wire.keys.status(self.prefix, self.map), None, timeout)
        return wire.StatusReply.decode(payload, self.limits)

    def keyframes(self, *, images: bool = False, timeout: float | None = None
                  ) -> list[wire.KeyframeInfo]:
        """Every stored keyframe (id, camera, pose, ...) sorted by id; with ``images``, each
        carries its image (large)."""
        timeout = _check_timeout(timeout, self.timeout)
        key = wire.keys.keyframes(self.prefix, self.map) + ("?image=true" if images else "")
        try:
            payloads = self._query_all(key, timeout)
        except NoReplyError as no_reply:
            # An empty map sends no reply at all: [] if its status answers with 0 keyframes
            # (the map is served), else nobody serves it and the NoReplyError stands.
            try:
                if self.status(timeout=timeout).keyframes == 0:
                    return []
            except NoReplyError:
                pass
            raise no_reply from None
        infos = [wire.KeyframeInfo.decode(p, self.limits) for p in payloads]
        return sorted(infos, key=lambda k: k.id)

    def cameras(self, *, timeout: float | None = None) -> dict[str, wire.WireCamera]:
        """Every camera the service knows for this map, by id."""
        puts = [wire.CameraPut.decode(p, self.limits)
                for p in self._query_all(wire.keys.cameras(self.prefix, self.map), timeout)]
        return {c.id: c.camera for c in sorted(puts, key=lambda c: c.id)}

    def maps(self, *, timeout: float | None = None) -> list[tuple[str, str]]:
        """(instance, map) of every live service instance under this prefix (any map)."""
        return self._tokens(wire.keys.liveliness_all(self.prefix), wire.keys.parse_liveliness,
                            "liveliness", timeout)

    def resident_maps(self, *, timeout: float | None = None) -> list[tuple[str, str]]:
        """(instance, map) of every map an instance holds in memory: a query on it answers
        without a load from storage (a service with ``max_resident_mb`` loads maps on first
        use and closes idle ones; without it every served map is resident)."""
        return self._tokens(wire.keys.resident_all(self.prefix), wire.keys.parse_resident,
                            "residency", timeout)

    def _tokens(self, key: str, parse: Callable[[str, str], tuple[str, str]], what: str,
                timeout: float | None) -> list[tuple[str, str]]:
        """The (instance, map) of each liveliness token matching ``key``, sorted; a token
        whose key does not parse is logged and skipped."""
        found = set()
        replies = self.session.liveliness().get(key,
                                                timeout=_check_timeout(timeout, self.timeout))
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                found.add(parse(self.prefix, str(reply.ok.key_expr)))
            except ProtocolError as exc:
                log.warning("ignoring %s token %s: %s", what, reply.ok.key_expr, exc)
        return sorted(found)

    def subscribe_events(self, callback: Callable[[wire.Event], None], *,
                         kinds: Iterable[wire.EventKind | str] | None = None) -> zenoh.Subscriber:
        """Call ``callback(event)`` for every event of this map (only ``kinds`` if given),
        in a Zenoh thread: keep it short. Undeclare the returned subscriber to stop."""
        wanted = None if kinds is None else {wire.EventKind(k) for k in kinds}

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                event = wire.Event.decode(sample.payload.to_bytes(), self.limits)
            except ProtocolError as exc:
                log.warning("ignoring malformed event on %s: %s", sample.key_expr, exc)
                return
            if wanted is None or event.kind in wanted:
                try:
                    callback(event)
                except Exception:  # a Zenoh thread must not die of a user callback
                    log.exception("event callback failed")

        return self.session.declare_subscriber(wire.keys.events(self.prefix, self.map),
                                               on_sample)

    # -- transport -------------------------------------------------------------------------
    def _query_one(self, key: str, payload: bytes | None, timeout: float | None) -> bytes:
        """The first successful reply's payload; errors are raised after every replier."""
        timeout = _check_timeout(timeout, self.timeout)
        error: Exception | None = None
        for reply in self.session.get(key, payload=payload, timeout=timeout):
            ok, data = _reply_bytes(reply)
            if ok:
                return data
            error = error or self._reply_error(data, key, timeout)
        raise error or self._no_reply(key, timeout)

    def _query_all(self, key: str, timeout: float | None) -> list[bytes]:
        """Payloads of every reply (a wildcard query); the first error reply is raised."""
        timeout = _check_timeout(timeout, self.timeout)
        payloads, answered = [], False
        for reply in self.session.get(key, timeout=timeout,
                                      consolidation=zenoh.ConsolidationMode.NONE):
            answered = True
            ok, data = _reply_bytes(reply)
            if not ok:
                raise self._reply_error(data, key, timeout)
            payloads.append(data)
        if not answered:
            raise self._no_reply(key, timeout)
        return payloads

    def _no_reply(self, key: str, timeout: float) -> NoReplyError:
        return NoReplyError(f"no reply on {key!r} within {timeout} s: is a reloc service "
                            f"serving map {self.map!r} under prefix {self.prefix!r} reachable? "
                            "(`reloc-client maps` lists the live ones)")

    def _reply_error(self, payload: bytes, key: str, timeout: float) -> Exception:
        try:
            err = wire.ErrorReply.decode(payload, self.limits)
        except ProtocolError:
            # Not ours: Zenoh itself answers "Timeout" when the query's time is up.
            text = payload.decode("utf-8", "replace")[:200]
            if text.strip().lower() == "timeout":
                return NoReplyError(f"no reply on {key!r} within {timeout} s (Zenoh timeout)")
            return ServiceError(ErrorCode.INTERNAL, f"non-protocol error reply on {key!r}: {text}")
        cls = ServiceBusy if err.code is ErrorCode.BUSY else ServiceError
        return cls(err.code, err.message)


def _error_code(code: Any) -> ErrorCode:
    """An event's ``code`` field as an ErrorCode (INTERNAL if unknown)."""
    return ErrorCode(code) if code in ErrorCode.__members__.values() else ErrorCode.INTERNAL


def _check_timeout(timeout: float | None, default: float) -> float:
    """``timeout`` seconds, or ``default`` for None; ValueError for <= 0 (not "the default")."""
    if timeout is None:
        return default
    if isinstance(timeout, bool) or not isinstance(timeout, int | float) or not timeout > 0:
        raise ValueError(f"timeout: expected a positive number of seconds or None (the "
                         f"client's default, {default} s), got {timeout!r}")
    return float(timeout)


def _reply_bytes(reply: zenoh.Reply) -> tuple[bool, bytes]:
    """(is a success, payload) of a Zenoh reply."""
    if reply.ok is not None:
        return True, reply.ok.payload.to_bytes()
    return False, b"" if reply.err is None else reply.err.payload.to_bytes()


__all__ = ["RelocClient", "RelocResult", "RelocStatus", "ServiceError", "ServiceBusy",
           "NoReplyError", "ServiceGone", "keyframe_put_bytes", "make_config",
           "to_wire_image", "to_wire_pose", "to_wire_camera", "to_wire_features",
           "to_wire_depth"]
