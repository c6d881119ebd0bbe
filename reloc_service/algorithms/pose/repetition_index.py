"""The nearest two landmarks of a query descriptor among every landmark of a map, at a cost
that does not grow in proportion to the map: an inverted file over the pool's descriptors
(Jegou et al. 2011, IVF; Muja and Lowe 2009, hierarchical k-means with a priority search).

A two-level k-means tree (:class:`~..place.vocabulary.VocabularyTree`, trained on a sample of
the pool) files every pool row under its leaf, about ``leaf_rows`` rows each. A query
descriptor is compared with the rows of its ``leaves`` nearest leaves among the children of
its ``branches`` nearest first-level nodes only: ``(1 + branches) * branching`` centres, where
``branching`` grows as the square root of the pool, and about ``leaves * leaf_rows`` rows,
whatever the pool's size; ``Q`` descriptors scan at most ``Q * leaves`` leaves, one matrix
product each. The search is approximate: a neighbour filed under a leaf not scanned is
missed. Descriptors close enough to be a repetition's (as close to the query as its own
match, within Lowe's ratio) lie near the query and mostly share its leaves. Pools up to
``exact_rows`` rows, whose whole scan is a bounded cost, are scanned in full (exact).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core import features as feature_lib
from ...core.background import stop_if
from ..place.vocabulary import VocabularyTree, pairwise_distances
from . import repetition_kernels

IntArray = npt.NDArray[np.int64]

#: Rows filed at a time (bounds the float32 copy of SIFT rows, the XOR of ORB's).
_FILE_CHUNK = 16384


@dataclass(frozen=True)
class IndexConf:
    """How the pool is indexed and searched."""

    #: Pools of at most this many rows are scanned in full (exact): the check's 300 query
    #: descriptors against 20k SIFT rows take about 0.1 s, a bounded cost.
    exact_rows: int = 20000
    #: Rows per leaf the tree is sized for (leaves = rows / leaf_rows, two levels).
    leaf_rows: int = 256
    #: First-level nodes whose children are ranked for each query descriptor ...
    branches: int = 4
    #: ... and the nearest of those children (leaves) scanned.
    leaves: int = 12
    #: Training sample per leaf (k-means runs on at most ``sample_per_leaf * leaves`` rows).
    sample_per_leaf: int = 32
    #: Lloyd iterations per k-means node.
    iterations: int = 3

    def __post_init__(self) -> None:
        if self.exact_rows < 0 or self.leaf_rows < 2 or self.branches < 1 or self.leaves < 1:
            raise ValueError(f"repetition index: expected exact_rows >= 0, leaf_rows >= 2, "
                             f"branches >= 1 and leaves >= 1, got {self.exact_rows}, "
                             f"{self.leaf_rows}, {self.branches}, {self.leaves}")


@dataclass(frozen=True, eq=False)
class RepetitionIndex:
    """Pool rows filed by leaf: ``order`` (N,) the pool rows leaf by leaf, ``offsets``
    (leaves + 1,) where each leaf's rows start in ``order``; ``tree`` None when the pool is
    scanned in full. ``descriptors`` (N, D) are the pool's own (not copied)."""

    descriptors: npt.NDArray[Any]
    tree: VocabularyTree | None
    order: npt.NDArray[np.int32]
    offsets: npt.NDArray[np.int64]
    branches: int
    leaves: int

    @classmethod
    def build(cls, descriptors: npt.NDArray[Any], conf: IndexConf = IndexConf(), *,
              seed: int = 0, cancelled: Callable[[], bool] | None = None) -> RepetitionIndex:
        """The index of pool ``descriptors`` (N, D) (uint8 SIFT or packed ORB bits);
        :class:`~reloc_service.core.errors.Cancelled` once ``cancelled()`` is true, checked
        before the tree is built and before each chunk of rows is filed under it."""
        empty32, empty64 = np.zeros(0, np.int32), np.zeros(1, np.int64)
        if len(descriptors) <= max(conf.exact_rows, conf.leaf_rows):
            return cls(descriptors, None, empty32, empty64, conf.branches, conf.leaves)
        branching = math.ceil(math.sqrt(len(descriptors) / conf.leaf_rows))
        stop_if(cancelled)
        rng = np.random.default_rng(seed)
        size = min(len(descriptors), conf.sample_per_leaf * branching * branching)
        sample = descriptors[np.sort(rng.choice(len(descriptors), size, replace=False))]
        tree = VocabularyTree.build(sample, branching=branching, depth=2,
                                    iterations=conf.iterations, rng=rng)
        filed = []
        for s in range(0, len(descriptors), _FILE_CHUNK):
            stop_if(cancelled)
            filed.append(_leaves_of(tree, descriptors[s:s + _FILE_CHUNK]))
        words = np.concatenate(filed)
        order = np.argsort(words, kind="stable").astype(np.int32)
        offsets = np.concatenate([[0], np.cumsum(np.bincount(words, minlength=tree.n_words))])
        return cls(descriptors, tree, order, offsets.astype(np.int64), conf.branches,
                   conf.leaves)

    @property
    def nbytes(self) -> int:
        """Bytes the index adds to its pool (the tree, the filing)."""
        tree = 0 if self.tree is None else sum(c.nbytes for c in self.tree.centres) + sum(
            c.nbytes for c in self.tree.children)
        return tree + self.order.nbytes + self.offsets.nbytes

    def nearest_two(self, desc: npt.NDArray[Any]
                    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int64]]:
        """(Q, 2) distances and (Q, 2) pool rows of the two nearest pool descriptors found
        for each of ``desc`` (Q, D), as :func:`~reloc_service.core.features.nearest_two`
        measures them; ``inf`` and -1 where fewer than two were found."""
        if self.tree is None:
            return _two_nearest(desc, self.descriptors)
        leaves = self._probe(desc)
        scanned = self._scan_compiled(desc, leaves)
        if scanned is not None:
            return scanned
        q = np.repeat(np.arange(len(desc)), leaves.shape[1])
        leaf = leaves.ravel()
        by_leaf = np.argsort(leaf, kind="stable")
        q, leaf = q[by_leaf], leaf[by_leaf]
        starts = np.flatnonzero(np.diff(leaf, prepend=-1))
        found_q, found_d, found_i = [], [], []
        # One scan per probed leaf, of every query descriptor probing it (a loop over the
        # leaves, ``leaves`` per descriptor, not over descriptors); each leaf's two nearest
        # are kept in scan order and the two nearest overall picked once at the end.
        for start, stop in zip(starts, np.append(starts[1:], len(leaf)), strict=True):
            lo, hi = self.offsets[leaf[start]], self.offsets[leaf[start] + 1]
            if hi == lo:
                continue
            rows = self.order[lo:hi].astype(np.int64)
            qs = q[start:stop]
            d, i = _two_nearest(desc[qs], self.descriptors[rows])
            found_q.append(np.repeat(qs, 2))
            found_d.append(d.ravel())
            found_i.append(np.where(i >= 0, rows[np.maximum(i, 0)], -1).ravel())
        if not found_q:
            return (np.full((len(desc), 2), np.inf, np.float32),
                    np.full((len(desc), 2), -1, np.int64))
        return _two_smallest(len(desc), np.concatenate(found_q), np.concatenate(found_d),
                             np.concatenate(found_i))

    def _scan_compiled(self, desc: npt.NDArray[Any], leaves: npt.NDArray[np.int64]
                       ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int64]] | None:
        """:meth:`nearest_two`'s scan of the probed ``leaves`` (Q, leaves) in one compiled
        pass (:mod:`.repetition_kernels`, the same distances and rows), where numba is
        installed and both sides are uint8 SIFT or ORB's whole 64-bit words; else None."""
        kernels = repetition_kernels.compiled()
        pool = self.descriptors
        if kernels is None or desc.dtype != np.uint8 or pool.dtype != np.uint8 or (
                desc.shape[1:] != pool.shape[1:]):
            return None
        binary = feature_lib.is_binary_descriptor(desc)
        if binary and desc.shape[1] % 8:
            return None
        out_d = np.full((len(desc), 2), np.inf, np.float32)
        out_i = np.full((len(desc), 2), -1, np.int64)
        # (descriptor, leaf) pairs by ascending leaf: each descriptor meets its leaves in the
        # order the numpy path files the candidates in, which decides ties.
        q = np.repeat(np.arange(len(desc), dtype=np.int64), leaves.shape[1])
        leaf = leaves.ravel()
        by_leaf = np.argsort(leaf, kind="stable")
        q, leaf = q[by_leaf], leaf[by_leaf]
        probed = leaf >= 0
        q, leaf = np.ascontiguousarray(q[probed]), np.ascontiguousarray(leaf[probed])
        if binary:
            kernels.leaf_nearest_two_hamming(
                np.ascontiguousarray(desc).view(np.uint64),
                np.ascontiguousarray(pool).view(np.uint64), self.order, self.offsets, q, leaf,
                out_d, out_i)
        else:
            kernels.leaf_nearest_two_l2(np.ascontiguousarray(desc), np.ascontiguousarray(pool),
                                        self.order, self.offsets, q, leaf, out_d, out_i)
        return out_d, out_i

    def scanned_rows(self, desc: npt.NDArray[Any]) -> npt.NDArray[np.int64]:
        """(Q,) pool rows :meth:`nearest_two` compares each of ``desc`` (Q, D) with: the
        per-query cost, every row when the pool is scanned in full."""
        if self.tree is None:
            return np.full(len(desc), len(self.descriptors), np.int64)
        leaves = self._probe(desc)
        sizes = np.diff(self.offsets)[np.maximum(leaves, 0)]
        return np.where(leaves >= 0, sizes, 0).sum(axis=1).astype(np.int64)

    def _probe(self, desc: npt.NDArray[Any]) -> npt.NDArray[np.int64]:
        """(Q, leaves) leaves to scan for each of ``desc``: the nearest ``leaves`` leaf
        centres among the children of its ``branches`` nearest first-level nodes (a priority
        search: a near leaf under the second-best node beats a far one under the best); -1
        for unused slots."""
        assert self.tree is not None
        x = desc if feature_lib.is_binary_descriptor(desc) else desc.astype(np.float32)
        top, kids = self.tree.centres[0][0], self.tree.children[0][0]
        first = _nearest_slots(x, top[None, None], kids[None, None] >= 0, self.branches)[:, 0]
        nodes = np.maximum(kids[first], 0)                                      # (Q, b)
        children = np.where((kids[first] >= 0)[:, :, None], self.tree.children[1][nodes], -1)
        centres = self.tree.centres[1][nodes].reshape(len(desc), 1, -1, x.shape[1])
        leaves = children.reshape(len(desc), 1, -1)
        slots = _nearest_slots(x, centres, leaves >= 0, self.leaves)[:, 0]       # (Q, l)
        return np.take_along_axis(leaves[:, 0], slots, axis=1).astype(np.int64)

def _leaves_of(tree: VocabularyTree, descriptors: npt.NDArray[Any]) -> npt.NDArray[np.int32]:
    """(N,) leaf of each of ``descriptors`` (N, D) in the two-level ``tree``: its nearest
    first-level centre's nearest child, as :meth:`VocabularyTree.quantise` finds it, but in
    one matrix product per first-level node (that traversal gathers each row's candidate
    centres, ten times slower on a pool)."""
    x = descriptors if feature_lib.is_binary_descriptor(descriptors) else (
        descriptors.astype(np.float32))
    kids = tree.children[0][0]
    node = kids[np.argmin(_to_centres(x, tree.centres[0][0], kids >= 0), axis=1)]
    leaves = np.empty(len(x), np.int32)
    for n in np.unique(node):
        members = np.flatnonzero(node == n)
        children = tree.children[1][n]
        leaves[members] = children[np.argmin(_to_centres(x[members], tree.centres[1][n],
                                                         children >= 0), axis=1)]
    return leaves


def _to_centres(x: npt.NDArray[Any], centres: npt.NDArray[Any], valid: npt.NDArray[np.bool_]
                ) -> npt.NDArray[np.float32]:
    """(N, k) distances from rows ``x`` (N, D) to ``centres`` (k, D) as the vocabulary
    measures them (:func:`..place.vocabulary.pairwise_distances`); ``inf`` at the slots not
    ``valid`` (k,)."""
    out = pairwise_distances(x, centres)
    out[:, ~valid] = np.inf
    return out


def _nearest_slots(x: npt.NDArray[Any], centres: npt.NDArray[Any],
                   valid: npt.NDArray[np.bool_], count: int) -> npt.NDArray[np.int64]:
    """(Q, n, count) indices of the ``count`` nearest of ``centres`` (broadcast to (Q, n, k,
    D)) to each row of ``x`` (Q, D) along the k axis; slots not ``valid`` (broadcast to
    (Q, n, k)) come last."""
    c = np.broadcast_to(centres, (len(x), *centres.shape[1:]))
    if feature_lib.is_binary_descriptor(x):
        dist = np.bitwise_count(c ^ x[:, None, None, :]).sum(-1, dtype=np.int32)
        dist = dist.astype(np.float32)
    else:
        # |c|^2 - 2 c.x: |x|^2 is common to every centre and does not change the order.
        dist = (np.einsum("qnkd,qnkd->qnk", c, c) - 2.0 * np.einsum("qnkd,qd->qnk", c, x)
                ).astype(np.float32)
    dist[~np.broadcast_to(valid, dist.shape)] = np.inf
    return np.argsort(dist, axis=-1, kind="stable")[..., :count].astype(np.int64)


def _two_nearest(desc: npt.NDArray[Any], train: npt.NDArray[Any]
                 ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int64]]:
    """:func:`~reloc_service.core.features.nearest_two`, also for fewer than two ``train``
    rows (``inf`` and -1 in the slots without one)."""
    if len(train) >= 2:
        d, i = feature_lib.nearest_two(desc, train)
        return d.astype(np.float32), i.astype(np.int64)
    dist = np.full((len(desc), 2), np.inf, np.float32)
    rows = np.full((len(desc), 2), -1, np.int64)
    if len(train) == 1:
        dist[:, 0] = feature_lib.descriptor_distance(desc, np.repeat(train, len(desc), axis=0))
        rows[:, 0] = 0
    return dist, rows


def _two_smallest(count: int, q: IntArray, d: npt.NDArray[np.float32], i: IntArray
                  ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int64]]:
    """(count, 2) the two smallest distances ``d`` (K,) found for each query row ``q`` (K,)
    and their pool rows ``i`` (K,), a tie going to the candidate found first (the order of
    the arrays); ``inf`` and -1 where fewer than two were found. Candidates without a row
    (``inf``, -1) are dropped."""
    best_d = np.full((count, 2), np.inf, np.float32)
    best_i = np.full((count, 2), -1, np.int64)
    real = np.flatnonzero(i >= 0)
    order = real[np.lexsort((real, d[real], q[real]))]  # by query, distance, then arrival
    qs = q[order]
    rank = np.arange(len(order)) - np.searchsorted(qs, qs, side="left")
    top = rank < 2
    best_d[qs[top], rank[top]] = d[order[top]]
    best_i[qs[top], rank[top]] = i[order[top]]
    return best_d, best_i
