"""Compiled scoring of ferns (numba), one pass per patch instead of numpy's many.

Scoring a patch adds, for each of its M visited model rows, that row's sparse log corrections
into a dense row of C scores (eq. 3.22); then the best ``k`` classes and their posteriors
(eq. 3.19) follow from one scan of that row. With numpy/scipy these are separate passes over
arrays of millions of entries (gather the visited rows, densify them, add the constants, mask,
partition, subtract, exponentiate, sum): at 500 patches x 2000 classes the copies and passes
cost more than the additions. Here one patch's C scores stay in the L1 cache while its M rows
are added, and nothing is copied. The additions are done in the same order as
:meth:`~reloc_service.ferns.classifier.FernScorer.scores` (ferns in order, from zero, then the
class constant), so the scores are bit for bit the same; the posteriors' normaliser is summed
in float64 (numpy sums float32 pairwise), so posteriors agree within float32 rounding.

:func:`compiled_classify_rows` imports numba on first use (numba and LLVM cost about half a
second and tens of MB at import: only a process that classifies with ferns pays) and returns
None where numba is not installed; the classifier then uses its numpy/scipy path.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt


def _classify_rows(rows: npt.NDArray[np.int64], indptr: npt.NDArray[np.integer],
                   indices: npt.NDArray[np.int32], data: npt.NDArray[np.float32],
                   const: npt.NDArray[np.float32], allowed: npt.NDArray[np.bool_],
                   use_allowed: bool, top_cols: npt.NDArray[np.int64],
                   top_post: npt.NDArray[np.float32]) -> None:
    """For each patch ``i`` (its model rows ``rows[i]``): the columns of the ``k`` best
    scores (best first, ties to the lower column; disallowed columns score -inf) into
    ``top_cols[i]`` and their posteriors (0 where -inf) into ``top_post[i]``."""
    n, m = rows.shape
    c = const.shape[0]
    k = top_cols.shape[1]
    s = np.empty(c, np.float32)
    best = np.empty(k, np.float32)
    starts = np.empty(m, np.int64)
    ends = np.empty(m, np.int64)
    touched = np.zeros(1, np.float32)
    for i in range(n):
        # The M rows lie anywhere in a model of tens of MB: read a little of each, every
        # cache line, before adding any, so their memory loads overlap instead of each
        # stalling the additions in turn (the loop is bound by memory latency otherwise).
        for j in range(m):
            r = rows[i, j]
            starts[j] = indptr[r]
            ends[j] = indptr[r + 1]
        acc = np.float32(0.0)
        for j in range(m):
            for e in range(starts[j], ends[j], 16):  # 16 entries: one 64-byte line
                acc += data[e] + np.float32(indices[e])
        touched[0] += acc  # keeps the reads from being optimised away
        s[:] = 0.0
        for j in range(m):
            for e in range(starts[j], ends[j]):
                s[indices[e]] += data[e]
        best[:] = -np.inf
        top_cols[i, :] = -1
        for col in range(c):
            v = s[col] + const[col]
            if use_allowed and not allowed[col]:
                v = -np.inf
            s[col] = v
            if v > best[k - 1]:  # strict: an equal later column does not displace
                pos = k - 1
                while pos > 0 and v > best[pos - 1]:
                    best[pos] = best[pos - 1]
                    top_cols[i, pos] = top_cols[i, pos - 1]
                    pos -= 1
                best[pos] = v
                top_cols[i, pos] = col
        _fill_unscored(top_cols[i])
        shift = best[0] if np.isfinite(best[0]) else np.float32(0.0)
        norm = 0.0
        for col in range(c):
            d = s[col] - shift
            if d > -88.0:  # exp(-88) < 1e-38: nothing next to the best class's exp(0) = 1
                norm += np.exp(d)
        norm = max(norm, 1e-30)
        for pos in range(k):
            top_post[i, pos] = np.exp(np.float64(best[pos] - shift)) / norm \
                if np.isfinite(best[pos]) else 0.0


def _fill_unscored(cols: npt.NDArray[np.int64]) -> None:
    """Slots left at -1 (fewer than k finite scores) get the lowest columns not yet taken,
    as a sort with ties to the lower index would give (their scores are all -inf)."""
    nxt = 0
    for pos in range(cols.shape[0]):
        if cols[pos] >= 0:
            continue
        while True:
            taken = False
            for q in range(cols.shape[0]):
                if cols[q] == nxt:
                    taken = True
            if not taken:
                break
            nxt += 1
        cols[pos] = nxt
        nxt += 1


@functools.cache
def compiled_classify_rows() -> Callable[..., None] | None:
    """:func:`_classify_rows` compiled by numba (cached on disk by numba after the first
    compile), or None where numba is not installed."""
    global _fill_unscored  # the compiled kernel calls the compiled helper by its global name
    try:
        import numba
    except ImportError:
        return None
    _fill_unscored = numba.njit(cache=True, nogil=True)(_fill_unscored)
    kernel: Any = numba.njit(cache=True, nogil=True)(_classify_rows)
    return kernel
