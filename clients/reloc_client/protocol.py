"""The reloc wire protocol, version 1: msgpack messages, their strict decoders, Zenoh keys.

This module is the single definition of the wire format for both ends (the service imports
it); ``docs/protocol.md`` describes the same format field by field for other languages.

Every message is a msgpack map with string keys and ``"v": 1``. Decoding validates
everything and raises :class:`ProtocolError` with an :class:`ErrorCode` and a message that
names the field and what was expected. Optional fields may be absent or nil; encoders omit
them when unset. Unknown fields are refused (``UNKNOWN_FIELD``) so a typo cannot pass
silently. ``encode()`` validates its own output, so it only produces what ``decode`` accepts.

Image bytes are never decoded here (no OpenCV): only their container is checked (format,
stated size against the PNG/JPEG header or the raw length, pixel limits).
"""

from __future__ import annotations

import enum
import math
import struct
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self, TypeVar

import msgpack
import numpy as np
import numpy.typing as npt

PROTOCOL_VERSION = 1
DEFAULT_PREFIX = "reloc"

#: Camera models and their accepted numbers of distortion values (reloc_service.cameras).
CAMERA_MODELS: dict[str, tuple[int, ...]] = {
    "pinhole": (0,), "radtan": (4, 5), "equidistant": (4,), "fov": (1,)}

QUAT_NORM_TOL = 1e-3
ROTATION_TOL = 1e-5
MAX_NAME_LEN = 128
_MAX_KEYFRAME_ID = 2**63 - 1
_FORBIDDEN_NAME_CHARS = frozenset("/*$#?")

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
    STORAGE_ERROR = "STORAGE_ERROR"
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


class ImageFormat(enum.StrEnum):
    """Encodings of an image on the wire."""

    JPEG = "jpeg"
    PNG = "png"
    MONO8 = "mono8"      # raw row-major uint8, len(data) == width * height


class DepthFormat(enum.StrEnum):
    """Encodings of a depth map on the wire (raw values; 0 = no measurement)."""

    PNG = "png"          # single-channel 16-bit PNG
    MONO16 = "mono16"    # raw row-major little-endian uint16, len(data) == 2 * width * height


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
    KEYFRAME_ADDED = "keyframe_added"
    KEYFRAME_REMOVED = "keyframe_removed"
    KEYFRAME_REJECTED = "keyframe_rejected"
    CAMERA_ADDED = "camera_added"
    CAMERA_REJECTED = "camera_rejected"
    MAP_SAVED = "map_saved"


# ================================================================================================
# Field validation: every reader takes the value and its dotted path, and raises ProtocolError.
# ================================================================================================

def _describe(value: Any) -> str:
    if isinstance(value, bytes | bytearray):
        return f"{len(value)} bytes"
    text = repr(value)
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


# ================================================================================================
# Names and key expressions
# ================================================================================================

def check_name(name: Any, what: str = "map name") -> str:
    """Return ``name`` if it can be one Zenoh key chunk (map, camera or instance name):
    non-empty, at most 128 characters, no ``/ * $ # ?``, no whitespace or control
    characters, not starting with ``@``; else raise ProtocolError(BAD_NAME)."""
    if not isinstance(name, str):
        raise _fail(ErrorCode.BAD_NAME, what, "a string", name)
    problem = (
        "a non-empty name" if not name else
        f"at most {MAX_NAME_LEN} characters" if len(name) > MAX_NAME_LEN else
        "no '/', '*', '$', '#' or '?'" if _FORBIDDEN_NAME_CHARS & set(name) else
        "no whitespace or control characters" if any(c.isspace() or not c.isprintable()
                                                      for c in name) else
        "a name not starting with '@' (reserved by Zenoh)" if name.startswith("@") else "")
    if problem:
        raise _fail(ErrorCode.BAD_NAME, what, problem, name)
    return name


def check_prefix(prefix: Any) -> str:
    """Return ``prefix`` if it is one or more valid name chunks joined by ``/``."""
    if not isinstance(prefix, str) or not prefix:
        raise _fail(ErrorCode.BAD_NAME, "prefix", "a non-empty string such as 'reloc'", prefix)
    for chunk in prefix.split("/"):
        check_name(chunk, f"prefix chunk of {prefix!r}")
    return prefix


def _check_kf_id(kf_id: Any, path: str = "keyframe id") -> int:
    return _int(kf_id, path, lo=0, hi=_MAX_KEYFRAME_ID)


class keys:  # noqa: N801 - a namespace used as ``keys.relocalize(prefix, map)``
    """Zenoh key expressions of one map (``prefix`` may have several chunks, default
    ``"reloc"``). Every function validates its names (ProtocolError BAD_NAME)."""

    @staticmethod
    def _base(prefix: str, map_name: str) -> str:
        return f"{check_prefix(prefix)}/{check_name(map_name)}"

    @staticmethod
    def keyframe(prefix: str, map_name: str, kf_id: int) -> str:
        """``<prefix>/<map>/keyframes/<id>``: put adds or replaces, delete removes, get reads."""
        return f"{keys._base(prefix, map_name)}/keyframes/{_check_kf_id(kf_id)}"

    @staticmethod
    def keyframes(prefix: str, map_name: str) -> str:
        """``<prefix>/<map>/keyframes/**``: get returns every stored keyframe."""
        return f"{keys._base(prefix, map_name)}/keyframes/**"

    @staticmethod
    def camera(prefix: str, map_name: str, camera_id: str) -> str:
        """``<prefix>/<map>/cameras/<id>``: put adds or replaces, get reads."""
        return f"{keys._base(prefix, map_name)}/cameras/{check_name(camera_id, 'camera id')}"

    @staticmethod
    def cameras(prefix: str, map_name: str) -> str:
        """``<prefix>/<map>/cameras/**``: get returns every camera."""
        return f"{keys._base(prefix, map_name)}/cameras/**"

    @staticmethod
    def relocalize(prefix: str, map_name: str) -> str:
        """``<prefix>/<map>/relocalize``: queryable, RelocalizeRequest -> RelocalizeReply."""
        return f"{keys._base(prefix, map_name)}/relocalize"

    @staticmethod
    def train(prefix: str, map_name: str) -> str:
        """``<prefix>/<map>/train``: queryable, TrainRequest -> TrainReply (at once)."""
        return f"{keys._base(prefix, map_name)}/train"

    @staticmethod
    def events(prefix: str, map_name: str) -> str:
        """``<prefix>/<map>/events``: the service publishes Event messages here."""
        return f"{keys._base(prefix, map_name)}/events"

    @staticmethod
    def status(prefix: str, map_name: str) -> str:
        """``<prefix>/<map>/status``: queryable, no payload -> StatusReply."""
        return f"{keys._base(prefix, map_name)}/status"

    @staticmethod
    def liveliness(prefix: str, instance: str, map_name: str) -> str:
        """``<prefix>/@live/<instance>/<map>``: the liveliness token of a serving instance."""
        return (f"{check_prefix(prefix)}/@live/{check_name(instance, 'instance name')}/"
                f"{check_name(map_name)}")

    @staticmethod
    def liveliness_all(prefix: str) -> str:
        """``<prefix>/@live/*/*``: liveliness get of every serving (instance, map)."""
        return f"{check_prefix(prefix)}/@live/*/*"

    @staticmethod
    def parse_keyframe(prefix: str, key: str) -> tuple[str, int]:
        """(map, keyframe id) of a concrete ``<prefix>/<map>/keyframes/<id>`` key."""
        map_name, leaf = keys._parse(prefix, key, "keyframes")
        if not leaf.isdigit() or (leaf != "0" and leaf.startswith("0")):
            raise _fail(ErrorCode.BAD_NAME, "keyframe key", "a decimal keyframe id", key)
        return map_name, _check_kf_id(int(leaf), f"keyframe id in {key!r}")

    @staticmethod
    def parse_camera(prefix: str, key: str) -> tuple[str, str]:
        """(map, camera id) of a concrete ``<prefix>/<map>/cameras/<id>`` key."""
        return keys._parse(prefix, key, "cameras")

    @staticmethod
    def parse_liveliness(prefix: str, key: str) -> tuple[str, str]:
        """(instance, map) of a ``<prefix>/@live/<instance>/<map>`` key."""
        head = f"{check_prefix(prefix)}/@live/"
        parts = key[len(head):].split("/") if key.startswith(head) else []
        if len(parts) != 2:
            raise _fail(ErrorCode.BAD_NAME, "liveliness key", f"'{head}<instance>/<map>'", key)
        return check_name(parts[0], "instance name"), check_name(parts[1])

    @staticmethod
    def _parse(prefix: str, key: str, collection: str) -> tuple[str, str]:
        head = f"{check_prefix(prefix)}/"
        parts = key[len(head):].split("/") if key.startswith(head) else []
        if len(parts) != 3 or parts[1] != collection:
            raise _fail(ErrorCode.BAD_NAME, f"{collection} key",
                        f"'{head}<map>/{collection}/<id>'", key)
        what = "camera id" if collection == "cameras" else "keyframe id"
        return check_name(parts[0]), check_name(parts[2], what)


# ================================================================================================
# Building blocks: pose, camera, image, depth, features
# ================================================================================================

def quat_xyzw_to_rotation(q: Sequence[float]) -> Array:
    """Unit quaternion (x, y, z, w), Hamilton, to a (3, 3) rotation matrix."""
    x, y, z, w = (float(v) for v in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def rotation_to_quat_xyzw(r: Array) -> tuple[float, float, float, float]:
    """(3, 3) rotation matrix to a unit quaternion (x, y, z, w) with w >= 0 (Shepperd)."""
    diag = np.array([r[0, 0], r[1, 1], r[2, 2]])
    trace = diag.sum()
    # Pick the largest of (w, x, y, z) to divide by: numerically safe for every rotation.
    if trace >= diag.max():
        s = 2.0 * math.sqrt(max(1.0 + trace, 0.0))
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(diag))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + r[i, i] - r[j, j] - r[k, k], 0.0))
        q = [0.0, 0.0, 0.0, (r[k, j] - r[j, k]) / s]
        q[i], q[j], q[k] = s / 4, (r[j, i] + r[i, j]) / s, (r[k, i] + r[i, k]) / s
    qa = np.array(q) / np.linalg.norm(q)
    qa = qa if qa[3] >= 0 else -qa
    return (float(qa[0]), float(qa[1]), float(qa[2]), float(qa[3]))


@dataclass(frozen=True)
class WirePose:
    """A pose ``a_from_b`` on the wire: translation ``t`` (metres) and unit quaternion ``q``
    (x, y, z, w, Hamilton). Messages carry ``world_from_cam`` (camera x right, y down, z
    forward)."""

    t: tuple[float, float, float]
    q: tuple[float, float, float, float]

    @classmethod
    def from_matrix(cls, a_from_b: npt.ArrayLike, path: str = "world_from_cam") -> WirePose:
        """From a (4, 4) homogeneous pose; ProtocolError(BAD_POSE) unless finite with an
        orthonormal rotation (det +1) and last row [0 0 0 1]."""
        m = np.asarray(a_from_b, dtype=np.float64)
        if m.shape != (4, 4):
            raise _fail(ErrorCode.BAD_POSE, path, "a (4, 4) pose", f"shape {m.shape}")
        if not np.all(np.isfinite(m)):
            raise _fail(ErrorCode.BAD_POSE, path, "finite values", "NaN or Inf")
        r = m[:3, :3]
        ortho = float(np.abs(r @ r.T - np.eye(3)).max())
        if ortho > ROTATION_TOL or np.linalg.det(r) <= 0:
            raise _fail(ErrorCode.BAD_POSE, path, "an orthonormal rotation with det +1",
                        f"|R R^T - I| = {ortho:.2e}, det = {np.linalg.det(r):.3f}")
        if np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9:
            raise _fail(ErrorCode.BAD_POSE, path, "last row [0 0 0 1]", m[3].tolist())
        t = m[:3, 3]
        return cls((float(t[0]), float(t[1]), float(t[2])), rotation_to_quat_xyzw(r))

    @classmethod
    def from_tq(cls, t: Sequence[float], q: Sequence[float],
                path: str = "world_from_cam") -> WirePose:
        """From translation (3,) and quaternion (x, y, z, w); normalises q (norm within 1e-3)."""
        return cls.from_wire({"t": list(t), "q": list(q)}, path)

    def matrix(self) -> Array:
        """(4, 4) float64 homogeneous pose."""
        m = np.eye(4)
        m[:3, :3] = quat_xyzw_to_rotation(self.q)
        m[:3, 3] = self.t
        return m

    def to_wire(self) -> dict[str, Any]:
        return {"t": list(self.t), "q": list(self.q)}

    @classmethod
    def from_wire(cls, value: Any, path: str) -> WirePose:
        f = _Fields(value, path)
        t = f.req("t", lambda v, p: _numbers(v, p, 3, ErrorCode.BAD_POSE))
        q = f.req("q", lambda v, p: _numbers(v, p, 4, ErrorCode.BAD_POSE))
        f.done()
        norm = math.sqrt(sum(c * c for c in q))
        if abs(norm - 1.0) > QUAT_NORM_TOL:
            raise _fail(ErrorCode.BAD_POSE, f"{path}.q",
                        f"a unit quaternion x y z w (norm 1 within {QUAT_NORM_TOL:g})",
                        f"norm {norm:.6f}")
        qn = (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm)
        return cls((t[0], t[1], t[2]), qn)


@dataclass(frozen=True)
class WireCamera:
    """The dataset camera dict: ``model`` (see CAMERA_MODELS), image size (px), focal lengths
    and principal point (px, pixel centres at integer coordinates), distortion values."""

    model: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], path: str = "camera") -> WireCamera:
        """Validate a camera dict (e.g. ``Camera.to_dict()`` or a ``cameras.json`` entry)."""
        return cls.from_wire(dict(d), path)

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model, "width": self.width, "height": self.height,
                "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "distortion": list(self.distortion)}

    to_wire = to_dict

    @classmethod
    def from_wire(cls, value: Any, path: str) -> WireCamera:
        f = _Fields(value, path)
        model = f.req("model", lambda v, p: _str(v, p, _UNLIMITED))
        size = [f.req(n, lambda v, p: _camera_int(v, p)) for n in ("width", "height")]
        intr = [f.req(n, _float) for n in ("fx", "fy", "cx", "cy")]
        dist = f.opt("distortion", lambda v, p: _list(v, p, _UNLIMITED, _float), ())
        f.done()
        if model not in CAMERA_MODELS:
            raise _fail(ErrorCode.BAD_CAMERA, f"{path}.model", f"one of {sorted(CAMERA_MODELS)}",
                        model)
        if intr[0] <= 0 or intr[1] <= 0:
            raise _fail(ErrorCode.BAD_CAMERA, path, "positive fx and fy", intr[:2])
        if len(dist) not in CAMERA_MODELS[model]:
            counts = " or ".join(map(str, CAMERA_MODELS[model]))
            raise _fail(ErrorCode.BAD_CAMERA, f"{path}.distortion",
                        f"{counts} values for model {model!r}", f"{len(dist)} values")
        fx, fy, cx, cy = intr
        return cls(model, size[0], size[1], fx, fy, cx, cy, tuple(dist))


def _camera_int(v: Any, p: str) -> int:
    n = _int(v, p)
    if n <= 0:
        raise _fail(ErrorCode.BAD_CAMERA, p, "a positive integer", v)
    return n


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_header(data: bytes) -> tuple[int, int, int, int] | None:
    """(width, height, bit depth, colour type) from a PNG's IHDR chunk; None if ``data`` is
    not a PNG."""
    if len(data) < 33 or not data.startswith(_PNG_SIGNATURE) or data[12:16] != b"IHDR":
        return None
    width, height, bit_depth, colour = struct.unpack(">IIBB", data[16:26])
    return width, height, bit_depth, colour


def jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's start-of-frame segment; None if ``data`` is not a JPEG.

    Walks the marker segments up to SOFn (a few dozen steps; nothing is decompressed)."""
    if len(data) < 4 or data[:2] != b"\xff\xd8":
        return None
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            return None
        marker = data[pos + 1]
        if marker == 0xFF:          # fill byte
            pos += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:   # standalone markers
            pos += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image / start of scan before any frame header
            return None
        (length,) = struct.unpack(">H", data[pos + 2:pos + 4])
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if pos + 9 > len(data):
                return None
            height, width = struct.unpack(">HH", data[pos + 5:pos + 9])
            return width, height
        if length < 2:
            return None
        pos += 2 + length
    return None


def _check_size(path: str, kind: str, width: int, height: int, limits: Limits) -> None:
    if width * height > limits.max_image_pixels:
        raise ProtocolError(ErrorCode.IMAGE_TOO_LARGE,
                            f"{path}: {kind} is {width}x{height} = {width * height} px; "
                            f"expected at most {limits.max_image_pixels} px")


def _container_size(data: bytes, fmt: str, path: str) -> tuple[int, int]:
    """(width, height) read from the PNG/JPEG header; BAD_IMAGE if the container is not one."""
    if fmt == "png":
        header = png_header(data)
        size = None if header is None else header[:2]
    else:
        size = jpeg_size(data)
    if size is None:
        raise _fail(ErrorCode.BAD_IMAGE, f"{path}.data", f"a {fmt.upper()} file", data)
    return size


def _parse_container(value: Any, path: str, limits: Limits, formats: type[enum.StrEnum],
                     what: str) -> tuple[Any, int, int, bytes, _Fields]:
    f = _Fields(value, path)
    names = [m.value for m in formats]  # type: ignore[attr-defined]
    fmt_s = f.req("format", lambda v, p: _str(v, p, limits))
    if fmt_s not in names:
        raise _fail(ErrorCode.BAD_IMAGE, f"{path}.format", f"one of {names}", fmt_s)
    width = f.req("width", lambda v, p: _int(v, p, lo=1, hi=2**31 - 1))
    height = f.req("height", lambda v, p: _int(v, p, lo=1, hi=2**31 - 1))
    _check_size(path, what, width, height, limits)
    data = f.req("data", _bytes)
    return formats(fmt_s), width, height, data, f


def _check_stated_size(path: str, stated: tuple[int, int], actual: tuple[int, int],
                       fmt: str) -> None:
    if stated != actual:
        raise ProtocolError(ErrorCode.BAD_IMAGE,
                            f"{path}: stated size {stated[0]}x{stated[1]} does not match the "
                            f"{fmt} data ({actual[0]}x{actual[1]})")


@dataclass(frozen=True)
class WireImage:
    """An image on the wire: JPEG, PNG, or raw row-major grey ``mono8`` bytes."""

    format: ImageFormat
    width: int
    height: int
    data: bytes = field(repr=False)

    @classmethod
    def from_array(cls, image: npt.ArrayLike) -> WireImage:
        """A (H, W) uint8 grey array as ``mono8`` (no encoding, no OpenCV)."""
        a = np.asarray(image)
        if a.ndim != 2 or a.dtype != np.uint8:
            raise _fail(ErrorCode.BAD_IMAGE, "image", "an (H, W) uint8 grey array",
                        f"shape {a.shape} {a.dtype}")
        return cls(ImageFormat.MONO8, int(a.shape[1]), int(a.shape[0]),
                   np.ascontiguousarray(a).tobytes())

    @classmethod
    def from_bytes(cls, data: bytes) -> WireImage:
        """An encoded PNG or JPEG file's bytes; the size is read from its header."""
        data = bytes(data)
        if png_header(data) is not None:
            fmt = ImageFormat.PNG
        elif jpeg_size(data) is not None:
            fmt = ImageFormat.JPEG
        else:
            raise _fail(ErrorCode.BAD_IMAGE, "image", "PNG or JPEG file bytes", data[:16])
        width, height = _container_size(data, fmt.value, "image")
        return cls(fmt, width, height, data)

    def to_array(self) -> npt.NDArray[np.uint8]:
        """(H, W) uint8 view of a ``mono8`` image (PNG/JPEG need a decoder, e.g. OpenCV)."""
        if self.format is not ImageFormat.MONO8:
            raise ValueError(f"to_array: only mono8 images can be viewed without a decoder, "
                             f"this one is {self.format.value}")
        return np.frombuffer(self.data, np.uint8).reshape(self.height, self.width)

    def to_wire(self) -> dict[str, Any]:
        return {"format": self.format.value, "width": self.width, "height": self.height,
                "data": self.data}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits = DEFAULT_LIMITS) -> WireImage:
        fmt, width, height, data, f = _parse_container(value, path, limits, ImageFormat, "image")
        f.done()
        if fmt is ImageFormat.MONO8:
            if len(data) != width * height:
                raise ProtocolError(ErrorCode.BAD_IMAGE,
                                    f"{path}.data: expected width*height = {width * height} "
                                    f"bytes for mono8 {width}x{height}, got {len(data)}")
        else:
            _check_stated_size(path, (width, height), _container_size(data, fmt.value, path),
                               fmt.value)
        return cls(fmt, width, height, data)


@dataclass(frozen=True)
class WireDepth:
    """A depth map along the optical axis: raw uint16 values times ``metres_per_unit``;
    raw 0 means no measurement."""

    format: DepthFormat
    width: int
    height: int
    data: bytes = field(repr=False)
    metres_per_unit: float = 0.001

    @classmethod
    def from_metres(cls, depth_m: npt.ArrayLike, metres_per_unit: float = 0.001) -> WireDepth:
        """(H, W) depth in metres (NaN or <= 0 where unknown) as ``mono16``."""
        d = np.asarray(depth_m, dtype=np.float64)
        if d.ndim != 2:
            raise _fail(ErrorCode.BAD_IMAGE, "depth", "an (H, W) array", f"shape {d.shape}")
        raw = np.nan_to_num(np.round(d / metres_per_unit), nan=0.0, posinf=0.0, neginf=0.0)
        raw = np.clip(raw, 0, 65535).astype("<u2")
        return cls(DepthFormat.MONO16, int(d.shape[1]), int(d.shape[0]), raw.tobytes(),
                   float(metres_per_unit))

    def to_metres(self) -> npt.NDArray[np.float32]:
        """(H, W) float32 metres, NaN where raw 0 (``mono16`` only)."""
        if self.format is not DepthFormat.MONO16:
            raise ValueError("to_metres: only mono16 depth can be read without a PNG decoder")
        raw = np.frombuffer(self.data, "<u2").reshape(self.height, self.width)
        metres = (raw * self.metres_per_unit).astype(np.float32)
        metres[raw == 0] = np.nan
        return metres

    def to_wire(self) -> dict[str, Any]:
        return {"format": self.format.value, "width": self.width, "height": self.height,
                "data": self.data, "metres_per_unit": self.metres_per_unit}

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits = DEFAULT_LIMITS) -> WireDepth:
        fmt, width, height, data, f = _parse_container(value, path, limits, DepthFormat, "depth")
        mpu = f.req("metres_per_unit", lambda v, p: _float(v, p, positive=True))
        f.done()
        if fmt is DepthFormat.MONO16:
            if len(data) != 2 * width * height:
                raise ProtocolError(ErrorCode.BAD_IMAGE,
                                    f"{path}.data: expected 2*width*height = {2 * width * height}"
                                    f" bytes for mono16 {width}x{height}, got {len(data)}")
        else:
            header = png_header(data)
            if header is None or header[2:] != (16, 0):
                raise _fail(ErrorCode.BAD_IMAGE, f"{path}.data",
                            "a single-channel 16-bit PNG",
                            "not a PNG" if header is None else
                            f"bit depth {header[2]}, colour type {header[3]}")
            _check_stated_size(path, (width, height), header[:2], "png")
        return cls(fmt, width, height, data, mpu)


def _readonly(a: npt.NDArray[Any]) -> npt.NDArray[Any]:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class WireFeatures:
    """Keypoints a mapping front end (e.g. SVO) sends with a keyframe, N of them.

    On the wire each array is packed little-endian bytes: ``keypoints_px`` float32 (N, 2)
    pixels (x right, y down, full resolution), ``landmark_ids`` int64 (N,) (-1 = none),
    ``points_world`` float64 (N, 3) metres in the world frame (NaN rows = unknown).
    """

    keypoints_px: Array
    landmark_ids: npt.NDArray[np.int64] | None = None
    points_world: Array | None = None

    def __post_init__(self) -> None:
        kp = _readonly(np.array(self.keypoints_px, dtype=np.float32).reshape(-1, 2))
        n = len(kp)
        ids = (None if self.landmark_ids is None else
               _readonly(np.array(self.landmark_ids, dtype=np.int64).reshape(-1)))
        pts = (None if self.points_world is None else
               _readonly(np.array(self.points_world, dtype=np.float64).reshape(-1, 3)))
        for name, arr in (("landmark_ids", ids), ("points_world", pts)):
            if arr is not None and len(arr) != n:
                raise ProtocolError(ErrorCode.BAD_FEATURES,
                                    f"features.{name}: expected {n} rows (one per keypoint), "
                                    f"got {len(arr)}")
        object.__setattr__(self, "keypoints_px", kp)
        object.__setattr__(self, "landmark_ids", ids)
        object.__setattr__(self, "points_world", pts)

    def __len__(self) -> int:
        return len(self.keypoints_px)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, WireFeatures):
            return NotImplemented
        return all(_array_eq(getattr(self, n), getattr(other, n))
                   for n in ("keypoints_px", "landmark_ids", "points_world"))

    __hash__ = object.__hash__

    def to_wire(self) -> dict[str, Any]:
        d: dict[str, Any] = {"keypoints_px": self.keypoints_px.astype("<f4").tobytes()}
        if self.landmark_ids is not None:
            d["landmark_ids"] = self.landmark_ids.astype("<i8").tobytes()
        if self.points_world is not None:
            d["points_world"] = self.points_world.astype("<f8").tobytes()
        return d

    @classmethod
    def from_wire(cls, value: Any, path: str, limits: Limits = DEFAULT_LIMITS) -> WireFeatures:
        f = _Fields(value, path)
        kp_b = f.req("keypoints_px", lambda v, p: _bytes(v, p, nonempty=False))
        ids_b = f.opt("landmark_ids", lambda v, p: _bytes(v, p, nonempty=False))
        pts_b = f.opt("points_world", lambda v, p: _bytes(v, p, nonempty=False))
        f.done()
        kp = _unpack(kp_b, "<f4", 2, f"{path}.keypoints_px")
        n = len(kp)
        if n > limits.max_features:
            raise ProtocolError(ErrorCode.PAYLOAD_TOO_LARGE,
                                f"{path}: {n} keypoints; expected at most {limits.max_features}")
        if not np.all(np.isfinite(kp)):
            raise _fail(ErrorCode.BAD_FEATURES, f"{path}.keypoints_px", "finite pixel positions",
                        show=False)
        ids = None if ids_b is None else _unpack(ids_b, "<i8", 1, f"{path}.landmark_ids")[:, 0]
        pts = None if pts_b is None else _unpack(pts_b, "<f8", 3, f"{path}.points_world")
        if ids is not None and np.any(ids < -1):
            raise _fail(ErrorCode.BAD_FEATURES, f"{path}.landmark_ids",
                        "ids >= 0, or -1 for none", int(ids.min()))
        if pts is not None and (np.any(np.isinf(pts))
                                or np.any(np.isnan(pts).any(1) != np.isnan(pts).all(1))):
            raise _fail(ErrorCode.BAD_FEATURES, f"{path}.points_world",
                        "rows of 3 finite values or 3 NaN (unknown)", show=False)
        return cls(kp, ids, pts)


def _unpack(data: bytes, dtype: str, cols: int, path: str) -> npt.NDArray[Any]:
    itemsize = np.dtype(dtype).itemsize * cols
    if len(data) % itemsize:
        raise ProtocolError(ErrorCode.BAD_FEATURES,
                            f"{path}: expected a multiple of {itemsize} bytes ({cols} x {dtype} "
                            f"per keypoint), got {len(data)}")
    return np.frombuffer(data, dtype).reshape(-1, cols)


def _array_eq(a: npt.NDArray[Any] | None, b: npt.NDArray[Any] | None) -> bool:
    if a is None or b is None:
        return a is b
    return a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))


# ================================================================================================
# Messages
# ================================================================================================

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
    if isinstance(obj["v"], bool) or obj["v"] != PROTOCOL_VERSION:
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

    def to_wire(self) -> dict[str, Any]:
        return {"id": self.id, "image": self.image.to_wire(), "camera_id": self.camera_id,
                "camera": _opt_wire(self.camera), "world_from_cam": self.world_from_cam.to_wire(),
                "timestamp": self.timestamp, "features": _opt_wire(self.features),
                "depth": _opt_wire(self.depth)}

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
        f.done()
        if depth is not None and (depth.width, depth.height) != (image.width, image.height):
            raise ProtocolError(ErrorCode.BAD_IMAGE,
                                f"{path}.depth: size {depth.width}x{depth.height} does not "
                                f"match the image's {image.width}x{image.height}")
        return cls(kf_id, image, pose, camera_id, camera, timestamp, features, depth)


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

    def to_wire(self) -> dict[str, Any]:
        return {"id": self.id, "camera": self.camera.to_wire(), "camera_id": self.camera_id,
                "world_from_cam": self.world_from_cam.to_wire(), "timestamp": self.timestamp,
                "num_landmarks": self.num_landmarks, "image": _opt_wire(self.image)}

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
            image=f.opt("image", lambda v, p: WireImage.from_wire(v, p, limits)))
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
    """A rough ``world_from_cam`` the caller believes in; candidates are keyframes whose
    centre is within ``radius_m`` metres of its centre."""

    world_from_cam: WirePose
    radius_m: float

    def to_wire(self) -> dict[str, Any]:
        return {"world_from_cam": self.world_from_cam.to_wire(), "radius_m": self.radius_m}

    @classmethod
    def from_wire(cls, value: Any, path: str) -> Prior:
        f = _Fields(value, path)
        out = cls(f.req("world_from_cam", WirePose.from_wire),
                  f.req("radius_m", lambda v, p: _float(v, p, positive=True)))
        f.done()
        return out


def _method(value: Any, path: str) -> str:
    """A method name or comma-separated fallback chain, e.g. ``"bow+p3p,sbi+esm"``."""
    s = _str(value, path, _SHORT)
    parts = [p.strip() for p in s.split(",")]
    if not all(parts) or any(c.isspace() for p in parts for c in p):
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

    def to_wire(self) -> dict[str, Any]:
        return {"map": self.map, "instance": self.instance, "keyframes": self.keyframes,
                "landmarks": self.landmarks, "trained": self.trained,
                "map_version": self.map_version, "methods": list(self.methods),
                "default_method": self.default_method, "cameras": list(self.cameras),
                "training": self.training, "uptime_s": self.uptime_s,
                "counters": dict(self.counters), "latency_s": dict(self.latency_s)}

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
            latency_s=f.opt("latency_s", lambda v, p: _timings(v, p, limits), {}))
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

__all__ = [
    "PROTOCOL_VERSION", "DEFAULT_PREFIX", "CAMERA_MODELS", "ErrorCode", "ProtocolError", "Limits",
    "DEFAULT_LIMITS", "ImageFormat", "DepthFormat", "ReplyStatus", "EventKind", "keys",
    "check_name", "check_prefix", "WirePose", "WireCamera", "WireImage", "WireDepth",
    "WireFeatures", "Prior", "Hypothesis", "Message", "KeyframePut", "KeyframeInfo", "CameraPut",
    "RelocalizeRequest", "RelocalizeReply", "TrainRequest", "TrainReply", "Event", "StatusReply",
    "ErrorReply", "encode_error", "unpack_message", "png_header", "jpeg_size",
    "quat_xyzw_to_rotation", "rotation_to_quat_xyzw", "MESSAGE_TYPES", *[
        n for n in dir() if n.startswith("decode_")]]
