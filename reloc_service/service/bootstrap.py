"""Copying the served maps from running replicas at start (``service.bootstrap_from_peers``):
the peer's history replayed so that the copy is the same map (same keyframes, intrinsics and
map version), with live puts held in the writers meanwhile."""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING, Any

import numpy as np
import zenoh
from reloc_client import protocol as wire

from . import handlers
from .runtime import MapRuntime

if TYPE_CHECKING:
    from .app import Service

log = logging.getLogger(__name__)


class Bootstrap:
    """Copy the served maps from running replicas (``service.bootstrap_from_peers``).

    A gate job holds the writer while the gets run, so keyframe puts arriving meanwhile wait
    in the writer queue (bounded by ``writer_queue_size``); the gate then applies the copies
    (journaled like any put) and the writer goes on with the buffered puts, in order."""

    #: Seconds for each get (a replica sending hundreds of keyframe images needs a while).
    TIMEOUT = 60.0

    def __init__(self, service: Service) -> None:
        self.service = service
        self.fetched: list[tuple[MapRuntime, str, Any, bytes]] = []
        self._ready = threading.Event()
        self._done = threading.Event()
        service._bootstrap_window = True
        assert service.writer is not None
        if not service.writer.submit(self._apply):
            raise RuntimeError("the writer queue refused the bootstrap job")
        for name in sorted(service.maps):   # each map's writer waits for the copy too
            service._writer_for(name).submit(self._hold)

    def _hold(self, _queued: float) -> None:
        self._done.wait(self.TIMEOUT * 6)

    def run(self) -> None:
        """Fetch cameras and keyframes of every served map, let the writer apply them, wait."""
        svc = self.service
        try:
            for name, rt in sorted(svc.maps.items()):
                for key, payload in self._get(wire.keys.cameras(svc.prefix, name)):
                    self.fetched.append((rt, "cam", key, payload))
                for key, payload in self._get(wire.keys.keyframes(svc.prefix, name)
                                              + "?image=true"):
                    self.fetched.append((rt, "kf", key, payload))
        finally:
            self._ready.set()
        if not self._done.wait(self.TIMEOUT * 2):
            log.error("bootstrap: the writer did not apply the copied maps in time")

    def _get(self, key: str) -> list[tuple[str, bytes]]:
        out = []
        for reply in self.service.session.get(
                key, timeout=self.TIMEOUT, target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE):
            if reply.ok is not None:
                out.append((str(reply.ok.key_expr), reply.ok.payload.to_bytes()))
            else:
                log.warning("bootstrap: an error reply to %s: %r", key,
                            reply.err.payload.to_bytes()[:200] if reply.err else b"")
        return out

    def _apply(self, _queued: float) -> None:
        svc = self.service
        try:
            if not self._ready.wait(self.TIMEOUT * 4):   # start-up failed before the gets
                return
            counts: dict[str, int] = {}
            for rt in {id(rt): rt for rt, *_ in self.fetched}.values():
                counts[rt.name] = self._replay_history(rt)
            for name, rt in svc.maps.items():
                rt.stats.count("bootstrap_keyframes", counts.get(name, 0))
            log.info("bootstrap: copied %s keyframes from running replicas",
                     counts or "no")
        finally:
            svc._bootstrap_window = False
            self._done.set()

    def _replay_history(self, rt: MapRuntime) -> int:
        """Apply the copies of ``rt``'s map as the peer built it: keyframes in the peer's
        insertion order, each with the intrinsics it was built with (a camera put again since
        then is put back to those intrinsics before it, as the peer's journal had it), then
        the cameras as the peer holds them now. The same history gives the same map and the
        same map version. Returns the keyframes copied."""
        copied = 0
        peer_ids: set[int] = set()
        for _rt, _op, _key, payload in (f for f in self.fetched if f[0] is rt and f[1] == "kf"):
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
        for _rt, _op, _key, payload in (f for f in self.fetched if f[0] is rt and f[1] == "cam"):
            try:
                put = wire.CameraPut.decode(payload, rt.limits)
                self._ensure_camera(rt, put.id, put.camera)
            except Exception as exc:
                log.warning("bootstrap: map %s: a copied camera was not applied: %s",
                            rt.name, exc)
        return copied

    def _copy_keyframe(self, rt: MapRuntime, info: wire.KeyframeInfo) -> int:
        svc = self.service
        if info.image is None or (rt.name, info.id) in svc._bootstrapped:
            return 0     # a second replica's copy of the same keyframe
        if _holds(rt, info):   # restored from this replica's own storage: not applied twice
            rt.stats.count("bootstrap_already_held")
            svc._bootstrapped[(rt.name, info.id)] = (info.world_from_cam.matrix(),
                                                     info.timestamp)
            return 0
        if info.camera_id is not None:
            self._ensure_camera(rt, info.camera_id, info.camera)
        message = wire.KeyframePut(
            id=info.id, image=info.image, world_from_cam=info.world_from_cam,
            camera_id=info.camera_id, camera=None if info.camera_id else info.camera,
            timestamp=info.timestamp)
        rt.put_keyframe(info.id, message.encode())
        svc._bootstrapped[(rt.name, info.id)] = (info.world_from_cam.matrix(), info.timestamp)
        return 1

    @staticmethod
    def _ensure_camera(rt: MapRuntime, camera_id: str, camera: wire.WireCamera) -> None:
        """Register ``camera`` under ``camera_id`` unless it already is (journaled, as a put)."""
        current = rt.camera(camera_id)
        if current is None or current.to_dict() != handlers.to_camera(camera).to_dict():
            rt.put_camera(camera_id, wire.CameraPut(camera_id, camera).encode())


def _holds(rt: MapRuntime, info: wire.KeyframeInfo) -> bool:
    """Whether ``rt`` already holds keyframe ``info`` as the peer does (pose, time, camera)."""
    kf = rt.map_state().keyframes.get(info.id)
    return (kf is not None and kf.timestamp == info.timestamp
            and np.allclose(kf.world_from_cam, info.world_from_cam.matrix(), atol=1e-9)
            and kf.camera.to_dict() == handlers.to_camera(info.camera).to_dict())
