"""PX4 over Zenoh: the relocalized body pose as a ``px4_msgs/msg/VehicleOdometry`` on
``/fmu/in/vehicle_visual_odometry``, the topic PX4's ``zenoh`` module (v1.17) bridges to uORB
``vehicle_visual_odometry``, which EKF2 fuses as external vision.

PX4's module speaks rmw_zenoh: data key ``<domain>/fmu/in/vehicle_visual_odometry/
px4_msgs::msg::dds_::VehicleOdometry_/<RIHS01 hash>``, the hash being rosidl's type description
hash of the .msg (``Tools/zenoh/px_generate_zenoh_topic_files.py`` reads it from rosidl's JSON),
and CDR little endian. The .msg ships with this package (``px4_msgs/``, with PX4's BSD-3-Clause
license); its hash is computed here as for every other type (:func:`types.type_hash`).

Frames. reloc's map frame is the VIO's world frame and the pose is the VIO's body; ROS
(REP-103) makes them ENU and FLU, PX4 wants NED and FRD:

- world ENU -> NED: ``(x, y, z) -> (y, x, -z)`` (``world_frame = "ned"``: already NED);
- body FLU -> FRD: 180 deg about x (``body_frame = "frd"``: already FRD);
- ``q`` is ``ned_from_frd`` as (w, x, y, z), Hamilton, w >= 0;
- ``position_variance``: the diagonal of the position covariance in NED;
- ``orientation_variance``: the diagonal of the attitude error covariance in the FRD body
  frame (the .msg: "expressed in body frame"): ROS's rotation errors are about the world's
  fixed axes, ``delta_body = frd_from_world @ delta_world``;
- the map's heading is the VIO's, not north: ``pose_frame = "frd"`` (POSE_FRAME_FRD, "arbitrary
  heading reference") unless the map is north-aligned (``"ned"``, POSE_FRAME_NED).

reloc measures no velocity: ``velocity``, ``angular_velocity`` and ``velocity_variance`` are NaN
(EKF2 uses a velocity only when all three values are finite) with VELOCITY_FRAME_UNKNOWN.

Time. EKF2 places an external vision sample by ``timestamp_sample`` on PX4's boot clock, and
PX4's zenoh module does no time synchronisation (it overwrites ``timestamp`` on receipt and
keeps ``timestamp_sample``). :class:`Px4Clock` learns PX4's clock from the ``timestamp`` of
PX4's own ``/fmu/out/vehicle_odometry``; ``timestamp_sample`` is the image stamp (the
companion's wall clock, as ROS camera drivers stamp) moved onto it. Without a recent PX4
sample the VehicleOdometry is withheld rather than sent on the wrong clock.
"""

from __future__ import annotations

import collections
import functools
import logging
import math
import struct
import threading
import time
from dataclasses import dataclass
from importlib import resources
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.geometry import matrix_to_quat_xyzw, pose_from_tq
from . import convert, graph
from . import types as ros
from .px4_conf import POSE_FRAMES, Px4Conf

Array = npt.NDArray[np.float64]
log = logging.getLogger(__name__)

VEHICLE_ODOMETRY = "px4_msgs/msg/VehicleOdometry"
VELOCITY_FRAME_UNKNOWN = 0

#: ``ned_from_enu``: x_N = y_E, y_N = x_E, z_N = -z_U (a proper rotation, det +1).
NED_FROM_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: ``flu_from_frd``: 180 deg about x.
FLU_FROM_FRD = np.diag([1.0, -1.0, -1.0])

# -- the message definition -----------------------------------------------------------------------

def msg_text() -> str:
    """PX4's VehicleOdometry.msg (license header included) as shipped with this package."""
    return (resources.files(__package__) / "px4_msgs" / "VehicleOdometry.msg").read_text(
        encoding="utf-8")


@functools.lru_cache(maxsize=1)
def vehicle_odometry_type() -> str:
    """Register VehicleOdometry in the bridge's type store (once); its ROS type name."""
    from rosbags.typesys import get_types_from_msg

    store = ros.typestore()
    if VEHICLE_ODOMETRY not in store.fielddefs:
        store.register(get_types_from_msg(msg_text(), VEHICLE_ODOMETRY))
    return VEHICLE_ODOMETRY


# -- conversions ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Px4Pose:
    """A body pose as VehicleOdometry carries it: NED (or FRD-world) position, FRD body."""

    position: Array                 # (3,) metres in the NED frame
    q_wxyz: Array                   # (4,) ned_from_frd, w >= 0
    position_variance: Array        # (3,) m^2, NED axes (NaN: unknown)
    orientation_variance: Array     # (3,) rad^2, FRD body axes (NaN: unknown)


def ned_from_world(world_frame: str) -> Array:
    """The rotation taking map-frame vectors to NED."""
    return NED_FROM_ENU if world_frame == "enu" else np.eye(3)


def body_from_frd(body_frame: str) -> Array:
    """The rotation taking FRD body vectors to the pose's body frame."""
    return FLU_FROM_FRD if body_frame == "flu" else np.eye(3)


def px4_pose(world_from_body: Array, covariance: Array | None, *, world_frame: str = "enu",
             body_frame: str = "flu") -> Px4Pose:
    """``world_from_body`` (4, 4) and its ROS covariance (6, 6: x y z in the world frame, then
    rotations about the world's fixed axes; None or all zeros: unknown) as PX4 wants them."""
    ned_w = ned_from_world(world_frame)
    world_from_frd = world_from_body[:3, :3] @ body_from_frd(body_frame)
    ned_from_frd = ned_w @ world_from_frd
    x, y, z, w = matrix_to_quat_xyzw(ned_from_frd)
    unknown = covariance is None or not np.any(covariance)
    if unknown:
        pos_var, rot_var = np.full(3, np.nan), np.full(3, np.nan)
    else:
        c = np.asarray(covariance, dtype=np.float64)
        pos_var = _diagonal(ned_w, c[:3, :3])
        # a world-axes rotation error delta_w is frd_from_world @ delta_w in the body
        rot_var = _diagonal(world_from_frd.T, c[3:, 3:])
    return Px4Pose(ned_w @ world_from_body[:3, 3], np.array([w, x, y, z]), pos_var, rot_var)


def _diagonal(a_from_b: Array, covariance_b: Array) -> Array:
    """diag(A C A^T): the variances along the axes of frame a of a covariance given in b."""
    return np.einsum("ij,jk,ik->i", a_from_b, covariance_b, a_from_b)


def microseconds(stamp: Any) -> int:
    """builtin_interfaces/Time -> integer microseconds."""
    return int(stamp.sec) * 1_000_000 + int(stamp.nanosec) // 1000


def quality_of(confidence: float) -> int:
    """reloc's confidence (0..1) as VehicleOdometry's quality (1..100): 0 is PX4's "invalid",
    and a published pose has passed verification."""
    if not math.isfinite(confidence):
        return 1
    return int(min(100, max(1, round(100.0 * confidence))))


def vehicle_odometry(pose: Px4Pose, *, timestamp_us: int, timestamp_sample_us: int,
                     pose_frame: int, reset_counter: int, quality: int) -> Any:
    """A px4_msgs/msg/VehicleOdometry message object (float32 fields, as PX4's)."""
    f32 = lambda v: np.asarray(v, dtype=np.float32)  # noqa: E731
    nan3 = np.full(3, np.nan, dtype=np.float32)
    return ros.message(
        vehicle_odometry_type(), timestamp=int(timestamp_us),
        timestamp_sample=int(timestamp_sample_us), pose_frame=pose_frame,
        position=f32(pose.position), q=f32(pose.q_wxyz),
        velocity_frame=VELOCITY_FRAME_UNKNOWN, velocity=nan3, angular_velocity=nan3.copy(),
        position_variance=f32(pose.position_variance),
        orientation_variance=f32(pose.orientation_variance), velocity_variance=nan3.copy(),
        reset_counter=reset_counter % 256, quality=quality)


# -- PX4's clock ------------------------------------------------------------------------------------

#: The clock offset is the best of the PX4 samples received this recently: long enough to hold
#: a sample that met no queueing (PX4 publishes vehicle_odometry at the EKF's rate, tens of Hz),
#: short enough that the two crystals' drift (tens of ppm: under 0.1 ms here) does not matter.
CLOCK_WINDOW_S = 2.0


class Px4Clock:
    """PX4's boot clock (``hrt_absolute_time``, microseconds) seen from the local wall clock,
    from the ``timestamp`` of PX4's own messages (PX4's zenoh module is not time-synchronised:
    it overwrites an incoming ``timestamp`` with its clock but keeps ``timestamp_sample``, which
    EKF2 uses to place the sample in its delay buffer).

    A sample received ``latency`` after PX4 stamped it gives ``px4 - received = offset -
    latency <= offset``: the largest over the window is the least delayed sample's."""

    def __init__(self, window_s: float = CLOCK_WINDOW_S) -> None:
        self.window_us = int(window_s * 1e6)
        self.samples = 0
        self._seen: collections.deque[tuple[int, int]] = collections.deque()  # (local, offset)
        self._last_px4 = -1
        self._lock = threading.Lock()

    def observe(self, px4_us: int, local_us: int) -> None:
        """One PX4 stamp ``px4_us`` received at ``local_us`` (wall clock, microseconds)."""
        with self._lock:
            if px4_us < self._last_px4:      # PX4 rebooted: its clock started again
                self._seen.clear()
            self._last_px4 = px4_us
            self._seen.append((local_us, px4_us - local_us))
            self.samples += 1

    def offset_us(self, now_us: int) -> int | None:
        """PX4's clock minus the wall clock, from the samples of the last window; None
        without one (PX4 silent, or not reachable)."""
        with self._lock:
            while self._seen and self._seen[0][0] < now_us - self.window_us:
                self._seen.popleft()
            return max((offset for _, offset in self._seen), default=None)

    def on_sample(self, sample: Any) -> None:
        """Zenoh callback on PX4's VehicleOdometry: its first field, ``timestamp``."""
        received = time.time_ns() // 1000
        data = sample.payload.to_bytes()
        if len(data) < 12 or data[:2] not in (b"\x00\x01", b"\x00\x00"):
            return
        (px4_us,) = struct.unpack_from("<Q" if data[1] else ">Q", data, 4)
        self.observe(px4_us, received)


# -- the publisher ---------------------------------------------------------------------------------

class Px4Publisher:
    """Publishes each relocalized pose as VehicleOdometry on an rmw_zenoh publisher (declared
    by the map's node, which owns its key and token)."""

    def __init__(self, publisher: Any, gid: bytes, conf: Px4Conf,
                 clock: Px4Clock | None = None) -> None:
        self.publisher = publisher
        self.gid = gid
        self.conf = conf
        self.clock = clock
        self.reset_counter = 0
        self.published = 0
        self.withheld = 0
        self._seq = 1
        self._lock = threading.Lock()

    def bump_reset_counter(self) -> int:
        """Count a jump of the map frame (``map_from_odom`` re-anchored): EKF2 then resets its
        position and yaw to the next sample instead of fusing it as a measurement."""
        with self._lock:
            self.reset_counter = (self.reset_counter + 1) % 256
            return self.reset_counter

    def times_us(self, stamp: Any, now_us: int) -> tuple[int, int] | None:
        """(timestamp, timestamp_sample) for an image stamped ``stamp`` (wall clock): on PX4's
        clock when ``clock_topic`` is set (None while it is unknown, or when the image would
        predate PX4's boot: another clock), else the wall clock and the stamp as they are."""
        sample_us = microseconds(stamp)
        if self.clock is None:
            return now_us, sample_us
        offset = self.clock.offset_us(now_us)
        if offset is None or sample_us + offset < 0:
            return None
        return now_us + offset, sample_us + offset

    def publish(self, stamp: Any, out: convert.PoseOut, confidence: float) -> Any:
        """Publish ``out`` (the body pose in the map frame, as on the ROS pose topic) of the
        image stamped ``stamp`` (builtin_interfaces/Time), with :meth:`times_us`. The message
        sent, or None when withheld (PX4's clock unknown)."""
        times = self.times_us(stamp, time.time_ns() // 1000)
        if times is None:
            self._withhold(stamp)
            return None
        world_from_body = pose_from_tq(out.position, out.quat_xyzw)
        pose = px4_pose(world_from_body, out.covariance, world_frame=self.conf.world_frame,
                        body_frame=self.conf.body_frame)
        with self._lock:
            msg = vehicle_odometry(pose, timestamp_us=times[0], timestamp_sample_us=times[1],
                                   pose_frame=POSE_FRAMES[self.conf.pose_frame],
                                   reset_counter=self.reset_counter,
                                   quality=quality_of(confidence))
            attachment = graph.Attachment(self._seq, time.time_ns(), self.gid)
            self._seq += 1
            self.publisher.put(ros.encode(msg, VEHICLE_ODOMETRY), attachment=attachment.encode())
            self.published += 1
        return msg

    def _withhold(self, stamp: Any) -> None:
        self.withheld += 1
        if self.withheld == 1 or self.withheld % 100 == 0:
            log.warning(
                "PX4: VehicleOdometry withheld (%d so far): no sample of PX4's clock on %s in "
                "the last %.0f s, or image stamp %.3f s predates PX4's boot; EKF2 places a "
                "sample by its timestamp_sample, on PX4's clock (set [ros2.px4] clock_topic = "
                "\"\" if the camera stamps in PX4's clock already)", self.withheld,
                self.conf.clock_topic, CLOCK_WINDOW_S, microseconds(stamp) / 1e6)
