"""Which regions' models the ferns relocalizer classifies a query against (module docstring of
:mod:`.ferns`): the attempts in the place prior's order, and what a position prior leaves of
the map (keyframes within its radius, the classes they observe)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from ...core.map import MapState
from ..ferns.scorer import FernScorer
from .base import Prior


def region_attempts(regions: tuple[int, ...], num_regions: int, fallback: bool
                    ) -> list[tuple[int, ...]]:
    """The region sets tried in turn: growing prefixes of the prior's ranking ``regions``,
    then every region (with ``fallback``); just every region when the prior ranked none
    (``regions`` is all of them)."""
    every = tuple(range(num_regions))
    if len(regions) >= num_regions:
        return [every]
    attempts = [regions[:i] for i in range(1, len(regions) + 1)]
    return attempts + [every] if fallback else attempts


def near_keyframes(state: MapState, prior: Prior) -> list[int]:
    """Keyframe ids within the prior's radius of its position."""
    ids = state.keyframe_ids()
    if not ids:
        return []
    dist = np.linalg.norm(state.positions_world(ids) - prior.world_from_cam[:3, 3], axis=1)
    return [k for k, d in zip(ids, dist, strict=True) if d <= prior.radius_m]


def allowed_classes(state: MapState, scorers: list[FernScorer], prior: Prior | None, kind: str
                    ) -> list[npt.NDArray[np.bool_] | None] | None:
    """Per model, the mask of classes the prior allows (None: all): the landmarks the
    ``kind`` features of keyframes within its radius observe; None if it leaves no
    keyframe."""
    if prior is None:
        return [None] * len(scorers)
    near = near_keyframes(state, prior)
    if not near:
        return None
    lms = [state.keyframes[k].features[kind].landmark_ids for k in near
           if kind in state.keyframes[k].features]
    seen = np.unique(np.concatenate(lms)) if lms else np.zeros(0, np.int64)
    return [np.isin(s.class_ids, seen) for s in scorers]
