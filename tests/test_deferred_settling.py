"""Settling deferred to verification: the intrinsics test runs only for a pose that passed
the cheaper tests, and the answers are those of settling every pose at once."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from reloc_service.algorithms.place.base import PlaceCandidate, create_place_finder
from reloc_service.algorithms.pose.base import PoseEstimate, PoseFinder, create_pose_finder
from reloc_service.algorithms.relocalizers.base import VerifyConf, verify
from reloc_service.algorithms.relocalizers.multi import MultiRelocalizer
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.frame import Frame
from reloc_service.core.map import MapState
from reloc_service.tools.synth.planar import PlanarScene, keyframe_grid, planar_scene, query_pose

CAMERA = PinholeCamera(width=320, height=240, fx=250.0, fy=250.0, cx=159.5, cy=119.5)


@pytest.fixture(scope="module")
def scene() -> PlanarScene:
    return planar_scene(keyframe_grid(4, 3), camera=CAMERA, max_features=1000)


def _estimate(inliers: int) -> PoseEstimate:
    return PoseEstimate(world_from_cam=np.eye(4), keyframe_ids=[0], num_matches=200,
                        inliers=inliers, reprojection_rms_px=0.5, covariance=np.eye(6) * 1e-6)


def test_verification_settles_only_past_the_cheaper_tests():
    settled: list[int] = []
    few = _estimate(3)
    few.deferred_settling = lambda: settled.append(3)
    ok, reason, _ = verify(few, VerifyConf())
    assert not ok and reason.startswith("too few inliers") and settled == []
    assert few.deferred_settling is not None  # still pending: nothing read its outcome
    many = _estimate(180)
    many.deferred_settling = lambda: settled.append(180)
    assert verify(many, VerifyConf())[0]
    assert settled == [180] and many.deferred_settling is None
    verify(many, VerifyConf())  # settled once only
    assert settled == [180]


@dataclass
class _CountedSettling(PoseFinder):
    """Answers the first group with too few inliers and the others with many, each with a
    deferred settling that counts its runs (eager in :meth:`find_pose`)."""

    pools_candidates = True
    name = "counted"
    runs: list[int] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.conf = None
        self.calls = 0

    def find_pose(self, query: Frame, candidates: list[PlaceCandidate], state: MapState
                  ) -> PoseEstimate | None:
        found = self.find_pose_deferred(query, candidates, state)
        assert found is not None
        found.settle()
        return found

    def find_pose_deferred(self, query: Frame, candidates: list[PlaceCandidate],
                           state: MapState) -> PoseEstimate | None:
        self.calls += 1
        call = self.calls
        est = _estimate(3 if call == 1 else 180)
        est.keyframe_ids = [c.keyframe_id for c in candidates]
        est.deferred_settling = lambda: self.runs.append(call)
        return est


def test_multi_never_settles_a_group_refused_by_a_cheaper_test(scene):
    pose = _CountedSettling()
    place = create_place_finder({"name": "sbi"}, scene.map)
    conf = MultiRelocalizer.Conf(num_candidates=3, max_groups=2, unique=False)
    reloc = MultiRelocalizer(scene.map, place, pose, conf=conf)
    result = reloc.relocalize(Frame(scene.render(query_pose(1)), CAMERA))
    assert result.ok and pose.calls == 2
    assert pose.runs == [2]  # the first group's refusal (3 inliers) read no settling


def test_p3p_deferred_estimate_settles_to_the_eager_one(scene):
    p3p = create_pose_finder({"name": "p3p"})
    state = scene.map.snapshot()
    p3p.prepare_map(state)
    place = create_place_finder({"name": "sbi"}, scene.map)
    place.train()
    image = scene.render(query_pose(2))
    candidates = place.find_places(Frame(image, CAMERA), 5)
    eager = p3p.find_pose(Frame(image, CAMERA), candidates, state)
    deferred = p3p.find_pose_deferred(Frame(image, CAMERA), candidates, state)
    assert eager is not None and deferred is not None
    assert eager.intrinsics is not None and eager.deferred_settling is None
    assert deferred.intrinsics is None and deferred.deferred_settling is not None
    deferred.settle()
    assert deferred.intrinsics is not None and "settle" in deferred.timings
    assert deferred.intrinsics.passed == eager.intrinsics.passed
    np.testing.assert_allclose(deferred.covariance, eager.covariance)
    np.testing.assert_allclose(deferred.world_from_cam, eager.world_from_cam)
