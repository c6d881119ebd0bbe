"""ROS 2 conversions (service/ros2/convert.py) and the ``[ros2]`` config section."""

from __future__ import annotations

import numpy as np
import pytest

from reloc_service.core.errors import ConfigError
from reloc_service.core.geometry import (
    compose,
    invert,
    look_at,
    pose_from_tq,
    se3_exp,
    so3_log,
)
from reloc_service.service.config import parse_config
from reloc_service.service.ros2 import convert
from reloc_service.service.ros2 import types as ros


def test_covariance_in_ros_convention_matches_sampled_body_poses():
    """Sample camera poses from our covariance (right perturbation), move them to the body,
    and measure ROS's (x y z rotX rotY rotZ) errors: their covariance is the converted one."""
    rng = np.random.default_rng(0)
    world_from_cam = look_at((1.0, -2.0, 1.5), (0.0, 1.0, 1.0))
    # a long lever arm, so that rotation errors move the body's position noticeably
    body_from_cam = pose_from_tq((0.8, 0.5, -0.6), (0.5, -0.5, 0.5, -0.5))
    a = rng.normal(size=(6, 6)) * np.array([0.02, 0.03, 0.01, 0.02, 0.03, 0.01])[:, None]
    cov_cam = a @ a.T
    world_from_body = compose(world_from_cam, invert(body_from_cam))
    expected = convert.ros_covariance(world_from_cam, cov_cam, world_from_body)
    errors = []
    for xi in rng.multivariate_normal(np.zeros(6), cov_cam, size=20000):
        body = compose(compose(world_from_cam, se3_exp(xi)), invert(body_from_cam))
        d_rot = so3_log(body[:3, :3] @ world_from_body[:3, :3].T)
        errors.append(np.concatenate([body[:3, 3] - world_from_body[:3, 3], d_rot]))
    measured = np.cov(np.array(errors).T)
    scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
    assert np.all(np.abs(measured - expected) <= 0.05 * scale)
    assert not np.allclose(expected, cov_cam, atol=1e-6)   # the conversion does something


def test_covariance_from_ros_undoes_ros_covariance():
    """Ours -> ROS -> ours and ROS -> ours -> ROS give back what went in."""
    rng = np.random.default_rng(1)
    world_from_cam = look_at((1.0, -2.0, 1.5), (0.0, 1.0, 1.0))
    body_from_cam = pose_from_tq((0.8, 0.5, -0.6), (0.5, -0.5, 0.5, -0.5))
    world_from_body = compose(world_from_cam, invert(body_from_cam))
    a = rng.normal(size=(6, 6)) * np.array([0.02, 0.03, 0.01, 0.02, 0.03, 0.01])[:, None]
    ours = a @ a.T
    ros = convert.ros_covariance(world_from_cam, ours, world_from_body)
    np.testing.assert_allclose(convert.covariance_from_ros(world_from_cam, ros, world_from_body),
                               ours, rtol=1e-9, atol=1e-15)
    b = rng.normal(size=(6, 6)) * 0.01
    ros2 = b @ b.T
    back = convert.ros_covariance(
        world_from_cam, convert.covariance_from_ros(world_from_cam, ros2, world_from_body),
        world_from_body)
    np.testing.assert_allclose(back, ros2, rtol=1e-9, atol=1e-15)


def test_odometry_covariance_unknown_and_invalid():
    """ROS's "unknown" (all zeros, or -1 first) is None; a matrix that is no covariance is a
    ValueError naming why; a valid one is converted."""
    world_from_cam = look_at((0.0, 0.0, 1.0), (1.0, 0.0, 1.0))
    world_from_body = world_from_cam
    assert convert.odometry_covariance(np.zeros(36), world_from_cam, world_from_body) is None
    unknown = np.zeros(36)
    unknown[0] = -1.0
    assert convert.odometry_covariance(unknown, world_from_cam, world_from_body) is None
    with pytest.raises(ValueError, match="positive semi-definite"):
        convert.odometry_covariance(np.diag([1.0, 1, 1, 1, 1, -0.5]).ravel(), world_from_cam,
                                    world_from_body)
    with pytest.raises(ValueError, match="symmetric"):
        asym = np.eye(6)
        asym[0, 1] = 0.5
        convert.odometry_covariance(asym.ravel(), world_from_cam, world_from_body)
    cov = np.diag([1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5])
    ours = convert.odometry_covariance(cov.ravel(), world_from_cam, world_from_body)
    assert ours is not None
    np.testing.assert_allclose(convert.ros_covariance(world_from_cam, ours, world_from_body),
                               cov, atol=1e-15)


def test_body_pose_undoes_the_extrinsics():
    world_from_body = pose_from_tq((1.0, 2.0, 0.5), (0.0, 0.0, 0.3826834, 0.9238795))
    body_from_cam = pose_from_tq((0.1, 0.0, 0.0), (-0.5, 0.5, -0.5, 0.5))
    out = convert.body_pose(world_from_body @ body_from_cam, None, body_from_cam)
    np.testing.assert_allclose(out.position, [1.0, 2.0, 0.5], atol=1e-9)
    np.testing.assert_allclose(np.abs(out.quat_xyzw), [0, 0, 0.3826834, 0.9238795], atol=1e-6)
    assert out.covariance.shape == (6, 6)


def _info(model: str, d: list[float], width: int = 640, height: int = 480):
    return ros.message(
        "sensor_msgs/msg/CameraInfo",
        header=ros.message("std_msgs/msg/Header",
                           stamp=ros.message("builtin_interfaces/msg/Time", sec=0, nanosec=0),
                           frame_id="cam"),
        height=height, width=width, distortion_model=model, d=np.array(d, np.float64),
        k=np.array([500.0, 0, 319.5, 0, 501.0, 239.5, 0, 0, 1]), r=np.eye(3).ravel(),
        p=np.zeros(12), binning_x=0, binning_y=0,
        roi=ros.message("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0,
                        width=0, do_rectify=False))


def test_camera_info_to_camera_models():
    pinhole = convert.camera_dict(_info("plumb_bob", [0, 0, 0, 0, 0]))
    assert pinhole == {"model": "pinhole", "width": 640, "height": 480, "fx": 500.0,
                       "fy": 501.0, "cx": 319.5, "cy": 239.5, "distortion": []}
    radtan = convert.camera_dict(_info("plumb_bob", [-0.2, 0.05, 1e-3, -1e-3, 0.01]))
    assert radtan["model"] == "radtan" and radtan["distortion"] == [-0.2, 0.05, 1e-3, -1e-3, 0.01]
    fisheye = convert.camera_dict(_info("equidistant", [0.1, 0.01, 0.001, 0.0001]))
    assert fisheye["model"] == "equidistant" and len(fisheye["distortion"]) == 4
    with pytest.raises(ValueError, match="k4..k6"):
        convert.camera_dict(_info("rational_polynomial", [0.1, 0, 0, 0, 0, 0.2, 0, 0]))
    with pytest.raises(ValueError, match="not supported"):
        convert.camera_dict(_info("double_sphere", [0.1, 0.2]))
    with pytest.raises(ValueError, match="positive size"):
        convert.camera_dict(_info("plumb_bob", [], width=0))


def test_raw_images_to_grey():
    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[..., 0] = 255                       # red
    padded = np.zeros((2, 12), np.uint8)    # step 12 > 3 * 3: row padding is skipped
    padded[:, :9] = rgb.reshape(2, 9)
    msg = ros.message("sensor_msgs/msg/Image", header=_info("plumb_bob", []).header, height=2,
                      width=3, encoding="rgb8", is_bigendian=0, step=12, data=padded.ravel())
    grey = convert.grey_from_raw(msg)
    assert grey.shape == (2, 3) and grey.dtype == np.uint8 and np.all(grey == 76)
    msg.encoding = "bgr8"
    assert np.all(convert.grey_from_raw(msg) == 29)
    msg.encoding = "mono16"
    with pytest.raises(ValueError, match="not supported"):
        convert.grey_from_raw(msg)
    msg.encoding, msg.step = "mono8", 100
    with pytest.raises(ValueError, match="do not hold"):
        convert.grey_from_raw(msg)


def test_odometry_pairing_by_nearest_stamp():
    poses = convert.StampedPoses()
    assert poses.newest() == float("-inf")
    for i in range(5):
        poses.add(10.0 + 0.1 * i, np.eye(4) * (i + 1))
    assert poses.nearest(10.21, 0.02)[0, 0] == 3
    assert poses.nearest(10.25, 0.02) is None
    assert poses.nearest(9.0, 0.02) is None
    assert poses.newest() == pytest.approx(10.4)
    poses.add(1.0, np.eye(4))   # time went back: start again
    assert poses.nearest(10.2, 0.5) is None and poses.nearest(1.0, 0.0) is not None


def test_ros2_section_is_off_by_default_and_strict():
    conf = parse_config({})
    assert conf.ros2.enabled is False
    on = parse_config({"ros2": {"enabled": True, "domain_id": 3, "distro": "humble",
                                "body_from_cam": [0, 0, 0.1, 0, 0, 0, 1]}}).ros2
    assert on.domain_id == 3 and on.body_from_cam == (0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0)
    assert on.resolve("pose", "desk-1") == "/reloc/desk_1/pose"
    assert on.resolve("/odom", "desk") == "/odom"
    for bad, match in (({"distro": "foxy"}, "distro"), ({"domain_id": 300}, "domain_id"),
                       ({"pose_topic": "a//b"}, "pose_topic"), ({"namespace": "x"}, "namespace"),
                       ({"body_from_cam": [0, 0, 0, 0, 0, 0, 2]}, "unit length"),
                       ({"body_from_cam": [0, 0, 0]}, "7 numbers"),
                       ({"image_type": "jpeg"}, "image_type"), ({"qos_depth": 0}, "qos_depth"),
                       ({"nope": 1}, "unknown option")):
        with pytest.raises(ConfigError, match=match):
            parse_config({"ros2": bad})
