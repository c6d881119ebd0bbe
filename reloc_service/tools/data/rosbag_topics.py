"""What a rosbag2 recording holds, read through rosbags (MCAP or SQLite3, a bag folder or its
storage file): its topics and their types, each topic checked against the role it is given,
and the header stamp of a message. Every problem is a DatasetError that names the topic and
what the bag holds instead.

Messages are decoded with the message definitions the live bridge uses (rosbags' Jazzy store,
:mod:`~reloc_service.service.ros2.types`), not the bag's own: rosbags' high-level reader checks
every topic's type hash at open with a hash function that differs from rosidl's for ``char``
fields, so one unrelated topic of such a type (a service event, ``std_msgs/Char``) would make it
refuse a real recording whole."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ...core.errors import DatasetError
from ...service.ros2 import types as ros

POSE_WITH_COVARIANCE_STAMPED = ros.POSE_WITH_COVARIANCE_STAMPED
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
#: Image topics: a JPEG/PNG CompressedImage or an 8-bit raw Image (the bridge's two kinds).
IMAGE_TYPES = (ros.COMPRESSED_IMAGE, ros.IMAGE)
#: Odometry topics: what a VIO publishes; the pose is ``world_from_body``.
ODOMETRY_TYPES = (ros.ODOMETRY, ros.POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED)
CAMERA_INFO_TYPES = (ros.CAMERA_INFO,)
TF_TYPES = (TF_MESSAGE,)


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag: its message type (None when its connections disagree) and count."""

    name: str
    msgtype: str | None
    count: int


@contextlib.contextmanager
def open_bag(path: Path) -> Iterator[Any]:
    """An open ``rosbags.rosbag2.Reader`` on the rosbag2 at ``path`` (a bag folder with
    ``metadata.yaml``, or one ``.mcap`` / ``.db3`` file); DatasetError when it is not one."""
    from rosbags.rosbag2 import Reader, ReaderError

    if not path.exists():
        raise DatasetError(f"bag {path} does not exist; expected a rosbag2 folder (with "
                           "metadata.yaml) or its .mcap / .db3 file")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise DatasetError(f"bag {path}: no metadata.yaml in this folder; expected a rosbag2 "
                           "folder (ros2 bag record writes one) or its .mcap / .db3 file")
    if path.is_file() and path.suffix not in (".mcap", ".db3"):
        raise DatasetError(f"bag {path}: expected a rosbag2 folder (with metadata.yaml) or a "
                           f".mcap / .db3 file, got a {path.suffix or 'suffix-less'} file")
    try:
        reader = Reader(path)
        reader.open()
    except (ReaderError, FileNotFoundError) as exc:
        raise DatasetError(f"bag {path}: cannot be read as a rosbag2 recording: {exc}") from None
    except Exception as exc:   # a damaged storage file raises whatever its parser raises
        raise DatasetError(f"bag {path}: cannot be read as a rosbag2 recording "
                           f"({type(exc).__name__}: {exc})") from None
    try:
        yield reader
    finally:
        reader.close()


def bag_topics(reader: Any) -> dict[str, TopicInfo]:
    """Every topic of the open bag, by name."""
    return {name: TopicInfo(name, info.msgtype, int(info.msgcount))
            for name, info in reader.topics.items()}


def describe_topics(topics: dict[str, TopicInfo], types: tuple[str, ...] | None = None) -> str:
    """``name (type, N messages)`` of every topic (of one of ``types``), for error messages."""
    chosen = [t for t in topics.values() if types is None or t.msgtype in types]
    if not chosen:
        return "none"
    return ", ".join(f"{t.name} ({t.msgtype or 'mixed types'}, {t.count} messages)"
                     for t in sorted(chosen, key=lambda t: t.name))


def require_topic(topics: dict[str, TopicInfo], name: str, types: tuple[str, ...], role: str,
                  bag: Path) -> TopicInfo:
    """The topic ``name`` holding messages of one of ``types``; DatasetError naming the topic,
    what it holds and the topics of the expected types present when it is missing, of another
    type or empty."""
    expected = " or ".join(types)
    candidates = describe_topics(topics, types)
    info = topics.get(name)
    if info is None:
        raise DatasetError(f"bag {bag}: no topic {name} ({role}, expected {expected}); topics "
                           f"of that type in the bag: {candidates}; all topics: "
                           f"{describe_topics(topics)}")
    if info.msgtype not in types:
        raise DatasetError(f"bag {bag}: topic {name} ({role}) holds {info.msgtype or 'mixed types'}"
                           f"; expected {expected}; topics of that type in the bag: {candidates}")
    if info.count == 0:
        raise DatasetError(f"bag {bag}: topic {name} ({role}, {info.msgtype}) has no messages")
    return info


def connections_of(reader: Any, topic: str) -> list[Any]:
    """The bag's connections of ``topic``."""
    return [c for c in reader.connections if c.topic == topic]


def stamp_ns(stamp: Any) -> int:
    """builtin_interfaces/Time -> integer nanoseconds (exact, a key for the images)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def read_messages(reader: Any, connections: list[Any], *, desc: str) -> Iterator[tuple[str, Any]]:
    """(topic, message) of the given connections in log order, with a progress line;
    DatasetError naming the topic when a message does not decode."""
    from ...core.progress import progress

    assert connections, "an empty list would read every topic"
    total = sum(int(c.msgcount) for c in connections)
    for connection, _, raw in progress(reader.messages(connections=connections), total=total,
                                       desc=desc):
        try:
            yield connection.topic, ros.decode(raw, connection.msgtype)
        except ValueError as exc:
            raise DatasetError(f"topic {connection.topic}: {exc}") from None
