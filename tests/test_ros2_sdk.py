"""A third-party rmw_zenoh implementation talks to reloc's ROS 2 node: zenoh-ros2-sdk (PyPI,
pure Python, written against rmw_zenoh_cpp) lists reloc's topics and service from the graph,
calls ``std_srvs/Trigger`` and receives the ``PoseWithCovarianceStamped``, computing its keys
and type hashes from the .msg/.srv files of tests/data/ros2_interfaces. The map is built by
the stand-in of test_ros2_bridge.py (images and odometry)."""
# ruff: noqa: E402

from __future__ import annotations

import numpy as np
import pytest
from ros2_standin import HASH, StandIn, compressed_image
from ros2_support import CIMG, body_from_cam, feed_map, pngs, pose_error, stamp, start_service
from scipy.spatial.transform import Rotation
from service_support import ROOT, endpoint, free_port, open_router, wait_until

sdk = pytest.importorskip("zenoh_ros2_sdk")

INTERFACES = ROOT / "tests" / "data" / "ros2_interfaces"


@pytest.fixture
def sdk_session(monkeypatch):
    """The SDK's process-wide session and registry, reset afterwards."""
    from zenoh_ros2_sdk import message_registry
    from zenoh_ros2_sdk.session import ZenohSession

    monkeypatch.setattr(message_registry, "_registry",
                        message_registry.MessageRegistry(str(INTERFACES)))
    yield ZenohSession
    if ZenohSession._instance is not None:
        ZenohSession._instance.close()


def test_zenoh_ros2_sdk_sees_calls_and_reads_reloc(synthetic_scene, sdk_session):
    from zenoh_ros2_sdk import (
        ROS2ServiceClient,
        ROS2Subscriber,
        get_service_names_and_types,
        get_topic_names_and_types,
    )

    scene = synthetic_scene
    port = free_port()
    with open_router(port):
        service = start_service(port, "room")
        drone = StandIn(endpoint(port))
        try:
            wait_until(lambda: any("/SS/" in t for t in drone.graph()))
            # a new session learns the graph over a moment (``ros2 topic list --spin-time``)
            topics = wait_until(lambda: (lambda t: t if len(t) >= 8 else None)(
                dict(get_topic_names_and_types(router_port=port, timeout=1.0))))
            assert topics == {
                "/diagnostics": ["diagnostic_msgs/msg/DiagnosticArray"],
                "/rosout": ["rcl_interfaces/msg/Log"],
                "/reloc/room/pose": ["geometry_msgs/msg/PoseWithCovarianceStamped"],
                "/camera/image_raw/compressed": ["sensor_msgs/msg/CompressedImage"],
                "/camera/camera_info": ["sensor_msgs/msg/CameraInfo"],
                "/odom": ["nav_msgs/msg/Odometry"], "/reloc/room/lost": ["std_msgs/msg/Bool"],
                "/tf": ["tf2_msgs/msg/TFMessage"]}
            services = wait_until(lambda: (lambda s: s if len(s) >= 2 else None)(
                dict(get_service_names_and_types(router_port=port, timeout=1.0))))
            assert services == {"/reloc/room/relocalize": ["std_srvs/srv/Trigger"],
                                "/reloc/room/mapping": ["std_srvs/srv/SetBool"]}

            feed_map(drone, scene.camera.to_dict(),
                     list(zip(pngs(scene.keyframe_images), scene.keyframe_poses, strict=True)),
                     repeat_nearby=False)
            wait_until(lambda: len(service.maps["room"].map_state().keyframes) == 6, timeout=60)
            drone.publish("/camera/image_raw/compressed", CIMG, HASH[CIMG],
                          compressed_image(stamp(200.0), "camera", "png",
                                           pngs(scene.query_images[:1])[0]))
            wait_until(lambda: service.ros2.counters["images"] == 7)

            poses: list = []
            sub = ROS2Subscriber("/reloc/room/pose", "geometry_msgs/msg/PoseWithCovarianceStamped",
                                 poses.append, router_port=port)
            # An empty request is written out: the SDK refuses an empty .srv request part.
            client = ROS2ServiceClient(
                "/reloc/room/relocalize", "std_srvs/srv/Trigger",
                request_definition="uint8 structure_needs_at_least_one_member\n",
                response_definition="bool success\nstring message\n", router_port=port,
                timeout=60)
            # its own hash computation from the .msg/.srv text gives the keys reloc serves on
            assert sub.keyexpr == ("0/reloc/room/pose/geometry_msgs::msg::dds_::"
                                   "PoseWithCovarianceStamped_/"
                                   + HASH["geometry_msgs/msg/PoseWithCovarianceStamped"])
            assert client.type_hash == HASH["std_srvs/srv/Trigger"]
            # the SDK's subscriber is declared (its token shows it; the pose publisher is a
            # zenoh-ext AdvancedPublisher, which has no matching status)
            wait_until(lambda: any("/MS/" in t and "/%reloc%room%pose/" in t
                                   for t in drone.graph()))
            response = client.call()
            assert response is not None and response.success, response
            wait_until(lambda: poses, timeout=10)
            msg = poses[0]
            assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (200, 0)
            assert msg.header.frame_id == "map"
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            got = np.eye(4)
            got[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
            got[:3, 3] = (p.x, p.y, p.z)
            metres, degrees = pose_error(got, scene.query_poses[0] @ np.linalg.inv(body_from_cam()))
            assert metres < 0.05 and degrees < 5.0
            assert not service.ros2.mismatches   # the SDK's tokens carry the same hashes
        finally:
            drone.close()
            service.stop()
