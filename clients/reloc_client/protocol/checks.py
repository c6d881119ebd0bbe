"""Protocol-wide basics: the version, error codes and ProtocolError, decoder size limits,
and the field validators every decoder is built from (``_int``, ``_str``, ..., ``_Fields``)."""

from __future__ import annotations

import enum
import math
import reprlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

PROTOCOL_VERSION = 1

Array = npt.NDArray[np.float64]
T = TypeVar("T")


class ErrorCode(enum.StrEnum):
    """Why a message was refused or a request failed (the ``error.code`` of an error reply)."""

    BAD_MSGPACK = "BAD_MSGPACK"            # not msgpack, or trailing bytes
    NOT_A_MAP = "NOT_A_MAP"                # the top level is not a map with string keys
    UNSUPPORTED_VERSION = "UNSUPPORTED_VERSION"
    MISSING_FIELD = "MISSING_FIELD"
    UNKNOWN_FIELD = "UNKNOWN_FIELD"
    WRONG_TYPE = "WRONG_TYPE"
    BAD_VALUE = "BAD_VALUE"                # well typed but out of range / malformed
    BAD_NAME = "BAD_NAME"                  # map, camera or instance name not a key chunk
    BAD_POSE = "BAD_POSE"                  # NaN/Inf, non-unit quaternion, non-orthonormal
    BAD_CAMERA = "BAD_CAMERA"
    UNKNOWN_CAMERA = "UNKNOWN_CAMERA"
    BAD_IMAGE = "BAD_IMAGE"                # container invalid or size mismatch
    BAD_FEATURES = "BAD_FEATURES"
    IMAGE_TOO_LARGE = "IMAGE_TOO_LARGE"
    PAYLOAD_TOO_LARGE = "PAYLOAD_TOO_LARGE"
    UNKNOWN_METHOD = "UNKNOWN_METHOD"
    NOT_TRAINED = "NOT_TRAINED"
    UNKNOWN_MAP = "UNKNOWN_MAP"
    UNKNOWN_KEYFRAME = "UNKNOWN_KEYFRAME"
    BUSY = "BUSY"
    QUOTA_EXCEEDED = "QUOTA_EXCEEDED"      # the map or the service holds what its quota allows
    STORAGE_ERROR = "STORAGE_ERROR"
    UNKNOWN_TRANSFER = "UNKNOWN_TRANSFER"  # an export or upload id the service does not hold
    INTERNAL = "INTERNAL"


class ProtocolError(ValueError):
    """A message does not follow the protocol: ``code`` says which way, ``message`` where."""

    def __init__(self, code: ErrorCode, message: str) -> None:
        super().__init__(f"{code.value}: {message}")
        self.code = ErrorCode(code)
        self.message = message


@dataclass(frozen=True)
class Limits:
    """Size limits a decoder enforces (the service passes its configured limits)."""

    max_payload_bytes: int = 32 * 1024 * 1024
    max_image_pixels: int = 4096 * 4096
    max_features: int = 50_000
    max_hypotheses: int = 32
    max_string_len: int = 4096
    max_list_len: int = 100_000


DEFAULT_LIMITS = Limits()
_SHORT = Limits(max_string_len=256)  # ids and method strings
_UNLIMITED = Limits(max_payload_bytes=2**62, max_image_pixels=2**62, max_features=2**62,
                    max_hypotheses=2**62, max_string_len=2**62, max_list_len=2**62)


# ================================================================================================
# Field validation: every reader takes the value and its dotted path, and raises ProtocolError.
# ================================================================================================

#: The repr of a value an error message shows: a few levels and items of a container, so a
#: value nested a thousand levels deep (a crafted request) is described, not recursed into.
_SHORT_REPR = reprlib.Repr()
_SHORT_REPR.maxlevel = 3
_SHORT_REPR.maxstring = _SHORT_REPR.maxother = 60


def _describe(value: Any) -> str:
    if isinstance(value, bytes | bytearray):
        return f"{len(value)} bytes"
    text = _SHORT_REPR.repr(value)
    text = text if len(text) <= 60 else text[:57] + "..."
    return f"{type(value).__name__} {text}" if not isinstance(value, int | float | str) else text


def _fail(code: ErrorCode, path: str, expected: str, value: Any = None, *,
          show: bool = True) -> ProtocolError:
    got = f", got {_describe(value)}" if show else ""
    return ProtocolError(code, f"{path}: expected {expected}{got}")


def _int(value: Any, path: str, *, lo: int | None = None, hi: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _fail(ErrorCode.WRONG_TYPE, path, "an integer", value)
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        bounds = (f"an integer >= {lo}" if hi is None else
                  f"an integer <= {hi}" if lo is None else f"an integer in [{lo}, {hi}]")
        raise _fail(ErrorCode.BAD_VALUE, path, bounds, value)
    return value


def _float(value: Any, path: str, *, positive: bool = False, non_negative: bool = False,
           unit: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _fail(ErrorCode.WRONG_TYPE, path, "a number", value)
    x = float(value)
    if not math.isfinite(x):
        raise _fail(ErrorCode.BAD_VALUE, path, "a finite number", value)
    if positive and not x > 0:
        raise _fail(ErrorCode.BAD_VALUE, path, "a positive number", value)
    if non_negative and x < 0:
        raise _fail(ErrorCode.BAD_VALUE, path, "a number >= 0", value)
    if unit and not 0.0 <= x <= 1.0:
        raise _fail(ErrorCode.BAD_VALUE, path, "a number in [0, 1]", value)
    return x


def _bool(value: Any, path: str) -> bool:
    if not isinstance(value, bool):
        raise _fail(ErrorCode.WRONG_TYPE, path, "a boolean", value)
    return value


def _str(value: Any, path: str, limits: Limits, *, nonempty: bool = False) -> str:
    if not isinstance(value, str):
        raise _fail(ErrorCode.WRONG_TYPE, path, "a string", value)
    if nonempty and not value:
        raise _fail(ErrorCode.BAD_VALUE, path, "a non-empty string", value)
    if len(value) > limits.max_string_len:
        raise _fail(ErrorCode.BAD_VALUE, path, f"at most {limits.max_string_len} characters",
                    f"{len(value)} characters", show=True)
    return value


def _bytes(value: Any, path: str, *, nonempty: bool = True) -> bytes:
    if not isinstance(value, bytes | bytearray):
        raise _fail(ErrorCode.WRONG_TYPE, path, "binary data (msgpack bin)", value)
    if nonempty and not value:
        raise _fail(ErrorCode.BAD_IMAGE, path, "non-empty binary data", value)
    return bytes(value)


def _list(value: Any, path: str, limits: Limits, item: Callable[[Any, str], T]) -> tuple[T, ...]:
    if not isinstance(value, list | tuple):
        raise _fail(ErrorCode.WRONG_TYPE, path, "an array", value)
    if len(value) > limits.max_list_len:
        raise _fail(ErrorCode.PAYLOAD_TOO_LARGE, path,
                    f"at most {limits.max_list_len} items", f"{len(value)} items")
    return tuple(item(v, f"{path}[{i}]") for i, v in enumerate(value))


def _numbers(value: Any, path: str, n: int, code: ErrorCode) -> tuple[float, ...]:
    """``n`` finite numbers; a wrong count or a non-finite number is ``code``."""
    if not isinstance(value, list | tuple):
        raise _fail(ErrorCode.WRONG_TYPE, path, f"an array of {n} numbers", value)
    if len(value) != n:
        raise _fail(code, path, f"an array of {n} numbers", f"{len(value)} items")
    out = []
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise _fail(ErrorCode.WRONG_TYPE, f"{path}[{i}]", "a number", v)
        if not math.isfinite(v):
            raise _fail(code, f"{path}[{i}]", "a finite number", v)
        out.append(float(v))
    return tuple(out)


def _str_map(value: Any, path: str, item: Callable[[Any, str], T], limits: Limits
             ) -> dict[str, T]:
    if not isinstance(value, dict):
        raise _fail(ErrorCode.WRONG_TYPE, path, "a map", value)
    if len(value) > limits.max_list_len:
        raise _fail(ErrorCode.PAYLOAD_TOO_LARGE, path, f"at most {limits.max_list_len} entries",
                    f"{len(value)} entries")
    out = {}
    for k, v in value.items():
        if not isinstance(k, str):
            raise _fail(ErrorCode.WRONG_TYPE, f"{path}", "string keys", k)
        out[k] = item(v, f"{path}.{k}")
    return out


class _Fields:
    """The fields of one msgpack map at ``path``: typed access, then :meth:`done` refuses
    whatever was not read."""

    def __init__(self, value: Any, path: str) -> None:
        if not isinstance(value, dict):
            raise _fail(ErrorCode.WRONG_TYPE, path, "a map", value)
        bad = [k for k in value if not isinstance(k, str)]
        if bad:
            raise _fail(ErrorCode.WRONG_TYPE, path, "a map with string keys", bad[0])
        self.value, self.path = value, path
        self.seen: set[str] = set()

    def req(self, name: str, parse: Callable[[Any, str], T]) -> T:
        self.seen.add(name)
        if self.value.get(name) is None:
            raise ProtocolError(ErrorCode.MISSING_FIELD,
                                f"{self.path}.{name}: missing required field")
        return parse(self.value[name], f"{self.path}.{name}")

    def opt(self, name: str, parse: Callable[[Any, str], T], default: Any = None) -> Any:
        self.seen.add(name)
        v = self.value.get(name)
        return default if v is None else parse(v, f"{self.path}.{name}")

    def done(self) -> None:
        unknown = sorted(set(self.value) - self.seen)
        if unknown:
            raise ProtocolError(ErrorCode.UNKNOWN_FIELD,
                                f"{self.path}: unknown field(s) {unknown}; expected only "
                                f"{sorted(self.seen)}")
