"""A map node's declarations on the ROS 2 graph: its node token, the publishers (pose,
/diagnostics, /rosout, /tf, PX4), subscribers (camera, camera_info, odometry, lost flag, the
map's events) and services (``relocalize``, ``mapping``) it declares, each with its liveliness
token, and their undeclaration when the node closes.

:class:`NodeDeclarations` is a part of :class:`.bridge.MapNode`: it declares the node's own
handlers, so it reads the node's state through the attributes listed on the class.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from typing import Any

import zenoh
from reloc_client import protocol as wire

from . import graph, px4, qos, rosout
from . import types as ros
from .conf import Ros2Conf
from .diagnostics import DIAGNOSTIC_ARRAY
from .mapping import Mapping
from .qos import TopicQos
from .trigger import TriggerDesk

log = logging.getLogger(__name__)


class NodeDeclarations:
    """What a map node declares (see module docstring); mixed into :class:`.bridge.MapNode`."""

    # the node's state the declarations read (set by MapNode.__init__)
    bridge: Any                                  # bridge.Ros2Bridge
    conf: Ros2Conf
    map_name: str
    node: graph.Node
    qos: graph.Qos
    mapping: Mapping
    triggers: TriggerDesk
    names: dict[str, tuple[str, str]]
    _entities: list[Any]
    _tokens: list[Any]
    _pending_tokens: list[str]
    # the node's handlers the declarations subscribe and serve
    _on_image: Callable[[Any], None]
    _on_camera_info: Callable[[Any], None]
    _on_odometry: Callable[[Any], None]
    _on_lost: Callable[[Any], None]
    _on_event_sample: Callable[[zenoh.Sample], None]
    _on_request: Callable[[zenoh.Query], None]
    _decode_and_handle: Callable[[bytes, str, Callable[[Any], None]], None]

    def _declare(self) -> None:
        conf, session = self.conf, self.bridge.session
        self._tokens.append(session.liveliness().declare_token(self.node.token()))
        pose_qos = conf.topic_qos("pose")
        pose_key, pose_token = self._endpoint(graph.EntityKind.PUBLISHER, conf.pose_topic,
                                              ros.POSE_WITH_COVARIANCE_STAMPED, pose_qos)
        self.pose_gid = graph.gid_of(pose_token)
        self.publisher = qos.declare_publisher(session, pose_key, pose_qos)
        self._entities.append(self.publisher)
        self.diagnostics_publisher: Any = None
        if conf.diagnostics_period_s > 0:
            diag_qos = conf.topic_qos("diagnostics")
            diag_key, diag_token = self._endpoint(graph.EntityKind.PUBLISHER,
                                                  conf.diagnostics_topic, DIAGNOSTIC_ARRAY,
                                                  diag_qos)
            self.diagnostics_gid = graph.gid_of(diag_token)
            self._diagnostics_seq = itertools.count(1)   # rmw_zenoh counts per publisher
            self.diagnostics_publisher = qos.declare_publisher(session, diag_key, diag_qos)
            self._entities.append(self.diagnostics_publisher)
        if conf.rosout:
            self._declare_rosout()
        image_type = ros.COMPRESSED_IMAGE if conf.image_type == "compressed" else ros.IMAGE
        odometry_type = ros.ODOMETRY if conf.odometry_type == "odometry" else ros.POSE_STAMPED
        self._subscribe(conf.image_topic, image_type, self._on_image, "image")
        self._subscribe(conf.camera_info_topic, ros.CAMERA_INFO, self._on_camera_info,
                        "camera_info")
        # the odometry places the map frame (map -> odom) even when no keyframe is added
        self._subscribe(conf.odometry_topic, odometry_type, self._on_odometry, "odometry")
        self._subscribe(conf.lost_topic, ros.BOOL, self._on_lost, "lost")
        self._entities.append(session.declare_subscriber(
            wire.keys.events(self.bridge.host.prefix, self.map_name), self._on_event_sample))
        self._declare_mapping()
        service_key, _ = self._endpoint(graph.EntityKind.SERVICE, conf.relocalize_service,
                                        ros.TRIGGER)
        self.service_key = service_key
        self._entities.append(session.declare_queryable(service_key, self._on_request,
                                                        complete=True))
        self.px4: px4.Px4Publisher | None = None
        self._px4_session: int | None = None   # the map frame's session PX4 was last fed
        self._px4_last_s = float("-inf")
        if conf.px4.enabled:
            self.px4 = self._declare_px4()
        for token in self._pending_tokens:
            self._tokens.append(session.liveliness().declare_token(token))
        log.info("ROS 2 node %s/%s (domain %d) serves map %s: pose on %s, service %s",
                 self.node.namespace, self.node.name, conf.domain_id, self.map_name,
                 conf.resolve(conf.pose_topic, self.map_name),
                 conf.resolve(conf.relocalize_service, self.map_name))

    def _declare_mapping(self) -> None:
        """The ``map -> odom`` publisher on /tf and the ``mapping`` SetBool service."""
        conf, session = self.conf, self.bridge.session
        tf_key, tf_token = self._endpoint(graph.EntityKind.PUBLISHER, conf.tf_topic,
                                          ros.TF_MESSAGE)
        tf_publisher = session.declare_publisher(tf_key)
        self._entities.append(tf_publisher)
        service_key, _ = self._endpoint(graph.EntityKind.SERVICE, conf.mapping_service,
                                        ros.SET_BOOL)
        self.mapping.attach(tf_publisher, graph.gid_of(tf_token), service_key)
        self._entities.append(session.declare_queryable(service_key, self.mapping.on_request,
                                                        complete=True))

    def _declare_px4(self) -> px4.Px4Publisher:
        """The VehicleOdometry publisher PX4's zenoh module subscribes to, and the subscriber
        to PX4's own VehicleOdometry whose stamps give PX4's clock (ros2/px4.py)."""
        conf, session, odometry = self.conf.px4, self.bridge.session, px4.vehicle_odometry_type()
        clock = None
        if conf.clock_topic:
            clock_key, _ = self._endpoint(graph.EntityKind.SUBSCRIBER, conf.clock_topic, odometry)
            clock = px4.Px4Clock()
            # PX4's attachments differ from rmw_zenoh's across versions: the stamp is read
            # from the payload, so every sample is taken
            self._entities.append(session.declare_subscriber(clock_key, clock.on_sample))
        key, token = self._endpoint(graph.EntityKind.PUBLISHER, conf.topic, odometry)
        publisher = px4.Px4Publisher(session.declare_publisher(key), graph.gid_of(token), conf,
                                     clock)
        self._entities.append(publisher.publisher)
        return publisher

    def _declare_rosout(self) -> None:
        """/rosout as every node has it; this node's warnings go there (rosout.py)."""
        key, token = self._endpoint(graph.EntityKind.PUBLISHER, rosout.ROSOUT, rosout.LOG,
                                    rosout.TOKEN_QOS)
        publisher = qos.declare_publisher(self.bridge.session, key, rosout.TOPIC_QOS)
        self._entities.append(publisher)
        self.rosout_handler = rosout.RosoutHandler.attach(
            self.map_name, rosout.LogPublisher(
                publisher, graph.gid_of(token),
                rosout.node_logger_name(self.node.namespace, self.node.name)))

    def _endpoint(self, kind: graph.EntityKind, name: str, ros_type: str,
                  topic_qos: TopicQos | graph.Qos | None = None) -> tuple[str, str]:
        """(data key, token) of an endpoint (``topic_qos`` in its token; None: reliable,
        volatile, ``qos_depth``); the token is declared after every entity."""
        absolute = self.conf.resolve(name, self.map_name)
        dds, type_hash = ros.dds_name(ros_type), self.bridge.hash_of(ros_type)
        token_qos = (self.qos if topic_qos is None else topic_qos
                     if isinstance(topic_qos, graph.Qos) else qos.token_qos(topic_qos))
        token = self.node.endpoint_token(self.bridge.next_id(), kind, absolute, dds, type_hash,
                                         token_qos)
        self._pending_tokens.append(token)
        self.names[absolute] = (dds, type_hash)
        return graph.data_key(self.conf.domain_id, absolute, dds, type_hash), token

    def _subscribe(self, name: str, ros_type: str, handle: Callable[[Any], None],
                   topic: str | None = None) -> None:
        """Subscribe with the QoS of ``topic`` (a key of ``[ros2.qos]``; None: the default)."""
        topic_qos = (qos.TopicQos(depth=self.conf.qos_depth) if topic is None
                     else self.conf.topic_qos(topic))
        key, _ = self._endpoint(graph.EntityKind.SUBSCRIBER, name, ros_type, topic_qos)
        bridge = self.bridge

        def on_sample(sample: zenoh.Sample) -> None:
            if sample.kind != zenoh.SampleKind.PUT:
                return
            attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
            try:
                graph.Attachment.decode(attachment)
            except ValueError as exc:   # rmw_zenoh drops such samples; so do we
                bridge.count("dropped_samples")
                log.debug("dropping a sample on %s: %s", key, exc)
                return
            payload = sample.payload.to_bytes()
            if not bridge.worker.submit(lambda _q: self._decode_and_handle(payload, ros_type,
                                                                            handle)):
                bridge.count("dropped_busy")

        self._entities.append(qos.declare_subscriber(bridge.session, key, topic_qos, on_sample))

    def close(self) -> None:
        self.triggers.close()   # waiting calls are answered before the service goes
        handler = getattr(self, "rosout_handler", None)
        if handler is not None:
            handler.detach()
        for entity in [*self._tokens, *reversed(self._entities)]:
            undeclare(entity)
        self._tokens, self._entities = [], []


def undeclare(entity: Any) -> None:
    """Undeclare a Zenoh entity or token; a failure (the session closing) is only logged."""
    try:
        entity.undeclare()
    except Exception as exc:
        log.debug("undeclare failed: %s", exc)
