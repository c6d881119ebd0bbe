"""Background work steps aside for the queries being answered (:mod:`reloc_service.core.
foreground`): a loaded map's later pools wait while a query runs and a moment after it,
never while a query waits for a pool. Real threads, a real stored map loaded by the
engine."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from reloc_service.algorithms.pose.map_pool import being_made, map_pool, pools_of
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD
from reloc_service.algorithms.relocalizers.map_pools import pool_finders, restore_pools
from reloc_service.core import foreground
from reloc_service.engine import Engine, EngineConf
from reloc_service.storage.snapshot import current_snapshot, model_dir_name
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
    check = foreground.yielding(stop.is_set)
    with foreground.answering():   # begun after the work: it would wait for it
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


def loaded(stored) -> tuple[Engine, Path]:
    """The stored map loaded without its background pools, and its method's model folder."""
    engine = Engine.load(stored.directory / "map", CONF, pools=False)
    return engine, current_snapshot(stored.directory / "map") / "models" / model_dir_name(METHOD)


class Gate:
    """A cancel check that holds its first caller until :meth:`open` (never cancels)."""

    def __init__(self) -> None:
        self.reached, self._open = threading.Event(), threading.Event()

    def __call__(self) -> bool:
        self.reached.set()
        self._open.wait(30)
        return False

    def open(self) -> None:
        self._open.set()


def make_pools(engine: Engine, models: Path, gate: Gate, out: list) -> threading.Thread:
    state = engine.map.snapshot()
    return run_in_thread(lambda: out.append(restore_pools(
        engine.relocalizer(METHOD), state, models, gate, step_aside=True)))


def test_pools_step_aside_for_a_query_begun_after_them_and_a_grace(stored) -> None:
    engine, models = loaded(stored)
    gate, read = Gate(), []
    maker = make_pools(engine, models, gate, read)
    assert gate.reached.wait(30)
    with foreground.answering():   # begun after the pools' work
        gate.open()
        maker.join(0.5)
        assert maker.is_alive() and not pools_of(engine.map.snapshot())
        ended = time.monotonic()
    maker.join(30)
    assert read and time.monotonic() - ended >= foreground.GRACE_S * 0.9
    assert sorted(kind for kind, _, _ in pools_of(engine.map.snapshot())) == sorted(
        {f.conf.kind for f in pool_finders(engine.relocalizer(METHOD))})
    engine.close()


def test_pools_go_on_beside_a_query_begun_before_them(stored) -> None:
    engine, models = loaded(stored)
    with foreground.answering():   # the cold query whose map is being loaded
        gate, read = Gate(), []
        gate.open()
        maker = make_pools(engine, models, gate, read)
        maker.join(30)
        assert not maker.is_alive() and read
    engine.close()


def test_a_query_that_needs_a_pool_waits_for_its_maker_which_goes_on(stored) -> None:
    engine, models = loaded(stored)
    state = engine.map.snapshot()
    first = pool_finders(engine.relocalizer(METHOD))[0]
    kind, conf = first.conf.kind, first.conf.repetition_index()
    gate, read = Gate(), []
    maker = make_pools(engine, models, gate, read)
    assert gate.reached.wait(30)
    with foreground.answering():   # another query, begun after the pools' work
        gate.open()
        # the maker claims the pool, then waits for the query this thread answers
        assert wait_for(lambda: being_made(state, kind, conf))
        maker.join(0.3)
        assert maker.is_alive()
        got = []
        waiter = run_in_thread(lambda: got.append(map_pool(state, kind, conf)))
        waiter.join(30)
        assert got, "the pool a query needs was not made while another query ran"
    maker.join(30)
    # made by the maker, from the index stored with the map, not built by the query
    assert read and kind in read[0]
    engine.close()


def wait_for(condition, timeout_s: float = 30.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.01)
    return condition()
