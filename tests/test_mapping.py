"""Map building: accuracy, neighbours only, depth keyframes, removal, SVO-style given
landmarks, extra feature kinds, configuration, and landmark_errors."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from conftest import SyntheticScene

from reloc_service.core.errors import ConfigError, GeometryError, MapError
from reloc_service.core.geometry import invert, look_at, transform_points
from reloc_service.core.map import KeyframeMap
from reloc_service.core.mapping import (
    DEFAULT_MAX_FEATURES,
    MapBuilder,
    MappingConf,
    first_observations,
    landmark_errors,
    select_neighbours,
)
from reloc_service.core.triangulation import TriangulationConf
from reloc_service.service.config import parse_config


class FakeDataset:
    """What landmark_errors needs of a Dataset: map entries and their depth maps."""

    def __init__(self, depths: list[np.ndarray]) -> None:
        self.map_entries = list(range(len(depths)))
        self.depths = depths

    def load_truth_depth(self, entry: int) -> np.ndarray:
        return self.depths[entry]


def _build(scene: SyntheticScene, conf: MappingConf | None = None, ids=None, **kw) -> MapBuilder:
    builder = MapBuilder(KeyframeMap(), conf)
    for i in (range(len(scene.keyframe_images)) if ids is None else ids):
        builder.add_keyframe(i, scene.keyframe_images[i], scene.camera, scene.keyframe_poses[i],
                             **kw)
    return builder


def test_synthetic_map_is_accurate(synthetic_scene, synthetic_map):
    errors, ranges = landmark_errors(synthetic_map, FakeDataset(synthetic_scene.keyframe_depths),
                                     return_range=True)
    assert len(errors) > 0.95 * len(synthetic_map.landmarks) > 500
    assert np.median(errors) < 0.004          # ~2 m range, 320x240, f = 250 px
    assert np.mean(errors < 0.03) > 0.95
    assert 1.2 < np.median(ranges) < 2.8
    obs = np.array([len(lm.observations) for lm in synthetic_map.landmarks.values()])
    assert obs.min() >= 2 and np.mean(obs >= 3) > 0.4   # tracks were extended


def test_radtan_map_is_accurate(synthetic_scene_radtan):
    builder = _build(synthetic_scene_radtan)
    errors = landmark_errors(builder.map.snapshot(), FakeDataset(synthetic_scene_radtan.keyframe_depths))
    assert np.median(errors) < 0.005


def test_select_neighbours_nearest_within_view_angle(synthetic_map):
    kf = synthetic_map.keyframes[0]
    assert select_neighbours(synthetic_map, kf, 3, 60.0) == [1, 2, 3]
    assert select_neighbours(synthetic_map, kf, 0, 60.0) == []
    turned = synthetic_map.keyframes[5]
    away = look_at(turned.position_world, turned.position_world - np.array([0.0, 1.0, 0.0]))
    fake = type(turned)(image=turned.image, camera=turned.camera, id=99, world_from_cam=away)
    assert select_neighbours(synthetic_map, fake, 5, 60.0) == []


def test_adding_a_keyframe_only_touches_its_neighbours(synthetic_scene, synthetic_map):
    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    builder = MapBuilder(kmap, MappingConf(neighbours=2))
    new = builder.add_keyframe(6, synthetic_scene.query_images[2], synthetic_scene.camera,
                               synthetic_scene.query_poses[2])
    after = kmap.snapshot()
    neighbours = select_neighbours(synthetic_map, new, 2, 60.0)
    assert len(neighbours) == 2
    others = [k for k in synthetic_map.keyframes if k not in neighbours]
    for kf_id in others:                      # not matched against: same landmarks
        assert np.array_equal(synthetic_map.keyframes[kf_id].features["sift"].landmark_ids,
                              after.keyframes[kf_id].features["sift"].landmark_ids)
    new_observers = set()
    for lm_id, lm in after.landmarks.items():
        old = (synthetic_map.landmarks[lm_id].observations if lm_id in synthetic_map.landmarks
               else frozenset())
        new_observers |= {o[0] for o in lm.observations - old}
    assert 6 in new_observers and new_observers <= {6, *neighbours}
    stats = builder.last_stats["sift"]
    assert stats.extended > 0 and stats.created + sum(stats.rejected.values()) > 0


def test_depth_keyframes_make_landmarks_from_depth(synthetic_scene):
    builder = _build(synthetic_scene, ids=[0])
    assert len(builder.map.snapshot().landmarks) == 0        # one view: nothing to triangulate
    kf = builder.add_keyframe(1, synthetic_scene.keyframe_images[1], synthetic_scene.camera,
                              synthetic_scene.keyframe_poses[1],
                              depth=synthetic_scene.keyframe_depths[1])
    stats = builder.last_stats["sift"]
    assert stats.from_depth > 0.7 * len(kf.features["sift"]) and stats.created == 0
    assert kf.depth is not None and kf.depth.dtype == np.float32
    errors = landmark_errors(builder.map.snapshot(), FakeDataset(synthetic_scene.keyframe_depths))
    assert np.median(errors) < 1e-3




def test_depth_landmarks_keep_their_measured_point_when_seen_again_from_nearby(
        panning_depth_map):
    """A camera panning in place with exact depth (conftest): track refinement on the
    keypoints alone cannot place a point along such nearly parallel rays; a depth landmark,
    stated exact, must stay where its depth put it (before, refinement slid many landmarks
    metres along their rays)."""
    state = panning_depth_map.state
    assert any(len(lm.observations) >= 2 for lm in state.landmarks.values())   # tracks extended
    errors = landmark_errors(state, FakeDataset(panning_depth_map.depths))
    assert len(errors) > 500
    assert np.percentile(errors, 99) < 1e-3, np.percentile(errors, [50, 90, 99])

def test_remove_keyframe_drops_its_observations(synthetic_map):
    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    builder = MapBuilder(kmap)
    removed = builder.remove_keyframe(2)
    assert removed is synthetic_map.keyframes[2]
    after = kmap.snapshot()
    assert 2 not in after.keyframes and after.version == synthetic_map.version + 1
    for lm_id, lm in synthetic_map.landmarks.items():
        rest = {o for o in lm.observations if o[0] != 2}
        if rest:
            assert after.landmarks[lm_id].observations == rest
        else:
            assert lm_id not in after.landmarks
    # A landmark seen by the removed keyframe and one other keeps its point (still valid for
    # pose estimation) with that one observation.
    only_two = [i for i, lm in synthetic_map.landmarks.items()
                if len(lm.observations) == 2 and any(o[0] == 2 for o in lm.observations)]
    assert only_two and all(len(after.landmarks[i].observations) == 1 for i in only_two)
    for k in after.keyframes:                 # features still agree with the landmarks
        feats = after.keyframes[k].features["sift"]
        for idx in np.flatnonzero(feats.has_landmark):
            assert (k, "sift", idx) in after.landmarks[int(feats.landmark_ids[idx])].observations
    with pytest.raises(MapError, match="keyframe 2"):
        builder.remove_keyframe(2)


def _svo_points(scene: SyntheticScene, kf: int, n: int, seed: int = 0):
    """World points on the rendered surface seen by keyframe ``kf`` and their pixels."""
    rng = np.random.default_rng(seed)
    cam = scene.camera
    px = np.column_stack([rng.uniform(30, cam.width - 30, n), rng.uniform(30, cam.height - 30, n)])
    rows, cols = np.rint(px[:, 1]).astype(int), np.rint(px[:, 0]).astype(int)
    px = np.column_stack([cols, rows]).astype(float)     # integer pixels: exact depth
    z = scene.keyframe_depths[kf][rows, cols].astype(np.float64)
    bearings = cam.unproject(px)
    p_cam = bearings / bearings[:, 2:] * z[:, None]
    return px, transform_points(scene.keyframe_poses[kf], p_cam)


def test_given_svo_landmarks_are_registered_and_described(synthetic_scene):
    scene = synthetic_scene
    px, pts = _svo_points(scene, 0, 60)
    ids = np.arange(1000, 1060)
    ids[::10] = -1                                    # some SVO features without a 3D point
    pts_given = pts.copy()
    pts_given[ids < 0] = np.nan
    builder = MapBuilder(KeyframeMap())
    kf = builder.add_keyframe(0, scene.keyframe_images[0], scene.camera, scene.keyframe_poses[0],
                              given_keypoints_px=px, given_landmark_ids=ids,
                              given_points_world=pts_given)
    feats = kf.features["sift"]
    state = builder.map.snapshot()
    given = feats.landmark_ids[feats.landmark_ids >= 1000]
    assert len(given) >= 40 and set(given.tolist()) <= set(ids.tolist())
    for lm_id in given.tolist():
        i = int(np.flatnonzero(ids == lm_id)[0])
        assert np.array_equal(state.landmarks[lm_id].point_world, pts[i])
    # Given keypoints come first with descriptors; detected ones within 2 px of them dropped.
    n_given = int(np.sum(np.isin(feats.keypoints_px, px).all(axis=1)))
    assert np.all(np.isfinite(feats.descriptors[:n_given]))
    d = np.linalg.norm(feats.keypoints_px[n_given:, None] - px[None], axis=2)
    assert d.min() > 2.0
    assert state.next_landmark_id >= 1060
    # SVO tracked the same points into the next keyframe: the same ids add observations.
    px1 = scene.camera.project(transform_points(invert(scene.keyframe_poses[1]), pts))
    builder.add_keyframe(1, scene.keyframe_images[1], scene.camera, scene.keyframe_poses[1],
                         given_keypoints_px=px1, given_landmark_ids=ids,
                         given_points_world=pts_given)
    state = builder.map.snapshot()
    assert all(1 in {o[0] for o in state.landmarks[i].observations} for i in given.tolist()
               if i in builder.map.snapshot().keyframes[1].features["sift"].landmark_ids)
    # Given keypoints without ids are matched by their descriptors and extend the tracks.
    px2 = scene.camera.project(transform_points(invert(scene.keyframe_poses[2]), pts))
    builder.add_keyframe(2, scene.keyframe_images[2], scene.camera, scene.keyframe_poses[2],
                         given_keypoints_px=px2)
    state = builder.map.snapshot()
    extended = [i for i in given.tolist() if 2 in {o[0] for o in state.landmarks[i].observations}]
    assert len(extended) > 10


def test_given_features_are_validated(synthetic_scene):
    builder = MapBuilder(KeyframeMap())
    args = (0, synthetic_scene.keyframe_images[0], synthetic_scene.camera,
            synthetic_scene.keyframe_poses[0])
    with pytest.raises(GeometryError, match="given_keypoints_px"):
        builder.add_keyframe(*args, given_keypoints_px=np.zeros((3, 3)))
    with pytest.raises(GeometryError, match="no finite 3D point"):
        builder.add_keyframe(*args, given_keypoints_px=np.zeros((2, 2)),
                             given_landmark_ids=[3, 4])
    with pytest.raises(GeometryError, match="need given_keypoints_px"):
        builder.add_keyframe(*args, given_landmark_ids=[3])
    assert len(builder.map) == 0


def test_feature_kinds_added_later_are_triangulated(synthetic_scene, synthetic_map):
    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    builder = MapBuilder(kmap)
    assert builder.add_feature_kinds(["orb"]) == [0, 1, 2, 3, 4, 5]
    state = kmap.snapshot()
    assert builder.conf.feature_kinds == ("sift", "orb")
    assert state.landmark_count("orb") > 500
    assert state.landmark_count("sift") == synthetic_map.landmark_count("sift")
    errors = landmark_errors(state, FakeDataset(synthetic_scene.keyframe_depths), kind="orb")
    assert np.median(errors) < 0.01
    assert builder.add_feature_kinds(["orb"]) == []


def test_mapping_conf_from_options():
    conf = MappingConf.from_options({"feature_kinds": ["sift", "orb"], "neighbours": 3,
                                     "triangulation": {"min_parallax_deg": 2}})
    assert conf.feature_kinds == ("sift", "orb") and conf.neighbours == 3
    assert conf.triangulation == TriangulationConf(min_parallax_deg=2.0)
    assert conf.with_kinds(["orb", "sift"]).feature_kinds == ("sift", "orb")
    with pytest.raises(ConfigError, match="unknown option"):
        MappingConf.from_options({"neighbors": 3})
    with pytest.raises(ConfigError, match="mapping.triangulation"):
        MappingConf.from_options({"triangulation": {"ratio": 2.0, "x": 1}})
    with pytest.raises(ConfigError, match="feature_kinds"):
        MappingConf(feature_kinds=("surf",))


def test_the_calibration_accuracy_is_a_mapping_option_the_map_states():
    """``[mapping] calibration_focal_sigma_rel`` / ``calibration_radial_sigma_px``: the
    map's stated calibration covariance (0.5 % and 2 px by default; 0: exact); negative or
    non-finite values are refused, and so is a map given a covariance that is not one."""
    assert np.allclose(MappingConf().calibration_covariance(), np.diag([0.005**2, 4.0]))
    conf = MappingConf.from_options({"calibration_focal_sigma_rel": 0.0,
                                     "calibration_radial_sigma_px": 0.5})
    kmap = KeyframeMap(calibration_covariance=conf.calibration_covariance())
    assert np.array_equal(kmap.snapshot().calibration_covariance, np.diag([0.0, 0.25]))
    for name in ("calibration_focal_sigma_rel", "calibration_radial_sigma_px"):
        for bad in (-0.1, float("nan"), "1"):
            with pytest.raises(ConfigError, match=f"mapping.{name}: expected"):
                MappingConf.from_options({name: bad})
    for bad_cov in (np.eye(3), np.diag([-1.0, 1.0]), np.array([[1.0, 2.0], [0.0, 1.0]])):
        with pytest.raises(MapError, match="calibration_covariance: expected"):
            KeyframeMap(calibration_covariance=bad_cov)


def test_max_features_one_number_or_a_table_per_kind():
    assert MappingConf.from_options({"max_features": 1500}).features_for("orb") == 1500
    table = MappingConf.from_options({"max_features": {"orb": 700}})
    assert (table.features_for("orb"), table.features_for("sift")) == (700, DEFAULT_MAX_FEATURES)
    with pytest.raises(ConfigError, match=r"unknown feature kind\(s\) \['surf'\]"):
        MappingConf.from_options({"max_features": {"surf": 100}})
    with pytest.raises(ConfigError, match="positive integer per kind.*'orb': 0"):
        MappingConf.from_options({"max_features": {"orb": 0}})
    for bad in (-3, "2000", True, 2.5):
        with pytest.raises(ConfigError, match="mapping.max_features: expected a positive"):
            MappingConf.from_options({"max_features": bad})
    toml = tomllib.loads("[mapping.max_features]\nsift = 1800\norb = 900\n")
    conf = MappingConf.from_options(parse_config(toml).mapping)
    assert (conf.features_for("sift"), conf.features_for("orb")) == (1800, 900)


def test_max_features_per_kind_caps_each_kind(synthetic_scene):
    conf = MappingConf(feature_kinds=("sift", "orb"), max_features={"sift": 300, "orb": 120})
    kf = _build(synthetic_scene, conf, ids=[0]).map.snapshot().keyframe(0)
    # ORB spreads the cap over its pyramid levels and may keep a few fewer
    assert 100 < len(kf.features["orb"]) <= 120 and 250 < len(kf.features["sift"]) <= 300
    wide = _build(synthetic_scene, MappingConf(feature_kinds=("orb",), max_features=300),
                  ids=[0]).map.snapshot().keyframe(0)
    assert 250 < len(wide.features["orb"]) <= 300


def test_first_observations_pick_the_lowest_keyframe(synthetic_map):
    first = first_observations(synthetic_map)
    seen = np.concatenate([ids for ids, _ in first.values()])
    assert len(seen) == len(np.unique(seen)) == len(synthetic_map.landmarks)
    for kf_id, (ids, px) in first.items():
        feats = synthetic_map.keyframes[kf_id].features["sift"]
        for lm_id, p in zip(ids[:20].tolist(), px[:20], strict=False):
            lm = synthetic_map.landmarks[lm_id]
            assert min(o[0] for o in lm.observations) == kf_id
            assert np.array_equal(feats.keypoints_px[feats.landmark_ids == lm_id][0], p)


def test_landmark_errors_measure_a_known_offset(synthetic_scene, synthetic_map):
    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    ids = np.array(sorted(synthetic_map.landmarks))
    base = landmark_errors(synthetic_map, FakeDataset(synthetic_scene.keyframe_depths))
    kmap.move_landmarks(ids, synthetic_map.landmark_points(ids) + (0.0, 0.0, 0.5))
    moved = landmark_errors(kmap.snapshot(), FakeDataset(synthetic_scene.keyframe_depths))
    assert np.median(moved) == pytest.approx(0.5, abs=0.01) and np.median(base) < 0.01
    # Landmarks moved in the features too.
    kf = kmap.snapshot().keyframes[0].features["sift"]
    has = kf.has_landmark
    assert np.allclose(kf.points_world[has], kmap.snapshot().landmark_points(kf.landmark_ids[has]))


@pytest.mark.slow
def test_room_landmarks_within_a_centimetre(tmp_path_factory):
    """Landmarks mapped from the photoreal ``room`` preset lie within a centimetre of the
    scene (median, also at 1.5-2.5 m range; renders ~150 frames)."""
    from reloc_service.tools.data.dataset import read_dataset
    from reloc_service.tools.synth import render_dataset

    root = render_dataset("room", tmp_path_factory.mktemp("room"), seed=0, workers=1,
                          progress=False)
    dataset = read_dataset(root)
    builder = MapBuilder(KeyframeMap())
    for i, entry in enumerate(dataset.map_entries):
        builder.add_keyframe(i, dataset.load_image(entry), dataset.camera(entry),
                             entry.world_from_cam)
    errors, ranges = landmark_errors(builder.map.snapshot(), dataset, return_range=True)
    near_two = (ranges > 1.5) & (ranges < 2.5)
    assert np.median(errors) < 0.01 and np.median(errors[near_two]) < 0.01


def test_a_jpeg_keyframe_is_decoded_once_and_kept_encoded(synthetic_scene):
    """The service decodes a client's JPEG once to check it; the map extracts features from
    those very pixels (no second decode) and keeps the keyframe as its JPEG, not 300 kB of
    pixels a keyframe (its pixels are decoded again when read after they left the cache)."""
    import cv2
    from reloc_client.protocol import WireImage

    from reloc_service.core.frame import RECENT_PIXELS, EncodedImage
    from reloc_service.service.codec import keyframe_image

    scene = synthetic_scene
    jpeg = cv2.imencode(".jpg", scene.keyframe_images[0], [cv2.IMWRITE_JPEG_QUALITY, 90])[1]
    image = keyframe_image(WireImage.from_bytes(jpeg.tobytes()), scene.camera, "keyframe.image")
    assert isinstance(image, EncodedImage)
    checked = RECENT_PIXELS.get(image)              # the pixels the service checked
    assert checked is not None and np.array_equal(checked, cv2.imdecode(jpeg, 0))
    builder = MapBuilder(KeyframeMap())
    kf = builder.add_keyframe(0, image, scene.camera, scene.keyframe_poses[0])
    assert kf.image_source is image and kf.encoded is image
    assert kf.image is checked                      # read while recent: the same pixels
    plain = MapBuilder(KeyframeMap()).add_keyframe(0, checked.copy(), scene.camera,
                                                   scene.keyframe_poses[0])
    a, b = kf.features["sift"], plain.features["sift"]
    assert np.array_equal(a.keypoints_px, b.keypoints_px)
    assert np.array_equal(a.descriptors, b.descriptors)
