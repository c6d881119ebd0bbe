"""``[ros2.px4]``: what reloc sends PX4's zenoh module (see :mod:`.px4`). A module of its own,
free of the ROS 2 extra's imports: the service's configuration is read by every install, the
PX4 publisher only where ``[ros2]`` is enabled."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ...core.errors import ConfigError
from ...core.plugins import make_conf

POSE_FRAME_NED = 1
POSE_FRAME_FRD = 2

WORLD_FRAMES = ("enu", "ned")
BODY_FRAMES = ("flu", "frd")
POSE_FRAMES = {"frd": POSE_FRAME_FRD, "ned": POSE_FRAME_NED}
_ABSOLUTE_NAME = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


#: What goes to PX4 (:attr:`Px4Conf.feed`).
FEEDS = ("odometry", "relocalizations")


@dataclass(frozen=True)
class Px4Conf:
    """``[ros2.px4]``: off unless ``enabled``."""

    enabled: bool = False
    #: PX4's zenoh module subscribes to this (dds_topics.yaml); a namespaced vehicle adds its
    #: prefix (``/px4_1/fmu/in/vehicle_visual_odometry``).
    topic: str = "/fmu/in/vehicle_visual_odometry"
    #: The map frame's convention: ``enu`` (ROS REP-103) or ``ned``.
    world_frame: str = "enu"
    #: The body frame of the published pose (the odometry's child frame): ``flu`` (REP-103)
    #: or ``frd``.
    body_frame: str = "flu"
    #: ``frd``: the map's heading is arbitrary (POSE_FRAME_FRD); ``ned``: the map is aligned
    #: with true north (POSE_FRAME_NED).
    pose_frame: str = "frd"
    #: PX4's own VehicleOdometry (its ``timestamp`` is PX4's boot clock): ``timestamp_sample``
    #: is the image stamp moved onto that clock. "": the image stamp as is (a camera already
    #: stamping in PX4's clock).
    clock_topic: str = "/fmu/out/vehicle_odometry"
    #: ``odometry``: every odometry message composed with ``map_from_odom`` while the map
    #: frame is anchored (the VIO's rate and smoothness, in the map frame; nothing while
    #: unanchored; a re-anchoring increments ``reset_counter``); reloc is then EKF2's only
    #: vision source. ``relocalizations``: only relocalized poses (a Trigger, the lost mode).
    feed: str = "odometry"
    #: At most this many VehicleOdometry messages per second from the odometry (PX4's docs
    #: ask 30-50 Hz of external vision); 0: every odometry message.
    max_rate_hz: float = 30.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_rate_hz) and self.max_rate_hz >= 0):
            raise ConfigError(f"ros2.px4.max_rate_hz: expected a number >= 0 (0: every "
                              f"odometry message), got {self.max_rate_hz}")
        for key, choices in (("world_frame", WORLD_FRAMES), ("body_frame", BODY_FRAMES),
                             ("pose_frame", tuple(POSE_FRAMES)), ("feed", FEEDS)):
            if getattr(self, key) not in choices:
                raise ConfigError(f"ros2.px4.{key}: expected one of {list(choices)}, got "
                                  f"{getattr(self, key)!r}")
        for key, example in (("topic", "/fmu/in/vehicle_visual_odometry"),
                             ("clock_topic", "/fmu/out/vehicle_odometry")):
            value = getattr(self, key)
            if not (_ABSOLUTE_NAME.match(value) or (key == "clock_topic" and value == "")):
                raise ConfigError(f"ros2.px4.{key}: expected an absolute ROS name like "
                                  f"{example!r}, got {value!r}")


def px4_conf(value: Any) -> Px4Conf:
    """``[ros2.px4]`` (a table, or a Px4Conf already) as a Px4Conf; ConfigError otherwise."""
    if isinstance(value, Px4Conf):
        return value
    if not isinstance(value, Mapping):
        raise ConfigError(f"ros2.px4: expected a table ([ros2.px4] with enabled, topic, "
                          f"world_frame, body_frame, pose_frame, clock_topic, feed, "
                          f"max_rate_hz), got {value!r}")
    return make_conf(Px4Conf, value, owner="ros2.px4")
