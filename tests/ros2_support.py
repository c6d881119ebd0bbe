"""Helpers shared by the ROS 2 bridge tests (not a test module): the camera mounted on the
body, a service with ``[ros2]`` behind a router, ROS stamps, a map fed as a drone's odometry
and images through the ROS 2 stand-in (:mod:`ros2_standin`)."""

from __future__ import annotations

import cv2
import numpy as np
from ros2_standin import HASH, StandIn, camera_info, compressed_image, odometry, rosbags_hash
from scipy.spatial.transform import Rotation
from service_support import endpoint, free_port

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
