"""Image messages of a bag to dataset files: a CompressedImage's JPEG or PNG bytes as recorded
(checked to decode, at the camera's size), a raw Image as a grey PNG (the bridge's
:func:`~reloc_service.service.ros2.convert.grey_from_raw`). Files are named after the image's
header stamp: ``<sec>.<fraction>.<ext>``, the fraction of a second with at least six digits
(TUM's names) and no trailing zeros beyond them."""

from __future__ import annotations

import collections
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ...core.errors import DatasetError
from ...service.ros2 import convert

_SIGNATURES = ((b"\x89PNG\r\n\x1a\n", "png"), (b"\xff\xd8\xff", "jpg"))


def encoded_image(msg: Any) -> tuple[bytes, str]:
    """(file bytes, extension) of an image message: a CompressedImage's bytes as they are,
    a raw Image encoded as a grey PNG; ValueError saying what was expected otherwise."""
    if hasattr(msg, "encoding"):   # sensor_msgs/Image
        grey = convert.grey_from_raw(msg)
        ok, png = cv2.imencode(".png", grey)
        if not ok:
            raise ValueError(f"a {grey.shape[1]}x{grey.shape[0]} grey image does not encode")
        return png.tobytes(), "png"
    data = bytes(np.asarray(msg.data, dtype=np.uint8))
    for signature, extension in _SIGNATURES:
        if data.startswith(signature):
            return data, extension
    raise ValueError(f"compressed image of format {msg.format!r} ({len(data)} bytes) is not "
                     "JPEG or PNG")


def decode_grey(data: bytes) -> npt.NDArray[np.uint8] | None:
    """The grey pixels of JPEG/PNG bytes (EXIF orientation ignored, as the dataset reader
    does), or None when they do not decode."""
    flags = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags) if data else None
    return None if image is None else np.asarray(image, dtype=np.uint8)


def image_size(msg: Any) -> tuple[int, int] | None:
    """(width, height) of an image message, None when it does not decode."""
    if hasattr(msg, "encoding"):
        return int(msg.width), int(msg.height)
    try:
        data, _ = encoded_image(msg)
    except ValueError:
        return None
    grey = decode_grey(data)
    return None if grey is None else (grey.shape[1], grey.shape[0])


def stamp_name(stamp_ns: int) -> str:
    """``1305031232.961662`` for 1305031232961662000 ns, ``12.500000`` for 12.5 s."""
    seconds, nanoseconds = divmod(stamp_ns, 1_000_000_000)
    return f"{seconds}." + f"{nanoseconds:09d}".rstrip("0").ljust(6, "0")


class ImageWriter:
    """Writes the chosen images under ``root/folder``; an image that cannot be used is skipped
    and counted by reason, an image of another size than the camera stops the conversion
    (the camera is wrong for all of them)."""

    def __init__(self, root: Path, folder: str, camera: Camera) -> None:
        self.root, self.folder, self.camera = root, folder, camera
        self.skipped: collections.Counter[str] = collections.Counter()
        (root / folder).mkdir(parents=True, exist_ok=True)

    def write(self, msg: Any, stamp_ns: int) -> str | None:
        """The written file's path relative to ``root``, or None when the image is skipped."""
        try:
            data, extension = encoded_image(msg)
        except ValueError as exc:
            self.skipped[str(exc)] += 1
            return None
        grey = decode_grey(data)
        if grey is None:
            self.skipped[f"{extension.upper()} bytes that do not decode"] += 1
            return None
        height, width = grey.shape
        if (width, height) != self.camera.size:
            raise DatasetError(f"image stamped {stamp_ns * 1e-9:.9f} s is {width}x{height} px "
                               f"but the camera is {self.camera.width}x{self.camera.height}; "
                               "expected the camera of these images (check --camera-info-topic "
                               "or the camera given)")
        path = f"{self.folder}/{stamp_name(stamp_ns)}.{extension}"
        (self.root / path).write_bytes(data)
        return path
