"""PQ codes with exact rows: a SIFT descriptor is stored in full beside its product-
quantization code where the code's error exceeds what the descriptor's own noise allows
(``[service] descriptor_codec = "pq-hybrid"``).

A query descriptor matched against a stored one differs from it by the noise of two views
of one patch (its squared L2 distance, median ``m`` over the map's landmarks seen twice or
more: each later row against its landmark's first, as :mod:`.landmark_descriptors`
measures it). A PQ code replaces the stored descriptor by a reconstruction off it by an
error ``e``, independent of the views' noise, so the expected squared distance to a query
grows from ``m`` to ``m + |e|^2``. A row is kept exact where ``|e|^2 > EXACT_SHARE * m``:
every other row's match distance grows by at most ``sqrt(1 + EXACT_SHARE)`` - 1 = 12 % in
quadrature, the bound the float16 landmark points keep (:mod:`.landmark_codec`: half a
sigma of rounding). The threshold (``EXACT_SHARE * m``) is measured once, when the codebook
is learnt, and saved with it, so a map loaded and saved again keeps exactly its exact rows
(decoded rows have error 0).

A snapshot stores, per kind, its codes as before (per row, or per shared row with
``"per-landmark"``), a uint8 mask over those code rows (:data:`EXACT_ROWS`), the full
descriptors of the masked rows in row order (:data:`EXACT`) and the threshold
(:data:`EXACT_THRESHOLD`, a (1,) float64 file next to the codebook); format 11.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ..core.errors import MapError
from .descriptor_pq import PQCodebook
from .landmark_descriptors import later_row_distances

#: Columns of a kind stored with exact rows: the mask over its code rows, the full rows.
EXACT_ROWS = "descriptors_exact_rows"
EXACT = "descriptors_exact"
#: File (``features/<kind>.<name>.npy``) of the squared error beyond which a row is exact.
EXACT_THRESHOLD = "pq_exact_threshold"
#: Share of the median two-view squared distance a code's squared error may add before its
#: row is stored exact: 0.25, the match distance grown by at most 12 % in quadrature.
EXACT_SHARE = 0.25


def exact_threshold(descriptors: list[npt.NDArray[np.uint8]],
                    landmark_ids: list[npt.NDArray[np.integer]]) -> float | None:
    """:data:`EXACT_SHARE` times the median squared L2 distance between the later rows of a
    landmark and its first row, over the keyframes' (N_i, D) ``descriptors`` and their (N_i,)
    ``landmark_ids`` (-1: none); None when no landmark has two rows (no noise measured)."""
    has = [np.asarray(i) >= 0 for i in landmark_ids]
    ids = np.concatenate([np.asarray(i)[h] for i, h in zip(landmark_ids, has, strict=True)]
                         or [np.zeros(0, np.int64)])
    if not len(ids):
        return None
    desc = np.concatenate([np.asarray(d)[h] for d, h in zip(descriptors, has, strict=True)])
    distances = later_row_distances(desc, ids)
    if not len(distances):
        return None
    return EXACT_SHARE * float(np.median(distances))


def squared_errors(descriptors: npt.NDArray[np.uint8], codes: npt.NDArray[np.uint8],
                   codebook: PQCodebook) -> npt.NDArray[np.float64]:
    """(N,) squared L2 distance of each descriptor row to its code's reconstruction."""
    if len(descriptors) != len(codes):
        raise MapError(f"{len(descriptors)} descriptors against {len(codes)} PQ codes")
    if not len(codes):
        return np.zeros(0)
    diff = descriptors.astype(np.float32) - codebook.decode(codes).astype(np.float32)
    return np.einsum("ij,ij->i", diff, diff).astype(np.float64)


def split_exact(descriptors: npt.NDArray[np.uint8], codes: npt.NDArray[np.uint8],
                codebook: PQCodebook) -> dict[str, np.ndarray]:
    """The exact-row columns of one kind: :data:`EXACT_ROWS` (uint8 mask over ``codes``'
    rows, 1 where the squared error exceeds ``codebook.exact_above``) and :data:`EXACT`
    (those rows of ``descriptors``, in row order)."""
    if codebook.exact_above is None:
        raise MapError("exact rows asked of a codebook without an exact threshold")
    mask = squared_errors(descriptors, codes, codebook) > codebook.exact_above
    return {EXACT_ROWS: mask.astype(np.uint8),
            EXACT: np.ascontiguousarray(descriptors[mask], np.uint8)}


def exact_rank(mask: npt.NDArray[np.uint8]) -> npt.NDArray[np.int64]:
    """(N,) row of the :data:`EXACT` column a masked code row reads (its rank among the
    masked rows; meaningless where unmasked)."""
    return np.cumsum(np.asarray(mask) != 0, dtype=np.int64) - 1


def check_exact(where: str, mask: np.ndarray, exact: np.ndarray, code_rows: int) -> None:
    """MapError naming ``where`` unless ``mask`` is a (code_rows,) 0/1 uint8 mask and
    ``exact`` holds one (n, D) uint8 row per masked row."""
    if mask.dtype != np.uint8 or mask.shape != (code_rows,):
        raise MapError(f"{where}: expected a ({code_rows},) uint8 exact-row mask, got "
                       f"{mask.shape} {mask.dtype}")
    count = int(np.count_nonzero(mask))
    if exact.dtype != np.uint8 or exact.ndim != 2 or len(exact) != count:
        raise MapError(f"{where}: expected ({count}, D) uint8 exact descriptors (one per "
                       f"masked row), got {exact.shape} {exact.dtype}")


def with_exact(decoded: npt.NDArray[np.uint8], mask: npt.NDArray[np.bool_],
               exact: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """``decoded`` (N, D) with its ``mask`` rows replaced by ``exact`` (one per masked row)."""
    if not len(exact):
        return decoded
    out = np.array(decoded, copy=True)
    out[mask] = exact
    return out
