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


def _first_row_of_each(landmark_ids: npt.NDArray[np.integer]
                       ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(rows with a landmark, the first row of each row's landmark): a scatter of the rows'
    minimum by id, not a sort (1.6 M rows: 0.1 s against 0.5 s for ``np.unique``, paid at
    the first read of a loaded map's features)."""
    ids = np.asarray(landmark_ids)
    rows = np.flatnonzero(ids >= 0)
    if not len(rows):
        return rows, rows
    first_of_id = np.full(int(ids[rows].max()) + 1, len(ids), np.int64)
    np.minimum.at(first_of_id, ids[rows], rows)
    return rows, first_of_id[ids[rows]]


def first_rows(landmark_ids: npt.NDArray[np.integer]) -> npt.NDArray[np.bool_]:
    """(N,) mask of the rows whose descriptor is stored: each landmark's first row in
    ``landmark_ids`` order, and every row without a landmark (id < 0)."""
    first = np.asarray(landmark_ids) < 0
    _, first_of_row = _first_row_of_each(landmark_ids)
    first[first_of_row] = True
    return first


def shared_index(landmark_ids: npt.NDArray[np.integer]) -> npt.NDArray[np.int64]:
    """(N,) row of the shared column each row reads: its landmark's first row's rank among
    the :func:`first_rows` (its own rank when it has no landmark)."""
    first = np.asarray(landmark_ids) < 0
    rows, first_of_row = _first_row_of_each(landmark_ids)
    first[first_of_row] = True
    rank = np.cumsum(first, dtype=np.int64) - 1
    rank[rows] = rank[first_of_row]
    return rank


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
