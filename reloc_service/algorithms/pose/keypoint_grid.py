"""Guided matching's windows found on a grid of the query's keypoints (numba, the optional
``[jit]`` extra), with the KD-tree's answers exactly.

Search by projection asks, for each of thousands of projected landmarks, the (up to) k query
keypoints nearest to it within the window radius, nearest first (``cKDTree.query`` with
``k`` and ``distance_upper_bound``). Most landmarks have none: the tree's search of every
one of them was most of a guided search (2.8 of 4.6 ms per search on 7scenes_redkitchen's
ORB step, 5300 landmarks against 500 keypoints). :func:`window_neighbours` bins the keypoints
into square cells a hair wider than the radius, so a keypoint within the radius of a pixel
lies in the pixel's cell or one of its eight neighbours, and one compiled pass per landmark
scans those nine cells. A keypoint is kept when its squared distance, summed as the tree sums
it (``dx * dx`` then ``+ dy * dy``), is below the squared radius, as the tree keeps it; the
kept ones are ordered by that distance, as the tree returns them. Where the tree's order or
choice is not the distance's alone (two candidate distances equal, or within a relative
1e-9 of each other or of the radius, where another summation could round the other way),
that landmark's windows are asked of the tree itself, so the answers are always the tree's
(``tests/test_pose_guided.py`` compares both on many random sets). :func:`compiled` returns
None where numba is not installed; the caller then asks the tree for every landmark.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.numeric import compile_once, numba_or_none

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Relative closeness of two squared distances (or of one to the squared radius) below which
#: the order or the choice is left to the KD-tree: far above a few ulps of rounding.
_NEAR_TIE = 1e-9
#: Most grid cells built (4 M: 40 MB of cell starts); beyond, the tree answers.
_MAX_CELLS = 1 << 22


def _scan(px: Array, keypoints_px: Array, origin: Array, cell: float, shape: IntArray,
          starts: IntArray, members: IntArray, radius2: float, near: IntArray,
          ask_tree: npt.NDArray[np.bool_]) -> None:
    """For each pixel ``px[i]``: ``near[i]`` the (up to ``near.shape[1]``) keypoints within
    the radius (squared distance below ``radius2``), nearest first, ``len(keypoints_px)``
    in empty slots; ``ask_tree[i]`` where two candidates' squared distances (or one and
    ``radius2``) are too close to order as the KD-tree would for sure. The keypoints of
    grid cell ``c`` (row-major in ``shape``) are ``members[starts[c]:starts[c + 1]]``."""
    n_kp = keypoints_px.shape[0]
    k = near.shape[1]
    best_d = np.empty(k + 1)
    best_j = np.empty(k + 1, np.int64)
    for i in range(px.shape[0]):
        cx = math.floor((px[i, 0] - origin[0]) / cell)
        cy = math.floor((px[i, 1] - origin[1]) / cell)
        count = 0
        doubtful = False
        for gx in range(max(cx - 1, 0), min(cx + 2, shape[0])):
            for gy in range(max(cy - 1, 0), min(cy + 2, shape[1])):
                c = gx * shape[1] + gy
                for t in range(starts[c], starts[c + 1]):
                    j = members[t]
                    dx = px[i, 0] - keypoints_px[j, 0]
                    dy = px[i, 1] - keypoints_px[j, 1]
                    s = 0.0
                    s += dx * dx
                    s += dy * dy
                    if abs(s - radius2) <= _NEAR_TIE * radius2:
                        doubtful = True
                    if not s < radius2:
                        continue
                    # insert into the sorted list of the k + 1 nearest so far
                    pos = count if count < k + 1 else k + 1
                    while pos > 0 and best_d[pos - 1] > s:
                        if pos < k + 1:
                            best_d[pos] = best_d[pos - 1]
                            best_j[pos] = best_j[pos - 1]
                        pos -= 1
                    if pos < k + 1:
                        best_d[pos] = s
                        best_j[pos] = j
                        if count < k + 1:
                            count += 1
        kept = min(count, k)
        # The kept ones, and the first left out (it decides the last kept), must be
        # strictly ordered with room to spare.
        for m in range(1, count):
            if best_d[m] - best_d[m - 1] <= _NEAR_TIE * best_d[m]:
                doubtful = True
        for m in range(k):
            near[i, m] = best_j[m] if m < kept else n_kp
        ask_tree[i] = doubtful


@compile_once
def compiled() -> Any:
    """:func:`_scan` compiled by numba (cached on disk after the first compile), or None where
    numba is not installed."""
    numba = numba_or_none()
    if numba is None:
        return None
    return numba.njit(cache=True, nogil=True)(_scan)


def window_neighbours(keypoints_px: Array, px: Array, k: int, radius_px: float,
                      tree: Any) -> IntArray:
    """(N, k) indices of the (up to) ``k`` keypoints (K, 2) nearest to each pixel of ``px``
    (N, 2) within ``radius_px``, nearest first, K in empty slots: what
    ``tree.query(px, k=k, distance_upper_bound=radius_px)`` returns (``tree`` the
    ``cKDTree`` of ``keypoints_px``, or a callable returning it, asked only where needed)."""
    scan = compiled()
    if scan is None or len(keypoints_px) == 0 or len(px) == 0 or not radius_px > 0:
        return _from_tree(tree, px, k, radius_px)
    cell = radius_px * (1.0 + _NEAR_TIE)
    origin = keypoints_px.min(axis=0) - cell
    kp_cells = np.floor((keypoints_px - origin) / cell).astype(np.int64)
    shape = kp_cells.max(axis=0) + 2
    if shape[0] * shape[1] > _MAX_CELLS:   # a radius tiny against the keypoints' spread
        return _from_tree(tree, px, k, radius_px)
    flat = kp_cells[:, 0] * shape[1] + kp_cells[:, 1]
    members = np.argsort(flat, kind="stable").astype(np.int64)
    starts = np.zeros(int(shape[0] * shape[1]) + 1, np.int64)
    np.cumsum(np.bincount(flat, minlength=int(shape[0] * shape[1])), out=starts[1:])
    near = np.empty((len(px), k), np.int64)
    ask_tree = np.empty(len(px), bool)
    scan(np.ascontiguousarray(px, np.float64), np.ascontiguousarray(keypoints_px, np.float64),
         origin.astype(np.float64), float(cell), shape.astype(np.int64), starts, members,
         float(radius_px) * float(radius_px), near, ask_tree)
    doubtful = np.flatnonzero(ask_tree)
    if len(doubtful):
        near[doubtful] = _from_tree(tree, px[doubtful], k, radius_px)
    return near


def _from_tree(tree: Any, px: Array, k: int, radius_px: float) -> IntArray:
    """(N, k) window indices of ``px`` asked of the KD-tree (``tree`` or a callable giving it)."""
    kd = tree() if callable(tree) else tree
    _, near = kd.query(px, k=k, distance_upper_bound=radius_px)
    return np.asarray(near).reshape(len(px), k).astype(np.int64, copy=False)


def warm_up() -> None:
    """Load (or compile) the kernel now, on a few keypoints."""
    scan = compiled()
    if scan is None:
        return
    kp = np.array([[10.0, 20.0], [300.0, 200.0]])
    scan(kp, kp, np.zeros(2), 10.0, np.array([40, 30], np.int64),
         np.zeros(1201, np.int64), np.zeros(2, np.int64), 100.0,
         np.empty((2, 2), np.int64), np.empty(2, bool))
