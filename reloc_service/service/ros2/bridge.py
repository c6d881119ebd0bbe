"""Every served map as a ROS 2 node on rmw_zenoh, on the service's own Zenoh session.

Per map, node ``<node_name>`` in namespace ``<namespace>/<map>``:

- subscribes to the camera (``sensor_msgs/CompressedImage`` or ``Image``), its
  ``sensor_msgs/CameraInfo``, the VIO odometry (``nav_msgs/Odometry`` or
  ``geometry_msgs/PoseStamped``) and a ``std_msgs/Bool`` lost flag;
- serves ``std_srvs/Trigger`` ``relocalize``: the newest image not yet answered for (waiting
  briefly for it, trigger.py) is relocalized through the same handler as a Zenoh relocalize
  query, the pose is published and the reply names the image and says what happened; while
  the lost flag is set, every Nth image is relocalized too; while tracking, with
  ``localize_every_n``, every Nth image is localized with the odometry's prior (localize.py);
- publishes ``geometry_msgs/PoseWithCovarianceStamped`` (the body pose in the map frame,
  the image's stamp, ROS's covariance convention), latched (qos.py);
- publishes its status on ``/diagnostics`` (diagnostics.py) and its warnings on ``/rosout``
  (rosout.py);
- builds the map: an image paired with the odometry of its stamp becomes a keyframe when
  the keyframe rule says so and, once the map can check it, it relocalizes in agreement with
  its odometry (:mod:`.mapping`, :mod:`.map_frame`: ``map_from_odom`` per odometry session,
  ``map -> odom`` on /tf, a std_srvs/SetBool ``mapping`` service); cameras and keyframes go
  through the service's writer (journaled like any put);
- declares the node, publisher, subscriber and service liveliness tokens and watches the
  graph: another node advertising one of our names with another type hash is reported loudly
  (rmw_zenoh would never deliver between them).

Zenoh callbacks only check the attachment and hand the sample to one ordered worker.
"""

from __future__ import annotations

import collections
import itertools
import logging
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import zenoh
from reloc_client import protocol as wire

from ...core.geometry import pose_from_tq
from ..workers import WorkerPool
from . import convert, diagnostics, graph
from . import types as ros
from .answering import CAMERA_ID, LatestImage, TriggerAnswering
from .conf import Ros2Conf
from .diagnostics import DIAGNOSTIC_ARRAY, DiagnosticsLoop, NodeStatus
from .localize import PriorLocalization
from .mapping import Mapping
from .node import NodeDeclarations, undeclare
from .trigger import TriggerDesk, image_problem, stamp_text

log = logging.getLogger(__name__)

#: Images waiting for the camera or the odometry of their stamp (VIO lags the camera; over
#: Zenoh, samples of different topics are not ordered among themselves).
PENDING_IMAGES = 64


class Host(Protocol):
    """What the bridge needs of the service (:class:`~reloc_service.service.app.Service`)."""

    session: Any
    prefix: str
    instance: str
    maps: dict[str, Any]
    relocalize_pool: WorkerPool | None

    def on_keyframe_sample(self, map_name: str, kf_id: int, payload: bytes | None) -> None: ...

    def on_camera_sample(self, map_name: str, camera_id: str, payload: bytes | None) -> None: ...

    def relocalize_payload(self, rt: Any, payload: bytes, queued_s: float) -> bytes: ...


class Ros2Bridge:
    """The ROS 2 face of a service (see module docstring)."""

    def __init__(self, host: Host, conf: Ros2Conf) -> None:
        self.host = host
        self.conf = conf
        self.session = host.session
        self.zid = str(self.session.zid())
        self.counters: collections.Counter[str] = collections.Counter()
        #: (name, type, hash) advertised by another node that does not match ours.
        self.mismatches: set[tuple[str, str, str]] = set()
        self._our_types: dict[str, tuple[str, str]] = {}   # ROS name -> (dds type, hash)
        self._ids = itertools.count()
        self._lock = threading.Lock()
        self._nodes: dict[str, MapNode] = {}
        self.worker = WorkerPool("ros2", workers=1, queue_size=256)
        self._graph = self.session.liveliness().declare_subscriber(
            f"{graph.ADMIN_SPACE}/{conf.domain_id}/**", self._on_token, history=True)
        self.diagnostics = (DiagnosticsLoop(self._publish_diagnostics, conf.diagnostics_period_s)
                            if conf.diagnostics_period_s > 0 else None)

    def hash_of(self, ros_type: str) -> str:
        """The type hash written in keys and tokens (configured, Humble's, or computed)."""
        return ros.key_hash(ros_type, self.conf.distro, self.conf.type_hashes)

    def next_id(self) -> int:
        return next(self._ids)

    def count(self, name: str) -> None:
        with self._lock:
            self.counters[name] += 1

    def serve_map(self, map_name: str) -> None:
        """Declare map ``map_name``'s node (once)."""
        with self._lock:
            if map_name in self._nodes:
                return
        node = MapNode(self, map_name)
        with self._lock:
            self._nodes[map_name] = node
            for name, typed in node.names.items():
                self._our_types[name] = typed

    def node(self, map_name: str) -> MapNode:
        return self._nodes[map_name]

    def diagnostics_changed(self) -> None:
        if self.diagnostics is not None:
            self.diagnostics.changed()

    def _publish_diagnostics(self) -> None:
        with self._lock:
            nodes = list(self._nodes.values())
        for node in nodes:
            node.publish_diagnostics()

    def close(self) -> None:
        """Undeclare every node (ROS tools see them go), then stop the worker."""
        if self.diagnostics is not None:
            self.diagnostics.close()
        with self._lock:
            nodes, self._nodes = list(self._nodes.values()), {}
        for node in nodes:
            node.close()
        undeclare(self._graph)
        self.worker.close(timeout=10.0)

    def _on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        endpoint = graph.parse_token(str(sample.key_expr))
        if endpoint is None or endpoint.zid == self.zid:
            return
        ours = self._our_types.get(endpoint.name)
        if ours is None or ours == (endpoint.dds_type, endpoint.type_hash):
            return
        key = (endpoint.name, endpoint.dds_type, endpoint.type_hash)
        if key not in self.mismatches:
            self.mismatches.add(key)
            log.warning(
                "ROS 2 TYPE MISMATCH on %s: node %s advertises %s %s, reloc uses %s %s; rmw_zenoh "
                "never delivers between different types or hashes (set [ros2] distro or "
                "type_hashes to match that node's ROS distribution)", endpoint.name,
                endpoint.node, endpoint.dds_type, endpoint.type_hash, ours[0], ours[1])


class MapNode(NodeDeclarations, TriggerAnswering):
    """One map's node: its entities (node.py), the latest image, the odometry, the keyframes
    and the answers of its relocalize service (answering.py)."""

    def __init__(self, bridge: Ros2Bridge, map_name: str) -> None:
        self.bridge = bridge
        self.map_name = map_name
        conf = self.conf = bridge.conf
        self.node = graph.Node(conf.domain_id, bridge.zid, bridge.next_id(), conf.node_name,
                               conf.node_namespace(map_name))
        self.qos = graph.Qos(depth=conf.qos_depth)   # an endpoint's without [ros2.qos] entry
        self.status = NodeStatus(map_name, on_change=bridge.diagnostics_changed)
        self.triggers = TriggerDesk(self._answer, max_age_s=conf.max_image_age_s,
                                    wait_s=conf.trigger_wait_s,
                                    topic=conf.resolve(conf.image_topic, map_name))
        self.keyframe_reports = diagnostics.KeyframeReports(
            self.status, bridge.host.instance,
            lambda: diagnostics.map_keyframes(bridge.host.maps.get(map_name)))
        self.body_from_cam = pose_from_tq(conf.body_from_cam[:3], conf.body_from_cam[3:])
        self.odometry = convert.StampedPoses()
        self.latest: LatestImage | None = None
        self.lost = False
        self.camera: dict[str, Any] | None = None
        self._pending: collections.deque[LatestImage] = collections.deque(maxlen=PENDING_IMAGES)
        self._images_lost = 0
        self._seq = itertools.count(1)
        self.names: dict[str, tuple[str, str]] = {}
        self._entities: list[Any] = []
        self._tokens: list[Any] = []
        self._pending_tokens: list[str] = []      # declared once every entity exists
        self._next_kf_id = self._restore_keyframes()
        self.localize = PriorLocalization(
            self, lambda latest, prior: self._submit_relocalize(latest, [], prior))
        self._declare()

    def map_frame_status(self) -> dict[str, str]:
        """The map frame's state (anchored, unanchored, lost), ``map_from_odom``
        (``tx ty tz qx qy qz qw``), whether mapping is on, and the counts, as strings."""
        return self.mapping.status()

    # -- samples (the bridge's worker) ----------------------------------------------------------
    def _decode_and_handle(self, payload: bytes, ros_type: str,
                           handle: Callable[[Any], None]) -> None:
        try:
            msg = ros.decode(payload, ros_type)
        except ValueError as exc:
            if handle == self._on_image:   # a Trigger after it answers that it was rejected
                self.triggers.received(None, None, str(exc))
            self.bridge.count("bad_samples")
            log.warning("map %s: a %s sample was not used: %s", self.map_name, ros_type, exc)
            return
        try:
            handle(msg)
        except Exception as exc:   # bad input never stops the bridge
            self.bridge.count("bad_samples")
            log.warning("map %s: a %s sample was not used: %s", self.map_name, ros_type, exc)

    def _on_camera_info(self, info: Any) -> None:
        camera = convert.camera_dict(info)
        if camera == self.camera:
            return
        put = wire.CameraPut(CAMERA_ID, wire.WireCamera.from_dict(camera))
        self.bridge.host.on_camera_sample(self.map_name, CAMERA_ID, put.encode())
        self.camera = camera
        self.bridge.count("cameras")
        self._retry_pending()

    def _on_lost(self, flag: Any) -> None:
        if flag.data and not self.lost:
            self._images_lost = 0      # every Nth image counted from the moment VIO was lost
        self.lost = bool(flag.data)
        self.mapping.frame.set_lost(self.lost)

    def _on_odometry(self, msg: Any) -> None:
        odometry = self.conf.odometry_type == "odometry"
        pose = msg.pose.pose if odometry else msg.pose
        # nav_msgs/Odometry carries the pose's covariance (PoseStamped has none): kept with
        # the pose, it becomes the covariance of the keyframes made from it.
        covariance = np.array(msg.pose.covariance, np.float64) if odometry else None
        stamp, odom_from_body = convert.stamp_seconds(msg.header.stamp), convert.pose_of(pose)
        if self.mapping.frame.on_odometry(msg.header.frame_id, stamp, odom_from_body):
            self.odometry = convert.StampedPoses()   # a reset: no image pairs across it
        self.odometry.add(stamp, odom_from_body, covariance)
        self.bridge.count("odometry")
        if self.px4 is not None and self.conf.px4.feed == "odometry":
            self._feed_px4(msg.header.stamp, odom_from_body, covariance)
        self.localize.retry()
        self._retry_pending()

    def _feed_px4(self, stamp: Any, odom_from_body: np.ndarray,
                  ros_covariance: np.ndarray | None) -> None:
        """The odometry composed with ``map_from_odom`` to PX4 while the map frame is anchored
        (at most ``max_rate_hz``); a new session's anchoring increments PX4's reset counter
        (EKF2 then resets to the next sample instead of fusing a jump)."""
        assert self.px4 is not None
        _, estimate = self.mapping.frame.current()
        if estimate is None:
            return
        seconds, session = convert.stamp_seconds(stamp), self.mapping.frame.session
        jumped = self._px4_session is not None and session != self._px4_session
        rate = self.conf.px4.max_rate_hz
        # (time going back starts a new session: the cap counts from its first message)
        if rate and not jumped and 0.0 <= seconds - self._px4_last_s < 1.0 / rate:
            return
        if jumped:
            self.px4.bump_reset_counter()
        self._px4_session, self._px4_last_s = session, seconds
        world_from_cam = estimate.map_from_odom @ odom_from_body @ self.body_from_cam
        covariance = self.mapping.camera_covariance(ros_covariance, odom_from_body, estimate)
        self.px4.publish(stamp, convert.body_pose(world_from_cam, covariance,
                                                  self.body_from_cam), 1.0)
        self.bridge.count("px4_odometry")

    def _retry_pending(self) -> None:
        """Images that waited for the camera or their odometry, in arrival order."""
        pending, self._pending = list(self._pending), collections.deque(maxlen=PENDING_IMAGES)
        for image in pending:
            self._maybe_keyframe(image)

    def _on_image(self, msg: Any) -> None:
        try:
            image = self._wire_image(msg)
            problem = image_problem(image, self._camera_size())
        except Exception as exc:
            problem = str(exc)
        if problem is not None:   # answered as rejected, never replaced by an older image
            self.status.count("images_rejected")
            received = self.triggers.received(msg.header.stamp, None, problem)
            raise ValueError(f"{received.label()} rejected: {problem}")
        latest = LatestImage(msg.header.stamp, image)
        self.latest = latest
        self.triggers.received(msg.header.stamp, image)
        self.bridge.count("images")
        n = self.conf.relocalize_every_n
        if self.lost and n:
            self._images_lost += 1
            if self._images_lost % n == 0:
                self._submit_relocalize(latest, [])
        self.localize.on_image(latest)
        self._maybe_keyframe(latest)

    def _wire_image(self, msg: Any) -> wire.WireImage:
        if self.conf.image_type == "compressed":
            return wire.WireImage.from_bytes(bytes(np.asarray(msg.data, np.uint8)))
        return wire.WireImage.from_array(convert.grey_from_raw(msg))

    def _camera_size(self) -> tuple[int, int] | None:
        camera = self.camera
        return None if camera is None else (int(camera["width"]), int(camera["height"]))

    def _maybe_keyframe(self, latest: LatestImage) -> None:
        """Add ``latest`` as a keyframe if its odometry is known and the rule selects it
        (kept waiting while the camera or the odometry of its stamp is unknown)."""
        stamp = convert.stamp_seconds(latest.stamp)
        paired = self.odometry.nearest_with_covariance(stamp, self.conf.max_stamp_difference_s)
        if self.camera is None or paired is None:
            if self.odometry.newest() > stamp + self.conf.max_stamp_difference_s:
                self.bridge.count("unpaired_images")   # its odometry will never come
            else:
                self._pending.append(latest)
            return
        odom_from_body, ros_covariance = paired
        self.mapping.consider(latest, odom_from_body, ros_covariance)

    def put_keyframe(self, latest: LatestImage, world_from_cam: np.ndarray,
                     pose_covariance: tuple[float, ...] | None) -> int:
        """Put ``latest`` as a keyframe at ``world_from_cam`` (the map frame) through the
        service's writer; its id (called under the mapping's lock: one put at a time)."""
        kf_id = self._next_kf_id
        self._next_kf_id += 1
        put = wire.KeyframePut(id=kf_id, image=latest.image,
                               world_from_cam=wire.WirePose.from_matrix(world_from_cam),
                               camera_id=CAMERA_ID,
                               timestamp=convert.stamp_seconds(latest.stamp),
                               pose_covariance=pose_covariance)
        self.keyframe_reports.put(kf_id, stamp_text(latest.stamp))
        self.bridge.host.on_keyframe_sample(self.map_name, kf_id, put.encode())
        self.bridge.count("keyframes")
        return kf_id

    def _on_event_sample(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        self.bridge.worker.submit(lambda _q: self.keyframe_reports.event(payload))

    def publish_diagnostics(self) -> None:
        """This node's DiagnosticStatus in a DiagnosticArray on /diagnostics."""
        if self.diagnostics_publisher is None:
            return
        mismatches = sum(1 for name, _t, _h in set(self.bridge.mismatches) if name in self.names)
        state = diagnostics.map_state(self.bridge.host.maps.get(self.map_name),
                                      camera_known=self.camera is not None, lost=self.lost,
                                      mismatches=mismatches)
        frame = getattr(self, "map_frame_status", None)   # the map frame's, when estimated
        with self.bridge._lock:
            shared = {f"bridge {k}": v for k, v in self.bridge.counters.items()}
        status = diagnostics.node_status(self.status, state, self.bridge.host.instance,
                                         {"trigger_waits": self.triggers.waited, **shared},
                                         dict(frame()) if callable(frame) else {})
        attachment = graph.Attachment(next(self._diagnostics_seq), time.time_ns(),
                                      self.diagnostics_gid)
        self.diagnostics_publisher.put(
            ros.encode(diagnostics.array_message([status]), DIAGNOSTIC_ARRAY),
            attachment=attachment.encode())

    def keyframe_covariance(self, ros_covariance: np.ndarray | None,
                             world_from_cam: np.ndarray, world_from_body: np.ndarray
                             ) -> tuple[float, ...] | None:
        """The odometry's pose covariance as the keyframe's (36 row-major values), or None
        (the map's default applies) where the odometry gives none or one that is not a
        covariance (counted: the keyframe is still made, the bridge goes on)."""
        if ros_covariance is None:
            return None
        try:
            ours = convert.odometry_covariance(ros_covariance, world_from_cam, world_from_body)
        except ValueError as exc:
            self.bridge.count("bad_odometry_covariance")
            log.warning("map %s: %s; the keyframe takes the map's default", self.map_name, exc)
            return None
        return None if ours is None else tuple(float(v) for v in ours.ravel())

    def _restore_keyframes(self) -> int:
        """The map's keyframes to the mapping (the rule applies to them too; an empty map's
        first odometry session defines the map frame); the next free id."""
        rt = self.bridge.host.maps.get(self.map_name)
        state = None if rt is None else rt.map_state()
        self.mapping = Mapping(self, CAMERA_ID, map_is_empty=state is None
                               or not state.keyframes)
        if state is None:
            return 0
        self.mapping.restore(state)
        return max(state.keyframe_ids(), default=-1) + 1

