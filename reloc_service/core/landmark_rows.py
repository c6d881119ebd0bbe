"""Keyframes whose features a snapshot stored for the keypoints with a landmark only.

Relocalization by landmarks (p3p, ferns, the verification's guided matching) reads a map
keyframe's keypoints that carry a landmark and nothing else; a snapshot may therefore keep
only those (``[service] keyframe_descriptors = "landmarks"``). A keyframe loaded from such a
snapshot is marked in its cache; what reads every keypoint of a map keyframe (a bag-of-words
vocabulary trained or a keyframe indexed again, 5-point matching) asks :func:`check_every_row`
first, which names the option instead of working on a part of the keypoints unawares.
"""

from __future__ import annotations

from .errors import MapError
from .frame import Frame

#: Keyframe cache key set on a keyframe whose features hold its landmark keypoints only.
LANDMARK_ROWS_ONLY = "features:landmark-rows-only"
#: The setting that keeps every keypoint, named by the error.
EVERY_ROW_OPTION = '[service] keyframe_descriptors = "all"'


def holds_landmark_rows_only(keyframe: Frame) -> bool:
    """Whether ``keyframe``'s features were stored for its landmark keypoints only."""
    return bool(keyframe.cache.get(LANDMARK_ROWS_ONLY, False))


def check_every_row(keyframe: Frame, reader: str) -> None:
    """MapError naming :data:`EVERY_ROW_OPTION` when ``keyframe`` holds its landmark
    keypoints only and ``reader`` (what is being done) needs every keypoint."""
    if holds_landmark_rows_only(keyframe):
        raise MapError(f"{reader} needs every keypoint of keyframe "
                       f"{getattr(keyframe, 'id', '?')}, but the map "
                       f"was saved with the keypoints that carry a landmark only; keep them all "
                       f"with {EVERY_ROW_OPTION} (the map must then be built again)")
