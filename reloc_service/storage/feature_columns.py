"""Keyframe features as snapshot columns: narrow lossless dtypes on disk, landmark points
derived from the landmark table, and each keyframe's :class:`Features` built on first use.

A snapshot (format 3) stores per feature kind one column per field, every keyframe's rows
concatenated. What a column holds is exactly what the map held, in fewer bytes:

- a field is stored in a narrower dtype only when every value survives the round trip
  (:func:`narrow`): OpenCV's keypoint positions are float32 values kept as float64, pyramid
  levels fit int8, landmark ids int32 below 2**31;
- ``points_world`` of a keypoint is the world point of its landmark (NaN without one), so it
  is not stored but looked up in the saved landmark columns (:func:`derive_points`); a kind
  whose points are not all that (a client gave points differing from the landmark's) keeps
  its stored column (:func:`points_are_derived` decides at save);
- ``landmark_ids`` is the inverse of the landmarks' observations (keyframe, kind, keypoint):
  rebuilt from them at load (:func:`ids_from_observations`), stored only where it differs;
- ``sizes`` that are a function of the pyramid level (ORB: 31 px times the level's scale)
  are stored as one (level, size) table per kind (:func:`sizes_by_level`);
- ``keypoints_px`` that are integer pixels of their pyramid level times the level's float32
  scale (OpenCV's ORB) are stored as int16 level pixels and one (level, scale) table per kind
  (:func:`level_pixels`; format 4), when every keypoint of the kind is exactly that;
- ``angles`` are not stored (ORB's since format 4; no kind's in a snapshot this reloc
  writes, which every reader of format 6 or later loads): nothing reads a map keypoint's
  angle after extraction (its descriptor is already steered by it), so a loaded keypoint
  has :data:`NO_ANGLE`, OpenCV's "no orientation", as a client-given keypoint has.

Loaded keyframes get a :class:`LazyFeatures` mapping: the canonical dtypes of
:class:`Features` (float64 keypoints, int64 ids, the points) are made per keyframe and kind
when first read, so a loaded map holds in memory only what queries touched, like the
memory-mapped columns it reads from.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Mapping, MutableMapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from ..core.errors import MapError
from ..core.frame import Features
from ..core.landmark_table import LandmarkColumns, LandmarkTable
from .descriptor_hybrid import EXACT, EXACT_ROWS, exact_rank, with_exact
from .descriptor_pq import (
    DESCRIPTOR_CODES,
    PQCodebook,
)
from .landmark_descriptors import (
    OWN_ROWS,
    ROW_OF,
    check_shared_count,
    shared_index,
)

Array = npt.NDArray[np.float64]

#: Fields of a format-3 feature column set: always stored, and stored unless derivable.
STORED_FIELDS = ("keypoints_px", "levels", "angles", "descriptors")
DERIVABLE_FIELDS = ("sizes", "landmark_ids", "points_world")
DERIVED_FIELD = "points_world"
#: The (K, 2) float32 table (level, size) a kind's sizes are read from when not stored.
SIZE_TABLE = "sizes_by_level"
#: Kinds whose keypoint angles a snapshot of format 4 or 5 does not store (one this reloc
#: writes stores no kind's), and the angle they load with.
ANGLELESS_KINDS = ("orb",)
NO_ANGLE = -1.0
#: The (N, 2) int16 pixels of each keypoint on its pyramid level, and the (K, 2) float32 table
#: (level, scale) that makes them ``keypoints_px`` (stored instead of it, format 4).
LEVEL_PIXELS = "keypoints_level_px"
SCALE_TABLE = "keypoint_scales_by_level"
#: (N, 2) int16 keypoints in eighths of a pixel, stored instead of ``keypoints_px`` by a
#: compact save (format 6): a rounding of at most 1/16 px, far below a SIFT keypoint's own
#: localisation error; images up to 4,095 px (else the float32 column is kept).
EIGHTH_PIXELS = "keypoints_px8"
#: The dtype :class:`Features` holds each field in (descriptors keep theirs).
CANONICAL = {"keypoints_px": np.float64, "levels": np.int16, "sizes": np.float32,
             "angles": np.float32, "landmark_ids": np.int64, "points_world": np.float64}
#: The narrower dtype tried for each field at save (kept only when lossless).
NARROWER = {"keypoints_px": np.float32, "levels": np.int8, "landmark_ids": np.int32}


def narrow(name: str, column: np.ndarray) -> np.ndarray:
    """``column`` in :data:`NARROWER`'s dtype for ``name`` when every value round-trips
    exactly (NaN included); else unchanged."""
    dtype = NARROWER.get(name)
    return column if dtype is None else narrowest(column, (dtype,))


def narrowest(column: np.ndarray, dtypes: Sequence[Any]) -> np.ndarray:
    """``column`` in the first of ``dtypes`` (narrowest first) that holds every value exactly
    (NaN included) and is narrower than its own; else unchanged."""
    for dtype in dtypes:
        if np.dtype(dtype).itemsize >= column.dtype.itemsize:
            continue
        with np.errstate(over="ignore", invalid="ignore"):
            small = column.astype(dtype)
        if np.array_equal(small.astype(column.dtype), column, equal_nan=column.dtype.kind == "f"):
            return small
    return column


def sizes_by_level(levels: npt.NDArray[Any], sizes: npt.NDArray[np.float32]
                   ) -> npt.NDArray[np.float32] | None:
    """(K, 2) float32 table of (level, size) when every keypoint's size is its level's (ORB);
    None when not (SIFT's sizes vary within an octave)."""
    values, first, index = np.unique(levels, return_index=True, return_inverse=True)
    table = np.stack([values.astype(np.float32), sizes[first].astype(np.float32)], axis=1)
    if not np.array_equal(values.astype(np.float32), values) or not np.array_equal(
            table[index.ravel(), 1], sizes):
        return None
    return table


def sizes_from_table(table: npt.NDArray[np.float32], levels: npt.NDArray[Any]
                     ) -> npt.NDArray[np.float32]:
    """(N,) float32 size of each level from a :func:`sizes_by_level` table."""
    pos = np.clip(np.searchsorted(table[:, 0], levels), 0, max(len(table) - 1, 0))
    if len(levels) and not np.array_equal(table[pos, 0], levels):
        raise MapError("keypoint levels outside the saved (level, size) table")
    return np.ascontiguousarray(table[pos, 1], dtype=np.float32)


def opencv_level_scales(levels: npt.NDArray[Any], scale_factor: float
                        ) -> npt.NDArray[np.float32]:
    """(K,) OpenCV ORB's float32 scale of each pyramid level in ``levels``:
    ``(float)std::pow((double)scaleFactor, level)`` with ``scaleFactor`` the float the
    detector was created with (orb.cpp ``getScale``; ``ORB::create`` takes a float)."""
    factor = float(np.float32(scale_factor))
    return np.array([factor ** int(v) for v in levels], np.float64).astype(np.float32)


def level_pixels(keypoints: np.ndarray, levels: npt.NDArray[Any], scale_factor: float
                 ) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.float32]] | None:
    """OpenCV's ORB detects at integer pixels of pyramid level ``l`` and returns them times
    the level's float32 scale (orb.cpp: ``allKeypoints[i].pt *= layerScale[octave]``, a
    float product): (N, 2) int16 level pixels and the (K, 2) float32 (level, scale) table
    when every float32 keypoint is exactly ``float32(pixel) * scale`` (checked here), else
    None (float64 keypoints, given keypoints, another detector)."""
    if keypoints.dtype != np.float32 or keypoints.ndim != 2 or len(keypoints) == 0:
        return None
    values, index = np.unique(levels, return_inverse=True)
    if values[0] < 0 or values[-1] > 31:
        return None
    scales = opencv_level_scales(values, scale_factor)
    scale = scales[index.ravel()][:, None]
    with np.errstate(invalid="ignore", over="ignore"):
        pixels = np.rint(keypoints / scale)
        if not np.all(np.abs(pixels) <= np.iinfo(np.int16).max):   # NaN fails too
            return None
        small = pixels.astype(np.int16)
    if not np.array_equal(small.astype(np.float32) * scale, keypoints):
        return None
    return small, np.stack([values.astype(np.float32), scales], axis=1)


def pixels_from_levels(pixels: npt.NDArray[np.int16], levels: npt.NDArray[Any],
                       table: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """(N, 2) float32 keypoints from :func:`level_pixels`' columns (the same float product)."""
    pos = np.clip(np.searchsorted(table[:, 0], levels), 0, max(len(table) - 1, 0))
    if len(levels) and not np.array_equal(table[pos, 0], levels):
        raise MapError("keypoint levels outside the saved (level, scale) table")
    return pixels.astype(np.float32) * table[pos, 1][:, None]


def observation_owners(landmarks: LandmarkColumns) -> npt.NDArray[np.int64]:
    """(O,) the landmark id of each observation row."""
    return np.repeat(np.asarray(landmarks.ids), np.diff(landmarks.obs_offsets))


def ids_from_observations(landmarks: LandmarkColumns, kind: str, n_rows: int,
                          kf_ids: npt.NDArray[np.int64], starts: npt.NDArray[np.int64],
                          owners: npt.NDArray[np.int64] | None = None
                          ) -> npt.NDArray[np.signedinteger[Any]] | None:
    """(n_rows,) landmark id of every ``kind`` keypoint (-1 without one) from the landmarks'
    observations, keyframe ``kf_ids[i]``'s keypoints starting at row ``starts[i]``
    (``kf_ids`` ascending); int32 when every id fits. None when two landmarks claim one
    keypoint or an observation names a keyframe without ``kind`` rows or a keypoint outside
    them (then the ids cannot be rebuilt: stored). ``owners``: :func:`observation_owners`,
    when already computed."""
    ids = np.asarray(landmarks.ids)
    fits = len(ids) == 0 or int(ids[-1]) < 2**31
    out: np.ndarray = np.full(n_rows, -1, np.int32 if fits else np.int64)
    if kind not in landmarks.kinds:
        return out
    sel = np.flatnonzero(landmarks.obs_kind == landmarks.kinds.index(kind))
    owner = (observation_owners(landmarks) if owners is None else owners)[sel]
    kf = landmarks.obs_keyframe[sel]
    pos = np.clip(np.searchsorted(kf_ids, kf), 0, max(len(kf_ids) - 1, 0))
    if len(kf) and (len(kf_ids) == 0 or not np.array_equal(kf_ids[pos], kf)):
        return None
    rows = starts[pos] + landmarks.obs_keypoint[sel]
    if len(rows) and (rows.min() < 0 or rows.max() >= n_rows):
        return None
    out[rows] = owner
    # a keypoint claimed twice leaves fewer rows set than observations (ids are >= 0)
    return out if np.count_nonzero(out >= 0) == len(rows) else None


def derive_points(landmarks: LandmarkColumns, landmark_ids: npt.NDArray[Any]) -> Array:
    """(N, 3) world point of each id's landmark in ``landmarks``, NaN where the id is -1;
    MapError if an id >= 0 is not a landmark there."""
    ids = np.asarray(landmark_ids, np.int64)
    out = np.full((len(ids), 3), np.nan)
    has = ids >= 0
    if has.any():
        rows = landmarks.rows(ids[has])
        if np.any(rows < 0):
            missing = ids[has][rows < 0][:5].tolist()
            raise MapError(f"keypoints name landmark(s) {missing} the snapshot does not hold")
        out[has] = landmarks.points_world[rows]
    return out


def points_are_derived(table: LandmarkTable, landmark_ids: npt.NDArray[np.int64],
                       points_world: Array) -> bool:
    """Whether ``points_world`` (N, 3) is exactly the landmark table's point of each id
    (NaN where -1): then the column need not be stored."""
    has = landmark_ids >= 0
    if not np.all(np.isnan(points_world[~has])):
        return False
    ids = landmark_ids[has]
    if not table.contains(ids).all():
        return False
    return bool(np.array_equal(table.points(ids), points_world[has]))


def feature_count(features: Mapping[str, Features], kind: str) -> int:
    """Number of ``kind`` keypoints (a loaded keyframe's features are not built for it)."""
    if isinstance(features, LazyFeatures):
        return features.count(kind)
    return len(features[kind])


class FeatureColumns:
    """The memory-mapped columns of one snapshot, per kind and field (narrow dtypes; the
    derivable fields only where stored), the size tables, and the landmark columns points
    and ids are derived from (set once they are read: :meth:`attach_landmarks`)."""

    def __init__(self, columns: Mapping[str, Mapping[str, np.ndarray]],
                 tables: Mapping[str, npt.NDArray[np.float32]] | None = None,
                 scales: Mapping[str, npt.NDArray[np.float32]] | None = None,
                 codebooks: Mapping[str, PQCodebook] | None = None) -> None:
        self.columns = {kind: dict(cols) for kind, cols in columns.items()}
        self.tables = dict(tables or {})
        #: kind -> codebook of the kinds whose descriptors are stored as PQ codes
        self.codebooks = dict(codebooks or {})
        #: kind -> (level, scale) table of the kinds whose keypoints are stored as level pixels
        self.scales = dict(scales or {})
        self.landmarks: LandmarkColumns | None = None
        #: kind -> (N,) row of its shared descriptor column each row reads (made on first
        #: read, from the landmark ids: :func:`.landmark_descriptors.shared_index`)
        self._shared_index: dict[str, npt.NDArray[np.int64]] = {}
        self._shared_lock = threading.Lock()
        #: kind -> (code rows,) row of its exact column each masked code row reads
        self._exact_rank: dict[str, npt.NDArray[np.int64]] = {}

    def attach_landmarks(self, landmarks: LandmarkColumns,
                         starts: Mapping[str, tuple[npt.NDArray[np.int64],
                                                    npt.NDArray[np.int64]]]) -> None:
        """Derive from ``landmarks`` what was not stored: each kind's landmark ids (one
        narrow column, from the observations; ``starts[kind]`` = keyframe ids ascending and
        their first rows)."""
        self.landmarks = landmarks
        owners = None
        for kind, cols in self.columns.items():
            if "landmark_ids" in cols:
                continue
            if owners is None:
                owners = observation_owners(landmarks)
            kf_ids, first = starts.get(kind, (np.zeros(0, np.int64), np.zeros(0, np.int64)))
            ids = ids_from_observations(landmarks, kind, len(cols["levels"]), kf_ids,
                                        first, owners)
            if ids is None:
                raise MapError(f"{kind} landmark ids not saved and not given by the landmarks' "
                               f"observations")
            ids.flags.writeable = False
            cols["landmark_ids"] = ids
        for kind, cols in self.columns.items():
            for shared in ROW_OF.keys() & cols.keys():
                check_shared_count(f"features/{kind}.{shared}", len(cols[shared]),
                                   cols["landmark_ids"], self._own(kind))

    def length(self, kind: str) -> int:
        return len(self.columns[kind]["levels"])

    def raw(self, kind: str, start: int, stop: int,
            rows: npt.NDArray[np.int64] | None = None) -> dict[str, np.ndarray]:
        """Rows ``start:stop`` of ``kind``'s columns as stored (no copy), sizes and
        keypoints from their tables where not stored (float32); no derived points.
        ``rows``: only those of them (indices into ``start:stop``), copied."""

        def take(column: np.ndarray) -> np.ndarray:
            part = column[start:stop]
            return part if rows is None else part[rows]

        cols = self.columns[kind]
        out = {f: take(c) for f, c in cols.items()
               if f not in ROW_OF and f not in (OWN_ROWS, EXACT_ROWS, EXACT)}
        shared = ROW_OF.keys() & cols.keys()
        for name in shared:
            out[ROW_OF[name]] = cols[name][take(self._shared_rows(kind))]
        if EXACT_ROWS in cols:   # per row: its code row's mask, and the masked rows' exact
            code_rows = (take(self._shared_rows(kind)) if shared
                         else np.arange(start, stop) if rows is None else start + rows)
            mask = cols[EXACT_ROWS][code_rows] != 0
            out[EXACT_ROWS] = mask
            out[EXACT] = cols[EXACT][self._exact_rows(kind)[code_rows[mask]]]
        if "sizes" not in out:
            out["sizes"] = sizes_from_table(self.tables[kind], out["levels"])
        if "angles" not in out:
            out["angles"] = np.full(len(out["levels"]), NO_ANGLE, np.float32)
        if EIGHTH_PIXELS in out:
            out["keypoints_px"] = out.pop(EIGHTH_PIXELS).astype(np.float32) / np.float32(8)
        if LEVEL_PIXELS in out:
            out["keypoints_px"] = pixels_from_levels(out.pop(LEVEL_PIXELS), out["levels"],
                                                     self.scales[kind])
        return out

    def rows_of_ranges(self, kind: str, ranges: npt.NDArray[np.int64],
                       rows: Callable[[npt.NDArray[np.int64]], npt.NDArray[np.int64]]
                       ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """Some rows of several keyframes, chosen at once: ``ranges`` (K, 2) their start and
        stop rows of ``kind``; ``rows(landmark_ids)`` says which, from the landmark ids of
        all of them in turn (read as stored, concatenated). Those rows of ``kind`` (M,), to
        read with :meth:`features_at`, and how many of them each range gave (K,)."""
        lengths = ranges[:, 1] - ranges[:, 0]
        offsets = np.concatenate([[0], np.cumsum(lengths)])
        # every range's rows, in turn: start + position within its range
        index = np.repeat(ranges[:, 0] - offsets[:-1], lengths) + np.arange(offsets[-1])
        wanted = rows(np.asarray(self.columns[kind]["landmark_ids"][index], np.int64))
        counts = np.bincount(np.searchsorted(offsets, wanted, side="right") - 1,
                             minlength=len(ranges)).astype(np.int64)
        return index[wanted], counts

    def features_at(self, kind: str, rows: npt.NDArray[np.int64]) -> Features:
        """Rows ``rows`` of ``kind`` (any keyframes', in that order) as :meth:`features`
        reads them."""
        return self.features(kind, 0, self.length(kind), rows)

    def _shared_rows(self, kind: str) -> npt.NDArray[np.int64]:
        """(N,) row of ``kind``'s shared descriptor column each of its rows reads (once)."""
        index = self._shared_index.get(kind)
        if index is None:
            if "landmark_ids" not in self.columns[kind]:
                raise MapError(f"{kind} descriptors read before the landmark ids were loaded")
            index = shared_index(self.columns[kind]["landmark_ids"], self._own(kind))
            with self._shared_lock:
                index = self._shared_index.setdefault(kind, index)
        return index

    def _exact_rows(self, kind: str) -> npt.NDArray[np.int64]:
        """(code rows,) row of ``kind``'s exact column each masked code row reads (once)."""
        rank = self._exact_rank.get(kind)
        if rank is None:
            rank = exact_rank(self.columns[kind][EXACT_ROWS])
            with self._shared_lock:
                rank = self._exact_rank.setdefault(kind, rank)
        return rank

    def _own(self, kind: str) -> npt.NDArray[np.bool_] | None:
        """``kind``'s rows that keep their own shared-column descriptor (None: none do)."""
        own = self.columns[kind].get(OWN_ROWS)
        return None if own is None else np.asarray(own) != 0

    def features(self, kind: str, start: int, stop: int,
                 rows: npt.NDArray[np.int64] | None = None) -> Features:
        """Rows ``start:stop`` of ``kind`` as :class:`Features` in its canonical dtypes
        (read-only: views of the map where the dtype is already canonical, else copies);
        ``rows``: only those of them (indices into ``start:stop``)."""
        if self.landmarks is None:
            raise MapError("features read before the landmark columns were loaded")
        arrays = {f: _canonical(f, c) for f, c in self.raw(kind, start, stop, rows).items()}
        if DESCRIPTOR_CODES in arrays:
            arrays["descriptors"] = self.codebooks[kind].decode(arrays.pop(DESCRIPTOR_CODES))
        if EXACT_ROWS in arrays:
            arrays["descriptors"] = with_exact(arrays["descriptors"], arrays.pop(EXACT_ROWS),
                                               arrays.pop(EXACT))
        if DERIVED_FIELD not in arrays:
            arrays[DERIVED_FIELD] = derive_points(self.landmarks, arrays["landmark_ids"])
        for a in arrays.values():
            a.flags.writeable = False
        return Features(kind=kind, **arrays)


def _canonical(name: str, column: np.ndarray) -> np.ndarray:
    dtype = CANONICAL.get(name)
    return column if dtype is None or column.dtype == dtype else column.astype(dtype)


class LazyFeatures(MutableMapping[str, Features]):
    """A loaded keyframe's ``features``: kind -> :class:`Features`, each built from the
    snapshot's columns on first read (two threads building at once build equal values) and
    kept. Setting or deleting a kind acts on this keyframe only (queries' frames use plain
    dicts; map changes copy keyframes with a new dict)."""

    __slots__ = ("_columns", "_rows", "_built", "_lock")

    def __init__(self, columns: FeatureColumns, rows: Mapping[str, tuple[int, int]]) -> None:
        self._columns = columns
        self._rows = dict(rows)
        self._built: dict[str, Features] = {}
        self._lock = threading.Lock()

    def __getitem__(self, kind: str) -> Features:
        feats = self._built.get(kind)
        if feats is None:
            start, stop = self._rows[kind]
            feats = self._columns.features(kind, start, stop)
            with self._lock:
                feats = self._built.setdefault(kind, feats)
        return feats

    def __setitem__(self, kind: str, feats: Features) -> None:
        with self._lock:
            self._built[kind] = feats
            self._rows.setdefault(kind, (0, 0))

    def __delitem__(self, kind: str) -> None:
        with self._lock:
            del self._rows[kind]
            self._built.pop(kind, None)

    def __iter__(self) -> Iterator[str]:
        return iter(list(self._rows))

    def __len__(self) -> int:
        return len(self._rows)

    def __contains__(self, kind: object) -> bool:
        return kind in self._rows

    def count(self, kind: str) -> int:
        """Number of ``kind`` keypoints, without building the features."""
        if kind in self._built:
            return len(self._built[kind])
        start, stop = self._rows[kind]
        return stop - start

    def peek(self, kind: str) -> Features | None:
        """``kind``'s Features, built as ``self[kind]`` builds them but not kept when not
        built yet (a pass over every keyframe of a map, reading each once, leaves them as
        they were); None when this keyframe has no ``kind``."""
        feats = self._built.get(kind)
        if feats is not None or kind not in self._rows:
            return feats
        return self._columns.features(kind, *self._rows[kind])

    def stored_range(self, kind: str) -> tuple[FeatureColumns, int, int] | None:
        """The snapshot's columns and the rows (start, stop) ``kind`` is read from, while it
        is not built or set here (:meth:`FeatureColumns.rows_of_ranges` chooses rows of
        several keyframes' at once); None once it is, or when this keyframe has no ``kind``."""
        if kind in self._built or kind not in self._rows:
            return None
        start, stop = self._rows[kind]
        return self._columns, start, stop

    @property
    def built_kinds(self) -> list[str]:
        """The kinds whose Features are built and kept (memory beside the stored rows)."""
        return sorted(self._built)

    def codebook(self, kind: str) -> PQCodebook | None:
        """The codebook ``kind``'s stored descriptors decode with (None: stored in full)."""
        return self._columns.codebooks.get(kind)

    def stored(self, kind: str) -> dict[str, np.ndarray] | None:
        """``kind``'s rows as stored in the snapshot when never built here (a save copies
        them as they are); None once built or set (read the Features then)."""
        if kind in self._built:
            return None
        return self._columns.raw(kind, *self._rows[kind])

    def __repr__(self) -> str:
        return f"LazyFeatures({sorted(self._rows)}, built={sorted(self._built)})"
