"""The whole-map pools at load: an engine that answers no query (a service's, with worker
processes) carries their stored index over in its saves, so a replica's load reads it rather
than building it; a closed engine stops making them; making them keeps no keyframe's
features built."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
from engine_support import count_builds, saved_trained_engine

from reloc_service.algorithms.pose.map_pool import MapPool, held_pool
from reloc_service.algorithms.pose.repetition_index import IndexConf
from reloc_service.algorithms.pose.repetition_store import STORE_DIR, load_index, stored_kinds
from reloc_service.algorithms.relocalizers import map_pools
from reloc_service.core.mapping import MappingConf
from reloc_service.engine import Engine, EngineConf
from reloc_service.storage.keyframe_parts import EVERYTHING
from reloc_service.storage.snapshot import current_snapshot, model_dir_name

#: Two p3p steps of different kinds (two pools, made one after the other), one with a
#: trained model (a load restores it, and makes the pools on a thread of their own).
METHOD = "sbi+p3p:orb,bow+p3p"


def conf() -> EngineConf:
    """Every pool indexed, however small the map."""
    return EngineConf(methods=(METHOD,), mapping=MappingConf(max_features=400),
                      options={"p3p": {"repetition_exact_rows": 0}})


@pytest.fixture(scope="module")
def saved(synthetic_scene, tmp_path_factory) -> Path:
    """A trained engine's save: its map, models and both pools' indexes."""
    _, directory = saved_trained_engine(synthetic_scene, conf(),
                                        tmp_path_factory.mktemp("replica-pools") / "map")
    assert sorted(stored(directory)) == ["orb", "sift"]
    return directory


def stored(directory: Path) -> list[str]:
    return stored_kinds(current_snapshot(directory) / "models" / model_dir_name(METHOD))



def test_a_replica_of_an_engine_without_pools_reads_their_index(saved, tmp_path,
                                                                 monkeypatch) -> None:
    service = Engine.load(saved, conf(), pools=False)   # makes no pool
    base = tmp_path / "base"
    service.save(base, exact_geometry=True, parts=EVERYTHING)   # what a rebase sends
    assert sorted(stored(base)) == ["orb", "sift"]
    made = count_builds(monkeypatch)
    replica = Engine.load(base, conf(), train=False)   # what a worker does with it
    assert replica.prepared.wait(60)
    assert not made, "the worker built an index the service's save could have carried"
    assert sorted(replica.pools_read) == ["orb", "sift"]
    for kind in ("orb", "sift"):
        assert held_pool(replica.map.snapshot(), kind, IndexConf(exact_rows=0)) is not None


def test_a_changed_map_carries_no_index_over(saved, synthetic_scene, tmp_path) -> None:
    service = Engine.load(saved, conf(), pools=False)
    scene = synthetic_scene
    pose = scene.keyframe_poses[0].copy()
    pose[:3, 3] += 0.05
    service.add_keyframe(1000, scene.keyframe_images[0], scene.camera, pose)
    base = tmp_path / "base"
    service.save(base)
    assert stored(base) == []   # its pools are for the other state: built at the next load


def test_closing_an_engine_stops_its_pools_before_the_next(saved, monkeypatch) -> None:
    first_started, release = threading.Event(), threading.Event()
    real = map_pools._make
    made: list[str] = []

    def slow_make(finder, state, directory, cancelled=None):
        made.append(finder.conf.kind)
        first_started.set()
        assert release.wait(60)
        return real(finder, state, directory, cancelled)

    monkeypatch.setattr(map_pools, "_make", slow_make)
    engine = Engine.load(saved, conf())
    assert first_started.wait(60)
    engine.close()   # evicted while its first pool is being made
    release.set()
    assert engine.prepared.wait(60)
    assert made == ["orb"], "the second pool was made for a closed map"
    state = engine.map.snapshot()
    assert held_pool(state, "sift", IndexConf(exact_rows=0)) is None
    assert np.isfinite(engine.held_bytes())


def test_making_the_pools_leaves_no_keyframe_features_built(saved) -> None:
    """The pools read every keyframe's features once; kept built, they would take memory
    (about 135 MB per 1000 keyframes) that the map's budget does not count."""
    engine = Engine.load(saved, conf())
    assert engine.prepared.wait(60)
    state = engine.map.snapshot()
    for kind in ("orb", "sift"):
        assert held_pool(state, kind, IndexConf(exact_rows=0)) is not None
    built = {kf_id: kf.features.built_kinds for kf_id, kf in state.keyframes.items()}
    assert not any(built.values()), built


def test_an_index_stored_as_leaves_is_the_filing_a_build_makes(saved, tmp_path) -> None:
    """The stored leaf of each row gives back the order and offsets of the index as built
    (seeded: a build again makes the same), and an index saved before leaves were stored
    (``<kind>.npz``: order and offsets themselves) is still read, to the same filing."""
    models = current_snapshot(saved) / "models" / model_dir_name(METHOD)
    state = Engine.load(saved, conf(), pools=False).map.snapshot()
    index_conf = IndexConf(exact_rows=0)
    for kind in ("orb", "sift"):
        stored_pool = load_index(models, state, kind, index_conf)
        assert stored_pool is not None
        built = MapPool.make(state, kind, index_conf).index
        assert np.array_equal(stored_pool.index.order, built.order)
        assert np.array_equal(stored_pool.index.offsets, built.offsets)
        leaves = np.load(models / STORE_DIR / f"{kind}.leaves.npz")["leaves"]
        assert leaves.dtype.itemsize <= 2 < built.order.dtype.itemsize
        old = tmp_path / kind
        (old / STORE_DIR).mkdir(parents=True)
        with np.load(models / STORE_DIR / f"{kind}.leaves.npz") as npz:
            arrays = {k: npz[k] for k in npz.files if k != "leaves"}
        np.savez(old / STORE_DIR / f"{kind}.npz", order=built.order, offsets=built.offsets,
                 **arrays)
        assert stored_kinds(old) == [kind]
        read = load_index(old, state, kind, index_conf)
        assert read is not None and np.array_equal(read.index.order, built.order)
