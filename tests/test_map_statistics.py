"""The keyframe statistics a save stores beside the models
(:mod:`reloc_service.algorithms.relocalizers.map_statistics`): a loaded engine answers as the
engine that computed them without computing them again, computes those whose inputs changed
(a keyframe removed, other options) to the values a computation gives, and refuses a damaged
file by name; an engine that answers no query carries them into its saves."""

from __future__ import annotations

import copy
import dataclasses
import re
import shutil
import threading
import tracemalloc
import weakref
from pathlib import Path
from types import MappingProxyType

import numpy as np
import pytest
from engine_support import FAST_MAPPING, query_frame, trained_engine

from reloc_service.algorithms.pose import held_out
from reloc_service.algorithms.pose.consistency_store import STORE_DIR, read_statistics
from reloc_service.algorithms.pose.map_consistency import (
    RECORD_BYTES,
    held_statistics,
    keyframe_statistic,
)
from reloc_service.algorithms.pose.map_pool import pool_bytes
from reloc_service.algorithms.pose.pnp_conf import PnPConf
from reloc_service.core.errors import StorageError
from reloc_service.core.geometry import look_at
from reloc_service.core.map import MapState
from reloc_service.engine import Engine, EngineConf
from reloc_service.storage.keyframe_parts import EVERYTHING
from reloc_service.storage.snapshot import current_snapshot, model_dir_name

#: Two p3p steps of different kinds, one with a trained model (a load restores it: nothing
#: is trained, so nothing computes the statistics at load).
METHOD = "sbi+p3p:orb,bow+p3p"
KINDS = ("orb", "sift")


def conf(**p3p: object) -> EngineConf:
    return EngineConf(methods=(METHOD,), mapping=FAST_MAPPING, options={"p3p": p3p})


@pytest.fixture(scope="module")
def saved(synthetic_scene, tmp_path_factory) -> tuple[Engine, Path]:
    """A trained engine (its statistics computed when it trained) and its save, with the
    landmark geometry as held: a load answers bit for bit as the engine did."""
    engine = trained_engine(synthetic_scene, conf())
    directory = tmp_path_factory.mktemp("statistics") / "map"
    engine.save(directory, exact_geometry=True)
    return engine, directory


def models(directory: Path) -> Path:
    return current_snapshot(directory) / "models" / model_dir_name(METHOD)


def count_held_out(monkeypatch) -> list[int]:
    """Record every re-triangulation of a keyframe's held-out landmarks from now on (one a
    statistic computed) in the returned list."""
    made: list[int] = []
    real = held_out.triangulate_midpoint
    lock = threading.Lock()

    def triangulate(*args, **kw):
        with lock:
            made.append(1)
        return real(*args, **kw)

    monkeypatch.setattr(held_out, "triangulate_midpoint", triangulate)
    return made


def computed_keyframes(state: MapState, counted: list[int], pnp: PnPConf
                       ) -> tuple[set[tuple[str, int]], dict[tuple[str, int], tuple]]:
    """The (kind, keyframe) whose statistics asking for them computed, and every
    (kind, keyframe)'s plain and gated statistics."""
    computed, values = set(), {}
    for kind in KINDS:
        for kf_id in state.keyframe_ids():
            before = len(counted)
            values[kind, kf_id] = tuple(keyframe_statistic(state, kf_id, kind, pnp, robust=r)
                                        for r in (False, True))
            if len(counted) > before:
                computed.add((kind, kf_id))
    return computed, values


def computed_afresh(state: MapState, pnp: PnPConf) -> dict[tuple[str, int], tuple]:
    """Every (kind, keyframe)'s statistics computed on ``state``'s data by keyframes that
    hold no record of them (new objects, equal features)."""
    keyframes = {}
    for kf_id, keyframe in state.keyframes.items():
        for kind in KINDS:
            keyframe = keyframe.with_features(kind, dataclasses.replace(keyframe.features[kind]))
        keyframes[kf_id] = keyframe
    fresh = dataclasses.replace(state, keyframes=MappingProxyType(keyframes))
    return {(kind, kf_id): tuple(keyframe_statistic(fresh, kf_id, kind, pnp, robust=r)
                                 for r in (False, True))
            for kind in KINDS for kf_id in fresh.keyframe_ids()}


def test_a_loaded_engine_answers_as_the_saved_one_without_computing_statistics(
        saved, synthetic_scene, monkeypatch) -> None:
    original, directory = saved
    loaded = Engine.load(directory, conf())
    assert sorted(loaded.statistics_read) == list(KINDS)
    assert loaded.prepared.wait(60)
    counted = count_held_out(monkeypatch)
    for i in range(len(synthetic_scene.query_images)):
        mine = loaded.relocalize(query_frame(synthetic_scene, i))
        theirs = original.relocalize(query_frame(synthetic_scene, i))
        assert mine.ok and theirs.ok, (mine.reason, theirs.reason)
        np.testing.assert_array_equal(mine.world_from_cam, theirs.world_from_cam)
        np.testing.assert_array_equal(mine.covariance, theirs.covariance)
    assert not counted, f"the loaded engine computed {len(counted)} keyframe statistics"


def test_an_engine_that_answers_no_query_carries_the_statistics_into_its_saves(
        saved, tmp_path, monkeypatch) -> None:
    _, directory = saved
    service = Engine.load(directory, conf(), pools=False)   # computes none
    base = tmp_path / "base"
    service.save(base, exact_geometry=True, parts=EVERYTHING)   # what a rebase sends
    for kind in KINDS:
        assert read_statistics(models(base), kind) == read_statistics(models(directory), kind)
    worker = Engine.load(base, conf(), pools=False)
    counted = count_held_out(monkeypatch)
    computed, _ = computed_keyframes(worker.map.snapshot(), counted, PnPConf())
    assert not computed


def test_a_removed_keyframe_makes_the_statistics_that_read_it_computed_again(
        saved, tmp_path, monkeypatch) -> None:
    """Every keyframe sees landmarks keyframe 5 saw: each stored statistic read its
    observations, and is computed again, to what a computation on the new map gives."""
    _, directory = saved
    service = Engine.load(directory, conf(), pools=False)
    service.remove_keyframe(5)
    changed = tmp_path / "changed"
    service.save(changed, exact_geometry=True)
    for kind in KINDS:   # carried over, stale
        assert sorted(read_statistics(models(changed), kind)) == [0, 1, 2, 3, 4]
    state = Engine.load(changed, conf(), pools=False).map.snapshot()
    counted = count_held_out(monkeypatch)
    computed, values = computed_keyframes(state, counted, PnPConf())
    assert computed == {(kind, k) for kind in KINDS for k in range(5)}
    assert values == computed_afresh(state, PnPConf())


def test_a_keyframe_added_apart_leaves_the_others_statistics_read(
        saved, synthetic_scene, tmp_path, monkeypatch) -> None:
    """A keyframe facing the wall no other keyframe sees changes none of their inputs:
    theirs are read, its own computed."""
    _, directory = saved
    service = Engine.load(directory, conf(), pools=False)
    pose = look_at((0.0, 0.3, 1.2), (0.0, -1.0, 1.0))
    service.add_keyframe(6, synthetic_scene.render(pose)[0], synthetic_scene.camera, pose)
    changed = tmp_path / "changed"
    service.save(changed, exact_geometry=True)
    state = Engine.load(changed, conf(), pools=False).map.snapshot()
    counted = count_held_out(monkeypatch)
    computed, values = computed_keyframes(state, counted, PnPConf())
    assert computed == {(kind, 6) for kind in KINDS}
    assert values == computed_afresh(state, PnPConf())


def test_statistics_stored_for_other_options_are_computed_again(saved, monkeypatch) -> None:
    _, directory = saved
    loaded = Engine.load(directory, conf(max_reproj_error_px=4.0), pools=False)
    assert sorted(loaded.statistics_read) == list(KINDS)
    state = loaded.map.snapshot()
    pnp = PnPConf(max_reproj_error_px=4.0)
    counted = count_held_out(monkeypatch)
    computed, values = computed_keyframes(state, counted, pnp)
    assert computed == {(kind, k) for kind in KINDS for k in state.keyframe_ids()}
    assert values == computed_afresh(state, pnp)


def test_a_damaged_statistics_file_is_refused_by_name_at_load(saved, tmp_path) -> None:
    _, directory = saved
    copy = tmp_path / "map"
    shutil.copytree(directory, copy)
    path = models(copy) / STORE_DIR / "sift.npz"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(StorageError, match=re.escape(str(path)) + ".*checksum mismatch"):
        Engine.load(copy, conf())


def test_a_map_lifted_from_depth_saved_with_rounded_points_reads_its_statistics(
        synthetic_scene, tmp_path, monkeypatch) -> None:
    """Landmarks lifted from depth maps are stated exact, and their statistics read their
    measured points: a save that rounds those points as a snapshot does by default (float32
    offsets from their anchor keyframe) still gives the statistics back, with the values the
    engine that saved them computed."""
    engine = Engine(conf())
    for i, image in enumerate(synthetic_scene.keyframe_images):
        engine.add_keyframe(i, image, synthetic_scene.camera, synthetic_scene.keyframe_poses[i],
                            depth=synthetic_scene.keyframe_depths[i])
    engine.train()
    state = engine.map.snapshot()
    assert np.any(state.landmark_sigmas(state.landmarks.id_array(), 0.0) == 0.0)
    saved_values = {(kind, k): tuple(keyframe_statistic(state, k, kind, PnPConf(), robust=r)
                                     for r in (False, True))
                    for kind in KINDS for k in state.keyframe_ids()}
    directory = tmp_path / "map"
    engine.save(directory)   # the default geometry: anchored float32 points
    assert (current_snapshot(directory) / "landmarks" / "anchored_points_world.npy").is_file()
    loaded = Engine.load(directory, conf(), pools=False)
    counted = count_held_out(monkeypatch)
    computed, values = computed_keyframes(loaded.map.snapshot(), counted, PnPConf())
    assert not computed, f"computed again: {sorted(computed)}"
    assert values == saved_values


class _Owner:
    """Stands for a keyframe as a key of the records' table (weakly referenced)."""

    def __init__(self, kf_id: int) -> None:
        self.id = kf_id


def test_the_records_count_against_the_memory_budget_within_their_bound(saved) -> None:
    """A trained engine's held bytes are its pools' and its keyframes' records', each
    record counted as ``RECORD_BYTES``: a bound on what copies of its records take, with
    their entries in a table like the records' (by tracemalloc), and not far above it."""
    engine, _ = saved
    state = engine.map.snapshot()
    records = {kind: held_statistics(state, kind) for kind in KINDS}
    count = sum(len(held) for held in records.values())
    assert count == len(KINDS) * len(state.keyframes)
    assert engine.held_bytes() == pool_bytes(state) + RECORD_BYTES * count
    owners = [_Owner(kf_id) for kf_id in state.keyframe_ids()]
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        table: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        for owner in owners:
            table[owner] = {kind: copy.deepcopy(records[kind][owner.id]) for kind in KINDS}
        held = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert RECORD_BYTES / 2 <= held / count <= RECORD_BYTES
