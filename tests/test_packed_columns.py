"""Low-entropy snapshot columns and place-finder models stored zlib-compressed (format 7):
exact round trips, older snapshots still read, damaged files refused by name."""

from __future__ import annotations

import hashlib
import io
import json
import zlib
from pathlib import Path

import msgpack
import numpy as np
import pytest
from stored_maps import V5_MAP, V6_MAP

from reloc_service.algorithms.relocalizers.factory import create_relocalizer
from reloc_service.algorithms.relocalizers.multi import PACKED_MODEL
from reloc_service.core.errors import StorageError
from reloc_service.core.map import KeyframeMap, MapState
from reloc_service.storage.keyframe_parts import EVERYTHING
from reloc_service.storage.packed_columns import (
    DELTA_PACKED,
    PACKED,
    RAW,
    deltas,
    packed_file,
    undelta,
    unpack,
)
from reloc_service.storage.snapshot import UNSHARED_FORMAT_VERSION, load_map, save_map
from reloc_service.storage.snapshot_files import current_snapshot


def _unpacked(path: str, data: bytes) -> np.ndarray:
    if path.endswith(RAW) and not path.endswith(PACKED):
        return np.load(io.BytesIO(data))
    return unpack(data, path, delta=path.endswith(DELTA_PACKED))


@pytest.mark.parametrize("column, suffix", [
    (np.arange(5, 10_005, dtype=np.int32), DELTA_PACKED),                 # landmark ids
    (np.repeat(np.arange(50, dtype=np.int8), 300), DELTA_PACKED),         # pyramid levels
    (np.tile(np.arange(4, dtype=np.int16), (2000, 1)), PACKED),           # 2-D: no differences
    (np.zeros(4000, np.float32), PACKED),                                 # exact-depth sigmas
    (np.random.default_rng(0).integers(0, 256, (3000, 32), dtype=np.uint8), RAW),  # ORB
])
def test_a_column_is_packed_only_when_that_saves_three_quarters(column, suffix):
    path, data = packed_file("landmarks/x", column)
    assert path == "landmarks/x" + suffix
    back = _unpacked(path, data)
    assert back.dtype == column.dtype and np.array_equal(back, column)


def test_differences_wrap_in_the_columns_dtype_and_sum_back_exactly():
    column = np.array([30000, -30000, 32767, -32768, 0, 5], np.int16)
    diffs = deltas(column)
    assert diffs.dtype == np.int16
    assert np.array_equal(undelta(diffs), column)


def _features(state: MapState) -> dict[tuple[int, str, str], np.ndarray]:
    return {(kf.id, kind, field): np.asarray(getattr(feats, field))
            for kf in state.keyframes.values() for kind, feats in kf.features.items()
            for field in ("keypoints_px", "levels", "sizes", "descriptors", "landmark_ids")}


def _assert_same_map(a: MapState, b: MapState) -> None:
    assert sorted(a.keyframes) == sorted(b.keyframes)
    fa, fb = _features(a), _features(b)
    assert fa.keys() == fb.keys()
    for key, value in fa.items():
        assert value.dtype == fb[key].dtype and np.array_equal(value, fb[key]), key
    assert sorted(a.landmarks) == sorted(b.landmarks)
    for lid in a.landmarks:
        la, lb = a.landmarks[lid], b.landmarks[lid]
        assert np.array_equal(la.point_world, lb.point_world)
        assert la.observations == lb.observations and la.depth_sigma_m == lb.depth_sigma_m


def test_a_saved_map_packs_its_repetitive_columns_and_loads_the_same(tmp_path, synthetic_map):
    # exact geometry: float64 points, so every loaded value can be compared for equality
    save_map(synthetic_map, tmp_path, parts=EVERYTHING, exact_geometry=True)
    manifest = json.loads((current_snapshot(tmp_path) / "manifest.json").read_text())
    assert manifest["format_version"] == UNSHARED_FORMAT_VERSION == 7
    files = manifest["files"]
    assert "landmarks/ids" + DELTA_PACKED in files and "landmarks/ids.npy" not in files
    assert "landmarks/obs_offsets" + DELTA_PACKED in files
    assert "landmarks/obs_kind" + PACKED in files or "landmarks/obs_kind" + DELTA_PACKED in files
    assert manifest["landmarks"]["count"] == len(synthetic_map.landmarks)
    loaded, _ = load_map(tmp_path)
    _assert_same_map(synthetic_map, loaded)


def test_a_format_6_snapshot_loads_the_same_and_saves_as_format_7(tmp_path):
    manifest = json.loads((V6_MAP / "snapshots" / "000001" / "manifest.json").read_text())
    assert manifest["format_version"] == 6
    assert not [f for f in manifest["files"] if f.endswith(".zlib") and "depth" not in f]
    v6, _ = load_map(V6_MAP)
    v5, _ = load_map(V5_MAP)
    _assert_same_map(v5, v6)
    save_map(v6, tmp_path, parts=EVERYTHING)
    again, _ = load_map(tmp_path)
    _assert_same_map(v6, again)
    assert np.array_equal(again.keyframes[0].depth, v6.keyframes[0].depth, equal_nan=True)


def _rewrite(snapshot: Path, relpath: str, data: bytes) -> None:
    """Replace a snapshot file and its manifest entry (size and checksum agree again)."""
    (snapshot / relpath).write_bytes(data)
    manifest_path = snapshot / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["files"][relpath] = {"size": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    manifest_path.write_text(json.dumps(manifest))


def test_a_packed_column_that_is_not_zlib_of_a_npy_is_refused_by_name(tmp_path, synthetic_map):
    save_map(synthetic_map, tmp_path, parts=EVERYTHING)
    snapshot = current_snapshot(tmp_path)
    _rewrite(snapshot, "landmarks/ids" + DELTA_PACKED, zlib.compress(b"not an array"))
    with pytest.raises(StorageError, match=r"ids\.delta\.npy\.zlib: expected the zlib of a"):
        load_map(tmp_path)
    with pytest.raises(StorageError, match="expected 1-D integer differences"):
        unpack(zlib.compress(_npy(np.zeros((2, 2), np.int32))), "x", delta=True)


def _npy(array: np.ndarray) -> bytes:
    from reloc_service.storage.packed_columns import npy_bytes

    return npy_bytes(array)


def _trained_bow(synthetic_map: MapState):
    kmap = KeyframeMap()
    kmap.replace_state(synthetic_map)
    reloc = create_relocalizer("bow+p3p", kmap, options={"bow": {"branching": 6, "depth": 3}})
    reloc.train()
    return kmap, reloc


def test_the_bow_model_is_saved_compressed_and_an_old_plain_one_still_loads(
        tmp_path, synthetic_map):
    kmap, reloc = _trained_bow(synthetic_map)
    reloc.save(tmp_path)
    packed = tmp_path / f"place_bow{PACKED_MODEL}"
    assert packed.is_file() and not (tmp_path / "place_bow.msgpack").exists()
    plain = msgpack.packb(reloc.place.state(), use_bin_type=True)
    assert packed.stat().st_size < len(plain)
    for directory in (tmp_path, _plain_model_dir(tmp_path / "old", plain)):
        other = create_relocalizer("bow+p3p", kmap, options={"bow": {"branching": 6, "depth": 3}})
        assert other.load(directory)
        assert msgpack.packb(other.place.state(), use_bin_type=True) == plain
    packed.write_bytes(b"damaged")
    with pytest.raises(StorageError, match=r"place_bow\.msgpack\.zlib: expected the zlib"):
        create_relocalizer("bow+p3p", kmap).load(tmp_path)


def _plain_model_dir(directory: Path, plain: bytes) -> Path:
    """A model directory as the code before format 7 wrote it: the msgpack state as is."""
    directory.mkdir()
    (directory / "place_bow.msgpack").write_bytes(plain)
    return directory
