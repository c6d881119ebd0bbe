"""The ``[ros2]`` section of ``reloc serve``: every served map as a ROS 2 node on rmw_zenoh.

Names follow ROS 2: an absolute name (``/camera/image_raw/compressed``) is used as is, a
relative one (``pose``) is put under the map's node namespace ``<namespace>/<map>``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from ...core.errors import ConfigError
from . import qos as qos_conf
from .px4_conf import Px4Conf, px4_conf

#: Distros whose rmw_zenoh puts RIHS01 type hashes in keys; Humble writes
#: ``TypeHashNotSupported``.
DISTROS = ("jazzy", "kilted", "rolling", "humble")
IMAGE_TYPES = ("compressed", "raw")
ODOMETRY_TYPES = ("odometry", "pose_stamped")
KEYFRAME_RULES = ("overlap", "distance")
_NAME = re.compile(r"^/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$")


@dataclass(frozen=True)
class Ros2Conf:
    """See module docstring; off unless ``enabled``."""

    enabled: bool = False
    domain_id: int = 0
    #: Each map is node ``node_name`` in namespace ``<namespace>/<map>``.
    namespace: str = "/reloc"
    node_name: str = "reloc"
    distro: str = "jazzy"
    #: ROS type (``geometry_msgs/msg/PoseWithCovarianceStamped``) -> hash, replacing the
    #: computed one (a distro whose message definitions differ).
    type_hashes: Any = field(default_factory=lambda: MappingProxyType({}))
    image_topic: str = "/camera/image_raw/compressed"
    #: ``compressed`` (sensor_msgs/CompressedImage, JPEG/PNG) or ``raw`` (sensor_msgs/Image).
    image_type: str = "compressed"
    camera_info_topic: str = "/camera/camera_info"
    odometry_topic: str = "/odom"
    #: ``odometry`` (nav_msgs/Odometry) or ``pose_stamped`` (geometry_msgs/PoseStamped).
    odometry_type: str = "odometry"
    pose_topic: str = "pose"
    relocalize_service: str = "relocalize"
    #: std_msgs/Bool: while the last value is true, every ``relocalize_every_n``-th image is
    #: relocalized and the pose published (0: only on a service call).
    lost_topic: str = "lost"
    relocalize_every_n: int = 0
    #: While tracking (not lost, the map frame anchored), every ``localize_every_n``-th image
    #: is localized with the odometry's pose in the map frame and its covariance as the
    #: query's prior, and the pose published (localize.py; 0: off).
    localize_every_n: int = 0
    #: The frame id of the published poses (the map's frame: the VIO frame it was built in).
    frame_id: str = "map"
    qos_depth: int = 10
    #: The camera's pose in the body frame of the odometry, ``tx ty tz qx qy qz qw``
    #: (camera x right, y down, z forward); the published pose is the body's.
    body_from_cam: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    #: Build the map from odometry + images: an image becomes a keyframe when the keyframe
    #: rule selects it and its relocalization agrees with its odometry (mapping.py). False: a
    #: finished map; the odometry still places the map frame (map -> odom, PX4's feed).
    build_map: bool = True
    keyframe_min_distance_m: float = 0.15
    keyframe_min_angle_deg: float = 15.0
    #: An image and an odometry message pair when their stamps differ by at most this.
    max_stamp_difference_s: float = 0.02
    # -- the map frame (deploy/ros2/README.md, "The map frame") --------------------------------
    #: ``overlap``: a keyframe when the camera is farther than ``keyframe_overlap_fraction`` x
    #: the scene depth of each keyframe (``keyframe_default_depth_m`` until the map knows it);
    #: ``distance``: farther than ``keyframe_min_distance_m``. Either: or turned more than
    #: ``keyframe_min_angle_deg``.
    keyframe_rule: str = "overlap"
    keyframe_overlap_fraction: float = 0.12
    keyframe_default_depth_m: float = 2.0
    #: std_srvs/SetBool: false pauses mapping, true resumes it.
    mapping_service: str = "mapping"
    #: ``map -> odom`` (tf2_msgs/TFMessage) is published here, child frame the odometry's
    #: header.frame_id unless ``odom_frame_id`` names it; republished with the images at most
    #: every ``tf_period_s`` while anchored (0: only when the estimate changes).
    tf_topic: str = "/tf"
    odom_frame_id: str = ""
    tf_period_s: float = 0.1
    #: A new odometry session is anchored by this many consecutive agreeing relocalizations;
    #: agreement is a Mahalanobis distance below the chi-square quantile of this confidence.
    anchor_samples: int = 3
    anchor_confidence: float = 0.999
    #: Keyframes are checked by relocalization once the map holds this many (before, the first
    #: session of an empty map adds them unquestioned: they define the map frame).
    anchor_min_keyframes: int = 3
    #: Odometry moving faster than this between two messages has jumped (a reset; 0: off).
    odometry_max_speed_m_s: float = 20.0
    odometry_max_turn_rate_deg_s: float = 720.0

    #: Trigger answers for the newest image received at most this long ago (reloc's clock,
    #: not the stamp: a drone's clock may be another); ten frames of a 10 Hz camera, so a
    #: dropped frame or two does not fail a call, while a stalled camera does.
    max_image_age_s: float = 1.0
    #: A Trigger with no unanswered image waits this long for the next one (the image
    #: published just before the call may still be on its way: samples of different keys
    #: are not ordered); 2.5 frames of a 10 Hz camera.
    trigger_wait_s: float = 0.25
    #: /diagnostics (diagnostic_msgs/DiagnosticArray) every this many seconds and on each
    #: change (ROS's diagnostic_updater publishes every 1 s); 0: off.
    diagnostics_period_s: float = 1.0
    diagnostics_topic: str = "/diagnostics"
    #: The bridge's WARNING and ERROR lines on /rosout (rcl_interfaces/Log), as every node's.
    rosout: bool = True
    #: Per-topic QoS overrides: ``[ros2.qos.<topic>]`` with reliability ("reliable",
    #: "best_effort"), durability ("volatile", "transient_local"), depth; topics in
    #: qos.TOPICS. Resolved into ``topic_qos``.
    qos: Any = field(default_factory=lambda: MappingProxyType({}))

    #: ``[ros2.px4]``: the pose as px4_msgs/VehicleOdometry for PX4's zenoh module (ros2/px4.py).
    px4: Px4Conf = field(default_factory=Px4Conf)

    def __post_init__(self) -> None:
        object.__setattr__(self, "px4", px4_conf(self.px4))
        if self.px4.enabled and not self.enabled:
            raise ConfigError("ros2.px4.enabled = true needs ros2.enabled = true (the PX4 "
                              "publisher belongs to each map's ROS 2 node)")
        if not 0 <= self.domain_id <= 232:
            raise ConfigError(f"ros2.domain_id: expected 0..232, got {self.domain_id}")
        _check_choice("distro", self.distro, DISTROS)
        _check_choice("image_type", self.image_type, IMAGE_TYPES)
        _check_choice("odometry_type", self.odometry_type, ODOMETRY_TYPES)
        _check_choice("keyframe_rule", self.keyframe_rule, KEYFRAME_RULES)
        if not self.namespace.startswith("/") or not (self.namespace == "/"
                                                       or _NAME.match(self.namespace)):
            raise ConfigError(f"ros2.namespace: expected an absolute ROS name like '/reloc', "
                              f"got {self.namespace!r}")
        for key in ("node_name", "frame_id"):
            if not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", getattr(self, key)):
                raise ConfigError(f"ros2.{key}: expected letters, digits and '_', got "
                                  f"{getattr(self, key)!r}")
        for key in ("image_topic", "camera_info_topic", "odometry_topic", "pose_topic",
                    "relocalize_service", "lost_topic", "mapping_service", "tf_topic",
                    "diagnostics_topic"):
            if not _NAME.match(getattr(self, key)):
                raise ConfigError(f"ros2.{key}: expected a ROS name ('/a/b' or 'b'), got "
                                  f"{getattr(self, key)!r}")
        self._check_numbers()
        object.__setattr__(self, "body_from_cam", tuple(float(v) for v in self.body_from_cam))
        if not isinstance(self.type_hashes, dict | MappingProxyType) or not all(
                isinstance(k, str) and isinstance(v, str) for k, v in self.type_hashes.items()):
            raise ConfigError(f"ros2.type_hashes: expected a table of type -> hash strings, "
                              f"got {self.type_hashes!r}")
        object.__setattr__(self, "type_hashes", MappingProxyType(dict(self.type_hashes)))
        object.__setattr__(self, "_topic_qos", qos_conf.parse_table(self.qos, self.qos_depth))
        object.__setattr__(self, "qos", MappingProxyType(
            {k: MappingProxyType(dict(v)) for k, v in self.qos.items()}))

    def topic_qos(self, topic: str) -> qos_conf.TopicQos:
        """The QoS of ``topic`` (a key of :data:`qos.TOPICS`), overrides applied."""
        return self._topic_qos[topic]  # type: ignore[attr-defined, no-any-return]

    def _check_numbers(self) -> None:
        if self.qos_depth < 1 or self.relocalize_every_n < 0:
            raise ConfigError(f"ros2: expected qos_depth >= 1 and relocalize_every_n >= 0, "
                              f"got {self.qos_depth} and {self.relocalize_every_n}")
        if self.localize_every_n < 0:
            raise ConfigError(f"ros2.localize_every_n: expected an integer >= 0 (0: off), "
                              f"got {self.localize_every_n}")
        for key in ("keyframe_min_distance_m", "keyframe_min_angle_deg",
                    "max_stamp_difference_s", "max_image_age_s", "trigger_wait_s",
                    "diagnostics_period_s"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"ros2.{key}: expected a number >= 0, got {value}")
        self._check_map_frame_numbers()
        if self.max_image_age_s <= 0:
            raise ConfigError(f"ros2.max_image_age_s: expected a number > 0, got "
                              f"{self.max_image_age_s}")
        pose = self.body_from_cam
        if len(pose) != 7 or not all(isinstance(v, int | float) and math.isfinite(v)
                                     for v in pose):
            raise ConfigError(f"ros2.body_from_cam: expected 7 numbers tx ty tz qx qy qz qw, "
                              f"got {list(pose)!r}")
        if abs(math.sqrt(sum(v * v for v in pose[3:])) - 1.0) > 1e-3:
            raise ConfigError(f"ros2.body_from_cam: the quaternion {list(pose[3:])} is not "
                              "unit length")

    def _check_map_frame_numbers(self) -> None:
        for key in ("keyframe_overlap_fraction", "keyframe_default_depth_m", "tf_period_s",
                    "odometry_max_speed_m_s", "odometry_max_turn_rate_deg_s"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"ros2.{key}: expected a number >= 0, got {value}")
        if self.keyframe_default_depth_m <= 0 or self.keyframe_overlap_fraction <= 0:
            raise ConfigError(f"ros2: expected keyframe_overlap_fraction > 0 and "
                              f"keyframe_default_depth_m > 0, got {self.keyframe_overlap_fraction}"
                              f" and {self.keyframe_default_depth_m}")
        if self.anchor_samples < 1 or self.anchor_min_keyframes < 1:
            raise ConfigError(f"ros2: expected anchor_samples >= 1 and anchor_min_keyframes >= 1,"
                              f" got {self.anchor_samples} and {self.anchor_min_keyframes}")
        if not 0.5 < self.anchor_confidence < 1:
            raise ConfigError(f"ros2.anchor_confidence: expected a probability in (0.5, 1), got "
                              f"{self.anchor_confidence}")
        if self.odom_frame_id and not re.match(r"^[A-Za-z_][A-Za-z0-9_/]*$", self.odom_frame_id):
            raise ConfigError(f"ros2.odom_frame_id: expected a tf frame name, got "
                              f"{self.odom_frame_id!r}")

    def node_namespace(self, map_name: str) -> str:
        """The namespace of map ``map_name``'s node (the map name made a ROS name chunk)."""
        chunk = re.sub(r"[^A-Za-z0-9_]", "_", map_name)
        if not re.match(r"^[A-Za-z_]", chunk):
            chunk = "m" + chunk
        return f"{self.namespace.rstrip('/')}/{chunk}"

    def resolve(self, name: str, map_name: str) -> str:
        """``name`` as an absolute ROS name for map ``map_name``'s node."""
        return name if name.startswith("/") else f"{self.node_namespace(map_name)}/{name}"


def _check_choice(key: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ConfigError(f"ros2.{key}: expected one of {list(choices)}, got {value!r}")
