"""``reloc serve`` with ``[ros2]`` over loopback Zenoh through a router, driven by a ROS 2
stand-in written from rmw_zenoh's design facts only (tests/ros2_standin.py): it publishes
CameraInfo, CompressedImage and Odometry, the service builds the map from them, the stand-in
calls the std_srvs/Trigger service and reads PoseWithCovarianceStamped. Samples without the
attachment and samples on another type hash are never used; requests without it get no reply."""
# ruff: noqa: E402

from __future__ import annotations

import logging

import numpy as np
import pytest
from ros2_standin import (
    HASH,
    StandIn,
    camera_info,
    compressed_image,
    odometry,
    parse_attachment,
    read_dataset,
    read_pose,
    read_trigger_response,
    rosbags_hash,
)
from ros2_support import (
    CIMG,
    ODOMETRY_COVARIANCE,
    body_from_cam,
    feed_map,
    pngs,
    pose_error,
    relocalize,
    stamp,
    start_service,
)
from service_support import endpoint, free_port, open_router, wait_until

from reloc_service.service.ros2 import convert


@pytest.fixture(scope="module")
def world():
    port = free_port()
    with open_router(port):
        service = start_service(port, "room")
        drone = StandIn(endpoint(port))
        drone.subscribe_poses("/reloc/room/pose")
        try:
            wait_until(lambda: any("/SS/" in t for t in drone.graph()))
            yield service, drone
        finally:
            drone.close()
            service.stop()


def test_the_graph_shows_the_node_its_topics_and_service(world):
    service, drone = world
    tokens = drone.graph()
    zid = str(service.session.zid())
    ours = [t for t in tokens if f"/{zid}/" in t]
    node = [t for t in ours if "/NN/" in t]
    assert len(node) == 1 and node[0].endswith("/NN/%/%reloc%room/reloc")
    expected = {   # the pose latched (transient local, depth 1), the service at depth 10
        "MP": "%reloc%room%pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/"
              + HASH["geometry_msgs/msg/PoseWithCovarianceStamped"] + "/:1:,1:,:,:,,",
        "SS": "%reloc%room%relocalize/std_srvs::srv::dds_::Trigger_/"
              + HASH["std_srvs/srv/Trigger"] + "/::,10:,:,:,,",
    }
    for kind, tail in expected.items():
        assert any(f"/{kind}/" in t and t.endswith(f"/reloc/{tail}") for t in ours), ours
    subscribed = {t.split("/")[9] for t in ours if "/MS/" in t}
    assert subscribed == {"%camera%image_raw%compressed", "%camera%camera_info", "%odom",
                          "%reloc%room%lost"}


def test_trigger_before_any_image_says_why(world):
    _service, drone = world
    [(payload, att)] = drone.call_trigger("/reloc/room/relocalize", seq=7)
    assert parse_attachment(att) == (7, drone.gid)
    success, message = read_trigger_response(payload)
    assert not success and "no image received on /camera/image_raw/compressed" in message


def test_map_from_odometry_then_relocalize_each_query(world, synthetic_scene):
    service, drone = world
    scene = synthetic_scene
    camera = scene.camera.to_dict()
    feed_map(drone, camera, list(zip(pngs(scene.keyframe_images), scene.keyframe_poses,
                                     strict=True)), repeat_nearby=True)
    rt = service.maps["room"]
    wait_until(lambda: len(rt.map_state().keyframes) == 6, timeout=60)
    service.wait_idle()
    assert len(rt.map_state().keyframes) == 6          # the nudged copies were not keyframes
    kf_poses = [rt.map_state().keyframes[k].world_from_cam for k in range(6)]
    for got, want in zip(kf_poses, scene.keyframe_poses, strict=True):
        assert np.allclose(got, want, atol=1e-6)        # odometry @ body_from_cam
    for k, world_from_cam in enumerate(kf_poses):      # the odometry's covariance, ours
        world_from_body = world_from_cam @ np.linalg.inv(body_from_cam())
        kf_cov = rt.map_state().keyframes[k].pose_covariance
        assert kf_cov is not None
        np.testing.assert_allclose(
            convert.ros_covariance(world_from_cam, kf_cov, world_from_body),
            ODOMETRY_COVARIANCE, rtol=1e-6, atol=1e-12)
    for i, (png, world_from_cam) in enumerate(zip(pngs(scene.query_images), scene.query_poses,
                                                  strict=True)):
        success, message, pose = relocalize(drone, service, png, stamp(200.0 + i), i + 1,
                                            "room")
        assert success, message
        assert pose.stamp == stamp(200.0 + i) and pose.frame_id == "map"
        metres, degrees = pose_error(pose.map_from_body,
                                     world_from_cam @ np.linalg.inv(body_from_cam()))
        assert metres < 0.05 and degrees < 5.0, (metres, degrees, message)
        cov = pose.covariance
        assert np.allclose(cov, cov.T) and np.all(np.diag(cov) > 0)
        assert np.all(np.linalg.eigvalsh(cov) > -1e-12)


def test_missing_attachment_or_another_type_hash_is_never_used(world, synthetic_scene, caplog):
    service, drone = world
    scene = synthetic_scene
    [png] = pngs(scene.query_images[:1])
    last = stamp(300.0)
    success, _, pose = relocalize(drone, service, png, last, 20, "room")
    assert success and pose.stamp == last
    images = service.ros2.counters["images"]
    dropped = service.ros2.counters["dropped_samples"]
    caplog.set_level(logging.WARNING, logger="reloc_service.service.ros2.bridge")
    # no attachment: rmw_zenoh subscribers drop it; so does reloc
    drone.publish("/camera/image_raw/compressed", CIMG, HASH[CIMG],
                  compressed_image(stamp(301.0), "camera", "png", png), attach=False)
    wait_until(lambda: service.ros2.counters["dropped_samples"] == dropped + 1)
    # another type hash (e.g. a node of another distro): another key, nothing is delivered,
    # but its token shows in the graph and reloc warns
    wrong = "RIHS01_" + "0" * 64
    drone.advertise("MP", "/camera/image_raw/compressed", CIMG, wrong)
    drone.publish("/camera/image_raw/compressed", CIMG, wrong,
                  compressed_image(stamp(302.0), "camera", "png", png), wait_matching=False)
    wait_until(lambda: service.ros2.mismatches)
    assert service.ros2.mismatches == {("/camera/image_raw/compressed", "sensor_msgs::msg::dds_::"
                                        "CompressedImage_", wrong)}
    # the warning follows the record of the mismatch (through every handler, /rosout's too)
    wait_until(lambda: any("TYPE MISMATCH" in r.getMessage() for r in caplog.records))
    # neither image was used: the image at 300 s, answered already, is still the newest
    [(payload, _att)] = drone.call_trigger("/reloc/room/relocalize", seq=21)
    success, message = read_trigger_response(payload)
    assert not success and "no image newer than image stamped 300.000000000" in message
    assert service.ros2.counters["images"] == images


def test_bad_messages_are_counted_and_the_node_keeps_working(world, synthetic_scene):
    service, drone = world
    bad = service.ros2.counters["bad_samples"]
    drone.publish("/camera/image_raw/compressed", CIMG, HASH[CIMG],
                  compressed_image(stamp(400.0), "camera", "png", b"not a png"))
    drone.publish("/camera/camera_info", "sensor_msgs/msg/CameraInfo",
                  rosbags_hash("sensor_msgs/msg/CameraInfo"), b"\x00\x01\x00\x00\xff")
    nan_pose = np.eye(4)
    nan_pose[:3, 3] = np.nan
    drone.publish("/odom", "nav_msgs/msg/Odometry", rosbags_hash("nav_msgs/msg/Odometry"),
                  odometry(stamp(400.0), nan_pose))
    wait_until(lambda: service.ros2.counters["bad_samples"] == bad + 3)
    [(payload, _att)] = drone.call_trigger("/reloc/room/relocalize", seq=25)
    success, message = read_trigger_response(payload)   # answered for the bad image
    assert not success and "image stamped 400.000000000 was rejected" in message, message
    [png] = pngs(synthetic_scene.query_images[:1])      # the camera still serves
    success, message, _pose = relocalize(drone, service, png, stamp(401.0), 26, "room")
    assert success and "image stamped 401.000000000" in message, message


def test_odometry_with_a_bad_covariance_still_makes_a_keyframe_with_the_default(
        world, synthetic_scene):
    """A covariance that is not one (not positive semi-definite) is counted and left out:
    the keyframe is made and takes the map's default."""
    service, drone = world
    scene = synthetic_scene
    rt = service.maps["room"]
    before = len(rt.map_state().keyframes)
    bad_cov = np.diag([1e-4, 1e-4, 1e-4, -1e-4, 1e-6, 1e-6])
    far = scene.keyframe_poses[0].copy()
    far[:3, 3] += (0.0, 0.0, 0.3)   # away from every keyframe: the rule makes it one
    [image] = pngs([scene.render(far)[0]])   # what the camera sees there: it relocalizes
    t = stamp(500.0)
    drone.publish("/odom", "nav_msgs/msg/Odometry", rosbags_hash("nav_msgs/msg/Odometry"),
                  odometry(t, far @ np.linalg.inv(body_from_cam()), bad_cov))
    drone.publish("/camera/image_raw/compressed", CIMG, HASH[CIMG],
                  compressed_image(t, "camera", "png", image))
    wait_until(lambda: len(rt.map_state().keyframes) == before + 1, timeout=60)
    assert service.ros2.counters["bad_odometry_covariance"] == 1
    newest = rt.map_state().keyframes[max(rt.map_state().keyframes)]
    assert newest.pose_covariance is None   # the map's default applies


def test_a_request_without_attachment_gets_no_reply(world):
    service, drone = world
    before = service.ros2.counters["dropped_requests"]
    assert drone.call_trigger("/reloc/room/relocalize", seq=30, attach=False, timeout=3.0) == []
    assert service.ros2.counters["dropped_requests"] == before + 1


def test_humble_writes_type_hash_not_supported_and_lost_relocalizes_every_nth(synthetic_scene):
    """Humble keys carry ``TypeHashNotSupported``; while ``lost`` is true, every 2nd image is
    relocalized without a call."""
    scene = synthetic_scene
    port = free_port()
    with open_router(port):
        service = start_service(port, "room", distro="humble", relocalize_every_n=2)
        humble = {t: "TypeHashNotSupported" for t in (CIMG, "sensor_msgs/msg/CameraInfo",
                                                      "nav_msgs/msg/Odometry",
                                                      "geometry_msgs/msg/PoseWithCovarianceStamped")}
        drone = StandIn(endpoint(port))
        try:
            drone.session.declare_subscriber(
                "0/reloc/room/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/"
                "TypeHashNotSupported", lambda s: drone.poses.put((s.payload.to_bytes(), None)))
            wait_until(lambda: any("TypeHashNotSupported" in t for t in drone.graph()))
            drone.publish("/camera/camera_info", "sensor_msgs/msg/CameraInfo",
                          humble["sensor_msgs/msg/CameraInfo"],
                          camera_info(stamp(1.0), scene.camera.to_dict()))
            for i, (png, pose) in enumerate(zip(pngs(scene.keyframe_images),
                                                scene.keyframe_poses, strict=True)):
                drone.publish("/odom", "nav_msgs/msg/Odometry", humble["nav_msgs/msg/Odometry"],
                              odometry(stamp(10.0 + i), pose @ np.linalg.inv(body_from_cam())))
                drone.publish("/camera/image_raw/compressed", CIMG, humble[CIMG],
                              compressed_image(stamp(10.0 + i), "camera", "png", png))
            rt = service.maps["room"]
            wait_until(lambda: len(rt.map_state().keyframes) == 6, timeout=60)
            drone.publish("/reloc/room/lost", "std_msgs/msg/Bool", "TypeHashNotSupported",
                          b"\x00\x01\x00\x00\x01")
            wait_until(lambda: service.ros2.node("room").lost)
            images = service.ros2.counters["images"]
            [png] = pngs(scene.query_images[:1])
            for k in range(4):   # images 1..4 after the flag: the 2nd and 4th are relocalized
                drone.publish("/camera/image_raw/compressed", CIMG, humble[CIMG],
                              compressed_image(stamp(50.0 + k), "camera", "png", png))
            wait_until(lambda: service.ros2.counters["images"] == images + 4)
            stamps = sorted(read_pose(drone.poses.get(timeout=30)[0]).stamp for _ in range(2))
            assert stamps == [stamp(51.0), stamp(53.0)]
            assert drone.poses.empty()
        finally:
            drone.close()
            service.stop()


@pytest.mark.slow
def test_desk_scene_over_ros2(tmp_path_factory):
    """The bridge end to end on a rendered scene: the ``desk`` preset's map frames with odometry
    build the map, each query image is relocalized through the Trigger service and comes back
    as PoseWithCovarianceStamped within 5 cm / 5 deg of the ground truth (about 15 s, 8 of them
    rendering the 640x480 scene)."""
    from reloc_service.tools.synth import render_dataset

    root = render_dataset("desk", tmp_path_factory.mktemp("ros2") / "desk", seed=0, workers=1,
                          progress=False)
    camera, map_frames, queries = read_dataset(root)
    port = free_port()
    with open_router(port):
        service = start_service(port, "desk", keyframe_min_distance_m=0.05,
                                keyframe_min_angle_deg=5.0)
        drone = StandIn(endpoint(port))
        drone.subscribe_poses("/reloc/desk/pose")
        try:
            wait_until(lambda: any("/SS/" in t for t in drone.graph()))
            feed_map(drone, camera, map_frames, repeat_nearby=False)
            rt = service.maps["desk"]
            wait_until(lambda: len(rt.map_state().keyframes) == len(map_frames), timeout=120)
            errors = []
            for i, (png, world_from_cam) in enumerate(queries):
                success, message, pose = relocalize(drone, service, png, stamp(500.0 + i),
                                                    i + 1, "desk")
                assert success, (i, message)
                if i == 0:
                    print(f"\nfirst Trigger response: {message!r}")
                assert pose.stamp == stamp(500.0 + i) and pose.frame_id == "map"
                errors.append(pose_error(pose.map_from_body,
                                         world_from_cam @ np.linalg.inv(body_from_cam())))
            print(f"\ndesk over ROS 2: {len(map_frames)} keyframes, {len(queries)} queries, "
                  f"max error {max(e[0] for e in errors) * 100:.2f} cm / "
                  f"{max(e[1] for e in errors):.2f} deg")
            assert all(m < 0.05 and d < 5.0 for m, d in errors), errors
        finally:
            drone.close()
            service.stop()
