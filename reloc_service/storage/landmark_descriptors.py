"""One stored descriptor per landmark: the rows of a feature kind that observe one landmark
share the descriptor of the first of them (``StoredParts.descriptors == "per-landmark"``).

A landmark seen by several keyframes has a descriptor in each (2.2 a landmark on the rendered
room); relocalization matches a query's descriptors against a keyframe's landmark keypoints
(p3p, the verification's guided matching) or learns from them (ferns, bag of words), and the
observations of one landmark describe one surface patch, seen from nearby keyframes. A
snapshot so stores, per kind, the descriptor (or PQ code) of each landmark's first row in
column order (its earliest keyframe, usually the one that made it) and of every row without a
landmark, in column order; nothing else. Which stored descriptor a row reads is a function of
the rows' landmark ids alone (:func:`shared_index`), which load rebuilds from the landmarks'
observations anyway: no index is stored. A map loaded so and saved again stores the same
bytes (the rows of one landmark read one descriptor, the first of them keeps it).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ..core.errors import MapError
from .descriptor_pq import DESCRIPTOR_CODES

#: Column of the shared descriptors (full) and of their PQ codes, in place of the per-row ones.
SHARED_DESCRIPTORS = "landmark_descriptors"
SHARED_CODES = "landmark_descriptors_pq"
#: Per-row column -> the shared column stored instead of it.
SHARED_OF = {"descriptors": SHARED_DESCRIPTORS, DESCRIPTOR_CODES: SHARED_CODES}
ROW_OF = {shared: row for row, shared in SHARED_OF.items()}


def first_rows(landmark_ids: npt.NDArray[np.integer]) -> npt.NDArray[np.bool_]:
    """(N,) mask of the rows whose descriptor is stored: each landmark's first row in
    ``landmark_ids`` order, and every row without a landmark (id < 0)."""
    ids = np.asarray(landmark_ids)
    first = ids < 0
    has = np.flatnonzero(~first)
    _, at = np.unique(ids[has], return_index=True)   # first occurrence of each id
    first[has[at]] = True
    return first


def shared_index(landmark_ids: npt.NDArray[np.integer]) -> npt.NDArray[np.int64]:
    """(N,) row of the shared column each row reads: its landmark's first row's rank among
    the :func:`first_rows` (its own rank when it has no landmark)."""
    ids = np.asarray(landmark_ids)
    first = first_rows(ids)
    rank = np.cumsum(first, dtype=np.int64) - 1
    has = np.flatnonzero(ids >= 0)
    _, at, inverse = np.unique(ids[has], return_index=True, return_inverse=True)
    out = rank
    out[has] = rank[has[at]][inverse.ravel()]
    return out


def share_descriptors(columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``columns`` (one kind's, every row) with its per-row descriptors or codes replaced by
    the :data:`SHARED_OF` column of the :func:`first_rows` (``landmark_ids`` must be there)."""
    keep = first_rows(columns["landmark_ids"])
    out = dict(columns)
    for row, shared in SHARED_OF.items():
        if row in out:
            out[shared] = out.pop(row)[keep]
    return out


def check_shared_count(where: str, stored: int, landmark_ids: npt.NDArray[np.integer]) -> None:
    """MapError naming ``where`` unless a shared column of ``stored`` rows holds what
    :func:`first_rows` keeps of ``landmark_ids``: one row per distinct landmark and one per
    row without a landmark (a scatter, not a sort: this runs at every load)."""
    ids = np.asarray(landmark_ids)
    has = ids[ids >= 0]
    seen = np.zeros(int(has.max()) + 1 if len(has) else 0, bool)
    seen[has] = True
    expected = int(seen.sum()) + len(ids) - len(has)
    if stored != expected:
        raise MapError(f"{where}: {stored} rows, expected {expected} (one per landmark its "
                       f"keypoints observe and one per keypoint without a landmark)")
