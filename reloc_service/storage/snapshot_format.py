"""The names and versions of the snapshot format that :mod:`.snapshot_save` writes and
:mod:`.snapshot` reads (layout: :mod:`.snapshot`'s docstring)."""

from __future__ import annotations

import re

import numpy as np

FORMAT = "reloc map"
FORMAT_VERSION = 11
#: A snapshot is written as the oldest format that reads what it holds: 11 with exact
#: descriptor rows beside PQ codes (``FORMAT_VERSION``), 10 with float16 landmark points,
#: 9 with rows keeping their own descriptor beside shared ones, 8 with shared descriptors,
#: else 7, so a reloc that reads up to that format still loads it.
EXACT_ROWS_FORMAT_VERSION = FORMAT_VERSION
HALF_POINTS_FORMAT_VERSION = 10
OWN_ROWS_FORMAT_VERSION = 9
SHARED_FORMAT_VERSION = 8
UNSHARED_FORMAT_VERSION = 7
#: Older format versions this reloc still reads.
READABLE_VERSIONS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11)
MODELS_DIR = "models"

FEATURE_FIELDS = ("keypoints_px", "levels", "sizes", "angles", "descriptors", "landmark_ids",
                  "points_world")
LANDMARK_FIELDS = ("ids", "points_world", "obs_offsets", "obs_keyframe", "obs_kind",
                   "obs_keypoint", "kinds")
#: Arrays added since the first snapshot format; older snapshots read without them.
OPTIONAL_LANDMARK_FIELDS = ("depth_sigmas_m",)
#: Landmark columns of format 2 (``kinds`` lives in the manifest).
LANDMARK_COLUMNS = ("ids", "points_world", "depth_sigmas_m", "obs_offsets", "obs_keyframe",
                    "obs_kind", "obs_keypoint")
#: Narrower dtypes tried for landmark integer columns at save (narrowest first; formats 3 and
#: 4), and the dtypes every landmark column is read back in (a copy when stored narrower).
LANDMARK_NARROWER: dict[str, tuple[type, ...]] = {
    "ids": (np.int32,), "obs_offsets": (np.int32,), "obs_keyframe": (np.int16, np.int32),
    "obs_kind": (np.int8,), "obs_keypoint": (np.int16, np.int32)}
LANDMARK_DTYPES = {"ids": np.int64, "obs_offsets": np.int64, "obs_keyframe": np.int64,
                   "obs_kind": np.int16, "obs_keypoint": np.int64}
#: Landmark columns stored as they are or narrowed (points and sigmas: :func:`encode_geometry`).
LANDMARK_INTEGERS = ("ids", "obs_offsets", "obs_keyframe", "obs_kind", "obs_keypoint")
#: Keyframe cache entries saved with the map: PTAM's small blurry images (``Frame.cache``
#: key prefix), so a place finder indexing a loaded map need not read every image.
THUMBNAIL_PREFIX = "sbi:"


def model_dir_name(method: str) -> str:
    """Directory name under ``models/`` for a method string (safe characters only)."""
    return re.sub(r"[^A-Za-z0-9._+,=-]", "_", method) or "_"



def thumbnail_path(key: str) -> str:
    """A small blurry image cache key's file in a snapshot (safe characters only)."""
    return f"thumbnails/{re.sub(r'[^A-Za-z0-9._-]', '_', key)}.npy"
