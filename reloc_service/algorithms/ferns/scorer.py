"""Scoring with a published ferns model (thesis eq. 3.22-3.23): :class:`FernScorer`, an
immutable snapshot of the sparse log corrections, turns the leaves of ``N`` patches into
per-class scores by one sparse product, and into each patch's best classes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from ...core.numeric import top_k
from . import kernels
from .fern_tests import FernTests

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
Leaves = npt.NDArray[np.uint16]

#: Scores held at once while classifying (patches x classes): 256 K float32, 1 MB, which
#: stays in cache.
SCORE_BLOCK_FLOATS = 1 << 18


@dataclass(frozen=True, eq=False)
class FernScorer:
    """An immutable snapshot of a trained model, safe to share between threads: ``log`` (M K,
    C) float32 CSR log corrections, ``const`` (C,) per-class constants, ``class_ids`` (C,)."""

    tests: FernTests
    class_ids: IntArray
    log: sp.csr_matrix
    const: npt.NDArray[np.float32]

    @property
    def num_classes(self) -> int:
        return len(self.class_ids)

    def scores(self, leaves: npt.ArrayLike) -> npt.NDArray[np.float32]:
        """(N, M) leaves -> (N, C) log-likelihoods ``log P(F_1..F_M | c)`` (eq. 3.22 with
        3.23), columns in :attr:`class_ids` order.

        The M visited rows of each patch are gathered (one sparse row index) and read as ONE
        row of N x C with repeated columns, which densifying sums: no sparse product needed."""
        rows = self.tests.rows_of(leaves)
        n, m = rows.shape
        c = self.num_classes
        if n == 0 or c == 0:
            return np.zeros((n, c), np.float32) + self.const[None, :]
        visited = self.log[rows.ravel()]
        summed = sp.csr_matrix((visited.data, visited.indices, visited.indptr[::m]), shape=(n, c))
        out = summed.toarray()  # duplicates add up (csr_todense accumulates)
        out += self.const[None, :]
        return out

    def classify(self, leaves: npt.ArrayLike, *, top_k: int = 1,
                 allowed: npt.NDArray[np.bool_] | None = None
                 ) -> tuple[IntArray, npt.NDArray[np.float32]]:
        """Best ``top_k`` classes of each of N patches: ((N, k) class labels, (N, k)
        posteriors with a uniform prior (eq. 3.19), best first). ``allowed`` (C,) restricts the
        classes (column order of :attr:`class_ids`); rows with no allowed class get
        posterior 0.

        Patches are scored in blocks of about :data:`SCORE_BLOCK_FLOATS` scores: the dense
        N x C matrix of a whole query (tens of MB) would be allocated, page-faulted and
        streamed through memory on every query, and its cost would swing with the state of
        the allocator. With numba (:mod:`.kernels`) each patch is scored and ranked in one
        compiled pass instead: the same scores, posteriors within float32 rounding."""
        return self._classify(leaves, top_k, allowed, compiled=kernels.compiled_classify_rows() is not None)

    def _classify(self, leaves: npt.ArrayLike, top_k: int,
                  allowed: npt.NDArray[np.bool_] | None, *, compiled: bool
                  ) -> tuple[IntArray, npt.NDArray[np.float32]]:
        leaves = np.asarray(leaves)
        n, c = len(leaves), self.num_classes
        k = min(top_k, c)
        labels, posts = np.zeros((n, k), np.int64), np.zeros((n, k), np.float32)
        if k == 0 or n == 0:
            return labels, posts
        if compiled:
            return self._classify_compiled(leaves, k, allowed)
        block = max(1, SCORE_BLOCK_FLOATS // c)
        for start in range(0, n, block):
            rows = slice(start, start + block)
            labels[rows], posts[rows] = self._classify_block(leaves[rows], k, allowed)
        return labels, posts

    def _classify_compiled(self, leaves: npt.NDArray[Any], k: int,
                           allowed: npt.NDArray[np.bool_] | None
                           ) -> tuple[IntArray, npt.NDArray[np.float32]]:
        rows = self.tests.rows_of(leaves)
        mask = (np.zeros(0, bool) if allowed is None
                else np.ascontiguousarray(allowed, dtype=bool))
        if allowed is not None and mask.shape != (self.num_classes,):
            raise ValueError(f"allowed: expected ({self.num_classes},), got {mask.shape}")
        cols = np.empty((len(rows), k), np.int64)
        posts = np.empty((len(rows), k), np.float32)
        kernel = kernels.compiled_classify_rows()
        assert kernel is not None  # _classify calls this only when numba is there
        kernel(rows, self.log.indptr, self.log.indices, self.log.data, self.const, mask,
               allowed is not None, cols, posts)
        return self.class_ids[cols], posts

    def _classify_block(self, leaves: npt.NDArray[Any], k: int,
                        allowed: npt.NDArray[np.bool_] | None
                        ) -> tuple[IntArray, npt.NDArray[np.float32]]:
        s = self.scores(leaves)
        if allowed is not None:
            s[:, ~np.asarray(allowed, bool)] = -np.inf
        top = top_k(s, k)
        top_s = np.take_along_axis(s, top, axis=1)
        # Softmax over all classes, shifted by the best score of each row (in place).
        shift = np.where(np.isfinite(top_s[:, :1]), top_s[:, :1], np.float32(0.0))
        s -= shift
        np.exp(s, out=s)
        norm = s.sum(axis=1, keepdims=True)
        post = np.exp(top_s - shift) / np.maximum(norm, np.float32(1e-30))
        return self.class_ids[top], post.astype(np.float32)

    def predict(self, leaves: npt.ArrayLike) -> IntArray:
        """(N, M) leaves -> (N,) most likely class label (eq. 3.18), -1 with no class."""
        labels, _ = self.classify(leaves, top_k=1)
        return labels[:, 0] if labels.shape[1] else np.full(len(labels), -1, np.int64)
