"""PX4 over Zenoh (service/ros2/px4.py): the relocalized pose as px4_msgs/msg/VehicleOdometry on
``/fmu/in/vehicle_visual_odometry``, NED/FRD, for PX4's zenoh module. A hand-worked frame
conversion, a Monte-Carlo check of the variances, the type hash of the shipped .msg against the
one PX4 keys with, the ``[ros2.px4]`` section, and end to end over Zenoh with a PX4-side
subscriber of the stand-in (its own key, hash and CDR reader)."""
# ruff: noqa: E402

from __future__ import annotations

import math
import re
import threading
import time

import numpy as np
import pytest
from ros2_standin import (
    HASH,
    PX4_HASH,
    PX4_VEHICLE_ODOMETRY,
    StandIn,
    compressed_image,
    px4_own_odometry,
    read_pose,
    read_trigger_response,
    read_vehicle_odometry,
    subscribe_px4,
)
from ros2_support import CIMG, feed_map, pngs, pose_error, stamp, start_service
from scipy.spatial.transform import Rotation
from service_support import ROOT, endpoint, free_port, open_router, wait_until

from reloc_service.core.errors import ConfigError
from reloc_service.service.config import load_config, parse_config
from reloc_service.service.ros2 import px4, px4_conf
from reloc_service.service.ros2 import types as ros
from reloc_service.service.ros2.conf import Ros2Conf

SHIPPED_MSG = ROOT / "reloc_service" / "service" / "ros2" / "px4_msgs" / "VehicleOdometry.msg"
TESTS_MSG = ROOT / "tests" / "data" / "ros2_interfaces" / "px4_msgs" / "msg" / "VehicleOdometry.msg"


def _yaw_pose(position, yaw_deg: float) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    out[:3, 3] = position
    return out


# -- the frame conversion ------------------------------------------------------------------------

def test_hand_worked_enu_flu_pose_becomes_ned_frd():
    """A FLU body at ENU (1, 2, 3), yawed 30 deg (counter-clockwise from east, i.e. heading
    60 deg east of north), with a ROS covariance of distinct variances:
    position (x y z, ENU) 0.01 0.04 0.09 m^2 (x-y correlated 0.005), rotation about the world's
    x y z 1e-4 4e-4 9e-4 rad^2.

    By hand:
    - position NED = (y, x, -z) = (2, 1, -3);
    - ned_from_frd = ned_from_enu @ Rz(30) @ Rx(180) = Rz(60) (NED yaw = 90 - 30 deg), so
      q (w x y z) = (cos 30, 0, 0, sin 30) = (0.8660254, 0, 0, 0.5);
    - position variance: NED axes are ENU's y, x, -z, so (0.04, 0.01, 0.09) (the correlation
      does not enter a diagonal);
    - orientation variance in the FRD body: the body's forward axis in ENU is
      (cos 30, sin 30, 0), so var = 0.75 * 1e-4 + 0.25 * 4e-4 = 1.75e-4; its right axis is
      (sin 30, -cos 30, 0): 0.25 * 1e-4 + 0.75 * 4e-4 = 3.25e-4; down is -z: 9e-4.
    """
    cov = np.zeros((6, 6))
    cov[:3, :3] = [[0.01, 0.005, 0.0], [0.005, 0.04, 0.0], [0.0, 0.0, 0.09]]
    cov[3:, 3:] = np.diag([1e-4, 4e-4, 9e-4])
    pose = px4.px4_pose(_yaw_pose([1.0, 2.0, 3.0], 30.0), cov)
    np.testing.assert_allclose(pose.position, [2.0, 1.0, -3.0], atol=1e-12)
    np.testing.assert_allclose(pose.q_wxyz, [math.sqrt(3) / 2, 0.0, 0.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(pose.position_variance, [0.04, 0.01, 0.09], atol=1e-15)
    np.testing.assert_allclose(pose.orientation_variance, [1.75e-4, 3.25e-4, 9e-4], atol=1e-15)


def test_ned_world_and_frd_body_pass_through_and_unknown_covariance_is_nan():
    world_from_body = _yaw_pose([1.0, 2.0, 3.0], 30.0)
    world_from_body[:3, :3] = Rotation.from_euler("zyx", [30, 10, -5], degrees=True).as_matrix()
    pose = px4.px4_pose(world_from_body, np.zeros((6, 6)), world_frame="ned", body_frame="frd")
    np.testing.assert_allclose(pose.position, [1.0, 2.0, 3.0])
    w, x, y, z = pose.q_wxyz
    np.testing.assert_allclose(Rotation.from_quat([x, y, z, w]).as_matrix(),
                               world_from_body[:3, :3], atol=1e-12)
    assert w >= 0
    assert np.all(np.isnan(pose.position_variance)) and np.all(np.isnan(pose.orientation_variance))
    # FLU body in a NED world: only the body flips (180 deg about x)
    flu = px4.px4_pose(world_from_body, None, world_frame="ned", body_frame="flu")
    w, x, y, z = flu.q_wxyz
    np.testing.assert_allclose(Rotation.from_quat([x, y, z, w]).as_matrix(),
                               world_from_body[:3, :3] @ np.diag([1.0, -1.0, -1.0]), atol=1e-12)


def test_orientation_variance_is_the_spread_of_the_body_attitude_error_monte_carlo():
    """Perturb a pitched, rolled, yawed pose by world-axes rotation errors drawn from the
    covariance; the attitude error of the PX4 quaternion, measured in the FRD body, has the
    variances the conversion predicts (5 sigma of a variance estimate from N draws)."""
    rng = np.random.default_rng(0)
    world_from_body = _yaw_pose([0.0, 0.0, 0.0], 0.0)
    world_from_body[:3, :3] = Rotation.from_euler("zyx", [40, 15, -20], degrees=True).as_matrix()
    a = rng.normal(size=(3, 3)) * 0.01
    rot_cov = a @ a.T + np.diag([1e-5, 4e-5, 9e-5])
    cov = np.zeros((6, 6))
    cov[3:, 3:] = rot_cov
    cov[:3, :3] = np.eye(3) * 0.01
    predicted = px4.px4_pose(world_from_body, cov).orientation_variance
    n = 2000   # a variance within 5 sqrt(2 / n) = 16 %; the NED-axes answer is 38-58 % off
    deltas = rng.multivariate_normal(np.zeros(3), rot_cov, size=n)     # about world axes
    nominal = _px4_rotation(px4.px4_pose(world_from_body, None))
    errors = np.empty((n, 3))
    for i, d in enumerate(deltas):
        perturbed = world_from_body.copy()
        perturbed[:3, :3] = Rotation.from_rotvec(d).as_matrix() @ world_from_body[:3, :3]
        # the error as a right perturbation: nominal @ exp(e) = perturbed, e in the FRD body
        errors[i] = Rotation.from_matrix(
            nominal.T @ _px4_rotation(px4.px4_pose(perturbed, None))).as_rotvec()
    sample = errors.var(axis=0)
    assert np.all(np.abs(sample - predicted) < 5 * predicted * math.sqrt(2 / n)), (sample,
                                                                                 predicted)


def _px4_rotation(pose: px4.Px4Pose) -> np.ndarray:
    w, x, y, z = pose.q_wxyz
    return Rotation.from_quat([x, y, z, w]).as_matrix()


def test_quality_and_microseconds():
    assert [px4.quality_of(c) for c in (0.0, 0.004, 0.5, 0.987, 1.0, float("nan"))] == \
        [1, 1, 50, 99, 100, 1]

    class Time:
        sec, nanosec = 1234, 567_890_123

    assert px4.microseconds(Time()) == 1_234_567_890


def test_px4_clock_takes_the_least_delayed_sample_of_the_window_and_restarts_with_px4():
    clock = px4.Px4Clock(window_s=2.0)
    assert clock.offset_us(10_000_000) is None
    # PX4 clock = wall - 9_000_000; received 3 ms, 1 ms, 7 ms after PX4 stamped them
    for px4_us, latency in ((1_000_000, 3000), (1_010_000, 1000), (1_020_000, 7000)):
        clock.observe(px4_us, px4_us + 9_000_000 + latency)
    assert clock.offset_us(10_030_000) == -9_001_000
    assert clock.offset_us(12_500_000) is None                     # all older than the window
    clock.observe(2_000_000, 12_600_000)
    clock.observe(50_000, 12_700_000)                              # PX4 rebooted
    assert clock.offset_us(12_700_000) == 50_000 - 12_700_000


def test_times_on_px4_clock_or_the_stamp_as_is():
    class Time:
        sec, nanosec = 100, 250_000_000

    conf = px4_conf.Px4Conf(enabled=True)
    assert px4.Px4Publisher(None, b"", conf, None).times_us(Time(), 7) == (7, 100_250_000)
    clock = px4.Px4Clock()
    with_clock = px4.Px4Publisher(None, b"", conf, clock)
    assert with_clock.times_us(Time(), 101_000_000) is None        # no PX4 sample yet
    clock.observe(5_000_000, 100_000_000)                          # PX4 booted at wall 95 s
    assert with_clock.times_us(Time(), 101_000_000) == (6_000_000, 5_250_000)
    clock.observe(5_000_001, 100_000_001)

    class Early:
        sec, nanosec = 90, 0                                       # before PX4 booted: no

    assert with_clock.times_us(Early(), 101_000_000) is None


# -- the type -------------------------------------------------------------------------------------

def test_type_hash_is_computed_from_the_shipped_msg_and_is_the_one_px4_keys_with():
    name = px4.vehicle_odometry_type()
    assert name == "px4_msgs/msg/VehicleOdometry"
    assert ros.dds_name(name) == "px4_msgs::msg::dds_::VehicleOdometry_"
    assert ros.type_hash(name) == PX4_HASH
    # the package's copy is the tests' copy, and both carry PX4's license
    assert SHIPPED_MSG.read_text() == TESTS_MSG.read_text() == px4.msg_text()
    for folder in (SHIPPED_MSG.parent, TESTS_MSG.parent):
        license_text = (folder / "LICENSE").read_text()
        assert "BSD 3-Clause License" in license_text and "PX4 Development Team" in license_text
        assert "#   BSD 3-Clause License" in (folder / "VehicleOdometry.msg").read_text()


def test_another_implementation_hashes_the_tests_msg_alike():
    """zenoh-ros2-sdk's own RIHS01 code on the tests' copy of the .msg."""
    utils = pytest.importorskip("zenoh_ros2_sdk.utils")
    assert utils.compute_type_hash_from_msg("px4_msgs/msg/VehicleOdometry",
                                            TESTS_MSG.read_text()) == PX4_HASH


def test_cdr_round_trip_of_a_message_with_float32_and_nan_velocity():
    pose = px4.px4_pose(_yaw_pose([1.0, 2.0, 3.0], 30.0), np.diag([1.0, 2, 3, 4, 5, 6]) * 1e-3)
    msg = px4.vehicle_odometry(pose, timestamp_us=5, timestamp_sample_us=3,
                               pose_frame=px4_conf.POSE_FRAME_FRD, reset_counter=257, quality=42)
    got = read_vehicle_odometry(ros.encode(msg, px4.VEHICLE_ODOMETRY))
    assert (got.timestamp, got.timestamp_sample, got.pose_frame, got.velocity_frame,
            got.reset_counter, got.quality) == (5, 3, 2, 0, 1, 42)
    np.testing.assert_allclose(got.position, [2.0, 1.0, -3.0], rtol=1e-7)
    assert np.all(np.isnan(got.velocity)) and np.all(np.isnan(got.angular_velocity))
    assert np.all(np.isnan(got.velocity_variance))
    # EKF2 takes q only within 1e-5 of unit norm in float32
    assert abs(np.linalg.norm(got.q.astype(np.float32)) - 1.0) < 1e-5


# -- configuration ----------------------------------------------------------------------------------

def test_px4_is_off_by_default_and_its_section_is_checked():
    assert not Ros2Conf().px4.enabled
    conf = parse_config({"ros2": {"enabled": True, "px4": {
        "enabled": True, "topic": "/px4_1/fmu/in/vehicle_visual_odometry", "world_frame": "ned",
        "body_frame": "frd", "pose_frame": "ned"}}}).ros2.px4
    assert conf == px4_conf.Px4Conf(True, "/px4_1/fmu/in/vehicle_visual_odometry", "ned", "frd", "ned")
    assert parse_config({"ros2": {"enabled": True, "px4": {"clock_topic": ""}}}).ros2.px4 \
        == px4_conf.Px4Conf(clock_topic="")
    bad = [({"px4": {"enabled": True}}, "needs ros2.enabled = true"),
           ({"enabled": True, "px4": {"frame": "enu"}}, r"unknown option\(s\) \['frame'\]"),
           ({"enabled": True, "px4": {"world_frame": "nwu"}}, r"world_frame: expected one of"),
           ({"enabled": True, "px4": {"body_frame": "rfu"}}, r"body_frame: expected one of"),
           ({"enabled": True, "px4": {"pose_frame": "enu"}}, r"pose_frame: expected one of"),
           ({"enabled": True, "px4": {"topic": "fmu/in/x"}}, r"expected an absolute ROS name"),
           ({"enabled": True, "px4": {"clock_topic": "x"}}, r"clock_topic: expected an absol"),
           ({"enabled": True, "px4": True}, r"ros2.px4: expected a table")]
    for section, message in bad:
        with pytest.raises(ConfigError, match=message):
            parse_config({"ros2": section})


def test_the_deploy_example_documents_the_defaults():
    conf = load_config(ROOT / "deploy" / "ros2" / "reloc-ros2.toml").ros2.px4
    assert conf == px4_conf.Px4Conf()


# -- over Zenoh -------------------------------------------------------------------------------------

def test_px4_receives_the_relocalized_pose_as_vehicle_odometry(synthetic_scene):
    """The stand-in builds the map and subscribes as PX4's zenoh module does. Before PX4's
    clock is known, a Trigger publishes the ROS pose but withholds the VehicleOdometry; once
    the stand-in publishes PX4's own odometry (stamps on a clock that booted 1000 s ago), the
    VehicleOdometry it decodes is the ROS pose converted to NED/FRD by hand, its
    timestamp_sample the image stamp on PX4's clock; after ``bump_reset_counter`` the next one
    carries reset_counter 1."""
    scene = synthetic_scene
    port = free_port()
    with open_router(port):
        service = start_service(port, "room", px4={"enabled": True,
                                                   "feed": "relocalizations"})
        drone = StandIn(endpoint(port))
        stop_clock = threading.Event()
        clock_thread: threading.Thread | None = None
        try:
            drone.subscribe_poses("/reloc/room/pose")
            received = subscribe_px4(drone)
            graph = wait_until(lambda: (lambda g: g if any(
                "/MS/" in t and "%fmu%out%vehicle_odometry/" in t for t in g) else None)(
                    drone.graph()))
            [token] = [t for t in graph if "/MP/" in t and "%fmu%in%vehicle_visual_odometry" in t]
            assert token.endswith("/px4_msgs::msg::dds_::VehicleOdometry_/" + PX4_HASH
                                  + "/::,10:,:,:,,")
            # a PX4 of another message version subscribes with another hash: reported
            other = "RIHS01_" + "0" * 64
            drone.advertise("MS", "/fmu/in/vehicle_visual_odometry", PX4_VEHICLE_ODOMETRY, other)
            wait_until(lambda: ("/fmu/in/vehicle_visual_odometry",
                                "px4_msgs::msg::dds_::VehicleOdometry_", other)
                       in service.ros2.mismatches)
            feed_map(drone, scene.camera.to_dict(), list(zip(
                pngs(scene.keyframe_images), scene.keyframe_poses, strict=True)),
                repeat_nearby=False)
            wait_until(lambda: len(service.maps["room"].map_state().keyframes) == 6, timeout=60)
            node = service.ros2.node("room")
            [png] = pngs(scene.query_images[:1])

            def trigger(seq: int):
                t = stamp(time.time())
                before = service.ros2.counters["images"]
                drone.publish("/camera/image_raw/compressed", CIMG, HASH[CIMG],
                              compressed_image(t, "camera", "png", png))
                wait_until(lambda: service.ros2.counters["images"] > before)
                [(payload, _att)] = drone.call_trigger("/reloc/room/relocalize", seq=seq)
                success, message = read_trigger_response(payload)
                assert success, message
                return t, message, read_pose(drone.poses.get(timeout=10)[0])

            trigger(1)
            assert node.px4.withheld == 1 and received.empty()      # PX4's clock unknown
            boot_us = time.time_ns() // 1000 - 1_000_000_000

            def px4_clock() -> None:
                # PX4 publishes its odometry all the time; the service withholds a pose when
                # its newest sample of PX4's clock is older than 2 s (a relocalization under
                # a loaded machine can take longer than that after a one-off burst).
                while not stop_clock.is_set():
                    drone.publish("/fmu/out/vehicle_odometry", "px4_msgs/msg/VehicleOdometry",
                                  PX4_HASH, px4_own_odometry(time.time_ns() // 1000 - boot_us))
                    stop_clock.wait(0.05)

            clock_thread = threading.Thread(target=px4_clock, daemon=True)
            clock_thread.start()
            wait_until(lambda: node.px4.clock.samples >= 5)
            for seq, reset in ((2, 0), (3, 1)):
                t, message, ros_pose = trigger(seq)
                odom = read_vehicle_odometry(received.get(timeout=10))
                _check_conversion(odom, ros_pose, message)
                on_px4_clock = t[0] * 1_000_000 + t[1] // 1000 - boot_us
                # the offset is PX4's minus the least delayed sample's latency (loopback)
                assert 0 <= on_px4_clock - odom.timestamp_sample < 50_000
                assert abs(odom.timestamp - (time.time_ns() // 1000 - boot_us)) < 10_000_000
                assert odom.reset_counter == reset
                node.px4.bump_reset_counter()
            assert received.empty()
        finally:
            stop_clock.set()
            if clock_thread is not None:
                clock_thread.join()
            drone.close()
            service.stop()


def _check_conversion(odom, ros_pose, message) -> None:
    """VehicleOdometry against the ROS pose (ENU map, FLU body), converted here independently."""
    ned_from_enu = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]], dtype=float)
    enu_from_frd = ros_pose.map_from_body[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    expected = np.eye(4)
    expected[:3, :3] = ned_from_enu @ enu_from_frd
    expected[:3, 3] = ned_from_enu @ ros_pose.map_from_body[:3, 3]
    got = np.eye(4)
    w, x, y, z = odom.q
    got[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    got[:3, 3] = odom.position
    metres, degrees = pose_error(got, expected)
    assert metres < 1e-5 and degrees < 1e-4, (metres, degrees)      # float32 on the wire
    cov = ros_pose.covariance
    np.testing.assert_allclose(odom.position_variance,
                               np.diag(ned_from_enu @ cov[:3, :3] @ ned_from_enu.T), rtol=1e-6)
    np.testing.assert_allclose(odom.orientation_variance,
                               np.diag(enu_from_frd.T @ cov[3:, 3:] @ enu_from_frd), rtol=1e-6)
    assert (odom.pose_frame, odom.velocity_frame) == (2, 0)          # FRD world, velocity unknown
    assert np.all(np.isnan(odom.velocity)) and np.all(np.isnan(odom.angular_velocity))
    confidence = float(re.search(r"confidence (\d\.\d\d)", message).group(1))
    assert abs(odom.quality - 100 * confidence) <= 1


def test_no_px4_publisher_unless_enabled(synthetic_scene):
    port = free_port()
    with open_router(port):
        service = start_service(port, "room")
        drone = StandIn(endpoint(port))
        try:
            wait_until(lambda: any("/SS/" in t for t in drone.graph()))
            assert service.ros2.node("room").px4 is None
            assert not [t for t in drone.graph() if "fmu" in t or "VehicleOdometry" in t]
        finally:
            drone.close()
            service.stop()
