"""Snapshots that keep each keyframe's keypoints with a landmark only: the rows and the
renumbered observations, the mark a loaded keyframe carries, and the methods that need every
keypoint refusing by the option's name (never working on part of them unawares)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from reloc_service.core.errors import MapError
from reloc_service.core.frame import Frame
from reloc_service.core.landmark_rows import EVERY_ROW_OPTION, holds_landmark_rows_only
from reloc_service.core.map import MapState
from reloc_service.engine import Engine, EngineConf
from reloc_service.storage.keyframe_parts import StoredParts
from reloc_service.storage.snapshot import load_map, save_map
from reloc_service.storage.snapshot_files import current_snapshot

LANDMARKS = StoredParts(descriptors="landmarks")


def _entries(directory: Path) -> list[dict]:
    manifest = json.loads((current_snapshot(directory) / "manifest.json").read_text())
    return manifest["keyframes"]


def _observed_rows_agree(state: MapState) -> None:
    """Every observation (keyframe, kind, keypoint) names a keypoint holding its landmark."""
    for lm_id, lm in state.landmarks.items():
        for kf_id, kind, kp in lm.observations:
            assert state.keyframes[kf_id].features[kind].landmark_ids[kp] == lm_id


def test_a_snapshot_keeps_the_landmark_keypoints_with_their_observations(
        tmp_path, synthetic_map):
    save_map(synthetic_map, tmp_path, parts=LANDMARKS)
    state, _ = load_map(tmp_path)
    dropped = 0
    for k, kf in synthetic_map.keyframes.items():
        full, kept = kf.features["sift"], state.keyframes[k].features["sift"]
        rows = np.flatnonzero(full.landmark_ids >= 0)
        dropped += len(full) - len(rows)
        for field in ("keypoints_px", "levels", "sizes", "descriptors", "landmark_ids"):
            assert np.array_equal(getattr(kept, field), getattr(full, field)[rows]), field
        assert np.allclose(kept.points_world, full.points_world[rows], atol=1e-6)  # float32 offsets
        assert holds_landmark_rows_only(state.keyframes[k])
        assert not holds_landmark_rows_only(kf)   # the map held in memory keeps every row
    assert dropped > 0
    assert all(e["landmark_rows_only"] for e in _entries(tmp_path))
    _observed_rows_agree(state)
    assert sorted(state.landmarks) == sorted(synthetic_map.landmarks)


def test_a_keyframe_stored_so_stays_marked_when_saved_with_every_row(tmp_path, synthetic_map):
    save_map(synthetic_map, tmp_path / "a", parts=LANDMARKS)
    state, _ = load_map(tmp_path / "a")
    save_map(state, tmp_path / "b")                 # "all": nothing more to drop, still marked
    assert all(e["landmark_rows_only"] for e in _entries(tmp_path / "b"))
    again, _ = load_map(tmp_path / "b")
    _observed_rows_agree(again)
    save_map(synthetic_map, tmp_path / "c")
    assert not any(e.get("landmark_rows_only") for e in _entries(tmp_path / "c"))


def test_an_engine_drops_rows_only_once_its_methods_are_trained(
        tmp_path, synthetic_map, synthetic_scene):
    save_map(synthetic_map, tmp_path / "src")
    engine = Engine.load(tmp_path / "src", EngineConf(methods=("bow+p3p",)), train=False)
    engine.save(tmp_path / "untrained", parts=LANDMARKS)   # a load would train bow: all rows
    assert not any(e.get("landmark_rows_only") for e in _entries(tmp_path / "untrained"))
    engine.train()
    engine.save(tmp_path / "trained", parts=LANDMARKS)
    assert all(e["landmark_rows_only"] for e in _entries(tmp_path / "trained"))
    restored = Engine.load(tmp_path / "trained", EngineConf(methods=("bow+p3p",)))
    query = Frame(image=synthetic_scene.query_images[1], camera=synthetic_scene.camera)
    assert restored.relocalize(query).ok               # the saved vocabulary and bags serve
    with pytest.raises(MapError, match=re.escape(EVERY_ROW_OPTION)):
        restored.train()                                # a vocabulary of part of the keypoints


def test_methods_needing_every_keypoint_refuse_a_map_stored_without_them(
        tmp_path, synthetic_map):
    save_map(synthetic_map, tmp_path, parts=LANDMARKS)
    for method in ("bow+p3p", "sbi+5pt"):
        with pytest.raises(MapError, match=re.escape(EVERY_ROW_OPTION)):
            Engine.load(tmp_path, EngineConf(methods=(method,)))


def test_an_engine_serving_5pt_keeps_every_row(tmp_path, synthetic_map):
    save_map(synthetic_map, tmp_path / "src")
    engine = Engine.load(tmp_path / "src", EngineConf(methods=("sbi+5pt",)))
    engine.save(tmp_path / "out", parts=LANDMARKS)
    assert not any(e.get("landmark_rows_only") for e in _entries(tmp_path / "out"))


def test_a_keyframe_without_landmarks_keeps_every_keypoint(tmp_path, synthetic_scene):
    from reloc_service.core.map import KeyframeMap
    from reloc_service.core.mapping import MapBuilder

    kmap = KeyframeMap()
    MapBuilder(kmap).add_keyframe(0, synthetic_scene.keyframe_images[0], synthetic_scene.camera,
                                  synthetic_scene.keyframe_poses[0])
    lone = kmap.snapshot()          # one keyframe: nothing triangulated yet
    assert not np.any(lone.keyframes[0].features["sift"].landmark_ids >= 0)
    save_map(lone, tmp_path, parts=LANDMARKS)
    state, _ = load_map(tmp_path)
    assert len(state.keyframes[0].features["sift"]) == len(lone.keyframes[0].features["sift"])
    assert not holds_landmark_rows_only(state.keyframes[0])
