"""A read-only view of one pinned map state: the map a relocalizer is given by the engine."""

from __future__ import annotations

from typing import Any

from .errors import MapError
from .map import KeyframeMap, MapState


class MapView(KeyframeMap):
    """A read-only :class:`KeyframeMap` showing one pinned :class:`MapState` (what a
    relocalizer is given; the engine re-pins it when it publishes)."""

    def __init__(self, state: MapState | None = None) -> None:
        super().__init__()
        self._pinned = state if state is not None else MapState()

    def pin(self, state: MapState) -> None:
        self._pinned = state

    def snapshot(self) -> MapState:
        return self._pinned

    @property
    def version(self) -> int:
        return self._pinned.version

    def __len__(self) -> int:
        return len(self._pinned.keyframes)

    def __contains__(self, kf_id: object) -> bool:
        return kf_id in self._pinned.keyframes

    def _read_only(self, *_: Any, **__: Any) -> Any:
        raise MapError("a relocalizer's map view is read-only; change the map through the engine")

    add_keyframe = remove_keyframe = add_landmarks = add_observations = replace_state = _read_only
