"""Several instances under one prefix: which maps another live instance serves (sharding,
:class:`Peers`), and copying the served maps from running replicas at start
(``service.bootstrap_from_peers``, :class:`Bootstrap`): the peer's history replayed so that
the copy is the same map (same keyframes, intrinsics and map version), with live puts held in
the writers meanwhile; only from peers whose map identity matches (:func:`choose_peers`),
and the map identity they compare. Replicas compared while they serve:
:mod:`.divergence`.

Both take the Zenoh session and what they need of the service as parameters, so this module
does not import the service (:mod:`.app` imports it)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
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
                 gate: WorkerPool, writer_for: Callable[[str], WorkerPool | Lane],
                 instance: str = "") -> None:
        """Copy ``maps`` (the service's served maps) from the replicas answering on
        ``prefix``; ``gate`` is the writer that applies the copies, ``writer_for`` gives each
        map's writer (held until the copies are applied)."""
        self.session = session
        self.prefix = prefix
        self.maps = maps
        self._gate = gate
        self._writer_for = writer_for
        self.instance = instance
        #: map -> the identity it takes from its peers (a map that holds nothing yet).
        self.adopt: dict[str, str] = {}
        #: (map, event fields) of each peer not followed: published once the map is declared.
        self.refusals: list[tuple[MapRuntime, dict[str, Any]]] = []
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
                followed = self._followed(rt)
                for key, payload, peer in self._get(wire.keys.cameras(self.prefix, name)):
                    if followed is None or peer in followed:
                        self.fetched.append((rt, WriteOp.CAMERA, key, payload))
                for key, payload, peer in self._get(wire.keys.keyframes(self.prefix, name)
                                                    + "?image=true"):
                    if followed is None or peer in followed:
                        self.fetched.append((rt, WriteOp.KEYFRAME, key, payload))
        finally:
            self._ready.set()
        if not self._done.wait(self.TIMEOUT * 2):
            log.error("bootstrap: the writer did not apply the copied maps in time")

    def _followed(self, rt: MapRuntime) -> set[str] | None:
        """The peers (Zenoh ids) ``rt`` copies from (None: any, a map without storage);
        each peer refused is logged and kept for its event, an identity to adopt noted."""
        peers = peer_statuses(self.session, self.prefix, rt.name, self.instance, rt.limits,
                              timeout=10.0)
        choice = choose_peers(rt, peers)
        for fields in choice.refused:
            log.error("bootstrap: map %s: not following %s: %s", rt.name, fields["peer"],
                      fields["message"])
            rt.diverged = fields["message"]
            self.refusals.append((rt, fields))
        if choice.adopt is not None:
            self.adopt[rt.name] = choice.adopt
        return choice.followed

    def _get(self, key: str) -> list[tuple[str, bytes, str]]:
        """(key, payload, replier's Zenoh id) of every reply to ``key``."""
        out = []
        for reply in self.session.get(
                key, timeout=self.TIMEOUT, target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE):
            if reply.ok is not None:
                out.append((str(reply.ok.key_expr), reply.ok.payload.to_bytes(),
                            _replier(reply)))
            else:
                log.warning("bootstrap: an error reply to %s: %r", key,
                            reply.err.payload.to_bytes()[:200] if reply.err else b"")
        return out

    def _apply(self, _queued: float) -> None:
        try:
            if not self._ready.wait(self.TIMEOUT * 4):   # start-up failed before the gets
                return
            counts: dict[str, int] = {}
            for name, map_id in sorted(self.adopt.items()):
                self._adopt(self.maps[name], map_id)
            for rt in {id(rt): rt for rt, *_ in self.fetched}.values():
                counts[rt.name] = self._replay_history(rt)
            for name, rt in self.maps.items():
                rt.stats.count("bootstrap_keyframes", counts.get(name, 0))
            log.info("bootstrap: copied %s keyframes from running replicas",
                     counts or "no")
        finally:
            self.active = False
            self._done.set()

    def _adopt(self, rt: MapRuntime, map_id: str) -> None:
        """Take the peers' identity for ``rt``; if its storage cannot, copy nothing into it
        (its own identity would then hold another map's keyframes)."""
        try:
            _adopt_identity(rt, map_id)
        except Exception as exc:
            log.error("bootstrap: map %s: cannot take the peers' identity %s (%s); nothing "
                      "copied, the map keeps identity %s", rt.name, map_id, exc, rt.map_id)
            self.fetched = [f for f in self.fetched if f[0] is not rt]

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


# -- map identity and divergence ------------------------------------------------------------------

def peer_statuses(session: Any, prefix: str, map_name: str, instance: str,
                  limits: wire.Limits, *, timeout: float = 2.0
                  ) -> dict[str, wire.StatusReply]:
    """The status of ``map_name`` as each other instance serving it reports it, by the
    replier's Zenoh id (what a keyframes get's replies are matched with)."""
    out: dict[str, wire.StatusReply] = {}
    try:
        replies = session.get(wire.keys.status(prefix, map_name) + "?content_hash=true",
                              timeout=timeout,
                              target=zenoh.QueryTarget.ALL,
                              consolidation=zenoh.ConsolidationMode.NONE)
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                status = wire.StatusReply.decode(reply.ok.payload.to_bytes(), limits)
            except wire.ProtocolError as exc:
                log.warning("map %s: a peer's status does not decode: %s", map_name, exc)
                continue
            if status.instance != instance:
                out[_replier(reply)] = status
    except Exception as exc:   # a closing session: no peer known
        log.debug("status get for map %s failed: %s", map_name, exc)
    return out


def _replier(reply: Any) -> str:
    """The Zenoh id of the session that sent ``reply`` (the same for all its queryables)."""
    replier = reply.replier_id
    return str(getattr(replier, "zid", replier))


@dataclass
class PeerChoice:
    """Which peers a replica follows (None: any), the identity it adopts (a map that holds
    nothing yet), and the event fields of each peer it refuses."""

    followed: set[str] | None
    adopt: str | None = None
    refused: list[dict[str, Any]] = field(default_factory=list)


def choose_peers(rt: MapRuntime, peers: Mapping[str, wire.StatusReply]) -> PeerChoice:
    """A replica follows only the peers serving its map's identity. A map holding keyframes
    keeps its identity; one holding none takes the identity most peers serve (ties: the
    lowest instance name's) so that it matches them at its next start. A map without storage
    has no identity and follows any peer, as a peer without one is followed by a new map."""
    local = rt.map_id
    if local is None:
        return PeerChoice(None)
    if not rt.map_state().keyframes:
        ids = sorted((-sum(p.map_id == s.map_id for p in peers.values()), s.instance, s.map_id)
                     for s in peers.values() if s.map_id)
        if not ids:
            return PeerChoice(None)
        local = ids[0][2]
    choice = PeerChoice(set(), adopt=local if local != rt.map_id else None)
    assert choice.followed is not None
    for peer, status in sorted(peers.items(), key=lambda p: p[1].instance):
        if status.map_id == local:
            choice.followed.add(peer)
        else:
            choice.refused.append(_identity_fields(rt, status, local, action="not followed"))
    return choice


def _identity_fields(rt: MapRuntime, peer: wire.StatusReply, local: str, *, action: str
                     ) -> dict[str, Any]:
    """The ``replica_diverged`` event fields of a peer serving another map identity."""
    return {"reason": "identity", "peer": peer.instance, "map_id": local,
            "peer_map_id": peer.map_id, "action": action,
            "message": (f"peer {peer.instance} serves map {rt.name!r} with identity "
                        f"{peer.map_id or 'unknown (it reports none)'}, this replica holds "
                        f"identity {local}: another map under the same name; {action}, this "
                        f"replica keeps and serves its own")}


def _adopt_identity(rt: MapRuntime, map_id: str) -> None:
    """Take a peer's identity for ``rt`` (holding nothing yet), then journal its cameras
    again under it (the segments holding them are replaced)."""
    if rt.store is None or rt.map_state().keyframes:
        return
    with rt.apply_lock():
        rt.store.adopt_identity(map_id)
        for camera_id, camera in sorted(rt.cameras().items()):
            rt.put_camera(camera_id, wire.CameraPut(
                camera_id, wire.WireCamera.from_dict(camera.to_dict())).encode())
