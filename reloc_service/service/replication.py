"""Several instances under one prefix: which maps another live instance serves (sharding,
:class:`Peers`), and copying the served maps from running replicas at start
(``service.bootstrap_from_peers``, :class:`Bootstrap`): the peer's history replayed so that
the copy is the same map (same keyframes, intrinsics and map version), with live puts held in
the writers meanwhile.

Both take the Zenoh session and what they need of the service as parameters, so this module
does not import the service (:mod:`.app` imports it)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt
import zenoh
from reloc_client import protocol as wire

from .codec import pose_covariance_of, to_camera
from .runtime import MapRuntime
from .served import WriteOp
from .workers import Lane, WorkerPool

log = logging.getLogger(__name__)


class Peers:
    """Whether another live instance serves a map (its liveliness token, or its answer to a
    status query; cached for a few seconds): then a put on it is that shard's, not an error
    here."""

    #: Seconds an answer is reused (a burst of puts on another shard's map asks once).
    CACHE_S = 2.0

    def __init__(self, session: Any, prefix: str, instance: str, limits: wire.Limits) -> None:
        self.session = session
        self.prefix = prefix
        self.instance = instance
        self.limits = limits
        self._cache: dict[str, tuple[float, bool]] = {}   # map -> (when, served elsewhere)

    def serves(self, map_name: str) -> bool:
        """Whether another live instance serves ``map_name``."""
        now = time.monotonic()
        cached = self._cache.get(map_name)
        if cached is not None and now - cached[0] < self.CACHE_S:
            return cached[1]
        found = False
        try:
            found = self._live_elsewhere(map_name)
            # A router whose access rules deny by default answers no liveliness query
            # (deploy/README.md, known limit): ask the map's status queryable instead.
            found = found or self._status_elsewhere(map_name)
        except Exception as exc:  # a closing session, a bad name: not served elsewhere
            log.debug("liveliness get for map %s failed: %s", map_name, exc)
        self._cache[map_name] = (now, found)
        return found

    def _live_elsewhere(self, map_name: str) -> bool:
        """Whether another instance holds a liveliness token for ``map_name``."""
        found = False
        key = f"{self.prefix}/@live/*/{wire.check_name(map_name)}"
        for reply in self.session.liveliness().get(key, timeout=1.0):
            if reply.ok is not None and not str(reply.ok.key_expr).startswith(
                    f"{self.prefix}/@live/{self.instance}/"):
                found = True
        return found

    def _status_elsewhere(self, map_name: str) -> bool:
        """Whether another instance answers a status query on ``map_name``."""
        for reply in self.session.get(wire.keys.status(self.prefix, map_name), timeout=1.0,
                                      payload=None):
            if reply.ok is None:
                continue
            try:
                status = wire.StatusReply.decode(reply.ok.payload.to_bytes(), self.limits)
            except wire.ProtocolError:
                continue
            if status.instance != self.instance:
                return True
        return False


class Bootstrap:
    """Copy the served maps from running replicas (``service.bootstrap_from_peers``).

    A gate job holds the writer while the gets run, so keyframe puts arriving meanwhile wait
    in the writer queue (bounded by ``writer_queue_size``); the gate then applies the copies
    (journaled like any put) and the writer goes on with the buffered puts, in order."""

    #: Seconds for each get (a replica sending hundreds of keyframe images needs a while).
    TIMEOUT = 60.0

    def __init__(self, session: Any, prefix: str, maps: Mapping[str, MapRuntime], *,
                 gate: WorkerPool, writer_for: Callable[[str], WorkerPool | Lane]) -> None:
        """Copy ``maps`` (the service's served maps) from the replicas answering on
        ``prefix``; ``gate`` is the writer that applies the copies, ``writer_for`` gives each
        map's writer (held until the copies are applied)."""
        self.session = session
        self.prefix = prefix
        self.maps = maps
        self._gate = gate
        self._writer_for = writer_for
        #: (map, CAMERA: a CameraPut or KEYFRAME: a KeyframeInfo, key, payload) as fetched.
        self.fetched: list[tuple[MapRuntime, WriteOp, Any, bytes]] = []
        #: While True, live keyframe puts go through :meth:`put_unless_copied`.
        self.active = True
        #: (map, keyframe id) -> (pose, timestamp, pose covariance) copied from a peer (or
        #: already held): a buffered live put identical to its copy is not applied twice.
        self.copied: dict[tuple[str, int], tuple[Any, Any, Any]] = {}
        self._ready = threading.Event()
        self._done = threading.Event()

    def _hold_writers(self) -> None:
        """The gate applies the copies; each map's writer waits for them too."""
        if not self._gate.submit(self._apply):
            raise RuntimeError("the writer queue refused the bootstrap job")
        for name in sorted(self.maps):
            self._writer_for(name).submit(self._hold)

    def _hold(self, _queued: float) -> None:
        self._done.wait(self.TIMEOUT * 6)

    def run(self) -> None:
        """Hold the writers, fetch cameras and keyframes of every served map, let the gate
        apply them, wait."""
        self._hold_writers()
        try:
            for name, rt in sorted(self.maps.items()):
                for key, payload in self._get(wire.keys.cameras(self.prefix, name)):
                    self.fetched.append((rt, WriteOp.CAMERA, key, payload))
                for key, payload in self._get(wire.keys.keyframes(self.prefix, name)
                                              + "?image=true"):
                    self.fetched.append((rt, WriteOp.KEYFRAME, key, payload))
        finally:
            self._ready.set()
        if not self._done.wait(self.TIMEOUT * 2):
            log.error("bootstrap: the writer did not apply the copied maps in time")

    def _get(self, key: str) -> list[tuple[str, bytes]]:
        out = []
        for reply in self.session.get(
                key, timeout=self.TIMEOUT, target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE):
            if reply.ok is not None:
                out.append((str(reply.ok.key_expr), reply.ok.payload.to_bytes()))
            else:
                log.warning("bootstrap: an error reply to %s: %r", key,
                            reply.err.payload.to_bytes()[:200] if reply.err else b"")
        return out

    def _apply(self, _queued: float) -> None:
        try:
            if not self._ready.wait(self.TIMEOUT * 4):   # start-up failed before the gets
                return
            counts: dict[str, int] = {}
            for rt in {id(rt): rt for rt, *_ in self.fetched}.values():
                counts[rt.name] = self._replay_history(rt)
            for name, rt in self.maps.items():
                rt.stats.count("bootstrap_keyframes", counts.get(name, 0))
            log.info("bootstrap: copied %s keyframes from running replicas",
                     counts or "no")
        finally:
            self.active = False
            self._done.set()

    def _replay_history(self, rt: MapRuntime) -> int:
        """Apply the copies of ``rt``'s map as the peer built it: keyframes in the peer's
        insertion order, each with the intrinsics it was built with (a camera put again since
        then is put back to those intrinsics before it, as the peer's journal had it), then
        the cameras as the peer holds them now. The same history gives the same map and the
        same map version. Returns the keyframes copied."""
        copied = 0
        peer_ids: set[int] = set()
        for payload in self._fetched_payloads(rt, WriteOp.KEYFRAME):
            try:
                info = wire.KeyframeInfo.decode(payload, rt.limits)
                peer_ids.add(info.id)
                copied += self._copy_keyframe(rt, info)
            except Exception as exc:
                log.warning("bootstrap: map %s: a copied keyframe was not applied: %s",
                            rt.name, exc)
        if peer_ids:   # restored from our own storage, removed by the peer meanwhile
            for kf_id in sorted(set(rt.map_state().keyframes) - peer_ids):
                rt.delete_keyframe(kf_id)
        for payload in self._fetched_payloads(rt, WriteOp.CAMERA):
            try:
                put = wire.CameraPut.decode(payload, rt.limits)
                self._ensure_camera(rt, put.id, put.camera)
            except Exception as exc:
                log.warning("bootstrap: map %s: a copied camera was not applied: %s",
                            rt.name, exc)
        return copied

    def _fetched_payloads(self, rt: MapRuntime, op: WriteOp) -> list[bytes]:
        """The payloads fetched for ``rt`` of kind ``op``, in the order the peers sent them."""
        return [payload for fetched_rt, fetched_op, _key, payload in self.fetched
                if fetched_rt is rt and fetched_op is op]

    def _copy_keyframe(self, rt: MapRuntime, info: wire.KeyframeInfo) -> int:
        if info.image is None or (rt.name, info.id) in self.copied:
            return 0     # a second replica's copy of the same keyframe
        if _holds(rt, info):   # restored from this replica's own storage: not applied twice
            rt.stats.count("bootstrap_already_held")
            self.copied[(rt.name, info.id)] = _copy_key(info)
            return 0
        if info.camera_id is not None:
            self._ensure_camera(rt, info.camera_id, info.camera)
        message = wire.KeyframePut(
            id=info.id, image=info.image, world_from_cam=info.world_from_cam,
            camera_id=info.camera_id, camera=None if info.camera_id else info.camera,
            timestamp=info.timestamp, pose_covariance=info.pose_covariance)
        rt.put_keyframe(info.id, message.encode())
        self.copied[(rt.name, info.id)] = _copy_key(info)
        return 1

    def put_unless_copied(self, rt: MapRuntime, kf_id: int, payload: bytes) -> None:
        """A live put buffered during the bootstrap: skipped if the copy already holds it."""
        copied = self.copied.get((rt.name, kf_id))
        if copied is not None:
            try:
                put = wire.KeyframePut.decode(payload, rt.limits)
            except wire.ProtocolError:
                put = None
            if (put is not None and put.timestamp == copied[1]
                    and np.allclose(put.world_from_cam.matrix(), copied[0], atol=1e-9)
                    and _same_covariance(pose_covariance_of(put), copied[2])):
                rt.stats.count("bootstrap_duplicates")
                return
        rt.put_keyframe(kf_id, payload)

    @staticmethod
    def _ensure_camera(rt: MapRuntime, camera_id: str, camera: wire.WireCamera) -> None:
        """Register ``camera`` under ``camera_id`` unless it already is (journaled, as a put)."""
        current = rt.camera(camera_id)
        if current is None or current.to_dict() != to_camera(camera).to_dict():
            rt.put_camera(camera_id, wire.CameraPut(camera_id, camera).encode())


def _copy_key(info: wire.KeyframeInfo) -> tuple[Any, Any, Any]:
    """What a buffered live put is compared with: the copy's pose, timestamp, covariance."""
    return info.world_from_cam.matrix(), info.timestamp, pose_covariance_of(info)


def _holds(rt: MapRuntime, info: wire.KeyframeInfo) -> bool:
    """Whether ``rt`` already holds keyframe ``info`` as the peer does (pose, its covariance,
    time, camera)."""
    kf = rt.map_state().keyframes.get(info.id)
    return (kf is not None and kf.timestamp == info.timestamp
            and np.allclose(kf.world_from_cam, info.world_from_cam.matrix(), atol=1e-9)
            and _same_covariance(kf.pose_covariance, pose_covariance_of(info))
            and kf.camera.to_dict() == to_camera(info.camera).to_dict())


def _same_covariance(a: npt.NDArray[np.float64] | None, b: npt.NDArray[np.float64] | None
                     ) -> bool:
    """Both None, or both given and equal (to rounding)."""
    if a is None or b is None:
        return a is None and b is None
    return bool(np.allclose(a, b, rtol=1e-12, atol=0.0))
