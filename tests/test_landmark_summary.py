"""Summary maps (``landmark_budget``): the rank of a keyframe's rows (views first, spread over
the coverage grid), the landmarks kept (those some keyframe ranks within its budget, with
every observation), the snapshot on disk and loaded back, older formats, and the option
refused by name when it is not a budget."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from stored_maps import stored_map

from reloc_service.algorithms.relocalizers.base import VerifyConf
from reloc_service.core.errors import ConfigError
from reloc_service.core.map import MapState
from reloc_service.service.config import ServiceSection
from reloc_service.storage.keyframe_parts import StoredParts
from reloc_service.storage.landmark_summary import (
    COVERAGE_GRID,
    kept_landmarks,
    landmark_views,
    row_ranks,
)
from reloc_service.storage.snapshot import load_map, save_map
from reloc_service.storage.snapshot_files import current_snapshot


def _manifest(directory: Path) -> dict:
    return json.loads((current_snapshot(directory) / "manifest.json").read_text())


def _budget(state: MapState) -> int:
    """A budget below most keyframes' landmark rows: half the median count."""
    counts = [int((kf.features["sift"].landmark_ids >= 0).sum()) for kf in state.keyframes.values()]
    return max(1, int(np.median(counts)) // 2)


def _reference_kept(state: MapState, budget: int) -> set[int]:
    """The landmarks some keyframe ranks within ``budget``, one keyframe at a time."""
    columns = state.landmarks.columns()
    views = dict(zip(columns.ids.tolist(), landmark_views(columns).tolist(), strict=True))
    kept: set[int] = set()
    for kf in state.keyframes.values():
        feats = kf.features["sift"]
        rows = np.flatnonzero(feats.landmark_ids >= 0)
        ids = feats.landmark_ids[rows]
        ranks = row_ranks(feats.keypoints_px[rows], np.array([views[i] for i in ids]),
                          (kf.camera.width, kf.camera.height))
        kept |= set(ids[ranks < budget].tolist())
    return kept


def test_the_grid_is_the_verifications_coverage_grid():
    assert COVERAGE_GRID == VerifyConf().coverage_grid


def test_rows_rank_by_views_within_a_cell_then_cells_interleave():
    # a 2x2 grid over a 100x100 image: cells 0 (top left) and 3 (bottom right)
    px = np.array([[10, 10], [20, 20], [30, 30], [80, 80], [90, 90]], float)
    views = np.array([2, 5, 2, 3, 9])
    ranks = row_ranks(px, views, (100, 100), grid=2)
    # cell 0 by views: row 1 (5), row 0 (2), row 2 (2, later); cell 3: row 4 (9), row 3 (3).
    # the best of each cell first (row 4 with 9 views before row 1 with 5), then the seconds
    # (row 3, 3 views, before row 0, 2), then row 2
    assert ranks.tolist() == [3, 1, 4, 2, 0]
    assert row_ranks(px[:0], views[:0], (100, 100)).size == 0


def test_views_count_distinct_keyframes(synthetic_map):
    columns = synthetic_map.landmarks.columns()
    views = landmark_views(columns)
    for row in (0, len(columns.ids) // 2, len(columns.ids) - 1):
        lm = columns.landmark(row)
        assert views[row] == len({kf for kf, _, _ in lm.observations})


def test_the_landmarks_kept_are_those_some_keyframe_ranks_within_its_budget(synthetic_map):
    budget = _budget(synthetic_map)
    columns = synthetic_map.landmarks.columns()
    keep = kept_landmarks(list(synthetic_map.keyframes.values()), columns, budget)
    assert set(columns.ids[keep].tolist()) == _reference_kept(synthetic_map, budget)
    assert 0 < keep.sum() < len(keep)
    assert kept_landmarks(list(synthetic_map.keyframes.values()), columns, 0).all()


def test_a_summary_map_round_trips_on_disk(tmp_path, synthetic_map):
    budget = _budget(synthetic_map)
    save_map(synthetic_map, tmp_path, parts=StoredParts(descriptors="landmarks",
                                                        landmark_budget=budget))
    state, _ = load_map(tmp_path)
    kept = _reference_kept(synthetic_map, budget)
    assert set(state.landmarks) == kept
    for lm_id in kept:   # every view of a kept landmark, its point within float32 offsets
        held, loaded = synthetic_map.landmarks[lm_id], state.landmarks[lm_id]
        assert {(k, kind) for k, kind, _ in loaded.observations} == \
            {(k, kind) for k, kind, _ in held.observations}
        assert np.allclose(loaded.point_world, held.point_world, atol=1e-5)
    for k, kf in synthetic_map.keyframes.items():
        full, stored = kf.features["sift"], state.keyframes[k].features["sift"]
        rows = np.flatnonzero(np.isin(full.landmark_ids, list(kept)))
        assert np.array_equal(stored.landmark_ids, full.landmark_ids[rows])
        assert np.array_equal(stored.descriptors, full.descriptors[rows])
        assert np.array_equal(stored.keypoints_px, full.keypoints_px[rows])
        mapped = int((full.landmark_ids >= 0).sum())
        assert len(rows) >= min(budget, mapped)   # its own best rows, at least
    for lm_id, lm in state.landmarks.items():
        for kf_id, kind, kp in lm.observations:
            assert state.keyframes[kf_id].features[kind].landmark_ids[kp] == lm_id
    assert _manifest(tmp_path)["format_version"] == 7   # any format-7 reader loads it


def test_a_summary_map_saved_again_keeps_its_landmarks(tmp_path, synthetic_map):
    parts = StoredParts(descriptors="landmarks", landmark_budget=_budget(synthetic_map))
    save_map(synthetic_map, tmp_path / "a", parts=parts)
    first, _ = load_map(tmp_path / "a")
    save_map(first, tmp_path / "b", parts=parts)
    second, _ = load_map(tmp_path / "b")
    assert set(second.landmarks) == set(first.landmarks)


@pytest.mark.parametrize("version", [7, 8])
def test_older_formats_load_and_save_as_a_summary(tmp_path, version):
    state, _ = load_map(stored_map(version))
    budget = _budget(state)
    save_map(state, tmp_path, parts=StoredParts(descriptors="landmarks", landmark_budget=budget))
    summary, _ = load_map(tmp_path)
    assert set(summary.landmarks) == _reference_kept(state, budget)
    assert len(summary.landmarks) < len(state.landmarks)


def test_without_a_budget_every_landmark_is_saved(tmp_path, synthetic_map):
    save_map(synthetic_map, tmp_path, parts=StoredParts(descriptors="landmarks"))
    state, _ = load_map(tmp_path)
    assert set(state.landmarks) == set(synthetic_map.landmarks)


@pytest.mark.parametrize("budget", [-1, "300", 2.5, True])
def test_a_budget_that_is_not_a_count_is_refused_by_name(budget):
    with pytest.raises(ConfigError, match=r"service\.landmark_budget: expected an integer >= 0"):
        ServiceSection(landmark_budget=budget)


def test_a_budget_with_every_row_kept_is_refused_by_name():
    with pytest.raises(ConfigError, match="landmark_budget: expected keyframe_descriptors other "
                                          "than 'all'"):
        ServiceSection(landmark_budget=300, keyframe_descriptors="all")
    assert ServiceSection(landmark_budget=300).stored_parts().landmark_budget == 300


@pytest.mark.parametrize("descriptors", ["per-landmark", "per-landmark-medoid"])
def test_a_summary_composes_with_one_descriptor_a_landmark(tmp_path, synthetic_map, descriptors):
    budget = _budget(synthetic_map)
    save_map(synthetic_map, tmp_path, parts=StoredParts(descriptors=descriptors,
                                                        landmark_budget=budget))
    state, _ = load_map(tmp_path)
    assert set(state.landmarks) == _reference_kept(synthetic_map, budget)
    for lm_id, lm in state.landmarks.items():
        for kf_id, kind, kp in lm.observations:
            assert state.keyframes[kf_id].features[kind].landmark_ids[kp] == lm_id
