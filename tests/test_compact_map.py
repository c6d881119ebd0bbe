"""A compact snapshot: depth maps dropped once their landmarks are made (or kept losslessly),
keyframe images only where a method reads pixels, older snapshots still read."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from stored_maps import V4_MAP

from reloc_service.algorithms.relocalizers.factory import create_relocalizer
from reloc_service.core.absent_image import AbsentImage
from reloc_service.core.errors import ConfigError, MapError
from reloc_service.core.frame import Frame
from reloc_service.core.map import KeyframeMap, MapState
from reloc_service.engine import Engine, EngineConf
from reloc_service.service.config import ServiceConf, ServiceSection
from reloc_service.service.map_digest import ContentDigest
from reloc_service.storage.keyframe_parts import EVERYTHING, StoredParts
from reloc_service.storage.snapshot import UNSHARED_FORMAT_VERSION, load_map, save_map
from reloc_service.storage.snapshot_files import current_snapshot

KEEP_IMAGES = 'keyframe_images = "always"'


@pytest.fixture(scope="module")
def depth_state(synthetic_scene, synthetic_map) -> MapState:
    """The synthetic map plus one keyframe put with a depth map (its landmarks made), as a
    sensor gives it: millimetres in 16 bits, 0 (NaN) where it has no value."""
    from reloc_service.core.mapping import MapBuilder

    raw = np.round(synthetic_scene.query_depths[0] * 1000.0).astype(np.uint16)
    raw[:8, :] = 0
    depth = (raw * 0.001).astype(np.float32)
    depth[raw == 0] = np.nan
    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    MapBuilder(kmap).add_keyframe(9, synthetic_scene.query_images[0], synthetic_scene.camera,
                                  synthetic_scene.query_poses[0], depth=depth)
    return kmap.snapshot()


def _manifest(directory: Path) -> dict:
    return json.loads((current_snapshot(directory) / "manifest.json").read_text())


def _assert_same_relocalization_data(a: MapState, b: MapState) -> None:
    """Poses, features and landmark observations equal: what relocalization reads."""
    assert a.keyframe_ids() == b.keyframe_ids()
    for k in a.keyframe_ids():
        ka, kb = a.keyframes[k], b.keyframes[k]
        assert np.array_equal(ka.world_from_cam, kb.world_from_cam)
        for kind in ka.features:
            fa, fb = ka.features[kind], kb.features[kind]
            assert np.array_equal(fa.descriptors, fb.descriptors)
            assert np.array_equal(fa.keypoints_px, fb.keypoints_px)
            assert np.array_equal(fa.landmark_ids, fb.landmark_ids)
        assert ka.cache.keys() & kb.cache.keys() >= {"sbi:40x30:2.5"}
    assert sorted(a.landmarks) == sorted(b.landmarks)


def test_a_compact_snapshot_stores_no_depth_nor_images_and_loads_the_same_map(
        tmp_path, depth_state):
    assert depth_state.keyframes[9].depth is not None
    for kf in depth_state.keyframes.values():
        kf.small_blurry_image()   # as the sbi place finder leaves them
    save_map(depth_state, tmp_path, parts=StoredParts())
    manifest = _manifest(tmp_path)
    assert manifest["format_version"] == UNSHARED_FORMAT_VERSION == 7
    assert not [f for f in manifest["files"] if f.startswith(("images/", "depth/"))]
    state, _ = load_map(tmp_path)
    _assert_same_relocalization_data(depth_state, state)
    kf = state.keyframes[9]
    assert kf.depth is None and isinstance(kf.image_source, AbsentImage)
    assert kf.image_shape == depth_state.keyframes[9].image.shape
    with pytest.raises(MapError, match=KEEP_IMAGES):
        kf.image   # noqa: B018
    # replicas compare content digests: equal with the pixels' checksum kept in their stead
    assert ContentDigest().of(state) == ContentDigest().of(depth_state)
    save_map(state, tmp_path / "again", parts=EVERYTHING)   # nothing to store: still absent
    again, _ = load_map(tmp_path / "again")
    assert ContentDigest().of(again) == ContentDigest().of(depth_state)


def test_lossless_depth_is_bit_exact_and_smaller_than_raw(tmp_path, depth_state):
    depth = depth_state.keyframes[9].depth
    assert depth is not None and np.isnan(depth).any()
    save_map(depth_state, tmp_path / "raw", parts=EVERYTHING)
    save_map(depth_state, tmp_path / "z", parts=StoredParts(depth="lossless", images="always"))
    loaded, _ = load_map(tmp_path / "z")
    assert loaded.keyframes[9].depth is not None
    assert loaded.keyframes[9].depth.dtype == np.float32
    assert np.array_equal(loaded.keyframes[9].depth, depth, equal_nan=True)
    assert np.array_equal(loaded.keyframes[9].image, depth_state.keyframes[9].image)
    raw = current_snapshot(tmp_path / "raw") / "depth" / "9.npy"
    packed = current_snapshot(tmp_path / "z") / "depth" / "9.f32.zlib"
    assert packed.stat().st_size < raw.stat().st_size / 2


def test_a_damaged_lossless_depth_is_refused_by_name(tmp_path, depth_state):
    save_map(depth_state, tmp_path, parts=StoredParts(depth="lossless"))
    path = current_snapshot(tmp_path) / "depth" / "9.f32.zlib"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x10
    path.write_bytes(bytes(data))
    with pytest.raises(Exception, match="9.f32.zlib: checksum mismatch"):
        load_map(tmp_path)


def test_a_format_4_snapshot_loads_with_its_images_and_depth_and_saves_compact(tmp_path):
    """tests/data/map_v4 was written by the format-4 code (the format-3 fixture plus a depth
    map with NaN holes and a pose covariance on keyframe 0)."""
    old = json.loads((V4_MAP / "snapshots" / "000001" / "manifest.json").read_text())
    assert old["format_version"] == 4
    state, _ = load_map(V4_MAP)
    kf0 = state.keyframes[0]
    stored_depth = np.load(V4_MAP / "snapshots" / "000001" / "depth" / "0.npy")
    assert kf0.depth is not None and np.array_equal(kf0.depth, stored_depth, equal_nan=True)
    assert np.isnan(kf0.depth).any() and kf0.pose_covariance is not None
    assert kf0.image.shape == (kf0.camera.height, kf0.camera.width)
    save_map(state, tmp_path, parts=StoredParts())
    assert _manifest(tmp_path)["format_version"] == UNSHARED_FORMAT_VERSION
    compact, _ = load_map(tmp_path)
    _assert_same_relocalization_data(state, compact)
    assert compact.keyframes[0].depth is None
    assert np.array_equal(compact.keyframes[0].pose_covariance, kf0.pose_covariance)
    assert ContentDigest().of(compact) == ContentDigest().of(state)


@pytest.mark.parametrize(("method", "reads"), [
    ("ferns", True), ("sbi+esm", True), ("sbi+p3p,sbi+esm", True),
    ("sbi+p3p:orb,bow+p3p,sbi+p3p", False), ("bow+p3p", False), ("sbi+none", False)])
def test_only_methods_that_read_keyframe_pixels_say_so(method, reads):
    assert create_relocalizer(method, KeyframeMap()).reads_keyframe_images is reads


def _saved_images(directory: Path) -> int:
    return sum(f.startswith("images/") for f in _manifest(directory)["files"])


def test_an_engine_saves_images_only_for_a_method_that_reads_them(tmp_path, synthetic_map):
    save_map(synthetic_map, tmp_path / "src")
    n = len(synthetic_map.keyframes)
    p3p = Engine.load(tmp_path / "src", EngineConf(methods=("sbi+p3p",)))
    p3p.save(tmp_path / "p3p")
    assert _saved_images(tmp_path / "p3p") == 0
    p3p.save(tmp_path / "kept", parts=StoredParts(images="always"))
    assert _saved_images(tmp_path / "kept") == n
    esm = Engine.load(tmp_path / "src", EngineConf(methods=("sbi+esm",)))
    esm.save(tmp_path / "esm")
    assert _saved_images(tmp_path / "esm") == n


def test_a_pixel_reading_method_on_a_map_saved_without_images_names_the_option(
        tmp_path, synthetic_map, synthetic_scene):
    for kf in synthetic_map.keyframes.values():
        kf.small_blurry_image()   # as the sbi place finder leaves them (stored thumbnails)
    save_map(synthetic_map, tmp_path / "src", parts=StoredParts())
    engine = Engine.load(tmp_path / "src", EngineConf(methods=("sbi+p3p",)))
    query = Frame(image=synthetic_scene.query_images[1], camera=synthetic_scene.camera)
    assert engine.relocalize(query).ok
    with pytest.raises(MapError, match=KEEP_IMAGES):
        engine.relocalize(Frame(image=synthetic_scene.query_images[1],
                                camera=synthetic_scene.camera), method="ferns")


def test_the_service_options_are_checked_and_a_replica_keeps_its_images():
    assert ServiceConf().service.stored_parts() == StoredParts(
        depth="drop", images="needed", descriptor_codec="none", descriptors="landmarks")
    with pytest.raises(ConfigError, match="service.keyframe_depth: expected one of drop"):
        ServiceSection(keyframe_depth="zip")
    with pytest.raises(ConfigError, match="service.keyframe_images: expected one of needed"):
        ServiceSection(keyframe_images="sometimes")
    assert ServiceSection(bootstrap_from_peers=True).stored_parts().images == "always"


def test_a_feature_kind_added_to_a_map_saved_without_images_names_the_option(
        tmp_path, synthetic_map):
    assert sorted({k for kf in synthetic_map.keyframes.values() for k in kf.features}) == ["sift"]
    save_map(synthetic_map, tmp_path, parts=StoredParts())
    with pytest.raises(MapError, match=KEEP_IMAGES):   # ORB features cannot be extracted
        Engine.load(tmp_path, EngineConf(methods=("sbi+p3p:orb",)))
