"""The whole-map work of a relocalizer's pose finders done when its map is loaded rather than
by the first query: each p3p finder's landmark pool and repetition index
(:mod:`..pose.map_pool`, read from the snapshot where it was stored with the model,
:mod:`..pose.repetition_store`) and the keyframes' agreement with the map's camera, in the
order the relocalizer's steps run, so the first step's pool is ready first."""

from __future__ import annotations

import logging
import time
from pathlib import Path

from ...core.errors import StorageError
from ...core.map import MapState
from ..pose.map_pool import held_pool, keep_pool, map_pool
from ..pose.p3p import P3PPoseFinder
from ..pose.repetition_store import load_index, save_index
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


def save_pools(relocalizer: Relocalizer, directory: Path, state: MapState) -> list[Path]:
    """Store beside ``relocalizer``'s model in ``directory`` the indexes of the pools made
    for ``state`` (none is made here: a pool not made yet is built at the next load)."""
    written = []
    for finder in pool_finders(relocalizer):
        conf = finder.conf.repetition_index()
        made = held_pool(state, finder.conf.kind, conf)
        if made is not None:
            path = save_index(directory, finder.conf.kind, conf, made)
            if path is not None:
                written.append(path)
    return written


def restore_pools(relocalizer: Relocalizer, state: MapState, directory: Path | None
                  ) -> list[str]:
    """Keep as ``state``'s pools those whose index is stored in model directory
    ``directory`` and fits (:func:`..pose.repetition_store.load_index`); their kinds."""
    return [f.conf.kind for f in pool_finders(relocalizer) if _restore(f, state, directory)]


def prepare_pools(relocalizer: Relocalizer, state: MapState, directory: Path | None) -> None:
    """Make every pool ``relocalizer``'s queries over ``state`` read, in the order its steps
    run, with the index stored in model directory ``directory`` where it fits
    (:func:`restore_pools`); then the rest of each finder's map work
    (:meth:`P3PPoseFinder.prepare_map`: the keyframes' agreement with the map's camera,
    seconds on a big map), so a query waits for the pools alone."""
    finders = pool_finders(relocalizer)
    for finder in finders:
        start = time.perf_counter()
        read = _restore(finder, state, directory)
        map_pool(state, finder.conf.kind, finder.conf.repetition_index())
        log.debug("%s pool of %d keyframes ready in %.2f s (%s)", finder.conf.kind,
                  len(state.keyframes), time.perf_counter() - start,
                  "index read" if read else "made")
    for finder in finders:
        finder.prepare_map(state)


def _restore(finder: P3PPoseFinder, state: MapState, directory: Path | None) -> bool:
    """Whether ``finder``'s pool over ``state`` is now kept with the index stored in
    ``directory`` (False: none stored, it does not fit, or a pool is kept already)."""
    kind, conf = finder.conf.kind, finder.conf.repetition_index()
    if directory is None or held_pool(state, kind, conf) is not None:
        return False
    try:
        made = load_index(directory, state, kind, conf)
    except StorageError as exc:   # its bytes were checked at load: a bug, not damage
        log.error("%s; building the index again", exc)
        return False
    if made is None:
        return False
    keep_pool(state, kind, conf, made)
    return True
