"""Small numeric helpers shared by the algorithms: zero-mean NCC, top-k selection, the
switch of the optional compiled kernels, and the thread count of the BLAS NumPy and SciPy use."""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

IntArray = npt.NDArray[np.int64]

#: Up to this k, top-k takes k argmax passes over each row (cheaper than a partition or a sort
#: of every row, and ties naturally go to the lower index).
_ARGMAX_PASSES_UP_TO = 4


def zncc(a: npt.ArrayLike, b: npt.ArrayLike, mask: npt.ArrayLike | None = None, *,
         flat: float = 0.0) -> float:
    """Zero-mean normalised cross-correlation of two same-shape images (over ``mask`` if
    given), in [-1, 1].

    A constant image (or an empty mask) has no correlation to measure; the answer is then
    ``flat``: 0.0 by default (uncorrelated), -1.0 where a caller ranks candidates by NCC and
    a flat image must never beat a real alignment (ESM)."""
    x = np.asarray(a, dtype=np.float64)
    y = np.asarray(b, dtype=np.float64)
    if mask is None:
        x, y = x.ravel(), y.ravel()
    else:
        keep = np.asarray(mask, dtype=bool)
        x, y = x[keep], y[keep]
    if len(x) == 0:
        return flat
    x = x - x.mean()
    y = y - y.mean()
    denom = float(np.sqrt((x @ x) * (y @ y)))
    return float(x @ y) / denom if denom > 1e-12 else flat


def top_k(scores: npt.ArrayLike, k: int, *, keep: npt.ArrayLike | None = None,
          tiebreak: npt.ArrayLike | None = None) -> IntArray:
    """Indices of the ``k`` largest scores, best first; equal scores go to the lower index.

    ``scores`` (C,) gives (min(k, kept),) indices into it: only entries where ``keep`` (C,)
    is true count, and ties go to the lower ``tiebreak`` (C,) value (e.g. keyframe ids)
    instead of the lower index. ``scores`` (N, C) gives (N, min(k, C)) column indices of
    each row (``keep`` and ``tiebreak`` are for 1-D scores only); a (N, C) float array is
    used as scratch space and restored, so pass a copy if another thread reads it."""
    s = np.asarray(scores)
    if s.ndim == 2:
        if keep is not None or tiebreak is not None:
            raise ValueError("top_k: keep and tiebreak apply to 1-D scores, got (N, C) scores")
        return _top_k_rows(s, min(k, s.shape[1]))
    if s.ndim != 1:
        raise ValueError(f"top_k: expected (C,) or (N, C) scores, got shape {s.shape}")
    cols = np.arange(len(s)) if keep is None else np.flatnonzero(keep)
    if tiebreak is not None:
        cols = cols[np.argsort(np.asarray(tiebreak)[cols], kind="stable")]
    if k <= 0 or len(cols) == 0:
        return np.zeros(0, np.int64)
    return cols[_top_k_rows(s[cols][None, :], min(k, len(cols)))[0]]


def _top_k_rows(scores: npt.NDArray[np.floating], k: int) -> IntArray:
    """(N, k) column indices of the k largest scores of each row, largest first, ties to the
    lower column. Modifies ``scores`` while it runs and restores it."""
    n = len(scores)
    if k <= 0:
        return np.zeros((n, 0), np.int64)
    if k > _ARGMAX_PASSES_UP_TO:
        return np.argsort(-scores, axis=1, kind="stable")[:, :k].astype(np.int64)
    out = np.empty((n, k), np.int64)
    rows = np.arange(n)
    saved = []
    for j in range(k):
        out[:, j] = scores.argmax(axis=1)
        saved.append(scores[rows, out[:, j]].copy())
        scores[rows, out[:, j]] = -np.inf
    for j in reversed(range(k)):
        scores[rows, out[:, j]] = saved[j]
    # A row whose remaining scores are all -inf would repeat a column: sort those rows instead.
    exhausted = np.flatnonzero(np.isneginf(saved[-1]))
    if len(exhausted):
        out[exhausted] = np.argsort(-scores[exhausted], axis=1, kind="stable")[:, :k]
    return out


def first_occurrences(values: npt.NDArray[np.int64]) -> IntArray:
    """(U,) ascending indices of the first occurrence of each distinct value of ``values``
    (N,): ``np.sort(np.unique(values, return_index=True)[1])``. One compiled pass over a hash
    table where numba is installed (:func:`_first_in_table`), where ``np.unique`` sorts:
    pooling the landmarks of a dozen keyframes (10 000 ids) spent 1.7 of its 3 ms there."""
    values = np.ascontiguousarray(values, np.int64)
    kernel = _first_occurrence_kernel()
    if kernel is None or len(values) == 0:
        return np.sort(np.unique(values, return_index=True)[1]).astype(np.int64)
    bits = max(4, (2 * len(values)).bit_length())   # more than 2N slots: at most half full
    first = np.empty(len(values), np.int64)
    count = kernel(values, np.zeros(1 << bits, np.int64), bits, first)
    return first[:count]


def _first_in_table(values: npt.NDArray[np.int64], table: npt.NDArray[np.int64], bits: int,
                    first: npt.NDArray[np.int64]) -> int:
    """Indices of the first occurrences of ``values`` into ``first``, in order; their count.
    ``table`` (2 ** ``bits``, zeros) holds 1 + the index of each distinct value seen so far,
    at the slot Fibonacci hashing gives its value, probing linearly."""
    mask = np.int64((1 << bits) - 1)
    shift = np.uint64(64 - bits)
    golden = np.uint64(0x9E3779B97F4A7C15)
    count = 0
    for i in range(values.shape[0]):
        v = values[i]
        slot = np.int64((np.uint64(v) * golden) >> shift)
        while True:
            held = table[slot]
            if held == 0:
                table[slot] = i + 1
                first[count] = i
                count += 1
                break
            if values[held - 1] == v:
                break
            slot = np.int64((slot + 1) & mask)
    return count


@functools.cache
def _first_occurrence_kernel() -> Any:
    """:func:`_first_in_table` compiled by numba (cached on disk), or None without numba."""
    numba = numba_or_none()
    if numba is None:
        return None
    return numba.njit(cache=True, nogil=True)(_first_in_table)


_T = TypeVar("_T")


def compile_once(make: Callable[[], _T]) -> Callable[[], _T]:
    """``make`` run once, its result kept, like ``functools.cache`` but under a lock: a
    kernel factory that rebinds module helpers to their compiled form (``helper =
    numba.njit(...)(helper)``) must not run twice at once. A service warms its kernels on
    a thread of its own while its first query may ask for them; two concurrent first calls
    under ``functools.cache`` both run the factory, and the second one's ``njit`` of an
    already compiled helper raises (numba: "A jit decorator was called on an already jitted
    function")."""
    lock = threading.Lock()
    made: list[_T] = []

    @functools.wraps(make)
    def once() -> _T:
        if not made:
            with lock:
                if not made:
                    made.append(make())
        return made[0]

    return once


def numba_or_none() -> Any:
    """The numba module where the optional ``[jit]`` extra is installed, else None: the one
    switch of every compiled kernel (each caller keeps its numpy path for None). Imported on
    first use: numba and LLVM cost about half a second and tens of MB."""
    try:
        import numba
    except ImportError:
        return None
    return numba


def limit_blas_threads(threads: int) -> list[int]:
    """Have every BLAS loaded in this process (NumPy's, SciPy's, OpenCV's OpenBLAS) use
    ``threads`` threads (0: leave them as they are); returns the counts they now use.

    reloc's matrix products are small (6x6 normal equations, descriptor distances of one
    query), so a query gains little from BLAS threads, while a BLAS thread that keeps spinning
    after a product takes the core that another worker, or a query's own helper thread
    (:mod:`.relocalizers.overlap`), would use: workers and the benchmark run with one, as
    they run OpenCV with one. Call it after the modules that load a BLAS are imported (a BLAS
    loaded later keeps its own default)."""
    from threadpoolctl import threadpool_info, threadpool_limits

    if threads < 0:
        raise ValueError(f"BLAS threads: expected 0 (the default) or a positive count, "
                         f"got {threads}")
    if threads:
        threadpool_limits(limits=threads, user_api="blas")
    return [int(lib["num_threads"]) for lib in threadpool_info() if lib["user_api"] == "blas"]
