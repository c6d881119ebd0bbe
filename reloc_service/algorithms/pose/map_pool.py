"""The landmarks of every keyframe of a map state, pooled and indexed for the repetition check
(:mod:`.repetition`): made once per map state and feature kind, and shared by every pose
finder of that kind over that state (a chain's ``p3p:sift-half`` and ``p3p`` steps hold one
SIFT pool, not two)."""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable
from dataclasses import dataclass

from ...core.foreground import waiting_for_background
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
    def make(cls, state: MapState, kind: str, conf: IndexConf,
             cancelled: Callable[[], bool] | None = None) -> MapPool:
        """The pool of ``state``'s ``kind`` landmarks and its index, built;
        :class:`~reloc_service.core.errors.Cancelled` once ``cancelled()`` is true (checked
        between the keyframes gathered and the index's chunks: what was made is dropped)."""
        ids = list(state.keyframes)
        pool = LandmarkPool.gather_streamed([state.keyframes[k] for k in ids], kind,
                                            cancelled)
        return cls(pool, RepetitionIndex.build(pool.descriptors, conf, cancelled=cancelled), ids)

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
#: Pools being made; a thread that wants one of them waits for ``_MADE``.
_MAKING: set[tuple[int, str, IndexConf]] = set()
_MADE = threading.Condition(_LOCK)


def map_pool(state: MapState, kind: str, conf: IndexConf,
             make: Callable[[], MapPool] | None = None) -> MapPool:
    """The :class:`MapPool` of ``state``'s ``kind`` landmarks, made on the first request for
    that state (by ``make``, default :meth:`MapPool.make`: a pool read from a snapshot); a
    request while another thread makes it waits for that one (one pool in memory, not
    two)."""
    key = (id(state), kind, conf)
    with _LOCK:
        while True:
            held = _POOLS.get(key)
            if held is not None and held[0]() is state:
                return held[1]
            if key not in _MAKING:
                _MAKING.add(key)
                break
            with waiting_for_background():   # the pool's maker must not step aside for us
                _MADE.wait()
    try:
        made = make() if make is not None else MapPool.make(state, kind, conf)
        return keep_pool(state, kind, conf, made)
    finally:
        with _LOCK:
            _MAKING.discard(key)
            _MADE.notify_all()


def being_made(state: MapState, kind: str, conf: IndexConf) -> bool:
    """Whether some thread is making the pool of ``state``'s ``kind`` landmarks (a request
    for it now waits for that thread)."""
    with _LOCK:
        return (id(state), kind, conf) in _MAKING


def held_pool(state: MapState, kind: str, conf: IndexConf) -> MapPool | None:
    """The pool of ``state``'s ``kind`` landmarks if one is made, else None (nothing made)."""
    with _LOCK:
        held = _POOLS.get((id(state), kind, conf))
    return held[1] if held is not None and held[0]() is state else None


def keep_pool(state: MapState, kind: str, conf: IndexConf, made: MapPool) -> MapPool:
    """Keep ``made`` as the pool of ``state``'s ``kind`` landmarks (one read from a snapshot,
    or just made), unless one is kept already: the one kept."""
    key = (id(state), kind, conf)
    with _LOCK:
        held = _POOLS.get(key)
        if held is not None and held[0]() is state:
            return held[1]
        _POOLS[key] = (weakref.ref(state, lambda _, key=key: _forget(key)), made)  # type: ignore[misc]
    return made


def pools_of(state: MapState) -> list[tuple[str, IndexConf, MapPool]]:
    """(kind, index options, pool) of every pool made for ``state``."""
    with _LOCK:
        held = [(key, entry) for key, entry in _POOLS.items() if key[0] == id(state)]
    return [(key[1], key[2], entry[1]) for key, entry in held if entry[0]() is state]


def pool_bytes(state: MapState) -> int:
    """Bytes held by the pools made for ``state`` (what its repetition check keeps in
    memory beside the map: about 80 MB per 1000 keyframes of SIFT landmarks)."""
    return sum(made.nbytes for _, _, made in pools_of(state))


def _forget(key: tuple[int, str, IndexConf]) -> None:
    with _LOCK:
        held = _POOLS.get(key)
        if held is not None and held[0]() is None:
            del _POOLS[key]
