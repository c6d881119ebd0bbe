"""A map node's ``relocalize`` std_srvs/Trigger service: a call is handed to the trigger desk
(trigger.py), which picks the image it answers for; that image is relocalized through the
service's relocalize pool and handler (as a Zenoh relocalize query is), the pose is published
as a geometry_msgs/PoseWithCovarianceStamped and fed to the map frame, and the reply names the
image and says what happened. The lost mode's relocalizations take the same path without a call.

:class:`TriggerAnswering` is a part of :class:`.bridge.MapNode`, reading the node's state
through the attributes listed on the class.
"""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh
from reloc_client import protocol as wire

from ...algorithms.relocalizers.tracking import TRACK
from .. import codec
from . import convert, graph, px4
from . import types as ros
from .conf import Ros2Conf
from .diagnostics import NodeStatus
from .mapping import Mapping
from .trigger import ReceivedImage, TriggerDesk, stamp_text

log = logging.getLogger(__name__)

CAMERA_ID = "ros2"

#: A Trigger call: its query and the request's attachment (the reply carries both back).
Call = tuple[zenoh.Query, graph.Attachment]


@dataclass(frozen=True)
class LatestImage:
    """An image received on the camera topic."""

    stamp: Any                      # builtin_interfaces/Time, copied to the published pose
    image: wire.WireImage



class TriggerAnswering:
    """The relocalize service's answers (see module docstring); mixed into
    :class:`.bridge.MapNode`."""

    # the node's state the answers read (set by MapNode.__init__ and its declarations)
    bridge: Any                                  # bridge.Ros2Bridge
    conf: Ros2Conf
    map_name: str
    status: NodeStatus
    triggers: TriggerDesk
    mapping: Mapping
    odometry: convert.StampedPoses
    camera: dict[str, Any] | None
    body_from_cam: np.ndarray
    px4: px4.Px4Publisher | None
    publisher: Any
    pose_gid: bytes
    service_key: str
    _seq: itertools.count[int]

    def _on_request(self, query: zenoh.Query) -> None:
        attachment = query.attachment.to_bytes() if query.attachment is not None else None
        try:
            request = graph.Attachment.decode(attachment)
            ros.decode(query.payload.to_bytes() if query.payload is not None else b"",
                       "std_srvs/srv/Trigger_Request")
        except ValueError as exc:
            self.bridge.count("dropped_requests")
            log.warning("map %s: dropping a relocalize request: %s", self.map_name, exc)
            query.drop()
            return
        self.status.count("trigger_calls")
        self.triggers.call((query, request))

    def _answer(self, calls: list[Call], received: ReceivedImage | None, reason: str) -> None:
        """The Trigger calls answer for ``received`` (relocalized, or rejected), or fail
        with ``reason`` when there is no image to answer for (trigger.py)."""
        if received is None or received.image is None:
            message = reason if received is None else (f"{received.label()} was rejected: "
                                                        f"{received.problem}")
            image = "" if received is None or received.stamp is None else stamp_text(
                received.stamp)
            for call in calls:
                self._reply(*call, False, message)
            self.status.answered(False, message, image)
            return
        self._submit_relocalize(LatestImage(received.stamp, received.image), calls)

    def _submit_relocalize(self, latest: LatestImage, calls: list[Call] | None,
                           prior: wire.Prior | None = None) -> None:
        """Relocalize ``latest`` for ``calls`` (none: the lost mode's, or with ``prior`` the
        tracking mode's, localize.py)."""
        calls = calls or []
        pool = self.bridge.host.relocalize_pool
        if pool is None or not pool.submit(lambda queued: self._relocalize(latest, calls,
                                                                           queued, prior)):
            self.bridge.count("busy")
            self._report(calls, latest, False, "all relocalize workers busy; call again later",
                         prior)

    def _relocalize(self, latest: LatestImage, calls: list[Call], queued_s: float,
                    prior: wire.Prior | None = None) -> None:
        success, message = False, "not relocalized"
        try:
            success, message = self._relocalize_and_publish(latest, queued_s, prior)
        except Exception as exc:
            code, text = codec.error_of(exc)
            message = f"{code.value}: {text}"
        finally:
            self._report(calls, latest, success, message, prior)

    def _report(self, calls: list[Call], latest: LatestImage, success: bool,
                message: str, prior: wire.Prior | None = None) -> None:
        """Reply to ``calls`` naming the image; a relocalization without a call (the lost
        mode's, or with a prior the tracking mode's) is reported to the status."""
        image = stamp_text(latest.stamp)
        message = f"image stamped {image}: {message}"
        for call in calls:
            self._reply(*call, success, message)
        if calls:
            self.status.answered(success, message, image)
        elif prior is not None:
            self.status.localized(success, message, image)
        else:
            self.status.lost_mode(success, message, image)

    def _relocalize_and_publish(self, latest: LatestImage, queued_s: float,
                                prior: wire.Prior | None = None) -> tuple[bool, str]:
        rt = self.bridge.host.maps.get(self.map_name)
        if rt is None:
            return False, f"map {self.map_name!r} is not served"
        if self.camera is None:
            topic = self.conf.resolve(self.conf.camera_info_topic, self.map_name)
            return False, f"no camera_info received on {topic} yet"
        request = wire.RelocalizeRequest(image=latest.image, camera_id=CAMERA_ID,
                                         timestamp=convert.stamp_seconds(latest.stamp),
                                         prior=prior)
        reply = wire.RelocalizeReply.decode(
            self.bridge.host.relocalize_payload(rt, request.encode(), queued_s), rt.limits)
        if reply.status is not wire.ReplyStatus.OK or reply.world_from_cam is None:
            self.bridge.count("not_relocalized")
            return False, reply.reason or reply.status.value
        world_from_cam = reply.world_from_cam.matrix()
        covariance = None if reply.covariance is None else np.reshape(reply.covariance, (6, 6))
        out = convert.body_pose(world_from_cam, covariance, self.body_from_cam)
        self.publish_pose(latest.stamp, out)
        self.bridge.count("poses")
        if prior is not None and reply.method == TRACK:
            self.bridge.count("tracked_poses")   # the prior's windows answered
        if self.px4 is not None and self.conf.px4.feed == "relocalizations":
            self.px4.publish(latest.stamp, out, reply.confidence)
        self._observe(latest, world_from_cam, covariance)
        x, y, z = out.position
        return True, (f"relocalized: position {x:.3f} {y:.3f} {z:.3f} m in {self.conf.frame_id}, "
                      f"{reply.inliers} inliers, confidence {reply.confidence:.2f}")

    def _observe(self, latest: LatestImage, map_from_cam: np.ndarray,
                 covariance: np.ndarray | None) -> None:
        """A relocalized image paired with the odometry of its stamp is one more
        ``map_from_odom`` sample (mapping.py); without odometry or a covariance, nothing."""
        paired = self.odometry.nearest_with_covariance(convert.stamp_seconds(latest.stamp),
                                                       self.conf.max_stamp_difference_s)
        if paired is None or covariance is None:
            return
        odom_from_body, ros_covariance = paired
        self.mapping.observe(latest, odom_from_body, ros_covariance, map_from_cam, covariance)

    def publish_pose(self, stamp: Any, out: convert.PoseOut) -> None:
        msg = pose_message(stamp, self.conf.frame_id, out)
        attachment = graph.Attachment(next(self._seq), time.time_ns(), self.pose_gid)
        self.publisher.put(ros.encode(msg, ros.POSE_WITH_COVARIANCE_STAMPED),
                           attachment=attachment.encode())

    def _reply(self, query: zenoh.Query, request: graph.Attachment, success: bool,
               message: str) -> None:
        """The Trigger response, attached with the request's sequence number and the
        client's GID (how rmw_zenoh's client matches it to its call)."""
        response = ros.message("std_srvs/srv/Trigger_Response", success=success,
                               message=message)
        attachment = graph.Attachment(request.sequence_number, time.time_ns(), request.gid)
        try:
            query.reply(self.service_key, ros.encode(response, "std_srvs/srv/Trigger_Response"),
                        attachment=attachment.encode())
        except Exception as exc:   # the client may have gone
            log.debug("relocalize reply not sent: %s", exc)
        finally:
            query.drop()



def pose_message(stamp: Any, frame_id: str, out: convert.PoseOut) -> Any:
    """A geometry_msgs/PoseWithCovarianceStamped."""
    m = ros.message
    header = m("std_msgs/msg/Header", stamp=stamp, frame_id=frame_id)
    pose = m("geometry_msgs/msg/Pose",
             position=m("geometry_msgs/msg/Point", x=float(out.position[0]),
                        y=float(out.position[1]), z=float(out.position[2])),
             orientation=m("geometry_msgs/msg/Quaternion", x=float(out.quat_xyzw[0]),
                           y=float(out.quat_xyzw[1]), z=float(out.quat_xyzw[2]),
                           w=float(out.quat_xyzw[3])))
    with_cov = m("geometry_msgs/msg/PoseWithCovariance", pose=pose,
                 covariance=np.ascontiguousarray(out.covariance, np.float64).ravel())
    return m(ros.POSE_WITH_COVARIANCE_STAMPED, header=header, pose=with_cov)
