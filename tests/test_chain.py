"""Fallback chains: first verified step wins, timings summed, every reason kept."""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable

import numpy as np
import pytest

from reloc_service.algorithms.relocalizers import overlap
from reloc_service.algorithms.relocalizers.base import Prior, Relocalizer, RelocResult
from reloc_service.algorithms.relocalizers.chain import ChainRelocalizer
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD, create_relocalizer, list_methods
from reloc_service.algorithms.relocalizers.multi import MultiRelocalizer
from reloc_service.core import features as feature_lib
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.errors import ConfigError, NotTrainedError
from reloc_service.core.frame import Features, Frame, Keyframe
from reloc_service.core.geometry import pose_error
from reloc_service.core.map import KeyframeMap
from reloc_service.core.mapping import MapBuilder, MappingConf
from reloc_service.tools.synth.planar import PlanarScene, keyframe_grid, planar_scene, query_pose

CAMERA = PinholeCamera(width=320, height=240, fx=250.0, fy=250.0, cx=159.5, cy=119.5)


@pytest.fixture(scope="module")
def scene() -> PlanarScene:
    return planar_scene(keyframe_grid(3, 2), camera=CAMERA, max_features=1000)


def test_factory_builds_a_chain_of_steps(scene):
    chain = create_relocalizer("sbi+p3p, sbi+none", scene.map, options={"p3p": {"kind": "orb"}})
    assert isinstance(chain, ChainRelocalizer)
    assert [s.method for s in chain.steps] == ["sbi+p3p", "sbi+none"]
    assert all(isinstance(s, MultiRelocalizer) for s in chain.steps)
    assert chain.method == "sbi+p3p,sbi+none"
    assert chain.required_features == {"orb"}
    with pytest.raises(ConfigError, match="empty step"):
        create_relocalizer("sbi+p3p,,sbi+none", scene.map)
    with pytest.raises(ConfigError, match="unknown place finder 'nope'"):
        create_relocalizer("sbi+p3p,nope+none", scene.map)


def test_first_step_answers(scene):
    gt = query_pose(0)
    result = create_relocalizer("sbi+p3p,sbi+none", scene.map).relocalize(
        Frame(scene.render(gt), CAMERA))
    assert result.ok and result.method == "sbi+p3p"
    assert pose_error(result.world_from_cam, gt)[0] < 0.01
    assert "pose" not in result.timings  # the second step never ran


def test_falls_back_and_sums_timings(scene):
    kmap = KeyframeMap()
    for kf in scene.map.snapshot().keyframes.values():  # keyframes without features: p3p fails
        kmap.add_keyframe(Keyframe(image=kf.image, camera=CAMERA, id=kf.id,
                                   world_from_cam=kf.world_from_cam))
    target = kmap.snapshot().keyframe(2)
    chain = create_relocalizer("sbi+p3p,sbi+none", kmap,
                               options={"multi": {"require_agreement": False}})
    result = chain.relocalize(Frame(target.image.copy(), CAMERA))
    assert result.ok and result.method == "sbi+none"
    assert np.array_equal(result.world_from_cam, target.world_from_cam)
    assert {"features", "match", "pose"} <= result.timings.keys()  # both steps' stages
    first = chain.steps[0].relocalize(Frame(target.image.copy(), CAMERA))
    assert not first.ok
    assert result.timings["place"] >= 0.0


def test_no_step_answers_gives_every_reason(scene):
    import cv2
    import skimage.data as data

    image = cv2.resize(cv2.cvtColor(data.chelsea(), cv2.COLOR_RGB2GRAY), CAMERA.size)
    result = create_relocalizer("sbi+p3p,sbi+none", scene.map).relocalize(Frame(image, CAMERA))
    assert not result.ok and result.method == "sbi+p3p,sbi+none"
    p3p_part, none_part = result.reason.split("; sbi+none: ", 1)
    assert p3p_part.startswith("sbi+p3p: ") and "too few inliers" in p3p_part
    assert "image alignment too weak" in none_part
    assert {"features", "match", "pose"} <= result.timings.keys()


def test_features_are_extracted_once_across_steps(scene, monkeypatch):
    calls = []
    real_extract = feature_lib.extract
    monkeypatch.setattr(feature_lib, "extract",
                        lambda *a, **k: calls.append(1) or real_extract(*a, **k))
    strict = create_relocalizer("sbi+p3p", scene.map,
                                options={"verify": {"min_inliers": 100_000}})
    chain = ChainRelocalizer(scene.map, [strict, create_relocalizer("sbi+p3p", scene.map)])
    gt = query_pose(1)
    result = chain.relocalize(Frame(scene.render(gt), CAMERA),
                              prior=Prior(world_from_cam=gt, radius_m=100.0))
    assert result.ok and pose_error(result.world_from_cam, gt)[0] < 0.01
    assert len(calls) == 1  # the second step reused the query's cached features
    assert result.timings["match"] > 0


class _Untrained(Relocalizer):
    name = "untrained"

    @property
    def method(self) -> str:
        return "untrained"

    @property
    def trained(self) -> bool:
        return False

    def add_keyframe(self, keyframe: Keyframe) -> None:
        self.added = keyframe.id

    def remove_keyframe(self, keyframe: Keyframe) -> None:
        self.removed = keyframe.id

    def relocalize(self, query, *, prior=None, hypotheses=1) -> RelocResult:
        raise NotTrainedError("call train() first")


def test_untrained_step_is_skipped_and_calls_are_forwarded(scene):
    untrained = _Untrained(scene.map)
    multi = create_relocalizer("sbi+p3p", scene.map)
    chain = ChainRelocalizer(scene.map, [untrained, multi])
    assert not chain.trained
    gt = query_pose(2)
    result = chain.relocalize(Frame(scene.render(gt), CAMERA))
    assert result.ok and result.method == "sbi+p3p"
    alone = ChainRelocalizer(scene.map, [untrained]).relocalize(Frame(scene.render(gt), CAMERA))
    assert not alone.ok and "untrained: not trained" in alone.reason
    kf = scene.map.snapshot().keyframe(0)
    chain.add_keyframe(kf)
    chain.remove_keyframe(kf)
    multi.add_keyframe(kf)  # restore the shared place finder's index
    assert untrained.added == 0 and untrained.removed == 0
    with pytest.raises(ConfigError):
        ChainRelocalizer(scene.map, [])


def test_save_and_load_each_step(scene, tmp_path):
    chain = create_relocalizer("sbi+p3p,sbi+none", scene.map)
    chain.save(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["0_sbi_p3p", "1_sbi_none"]
    assert chain.load(tmp_path) is False  # sbi has no trained model to restore


# -- the default: an ORB step first, SIFT steps behind it ----------------------------------------

@pytest.fixture(scope="module")
def two_kind_scene() -> PlanarScene:
    """SIFT and ORB landmarks on the same plane, as maps built for the default carry."""
    return planar_scene(keyframe_grid(3, 2), kinds=("sift", "orb"), camera=CAMERA,
                        max_features=1000)


def _map_with_orb(scene: PlanarScene, orb_points: Callable[[Features], np.ndarray] | None
                  ) -> KeyframeMap:
    """A copy of ``scene``'s map whose ORB features lose their landmarks (``orb_points``
    None) or get the world points ``orb_points(features)``; SIFT kept as it is."""
    kmap = KeyframeMap()
    for kf in scene.map.snapshot().keyframes.values():
        orb = kf.features["orb"]
        if orb_points is None:
            orb = Features.create("orb", orb.keypoints_px, orb.descriptors, levels=orb.levels,
                                  sizes=orb.sizes, angles=orb.angles)
        else:
            orb = dataclasses.replace(orb, points_world=orb_points(orb))
        kmap.add_keyframe(Keyframe(image=kf.image, camera=CAMERA, id=kf.id,
                                   world_from_cam=kf.world_from_cam,
                                   features={"sift": kf.features["sift"], "orb": orb}))
    return kmap


def test_method_string_names_each_steps_features(two_kind_scene):
    chain = create_relocalizer(DEFAULT_METHOD, two_kind_scene.map)
    assert chain.method == DEFAULT_METHOD == "sbi+p3p:orb,sbi+p3p:sift-half,bow+p3p,sbi+p3p"
    orb_step, half_step, *sift_steps = chain.steps
    assert orb_step.pose.conf.kind == "orb" and orb_step.pose.conf.max_features == 500
    assert orb_step.pose.conf.first_pool_keyframes == 1
    assert (half_step.pose.conf.kind, half_step.pose.conf.query_scale) == ("sift", 0.5)
    assert [s.pose.conf.kind for s in sift_steps] == ["sift", "sift"]
    assert [s.pose.conf.first_pool_keyframes for s in sift_steps] == [None, None]
    assert [s.pose.conf.query_scale for s in sift_steps] == [1.0, 1.0]
    assert chain.required_features == {"orb", "sift"}
    # Options of the pose finder apply to its variants, the variant's own table last; the
    # suffix wins over options["p3p"]'s feature settings, so "sbi+p3p" keeps them.
    options = {"p3p": {"kind": "orb", "max_features": 800, "ratio": 0.7},
               "p3p:sift": {"max_features": 1500}}
    plain, sift = create_relocalizer("sbi+p3p,sbi+p3p:sift", two_kind_scene.map,
                                     options=options).steps
    assert (plain.method, plain.pose.conf.kind, plain.pose.conf.max_features) == (
        "sbi+p3p", "orb", 800)
    assert (sift.method, sift.pose.conf.kind, sift.pose.conf.max_features) == (
        "sbi+p3p:sift", "sift", 1500)
    assert plain.pose.conf.ratio == sift.pose.conf.ratio == 0.7
    with pytest.raises(ConfigError, match="features one of"):
        create_relocalizer("sbi+p3p:surf", two_kind_scene.map)
    with pytest.raises(ConfigError, match="takes no features"):
        create_relocalizer("sbi+esm:orb", two_kind_scene.map)
    with pytest.raises(ConfigError, match="unknown pose finder"):
        create_relocalizer("sbi+p4p:orb", two_kind_scene.map)
    listed = {m["method"] for m in list_methods()}
    assert {"sbi+p3p:orb", "bow+p3p:sift", DEFAULT_METHOD} <= listed
    assert "sbi+esm:orb" not in listed


@pytest.fixture(scope="module")
def room_two_kinds(synthetic_scene) -> KeyframeMap:
    """The synthetic room (a scene with depth) mapped with SIFT and ORB landmarks."""
    kmap = KeyframeMap()
    builder = MapBuilder(kmap, MappingConf(feature_kinds=("sift", "orb")))
    for i, (image, pose) in enumerate(zip(synthetic_scene.keyframe_images,
                                          synthetic_scene.keyframe_poses, strict=True)):
        builder.add_keyframe(i, image, synthetic_scene.camera, pose, timestamp=float(i))
    return kmap


def test_default_answers_with_orb_when_it_verifies(synthetic_scene, room_two_kinds):
    query = Frame(synthetic_scene.query_images[1], synthetic_scene.camera)
    chain = create_relocalizer("sbi+p3p:orb,sbi+p3p", room_two_kinds)
    result = chain.relocalize(query)
    assert result.ok and result.method == "sbi+p3p:orb"
    # within the evaluation's 5 cm: ORB's coarser keypoints (8 pyramid levels, no sub-pixel
    # refinement) give about 1 cm here where SIFT gives a few millimetres
    assert pose_error(result.world_from_cam, synthetic_scene.query_poses[1])[0] < 0.05
    assert set(query.features) == {"orb"}  # SIFT never extracted: the fast path answered


def test_orb_leaves_a_plane_seen_face_on_to_the_last_step(two_kind_scene):
    """On one plane seen from above the focal and the height trade off: ORB's check of the
    query's intrinsics is inconclusive, so the ORB step leaves the query to the SIFT step,
    which, being the last, answers trusting the calibration."""
    gt = query_pose(1)
    chain = create_relocalizer("sbi+p3p:orb,sbi+p3p", two_kind_scene.map)
    orb_alone = chain.steps[0].relocalize(Frame(two_kind_scene.render(gt), CAMERA))
    assert not orb_alone.ok and "intrinsics unchecked" in orb_alone.reason
    result = chain.relocalize(Frame(two_kind_scene.render(gt), CAMERA))
    assert result.ok and result.method == "sbi+p3p"
    assert pose_error(result.world_from_cam, gt)[0] < 0.01
    alone = create_relocalizer("sbi+p3p:orb", two_kind_scene.map)  # the last step trusts
    assert alone.relocalize(Frame(two_kind_scene.render(gt), CAMERA)).ok


def test_sift_step_answers_when_orb_cannot_verify(two_kind_scene):
    kmap = _map_with_orb(two_kind_scene, None)  # ORB keypoints, but no ORB landmark
    gt = query_pose(2)
    chain = create_relocalizer("sbi+p3p:orb,sbi+p3p", kmap)
    orb_alone = chain.steps[0].relocalize(Frame(two_kind_scene.render(gt), CAMERA))
    assert not orb_alone.ok and "too few inliers" in orb_alone.reason
    result = chain.relocalize(Frame(two_kind_scene.render(gt), CAMERA))
    assert result.ok and result.method == "sbi+p3p"
    assert pose_error(result.world_from_cam, gt)[0] < 0.01


def test_a_failed_group_starts_the_next_steps_extraction_ahead(two_kind_scene, synthetic_scene,
                                                               room_two_kinds, monkeypatch):
    """The ORB step (no ORB landmark here) fails its first group with another to go: with
    ``look_ahead`` the SIFT step's features are extracted then, once, on a helper thread,
    and the answer is the same as without; a first group that verifies starts nothing."""
    monkeypatch.setattr(overlap, "idle_core", lambda: True)
    calls: list[tuple[str, str]] = []
    real_extract = feature_lib.extract

    def counted(image, conf=None, **kwargs):
        calls.append((conf.kind, threading.current_thread().name))
        return real_extract(image, conf, **kwargs)

    monkeypatch.setattr(feature_lib, "extract", counted)
    kmap = _map_with_orb(two_kind_scene, None)
    gt = query_pose(2)
    answers = {}
    for look_ahead in (True, False):
        calls.clear()
        chain = create_relocalizer("sbi+p3p:orb,sbi+p3p", kmap,
                                   options={"multi": {"look_ahead": look_ahead}})
        assert len(chain.steps[0]._candidate_groups(
            Frame(two_kind_scene.render(gt), CAMERA), kmap.snapshot(), None, 1)) >= 2
        query = Frame(two_kind_scene.render(gt), CAMERA)
        result = chain.relocalize(query)
        assert result.ok and result.method == "sbi+p3p"
        answers[look_ahead] = result
        sift = [thread for kind, thread in calls if kind == "sift"]
        main = threading.current_thread().name
        assert sift == (["reloc-beside"] if look_ahead else [main])
        assert not query.pending_features("sift")
    on, off = answers[True], answers[False]
    assert np.array_equal(on.world_from_cam, off.world_from_cam)
    assert (on.inliers, on.num_matches, on.matched_keyframe_ids) == (
        off.inliers, off.num_matches, off.matched_keyframe_ids)
    calls.clear()
    query = Frame(synthetic_scene.query_images[1], synthetic_scene.camera)
    verified = create_relocalizer("sbi+p3p:orb,sbi+p3p", room_two_kinds).relocalize(query)
    assert verified.ok and verified.method == "sbi+p3p:orb"
    assert [kind for kind, _ in calls] == ["orb"] and set(query.features) == {"orb"}


def test_orb_step_refuses_the_pose_of_scrambled_landmarks(two_kind_scene):
    """ORB landmarks whose world points are shuffled among them: whatever pose RANSAC finds
    on those matches is wrong, and the ORB step must say "not relocalized", not answer it;
    the SIFT step behind it then answers the right pose."""
    rng = np.random.default_rng(0)
    all_points = np.concatenate([kf.features["orb"].points_world for kf in
                                 two_kind_scene.map.snapshot().keyframes.values()])
    all_points = all_points[np.isfinite(all_points).all(axis=1)]

    def scrambled(orb: Features) -> np.ndarray:
        points = orb.points_world.copy()
        has = orb.landmark_ids >= 0
        points[has] = all_points[rng.integers(0, len(all_points), int(has.sum()))]
        return points

    kmap = _map_with_orb(two_kind_scene, scrambled)
    chain = create_relocalizer("sbi+p3p:orb,sbi+p3p", kmap)
    for index in range(3):
        gt = query_pose(index)
        orb_alone = chain.steps[0].relocalize(Frame(two_kind_scene.render(gt), CAMERA))
        assert not orb_alone.ok and orb_alone.world_from_cam is None
        result = chain.relocalize(Frame(two_kind_scene.render(gt), CAMERA))
        assert result.ok and result.method == "sbi+p3p"
        assert pose_error(result.world_from_cam, gt)[0] < 0.01


def test_a_later_step_reuses_the_orb_features_of_the_first(two_kind_scene):
    strict = create_relocalizer("sbi+p3p:orb", two_kind_scene.map,
                                options={"verify": {"min_inliers": 100_000}})
    chain = ChainRelocalizer(two_kind_scene.map,
                             [strict, create_relocalizer("sbi+p3p:orb", two_kind_scene.map)])
    query = Frame(two_kind_scene.render(query_pose(0)), CAMERA)
    first = strict.relocalize(query)
    assert not first.ok
    cached = query.features["orb"]
    result = chain.relocalize(query)
    assert result.ok and result.method == "sbi+p3p:orb"
    assert query.features["orb"] is cached  # no step extracted ORB again


def test_save_dirs_of_a_chain_with_feature_suffixes(two_kind_scene, tmp_path):
    create_relocalizer("sbi+p3p:orb,sbi+p3p", two_kind_scene.map).save(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["0_sbi_p3p_orb", "1_sbi_p3p"]


def _shifted(offset_m: np.ndarray) -> Callable[[Features], np.ndarray]:
    """ORB landmarks moved rigidly by ``offset_m``: the ORB step then verifies a consistent
    pose that is wrong by that offset, as a repeated texture elsewhere would give."""
    return lambda orb: orb.points_world + offset_m


@pytest.fixture()
def every_answer_narrow(monkeypatch):
    """Every step's answer counts as resting on a small part of the image (the synthetic
    scenes cannot give a narrow support that the planar-patch test lets through)."""
    from reloc_service.algorithms.relocalizers import chain as chain_module

    monkeypatch.setattr(chain_module, "narrow_support", lambda estimate, conf: True)


def test_narrow_support_is_the_inliers_hull_against_the_patch_share():
    from reloc_service.algorithms.pose.base import PoseEstimate
    from reloc_service.algorithms.relocalizers.base import VerifyConf
    from reloc_service.algorithms.relocalizers.chain_hooks import narrow_support

    corners = np.array([[0, 0], [80, 0], [80, 60], [0, 60], [40, 30]], np.float64)
    est = PoseEstimate(np.eye(4), [0], inlier_px=corners, image_size=(320, 240))
    assert narrow_support(est, VerifyConf())  # 1/16 of the image < 4 of 16 cells
    est.inlier_px = corners * 3.0  # 9/16 of it
    assert not narrow_support(est, VerifyConf())
    est.inlier_px = None
    assert not narrow_support(est, VerifyConf())


def test_a_later_step_overrules_a_narrow_answer_that_explains_less(
        synthetic_scene, room_two_kinds, every_answer_narrow):
    """The ORB step verifies a pose 15 cm off (its landmarks moved); asked for a second
    opinion, the SIFT step finds its own pose explains clearly more SIFT keypoints and
    answers that. Without the second opinion the chain would answer ORB's. (The room: a
    scene with depth lets the ORB step check the query's intrinsics, so it answers rather
    than deferring as on a plane seen face on.)"""
    kmap = _room_with(room_two_kinds, "orb", lambda f, _: f.points_world + [0.15, 0.0, 0.0])
    query, gt = _room_query(synthetic_scene, 1)
    chain = create_relocalizer("sbi+p3p:orb,sbi+p3p", kmap)
    orb_alone = chain.steps[0].relocalize(query())
    assert orb_alone.ok and pose_error(orb_alone.world_from_cam, gt)[0] > 0.1
    result = chain.relocalize(query())
    assert result.ok and result.method == "sbi+p3p"
    assert pose_error(result.world_from_cam, gt)[0] < 0.01


def test_a_later_step_that_explains_a_narrow_answer_answers_more_precisely(
        synthetic_scene, room_two_kinds, every_answer_narrow):
    """A right ORB answer is explained by the SIFT step's own pose: the SIFT pose answers."""
    query, gt = _room_query(synthetic_scene, 1)
    chain = create_relocalizer("sbi+p3p:orb,sbi+p3p", room_two_kinds)
    result = chain.relocalize(query())
    assert result.ok and result.method == "sbi+p3p"
    assert pose_error(result.world_from_cam, gt)[0] < 0.01


def test_a_narrow_answer_stands_when_no_later_step_verifies(synthetic_scene, room_two_kinds,
                                                            every_answer_narrow):
    """The SIFT step verifies nothing (its landmarks scrambled): the ORB answer stands."""
    rng = np.random.default_rng(1)

    def scrambled(sift: Features, kf: Keyframe) -> np.ndarray:
        points = sift.points_world.copy()
        mapped = sift.landmark_ids >= 0
        points[mapped] = kf.world_from_cam[:3, 3] + rng.uniform(-2, 2, (int(mapped.sum()), 3))
        return points

    kmap = _room_with(room_two_kinds, "sift", scrambled)
    query, gt = _room_query(synthetic_scene, 1)
    chain = create_relocalizer("sbi+p3p:orb,sbi+p3p", kmap)
    frame = query()
    result = chain.relocalize(frame)
    assert result.ok and result.method == "sbi+p3p:orb"
    assert pose_error(result.world_from_cam, gt)[0] < 0.05
    assert "sift" in frame.features  # the SIFT step was asked


def _room_with(kmap: KeyframeMap, kind: str,
               points: Callable[[Features, Keyframe], np.ndarray]) -> KeyframeMap:
    """A copy of ``kmap`` whose ``kind`` landmarks are put at ``points(features, keyframe)``,
    the other kind's kept as they are."""
    copy = KeyframeMap()
    for kf in kmap.snapshot().keyframes.values():
        features = dict(kf.features)
        features[kind] = dataclasses.replace(features[kind],
                                             points_world=points(features[kind], kf))
        copy.add_keyframe(Keyframe(image=kf.image, camera=kf.camera, id=kf.id,
                                   world_from_cam=kf.world_from_cam, features=features))
    return copy


def _room_query(scene, index: int) -> tuple[Callable[[], Frame], np.ndarray]:
    """A fresh query frame of the room's ``index``-th query (features are cached on a
    frame, so each relocalization gets its own), and its ground truth."""
    return (lambda: Frame(scene.query_images[index], scene.camera)), scene.query_poses[index]
