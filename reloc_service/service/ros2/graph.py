"""rmw_zenoh's graph format: data key expressions, liveliness tokens, QoS strings, entity GIDs
and the 33-byte sample attachment (ros2/rmw_zenoh docs/design.md and
``rmw_zenoh_cpp/src/detail/{liveliness_utils,qos,attachment_helpers}.cpp``).

- data key: ``<domain>/<name without leading slash>/<DDS type name>/<type hash>``;
- token: ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/<enclave>/<namespace>/<node>`` and, for
  a publisher (MP), subscriber (MS), service (SS) or client (SC),
  ``/<topic>/<type>/<hash>/<qos>``, every name with ``/`` mangled to ``%``;
- an entity's GID: XXH3-128 of its token, low 64 bits then high 64 bits, each little endian;
- attachment: int64 sequence number, int64 source timestamp (ns), the serialized 16-byte GID
  (a length byte 16, then the bytes), little endian.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

import xxhash

ADMIN_SPACE = "@ros2_lv"
GID_SIZE = 16
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE
_ATTACHMENT = struct.Struct("<qqB16s")

# rmw_zenoh's default QoS (qos.cpp): fields equal to it are left empty in the QoS string.
DEFAULT_DEPTH = 42


class EntityKind(enum.Enum):
    """The entity kinds of a liveliness token."""

    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIBER = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


class Reliability(enum.IntEnum):
    """``rmw_qos_reliability_policy_e``."""

    RELIABLE = 1
    BEST_EFFORT = 2


class Durability(enum.IntEnum):
    """``rmw_qos_durability_policy_e``."""

    TRANSIENT_LOCAL = 1
    VOLATILE = 2


@dataclass(frozen=True)
class Qos:
    """The QoS settings reloc uses (history KEEP_LAST; deadline, lifespan and liveliness at
    rmw_zenoh's defaults)."""

    depth: int = 10
    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    #: (seconds, nanoseconds), None for the default (/rosout's is 10 s: a real rmw_zenoh
    #: token of it reads ``:1:,1000:,:10,0:,,``).
    lifespan: tuple[int, int] | None = None

    def encode(self) -> str:
        """The compact string of a token: ``<rel>:<dur>:<hist>,<depth>:<deadline s,ns>:
        <lifespan s,ns>:<liveliness kind,s,ns>``, each field empty when it is the default."""
        rel = "" if self.reliability is Reliability.RELIABLE else str(int(self.reliability))
        dur = "" if self.durability is Durability.VOLATILE else str(int(self.durability))
        depth = "" if self.depth == DEFAULT_DEPTH else str(self.depth)
        lifespan = "," if self.lifespan is None else f"{self.lifespan[0]},{self.lifespan[1]}"
        return f"{rel}:{dur}:,{depth}:,:{lifespan}:,,"


def mangle(name: str) -> str:
    """``/`` -> ``%`` (a name as one key chunk)."""
    return name.replace("/", "%")


def data_key(domain_id: int, name: str, dds_type: str, type_hash: str) -> str:
    """The key expression samples and queries of topic/service ``name`` travel on."""
    return f"{domain_id}/{name.strip('/')}/{dds_type}/{type_hash}"


@dataclass(frozen=True)
class Node:
    """A node as its tokens name it (``namespace`` absolute, ``/`` for none)."""

    domain_id: int
    zid: str
    node_id: int
    name: str
    namespace: str = "/"
    enclave: str = "/"

    def token(self) -> str:
        return self._prefix(self.node_id, EntityKind.NODE)

    def _prefix(self, entity_id: int, kind: EntityKind) -> str:
        return (f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{entity_id}/"
                f"{kind.value}/{mangle(self.enclave)}/{mangle(self.namespace)}/"
                f"{mangle(self.name)}")

    def endpoint_token(self, entity_id: int, kind: EntityKind, name: str, dds_type: str,
                       type_hash: str, qos: Qos) -> str:
        """The token of a publisher, subscriber, service or client ``name`` (absolute)."""
        if kind is EntityKind.NODE:
            raise ValueError("endpoint_token: a node's token is Node.token()")
        return (f"{self._prefix(entity_id, kind)}/{mangle(name)}/{mangle(dds_type)}/"
                f"{mangle(type_hash)}/{qos.encode()}")


@dataclass(frozen=True)
class Endpoint:
    """A parsed endpoint token (what another participant advertises)."""

    zid: str
    kind: EntityKind
    node: str
    name: str
    dds_type: str
    type_hash: str


def parse_token(key: str) -> Endpoint | None:
    """The endpoint a liveliness token advertises; None for a node token or a key that is
    not an rmw_zenoh token."""
    parts = key.split("/")
    if len(parts) < 13 or parts[0] != ADMIN_SPACE:
        return None
    try:
        kind = EntityKind(parts[5])
    except ValueError:
        return None
    if kind is EntityKind.NODE:
        return None
    unmangle = lambda s: s.replace("%", "/")  # noqa: E731
    return Endpoint(zid=parts[2], kind=kind, node=unmangle(parts[8]), name=unmangle(parts[9]),
                    dds_type=unmangle(parts[10]), type_hash=unmangle(parts[11]))


def gid_of(token: str) -> bytes:
    """An entity's 16-byte GID: XXH3-128 of its token, low 64 bits first, little endian."""
    value = xxhash.xxh3_128_intdigest(token.encode())
    low, high = value & (2**64 - 1), value >> 64
    return low.to_bytes(8, "little") + high.to_bytes(8, "little")


@dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to every sample, query and reply."""

    sequence_number: int
    timestamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        if len(self.gid) != GID_SIZE:
            raise ValueError(f"attachment gid: expected {GID_SIZE} bytes, got {len(self.gid)}")
        return _ATTACHMENT.pack(self.sequence_number, self.timestamp_ns, GID_SIZE, self.gid)

    @classmethod
    def decode(cls, data: bytes | None) -> Attachment:
        """ValueError naming what is wrong when ``data`` is not an rmw_zenoh attachment."""
        if data is None:
            raise ValueError("no attachment (rmw_zenoh attaches a sequence number, a "
                             "timestamp and the sender's GID to every sample)")
        if len(data) != ATTACHMENT_SIZE:
            raise ValueError(f"attachment: expected {ATTACHMENT_SIZE} bytes, got {len(data)}")
        seq, stamp, gid_len, gid = _ATTACHMENT.unpack(data)
        if gid_len != GID_SIZE:
            raise ValueError(f"attachment: expected a GID of {GID_SIZE} bytes, length byte "
                             f"says {gid_len}")
        return cls(seq, stamp, gid)
