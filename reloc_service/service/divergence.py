"""Replicas compared while they serve (:class:`DivergenceWatch`): each served map against
the peers serving it (another identity, or another content at the same map version), and the
catch-up of keyframes a peer holds that this instance lacks (:func:`fetch_missing`,
:func:`apply_copies`). Copying a map at start is :mod:`.replication`'s
:class:`~.replication.Bootstrap`."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import zenoh
from reloc_client import protocol as wire
from reloc_client.protocol import EventKind

from .replication import Bootstrap, _holds, _identity_fields, _replier, peer_statuses
from .runtime import MapRuntime
from .workers import Lane, WorkerPool

log = logging.getLogger(__name__)


class DivergenceWatch:
    """Compares each served map with the peers serving it, every ``interval_s``: another
    identity, another content hash at the same map version (seen twice in a row: a put
    applied between the two reads of a status is not divergence), or another content hash
    and a version behind a peer's for ``lag_s`` are reported (ERROR log, ``replica_diverged`` event, status
    ``diverged``) once each, and cleared from the status when they no longer hold."""

    def __init__(self, session: Any, prefix: str, instance: str,
                 maps: Mapping[str, MapRuntime], *, interval_s: float,
                 lag_s: float | None = None,
                 writer_for: Callable[[str], WorkerPool | Lane] | None = None) -> None:
        """With ``writer_for`` (each map's writer), a replica reported lagging catches up:
        a job on its writer copies what the peer holds and it lacks (:func:`catch_up`)."""
        self.session = session
        self._writer_for = writer_for
        self.prefix = prefix
        self.instance = instance
        self.maps = maps
        self.interval_s = interval_s
        #: Seconds behind a peer's version before this replica reports it lags.
        self.lag_s = 6 * interval_s if lag_s is None else lag_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        #: (map, peer instance) -> what was seen last: a content mismatch (version, hashes),
        #: the time this replica fell behind, the reason reported.
        self._mismatch: dict[tuple[str, str], tuple[int, str, str]] = {}
        #: (map, peer instance) -> (when this replica was first seen behind, the peer's
        #: version then): it lags if it has not reached that version ``lag_s`` later (a
        #: replica a few puts behind a stream it follows keeps reaching it).
        self._behind_since: dict[tuple[str, str], tuple[float, int]] = {}
        self._reported: dict[tuple[str, str], str] = {}

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="replica-watch", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                self.check_once()
            except Exception as exc:   # a closing session, a map going: next round
                log.debug("replica check failed: %s", exc)

    def check_once(self) -> dict[str, str]:
        """Compare every served map with its peers now; map -> what diverges ("" if none)."""
        out = {}
        for name, rt in sorted(self.maps.items()):
            peers = peer_statuses(self.session, self.prefix, name, self.instance, rt.limits)
            problems = [p for p in (self._compare(rt, peer, zid) for zid, peer in
                                    sorted(peers.items(), key=lambda p: p[1].instance)) if p]
            rt.diverged = "; ".join(problems)
            out[name] = rt.diverged
        return out

    def _compare(self, rt: MapRuntime, peer: wire.StatusReply, zid: str) -> str:
        """What diverges between ``rt`` and ``peer`` ("" if nothing), reported when new; a
        lag starts a catch-up from that peer."""
        key = (rt.name, peer.instance)
        if peer.replaying or rt.replaying:   # identity and content known once replayed
            return ""
        state = rt.map_state()
        local_id = rt.map_id or ""
        fields: dict[str, Any] | None = None
        if local_id and peer.map_id != local_id:
            fields = _identity_fields(rt, peer, local_id, action="not followed")
        elif peer.map_id and peer.content_hash:
            fields = self._content(rt, peer, state.version, rt.content.of(state))
        if fields is None:
            self._reported.pop(key, None)
            return ""
        if self._reported.get(key) != fields["reason"]:
            self._reported[key] = fields["reason"]
            log.error("map %s: replica diverged: %s", rt.name, fields["message"])
            rt.publish(EventKind.REPLICA_DIVERGED, **fields)
        if fields["reason"] == "lagging" and self._writer_for is not None:
            self._catch_up(rt, peer, zid)
        return str(fields["message"])

    def _catch_up(self, rt: MapRuntime, peer: wire.StatusReply, zid: str) -> None:
        """Fetch what ``rt`` lacks from ``peer`` here, then put it on ``rt``'s writer (after
        the puts already queued)."""
        assert self._writer_for is not None
        try:
            infos = fetch_missing(self.session, self.prefix, rt, zid)
        except Exception as exc:   # a peer gone, a reply that does not decode: next check
            log.error("map %s: catching up from %s failed: %s", rt.name, peer.instance, exc)
            return
        if infos and not self._writer_for(rt.name).submit(lambda _q: self._apply(rt, infos)):
            log.warning("map %s: writer queue full; catching up at the next check", rt.name)

    @staticmethod
    def _apply(rt: MapRuntime, infos: list[wire.KeyframeInfo]) -> None:
        try:
            apply_copies(rt, infos)
        except Exception as exc:
            log.error("map %s: applying the keyframes caught up failed: %s", rt.name, exc)

    def _content(self, rt: MapRuntime, peer: wire.StatusReply, version: int, digest: str
                 ) -> dict[str, Any] | None:
        """A content or version divergence of the same map identity, or None."""
        key = (rt.name, peer.instance)
        base = {"peer": peer.instance, "map_id": rt.map_id, "peer_map_id": peer.map_id,
                "map_version": version, "peer_map_version": peer.map_version,
                "content_hash": digest, "peer_content_hash": peer.content_hash}
        seen = (peer.map_version, digest, peer.content_hash)
        if digest == peer.content_hash:   # the same content (whatever history led there)
            self._mismatch.pop(key, None)
            self._behind_since.pop(key, None)
            return None
        if version == peer.map_version and digest != peer.content_hash:
            repeated = self._mismatch.get(key) == seen
            self._mismatch[key] = seen
            if repeated:
                return {**base, "reason": "content", "message": (
                    f"peer {peer.instance} holds other content for map {rt.name!r} at the "
                    f"same map version {version} (content hash {peer.content_hash[:16]} "
                    f"there, {digest[:16]} here)")}
            return None
        self._mismatch.pop(key, None)
        if version < peer.map_version:
            since, target = self._behind_since.get(key, (0.0, -1))
            if version >= target:   # reached where the peer was: measure from now
                since, target = time.monotonic(), peer.map_version
                self._behind_since[key] = (since, target)
            if time.monotonic() - since >= self.lag_s:
                return {**base, "reason": "lagging", "message": (
                    f"this replica lags peer {peer.instance} on map {rt.name!r}: map version "
                    f"{version} here, {peer.map_version} there, for "
                    f"{time.monotonic() - since:.0f} s")}
            return None
        self._behind_since.pop(key, None)
        return None


def fetch_missing(session: Any, prefix: str, rt: MapRuntime, peer: str
                  ) -> list[wire.KeyframeInfo]:
    """The keyframes (with images) that peer ``peer`` (a Zenoh id) holds and ``rt`` lacks
    or holds otherwise (pose, covariance, time, camera). Asked of other sessions only: this
    service's own keyframes queryable answers on the map's writer."""
    wanted = []
    for _key, payload, replier in _replies(session, wire.keys.keyframes(prefix, rt.name)):
        if replier == peer:
            info = wire.KeyframeInfo.decode(payload, rt.limits)
            if not _holds(rt, info):
                wanted.append(info.id)
    out = []
    for kf_id in wanted:
        for _key, payload, replier in _replies(
                session, wire.keys.keyframe(prefix, rt.name, kf_id) + "?image=true"):
            info = wire.KeyframeInfo.decode(payload, rt.limits)
            if replier == peer and info.image is not None:
                out.append(info)
    return out


def apply_copies(rt: MapRuntime, infos: list[wire.KeyframeInfo]) -> int:
    """Put the copied keyframes ``infos`` into ``rt`` (on its writer: journaled like any
    put), each with its camera; those it holds by now are skipped. Keyframes only ``rt``
    holds are kept (a removal is not inferred from a peer's absence). The number put."""
    copied = 0
    for info in infos:
        if info.image is None or _holds(rt, info):
            continue
        if info.camera_id is not None:
            Bootstrap._ensure_camera(rt, info.camera_id, info.camera)
        rt.put_keyframe(info.id, wire.KeyframePut(
            id=info.id, image=info.image, world_from_cam=info.world_from_cam,
            camera_id=info.camera_id, camera=None if info.camera_id else info.camera,
            timestamp=info.timestamp, pose_covariance=info.pose_covariance).encode())
        copied += 1
    if copied:
        rt.stats.count("catch_up_keyframes", copied)
        log.warning("map %s: caught up %d keyframes from a peer (ids %s)", rt.name, copied,
                    [info.id for info in infos][:20])
    return copied


def _replies(session: Any, key: str, timeout: float = 30.0) -> list[tuple[str, bytes, str]]:
    """(key, payload, replier's Zenoh id) of every ok reply to a get on ``key``."""
    return [(str(r.ok.key_expr), r.ok.payload.to_bytes(), _replier(r))
            for r in session.get(key, timeout=timeout, target=zenoh.QueryTarget.ALL,
                                 consolidation=zenoh.ConsolidationMode.NONE,
                                 allowed_destination=zenoh.Locality.REMOTE)
            if r.ok is not None]
