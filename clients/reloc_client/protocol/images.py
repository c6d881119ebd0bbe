"""Image, depth and feature containers: PNG/JPEG header checks (nothing is decoded),
WireImage, WireDepth and WireFeatures."""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from .checks import (
    DEFAULT_LIMITS,
    Array,
    ErrorCode,
    Limits,
    ProtocolError,
    _bytes,
    _fail,
    _Fields,
    _float,
    _int,
    _str,
)


class ImageFormat(enum.StrEnum):
    """Encodings of an image on the wire."""

    JPEG = "jpeg"
    PNG = "png"
    MONO8 = "mono8"      # raw row-major uint8, len(data) == width * height


class DepthFormat(enum.StrEnum):
    """Encodings of a depth map on the wire (raw values; 0 = no measurement)."""

    PNG = "png"          # single-channel 16-bit PNG
    MONO16 = "mono16"    # raw row-major little-endian uint16, len(data) == 2 * width * height



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
