"""One stored descriptor per landmark (``keyframe_descriptors = "per-landmark"``): the rows of a
landmark read its first row's descriptor, the map loads and saves again unchanged, a shared
column of the wrong length is refused by name, and format-7 snapshots still load."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from reloc_service.core.errors import StorageError
from reloc_service.core.map import MapState
from reloc_service.storage.keyframe_parts import EVERYTHING, StoredParts
from reloc_service.storage.landmark_descriptors import (
    SHARED_DESCRIPTORS,
    first_rows,
    shared_index,
)
from reloc_service.storage.snapshot import FORMAT_VERSION, load_map, save_map
from reloc_service.storage.snapshot_files import current_snapshot

DATA = Path(__file__).parent / "data"
#: written by the format-7 code: map_v6 loaded and saved with lossless depth and every image
V7_MAP = DATA / "map_v7"
V6_MAP = DATA / "map_v6"
PER_LANDMARK = StoredParts(descriptors="per-landmark")


def test_shared_index_gives_each_row_its_landmarks_first_row():
    ids = np.array([5, -1, 3, 5, 3, -1, 7, 5])
    assert first_rows(ids).tolist() == [True, True, True, False, False, True, True, False]
    # stored rows: 5, -1, 3, -1, 7 -> ranks 0..4
    assert shared_index(ids).tolist() == [0, 1, 2, 0, 2, 3, 4, 0]
    assert shared_index(np.zeros(0, np.int64)).tolist() == []
    assert shared_index(np.full(3, -1)).tolist() == [0, 1, 2]


def test_shared_index_agrees_with_a_sort_on_random_ids():
    ids = np.random.default_rng(0).integers(-1, 500, 5000)
    has = np.flatnonzero(ids >= 0)
    _, at, inverse = np.unique(ids[has], return_index=True, return_inverse=True)
    first = ids < 0
    first[has[at]] = True
    rank = np.cumsum(first) - 1
    expected = rank.copy()
    expected[has] = rank[has[at]][inverse]
    assert np.array_equal(first_rows(ids), first)
    assert np.array_equal(shared_index(ids), expected)


def _rows_in_snapshot_order(state: MapState, kind: str):
    """(keyframe id, Features) of ``kind`` in the order a snapshot concatenates them."""
    return [(k, kf.features[kind]) for k, kf in state.keyframes.items() if kind in kf.features]


def test_per_landmark_descriptors_round_trip(tmp_path, synthetic_map):
    save_map(synthetic_map, tmp_path / "full", parts=StoredParts(descriptors="landmarks"))
    snap = save_map(synthetic_map, tmp_path / "shared", parts=PER_LANDMARK)
    manifest = json.loads((snap / "manifest.json").read_text())
    assert manifest["format_version"] == FORMAT_VERSION == 8
    assert f"features/sift.{SHARED_DESCRIPTORS}.npy" in manifest["files"]
    assert "features/sift.descriptors.npy" not in manifest["files"]
    loaded, _ = load_map(tmp_path / "shared")
    first: dict[int, np.ndarray] = {}   # landmark id -> descriptor of its first row
    observed = 0
    for k, feats in _rows_in_snapshot_order(synthetic_map, "sift"):
        got = loaded.keyframes[k].features["sift"]
        has = feats.landmark_ids >= 0
        assert np.array_equal(got.landmark_ids, feats.landmark_ids[has])
        assert np.array_equal(got.keypoints_px, feats.keypoints_px[has])
        for lm, desc, mine in zip(feats.landmark_ids[has], got.descriptors,
                                  feats.descriptors[has], strict=True):
            expected = first.setdefault(int(lm), mine)
            assert np.array_equal(desc, expected)
            observed += 1
    assert observed > len(first)   # some landmark was seen twice: its descriptor shared
    full = current_snapshot(tmp_path / "full") / "features" / "sift.descriptors.npy"
    shared = snap / "features" / f"sift.{SHARED_DESCRIPTORS}.npy"
    assert shared.stat().st_size < full.stat().st_size * len(first) / observed + 1024
    # saved again (rows copied as stored, then as built): the same shared column
    again = save_map(loaded, tmp_path / "again", parts=PER_LANDMARK)
    assert (again / shared.relative_to(snap)).read_bytes() == shared.read_bytes()
    for kf in loaded.keyframes.values():
        kf.features["sift"]   # noqa: B018 (built now)
    thrice = save_map(loaded, tmp_path / "thrice", parts=PER_LANDMARK)
    assert (thrice / shared.relative_to(snap)).read_bytes() == shared.read_bytes()


def _rewrite(snapshot: Path, relpath: str, data: bytes) -> None:
    """Replace a snapshot file and its manifest entry (size and checksum agree again)."""
    (snapshot / relpath).write_bytes(data)
    manifest_path = snapshot / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["files"][relpath] = {"size": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    manifest_path.write_text(json.dumps(manifest))


def test_a_shared_column_of_the_wrong_length_is_refused_by_name(tmp_path, synthetic_map):
    snap = save_map(synthetic_map, tmp_path, parts=PER_LANDMARK)
    rel = f"features/sift.{SHARED_DESCRIPTORS}.npy"
    column = np.load(snap / rel)
    import io
    buf = io.BytesIO()
    np.save(buf, column[:-1])
    _rewrite(snap, rel, buf.getvalue())
    with pytest.raises(StorageError, match=rf"sift\.{SHARED_DESCRIPTORS}: {len(column) - 1} "
                                           rf"rows, expected {len(column)}"):
        load_map(tmp_path)


def test_a_damaged_shared_column_is_refused_by_name(tmp_path, synthetic_map):
    snap = save_map(synthetic_map, tmp_path, parts=PER_LANDMARK)
    path = snap / "features" / f"sift.{SHARED_DESCRIPTORS}.npy"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x10
    path.write_bytes(bytes(data))
    with pytest.raises(StorageError, match=rf"sift\.{SHARED_DESCRIPTORS}\.npy: checksum"):
        load_map(tmp_path)


def test_a_format_7_snapshot_loads_the_same_and_saves_as_format_8(tmp_path):
    manifest = json.loads((V7_MAP / "snapshots" / "000001" / "manifest.json").read_text())
    assert manifest["format_version"] == 7
    v7, _ = load_map(V7_MAP)
    v6, _ = load_map(V6_MAP)
    assert v7.keyframe_ids() == v6.keyframe_ids()
    for k in v6.keyframe_ids():
        for kind, feats in v6.keyframes[k].features.items():
            got = v7.keyframes[k].features[kind]
            assert np.array_equal(got.descriptors, feats.descriptors)
            assert np.array_equal(got.keypoints_px, feats.keypoints_px)
            assert np.array_equal(got.landmark_ids, feats.landmark_ids)
    assert sorted(v7.landmarks) == sorted(v6.landmarks)
    save_map(v7, tmp_path / "full", parts=EVERYTHING)
    save_map(v7, tmp_path / "shared", parts=PER_LANDMARK)
    for name in ("full", "shared"):
        snap = current_snapshot(tmp_path / name)
        # only a snapshot that shares descriptors needs format 8's reader
        assert json.loads((snap / "manifest.json").read_text())["format_version"] == (
            8 if name == "shared" else 7)
        again, _ = load_map(tmp_path / name)
        assert sorted(again.landmarks) == sorted(v7.landmarks)
