"""``reloc dataset from-rosbag`` and ``to-rosbag``: argument parsing and printing only; the work
is in :mod:`.rosbag` and :mod:`.rosbag_write` (imported when the command runs, and only when
rosbags, the ``ros2`` extra, is installed)."""

from __future__ import annotations

import argparse
import importlib.util
import sys
from collections.abc import Callable
from typing import Any

#: Exit status when the ``ros2`` extra is missing (as for the ``tools`` extra).
UNAVAILABLE = 2
ROS2_EXTRA_HINT = "needs the ros2 extra (rosbags): pip install 'reloc[ros2]'"
# The live bridge's defaults (reloc_service.service.ros2.conf.Ros2Conf), repeated here so that
# ``--help`` imports nothing; tests/test_rosbag.py keeps the two in step.
BRIDGE_IMAGE_TOPIC = "/camera/image_raw/compressed"
BRIDGE_CAMERA_INFO_TOPIC = "/camera/camera_info"
BRIDGE_ODOMETRY_TOPIC = "/odom"
BRIDGE_MAX_STAMP_DIFFERENCE_S = 0.02


def add_rosbag_commands(commands: Any) -> None:
    """Add ``from-rosbag`` and ``to-rosbag`` to the ``reloc dataset`` subparsers."""
    _add_from_rosbag(commands.add_parser(
        "from-rosbag", help="build a dataset from a rosbag2 recording (MCAP or SQLite3)",
        description="Pair each image of a rosbag2 recording with the odometry (or /tf "
        "transform) of its stamp, as the live ROS 2 bridge does, and write a reloc dataset "
        "ready for 'reloc-client upload' or 'reloc eval'. Map keyframes and held-out queries "
        "(scored against the odometry) are chosen by the options below."))
    _add_to_rosbag(commands.add_parser(
        "to-rosbag", help="write a dataset as a rosbag2 recording (MCAP or SQLite3)",
        description="Write every map and query frame of a reloc dataset as a recording: "
        "sensor_msgs/CompressedImage (the image files' bytes), sensor_msgs/CameraInfo and "
        "nav_msgs/Odometry from the ground-truth poses, on the live bridge's default topics. "
        "Stamps come from the image names where they are times (TUM, EuRoC), else --rate."))


def _add_from_rosbag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", help="rosbag2 folder (with metadata.yaml) or its .mcap/.db3 file")
    parser.add_argument("dst", help="destination dataset folder (created; must be new or empty)")
    parser.add_argument("--image-topic", required=True, metavar="TOPIC",
                        help="sensor_msgs/CompressedImage (JPEG/PNG) or sensor_msgs/Image topic")
    poses = parser.add_argument_group("poses (one of)")
    poses.add_argument("--odometry-topic", metavar="TOPIC",
                       help="nav_msgs/Odometry, geometry_msgs/PoseStamped or "
                       "PoseWithCovarianceStamped: the body's pose")
    poses.add_argument("--tf-parent", metavar="FRAME",
                       help="with --tf-child: the transform FRAME -> CHILD on --tf-topic is "
                       "the body's pose (e.g. odom -> base_link)")
    poses.add_argument("--tf-child", metavar="FRAME", help="see --tf-parent")
    poses.add_argument("--tf-topic", default="/tf", metavar="TOPIC",
                       help="tf2_msgs/TFMessage topic (default: /tf)")
    camera = parser.add_argument_group("camera (one of)")
    camera.add_argument("--camera-info-topic", metavar="TOPIC",
                        help="sensor_msgs/CameraInfo of the images (K and D of the raw image)")
    camera.add_argument("--camera-json", metavar="FILE",
                        help="camera dict (Camera.to_dict()) or one-camera cameras.json")
    camera.add_argument("--intrinsics", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"),
                        help="a pinhole camera; the image size is read from the first image")
    parser.add_argument("--camera-id", default=None, metavar="ID",
                        help="camera id in the dataset (default: the images' frame id)")
    parser.add_argument("--body-from-cam", type=float, nargs=7, default=None,
                        metavar=("TX", "TY", "TZ", "QX", "QY", "QZ", "QW"),
                        help="the camera's pose in the body frame of the odometry, as the "
                        "bridge's [ros2] body_from_cam (default: identity)")
    parser.add_argument("--max-stamp-difference", type=float,
                        default=BRIDGE_MAX_STAMP_DIFFERENCE_S, metavar="S",
                        help="an image pairs with the pose stamped nearest it within S seconds "
                        f"(default: {BRIDGE_MAX_STAMP_DIFFERENCE_S}, the bridge's)")
    frames = parser.add_argument_group(
        "frames", "times are seconds since the first image; queries are held out first "
        "(never map frames), keyframes chosen among the rest")
    rule = frames.add_mutually_exclusive_group()
    rule.add_argument("--keyframe-every", type=int, default=1, metavar="N",
                      help="every N-th remaining image is a map keyframe (default: 1, all)")
    rule.add_argument("--keyframe-rule", type=float, nargs=2, default=None,
                      metavar=("METRES", "DEGREES"),
                      help="the live bridge's rule: an image is a keyframe when its camera is "
                      "farther than METRES from every keyframe or turned more than DEGREES")
    frames.add_argument("--queries-every", type=int, default=0, metavar="M",
                        help="hold out every M-th image (M >= 2) as a query (default: none)")
    frames.add_argument("--map-time", type=float, nargs=2, default=None, metavar=("T0", "T1"),
                        help="map keyframes only from this time range")
    frames.add_argument("--query-time", type=float, nargs=2, default=None, metavar=("T0", "T1"),
                        help="queries only from this time range (all of it without "
                        "--queries-every)")


def _add_to_rosbag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="reloc dataset v1 folder (one camera)")
    parser.add_argument("bag", help="rosbag2 folder to create")
    parser.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap",
                        help="storage plugin (default: mcap, ROS 2 Jazzy's default)")
    parser.add_argument("--image-topic", default=BRIDGE_IMAGE_TOPIC, metavar="TOPIC")
    parser.add_argument("--camera-info-topic", default=BRIDGE_CAMERA_INFO_TOPIC, metavar="TOPIC")
    parser.add_argument("--odometry-topic", default=BRIDGE_ODOMETRY_TOPIC, metavar="TOPIC")
    parser.add_argument("--tf-topic", default=None, metavar="TOPIC",
                        help="also write the odom -> base_link transform on TOPIC (e.g. /tf)")
    parser.add_argument("--body-from-cam", type=float, nargs=7, default=None,
                        metavar=("TX", "TY", "TZ", "QX", "QY", "QZ", "QW"),
                        help="the camera's pose in the body frame (default: identity)")
    parser.add_argument("--rate", type=float, default=30.0, metavar="HZ",
                        help="frame rate where image names are not times (default: 30)")


def run_rosbag_command(args: argparse.Namespace, summarize: Callable[[Any], str]) -> int:
    """Run ``from-rosbag`` (the dataset made printed by ``summarize``) or ``to-rosbag``; 2 when
    rosbags is missing. Errors propagate to :func:`~.cli.main_dataset`, which prints them and
    returns 1."""
    if importlib.util.find_spec("rosbags") is None:
        print(f"reloc dataset {args.dataset_command} {ROS2_EXTRA_HINT}", file=sys.stderr)
        return UNAVAILABLE
    if args.dataset_command == "to-rosbag":
        return _to_rosbag(args)
    return _from_rosbag(args, summarize)


def _body_from_cam(values: list[float] | None) -> Any:
    import numpy as np

    from ...core.errors import DatasetError, GeometryError
    from ...core.geometry import pose_from_tum

    if values is None:
        return np.eye(4)
    try:
        return pose_from_tum(values)
    except GeometryError as exc:
        raise DatasetError(f"--body-from-cam: {exc}") from None


def _from_rosbag(args: argparse.Namespace, summarize: Callable[[Any], str]) -> int:
    from .dataset import read_camera_json
    from .rosbag import CameraSource, PoseSource, RosbagOptions, convert_rosbag
    from .rosbag_select import Selection

    selection = Selection(keyframe_every=args.keyframe_every,
                          keyframe_rule=tuple(args.keyframe_rule) if args.keyframe_rule else None,
                          queries_every=args.queries_every,
                          map_range=tuple(args.map_time) if args.map_time else None,
                          query_range=tuple(args.query_time) if args.query_time else None)
    camera = CameraSource(
        camera_info_topic=args.camera_info_topic,
        camera=read_camera_json(args.camera_json) if args.camera_json else None,
        intrinsics=tuple(args.intrinsics) if args.intrinsics else None)
    poses = PoseSource(odometry_topic=args.odometry_topic, tf_parent=args.tf_parent,
                       tf_child=args.tf_child, tf_topic=args.tf_topic)
    options = RosbagOptions(args.image_topic, poses, camera,
                            body_from_cam=_body_from_cam(args.body_from_cam),
                            max_stamp_difference_s=args.max_stamp_difference,
                            camera_id=args.camera_id, selection=selection)
    dataset, report = convert_rosbag(args.bag, args.dst, options)
    print("\n".join(report.lines()))
    print(summarize(dataset))
    if not dataset.query_entries:
        print("note: no queries held out (--queries-every or --query-time to score the map)",
              file=sys.stderr)
    return 0


def _to_rosbag(args: argparse.Namespace) -> int:
    from .rosbag_write import BagLayout, write_rosbag

    layout = BagLayout(storage=args.storage, image_topic=args.image_topic,
                       camera_info_topic=args.camera_info_topic,
                       odometry_topic=args.odometry_topic, tf_topic=args.tf_topic,
                       body_from_cam=_body_from_cam(args.body_from_cam), rate_hz=args.rate)
    frames = write_rosbag(args.dataset, args.bag, layout)
    topics = [args.image_topic, args.camera_info_topic, args.odometry_topic]
    print(f"wrote {frames} frames to {args.bag} ({args.storage}): "
          + ", ".join(topics + ([args.tf_topic] if args.tf_topic else [])))
    return 0
