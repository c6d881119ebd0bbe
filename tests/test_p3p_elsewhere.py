"""The repetition check's pose "elsewhere" (the keyframes what a pose leaves unexplained points
to) is judged plausible before its errors are settled: the intrinsics test runs only for a pose
that is kept, and then only when its verification asks (its settling deferred as
:meth:`find_pose_deferred` defers it, a stage of its own in the timings)."""

from __future__ import annotations

import numpy as np

from reloc_service.algorithms.pose.base import PoseEstimate
from reloc_service.algorithms.pose.p3p import P3PPoseFinder


class _Landmarks:
    """Landmarks 100+ are seen by keyframes 7 (10 of them) and 8 (2); the rest by 1."""

    def observing_keyframes(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if ids[0] >= 100:
            return np.array([7, 8]), np.array([10, 2])
        return np.array([1]), np.array([len(ids)])


class _State:
    landmarks = _Landmarks()

    def nearest_keyframes(self, *_: object) -> list[int]:
        return [1, 2]


def _elsewhere(monkeypatch, plausible: bool) -> tuple[list[PoseEstimate], list[PoseEstimate],
                                                      PoseEstimate]:
    finder = P3PPoseFinder(P3PPoseFinder.Conf())
    first = PoseEstimate(world_from_cam=np.eye(4), keyframe_ids=[1], inliers=12,
                         inlier_landmark_ids=np.arange(12))
    found = PoseEstimate(world_from_cam=np.eye(4), keyframe_ids=[7], inliers=30)
    asked: list[list[int]] = []
    settled: list[PoseEstimate] = []

    def unsettled(query, candidates, state):
        asked.append([c.keyframe_id for c in candidates])
        return found

    monkeypatch.setattr(finder, "_unsettled_pose", unsettled)
    monkeypatch.setattr(finder, "_settled", lambda est, state: settled.append(est) or est)
    got = finder._elsewhere(None, first, _State(), np.arange(100, 110),  # type: ignore[arg-type]
                            lambda _: plausible)
    assert asked == [[7]]  # the far keyframe with most votes, as many as the pose's own
    return got, settled, found


def test_an_implausible_pose_elsewhere_is_dropped_unsettled(monkeypatch) -> None:
    got, settled, _ = _elsewhere(monkeypatch, plausible=False)
    assert got == [] and settled == []


def test_a_plausible_pose_elsewhere_is_kept_and_settled_when_verified(monkeypatch) -> None:
    got, settled, found = _elsewhere(monkeypatch, plausible=True)
    assert got == [found] and settled == []
    found.settle()  # what the verification does once the cheaper tests pass
    assert settled == [found] and "settle" in found.timings


def test_find_pose_times_the_settling_as_its_own_stage(monkeypatch) -> None:
    finder = P3PPoseFinder(P3PPoseFinder.Conf())
    found = PoseEstimate(world_from_cam=np.eye(4), keyframe_ids=[7], inliers=30,
                         timings={"solve": 0.01})
    settled: list[PoseEstimate] = []
    monkeypatch.setattr(finder, "_unsettled_pose", lambda *_: found)
    monkeypatch.setattr(finder, "_settled", lambda est, state: settled.append(est) or est)
    got = finder.find_pose(None, [], None)  # type: ignore[arg-type]
    assert got is found and settled == [found]
    assert got.timings["solve"] == 0.01 and got.timings["settle"] >= 0.0
