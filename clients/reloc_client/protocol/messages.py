"""The top-level messages: unpack_message, the Message base, every message class (KeyframePut
... ErrorReply), encode_error and the ``decode_*`` aliases."""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self

import msgpack
import numpy as np

from .checks import (
    _SHORT,
    _UNLIMITED,
    DEFAULT_LIMITS,
    PROTOCOL_VERSION,
    ErrorCode,
    Limits,
    ProtocolError,
    _bool,
    _fail,
    _Fields,
    _float,
    _int,
    _list,
    _numbers,
    _str,
    _str_map,
)
from .geometry import WireCamera, WirePose, pose_covariance_problem
from .images import WireDepth, WireFeatures, WireImage
from .keys import _check_kf_id, check_name
from .methods import split_chain


class ReplyStatus(enum.StrEnum):
    """``status`` of a relocalize reply."""

    OK = "ok"
    NOT_RELOCALIZED = "not_relocalized"
    BUSY = "busy"


class EventKind(enum.StrEnum):
    """``kind`` of an event published on ``<prefix>/<map>/events``."""

    TRAIN_STARTED = "train_started"
    TRAIN_PROGRESS = "train_progress"
    TRAIN_DONE = "train_done"
    TRAIN_FAILED = "train_failed"
    KEYFRAME_ACCEPTED = "keyframe_accepted"   # journaled (durable); applied later
    KEYFRAME_ADDED = "keyframe_added"
    KEYFRAME_REMOVED = "keyframe_removed"
    KEYFRAME_REJECTED = "keyframe_rejected"
    CAMERA_ADDED = "camera_added"
    CAMERA_REJECTED = "camera_rejected"
    MAP_SAVED = "map_saved"
    STORAGE_DAMAGED = "storage_damaged"    # restoring the map skipped or recovered something
    REPLICA_DIVERGED = "replica_diverged"  # a peer serves another map, or another content


def unpack_message(data: bytes, limits: Limits = DEFAULT_LIMITS) -> dict[str, Any]:
    """msgpack bytes -> the top-level map, with size, syntax and version checked."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise _fail(ErrorCode.WRONG_TYPE, "payload", "bytes", data)
    if len(data) > limits.max_payload_bytes:
        raise ProtocolError(ErrorCode.PAYLOAD_TOO_LARGE,
                            f"payload: {len(data)} bytes; expected at most "
                            f"{limits.max_payload_bytes}")
    try:
        obj = msgpack.unpackb(bytes(data), raw=False, strict_map_key=False)
    except (ValueError, msgpack.UnpackException, UnicodeDecodeError, TypeError) as exc:
        raise ProtocolError(ErrorCode.BAD_MSGPACK,
                            f"payload: expected one msgpack map, could not unpack "
                            f"({type(exc).__name__}: {str(exc)[:80]})") from None
    if not isinstance(obj, dict):
        raise _fail(ErrorCode.NOT_A_MAP, "payload", "a msgpack map", obj)
    if any(not isinstance(k, str) for k in obj):
        raise ProtocolError(ErrorCode.NOT_A_MAP, "payload: expected a map with string keys")
    if "v" not in obj:
        raise ProtocolError(ErrorCode.MISSING_FIELD,
                            f"payload.v: missing protocol version; expected v = {PROTOCOL_VERSION}")
    # An integer exactly: 1.0 and True compare equal to 1 in Python but are other msgpack types.
    if type(obj["v"]) is not int or obj["v"] != PROTOCOL_VERSION:
        raise _fail(ErrorCode.UNSUPPORTED_VERSION, "payload.v",
                    f"protocol version {PROTOCOL_VERSION}", obj["v"])
    return obj


class Message:
    """Base of every top-level message: ``encode() -> bytes`` and ``decode(bytes, limits)``."""

    NAME: ClassVar[str]

    def to_wire(self) -> dict[str, Any]:
        raise NotImplementedError

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> Self:
        raise NotImplementedError

    def encode(self) -> bytes:
        """msgpack bytes; the output is validated (limits aside) before it is returned."""
        obj = {"v": PROTOCOL_VERSION, **_drop_none(self.to_wire())}
        type(self).from_wire(obj, type(self).NAME, _UNLIMITED)
        return msgpack.packb(obj, use_bin_type=True)

    @classmethod
    def decode(cls, data: bytes, limits: Limits = DEFAULT_LIMITS) -> Self:
        """Validate ``data`` against ``limits``; ProtocolError naming the first problem."""
        return cls.from_wire(unpack_message(data, limits), cls.NAME, limits)


def _drop_none(d: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in d.items() if v is not None}


def _opt_wire(x: Any) -> Any:
    return None if x is None else x.to_wire()


def _opt_list(x: tuple[float, ...] | None) -> list[float] | None:
    return None if x is None else list(x)


def _pose_covariance(value: Any, path: str) -> tuple[float, ...]:
    """36 numbers, row-major, that make a pose covariance (see
    :func:`.geometry.pose_covariance_problem`); BAD_VALUE naming what is wrong otherwise."""
    numbers = _numbers(value, path, 36, ErrorCode.BAD_VALUE)
    problem = pose_covariance_problem(np.reshape(numbers, (6, 6)))
    if problem is not None:
        raise ProtocolError(ErrorCode.BAD_VALUE,
                            f"{path}: expected a 6x6 row-major pose covariance (symmetric, "
                            f"positive semi-definite; twist (rho, omega), m and rad): {problem}")
    return numbers


def _camera_choice(f: _Fields, path: str, image: WireImage | None
                   ) -> tuple[str | None, WireCamera | None]:
    """Exactly one of ``camera_id`` / ``camera``; an inline camera must match the image."""
    camera_id = f.opt("camera_id", lambda v, p: check_name(v, p))
    camera = f.opt("camera", WireCamera.from_wire)
    if (camera_id is None) == (camera is None):
        raise ProtocolError(ErrorCode.MISSING_FIELD if camera is None else ErrorCode.BAD_VALUE,
                            f"{path}: expected exactly one of 'camera_id' (a camera put "
                            f"before) or 'camera' (a camera dict)")
    if camera is not None and image is not None and (camera.width, camera.height) != (
            image.width, image.height):
        raise ProtocolError(ErrorCode.BAD_IMAGE,
                            f"{path}.image: size {image.width}x{image.height} does not match "
                            f"the camera's {camera.width}x{camera.height}")
    return camera_id, camera


@dataclass(frozen=True)
class KeyframePut(Message):
    """Put on ``<prefix>/<map>/keyframes/<id>``: add or replace keyframe ``id``."""

    NAME: ClassVar[str] = "keyframe"
    id: int
    image: WireImage
    world_from_cam: WirePose
    camera_id: str | None = None
    camera: WireCamera | None = None
    timestamp: float | None = None
    features: WireFeatures | None = None
    depth: WireDepth | None = None
    #: 6x6 row-major covariance of ``world_from_cam`` (36 floats; twist (rho, omega), right
    #: perturbation, metres and radians); None: the map's default applies.
    pose_covariance: tuple[float, ...] | None = None

    def to_wire(self) -> dict[str, Any]:
        return {"id": self.id, "image": self.image.to_wire(), "camera_id": self.camera_id,
                "camera": _opt_wire(self.camera), "world_from_cam": self.world_from_cam.to_wire(),
                "timestamp": self.timestamp, "features": _opt_wire(self.features),
                "depth": _opt_wire(self.depth),
                "pose_covariance": _opt_list(self.pose_covariance)}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> KeyframePut:
        f = _Fields(value, path)
        f.seen.add("v")
        kf_id = f.req("id", _check_kf_id)
        image = f.req("image", lambda v, p: WireImage.from_wire(v, p, limits))
        camera_id, camera = _camera_choice(f, path, image)
        pose = f.req("world_from_cam", WirePose.from_wire)
        timestamp = f.opt("timestamp", _float)
        features = f.opt("features", lambda v, p: WireFeatures.from_wire(v, p, limits))
        depth = f.opt("depth", lambda v, p: WireDepth.from_wire(v, p, limits))
        pose_covariance = f.opt("pose_covariance", _pose_covariance)
        f.done()
        if depth is not None and (depth.width, depth.height) != (image.width, image.height):
            raise ProtocolError(ErrorCode.BAD_IMAGE,
                                f"{path}.depth: size {depth.width}x{depth.height} does not "
                                f"match the image's {image.width}x{image.height}")
        return cls(kf_id, image, pose, camera_id, camera, timestamp, features, depth,
                   pose_covariance)


@dataclass(frozen=True)
class KeyframeInfo(Message):
    """A reply to a get on ``<prefix>/<map>/keyframes/**`` (one per stored keyframe); the
    image is included only when the selector has the parameter ``image=true``."""

    NAME: ClassVar[str] = "keyframe_info"
    id: int
    camera: WireCamera
    world_from_cam: WirePose
    camera_id: str | None = None
    timestamp: float | None = None
    num_landmarks: int = 0
    image: WireImage | None = None
    #: As in :class:`KeyframePut`: the covariance the keyframe was put with (None: none was,
    #: the map's default applies).
    pose_covariance: tuple[float, ...] | None = None

    def to_wire(self) -> dict[str, Any]:
        return {"id": self.id, "camera": self.camera.to_wire(), "camera_id": self.camera_id,
                "world_from_cam": self.world_from_cam.to_wire(), "timestamp": self.timestamp,
                "num_landmarks": self.num_landmarks, "image": _opt_wire(self.image),
                "pose_covariance": _opt_list(self.pose_covariance)}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> KeyframeInfo:
        f = _Fields(value, path)
        f.seen.add("v")
        out = cls(
            id=f.req("id", _check_kf_id),
            camera=f.req("camera", WireCamera.from_wire),
            world_from_cam=f.req("world_from_cam", WirePose.from_wire),
            camera_id=f.opt("camera_id", lambda v, p: check_name(v, p)),
            timestamp=f.opt("timestamp", _float),
            num_landmarks=f.opt("num_landmarks", lambda v, p: _int(v, p, lo=0), 0),
            image=f.opt("image", lambda v, p: WireImage.from_wire(v, p, limits)),
            pose_covariance=f.opt("pose_covariance", _pose_covariance))
        f.done()
        return out


@dataclass(frozen=True)
class CameraPut(Message):
    """Put on ``<prefix>/<map>/cameras/<id>`` (also a reply to a get on ``cameras/**``)."""

    NAME: ClassVar[str] = "camera_put"
    id: str
    camera: WireCamera

    def to_wire(self) -> dict[str, Any]:
        return {"id": self.id, "camera": self.camera.to_wire()}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> CameraPut:
        f = _Fields(value, path)
        f.seen.add("v")
        out = cls(f.req("id", lambda v, p: check_name(v, p)), f.req("camera", WireCamera.from_wire))
        f.done()
        return out


@dataclass(frozen=True)
class Prior:
    """A ``world_from_cam`` the caller believes in (a VIO's, say), with at least one of:

    - ``radius_m``: candidates of the place finders are keyframes whose centre is within that
      many metres of its centre (as before the covariance existed);
    - ``covariance``: 36 numbers, row-major, the 6x6 covariance of the prior (twist (rho,
      omega), right perturbation ``world_from_cam @ exp(xi)``, metres and radians, as every
      pose covariance of the protocol): the service first tracks, matching the landmarks
      the prior predicts visible in windows this covariance sets, and only where that does
      not verify runs the full method (restricted by ``radius_m`` when also given).
    """

    world_from_cam: WirePose
    radius_m: float | None = None
    covariance: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.radius_m is None and self.covariance is None:
            raise ProtocolError(ErrorCode.MISSING_FIELD,
                                "prior: expected 'radius_m' (metres), 'covariance' (36 numbers, "
                                "a 6x6 pose covariance) or both")
        if self.covariance is not None:
            _pose_covariance(list(self.covariance), "prior.covariance")

    def to_wire(self) -> dict[str, Any]:
        out: dict[str, Any] = {"world_from_cam": self.world_from_cam.to_wire()}
        if self.radius_m is not None:
            out["radius_m"] = self.radius_m
        if self.covariance is not None:
            out["covariance"] = list(self.covariance)
        return out

    @classmethod
    def from_wire(cls, value: Any, path: str) -> Prior:
        f = _Fields(value, path)
        pose = f.req("world_from_cam", WirePose.from_wire)
        radius = f.opt("radius_m", lambda v, p: _float(v, p, positive=True))
        covariance = f.opt("covariance", _pose_covariance)
        f.done()
        if radius is None and covariance is None:
            raise ProtocolError(ErrorCode.MISSING_FIELD,
                                f"{path}: expected 'radius_m' (metres), 'covariance' (36 "
                                f"numbers, a 6x6 pose covariance) or both")
        return cls(pose, radius, covariance)


def _method(value: Any, path: str) -> str:
    """A method name or comma-separated fallback chain, e.g. ``"bow+p3p,sbi+esm"``: steps
    that are not empty and hold no space. The steps' own form (:class:`.MethodSpec`) is left
    to the service, which answers any method it does not serve with ``UNKNOWN_METHOD`` and
    the list of those it does."""
    s = _str(value, path, _SHORT)
    try:
        steps = split_chain(s)
    except ValueError:
        steps = ()
    if not steps or any(c.isspace() for step in steps for c in step):
        raise _fail(ErrorCode.BAD_VALUE, path,
                    "a method such as 'sbi+p3p' or a comma-separated chain such as "
                    "'bow+p3p,sbi+esm'", value)
    return s


@dataclass(frozen=True)
class RelocalizeRequest(Message):
    """Query on ``<prefix>/<map>/relocalize``: where was this image taken?"""

    NAME: ClassVar[str] = "relocalize"
    image: WireImage
    camera_id: str | None = None
    camera: WireCamera | None = None
    method: str | None = None
    prior: Prior | None = None
    hypotheses: int = 1
    request_id: str | None = None
    timestamp: float | None = None

    def to_wire(self) -> dict[str, Any]:
        return {"image": self.image.to_wire(), "camera_id": self.camera_id,
                "camera": _opt_wire(self.camera), "method": self.method,
                "prior": _opt_wire(self.prior),
                "hypotheses": None if self.hypotheses == 1 else self.hypotheses,
                "request_id": self.request_id, "timestamp": self.timestamp}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> RelocalizeRequest:
        f = _Fields(value, path)
        f.seen.add("v")
        image = f.req("image", lambda v, p: WireImage.from_wire(v, p, limits))
        camera_id, camera = _camera_choice(f, path, image)
        out = cls(
            image=image, camera_id=camera_id, camera=camera,
            method=f.opt("method", _method),
            prior=f.opt("prior", Prior.from_wire),
            hypotheses=f.opt("hypotheses", lambda v, p: _int(v, p, lo=1, hi=limits.max_hypotheses),
                             1),
            request_id=f.opt("request_id", lambda v, p: _str(v, p, _SHORT)),
            timestamp=f.opt("timestamp", _float))
        f.done()
        return out


def _covariance(value: Any, path: str) -> tuple[float, ...]:
    return _numbers(value, path, 36, ErrorCode.BAD_VALUE)


def _timings(value: Any, path: str, limits: Limits) -> dict[str, float]:
    return _str_map(value, path, lambda v, p: _float(v, p, non_negative=True), limits)


def _kf_ids(value: Any, path: str, limits: Limits) -> tuple[int, ...]:
    return _list(value, path, limits, _check_kf_id)


@dataclass(frozen=True)
class Hypothesis:
    """One further verified pose of a relocalize reply (fields as in the reply)."""

    world_from_cam: WirePose
    method: str = ""
    confidence: float = 0.0
    inliers: int = 0
    num_matches: int = 0
    reprojection_rms_px: float | None = None
    covariance: tuple[float, ...] | None = None
    matched_keyframe_ids: tuple[int, ...] = ()

    def to_wire(self) -> dict[str, Any]:
        return _drop_none({
            "world_from_cam": self.world_from_cam.to_wire(), "method": self.method,
            "confidence": self.confidence, "inliers": self.inliers,
            "num_matches": self.num_matches, "reprojection_rms_px": self.reprojection_rms_px,
            "covariance": None if self.covariance is None else list(self.covariance),
            "matched_keyframe_ids": list(self.matched_keyframe_ids)})

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits = DEFAULT_LIMITS) -> Hypothesis:
        f = _Fields(value, path)
        out = cls(
            world_from_cam=f.req("world_from_cam", WirePose.from_wire),
            method=f.opt("method", lambda v, p: _str(v, p, limits), ""),
            confidence=f.opt("confidence", lambda v, p: _float(v, p, unit=True), 0.0),
            inliers=f.opt("inliers", lambda v, p: _int(v, p, lo=0), 0),
            num_matches=f.opt("num_matches", lambda v, p: _int(v, p, lo=0), 0),
            reprojection_rms_px=f.opt("reprojection_rms_px",
                                      lambda v, p: _float(v, p, non_negative=True)),
            covariance=f.opt("covariance", _covariance),
            matched_keyframe_ids=f.opt("matched_keyframe_ids",
                                       lambda v, p: _kf_ids(v, p, limits), ()))
        f.done()
        return out


@dataclass(frozen=True)
class RelocalizeReply(Message):
    """Reply to a relocalize query. ``world_from_cam`` is set iff ``status`` is ``ok``;
    ``covariance`` is 6x6 row-major (twist (rho, omega), right perturbation, m and rad)."""

    NAME: ClassVar[str] = "relocalize_reply"
    status: ReplyStatus
    method: str = ""
    world_from_cam: WirePose | None = None
    covariance: tuple[float, ...] | None = None
    confidence: float = 0.0
    inliers: int = 0
    num_matches: int = 0
    reprojection_rms_px: float | None = None
    matched_keyframe_ids: tuple[int, ...] = ()
    map_version: int = 0
    timings: Mapping[str, float] = field(default_factory=dict)
    reason: str = ""
    hypotheses: tuple[Hypothesis, ...] = ()
    request_id: str | None = None
    timestamp: float | None = None

    def to_wire(self) -> dict[str, Any]:
        return {
            "status": ReplyStatus(self.status).value, "method": self.method,
            "world_from_cam": _opt_wire(self.world_from_cam),
            "covariance": None if self.covariance is None else list(self.covariance),
            "confidence": self.confidence, "inliers": self.inliers,
            "num_matches": self.num_matches, "reprojection_rms_px": self.reprojection_rms_px,
            "matched_keyframe_ids": list(self.matched_keyframe_ids),
            "map_version": self.map_version, "timings": dict(self.timings),
            "reason": self.reason, "hypotheses": [h.to_wire() for h in self.hypotheses],
            "request_id": self.request_id, "timestamp": self.timestamp}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits) -> RelocalizeReply:
        f = _Fields(value, path)
        f.seen.add("v")
        status = f.req("status", lambda v, p: _enum(ReplyStatus, v, p))
        out = cls(
            status=status,
            method=f.opt("method", lambda v, p: _str(v, p, limits), ""),
            world_from_cam=f.opt("world_from_cam", WirePose.from_wire),
            covariance=f.opt("covariance", _covariance),
            confidence=f.opt("confidence", lambda v, p: _float(v, p, unit=True), 0.0),
            inliers=f.opt("inliers", lambda v, p: _int(v, p, lo=0), 0),
            num_matches=f.opt("num_matches", lambda v, p: _int(v, p, lo=0), 0),
            reprojection_rms_px=f.opt("reprojection_rms_px",
                                      lambda v, p: _float(v, p, non_negative=True)),
            matched_keyframe_ids=f.opt("matched_keyframe_ids",
                                       lambda v, p: _kf_ids(v, p, limits), ()),
            map_version=f.opt("map_version", lambda v, p: _int(v, p, lo=0), 0),
            timings=f.opt("timings", lambda v, p: _timings(v, p, limits), {}),
            reason=f.opt("reason", lambda v, p: _str(v, p, limits), ""),
            hypotheses=f.opt("hypotheses", lambda v, p: _list(
                v, p, limits, lambda h, q: Hypothesis.from_wire(h, q, limits)), ()),
            request_id=f.opt("request_id", lambda v, p: _str(v, p, limits)),
            timestamp=f.opt("timestamp", _float))
        f.done()
        if (status is ReplyStatus.OK) != (out.world_from_cam is not None):
            raise ProtocolError(ErrorCode.BAD_VALUE,
                                f"{path}.world_from_cam: expected a pose exactly when status is "
                                f"'ok', status is {status.value!r}")
        return out


def _enum(kind: type[enum.StrEnum], value: Any, path: str) -> Any:
    names = [m.value for m in kind]  # type: ignore[attr-defined]
    if not isinstance(value, str):
        raise _fail(ErrorCode.WRONG_TYPE, path, f"a string, one of {names}", value)
    if value not in names:
        raise _fail(ErrorCode.BAD_VALUE, path, f"one of {names}", value)
    return kind(value)


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


def _plain(value: Any, path: str) -> Any:
    """Event field values: nil, bool, int, float, str, and arrays/maps of them."""
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, list | tuple):
        return [_plain(v, f"{path}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, dict):
        return _str_map(value, path, _plain, _UNLIMITED)
    raise _fail(ErrorCode.WRONG_TYPE, path, "nil, bool, number, string, array or map", value)


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
            resident=f.opt("resident", _bool, True))
        f.done()
        return out


def _hex_digest(value: Any, path: str) -> str:
    """A lowercase hexadecimal digest of 32 to 128 digits (a map identity, a content hash)."""
    if not isinstance(value, str):
        raise _fail(ErrorCode.WRONG_TYPE, path, "a string of hex digits", value)
    if not 32 <= len(value) <= 128 or any(c not in "0123456789abcdef" for c in value):
        raise _fail(ErrorCode.BAD_VALUE, path, "32 to 128 lowercase hex digits", value)
    return value


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
