"""A resident map counts its repetition pools (``[service] max_resident_mb``): the pools are
made when the map is loaded, before its first query, and their bytes join the map's usage in
what the budget weighs, so a budget that the maps' usage alone would fit closes one of them.
Real services on loopback, real storage."""

from __future__ import annotations

import sys
import threading
import weakref
from pathlib import Path

import pytest
from reloc_client.client import RelocClient
from service_support import AMPLE_MB, endpoint, free_port, limit_maps, service_conf, wait_until

from reloc_service.algorithms.pose import landmark_pool
from reloc_service.algorithms.pose.map_pool import pools_of
from reloc_service.algorithms.relocalizers import map_pools
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.engine import Engine, EngineConf
from reloc_service.service.app import Service
from reloc_service.tools.bench.stored_map import StoredMap, copy_map, engine_from_images, stored_template

METHOD = "sbi+p3p"


def conf(port: int, storage: Path, budget_mb: float):
    return service_conf(port, storage, methods=[METHOD], default_method=METHOD,
                        worker_mode="thread", workers=2, snapshot_every=0,
                        max_resident_mb=budget_mb)


@pytest.fixture(scope="module")
def template(synthetic_scene, tmp_path_factory) -> tuple[StoredMap, int]:
    """A stored trained map of the scene's 6 keyframes and the bytes its pools hold once
    it is loaded."""
    storage = tmp_path_factory.mktemp("pools-template") / "storage"
    engine = engine_from_images(synthetic_scene.camera, synthetic_scene.keyframe_images,
                                synthetic_scene.keyframe_poses, EngineConf(methods=(METHOD,)))
    stored = stored_template(storage, "template", engine)
    loaded = Engine.load(stored.directory / "map", EngineConf(methods=(METHOD,)))
    assert loaded.prepared.wait(60)
    return stored, loaded.held_bytes()


def test_a_loaded_map_counts_its_pools_before_any_query(template, tmp_path) -> None:
    stored, pool_bytes = template
    assert pool_bytes > 0
    storage = tmp_path / "storage"
    copy_map(stored, storage, "alpha")
    port = free_port()
    service = Service(conf(port, storage, AMPLE_MB)).start()
    try:
        residency = service.registry.residency
        assert residency is not None
        with RelocClient(endpoint(port), map="alpha", timeout=30) as client:
            client.status()
        residency.acquire("alpha", timeout=30)   # a cold load, no query
        residency.release("alpha")
        rt = service.maps["alpha"]
        assert rt.engine.prepared.wait(30)
        assert rt.engine.held_bytes() == pool_bytes
        assert residency.resident_bytes() == rt.usage.total + pool_bytes
    finally:
        service.stop()


def test_the_budget_closes_a_map_its_pools_take_over(template, synthetic_scene, tmp_path
                                                     ) -> None:
    stored, pool_bytes = template
    storage = tmp_path / "storage"
    for name in ("alpha", "bravo"):
        copy_map(stored, storage, name)
    port = free_port()
    service = Service(conf(port, storage, AMPLE_MB)).start()
    try:
        residency = service.registry.residency
        assert residency is not None
        # Two maps' usage fits, two maps with their pools do not.
        limit_maps(service, 2 * stored.counted_bytes + pool_bytes // 2)
        for name in ("alpha", "bravo"):
            with RelocClient(endpoint(port), map=name, timeout=30) as client:
                assert client.relocalize(synthetic_scene.query_images[0], camera_id="cam0").ok
            assert service.maps[name].engine.prepared.wait(30)
        wait_until(lambda: list(service.maps) == ["bravo"], timeout=30)
        assert residency.resident_bytes() <= residency.budget
        assert residency.kept_held["alpha"] == pool_bytes
    finally:
        service.stop()


def test_closing_a_map_frees_it_and_gives_its_heap_pages_back(template, synthetic_scene,
                                                              tmp_path, monkeypatch) -> None:
    from reloc_service.service import memory

    # who trims: the residency also trims when it measures its baseline and after a cold
    # load; the close of an idle map must too, once the map is collected
    callers: list[str] = []
    real = memory.trim_now

    def trim() -> bool:
        callers.append(sys._getframe(1).f_code.co_name)
        return real()

    monkeypatch.setattr(memory, "trim_now", trim)
    stored, pool_bytes = template
    storage = tmp_path / "storage"
    for name in ("alpha", "bravo"):
        copy_map(stored, storage, name)
    port = free_port()
    service = Service(conf(port, storage, AMPLE_MB)).start()
    try:
        residency = service.registry.residency
        assert residency is not None
        limit_maps(service, 1.5 * (stored.counted_bytes + pool_bytes))   # one map fits, not two
        with RelocClient(endpoint(port), map="alpha", timeout=30) as client:
            assert client.relocalize(synthetic_scene.query_images[0], camera_id="cam0").ok
        alpha = weakref.ref(service.maps["alpha"].engine)
        with RelocClient(endpoint(port), map="bravo", timeout=30) as client:
            assert client.relocalize(synthetic_scene.query_images[0], camera_id="cam0").ok
        wait_until(lambda: residency.evictions == 1, timeout=30)
        # freed by the close itself: the map's objects are in reference cycles, which the
        # cyclic collector, left to itself, may not visit for minutes
        assert alpha() is None
        assert list(service.maps) == ["bravo"]
        assert "release_memory" in callers
    finally:
        service.stop()


CHAIN = DEFAULT_METHOD   # its first step's pool is ORB's, SIFT's next


@pytest.fixture(scope="module")
def chain_template(synthetic_scene, tmp_path_factory) -> StoredMap:
    """A stored trained map of the scene's keyframes for the default method (a chain whose
    models are restored at load, so its pools are made then): an ORB and a SIFT pool."""
    storage = tmp_path_factory.mktemp("chain-template") / "storage"
    engine = engine_from_images(synthetic_scene.camera, synthetic_scene.keyframe_images,
                                synthetic_scene.keyframe_poses, EngineConf(methods=(CHAIN,)))
    return stored_template(storage, "template", engine)


def test_a_map_counts_its_pools_reserve_while_they_are_made(chain_template, tmp_path,
                                                            monkeypatch) -> None:
    # the SIFT pool is held until the test lets it go (the real making then), so the map
    # is seen while it is being made
    let_go = threading.Event()
    real_make = map_pools._make

    def held_make(finder, state, directory, cancelled=None):
        if finder.conf.kind != "orb":
            let_go.wait(60)
        return real_make(finder, state, directory, cancelled)

    monkeypatch.setattr(map_pools, "_make", held_make)
    storage = tmp_path / "storage"
    copy_map(chain_template, storage, "alpha")
    port = free_port()
    service = Service(service_conf(port, storage, methods=[CHAIN], default_method=CHAIN,
                                   worker_mode="thread", workers=2, snapshot_every=0,
                                   max_resident_mb=AMPLE_MB)).start()
    try:
        residency = service.registry.residency
        assert residency is not None
        residency.acquire("alpha", timeout=30)   # a cold load, no query
        residency.release("alpha")
        rt = service.maps["alpha"]
        engine = rt.engine
        # the first step's pool (ORB) is made while the next one is held
        wait_until(lambda: engine.held_bytes() > 0, timeout=30)
        assert not engine.prepared.is_set()
        made_at_load = engine.held_bytes()
        reserve = residency.pool_reserve.reserve(rt.usage.keyframes)
        assert reserve > made_at_load
        assert residency.counted("alpha", rt) >= rt.usage.total + reserve
        assert residency.pool_reserve.measured == 0

        let_go.set()
        assert engine.prepared.wait(30)
        held = engine.held_bytes()
        assert held > made_at_load   # the SIFT pool too
        assert residency.counted("alpha", rt) == rt.usage.total + held
        wait_until(lambda: residency.pool_reserve.measured == 1, timeout=30)
        assert residency.pool_reserve.pools(rt.usage.keyframes) == pytest.approx(held, abs=1)
    finally:
        let_go.set()
        service.stop()


def test_closing_an_engine_stops_the_pool_it_is_making(chain_template, monkeypatch) -> None:
    # the SIFT pool's gathering is held at its first read (two keyframes at a time) until
    # the engine is closed, then at every later one until the test ends: the build ends
    # only if the close stops it between two reads (a close that waited for the pool would
    # wait for the test)
    reached, closed, test_over = threading.Event(), threading.Event(), threading.Event()
    sift_reads: list[int] = []
    real_runs = landmark_pool._stored_runs   # how a map's pool reads its keyframes

    def held_runs(keyframes, kind):
        for run in real_runs(keyframes, kind):
            if kind != "orb":
                sift_reads.append(run[0])
                if len(sift_reads) == 1:
                    reached.set()
                    closed.wait(60)
                else:
                    test_over.wait(120)
            yield run

    monkeypatch.setattr(landmark_pool, "STORED_RUN", 2)
    monkeypatch.setattr(landmark_pool, "_stored_runs", held_runs)
    before = set(threading.enumerate())
    try:
        engine = Engine.load(chain_template.directory / "map", EngineConf(methods=(CHAIN,)))
        builds = [t for t in threading.enumerate() if t.name == "map-pools" and t not in before]
        assert len(builds) == 1
        assert reached.wait(30)
        assert not engine.prepared.is_set()
        engine.close()
        closed.set()
        builds[0].join(30)
        assert not builds[0].is_alive()
        assert engine.prepared.is_set()
        assert len(sift_reads) == 1
        assert len(engine.map.snapshot().keyframes) > landmark_pool.STORED_RUN
        # the ORB pool made before the close is kept; nothing of the SIFT one
        assert [kind for kind, _, _ in pools_of(engine._published)] == ["orb"]
        assert engine.held_bytes() > 0
    finally:
        closed.set()
        test_over.set()
