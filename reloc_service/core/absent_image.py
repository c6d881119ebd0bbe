"""A keyframe image a compact snapshot did not store: its size and checksum, no pixels.

Relocalization reads a keyframe's features, landmarks and small blurry images, not its
pixels; only a method that warps or re-extracts them does (ferns, ESM, features of a kind the
map lacks). A map saved without images gives its keyframes an :class:`AbsentImage`: reading
the pixels raises a :class:`MapError` that says which option keeps them, never a silent
failure, and the CRC-32 of the pixels it stood for keeps the map's content digest (the one
replicas compare) what it was when the image was held.
"""

from __future__ import annotations

import zlib

import numpy as np
import numpy.typing as npt

from .errors import MapError
from .frame import EncodedImage

#: The storage option that keeps keyframe images, as an error names it.
KEEP_IMAGES_OPTION = '[service] keyframe_images = "always"'


class AbsentImage(EncodedImage):
    """Stands for an (H, W) grey keyframe image not stored; :meth:`decode` raises MapError."""

    __slots__ = ("crc32",)

    def __init__(self, shape: tuple[int, int], crc32: int) -> None:
        # EncodedImage's fields, set directly: there are no bytes to read a format from
        self.data = b""
        self.format = "none"
        self.shape = (int(shape[0]), int(shape[1]))
        self.crc32 = int(crc32)

    def decode(self) -> npt.NDArray[np.uint8]:
        raise MapError(f"keyframe image ({self.shape[1]}x{self.shape[0]}) not stored: the map "
                       f"was saved with only what its methods read; a method that reads "
                       f"keyframe pixels (ferns, sbi+esm, a new feature kind) needs "
                       f"{KEEP_IMAGES_OPTION} and the keyframes put again")

    def tobytes(self) -> bytes:
        raise MapError(f"keyframe image not stored (see {KEEP_IMAGES_OPTION})")


def pixels_crc32(pixels: npt.NDArray[np.uint8]) -> int:
    """CRC-32 of an image's pixels in C order (what :class:`AbsentImage` keeps)."""
    return zlib.crc32(np.ascontiguousarray(pixels).data)
