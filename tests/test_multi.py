"""The multi relocalizer (place finder + pose finder), the gt place finder and the none pose
finder, end to end on a rendered textured plane."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from reloc_service.algorithms.place.base import PlaceCandidate, create_place_finder
from reloc_service.algorithms.place.sbi import SmallBlurryImageFinder
from reloc_service.algorithms.pose.base import PoseEstimate, PoseFinder, create_pose_finder
from reloc_service.algorithms.relocalizers.base import Prior, RelocStatus
from reloc_service.algorithms.relocalizers.factory import create_relocalizer
from reloc_service.algorithms.relocalizers.multi import MultiRelocalizer
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.errors import ConfigError, NotTrainedError
from reloc_service.core.frame import Frame, Keyframe
from reloc_service.core.geometry import pose_error
from reloc_service.core.map import KeyframeMap, MapState
from reloc_service.tools.synth.planar import (
    PlanarScene,
    downward_pose,
    keyframe_grid,
    planar_scene,
    query_pose,
)

ROOT = Path(__file__).resolve().parents[1]

CAMERA = PinholeCamera(width=320, height=240, fx=250.0, fy=250.0, cx=159.5, cy=119.5)


@pytest.fixture(scope="module")
def scene() -> PlanarScene:
    return planar_scene(keyframe_grid(4, 3), camera=CAMERA, max_features=1000)


def fresh_map(scene: PlanarScene) -> KeyframeMap:
    """A copy of the scene's map (tests that remove keyframes must not change the fixture)."""
    kmap = KeyframeMap()
    kmap.replace_state(scene.map.snapshot())
    return kmap


def unrelated_image() -> np.ndarray:
    import skimage.data as data

    return cv2.resize(cv2.cvtColor(data.chelsea(), cv2.COLOR_RGB2GRAY), CAMERA.size)


def test_factory_builds_multi_with_its_parts(scene):
    reloc = create_relocalizer("sbi+p3p", scene.map, options={"p3p": {"kind": "orb"},
                                                               "multi": {"num_candidates": 3}})
    assert isinstance(reloc, MultiRelocalizer)
    assert reloc.method == "sbi+p3p" and reloc.required_features == {"orb"}
    assert reloc.group_size == 3
    assert create_relocalizer("sbi+none", scene.map).group_size == 1
    with pytest.raises(ConfigError, match="unknown option"):
        create_relocalizer("sbi+p3p", scene.map, options={"multi": {"k": 3}})
    with pytest.raises(ConfigError, match="unknown option"):
        create_relocalizer("sbi+p3p", scene.map, options={"verify": {"inliers": 3}})
    with pytest.raises(ConfigError):
        create_relocalizer("sbi+", scene.map)
    with pytest.raises(ConfigError, match="unknown place finder"):
        create_relocalizer("nope+p3p", scene.map)


@pytest.mark.parametrize("index", [0, 1, 2])
def test_sbi_p3p_relocalizes_rendered_queries(scene, index):
    gt = query_pose(index)
    result = create_relocalizer("sbi+p3p", scene.map).relocalize(Frame(scene.render(gt), CAMERA))
    assert result.status is RelocStatus.OK, result.reason
    dt, dr = pose_error(result.world_from_cam, gt)
    assert dt < 0.01 and np.degrees(dr) < 0.5
    assert result.method == "sbi+p3p" and result.map_version == scene.map.version
    assert result.inliers >= 50 and result.covariance.shape == (6, 6)
    assert 0 < result.confidence <= 1 and result.matched_keyframe_ids
    assert {"place", "features", "match", "solve", "verify"} <= result.timings.keys()


def test_place_not_in_the_map_is_refused(scene):
    for spec in ("sbi+p3p", "sbi+none"):
        result = create_relocalizer(spec, scene.map).relocalize(Frame(unrelated_image(), CAMERA))
        assert result.status is RelocStatus.NOT_RELOCALIZED and result.reason
        assert result.world_from_cam is None


def test_removed_keyframe_is_never_proposed(scene):
    kmap = fresh_map(scene)
    reloc = create_relocalizer("sbi+p3p", kmap, options={"multi": {"num_candidates": 3}})
    state = kmap.snapshot()
    target = state.keyframe(5)
    query = Frame(target.image.copy(), CAMERA)
    assert 5 in reloc.relocalize(query).matched_keyframe_ids
    kmap.remove_keyframe(5)
    reloc.remove_keyframe(target)
    result = reloc.relocalize(Frame(target.image.copy(), CAMERA), hypotheses=3)
    proposed = reloc.place.find_places(Frame(target.image.copy(), CAMERA), 100)
    assert 5 not in {c.keyframe_id for c in proposed}
    assert 5 not in result.matched_keyframe_ids
    assert result.ok  # the neighbours still see the place
    dt, _ = pose_error(result.world_from_cam, target.world_from_cam)
    assert dt < 0.01


def test_prior_restricts_candidates(scene):
    gt = query_pose(0)
    reloc = create_relocalizer("sbi+p3p", scene.map)
    query = Frame(scene.render(gt), CAMERA)
    near = reloc.relocalize(query, prior=Prior(world_from_cam=gt, radius_m=0.5))
    assert near.ok
    positions = scene.map.snapshot().positions_world(near.matched_keyframe_ids)
    assert np.all(np.linalg.norm(positions - gt[:3, 3], axis=1) <= 0.5)
    far = gt.copy()
    far[:3, 3] += [20.0, 0.0, 0.0]
    result = reloc.relocalize(Frame(scene.render(gt), CAMERA),
                              prior=Prior(world_from_cam=far, radius_m=1.0))
    assert not result.ok and "prior" in result.reason


def test_further_hypotheses_come_from_other_groups(scene):
    gt = query_pose(2)
    reloc = create_relocalizer("sbi+p3p", scene.map, options={"multi": {"num_candidates": 2}})
    result = reloc.relocalize(Frame(scene.render(gt), CAMERA), hypotheses=3)
    assert result.ok and len(result.hypotheses) >= 1
    groups = [set(result.matched_keyframe_ids)] + [set(h.matched_keyframe_ids)
                                                    for h in result.hypotheses]
    for i, a in enumerate(groups):
        for b in groups[i + 1:]:
            assert not a & b  # independent keyframe groups
    for h in result.hypotheses:
        assert h.ok and pose_error(h.world_from_cam, gt)[0] < 0.02
    single = reloc.relocalize(Frame(scene.render(gt), CAMERA))
    assert single.hypotheses == []


def test_max_groups_falls_back_to_later_groups(scene):
    class FirstGroupFails(PoseFinder):
        name = "first-fails"

        def __init__(self) -> None:
            super().__init__(None)
            self.inner = create_pose_finder({"name": "p3p"})
            self.calls = 0

        def find_pose(self, query, candidates, state):
            self.calls += 1
            return None if self.calls == 1 else self.inner.find_pose(query, candidates, state)

    gt = query_pose(1)
    place = create_place_finder({"name": "sbi"}, scene.map)
    for max_groups, unique, expect_ok, calls in ((1, True, False, 1), (3, True, True, 3),
                                                 (3, False, True, 2)):
        pose = FirstGroupFails()
        pose.pools_candidates = True
        conf = MultiRelocalizer.Conf(num_candidates=3, max_groups=max_groups, unique=unique)
        reloc = MultiRelocalizer(scene.map, place, pose, conf=conf)
        result = reloc.relocalize(Frame(scene.render(gt), CAMERA))
        assert result.ok is expect_ok
        # Every group is heard for uniqueness; without it, the first verified group answers.
        assert pose.calls == calls


@dataclass
class FixedPoses(PoseFinder):
    """A pose finder answering a given pose per call, with strong evidence."""

    poses: list[np.ndarray]
    pools_candidates = True
    name = "fixed"

    def __post_init__(self) -> None:
        self.conf = None
        self.calls = 0

    def find_pose(self, query: Frame, candidates: list[PlaceCandidate], state: MapState
                  ) -> PoseEstimate | None:
        pose = self.poses[min(self.calls, len(self.poses) - 1)]
        self.calls += 1
        return PoseEstimate(world_from_cam=pose, keyframe_ids=[c.keyframe_id for c in candidates],
                            num_matches=200, inliers=180, reprojection_rms_px=0.5,
                            covariance=np.eye(6) * 1e-6)


def test_agreement_check(scene):
    place = create_place_finder({"name": "sbi"}, scene.map)
    query = Frame(scene.render(query_pose(0)), CAMERA)
    a = downward_pose(0.0, 0.0, 1.2)
    b = downward_pose(0.5, 0.0, 1.2)
    conf = MultiRelocalizer.Conf(num_candidates=3, require_agreement=True)
    agree = MultiRelocalizer(scene.map, place, FixedPoses([a, a]), conf=conf).relocalize(query)
    assert agree.ok and agree.hypotheses == []
    assert len(MultiRelocalizer(scene.map, place, FixedPoses([a, a]), conf=conf).relocalize(
        query, hypotheses=2).hypotheses) == 1
    disagree = MultiRelocalizer(scene.map, place, FixedPoses([a, b]), conf=conf).relocalize(query)
    assert not disagree.ok and "disagree" in disagree.reason
    small = KeyframeMap()
    small.add_keyframe(scene.map.snapshot().keyframe(0))
    lonely = MultiRelocalizer(small, create_place_finder({"name": "sbi"}, small),
                              FixedPoses([a]), conf=conf).relocalize(query)
    assert not lonely.ok and "fewer than two" in lonely.reason


def test_empty_map_and_untrained_place_finder(scene):
    result = create_relocalizer("sbi+p3p", KeyframeMap()).relocalize(
        Frame(scene.render(query_pose(0)), CAMERA))
    assert not result.ok and "no keyframe" in result.reason

    class Untrained(SmallBlurryImageFinder):
        @property
        def trained(self) -> bool:
            return False

    reloc = MultiRelocalizer(scene.map, Untrained(scene.map, SmallBlurryImageFinder.Conf()),
                             create_pose_finder({"name": "p3p"}))
    assert not reloc.trained
    with pytest.raises(NotTrainedError):
        reloc.relocalize(Frame(scene.render(query_pose(0)), CAMERA))


# -- the none pose finder and the gt place finder -----------------------------------------------

def test_none_answers_the_keyframe_pose_with_ncc_evidence(scene):
    kmap = fresh_map(scene)
    kf = kmap.snapshot().keyframe(6)
    reloc = create_relocalizer("sbi+none", kmap, options={"multi": {"require_agreement": False}})
    result = reloc.relocalize(Frame(kf.image.copy(), CAMERA))
    assert result.ok and np.array_equal(result.world_from_cam, kf.world_from_cam)
    assert result.matched_keyframe_ids == [6] and result.confidence > 0.9
    assert "pose" in result.timings
    assert reloc.relocalize(Frame(kf.image.copy(), CAMERA), hypotheses=3).hypotheses == []
    # A near-duplicate keyframe (1 cm away) is a second, verified hypothesis.
    twin_pose = kf.world_from_cam.copy()
    twin_pose[:3, 3] += [0.01, 0.0, 0.0]
    twin = Keyframe(image=scene.render(twin_pose), camera=CAMERA, id=50, world_from_cam=twin_pose)
    kmap.add_keyframe(twin)
    reloc.add_keyframe(twin)
    more = reloc.relocalize(Frame(kf.image.copy(), CAMERA), hypotheses=3)
    assert more.ok and more.matched_keyframe_ids == [6]
    assert [h.matched_keyframe_ids for h in more.hypotheses] == [[50]]
    assert np.array_equal(more.hypotheses[0].world_from_cam, twin_pose)


def test_photometric_pose_needs_two_agreeing_keyframes(scene):
    kmap = fresh_map(scene)
    kf = kmap.snapshot().keyframe(6)
    reloc = create_relocalizer("sbi+none", kmap)  # agreement implied by the none pose finder
    alone = reloc.relocalize(Frame(kf.image.copy(), CAMERA))
    assert not alone.ok and "agreement check" in alone.reason
    twin_pose = kf.world_from_cam.copy()
    twin_pose[:3, 3] += [0.05, 0.0, 0.0]
    twin = Keyframe(image=scene.render(twin_pose), camera=CAMERA, id=50, world_from_cam=twin_pose)
    kmap.add_keyframe(twin)
    reloc.add_keyframe(twin)
    assert reloc.relocalize(Frame(kf.image.copy(), CAMERA)).ok
    # Geometric pose finders are not held to it by default.
    assert create_relocalizer("sbi+p3p", kmap).require_agreement is False


def test_gt_place_finder_exists_only_where_the_evaluation_tools_are_loaded():
    code = ("from reloc_service.core.map import KeyframeMap\n"
            "from reloc_service.algorithms.relocalizers import create_relocalizer\n"
            "try:\n    create_relocalizer('gt+p3p', KeyframeMap())\n"
            "except Exception as exc:\n    print(type(exc).__name__, exc)\n"
            "import reloc_service.tools.eval.evaluate\n"
            "print(create_relocalizer('gt+p3p', KeyframeMap()).method)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=ROOT).stdout.splitlines()
    assert out[0].startswith("ConfigError unknown place finder 'gt'"), out
    assert out[1] == "gt+p3p"


def test_the_service_never_serves_the_gt_place_finder():
    import reloc_service.tools.eval.gt  # noqa: F401 (registers gt in this process)
    from reloc_service.service.config import parse_config

    with pytest.raises(ConfigError, match="evaluation only"):
        parse_config({"service": {"methods": ["sbi+p3p", "gt+p3p"], "default_method": "sbi+p3p"}})


def test_gt_place_finder_ranks_by_true_distance(scene):
    import reloc_service.tools.eval.gt  # noqa: F401 (registers gt in this process)

    reloc = create_relocalizer("gt+none", scene.map)
    state = scene.map.snapshot()
    gt = query_pose(1)
    query = Frame(scene.render(gt), CAMERA, gt_world_from_cam=gt)
    found = reloc.place.find_places(query, 12)
    dist = np.linalg.norm(state.positions_world([c.keyframe_id for c in found]) - gt[:3, 3], axis=1)
    assert dist[0] == pytest.approx(dist.min())
    assert [c.score for c in found] == sorted((c.score for c in found), reverse=True)
    assert {c.keyframe_id for c in reloc.place.find_places(query, 12, allowed={0, 3})} == {0, 3}
    with pytest.raises(ConfigError, match="ground-truth"):
        reloc.relocalize(Frame(scene.render(gt), CAMERA))
    result = create_relocalizer("gt+p3p", scene.map).relocalize(query)
    assert result.ok and pose_error(result.world_from_cam, gt)[0] < 0.01


def test_gt_place_finder_follows_add_and_remove(scene):
    kmap = fresh_map(scene)
    import reloc_service.tools.eval.gt  # noqa: F401 (registers gt in this process)

    finder = create_place_finder({"name": "gt"}, kmap)
    kf = kmap.snapshot().keyframe(4)
    query = Frame(kf.image.copy(), CAMERA, gt_world_from_cam=kf.world_from_cam)
    assert finder.find_places(query, 1)[0].keyframe_id == 4
    kmap.remove_keyframe(4)
    finder.remove_keyframe(kf)
    assert 4 not in {c.keyframe_id for c in finder.find_places(query, 20)}
    moved = Keyframe(image=kf.image, camera=CAMERA, id=40, world_from_cam=kf.world_from_cam)
    kmap.add_keyframe(moved)
    finder.add_keyframe(moved)
    assert finder.find_places(query, 1)[0].keyframe_id == 40


def test_save_and_load_the_place_finders_model(scene, tmp_path):
    reloc = create_relocalizer("sbi+p3p", scene.map)
    reloc.save(tmp_path)
    assert list(tmp_path.iterdir()) == [] and reloc.load(tmp_path) is False

    class WithModel(SmallBlurryImageFinder):
        loaded: dict | None = None

        def state(self, *, centres="float16"):
            return {"words": b"\x00\x01\x02", "k": 3, "ids": [4, 5]}

        def load_state(self, state):
            self.loaded = state

    place = WithModel(scene.map, SmallBlurryImageFinder.Conf())
    MultiRelocalizer(scene.map, place, create_pose_finder({"name": "p3p"})).save(tmp_path)
    other = WithModel(scene.map, SmallBlurryImageFinder.Conf())
    assert MultiRelocalizer(scene.map, other, create_pose_finder({"name": "p3p"})).load(tmp_path)
    assert other.loaded == {"words": b"\x00\x01\x02", "k": 3, "ids": [4, 5]}


def test_disagreeing_verified_groups_without_features_to_compare_are_ambiguous(scene):
    place = create_place_finder({"name": "sbi"}, scene.map)
    query = Frame(scene.render(query_pose(0)), CAMERA)
    a, b = downward_pose(0.0, 0.0, 1.2), downward_pose(1.5, 0.0, 1.2)
    conf = MultiRelocalizer.Conf(num_candidates=3)
    refused = MultiRelocalizer(scene.map, place, FixedPoses([a, b]), conf=conf).relocalize(query)
    assert not refused.ok and refused.reason.startswith("ambiguous places"), refused.reason
    confirmed = MultiRelocalizer(scene.map, place, FixedPoses([a, a]), conf=conf)
    assert confirmed.relocalize(query).ok and confirmed.pose.calls == 3
    first_only = MultiRelocalizer(scene.map, place, FixedPoses([a, b]),
                                  conf=MultiRelocalizer.Conf(num_candidates=3, unique=False))
    assert first_only.relocalize(query).ok and first_only.pose.calls == 1


class CountsSettles(PoseFinder):
    """The p3p pose finder, counting the deferred settlings (intrinsics tests) that run."""

    name = "counts-settles"
    pools_candidates = True

    def __init__(self) -> None:
        super().__init__(None)
        self.inner = create_pose_finder({"name": "p3p"})
        self.settles = 0

    def find_pose(self, query, candidates, state):
        return self.inner.find_pose(query, candidates, state)

    def find_pose_deferred(self, query, candidates, state, *, known=None):
        est = self.inner.find_pose_deferred(query, candidates, state, known=known)
        if est is not None and est.deferred_settling is not None:
            pending = est.deferred_settling

            def counted() -> None:
                self.settles += 1
                pending()

            est.deferred_settling = counted
        return est

    def support(self, query, world_from_cam, state):
        return self.inner.support(query, world_from_cam, state)


def _settle_runs(scene, make_pose, max_groups):
    """(result, settles counted) of the query at pose 1 by ``make_pose()``, keyed by
    (skip_duplicate_settle, hypotheses) for (True, 1), (False, 1) and (True, 2); each run
    must find the query's pose."""
    place = create_place_finder({"name": "sbi"}, scene.map)
    query_at = query_pose(1)
    runs = {}
    for skip, hypotheses in ((True, 1), (False, 1), (True, 2)):
        pose = make_pose()
        conf = MultiRelocalizer.Conf(num_candidates=1, max_groups=max_groups, overlap=False,
                                     skip_duplicate_settle=skip)
        result = MultiRelocalizer(scene.map, place, pose, conf=conf).relocalize(
            Frame(scene.render(query_at), CAMERA), hypotheses=hypotheses)
        assert result.ok and pose_error(result.world_from_cam, query_at)[0] < 0.02
        runs[skip, hypotheses] = (result, pose.settles)
    return runs


def test_groups_agreeing_with_a_verified_pose_are_not_settled_again(scene):
    # One keyframe per group: the three nearest keyframes all give the query's pose, so the
    # second and third groups repeat the first's solution and cannot change the answer.
    runs = _settle_runs(scene, CountsSettles, max_groups=3)
    (skipped, fewer), (full, every), (_, asked) = (runs[True, 1], runs[False, 1],
                                                   runs[True, 2])
    assert fewer == 1 and every == 3 and asked == 3  # more hypotheses read every group
    assert np.array_equal(skipped.world_from_cam, full.world_from_cam)
    assert skipped.inliers == full.inliers
    assert np.array_equal(skipped.covariance, full.covariance)


class OffersItsOwnPose(CountsSettles):
    """:class:`CountsSettles` whose repetition search offers, as an alternative, the pose its
    first estimate's own keyframes give again (an alternative that agrees with it)."""

    name = "offers-its-own-pose"

    def alternatives(self, query, estimate, state, *, plausible=lambda _: True):
        again = self.find_pose_deferred(
            query, [PlaceCandidate(k, 0.0) for k in estimate.keyframe_ids], state)
        return [] if again is None else [again]


def test_alternatives_agreeing_with_a_verified_pose_are_not_settled(scene):
    runs = _settle_runs(scene, OffersItsOwnPose, max_groups=1)
    (skipped, fewer), (full, every), (asked_for_two, asked) = (runs[True, 1], runs[False, 1],
                                                                runs[True, 2])
    # The group's, and the alternative's; asked for two hypotheses, two groups are heard and
    # the alternative is verified for them.
    assert fewer == 1 and every == 2 and asked == 3
    assert len(asked_for_two.hypotheses) == 1
    assert np.array_equal(skipped.world_from_cam, full.world_from_cam)
    assert skipped.inliers == full.inliers
    assert np.array_equal(skipped.covariance, full.covariance)


def _early_runs(scene, monkeypatch):
    """{duplicates_early: (result, PnP solves)} of the query at pose 1, one keyframe per group
    (three groups), each group's pose grown below 100 000 inliers (so always); each run must
    find the query's pose."""
    import reloc_service.algorithms.pose.p3p as p3p

    solves: list[int] = []
    real_solve = p3p.solve_pnp_indexed
    monkeypatch.setattr(p3p, "solve_pnp_indexed",
                        lambda px, *a, **k: solves.append(len(px)) or real_solve(px, *a, **k))
    place = create_place_finder({"name": "sbi"}, scene.map)
    query_at = query_pose(1)
    runs = {}
    for early in (False, True):
        pose = create_pose_finder({"name": "p3p", "guided_below_inliers": 100_000})
        conf = MultiRelocalizer.Conf(num_candidates=1, max_groups=3, overlap=False,
                                     duplicates_early=early)
        solves.clear()
        result = MultiRelocalizer(scene.map, place, pose, conf=conf).relocalize(
            Frame(scene.render(query_at), CAMERA))
        assert result.ok and pose_error(result.world_from_cam, query_at)[0] < 0.02
        runs[early] = (result, len(solves))
    return runs


def test_duplicates_early_stops_a_later_group_at_its_first_agreeing_pose(scene, monkeypatch):
    # Each group gives the query's pose: with duplicates_early the second and third groups
    # end at their pose before growth, which agrees with the first's, and the answer is the
    # first group's as before.
    runs = _early_runs(scene, monkeypatch)
    (full, n_full), (early, n_early) = runs[False], runs[True]
    assert n_early == n_full - 2  # two later groups not grown
    assert np.array_equal(early.world_from_cam, full.world_from_cam)
    assert early.inliers == full.inliers and np.array_equal(early.covariance, full.covariance)


def test_duplicates_early_needs_an_early_pose_that_chance_would_not_produce(scene, monkeypatch):
    # As above, but no early pose passes as a first consensus (plausible_first_pose says
    # no, as it does for a pose of a few inliers): every later group is found in full.
    import reloc_service.algorithms.relocalizers.multi as multi

    asked: list[int] = []

    def refuses(est, conf):
        asked.append(int(est.inliers or 0))
        return False

    monkeypatch.setattr(multi, "plausible_first_pose", refuses)
    runs = _early_runs(scene, monkeypatch)
    assert runs[True][1] == runs[False][1] and asked  # asked, refused: nothing skipped
