"""The whole-map work of a relocalizer's pose finders done when its map is loaded rather than
by the first query: each p3p finder's landmark pool and repetition index
(:mod:`..pose.map_pool`, read from the snapshot where it was stored with the model,
:mod:`..pose.repetition_store`), in the order the relocalizer's steps run, so the first
step's pool is ready first. The keyframes' agreement with the map's camera is left to the
queries that read it (a few keyframes each; the whole map's takes seconds of CPU the first
queries would compete with), or read from the snapshot where stored
(:mod:`.map_statistics`)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path

from ...core.errors import Cancelled, StorageError
from ...core.foreground import yielding
from ...core.map import MapState
from ..pose.map_pool import MapPool, held_pool, map_pool
from ..pose.p3p import P3PPoseFinder
from ..pose.repetition_index import IndexConf
from ..pose.repetition_store import copy_index, load_index, save_index
from .base import Relocalizer

log = logging.getLogger(__name__)


def pool_finders(relocalizer: Relocalizer) -> list[P3PPoseFinder]:
    """The p3p pose finders of ``relocalizer`` (a chain's steps in order), one per distinct
    feature kind and index options (two finders of one kind share a pool)."""
    steps = getattr(relocalizer, "steps", None)
    found: list[P3PPoseFinder] = []
    for step in (steps if steps is not None else [relocalizer]):
        if steps is not None:
            found += pool_finders(step)
            continue
        pose = getattr(step, "pose", None)
        if isinstance(pose, P3PPoseFinder):
            found.append(pose)
    seen: set[tuple[str, object]] = set()
    unique = []
    for finder in found:
        key = (finder.conf.kind, finder.conf.repetition_index())
        if key not in seen:
            seen.add(key)
            unique.append(finder)
    return unique


def save_pools(relocalizer: Relocalizer, directory: Path, state: MapState,
               stored: Path | None = None) -> list[Path]:
    """Store beside ``relocalizer``'s model in ``directory`` the indexes of the pools made
    for ``state``; a pool not made here (an engine that answers no query: a service's, with
    worker processes) has its index copied from model directory ``stored``, where ``state``
    was loaded from, if given (none is made here: else it is built at the next load)."""
    written = []
    for finder in pool_finders(relocalizer):
        conf = finder.conf.repetition_index()
        made = held_pool(state, finder.conf.kind, conf)
        if made is not None:
            path = save_index(directory, finder.conf.kind, conf, made)
        else:
            path = None if stored is None else copy_index(stored, directory, finder.conf.kind)
        if path is not None:
            written.append(path)
    return written


def restore_pools(relocalizer: Relocalizer, state: MapState, directory: Path | None,
                  cancelled: Callable[[], bool] | None = None, *,
                  first: bool = False, step_aside: bool = False) -> list[str]:
    """Make ``relocalizer``'s pools over ``state`` in the order its steps run (``first``:
    only the first step's), each with the index stored in model directory ``directory``
    where it fits (:func:`..pose.repetition_store.load_index`), else built, unless made
    already; the kinds whose index was read. Stops once ``cancelled()`` is true (the map
    was closed: a pool made for it would only hold its memory longer), in the middle of a
    pool too (between its keyframes and its index's chunks: what was made of it is
    dropped, never kept for a query). ``step_aside``: between a pool's keyframes and chunks
    (never between two pools) wait while queries begun after this call are answered
    (:func:`...core.foreground.step_aside`). A pool is claimed before it pauses: a query
    that needs it meanwhile waits for this maker, which then goes on, rather than building
    its own (without the stored index: seconds on a large map)."""
    read = []
    checks = cancelled
    if step_aside:
        checks = yielding(cancelled if cancelled is not None else lambda: False)
    finders = pool_finders(relocalizer)
    for finder in finders[:1] if first else finders:
        if cancelled is not None and cancelled():
            log.debug("pools of %d keyframes: cancelled", len(state.keyframes))
            break
        if held_pool(state, finder.conf.kind, finder.conf.repetition_index()) is not None:
            continue
        start = time.perf_counter()
        try:
            if _make(finder, state, directory, checks):
                read.append(finder.conf.kind)
        except Cancelled:
            log.debug("%s pool of %d keyframes: cancelled after %.2f s", finder.conf.kind,
                      len(state.keyframes), time.perf_counter() - start)
            break
        log.info("%s pool of %d keyframes ready in %.2f s (%s)", finder.conf.kind,
                  len(state.keyframes), time.perf_counter() - start,
                  "index read" if read and read[-1] == finder.conf.kind else "made")
    return read


def _make(finder: P3PPoseFinder, state: MapState, directory: Path | None,
          cancelled: Callable[[], bool] | None = None) -> bool:
    """Make ``finder``'s pool over ``state`` (unless made) through :func:`.map_pool`, so a
    query asking for it meanwhile waits instead of building its own; whether its index was
    read from ``directory``. :class:`Cancelled` once ``cancelled()`` is true (nothing kept:
    a query waiting for it then makes its own)."""
    kind, conf = finder.conf.kind, finder.conf.repetition_index()
    read = False

    def make() -> MapPool:
        nonlocal read
        stored = _stored(directory, state, kind, conf, cancelled)
        read = stored is not None
        return stored if stored is not None else MapPool.make(state, kind, conf, cancelled)

    map_pool(state, kind, conf, make)
    return read


def _stored(directory: Path | None, state: MapState, kind: str, conf: IndexConf,
            cancelled: Callable[[], bool] | None) -> MapPool | None:
    if directory is None:
        return None
    try:
        return load_index(directory, state, kind, conf, cancelled)
    except StorageError as exc:   # its bytes were checked at load: a bug, not damage
        log.error("%s; building the index again", exc)
        return None
