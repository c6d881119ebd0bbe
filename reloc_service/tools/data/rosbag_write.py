"""A reloc dataset v1 written as a rosbag2 recording (MCAP or SQLite3, through rosbags' writer),
as a drone's camera and VIO would have recorded it: per frame a sensor_msgs/CompressedImage
(the dataset's JPEG or PNG bytes as they are), its sensor_msgs/CameraInfo and a nav_msgs/Odometry
of the body from the ground-truth pose (and, on request, the same transform on ``/tf``).

Map and query frames both go in, in time order: the stamp is the image file's name where it
is one (TUM's seconds ``1305031232.961662``, EuRoC's nanoseconds), else the frames follow in
path order at a fixed rate. A recording to replay to the live bridge, or to test
``reloc dataset from-rosbag`` with."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ...core.cameras import Camera
from ...core.errors import DatasetError
from ...core.geometry import invert, matrix_to_quat_xyzw
from ...core.progress import progress
from ...service.ros2 import types as ros
from ...service.ros2.conf import Ros2Conf
from .dataset import Dataset, DatasetEntry, read_dataset
from .rosbag_topics import TF_MESSAGE

Array = npt.NDArray[np.float64]

STORAGES = ("mcap", "sqlite3")
#: A file stem that is a time: seconds with a fraction (TUM) or integer nanoseconds (EuRoC).
_SECONDS = re.compile(r"^(\d+)\.(\d{1,9})$")
_NANOSECONDS = re.compile(r"^\d{16,19}$")
_FIRST_STAMP_NS = 1_000_000_000   # stamps of frames without a time in their name start at 1 s


@dataclass(frozen=True)
class BagLayout:
    """Topics, frames and storage of the bag written; the topics default to the bridge's."""

    storage: str = "mcap"
    image_topic: str = Ros2Conf.image_topic
    camera_info_topic: str = Ros2Conf.camera_info_topic
    odometry_topic: str = Ros2Conf.odometry_topic
    tf_topic: str | None = None
    odom_frame: str = "odom"
    body_frame: str = "base_link"
    body_from_cam: Array = field(default_factory=lambda: np.eye(4))
    rate_hz: float = 30.0

    def __post_init__(self) -> None:
        if self.storage not in STORAGES:
            raise DatasetError(f"bag storage: expected one of {list(STORAGES)}, got "
                               f"{self.storage!r}")
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise DatasetError(f"frame rate: expected a positive number of Hz, got {self.rate_hz}")


def write_rosbag(dataset_root: str | Path, bag: str | Path, layout: BagLayout | None = None
                 ) -> int:
    """Write the dataset in ``dataset_root`` as a new rosbag2 ``bag``; the number of frames."""
    from rosbags.rosbag2 import Writer
    from rosbags.rosbag2.enums import StoragePlugin

    layout = layout or BagLayout()
    dataset, bag = read_dataset(dataset_root), Path(bag)
    if bag.exists():
        raise DatasetError(f"bag {bag} exists; expected a new path (rosbag2 never overwrites)")
    _, camera = _single_camera(dataset)
    camera_info_message(camera)   # a camera with no CameraInfo equivalent stops here
    frames = frame_stamps(_frames(dataset), layout.rate_hz)
    plugin = StoragePlugin.MCAP if layout.storage == "mcap" else StoragePlugin.SQLITE3
    store = ros.typestore()
    with Writer(bag, version=9, storage_plugin=plugin) as writer:
        topics = {ros.CAMERA_INFO: layout.camera_info_topic, ros.COMPRESSED_IMAGE:
                  layout.image_topic, ros.ODOMETRY: layout.odometry_topic}
        if layout.tf_topic:
            topics[TF_MESSAGE] = layout.tf_topic
        connections = {t: writer.add_connection(name, t, typestore=store)
                       for t, name in topics.items()}
        for stamp_ns, entry in progress(frames, desc=f"write {bag.name}"):
            for ros_type, msg in _frame_messages(dataset, entry, stamp_ns, camera, layout):
                writer.write(connections[ros_type], stamp_ns, ros.encode(msg, ros_type))
    return len(frames)


def _single_camera(dataset: Dataset) -> tuple[str, Camera]:
    if len(dataset.cameras) != 1:
        raise DatasetError(f"{dataset.root}: expected one camera (a bag holds one image topic), "
                           f"got {len(dataset.cameras)}: {sorted(dataset.cameras)}")
    ((camera_id, camera),) = dataset.cameras.items()
    return camera_id, camera


def _frames(dataset: Dataset) -> list[DatasetEntry]:
    """Map and query entries, each image once (a query may also be a map frame)."""
    seen: dict[str, DatasetEntry] = {}
    for entry in dataset.map_entries + dataset.query_entries:
        seen.setdefault(entry.image_path, entry)
    return list(seen.values())


def frame_stamps(entries: list[DatasetEntry], rate_hz: float) -> list[tuple[int, DatasetEntry]]:
    """(stamp ns, entry) in time order: every stem a time, else path order at ``rate_hz``."""
    stamps = [stem_stamp_ns(Path(e.image_path).stem) for e in entries]
    if all(s is not None for s in stamps) and len(set(stamps)) == len(stamps):
        return sorted(zip(stamps, entries, strict=True), key=lambda pair: pair[0])  # type: ignore[arg-type, return-value]
    ordered = sorted(entries, key=lambda e: e.image_path)
    step_ns = 1e9 / rate_hz
    return [(_FIRST_STAMP_NS + round(i * step_ns), e) for i, e in enumerate(ordered)]


def stem_stamp_ns(stem: str) -> int | None:
    """The time a file stem names, in ns (``1305031232.961662`` s, ``1403636579763555584``
    ns), or None."""
    match = _SECONDS.match(stem)
    if match:
        return int(match.group(1)) * 1_000_000_000 + int(match.group(2).ljust(9, "0"))
    return int(stem) if _NANOSECONDS.match(stem) else None


# -- messages ----------------------------------------------------------------------------------

def _time(stamp_ns: int) -> Any:
    seconds, nanoseconds = divmod(stamp_ns, 1_000_000_000)
    return ros.message("builtin_interfaces/msg/Time", sec=seconds, nanosec=nanoseconds)


def header_message(stamp_ns: int, frame_id: str) -> Any:
    return ros.message("std_msgs/msg/Header", stamp=_time(stamp_ns), frame_id=frame_id)


def camera_info_message(camera: Camera, header: Any = None) -> Any:
    """sensor_msgs/CameraInfo of ``camera`` (``header`` default: stamp 0, no frame): the
    inverse of the bridge's :func:`~reloc_service.service.ros2.convert.camera_dict`."""
    models = {"pinhole": "plumb_bob", "radtan": "plumb_bob", "equidistant": "equidistant"}
    if camera.model not in models:
        raise DatasetError(f"camera model {camera.model!r} has no CameraInfo equivalent; "
                           f"expected one of {sorted(models)}")
    d = list(camera.distortion) if camera.model != "pinhole" else [0.0] * 5
    k = np.array([camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1], dtype=np.float64)
    p = np.array([camera.fx, 0, camera.cx, 0, 0, camera.fy, camera.cy, 0, 0, 0, 1, 0],
                 dtype=np.float64)
    roi = ros.message("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0,
                      width=0, do_rectify=False)
    return ros.message(ros.CAMERA_INFO, header=header or header_message(0, ""), height=camera.height,
                       width=camera.width, distortion_model=models[camera.model],
                       d=np.array(d, dtype=np.float64), k=k, r=np.eye(3).ravel(), p=p,
                       binning_x=0, binning_y=0, roi=roi)


def _frame_messages(dataset: Dataset, entry: DatasetEntry, stamp_ns: int, camera: Camera,
                    layout: BagLayout) -> list[tuple[str, Any]]:
    """The messages of one frame: camera info, image, odometry (and transform)."""
    data = _image_bytes(dataset.root / entry.image_path)
    header = header_message(stamp_ns, entry.camera_id)
    camera_info = camera_info_message(camera, header)
    image = ros.message(ros.COMPRESSED_IMAGE, header=header,
                        format="png" if data.startswith(b"\x89PNG") else "jpeg",
                        data=np.frombuffer(data, dtype=np.uint8))
    world_from_body = entry.world_from_cam @ invert(layout.body_from_cam)
    messages = [(ros.CAMERA_INFO, camera_info), (ros.COMPRESSED_IMAGE, image),
                (ros.ODOMETRY, odometry_message(world_from_body, stamp_ns, layout))]
    if layout.tf_topic:
        messages.append((TF_MESSAGE, transform_message(world_from_body, stamp_ns, layout)))
    return messages


def _image_bytes(path: Path) -> bytes:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    if not data.startswith((b"\x89PNG", b"\xff\xd8")):
        raise DatasetError(f"{path}: expected a PNG or JPEG file (CompressedImage carries one)")
    return data


def _vector(name: str, values: Array) -> Any:
    x, y, z = (float(v) for v in values)
    return ros.message(name, x=x, y=y, z=z)


def _quaternion(rotation: Array) -> Any:
    x, y, z, w = (float(v) for v in matrix_to_quat_xyzw(rotation))
    return ros.message("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w)


def odometry_message(world_from_body: Array, stamp_ns: int, layout: BagLayout) -> Any:
    """nav_msgs/Odometry of the body in the odometry frame; covariances all zero (unknown)."""
    m = ros.message
    pose = m("geometry_msgs/msg/Pose",
             position=_vector("geometry_msgs/msg/Point", world_from_body[:3, 3]),
             orientation=_quaternion(world_from_body[:3, :3]))
    zero = np.zeros(3)
    twist = m("geometry_msgs/msg/Twist", linear=_vector("geometry_msgs/msg/Vector3", zero),
              angular=_vector("geometry_msgs/msg/Vector3", zero))
    return m(ros.ODOMETRY, header=header_message(stamp_ns, layout.odom_frame),
             child_frame_id=layout.body_frame,
             pose=m("geometry_msgs/msg/PoseWithCovariance", pose=pose, covariance=np.zeros(36)),
             twist=m("geometry_msgs/msg/TwistWithCovariance", twist=twist,
                     covariance=np.zeros(36)))


def transform_message(world_from_body: Array, stamp_ns: int, layout: BagLayout) -> Any:
    """tf2_msgs/TFMessage with the one transform ``odom_frame -> body_frame``."""
    m = ros.message
    transform = m("geometry_msgs/msg/Transform",
                  translation=_vector("geometry_msgs/msg/Vector3", world_from_body[:3, 3]),
                  rotation=_quaternion(world_from_body[:3, :3]))
    stamped = m("geometry_msgs/msg/TransformStamped", header=header_message(stamp_ns, layout.odom_frame),
                child_frame_id=layout.body_frame, transform=transform)
    return m(TF_MESSAGE, transforms=[stamped])
