"""The ROS 2 stand-in's latched topics (transient-local QoS, as /diagnostics and /rosout are
published), and readers of diagnostic_msgs/DiagnosticArray and rcl_interfaces/Log; the rest of
the participant is tests/ros2_standin.py."""

from __future__ import annotations

import queue
from dataclasses import dataclass

import zenoh
from ros2_standin import Reader, StandIn, attachment, dds, key

# -- latched topics, /diagnostics -----------------------------------------------------------------
# rmw_zenoh facts used below (rmw_publisher_data.cpp, rmw_subscription_data.cpp): a
# TRANSIENT_LOCAL publisher is a zenoh-ext AdvancedPublisher caching `depth` samples with
# publisher detection and, RELIABLE too, sample-miss detection with a sporadic 500 ms
# heartbeat; a TRANSIENT_LOCAL subscription is an AdvancedSubscriber with history (`depth`
# samples, late publishers detected), subscriber detection and, RELIABLE too, recovery from
# the heartbeat. The QoS string of a reliable transient-local depth-1 endpoint is
# ":1:,1:,:,:,," (durability TRANSIENT_LOCAL = 1; the defaults are left empty).
LATCHED_QOS = ":1:,1:,:,:,,"


class LatchingStandIn(StandIn):
    """The stand-in with transient-local publishers and subscriptions and a generic reader."""

    def __init__(self, router: str, domain: int = 0) -> None:
        super().__init__(router, domain)
        self.samples: dict[str, queue.Queue[tuple[bytes, bytes | None]]] = {}

    def advertise_with_qos(self, kind: str, name: str, ros_type: str, type_hash: str,
                           qos: str) -> None:
        eid = len(self.tokens) + 10
        self.tokens.append(self.session.liveliness().declare_token(
            f"@ros2_lv/{self.domain}/{self.zid}/0/{eid}/{kind}/%/%/drone/"
            f"{name.replace('/', '%')}/{dds(ros_type)}/{type_hash}/{qos}"))

    def publish_latched(self, name: str, ros_type: str, type_hash: str,
                        payload: bytes) -> None:
        """Publish once on a reliable transient-local depth-1 publisher (as a camera driver
        latching its CameraInfo) and keep the publisher (its cache) alive."""
        from zenoh import ext

        k = key(self.domain, name, ros_type, type_hash)
        if k not in self._publishers:
            self._publishers[k] = ext.declare_advanced_publisher(
                self.session, k, cache=ext.CacheConfig(max_samples=1),
                publisher_detection=True,
                sample_miss_detection=ext.MissDetectionConfig(heartbeat=None,
                                                              sporadic_heartbeat=0.5))
            self.advertise_with_qos("MP", name, ros_type, type_hash, LATCHED_QOS)
        self.seq += 1
        self._publishers[k].put(payload, attachment=attachment(self.seq, self.gid))

    def subscribe(self, name: str, ros_type: str, type_hash: str, *, latched: bool = False,
                  depth: int = 1) -> queue.Queue[tuple[bytes, bytes | None]]:
        """A subscription whose (payload, attachment) samples go to the returned queue;
        ``latched``: reliable transient-local ``depth`` (it gets the publisher's cache)."""
        from zenoh import ext

        out: queue.Queue[tuple[bytes, bytes | None]] = queue.Queue()

        def on_sample(sample: zenoh.Sample) -> None:
            att = sample.attachment.to_bytes() if sample.attachment is not None else None
            out.put((sample.payload.to_bytes(), att))

        k = key(self.domain, name, ros_type, type_hash)
        if latched:
            self._subs.append(ext.declare_advanced_subscriber(
                self.session, k, on_sample,
                history=ext.HistoryConfig(detect_late_publishers=True, max_samples=depth),
                recovery=ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
                subscriber_detection=True))
            self.advertise_with_qos("MS", name, ros_type, type_hash, f":1:,{depth}:,:,:,,")
        else:
            self._subs.append(self.session.declare_subscriber(k, on_sample))
            self.advertise("MS", name, ros_type, type_hash)
        self.samples[name] = out
        return out


@dataclass
class DiagnosticStatus:
    level: int
    name: str
    message: str
    hardware_id: str
    values: dict[str, str]


def read_diagnostic_array(data: bytes) -> tuple[tuple[int, int], list[DiagnosticStatus]]:
    """diagnostic_msgs/DiagnosticArray: (header stamp, statuses)."""
    r = Reader(data)
    stamp = (r.i32(), r.u32())
    r.string()                                   # frame_id
    statuses = []
    for _ in range(r.u32()):
        level = r.u8()
        name, message, hardware_id = r.string(), r.string(), r.string()
        values = {}
        for _ in range(r.u32()):
            k = r.string()
            values[k] = r.string()
        statuses.append(DiagnosticStatus(level, name, message, hardware_id, values))
    assert r.pos == len(r.body), (r.pos, len(r.body))   # every byte read
    return stamp, statuses


# rcl_interfaces/msg/Log on /rosout: its official hash and QoS as a real rmw_zenoh node's token
# carries them (reliable, transient local, depth 1000, lifespan 10 s).
ROSOUT_HASH = "RIHS01_e28ce254ca8abc06abf92773b74602cdbf116ed34fbaf294fb9f81da9f318eac"
ROSOUT_QOS = ":1:,1000:,:10,0:,,"


@dataclass
class LogReading:
    stamp: tuple[int, int]
    level: int
    name: str
    msg: str
    file: str
    function: str
    line: int


def read_log(data: bytes) -> LogReading:
    r = Reader(data)
    stamp = (r.i32(), r.u32())
    level = r.u8()
    name, msg, file, function = r.string(), r.string(), r.string(), r.string()
    line = r.u32()
    assert r.pos == len(r.body), (r.pos, len(r.body))
    return LogReading(stamp, level, name, msg, file, function, line)
