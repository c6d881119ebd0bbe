"""Relocalize workers as processes (service/processes.py), on loopback with real Zenoh: the
same answers as the thread workers, changes visible to the next query, "busy" with every
query answered, a worker killed with -9 replaced, and no process left after a stop."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from reloc_client import protocol as wire
from reloc_client.client import RelocClient
from reloc_client.protocol import ErrorCode
from service_support import (
    ROOT,
    endpoint,
    free_port,
    raw_session,
    service_conf,
    stop_process,
    wait_until,
)

from reloc_service.service import handlers
from reloc_service.service.app import Service

MAP = "lab"
KEYFRAMES = 4   # of the scene's 6: the others are put by the tests


def _camera_put(scene) -> bytes:
    return wire.CameraPut("cam0", wire.WireCamera.from_dict(scene.camera.to_dict())).encode()


def _keyframe_put(scene, kf_id: int) -> bytes:
    return wire.KeyframePut(id=kf_id, image=wire.WireImage.from_array(
        scene.keyframe_images[kf_id]), world_from_cam=wire.WirePose.from_matrix(
        scene.keyframe_poses[kf_id]), camera_id="cam0").encode()


def _request(image: np.ndarray, request_id: str = "r") -> bytes:
    ok, png = cv2.imencode(".png", image)
    assert ok
    h, w = image.shape
    return wire.RelocalizeRequest(
        image=wire.WireImage(wire.ImageFormat.PNG, w, h, png.tobytes()), camera_id="cam0",
        request_id=request_id).encode()


def _serve(conf, scene, keyframes: int = KEYFRAMES) -> Service:
    service = Service(conf).start()
    service.on_camera_sample(MAP, "cam0", _camera_put(scene))
    for kf_id in range(keyframes):
        service.on_keyframe_sample(MAP, kf_id, _keyframe_put(scene, kf_id))
    assert service.wait_idle(60)
    return service


@pytest.fixture(scope="module")
def served(synthetic_scene):
    """A service with 2 worker processes (in memory) and its map of 4 keyframes."""
    port = free_port()
    service = _serve(service_conf(port, "", maps=(MAP,), workers=2, queue_size=8),
                     synthetic_scene)
    assert service.conf.service.worker_mode == "process"   # the default
    assert service.processes is not None
    service.start_workers_in_background()   # as `reloc serve` and the demo do
    # started before any query: the first one does not pay for spawning the workers
    wait_until(lambda: len(service.processes.pids()) == 2, timeout=60)
    # and holding the map: the queries below go to them (before, the service answers)
    wait_until(lambda: service.processes.replica_ready(MAP), timeout=60)
    try:
        yield service, port, synthetic_scene
    finally:
        service.stop(final_snapshot=False)


def _get_all(session, key: str, payloads: list[bytes], timeout: float = 60.0
             ) -> list[list[tuple[str, bytes]]]:
    """Send every query at once, then collect each one's replies: ("ok"|"err", payload)."""
    handlers_ = [session.get(key, payload=p, timeout=timeout) for p in payloads]
    out = []
    for h in handlers_:
        replies = []
        for reply in h:
            if reply.ok is not None:
                replies.append(("ok", reply.ok.payload.to_bytes()))
            else:
                replies.append(("err", reply.err.payload.to_bytes()))
        out.append(replies)
    return out


def _pose(reply: bytes) -> tuple[str, np.ndarray | None]:
    r = wire.RelocalizeReply.decode(reply)
    return r.status.value, None if r.world_from_cam is None else r.world_from_cam.matrix()


def test_process_answers_equal_thread_answers(served):
    """Each query through a worker process (its replica) gives the pose the service's own
    map gives in a thread (the "thread" worker mode's path)."""
    service, port, scene = served
    rt = service.maps[MAP]
    with raw_session(port) as session:
        key = wire.keys.relocalize("reloc", MAP)
        payloads = [_request(image, f"q{i}") for i, image in enumerate(scene.query_images)]
        remote = _get_all(session, key, payloads)
    assert service.processes is not None and len(service.processes.pids()) == 2
    relocalized = 0
    for payload, replies in zip(payloads, remote, strict=True):
        assert [kind for kind, _ in replies] == ["ok"], replies
        status, pose = _pose(replies[0][1])
        local_status, local_pose = _pose(handlers.relocalize(rt, payload))
        assert status == local_status
        if pose is not None:
            relocalized += 1
            np.testing.assert_allclose(pose, local_pose, rtol=0, atol=1e-9)
    assert relocalized >= 2


def test_thread_mode_gives_the_same_poses(synthetic_scene, served):
    """worker_mode = "thread" keeps today's path; built from the same puts, it answers as
    the process workers do."""
    _, port, scene = served
    other = free_port()
    service = _serve(service_conf(other, "", maps=(MAP,), workers=2, worker_mode="thread"),
                     scene)
    try:
        assert service.processes is None
        payload = _request(scene.query_images[0])
        key = wire.keys.relocalize("reloc", MAP)
        with raw_session(port) as a, raw_session(other) as b:
            (ra,), (rb,) = _get_all(a, key, [payload])[0], _get_all(b, key, [payload])[0]
        assert ra[0] == rb[0] == "ok"
        (sa, pa), (sb, pb) = _pose(ra[1]), _pose(rb[1])
        assert sa == sb == "ok"
        np.testing.assert_allclose(pa, pb, rtol=0, atol=1e-9)
    finally:
        service.stop(final_snapshot=False)


def test_a_query_after_an_applied_put_sees_it(served):
    """keyframe_added, then a query: the worker answering it has applied the put (same map
    version, the new keyframe among those matched); the same after a delete."""
    service, port, scene = served
    new = KEYFRAMES
    with RelocClient(endpoint(port), map=MAP, timeout=60) as client:
        added = threading.Event()
        versions: dict[str, int] = {}

        def on_event(event: wire.Event) -> None:
            if event.kind.value in ("keyframe_added", "keyframe_removed") \
                    and event.fields.get("id") == new:
                versions[event.kind.value] = event.fields["map_version"]
                added.set()

        sub = client.subscribe_events(on_event)
        time.sleep(0.2)
        try:
            client.add_keyframe(new, scene.keyframe_images[new], scene.keyframe_poses[new],
                                camera_id="cam0", wait=True)
            assert added.wait(60)
            for _ in range(4):   # both workers, whichever answers
                result = client.relocalize(scene.keyframe_images[new], camera_id="cam0")
                assert result.map_version == versions["keyframe_added"]
                assert result.ok and new in result.matched_keyframe_ids
            added.clear()
            client.remove_keyframe(new, wait=True)
            assert added.wait(60)
            for _ in range(4):
                result = client.relocalize(scene.keyframe_images[new], camera_id="cam0")
                assert result.map_version == versions["keyframe_removed"]
                assert new not in result.matched_keyframe_ids
        finally:
            sub.undeclare()


def test_queries_before_the_workers_hold_the_map_are_answered_by_the_service(synthetic_scene):
    """A service whose worker processes have not started (or not loaded the map yet) answers
    a query itself, at once, and starts them in the background; once they hold the map they
    answer, with the same pose."""
    service = _serve(service_conf(free_port(), "", maps=(MAP,), workers=1, queue_size=8),
                     synthetic_scene)
    try:
        procs, rt = service.processes, service.maps[MAP]
        assert procs is not None and procs.pids() == [] and not procs.replica_ready(MAP)
        payload = _request(synthetic_scene.query_images[0])
        first = _pose(service.relocalize_payload(rt, payload, 0.0))
        assert rt.stats.counters["relocalize_in_service"] == 1
        assert first[0] == "ok"
        wait_until(lambda: procs.replica_ready(MAP), timeout=60)   # started meanwhile
        again = _pose(service.relocalize_payload(rt, payload, 0.0))
        assert rt.stats.counters["relocalize_in_service"] == 1   # the worker answered
        assert len(procs.pids()) == 1 and again[0] == first[0]
        np.testing.assert_allclose(again[1], first[1], rtol=0, atol=1e-9)
    finally:
        service.stop(final_snapshot=False)


def test_workers_still_starting_get_no_query(synthetic_scene):
    """Once the worker processes are listed, while they are still warming up (their kernels)
    and before they have loaded the map, the map is not ready on them: a query then is
    answered by the service at once, not queued behind the workers' start and their load of
    the map (seconds: a query sent in that window used to wait for both)."""
    service = _serve(service_conf(free_port(), "", maps=(MAP,), workers=1, queue_size=8),
                     synthetic_scene)
    try:
        procs, rt = service.processes, service.maps[MAP]
        assert procs is not None
        service.start_workers_in_background()
        wait_until(lambda: len(procs.pids()) == 1, timeout=60, interval=0.005)
        assert not procs.replica_ready(MAP)        # listed, not holding the map yet
        payload = _request(synthetic_scene.query_images[0])
        first = _pose(service.relocalize_payload(rt, payload, 0.0))
        assert rt.stats.counters["relocalize_in_service"] == 1 and first[0] == "ok"
        wait_until(lambda: procs.replica_ready(MAP), timeout=60)
        assert all(MAP in h.holds for h in procs._handles)
        again = _pose(service.relocalize_payload(rt, payload, 0.0))
        assert rt.stats.counters["relocalize_in_service"] == 1   # a worker answered
        np.testing.assert_allclose(again[1], first[1], rtol=0, atol=1e-9)
    finally:
        service.stop(final_snapshot=False)


def test_killed_worker_is_replaced_and_its_query_answered(served):
    """kill -9 of both workers while each holds a query (stopped first, so they hold it for
    sure): each of those queries gets one INTERNAL error reply naming the signal, and the
    next queries are answered by new processes."""
    service, port, scene = served
    procs = service.processes
    assert procs is not None
    before = procs.pids()
    assert len(before) == 2
    key = wire.keys.relocalize("reloc", MAP)
    payloads = [_request(scene.query_images[i % 3], f"k{i}") for i in range(4)]
    with raw_session(port) as session:
        for pid in before:
            os.kill(pid, signal.SIGSTOP)
        pending = [session.get(key, payload=p, timeout=60) for p in payloads[:2]]
        wait_until(lambda: procs.in_flight == 2)
        for pid in before:
            os.kill(pid, signal.SIGKILL)
        for h in pending:
            replies = list(h)
            assert len(replies) == 1 and replies[0].err is not None, replies
            error = wire.decode_error_reply(replies[0].err.payload.to_bytes())
            assert error.code is ErrorCode.INTERNAL and "SIGKILL" in error.message, error
        # answered at once (by the service while the new workers start and load the map)
        after = _get_all(session, key, payloads)
    assert [[kind for kind, _ in r] for r in after] == [["ok"]] * 4, after
    assert all(_pose(r[0][1])[0] in ("ok", "not_relocalized") for r in after)
    wait_until(lambda: len(procs.pids()) == 2 and procs.replica_ready(MAP), timeout=60)
    now = procs.pids()
    assert not set(now) & set(before)
    for pid in before:
        assert not _alive(pid)


def test_worker_killed_while_idle_is_replaced(served):
    """A worker killed between queries: each query still gets exactly one reply, at most
    the one handed to the dead worker an INTERNAL error (usually none: a worker found dead
    before it got the query is replaced and the query sent again), then every query is
    answered by a new process."""
    service, port, scene = served
    procs = service.processes
    assert procs is not None
    victim = procs.pids()[0]
    os.kill(victim, signal.SIGKILL)
    wait_until(lambda: not _alive(victim))
    key = wire.keys.relocalize("reloc", MAP)
    payloads = [_request(scene.query_images[i % 3], f"i{i}") for i in range(4)]
    with raw_session(port) as session:
        first = _get_all(session, key, payloads)
        then = _get_all(session, key, payloads)
    assert all(len(r) == 1 for r in first), first
    errors = [wire.decode_error_reply(r[0][1]) for r in first if r[0][0] == "err"]
    assert len(errors) <= 1 and all(e.code is ErrorCode.INTERNAL and "SIGKILL" in e.message
                                    for e in errors), (victim, errors)
    assert [[kind for kind, _ in r] for r in then] == [["ok"]] * 4, then
    # the replacement is listed once it has warmed up (the queries meanwhile are answered
    # by the live worker, or by the service itself while none holds the map)
    wait_until(lambda: len(procs.pids()) == 2, timeout=60)
    assert victim not in procs.pids()


def test_full_queue_is_busy_and_every_query_answered(synthetic_scene):
    """1 worker process and 1 queue slot under 10 queries at once: some are "busy" at once,
    the others answered; each query exactly one reply, no error. (How many are answered
    depends on whether the worker took the first query off the queue before the others
    arrived: at least one, usually two.)"""
    port = free_port()
    service = _serve(service_conf(port, "", maps=(MAP,), workers=1, queue_size=1),
                     synthetic_scene, keyframes=3)
    try:
        key = wire.keys.relocalize("reloc", MAP)
        payloads = [_request(synthetic_scene.query_images[i % 3], f"b{i}") for i in range(10)]
        with raw_session(port) as session:
            replies = _get_all(session, key, payloads)
        statuses = []
        for r in replies:
            assert [kind for kind, _ in r] == ["ok"], r
            statuses.append(_pose(r[0][1])[0])
        assert statuses.count("busy") >= 1, statuses
        assert len(statuses) == 10 and len(statuses) - statuses.count("busy") >= 1, statuses
        assert set(statuses) <= {"busy", "ok", "not_relocalized"}, statuses
    finally:
        service.stop(final_snapshot=False)


def test_stop_leaves_no_worker_process(synthetic_scene):
    port = free_port()
    service = _serve(service_conf(port, "", maps=(MAP,), workers=2), synthetic_scene,
                     keyframes=3)
    try:
        with raw_session(port) as session:
            _get_all(session, wire.keys.relocalize("reloc", MAP),
                     [_request(synthetic_scene.query_images[0])])
        assert service.processes is not None
        procs = service.processes   # started once that first answer was made
        wait_until(lambda: len(procs.pids()) == 2, timeout=60)
        pids = procs.pids()
        assert all(_alive(p) for p in pids)
    finally:
        service.stop(final_snapshot=False)
    for pid in pids:
        assert not _alive(pid), f"worker {pid} still runs after stop"


@pytest.mark.slow  # reloc serve with worker processes started and stopped: 17 s in CI
def test_sigterm_of_reloc_serve_leaves_no_process(synthetic_scene, tmp_path):
    """`reloc serve` with worker processes, SIGTERM: it exits 0 and none of its descendants
    (the forkserver, the workers) is left."""
    port = free_port()
    config = tmp_path / "serve.toml"
    config.write_text(f'[zenoh]\nlisten = ["{endpoint(port)}"]\n'
                      f'[service]\ninstance = "procs"\nstorage = ""\nworkers = 2\n'
                      f'worker_mode = "process"\n[maps.{MAP}]\n')
    log = tmp_path / "serve.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", "serve",
                                 "--config", str(config)], cwd=ROOT, stdout=out,
                                stderr=subprocess.STDOUT)
    try:
        scene = synthetic_scene
        with _client_when_served(port, proc, log) as client:
            client.set_camera("cam0", scene.camera, wait=True)
            for kf_id in range(3):
                client.add_keyframe(kf_id, scene.keyframe_images[kf_id],
                                    scene.keyframe_poses[kf_id], camera_id="cam0", wait=True)
            _wait_keyframes(client, 3)
            client.relocalize(scene.query_images[0], camera_id="cam0")
        descendants = _descendants(proc.pid)
        assert len(descendants) >= 2, descendants   # at least the two workers
    finally:
        stop_process(proc)
    assert proc.returncode == 0, log.read_text(errors="replace")[-2000:]
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(_alive(p) for p in descendants):
        time.sleep(0.1)
    assert not [p for p in descendants if _alive(p)], "processes left after SIGTERM"


def _client_when_served(port: int, proc: subprocess.Popen, log: Path) -> RelocClient:
    """A client of the ``reloc serve`` child once it answers a status query."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        assert proc.poll() is None, log.read_text(errors="replace")[-2000:]
        try:
            client = RelocClient(endpoint(port), map=MAP, timeout=60)
        except ConnectionError:   # not listening yet
            time.sleep(0.2)
            continue
        try:
            client.status(timeout=1)
            return client
        except Exception:
            client.close()
            time.sleep(0.2)
    raise AssertionError("reloc serve did not answer within 60 s")


def _wait_keyframes(client: RelocClient, n: int) -> None:
    deadline = time.monotonic() + 60
    while client.status(timeout=10).keyframes < n:
        assert time.monotonic() < deadline, "keyframes not applied within 60 s"
        time.sleep(0.1)


def _alive(pid: int) -> bool:
    """``pid`` runs (a zombie, dead but not yet reaped, does not count)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"


def _descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (children, grandchildren, ...), from /proc."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            parents[int(entry.name)] = int(fields[1])
    found, frontier = [], [pid]
    while frontier:
        current = frontier.pop()
        children = [p for p, pp in parents.items() if pp == current]
        found.extend(children)
        frontier.extend(children)
    return found


def test_stale_replica_directories_of_dead_services_are_removed(tmp_path):
    """A service killed -9 cannot remove its replica bases; the next one removes the
    directories whose pid no longer runs, and keeps those of running services."""
    from reloc_service.service.replica_scratch import SCRATCH_PREFIX, remove_stale_scratch

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    dead = tmp_path / f"{SCRATCH_PREFIX}{gone.pid}-abc"
    live = tmp_path / f"{SCRATCH_PREFIX}{os.getpid()}-def"
    other = tmp_path / "reloc-replicas-notapid"
    for path in (dead, live, other):
        (path / "map-1").mkdir(parents=True)
    assert remove_stale_scratch(tmp_path) == [dead]
    assert not dead.exists() and live.is_dir() and other.is_dir()
