"""Ground-truth place finder (thesis 4, figure 4.2): the keyframes nearest to the query's true
pose, to evaluate pose finders with an ideal first step. Evaluation only."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ...algorithms.place.base import PlaceCandidate, PlaceFinder, register
from ...core.errors import ConfigError
from ...core.frame import Frame, Keyframe
from ...core.map import KeyframeMap
from ...core.numeric import top_k


@register("gt")
class GroundTruthPlaceFinder(PlaceFinder):
    """Ranks keyframes by ``distance + angle_weight_m_per_rad * angle`` between camera centres
    and viewing directions of the keyframe and the query's ground-truth pose. Not thread-safe
    (no lock): used behind the engine's read-write lock like every place finder."""

    evaluation_only = True

    @dataclass(frozen=True)
    class Conf:
        #: Metres a radian of viewing-direction difference counts for.
        angle_weight_m_per_rad: float = 0.1

        def __post_init__(self) -> None:
            if self.angle_weight_m_per_rad < 0:
                raise ConfigError(f"gt: angle_weight_m_per_rad must be >= 0, "
                                  f"got {self.angle_weight_m_per_rad}")

    def __init__(self, kmap: KeyframeMap, conf: GroundTruthPlaceFinder.Conf) -> None:
        super().__init__(kmap, conf)
        self._poses: dict[int, npt.NDArray[np.float64]] = {}
        self.train()

    def add_keyframe(self, keyframe: Keyframe) -> None:
        self._poses[keyframe.id] = keyframe.world_from_cam.copy()

    def remove_keyframe(self, keyframe: Keyframe) -> None:
        self._poses.pop(keyframe.id, None)

    def train(self) -> None:
        """Re-index every keyframe of the map (also run at construction)."""
        self._poses = {i: kf.world_from_cam.copy()
                       for i, kf in self.map.snapshot().keyframes.items()}

    def find_places(self, query: Frame, k: int, *, allowed: set[int] | None = None
                    ) -> list[PlaceCandidate]:
        """Up to ``k`` keyframes nearest to ``query.gt_world_from_cam``; ConfigError without it."""
        if query.gt_world_from_cam is None:
            raise ConfigError("place finder 'gt' needs the query's ground-truth pose "
                              "(Frame.gt_world_from_cam); it is for evaluation only")
        items = [(i, p) for i, p in self._poses.items() if allowed is None or i in allowed]
        if not items or k <= 0:
            return []
        ids = np.array([i for i, _ in items], np.int64)
        world_from_kf = np.stack([p for _, p in items])
        cost = self._cost(world_from_kf, query.gt_world_from_cam)
        order = top_k(-cost, k, tiebreak=ids)  # least cost first, ties to the lower id
        return [PlaceCandidate(int(ids[i]), -float(cost[i])) for i in order]

    def _cost(self, world_from_kf: npt.NDArray[np.float64],
              world_from_query: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """(K,) centre distance (m) plus weighted angle between optical axes (rad)."""
        dist = np.linalg.norm(world_from_kf[:, :3, 3] - world_from_query[:3, 3], axis=1)
        cos = np.clip(world_from_kf[:, :3, 2] @ world_from_query[:3, 2], -1.0, 1.0)
        return dist + self.conf.angle_weight_m_per_rad * np.arccos(cos)
