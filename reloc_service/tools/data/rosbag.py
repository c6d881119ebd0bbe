"""A rosbag2 recording (MCAP or SQLite3, read through rosbags) to a reloc dataset v1.

Each image is paired with the odometry (or the ``/tf`` transform) of its header stamp as the
live ROS 2 bridge pairs them: the nearest pose within ``max_stamp_difference_s``
(:class:`~reloc_service.service.ros2.convert.StampedPoses`), then ``world_from_cam =
world_from_body @ body_from_cam``. The camera comes from a CameraInfo topic (the bridge's
:func:`~reloc_service.service.ros2.convert.camera_dict`) or is given. CompressedImage bytes
are written as recorded; raw Images become grey PNG. Two passes over the bag: poses, stamps
and the camera first, then only the chosen images, so a long flight is never held in memory.
"""

from __future__ import annotations

import collections
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera, PinholeCamera, camera_from_dict
from ...core.errors import CameraError, DatasetError
from ...service.ros2 import convert
from ...service.ros2.conf import Ros2Conf
from .dataset import Dataset, DatasetEntry, camera_id_problem, read_dataset
from .dataset_write import write_dataset
from .rosbag_images import ImageWriter, image_size
from .rosbag_select import Selection, select_frames
from .rosbag_topics import (
    CAMERA_INFO_TYPES,
    IMAGE_TYPES,
    ODOMETRY_TYPES,
    TF_TYPES,
    bag_topics,
    connections_of,
    open_bag,
    read_messages,
    require_topic,
    stamp_ns,
)

Array = npt.NDArray[np.float64]

#: The live bridge's pairing tolerance, the default here too.
MAX_STAMP_DIFFERENCE_S = Ros2Conf.max_stamp_difference_s
IMAGES_FOLDER = "images"
DEFAULT_CAMERA_ID = "camera"


@dataclass(frozen=True)
class PoseSource:
    """Where the body poses come from: an odometry topic, or the ``parent -> child``
    transform on a TFMessage topic (``world_from_body`` = ``parent_from_child``)."""

    odometry_topic: str | None = None
    tf_parent: str | None = None
    tf_child: str | None = None
    tf_topic: str = "/tf"

    def __post_init__(self) -> None:
        tf_frames = (self.tf_parent, self.tf_child)
        if any(f is not None for f in tf_frames) and any(f is None for f in tf_frames):
            raise DatasetError("poses from /tf: expected both a parent and a child frame "
                               "(--tf-parent and --tf-child)")
        if (self.odometry_topic is None) == (self.tf_parent is None):
            raise DatasetError("poses: expected either an odometry topic (--odometry-topic) or "
                               "a transform (--tf-parent and --tf-child), not both or neither")

    @property
    def topic(self) -> str:
        return self.odometry_topic or self.tf_topic

    @property
    def role(self) -> str:
        return "odometry" if self.odometry_topic else "transforms"

    def describe(self) -> str:
        if self.odometry_topic:
            return f"odometry on {self.odometry_topic}"
        return f"transform {self.tf_parent} -> {self.tf_child} on {self.tf_topic}"


@dataclass(frozen=True)
class CameraSource:
    """The camera: a CameraInfo topic, a camera given whole, or pinhole intrinsics
    ``fx fy cx cy`` whose image size is read from the first image."""

    camera_info_topic: str | None = None
    camera: Camera | None = None
    intrinsics: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        given = sum(v is not None for v in (self.camera_info_topic, self.camera, self.intrinsics))
        if given != 1:
            raise DatasetError("camera: expected exactly one of a CameraInfo topic "
                               "(--camera-info-topic), a camera file (--camera-json) or pinhole "
                               f"intrinsics (--intrinsics), got {given}")


@dataclass(frozen=True)
class RosbagOptions:
    """How to read a bag: topics, the camera's mounting and the pairing tolerance."""

    image_topic: str
    poses: PoseSource
    camera: CameraSource
    body_from_cam: Array = field(default_factory=lambda: np.eye(4))
    max_stamp_difference_s: float = MAX_STAMP_DIFFERENCE_S
    camera_id: str | None = None
    selection: Selection = field(default_factory=Selection)


@dataclass
class RosbagReport:
    """What the conversion did with the bag's images."""

    images: int = 0
    paired: int = 0
    unpaired: int = 0
    duplicate_stamps: int = 0
    keyframes: int = 0
    queries: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        out = [f"images: {self.images} read, {self.paired} paired with a pose, {self.unpaired} "
               f"without a pose within the stamp tolerance, {self.duplicate_stamps} with a "
               "stamp already seen",
               f"chosen: {self.keyframes} map keyframes, {self.queries} queries"]
        out += [f"skipped {n} image(s): {reason}" for reason, n in self.skipped.items()]
        return out + self.notes


@dataclass
class _FirstPass:
    """What the first pass over the bag gathers."""

    poses: convert.StampedPoses
    pose_count: int
    image_stamps: list[int]
    camera_info: Any | None
    camera_frame: str
    first_image_size: tuple[int, int] | None
    camera_info_changes: int = 0
    tf_edges: collections.Counter[str] = field(default_factory=collections.Counter)
    pose_span: tuple[float, float] = (0.0, 0.0)


def convert_rosbag(bag: str | Path, dst: str | Path, options: RosbagOptions
                   ) -> tuple[Dataset, RosbagReport]:
    """Convert the rosbag2 recording ``bag`` into a new reloc dataset folder ``dst`` and return
    it, read back, with a report. DatasetError (nothing left in ``dst``) when a topic is
    missing or of the wrong type, no image pairs with a pose, or the camera does not fit."""
    bag, dst = Path(bag), Path(dst)
    _check_destination(dst)
    report = RosbagReport()
    with open_bag(bag) as reader:
        first = _first_pass(reader, bag, options)
        camera = _camera(first, options.camera)
        world_from_cam, stamps = _pair(first, options, report, bag)
        map_idx, query_idx = select_frames(_seconds(stamps - first.image_stamps[0]),
                                           world_from_cam, options.selection)
        roles = {int(stamps[i]): ("map", i) for i in map_idx}
        roles |= {int(stamps[i]): ("query", i) for i in query_idx}
        camera_id = options.camera_id or _camera_id(first.camera_frame)
        try:
            dst.mkdir(parents=True, exist_ok=True)
            return _write(reader, options.image_topic, dst, camera_id, camera, roles,
                          world_from_cam, report), report
        except BaseException:
            shutil.rmtree(dst, ignore_errors=True)   # no half-written dataset is left behind
            raise


def _check_destination(dst: Path) -> None:
    if dst.exists() and (not dst.is_dir() or any(dst.iterdir())):
        raise DatasetError(f"destination {dst} exists and is not an empty folder; expected a "
                           "new folder")


# -- first pass: poses, image stamps, the camera ---------------------------------------------

def _first_pass(reader: Any, bag: Path, options: RosbagOptions) -> _FirstPass:
    topics = bag_topics(reader)
    require_topic(topics, options.image_topic, IMAGE_TYPES, "images", bag)
    source = options.poses
    require_topic(topics, source.topic, ODOMETRY_TYPES if source.odometry_topic else TF_TYPES,
                  source.role, bag)
    info_topic = options.camera.camera_info_topic
    if info_topic:
        require_topic(topics, info_topic, CAMERA_INFO_TYPES, "camera info", bag)
    wanted = [options.image_topic, source.topic] + ([info_topic] if info_topic else [])
    connections = [c for topic in dict.fromkeys(wanted) for c in connections_of(reader, topic)]
    rows: list[tuple[float, Array]] = []
    first = _FirstPass(convert.StampedPoses(), 0, [], None, "", None)
    for topic, msg in read_messages(reader, connections, desc=f"read {bag.name}"):
        if topic == source.topic:
            rows += _poses_of(msg, source, first.tf_edges)
        if topic == options.image_topic:
            first.image_stamps.append(stamp_ns(msg.header.stamp))
            if len(first.image_stamps) == 1:
                first.camera_frame = str(msg.header.frame_id)
            if first.first_image_size is None:   # the first image that decodes
                first.first_image_size = image_size(msg)
        if topic == info_topic:
            _note_camera_info(first, msg)
    first.poses, first.pose_count = _stamped_poses(rows, source, bag, first.tf_edges), len(rows)
    first.pose_span = (rows[0][0], rows[-1][0])
    return first


def _poses_of(msg: Any, source: PoseSource, edges: collections.Counter[str]
              ) -> list[tuple[float, Array]]:
    """(stamp, world_from_body) of an odometry message, or of each matching transform of a
    TFMessage (frame names compared without a leading slash, as tf2 does; every transform
    seen is counted in ``edges``)."""
    if source.odometry_topic:
        pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
        return [(convert.stamp_seconds(msg.header.stamp), _checked_pose(pose, source))]
    parent, child = source.tf_parent.lstrip("/"), source.tf_child.lstrip("/")  # type: ignore[union-attr]
    rows = []
    for t in msg.transforms:
        edge = (t.header.frame_id.lstrip("/"), t.child_frame_id.lstrip("/"))
        edges[f"{edge[0]} -> {edge[1]}"] += 1
        if edge == (parent, child):
            pose = SimpleNamespace(position=t.transform.translation,
                                   orientation=t.transform.rotation)
            rows.append((convert.stamp_seconds(t.header.stamp), _checked_pose(pose, source)))
    return rows


def _checked_pose(pose: Any, source: PoseSource) -> Array:
    try:
        return convert.pose_of(pose)
    except ValueError as exc:
        raise DatasetError(f"{source.describe()}: {exc}") from None


def _stamped_poses(rows: list[tuple[float, Array]], source: PoseSource, bag: Path,
                   edges: collections.Counter[str]) -> convert.StampedPoses:
    """The whole pose track by stamp (sorted: the bridge's buffer starts again when time goes
    back, which a bag's log order must not trigger)."""
    if not rows:
        seen = (f"; transforms on {source.tf_topic}: "
                + (", ".join(f"{e} ({n})" for e, n in sorted(edges.items())) or "none")
                if not source.odometry_topic else "")
        raise DatasetError(f"bag {bag}: no pose in {source.describe()}; expected the body's "
                           f"pose over the flight{seen}")
    rows.sort(key=lambda row: row[0])
    poses = convert.StampedPoses(size=len(rows))
    for stamp, world_from_body in rows:
        poses.add(stamp, world_from_body)
    return poses


def _note_camera_info(first: _FirstPass, msg: Any) -> None:
    if first.camera_info is None:
        first.camera_info = msg
    elif _calibration(msg) != _calibration(first.camera_info):
        first.camera_info_changes += 1


def _calibration(info: Any) -> tuple[Any, ...]:
    """What of a CameraInfo makes the camera (compared, not yet checked)."""
    return (int(info.width), int(info.height), str(info.distortion_model),
            tuple(np.asarray(info.k, np.float64)), tuple(np.asarray(info.d, np.float64)))


def _camera(first: _FirstPass, source: CameraSource) -> Camera:
    if source.camera is not None:
        return source.camera
    if source.intrinsics is not None:
        if first.first_image_size is None:
            raise DatasetError("--intrinsics: no image of the image topic decodes, so their size "
                               "is unknown; expected JPEG/PNG or raw 8-bit images")
        width, height = first.first_image_size
        return PinholeCamera(width, height, *source.intrinsics)
    try:
        camera = camera_from_dict(convert.camera_dict(first.camera_info))
    except (ValueError, CameraError) as exc:
        raise DatasetError(f"topic {source.camera_info_topic}: {exc}") from None
    if first.camera_info_changes:
        raise DatasetError(f"topic {source.camera_info_topic}: the camera changes "
                           f"{first.camera_info_changes} time(s) during the recording; expected "
                           "one calibration (pass --camera-json to choose one)")
    return camera


def _camera_id(frame_id: str) -> str:
    """The camera id: the images' frame id where it makes one, else ``camera``."""
    name = frame_id.strip("/").replace("/", "_")
    return name if name and camera_id_problem(name) is None else DEFAULT_CAMERA_ID


# -- pairing ---------------------------------------------------------------------------------

def _pair(first: _FirstPass, options: RosbagOptions, report: RosbagReport, bag: Path
          ) -> tuple[Array, npt.NDArray[np.int64]]:
    """``world_from_cam`` (N, 4, 4) and stamps (N,) ns of the images paired with a pose, in
    stamp order; DatasetError when none pairs."""
    stamps = np.array(sorted(set(first.image_stamps)), dtype=np.int64)
    report.images = len(first.image_stamps)
    report.duplicate_stamps = report.images - len(stamps)
    kept, poses = [], []
    for i, stamp in enumerate(stamps):
        world_from_body = first.poses.nearest(float(_seconds(stamp)),
                                              options.max_stamp_difference_s)
        if world_from_body is not None:
            kept.append(i)
            poses.append(world_from_body @ options.body_from_cam)
    report.paired, report.unpaired = len(kept), len(stamps) - len(kept)
    if not kept:
        raise DatasetError(_no_pair_message(first, stamps, options, bag))
    return np.array(poses), stamps[kept]


def _no_pair_message(first: _FirstPass, stamps: npt.NDArray[np.int64], options: RosbagOptions,
                     bag: Path) -> str:
    pose_span = f"{first.pose_count} poses from {first.pose_span[0]:.3f} to " \
                f"{first.pose_span[1]:.3f} s"
    return (f"bag {bag}: no image on {options.image_topic} has a pose in "
            f"{options.poses.describe()} within {options.max_stamp_difference_s} s of its stamp "
            f"(images from {_seconds(stamps[0]):.3f} to {_seconds(stamps[-1]):.3f} s, "
            f"{pose_span}; header stamps); expected both on one clock, or raise "
            "--max-stamp-difference")


def _seconds(ns: Any) -> Any:
    return np.asarray(ns, dtype=np.int64) * 1e-9


# -- second pass: the chosen images ----------------------------------------------------------

def _write(reader: Any, image_topic: str, dst: Path, camera_id: str, camera: Camera,
           roles: dict[int, tuple[str, int]], world_from_cam: Array,
           report: RosbagReport) -> Dataset:
    writer = ImageWriter(dst, IMAGES_FOLDER, camera)
    entries: dict[str, list[DatasetEntry]] = {"map": [], "query": []}
    connections = connections_of(reader, image_topic)
    for _, msg in read_messages(reader, connections, desc=f"write {len(roles)} images"):
        stamp = stamp_ns(msg.header.stamp)
        role = roles.pop(stamp, None)
        if role is None:
            continue
        path = writer.write(msg, stamp)
        if path is not None:
            entries[role[0]].append(DatasetEntry(path, camera_id, world_from_cam[role[1]]))
    report.skipped = dict(writer.skipped)
    report.keyframes, report.queries = len(entries["map"]), len(entries["query"])
    if not entries["map"]:
        raise DatasetError(f"topic {image_topic}: no map keyframe image could be written ("
                           + "; ".join(f"{n} {r}" for r, n in writer.skipped.items()) + ")")
    write_dataset(dst, {camera_id: camera}, entries["map"], entries["query"])
    return read_dataset(dst)


__all__ = ["CameraSource", "PoseSource", "RosbagOptions", "RosbagReport", "Selection",
           "convert_rosbag"]
