"""The landmarks seen by some keyframes, pooled one row per landmark: what the P3P pose finder
matches a query against and what guided matching projects into it."""

from __future__ import annotations

import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.background import stop_if
from ...core.frame import Features, Keyframe
from ...core.map import MapState
from ...core.numeric import first_occurrences
from .point_uncertainty import PointUncertainty

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class LandmarkPool:
    """The landmarks seen by some keyframes, one row per landmark (L rows): the descriptor of
    its observation in the best-ranked keyframe, its id, world point and that keyframe."""

    descriptors: npt.NDArray[Any]
    landmark_ids: npt.NDArray[np.int64]
    points_world: Array
    keyframe_rows: npt.NDArray[np.int64]

    @classmethod
    def gather(cls, keyframes: list[Keyframe], kind: str,
               cancelled: Callable[[], bool] | None = None) -> LandmarkPool:
        """Pool ``kind`` landmarks of ``keyframes`` (best first). A landmark seen by several
        keyframes keeps one row: duplicates would fail Lowe's ratio test against themselves.
        :class:`~reloc_service.core.errors.Cancelled` once ``cancelled()`` is true, checked
        before each keyframe's features are read (for a keyframe loaded from a snapshot, a
        decoding: most of a large map's gathering)."""
        feats = []
        for kf in keyframes:
            stop_if(cancelled)
            feats.append(_peek(kf, kind))
        if len(feats) == 1 and feats[0] is not None and len(feats[0]):
            f = feats[0]
            idx = _landmark_rows(f)
            return cls(f.descriptors[idx], f.landmark_ids[idx], f.points_world[idx],
                       np.zeros(len(idx), np.int64))
        local = [np.zeros(0, np.int64) if f is None else np.flatnonzero(f.landmark_ids >= 0)
                 for f in feats]
        if not sum(len(i) for i in local):
            return cls.empty(kind)
        ids = np.concatenate([f.landmark_ids[i] for f, i in zip(feats, local, strict=True)
                              if f is not None])
        kf_rows = np.repeat(np.arange(len(feats)), [len(i) for i in local])
        # The first occurrence is in the best-ranked keyframe; sorted, rows stay grouped by
        # keyframe, so only the kept descriptors are copied (not every observation's).
        first = first_occurrences(ids)
        rows, idx = kf_rows[first], np.concatenate(local)[first]
        # rows ascend: each keyframe's picks are one run of idx (one pass, not one per keyframe)
        starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
        picks = [(feats[rows[s]], run) for s, run in zip(starts, np.split(idx, starts[1:]),
                                                          strict=True)]
        return cls(np.concatenate([f.descriptors[i] for f, i in picks if f is not None]),
                   ids[first], np.concatenate([f.points_world[i] for f, i in picks
                                               if f is not None]), rows)

    @classmethod
    def gather_streamed(cls, keyframes: list[Keyframe], kind: str,
                        cancelled: Callable[[], bool] | None = None) -> LandmarkPool:
        """:meth:`gather`'s pool, for a whole map: the rows it keeps are chosen first from
        the landmark ids alone, then read into the pool's arrays, made once at their final
        size. Keyframes loaded from a snapshot are read up to :data:`STORED_RUN` at a time,
        and only those rows of them are decoded. Holding every keyframe's features until the
        end took about 1.5 times the pool at its peak, and the rows read keyframe by
        keyframe then concatenated about 1.0 times (scripts/pool_build_peak.py on the fleet
        template), the concatenated parts then held by the C heap until trimmed; reading
        one keyframe at a time was most of the time. Slower than :meth:`gather` on a few
        keyframes (a table of the ids seen, two passes)."""
        seen = _SeenIds()

        def new_rows(ids: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
            """The rows of ``ids`` (in turn) of landmarks no earlier row gave."""
            local = np.flatnonzero(ids >= 0)
            local = local[first_occurrences(ids[local])]
            return local[seen.take_new(ids[local])]

        reads: list[tuple[Any, npt.NDArray[np.int64]]] = []   # (columns or Features, rows)
        counts = np.zeros(len(keyframes), np.int64)
        for first, columns, ranges in _stored_runs(keyframes, kind):
            stop_if(cancelled)
            if columns is None:
                feats = _peek(keyframes[first], kind)
                if feats is None:
                    continue
                source, wanted = feats, new_rows(feats.landmark_ids)
                counts[first] = len(wanted)
            else:
                source = columns
                wanted, got = columns.rows_of_ranges(kind, np.array(ranges, np.int64), new_rows)
                counts[first:first + len(got)] = got
            if len(wanted):
                reads.append((source, wanted))
        if not reads:
            return cls.empty(kind)
        return cls._read(reads, kind, np.repeat(np.arange(len(keyframes), dtype=np.int64),
                                                counts), cancelled)

    @classmethod
    def _read(cls, reads: list[tuple[Any, npt.NDArray[np.int64]]], kind: str,
              keyframe_rows: npt.NDArray[np.int64],
              cancelled: Callable[[], bool] | None) -> LandmarkPool:
        """The pool of one row per ``keyframe_rows`` entry, read in turn from ``reads``:
        (snapshot columns, their rows) or (built Features, their rows), at most
        :data:`READ_CHUNK_ROWS` rows between two cancel checks."""
        total = len(keyframe_rows)
        pool = None
        at = 0
        for source, all_wanted in reads:
            for begin in range(0, len(all_wanted), READ_CHUNK_ROWS):
                stop_if(cancelled)
                wanted = all_wanted[begin:begin + READ_CHUNK_ROWS]
                f = (source.take(wanted) if isinstance(source, Features)
                     else source.features_at(kind, wanted))
                if pool is None:
                    pool = cls(np.empty((total, f.descriptors.shape[1]), f.descriptors.dtype),
                               np.empty(total, np.int64), np.empty((total, 3)), keyframe_rows)
                part = slice(at, at + len(f))
                pool.descriptors[part] = f.descriptors
                pool.landmark_ids[part] = f.landmark_ids
                pool.points_world[part] = f.points_world
                at += len(f)
        if pool is None or at != total:
            raise RuntimeError(f"expected {total} pool rows, read {at}")
        return pool

    @classmethod
    def empty(cls, kind: str) -> LandmarkPool:
        """A pool of no landmark (``kind``'s descriptor width: both kinds are uint8)."""
        width = 128 if kind == "sift" else 32
        return cls(np.zeros((0, width), np.uint8), np.zeros(0, np.int64), np.zeros((0, 3)),
                   np.zeros(0, np.int64))

    def uncertainty(self, state: MapState, keyframes: list[Keyframe],
                    rows: npt.NDArray[np.int64]) -> PointUncertainty:
        """The depth uncertainty of the landmarks of pool ``rows`` (``keyframes`` as given to
        :meth:`gather`), along the rays from the keyframe each row came from."""
        sigmas = state.landmark_sigmas(self.landmark_ids[rows], 0.0)
        centres = np.array([kf.position_world for kf in keyframes]).reshape(-1, 3)
        return PointUncertainty(sigmas, centres[self.keyframe_rows[rows]])

    def rows_of(self, landmark_ids: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        """(M,) pool row of each landmark id; -1 where the pool does not hold it."""
        if len(self.landmark_ids) == 0:
            return np.full(len(landmark_ids), -1, np.int64)
        order = np.argsort(self.landmark_ids, kind="stable")
        pos = np.clip(np.searchsorted(self.landmark_ids[order], landmark_ids), 0, len(order) - 1)
        return np.where(self.landmark_ids[order][pos] == landmark_ids, order[pos], -1
                        ).astype(np.int64)

    def keyframes_of(self, rows: npt.NDArray[np.int64], keyframe_ids: list[int]) -> list[int]:
        """Ids of the keyframes whose landmarks (pool ``rows``) gave inliers, most first."""
        counts = np.bincount(self.keyframe_rows[rows], minlength=len(keyframe_ids))
        order = np.argsort(-counts, kind="stable")
        return [keyframe_ids[i] for i in order if counts[i] > 0]


class _SeenIds:
    """The landmark ids a pool holds so far, as a growing boolean table indexed by id."""

    def __init__(self) -> None:
        self._seen = np.zeros(0, bool)

    def take_new(self, ids: npt.NDArray[np.int64]) -> npt.NDArray[np.bool_]:
        """Which of ``ids`` (distinct, non-negative) were not seen before; marks them seen."""
        if len(ids) == 0:
            return np.zeros(0, bool)
        top = int(ids.max()) + 1
        if top > len(self._seen):
            grown = np.zeros(max(top, 2 * len(self._seen)), bool)
            grown[:len(self._seen)] = self._seen
            self._seen = grown
        new = ~self._seen[ids]
        self._seen[ids[new]] = True
        return new


#: Per keyframe features: the rows :meth:`LandmarkPool.gather` keeps of it alone (a few
#: kB each, weakly held: gone with the features). Features are never changed in place
#: (:meth:`Features.with_landmarks` copies), so the rows stay right while they live.
_LANDMARK_ROWS: weakref.WeakKeyDictionary[Features, npt.NDArray[np.int64]] = (
    weakref.WeakKeyDictionary())


def _landmark_rows(features: Features) -> npt.NDArray[np.int64]:
    """Rows of ``features`` with a landmark, the first row of each landmark id (ascending):
    the rows a pool of this keyframe alone holds. Computed once per features object (the
    fast path pools the best keyframe alone for every query)."""
    rows = _LANDMARK_ROWS.get(features)
    if rows is None:
        local = np.flatnonzero(features.landmark_ids >= 0)
        rows = local[np.sort(np.unique(features.landmark_ids[local], return_index=True)[1])]
        rows.flags.writeable = False
        _LANDMARK_ROWS[features] = rows
    return rows


def peek_features(kf: Keyframe, kind: str) -> Features | None:
    """``kf``'s ``kind`` features, read as :meth:`LandmarkPool.gather` reads them (without
    keeping them built on a keyframe loaded from a snapshot)."""
    return _peek(kf, kind)


#: Keyframes read from one snapshot's columns at once by :meth:`LandmarkPool.gather_streamed`:
#: most of the per-call work shared, the decoded rows of a few dozen keyframes held at a time
#: (a few MB), and a cancellation seen within one such read.
STORED_RUN = 64

#: Rows decoded between two cancel checks of :meth:`LandmarkPool._read`: a run of 64 stored
#: keyframes holds about 30000 SIFT rows of the fleet template, 25 ms of decoding that a
#: query arriving meanwhile shared the CPU with (the pools step aside only between units:
#: :mod:`...core.foreground`); a chunk of this size is a few milliseconds.
READ_CHUNK_ROWS = 4096


def _stored_runs(keyframes: list[Keyframe], kind: str
                 ) -> Iterator[tuple[int, Any, list[tuple[int, int]]]]:
    """``keyframes`` in turn as runs (first, columns, ranges): up to :data:`STORED_RUN`
    consecutive keyframes whose ``kind`` is read from the same snapshot columns (not built:
    ``LazyFeatures.stored_range``) and their rows (start, stop) there, or one keyframe read
    alone (columns None, no ranges)."""
    first, columns = 0, None
    ranges: list[tuple[int, int]] = []
    for row, kf in enumerate(keyframes):
        stored_range = getattr(kf.features, "stored_range", None)
        stored = None if stored_range is None else stored_range(kind)
        if ranges and (stored is None or stored[0] is not columns or len(ranges) >= STORED_RUN):
            yield first, columns, ranges
            ranges = []
        if stored is None:
            yield row, None, []
            continue
        if not ranges:
            first, columns = row, stored[0]
        ranges.append(stored[1:])
    if ranges:
        yield first, columns, ranges


def _peek(kf: Keyframe, kind: str) -> Features | None:
    """``kf``'s ``kind`` features, read without keeping them built on a keyframe loaded from
    a snapshot (a pool reads every keyframe once: kept, they took about 135 MB per 1000
    keyframes that no budget counted)."""
    peek = getattr(kf.features, "peek", None)
    return peek(kind) if peek is not None else kf.features.get(kind)
