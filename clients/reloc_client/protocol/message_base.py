"""The messages' common ground: the reply status and event kinds, ``unpack_message`` (size,
syntax and version of a payload), the :class:`Message` base, and the field decoders several
messages share."""

from __future__ import annotations

import enum
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
    _fail,
    _Fields,
    _float,
    _list,
    _numbers,
    _str,
    _str_map,
)
from .geometry import WireCamera, pose_covariance_problem
from .images import WireImage
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


def _covariance(value: Any, path: str) -> tuple[float, ...]:
    return _numbers(value, path, 36, ErrorCode.BAD_VALUE)


def _timings(value: Any, path: str, limits: Limits) -> dict[str, float]:
    return _str_map(value, path, lambda v, p: _float(v, p, non_negative=True), limits)


def _kf_ids(value: Any, path: str, limits: Limits) -> tuple[int, ...]:
    return _list(value, path, limits, _check_kf_id)


def _enum(kind: type[enum.StrEnum], value: Any, path: str) -> Any:
    names = [m.value for m in kind]  # type: ignore[attr-defined]
    if not isinstance(value, str):
        raise _fail(ErrorCode.WRONG_TYPE, path, f"a string, one of {names}", value)
    if value not in names:
        raise _fail(ErrorCode.BAD_VALUE, path, f"one of {names}", value)
    return kind(value)


def _plain(value: Any, path: str) -> Any:
    """Event field values: nil, bool, int, float, str, and arrays/maps of them."""
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, list | tuple):
        return [_plain(v, f"{path}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, dict):
        return _str_map(value, path, _plain, _UNLIMITED)
    raise _fail(ErrorCode.WRONG_TYPE, path, "nil, bool, number, string, array or map", value)


def _hex_digest(value: Any, path: str) -> str:
    """A lowercase hexadecimal digest of 32 to 128 digits (a map identity, a content hash)."""
    if not isinstance(value, str):
        raise _fail(ErrorCode.WRONG_TYPE, path, "a string of hex digits", value)
    if not 32 <= len(value) <= 128 or any(c not in "0123456789abcdef" for c in value):
        raise _fail(ErrorCode.BAD_VALUE, path, "32 to 128 lowercase hex digits", value)
    return value
