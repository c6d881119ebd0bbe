"""Sparse fern counts in their smallest types: the (fern, leaf) x class matrix N[m K + k, c].

A CSR matrix whose columns are ``uint16`` (up to 65536 classes; ``int32`` beyond) and whose
counts are the smallest unsigned type holding the largest (``uint8`` when every count is below
256, as with 100 warps per view): 3 bytes per non-zero instead of scipy's float32 value and
int32 column (8 bytes). Scoring reads every visited row of the model, tens of MB per query,
from memory: fewer bytes per entry is most of its speed. A count becomes the log correction
``log(1 + N / Nr)`` of eq. 3.23 through a float32 table (:meth:`FernClassifier.scorer`), so
the values added are those the float32 CSR held, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

#: Most classes whose column index fits the compact column type.
MAX_UINT16_COLUMNS = 1 << 16


@dataclass(frozen=True, eq=False)
class SparseCounts:
    """Positive integer counts in CSR form: row ``r``'s entries are ``indptr[r]:indptr[r+1]``
    of ``columns`` (ascending within a row) and ``counts``; ``num_columns`` classes."""

    indptr: npt.NDArray[np.integer]
    columns: npt.NDArray[np.integer]
    counts: npt.NDArray[np.unsignedinteger]
    num_columns: int

    @classmethod
    def empty(cls, num_rows: int, num_columns: int = 0) -> SparseCounts:
        return cls(np.zeros(num_rows + 1, np.int32), np.zeros(0, np.uint16),
                   np.zeros(0, np.uint8), num_columns)

    @classmethod
    def from_csr(cls, matrix: sp.csr_matrix) -> SparseCounts:
        """Compact copy of a canonical CSR matrix of positive integer counts."""
        num_columns = matrix.shape[1]
        data = np.asarray(matrix.data)
        largest = int(data.max(initial=0))
        if data.size and data.min() <= 0:
            raise ValueError("counts must be positive")
        column_type = np.uint16 if num_columns <= MAX_UINT16_COLUMNS else np.int32
        count_type = np.min_scalar_type(largest) if largest > 0 else np.dtype(np.uint8)
        return cls(matrix.indptr.copy(), matrix.indices.astype(column_type),
                   data.astype(count_type), num_columns)

    @property
    def num_rows(self) -> int:
        return len(self.indptr) - 1

    @property
    def nnz(self) -> int:
        return len(self.counts)

    @property
    def nbytes(self) -> int:
        return int(self.indptr.nbytes + self.columns.nbytes + self.counts.nbytes)

    def max_count(self) -> int:
        return int(self.counts.max(initial=0))

    def to_csr(self, num_columns: int | None = None) -> sp.csr_matrix:
        """The counts as a canonical int32 scipy CSR matrix (``num_columns`` wide)."""
        shape = (self.num_rows, self.num_columns if num_columns is None else num_columns)
        return sp.csr_matrix((self.counts.astype(np.int32), self.columns.astype(np.int32),
                              self.indptr), shape=shape)

    def gather(self, rows: npt.NDArray[np.int64]
               ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """Entries of ``rows`` (R,), concatenated in order: (E,) positions into
        :attr:`columns` / :attr:`counts`, and (R,) the number of entries of each row."""
        starts = self.indptr[rows].astype(np.int64)
        lengths = self.indptr[rows + 1].astype(np.int64) - starts
        positions = np.repeat(starts - np.cumsum(lengths) + lengths, lengths)
        positions += np.arange(len(positions))
        return positions, lengths
