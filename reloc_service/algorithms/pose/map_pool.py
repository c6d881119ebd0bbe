"""The landmarks of every keyframe of a map state, pooled and indexed for the repetition check
(:mod:`.repetition`): made once per map state and feature kind, and shared by every pose
finder of that kind over that state (a chain's ``p3p:sift-half`` and ``p3p`` steps hold one
SIFT pool, not two)."""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass

from ...core.map import MapState
from .landmark_pool import LandmarkPool
from .repetition_index import IndexConf, RepetitionIndex


@dataclass(frozen=True, eq=False)
class MapPool:
    """Every ``kind`` landmark of a map state (:meth:`LandmarkPool.gather` of its keyframes
    in ``keyframe_ids`` order) and its :class:`RepetitionIndex`."""

    pool: LandmarkPool
    index: RepetitionIndex
    keyframe_ids: list[int]

    @classmethod
    def make(cls, state: MapState, kind: str, conf: IndexConf) -> MapPool:
        ids = list(state.keyframes)
        pool = LandmarkPool.gather([state.keyframes[k] for k in ids], kind)
        return cls(pool, RepetitionIndex.build(pool.descriptors, conf), ids)

    @property
    def nbytes(self) -> int:
        """Bytes held: the pool's arrays and the index's own."""
        p = self.pool
        return (p.descriptors.nbytes + p.landmark_ids.nbytes + p.points_world.nbytes
                + p.keyframe_rows.nbytes + self.index.nbytes)


#: Pools by (state id, kind, index options); an entry goes with its state (the weak
#: reference's callback), so an id is never read for a later state that reuses it.
_POOLS: dict[tuple[int, str, IndexConf], tuple[weakref.ref[MapState], MapPool]] = {}
_LOCK = threading.Lock()


def map_pool(state: MapState, kind: str, conf: IndexConf) -> MapPool:
    """The :class:`MapPool` of ``state``'s ``kind`` landmarks, made on the first request for
    that state (two threads asking at once may both make it; one is kept)."""
    key = (id(state), kind, conf)
    with _LOCK:
        held = _POOLS.get(key)
    if held is not None and held[0]() is state:
        return held[1]
    made = MapPool.make(state, kind, conf)
    with _LOCK:
        held = _POOLS.get(key)
        if held is not None and held[0]() is state:
            return held[1]
        _POOLS[key] = (weakref.ref(state, lambda _, key=key: _forget(key)), made)  # type: ignore[misc]
    return made


def _forget(key: tuple[int, str, IndexConf]) -> None:
    with _LOCK:
        held = _POOLS.get(key)
        if held is not None and held[0]() is None:
            del _POOLS[key]
