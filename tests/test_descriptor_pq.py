"""SIFT descriptors stored as product-quantization codes: the codebook, the snapshot columns
(format 6), saves that never code a descriptor twice, and older snapshots still read."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from stored_maps import V4_MAP, V5_MAP

from reloc_service.core.errors import ConfigError, StorageError
from reloc_service.core.map import MapState
from reloc_service.service.config import ServiceConf, ServiceSection
from reloc_service.storage import descriptor_pq
from reloc_service.storage.descriptor_pq import PQCodebook, seeded_rows, train_codebook
from reloc_service.storage.keyframe_parts import EVERYTHING, StoredParts
from reloc_service.storage.snapshot import UNSHARED_FORMAT_VERSION, load_map, save_map
from reloc_service.storage.snapshot_files import current_snapshot

#: the codec alone: every keypoint kept (tests/test_landmark_rows.py drops those without one)
PQ = StoredParts(descriptor_codec="pq")


@pytest.fixture
def small_training(monkeypatch):
    """The synthetic map holds 3,127 SIFT descriptors: let a codebook be learnt from them
    (the default asks for 16,384, 64 per centroid)."""
    monkeypatch.setattr(descriptor_pq, "MIN_TRAIN_SAMPLES", 1024)


@pytest.fixture
def fresh_map(synthetic_map) -> MapState:
    """The synthetic map with keyframes of its own: a save keeps the codebook it learnt in
    its keyframes' caches, which the session's map must not carry into other tests."""
    keyframes = {k: dataclasses.replace(kf, cache={}) for k, kf in synthetic_map.keyframes.items()}
    return dataclasses.replace(synthetic_map, keyframes=keyframes)


def _sift(state: MapState) -> np.ndarray:
    return np.concatenate([kf.features["sift"].descriptors for kf in state.keyframes.values()])


def _files(directory: Path) -> dict[str, int]:
    snap = current_snapshot(directory)
    manifest = json.loads((snap / "manifest.json").read_text())
    return {f: (snap / f).stat().st_size for f in manifest["files"]}


def test_a_codebook_codes_sift_in_a_quarter_of_the_bytes_close_to_the_original(fresh_map):
    desc = _sift(fresh_map)
    codebook = train_codebook(desc, subspaces=32)
    assert codebook is None   # 3,127 descriptors: too few for 256 centroids per sub-vector
    codebook = train_codebook(np.tile(desc, (6, 1)))
    assert codebook is not None and codebook.centroids.shape == (32, 256, 4)
    codes = codebook.encode(desc)
    assert codes.shape == (len(desc), 32) and codes.dtype == np.uint8
    decoded = codebook.decode(codes)
    assert decoded.dtype == np.uint8 and decoded.shape == desc.shape
    err = np.linalg.norm(decoded.astype(float) - desc, axis=1) / np.linalg.norm(desc, axis=1)
    # the nearest other descriptor is ~60% of a descriptor's length away; coding moves it ~15%
    assert np.median(err) < 0.2
    # the decoded descriptor is its own code: a second coding changes nothing
    assert np.array_equal(codebook.encode(decoded), codes)


@pytest.mark.parametrize("subspaces", [32, 16])
def test_decoding_puts_each_sub_vector_s_centroid_in_its_place(subspaces):
    rng = np.random.default_rng(0)
    centroids = rng.integers(0, 256, (subspaces, 256, 128 // subspaces), dtype=np.uint8)
    codes = rng.integers(0, 256, (300, subspaces), dtype=np.uint8)
    decoded = PQCodebook(centroids).decode(codes)
    width = 128 // subspaces
    for j in (0, subspaces // 2, subspaces - 1):
        assert np.array_equal(decoded[:, j * width:(j + 1) * width], centroids[j][codes[:, j]])
    assert PQCodebook(centroids).decode(codes[:0]).shape == (0, 128)


def test_seeded_rows_draw_across_keyframes_without_concatenating_everything():
    rng = np.random.default_rng(0)
    parts = [rng.integers(0, 255, (n, 128), dtype=np.uint8) for n in (5, 0, 7, 3)]
    assert np.array_equal(seeded_rows(parts), np.concatenate(parts))
    drawn = seeded_rows(parts, limit=6)
    everything = {row.tobytes() for row in np.concatenate(parts)}
    assert len(drawn) == 6 and all(row.tobytes() in everything for row in drawn)


def test_a_codebook_of_the_wrong_shape_is_refused_by_name():
    with pytest.raises(StorageError, match=r"expected \(M, 256, D/M\) uint8"):
        PQCodebook(np.zeros((32, 16, 4), np.uint8))


def test_a_compact_snapshot_stores_sift_codes_and_loads_them_decoded(
        tmp_path, fresh_map, small_training):
    save_map(fresh_map, tmp_path / "full", parts=EVERYTHING)
    save_map(fresh_map, tmp_path / "pq", parts=PQ)
    full, pq = _files(tmp_path / "full"), _files(tmp_path / "pq")
    assert "features/sift.descriptors.npy" not in pq
    assert "features/sift.keypoints_px8.npy" in pq and "features/sift.keypoints_px.npy" not in pq
    assert "features/sift.angles.npy" not in pq
    codes = pq["features/sift.descriptors_pq.npy"] + pq["features/sift.pq_codebook.npy"]
    assert codes < full["features/sift.descriptors.npy"] / 3
    manifest = json.loads((current_snapshot(tmp_path / "pq") / "manifest.json").read_text())
    assert manifest["format_version"] == UNSHARED_FORMAT_VERSION == 7
    state, _ = load_map(tmp_path / "pq")
    for k, kf in fresh_map.keyframes.items():
        a, b = kf.features["sift"], state.keyframes[k].features["sift"]
        assert b.descriptors.dtype == np.uint8 and b.descriptors.shape == a.descriptors.shape
        # keypoints in eighths of a pixel (rounded by at most 1/16 px), sizes float16
        assert np.abs(a.keypoints_px - b.keypoints_px).max() <= 1 / 16 + 1e-9
        assert np.allclose(a.sizes, b.sizes, rtol=1e-3)
        assert np.all(b.angles == -1)      # not stored: read by nothing once extracted
        assert np.array_equal(a.landmark_ids, b.landmark_ids)
    err = np.linalg.norm(_sift(state).astype(float) - _sift(fresh_map), axis=1)
    assert np.median(err / np.linalg.norm(_sift(fresh_map), axis=1)) < 0.2


def test_saving_a_loaded_map_again_never_codes_a_descriptor_twice(
        tmp_path, fresh_map, small_training):
    save_map(fresh_map, tmp_path / "a", parts=PQ)
    loaded, _ = load_map(tmp_path / "a")
    first = np.load(current_snapshot(tmp_path / "a") / "features" / "sift.descriptors_pq.npy")
    save_map(loaded, tmp_path / "b", parts=PQ)      # codes copied as stored
    for kf in loaded.keyframes.values():
        kf.features["sift"]                                     # built: decoded descriptors
    save_map(loaded, tmp_path / "c", parts=PQ)      # coded again, same codebook
    first_px = np.load(current_snapshot(tmp_path / "a") / "features" / "sift.keypoints_px8.npy")
    for name in ("b", "c"):
        snap = current_snapshot(tmp_path / name) / "features"
        assert np.array_equal(np.load(snap / "sift.descriptors_pq.npy"), first)
        assert np.array_equal(np.load(snap / "sift.keypoints_px8.npy"), first_px)
    # an in-memory map keeps its first codebook across saves (kept in the keyframes' caches)
    save_map(fresh_map, tmp_path / "d", parts=PQ)
    book_a = np.load(current_snapshot(tmp_path / "a") / "features" / "sift.pq_codebook.npy")
    book_d = np.load(current_snapshot(tmp_path / "d") / "features" / "sift.pq_codebook.npy")
    assert np.array_equal(book_a, book_d)


def test_pq16_codes_sift_in_16_bytes_and_a_saved_map_changes_codebook_with_the_codec(
        tmp_path, fresh_map, small_training):
    save_map(fresh_map, tmp_path / "pq", parts=PQ)
    loaded, _ = load_map(tmp_path / "pq")
    save_map(loaded, tmp_path / "pq16", parts=StoredParts(descriptor_codec="pq16"))
    snap = current_snapshot(tmp_path / "pq16") / "features"
    codes = np.load(snap / "sift.descriptors_pq.npy")
    assert codes.shape == (len(_sift(fresh_map)), 16) and codes.dtype == np.uint8
    assert np.load(snap / "sift.pq_codebook.npy").shape == (16, 256, 8)
    state, _ = load_map(tmp_path / "pq16")
    coarse, fine = _sift(state).astype(float), _sift(loaded).astype(float)
    truth = _sift(fresh_map).astype(float)
    norm = np.linalg.norm(truth, axis=1)
    # 8-value sub-vectors quantize coarser than 4-value ones, but stay below the ~60% distance
    # to the nearest other descriptor
    err16 = np.median(np.linalg.norm(coarse - truth, axis=1) / norm)
    err32 = np.median(np.linalg.norm(fine - truth, axis=1) / norm)
    assert err32 < err16 < 0.35
    # and back to "pq": a 32-sub-vector codebook is learnt again, not the 16 one reused
    save_map(state, tmp_path / "pq32", parts=PQ)
    snap = current_snapshot(tmp_path / "pq32") / "features"
    assert np.load(snap / "sift.descriptors_pq.npy").shape[1] == 32


def test_a_compact_snapshot_stores_small_blurry_images_as_float16(tmp_path, fresh_map):
    key = "sbi:40x30:2.5"
    for kf in fresh_map.keyframes.values():
        kf.small_blurry_image()
    save_map(fresh_map, tmp_path / "full", parts=EVERYTHING)
    save_map(fresh_map, tmp_path / "pq", parts=PQ)
    name = "thumbnails/sbi_40x30_2.5.npy"
    assert _files(tmp_path / "pq")[name] < _files(tmp_path / "full")[name] * 0.55
    state, _ = load_map(tmp_path / "pq")
    for k, kf in fresh_map.keyframes.items():
        thumb = state.keyframes[k].cache[key]
        assert thumb.dtype == np.float32
        assert np.abs(thumb - kf.cache[key]).max() <= 0.0625


def test_a_replica_save_of_a_coded_map_stores_the_decoded_descriptors_in_full(
        tmp_path, fresh_map, small_training):
    save_map(fresh_map, tmp_path / "pq", parts=PQ)
    loaded, _ = load_map(tmp_path / "pq")
    save_map(loaded, tmp_path / "full", parts=EVERYTHING)
    assert "features/sift.descriptors_pq.npy" not in _files(tmp_path / "full")
    again, _ = load_map(tmp_path / "full")
    assert np.array_equal(_sift(again), _sift(loaded))


def test_too_few_descriptors_are_stored_in_full(tmp_path, fresh_map):
    save_map(fresh_map, tmp_path, parts=PQ)
    files = _files(tmp_path)
    assert "features/sift.descriptors.npy" in files
    state, _ = load_map(tmp_path)
    assert np.array_equal(_sift(state), _sift(fresh_map))


def test_a_format_5_snapshot_loads_and_saves_as_format_6(tmp_path, small_training):
    """tests/data/map_v5 was written by the format-5 code (map_v4 loaded and saved with
    ``StoredParts(depth="lossless")``): full SIFT descriptors, lossless depth."""
    manifest = json.loads((V5_MAP / "snapshots" / "000001" / "manifest.json").read_text())
    assert manifest["format_version"] == 5
    v5, _ = load_map(V5_MAP)
    v4, _ = load_map(V4_MAP)
    assert np.array_equal(_sift(v5), _sift(v4))
    assert np.array_equal(v5.keyframes[0].depth, v4.keyframes[0].depth, equal_nan=True)
    save_map(v5, tmp_path, parts=PQ)
    again, _ = load_map(tmp_path)
    assert _sift(again).shape == _sift(v4).shape


def test_the_codec_is_a_service_option_checked_by_name():
    assert ServiceConf().service.stored_parts().descriptor_codec == "none"
    assert ServiceSection(descriptor_codec="pq").stored_parts().descriptor_codec == "pq"
    with pytest.raises(ConfigError, match=r"service\.descriptor_codec: expected one of none, pq, pq16"):
        ServiceSection(descriptor_codec="zip")
