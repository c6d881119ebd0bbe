"""Quotas on what the maps hold: maps per service, keyframes per map, bytes per map and in
total (``[quotas]``, :class:`~.config.QuotasConf`). A put beyond one is refused with
``QUOTA_EXCEEDED`` naming the quota, its limit and the current use, before anything is
journaled; deleting keyframes frees their share.

What a keyframe counts (:func:`keyframe_bytes`): its image as the map holds it (the encoded
bytes a client sent or a snapshot maps, or the pixels when it holds raw pixels), its depth,
and its features at their in-memory size (per keypoint :data:`KEYPOINT_BYTES` plus the
descriptor, :data:`DESCRIPTOR_BYTES`), counted from the keypoint counts so a loaded map's
features are not built to be counted. A put not applied yet counts its payload bytes (its
features are computed when it is applied, and counted then): a map may so end one keyframe's
features above its byte quota, never more.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable

from reloc_client.protocol import ErrorCode, ProtocolError

from ..core.frame import EncodedImage, Keyframe
from ..core.map import MapState
from .config import QuotasConf

#: Bytes of one keypoint besides its descriptor, as :class:`~..core.frame.Features` holds
#: it: position (2 float64), level (int16), size and angle (float32), landmark id (int64),
#: world point (3 float64).
KEYPOINT_BYTES = 16 + 2 + 4 + 4 + 8 + 24
#: Descriptor bytes per keypoint by feature kind (uint8 ORB bits, uint8 SIFT values); a kind
#: not named counts as SIFT.
DESCRIPTOR_BYTES = {"orb": 32, "sift": 128}


def keyframe_bytes(keyframe: Keyframe) -> int:
    """The bytes ``keyframe`` counts against its map's quota (see module docstring)."""
    source = keyframe.image_source
    if isinstance(source, EncodedImage):   # bytes sent, or a snapshot file's mapped array
        data = source.data
        image = len(data) if isinstance(data, bytes) else data.nbytes
    else:
        image = source.nbytes
    depth = 0 if keyframe.depth is None else keyframe.depth.nbytes
    features = sum(_keypoints(keyframe, kind) * (KEYPOINT_BYTES + DESCRIPTOR_BYTES.get(kind, 128))
                   for kind in keyframe.features)
    return int(image + depth + features)


def _keypoints(keyframe: Keyframe, kind: str) -> int:
    """Keypoints of ``kind``, without building a loaded keyframe's features."""
    count = getattr(keyframe.features, "count", None)   # LazyFeatures (a loaded map)
    return int(count(kind)) if callable(count) else len(keyframe.features[kind])


class MapUsage:
    """The keyframes of one map (applied, or accepted and waiting) and the bytes each
    counts; changed only through :class:`Quotas` (under its lock)."""

    def __init__(self) -> None:
        self.bytes_of: dict[int, int] = {}
        self.total = 0

    @classmethod
    def of(cls, state: MapState) -> MapUsage:
        """The use of the keyframes in ``state`` (a map loaded from its snapshot)."""
        usage = cls()
        for kf_id, keyframe in state.keyframes.items():
            usage.set_bytes(kf_id, keyframe_bytes(keyframe))
        return usage

    @property
    def keyframes(self) -> int:
        return len(self.bytes_of)

    def set_bytes(self, kf_id: int, size: int | None) -> None:
        old = self.bytes_of.pop(kf_id, 0)
        if size is not None:
            self.bytes_of[kf_id] = size
        self.total += (size or 0) - old


class Quotas:
    """The service's quotas checked against every map's :class:`MapUsage` (``usages``
    lists them); one lock orders the checks of maps written at once on different writer
    threads, so two maps cannot both take the last bytes of the total."""

    def __init__(self, conf: QuotasConf, usages: Callable[[], Iterable[MapUsage]]) -> None:
        self.conf = conf
        self._usages = usages
        self._lock = threading.Lock()

    def check_new_map(self, name: str, served: int) -> None:
        """QUOTA_EXCEEDED if a put may not create map ``name`` with ``served`` maps served."""
        if served >= self.conf.max_maps:
            raise ProtocolError(
                ErrorCode.QUOTA_EXCEEDED,
                f"quotas.max_maps: {served} maps are served, the limit is "
                f"{self.conf.max_maps}; map {name!r} is not created (put on a served map, or "
                f"raise the quota)")

    def admit(self, name: str, usage: MapUsage, kf_id: int, size: int) -> None:
        """Count a put of keyframe ``kf_id`` (``size`` payload bytes) on map ``name``, or
        raise QUOTA_EXCEEDED naming the quota, its limit and the use (nothing counted).
        Replacing a keyframe adds none and frees its old bytes."""
        q = self.conf
        with self._lock:
            old = usage.bytes_of.get(kf_id)
            if old is None and usage.keyframes >= q.max_keyframes_per_map:
                self._refuse(f"quotas.max_keyframes_per_map: map {name!r} holds "
                             f"{usage.keyframes} keyframes, the limit is "
                             f"{q.max_keyframes_per_map}")
            delta = size - (old or 0)
            if usage.total + delta > q.max_map_bytes:
                self._refuse(f"quotas.max_map_bytes: map {name!r} holds {usage.total} bytes "
                             f"and keyframe {kf_id} adds {size}, over the limit of "
                             f"{q.max_map_bytes} bytes")
            total = sum(u.total for u in self._usages())
            if total + delta > q.max_total_bytes:
                self._refuse(f"quotas.max_total_bytes: the maps hold {total} bytes together "
                             f"and keyframe {kf_id} of map {name!r} adds {size}, over the "
                             f"limit of {q.max_total_bytes} bytes")
            usage.set_bytes(kf_id, size)

    @staticmethod
    def _refuse(problem: str) -> None:
        raise ProtocolError(ErrorCode.QUOTA_EXCEEDED,
                            f"{problem}; delete keyframes (or raise the quota) to add more")

    def count(self, usage: MapUsage, kf_id: int, size: int | None) -> None:
        """Set what keyframe ``kf_id`` counts (None: nothing, it left the map)."""
        with self._lock:
            usage.set_bytes(kf_id, size)
