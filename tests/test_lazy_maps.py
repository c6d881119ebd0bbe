"""Many maps with bounded memory (``[service] max_resident_mb``): a service registers its
stored maps without loading them, loads each on its first use (a cold load), closes the least
recently used idle ones past the budget (releasing their files) and loads them again on
demand with the same answers; a put on a closed map loads it and is durable; a map with puts
waiting or a training job is never closed. Real services on loopback, real storage."""
# ruff: noqa: E402

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np
import pytest
from lazy_maps_support import METHOD, NAMES, conf, pose_of, scene_template, stored_maps
from reloc_client import protocol as wire
from reloc_client.client import RelocClient, ServiceBusy, to_wire_image
from service_support import (
    AMPLE_MB,
    Events,
    ServiceProcess,
    durable_keyframe_ids,
    endpoint,
    free_port,
    limit_maps,
    wait_until,
    write_config,
)

from reloc_service.engine import Engine, EngineConf
from reloc_service.service.app import Service
from reloc_service.service.residency import MB, counted_bytes
from reloc_service.service.workers import Lane
from reloc_service.tools.bench.stored_map import (
    StoredMap,
    engine_from_images,
    stored_template,
)


@pytest.fixture(scope="module")
def template(synthetic_scene, tmp_path_factory) -> StoredMap:
    """The scene's stored map (:func:`lazy_maps_support.scene_template`)."""
    return scene_template(synthetic_scene, tmp_path_factory.mktemp("lazy-template") / "storage")


def loaded_pool_bytes(stored: StoredMap) -> int:
    """What the pools of ``stored`` hold once a load has made them."""
    loaded = Engine.load(stored.directory / "map", EngineConf(methods=(METHOD,)))
    assert loaded.prepared.wait(60)
    return loaded.held_bytes()


#: How many times :func:`big_template` holds each of the scene's keyframes: a map then counts
#: about 2.2 MB (0.55 MB each time), ten times what a service's baseline varies by between
#: two starts (0.2 MB, after its warm-up and a heap trim), so a budget derived from a probe
#: service's baseline holds the number of maps a test asks for.
REPEATS = 4


@pytest.fixture(scope="module")
def big_template(synthetic_scene, tmp_path_factory) -> StoredMap:
    """A stored map as :func:`template`, with each keyframe held :data:`REPEATS` times (ids
    0..6 x REPEATS - 1, same images and poses): the budget tests' map."""
    storage = tmp_path_factory.mktemp("lazy-big-template") / "storage"
    engine = engine_from_images(synthetic_scene.camera, synthetic_scene.keyframe_images * REPEATS,
                                synthetic_scene.keyframe_poses * REPEATS,
                                EngineConf(methods=(METHOD,)))
    return stored_template(storage, "template", engine)


def open_paths(directory: Path) -> set[str]:
    """Files under ``directory`` this process holds open."""
    out = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith(str(directory)):
            out.add(target)
    return out


def maps_budget(client: RelocClient, maps: float, map_bytes: int) -> int:
    """The maps' share of the budget as the status says (once a query settled it), checked to
    hold as many whole maps as the ``maps`` asked for: what the test relies on. The share is
    derived from a probe service's baseline, which moves by a few tenths of a MB between two
    starts (0.2 MB measured on an idle machine, 0.65 MB seen beside other work), less than
    half a map; a budget asked at 1.5 maps thus still holds one map and not two."""
    share = client.status().counters["memory_maps_budget_bytes"]
    assert int(share // map_bytes) == int(maps), (
        f"the maps' share is {share / MB:.2f} MB, {maps * map_bytes / MB:.2f} MB asked "
        f"({map_bytes / MB:.2f} MB a map): the baseline moved between the probe and this "
        "start by more than the maps' margin")
    return share


def test_start_registers_stored_maps_without_loading_them(template, synthetic_scene,
                                                          tmp_path):
    storage = stored_maps(template, tmp_path / "storage")
    port = free_port()
    service = Service(conf(port, storage, max_resident_mb=AMPLE_MB)).start()
    try:
        assert service.maps == {}   # nothing loaded at start
        assert not open_paths(storage / "alpha")   # no journal or lock of a map open
        with RelocClient(endpoint(port), map="alpha", timeout=30) as client:
            assert sorted(m for _, m in client.maps()) == sorted(NAMES)
            assert client.resident_maps() == []   # served, none in memory
        for name in NAMES:
            with RelocClient(endpoint(port), map=name, timeout=30) as client:
                status = client.status()
                assert not status.resident and status.keyframes == 6
        for name in NAMES:   # a query on each loads it, then answers
            with RelocClient(endpoint(port), map=name, timeout=30) as client:
                pose = pose_of(client, synthetic_scene, 0)
                assert np.linalg.norm(pose[:3, 3] - synthetic_scene.query_poses[0][:3, 3]) < 0.05
                status = client.status()
                assert status.resident and status.trained and status.landmarks > 0
        assert sorted(service.maps) == sorted(NAMES)
        with RelocClient(endpoint(port), map="alpha", timeout=30) as client:
            assert client.resident_maps() == [(service.instance, n) for n in sorted(NAMES)]
            assert sorted(m for _, m in client.maps()) == sorted(NAMES)   # unchanged
    finally:
        service.stop()


def test_a_query_that_cannot_wait_gets_busy_with_a_retry_hint(template, synthetic_scene,
                                                              tmp_path):
    storage = stored_maps(template, tmp_path / "storage", names=("alpha",))
    port = free_port()
    service = Service(conf(port, storage, max_resident_mb=AMPLE_MB,
                           cold_load_wait_s=0)).start()
    try:
        with RelocClient(endpoint(port), map="alpha", timeout=30) as client:
            with pytest.raises(ServiceBusy, match="loaded from storage.*retry"):
                client.relocalize(synthetic_scene.query_images[0], camera_id="cam0")
            wait_until(lambda: "alpha" in service.maps, timeout=30)   # the load went on
            assert client.relocalize(synthetic_scene.query_images[0], camera_id="cam0").ok
    finally:
        service.stop()


def test_small_budget_keeps_recent_maps_and_reloads_the_others(template, synthetic_scene,
                                                               tmp_path):
    map_bytes = template.counted_bytes
    pool_bytes = loaded_pool_bytes(template)
    storage = stored_maps(template, tmp_path / "storage")
    port = free_port()
    service = Service(conf(port, storage, max_resident_mb=AMPLE_MB)).start()
    residency = service.registry.residency
    assert residency is not None
    # the service knows what these maps' pools hold, as once it has made one map's: each
    # map counts that much more while its pools are made (pool_reserve), and one map so
    # fits the share, two maps with their pools do not
    residency.pool_reserve.learn(template.keyframes, pool_bytes)
    assert map_bytes + residency.pool_reserve.reserve(template.keyframes) \
        <= 1.5 * (map_bytes + pool_bytes) < 2 * (map_bytes + pool_bytes)
    share = 1.5 * (map_bytes + pool_bytes)
    limit_maps(service, share)
    counted_after_load: list[int] = []
    tell = residency.on_change

    def record(name: str, resident: bool) -> None:
        if resident:
            counted_after_load.append(residency.resident_bytes())
        if tell is not None:
            tell(name, resident)

    residency.on_change = record
    try:
        clients = {n: RelocClient(endpoint(port), map=n, timeout=30) for n in NAMES}
        first = {}
        for name in NAMES:
            first[name] = pose_of(clients[name], synthetic_scene, 1)
            wait_until(lambda name=name: list(service.maps) == [name], timeout=30)
            assert residency.resident_bytes() <= share
        assert not open_paths(storage / "alpha")   # closed: journal and lock released
        assert not clients["alpha"].status().resident
        wait_until(lambda: clients["alpha"].resident_maps() == [(service.instance, "charlie")])
        again = pose_of(clients["alpha"], synthetic_scene, 1)   # loaded again on demand
        np.testing.assert_allclose(again, first["alpha"], atol=1e-9)
        assert clients["alpha"].status().resident
        wait_until(lambda: list(service.maps) == ["alpha"], timeout=30)
        assert residency.evictions >= 3 and residency.loads == 4
        # Each cold load closed the idle map before it loaded: never two maps counted at once.
        assert len(counted_after_load) == 4
        assert max(counted_after_load) <= share
        assert residency.peak_bytes == max(counted_after_load)
        for client in clients.values():
            client.close()
    finally:
        service.stop()


def test_a_map_with_puts_waiting_or_training_is_not_closed(template, synthetic_scene,
                                                           tmp_path):
    map_bytes = template.counted_bytes
    storage = stored_maps(template, tmp_path / "storage", names=("alpha", "bravo"))
    port = free_port()
    service = Service(conf(port, storage, max_resident_mb=AMPLE_MB)).start()
    residency = service.registry.residency
    assert residency is not None and service.writes.pool is not None
    small = int(1.5 * map_bytes)   # one map fits, two do not

    def load_both_alpha_oldest() -> None:
        residency.budget = AMPLE_MB * MB
        for name in ("alpha", "bravo"):
            assert residency.acquire(name, 30) is not None
            residency.release(name)

    def shrink_and_wait_for_one_closed() -> None:
        residency.budget = small
        residency._wake.set()
        wait_until(lambda: len(service.maps) == 1, timeout=30)

    try:
        # puts waiting in alpha's writer lane behind a running one: alpha, the least
        # recently used, is kept and bravo closed instead
        load_both_alpha_oldest()
        gate = threading.Event()
        lane = Lane(service.writes.pool, "alpha")
        assert lane.submit(lambda _q: gate.wait(30)) and lane.submit(lambda _q: None)
        wait_until(lambda: lane.pending == 1)
        shrink_and_wait_for_one_closed()
        assert list(service.maps) == ["alpha"]
        gate.set()
        wait_until(lambda: lane.pending == 0)
        # a training job running on alpha: alpha is kept while it runs
        load_both_alpha_oldest()
        rt = service.maps["alpha"]
        train, training = rt.engine.train, threading.Event()

        def held_train(*args, **kwargs):
            training.wait(30)
            return train(*args, **kwargs)

        rt.engine.train = held_train   # the real training, held until the test lets it go
        rt.start_training(None)
        shrink_and_wait_for_one_closed()
        assert list(service.maps) == ["alpha"]
        # the job ends only once its snapshot runs: never idle in between, whatever the
        # evictor's timing (a close there would lose the models just trained)
        idle_when_done = []
        publish = rt.publish

        def watched_publish(kind, **fields):
            if kind is wire.EventKind.TRAIN_DONE:
                idle_when_done.append(residency.idle(rt) and not snapshot_saved())
            publish(kind, **fields)

        saved = []
        snapshot = rt._snapshot

        def snapshot_saved() -> bool:
            return bool(saved)

        def recorded_snapshot():
            snapshot()
            saved.append(True)

        rt.publish = watched_publish
        rt._snapshot = recorded_snapshot
        training.set()
        wait_until(lambda: rt.training_thread() is None and not rt.maintenance_running())
        assert idle_when_done == [False]
        # idle now: loading bravo closes alpha, the least recently used
        assert residency.acquire("bravo", 30) is not None
        residency.release("bravo")
        wait_until(lambda: list(service.maps) == ["bravo"], timeout=30)
    finally:
        service.stop()


def test_worker_processes_drop_the_replica_of_a_closed_map(template, synthetic_scene,
                                                           tmp_path):
    map_bytes = template.counted_bytes
    storage = stored_maps(template, tmp_path / "storage", names=("alpha", "bravo"))
    port = free_port()
    # one map fits (held twice: the service's and the worker's replica), two do not
    service = Service(conf(port, storage, max_resident_mb=AMPLE_MB, worker_mode="process",
                           workers=1)).start()
    try:
        limit_maps(service, 3 * map_bytes)
        processes = service.processes
        assert processes is not None
        with RelocClient(endpoint(port), map="alpha", timeout=60) as alpha, \
                RelocClient(endpoint(port), map="bravo", timeout=60) as bravo:
            first = pose_of(alpha, synthetic_scene, 2)   # answered by the worker's replica
            pose_of(bravo, synthetic_scene, 2)
            wait_until(lambda: list(service.maps) == ["bravo"], timeout=30)
            # asked directly, the worker no longer holds alpha
            request = wire.RelocalizeRequest(image=to_wire_image(synthetic_scene.query_images[2]),
                                             camera_id="cam0").encode()
            answer = processes.relocalize("alpha", request, 0.0)
            assert answer.error and b"has no replica" in answer.payload
            np.testing.assert_allclose(pose_of(alpha, synthetic_scene, 2), first, atol=1e-9)
    finally:
        service.stop()


def test_worker_processes_start_after_the_first_answer(template, synthetic_scene, tmp_path):
    """With maps loaded on first use no map is held at start: `reloc serve`'s early start of
    the worker processes is skipped (their spawn and imports would slow the first query's
    cold load); the service answers the first query itself, then starts them."""
    storage = stored_maps(template, tmp_path / "storage", names=("alpha",))
    port = free_port()
    service = Service(conf(port, storage, max_resident_mb=AMPLE_MB, worker_mode="process",
                           workers=1)).start()
    try:
        processes = service.processes
        assert processes is not None
        service.start_workers_in_background()   # as `reloc serve` does after its start
        assert "start-workers" not in {t.name for t in threading.enumerate()}
        assert processes.pids() == []
        with RelocClient(endpoint(port), map="alpha", timeout=60) as client:
            pose_of(client, synthetic_scene, 0)
            assert client.status().counters["relocalize_in_service"] == 1
        wait_until(lambda: len(processes.pids()) == 1, timeout=60)
    finally:
        service.stop()


def test_worker_processes_replicas_count_against_the_budget(template, synthetic_scene,
                                                            tmp_path):
    """With worker processes each resident map is held twice (the service's map, the
    worker's replica): the budget counts both, so fewer maps stay resident than one copy
    each would allow."""
    map_bytes = template.counted_bytes
    storage = stored_maps(template, tmp_path / "storage")
    port = free_port()
    service = Service(conf(port, storage, max_resident_mb=AMPLE_MB, worker_mode="process",
                           workers=1)).start()
    residency = service.registry.residency
    assert residency is not None and residency.copies == 2
    try:
        share = 4.5 * map_bytes   # three maps fit once each (pools included), not twice
        limit_maps(service, share)
        for name in NAMES:
            with RelocClient(endpoint(port), map=name, timeout=60) as client:
                pose_of(client, synthetic_scene, 1)
        wait_until(lambda: residency.resident_bytes() <= share, timeout=30)
        one_copy = [counted_bytes(rt) for rt in service.maps.values()]
        assert len(NAMES) * max(one_copy) <= share   # one copy each would all fit
        assert len(service.maps) < len(NAMES)
        assert residency.resident_bytes() == 2 * sum(one_copy)
        assert residency.peak_bytes <= share   # each load made room for both copies
    finally:
        service.stop()


@pytest.mark.slow   # three service processes: about 15 s
def test_put_on_a_closed_map_loads_it_and_survives_kill_9(big_template, synthetic_scene,
                                                          tmp_path):
    map_bytes = big_template.counted_bytes
    stored_maps(big_template, tmp_path / "storage", names=("lab", "other"))
    port = free_port()
    # a query waits for its map's cold load up to the client's timeout (the default 5 s is
    # short for a fresh process beside other tests)
    settings = {"worker_mode": "thread", "methods": [METHOD], "default_method": METHOD,
                "snapshot_every": 0, "cold_load_wait_s": 25.0}
    # the budget: what `reloc serve` measures as its own memory (its status says, once a
    # query has settled it), plus one and a half maps
    probe = ServiceProcess(write_config(tmp_path, port, max_resident_mb=AMPLE_MB, **settings),
                           port, tmp_path / "log0.txt")
    try:
        assert probe.client is not None
        pose_of(probe.client, synthetic_scene, 0)
        baseline = probe.client.status().counters["memory_baseline_bytes"]
    finally:
        assert probe.terminate() == 0
    config = write_config(tmp_path, port, max_resident_mb=(baseline + 1.5 * map_bytes) / MB,
                          **settings)
    service = ServiceProcess(config, port, tmp_path / "log1.txt")
    try:
        assert service.client is not None
        lab = service.client
        pose_of(lab, synthetic_scene, 0)   # lab resident
        maps_budget(lab, 1.5, map_bytes)
        with RelocClient(endpoint(port), map="other", timeout=30) as other:
            pose_of(other, synthetic_scene, 0)   # other resident, lab closed
        wait_until(lambda: not lab.status().resident, timeout=30)
        events = Events(lab)
        lab.add_keyframe(77, synthetic_scene.query_images[2], synthetic_scene.query_poses[2],
                         camera_id="cam0")
        events.wait("keyframe_added", id=77, timeout=60)
        assert lab.status().resident and lab.status().keyframes == 6 * REPEATS + 1
        service.kill9()
    finally:
        service.close()
    assert 77 in durable_keyframe_ids(tmp_path / "storage" / "lab")
    restarted = ServiceProcess(config, port, tmp_path / "log2.txt")
    try:
        assert restarted.client is not None
        assert 77 in {info.id for info in restarted.client.keyframes()}
    finally:
        assert restarted.terminate() == 0
