"""Which of a keyframe's bulky parts a snapshot stores: its image and its depth map.

A keyframe's depth map is an input to landmark creation only: the builder turns it into
landmarks when the keyframe is added (:func:`..core.landmarks.landmarks_for_keyframe`), and
nothing reads it afterwards. Its image is read by few methods (ferns' warps, ESM, features of
a kind the map lacks: :attr:`Relocalizer.reads_keyframe_images`); relocalization and
re-training of the others use the features, landmarks and small blurry images a snapshot
stores anyway. So by default (:class:`StoredParts`) a snapshot keeps:

- depth: ``"drop"`` (none), ``"lossless"`` (the float32 metres zlib-compressed, bit-exact:
  about 16x smaller on a rendered room), or ``"raw"`` (the float32 ``.npy``, as format 4);
- images: ``"needed"`` (only when a method of the map reads them, else an
  :class:`..core.absent_image.AbsentImage`: size and CRC-32 of the pixels, no file) or
  ``"always"``;
- features: ``"all"``, ``"landmarks"`` (the rows of keypoints that carry a landmark, where
  every method of the map is trained and none reads other keypoints: :mod:`.landmark_rows`)
  or ``"per-landmark"`` (those rows, with one descriptor a landmark shared by its rows:
  :mod:`.landmark_descriptors`; ``"per-landmark-medoid"``: the rows' medoid's rather than
  the first row's);
- SIFT descriptors: ``"none"`` (in full), ``"pq"`` (product-quantization codes, 32 bytes
  instead of 128, decoded when a keyframe's features are first read: :mod:`.descriptor_pq`)
  or ``"pq16"`` (16-byte codes, coarser), or ``"pq-hybrid"`` (``"pq"`` codes, and in full
  the rows the codes reconstruct worse than the descriptors' own noise allows:
  :mod:`.descriptor_hybrid`; format 11);
- a bag-of-words vocabulary's centres (``vocabulary``): ``"float16"`` or ``"uint8"`` (SIFT
  means rounded to SIFT's own integer grid: :meth:`..algorithms.place.vocabulary.VocabularyTree.to_state`
  documents the bound; read by every reloc that reads float16 centres);
- landmark points (``landmark_points``): ``"float32"`` offsets from their anchor keyframe, or
  ``"float16"`` where the rounding is within a quarter of each landmark's uncertainty
  (:mod:`.landmark_codec`; a snapshot with float16 points is format 10);
- landmarks (``landmark_budget``): every one (0), or a summary map's, at most that many of
  each keyframe's rows of a kind ranked by views and spread (:mod:`.landmark_summary`; the
  format is unchanged: a summary map is a map with fewer landmarks).

The service's defaults (``[service]`` in the configuration) store landmark rows, in full.

A replica that must hold what its source holds saves :data:`EVERYTHING`.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core.absent_image import AbsentImage, pixels_crc32
from ..core.errors import ConfigError, StorageError
from ..core.frame import Keyframe
from .descriptor_pq import CODEC_SUBSPACES
from .landmark_rows import ROW_MODES
from .snapshot_files import SnapshotReader

DEPTH_MODES = ("drop", "lossless", "raw")
IMAGE_MODES = ("needed", "always")
#: How SIFT descriptors are stored: in full, or as product-quantization codes
#: (:mod:`.descriptor_pq`); ORB's 32-byte binary descriptors are stored as they are.
DESCRIPTOR_CODECS = ("none", *CODEC_SUBSPACES)
#: How a bag-of-words vocabulary's float centres are stored (``[service] vocabulary_centres``).
VOCABULARY_MODES = ("float16", "uint8")
#: How landmark points' offsets from their anchor are stored (``[service] landmark_points``).
POINT_MODES = ("float32", "float16")


def _check_choice(key: str, value: str, choices: tuple[str, ...]) -> None:
    """ConfigError naming ``key`` and its choices unless ``value`` is one of them."""
    if value not in choices:
        raise ConfigError(f"{key}: expected one of {', '.join(choices)}, got {value!r}")


def _check_budget(budget: object, descriptors: str) -> None:
    """ConfigError unless ``budget`` is an integer >= 0, and > 0 only with landmark rows (a
    summary map drops the rows of the landmarks it drops: "all" would keep them)."""
    if isinstance(budget, bool) or not isinstance(budget, int) or budget < 0:
        raise ConfigError(f"landmark_budget: expected an integer >= 0 (0: every landmark), "
                          f"got {budget!r}")
    if budget > 0 and descriptors == "all":
        raise ConfigError(f"landmark_budget: expected keyframe_descriptors other than 'all' "
                          f"with a budget ({budget}): a summary map keeps landmark rows only")


#: Keyframe cache entry of the CRC-32 and (H, W) of its pixels (an image's bytes never
#: change while the keyframe object lives: a replaced keyframe is a new object).
IMAGE_CRC_KEY = "image:crc32"
#: Suffix of a losslessly compressed depth map: zlib of its float32 bytes, C order.
LOSSLESS_DEPTH_SUFFIX = ".f32.zlib"


@dataclass(frozen=True)
class StoredParts:
    """What a snapshot stores of each keyframe's depth and image (see module docstring)."""

    depth: str = "drop"
    images: str = "needed"
    descriptor_codec: str = "none"
    descriptors: str = "all"
    vocabulary: str = "float16"
    landmark_points: str = "float32"
    landmark_budget: int = 0

    def __post_init__(self) -> None:
        _check_choice("keyframe_depth", self.depth, DEPTH_MODES)
        _check_choice("keyframe_images", self.images, IMAGE_MODES)
        _check_choice("keyframe_descriptors", self.descriptors, ROW_MODES)
        _check_choice("descriptor_codec", self.descriptor_codec, DESCRIPTOR_CODECS)
        _check_choice("vocabulary_centres", self.vocabulary, VOCABULARY_MODES)
        _check_choice("landmark_points", self.landmark_points, POINT_MODES)
        _check_budget(self.landmark_budget, self.descriptors)

    def keeps_images(self, methods_read_images: bool) -> bool:
        """Whether a map whose methods do (or do not) read keyframe pixels stores images."""
        return self.images == "always" or methods_read_images


#: Everything as held: raw depth, every image and full descriptors (a worker's replica).
EVERYTHING = StoredParts(depth="raw", images="always")


def image_entry(kf: Keyframe) -> dict[str, Any]:
    """The manifest fields of a keyframe whose image is not stored: its (H, W) and the CRC-32
    of its pixels (decoded once for the keyframe, kept in its cache: a map snapshotted every
    200 puts does not decode its 1000 images each time)."""
    source = kf.image_source
    if isinstance(source, AbsentImage):
        return {"image": None, "image_shape": list(source.shape), "image_crc32": source.crc32}
    if IMAGE_CRC_KEY not in kf.cache:
        pixels = kf.image
        kf.cache[IMAGE_CRC_KEY] = (pixels_crc32(pixels), list(pixels.shape))
    crc, shape = kf.cache[IMAGE_CRC_KEY]
    return {"image": None, "image_shape": shape, "image_crc32": crc}


def absent_image(entry: Mapping[str, Any]) -> AbsentImage:
    """The :class:`AbsentImage` of a manifest entry without an image file; ValueError naming
    the field when its shape or checksum is not what :func:`image_entry` writes."""
    shape, crc = entry.get("image_shape"), entry.get("image_crc32")
    if (not isinstance(shape, list) or len(shape) != 2
            or not all(isinstance(v, int) and v > 0 for v in shape)):
        raise ValueError(f"image_shape: expected [height, width] of positive integers, got "
                         f"{shape!r}")
    if not isinstance(crc, int) or not 0 <= crc < 2**32:
        raise ValueError(f"image_crc32: expected an unsigned 32-bit integer, got {crc!r}")
    return AbsentImage((shape[0], shape[1]), crc)


def depth_file(kf_id: int, depth: npt.NDArray[Any], mode: str) -> tuple[str, bytes] | None:
    """(relative path, bytes) of a keyframe's depth map as ``mode`` stores it; None: not
    stored (``"drop"``). ``"raw"`` is the caller's ``.npy`` (returned as None too)."""
    if mode != "lossless":
        return None
    data = np.ascontiguousarray(depth, np.float32)
    return f"depth/{kf_id}{LOSSLESS_DEPTH_SUFFIX}", zlib.compress(data.tobytes(), 6)


def read_lossless_depth(reader: SnapshotReader, entry: Mapping[str, Any]
                        ) -> npt.NDArray[np.float32]:
    """The (H, W) float32 depth map of ``entry`` stored by ``"lossless"`` (checked file),
    read-only; StorageError when it does not decompress to the keyframe's image size."""
    rel = str(entry["depth"])
    shape = entry.get("image_shape") or [entry["camera"]["height"], entry["camera"]["width"]]
    try:
        raw = zlib.decompress(reader.map(rel).tobytes())
    except zlib.error as exc:
        raise StorageError(f"{reader.root / rel}: not zlib data ({exc})") from exc
    h, w = int(shape[0]), int(shape[1])
    if len(raw) != h * w * 4:
        raise StorageError(f"{reader.root / rel}: {len(raw)} bytes, expected {h}x{w} float32")
    depth = np.frombuffer(raw, np.float32).reshape(h, w)
    return depth
