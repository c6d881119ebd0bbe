"""Conversions between ROS 2 messages and reloc's types: stamps, poses, the covariance in
ROS's convention, CameraInfo to a camera, image messages to grey pixels and the pairing of
images with odometry (the keyframe rule is :mod:`.keyframe_rule`)."""

from __future__ import annotations

import bisect
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from reloc_client.protocol import pose_covariance_problem

from ...core.geometry import invert, matrix_to_quat_xyzw, pose_from_tq, se3_adjoint, skew

Array = npt.NDArray[np.float64]


def stamp_seconds(stamp: Any) -> float:
    """builtin_interfaces/Time -> seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def pose_of(pose_msg: Any) -> Array:
    """geometry_msgs/Pose -> (4, 4) ``parent_from_child``; ValueError unless finite with a
    non-zero quaternion."""
    t = (pose_msg.position.x, pose_msg.position.y, pose_msg.position.z)
    q = np.array([pose_msg.orientation.x, pose_msg.orientation.y, pose_msg.orientation.z,
                  pose_msg.orientation.w], dtype=np.float64)
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))) or np.linalg.norm(q) < 1e-6:
        raise ValueError(f"pose: expected a finite position and a non-zero quaternion, got "
                         f"{t} {tuple(q)}")
    return pose_from_tq(t, q / np.linalg.norm(q))


def ros_covariance(world_from_cam: Array, covariance_cam: Array, world_from_body: Array
                   ) -> Array:
    """Our 6x6 covariance of ``world_from_cam`` (twist (rho, omega), right perturbation
    ``world_from_cam @ exp(xi)``) as ROS's covariance of the body position and orientation:
    (x, y, z, rotX, rotY, rotZ), position errors in the world frame and rotations about the
    world's fixed axes (first order).

    A right perturbation of the camera is the left one ``exp(Ad(world_from_cam) xi)``
    shared by every frame rigidly attached to it; the body's position then moves by
    ``rho_w + omega_w x p_body``."""
    g = _ros_from_ours(world_from_cam, world_from_body)
    out = g @ np.asarray(covariance_cam, dtype=np.float64) @ g.T
    return 0.5 * (out + out.T)


def covariance_from_ros(world_from_cam: Array, covariance_ros: Array, world_from_body: Array
                        ) -> Array:
    """The inverse of :func:`ros_covariance`: ROS's 6x6 covariance of a body pose ((x, y, z,
    rotX, rotY, rotZ) in the parent frame, e.g. a nav_msgs/Odometry's ``pose.covariance``)
    as ours of ``world_from_cam`` for the camera rigidly attached to that body (twist
    (rho, omega), right perturbation)."""
    g_inv = np.linalg.inv(_ros_from_ours(world_from_cam, world_from_body))
    out = g_inv @ np.asarray(covariance_ros, dtype=np.float64) @ g_inv.T
    return 0.5 * (out + out.T)


def _ros_from_ours(world_from_cam: Array, world_from_body: Array) -> Array:
    """(6, 6) first-order map from our twist of ``world_from_cam`` to ROS's (position of the
    body, rotation about the world axes): the adjoint to a world twist, then the lever arm to
    the body's centre."""
    lever = np.eye(6)
    lever[:3, 3:] = -skew(world_from_body[:3, 3])
    return lever @ se3_adjoint(world_from_cam)


def odometry_covariance(values: Any, world_from_cam: Array, world_from_body: Array
                        ) -> Array | None:
    """Our pose covariance of the camera from a ROS pose covariance (36 row-major values) of
    its body; None where ROS says it is unknown (all zeros, or -1 first, REP 103's and
    geometry_msgs' conventions for a covariance not filled in). ValueError when the values
    are not a covariance (not finite, not symmetric, not positive semi-definite)."""
    c = np.asarray(values, dtype=np.float64).reshape(6, 6)
    if not np.any(c) or c[0, 0] == -1.0:
        return None
    problem = pose_covariance_problem(c)
    if problem is not None:
        raise ValueError(f"odometry pose covariance: {problem}")
    return covariance_from_ros(world_from_cam, c, world_from_body)


@dataclass(frozen=True)
class PoseOut:
    """A body pose to publish: position, quaternion (x, y, z, w) and ROS covariance."""

    position: Array
    quat_xyzw: Array
    covariance: Array


def body_pose(world_from_cam: Array, covariance_cam: Array | None, body_from_cam: Array
              ) -> PoseOut:
    """The body's pose and ROS covariance from a relocalized camera pose (covariance zeros
    when none is known: ROS's "unknown" is a -1 first element, but a verified pose has one)."""
    world_from_body = world_from_cam @ invert(body_from_cam)
    cov = (np.zeros((6, 6)) if covariance_cam is None
           else ros_covariance(world_from_cam, covariance_cam, world_from_body))
    return PoseOut(world_from_body[:3, 3].copy(), matrix_to_quat_xyzw(world_from_body[:3, :3]),
                   cov)


# -- cameras and images ------------------------------------------------------------------------

def camera_dict(info: Any) -> dict[str, Any]:
    """sensor_msgs/CameraInfo -> reloc's camera dict (the image is never rectified: K and D
    describe the raw image). ValueError for a model reloc has no equivalent of."""
    k = np.asarray(info.k, dtype=np.float64)
    d = [float(v) for v in np.asarray(info.d, dtype=np.float64)]
    model = info.distortion_model
    if k[0] <= 0 or k[4] <= 0 or info.width == 0 or info.height == 0:
        raise ValueError(f"camera_info: expected a positive size and focal lengths, got "
                         f"{info.width}x{info.height}, fx {k[0]}, fy {k[4]}")
    base = {"width": int(info.width), "height": int(info.height), "fx": float(k[0]),
            "fy": float(k[4]), "cx": float(k[2]), "cy": float(k[5])}
    if not any(d):
        return {"model": "pinhole", **base, "distortion": []}
    if model in ("plumb_bob", "rational_polynomial"):
        if any(d[5:]):
            raise ValueError(f"camera_info: {model} with non-zero k4..k6 {d[5:]} is not "
                             "supported; expected plumb_bob (k1 k2 p1 p2 k3)")
        return {"model": "radtan", **base, "distortion": d[:5]}
    if model == "equidistant" and len(d) >= 4:
        return {"model": "equidistant", **base, "distortion": d[:4]}
    raise ValueError(f"camera_info: distortion model {model!r} with {len(d)} values is not "
                     "supported; expected plumb_bob, rational_polynomial or equidistant")


_RAW_CHANNELS = {"mono8": 1, "8UC1": 1, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}


def grey_from_raw(image: Any) -> npt.NDArray[np.uint8]:
    """sensor_msgs/Image (8-bit encodings) -> (H, W) uint8 grey."""
    channels = _RAW_CHANNELS.get(image.encoding)
    if channels is None:
        raise ValueError(f"image: encoding {image.encoding!r} is not supported; expected one "
                         f"of {sorted(_RAW_CHANNELS)}")
    h, w, step = int(image.height), int(image.width), int(image.step)
    data = np.asarray(image.data, dtype=np.uint8)
    if step < w * channels or len(data) < step * h:
        raise ValueError(f"image: {len(data)} bytes with step {step} do not hold a {w}x{h} "
                         f"{image.encoding} image")
    pixels = data[:step * h].reshape(h, step)[:, :w * channels].reshape(h, w, channels)
    if channels == 1:
        return np.ascontiguousarray(pixels[..., 0])
    code = {"rgb8": cv2.COLOR_RGB2GRAY, "bgr8": cv2.COLOR_BGR2GRAY,
            "rgba8": cv2.COLOR_RGBA2GRAY, "bgra8": cv2.COLOR_BGRA2GRAY}[image.encoding]
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(pixels), code), dtype=np.uint8)


# -- pairing -----------------------------------------------------------------------------------

class StampedPoses:
    """The last ``size`` odometry poses by stamp (each with its ROS pose covariance, 36
    values, or None); the one nearest an image's stamp. Added to by the bridge's worker and
    read by the relocalize workers too (a relocalized image's odometry): one lock keeps the
    three queues in step, so a lookup never pairs a stamp with its neighbour's pose."""

    def __init__(self, size: int = 400) -> None:
        self._stamps: deque[float] = deque(maxlen=size)
        self._poses: deque[Array] = deque(maxlen=size)
        self._covariances: deque[Array | None] = deque(maxlen=size)
        self._lock = threading.Lock()

    def add(self, stamp: float, world_from_body: Array, covariance: Array | None = None
            ) -> None:
        with self._lock:
            if self._stamps and stamp < self._stamps[-1]:
                self._stamps.clear()   # time went back (a bag restarted): start again
                self._poses.clear()
                self._covariances.clear()
            self._stamps.append(stamp)
            self._poses.append(world_from_body)
            self._covariances.append(covariance)

    def newest(self) -> float:
        """The newest stamp (-inf when empty)."""
        with self._lock:
            return self._stamps[-1] if self._stamps else float("-inf")

    def nearest(self, stamp: float, tolerance_s: float) -> Array | None:
        """The pose stamped within ``tolerance_s`` of ``stamp`` (nearest), else None."""
        found = self.nearest_with_covariance(stamp, tolerance_s)
        return None if found is None else found[0]

    def nearest_with_covariance(self, stamp: float, tolerance_s: float
                                ) -> tuple[Array, Array | None] | None:
        """(pose, its ROS covariance or None) stamped nearest ``stamp`` within
        ``tolerance_s``, else None."""
        with self._lock:
            best = self._nearest_index(stamp, tolerance_s)
            return None if best is None else (self._poses[best], self._covariances[best])

    def _nearest_index(self, stamp: float, tolerance_s: float) -> int | None:
        stamps = list(self._stamps)
        i = bisect.bisect_left(stamps, stamp)
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(stamps) and abs(stamps[j] - stamp) <= tolerance_s and (
                    best is None or abs(stamps[j] - stamp) < abs(stamps[best] - stamp)):
                best = j
        return best
