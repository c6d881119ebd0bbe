"""The service's other messages (training, events, status, errors), ``encode_error``, the
``decode_*`` aliases of every message and :data:`MESSAGE_TYPES`. The messages that build a map
are in :mod:`.keyframe_messages`, the relocalize query and reply in
:mod:`.relocalize_messages`, their common base in :mod:`.message_base`."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from .checks import (
    _SHORT,
    ErrorCode,
    Limits,
    ProtocolError,
    _bool,
    _Fields,
    _float,
    _int,
    _list,
    _str,
    _str_map,
)
from .keyframe_messages import CameraPut, KeyframeInfo, KeyframePut
from .keys import check_name
from .message_base import (
    EventKind,
    Message,
    _enum,
    _hex_digest,
    _method,
    _plain,
    _timings,
)
from .relocalize_messages import RelocalizeReply, RelocalizeRequest


@dataclass(frozen=True)
class TrainRequest(Message):
    """Query on ``<prefix>/<map>/train``: (re)train ``method`` (all trainable methods when
    unset) in the background."""

    NAME: ClassVar[str] = "train"
    method: str | None = None
    request_id: str | None = None

    def to_wire(self) -> dict[str, Any]:
        return {"method": self.method, "request_id": self.request_id}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> TrainRequest:
        f = _Fields(value, path)
        f.seen.add("v")
        out = cls(f.opt("method", _method),
                  f.opt("request_id", lambda v, p: _str(v, p, _SHORT)))
        f.done()
        return out


@dataclass(frozen=True)
class TrainReply(Message):
    """Immediate reply to a train query: ``accepted`` with the ``job_id`` whose events to
    wait for (a job already running is reported with its id), or refused with a ``reason``."""

    NAME: ClassVar[str] = "train_reply"
    accepted: bool
    job_id: str | None = None
    reason: str = ""

    def to_wire(self) -> dict[str, Any]:
        return {"accepted": self.accepted, "job_id": self.job_id, "reason": self.reason}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> TrainReply:
        f = _Fields(value, path)
        f.seen.add("v")
        out = cls(f.req("accepted", _bool),
                  f.opt("job_id", lambda v, p: _str(v, p, limits, nonempty=True)),
                  f.opt("reason", lambda v, p: _str(v, p, limits), ""))
        f.done()
        if out.accepted and out.job_id is None:
            raise ProtocolError(ErrorCode.MISSING_FIELD,
                                f"{path}.job_id: missing; an accepted train reply has a job id")
        return out


@dataclass(frozen=True)
class Event(Message):
    """Published on ``<prefix>/<map>/events``: ``kind``, the map, ``time`` (Unix seconds)
    and kind-specific ``fields`` (see docs/protocol.md)."""

    NAME: ClassVar[str] = "event"
    kind: EventKind
    map: str
    time: float
    fields: Mapping[str, Any] = field(default_factory=dict)

    def to_wire(self) -> dict[str, Any]:
        return {"kind": EventKind(self.kind).value, "map": self.map, "time": self.time,
                "fields": dict(self.fields)}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> Event:
        f = _Fields(value, path)
        f.seen.add("v")
        out = cls(f.req("kind", lambda v, p: _enum(EventKind, v, p)),
                  f.req("map", lambda v, p: check_name(v, p)),
                  f.req("time", lambda v, p: _float(v, p, non_negative=True)),
                  f.opt("fields", lambda v, p: _str_map(v, p, _plain, limits), {}))
        f.done()
        return out


@dataclass(frozen=True)
class StatusReply(Message):
    """Reply to a query on ``<prefix>/<map>/status`` (the query has no payload)."""

    NAME: ClassVar[str] = "status"
    map: str
    instance: str
    keyframes: int
    landmarks: int
    trained: bool
    map_version: int
    methods: tuple[str, ...] = ()
    default_method: str = ""
    cameras: tuple[str, ...] = ()
    training: bool = False
    uptime_s: float = 0.0
    counters: Mapping[str, int] = field(default_factory=dict)
    latency_s: Mapping[str, float] = field(default_factory=dict)
    #: Why the map is served degraded (what its restore lacks: the missing keyframe ids or
    #: sequence numbers); empty when it is not.
    degraded: str = ""
    #: The map is served from its snapshot while its journal backlog replays (progress in
    #: the counters ``replay_records_done`` and ``replay_records_total``).
    replaying: bool = False
    #: The map's identity (a UUID's 32 hex digits, made when the map was created); empty
    #: when the service keeps no storage for it.
    map_id: str = ""
    #: A digest of the map's content (keyframe ids, poses, timestamps, images): two replicas
    #: of the same map at the same version have the same one. Empty when not computed.
    content_hash: str = ""
    #: Why this replica disagrees with a peer serving the same map name (another identity,
    #: another content at the same version, or lagging behind); empty when it does not.
    diverged: str = ""
    #: The map is in the service's memory; false for a stored map not loaded yet, or closed
    #: while idle (``max_resident_mb``): its keyframes, version and cameras are then those
    #: its storage records, landmarks 0 and trained false until it is loaded.
    resident: bool = True
    #: The calibration accuracy the map's answers state in their covariance, 1 sigma:
    #: ``focal_rel`` (relative) and ``radial_px`` (px at the farthest image corner); sent
    #: only when the map sets its own (``[maps.NAME]``), else empty (the service-wide
    #: ``[mapping]`` values).
    calibration_sigma: Mapping[str, float] = field(default_factory=dict)
    #: The keyframe pose uncertainty the map measured of itself and states for keyframes put
    #: without a covariance (``[mapping]`` sigmas ``"auto"``), 1 sigma per axis:
    #: ``position_m``, ``rotation_deg``, the bounds of their 68 % bootstrap intervals
    #: (``position_low_m`` ... ``rotation_high_deg``) and the ``keyframes`` measured; empty
    #: when it measured none.
    keyframe_pose_sigma: Mapping[str, float] = field(default_factory=dict)

    def to_wire(self) -> dict[str, Any]:
        # the optional fields only when set: a client that predates them reads a healthy
        # map's status
        return {"map": self.map, "instance": self.instance, "keyframes": self.keyframes,
                "landmarks": self.landmarks, "trained": self.trained,
                "map_version": self.map_version, "methods": list(self.methods),
                "default_method": self.default_method, "cameras": list(self.cameras),
                "training": self.training, "uptime_s": self.uptime_s,
                "counters": dict(self.counters), "latency_s": dict(self.latency_s),
                **({"replaying": True} if self.replaying else {}),
                **({} if self.resident else {"resident": False}),
                **({"calibration_sigma": dict(self.calibration_sigma)}
                   if self.calibration_sigma else {}),
                **({"keyframe_pose_sigma": dict(self.keyframe_pose_sigma)}
                   if self.keyframe_pose_sigma else {}),
                **{k: v for k, v in (("degraded", self.degraded), ("map_id", self.map_id),
                                     ("content_hash", self.content_hash),
                                     ("diverged", self.diverged)) if v}}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> StatusReply:
        f = _Fields(value, path)
        f.seen.add("v")
        nonneg = lambda v, p: _int(v, p, lo=0)  # noqa: E731
        out = cls(
            map=f.req("map", lambda v, p: check_name(v, p)),
            instance=f.req("instance", lambda v, p: check_name(v, p)),
            keyframes=f.req("keyframes", nonneg),
            landmarks=f.req("landmarks", nonneg),
            trained=f.req("trained", _bool),
            map_version=f.req("map_version", nonneg),
            methods=f.opt("methods", lambda v, p: _list(v, p, limits, _method), ()),
            default_method=f.opt("default_method", lambda v, p: _str(v, p, limits), ""),
            cameras=f.opt("cameras", lambda v, p: _list(v, p, limits, check_name), ()),
            training=f.opt("training", _bool, False),
            uptime_s=f.opt("uptime_s", lambda v, p: _float(v, p, non_negative=True), 0.0),
            counters=f.opt("counters", lambda v, p: _str_map(v, p, nonneg, limits), {}),
            latency_s=f.opt("latency_s", lambda v, p: _timings(v, p, limits), {}),
            degraded=f.opt("degraded", lambda v, p: _str(v, p, limits), ""),
            replaying=f.opt("replaying", _bool, False),
            map_id=f.opt("map_id", _hex_digest, ""),
            content_hash=f.opt("content_hash", _hex_digest, ""),
            diverged=f.opt("diverged", lambda v, p: _str(v, p, limits), ""),
            resident=f.opt("resident", _bool, True),
            calibration_sigma=f.opt("calibration_sigma",
                                    lambda v, p: _timings(v, p, limits), {}),
            keyframe_pose_sigma=f.opt("keyframe_pose_sigma",
                                      lambda v, p: _timings(v, p, limits), {}))
        f.done()
        return out


@dataclass(frozen=True)
class ErrorReply(Message):
    """The payload of a Zenoh error reply (``query.reply_err``): ``{"v": 1, "error":
    {"code": ErrorCode, "message": str}}``."""

    NAME: ClassVar[str] = "error_reply"
    code: ErrorCode
    message: str

    @classmethod
    def from_exception(cls, exc: ProtocolError) -> ErrorReply:
        return cls(exc.code, exc.message)

    def to_wire(self) -> dict[str, Any]:
        return {"error": {"code": ErrorCode(self.code).value, "message": self.message}}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> ErrorReply:
        f = _Fields(value, path)
        f.seen.add("v")
        inner = _Fields(f.req("error", lambda v, p: v), f"{path}.error")
        f.done()
        code = inner.req("code", lambda v, p: _str(v, p, limits))
        message = inner.req("message", lambda v, p: _str(v, p, limits))
        inner.done()
        # An unknown code from a newer service is still an error: keep it as INTERNAL.
        known = code in ErrorCode.__members__.values()
        return cls(ErrorCode(code) if known else ErrorCode.INTERNAL,
                   message if known else f"[{code}] {message}")


def encode_error(code: ErrorCode, message: str) -> bytes:
    """The error reply payload for ``code`` and ``message``."""
    return ErrorReply(ErrorCode(code), message).encode()


# Function-style aliases (``decode_relocalize_request(data, limits)``), one per message.
decode_keyframe_put = KeyframePut.decode
decode_keyframe_info = KeyframeInfo.decode
decode_camera_put = CameraPut.decode
decode_relocalize_request = RelocalizeRequest.decode
decode_relocalize_reply = RelocalizeReply.decode
decode_train_request = TrainRequest.decode
decode_train_reply = TrainReply.decode
decode_event = Event.decode
decode_status_reply = StatusReply.decode
decode_error_reply = ErrorReply.decode

MESSAGE_TYPES: tuple[type[Message], ...] = (
    KeyframePut, KeyframeInfo, CameraPut, RelocalizeRequest, RelocalizeReply, TrainRequest,
    TrainReply, Event, StatusReply, ErrorReply)
