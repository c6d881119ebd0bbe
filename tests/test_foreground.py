"""Background work steps aside for the queries being answered (:mod:`reloc_service.core.
foreground`): a loaded map's later pools wait while a query runs and a moment after it,
never while a query waits for a pool. Real threads, a real stored map loaded by the
engine."""

from __future__ import annotations

import threading
import time

import pytest

from reloc_service.algorithms.pose.map_pool import being_made, map_pool, pools_of
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.algorithms.relocalizers.map_pools import pool_finders
from reloc_service.core import foreground
from reloc_service.engine import Engine, EngineConf
from reloc_service.tools.bench.stored_map import engine_from_images, stored_template

METHOD = DEFAULT_METHOD


def run_in_thread(target) -> threading.Thread:
    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    return thread


def test_step_aside_returns_at_once_when_no_query_ran_for_the_grace() -> None:
    time.sleep(foreground.GRACE_S)
    start = time.monotonic()
    foreground.step_aside()
    assert time.monotonic() - start < foreground.POLL_S


def test_step_aside_waits_until_the_query_ends() -> None:
    started, release = threading.Event(), threading.Event()

    def query() -> None:
        with foreground.answering():
            started.set()
            release.wait(10)

    thread = run_in_thread(query)
    assert started.wait(10)
    stepped = threading.Event()
    aside = run_in_thread(lambda: (foreground.step_aside(), stepped.set()))
    assert not stepped.wait(0.3)   # the query still runs
    released = time.monotonic()
    release.set()
    assert stepped.wait(10)
    # and a grace after it, for the next query a client sends on the answer
    assert time.monotonic() - released >= foreground.GRACE_S * 0.9
    thread.join(10)
    aside.join(10)


def test_step_aside_goes_on_while_a_query_waits_for_background_work() -> None:
    started, release = threading.Event(), threading.Event()

    def query() -> None:
        with foreground.answering(), foreground.waiting_for_background():
            started.set()
            release.wait(10)

    thread = run_in_thread(query)
    assert started.wait(10)
    try:
        assert not foreground.queries_running()
        start = time.monotonic()
        foreground.step_aside()
        assert time.monotonic() - start < 1.0
    finally:
        release.set()
        thread.join(10)


def test_a_stopped_background_work_does_not_wait_for_the_queries() -> None:
    stop = threading.Event()
    with foreground.answering():
        check = foreground.yielding(stop.is_set)
        timer = threading.Timer(0.2, stop.set)
        timer.start()
        start = time.monotonic()
        assert check() is True
        assert time.monotonic() - start < 5.0
        timer.join()


#: Every pool indexed, so that each is read from the map's stored index at load.
CONF = EngineConf(methods=(METHOD,), options={"p3p": {"repetition_exact_rows": 0}})


@pytest.fixture(scope="module")
def stored(synthetic_scene, tmp_path_factory):
    """A stored trained map of the scene's keyframes whose method makes two pools or more."""
    storage = tmp_path_factory.mktemp("foreground") / "storage"
    engine = engine_from_images(synthetic_scene.camera, synthetic_scene.keyframe_images,
                                synthetic_scene.keyframe_poses, CONF)
    made = stored_template(storage, "template", engine)
    assert len(pool_finders(engine.relocalizer(METHOD))) >= 2
    return made


def kinds_made(engine: Engine) -> list[str]:
    return sorted(kind for kind, _, _ in pools_of(engine.map.snapshot()))


def wait_for(condition, timeout_s: float = 30.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.01)
    return condition()


def test_a_loaded_maps_later_pools_wait_for_the_query_being_answered(stored) -> None:
    with foreground.answering():
        engine = Engine.load(stored.directory / "map", CONF)
        finders = pool_finders(engine.relocalizer(METHOD))
        assert wait_for(lambda: kinds_made(engine) == [finders[0].conf.kind])  # made at once
        assert not engine.prepared.wait(0.5)                                   # the others wait
    assert engine.prepared.wait(30)
    assert kinds_made(engine) == sorted({f.conf.kind for f in finders})
    engine.close()


def test_a_query_that_needs_a_later_pool_waits_for_its_maker_which_goes_on(stored) -> None:
    with foreground.answering():
        engine = Engine.load(stored.directory / "map", CONF)
        state = engine.map.snapshot()
        later = pool_finders(engine.relocalizer(METHOD))[1]
        kind, conf = later.conf.kind, later.conf.repetition_index()
        # the maker claims the pool, then waits for the query this thread answers
        assert wait_for(lambda: being_made(state, kind, conf))
        assert not engine.prepared.wait(0.3)
        got = []
        thread = run_in_thread(lambda: got.append(map_pool(state, kind, conf)))
        thread.join(30)
        assert got, "the pool a query needs was not made while another query ran"
    assert engine.prepared.wait(30)
    # made by the maker, from the index stored with the map, not built by the query
    assert kind in engine.pools_read
    engine.close()
