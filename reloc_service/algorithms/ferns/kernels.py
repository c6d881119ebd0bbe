"""Compiled scoring of ferns (numba), one pass per patch instead of numpy's many.

Scoring a patch adds, for each of its M visited model rows, that row's sparse log corrections
into a dense row of C scores (eq. 3.22); then the best ``k`` classes and their posteriors
(eq. 3.19) follow from one scan of that row. With numpy/scipy these are separate passes over
arrays of millions of entries (gather the visited rows, densify them, add the constants, mask,
partition, subtract, exponentiate, sum): at 500 patches x 2000 classes the copies and passes
cost more than the additions. Here one patch's C scores stay in the L1 cache while its M rows
are added, and nothing is copied. The additions are done in the same order as
:meth:`~reloc_service.algorithms.ferns.scorer.FernScorer.scores` (ferns in order, from zero, then the
class constant), so the scores are bit for bit the same; the posteriors' normaliser is summed
in float64 (numpy sums float32 pairwise) over the classes that can change it in float32 (see
:func:`negligible_log_ratio`), so posteriors agree within float32 rounding.

The leaves of N patches (:func:`_leaves_at`) are read in the image directly, 2 S M pixels per
patch, clamping coordinates at the border (what numpy's path gets by replicating the border
into a padded copy): the same leaves, without numpy's (N, S M) int64 index arrays and gathers.

:func:`compiled_classify_rows` and :func:`compiled_leaves_at` import numba on first use (numba
and LLVM cost about half a second and tens of MB at import: only a process that classifies with
ferns pays) and return None where numba is not installed; the classifier then uses its
numpy/scipy path.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.numeric import compile_once, numba_or_none


def negligible_log_ratio(num_classes: int) -> float:
    """Score difference below which a class cannot change a posterior in float32: the
    normaliser is at least 1 (the best class's exp(0)), so ``num_classes`` terms each below
    ``exp(-t)`` with ``t = ln(num_classes) + 25 ln 2`` add less than 2^-25 to it, under half
    of float32's relative rounding step (2^-24). Skipping them saves most of the exponentials
    (at 2000 classes about 1180 of a patch's classes lie within exp's float32 range of the
    best, 260 within this bound)."""
    return math.log(max(num_classes, 1)) + 25.0 * math.log(2.0)


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
    cutoff = -negligible_log_ratio(c)
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
            if d > cutoff:  # the others cannot change the float32 posteriors
                norm += np.exp(d)
        norm = max(norm, 1e-30)
        for pos in range(k):
            top_post[i, pos] = np.exp(np.float64(best[pos] - shift)) / norm \
                if np.isfinite(best[pos]) else 0.0


def _leaves_at(image: npt.NDArray[Any], xs: npt.NDArray[np.int64], ys: npt.NDArray[np.int64],
               off_a: npt.NDArray[np.int64], off_b: npt.NDArray[np.int64],
               num_ferns: int, out: npt.NDArray[np.uint16]) -> None:
    """Leaves ``out`` (N, M) of the patches of ``image`` (H, W) centred at pixels ``(xs, ys)``
    (N,): test ``j`` of fern ``m`` compares the pixels at offsets ``off_a[j M + m]`` and
    ``off_b[j M + m]`` (dy, dx), coordinates clamped into the image (a replicated border);
    first test = top bit."""
    h, w = image.shape
    num_tests = off_a.shape[0] // num_ferns
    flat = image.ravel()
    # Fern-major linear offsets (fern m's tests contiguous) for patches inside the image.
    reach = 0
    lin_a = np.empty(off_a.shape[0], np.int64)
    lin_b = np.empty(off_a.shape[0], np.int64)
    for m in range(num_ferns):
        for j in range(num_tests):
            t = j * num_ferns + m
            lin_a[m * num_tests + j] = off_a[t, 0] * w + off_a[t, 1]
            lin_b[m * num_tests + j] = off_b[t, 0] * w + off_b[t, 1]
            reach = max(reach, abs(off_a[t, 0]), abs(off_a[t, 1]), abs(off_b[t, 0]),
                        abs(off_b[t, 1]))
    for i in range(xs.shape[0]):
        x, y = xs[i], ys[i]
        if reach <= x < w - reach and reach <= y < h - reach:
            base = y * w + x
            for m in range(num_ferns):
                leaf = 0
                for j in range(m * num_tests, (m + 1) * num_tests):
                    leaf = (leaf << 1) | (1 if flat[base + lin_a[j]] < flat[base + lin_b[j]]
                                          else 0)
                out[i, m] = leaf
            continue
        for m in range(num_ferns):  # near the border: clamp every coordinate
            leaf = 0
            for j in range(num_tests):
                t = j * num_ferns + m
                ya = min(max(y + off_a[t, 0], 0), h - 1)
                xa = min(max(x + off_a[t, 1], 0), w - 1)
                yb = min(max(y + off_b[t, 0], 0), h - 1)
                xb = min(max(x + off_b[t, 1], 0), w - 1)
                leaf = (leaf << 1) | (1 if image[ya, xa] < image[yb, xb] else 0)
            out[i, m] = leaf


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


@compile_once
def compiled_classify_rows() -> Callable[..., None] | None:
    """:func:`_classify_rows` compiled by numba (cached on disk by numba after the first
    compile), or None where numba is not installed."""
    global _fill_unscored, negligible_log_ratio  # the kernel calls compiled helpers by name
    numba = numba_or_none()
    if numba is None:
        return None
    _fill_unscored = numba.njit(cache=True, nogil=True)(_fill_unscored)
    negligible_log_ratio = numba.njit(cache=True, nogil=True)(negligible_log_ratio)
    kernel: Any = numba.njit(cache=True, nogil=True)(_classify_rows)
    return kernel


@functools.cache
def compiled_leaves_at() -> Callable[..., None] | None:
    """:func:`_leaves_at` compiled by numba, or None where numba is not installed."""
    numba = numba_or_none()
    if numba is None:
        return None
    kernel: Any = numba.njit(cache=True, nogil=True)(_leaves_at)
    return kernel
