"""Helpers shared by the ROS 2 bridge tests (not a test module): the camera mounted on the
body, a service with ``[ros2]`` behind a router, ROS stamps, a map fed as a drone's odometry
and images through the ROS 2 stand-in (:mod:`ros2_standin`) and the service that built it, a
frame (odometry and image) published, a Trigger call for an image, the map frame's status."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import cv2
import numpy as np
from ros2_standin import (
    HASH,
    StandIn,
    camera_info,
    compressed_image,
    odometry,
    odometry_in,
    parse_attachment,
    read_pose,
    read_trigger_response,
    rosbags_hash,
)
from scipy.spatial.transform import Rotation
from service_support import endpoint, free_port, open_router, wait_until

from reloc_service.core.geometry import invert
from reloc_service.service.app import Service
from reloc_service.service.config import parse_config

CIMG = "sensor_msgs/msg/CompressedImage"
# FLU body, camera optical frame looking forward, 10 cm ahead and 5 cm above the body origin.
BODY_FROM_CAM_R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
BODY_FROM_CAM_T = np.array([0.1, 0.0, 0.05])


def body_from_cam() -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = BODY_FROM_CAM_R, BODY_FROM_CAM_T
    return out


def ros2_section(**extra) -> dict:
    q = Rotation.from_matrix(BODY_FROM_CAM_R).as_quat()
    # the fixed-metres rule the scenes below were laid out for (overlap rule: opt in)
    return {"enabled": True, "body_from_cam": [*BODY_FROM_CAM_T, *q], "keyframe_rule": "distance",
            **extra}


def start_service(router_port: int, map_name: str, **ros2) -> Service:
    conf = parse_config({
        "zenoh": {"mode": "peer", "listen": [endpoint(free_port())],
                  "connect": [endpoint(router_port)], "multicast_scouting": False},
        "service": {"instance": "ros2test", "storage": "", "workers": 1},
        "maps": {map_name: {}}, "ros2": ros2_section(**ros2)})
    return Service(conf).start()


def stamp(t: float) -> tuple[int, int]:
    return int(t), int(round((t - int(t)) * 1e9))


def pose_error(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between two poses."""
    angle = Rotation.from_matrix(a[:3, :3].T @ b[:3, :3]).magnitude()
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3])), float(np.degrees(angle))


#: The pose covariance the map's odometry says it has (ROS's order: x y z, then rotations about
#: the parent's x y z): 1, 2, 3 cm and 0.2, 0.3, 0.4 deg, x correlated with rotZ.
ODOMETRY_COVARIANCE = np.diag(np.square([0.01, 0.02, 0.03, 0.0035, 0.0052, 0.007]))
ODOMETRY_COVARIANCE[0, 5] = ODOMETRY_COVARIANCE[5, 0] = 0.5 * 0.01 * 0.007


def feed_map(drone: StandIn, camera: dict, frames: list[tuple[bytes, np.ndarray]], *,
             repeat_nearby: bool) -> None:
    """CameraInfo, then each frame's odometry (with :data:`ODOMETRY_COVARIANCE`) and image
    (stamps 100 + i / 10 s); with ``repeat_nearby`` each frame again 2 cm further, which the
    keyframe rule must skip."""
    drone.publish("/camera/camera_info", "sensor_msgs/msg/CameraInfo",
                  rosbags_hash("sensor_msgs/msg/CameraInfo"), camera_info(stamp(99.0), camera))
    odom_hash = rosbags_hash("nav_msgs/msg/Odometry")
    for i, (png, world_from_cam) in enumerate(frames):
        shots = [(0.0, world_from_cam)]
        if repeat_nearby:
            nudged = world_from_cam.copy()
            nudged[:3, 3] += (0.02, 0.0, 0.0)
            shots.append((0.05, nudged))
        for dt, pose in shots:
            t = stamp(100.0 + 0.1 * i + dt)
            drone.publish("/odom", "nav_msgs/msg/Odometry", odom_hash,
                          odometry(t, pose @ np.linalg.inv(body_from_cam()),
                                   ODOMETRY_COVARIANCE))
            drone.publish("/camera/image_raw/compressed", CIMG, HASH[CIMG],
                          compressed_image(t, "camera", "png", png))


def pngs(images) -> list[bytes]:
    return [cv2.imencode(".png", im)[1].tobytes() for im in images]


@contextmanager
def drone_built_map(scene, subscribe: Callable[[StandIn], Any] = lambda drone: None,
                    **ros2: Any) -> Iterator[tuple[Service, StandIn, Any]]:
    """A service with ``[ros2]`` (``ros2`` keys) behind a router, whose map "room" a drone
    built over ROS 2 from the scene's 6 keyframes (the first session: its odometry frame
    ``odom`` is the map frame); (service, the drone subscribed to the pose, what ``subscribe``
    returned: it declares the drone's other subscriptions before the map is fed)."""
    port = free_port()
    with open_router(port):
        service = start_service(port, "room", **ros2)
        drone = StandIn(endpoint(port))
        drone.subscribe_poses("/reloc/room/pose")
        extra = subscribe(drone)
        try:
            wait_until(lambda: any("/SS/" in t for t in drone.graph()))
            feed_map(drone, scene.camera.to_dict(),
                     list(zip(pngs(scene.keyframe_images), scene.keyframe_poses, strict=True)),
                     repeat_nearby=False)
            wait_until(lambda: len(service.maps["room"].map_state().keyframes) == 6, timeout=60)
            service.wait_idle()
            yield service, drone, extra
        finally:
            drone.close()
            service.stop()


def pose(yaw_deg: float, t: tuple[float, float, float]) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    out[:3, 3] = t
    return out


def odom_hash() -> str:
    return rosbags_hash("nav_msgs/msg/Odometry")


def publish_frame(drone: StandIn, t: float, frame_id: str, odom_from_cam: np.ndarray,
                  png: bytes) -> None:
    """The odometry of the body carrying a camera at ``odom_from_cam``, then the image."""
    drone.publish("/odom", "nav_msgs/msg/Odometry", odom_hash(),
                  odometry_in(frame_id, stamp(t), odom_from_cam @ invert(body_from_cam()),
                              ODOMETRY_COVARIANCE))
    drone.publish("/camera/image_raw/compressed", CIMG, HASH[CIMG],
                  compressed_image(stamp(t), "camera", "png", png))


def relocalize(drone: StandIn, service: Service, png: bytes, t: tuple[int, int], seq: int,
               map_name: str):
    """Publish ``png``, call the Trigger service; (success, message, pose reading or None)."""
    before = service.ros2.counters["images"]
    drone.publish("/camera/image_raw/compressed", CIMG, HASH[CIMG],
                  compressed_image(t, "camera", "png", png))
    wait_until(lambda: service.ros2.counters["images"] > before)
    replies = drone.call_trigger(f"/reloc/{map_name}/relocalize", seq=seq)
    assert len(replies) == 1
    payload, att = replies[0]
    assert att is not None and parse_attachment(att) == (seq, drone.gid)  # matched to the call
    success, message = read_trigger_response(payload)
    if not success:
        return success, message, None
    data, pose_att = drone.poses.get(timeout=10)
    assert pose_att is not None and len(pose_att) == 33 and pose_att[16] == 16
    return success, message, read_pose(data)


def counts(service: Service) -> dict[str, str]:
    return service.ros2.node("room").map_frame_status()


def settle(service: Service, images: int, odometry: int | None = None) -> None:
    """Until the bridge has taken ``images`` images (and ``odometry`` odometry messages) and
    checked every keyframe candidate. The odometry and the images come through different
    subscribers, whose callbacks Zenoh does not order: an odometry reset published before an
    image can be taken after it, so a test that counts resets waits for the odometry too."""
    wait_until(lambda: service.ros2.counters["images"] >= images, timeout=60)
    if odometry is not None:
        wait_until(lambda: service.ros2.counters["odometry"] >= odometry, timeout=60)
    assert service.ros2.worker.join(timeout=60)    # every image considered
    wait_until(lambda: counts(service)["candidates_waiting"] == "0", timeout=90)
    service.wait_idle()
