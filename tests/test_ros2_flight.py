"""The flight loop over real Zenoh, driven as a drone node would (tests/ros2_standin.py): a
relocalization asked for by Trigger is one more ``map_from_odom`` sample (a hovering drone
re-anchors without moving a keyframe apart), a paused map still places the map frame, and PX4
gets the odometry composed with ``map_from_odom``: in the map frame while anchored, nothing
while not, and a reset counter that says when the frame jumped."""

from __future__ import annotations

import queue
import time

import numpy as np
import pytest
from ros2_standin import (
    StandIn,
    call_set_bool,
    odometry_in,
    read_vehicle_odometry,
    subscribe_px4,
)
from ros2_support import (
    ODOMETRY_COVARIANCE,
    body_from_cam,
    counts,
    drone_built_map,
    odom_hash,
    pngs,
    pose,
    pose_error,
    publish_frame,
    relocalize,
    settle,
    stamp,
)
from service_support import wait_until

from reloc_service.core.geometry import invert, pose_from_tum

#: The VIO restarted in frame ``odom_2``, turned 60 deg and shifted: odom2_from_map.
ODOM2_FROM_MAP = pose(60.0, (1.0, -1.0, 0.1))
NED_FROM_ENU = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]], dtype=float)


def publish_odometry(drone: StandIn, t: float, frame_id: str, odom_from_cam: np.ndarray) -> None:
    drone.publish("/odom", "nav_msgs/msg/Odometry", odom_hash(),
                  odometry_in(frame_id, stamp(t), odom_from_cam @ invert(body_from_cam()),
                              ODOMETRY_COVARIANCE))


@pytest.fixture
def flying(synthetic_scene):
    """A service whose map "room" a drone built from the 6 synthetic keyframes (odometry frame
    ``odom``: the map frame), PX4's feed on (the odometry composed with map_from_odom, every
    message, stamps as they are), the drone and what it receives as PX4. Each test has its
    own: they restart the VIO and pause mapping, which a shared map frame would carry over."""
    with drone_built_map(synthetic_scene, subscribe_px4,
                         px4={"enabled": True, "clock_topic": "", "max_rate_hz": 0.0}) as built:
        yield built


def hover_then_trigger(service, drone, scene, frame_id: str, odom_from_map: np.ndarray,
                       t0: float, calls: int) -> list[bool]:
    """The drone restarted its VIO in ``frame_id`` and hovers at keyframe 2's view: images
    with their odometry (one probe at most: it does not move), then ``calls`` Trigger calls on
    the same view, each with the odometry of its stamp; their successes."""
    world_from_cam = scene.keyframe_poses[2]
    [png] = pngs([scene.keyframe_images[2]])
    images, odometry = service.ros2.counters["images"], service.ros2.counters["odometry"]
    for i in range(4):
        publish_frame(drone, t0 + 0.1 * i, frame_id, odom_from_map @ world_from_cam, png)
    settle(service, images + 4, odometry + 4)
    successes = []
    for i in range(calls):
        t = t0 + 1.0 + i
        publish_odometry(drone, t, frame_id, odom_from_map @ world_from_cam)
        success, _message, _reading = relocalize(drone, service, png, stamp(t), 100 + i, "room")
        successes.append(success)
    return successes


def test_a_hovering_drone_re_anchors_from_the_relocalizations_it_asks_for(flying,
                                                                          synthetic_scene):
    """After a VIO restart in a new frame the drone hovers: no keyframe-apart motion, so the
    map frame gets one probe; its Trigger calls then anchor the new session, within 5 cm /
    2 deg of the truth, and no keyframe is added."""
    service, drone, _px4 = flying
    keyframes = len(service.maps["room"].map_state().keyframes)
    successes = hover_then_trigger(service, drone, synthetic_scene, "odom_2", ODOM2_FROM_MAP,
                                   700.0, calls=3)
    assert all(successes)
    status = counts(service)
    assert status["state"] == "anchored", status
    metres, degrees = pose_error(pose_from_tum(np.array(status["map_from_odom"].split(), float)),
                                 invert(ODOM2_FROM_MAP))
    assert metres < 0.05 and degrees < 2.0, (metres, degrees)
    assert len(service.maps["room"].map_state().keyframes) == keyframes


def test_a_paused_map_still_places_the_map_frame(flying, synthetic_scene):
    """Mapping paused (as with build_map = false): after a VIO restart, images a keyframe
    apart are still relocalized as probes and anchor the new session; nothing is added."""
    service, drone, _px4 = flying
    scene = synthetic_scene
    _payload = call_set_bool(drone, "/reloc/room/mapping", False, seq=1)
    wait_until(lambda: counts(service)["mapping"] == "paused")
    keyframes = len(service.maps["room"].map_state().keyframes)
    images, odometry = service.ros2.counters["images"], service.ros2.counters["odometry"]
    shots = [0, 2, 4, 5]
    for i, k in enumerate(shots):
        publish_frame(drone, 800.0 + i, "odom_2", ODOM2_FROM_MAP @ scene.keyframe_poses[k],
                      pngs([scene.keyframe_images[k]])[0])
    settle(service, images + len(shots), odometry + len(shots))
    status = counts(service)
    assert status["state"] == "anchored", status
    metres, degrees = pose_error(pose_from_tum(np.array(status["map_from_odom"].split(), float)),
                                 invert(ODOM2_FROM_MAP))
    assert metres < 0.05 and degrees < 2.0, (metres, degrees)
    assert len(service.maps["room"].map_state().keyframes) == keyframes


def drain(px4: queue.Queue[bytes]) -> list:
    out = []
    while True:
        try:
            out.append(read_vehicle_odometry(px4.get(timeout=0.5)))
        except queue.Empty:
            return out


def ned_position(world_from_cam: np.ndarray) -> np.ndarray:
    """The body's position of a camera at ``world_from_cam`` (ENU map) in NED."""
    return NED_FROM_ENU @ (world_from_cam @ invert(body_from_cam()))[:3, 3]


def test_px4_gets_the_odometry_in_the_map_frame_and_nothing_while_unanchored(
        flying, synthetic_scene):
    """While the map's own session runs, each odometry message reaches PX4 as the body pose
    in NED (map_from_odom the identity). After a VIO restart in another frame, odometry goes
    to PX4 only once the new session is anchored: then in the map frame (the truth within
    5 cm, not the raw odometry 1 m away) and with reset_counter 1."""
    service, drone, px4 = flying
    scene = synthetic_scene
    drain(px4)
    world_from_cam = scene.keyframe_poses[1]
    publish_odometry(drone, 600.0, "odom", world_from_cam)
    [first] = drain(px4)
    np.testing.assert_allclose(first.position, ned_position(world_from_cam), atol=1e-5)
    assert first.reset_counter == 0 and first.timestamp_sample == 600_000_000
    # the restart: odometry in odom_2, unanchored, then the drone hovers and asks (anchors)
    fed = service.ros2.counters["px4_odometry"]
    publish_odometry(drone, 650.0, "odom_2", ODOM2_FROM_MAP @ world_from_cam)
    wait_until(lambda: counts(service)["state"] == "unanchored")
    time.sleep(0.5)                                        # what would have been sent, arrives
    assert service.ros2.counters["px4_odometry"] == fed and drain(px4) == []
    assert all(hover_then_trigger(service, drone, scene, "odom_2", ODOM2_FROM_MAP, 700.0,
                                  calls=3))
    assert counts(service)["state"] == "anchored"
    drain(px4)
    world_from_cam = scene.keyframe_poses[4]
    publish_odometry(drone, 760.0, "odom_2", ODOM2_FROM_MAP @ world_from_cam)
    [after] = drain(px4)
    assert after.reset_counter == 1
    assert np.linalg.norm(after.position - ned_position(world_from_cam)) < 0.05
    raw = NED_FROM_ENU @ (ODOM2_FROM_MAP @ world_from_cam @ invert(body_from_cam()))[:3, 3]
    assert np.linalg.norm(after.position - raw) > 0.5      # not the odometry as it came
