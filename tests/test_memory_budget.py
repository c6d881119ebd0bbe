"""The memory budget counts the whole service (``[service] max_resident_mb``): the
processes' own resident memory with no map (the service's, measured after its warm-up, and
each worker process's), and what each worker's query may hold while it runs, sized by the
largest image a query may carry; the maps get the rest, a budget below that baseline refuses
to start. Real services on loopback, real storage; the counters read from ``status``."""

from __future__ import annotations

import re

import pytest
from lazy_maps_support import conf, pose_of, scene_template, stored_maps
from reloc_client.client import RelocClient
from service_support import AMPLE_MB, endpoint, free_port, wait_until

from reloc_service.core.errors import ConfigError
from reloc_service.service.app import Service
from reloc_service.service.memory import rss_bytes, trim_now
from reloc_service.service.memory_baseline import query_working_bytes
from reloc_service.service.residency import MB, counted_bytes
from reloc_service.tools.bench.stored_map import StoredMap


@pytest.fixture(scope="module")
def template(synthetic_scene, tmp_path_factory) -> StoredMap:
    """The scene's stored map (:func:`lazy_maps_support.scene_template`)."""
    return scene_template(synthetic_scene, tmp_path_factory.mktemp("budget-template")
                          / "storage")


def test_a_budget_below_the_services_own_memory_refuses_to_start(template, tmp_path):
    storage = stored_maps(template, tmp_path / "storage", names=("alpha",))
    trim_now()   # as the service measures: the heap's free pages given back first
    own_mb = rss_bytes() / MB   # this process, before the service adds to it
    with pytest.raises(ConfigError) as refused:
        Service(conf(free_port(), storage, max_resident_mb=1)).start()
    message = str(refused.value)
    assert "service.max_resident_mb = 1 MB" in message
    measured = re.search(r"resident memory with no map and its workers' queries, (\d+) MB",
                         message)
    queries = re.search(r"(\d+) MB of it for the queries", message)
    assert queries is not None and int(queries[1]) > 0
    assert measured is not None and int(measured[1]) >= int(own_mb) + int(queries[1])
    # refused, it let go of the storage: a service with a budget above it starts there
    service = Service(conf(free_port(), storage, max_resident_mb=AMPLE_MB)).start()
    service.stop()


def test_the_maps_get_the_budget_minus_the_measured_baseline(template, synthetic_scene,
                                                             tmp_path):
    storage = stored_maps(template, tmp_path / "storage", names=("alpha",))
    port = free_port()
    trim_now()   # as the service measures: the heap's free pages given back first
    before = rss_bytes()
    camera = synthetic_scene.camera
    pixels = camera.width * camera.height   # queries no larger than the scene's camera
    service = Service(conf(port, storage, max_resident_mb=AMPLE_MB,
                           limits={"max_image_pixels": pixels})).start()
    try:
        residency = service.registry.residency
        assert residency is not None
        # measured at the warm-up's end (no map yet), in place of the estimate at declaration
        assert residency.baseline_settled.wait(60)
        with RelocClient(endpoint(port), map="alpha", timeout=30) as client:
            pose_of(client, synthetic_scene, 0)
            memory = client.status().counters
            counted = counted_bytes(service.maps["alpha"])
        assert memory["memory_budget_bytes"] == AMPLE_MB * MB
        # this process's own memory, measured before the map was loaded
        assert before <= memory["memory_baseline_service_bytes"] <= rss_bytes()
        assert memory["memory_baseline_workers_bytes"] == 0   # thread mode: no worker process
        # each worker's query, answered on a thread of this process, at most that size
        assert memory["memory_baseline_queries_bytes"] == 2 * query_working_bytes(pixels)
        assert query_working_bytes(pixels) < query_working_bytes(1280 * 960)   # the default
        assert memory["memory_baseline_bytes"] == (memory["memory_baseline_service_bytes"]
                                                   + memory["memory_baseline_queries_bytes"])
        assert memory["memory_maps_budget_bytes"] == (AMPLE_MB * MB
                                                      - memory["memory_baseline_bytes"])
        assert memory["memory_maps_bytes"] == counted > 0
    finally:
        service.stop()


def test_worker_processes_own_memory_counts_against_the_budget(template, synthetic_scene,
                                                               tmp_path):
    storage = stored_maps(template, tmp_path / "storage", names=("alpha",))
    port = free_port()
    service = Service(conf(port, storage, max_resident_mb=AMPLE_MB, worker_mode="process",
                           workers=1)).start()
    try:
        with RelocClient(endpoint(port), map="alpha", timeout=60) as client:
            assert client.status().counters["memory_baseline_workers_bytes"] == 0   # none yet
            pose_of(client, synthetic_scene, 0)   # starts the worker (answered meanwhile here)
            # the worker and the forkserver it was forked from, once it has warmed up and
            # before it holds a replica
            wait_until(lambda: client.status().counters["memory_baseline_workers_bytes"] > 0,
                       timeout=60)
            memory = client.status().counters
        assert memory["memory_baseline_queries_bytes"] == query_working_bytes(   # one worker
            1280 * 960)   # the default limits.max_image_pixels
        assert memory["memory_baseline_bytes"] == (memory["memory_baseline_service_bytes"]
                                                   + memory["memory_baseline_workers_bytes"]
                                                   + memory["memory_baseline_queries_bytes"])
        assert memory["memory_maps_budget_bytes"] == (AMPLE_MB * MB
                                                      - memory["memory_baseline_bytes"])
    finally:
        service.stop()
