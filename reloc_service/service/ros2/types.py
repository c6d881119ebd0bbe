"""The ROS 2 interfaces reloc speaks: their DDS names, RIHS01 type hashes (REP-2011) computed
from the type descriptions, and CDR (little endian, header ``00 01 00 00``) through rosbags.

The message definitions come from rosbags' Jazzy type store. rosbags has no service types, so
``std_srvs/srv/Trigger`` is described here; and rosbags' own ``hash_rihs01`` gives ``char``
FIELD_TYPE_CHAR where rosidl, which turns a .msg ``char`` into IDL ``uint8``, writes uint8's
id; that breaks every service hash (``ServiceEventInfo.client_gid`` is a
``char[16]``), so :func:`type_hash` has its own field-type table.
"""

from __future__ import annotations

import functools
import hashlib
import json
from collections.abc import Mapping
from typing import Any

from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
BOOL = "std_msgs/msg/Bool"
TRIGGER = "std_srvs/srv/Trigger"
SET_BOOL = "std_srvs/srv/SetBool"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"

#: What rmw_zenoh on Humble writes instead of a hash (Humble has no type hashes).
HASH_NOT_SUPPORTED = "TypeHashNotSupported"

# type_description_interfaces/msg/FieldType ids; +48 fixed array, +96 bounded sequence,
# +144 unbounded sequence.
_FIELD_TYPE_IDS = {
    "nested": 1, "int8": 2, "uint8": 3, "int16": 4, "uint16": 5, "int32": 6, "uint32": 7,
    "int64": 8, "uint64": 9, "float32": 10, "float64": 11, "float128": 12,
    # A .msg ``char`` becomes IDL ``uint8`` (rosidl_adapter), so its id is uint8's, not
    # FIELD_TYPE_CHAR (13) as rosbags has it: only then is the Trigger hash the official one.
    "char": 3,
    "wchar": 14, "bool": 15, "byte": 16, "octet": 16, "string": 17, "wstring": 18,
    "bounded_string": 21, "bounded_wstring": 22}
_ARRAY, _BOUNDED_SEQUENCE, _SEQUENCE = 48, 96, 144

# std_srvs/srv/Trigger as rosidl generates it: request, response and the event message that
# every Iron+ service type embeds (its hash covers all three). rosbags' message parser renames
# ``srv`` types, so their field definitions are written in its format directly.
def _trigger_fielddefs() -> dict[str, Any]:
    from rosbags.typesys.base import Nodetype

    base = lambda t: (Nodetype.BASE, (t, 0))  # noqa: E731
    name = lambda t: (Nodetype.NAME, t)  # noqa: E731
    at_most_one = lambda t: (Nodetype.SEQUENCE, (name(t), 1))  # noqa: E731
    return {
        "std_srvs/srv/Trigger_Request": ([], [("structure_needs_at_least_one_member",
                                               base("uint8"))]),
        "std_srvs/srv/Trigger_Response": ([], [("success", base("bool")),
                                               ("message", base("string"))]),
        "std_srvs/srv/Trigger_Event": ([], [
            ("info", name("service_msgs/msg/ServiceEventInfo")),
            ("request", at_most_one("std_srvs/srv/Trigger_Request")),
            ("response", at_most_one("std_srvs/srv/Trigger_Response"))]),
    }


def _set_bool_fielddefs() -> dict[str, Any]:
    """std_srvs/srv/SetBool as rosidl generates it (request ``bool data``; response ``bool
    success``, ``string message``; its event), in the format of :func:`_trigger_fielddefs`."""
    from rosbags.typesys.base import Nodetype

    base = lambda t: (Nodetype.BASE, (t, 0))  # noqa: E731
    at_most_one = lambda t: (Nodetype.SEQUENCE, ((Nodetype.NAME, t), 1))  # noqa: E731
    return {
        "std_srvs/srv/SetBool_Request": ([], [("data", base("bool"))]),
        "std_srvs/srv/SetBool_Response": ([], [("success", base("bool")),
                                               ("message", base("string"))]),
        "std_srvs/srv/SetBool_Event": ([], [
            ("info", (Nodetype.NAME, "service_msgs/msg/ServiceEventInfo")),
            ("request", at_most_one("std_srvs/srv/SetBool_Request")),
            ("response", at_most_one("std_srvs/srv/SetBool_Response"))]),
    }


_SERVICES = {TRIGGER: ("std_srvs/srv/Trigger_Request", "std_srvs/srv/Trigger_Response",
                       "std_srvs/srv/Trigger_Event"),
             SET_BOOL: ("std_srvs/srv/SetBool_Request", "std_srvs/srv/SetBool_Response",
                        "std_srvs/srv/SetBool_Event")}


@functools.lru_cache(maxsize=1)
def typestore() -> Typestore:
    """rosbags' Jazzy type store plus the Trigger and SetBool services' messages."""
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(_trigger_fielddefs())
    store.register(_set_bool_fielddefs())
    return store


def dds_name(ros_type: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_`` (a service: its name without the
    ``Request_``/``Response_`` suffix, as rmw_zenoh writes it)."""
    pkg, kind, name = _split(ros_type)
    return f"{pkg}::{kind}::dds_::{name}_"


def _split(ros_type: str) -> tuple[str, str, str]:
    parts = ros_type.split("/")
    if len(parts) != 3 or parts[1] not in ("msg", "srv") or not all(parts):
        raise ValueError(f"ROS type: expected 'package/msg/Name' or 'package/srv/Name', got "
                         f"{ros_type!r}")
    return parts[0], parts[1], parts[2]


# -- RIHS01 ------------------------------------------------------------------------------------

def _field(name: str, desc: Any, refs: dict[str, Any]) -> dict[str, Any]:
    """One field of a type description (REP-2011 key order)."""
    from rosbags.typesys.base import Nodetype

    increment = capacity = string_capacity = 0
    nested = ""
    node, rest = desc
    if node == Nodetype.ARRAY:
        increment, capacity = _ARRAY, rest[1]
        node, rest = rest[0]
    elif node == Nodetype.SEQUENCE:
        increment, capacity = (_BOUNDED_SEQUENCE, rest[1]) if rest[1] else (_SEQUENCE, 0)
        node, rest = rest[0]
    if node == Nodetype.NAME:
        nested = rest
        type_id = _FIELD_TYPE_IDS["nested"]
        _describe(rest, refs)
    elif rest[0] in ("string", "wstring") and rest[1]:
        type_id, string_capacity = _FIELD_TYPE_IDS[f"bounded_{rest[0]}"], rest[1]
    else:
        type_id = _FIELD_TYPE_IDS[rest[0]]
    return {"name": name, "type": {"type_id": type_id + increment, "capacity": capacity,
                                   "string_capacity": string_capacity,
                                   "nested_type_name": nested}}


def _describe(ros_type: str, refs: dict[str, Any]) -> dict[str, Any]:
    """The type description of a message, its referenced types added to ``refs``."""
    from rosbags.typesys.base import Nodetype

    if ros_type in refs:
        return refs[ros_type]
    refs[ros_type] = {}   # placeholder against cycles
    fields = typestore().fielddefs[ros_type][1] or [
        ("structure_needs_at_least_one_member", (Nodetype.BASE, ("uint8", 0)))]
    refs[ros_type] = {"type_name": ros_type,
                      "fields": [_field(n, d, refs) for n, d in fields]}
    return refs[ros_type]


def _service_description(ros_type: str, refs: dict[str, Any]) -> dict[str, Any]:
    request, response, event = _SERVICES[ros_type]
    for name in (request, response, event):
        _describe(name, refs)
    nested = lambda field, name: {  # noqa: E731
        "name": field, "type": {"type_id": 1, "capacity": 0, "string_capacity": 0,
                                "nested_type_name": name}}
    return {"type_name": ros_type, "fields": [nested("request_message", request),
                                              nested("response_message", response),
                                              nested("event_message", event)]}


@functools.lru_cache(maxsize=64)
def type_hash(ros_type: str) -> str:
    """``RIHS01_<sha256>`` of the type description of ``ros_type`` (a message of rosbags'
    Jazzy store or a service of this module): the JSON of REP-2011 (``type_description``
    then ``referenced_type_descriptions`` sorted by name, no default values, ``", "`` and
    ``": "`` separators)."""
    _split(ros_type)
    refs: dict[str, Any] = {}
    if ros_type in _SERVICES:
        top = _service_description(ros_type, refs)
    elif ros_type in typestore().fielddefs:
        top = _describe(ros_type, refs)
    else:
        raise ValueError(f"type_hash: no type description of {ros_type!r}")
    refs.pop(ros_type, None)
    document = {"type_description": top,
                "referenced_type_descriptions": [refs[k] for k in sorted(refs)]}
    text = json.dumps(document, separators=(", ", ": "), ensure_ascii=True)
    return "RIHS01_" + hashlib.sha256(text.encode("utf-8")).hexdigest()


def key_hash(ros_type: str, distro: str, overrides: Mapping[str, str]) -> str:
    """The type hash rmw_zenoh of ``distro`` writes in keys and tokens: ``overrides`` first,
    ``TypeHashNotSupported`` on Humble, else :func:`type_hash`."""
    if ros_type in overrides:
        return overrides[ros_type]
    if distro == "humble":
        return HASH_NOT_SUPPORTED
    return type_hash(ros_type)


# -- CDR -----------------------------------------------------------------------------------------

def encode(message: Any, ros_type: str) -> bytes:
    """CDR little endian with its encapsulation header."""
    return bytes(typestore().serialize_cdr(message, ros_type))


def decode(data: bytes, ros_type: str) -> Any:
    """A rosbags message object; ValueError when ``data`` is not a CDR ``ros_type``."""
    if len(data) < 4 or data[:2] not in (b"\x00\x01", b"\x00\x00"):
        raise ValueError(f"{ros_type}: expected CDR with the header 00 01 00 00 (little "
                         f"endian) or 00 00 00 00, got {bytes(data[:4]).hex(' ')}")
    try:
        return typestore().deserialize_cdr(bytes(data), ros_type)
    except Exception as exc:   # rosbags raises struct/index/assertion errors on bad input
        raise ValueError(f"{ros_type}: the CDR payload does not decode ({len(data)} bytes): "
                         f"{type(exc).__name__}: {exc}") from None


def message(ros_type: str, **fields: Any) -> Any:
    """A rosbags message object of ``ros_type``."""
    return typestore().types[ros_type](**fields)
