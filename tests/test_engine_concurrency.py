"""The engine's lock discipline with the real methods: only the engine creates locks, and
queries running while mapping and training answer as sequential ones would, against indexes that
match the map."""

from __future__ import annotations

import functools
import linecache
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from engine_support import FAST_MAPPING, add_keyframes, query_frame

import reloc_service
from reloc_service.algorithms.relocalizers.base import RelocResult
from reloc_service.engine import Engine, EngineConf

REAL_METHODS = ("sbi+p3p", "bow+p3p", "ferns")
REAL_OPTIONS = {"bow": {"branching": 6, "depth": 3},
                "ferns": {"num_ferns": 40, "num_tests": 10, "num_warps": 10, "workers": 2}}


def _real_engine(scene, ids) -> Engine:
    engine = Engine(EngineConf(methods=REAL_METHODS, options=REAL_OPTIONS, mapping=FAST_MAPPING))
    add_keyframes(engine, scene, ids)
    engine.train()
    return engine


def test_only_the_engine_creates_locks(synthetic_scene, monkeypatch):
    """The engine is the one place that locks (its readers-writer lock's own module aside):
    building, mapping, training and querying the real methods creates no lock in the map,
    the indexes or the relocalizers, and a query creates none at all."""
    root = str(Path(reloc_service.__file__).parent)
    sites: list[str] = []

    def counting(name: str):
        real = getattr(threading, name)

        def make(*args: Any, **kwargs: Any) -> Any:
            caller = sys._getframe(1)
            path = caller.f_code.co_filename
            # Our own creations only: a library's lock (numpy's random generators, a thread
            # pool's) is attributed to the line of ours that called the library.
            if path.startswith(root) and f"{name}(" in linecache.getline(path, caller.f_lineno):
                sites.append(f"{Path(path).relative_to(root)}:{caller.f_lineno}")
            return real(*args, **kwargs)
        return make

    for name in ("Lock", "RLock", "Condition"):
        monkeypatch.setattr(threading, name, counting(name))
    engine = _real_engine(synthetic_scene, range(3))
    engine.remove_keyframe(2)
    # The engine's readers-writer lock creates its condition in its own module.
    engine_sites = {"engine/engine.py", "core/read_write_lock.py"}
    assert sites and {s.split(":")[0] for s in sites} == engine_sites, sites
    built = len(sites)
    for method in REAL_METHODS:
        engine.relocalize(query_frame(synthetic_scene), method=method)
    assert len(sites) == built, f"locks created by queries: {sites[built:]}"


def test_concurrent_queries_on_real_methods_while_mapping_and_training(synthetic_scene):
    """Threads query sbi+p3p, bow+p3p and ferns non-stop while keyframes are added, replaced
    and removed and two methods are retrained: no exception, every answer is a correct pose
    or NOT_RELOCALIZED, and each was computed on one published map version, matching only
    keyframes of that version. Afterwards every index holds exactly the map's keyframes.
    (The engine's exclusion itself is proven by the probe of
    ``test_concurrent_queries_see_consistent_map_versions``: the real methods pin a map
    snapshot per query and would hide a missing read lock most of the time.)"""
    from reloc_service.core.geometry import pose_error

    scene = synthetic_scene
    engine = _real_engine(scene, range(4))
    published = {engine.map.version: set(engine.map.snapshot().keyframes)}
    stop = threading.Event()
    answers: list[tuple[str, int, RelocResult]] = []
    errors: list[BaseException] = []

    def guarded(work) -> None:
        try:
            work()
        except BaseException as exc:  # noqa: BLE001 - the test reports it
            errors.append(exc)

    def query_loop(first: int) -> None:
        i = first
        while not stop.is_set():
            method, q = REAL_METHODS[i % len(REAL_METHODS)], i % 3
            answers.append((method, q, engine.relocalize(query_frame(scene, q), method=method)))
            i += 1

    def retrain() -> None:
        engine.train(["bow+p3p"])
        engine.train(["ferns"])

    threads = [threading.Thread(target=guarded, args=(functools.partial(query_loop, k),))
               for k in range(3)]
    trainer = threading.Thread(target=guarded, args=(retrain,))
    for t in [*threads, trainer]:
        t.start()
    try:
        for change in (("add", 4), ("remove", 1), ("add", 5), ("add", 2), ("remove", 0),
                       ("add", 1)):   # ("add", 2): a replaced keyframe
            if change[0] == "add":
                add_keyframes(engine, scene, [change[1]])
            else:
                engine.remove_keyframe(change[1])
            published[engine.map.version] = set(engine.map.snapshot().keyframes)
        trainer.join()
    finally:
        stop.set()
        for t in threads:
            t.join()
    assert not errors, errors
    assert {m for m, _, _ in answers} == set(REAL_METHODS)
    for method, q, r in answers:
        assert r.method == method and r.map_version in published
        assert set(r.matched_keyframe_ids) <= published[r.map_version], (method, r)
        if r.ok:
            dist, angle = pose_error(r.world_from_cam, scene.query_poses[q])
            assert dist < 0.05 and np.degrees(angle) < 1.0, (method, q, dist, r.reason)
        else:
            assert r.reason, (method, q)
    _assert_indexes_match_map(engine)


def _assert_indexes_match_map(engine: Engine) -> None:
    """Every relocalizer learnt exactly the published map (no lost or doubled update)."""
    state = engine.map.snapshot()
    ids = state.keyframe_ids()
    assert engine.status()["map_version"] == state.version
    assert len(engine.relocalizer("sbi+p3p").place) == len(ids)
    assert engine.relocalizer("bow+p3p").place.indexed_keyframe_ids() == ids
    ferns = engine.relocalizer("ferns")
    observed = {(lm.id, o[0], o[2]) for lm in state.landmarks.values() for o in lm.observations
                if o[1] == "sift"}
    assert ferns.trained_observations() <= observed
    assert {kf for _, kf, _ in ferns.trained_observations()} == {kf for _, kf, _ in observed}


def _answer(result: RelocResult) -> tuple[Any, ...]:
    """What a query answered, bit for bit."""
    pose = None if result.world_from_cam is None else result.world_from_cam.tobytes()
    return (result.ok, result.reason, result.inliers, result.num_matches, pose,
            tuple(result.matched_keyframe_ids), result.map_version)


@pytest.mark.slow
def test_concurrent_queries_answer_as_sequential_ones(synthetic_scene):
    """Queries share a relocalizer under the read lock, so ``relocalize`` must not change
    what another query reads: queries started together right after a map change (bow's
    inverted file and ferns' landmark table are stale, so the racing queries rebuild them)
    answer bit for bit what the same queries answer one after another."""
    scene = synthetic_scene
    engine = _real_engine(scene, range(3))
    add_keyframes(engine, scene, [3])
    work = [(m, q) for m in REAL_METHODS for q in range(3)]
    start = threading.Barrier(3)
    answers: dict[int, dict[tuple[str, int], tuple[Any, ...]]] = {k: {} for k in range(3)}
    errors: list[BaseException] = []

    def queries(k: int) -> None:
        try:
            start.wait(10)
            for method, q in work[k:] + work[:k]:   # each thread in another order
                result = engine.relocalize(query_frame(scene, q), method=method)
                answers[k][method, q] = _answer(result)
        except BaseException as exc:  # noqa: BLE001 - the test reports it
            errors.append(exc)

    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-5)   # switch threads often: interleave the queries finely
    try:
        threads = [threading.Thread(target=queries, args=(k,)) for k in range(3)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(interval)
    assert not errors, errors
    sequential = {(m, q): _answer(engine.relocalize(query_frame(scene, q), method=m)) for m, q in work}
    assert sum(a[0] for a in sequential.values()) >= len(work) - 2   # mostly relocalized
    for k in range(3):
        assert answers[k] == sequential, k
