"""The bridge's warnings on ``/rosout`` (rcl_interfaces/msg/Log), where ``rqt_console`` and
``ros2 topic echo /rosout`` read every node's log.

Every ROS 2 node publishes ``/rosout`` reliable, transient local, depth 1000, lifespan 10 s
(rcl's ``rcl_qos_profile_rosout_default``); so does each map's node, with its WARNING and
ERROR records: those of ``reloc_service.service.ros2`` that name its map (``map <name>: ...``)
and those that name no map (e.g. a ROS 2 type mismatch, which concerns every node). INFO
lines (each keyframe added) stay in reloc's own log: /rosout is what needs a look.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from . import graph
from . import types as ros
from .qos import Durability, TopicQos

LOG = "rcl_interfaces/msg/Log"
ROSOUT = "/rosout"
#: rcl's rosout QoS: the publisher's, and its token's (which carries the 10 s lifespan too).
TOPIC_QOS = TopicQos(durability=Durability.TRANSIENT_LOCAL, depth=1000)
TOKEN_QOS = graph.Qos(depth=1000, durability=graph.Durability.TRANSIENT_LOCAL,
                      lifespan=(10, 0))
#: rcl_interfaces/msg/Log levels of Python's.
LEVELS = {logging.DEBUG: 10, logging.INFO: 20, logging.WARNING: 30, logging.ERROR: 40,
          logging.CRITICAL: 50}
WATCHED_LOGGER = "reloc_service.service.ros2"


def ros_level(levelno: int) -> int:
    """The Log level of a Python level (the highest not above it)."""
    return max((v for k, v in LEVELS.items() if k <= levelno), default=10)


def log_message(record: logging.LogRecord, logger_name: str) -> Any:
    """An rcl_interfaces/msg/Log of ``record`` from node logger ``logger_name``."""
    m = ros.message
    t = record.created
    return m(LOG, stamp=m("builtin_interfaces/msg/Time", sec=int(t),
                          nanosec=int((t - int(t)) * 1e9)),
             level=ros_level(record.levelno), name=logger_name, msg=record.getMessage(),
             file=record.pathname, function=record.funcName, line=int(record.lineno))


def node_logger_name(namespace: str, node: str) -> str:
    """rcl's logger name of a node: its namespace and name joined with dots."""
    return ".".join([*(p for p in namespace.split("/") if p), node])


class LogPublisher:
    """Publishes records as Log messages of one node on its /rosout publisher."""

    def __init__(self, publisher: Any, gid: bytes, logger_name: str) -> None:
        self.publisher = publisher
        self.gid = gid
        self.logger_name = logger_name
        self._seq = itertools.count(1)   # rmw_zenoh numbers each publisher's samples

    def __call__(self, record: logging.LogRecord) -> None:
        attachment = graph.Attachment(next(self._seq), time.time_ns(), self.gid)
        self.publisher.put(ros.encode(log_message(record, self.logger_name), LOG),
                           attachment=attachment.encode())


class RosoutHandler(logging.Handler):
    """Hands the WARNING+ records of one map's node to ``publish`` (see module docstring);
    a failure to publish is never logged again through it."""

    def __init__(self, map_name: str, publish: Callable[[logging.LogRecord], None]) -> None:
        super().__init__(logging.WARNING)
        self.map_name = map_name
        self._publish = publish
        self._inside = threading.local()

    @classmethod
    def attach(cls, map_name: str, publish: Callable[[logging.LogRecord], None]
               ) -> RosoutHandler:
        """A handler on the bridge's loggers, publishing through ``publish``."""
        handler = cls(map_name, publish)
        logging.getLogger(WATCHED_LOGGER).addHandler(handler)
        return handler

    def detach(self) -> None:
        logging.getLogger(WATCHED_LOGGER).removeHandler(self)

    def emit(self, record: logging.LogRecord) -> None:
        if getattr(self._inside, "active", False) or not self._concerns_us(record):
            return
        self._inside.active = True
        try:
            self._publish(record)
        except Exception:   # never back into logging (it would come here again)
            pass
        finally:
            self._inside.active = False

    def _concerns_us(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not message.startswith("map ") or message.startswith(f"map {self.map_name}:")
