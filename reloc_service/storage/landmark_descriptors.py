"""One stored descriptor per landmark: the rows of a feature kind that observe one landmark
share the descriptor of the first of them (``StoredParts.descriptors == "per-landmark"``).

A landmark seen by several keyframes has a descriptor in each (2.2 a landmark on the rendered
room); relocalization matches a query's descriptors against a keyframe's landmark keypoints
(p3p, the verification's guided matching) or learns from them (ferns, bag of words), and the
observations of one landmark describe one surface patch, seen from nearby keyframes. A
snapshot so stores, per kind, the descriptor (or PQ code) of each landmark's first row in
column order (its earliest keyframe, usually the one that made it) and of every row without a
landmark, in column order; nothing else. Which stored descriptor a row reads is a function of
the rows' landmark ids alone (:func:`shared_index`), which load rebuilds from the landmarks'
observations anyway: no index is stored. A map loaded so and saved again stores the same
bytes (the rows of one landmark read one descriptor, the first of them keeps it).

A row keeps its own descriptor (or code) beside the shared one where the two differ by more
than descriptor noise (:func:`own_rows`; format 9, the per-row mask :data:`OWN_ROWS`): on a
scene of repeated texture the first row's descriptor, seen from another viewpoint, matched
the query worse than the row's own and cost 7 points of recall at 5 cm. The noise is
measured on the map itself at save: the distances between each landmark's later rows and
its first row are, for most rows, the difference of two views of one patch; their median
scales a noise model (ORB: each of the 256 bits flips independently, a binomial; SIFT: each
of the 128 values moves by independent Gaussian noise, a chi-square of 128 degrees of
freedom in units of the squared distance's median), and a row whose distance lies beyond
the model's :data:`OWN_FALSE_ALARM` quantile keeps its own. A loaded map's later rows read
either their landmark's descriptor (distance 0) or their own (beyond the first save's
threshold); while those that share are more than half of them, the median is 0, and a
save again keeps exactly the rows that differ, so it stores the same bytes.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ..core import distributions
from ..core.errors import MapError
from ..core.frame import is_binary_descriptor
from .descriptor_pq import DESCRIPTOR_CODES, PQCodebook

#: Column of the shared descriptors (full) and of their PQ codes, in place of the per-row ones.
SHARED_DESCRIPTORS = "landmark_descriptors"
SHARED_CODES = "landmark_descriptors_pq"
#: Per-row column -> the shared column stored instead of it.
SHARED_OF = {"descriptors": SHARED_DESCRIPTORS, DESCRIPTOR_CODES: SHARED_CODES}
ROW_OF = {shared: row for row, shared in SHARED_OF.items()}
#: Per-row column (uint8, 1 or 0): the rows with a landmark that keep their own descriptor
#: in the shared column, beside their landmark's (absent: none do, format 8).
OWN_ROWS = "own_descriptor_rows"
#: Rate at which a row whose descriptor differs from its landmark's by noise alone is still
#: taken as different (and keeps its own: a few bytes spent, no answer changed).
OWN_FALSE_ALARM = 0.01
#: Rows compared at a time (their float32 differences: 2000 x 128 x 4 bytes = 1 MB).
_CHUNK = 2000


def _first_row_of_each(landmark_ids: npt.NDArray[np.integer]
                       ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(rows with a landmark, the first row of each row's landmark): a scatter of the rows'
    minimum by id, not a sort (1.6 M rows: 0.1 s against 0.5 s for ``np.unique``, paid at
    the first read of a loaded map's features)."""
    ids = np.asarray(landmark_ids)
    rows = np.flatnonzero(ids >= 0)
    if not len(rows):
        return rows, rows
    first_of_id = np.full(int(ids[rows].max()) + 1, len(ids), np.int64)
    np.minimum.at(first_of_id, ids[rows], rows)
    return rows, first_of_id[ids[rows]]


def first_rows(landmark_ids: npt.NDArray[np.integer],
               own: npt.NDArray[np.bool_] | None = None) -> npt.NDArray[np.bool_]:
    """(N,) mask of the rows whose descriptor is stored: each landmark's first row in
    ``landmark_ids`` order, every row without a landmark (id < 0), and the ``own`` rows."""
    first = np.asarray(landmark_ids) < 0
    _, first_of_row = _first_row_of_each(landmark_ids)
    first[first_of_row] = True
    if own is not None:
        first |= np.asarray(own, bool)
    return first


def shared_index(landmark_ids: npt.NDArray[np.integer],
                 own: npt.NDArray[np.bool_] | None = None) -> npt.NDArray[np.int64]:
    """(N,) row of the shared column each row reads: its own rank among the
    :func:`first_rows` where it has no landmark or is an ``own`` row, else its landmark's
    first row's."""
    first = np.asarray(landmark_ids) < 0
    rows, first_of_row = _first_row_of_each(landmark_ids)
    first[first_of_row] = True
    if own is not None:
        own = np.asarray(own, bool)
        first |= own
        keeps = own[rows]
        rows, first_of_row = rows[~keeps], first_of_row[~keeps]
    rank = np.cumsum(first, dtype=np.int64) - 1
    rank[rows] = rank[first_of_row]
    return rank


def own_rows(descriptors: np.ndarray, landmark_ids: npt.NDArray[np.integer], *,
             rate: float = OWN_FALSE_ALARM) -> npt.NDArray[np.bool_]:
    """(N,) mask of the rows with a landmark whose ``descriptors`` row differs from its
    landmark's first row's by more than descriptor noise at false-alarm ``rate`` (see the
    module's docstring; the first rows themselves are never in it)."""
    own = np.zeros(len(landmark_ids), bool)
    rows, first_of_row = _first_row_of_each(landmark_ids)
    later = rows != first_of_row
    rows, first = rows[later], first_of_row[later]
    if not len(rows):
        return own
    desc = np.asarray(descriptors)
    distances = np.concatenate([
        _distances(desc[rows[i:i + _CHUNK]], desc[first[i:i + _CHUNK]])
        for i in range(0, len(rows), _CHUNK)])
    own[rows[distances > noise_threshold(distances, desc, rate=rate)]] = True
    return own


def _distances(a: np.ndarray, b: np.ndarray) -> npt.NDArray[np.float64]:
    """Row by row: Hamming distances of packed binary descriptors, else squared L2."""
    if is_binary_descriptor(a):
        return np.unpackbits(a ^ b, axis=1).sum(axis=1, dtype=np.int64).astype(np.float64)
    diff = a.astype(np.float32) - b.astype(np.float32)
    return np.einsum("ij,ij->i", diff, diff).astype(np.float64)


def noise_threshold(distances: npt.NDArray[np.float64], descriptors: np.ndarray, *,
                    rate: float = OWN_FALSE_ALARM) -> float:
    """The distance that noise alone exceeds with probability ``rate``, the noise scaled so
    the model's median is the median of ``distances`` (:func:`_distances`' units): binary
    descriptors of B bits, a Binomial(B, median / B) quantile; real ones of D values, the
    median times a chi-square(D) quantile over its median."""
    median = float(np.median(distances))
    if is_binary_descriptor(descriptors):
        bits = 8 * descriptors.shape[1]
        return distributions.binom.ppf(1.0 - rate, bits, median / bits)
    dims = descriptors.shape[1]
    return median * distributions.chi2.ppf(1.0 - rate, dims) / distributions.chi2.median(dims)


def share_descriptors(columns: dict[str, np.ndarray], codebook: PQCodebook | None = None
                      ) -> dict[str, np.ndarray]:
    """``columns`` (one kind's, every row) with its per-row descriptors or codes replaced by
    the :data:`SHARED_OF` column of the :func:`first_rows` and the :func:`own_rows` (compared
    as ``codebook`` decodes them where they are its codes), and the own rows' mask as
    :data:`OWN_ROWS` where there are any (``landmark_ids`` must be there)."""
    ids = columns["landmark_ids"]
    if DESCRIPTOR_CODES in columns:
        if codebook is None:
            raise MapError("PQ codes shared without their codebook")
        own = own_rows(codebook.decode(np.asarray(columns[DESCRIPTOR_CODES])), ids)
    else:
        own = own_rows(columns["descriptors"], ids)
    keep = first_rows(ids, own)
    out = dict(columns)
    for row, shared in SHARED_OF.items():
        if row in out:
            out[shared] = out.pop(row)[keep]
    if own.any():
        out[OWN_ROWS] = own.astype(np.uint8)
    return out


def check_shared_count(where: str, stored: int, landmark_ids: npt.NDArray[np.integer],
                       own: npt.NDArray[np.bool_] | None = None) -> None:
    """MapError naming ``where`` unless a shared column of ``stored`` rows holds what
    :func:`first_rows` keeps of ``landmark_ids`` and ``own``: one row per distinct landmark,
    one per row without a landmark and one per own row (a scatter, not a sort: this runs at
    every load)."""
    ids = np.asarray(landmark_ids)
    has = ids[ids >= 0]
    seen = np.zeros(int(has.max()) + 1 if len(has) else 0, bool)
    seen[has] = True
    extra = 0
    if own is not None:
        own = np.asarray(own, bool)
        if len(own) != len(ids):
            raise MapError(f"{where}: own-row mask of {len(own)} rows, expected {len(ids)}")
        extra = int(np.count_nonzero(own & (ids >= 0)))
        if extra != int(np.count_nonzero(own)):
            raise MapError(f"{where}: own-row mask marks rows without a landmark")
    expected = int(seen.sum()) + len(ids) - len(has) + extra
    if stored != expected:
        raise MapError(f"{where}: {stored} rows, expected {expected} (one per landmark its "
                       f"keypoints observe, one per keypoint without a landmark and one per "
                       f"keypoint that keeps its own)")
