"""The map's landmarks as a table: columns of ids, points, depth sigmas and CSR observations
(memory-mapped when loaded from a snapshot) plus a small copy-on-write overlay of the
landmarks changed since (:class:`LandmarkTable`), so a map of 500k landmarks holds no 500k
Python objects and a change copies only what it touches; :class:`LandmarkEditor` collects one
map write's changes. :mod:`.map` holds the table in each :class:`~.map.MapState`."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

#: An observation: (keyframe id, feature kind, keypoint index in that keyframe's features).
Observation = tuple[int, str, int]


@dataclass(frozen=True)
class Landmark:
    """A 3D point of the map and the keypoints that observe it."""

    id: int
    point_world: Array
    observations: frozenset[Observation]
    #: 1-sigma uncertainty of the point along the ray of the keyframe that created it,
    #: metres (from the triangulation's information matrix); 0 where unknown (depth maps,
    #: client-given points).
    depth_sigma_m: float = 0.0


#: Overlay entries (changed or removed landmarks) above which a table is compacted into new
#: columns: a fixed floor so small maps do not compact on every change, and a share of the
#: base so the O(L) compaction is amortised over O(L) changes.
COMPACT_MIN_OVERLAY = 8192
COMPACT_SHARE = 8


@dataclass(frozen=True, eq=False)
class LandmarkColumns:
    """Landmarks as columns (what a snapshot saves and memory-maps): ``ids`` (L,) int64
    ascending, ``points_world`` (L, 3) float64, ``depth_sigmas_m`` (L,) float64, and the
    observations in CSR form: landmark i's are rows ``obs_offsets[i]:obs_offsets[i + 1]`` of
    ``obs_keyframe`` (int64), ``obs_kind`` (int16 index into ``kinds``), ``obs_keypoint``
    (int64). Point and sigma are read as float64: a landmark is a world coordinate, and
    world float32 would move points 100 m from the origin by up to 4 micrometres (a snapshot
    stores float32 offsets from an observing keyframe instead, where that is far below the
    landmark's uncertainty, and a loaded map decodes their rows on read: points and sigmas
    are then :class:`~.landmark_codec.RowDecoded` columns, gathered by row like arrays)."""

    ids: npt.NDArray[np.int64]
    points_world: Array
    depth_sigmas_m: Array
    obs_offsets: npt.NDArray[np.int64]
    obs_keyframe: npt.NDArray[np.int64]
    obs_kind: npt.NDArray[np.int16]
    obs_keypoint: npt.NDArray[np.int64]
    kinds: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.ids)

    @classmethod
    def empty(cls) -> LandmarkColumns:
        z = np.zeros(0, np.int64)
        return cls(z, np.zeros((0, 3)), np.zeros(0), np.zeros(1, np.int64), z,
                   np.zeros(0, np.int16), z, ())

    @classmethod
    def from_landmarks(cls, landmarks: Iterable[Landmark]) -> LandmarkColumns:
        """Columns of ``landmarks`` (any order; sorted by id here)."""
        lms = sorted(landmarks, key=lambda lm: lm.id)
        if not lms:
            return cls.empty()
        kinds = tuple(sorted({o[1] for lm in lms for o in lm.observations}))
        kind_index = {k: i for i, k in enumerate(kinds)}
        flat = [o for lm in lms for o in sorted(lm.observations)]
        counts = np.fromiter((len(lm.observations) for lm in lms), np.int64, len(lms))
        return cls(np.fromiter((lm.id for lm in lms), np.int64, len(lms)),
                   np.stack([np.asarray(lm.point_world, np.float64) for lm in lms]),
                   np.fromiter((lm.depth_sigma_m for lm in lms), np.float64, len(lms)),
                   np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
                   np.fromiter((o[0] for o in flat), np.int64, len(flat)),
                   np.fromiter((kind_index[o[1]] for o in flat), np.int16, len(flat)),
                   np.fromiter((o[2] for o in flat), np.int64, len(flat)), kinds)

    def rows(self, landmark_ids: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        """(N,) row of each id; -1 where absent."""
        if len(self.ids) == 0:
            return np.full(len(landmark_ids), -1, np.int64)
        pos = np.clip(np.searchsorted(self.ids, landmark_ids), 0, len(self.ids) - 1)
        return np.where(self.ids[pos] == landmark_ids, pos, -1)

    def landmark(self, row: int) -> Landmark:
        a, b = int(self.obs_offsets[row]), int(self.obs_offsets[row + 1])
        kinds = self.kinds
        obs = frozenset(zip(self.obs_keyframe[a:b].tolist(),
                            [kinds[k] for k in self.obs_kind[a:b].tolist()],
                            self.obs_keypoint[a:b].tolist(), strict=True))
        return Landmark(int(self.ids[row]), self.points_world[row], obs,
                        float(self.depth_sigmas_m[row]))

    def select(self, keep: npt.NDArray[np.bool_]) -> LandmarkColumns:
        """The rows where ``keep`` (L,) is True (vectorised, observations included)."""
        counts = np.diff(self.obs_offsets)
        obs_keep = np.repeat(keep, counts)
        return LandmarkColumns(self.ids[keep], self.points_world[keep],
                               self.depth_sigmas_m[keep],
                               np.concatenate([[0], np.cumsum(counts[keep])]).astype(np.int64),
                               self.obs_keyframe[obs_keep], self.obs_kind[obs_keep],
                               self.obs_keypoint[obs_keep], self.kinds)

    @staticmethod
    def merge(a: LandmarkColumns, b: LandmarkColumns) -> LandmarkColumns:
        """Rows of ``a`` and ``b`` (disjoint ids), sorted by id."""
        kinds = tuple(sorted(set(a.kinds) | set(b.kinds)))
        remap_a = np.array([kinds.index(k) for k in a.kinds] or [0], np.int16)
        remap_b = np.array([kinds.index(k) for k in b.kinds] or [0], np.int16)
        ids = np.concatenate([a.ids, b.ids])
        order = np.argsort(ids, kind="stable")
        counts = np.concatenate([np.diff(a.obs_offsets), np.diff(b.obs_offsets)])
        starts = np.concatenate([a.obs_offsets[:-1], b.obs_offsets[:-1] + a.obs_offsets[-1]])
        # gather each landmark's observation run in the new order
        run = np.repeat(starts[order] - np.concatenate([[0], np.cumsum(counts[order])[:-1]]),
                        counts[order]) + np.arange(int(counts.sum()))
        kind = np.concatenate([remap_a[a.obs_kind], remap_b[b.obs_kind]]) if len(counts) else \
            np.zeros(0, np.int16)
        return LandmarkColumns(
            ids[order], np.concatenate([a.points_world, b.points_world])[order],
            np.concatenate([a.depth_sigmas_m, b.depth_sigmas_m])[order],
            np.concatenate([[0], np.cumsum(counts[order])]).astype(np.int64),
            np.concatenate([a.obs_keyframe, b.obs_keyframe])[run],
            kind[run].astype(np.int16),
            np.concatenate([a.obs_keypoint, b.obs_keypoint])[run], kinds)


class LandmarkTable(Mapping[int, Landmark]):
    """An immutable ``landmark id -> Landmark`` mapping stored as columns.

    ``base`` holds frozen columns (possibly memory-mapped from a snapshot); ``overlay`` the
    landmarks changed since (a :class:`Landmark`, or None for a removed one). A map change
    copies only the overlay, so adding a keyframe to a map of 500k landmarks costs what it
    changes; the overlay is folded into new columns once it outgrows its share of the base.
    ``Landmark`` objects are made on access; the hot paths use the vectorised
    :meth:`points`, :meth:`sigmas`, :meth:`contains` and :meth:`id_array` instead."""

    __slots__ = ("_base", "_overlay", "_len", "_overlay_cols", "_overlay_obs")

    def __init__(self, base: LandmarkColumns | None = None,
                 overlay: Mapping[int, Landmark | None] | None = None, *,
                 length: int | None = None) -> None:
        self._base = base if base is not None else LandmarkColumns.empty()
        self._overlay: dict[int, Landmark | None] = dict(overlay or {})
        if length is None:
            shadowed = self._in_base(np.fromiter(self._overlay, np.int64, len(self._overlay)))
            added = sum(v is not None for v in self._overlay.values())
            length = len(self._base) - int(shadowed.sum()) + added
        self._len = length
        self._overlay_cols: tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_], Array,
                                  Array] | None = None
        self._overlay_obs: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]] | None = None

    @classmethod
    def from_mapping(cls, landmarks: Mapping[int, Landmark]) -> LandmarkTable:
        if isinstance(landmarks, LandmarkTable):
            return landmarks
        return cls(LandmarkColumns.from_landmarks(landmarks.values()))

    def _in_base(self, ids: npt.NDArray[np.int64]) -> npt.NDArray[np.bool_]:
        return self._base.rows(ids) >= 0

    # -- Mapping -------------------------------------------------------------------------------
    def __getitem__(self, lm_id: int) -> Landmark:
        if lm_id in self._overlay:
            lm = self._overlay[lm_id]
            if lm is None:
                raise KeyError(lm_id)
            return lm
        row = int(self._base.rows(np.array([lm_id], np.int64))[0])
        if row < 0:
            raise KeyError(lm_id)
        return self._base.landmark(row)

    def __contains__(self, lm_id: object) -> bool:
        if lm_id in self._overlay:
            return self._overlay[lm_id] is not None  # type: ignore[index]
        if not isinstance(lm_id, int | np.integer):
            return False
        return bool(self._base.rows(np.array([lm_id], np.int64))[0] >= 0)

    def __iter__(self) -> Iterator[int]:
        return iter(self.id_array().tolist())

    def __len__(self) -> int:
        return self._len

    # -- vectorised ----------------------------------------------------------------------------
    def id_array(self) -> npt.NDArray[np.int64]:
        """(L,) every landmark id, ascending."""
        if not self._overlay:
            return np.asarray(self._base.ids)
        ov, alive = self._overlay_arrays()[:2]
        base = self._base.ids[~np.isin(self._base.ids, ov)]
        # disjoint sets: a sort, not np.union1d (whose hashing unique took seconds here)
        return np.sort(np.concatenate([base, ov[alive]]))

    def contains(self, landmark_ids: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """(N,) whether each id is a landmark."""
        ids = np.asarray(landmark_ids, np.int64).ravel()
        found = self._base.rows(ids) >= 0
        hit, pos = self._overlay_rows(ids)
        found[hit] = self._overlay_arrays()[1][pos]
        return found

    def points(self, landmark_ids: npt.ArrayLike) -> Array:
        """(N, 3) world points of ``landmark_ids`` (KeyError if one is not a landmark)."""
        return self._column(landmark_ids, "points_world", 2)

    def sigmas(self, landmark_ids: npt.ArrayLike, default: float | None = None) -> Array:
        """(N,) depth sigmas of ``landmark_ids``; ``default`` for ids that are not landmarks
        (KeyError if None)."""
        return self._column(landmark_ids, "depth_sigmas_m", 3, default)

    def observing_keyframes(self, landmark_ids: npt.ArrayLike
                            ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """Keyframes observing the distinct ``landmark_ids`` (ids that are not landmarks are
        ignored): (K,) keyframe ids ascending and (K,) how many of those landmarks each
        observes (a landmark counts once per keyframe, whatever its observations' kinds).
        Vectorised over the base's observation runs; only overlay landmarks are objects."""
        ids = np.unique(np.asarray(landmark_ids, np.int64).ravel())
        hit, pos = self._overlay_rows(ids)
        in_overlay = np.zeros(len(ids), bool)
        in_overlay[hit] = True
        base = self._base
        rows = base.rows(ids[~in_overlay])
        rows = rows[rows >= 0]
        starts, counts = base.obs_offsets[rows], np.diff(base.obs_offsets)[rows]
        run = np.repeat(starts - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())
        pairs = [np.column_stack([np.repeat(rows, counts), base.obs_keyframe[run]])]
        if len(hit):  # the overlay's landmarks, keyed apart from the base's rows
            pair_ids, pair_kfs = self._overlay_observations()
            wanted = ids[hit]
            lo = np.searchsorted(pair_ids, wanted, "left")
            n = np.searchsorted(pair_ids, wanted, "right") - lo
            at = np.repeat(lo - np.cumsum(n) + n, n) + np.arange(n.sum())
            pairs.append(np.column_stack([-1 - pair_ids[at], pair_kfs[at]]))
        both = np.concatenate(pairs).astype(np.int64)
        # Distinct (landmark, keyframe) pairs through one int64 key per pair: np.unique with
        # axis=0 sorts the rows as records, several times slower on a pose's inliers.
        span = int(both[:, 1].max()) + 1 if len(both) else 1
        _, first = np.unique((both[:, 0] - both[:, 0].min(initial=0)) * span + both[:, 1],
                             return_index=True)
        kf_ids, votes = np.unique(both[first, 1], return_counts=True)
        return kf_ids.astype(np.int64), votes.astype(np.int64)

    def _overlay_arrays(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_], Array,
                                       Array]:
        """The overlay as sorted columns (ids, alive, points, sigmas), made once per table
        (it never changes; two racing readers build the same arrays)."""
        cols = self._overlay_cols
        if cols is None:
            cols = self._overlay_cols = _overlay_columns(self._overlay)
        return cols

    def _overlay_observations(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """The overlay's live landmarks' (landmark id, keyframe id) pairs, one per distinct
        pair, as two (P,) columns sorted by landmark id (made once per table, as
        :meth:`_overlay_arrays`)."""
        pairs = self._overlay_obs
        if pairs is None:
            pairs = self._overlay_obs = _overlay_observation_pairs(self._overlay)
        return pairs

    def _overlay_rows(self, ids: npt.NDArray[np.int64]
                      ) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
        """Positions in ``ids`` that the overlay holds, and their rows in its columns."""
        if not self._overlay:
            return np.zeros(0, np.intp), np.zeros(0, np.intp)
        ov = self._overlay_arrays()[0]
        pos = np.clip(np.searchsorted(ov, ids), 0, len(ov) - 1)
        hit = np.flatnonzero(ov[pos] == ids)
        return hit, pos[hit]

    def _column(self, landmark_ids: npt.ArrayLike, name: str, index: int,
                default: float | None = None) -> Array:
        ids = np.asarray(landmark_ids, np.int64).ravel()
        column = getattr(self._base, name)
        rows = self._base.rows(ids)
        missing = rows < 0
        out = np.array(column[np.maximum(rows, 0)] if len(column) else
                       np.zeros((len(ids), *column.shape[1:])), np.float64)
        hit, pos = self._overlay_rows(ids)
        overlay = self._overlay_arrays() if len(hit) else None
        if overlay is not None:
            missing[hit] = ~overlay[1][pos]
            out[hit] = overlay[index][pos]
        if missing.any():
            if default is None:
                raise KeyError(int(ids[np.flatnonzero(missing)[0]]))
            out[missing] = default
        return out

    # -- copy on write -------------------------------------------------------------------------
    def evolve(self, changes: Mapping[int, Landmark | None]) -> LandmarkTable:
        """A new table with ``changes`` applied (None removes); this one is unchanged."""
        if not changes:
            return self
        ids = np.fromiter(changes, np.int64, len(changes))
        now = np.fromiter((v is not None for v in changes.values()), bool, len(changes))
        # The length follows from what the changes touch: no pass over the whole overlay.
        overlay = self._overlay
        was = self._base.rows(ids) >= 0
        for i, lm_id in enumerate(ids.tolist()):     # the changes only, not the overlay
            if lm_id in overlay:
                was[i] = overlay[lm_id] is not None
        length = self._len + int(now.sum()) - int(was.sum())
        table = LandmarkTable(self._base, {**self._overlay, **changes}, length=length)
        if len(table._overlay) > max(COMPACT_MIN_OVERLAY, len(self._base) // COMPACT_SHARE):
            return LandmarkTable(table.columns())
        # The overlay's columns follow from the previous ones and the changes (vectorised),
        # so the first query after a publish does not rebuild them from the whole overlay.
        old, new = self._overlay_arrays(), _overlay_columns(changes)
        keep = ~np.isin(old[0], new[0])
        merged = [np.concatenate([o[keep], n]) for o, n in zip(old, new, strict=True)]
        order = np.argsort(merged[0], kind="stable")
        table._overlay_cols = (merged[0][order], merged[1][order], merged[2][order],
                               merged[3][order])
        if self._overlay_obs is not None:  # likewise the observation pairs, once made
            (old_ids, old_kfs), (new_ids, new_kfs) = (self._overlay_obs,
                                                      _overlay_observation_pairs(changes))
            kept = ~np.isin(old_ids, ids)
            pair_ids = np.concatenate([old_ids[kept], new_ids])
            order = np.argsort(pair_ids, kind="stable")
            table._overlay_obs = (pair_ids[order],
                                  np.concatenate([old_kfs[kept], new_kfs])[order])
        return table

    def columns(self) -> LandmarkColumns:
        """All landmarks as one set of columns (the base itself when nothing changed)."""
        if not self._overlay:
            return self._base
        ov = np.fromiter(self._overlay, np.int64, len(self._overlay))
        kept = self._base.select(~np.isin(self._base.ids, ov))
        added = LandmarkColumns.from_landmarks(v for v in self._overlay.values() if v is not None)
        return LandmarkColumns.merge(kept, added)

    def editor(self) -> LandmarkEditor:
        return LandmarkEditor(self)


def _overlay_columns(overlay: Mapping[int, Landmark | None]
                     ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_], Array, Array]:
    """(ids ascending, alive, points (NaN if removed), sigmas) of an overlay."""
    ids = np.fromiter(overlay, np.int64, len(overlay))
    order = np.argsort(ids)
    lms = [overlay[int(i)] for i in ids[order]]
    alive = np.array([lm is not None for lm in lms], bool)
    points = np.array([lm.point_world if lm is not None else (np.nan,) * 3 for lm in lms],
                      np.float64).reshape(-1, 3)
    sigmas = np.array([lm.depth_sigma_m if lm is not None else np.nan for lm in lms],
                      np.float64)
    return ids[order], alive, points, sigmas


def _overlay_observation_pairs(overlay: Mapping[int, Landmark | None]
                               ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(P,) landmark ids ascending and (P,) keyframe ids: one row per distinct keyframe
    observing each live landmark of an overlay."""
    per = [(lm_id, {o[0] for o in lm.observations}) for lm_id, lm in overlay.items()
           if lm is not None]
    lengths = np.fromiter((len(kfs) for _, kfs in per), np.int64, len(per))
    lm_ids = np.repeat(np.fromiter((i for i, _ in per), np.int64, len(per)), lengths)
    kf_ids = np.fromiter((kf for _, kfs in per for kf in kfs), np.int64, int(lengths.sum()))
    order = np.argsort(lm_ids, kind="stable")
    return lm_ids[order], kf_ids[order]


class LandmarkEditor:
    """The changes of one map write: reads see the table with the changes so far; ``commit``
    returns the new table (copy on write)."""

    def __init__(self, table: LandmarkTable) -> None:
        self._table = table
        self._changes: dict[int, Landmark | None] = {}

    def get(self, lm_id: int) -> Landmark | None:
        if lm_id in self._changes:
            return self._changes[lm_id]
        return self._table.get(lm_id)

    def __getitem__(self, lm_id: int) -> Landmark:
        lm = self.get(lm_id)
        if lm is None:
            raise KeyError(lm_id)
        return lm

    def __contains__(self, lm_id: int) -> bool:
        return self.get(lm_id) is not None

    def __setitem__(self, lm_id: int, landmark: Landmark) -> None:
        self._changes[lm_id] = landmark

    def __delitem__(self, lm_id: int) -> None:
        if lm_id not in self:
            raise KeyError(lm_id)
        self._changes[lm_id] = None

    def commit(self) -> LandmarkTable:
        return self._table.evolve(self._changes)
