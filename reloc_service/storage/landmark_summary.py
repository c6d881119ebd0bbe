"""A summary map: the landmarks a snapshot keeps when each keyframe keeps at most ``budget``
of its landmark rows of a kind (``StoredParts.landmark_budget``).

A keyframe's rows are ranked in two passes: within each cell of a ``grid`` x ``grid``
partition of its image, by the number of keyframes that see the row's landmark (most first:
a landmark matched again from another view is one a query is likely to match too, and its
point was fixed by more than one view), ties by row order; then the cells interleaved, the
best row of every cell before the second of any (ties again by views, then row), so a cut
at any budget keeps the image covered as the verification's coverage test counts it (the
grid is the verification's, ``VerifyConf.coverage_grid``). A landmark is kept when some
keyframe keeps its row, and then with all its observations: a kept landmark loses no view
and a dropped one leaves no row behind (:func:`kept_landmarks`). A keyframe thus stores its
own best ``budget`` rows and the rows of landmarks its neighbours keep.

The result is an ordinary snapshot with fewer landmarks: any reader of the format it is
saved as loads it. Saved again, a summary map keeps what it holds when ranks of the kept
rows do not change (no row of a landmark kept is dropped; a landmark's views are all kept).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from ..core.frame import Keyframe
from ..core.landmark_table import LandmarkColumns

#: The verification's coverage grid (``VerifyConf.coverage_grid``): cells of the image whose
#: coverage a cut keeps.
COVERAGE_GRID = 4

IntArray = npt.NDArray[np.int64]


def landmark_views(columns: LandmarkColumns) -> IntArray:
    """(L,) number of distinct keyframes observing each landmark of ``columns``."""
    counts = np.diff(columns.obs_offsets)
    owner = np.repeat(np.arange(len(columns.ids), dtype=np.int64), counts)
    pairs = np.unique(np.stack([owner, np.asarray(columns.obs_keyframe, np.int64)]), axis=1)
    return np.bincount(pairs[0], minlength=len(columns.ids)).astype(np.int64)


def row_ranks(keypoints_px: npt.NDArray[np.float64], views: IntArray,
              image_size: tuple[int, int], grid: int = COVERAGE_GRID) -> IntArray:
    """(N,) rank of each of a keyframe's landmark rows (0 best; module docstring): within its
    grid cell by ``views`` (most first, then row), then the cells interleaved.
    ``keypoints_px`` (N, 2) pixels, ``image_size`` (width, height)."""
    n = len(views)
    if n == 0:
        return np.zeros(0, np.int64)
    width, height = image_size
    col = np.clip((keypoints_px[:, 0] + 0.5) * grid // width, 0, grid - 1).astype(np.int64)
    row = np.clip((keypoints_px[:, 1] + 0.5) * grid // height, 0, grid - 1).astype(np.int64)
    cell = row * grid + col
    index = np.arange(n, dtype=np.int64)
    by_cell = np.lexsort((index, -views, cell))          # each cell's rows, best first
    starts = np.searchsorted(cell[by_cell], cell[by_cell])   # first position of each cell
    in_cell = np.empty(n, np.int64)
    in_cell[by_cell] = np.arange(n) - starts
    order = np.lexsort((index, -views, in_cell))
    ranks = np.empty(n, np.int64)
    ranks[order] = np.arange(n)
    return ranks


def kept_landmarks(keyframes: Sequence[Keyframe], columns: LandmarkColumns,
                   budget: int, grid: int = COVERAGE_GRID) -> npt.NDArray[np.bool_]:
    """(L,) whether each landmark of ``columns`` is kept: some keyframe ranks its row among
    its best ``budget`` of that kind (:func:`row_ranks`). ``budget`` 0 keeps every one."""
    keep = np.zeros(len(columns.ids), bool)
    if budget <= 0 or len(columns.ids) == 0:
        keep[:] = True
        return keep
    views = landmark_views(columns)
    for kf in keyframes:
        size = (kf.camera.width, kf.camera.height)
        for kind in kf.features:
            feats = kf.features[kind]
            rows = columns.rows(np.asarray(feats.landmark_ids, np.int64))
            has = np.flatnonzero(rows >= 0)
            ranks = row_ranks(np.asarray(feats.keypoints_px, np.float64)[has],
                              views[rows[has]], size, grid)
            keep[rows[has[ranks < budget]]] = True
    return keep
