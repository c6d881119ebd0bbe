"""Which putative matches a PnP solve gets: one query keypoint per landmark (the nearest in
descriptor distance), and the union of two match lists kept one to one (the first list wins).
Used by the P3P pose finder (:mod:`.p3p`) and tracking with a prior."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .kernels import compiled


def union_matches(first_q: npt.NDArray[np.int64], first_rows: npt.NDArray[np.int64],
           second_q: npt.NDArray[np.int64], second_rows: npt.NDArray[np.int64]
           ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Correspondences (query index, pool row) of both lists, the first list winning where a
    query keypoint or a pool row appears in both; rows of -1 are dropped."""
    q = np.concatenate([first_q, second_q])
    rows = np.concatenate([first_rows, second_rows])
    valid = np.flatnonzero(rows >= 0)
    keep = np.sort(valid[np.unique(q[valid], return_index=True)[1]])
    keep = np.sort(keep[np.unique(rows[keep], return_index=True)[1]])
    return q[keep], rows[keep]


def best_per_landmark(landmark_ids: npt.NDArray[np.int64], dist: npt.NDArray[np.float32],
                       rows: npt.NDArray[np.int64] | None = None, pool_size: int = 0
                       ) -> npt.NDArray[np.int64]:
    """Indices of the matches to keep: for each landmark, the query keypoint nearest to it
    (the first of equally near ones). With the matches' pool ``rows`` (one row per landmark,
    ``pool_size`` rows), one compiled pass where numba is installed (:mod:`.kernels`)."""
    kernels = compiled()
    if kernels is not None and rows is not None:
        keep = np.empty(len(rows), np.int64)
        count = kernels.best_per_row(np.ascontiguousarray(rows, np.int64),
                                     np.ascontiguousarray(dist, np.float32),
                                     np.full(pool_size, -1, np.int64), keep)
        return keep[:count]
    order = np.lexsort((dist, landmark_ids))
    _, first = np.unique(landmark_ids[order], return_index=True)
    return np.sort(order[first])
