"""The helper threads of algorithms/relocalizers/overlap.py and the multi relocalizer's overlap option:
the place finder beside the query's feature extraction gives the same answers as without,
and the errors of either side reach the caller as without."""

from __future__ import annotations

import functools
import threading

import cv2
import numpy as np
import pytest

from reloc_service.algorithms.relocalizers import overlap
from reloc_service.algorithms.relocalizers.chain import ChainRelocalizer, _narrow, extract_ahead
from reloc_service.algorithms.relocalizers.chain_hooks import ANSWERED
from reloc_service.algorithms.relocalizers.factory import DEFAULT_METHOD, create_relocalizer
from reloc_service.algorithms.relocalizers.multi import MultiRelocalizer
from reloc_service.core import features as feature_lib
from reloc_service.core.errors import ConfigError, GeometryError, MapError
from reloc_service.core.features import FeatureConf
from reloc_service.core.frame import Frame
from reloc_service.engine import Engine, EngineConf
from reloc_service.service.config import parse_config

OFF = {"multi": {"overlap": False}}


@pytest.fixture
def idle(monkeypatch):
    """A machine with a core to spare, whatever else runs beside the tests."""
    monkeypatch.setattr(overlap, "idle_core", lambda: True)


@pytest.fixture(scope="module")
def engines(synthetic_scene):
    """The default method over the rendered room, with the overlap on (the default) and off."""
    built = {}
    for name, options in (("on", {}), ("off", OFF)):
        engine = Engine(EngineConf(options=options))
        for i, (image, pose) in enumerate(zip(synthetic_scene.keyframe_images,
                                              synthetic_scene.keyframe_poses, strict=True)):
            engine.add_keyframe(i, image, synthetic_scene.camera, pose)
        engine.train()
        built[name] = engine
    return built


def jpeg_queries(scene) -> list[np.ndarray]:
    """The rendered queries and an unrelated image (the ORB step cannot verify it, so the
    SIFT steps run), each through a JPEG as the service receives it."""
    unrelated = np.ascontiguousarray(np.rot90(scene.keyframe_images[0], 2))
    images = [*scene.query_images, unrelated]
    return [cv2.imdecode(cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, 90])[1],
                         cv2.IMREAD_GRAYSCALE) for im in images]


def test_the_overlap_gives_the_same_answers(engines, synthetic_scene, idle):
    overlapped = 0
    for image in jpeg_queries(synthetic_scene):
        on = engines["on"].relocalize(Frame(image.copy(), synthetic_scene.camera))
        off = engines["off"].relocalize(Frame(image.copy(), synthetic_scene.camera))
        assert (on.status, on.method, on.reason) == (off.status, off.method, off.reason)
        assert (on.inliers, on.num_matches, on.matched_keyframe_ids) == (
            off.inliers, off.num_matches, off.matched_keyframe_ids)
        assert on.confidence == off.confidence
        if on.ok:
            assert np.array_equal(on.world_from_cam, off.world_from_cam)
            assert np.array_equal(on.covariance, off.covariance)
        assert "overlap_wait" not in off.timings
        overlapped += "overlap_wait" in on.timings
    assert sum(r.ok for r in [engines["off"].relocalize(Frame(im, synthetic_scene.camera))
                              for im in jpeg_queries(synthetic_scene)]) >= 2
    assert overlapped >= 2, "the helper thread never ran the place finder"


def test_a_first_verified_pose_the_chain_holds_starts_the_next_steps_features(
        synthetic_scene, idle):
    """The chain's hook at a step's first verified pose extracts the next step's features
    ahead exactly where the chain will hold that pose as a contender and ask the next step
    (narrow support, or an intrinsics test without power while a later step matches other
    features), and nowhere else. A coverage test asking for 9 of 16 cells makes some of
    the room's answers narrow (inliers' hull under 9/16 of the image)."""
    engine = Engine(EngineConf(options={"verify": {"min_inlier_cells": 9}}))
    for i, (image, pose) in enumerate(zip(synthetic_scene.keyframe_images,
                                          synthetic_scene.keyframe_poses, strict=True)):
        engine.add_keyframe(i, image, synthetic_scene.camera, pose)
    engine.train()
    chain = engine.relocalizer(DEFAULT_METHOD)
    assert isinstance(chain, ChainRelocalizer)
    seen = {True: 0, False: 0}
    for i in range(len(chain.steps) - 1):
        for image in jpeg_queries(synthetic_scene):
            first = Frame(image.copy(), synthetic_scene.camera)
            if not chain.steps[i].relocalize(first).ok:
                continue
            estimate = first.cache[ANSWERED]
            held = _narrow(chain.steps[i], estimate) or chain._underpowered(i, estimate)
            query = Frame(image.copy(), synthetic_scene.camera)
            chain._ahead_if_held(i, functools.partial(extract_ahead, query, chain.steps[i + 1]),
                                 estimate)
            kinds = set(chain.steps[i + 1].feature_confs())
            started = {k for k in kinds if k in query.features or query.pending_features(k)}
            assert started == (kinds if held else set()), (i, held)
            seen[held] += 1
            for kind in started:  # waited for, not extracted again
                query.features_of(kind, lambda: pytest.fail("the extraction ahead failed"))
    assert seen[True] >= 1 and seen[False] >= 1, seen


def test_the_option_is_read_from_the_service_config(synthetic_map):
    conf = parse_config({"options": {"multi": {"overlap": False}}})
    engine = Engine(EngineConf(options=conf.options))
    chain = engine.relocalizer(DEFAULT_METHOD)
    assert isinstance(chain, ChainRelocalizer)
    assert [step.conf.overlap for step in chain.steps] == [False] * len(chain.steps) == [False] * 4
    default = create_relocalizer("sbi+p3p:orb", Engine().map)
    assert isinstance(default, MultiRelocalizer) and default.conf.overlap is True
    with pytest.raises(ConfigError, match="overlap"):
        create_relocalizer("sbi+p3p", Engine().map, options={"multi": {"overlap": "sometimes"}})
    conf = parse_config({"options": {"multi": {"look_ahead": False}}})
    chain = Engine(EngineConf(options=conf.options)).relocalizer(DEFAULT_METHOD)
    assert [step.conf.look_ahead for step in chain.steps] == [False] * len(chain.steps)
    assert default.conf.look_ahead is True
    with pytest.raises(ConfigError, match="look_ahead"):
        create_relocalizer("sbi+p3p", Engine().map, options={"multi": {"look_ahead": 2}})


@pytest.mark.parametrize("mode", ["on", "off"])
def test_a_place_finder_error_reaches_the_caller(engines, synthetic_scene, monkeypatch, mode,
                                                idle):
    """On a helper thread the place finder's error is the caller's, as without the overlap."""
    step = engines[mode].relocalizer(DEFAULT_METHOD).steps[0]
    threads = []

    def broken(*_, **__):
        threads.append(threading.get_ident())
        raise MapError("the place finder's index is broken")

    monkeypatch.setattr(step.place, "find_places", broken)
    with pytest.raises(MapError, match="index is broken"):
        engines[mode].relocalize(Frame(synthetic_scene.query_images[0], synthetic_scene.camera))
    assert (threads[0] != threading.get_ident()) == (mode == "on")


@pytest.mark.parametrize("mode", ["on", "off"])
def test_a_feature_error_reaches_the_caller(engines, synthetic_scene, monkeypatch, mode, idle):
    """An extraction that fails beside the place finder fails the query with its error."""
    from reloc_service.algorithms.pose import p3p

    def broken(*_, **__):
        raise GeometryError("the detector refused the image")

    monkeypatch.setattr(p3p.feature_lib, "extract", broken)
    with pytest.raises(GeometryError, match="detector refused"):
        engines[mode].relocalize(Frame(synthetic_scene.query_images[0], synthetic_scene.camera))


def test_run_beside_runs_on_a_helper_and_gives_back_its_error(idle):
    seen = overlap.run_beside(threading.get_ident)
    assert seen.overlapped and seen.result() != threading.get_ident()
    error = ValueError("from the helper")

    def fail():
        raise error

    failed = overlap.run_beside(fail)
    with pytest.raises(ValueError) as caught:
        failed.result()
    assert caught.value is error
    inline = overlap.run_beside(threading.get_ident, enabled=False)
    assert not inline.overlapped and inline.result() == threading.get_ident()


def test_a_query_that_finds_every_helper_busy_runs_the_step_itself(idle):
    release = threading.Event()
    held = [overlap.run_beside(release.wait) for _ in range(overlap.MAX_HELPERS)]
    try:
        assert all(h.overlapped for h in held)
        busy = overlap.run_beside(threading.get_ident)
        assert not busy.overlapped and busy.result() == threading.get_ident()
    finally:
        release.set()
        for h in held:
            h.result()
    again = overlap.run_beside(threading.get_ident)
    assert again.overlapped and again.result() != threading.get_ident()


def test_without_an_idle_core_the_step_runs_in_the_callers_thread(monkeypatch):
    monkeypatch.setattr(overlap, "idle_core", lambda: False)
    step = overlap.run_beside(threading.get_ident)
    assert not step.overlapped and step.result() == threading.get_ident()


def test_run_ahead_needs_nobody_to_wait_and_frees_its_helper_when_done(idle):
    release = threading.Event()
    ahead = overlap.run_ahead(lambda: release.wait() and threading.get_ident())
    assert ahead is not None and not ahead.done
    release.set()
    assert ahead.result() != threading.get_ident()
    # its helper is free for the next query once the step ended, whoever waited for it
    release = threading.Event()
    held = [overlap.run_beside(release.wait) for _ in range(overlap.MAX_HELPERS)]
    release.set()
    assert all([h.overlapped for h in held]) and [h.result() for h in held]
    error = ValueError("from ahead")

    def fail():
        raise error

    failed = overlap.run_ahead(fail)
    assert failed is not None
    with pytest.raises(ValueError) as caught:
        failed.result()
    assert caught.value is error


def test_run_ahead_without_an_idle_core_or_a_free_helper_runs_nothing(monkeypatch):
    ran = []
    monkeypatch.setattr(overlap, "idle_core", lambda: False)
    assert overlap.run_ahead(lambda: ran.append(1)) is None
    monkeypatch.setattr(overlap, "idle_core", lambda: True)
    release = threading.Event()
    held = [overlap.run_beside(release.wait) for _ in range(overlap.MAX_HELPERS)]
    try:
        assert overlap.run_ahead(lambda: ran.append(1)) is None
    finally:
        release.set()
        for h in held:
            h.result()
    assert ran == []


def helper_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == overlap.THREAD_NAME and t.is_alive()]


def test_close_helpers_lets_the_steps_under_way_finish_and_joins_every_helper(idle):
    beside = overlap.run_beside(threading.get_ident)
    assert beside.overlapped and helper_threads()
    assert overlap.close_helpers(timeout=5.0) and helper_threads() == []
    assert beside.result() != threading.get_ident()        # its answer kept for the caller
    release = threading.Event()
    ahead = overlap.run_ahead(lambda: release.wait(5.0) and "extracted")
    assert ahead is not None and helper_threads()
    threading.Timer(0.2, release.set).start()
    assert overlap.close_helpers(timeout=5.0) and helper_threads() == []
    assert ahead.done and ahead.result() == "extracted"     # finished, not cut short
    # the pool is usable again: a later query starts a new helper, which close stops too
    again = overlap.run_beside(threading.get_ident)
    assert again.overlapped and again.result() != threading.get_ident()
    assert overlap.close_helpers(timeout=5.0) and helper_threads() == []


def test_close_helpers_names_a_step_that_outlives_its_wait(idle):
    release = threading.Event()
    ahead = overlap.run_ahead(release.wait)
    assert ahead is not None
    try:
        assert not overlap.close_helpers(timeout=0.1)
    finally:
        release.set()
    assert ahead.result() and overlap.close_helpers(timeout=5.0) and helper_threads() == []


def test_a_query_racing_close_helpers_always_gets_its_answer(idle):
    answers: list[int] = []
    stop = threading.Event()

    def queries() -> None:
        while not stop.is_set():
            answers.append(overlap.run_beside(lambda: 1).result())

    asking = threading.Thread(target=queries)
    asking.start()
    try:
        for _ in range(20):
            assert overlap.close_helpers(timeout=5.0)
    finally:
        stop.set()
        asking.join(10.0)
    assert not asking.is_alive(), "a query waited for a helper that close_helpers stopped"
    assert answers and set(answers) == {1}


def test_features_of_waits_for_the_extraction_ahead(synthetic_scene, idle):
    frame = Frame(synthetic_scene.query_images[0], synthetic_scene.camera)
    orb = feature_lib.extract(frame.image, FeatureConf("orb", 200))
    release = threading.Event()

    def slow() -> None:
        release.wait()
        frame.features["orb"] = orb

    ahead = overlap.run_ahead(slow)
    assert ahead is not None
    frame.expect_features("orb", ahead)
    assert frame.pending_features("orb") and "orb" not in frame.features
    threading.Timer(0.05, release.set).start()
    assert frame.features_of("orb", lambda: pytest.fail("extracted twice")) is orb
    assert not frame.pending_features("orb")
    assert frame.features_of("orb", lambda: pytest.fail("extracted twice")) is orb


def test_features_of_redoes_a_failed_extraction_ahead_and_raises_its_error(synthetic_scene,
                                                                         idle):
    frame = Frame(synthetic_scene.query_images[0], synthetic_scene.camera)

    def broken() -> None:
        raise GeometryError("the detector refused the image ahead")

    def broken_here() -> None:
        raise GeometryError("the detector refused the image here too")

    ahead = overlap.run_ahead(broken)
    assert ahead is not None
    frame.expect_features("sift", ahead)
    with pytest.raises(GeometryError, match="here too"):  # the extraction ran again, here
        frame.features_of("sift", broken_here)
    assert "sift" not in frame.features
    sift = frame.features_of("sift", lambda: feature_lib.extract(frame.image))
    assert frame.features["sift"] is sift and len(sift) > 0


@pytest.mark.parametrize(("running", "idle"), [(1, True), (2, False), (5, False)])
def test_an_idle_core_is_read_from_the_kernels_run_queue(tmp_path, monkeypatch, running, idle):
    loadavg = tmp_path / "loadavg"
    loadavg.write_text(f"1.93 2.20 1.92 {running}/124 22149\n")
    monkeypatch.setattr(overlap, "IDLE_READING_S", 0.0)
    monkeypatch.setattr(overlap, "_RUN_QUEUE", overlap._RunQueue(str(loadavg), cores=2))
    assert overlap.idle_core() is idle
    monkeypatch.setattr(overlap, "_RUN_QUEUE", overlap._RunQueue(str(tmp_path / "none")))
    assert overlap.idle_core() is True  # no /proc: as on a machine of its own


def test_a_reading_of_the_run_queue_answers_for_a_while(tmp_path, monkeypatch):
    loadavg = tmp_path / "loadavg"
    loadavg.write_text("1.0 1.0 1.0 3/124 22149\n")
    monkeypatch.setattr(overlap, "IDLE_READING_S", 60.0)
    monkeypatch.setattr(overlap, "_last_reading", (-1e9, True))
    monkeypatch.setattr(overlap, "_RUN_QUEUE", overlap._RunQueue(str(loadavg), cores=2))
    assert overlap.idle_core() is False
    loadavg.write_text("0.1 0.1 0.1 1/124 22150\n")
    assert overlap.idle_core() is False  # the same reading
    monkeypatch.setattr(overlap, "IDLE_READING_S", 0.0)
    assert overlap.idle_core() is True


def test_the_running_count_of_this_machines_loadavg():
    with open(overlap.LOADAVG) as f:
        assert overlap.running_threads(f.read()) >= 1  # this test's thread runs
    with pytest.raises(ValueError, match="loadavg"):
        overlap.running_threads("1.0 2.0")
