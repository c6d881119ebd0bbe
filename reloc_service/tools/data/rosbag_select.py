"""Which paired images of a recording become map keyframes and which are held out as queries
(scored against the odometry's pose): queries first, so a query is never a map frame, then
keyframes among the rest, every N-th or by the live bridge's keyframe rule."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ...core.errors import DatasetError
from ...service.ros2.keyframe_rule import KeyframeRule, Rule

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]


@dataclass(frozen=True)
class Selection:
    """The choice of frames. Times are seconds since the first image of the image topic.

    ``queries_every`` M >= 2 holds out every M-th frame (from the M // 2-th, half-way between
    keyframes) of ``query_range`` as a query; with ``query_range`` alone every frame in it is
    a query; neither: no queries. Keyframes are the other frames of ``map_range``: every
    ``keyframe_every``-th, or (``keyframe_rule`` = metres, degrees) each frame farther than the
    distance from every keyframe so far or turned more than the angle from each, the rule of
    the live bridge."""

    keyframe_every: int = 1
    keyframe_rule: tuple[float, float] | None = None
    queries_every: int = 0
    map_range: tuple[float, float] | None = None
    query_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.keyframe_every < 1:
            raise DatasetError(f"keyframes: expected every N-th frame with N >= 1, got "
                               f"{self.keyframe_every}")
        if self.queries_every == 1 or self.queries_every < 0:
            raise DatasetError(f"queries: expected every M-th frame with M >= 2 (M = 1 would "
                               f"leave no frame for the map), or 0 for none, got "
                               f"{self.queries_every}")
        rule = self.keyframe_rule
        if rule is not None and not all(math.isfinite(v) and v >= 0 for v in rule):
            raise DatasetError(f"keyframe rule: expected a distance (m) and an angle (deg) >= 0, "
                               f"got {rule}")
        for name in ("map_range", "query_range"):
            bounds = getattr(self, name)
            if bounds is not None and not bounds[0] <= bounds[1]:
                raise DatasetError(f"{name.replace('_', ' ')} ({bounds[0]}, {bounds[1]}) is "
                                   "empty; expected T0 <= T1")


def select_frames(times: Array, world_from_cam: Array, selection: Selection
                  ) -> tuple[IntArray, IntArray]:
    """Indices of the map keyframes and of the queries among frames at ``times`` (N,) seconds
    with poses ``world_from_cam`` (N, 4, 4); DatasetError when no keyframe is left."""
    queries = _queries(times, selection)
    candidates = np.setdiff1d(_in_range(times, selection.map_range), queries)
    if selection.keyframe_rule is None:
        keyframes = candidates[::selection.keyframe_every]
    else:
        distance_m, angle_deg = selection.keyframe_rule
        keyframes = _by_rule(candidates, world_from_cam,
                             KeyframeRule(Rule.DISTANCE, min_distance_m=distance_m,
                                          min_angle_deg=angle_deg))
    if keyframes.size == 0:
        raise DatasetError(f"frame selection: no map keyframe among {len(times)} paired images "
                           f"(images span {times[0]:.3f} .. {times[-1]:.3f} s; map time range "
                           f"{selection.map_range}, {queries.size} queries held out)")
    return keyframes, queries


def _queries(times: Array, selection: Selection) -> IntArray:
    in_range = _in_range(times, selection.query_range)
    every = selection.queries_every
    if every:
        return in_range[every // 2::every]
    return in_range if selection.query_range is not None else np.zeros(0, dtype=np.intp)


def _by_rule(candidates: IntArray, world_from_cam: Array, rule: KeyframeRule) -> IntArray:
    chosen: list[int] = []
    for i in candidates:
        if rule.is_new(world_from_cam[i], [(world_from_cam[k], None) for k in chosen]):
            chosen.append(int(i))
    return np.array(chosen, dtype=np.intp)


def _in_range(times: Array, bounds: tuple[float, float] | None) -> IntArray:
    if bounds is None:
        return np.arange(len(times))
    return np.flatnonzero((times >= bounds[0]) & (times <= bounds[1]))
