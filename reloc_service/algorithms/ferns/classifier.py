"""Random ferns classifier with sparse counts (thesis 3.2, eq. 3.17-3.23; Ozuysal et al. 2010).

A fern is ``S`` binary pixel comparisons on a patch (eq. 3.17); its ``S`` bits form a leaf
index ``k`` in ``[0, K)``, ``K = 2^S``. Training counts ``N[k, c]`` (samples of class ``c``
reaching leaf ``k``) per fern and ``N[c]`` (samples of class ``c``); a patch scores, per class,
the semi-naive Bayes log-likelihood (eq. 3.22 with 3.23)::

    score[c] = sum_m log((N_m[k_m, c] + Nr) / (N[c] + K Nr))
             = M log(Nr / (N[c] + K Nr))  +  sum_m log((N_m[k_m, c] + Nr) / Nr)

The first term is a constant per class; the second is non-zero only where ``N_m[k_m, c] > 0``.
Almost every (leaf, class) count is zero, so the model is sparse: a CSR matrix with rows
``(fern, leaf)`` flattened (``m K + k``), columns = classes, holding the float32 log
corrections ``log(1 + N / Nr)`` of the non-zero counts (8 bytes per non-zero: a float32 and an
int32 column). Memory and time grow with the training samples, not with ``M K C`` (the dense
table of the thesis: 78 MB for 200 classes). Scoring ``N`` patches is one sparse product: an
``(N, M K)`` indicator of the visited leaves times that matrix.

The counts are not stored twice: ``N = Nr expm1(correction)`` recovers them exactly (float32
keeps 24 bits: exact for every count below 2^20, and a class may not have more samples than
that). So counts stay exact integers, and removing samples that were added (the same leaves,
the same classes) gives back exactly the previous model. Updates are buffered as integer deltas
and merged lazily; :meth:`FernClassifier.scorer` publishes an immutable snapshot for readers.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from .fern_tests import FernConf, FernTests
from .scorer import FernScorer

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Most samples of one class: counts up to this round-trip exactly through float32 logs.
MAX_CLASS_SAMPLES = 1 << 20
#: Buffered (fern, leaf, class) increments merged into the model beyond this many.
_FLUSH_ENTRIES = 8_000_000


class _LogCodec:
    """Counts <-> float32 ``log(1 + N / Nr)`` through a table (exact, and much faster than
    float64 transcendental functions over millions of entries)."""

    def __init__(self, regularization: float) -> None:
        self.nr = regularization
        self.table = np.zeros(0, np.float32)

    def _ensure(self, max_count: int) -> None:
        if len(self.table) > max_count:
            return
        size = max(1024, 2 * max_count + 1)
        table = np.log1p(np.arange(size, dtype=np.float64) / self.nr).astype(np.float32)
        if np.any(np.diff(table) <= 0):
            raise ValueError(f"regularization {self.nr} too small: counts up to {size} are not "
                             "distinct in float32")
        self.table = table

    def encode(self, counts: npt.NDArray[np.integer]) -> npt.NDArray[np.float32]:
        self._ensure(int(counts.max(initial=0)))
        return self.table[counts]

    def decode(self, values: npt.NDArray[np.float32]) -> npt.NDArray[np.int32]:
        """Exact counts of encoded ``values``."""
        if len(values) == 0:
            return np.zeros(0, np.int32)
        self._ensure(int(np.rint(self.nr * np.expm1(float(values.max())))) + 1)
        guess = np.rint(np.float32(self.nr) * np.expm1(values)).astype(np.int64)
        np.clip(guess, 0, len(self.table) - 1, out=guess)
        wrong = self.table[guess] != values  # float32 expm1 is off by one on rare large counts
        if wrong.any():
            guess[wrong] = np.searchsorted(self.table, values[wrong])
        return guess.astype(np.int32)


class FernClassifier(FernTests):
    """Ferns with sparse per-class counts that can be added and removed (module docstring).

    Classes are arbitrary int64 labels (landmark ids); internally each has a column. Not
    thread-safe for writers; readers take a :meth:`scorer` snapshot.
    """

    def __init__(self, conf: FernConf | None = None) -> None:
        super().__init__(conf or FernConf())
        self._class_ids = np.zeros(0, np.int64)
        self._class_counts = np.zeros(0, np.int64)
        self._column: dict[int, int] = {}
        self._codec = _LogCodec(self.conf.regularization)
        self._log = sp.csr_matrix((self.num_rows, 0), dtype=np.float32)
        self._pending: list[tuple[npt.NDArray[Any], npt.NDArray[Any], int]] = []
        self._pending_entries = 0
        self._scorer: FernScorer | None = None

    # -- queries -----------------------------------------------------------------------------
    @property
    def class_ids(self) -> IntArray:
        """(C,) labels of the classes with at least one sample, in column order."""
        self._flush()
        return self._class_ids.copy()

    @property
    def class_counts(self) -> IntArray:
        """(C,) N[c], the number of training samples of each class (column order)."""
        self._flush()
        return self._class_counts.copy()

    @property
    def num_classes(self) -> int:
        self._flush()
        return len(self._class_ids)

    @property
    def nnz(self) -> int:
        """Number of non-zero (fern, leaf, class) counts."""
        self._flush()
        return int(self._log.nnz)

    def nbytes(self) -> int:
        """Bytes held by the model: sparse log corrections, class arrays, constants, tests."""
        sc = self.scorer()
        total = sc.log.data.nbytes + sc.log.indices.nbytes + sc.log.indptr.nbytes
        total += self._class_ids.nbytes + self._class_counts.nbytes + sc.const.nbytes
        return int(total + self.off_a.nbytes + self.off_b.nbytes)

    def dense_nbytes(self, num_classes: int | None = None) -> int:
        """Bytes of the dense float32 table M x 2^S x C the thesis stores (section 3.2)."""
        c = self.num_classes if num_classes is None else num_classes
        return int(self.num_rows) * int(c) * 4

    def scorer(self) -> FernScorer:
        """The current model as an immutable :class:`FernScorer` (cached until an update)."""
        self._flush()
        if self._scorer is None:
            nr, m, k = self.conf.regularization, self.num_ferns, self.num_leaves
            const = (m * (np.log(nr) - np.log(self._class_counts + k * nr))).astype(np.float32)
            self._scorer = FernScorer(self, self._class_ids.copy(), self._log, const)
        return self._scorer

    def scores(self, leaves: npt.ArrayLike) -> npt.NDArray[np.float32]:
        """See :meth:`FernScorer.scores`."""
        return self.scorer().scores(leaves)

    def classify(self, leaves: npt.ArrayLike, *, top_k: int = 1,
                 allowed: npt.NDArray[np.bool_] | None = None
                 ) -> tuple[IntArray, npt.NDArray[np.float32]]:
        """See :meth:`FernScorer.classify`."""
        return self.scorer().classify(leaves, top_k=top_k, allowed=allowed)

    def predict(self, leaves: npt.ArrayLike) -> IntArray:
        """See :meth:`FernScorer.predict`."""
        return self.scorer().predict(leaves)

    # -- training ----------------------------------------------------------------------------
    def add(self, leaves: npt.ArrayLike, labels: npt.ArrayLike) -> None:
        """Count samples: ``leaves`` (N, M) of patches of classes ``labels`` (N,) int64."""
        self._update(leaves, labels, +1)

    def remove(self, leaves: npt.ArrayLike, labels: npt.ArrayLike) -> None:
        """Uncount samples previously given to :meth:`add` (the same leaves and labels)."""
        self._update(leaves, labels, -1)

    def _update(self, leaves: npt.ArrayLike, labels: npt.ArrayLike, sign: int) -> None:
        lab = np.asarray(labels, dtype=np.int64).ravel()
        rows = self.rows_of(leaves)
        if len(rows) != len(lab):
            raise ValueError(f"leaves: expected ({len(lab)}, {self.num_ferns}), got {rows.shape}")
        if len(lab) == 0:
            return
        cols = self._columns_for(lab, create=sign > 0)
        counts = self._class_counts + sign * np.bincount(cols, minlength=len(self._class_counts))
        if counts.min(initial=0) < 0:
            raise ValueError("remove: more samples removed than were added for some class")
        if counts.max(initial=0) > MAX_CLASS_SAMPLES:
            raise ValueError(f"a class may have at most {MAX_CLASS_SAMPLES} samples")
        self._class_counts = counts
        index_type = np.int32 if self.num_rows < 2**31 else np.int64
        self._pending.append((rows.ravel().astype(index_type),
                              np.repeat(cols.astype(np.int32), self.num_ferns), sign))
        self._pending_entries += rows.size
        self._scorer = None
        if self._pending_entries > _FLUSH_ENTRIES:
            self._flush()

    def _columns_for(self, labels: IntArray, *, create: bool) -> IntArray:
        """Column of each label; new labels get new columns (only when adding)."""
        uniq, inverse = np.unique(labels, return_inverse=True)
        cols = np.empty(len(uniq), np.int64)
        new: list[int] = []
        for i, lab in enumerate(uniq.tolist()):  # one step per distinct class, not per sample
            col = self._column.get(lab)
            if col is None:
                if not create:
                    raise ValueError(f"remove: class {lab} has no samples")
                col = len(self._class_ids) + len(new)
                self._column[lab] = col
                new.append(lab)
            cols[i] = col
        if new:
            self._class_ids = np.concatenate([self._class_ids, np.asarray(new, np.int64)])
            self._class_counts = np.concatenate([self._class_counts, np.zeros(len(new), np.int64)])
        return cols[inverse]

    def _flush(self) -> None:
        """Merge buffered updates into the sparse model; drop classes left without samples."""
        if not self._pending:
            return
        num_cols = len(self._class_ids)
        rows = np.concatenate([p[0] for p in self._pending])
        cols = np.concatenate([p[1] for p in self._pending])
        vals = np.concatenate([np.full(len(p[0]), p[2], np.int32) for p in self._pending])
        self._pending, self._pending_entries = [], 0
        delta = sp.csr_matrix((vals, (rows, cols)), shape=(self.num_rows, num_cols), dtype=np.int32)
        del rows, cols, vals
        counts = self._count_matrix(num_cols) + delta  # both canonical: a linear merge
        counts.eliminate_zeros()
        if counts.nnz and counts.data.min() < 0:
            raise ValueError("remove: a (leaf, class) count went negative; samples removed "
                             "were not the ones added")
        self._log = self._encode(self._drop_empty_classes(counts))

    def _count_matrix(self, num_cols: int | None = None) -> sp.csr_matrix:
        """The exact integer counts N[m K + k, c] (int32 CSR) decoded from the model."""
        lg = self._log
        data = self._codec.decode(lg.data)
        return sp.csr_matrix((data, lg.indices, lg.indptr),
                             shape=(self.num_rows, lg.shape[1] if num_cols is None else num_cols))

    def _encode(self, counts: sp.csr_matrix) -> sp.csr_matrix:
        """Integer counts -> float32 log corrections log(1 + N / Nr), same structure."""
        return sp.csr_matrix((self._codec.encode(counts.data), counts.indices, counts.indptr),
                             shape=counts.shape)

    def _drop_empty_classes(self, counts: sp.csr_matrix) -> sp.csr_matrix:
        keep = self._class_counts > 0
        if keep.all():
            return counts
        remap = np.cumsum(keep) - 1
        # A class with N[c] = 0 has no non-zero count left (each sample counts once per fern).
        counts = sp.csr_matrix((counts.data, remap[counts.indices].astype(counts.indices.dtype),
                                counts.indptr), shape=(self.num_rows, int(keep.sum())))
        self._class_ids = self._class_ids[keep]
        self._class_counts = self._class_counts[keep]
        self._column = {int(lab): i for i, lab in enumerate(self._class_ids.tolist())}
        return counts

    # -- derived models and persistence ------------------------------------------------------
    def _derived(self, conf: FernConf, off_a: IntArray, off_b: IntArray) -> FernClassifier:
        sub = FernClassifier.__new__(FernClassifier)
        FernTests.__init__(sub, conf, off_a, off_b)
        sub._class_ids = self._class_ids.copy()
        sub._class_counts = self._class_counts.copy()
        sub._column = dict(self._column)
        sub._pending, sub._pending_entries, sub._scorer = [], 0, None
        sub._codec = self._codec  # the same regularization
        return sub

    def first_ferns(self, num_ferns: int) -> FernClassifier:
        """A classifier made of this one's first ``num_ferns`` ferns and their counts (ferns
        are independent draws, so this is an M = ``num_ferns`` classifier)."""
        self._flush()
        if not 1 <= num_ferns <= self.num_ferns:
            raise ValueError(f"num_ferns must be in [1, {self.num_ferns}], got {num_ferns}")
        conf = FernConf(num_ferns, self.num_tests, self.conf.patch_size,
                        self.conf.regularization, self.conf.seed)
        idx = (np.arange(self.num_tests)[:, None] * self.num_ferns + np.arange(num_ferns)).ravel()
        sub = self._derived(conf, self.off_a[idx], self.off_b[idx])
        sub._log = self._log[: num_ferns * self.num_leaves].tocsr()
        return sub

    def first_tests(self, num_tests: int) -> FernClassifier:
        """A classifier whose ferns are the first ``num_tests`` tests of this one's (the top
        bits of a leaf), with the counts of the leaves sharing those bits summed."""
        self._flush()
        if not 1 <= num_tests <= self.num_tests:
            raise ValueError(f"num_tests must be in [1, {self.num_tests}], got {num_tests}")
        conf = FernConf(self.num_ferns, num_tests, self.conf.patch_size,
                        self.conf.regularization, self.conf.seed)
        n = num_tests * self.num_ferns
        sub = self._derived(conf, self.off_a[:n], self.off_b[:n])
        fern, leaf = np.divmod(np.arange(self.num_rows), self.num_leaves)
        new_rows = fern * sub.num_leaves + (leaf >> (self.num_tests - num_tests))
        merge = sp.csr_matrix((np.ones(self.num_rows, np.int32),
                               (new_rows, np.arange(self.num_rows))),
                              shape=(sub.num_rows, self.num_rows))
        counts = (merge @ self._count_matrix()).tocsr()
        counts.sort_indices()
        sub._log = sub._encode(counts)
        return sub

    def subset(self, labels: npt.ArrayLike) -> FernClassifier:
        """A classifier of only the classes ``labels`` (those this one knows), same ferns."""
        self._flush()
        keep = np.flatnonzero(np.isin(self._class_ids, np.asarray(labels, np.int64)))
        sub = self._derived(self.conf, self.off_a, self.off_b)
        sub._class_ids, sub._class_counts = self._class_ids[keep], self._class_counts[keep]
        sub._column = {int(lab): i for i, lab in enumerate(sub._class_ids.tolist())}
        sub._log = self._log[:, keep].tocsr()
        sub._log.sort_indices()
        return sub

    def count_table(self) -> tuple[IntArray, IntArray, IntArray, IntArray]:
        """Every non-zero count as (fern, leaf, class label, N[k, c]) int64 arrays, sorted by
        (fern, leaf, class label): a canonical form to compare two models."""
        self._flush()
        c = self._count_matrix().tocoo()
        fern, leaf = np.divmod(c.row.astype(np.int64), self.num_leaves)
        label = self._class_ids[c.col]
        order = np.lexsort((label, leaf, fern))
        return fern[order], leaf[order], label[order], c.data.astype(np.int64)[order]

    def to_arrays(self) -> dict[str, npt.NDArray[Any]]:
        """The model as plain arrays (tests, classes, CSR counts) for ``np.savez``: counts,
        class columns and row offsets each in the smallest unsigned type that holds them
        (class columns below a region's 1-2 thousand classes: 2 bytes, not 4; offsets below
        2^32: 4 bytes, not 8), exactly; :meth:`from_arrays` widens them back."""
        self._flush()
        c = self._count_matrix()
        return {"off_a": self.off_a, "off_b": self.off_b, "class_ids": self._class_ids,
                "class_counts": self._class_counts, "indptr": _narrowest(c.indptr),
                "indices": _narrowest(c.indices, len(self._class_ids)),
                "counts": _narrowest(c.data)}

    @classmethod
    def from_arrays(cls, conf: FernConf, arrays: dict[str, npt.NDArray[Any]]) -> FernClassifier:
        """Inverse of :meth:`to_arrays`; ValueError if the arrays do not fit ``conf``."""
        clf = cls(conf)
        if not (np.array_equal(clf.off_a, arrays["off_a"])
                and np.array_equal(clf.off_b, arrays["off_b"])):
            raise ValueError("saved fern tests differ from those drawn by the configuration")
        ids = np.asarray(arrays["class_ids"], np.int64)
        class_counts = np.asarray(arrays["class_counts"], np.int64)
        indptr = np.asarray(arrays["indptr"], np.int64)
        if len(indptr) != clf.num_rows + 1 or len(ids) != len(class_counts):
            raise ValueError(f"saved fern counts have {len(indptr) - 1} rows, expected "
                             f"{clf.num_rows}")
        counts = sp.csr_matrix((np.asarray(arrays["counts"], np.int32),
                                np.asarray(arrays["indices"], np.int32), indptr),
                               shape=(clf.num_rows, len(ids)))
        if counts.nnz and (counts.data.min() <= 0 or counts.indices.max() >= len(ids)):
            raise ValueError("saved fern counts are not positive counts of the saved classes")
        counts.sort_indices()
        clf._class_ids, clf._class_counts = ids, class_counts
        clf._column = {int(lab): i for i, lab in enumerate(ids.tolist())}
        clf._log = clf._encode(counts)
        return clf


def _narrowest(values: npt.NDArray[Any], bound: int | None = None) -> npt.NDArray[Any]:
    """Non-negative integer ``values`` in the smallest unsigned type that holds them (and
    every value below ``bound`` where given, so a model's arrays keep one type)."""
    top = int(values.max(initial=0)) if bound is None else max(bound - 1, 0)
    return values.astype(np.min_scalar_type(top))
