"""Per-topic QoS of the ``[ros2]`` bridge and the Zenoh entities rmw_zenoh makes of it.

rmw_zenoh (``rmw_publisher_data.cpp``, ``rmw_subscription_data.cpp``) declares every
publisher and subscription through zenoh-ext:

- a TRANSIENT_LOCAL publisher is an AdvancedPublisher with a cache of ``depth`` samples and
  publisher detection (a liveliness token late subscribers find it by); RELIABLE as well, it
  adds sample-miss detection with a sporadic heartbeat (500 ms);
- a TRANSIENT_LOCAL subscription is an AdvancedSubscriber with history (``depth`` samples,
  detecting late publishers) and subscriber detection; RELIABLE as well, it recovers missed
  samples from the heartbeat;
- VOLATILE entities are plain publishers and subscribers.

A late subscriber of a transient-local publisher thus gets the cached samples, and a
transient-local subscription gets those of a latched publisher declared before it.

This module's configuration half imports nothing heavy (``conf.py`` validates the
``[ros2.qos]`` table with it); the declarations import zenoh when called.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from ...core.errors import ConfigError

#: rmw_zenoh's heartbeat period for RELIABLE + TRANSIENT_LOCAL publishers (seconds).
HEARTBEAT_PERIOD_S = 0.5


class Reliability(enum.StrEnum):
    RELIABLE = "reliable"
    BEST_EFFORT = "best_effort"


class Durability(enum.StrEnum):
    VOLATILE = "volatile"
    TRANSIENT_LOCAL = "transient_local"


@dataclass(frozen=True)
class TopicQos:
    """History KEEP_LAST ``depth``, ``reliability`` and ``durability`` of one topic."""

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    depth: int = 10

    @property
    def reliable(self) -> bool:
        return self.reliability is Reliability.RELIABLE

    @property
    def transient_local(self) -> bool:
        return self.durability is Durability.TRANSIENT_LOCAL


#: The bridge's topics (keys of ``[ros2.qos]``) and their defaults; None: ``qos_depth``,
#: reliable, volatile. The pose is latched as amcl_pose is (a late subscriber gets the last
#: one); CameraInfo is read latched (a camera driver that publishes it once, transient local,
#: is heard even when reloc starts later); /diagnostics as ROS's diagnostic_updater (depth 1).
TOPICS: dict[str, TopicQos | None] = {
    "image": None,
    "camera_info": TopicQos(durability=Durability.TRANSIENT_LOCAL, depth=1),
    "odometry": None,
    "lost": None,
    "pose": TopicQos(durability=Durability.TRANSIENT_LOCAL, depth=1),
    "diagnostics": TopicQos(depth=1),
}
_FIELDS = ("reliability", "durability", "depth")


def parse_table(table: Mapping[str, Any], default_depth: int) -> dict[str, TopicQos]:
    """The QoS of every topic: the defaults, overridden field by field by ``table``
    (``{topic: {reliability, durability, depth}}``); ConfigError naming what was expected."""
    if not isinstance(table, Mapping):
        raise ConfigError(f"ros2.qos: expected a table of topic -> QoS, got {table!r}")
    unknown = sorted(set(table) - set(TOPICS))
    if unknown:
        raise ConfigError(f"ros2.qos: unknown topic(s) {unknown}; expected some of "
                          f"{list(TOPICS)}")
    out = {}
    for topic, default in TOPICS.items():
        base = default or TopicQos(depth=default_depth)
        out[topic] = _override(topic, base, table.get(topic, {}))
    return out


def _override(topic: str, base: TopicQos, fields: Any) -> TopicQos:
    path = f"ros2.qos.{topic}"
    if not isinstance(fields, Mapping):
        raise ConfigError(f"{path}: expected a table with {list(_FIELDS)}, got {fields!r}")
    unknown = sorted(set(fields) - set(_FIELDS))
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {unknown}; expected some of {list(_FIELDS)}")
    reliability = _choice(f"{path}.reliability", fields.get("reliability", base.reliability),
                          Reliability)
    durability = _choice(f"{path}.durability", fields.get("durability", base.durability),
                         Durability)
    depth = fields.get("depth", base.depth)
    if isinstance(depth, bool) or not isinstance(depth, int) or depth < 1:
        raise ConfigError(f"{path}.depth: expected an integer >= 1, got {depth!r}")
    return TopicQos(Reliability(reliability), Durability(durability), depth)


def _choice(path: str, value: Any, choices: type[enum.StrEnum]) -> str:
    names = [c.value for c in choices]  # type: ignore[attr-defined]
    if value not in names:
        raise ConfigError(f"{path}: expected one of {names}, got {value!r}")
    return str(value)


# -- Zenoh entities as rmw_zenoh declares them --------------------------------------------------

def declare_publisher(session: Any, key: str, qos: TopicQos) -> Any:
    """A publisher on ``key`` with ``qos`` (see module docstring). Sample-miss detection is on
    for every transient-local publisher, best effort too: its sequence numbers are what lets
    the cache work on a session without Zenoh timestamping (reloc's)."""
    import zenoh
    from zenoh import ext

    reliability = (zenoh.Reliability.RELIABLE if qos.reliable
                   else zenoh.Reliability.BEST_EFFORT)
    if not qos.transient_local:
        return session.declare_publisher(key, reliability=reliability,
                                         congestion_control=zenoh.CongestionControl.DROP)
    return ext.declare_advanced_publisher(
        session, key, reliability=reliability,
        congestion_control=zenoh.CongestionControl.DROP,
        cache=ext.CacheConfig(max_samples=qos.depth), publisher_detection=True,
        sample_miss_detection=ext.MissDetectionConfig(heartbeat=None,
                                                      sporadic_heartbeat=HEARTBEAT_PERIOD_S))


def declare_subscriber(session: Any, key: str, qos: TopicQos,
                       callback: Callable[[Any], None]) -> Any:
    """A subscriber on ``key`` with ``qos`` (see module docstring)."""
    from zenoh import ext

    if not qos.transient_local:
        return session.declare_subscriber(key, callback)
    recovery = (ext.RecoveryConfig(periodic_queries=None, heartbeat=True) if qos.reliable
                else None)
    return ext.declare_advanced_subscriber(
        session, key, callback,
        history=ext.HistoryConfig(detect_late_publishers=True, max_samples=qos.depth),
        recovery=recovery, subscriber_detection=True)


def token_qos(qos: TopicQos) -> Any:
    """``qos`` as the :class:`graph.Qos` of a liveliness token."""
    from . import graph

    return graph.Qos(depth=qos.depth,
                     reliability=(graph.Reliability.RELIABLE if qos.reliable
                                  else graph.Reliability.BEST_EFFORT),
                     durability=(graph.Durability.TRANSIENT_LOCAL if qos.transient_local
                                 else graph.Durability.VOLATILE))
