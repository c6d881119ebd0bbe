"""A relocalizer's keyframe statistics (:mod:`..pose.map_consistency`: each keyframe's
intrinsics estimate on its landmarks re-triangulated without it, which the intrinsics test of
every query near it reads) saved beside its model and given back to the map when it is
loaded (:mod:`..pose.consistency_store`), so that the first queries of a loaded map do not
compute them again.

A save stores those its keyframes hold: computed here, or given by the snapshot the map was
loaded from and not checked yet (an engine that answers no query, a service's with worker
processes, computes none; its saves carry the loaded ones over, to the replica bases its
workers load and to the next snapshot). Whether an entry still fits its keyframe is for its
digest to say, at the first query that reads it.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ...core.errors import StorageError
from ...core.map import MapState
from ..pose.consistency_store import read_statistics, stored_kinds, write_statistics
from ..pose.map_consistency import held_statistics, offer_statistics
from .base import Relocalizer

log = logging.getLogger(__name__)


def save_statistics(relocalizer: Relocalizer, directory: Path, state: MapState) -> list[Path]:
    """Store in model directory ``directory`` the statistics the keyframes of ``state`` hold
    for the feature kinds ``relocalizer`` reads; the files written."""
    written = []
    for kind in sorted(relocalizer.required_features):
        path = write_statistics(directory, kind, held_statistics(state, kind))
        if path is not None:
            written.append(path)
    return written


def restore_statistics(relocalizer: Relocalizer, state: MapState, directory: Path) -> list[str]:
    """Give the keyframes of ``state`` the statistics stored in model directory
    ``directory`` for the feature kinds ``relocalizer`` reads; the kinds read. A file the
    snapshot's checksum passed but that is not one of stored statistics is logged and
    skipped: its keyframes compute theirs."""
    read = []
    for kind in sorted(relocalizer.required_features & set(stored_kinds(directory))):
        try:
            stored = read_statistics(directory, kind)
        except StorageError as exc:   # its bytes were checked at load: a bug, not damage
            log.error("%s; the keyframes' statistics are computed again", exc)
            continue
        offer_statistics(state, kind, stored)
        read.append(kind)
    return read
