"""The repetition index's leaf scan compiled (numba, the optional ``[jit]`` extra), with the
numpy path's answers (:meth:`.repetition_index.RepetitionIndex.nearest_two`).

The numpy path scans each probed leaf once for every query descriptor probing it: one
distance matrix per leaf, a few dozen small numpy calls each, about a hundred leaves per
search, so the calls' overhead is most of the search. :func:`_leaf_nearest_two_l2` (uint8
SIFT) and :func:`_leaf_nearest_two_hamming` (ORB's 64-bit words) take the probed leaves in
ascending order, each for every query descriptor probing it (so each descriptor meets its
leaves in the order the numpy path files its candidates), and keep:

- in each leaf the two nearest rows by the exact integer distance (the squared L2 of uint8
  SIFT stays below 2^24, so the numpy path's float32 products are exact integers too), the
  first of equal ones as two ``argmin`` passes find them;
- over the leaves the two smallest of those candidates by their float32 distance (the
  float32 root for SIFT, as the numpy path compares them), a tie going to the candidate
  filed first (an earlier leaf, the leaf's nearest before its second), as the numpy path's
  stable ranking sends it.

So the distances and rows are the numpy path's, value for value
(``tests/test_repetition_index.py`` compares both paths). Measured (CPU time, one BLAS
thread, load about 13 on 2 cores) on a 28k-row pool of room-hard's keyframes (about 3100
rows scanned per descriptor): 100 / 200 SIFT descriptors 7.3 / 12.9 ms against the numpy
path's 12.0 / 15.4 ms; ORB 1.9 / 3.1 ms against 4.3 / 5.2 ms. :func:`compiled` imports numba on
first use and returns None where it is not installed.

The two scans are one loop apart from their distance; they stay two functions because one
scan taking the distance as a compiled function (an argument or a closure's) answers the
same as fast, but numba's disk cache keys such a function by the objects' identity and
misses in every new process: each worker would compile it again, about 2.3 s under load.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from ...core.numeric import compile_once, numba_or_none
from . import guided_kernels
from .guided_kernels import _hamming_words

#: Larger than any distance a descriptor pair has (the per-leaf scan's start).
_FAR = 1 << 62


def _squared_l2_rows(a: npt.NDArray[np.uint8], i: int, b: npt.NDArray[np.uint8], j: int
                     ) -> int:
    """Squared L2 distance of row ``i`` of ``a`` and row ``j`` of ``b`` (uint8 SIFT), exact in
    32-bit integers (at most 128 * 255^2 < 2^31), which the compiler vectorises eight lanes
    at a time."""
    d2 = np.int32(0)
    for t in range(a.shape[1]):
        diff = np.int32(a[i, t]) - np.int32(b[j, t])
        d2 += diff * diff
    return int(d2)


def _merge(dist: Any, row: int, out_d: Any, out_i: Any, q: int) -> None:
    """Offer candidate ``row`` at ``dist`` to query ``q``'s two smallest so far (``out_d[q]``,
    ``out_i[q]``), behind equal ones already there (a stable ranking's order)."""
    if dist < out_d[q, 0]:
        out_d[q, 1], out_i[q, 1] = out_d[q, 0], out_i[q, 0]
        out_d[q, 0], out_i[q, 0] = dist, row
    elif dist < out_d[q, 1]:
        out_d[q, 1], out_i[q, 1] = dist, row


def _leaf_nearest_two_l2(desc: npt.NDArray[np.uint8], pool: npt.NDArray[np.uint8],
                         order: npt.NDArray[np.int32], offsets: npt.NDArray[np.int64],
                         pair_q: npt.NDArray[np.int64], pair_leaf: npt.NDArray[np.int64],
                         out_d: npt.NDArray[np.float32], out_i: npt.NDArray[np.int64]) -> None:
    """For each (query row ``pair_q[p]`` of ``desc`` (Q, D), leaf ``pair_leaf[p]``) in turn
    (uint8 SIFT; pairs by ascending leaf, so each query meets its leaves in ascending order
    and a leaf's rows stay in cache for every query probing it): the two nearest of the
    ``pool`` rows filed under the leaf (``order[offsets[l]:offsets[l + 1]]``) offered to the
    query's two nearest in ``out_d[q]`` (float32 L2, filled with inf) and ``out_i[q]`` (pool
    rows, filled with -1), as the module's doc says."""
    for p in range(pair_q.shape[0]):
        q, leaf = pair_q[p], pair_leaf[p]
        b0, b1, r0, r1 = _FAR, _FAR, -1, -1
        for t in range(offsets[leaf], offsets[leaf + 1]):
            row = int(order[t])
            d2 = _squared_l2_rows(desc, q, pool, row)
            if d2 < b0:
                b0, b1, r0, r1 = d2, b0, row, r0
            elif d2 < b1:
                b1, r1 = d2, row
        if r0 >= 0:
            _merge(np.float32(math.sqrt(b0)), r0, out_d, out_i, q)
        if r1 >= 0:
            _merge(np.float32(math.sqrt(b1)), r1, out_d, out_i, q)


def _leaf_nearest_two_hamming(desc_words: npt.NDArray[np.uint64],
                              pool_words: npt.NDArray[np.uint64],
                              order: npt.NDArray[np.int32], offsets: npt.NDArray[np.int64],
                              pair_q: npt.NDArray[np.int64], pair_leaf: npt.NDArray[np.int64],
                              out_d: npt.NDArray[np.float32], out_i: npt.NDArray[np.int64]
                              ) -> None:
    """:func:`_leaf_nearest_two_l2` for binary descriptors as 64-bit words, by Hamming
    distance."""
    for p in range(pair_q.shape[0]):
        q, leaf = pair_q[p], pair_leaf[p]
        b0, b1, r0, r1 = _FAR, _FAR, -1, -1
        for t in range(offsets[leaf], offsets[leaf + 1]):
            row = int(order[t])
            d = _hamming_words(desc_words, q, pool_words, row)
            if d < b0:
                b0, b1, r0, r1 = d, b0, row, r0
            elif d < b1:
                b1, r1 = d, row
        if r0 >= 0:
            _merge(np.float32(b0), r0, out_d, out_i, q)
        if r1 >= 0:
            _merge(np.float32(b1), r1, out_d, out_i, q)


class RepetitionKernels(NamedTuple):
    """The compiled functions (see the module's doc)."""

    leaf_nearest_two_l2: Any
    leaf_nearest_two_hamming: Any


@compile_once
def compiled() -> RepetitionKernels | None:
    """The kernels compiled by numba (cached on disk by numba after the first compile), or
    None where numba is not installed."""
    global _merge, _hamming_words, _squared_l2_rows
    numba = numba_or_none()
    if numba is None:
        return None
    # Guided matching's kernels compile the Hamming distance this module inlines too.
    guided_kernels.compiled()
    _hamming_words = guided_kernels._hamming_words
    helper: Any = numba.njit(cache=True, nogil=True, inline="always")
    _merge = helper(getattr(_merge, "py_func", _merge))
    _squared_l2_rows = helper(getattr(_squared_l2_rows, "py_func", _squared_l2_rows))
    jit: Any = numba.njit(cache=True, nogil=True)
    return RepetitionKernels(jit(_leaf_nearest_two_l2), jit(_leaf_nearest_two_hamming))


def warm_up() -> None:
    """Load (or compile) every kernel now, on a few descriptors."""
    k = compiled()
    if k is None:
        return
    order, offsets, pairs = np.arange(2, dtype=np.int32), np.array([0, 2]), np.zeros(1, np.int64)
    out_d, out_i = np.full((1, 2), np.inf, np.float32), np.full((1, 2), -1, np.int64)
    k.leaf_nearest_two_l2(np.zeros((1, 128), np.uint8), np.zeros((2, 128), np.uint8), order,
                          offsets, pairs, pairs, out_d, out_i)
    k.leaf_nearest_two_hamming(np.zeros((1, 4), np.uint64), np.zeros((2, 4), np.uint64), order,
                               offsets, pairs, pairs, out_d, out_i)
