"""PQ codes with exact rows (``descriptor_codec = "pq-hybrid"``, format 11): the threshold
from the map's two-view descriptor noise, the rows kept in full, saves that keep the same
rows, damaged columns refused by name, and the other codecs' formats unchanged."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from reloc_service.core.errors import ConfigError, StorageError
from reloc_service.core.map import MapState
from reloc_service.service.config import ServiceSection
from reloc_service.storage import descriptor_pq
from reloc_service.storage.descriptor_hybrid import (
    EXACT,
    EXACT_ROWS,
    EXACT_SHARE,
    EXACT_THRESHOLD,
    exact_threshold,
    split_exact,
    squared_errors,
    with_exact,
)
from reloc_service.storage.descriptor_pq import PQCodebook
from reloc_service.storage.keyframe_parts import StoredParts
from reloc_service.storage.snapshot import load_map, save_map
from reloc_service.storage.snapshot_files import current_snapshot
from reloc_service.storage.snapshot_format import EXACT_ROWS_FORMAT_VERSION

HYBRID = StoredParts(descriptor_codec="pq-hybrid")


@pytest.fixture
def small_training(monkeypatch):
    """Let a codebook be learnt from the synthetic map's 3,127 SIFT descriptors."""
    monkeypatch.setattr(descriptor_pq, "MIN_TRAIN_SAMPLES", 1024)


@pytest.fixture
def fresh_map(synthetic_map) -> MapState:
    """The synthetic map with caches of its own (a save keeps its codebook there)."""
    keyframes = {k: dataclasses.replace(kf, cache={}) for k, kf in synthetic_map.keyframes.items()}
    return dataclasses.replace(synthetic_map, keyframes=keyframes)


def _manifest(directory: Path) -> dict:
    return json.loads((current_snapshot(directory) / "manifest.json").read_text())


def _sift_rows(state: MapState) -> tuple[np.ndarray, np.ndarray]:
    """Every keyframe's SIFT descriptors and landmark ids, in keyframe order."""
    feats = [kf.features["sift"] for kf in state.keyframes.values()]
    return (np.concatenate([np.asarray(f.descriptors) for f in feats]),
            np.concatenate([np.asarray(f.landmark_ids) for f in feats]))


def test_the_threshold_is_a_share_of_the_median_distance_of_later_rows_to_their_first():
    rng = np.random.default_rng(0)
    desc = [rng.integers(0, 200, (4, 128), dtype=np.uint8),
            rng.integers(0, 200, (3, 128), dtype=np.uint8)]
    ids = [np.array([7, 3, -1, 5]), np.array([3, 7, 9])]
    # landmark 7: rows 0 (first) and 5; landmark 3: rows 1 (first) and 4; 5 and 9 seen once
    flat = np.concatenate(desc).astype(float)
    later = [((flat[5] - flat[0]) ** 2).sum(), ((flat[4] - flat[1]) ** 2).sum()]
    assert exact_threshold(desc, ids) == pytest.approx(EXACT_SHARE * np.median(later))
    assert exact_threshold(desc[:1], ids[:1]) is None          # no landmark seen twice
    assert exact_threshold([desc[0][:0]], [ids[0][:0]]) is None


def test_rows_beyond_the_threshold_are_kept_exact_and_read_back_in_full():
    rng = np.random.default_rng(1)
    centroids = rng.integers(0, 256, (32, 256, 4), dtype=np.uint8)
    desc = rng.integers(0, 256, (200, 128), dtype=np.uint8)
    codebook = PQCodebook(centroids)
    codes = codebook.encode(desc)
    err = squared_errors(desc, codes, codebook)
    limit = float(np.median(err))
    cols = split_exact(desc, codes, PQCodebook(centroids, exact_above=limit))
    mask = cols[EXACT_ROWS] != 0
    assert np.array_equal(mask, err > limit) and 0 < mask.sum() < len(desc)
    read = with_exact(codebook.decode(codes), mask, cols[EXACT])
    assert np.array_equal(read[mask], desc[mask])
    assert np.all(squared_errors(desc, codebook.encode(desc), codebook)[~mask] <= limit)
    assert np.all(((read.astype(float) - desc) ** 2).sum(1) <= limit)
    with pytest.raises(Exception, match="without an exact threshold"):
        split_exact(desc, codes, codebook)


def test_a_hybrid_snapshot_reads_every_row_within_the_threshold_and_the_far_ones_exactly(
        tmp_path, fresh_map, small_training):
    save_map(fresh_map, tmp_path / "h", parts=HYBRID)
    manifest = _manifest(tmp_path / "h")
    assert manifest["format_version"] == EXACT_ROWS_FORMAT_VERSION == 11
    files = manifest["files"]
    assert f"features/sift.{EXACT_THRESHOLD}.npy" in files
    assert "features/sift.descriptors.npy" not in files
    snap = current_snapshot(tmp_path / "h") / "features"
    threshold = float(np.load(snap / f"sift.{EXACT_THRESHOLD}.npy")[0])
    assert threshold == pytest.approx(exact_threshold(*map(list, zip(*[
        (kf.features["sift"].descriptors, kf.features["sift"].landmark_ids)
        for kf in fresh_map.keyframes.values()], strict=True))))
    state, _ = load_map(tmp_path / "h")
    held, ids = _sift_rows(fresh_map)
    read, read_ids = _sift_rows(state)
    assert np.array_equal(ids, read_ids)
    err = ((read.astype(float) - held) ** 2).sum(1)
    assert np.all(err <= threshold)
    exact = np.load(snap / f"sift.{EXACT}.npy")
    assert 0 < len(exact) < len(held)         # some rows exact, most coded
    assert np.count_nonzero(err == 0) >= len(exact)


@pytest.mark.parametrize("descriptors", ["all", "per-landmark", "per-landmark-medoid"])
def test_a_loaded_hybrid_map_saved_again_stores_the_same_bytes(
        tmp_path, fresh_map, small_training, descriptors):
    parts = dataclasses.replace(HYBRID, descriptors=descriptors)
    save_map(fresh_map, tmp_path / "a", parts=parts)
    loaded, _ = load_map(tmp_path / "a")
    save_map(loaded, tmp_path / "b", parts=parts)          # stored rows copied
    for kf in loaded.keyframes.values():
        kf.features["sift"]                                  # built: decoded, exact rows in
    save_map(loaded, tmp_path / "c", parts=parts)
    first = _manifest(tmp_path / "a")["files"]
    assert any(EXACT_ROWS in f for f in first)
    for name in ("b", "c"):
        again = _manifest(tmp_path / name)["files"]
        assert {f: e["sha256"] for f, e in again.items() if f.startswith("features/")} == {
            f: e["sha256"] for f, e in first.items() if f.startswith("features/")}


def test_a_hybrid_map_saved_as_pq_or_in_full_keeps_its_exact_rows(
        tmp_path, fresh_map, small_training):
    save_map(fresh_map, tmp_path / "h", parts=HYBRID)
    loaded, _ = load_map(tmp_path / "h")
    save_map(loaded, tmp_path / "full", parts=StoredParts())
    save_map(loaded, tmp_path / "pq", parts=StoredParts(descriptor_codec="pq"))
    assert _manifest(tmp_path / "pq")["format_version"] == 7
    full, _ = load_map(tmp_path / "full")
    assert np.array_equal(_sift_rows(full)[0], _sift_rows(load_map(tmp_path / "h")[0])[0])


def _rewrite(snapshot: Path, relpath: str, array: np.ndarray) -> None:
    """Replace a file of ``snapshot`` with ``array`` and update the manifest's checksum."""
    import hashlib
    import io
    buf = io.BytesIO()
    np.save(buf, array)
    (snapshot / relpath).write_bytes(buf.getvalue())
    manifest = json.loads((snapshot / "manifest.json").read_text())
    manifest["files"][relpath] = {"sha256": hashlib.sha256(buf.getvalue()).hexdigest(),
                                  "size": len(buf.getvalue())}
    (snapshot / "manifest.json").write_text(json.dumps(manifest))


def test_exact_rows_not_matching_their_mask_are_refused_by_name(
        tmp_path, fresh_map, small_training):
    save_map(fresh_map, tmp_path / "h", parts=HYBRID)
    snap = current_snapshot(tmp_path / "h")
    exact = np.load(snap / "features" / f"sift.{EXACT}.npy")
    _rewrite(snap, f"features/sift.{EXACT}.npy", exact[:-1])
    with pytest.raises(StorageError, match=r"exact descriptors \(one per masked row\)"):
        load_map(tmp_path / "h")


def test_exact_rows_without_their_threshold_are_refused_by_name(
        tmp_path, fresh_map, small_training):
    save_map(fresh_map, tmp_path / "h", parts=HYBRID)
    snap = current_snapshot(tmp_path / "h")
    manifest = json.loads((snap / "manifest.json").read_text())
    del manifest["files"][f"features/sift.{EXACT_THRESHOLD}.npy"]
    (snap / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(StorageError, match="saved without their threshold"):
        load_map(tmp_path / "h")


def test_the_hybrid_codec_is_a_service_option_checked_by_name():
    assert ServiceSection(descriptor_codec="pq-hybrid").stored_parts().descriptor_codec == \
        "pq-hybrid"
    with pytest.raises(ConfigError, match="descriptor_codec: expected one of"):
        ServiceSection(descriptor_codec="pq-exact")
