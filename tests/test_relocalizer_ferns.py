"""Tests of the ferns relocalizer on a small scene: a textured plane seen from known poses.

The views are rendered with ``cv2.warpPerspective`` (the plane's homography); SIFT keypoints are
lifted onto the plane analytically, and keypoints of different views whose world points agree
within 6 mm become one landmark (as SVO would send them with the keyframes).
"""

from __future__ import annotations

import copy
import dataclasses
import json
from dataclasses import dataclass

import cv2
import numpy as np
import pytest
import skimage.data
from scipy.spatial import cKDTree

from reloc_service.algorithms.ferns.fern_tests import FernConf
from reloc_service.algorithms.ferns.training import WarpConf
from reloc_service.algorithms.relocalizers.base import Prior
from reloc_service.algorithms.relocalizers.factory import create_relocalizer
from reloc_service.algorithms.relocalizers.ferns import FernsRelocalizer
from reloc_service.algorithms.relocalizers.ferns_conf import FernsConf
from reloc_service.core.cameras import PinholeCamera
from reloc_service.core.errors import ConfigError, NotTrainedError, StorageError
from reloc_service.core.frame import Features, Frame, Keyframe
from reloc_service.core.geometry import pose_error, so3_exp
from reloc_service.core.map import KeyframeMap

CAMERA = PinholeCamera(width=320, height=240, fx=280.0, fy=280.0, cx=159.5, cy=119.5)
METRES_PER_TEXEL = 0.004
#: Small and fast: enough for a 500-landmark scene.
FAST = dict(num_ferns=40, num_tests=10, num_warps=25, workers=2)


def _grey(name: str) -> np.ndarray:
    img = getattr(skimage.data, name)()
    return cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


def _pose(x: float, y: float, z: float, rx: float = 0.0, ry: float = 0.0, rz: float = 0.0
          ) -> np.ndarray:
    """world_from_cam of a camera at (x, y, z) looking along +z at the plane z = 0."""
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = so3_exp(np.array([rx, ry, rz]))
    world_from_cam[:3, 3] = (x, y, z)
    return world_from_cam


def render(texture: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray:
    """The plane z = 0 (texel (u, v) at world (s (u - cu), s (v - cv), 0)) seen by CAMERA."""
    h, w = texture.shape
    s = METRES_PER_TEXEL
    world_from_texel = np.array([[s, 0, -s * (w - 1) / 2], [0, s, -s * (h - 1) / 2], [0, 0, 0]])
    rot, centre = world_from_cam[:3, :3], world_from_cam[:3, 3]
    cam_from_texel = rot.T @ world_from_texel
    cam_from_texel[:, 2] -= rot.T @ centre
    return cv2.warpPerspective(texture, CAMERA.K @ cam_from_texel, CAMERA.size,
                               flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def lift(px: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray:
    """(N, 3) world points of pixels on the plane z = 0."""
    rays = CAMERA.unproject(px) @ world_from_cam[:3, :3].T
    centre = world_from_cam[:3, 3]
    return centre + (-centre[2] / rays[:, 2])[:, None] * rays


@dataclass
class View:
    image: np.ndarray
    world_from_cam: np.ndarray
    px: np.ndarray
    descriptors: np.ndarray
    points_world: np.ndarray


def make_views(texture: np.ndarray, poses: list[np.ndarray]) -> list[View]:
    views = []
    for world_from_cam in poses:
        image = render(texture, world_from_cam)
        kps, desc = cv2.SIFT.create(nfeatures=600).detectAndCompute(image, None)
        px = cv2.KeyPoint.convert(kps).astype(np.float64)
        views.append(View(image, world_from_cam, px, desc, lift(px, world_from_cam)))
    return views


def landmark_labels(views: list[View], radius: float = 0.006) -> list[np.ndarray]:
    """Per view, the landmark id of each keypoint (-1: seen by fewer than two views)."""
    points = np.concatenate([v.points_world for v in views])
    owner = np.concatenate([np.full(len(v.px), i) for i, v in enumerate(views)])
    label = np.full(len(points), -1)
    tree = cKDTree(points)
    next_id = 0
    for i in range(len(points)):  # test scaffolding: greedy clustering, one keypoint per view
        if label[i] >= 0:
            continue
        seen, members = set(), []
        for j in sorted(tree.query_ball_point(points[i], radius)):
            if label[j] < 0 and owner[j] not in seen:
                seen.add(owner[j])
                members.append(j)
        label[members] = next_id
        next_id += 1
    label[np.bincount(label)[label] < 2] = -1
    return np.split(label, np.cumsum([len(v.px) for v in views])[:-1])


def make_keyframe(view: View, kf_id: int, labels: np.ndarray, means: dict[int, np.ndarray]
                  ) -> Keyframe:
    points = np.array([means[lab] if lab >= 0 else np.full(3, np.nan) for lab in labels])
    feats = Features.create("sift", view.px, view.descriptors, landmark_ids=labels,
                            points_world=points.reshape(-1, 3))
    return Keyframe(image=view.image, camera=CAMERA, id=kf_id, world_from_cam=view.world_from_cam,
                    features={"sift": feats})


@dataclass
class Scene:
    texture: np.ndarray
    keyframes: list[Keyframe]
    queries: list[np.ndarray]

    def map(self, ids: list[int] | None = None) -> KeyframeMap:
        kmap = KeyframeMap()
        for kf in self.keyframes:
            if ids is None or kf.id in ids:
                kmap.add_keyframe(kf)
        return kmap


@pytest.fixture(scope="module")
def scene() -> Scene:
    texture = _grey("astronaut")
    poses = [_pose(-0.25, -0.1, -2.0, 0.05, -0.1), _pose(0.2, -0.1, -2.0, 0.0, 0.1, 0.05),
             _pose(-0.2, 0.2, -1.8, -0.08, -0.05), _pose(0.25, 0.2, -2.1, -0.05, 0.1, -0.05)]
    views = make_views(texture, poses)
    labels = landmark_labels(views)
    points = np.concatenate([v.points_world for v in views])
    flat = np.concatenate(labels)
    means = {int(lab): points[flat == lab].mean(0) for lab in np.unique(flat[flat >= 0])}
    keyframes = [make_keyframe(v, i, lab, means)
                 for i, (v, lab) in enumerate(zip(views, labels, strict=True))]
    queries = [_pose(0.0, 0.05, -1.9, 0.03, 0.02, 0.1), _pose(-0.3, 0.25, -1.7, -0.1, -0.1, 0.3)]
    return Scene(texture, keyframes, queries)


@pytest.fixture(scope="module")
def trained(scene: Scene) -> FernsRelocalizer:
    reloc = FernsRelocalizer(scene.map(), FernsConf(**FAST))
    reloc.train()
    return reloc


def _tables(reloc: FernsRelocalizer) -> list[tuple[np.ndarray, ...]]:
    return [(*c.count_table(), c.class_ids, c.class_counts) for c in reloc.classifiers]


def _same(a: list[tuple[np.ndarray, ...]], b: list[tuple[np.ndarray, ...]]) -> bool:
    return len(a) == len(b) and all(
        all(np.array_equal(x, y) for x, y in zip(ta, tb, strict=True))
        for ta, tb in zip(a, b, strict=True))


def _map_observations(kmap: KeyframeMap) -> set[tuple[int, int, int]]:
    landmarks = kmap.snapshot().landmarks.values()
    return {(lm.id, o[0], o[2]) for lm in landmarks for o in lm.observations}


def test_relocalizes_a_query_of_the_mapped_plane(scene: Scene, trained: FernsRelocalizer) -> None:
    for world_from_cam in scene.queries:
        result = trained.relocalize(Frame(render(scene.texture, world_from_cam), CAMERA))
        assert result.ok, result.reason
        dt, dr = pose_error(result.world_from_cam, world_from_cam)
        assert dt < 0.03 and np.degrees(dr) < 1.0, (dt, np.degrees(dr))
        assert result.method == "ferns" and result.inliers >= 50
        assert result.matched_keyframe_ids and set(result.matched_keyframe_ids) <= {0, 1, 2, 3}
        assert result.covariance is not None and result.reprojection_rms_px < 2.0
        assert {"features", "classify", "solve", "verify"} <= set(result.timings)


def test_refuses_a_query_of_an_unmapped_place(scene: Scene, trained: FernsRelocalizer) -> None:
    for name in ("coffee", "brick"):
        result = trained.relocalize(Frame(render(_grey(name), _pose(0.0, 0.0, -2.0)), CAMERA))
        assert not result.ok and result.world_from_cam is None and result.reason


def test_prior_restricts_the_classes(scene: Scene, trained: FernsRelocalizer) -> None:
    query = Frame(render(scene.texture, scene.queries[0]), CAMERA)
    far = trained.relocalize(query, prior=Prior(_pose(30.0, 0.0, -2.0), radius_m=1.0))
    assert not far.ok and "prior" in far.reason
    near = trained.relocalize(query, prior=Prior(scene.queries[0], radius_m=1.0))
    assert near.ok


def test_all_map_observations_are_trained(scene: Scene, trained: FernsRelocalizer) -> None:
    assert trained.trained_observations() == _map_observations(trained.map)
    assert trained.num_classes == len(trained.map.snapshot().landmarks)
    assert trained.required_features == frozenset({"sift"})


def test_adding_then_removing_a_keyframe_restores_exactly_the_counts(scene: Scene) -> None:
    kmap = scene.map([0, 1, 2])
    reloc = FernsRelocalizer(kmap, FernsConf(**FAST))
    reloc.train()
    before = _tables(reloc)
    kmap.add_keyframe(scene.keyframes[3])
    reloc.add_keyframe(scene.keyframes[3])
    assert not _same(_tables(reloc), before)
    assert reloc.trained_observations() == _map_observations(kmap)
    kmap.remove_keyframe(3)
    reloc.remove_keyframe(scene.keyframes[3])
    assert _same(_tables(reloc), before)


def test_online_updates_equal_training_from_scratch(scene: Scene) -> None:
    """Keyframes added and removed online, a keyframe replaced (same id, other image) and an
    observation gained by an older keyframe: the counts equal a fresh train() of the final map."""
    kmap = KeyframeMap()
    reloc = FernsRelocalizer(kmap, FernsConf(**FAST))
    for kf in scene.keyframes:
        kmap.add_keyframe(kf)
        reloc.add_keyframe(kf)
    kmap.remove_keyframe(1)
    reloc.remove_keyframe(scene.keyframes[1])
    view = make_views(scene.texture, [scene.keyframes[1].world_from_cam @ _pose(0.02, 0, 0)])[0]
    replaced = make_keyframe(view, 2, np.full(len(view.px), -1), {})
    kmap.add_keyframe(replaced)        # keyframe 2 replaced: its landmarks' observations go
    reloc.add_keyframe(replaced)
    free = int(np.flatnonzero(kmap.snapshot().keyframe(0).features["sift"].landmark_ids < 0)[0])
    landmark = next(iter(kmap.snapshot().landmarks))
    assert kmap.add_observations("sift", [(landmark, 0, free)]) == 1
    reloc.update()                     # an older keyframe gained an observation
    assert (landmark, 0, free) in reloc.trained_observations()
    assert reloc.trained_observations() == _map_observations(kmap)
    fresh = FernsRelocalizer(kmap, FernsConf(**FAST))
    fresh.train()
    assert _same(_tables(reloc), _tables(fresh))


def test_save_and_load_round_trip(scene: Scene, trained: FernsRelocalizer, tmp_path) -> None:
    trained.save(tmp_path)
    meta = json.loads((tmp_path / "ferns.json").read_text())
    assert meta["format_version"] == 1
    loaded = FernsRelocalizer(trained.map, FernsConf(**FAST))
    assert loaded.load(tmp_path)
    assert _same(_tables(loaded), _tables(trained))
    assert loaded.trained_observations() == trained.trained_observations()
    query = Frame(render(scene.texture, scene.queries[1]), CAMERA)
    a, b = trained.relocalize(query), loaded.relocalize(query)
    assert a.ok and b.ok and np.allclose(a.world_from_cam, b.world_from_cam)
    # Other options: nothing to restore. A newer format: a clear error.
    assert not FernsRelocalizer(trained.map, FernsConf(**{**FAST, "num_tests": 9})).load(tmp_path)
    assert not FernsRelocalizer(trained.map).load(tmp_path / "missing")
    meta["format_version"] = 99
    (tmp_path / "ferns.json").write_text(json.dumps(meta))
    with pytest.raises(StorageError):
        loaded.load(tmp_path)


def test_load_refuses_a_model_of_other_keyframes(scene: Scene, trained: FernsRelocalizer,
                                                 tmp_path) -> None:
    trained.save(tmp_path)
    assert not FernsRelocalizer(scene.map([0, 1]), FernsConf(**FAST)).load(tmp_path)


def test_max_classes_keeps_the_most_observed_landmarks(scene: Scene) -> None:
    kmap = scene.map()
    reloc = FernsRelocalizer(kmap, FernsConf(**{**FAST, "max_classes": 100, "partition": "select"}))
    reloc.train()
    assert reloc.num_classes == 100
    seen = {lm.id: len(lm.observations) for lm in kmap.snapshot().landmarks.values()}
    kept = set(reloc.classifiers[0].class_ids.tolist())
    assert min(seen[i] for i in kept) >= max(seen[i] for i in set(seen) - kept)


def test_regions_split_a_large_map_into_models(scene: Scene) -> None:
    kmap = scene.map()
    reloc = FernsRelocalizer(kmap, FernsConf(**{**FAST, "max_classes": 250,
                                                "partition": "regions"}))
    reloc.train()
    sizes = [c.num_classes for c in reloc.classifiers]
    assert len(sizes) >= 2 and max(sizes) <= 250
    models = [set(c.class_ids.tolist()) for c in reloc.classifiers]
    assert sum(sizes) == len(set().union(*models))          # each landmark in one model
    state = kmap.snapshot()
    region = {k: next(i for i, r in enumerate(reloc.regions) if k in r)
              for k in state.keyframes}
    for lm in set(state.landmarks) - set().union(*models):  # left out only if its models are full
        assert all(sizes[region[o[0]]] == 250 for o in state.landmarks[lm].observations)
    result = reloc.relocalize(Frame(render(scene.texture, scene.queries[0]), CAMERA))
    assert result.ok, result.reason


def test_offline_mode_needs_train(scene: Scene) -> None:
    kmap = scene.map([0, 1])
    reloc = FernsRelocalizer(kmap, FernsConf(**{**FAST, "online": False}))
    reloc.add_keyframe(scene.keyframes[0])
    assert not reloc.trained
    with pytest.raises(NotTrainedError):
        reloc.relocalize(Frame(render(scene.texture, scene.queries[0]), CAMERA))
    reloc.train()
    assert reloc.trained and reloc.num_classes > 0


def test_factory_builds_it_from_options(scene: Scene) -> None:
    reloc = create_relocalizer("ferns", scene.map([0]),
                               options={"ferns": {"num_ferns": 10, "num_tests": 8},
                                        "verify": {"min_inliers": 30},
                                        "p3p": {"max_reproj_error_px": 4.0, "ratio": 0.7}})
    assert isinstance(reloc, FernsRelocalizer)
    assert reloc.conf.num_ferns == 10 and reloc.verify_conf.min_inliers == 30
    assert reloc.pnp_conf.max_reproj_error_px == 4.0
    with pytest.raises(ConfigError):
        create_relocalizer("ferns", scene.map([0]), options={"ferns": {"num_fern": 10}})
    with pytest.raises(ConfigError):
        FernsConf(partition="everywhere")


def test_ferns_options_carry_every_classifier_and_warp_option():
    """FernsConf hands its options to FernConf and WarpConf by name: each of theirs (but
    ``include_identity``, always on) is a ferns option, with the relocalizer's default."""
    ferns = {f.name for f in dataclasses.fields(FernsConf)}
    assert {f.name for f in dataclasses.fields(FernConf)} <= ferns
    assert {f.name for f in dataclasses.fields(WarpConf)} - {"include_identity"} <= ferns
    conf = FernsConf(max_rotation_rad=3.0, num_tests=9, seed=4)
    assert conf.warp_conf() == WarpConf(max_rotation_rad=3.0, seed=4, num_warps=100,
                                        include_identity=True)
    assert conf.fern_conf() == FernConf(num_tests=9, seed=4)
    assert FernsConf().warp_conf().max_rotation_rad == 0.6


def test_keypoints_proposing_several_landmarks_agree_by_chance_more_often():
    """A keypoint proposes its top_k landmarks and RANSAC may use any: its chance of agreeing
    with a wrong pose is 1 - (1 - p)^k. Counted per keypoint, a consensus of 15 among 1000
    two-candidate keypoints (a wrong pose on room-hard) is then no longer out of chance's reach."""
    from reloc_service.algorithms.pose.base import log10_false_alarms
    from reloc_service.algorithms.relocalizers.ferns_pose import per_keypoint_chance

    p = 2.56e-4  # pi 5^2 / (640 x 480)
    assert per_keypoint_chance(p, 1000, 1000) == pytest.approx(p)
    two = per_keypoint_chance(p, 2000, 1000)
    assert two == pytest.approx(1 - (1 - p) ** 2)
    assert log10_false_alarms(1000, 15, 3, p) < -2 < log10_false_alarms(1000, 15, 3, two)
    assert per_keypoint_chance(None, 10, 5) is None


# -- region prior ------------------------------------------------------------------------------
PLACE_B_OFFSET = np.array([10.0, 0.0, 0.0])  # a second place 10 m away, another texture


def _shifted(world_from_cam: np.ndarray) -> np.ndarray:
    out = world_from_cam.copy()
    out[:3, 3] += PLACE_B_OFFSET
    return out


@pytest.fixture(scope="module")
def two_places(scene: Scene) -> tuple[FernsRelocalizer, Scene, np.ndarray]:
    """The scene's plane (keyframes 0-3) and a plane of another photo 10 m away (keyframes
    10-13, same relative poses), one region each; the relocalizer classifies a query against
    one region only. Returns it, the second place's scene and its texture."""
    texture_b = _grey("coffee")
    views = make_views(texture_b, [kf.world_from_cam for kf in scene.keyframes])
    labels = landmark_labels(views)
    first_id = 1 + max(int(kf.features["sift"].landmark_ids.max()) for kf in scene.keyframes)
    labels = [np.where(lab >= 0, lab + first_id, -1) for lab in labels]
    points = np.concatenate([v.points_world for v in views]) + PLACE_B_OFFSET
    flat = np.concatenate(labels)
    means = {int(lab): points[flat == lab].mean(0) for lab in np.unique(flat[flat >= 0])}
    for v in views:
        v.world_from_cam = _shifted(v.world_from_cam)
    keyframes_b = [make_keyframe(v, 10 + i, lab, means)
                   for i, (v, lab) in enumerate(zip(views, labels, strict=True))]
    place_b = Scene(texture_b, keyframes_b, scene.queries)
    kmap = KeyframeMap()
    for kf in scene.keyframes + keyframes_b:
        kmap.add_keyframe(kf)
    num_a = len({int(x) for kf in scene.keyframes for x in kf.features["sift"].landmark_ids
                 if x >= 0})
    num_b = len(means)
    # Room for the larger place: two regions, which k-means cuts between the places.
    # Four keyframes per place: the nearest keyframe alone votes (five would always include
    # the other place's).
    reloc = FernsRelocalizer(kmap, FernsConf(**{**FAST, "max_classes": max(num_a, num_b),
                                                "max_regions": 1, "place_keyframes": 1}))
    reloc.train()
    return reloc, place_b, texture_b


def _region_of(reloc: FernsRelocalizer, keyframe_id: int) -> int:
    return next(i for i, r in enumerate(reloc.regions) if keyframe_id in r)


def test_region_prior_picks_the_region_of_the_query(
        scene: Scene, two_places: tuple[FernsRelocalizer, Scene, np.ndarray]) -> None:
    reloc, place_b, texture_b = two_places
    assert len(reloc.regions) == 2
    assert _region_of(reloc, 0) != _region_of(reloc, 10)  # each place is its own region
    for texture, offset, kf_id in ((scene.texture, np.zeros(3), 0), (texture_b, PLACE_B_OFFSET, 10)):
        for world_from_cam in scene.queries:
            query = Frame(render(texture, world_from_cam), CAMERA)
            assert reloc.choose_regions(query) == (_region_of(reloc, kf_id),)
            result = reloc.relocalize(query)
            assert result.ok, result.reason
            truth = world_from_cam.copy()
            truth[:3, 3] += offset
            dt, dr = pose_error(result.world_from_cam, truth)
            assert dt < 0.03 and np.degrees(dr) < 1.0, (dt, np.degrees(dr))
            assert "place" in result.timings


def test_a_query_classified_in_the_wrong_region_is_not_relocalized(
        scene: Scene, two_places: tuple[FernsRelocalizer, Scene, np.ndarray]) -> None:
    reloc, place_b, texture_b = two_places
    for texture, wrong in ((texture_b, _region_of(reloc, 0)), (scene.texture, _region_of(reloc, 10))):
        for world_from_cam in scene.queries:
            result = reloc.relocalize_in(Frame(render(texture, world_from_cam), CAMERA), [wrong])
            assert not result.ok and result.world_from_cam is None and result.reason
    with pytest.raises(ValueError):
        reloc.relocalize_in(Frame(render(scene.texture, scene.queries[0]), CAMERA), [5])


def test_without_region_prior_every_region_is_classified(
        two_places: tuple[FernsRelocalizer, Scene, np.ndarray]) -> None:
    reloc, place_b, texture_b = two_places
    query = Frame(render(texture_b, place_b.queries[0]), CAMERA)
    for changes in ({"region_prior": "none"}, {"max_regions": 2}):
        every = copy.copy(reloc)  # the same trained models, other query options
        every.conf = dataclasses.replace(reloc.conf, **changes)
        assert every.choose_regions(query) == (0, 1)
        assert every.relocalize(query).ok
    with pytest.raises(ConfigError):
        FernsConf(region_prior="nearest")
    with pytest.raises(ConfigError):
        FernsConf(max_regions=0)


def test_a_fallback_classifies_each_region_once(
        scene: Scene, two_places: tuple[FernsRelocalizer, Scene, np.ndarray],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A query the prior sends to the wrong region falls back to every region: its leaves
    are read once and each region classifies it once (the wrong region's classes are
    reused), and the pose is the one classifying every region at once gives."""
    from reloc_service.algorithms.ferns.fern_tests import FernTests
    from reloc_service.algorithms.ferns.scorer import FernScorer

    reloc, place_b, texture_b = two_places
    query_image = render(texture_b, place_b.queries[0])
    wrong = _region_of(reloc, 0)
    expected = reloc.relocalize_in(Frame(query_image, CAMERA), range(len(reloc.regions)))
    assert expected.ok, expected.reason
    calls = {"leaves": 0, "classify": 0}

    def counted(name: str, fn):  # noqa: ANN001, ANN202 (test scaffolding)
        def wrapper(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            calls[name] += 1
            return fn(*args, **kwargs)
        return wrapper

    monkeypatch.setattr(FernTests, "leaves_at", counted("leaves", FernTests.leaves_at))
    monkeypatch.setattr(FernScorer, "classify", counted("classify", FernScorer.classify))
    monkeypatch.setattr(reloc, "choose_regions", lambda query, prior=None: (wrong,))
    result = reloc.relocalize(Frame(query_image, CAMERA))
    assert result.ok, result.reason
    assert calls == {"leaves": 1, "classify": len(reloc.regions)}
    np.testing.assert_allclose(result.world_from_cam, expected.world_from_cam, atol=1e-9)


def test_regions_are_tried_in_the_prior_order_one_more_each_time(
        two_places: tuple[FernsRelocalizer, Scene, np.ndarray]) -> None:
    """The best region alone, then pooled with the next, ..., then every region (with the
    fallback); a prior that ranked no region (all of them returned) gives one attempt."""
    reloc, _, _ = two_places
    staged = copy.copy(reloc)
    staged.conf = dataclasses.replace(reloc.conf, max_regions=2)
    assert staged._attempts((4, 1), 6) == [(4,), (4, 1), (0, 1, 2, 3, 4, 5)]
    assert staged._attempts((3,), 6) == [(3,), (0, 1, 2, 3, 4, 5)]
    assert staged._attempts((0, 1), 2) == [(0, 1)]
    staged.conf = dataclasses.replace(reloc.conf, max_regions=2, region_fallback=False)
    assert staged._attempts((4, 1), 6) == [(4,), (4, 1)]
