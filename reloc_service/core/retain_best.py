"""The order in which OpenCV's ``KeyPointsFilter::retainBest`` leaves the strongest
keypoints: ``std::nth_element`` (libstdc++'s introselect) by descending response, then
``std::partition`` of the rest by the boundary response. ``cv2.SIFT`` with ``nfeatures``
caps its detection so, and lists the kept keypoints in that order; a step that caps a
detection it already holds lists them in the same order, so what it matches and samples
(ties, RANSAC's draws) is what the extraction's order gives, answer for answer.

The emulation is exact for introselect's partitioning and final insertion sort; where
introselect would give up on them (depth ``2 log2 n`` reached, its heap select) it says so
and the caller extracts instead. ``tests/test_features.py`` checks it against OpenCV.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt


def retain_best(response: npt.ArrayLike, count: int) -> list[int] | None:
    """Indices, in OpenCV's order, of the keypoints ``retainBest`` keeps of those with
    ``response`` (in the detector's order) capped at ``count``: the ``count`` strongest and
    any tied with the weakest of them; all of them, in order, when there are at most
    ``count``. None where introselect would fall back to its heap select."""
    r = [float(x) for x in np.asarray(response, np.float32)]
    if count >= len(r):
        return list(range(len(r)))
    if count <= 0:
        return []
    order = list(range(len(r)))
    if not _introselect(r, order, count - 1):
        return None
    return order[:_partition_ties(r, order, count, r[order[count - 1]])]


def _introselect(r: list[float], order: list[int], nth: int) -> bool:
    """libstdc++'s ``__introselect`` of ``order`` with the comparator ``r[a] > r[b]``,
    in place; False where it would reach its depth limit (and heap select instead)."""
    first, last = 0, len(order)
    depth = 2 * (len(order).bit_length() - 1)
    while last - first > 3:
        if depth == 0:
            return False
        depth -= 1
        _median_to_first(r, order, first, first + 1, first + (last - first) // 2, last - 1)
        cut = _unguarded_partition(r, order, first + 1, last, r[order[first]])
        first, last = (cut, last) if cut <= nth else (first, cut)
    _insertion_sort(r, order, first, last)
    return True


def _median_to_first(r: list[float], order: list[int], result: int, a: int, b: int,
                     c: int) -> None:
    """libstdc++'s ``__move_median_to_first``: the median of ``a``, ``b``, ``c`` swapped
    into ``result``."""
    def gt(i: int, j: int) -> bool:
        return r[order[i]] > r[order[j]]
    if gt(a, b):
        m = b if gt(b, c) else (c if gt(a, c) else a)
    else:
        m = a if gt(a, c) else (c if gt(b, c) else b)
    order[result], order[m] = order[m], order[result]


def _unguarded_partition(r: list[float], order: list[int], lo: int, hi: int,
                         pivot: float) -> int:
    """libstdc++'s ``__unguarded_partition`` of ``order[lo:hi]`` around ``pivot`` (the
    stronger first); the cut."""
    while True:
        while r[order[lo]] > pivot:
            lo += 1
        hi -= 1
        while pivot > r[order[hi]]:
            hi -= 1
        if not lo < hi:
            return lo
        order[lo], order[hi] = order[hi], order[lo]
        lo += 1


def _insertion_sort(r: list[float], order: list[int], first: int, last: int) -> None:
    """libstdc++'s ``__insertion_sort`` of ``order[first:last]``, strongest first."""
    for i in range(first + 1, last):
        v = order[i]
        if r[v] > r[order[first]]:
            order[first + 1:i + 1] = order[first:i]
            order[first] = v
            continue
        j = i
        while r[v] > r[order[j - 1]]:
            order[j] = order[j - 1]
            j -= 1
        order[j] = v


def _partition_ties(r: list[float], order: list[int], lo: int, bound: float) -> int:
    """libstdc++'s bidirectional ``std::partition`` of ``order[lo:]`` by response at least
    ``bound`` (the ties of the weakest kept keypoint), in place; the end of those kept."""
    hi = len(order)
    while True:
        while lo != hi and r[order[lo]] >= bound:
            lo += 1
        if lo == hi:
            return lo
        hi -= 1
        while lo != hi and not r[order[hi]] >= bound:
            hi -= 1
        if lo == hi:
            return lo
        order[lo], order[hi] = order[hi], order[lo]
        lo += 1
