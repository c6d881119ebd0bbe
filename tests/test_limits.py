"""Bounded cost per request and clear errors (fault cases 10-13 and "errors" of
docs/reliability.md), on real Zenoh sessions over loopback: crafted images that declare a huge
size, payloads above the limit, a writer queue bounded in bytes, maps created only by a valid
put, no training from an empty get, malformed keys, protocol version types, client timeouts and
two shards behind the ground-station router."""
# ruff: noqa: E402

from __future__ import annotations

import logging
import threading
from pathlib import Path

import cv2
import msgpack
import numpy as np
import pytest
import zenoh
from reloc_client import cli
from reloc_client import protocol as wire
from reloc_client.client import RelocClient, ServiceError
from service_support import (
    BLOCK,
    CREDENTIALS,
    ROOT,
    Events,
    ServiceProcess,
    endpoint,
    free_port,
    ground_station,
    raw_session,
    service_conf,
    user_client,
    wait_until,
    write_config,
)

from reloc_service.core.cameras import PinholeCamera
from reloc_service.service import codec
from reloc_service.service.app import Service
from reloc_service.service.config import ServiceConf, load_config
from reloc_service.service.workers import WorkerPool

MAP = "lab"
METHOD = "sbi+p3p"
MiB = 1024 * 1024


def upload(client: RelocClient, scene, events: Events, n: int = 4) -> None:
    client.set_camera("cam0", scene.camera)
    events.wait("camera_added", id="cam0")
    for kf_id in range(n):
        client.add_keyframe(kf_id, scene.keyframe_images[kf_id], scene.keyframe_poses[kf_id],
                            camera_id="cam0")
    for kf_id in range(n):
        events.wait("keyframe_added", id=kf_id)


@pytest.fixture(scope="module")
def served(synthetic_scene, tmp_path_factory):
    """An in-process service (storage on disk, new maps allowed, a 16 Mpx pixel limit so the
    map-camera rule is what refuses) with map ``lab`` (4 keyframes, 320x240) and ``empty``."""
    port = free_port()
    storage = tmp_path_factory.mktemp("storage")
    conf = service_conf(port, storage, maps=("empty",), methods=[METHOD],
                        default_method=METHOD, train_on_load=False,
                        limits={"max_image_pixels": 4096 * 4096})
    service = Service(conf).start()
    client = RelocClient(endpoint(port), map=MAP, timeout=30)
    events = Events(client)
    upload(client, synthetic_scene, events)
    yield service, port, client, events, storage
    events.close()
    client.close()
    service.stop()


def flat_image(width: int, height: int, fmt: str) -> bytes:
    """A flat grey image encoded as ``fmt``: tiny bytes that declare ``width`` x ``height``."""
    ok, buf = cv2.imencode(f".{fmt}", np.full((height, width), 128, np.uint8))
    assert ok
    return buf.tobytes()


def inline_camera(width: int, height: int) -> PinholeCamera:
    return PinholeCamera(width=width, height=height, fx=0.8 * width, fy=0.8 * width,
                         cx=width / 2, cy=height / 2)


# -- case 10: a query image bounded by the map's cameras, headers checked before decoding --------

@pytest.mark.slow
def test_inline_query_camera_larger_than_the_maps_cameras_is_refused(served, synthetic_scene):
    _, _, client, _, _ = served
    big = flat_image(640, 480, "png")
    with pytest.raises(ServiceError) as err:
        client.relocalize(wire.WireImage.from_bytes(big), camera=inline_camera(640, 480))
    assert err.value.code is wire.ErrorCode.IMAGE_TOO_LARGE
    assert "largest known camera, 320x240" in err.value.message
    # The map's own size passes the rule (a pose or "not relocalized", never a size error).
    try:
        client.relocalize(synthetic_scene.query_images[0], camera=synthetic_scene.camera)
    except ServiceError as exc:
        assert exc.code is not wire.ErrorCode.IMAGE_TOO_LARGE, exc


def test_decoder_checks_the_header_against_the_camera_before_allocating():
    """A WireImage built past the wire decoder (as a bridge might) whose PNG/JPEG header
    declares 4096x4096 for a 320x240 camera is refused from the header, not decoded."""
    camera = inline_camera(320, 240)
    for fmt in ("png", "jpeg"):
        image = wire.WireImage(wire.ImageFormat(fmt), 320, 240,
                               flat_image(4096, 4096, "jpg" if fmt == "jpeg" else fmt))
        with pytest.raises(wire.ProtocolError) as err:
            codec.decode_image(image, camera, "relocalize.image")
        assert err.value.code is wire.ErrorCode.BAD_IMAGE
        assert "header declares 4096x4096" in err.value.message


def test_a_keyframe_keeps_the_jpeg_or_grey_png_it_was_sent_as(synthetic_scene):
    """The map saves a keyframe's image as the client sent it (a JPEG a third of a PNG of its
    pixels, never re-encoded); raw or colour images are kept as pixels (saved as grey PNG)."""
    from reloc_service.core.frame import EncodedImage

    camera, grey = synthetic_scene.camera, synthetic_scene.keyframe_images[0]
    for fmt, ext in (("jpeg", ".jpg"), ("png", ".png")):
        ok, data = cv2.imencode(ext, grey)
        image = wire.WireImage(wire.ImageFormat(fmt), 320, 240, data.tobytes())
        kept = codec.keyframe_image(image, camera, "keyframe.image")
        assert isinstance(kept, EncodedImage) and kept.tobytes() == data.tobytes()
        assert np.array_equal(kept.decode(), codec.decode_image(image, camera, "keyframe.image"))
    ok, colour = cv2.imencode(".png", cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    kept = codec.keyframe_image(wire.WireImage(wire.ImageFormat.PNG, 320, 240, colour.tobytes()),
                                camera, "keyframe.image")
    assert isinstance(kept, np.ndarray) and np.array_equal(kept, grey)
    raw = codec.keyframe_image(wire.WireImage.from_array(grey), camera, "keyframe.image")
    assert isinstance(raw, np.ndarray) and np.array_equal(raw, grey)


def test_default_pixel_limit_fits_a_companion_computer():
    assert ServiceConf().limits.max_image_pixels == 1280 * 960
    assert load_config(ROOT / "config" / "default.toml") == ServiceConf(), \
        "config/default.toml and the embedded default differ"


def _rss_kb(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise AssertionError(f"no {field} in /proc/{pid}/status")


@pytest.mark.slow
def test_crafted_png_and_jpeg_queries_cost_under_300_mb(synthetic_scene, tmp_path):
    """Crafted images against a service process with the default limits and a trained VGA-less
    (320x240) map: a 16 KB PNG and a small JPEG declaring 4096x4096 with an inline 4096x4096
    camera get IMAGE_TOO_LARGE, and the service's peak resident memory rises < 300 MB."""
    port = free_port()
    config = write_config(tmp_path, port, methods=[METHOD], default_method=METHOD)
    service = ServiceProcess(config, port, tmp_path / "log.txt")
    try:
        client = service.client
        events = Events(client)
        upload(client, synthetic_scene, events, n=len(synthetic_scene.keyframe_images))
        client.train(wait=True, timeout=120)
        pid = service.proc.pid
        Path(f"/proc/{pid}/clear_refs").write_text("5")    # reset the peak (VmHWM)
        idle_kb = _rss_kb(pid, "VmRSS")
        png, jpeg = flat_image(4096, 4096, "png"), flat_image(4096, 4096, "jpg")
        assert len(png) < 100_000 and len(jpeg) < 200_000
        for data in (png, jpeg):
            with pytest.raises(ServiceError) as err:
                client.relocalize(wire.WireImage.from_bytes(data),
                                  camera=inline_camera(4096, 4096), timeout=60)
            assert err.value.code is wire.ErrorCode.IMAGE_TOO_LARGE, err.value
        peak_mb = (_rss_kb(pid, "VmHWM") - idle_kb) / 1024
        print(f"crafted PNG + JPEG queries: service peak +{peak_mb:.0f} MB")
        assert peak_mb < 300, f"peak resident memory +{peak_mb:.0f} MB"
        events.close()
    finally:
        service.terminate()


# -- case 11: payload size before the copy, the writer bounded in bytes ---------------------------

def test_worker_pool_is_bounded_in_bytes():
    gate = threading.Event()
    pool = WorkerPool("w", workers=1, queue_size=100, max_bytes=100)
    try:
        assert pool.submit(lambda _q: gate.wait(10), size=60)   # runs, holds 60 bytes
        assert not pool.submit(lambda _q: None, size=60)        # 120 > 100: refused at once
        assert pool.submit(lambda _q: None, size=40)
        assert pool.submit(lambda _q: None)                     # callers without a size
        assert pool.held_bytes == 100
        gate.set()
        assert pool.join(10) and pool.held_bytes == 0
        assert pool.submit(lambda _q: None, size=500)           # alone: always admitted
        assert pool.join(10)
    finally:
        gate.set()
        pool.close()


def test_puts_beyond_the_writers_byte_budget_are_rejected_busy(served):
    """The map's writer blocked (a job holding it), 10 puts of 20 MiB: the default 128 MiB
    budget takes 6, the others get BUSY at once instead of 200 MiB waiting in memory."""
    service, port, _, events, _ = served
    gate = threading.Event()
    writer = service._writer_for(MAP)
    assert writer.submit(lambda _q: gate.wait(60))
    payload = b"\x00" * (20 * MiB)
    try:
        with raw_session(port) as session:
            for kf_id in range(1000, 1010):
                session.put(wire.keys.keyframe("reloc", MAP, kf_id), payload,
                            congestion_control=zenoh.CongestionControl.BLOCK)
            busy = [events.wait("keyframe_rejected", id=kf_id, code="BUSY", timeout=30)
                    for kf_id in range(1006, 1010)]
        assert len(busy) == 4
        assert writer.held_bytes <= service.conf.service.writer_queue_bytes
    finally:
        gate.set()
    assert service.wait_idle(60)


def test_oversized_put_and_query_are_refused_before_the_copy(served):
    service, port, client, events, _ = served
    limit = service.limits.max_payload_bytes
    too_big = b"\x00" * (limit + 1)
    with raw_session(port) as session:
        session.put(wire.keys.keyframe("reloc", MAP, 77), too_big,
                    congestion_control=zenoh.CongestionControl.BLOCK)
        event = events.wait("keyframe_rejected", id=77, code="PAYLOAD_TOO_LARGE")
        assert f"expected at most {limit}" in event.fields["message"]
        replies = list(session.get(wire.keys.relocalize("reloc", MAP), payload=too_big,
                                   timeout=30))
    assert len(replies) == 1 and replies[0].err is not None
    err = wire.ErrorReply.decode(replies[0].err.payload.to_bytes())
    assert err.code is wire.ErrorCode.PAYLOAD_TOO_LARGE


@pytest.mark.slow
def test_an_oversized_put_is_not_copied_by_the_service(tmp_path):
    """A 256 MiB put (limit 32 MiB) on a service process: Zenoh itself reassembles the message
    (+256 MiB, unavoidable at this end), the service refuses it from its length without a
    Python copy, so the peak stays under 1.5 x the payload (it was 2 x and more)."""
    port = free_port()
    service = ServiceProcess(write_config(tmp_path, port), port, tmp_path / "log.txt")
    try:
        events = Events(service.client)
        pid = service.proc.pid
        Path(f"/proc/{pid}/clear_refs").write_text("5")
        idle_kb = _rss_kb(pid, "VmRSS")
        with raw_session(port) as session:
            session.put(wire.keys.keyframe("reloc", "lab", 5), b"\x00" * (256 * MiB),
                        congestion_control=zenoh.CongestionControl.BLOCK)
            events.wait("keyframe_rejected", id=5, code="PAYLOAD_TOO_LARGE", timeout=60)
        peak_mb = (_rss_kb(pid, "VmHWM") - idle_kb) / 1024
        print(f"256 MiB put: service peak +{peak_mb:.0f} MB")
        assert peak_mb < 384, f"peak resident memory +{peak_mb:.0f} MB"
        events.close()
    finally:
        service.terminate()


# -- case 12: a map only from a valid put ---------------------------------------------------------

def test_garbage_on_new_map_names_creates_nothing(served, synthetic_scene):
    service, port, _, _, storage = served
    rejected: list[wire.Event] = []
    with raw_session(port) as session:
        sub = session.declare_subscriber(
            "reloc/*/events", lambda s: rejected.append(wire.Event.decode(s.payload.to_bytes())))

        def send(key: str, payload: bytes) -> None:
            # Block rather than drop under congestion: a dropped put would be Zenoh's
            # choice, not the service's, and this test is about what the service does.
            session.put(key, payload, congestion_control=BLOCK)

        try:
            # Zenoh routes a new subscriber asynchronously: events the service publishes before
            # it knows this one are lost. Probe (garbage too) until a rejection is heard.
            def heard() -> bool:
                send(wire.keys.keyframe("reloc", "junkprobe", 1), b"\xc1garbage")
                return any(e.map == "junkprobe" for e in rejected)
            wait_until(heard, timeout=20, interval=0.2)
            for i in range(20):
                send(wire.keys.keyframe("reloc", f"junk{i}", 1), b"\xc1garbage")
            send(wire.keys.camera("reloc", "junkcam", "c0"), b"\xc1garbage")
            session.delete(wire.keys.keyframe("reloc", "junkdel", 3), congestion_control=BLOCK)
            # A valid first put (inline camera) still creates its map.
            put = wire.KeyframePut(
                id=0, image=wire.WireImage.from_array(synthetic_scene.keyframe_images[0]),
                world_from_cam=wire.WirePose.from_matrix(synthetic_scene.keyframe_poses[0]),
                camera=wire.WireCamera.from_dict(synthetic_scene.camera.to_dict()))
            send(wire.keys.keyframe("reloc", "fresh", 0), put.encode())
            assert service.wait_idle(30)
            wait_until(lambda: sum(e.map != "junkprobe" for e in rejected) >= 22, timeout=20)
        finally:
            sub.undeclare()
    junk = [m for m in service.maps if m.startswith("junk")]
    assert junk == [], f"maps created by garbage: {junk}"
    assert not [p.name for p in storage.iterdir() if p.name.startswith("junk")]
    kinds = {(e.map, e.kind.value, e.fields.get("code")) for e in rejected}
    for i in range(20):
        assert (f"junk{i}", "keyframe_rejected", "BAD_MSGPACK") in kinds
    assert ("junkcam", "camera_rejected", "BAD_MSGPACK") in kinds
    assert ("junkdel", "keyframe_rejected", "UNKNOWN_MAP") in kinds
    # its own writer (one per map) may still be applying it: wait for the map, not the others
    wait_until(lambda: "fresh" in service.maps, timeout=30)
    assert (storage / "fresh").is_dir()


# -- case 13: an empty payload is not a train request; the companion example on loopback ---------

def test_an_empty_get_on_everything_trains_nothing(served):
    service, port, client, events, _ = served
    with raw_session(port) as session:
        replies = list(session.get("reloc/**", timeout=20,
                                   consolidation=zenoh.ConsolidationMode.NONE))
        train_replies = list(session.get(wire.keys.train("reloc", MAP), timeout=20))
    assert replies, "the get reached the service"
    errors = [wire.ErrorReply.decode(r.err.payload.to_bytes()) for r in train_replies]
    assert [e.code for e in errors] == [wire.ErrorCode.MISSING_FIELD]
    assert "empty payload is not a train request" in errors[0].message
    assert not client.status().training
    assert not [e for e in events.drain() if e.kind.value == "train_started"]
    assert not any(rt.status().training for rt in service.maps.values())


def test_companion_example_listens_on_loopback_only():
    conf = load_config(ROOT / "config" / "companion.toml")
    assert conf.zenoh.listen and all(ep.startswith(("tcp/127.0.0.1:", "tcp/[::1]:"))
                                     for ep in conf.zenoh.listen), conf.zenoh.listen


# -- unclear errors made clear ------------------------------------------------------------------

def test_keyframes_of_an_empty_map_is_an_empty_list(served):
    _, port, _, _, _ = served
    with RelocClient(endpoint(port), map="empty", timeout=10) as client:
        assert client.keyframes() == []


def test_malformed_keyframe_ids_get_a_rejected_event(served):
    _, port, _, events, _ = served
    with raw_session(port) as session:
        for leaf in ("007", "-1", str(2**63), "abc"):
            session.put(f"reloc/{MAP}/keyframes/{leaf}", b"x")
        for leaf in ("007", "-1", str(2**63), "abc"):
            event = events.wait("keyframe_rejected", id=leaf, code="BAD_NAME")
            assert "keyframe" in event.fields["message"]


def test_malformed_map_names_are_warned_once_per_key(served, caplog):
    _, port, _, events, _ = served
    long_name = "m" * 129
    keys = [f"reloc/{long_name}/keyframes/1", f"reloc/{long_name}/cameras/c"]
    caplog.set_level(logging.WARNING, logger="reloc_service.service.app")
    with raw_session(port) as session:
        for _ in range(3):
            for key in keys:
                session.put(key, b"x")
        # A valid put after them on the same link: once it is rejected, the others were seen.
        session.put(wire.keys.keyframe("reloc", MAP, 4242), b"x")
        events.wait("keyframe_rejected", id=4242)
    for key in keys:
        warnings = [r for r in caplog.records if key in r.getMessage()]
        assert len(warnings) == 1, [r.getMessage() for r in warnings]
        assert "at most 128 characters" in warnings[0].getMessage()
        assert warnings[0].levelno == logging.WARNING


def test_protocol_version_must_be_the_integer_1():
    for v in (1.0, True):
        data = msgpack.packb({"v": v}, use_bin_type=True)
        with pytest.raises(wire.ProtocolError) as err:
            wire.TrainRequest.decode(data)
        assert err.value.code is wire.ErrorCode.UNSUPPORTED_VERSION
    assert wire.TrainRequest.decode(msgpack.packb({"v": 1})) == wire.TrainRequest()


def test_client_timeouts_must_be_positive(served, synthetic_scene):
    _, _, client, _, _ = served
    for bad in (0, -1.0):
        with pytest.raises(ValueError, match="positive number of seconds"):
            client.relocalize(synthetic_scene.query_images[0], camera_id="cam0", timeout=bad)
        with pytest.raises(ValueError, match="positive number of seconds"):
            client.keyframes(timeout=bad)
        with pytest.raises(ValueError, match="positive number of seconds"):
            client.status(timeout=bad)
    assert client.status(timeout=None).map == MAP


def test_cli_timeout_zero_is_a_usage_error(capsys):
    for argv in (["--timeout", "0", "--map", "x", "status"],
                 ["--map", "x", "train", "--wait", "--train-timeout", "-5"]):
        with pytest.raises(SystemExit) as exit_:
            cli.main(argv)
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert "expected a positive number of seconds" in err and "Traceback" not in err


def test_a_shard_behind_the_router_does_not_reject_another_shards_map(synthetic_scene,
                                                                      tmp_path):
    """deploy/ground: shard B (map drone2) must not answer drone1's puts on map drone1 with
    UNKNOWN_MAP, though the router's deny-by-default rules hide liveliness from it; a put on a
    map nobody serves is still rejected (by both shards)."""
    with ground_station(tmp_path) as ep:
        with user_client(ep, "drone1", "drone1", CREDENTIALS["drone1"], timeout=10) as drone1, \
                user_client(ep, "nobody", "ground", CREDENTIALS["ground"],
                            timeout=10) as ground:
            mine, nobody = Events(drone1), Events(ground)
            drone1.set_camera("cam1", synthetic_scene.camera)
            mine.wait("camera_added", id="cam1")
            ground.set_camera("cam9", synthetic_scene.camera)   # after drone1's, same writers
            # Both shards reject it, each after it has handled drone1's earlier put.
            wait_until(lambda: len([e for e in nobody.drain()
                                    if e.kind.value == "camera_rejected"]) == 2, timeout=30)
            rejected = [e for e in mine.drain() if e.kind.value == "camera_rejected"]
            assert rejected == [], [dict(e.fields) for e in rejected]
            mine.close()
            nobody.close()
