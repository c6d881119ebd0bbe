"""Reliability, bounded in time, on loopback: bad input (property-based and fuzzed payloads on
the wire decoder, the handlers and every queryable: each gets an error reply, none crashes or
stalls the service), load (clients x queries while keyframes stream in: no unexpected error,
bounded p99 and memory, explicit "busy" under overload), faults (kill -9 during training,
router restart) and storage that cannot be written (a clear error, not a crash).

kill -9 during an upload and the survival of trained models are in
test_service_durability.py; they are not repeated here."""
# ruff: noqa: E402

from __future__ import annotations

import copy
import errno
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from reloc_client import protocol as wire
from reloc_client.client import NoReplyError, RelocClient, ServiceBusy, ServiceError
from reloc_client.protocol import ErrorCode, ProtocolError
from service_support import (
    BLOCK,
    ROOT,
    Events,
    endpoint,
    free_port,
    raw_session,
    service_conf,
    stop_process,
    wait_until,
)

from reloc_service.core.errors import StorageError
from reloc_service.service import codec, handlers
from reloc_service.service.app import Service
from reloc_service.storage import journal

MAP = "lab"
FUZZ = settings(max_examples=150, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow, HealthCheck.data_too_large])


@pytest.fixture(scope="module")
def served(synthetic_scene, tmp_path_factory):
    """A service (in memory, small limits) whose map has a camera and two keyframes."""
    port = free_port()
    scene = synthetic_scene
    conf = service_conf(port, "", maps=(MAP,), workers=2, queue_size=8,
                        limits={"max_payload_bytes": 1 << 20, "max_image_pixels": 640 * 480})
    with Service(conf) as service:
        service.on_camera_sample(MAP, "cam0", wire.CameraPut(
            "cam0", wire.WireCamera.from_dict(scene.camera.to_dict())).encode())
        for kf_id in range(2):
            service.on_keyframe_sample(MAP, kf_id, _keyframe_put(scene, kf_id))
        assert service.wait_idle(60)
        assert len(service.maps[MAP].map_state().keyframes) == 2
        yield service, port, scene


def _keyframe_put(scene, kf_id: int) -> bytes:
    return wire.KeyframePut(id=kf_id, image=wire.WireImage.from_array(
        scene.keyframe_images[kf_id]), world_from_cam=wire.WirePose.from_matrix(
        scene.keyframe_poses[kf_id]), camera_id="cam0").encode()


def _valid_request(scene) -> dict:
    ok, png = cv2.imencode(".png", scene.query_images[0])
    h, w = scene.query_images[0].shape
    return {"v": 1, "camera_id": "cam0", "request_id": "r",
            "image": {"format": "png", "width": w, "height": h, "data": png.tobytes()}}


# -- payload strategies -----------------------------------------------------------------------

_scalars = st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1),
                     st.floats(allow_nan=True), st.text(max_size=20), st.binary(max_size=64))
_values = st.recursive(_scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=8), inner, max_size=4)),
    max_leaves=12)


def _paths(d: dict, prefix: tuple = ()) -> list[tuple]:
    out = []
    for k, v in d.items():
        out.append((*prefix, k))
        if isinstance(v, dict):
            out.extend(_paths(v, (*prefix, k)))
    return out


BASES: dict[str, dict] = {}   # valid messages by name (kept out of Hypothesis' reprs)


@st.composite
def bad_requests(draw, name: str) -> bytes:
    """The valid message ``BASES[name]`` broken in one of many ways."""
    base = BASES[name]
    kind = draw(st.sampled_from(["random", "msgpack", "truncated", "type", "drop",
                                 "corrupt_image", "huge_image", "bad_numbers"]))
    if kind in ("corrupt_image", "huge_image") and "image" not in base:
        kind = "type"
    if kind == "random":
        return draw(st.binary(max_size=512))
    if kind == "msgpack":
        return msgpack.packb(draw(_values), use_bin_type=True)
    packed = msgpack.packb(base, use_bin_type=True)
    if kind == "truncated":
        return packed[:draw(st.integers(0, len(packed) - 1))]
    request = copy.deepcopy(base)
    path = draw(st.sampled_from(_paths(base)))
    parent = request
    for k in path[:-1]:
        parent = parent[k]
    if kind == "type":
        parent[path[-1]] = draw(_values)
    elif kind == "drop":
        del parent[path[-1]]
    elif kind == "corrupt_image":
        data = bytearray(request["image"]["data"])
        start = draw(st.integers(0, len(data) - 1))
        data[start:start + 64] = draw(st.binary(min_size=1, max_size=64))
        request["image"]["data"] = bytes(data[:draw(st.integers(1, len(data)))])
    elif kind == "huge_image":
        request["image"].update(width=draw(st.integers(641, 2**31)),
                                height=draw(st.integers(481, 2**31)))
    else:
        request[draw(st.sampled_from(["hypotheses", "timestamp", "prior"]))] = draw(
            st.sampled_from([float("nan"), float("inf"), -1, 2**64 - 1, {"radius_m": -1.0}]))
    return msgpack.packb(request, use_bin_type=True)


def _expect_clean_error(call) -> str:
    """Run ``call``; a reply is fine, an exception must map to a protocol error code other
    than INTERNAL (an unexpected exception is a bug)."""
    try:
        call()
        return "reply"
    except Exception as exc:  # noqa: BLE001 - every exception is classified
        code, message = codec.error_of(exc)
        assert code is not ErrorCode.INTERNAL, f"unexpected {type(exc).__name__}: {exc}"
        assert message
        return code.value


COUNTS: dict[str, int] = {}


def test_fuzz_the_relocalize_handler(served):
    service, _, scene = served
    rt = service.maps[MAP]
    BASES["relocalize"] = _valid_request(scene)

    @FUZZ
    @given(payload=bad_requests("relocalize"))
    def run(payload: bytes) -> None:
        COUNTS["relocalize"] = COUNTS.get("relocalize", 0) + 1
        _expect_clean_error(lambda: handlers.relocalize(rt, payload))

    run()
    assert COUNTS["relocalize"] >= 100


def test_fuzz_keyframe_and_camera_puts_and_train(served):
    service, _, scene = served
    rt = service.maps[MAP]
    BASES["keyframe"] = msgpack.unpackb(_keyframe_put(scene, 0), raw=False)
    BASES["camera"] = msgpack.unpackb(wire.CameraPut("cam9", wire.WireCamera.from_dict(
        scene.camera.to_dict())).encode(), raw=False)

    @FUZZ
    @given(kf=bad_requests("keyframe"), cam=bad_requests("camera"), raw=st.binary(max_size=256))
    def run(kf: bytes, cam: bytes, raw: bytes) -> None:
        COUNTS["puts"] = COUNTS.get("puts", 0) + 3
        _expect_clean_error(lambda: codec.decode_keyframe_put(rt, 0, kf))
        _expect_clean_error(lambda: codec.decode_camera_put("cam9", cam, rt.limits))
        _expect_clean_error(lambda: wire.TrainRequest.decode(raw, rt.limits))

    run()


@settings(max_examples=300, deadline=None, derandomize=True)
@given(payload=st.one_of(st.binary(max_size=300), _values.map(
    lambda v: msgpack.packb(v, use_bin_type=True))))
def test_wire_decoder_refuses_garbage_with_protocol_errors(payload):
    for message in (wire.RelocalizeRequest, wire.KeyframePut, wire.CameraPut,
                    wire.TrainRequest, wire.StatusReply, wire.RelocalizeReply, wire.Event):
        try:
            message.decode(payload, wire.DEFAULT_LIMITS)
        except ProtocolError as exc:
            assert exc.code in ErrorCode and exc.message


def test_fuzz_every_queryable_over_zenoh(served):
    """Junk on every queryable and every put key: each query gets an error reply in time, the
    service keeps answering, and its put rejections are events, not crashes."""
    service, port, scene = served
    rng = np.random.default_rng(0)
    base = _valid_request(scene)
    payloads = [rng.bytes(int(n)) for n in rng.integers(0, 400, 12)]
    payloads += [msgpack.packb(base, use_bin_type=True)[:int(n)]
                 for n in rng.integers(1, 2000, 6)]
    payloads += [msgpack.packb({**base, "image": {**base["image"], "width": 10**6}}),
                 msgpack.packb({**base, "camera_id": 12}),
                 msgpack.packb({**base, "image": {**base["image"], "data": b"\x89PNG junk"}}),
                 b"\x00" * ((1 << 20) + 1)]                 # over max_payload_bytes
    replies: dict[str, int] = {}
    with raw_session(port) as session:
        for kind in ("relocalize", "train", "status"):
            for payload in payloads:
                got = list(session.get(f"reloc/{MAP}/{kind}", payload=payload, timeout=20))
                assert len(got) == 1, (kind, payload[:20])
                outcome = "ok" if got[0].ok is not None else "error"
                if outcome == "error":
                    err = wire.ErrorReply.decode(got[0].err.payload.to_bytes())
                    assert err.code is not ErrorCode.INTERNAL, err
                replies[f"{kind}:{outcome}"] = replies.get(f"{kind}:{outcome}", 0) + 1
        assert replies.get("relocalize:ok", 0) == 0 and replies.get("train:ok", 0) == 0
        for i, payload in enumerate(payloads[:8]):
            session.put(f"reloc/{MAP}/keyframes/{100 + i}", payload, congestion_control=BLOCK)
            session.put(f"reloc/{MAP}/cameras/junk{i}", payload, congestion_control=BLOCK)
        session.put(f"reloc/{MAP}/keyframes/not-a-number", b"x", congestion_control=BLOCK)
        for kind in ("keyframes", "cameras"):   # map copies still work
            assert len(list(session.get(f"reloc/{MAP}/{kind}/**", timeout=20))) >= 1
    rt = service.maps[MAP]
    # the puts reach the service through its subscribers, in no order with the queries
    # above: wait for their rejections rather than take the last get as proof they arrived
    wait_until(lambda: rt.stats.counters["rejected"] >= 16, timeout=60)
    assert service.wait_idle(30)
    assert len(rt.map_state().keyframes) == 2 and rt.camera_ids() == ["cam0"]
    with RelocClient(endpoint(port), map=MAP, timeout=30) as client:
        assert client.status().keyframes == 2
        result = client.relocalize(scene.query_images[0], camera_id="cam0")
        assert result.ok, result.reason
    n = sum(replies.values()) + 17
    print(f"\nbad inputs over zenoh: {n} ({replies}), crashes 0; handler fuzz {COUNTS}")


# -- overload and load ------------------------------------------------------------------------

def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _hammer(port: int, scene, clients: int, seconds: float, stream: bool = False
            ) -> tuple[list[float], dict[str, int]]:
    """``clients`` threads relocalizing for ``seconds`` (optionally while keyframes stream
    in); round-trip times of answered queries and outcome counts."""
    latencies: list[float] = []
    outcomes: dict[str, int] = {}
    lock = threading.Lock()
    stop = time.monotonic() + seconds

    def worker(i: int) -> None:
        with RelocClient(endpoint(port), map=MAP, timeout=30) as c:
            k = i
            while time.monotonic() < stop:
                t0 = time.perf_counter()
                try:
                    r = c.relocalize(scene.query_images[k % 3], camera_id="cam0")
                    kind = "ok" if r.ok else "not_relocalized"
                except ServiceBusy:
                    kind = "busy"
                except (ServiceError, NoReplyError) as exc:
                    kind = f"error:{exc}"
                dt = time.perf_counter() - t0
                with lock:
                    outcomes[kind] = outcomes.get(kind, 0) + 1
                    if kind != "busy":
                        latencies.append(dt)
                if kind == "busy":
                    time.sleep(0.01)
                k += 1

    def streamer() -> None:
        with RelocClient(endpoint(port), map=MAP) as c:
            kf_id = 1000
            while time.monotonic() < stop:
                i = kf_id % len(scene.keyframe_images)
                c.add_keyframe(kf_id, scene.keyframe_images[i], scene.keyframe_poses[i],
                               camera_id="cam0")
                kf_id += 1
                time.sleep(0.5)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(clients)]
    if stream:
        threads.append(threading.Thread(target=streamer))
    for t in threads:
        t.start()
    for t in threads:
        t.join(seconds + 120)
    return latencies, outcomes


def test_overload_is_answered_busy_at_once(synthetic_scene):
    scene = synthetic_scene
    port = free_port()
    with Service(service_conf(port, "", maps=(MAP,), workers=1, queue_size=1)) as service:
        service.on_camera_sample(MAP, "cam0", wire.CameraPut(
            "cam0", wire.WireCamera.from_dict(scene.camera.to_dict())).encode())
        for kf_id in range(3):
            service.on_keyframe_sample(MAP, kf_id, _keyframe_put(scene, kf_id))
        assert service.wait_idle(60)
        latencies, outcomes = _hammer(port, scene, clients=6, seconds=2.0)
    assert outcomes.get("busy", 0) > 0, outcomes
    assert not [k for k in outcomes if k.startswith("error")], outcomes
    assert outcomes.get("ok", 0) > 0
    print(f"\noverload (1 worker, queue 1, 6 clients, 2 s): {outcomes}, answered p99 "
          f"{np.percentile(latencies, 99) * 1e3:.0f} ms")


@pytest.mark.slow
def test_load_clients_queries_and_streaming_keyframes(served):
    service, port, scene = served
    rss_before = _rss_mb()
    seconds, clients = 15.0, 4
    latencies, outcomes = _hammer(port, scene, clients=clients, seconds=seconds, stream=True)
    assert service.wait_idle(60)
    rss_after = _rss_mb()
    answered = len(latencies)
    p50, p99 = np.percentile(latencies, [50, 99])
    print(f"\nload: {clients} clients x {seconds:.0f} s while keyframes stream in: "
          f"{answered} answered ({answered / seconds:.1f} queries/s), busy "
          f"{outcomes.get('busy', 0)}, p50 {p50 * 1e3:.0f} ms, p99 {p99 * 1e3:.0f} ms, "
          f"outcomes {outcomes}, RSS {rss_before:.0f} -> {rss_after:.0f} MB "
          f"(service + clients in this process)")
    assert not [k for k in outcomes if k.startswith("error")], outcomes
    assert outcomes.get("ok", 0) >= answered * 0.9
    assert p99 < 5.0
    assert rss_after - rss_before < 300


# -- storage that cannot be written -----------------------------------------------------------

def test_storage_under_a_file_is_a_clear_error(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    for storage in (blocker / "maps", Path("/proc/reloc-maps")):
        service = Service(service_conf(free_port(), storage, maps=(MAP,)))
        with pytest.raises(StorageError, match="storage directory"):
            service.start()
        service.stop(final_snapshot=False)


def test_disk_full_rejects_puts_with_storage_error_then_recovers(synthetic_scene, tmp_path,
                                                                 monkeypatch):
    scene = synthetic_scene
    port = free_port()
    with Service(service_conf(port, tmp_path / "storage", maps=(MAP,))) as service, \
            RelocClient(endpoint(port), map=MAP, timeout=20) as client:
        events = Events(client)
        client.set_camera("cam0", scene.camera)
        events.wait("camera_added", id="cam0")

        def no_space(fd: int, data: bytes) -> None:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        monkeypatch.setattr(journal, "_write_all", no_space)
        client.add_keyframe(0, scene.keyframe_images[0], scene.keyframe_poses[0],
                            camera_id="cam0")
        rejected = events.wait("keyframe_rejected", id=0)
        assert rejected.fields["code"] == "STORAGE_ERROR"
        assert "No space left on device" in rejected.fields["message"]
        assert client.status().keyframes == 0        # not applied: it is not durable
        monkeypatch.undo()
        client.add_keyframe(0, scene.keyframe_images[0], scene.keyframe_poses[0],
                            camera_id="cam0")
        events.wait("keyframe_added", id=0)
        assert client.status().keyframes == 1
        events.close()
    assert service.maps[MAP].stats.counters["rejected"] == 1


# -- process faults ---------------------------------------------------------------------------

def _spawn(args: list[str], log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "reloc_service.cli.main", *args], cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)},
                            stdout=open(log, "ab"), stderr=subprocess.STDOUT)


def _stop(proc: subprocess.Popen) -> None:
    stop_process(proc, signal.SIGINT)


def _client(port: int) -> RelocClient | None:
    try:
        return RelocClient(endpoint(port), map=MAP, timeout=10)
    except ConnectionError:
        return None


def _answers(client: RelocClient):
    try:
        return client.status(timeout=2)
    except (NoReplyError, ServiceError):
        return None


def _restored(client: RelocClient):
    """The map's status once it answers and its journal backlog has replayed."""
    status = _answers(client)
    return status if status is not None and not status.replaying else None


@pytest.mark.slow
def test_kill_9_during_training_then_restart_restores_everything(synthetic_scene, tmp_path):
    scene = synthetic_scene
    port = free_port()
    config = tmp_path / "service.toml"   # two methods: training takes a while
    config.write_text('[service]\nmethods = ["sbi+p3p", "bow+p3p"]\n'
                      'default_method = "sbi+p3p"\n')
    args = ["serve", "--config", str(config), "--listen", endpoint(port), "--storage",
            str(tmp_path / "s"), "--instance", "trainee"]
    service = _spawn(args, tmp_path / "log1.txt")
    try:
        client = wait_until(lambda: _client(port), timeout=60, interval=0.2)
        events = Events(client)
        client.set_camera("cam0", scene.camera)
        n = len(scene.keyframe_images)
        for kf_id in range(n):
            client.add_keyframe(kf_id, scene.keyframe_images[kf_id], scene.keyframe_poses[kf_id],
                                camera_id="cam0")
        events.wait("keyframe_added", id=n - 1, timeout=60)
        before = client.status().keyframes
        assert client.train().accepted
        service.send_signal(signal.SIGKILL)             # in the middle of training
        service.wait(10)
        trained_before_kill = any(e.kind.value == "train_done" for e in events.drain())
        client.close()
    finally:
        if service.poll() is None:
            service.kill()
    service = _spawn(args, tmp_path / "log2.txt")
    try:
        client = wait_until(lambda: _client(port), timeout=60, interval=0.2)
        status = wait_until(lambda: _restored(client), timeout=60)
        assert status.keyframes == before == n
        # train_on_load: the restarted service trains again; the models come back
        wait_until(lambda: (_answers(client) or status).trained, timeout=240, interval=0.5)
        result = client.relocalize(scene.query_images[0], camera_id="cam0")
        assert result.ok, result.reason
        print(f"\nkill -9 during training (finished before the kill: {trained_before_kill}): "
              f"keyframes {before} before, {status.keyframes} after; trained again on load")
        client.close()
    finally:
        _stop(service)


@pytest.mark.slow
def test_router_restart_clients_and_service_reconnect(synthetic_scene, tmp_path):
    scene = synthetic_scene
    port = free_port()
    router = _spawn(["router", "--listen", endpoint(port)], tmp_path / "router1.txt")
    service = None
    try:
        client = wait_until(lambda: _client(port), timeout=30, interval=0.2)
        service = _spawn(["serve", "--mode", "client", "--connect", endpoint(port), "--storage",
                          str(tmp_path / "s"), "--instance", "behind"], tmp_path / "svc.txt")

        def camera_put_answered():   # the map appears with a put once the service is there
            client.set_camera("cam0", scene.camera)
            return _answers(client)

        wait_until(camera_put_answered, timeout=60, interval=0.5)
        client.add_keyframe(0, scene.keyframe_images[0], scene.keyframe_poses[0],
                            camera_id="cam0")
        wait_until(lambda: (_answers(client) or wire).__dict__.get("keyframes") == 1,
                   timeout=30)
        router.send_signal(signal.SIGKILL)
        router.wait(10)
        time.sleep(1.0)
        assert _answers(client) is None                # nothing routes now
        router = _spawn(["router", "--listen", endpoint(port)], tmp_path / "router2.txt")
        status = wait_until(lambda: _answers(client), timeout=60, interval=0.5)
        assert status.keyframes == 1 and service.poll() is None
        client.add_keyframe(1, scene.keyframe_images[1], scene.keyframe_poses[1],
                            camera_id="cam0")
        wait_until(lambda: (_answers(client) or status).keyframes == 2, timeout=30)
        print("\nrouter restart: keyframes 1 before, 2 after (one put after the restart)")
        client.close()
    finally:
        if service is not None:
            _stop(service)
        _stop(router)
