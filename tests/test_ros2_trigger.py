"""The Trigger answers for the image asked about, the latched pose and CameraInfo, and
/diagnostics, driven over real Zenoh sessions through a router by the ROS 2 stand-in
(tests/ros2_standin.py, which parses CDR itself and imports nothing of reloc's ROS 2 code)."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
from ros2_standin import (
    HASH,
    camera_info,
    compressed_image,
    odometry,
    parse_attachment,
    read_pose,
    read_trigger_response,
    rosbags_hash,
)
from ros2_standin_latched import ROSOUT_HASH, ROSOUT_QOS, LatchingStandIn, read_diagnostic_array, read_log
from ros2_support import CIMG, body_from_cam, feed_map, pngs, stamp, start_service
from service_support import endpoint, free_port, open_router, wait_until

from reloc_service.core.errors import ConfigError
from reloc_service.service.ros2 import types as ros
from reloc_service.service.ros2.conf import Ros2Conf

POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
DIAG = "diagnostic_msgs/msg/DiagnosticArray"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMAGE_TOPIC = "/camera/image_raw/compressed"


def stamp_of(t: tuple[int, int]) -> str:
    return f"{t[0]}.{t[1]:09d}"


def trigger(drone: LatchingStandIn, seq: int) -> tuple[bool, str]:
    [(payload, att)] = drone.call_trigger("/reloc/trig/relocalize", seq=seq)
    assert att is not None and parse_attachment(att) == (seq, drone.gid)
    return read_trigger_response(payload)


def publish_image(drone: LatchingStandIn, t: tuple[int, int], png: bytes) -> None:
    drone.publish(IMAGE_TOPIC, CIMG, HASH[CIMG], compressed_image(t, "camera", "png", png))


@pytest.fixture(scope="module")
def rig(synthetic_scene):
    """A service with map ``trig`` built from the scene's keyframes over ROS 2, and a drone
    subscribed to /diagnostics; (service, drone, diagnostics queue, log records)."""
    records: list[logging.LogRecord] = []
    handler = logging.Handler(logging.INFO)
    handler.emit = records.append  # type: ignore[method-assign]
    logger = logging.getLogger("reloc_service.service.ros2")
    logger.addHandler(handler)
    previous = logger.level
    logger.setLevel(logging.INFO)
    port = free_port()
    with open_router(port):
        service = start_service(port, "trig", trigger_wait_s=1.0, max_image_age_s=1.0,
                                diagnostics_period_s=0.5, relocalize_every_n=1)
        drone = LatchingStandIn(endpoint(port))
        try:
            diagnostics = drone.subscribe("/diagnostics", DIAG, rosbags_hash(DIAG))
            drone.subscribe_poses("/reloc/trig/pose")
            wait_until(lambda: any("/SS/" in t for t in drone.graph()))
            scene = synthetic_scene
            feed_map(drone, scene.camera.to_dict(), list(zip(
                pngs(scene.keyframe_images), scene.keyframe_poses, strict=True)),
                repeat_nearby=False)
            rt = service.maps["trig"]
            wait_until(lambda: len(rt.map_state().keyframes) == 6, timeout=60)
            [png] = pngs(scene.query_images[:1])   # the workers load the map once, here
            publish_image(drone, stamp(900.0), png)
            # received before the call: the call then answers for it, not for the last
            # keyframe image (also fresh and unanswered when the machine is slow)
            node = service.ros2.node("trig")
            wait_until(lambda: node.latest is not None and node.latest.stamp.sec == 900)
            success, message = trigger(drone, 1)
            assert success and message.startswith("image stamped 900.000000000: "), message
            assert read_pose(drone.poses.get(timeout=10)[0]).stamp == stamp(900.0)
            assert drone.poses.empty()
            yield service, drone, diagnostics, records
        finally:
            drone.close()
            service.stop()
            logger.removeHandler(handler)
            logger.setLevel(previous)


def test_forty_triggers_each_answer_for_the_image_just_published(rig, synthetic_scene):
    """Each call goes out right after its image (no wait for reloc to receive it): the
    reply names that image's stamp, and a published pose carries it."""
    service, drone, _diag, _records = rig
    queries = pngs(synthetic_scene.query_images)
    answered = []
    for i in range(40):
        t = stamp(1000.0 + 0.1 * i)
        publish_image(drone, t, queries[i % len(queries)])
        success, message = trigger(drone, 100 + i)
        assert message.startswith(f"image stamped {stamp_of(t)}: "), (i, message)
        if success:
            assert read_pose(drone.poses.get(timeout=10)[0]).stamp == t
        answered.append(success)
    assert sum(answered) >= 30, answered   # the scene's queries relocalize
    # how many calls arrived before their image (they waited for it)
    print(f"\n40 Trigger calls: {service.ros2.node('trig').triggers.waited} waited for their "
          f"image, {sum(answered)} relocalized")


def test_a_corrupt_image_then_trigger_fails_naming_it(rig, synthetic_scene):
    service, drone, _diag, _records = rig
    [png] = pngs(synthetic_scene.query_images[:1])
    publish_image(drone, stamp(2000.0), png)          # a good image, answered
    assert trigger(drone, 201)[0]
    drone.poses.get(timeout=10)
    # cut short: refused when it arrives
    publish_image(drone, stamp(2001.0), png[: len(png) // 2])
    success, message = trigger(drone, 202)
    assert not success
    assert message == ("image stamped 2001.000000000 was rejected: the PNG file is cut short "
                       "(it does not end with the IEND chunk)"), message
    # not an image at all
    publish_image(drone, stamp(2002.0), b"not a png")
    success, message = trigger(drone, 203)
    assert not success and message.startswith("image stamped 2002.000000000 was rejected: ")
    # whole but damaged inside: found by its relocalization's decode
    damaged = bytearray(png)
    damaged[len(png) // 2: len(png) // 2 + 64] = bytes(64)
    publish_image(drone, stamp(2003.0), bytes(damaged))
    success, message = trigger(drone, 204)
    assert not success and message.startswith("image stamped 2003.000000000: BAD_IMAGE"), message
    # a message that is no CompressedImage: answered without a stamp, never with an old pose
    drone.publish(IMAGE_TOPIC, CIMG, HASH[CIMG], b"\x00\x01\x00\x00\xff")
    success, message = trigger(drone, 205)
    assert not success and message.startswith(
        "the image message that did not decode was rejected: "), message
    assert drone.poses.empty()                          # no pose for any of them
    assert service.ros2.node("trig").status.counters["images_rejected"] >= 2


def test_a_stale_or_missing_image_gives_success_false(rig, synthetic_scene):
    service, drone, _diag, _records = rig
    [png] = pngs(synthetic_scene.query_images[:1])
    before = service.ros2.counters["images"]
    publish_image(drone, stamp(3000.0), png)
    wait_until(lambda: service.ros2.counters["images"] > before)
    time.sleep(1.1)                                      # max_image_age_s = 1.0
    success, message = trigger(drone, 300)
    assert not success and "image stamped 3000.000000000, arrived" in message, message
    assert "expected one at most 1.00 s old" in message
    publish_image(drone, stamp(3001.0), png)
    success, message = trigger(drone, 301)
    assert success and message.startswith("image stamped 3001.000000000: relocalized")
    drone.poses.get(timeout=10)
    success, message = trigger(drone, 302)                # nothing new since
    assert not success and message == (
        "no image newer than image stamped 3001.000000000 (answered already) arrived on "
        f"{IMAGE_TOPIC} within 1.00 s")


def test_a_late_subscriber_receives_the_last_pose(rig, synthetic_scene):
    """A subscriber declared after the pose was published, transient local as rmw_zenoh
    declares one (AdvancedSubscriber with history), gets the last pose."""
    service, drone, _diag, _records = rig
    [png] = pngs(synthetic_scene.query_images[1:2])
    publish_image(drone, stamp(4000.0), png)
    assert trigger(drone, 400)[0]
    published = read_pose(drone.poses.get(timeout=10)[0])
    late = LatchingStandIn(drone_router(service))
    try:
        poses = late.subscribe("/reloc/trig/pose", POSE, HASH[POSE], latched=True)
        data, att = poses.get(timeout=10)
        got = read_pose(data)
        assert got.stamp == stamp(4000.0) == published.stamp
        np.testing.assert_allclose(got.map_from_body, published.map_from_body)
        assert att is not None and len(att) == 33
        assert poses.empty()                             # depth 1: only the last
    finally:
        late.close()


def drone_router(service) -> str:
    """The router the service connects to (the stand-ins' too)."""
    [router] = service.conf.zenoh.connect
    return router


def test_diagnostics_carry_the_official_hash_the_keyframes_and_the_last_answer(rig):
    service, drone, diagnostics, records = rig
    full = ros.type_hash(DIAG)
    assert full.startswith("RIHS01_5a8a36ef") and full.endswith("5a333e")   # official
    assert rosbags_hash(DIAG) == full                    # the stand-in's key has it too
    tokens = drone.graph()
    assert any("/MP/" in t and f"/%diagnostics/diagnostic_msgs::msg::dds_::DiagnosticArray_/"
               f"{full}/::,1:,:,:,," in t for t in tokens), tokens
    assert not trigger(drone, 500)[0]                    # no new image: a failed answer
    while True:   # the statuses published until the one after that answer
        data, att = diagnostics.get(timeout=5)
        assert att is not None and len(att) == 33
        _stamp, [status] = read_diagnostic_array(data)
        if "no image newer" in status.values.get("last answer reason", ""):
            break
    assert status.name == "reloc: trig" and status.hardware_id == "ros2test"
    assert status.values["map keyframes"] == "6"
    assert status.values["map version"] == str(service.maps["trig"].map_state().version)
    assert status.values["keyframes_added"] == "6"
    assert status.level == 1 and status.message.startswith("last answer failed: no image")
    assert "no image newer than" in status.values["last answer reason"]
    added = [r.getMessage() for r in records if "added" in r.getMessage()]
    assert sum("keyframe" in m for m in added) == 6, added


def test_a_keyframe_the_map_refuses_is_reported(rig, synthetic_scene):
    """An image that passes the arrival check but does not decode becomes a keyframe
    candidate whose check (its relocalization) fails, or, before the map can relocalize, a
    put the map refuses: either way a WARNING line and a counter on /diagnostics."""
    service, drone, diagnostics, records = rig
    [png] = pngs(synthetic_scene.keyframe_images[:1])
    damaged = bytearray(png)
    damaged[len(png) // 2: len(png) // 2 + 64] = bytes(64)
    far = synthetic_scene.keyframe_poses[0].copy()
    far[:3, 3] += (5.0, 0.0, 0.0)
    t = stamp(5000.0)
    drone.publish("/odom", "nav_msgs/msg/Odometry", rosbags_hash("nav_msgs/msg/Odometry"),
                  odometry(t, far @ np.linalg.inv(body_from_cam())))
    publish_image(drone, t, bytes(damaged))
    node = service.ros2.node("trig")
    wait_until(lambda: node.status.counters["keyframes_refused"] == 1, timeout=30)
    assert any(r.levelno == logging.WARNING and "refused (5000.000000000)" in r.getMessage()
               and "does not decode" in r.getMessage() for r in records)
    while True:   # the statuses published until the one after the refusal
        _stamp, [status] = read_diagnostic_array(diagnostics.get(timeout=5)[0])
        if status.values.get("keyframes_refused") == "1":
            break
    assert status.values["last keyframe"] == "failed"
    assert status.values["last keyframe image stamp"] == "5000.000000000"


def test_a_failed_lost_mode_relocalization_is_reported(rig, synthetic_scene):
    """While lost, each image is relocalized without a call (relocalize_every_n = 1); one
    that fails is logged as a WARNING and counted on /diagnostics."""
    service, drone, diagnostics, records = rig
    node = service.ros2.node("trig")
    drone.publish("/reloc/trig/lost", "std_msgs/msg/Bool", rosbags_hash("std_msgs/msg/Bool"),
                  b"\x00\x01\x00\x00\x01")
    wait_until(lambda: node.lost)
    try:
        [png] = pngs(synthetic_scene.query_images[:1])
        damaged = bytearray(png)
        damaged[len(png) // 2: len(png) // 2 + 64] = bytes(64)
        publish_image(drone, stamp(6000.0), bytes(damaged))
        wait_until(lambda: node.status.counters["lost_mode_failed"] == 1, timeout=30)
    finally:
        drone.publish("/reloc/trig/lost", "std_msgs/msg/Bool",
                      rosbags_hash("std_msgs/msg/Bool"), b"\x00\x01\x00\x00\x00")
        wait_until(lambda: not node.lost)
    assert any(r.levelno == logging.WARNING and "lost-mode relocalization of 6000.000000000 "
               "failed: image stamped 6000.000000000: BAD_IMAGE" in r.getMessage()
               for r in records)
    while True:   # the statuses published until the one after the failure
        _stamp, [status] = read_diagnostic_array(diagnostics.get(timeout=5)[0])
        if status.values.get("lost_mode_failed") == "1":
            break
    assert status.values["last lost_mode"] == "failed"
    assert drone.poses.empty()


def test_warnings_reach_rosout_with_the_official_hash(rig):
    """A late /rosout subscriber (transient local, as rqt_console's) gets the node's earlier
    warnings, e.g. the rejected image, as rcl_interfaces/msg/Log."""
    service, drone, _diag, _records = rig
    assert ros.type_hash("rcl_interfaces/msg/Log") == ROSOUT_HASH
    bad = service.ros2.counters["bad_samples"]
    publish_image(drone, stamp(7000.0), b"not a png")
    wait_until(lambda: service.ros2.counters["bad_samples"] > bad)
    late = LatchingStandIn(drone_router(service))
    try:
        tokens = late.graph()
        assert any("/MP/" in t and "/reloc/trig/reloc/%rosout/rcl_interfaces::msg::dds_::Log_/"
                   f"{ROSOUT_HASH}/{ROSOUT_QOS}" in t.replace("%reloc%trig/", "/reloc/trig/")
                   for t in tokens), tokens
        logs = late.subscribe("/rosout", "rcl_interfaces/msg/Log", ROSOUT_HASH, latched=True,
                              depth=1000)
        lines: list = []

        def rejected() -> list:
            while not logs.empty():
                lines.append(read_log(logs.get()[0]))
            return [m for m in lines if "image stamped 7000.000000000 rejected" in m.msg]

        rejected = wait_until(rejected, timeout=10)
        assert rejected and rejected[0].level == 30 and rejected[0].name == "reloc.trig.reloc"
        assert rejected[0].file.endswith("bridge.py") and rejected[0].line > 0
        assert all(m.level >= 30 for m in lines)
    finally:
        late.close()


def test_a_latched_camera_info_published_before_reloc_starts_is_received(synthetic_scene):
    """And the per-topic QoS shows in the tokens."""
    port = free_port()
    with open_router(port):
        drone = LatchingStandIn(endpoint(port))
        try:
            drone.publish_latched("/camera/camera_info", CAMERA_INFO, rosbags_hash(CAMERA_INFO),
                                  camera_info(stamp(1.0), synthetic_scene.camera.to_dict()))
            time.sleep(0.3)                                # reloc is not running yet
            service = start_service(port, "late", qos={"image": {
                "reliability": "best_effort", "depth": 5}})
            try:
                wait_until(lambda: service.ros2.counters["cameras"] == 1, timeout=10)
                assert service.ros2.node("late").camera["width"] == 320
                # the node's tokens reach the drone's graph a moment after the sample
                def qos_tokens() -> bool:
                    tokens = drone.graph()
                    return any("/MS/" in t and "%camera%camera_info/" in t
                               and t.endswith("/:1:,1:,:,:,,") for t in tokens) and any(
                        "/MS/" in t and "%camera%image_raw%compressed/" in t
                        and t.endswith("/2::,5:,:,:,,") for t in tokens)
                wait_until(qos_tokens, timeout=10)
            finally:
                service.stop()
        finally:
            drone.close()


@pytest.mark.parametrize("table, expected", [
    ({"pose": {"durability": "latched"}}, "ros2.qos.pose.durability: expected one of"),
    ({"image": {"depth": 0}}, "ros2.qos.image.depth: expected an integer >= 1"),
    ({"camera": {}}, "ros2.qos: unknown topic(s) ['camera']"),
    ({"pose": {"history": "keep_all"}}, "ros2.qos.pose: unknown key(s) ['history']"),
])
def test_bad_qos_is_a_config_error(table, expected):
    with pytest.raises(ConfigError, match=expected.replace("(", r"\(").replace(")", r"\)")
                       .replace("[", r"\[").replace("]", r"\]")):
        Ros2Conf(qos=table)


def test_qos_defaults_and_overrides():
    conf = Ros2Conf(qos={"pose": {"depth": 5}, "image": {"reliability": "best_effort"}})
    assert conf.topic_qos("pose").transient_local and conf.topic_qos("pose").depth == 5
    assert conf.topic_qos("camera_info").transient_local
    assert not conf.topic_qos("image").reliable and conf.topic_qos("image").depth == 10
    assert conf.topic_qos("diagnostics").depth == 1


def test_the_deployed_config_parses_with_the_documented_qos():
    import tomllib
    from pathlib import Path

    from reloc_service.service.config import parse_config

    path = Path(__file__).resolve().parents[1] / "deploy" / "ros2" / "reloc-ros2.toml"
    conf = parse_config(tomllib.loads(path.read_text())).ros2
    assert conf.max_image_age_s == 1.0 and conf.trigger_wait_s == 0.25
    assert conf.diagnostics_period_s == 1.0 and conf.rosout
    assert conf.topic_qos("pose").transient_local and conf.topic_qos("pose").depth == 1
    assert conf.topic_qos("camera_info").transient_local
    assert not conf.topic_qos("image").transient_local


# -- the desk alone: which image a call answers for ----------------------------------------------

class _Stamp:
    def __init__(self, sec: int) -> None:
        self.sec, self.nanosec = sec, 0


def _desk(wait_s: float, max_age_s: float = 10.0):
    from reloc_service.service.ros2.trigger import TriggerDesk

    answers: list[tuple[list, object, str]] = []
    desk = TriggerDesk(lambda calls, image, reason: answers.append((calls, image, reason)),
                       max_age_s=max_age_s, wait_s=wait_s, topic="/cam")
    return desk, answers


def test_calls_waiting_together_all_answer_for_the_next_image_and_only_once():
    desk, answers = _desk(wait_s=5.0)
    try:
        desk.call("a")
        desk.call("b")
        assert answers == []                                     # both wait
        image = desk.received(_Stamp(1), None, "cut short")
        assert answers == [(["a", "b"], image, "")]
        desk.call("c")                                           # answered already: waits
        assert len(answers) == 1
        later = desk.received(_Stamp(2), None, "cut short")
        assert answers[1] == (["c"], later, "")
    finally:
        desk.close()


def test_an_unanswered_fresh_image_answers_at_once_and_a_wait_ends_with_the_reason():
    desk, answers = _desk(wait_s=0.05)
    try:
        image = desk.received(_Stamp(7), None, "x")
        desk.call("a")
        assert answers == [(["a"], image, "")]
        desk.call("b")
        wait_until(lambda: len(answers) == 2, timeout=5)
        assert answers[1][:2] == (["b"], None)
        assert answers[1][2] == ("no image newer than image stamped 7.000000000 (answered "
                                 "already) arrived on /cam within 0.05 s")
    finally:
        desk.close()


def test_a_waiting_call_is_answered_when_the_desk_closes():
    desk, answers = _desk(wait_s=60.0)
    desk.call("a")
    desk.close()
    assert answers == [(["a"], None, "reloc is shutting down")]


def test_the_arrival_check_reads_the_header_and_the_end_only(synthetic_scene):
    import cv2
    from reloc_client import protocol as wire

    from reloc_service.service.ros2.trigger import image_problem

    grey = synthetic_scene.query_images[0]
    jpeg = cv2.imencode(".jpg", grey)[1].tobytes()
    png = cv2.imencode(".png", grey)[1].tobytes()
    for data in (jpeg, png, jpeg + b"\0\0"):             # whole (a JPEG may be padded)
        assert image_problem(wire.WireImage.from_bytes(data), (320, 240)) is None
    assert image_problem(wire.WireImage.from_bytes(jpeg[:-100]), None) == (
        "the JPEG file is cut short (it does not end with the EOI marker)")
    assert image_problem(wire.WireImage.from_bytes(png[:-20]), None) == (
        "the PNG file is cut short (it does not end with the IEND chunk)")
    assert image_problem(wire.WireImage.from_bytes(png), (640, 480)) == (
        "its size 320x240 is not the camera's 640x480 (camera_info)")
    assert image_problem(wire.WireImage.from_array(grey), (320, 240)) is None
