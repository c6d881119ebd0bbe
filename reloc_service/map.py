"""The keyframe map: keyframes, landmarks with their observations, and a version counter.

Landmarks live in a :class:`LandmarkTable`: columns of ids, points, depth sigmas and CSR
observations (memory-mapped when loaded from a snapshot) plus a small copy-on-write overlay of
the landmarks changed since, so a map of 500k landmarks holds no 500k Python objects and a
change copies only what it touches.

A writer publishes a new immutable :class:`MapState` (copy on write); readers call
:meth:`KeyframeMap.snapshot` once and see one consistent map for as long as they hold it,
however many keyframes arrive meanwhile. One writer at a time: the map takes no lock (the
engine's writer mutex serialises its builder, see :mod:`reloc_service.engine`).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType

import numpy as np
import numpy.typing as npt

from .errors import MapError
from .frame import Features, Keyframe

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

    __slots__ = ("_base", "_overlay", "_len", "_overlay_cols")

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
        for lm_id in ids[hit].tolist():  # the overlay's landmarks only
            lm = self._overlay[lm_id]
            if lm is not None:
                kfs = sorted({o[0] for o in lm.observations})
                pairs.append(np.column_stack([np.full(len(kfs), -1 - lm_id), kfs]))
        seen = np.unique(np.concatenate(pairs).astype(np.int64), axis=0)
        kf_ids, votes = np.unique(seen[:, 1], return_counts=True)
        return kf_ids.astype(np.int64), votes.astype(np.int64)

    def _overlay_arrays(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_], Array,
                                       Array]:
        """The overlay as sorted columns (ids, alive, points, sigmas), made once per table
        (it never changes; two racing readers build the same arrays)."""
        cols = self._overlay_cols
        if cols is None:
            cols = self._overlay_cols = _overlay_columns(self._overlay)
        return cols

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


@dataclass(frozen=True)
class MapState:
    """An immutable view of the map at one version. ``landmarks`` is a
    :class:`LandmarkTable` (a plain mapping given here is converted)."""

    keyframes: Mapping[int, Keyframe] = field(default_factory=lambda: MappingProxyType({}))
    landmarks: LandmarkTable = field(default_factory=LandmarkTable)
    version: int = 0
    next_landmark_id: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.landmarks, LandmarkTable):
            object.__setattr__(self, "landmarks", LandmarkTable.from_mapping(self.landmarks))

    def keyframe(self, kf_id: int) -> Keyframe:
        """The keyframe ``kf_id``; MapError if it is not in the map."""
        try:
            return self.keyframes[kf_id]
        except KeyError:
            raise MapError(f"no keyframe {kf_id} in the map") from None

    def keyframe_ids(self) -> list[int]:
        """Keyframe ids in ascending order."""
        return sorted(self.keyframes)

    def positions_world(self, kf_ids: Iterable[int] | None = None) -> Array:
        """(K, 3) camera centres of ``kf_ids`` (default: all, ascending id)."""
        ids = self.keyframe_ids() if kf_ids is None else list(kf_ids)
        if not ids:
            return np.zeros((0, 3))
        return np.stack([self.keyframes[i].world_from_cam[:3, 3] for i in ids])

    def nearest_keyframes(self, world_from_cam: Array, count: int, max_view_angle_deg: float,
                          *, exclude: int | None = None) -> list[int]:
        """Up to ``count`` keyframe ids (not ``exclude``), nearest centre to
        ``world_from_cam``'s first, among those whose optical axis is within
        ``max_view_angle_deg`` of its optical axis (keyframes that see what it sees)."""
        ids = [k for k in self.keyframe_ids() if k != exclude]
        if not ids or count <= 0:
            return []
        poses = np.stack([self.keyframes[k].world_from_cam for k in ids])
        angle = np.arccos(np.clip(poses[:, :3, 2] @ world_from_cam[:3, 2], -1.0, 1.0))
        dist = np.linalg.norm(poses[:, :3, 3] - world_from_cam[:3, 3], axis=1)
        ok = np.flatnonzero(angle <= np.deg2rad(max_view_angle_deg))
        return [ids[i] for i in ok[np.argsort(dist[ok], kind="stable")][:count]]

    def landmark_points(self, landmark_ids: npt.ArrayLike) -> Array:
        """(L, 3) world points of ``landmark_ids`` (vectorised; KeyError on an unknown id)."""
        return self.landmarks.points(landmark_ids)

    def landmark_sigmas(self, landmark_ids: npt.ArrayLike, default: float = 0.0) -> Array:
        """(L,) depth sigmas of ``landmark_ids``; ``default`` where an id is not a landmark."""
        return self.landmarks.sigmas(landmark_ids, default)

    def landmark_count(self, kind: str | None = None) -> int:
        """Number of landmarks (observed through ``kind`` features, if given)."""
        if kind is None:
            return len(self.landmarks)
        cols = self.landmarks.columns()
        if kind not in cols.kinds:
            return 0
        hit = cols.obs_kind == cols.kinds.index(kind)
        owner = np.repeat(np.arange(len(cols)), np.diff(cols.obs_offsets))
        return int(np.count_nonzero(np.bincount(owner[hit], minlength=len(cols))))


class KeyframeMap:
    """A versioned keyframe map (copy on write; see module docstring).

    Readers need no lock: :meth:`snapshot` returns the last published state, which never
    changes, and publishing is one attribute store. Writers are NOT thread-safe: each one reads
    the current state, copies and publishes it, so two concurrent writers would lose one's
    change. Only one thread may write at a time (the engine's writer mutex guarantees it)."""

    def __init__(self) -> None:
        self._state = MapState()

    # -- readers -------------------------------------------------------------------------------
    def snapshot(self) -> MapState:
        """The current immutable state; cheap (no copy)."""
        return self._state

    @property
    def version(self) -> int:
        return self._state.version

    def __len__(self) -> int:
        return len(self._state.keyframes)

    def __contains__(self, kf_id: object) -> bool:
        return kf_id in self._state.keyframes

    # -- writers -------------------------------------------------------------------------------
    def add_keyframe(self, keyframe: Keyframe) -> MapState:
        """Add ``keyframe``, or replace the keyframe with the same id (its old observations and
        the landmarks left without any are removed first). Keypoints that already carry a
        landmark id and a 3D point (as SVO sends them) register that landmark: an id unknown to
        the map creates it, a known one gains an observation."""
        keyframes = dict(self._state.keyframes)
        landmarks = self._state.landmarks.editor()
        if keyframe.id in keyframes:
            _drop_observations(keyframes.pop(keyframe.id), landmarks)
        keyframes[keyframe.id] = keyframe
        next_id = self._state.next_landmark_id
        for kind, feats in keyframe.features.items():
            given_next = _register_given_landmarks(keyframe.id, kind, feats, landmarks)
            next_id = max(next_id, given_next)
        return self._publish(keyframes, landmarks, next_id)

    def remove_keyframe(self, kf_id: int) -> MapState:
        """Remove keyframe ``kf_id`` and its observations; landmarks left with no observation
        are removed. MapError if the id is unknown."""
        keyframes = dict(self._state.keyframes)
        if kf_id not in keyframes:
            raise MapError(f"cannot remove keyframe {kf_id}: not in the map")
        landmarks = self._state.landmarks.editor()
        _drop_observations(keyframes.pop(kf_id), landmarks)
        return self._publish(keyframes, landmarks, self._state.next_landmark_id)

    def add_landmarks(self, kind: str, points_world: npt.ArrayLike,
                      observations: Iterable[Iterable[tuple[int, int]]], *,
                      depth_sigmas_m: npt.ArrayLike | None = None) -> list[int]:
        """Create landmarks at ``points_world`` (L, 3), each observed by the given
        ``(keyframe id, keypoint index)`` pairs of features ``kind``, with their depth
        uncertainty (L,) if known; the keyframes' features are updated to point at them.
        Returns the new landmark ids. A keypoint that already has a landmark keeps it (that
        observation is skipped)."""
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        obs_lists = [list(o) for o in observations]
        if len(obs_lists) != len(pts):
            raise MapError(f"add_landmarks: {len(pts)} points but {len(obs_lists)} "
                           "observation lists")
        sigmas = (np.zeros(len(pts)) if depth_sigmas_m is None
                  else np.asarray(depth_sigmas_m, dtype=np.float64).reshape(-1))
        if len(sigmas) != len(pts) or not np.all(np.isfinite(sigmas) & (sigmas >= 0)):
            raise MapError(f"add_landmarks: expected {len(pts)} finite depth sigmas >= 0")
        keyframes = dict(self._state.keyframes)
        landmarks = self._state.landmarks.editor()
        next_id = self._state.next_landmark_id
        updates: dict[int, list[tuple[int, int, Array]]] = {}
        new_ids: list[int] = []
        taken: set[tuple[int, int]] = set()
        for point, obs, sigma in zip(pts, obs_lists, sigmas.tolist(), strict=True):
            fresh = [(k, i) for k, i in obs if k in keyframes and (k, i) not in taken
                     and keyframes[k].features[kind].landmark_ids[i] < 0]
            taken.update(fresh)
            if not fresh:
                continue
            lm_id = next_id
            next_id += 1
            landmarks[lm_id] = Landmark(lm_id, point.copy(),
                                        frozenset((k, kind, int(i)) for k, i in fresh),
                                        sigma)
            for k, i in fresh:
                updates.setdefault(k, []).append((int(i), lm_id, point))
            new_ids.append(lm_id)
        _apply_updates(keyframes, kind, updates)
        self._publish(keyframes, landmarks, next_id)
        return new_ids

    def add_observations(self, kind: str, triples: Iterable[tuple[int, int, int]]) -> int:
        """Attach keypoints to existing landmarks: ``(landmark id, keyframe id, keypoint index)``.
        Keypoints that already have a landmark, unknown landmarks or keyframes are skipped.
        Returns the number of observations added."""
        keyframes = dict(self._state.keyframes)
        landmarks = self._state.landmarks.editor()
        updates: dict[int, list[tuple[int, int, Array]]] = {}
        taken: set[tuple[int, int]] = set()
        for lm_id, k, i in triples:
            if lm_id not in landmarks or k not in keyframes or (k, i) in taken:
                continue
            if keyframes[k].features[kind].landmark_ids[i] >= 0:
                continue
            taken.add((k, i))
            lm = landmarks[lm_id]
            landmarks[lm_id] = replace(lm, observations=lm.observations | {(k, kind, int(i))})
            updates.setdefault(k, []).append((int(i), lm_id, lm.point_world))
        _apply_updates(keyframes, kind, updates)
        self._publish(keyframes, landmarks, self._state.next_landmark_id)
        return len(taken)

    def move_landmarks(self, landmark_ids: npt.ArrayLike, points_world: npt.ArrayLike) -> MapState:
        """Move landmarks to new world points (L, 3), in the landmarks and in the features of
        the keyframes observing them (after a re-refinement with more observations)."""
        ids = np.asarray(landmark_ids, dtype=np.int64).ravel()
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        if len(ids) != len(pts):
            raise MapError(f"move_landmarks: {len(ids)} ids but {len(pts)} points")
        if len(ids) == 0:
            return self._state
        order = np.argsort(ids)
        ids, pts = ids[order], pts[order]
        keyframes = dict(self._state.keyframes)
        landmarks = self._state.landmarks.editor()
        observers: set[int] = set()
        for lm_id, point in zip(ids.tolist(), pts, strict=True):
            lm = landmarks[lm_id]
            landmarks[lm_id] = replace(lm, point_world=point.copy())
            observers.update(o[0] for o in lm.observations)
        for k in observers:
            keyframes[k] = _with_moved_points(keyframes[k], ids, pts)
        return self._publish(keyframes, landmarks, self._state.next_landmark_id)

    def replace_state(self, state: MapState) -> None:
        """Install a whole state (used when loading a saved map)."""
        self._state = state

    def _publish(self, keyframes: dict[int, Keyframe], landmarks: LandmarkEditor,
                 next_landmark_id: int) -> MapState:
        self._state = MapState(MappingProxyType(keyframes), landmarks.commit(),
                               self._state.version + 1, next_landmark_id)
        return self._state


def _drop_observations(keyframe: Keyframe, landmarks: LandmarkEditor) -> None:
    """Remove ``keyframe``'s observations from ``landmarks`` (in place); drop emptied ones."""
    for kind, feats in keyframe.features.items():
        for idx in np.flatnonzero(feats.landmark_ids >= 0):
            lm_id = int(feats.landmark_ids[idx])
            lm = landmarks.get(lm_id)
            if lm is None:
                continue
            remaining = lm.observations - {(keyframe.id, kind, int(idx))}
            if remaining:
                landmarks[lm_id] = replace(lm, observations=remaining)
            else:
                del landmarks[lm_id]


def _register_given_landmarks(kf_id: int, kind: str, feats: Features,
                              landmarks: LandmarkEditor) -> int:
    """Register landmarks that arrive with a keyframe; returns the next free landmark id."""
    next_id = 0
    for idx in np.flatnonzero(feats.landmark_ids >= 0):
        lm_id = int(feats.landmark_ids[idx])
        obs = (kf_id, kind, int(idx))
        lm = landmarks.get(lm_id)
        if lm is None:
            point = feats.points_world[idx]
            if not np.all(np.isfinite(point)):
                raise MapError(f"keyframe {kf_id}: landmark {lm_id} has no finite 3D point")
            landmarks[lm_id] = Landmark(lm_id, point.copy(), frozenset({obs}))
        else:
            landmarks[lm_id] = replace(lm, observations=lm.observations | {obs})
        next_id = max(next_id, lm_id + 1)
    return next_id


def _with_moved_points(keyframe: Keyframe, sorted_ids: npt.NDArray[np.int64],
                       points_world: Array) -> Keyframe:
    """``keyframe`` with the points of landmarks ``sorted_ids`` replaced by ``points_world``."""
    for kind, feats in keyframe.features.items():
        idx = np.flatnonzero(np.isin(feats.landmark_ids, sorted_ids))
        if len(idx):
            pos = np.searchsorted(sorted_ids, feats.landmark_ids[idx])
            keyframe = keyframe.with_features(
                kind, feats.with_landmarks(idx, feats.landmark_ids[idx], points_world[pos]))
    return keyframe


def _apply_updates(keyframes: dict[int, Keyframe], kind: str,
                   updates: dict[int, list[tuple[int, int, Array]]]) -> None:
    """Write landmark ids and points into the keyframes' features (new keyframe objects)."""
    for k, rows in updates.items():
        idx = [r[0] for r in rows]
        ids = [r[1] for r in rows]
        pts = np.stack([r[2] for r in rows])
        kf = keyframes[k]
        keyframes[k] = kf.with_features(kind, kf.features[kind].with_landmarks(idx, ids, pts))
