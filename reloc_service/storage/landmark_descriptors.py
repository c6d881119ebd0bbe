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

With ``medoid`` (``"per-landmark-medoid"``) the shared descriptor is the medoid of the
landmark's rows (the row whose summed distance to the others is least: L2 for SIFT, Hamming
for ORB; ties to the earliest row) rather than the first row's, stored in the first row's
place, so the reader and the format are unchanged. A query seen near any of the landmark's
keyframes then reads the central view rather than one end of the track, and fewer rows
differ from it beyond noise (the noise is measured as without it, later rows against their
first: two views of one patch; distances to a medoid, chosen as the least, would understate
it). The first row has no own slot (the shared one is in its
place): where it differs from the medoid beyond noise the landmark keeps its first row's
descriptor as before. A landmark of one or two rows keeps its first row's (two rows tie).
A loaded map saved again: its rows read the medoid or their own; with the median 0 a first
row that is not the medoid again differs beyond noise, so each landmark keeps what it
stored.
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


def later_row_distances(descriptors: np.ndarray, landmark_ids: npt.NDArray[np.integer]
                        ) -> npt.NDArray[np.float64]:
    """Distances (:func:`_distances`' units) of each landmark's later rows to its first row:
    the noise of two views of one patch that :func:`own_rows` measures."""
    rows, first = _first_row_of_each(landmark_ids)
    later = rows != first
    return _row_distances(np.asarray(descriptors), rows[later], first[later])


def own_rows(descriptors: np.ndarray, landmark_ids: npt.NDArray[np.integer], *,
             rate: float = OWN_FALSE_ALARM) -> npt.NDArray[np.bool_]:
    """(N,) mask of the rows with a landmark whose ``descriptors`` row differs from its
    landmark's first row's by more than descriptor noise at false-alarm ``rate`` (see the
    module's docstring; the first rows themselves are never in it)."""
    return own_and_reference(descriptors, landmark_ids, rate=rate)[0]


def own_and_reference(descriptors: np.ndarray, landmark_ids: npt.NDArray[np.integer], *,
                      rate: float = OWN_FALSE_ALARM, medoid: bool = False
                      ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.int64]]:
    """(own-row mask as :func:`own_rows`, (N,) the row whose descriptor each row's landmark
    shares, -1 for rows without one): the first row of each landmark, or with ``medoid`` its
    medoid where the first row is within noise of it (module docstring). Rows are compared
    with the shared descriptor they would read."""
    own = np.zeros(len(landmark_ids), bool)
    reference = np.full(len(landmark_ids), -1, np.int64)
    rows, first = _first_row_of_each(landmark_ids)
    if not len(rows):
        return own, reference
    desc = np.asarray(descriptors)
    distances = _row_distances(desc, rows, first)
    later = rows != first
    if not later.any():
        reference[rows] = first
        return own, reference
    # the noise of two views of one patch: later rows against their first, whatever is shared
    threshold = noise_threshold(distances[later], desc, rate=rate)
    ref = first
    if medoid:   # a first row beyond noise of its medoid: the landmark keeps the first's
        ref = _medoid_of_each(desc, rows, first)
        distances = _row_distances(desc, rows, ref)
        far_first = np.zeros(len(landmark_ids), bool)
        far_first[rows[(rows == first) & (distances > threshold)]] = True
        back = far_first[first]
        ref = np.where(back, first, ref)
        distances[back] = _row_distances(desc, rows[back], ref[back])
    own[rows[(rows != ref) & (rows != first) & (distances > threshold)]] = True
    reference[rows] = ref
    return own, reference


def _row_distances(desc: np.ndarray, rows: npt.NDArray[np.int64],
                   ref: npt.NDArray[np.int64]) -> npt.NDArray[np.float64]:
    """:func:`_distances` of ``desc[rows]`` to ``desc[ref]``, :data:`_CHUNK` rows at a time."""
    if not len(rows):
        return np.zeros(0)
    return np.concatenate([_distances(desc[rows[i:i + _CHUNK]], desc[ref[i:i + _CHUNK]])
                           for i in range(0, len(rows), _CHUNK)])


def _medoid_of_each(desc: np.ndarray, rows: npt.NDArray[np.int64],
                    first: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """For each of ``rows`` (with ``first``, its landmark's first row), its landmark's medoid
    row: least summed distance to the landmark's rows (L2 for real descriptors, Hamming for
    binary), ties to the earliest row. Landmarks of equal row count k >= 3 are batched, their
    k x k distances computed at once; one or two rows: the first."""
    order = np.lexsort((rows, first))          # grouped by landmark, rows ascending
    grouped, group_of = rows[order], first[order]
    starts = np.flatnonzero(np.r_[True, group_of[1:] != group_of[:-1]])
    sizes = np.diff(np.r_[starts, len(grouped)])
    medoid = group_of.copy()
    binary = is_binary_descriptor(desc)
    for k in np.unique(sizes[sizes >= 3]):
        at = starts[sizes == k][:, None] + np.arange(k)          # (G, k) positions
        per_block = max(1, _CHUNK // int(k * k))
        for i in range(0, len(at), per_block):
            block = at[i:i + per_block]
            members = grouped[block]                               # (B, k) rows
            best = _pairwise_sums(desc[members], binary).argmin(axis=1)
            medoid[block] = members[np.arange(len(members)), best][:, None]
    out = np.empty_like(medoid)
    out[order] = medoid
    return out


def _pairwise_sums(group: np.ndarray, binary: bool) -> npt.NDArray[np.float64]:
    """(B, k) summed distance of each of a (B, k, D) group's rows to the group's others."""
    if binary:
        xor = group[:, :, None, :] ^ group[:, None, :, :]
        return np.unpackbits(xor, axis=-1).sum(axis=(2, 3), dtype=np.int64).astype(np.float64)
    g = group.astype(np.float32)
    diff = g[:, :, None, :] - g[:, None, :, :]
    return np.sqrt(np.einsum("bijd,bijd->bij", diff, diff)).sum(axis=2, dtype=np.float64)


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


def share_descriptors(columns: dict[str, np.ndarray], codebook: PQCodebook | None = None,
                      medoid: bool = False) -> dict[str, np.ndarray]:
    """``columns`` (one kind's, every row) with its per-row descriptors or codes replaced by
    the :data:`SHARED_OF` column of the :func:`first_rows` and the :func:`own_rows` (compared
    as ``codebook`` decodes them where they are its codes), and the own rows' mask as
    :data:`OWN_ROWS` where there are any (``landmark_ids`` must be there); ``medoid``: each
    landmark's first row holds its medoid's descriptor or code (:func:`own_and_reference`)."""
    ids = columns["landmark_ids"]
    if DESCRIPTOR_CODES in columns:
        if codebook is None:
            raise MapError("PQ codes shared without their codebook")
        own, reference = own_and_reference(
            codebook.decode(np.asarray(columns[DESCRIPTOR_CODES])), ids, medoid=medoid)
    else:
        own, reference = own_and_reference(columns["descriptors"], ids, medoid=medoid)
    keep = first_rows(ids, own)
    rows, first = _first_row_of_each(ids)
    moved = rows[(rows == first) & (reference[rows] != rows)]
    out = dict(columns)
    for row, shared in SHARED_OF.items():
        if row in out:
            values = np.asarray(out.pop(row))
            if len(moved):    # the first row's slot holds its landmark's medoid
                values = values.copy()
                values[moved] = values[reference[moved]]
            out[shared] = values[keep]
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
