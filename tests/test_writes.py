"""The write path's threads: a keyed pool that keeps each map's writes in order on a few
threads shared by every map (no thread per map), and a service that creates 100 maps by puts
over Zenoh on a bounded number of threads."""
# ruff: noqa: E402

from __future__ import annotations

import dataclasses
import threading
import time

import cv2
import numpy as np
import pytest
from reloc_client import protocol as wire
from service_support import BLOCK, free_port, raw_session, service_conf, wait_until

from reloc_service.service.app import Service
from reloc_service.service.config import QuotasConf
from reloc_service.service.workers import KeyedPool


@pytest.fixture
def pool():
    pool = KeyedPool("test", workers=3, queue_size=100, max_bytes=1000)
    yield pool
    pool.close()


def test_each_keys_jobs_run_in_order_and_never_two_at_once(pool):
    ran: dict[str, list[int]] = {k: [] for k in "abcdef"}
    active: dict[str, int] = dict.fromkeys("abcdef", 0)
    overlaps: list[str] = []
    lock = threading.Lock()

    def job(key: str, i: int):
        def run(_queued: float) -> None:
            with lock:
                active[key] += 1
                if active[key] > 1:
                    overlaps.append(key)
            time.sleep(0.001)
            with lock:
                active[key] -= 1
                ran[key].append(i)
        return run

    for i in range(40):
        for key in ran:
            assert pool.submit(key, job(key, i))
    assert pool.join(30)
    assert all(seq == list(range(40)) for seq in ran.values()), ran
    assert overlaps == []
    assert pool.pending() == 0 and pool.held_bytes == 0


def test_a_blocked_key_holds_one_thread_and_the_others_go_on(pool):
    gate = threading.Event()
    done: list[str] = []
    assert pool.submit("slow", lambda _q: gate.wait(30))
    assert pool.submit("slow", lambda _q: done.append("slow"))   # waits behind its own key
    for key in ("a", "b", "c", "d"):
        assert pool.submit(key, lambda _q, key=key: done.append(key))
    wait_until(lambda: len(done) == 4, timeout=10)
    assert sorted(done) == ["a", "b", "c", "d"] and pool.pending("slow") == 1
    gate.set()
    assert pool.join(10) and done[-1] == "slow"


def test_the_pool_has_its_threads_whatever_the_number_of_keys(pool):
    before = threading.active_count()
    for i in range(300):
        assert pool.submit(f"map{i}", lambda _q: time.sleep(0.0005))
    assert threading.active_count() == before == threading.active_count()
    assert pool.join(30)
    assert threading.active_count() == before and pool.threads == 3


def test_the_queue_of_a_key_and_the_bytes_of_all_keys_are_bounded(pool):
    gate = threading.Event()
    small = KeyedPool("small", workers=1, queue_size=2, max_bytes=100)
    try:
        started = threading.Event()
        assert small.submit("a", lambda _q: (started.set(), gate.wait(10)), size=60)
        assert started.wait(10)                                      # running, not waiting
        assert small.submit("a", lambda _q: None) and small.submit("a", lambda _q: None)
        assert not small.submit("a", lambda _q: None)                # 2 waiting already
        assert not small.submit("b", lambda _q: None, size=50)       # 110 > 100 bytes
        assert small.submit("b", lambda _q: None, size=40)
        queued = small.take_queued()
        assert len(queued) == 3 and small.held_bytes == 60
        gate.set()
        assert small.join(10) and small.held_bytes == 0
        assert small.submit("c", lambda _q: None, size=500)          # alone: admitted
        small.close()
        assert not small.submit("c", lambda _q: None)
    finally:
        gate.set()
        small.close()


def _tiny_put(kf_id: int, rng: np.random.Generator) -> bytes:
    """A valid 64x48 keyframe put with its camera inline (PNG of noise)."""
    ok, png = cv2.imencode(".png", rng.integers(0, 255, (48, 64), dtype=np.uint8))
    assert ok
    camera = wire.WireCamera.from_dict({"model": "pinhole", "width": 64, "height": 48,
                                        "fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 23.5})
    return wire.KeyframePut(id=kf_id, image=wire.WireImage.from_bytes(png.tobytes()),
                            world_from_cam=wire.WirePose.from_matrix(np.eye(4)),
                            camera=camera).encode()


def test_100_maps_created_by_puts_add_no_thread_per_map():
    """100 new maps by puts over Zenoh (max_maps raised): every put is applied, and the
    service's threads stay within 8 of what they were before the first put (the writer
    pool's 4 threads exist from the start; the margin is for Zenoh's callback threads and a
    transient snapshot or heap-trim timer). A writer per map added 100."""
    port = free_port()
    conf = service_conf(port, methods=["sbi+p3p"], default_method="sbi+p3p",
                        train_on_load=False, worker_mode="thread")
    conf = dataclasses.replace(conf, quotas=QuotasConf(max_maps=200))
    rng = np.random.default_rng(0)
    payloads = [_tiny_put(0, rng) for _ in range(100)]
    with Service(conf) as service, raw_session(port) as session:
        time.sleep(0.5)   # the session's own threads are up
        before = threading.active_count()
        peak = before
        for i, payload in enumerate(payloads):
            session.put(wire.keys.keyframe("reloc", f"m{i:03d}", 0), payload,
                        congestion_control=BLOCK)
            peak = max(peak, threading.active_count())

        def all_applied() -> bool:
            nonlocal peak
            peak = max(peak, threading.active_count())
            return len(service.maps) == 100 and all(
                0 in rt.map_state().keyframes for rt in service.maps.values())

        wait_until(all_applied, timeout=60, interval=0.05)
        assert service.wait_idle(30)
        after = threading.active_count()
        print(f"threads: {before} before, peak {peak}, {after} after 100 maps")
        assert peak <= before + 8, (before, peak)
        assert after <= before + 8, (before, after)
