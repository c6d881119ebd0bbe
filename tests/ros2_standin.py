"""A minimal ROS 2 participant on rmw_zenoh, written from rmw_zenoh's design facts only (it
imports nothing of reloc_service.service.ros2): its own CDR writer and reader for the few
messages it needs, its own keys, tokens and attachments. It stands in for a ROS 2 drone:
publishes CameraInfo, CompressedImage and Odometry, calls the std_srvs/Trigger service and
reads PoseWithCovarianceStamped.

Facts used: data key ``<domain>/<name without leading slash>/<DDS type>/<RIHS01 hash>``;
token ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/<enclave>/<ns>/<node>/<topic>/<type>/
<hash>/<qos>`` with ``/`` -> ``%``; CDR little endian after ``00 01 00 00``, alignment
counted from the end of that header; attachment int64 sequence number, int64 timestamp (ns),
byte 16, 16-byte GID; services are queries carrying the request and its attachment.
"""

from __future__ import annotations

import json
import queue
import struct
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from scipy.spatial.transform import Rotation

# Official RIHS01 hashes (Jazzy's type description JSON); Odometry and CameraInfo are
# computed by rosbags (a third-party implementation, right for types without ``char``).
HASH = {
    "geometry_msgs/msg/PoseWithCovarianceStamped":
        "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
    "sensor_msgs/msg/CompressedImage":
        "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a",
    "std_srvs/srv/Trigger":
        "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f",
}


def rosbags_hash(ros_type: str) -> str:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY).hash_rihs01(ros_type)


def dds(ros_type: str) -> str:
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def key(domain: int, name: str, ros_type: str, type_hash: str) -> str:
    return f"{domain}/{name.lstrip('/')}/{dds(ros_type)}/{type_hash}"


# -- CDR --------------------------------------------------------------------------------------

class Writer:
    def __init__(self) -> None:
        self.body = bytearray()

    def _align(self, n: int) -> None:
        self.body += b"\0" * (-len(self.body) % n)

    def u8(self, v: int) -> Writer:
        self.body += struct.pack("<B", v)
        return self

    def i32(self, v: int) -> Writer:
        self._align(4)
        self.body += struct.pack("<i", v)
        return self

    def u32(self, v: int) -> Writer:
        self._align(4)
        self.body += struct.pack("<I", v)
        return self

    def f64s(self, values: Any) -> Writer:
        self._align(8)
        self.body += struct.pack(f"<{len(values)}d", *[float(v) for v in values])
        return self

    def string(self, s: str) -> Writer:
        data = s.encode() + b"\0"
        self.u32(len(data))
        self.body += data
        return self

    def octets(self, data: bytes) -> Writer:
        self.u32(len(data))
        self.body += data
        return self

    def header(self, stamp: tuple[int, int], frame_id: str) -> Writer:
        return self.i32(stamp[0]).u32(stamp[1]).string(frame_id)

    def done(self) -> bytes:
        return b"\x00\x01\x00\x00" + bytes(self.body)


class Reader:
    def __init__(self, data: bytes) -> None:
        assert data[:4] == b"\x00\x01\x00\x00", data[:4].hex()
        self.body, self.pos = data[4:], 0

    def _take(self, fmt: str, align: int) -> Any:
        self.pos += -self.pos % align
        out = struct.unpack_from("<" + fmt, self.body, self.pos)
        self.pos += struct.calcsize("<" + fmt)
        return out

    def u8(self) -> int:
        return self._take("B", 1)[0]

    def i32(self) -> int:
        return self._take("i", 4)[0]

    def u32(self) -> int:
        return self._take("I", 4)[0]

    def f64s(self, n: int) -> np.ndarray:
        return np.array(self._take(f"{n}d", 8))

    def string(self) -> str:
        n = self.u32()
        s = self.body[self.pos:self.pos + n - 1].decode()
        self.pos += n
        return s


def compressed_image(stamp: tuple[int, int], frame_id: str, fmt: str, data: bytes) -> bytes:
    return Writer().header(stamp, frame_id).string(fmt).octets(data).done()


def camera_info(stamp: tuple[int, int], camera: dict[str, Any]) -> bytes:
    d = list(camera["distortion"]) + [0.0] * (5 - len(camera["distortion"]))
    k = [camera["fx"], 0, camera["cx"], 0, camera["fy"], camera["cy"], 0, 0, 1]
    p = [camera["fx"], 0, camera["cx"], 0, 0, camera["fy"], camera["cy"], 0, 0, 0, 1, 0]
    w = Writer().header(stamp, "camera").u32(camera["height"]).u32(camera["width"])
    w.string("plumb_bob").u32(len(d)).f64s(d).f64s(k).f64s(np.eye(3).ravel()).f64s(p)
    return w.u32(0).u32(0).u32(0).u32(0).u32(0).u32(0).u8(0).done()   # binning, roi


def odometry(stamp: tuple[int, int], odom_from_body: np.ndarray,
             covariance: np.ndarray | None = None) -> bytes:
    """nav_msgs/Odometry; ``covariance`` (6, 6) of the pose in ROS's order (zeros: unknown)."""
    q = Rotation.from_matrix(odom_from_body[:3, :3]).as_quat()   # x y z w
    w = Writer().header(stamp, "odom").string("base_link")
    cov = np.zeros(36) if covariance is None else np.asarray(covariance, np.float64).ravel()
    w.f64s(odom_from_body[:3, 3]).f64s(q).f64s(cov)             # pose with covariance
    return w.f64s(np.zeros(6)).f64s(np.zeros(36)).done()          # twist with covariance


@dataclass
class PoseReading:
    stamp: tuple[int, int]
    frame_id: str
    map_from_body: np.ndarray
    covariance: np.ndarray


def read_pose(data: bytes) -> PoseReading:
    r = Reader(data)
    stamp = (r.i32(), r.u32())
    frame_id = r.string()
    position, q, cov = r.f64s(3), r.f64s(4), r.f64s(36)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_quat(q).as_matrix()
    pose[:3, 3] = position
    return PoseReading(stamp, frame_id, pose, cov.reshape(6, 6))


def read_trigger_response(data: bytes) -> tuple[bool, str]:
    r = Reader(data)
    return bool(r.u8()), r.string()


def attachment(seq: int, gid: bytes) -> bytes:
    return struct.pack("<qqB", seq, time.time_ns(), 16) + gid


def parse_attachment(data: bytes) -> tuple[int, bytes]:
    assert len(data) == 33 and data[16] == 16, data.hex()
    return struct.unpack_from("<q", data)[0], data[17:]


# -- the participant ----------------------------------------------------------------------------

class StandIn:
    """A ROS 2 'drone' node on a Zenoh session connected to ``router``."""

    def __init__(self, router: str, domain: int = 0) -> None:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([router]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)
        self.domain = domain
        self.zid = str(self.session.zid())
        self.gid = bytes(range(100, 116))
        self.seq = 0
        self.tokens: list[Any] = [self.session.liveliness().declare_token(
            f"@ros2_lv/{domain}/{self.zid}/0/0/NN/%/%/drone")]
        self.poses: queue.Queue[tuple[bytes, bytes | None]] = queue.Queue()
        self._subs: list[Any] = []
        self._publishers: dict[str, Any] = {}

    def advertise(self, kind: str, name: str, ros_type: str, type_hash: str) -> None:
        """Declare a liveliness token as rmw_zenoh does for an endpoint."""
        eid = len(self.tokens) + 10
        self.tokens.append(self.session.liveliness().declare_token(
            f"@ros2_lv/{self.domain}/{self.zid}/0/{eid}/{kind}/%/%/drone/"
            f"{name.replace('/', '%')}/{dds(ros_type)}/{type_hash}/::,10:,:,:,,"))

    def publish(self, name: str, ros_type: str, type_hash: str, payload: bytes, *,
                attach: bool = True, wait_matching: bool = True) -> None:
        """Put one sample; the first one on a key waits (10 s at most) until a subscriber
        matches, as a ROS publisher that waits for its subscription count."""
        k = key(self.domain, name, ros_type, type_hash)
        if k not in self._publishers:
            # BLOCK, as rmw_zenoh for a reliable KEEP_ALL publisher: a burst of images is not
            # dropped by the sender's queue
            self._publishers[k] = self.session.declare_publisher(
                k, congestion_control=zenoh.CongestionControl.BLOCK)
            deadline = time.monotonic() + 10.0
            while (wait_matching and not self._publishers[k].matching_status.matching
                   and time.monotonic() < deadline):
                time.sleep(0.02)
        self.seq += 1
        self._publishers[k].put(payload,
                                attachment=attachment(self.seq, self.gid) if attach else None)

    def subscribe_poses(self, name: str) -> None:
        ros_type = "geometry_msgs/msg/PoseWithCovarianceStamped"

        def on_sample(sample: zenoh.Sample) -> None:
            att = sample.attachment.to_bytes() if sample.attachment is not None else None
            self.poses.put((sample.payload.to_bytes(), att))

        self._subs.append(self.session.declare_subscriber(
            key(self.domain, name, ros_type, HASH[ros_type]), on_sample))
        self.advertise("MS", name, ros_type, HASH[ros_type])

    def call_trigger(self, name: str, *, seq: int, attach: bool = True, timeout: float = 60.0
                     ) -> list[tuple[bytes, bytes | None]]:
        """A std_srvs/Trigger call: the (payload, attachment) of every reply."""
        request = Writer().u8(0).done()
        replies = self.session.get(
            key(self.domain, name, "std_srvs/srv/Trigger", HASH["std_srvs/srv/Trigger"]),
            payload=request, attachment=attachment(seq, self.gid) if attach else None,
            timeout=timeout)
        out = []
        for reply in replies:
            assert reply.ok is not None, reply.err.payload.to_bytes() if reply.err else None
            att = reply.ok.attachment.to_bytes() if reply.ok.attachment is not None else None
            out.append((reply.ok.payload.to_bytes(), att))
        return out

    def graph(self) -> list[str]:
        """Every liveliness token of the domain (what ``ros2 node/topic list`` read)."""
        return sorted(str(r.ok.key_expr) for r in
                      self.session.liveliness().get(f"@ros2_lv/{self.domain}/**", timeout=5.0)
                      if r.ok is not None)

    def close(self) -> None:
        for entity in [*self._subs, *self._publishers.values(), *self.tokens]:
            entity.undeclare()
        self.session.close()


def read_dataset(root: Path) -> tuple[dict[str, Any], list[tuple[bytes, np.ndarray]],
                                      list[tuple[bytes, np.ndarray]]]:
    """(camera dict, map frames, query frames) of a reloc dataset: PNG bytes and
    world_from_cam."""
    camera = next(iter(json.loads((root / "cameras.json").read_text()).values()))

    def frames(name: str) -> list[tuple[bytes, np.ndarray]]:
        out = []
        for line in (root / name).read_text().splitlines():
            if not line.strip() or line.startswith("#"):
                continue
            path, _cam, *values = line.split()
            t, q = np.array(values[:3], float), np.array(values[3:], float)
            pose = np.eye(4)
            pose[:3, :3] = Rotation.from_quat(q).as_matrix()
            pose[:3, 3] = t
            out.append(((root / path).read_bytes(), pose))
        return out

    return camera, frames("map.txt"), frames("queries.txt")


# -- the map frame: odometry in a named frame, /tf, the mapping SetBool service ----------------

# Official RIHS01 hashes, from rosidl-generated type support code (tf2_msgs TFMessage,
# std_srvs SetBool of Jazzy/Kilted).
HASH["tf2_msgs/msg/TFMessage"] = (
    "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087")
HASH["std_srvs/srv/SetBool"] = (
    "RIHS01_abe9e4bb6b41b40e6789712c00ec8871923e089af3f667a79992a428cff2da0a")


def odometry_in(frame_id: str, stamp: tuple[int, int], odom_from_body: np.ndarray,
                covariance: np.ndarray | None = None) -> bytes:
    """nav_msgs/Odometry whose header names ``frame_id`` (a VIO's odometry frame)."""
    q = Rotation.from_matrix(odom_from_body[:3, :3]).as_quat()
    w = Writer().header(stamp, frame_id).string("base_link")
    cov = np.zeros(36) if covariance is None else np.asarray(covariance, np.float64).ravel()
    w.f64s(odom_from_body[:3, 3]).f64s(q).f64s(cov)
    return w.f64s(np.zeros(6)).f64s(np.zeros(36)).done()


@dataclass
class TransformReading:
    stamp: tuple[int, int]
    parent: str
    child: str
    parent_from_child: np.ndarray


def read_tf(data: bytes) -> list[TransformReading]:
    """tf2_msgs/TFMessage: a sequence of geometry_msgs/TransformStamped."""
    r = Reader(data)
    out = []
    for _ in range(r.u32()):
        stamp = (r.i32(), r.u32())
        parent = r.string()
        child = r.string()
        t, q = r.f64s(3), r.f64s(4)
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_quat(q).as_matrix()
        pose[:3, 3] = t
        out.append(TransformReading(stamp, parent, child, pose))
    return out


def subscribe_tf(drone: StandIn, name: str = "/tf") -> queue.Queue[tuple[str, bytes]]:
    """Every /tf sample as (key, payload), on the official TFMessage hash."""
    ros_type = "tf2_msgs/msg/TFMessage"
    samples: queue.Queue[tuple[str, bytes]] = queue.Queue()
    drone._subs.append(drone.session.declare_subscriber(
        key(drone.domain, name, ros_type, HASH[ros_type]),
        lambda s: samples.put((str(s.key_expr), s.payload.to_bytes()))))
    drone.advertise("MS", name, ros_type, HASH[ros_type])
    return samples


def call_set_bool(drone: StandIn, name: str, data: bool, *, seq: int, timeout: float = 30.0
                  ) -> list[tuple[bool, str, bytes | None]]:
    """A std_srvs/SetBool call: (success, message, attachment) of every reply."""
    ros_type = "std_srvs/srv/SetBool"
    replies = drone.session.get(key(drone.domain, name, ros_type, HASH[ros_type]),
                                payload=Writer().u8(1 if data else 0).done(),
                                attachment=attachment(seq, drone.gid), timeout=timeout)
    out = []
    for reply in replies:
        assert reply.ok is not None, reply.err.payload.to_bytes() if reply.err else None
        r = Reader(reply.ok.payload.to_bytes())
        success, message = bool(r.u8()), r.string()
        att = reply.ok.attachment.to_bytes() if reply.ok.attachment is not None else None
        out.append((success, message, att))
    return out


# -- PX4: px4_msgs/msg/VehicleOdometry as PX4's zenoh module (v1.17) receives it ---------------

#: The RIHS01 hash PX4's zenoh module puts in its VehicleOdometry keys (rosidl's hash of
#: PX4's msg/versioned/VehicleOdometry.msg, as a third-party Zenoh client subscribed to PX4's
#: ``/fmu/out/vehicle_odometry`` with it).
PX4_VEHICLE_ODOMETRY = "px4_msgs/msg/VehicleOdometry"
PX4_HASH = "RIHS01_4295b96ad312084aa35c84bdcec65ba2f57eb4f6a293d57d52d95acbe99ff817"


@dataclass
class VehicleOdometryReading:
    timestamp: int
    timestamp_sample: int
    pose_frame: int
    position: np.ndarray            # float32 values, as PX4 receives them
    q: np.ndarray                   # w x y z
    velocity_frame: int
    velocity: np.ndarray
    angular_velocity: np.ndarray
    position_variance: np.ndarray
    orientation_variance: np.ndarray
    velocity_variance: np.ndarray
    reset_counter: int
    quality: int


def read_vehicle_odometry(data: bytes) -> VehicleOdometryReading:
    """CDR of VehicleOdometry: uint64 x2, uint8, float32[3], float32[4], uint8, float32[3] x5,
    uint8, int8 (each aligned to its own size, counted after the 4-byte header)."""
    r = Reader(data)
    timestamp, sample = r._take("2Q", 8)
    pose_frame = r.u8()
    position, q = np.array(r._take("3f", 4)), np.array(r._take("4f", 4))
    velocity_frame = r.u8()
    vectors = [np.array(r._take("3f", 4)) for _ in range(5)]
    reset_counter, quality = r._take("Bb", 1)
    assert r.pos == len(r.body), (r.pos, len(r.body))     # nothing left over
    return VehicleOdometryReading(timestamp, sample, pose_frame, position, q, velocity_frame,
                                  *vectors, reset_counter, quality)


def subscribe_px4(drone: StandIn, name: str = "/fmu/in/vehicle_visual_odometry"
                  ) -> queue.Queue[bytes]:
    """Subscribe as PX4's zenoh module does (its key, an MS token; it ignores attachments)."""
    received: queue.Queue[bytes] = queue.Queue()
    drone._subs.append(drone.session.declare_subscriber(
        key(drone.domain, name, PX4_VEHICLE_ODOMETRY, PX4_HASH),
        lambda sample: received.put(sample.payload.to_bytes())))
    drone.advertise("MS", name, PX4_VEHICLE_ODOMETRY, PX4_HASH)
    return received


def px4_own_odometry(px4_timestamp_us: int) -> bytes:
    """A VehicleOdometry as PX4 publishes it on /fmu/out/vehicle_odometry: ``timestamp`` on
    PX4's boot clock (the pose itself is not read by the tests)."""
    nan = float("nan")
    body = struct.pack("<QQB3x3f4fB3x15fBb", px4_timestamp_us, px4_timestamp_us, 1,
                       0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1, *([nan] * 6), *([0.01] * 9), 0, 0)
    return b"\x00\x01\x00\x00" + body
