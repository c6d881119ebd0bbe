"""A served map's write path (:class:`MapChanges`): keyframe and camera puts and keyframe
deletes validated, counted against the quotas, journaled, then applied (or deferred while a
snapshot is saved) and forwarded to the replicas; at shutdown, journaled only."""

from __future__ import annotations

import logging
from typing import Any

from reloc_client import protocol as wire
from reloc_client.protocol import EventKind

from ..core.errors import MapError
from .codec import KeyframeInput, decode_camera_put, decode_keyframe_put
from .quotas import keyframe_bytes
from .runtime_state import RuntimeState
from .served import WriteOp

log = logging.getLogger(__name__)


class MapChanges(RuntimeState):
    """A map's changes, from its writer thread (see module docstring)."""

    # -- map changes (writer thread) -------------------------------------------------------------
    def put_keyframe(self, kf_id: int, payload: bytes) -> None:
        """Validate, journal, apply (or defer during a snapshot) a KeyframePut."""
        try:
            kf = decode_keyframe_put(self, kf_id, payload)
            with self._apply_lock:
                self._admit(kf_id, len(payload))   # QUOTA_EXCEEDED: nothing journaled
                try:
                    self._journal_record(WriteOp.KEYFRAME, kf_id, payload)
                    self.publish(EventKind.KEYFRAME_ACCEPTED, id=kf_id)
                    self._apply_or_defer(WriteOp.KEYFRAME, kf)
                except Exception:
                    self._recount(kf_id)
                    raise
        except Exception as exc:
            self.reject(EventKind.KEYFRAME_REJECTED, exc, id=kf_id)

    def _admit(self, kf_id: int, size: int) -> None:
        """Count a put against the quotas (QUOTA_EXCEEDED beyond them)."""
        if self.quotas is not None:
            self.quotas.admit(self.name, self.usage, kf_id, size)

    def _recount(self, kf_id: int) -> None:
        """Count keyframe ``kf_id`` as the map now holds it (a put that failed on the way
        counts what stayed: the old keyframe, or nothing)."""
        keyframe = self.engine.map.snapshot().keyframes.get(kf_id)
        size = None if keyframe is None else keyframe_bytes(keyframe)
        if self.quotas is not None:
            self.quotas.count(self.usage, kf_id, size)
        else:
            self.usage.set_bytes(kf_id, size)

    def delete_keyframe(self, kf_id: int) -> None:
        """Journal and apply the removal of keyframe ``kf_id``."""
        try:
            with self._apply_lock:
                if kf_id not in self.engine.map and not self._deferred_has(kf_id):
                    raise MapError(f"cannot remove keyframe {kf_id}: not in map {self.name!r}")
                self._journal_record(WriteOp.DELETE, kf_id)
                self.publish(EventKind.KEYFRAME_ACCEPTED, id=kf_id, removed=True)
                self._apply_or_defer(WriteOp.DELETE, kf_id)
                self._recount(kf_id)   # frees its quota (once applied)
        except Exception as exc:
            self.reject(EventKind.KEYFRAME_REJECTED, exc, id=kf_id)

    def put_camera(self, camera_id: str, payload: bytes) -> None:
        """Validate, journal and register a CameraPut."""
        try:
            camera = decode_camera_put(camera_id, payload, self.limits)
            with self._apply_lock:
                self._journal_record(WriteOp.CAMERA, camera_id, payload)
                previous = self._cameras.get(camera_id)
                self.apply_change(WriteOp.CAMERA, camera_id, camera)
                if self.replicas is not None:
                    self.replicas.forward(self.name, WriteOp.CAMERA, camera_id, camera)
            self.stats.count("cameras_put")
            if previous is None or previous.to_dict() == camera.to_dict():
                self.publish(EventKind.CAMERA_ADDED, id=camera_id)
                return
            # Never rewritten: the keyframes already built keep the intrinsics they were built
            # with (a replica copies them so, see replication.Bootstrap); only new puts use these.
            kept = sum(1 for c in self._kf_camera_ids.values() if c == camera_id)
            log.warning("map %s: camera %s changed; %d keyframes built with it keep their "
                        "intrinsics", self.name, camera_id, kept)
            self.publish(EventKind.CAMERA_ADDED, id=camera_id, changed=True,
                         keyframes_kept=kept)
        except Exception as exc:
            self.reject(EventKind.CAMERA_REJECTED, exc, id=camera_id)

    def _journal_record(self, op: WriteOp, ident: Any, payload: bytes | None = None) -> None:
        """Append a change as the journal stores it: the op's string, the id, and the put as
        it was sent (a delete has none)."""
        if self.store is not None:
            record: dict[str, Any] = {"op": op.value, "id": ident}
            if payload is not None:
                record["payload"] = payload
            self.store.append(record)

    def _deferred_has(self, kf_id: int) -> bool:
        return any(op is WriteOp.KEYFRAME and item.kf_id == kf_id for op, item in self._deferred)

    def _apply_or_defer(self, op: WriteOp, item: Any) -> None:
        if self._snapshotting:
            self._deferred.append((op, item))
        else:
            self._apply(op, item)

    def _apply(self, op: WriteOp, item: Any, *, replay: bool = False) -> None:
        if op is WriteOp.KEYFRAME:
            kf: KeyframeInput = item
            self.apply_change(WriteOp.KEYFRAME, kf)
            self._recount(kf.kf_id)   # its features are known now
            if self.replicas is not None:   # before keyframe_added: a query after it sees it
                self.replicas.forward(self.name, WriteOp.KEYFRAME, kf)
            if kf.camera_id is not None:
                self._kf_camera_ids[kf.kf_id] = kf.camera_id
            else:
                self._kf_camera_ids.pop(kf.kf_id, None)
            if not replay:
                self.stats.count("keyframes_put")
                self.publish(EventKind.KEYFRAME_ADDED, id=kf.kf_id,
                             map_version=self.engine.map.version)
        elif op is WriteOp.DELETE:
            self.apply_change(WriteOp.DELETE, item)
            self._recount(item)
            if self.replicas is not None:
                self.replicas.forward(self.name, WriteOp.DELETE, item)
            self._kf_camera_ids.pop(item, None)
            if not replay:
                self.stats.count("keyframes_deleted")
                self.publish(EventKind.KEYFRAME_REMOVED, id=item,
                             map_version=self.engine.map.version)

    def wants_snapshot(self) -> bool:
        return self.store is not None and self.store.wants_snapshot()

    # -- shutdown --------------------------------------------------------------------------------
    def journal_only(self, op: WriteOp, ident: Any, payload: bytes | None) -> bool:
        """At shutdown: validate and journal a queued keyframe put or delete without applying
        it (applying runs SIFT and triangulation, ~0.3 s a keyframe); the journal replay at
        the next start applies it. False without storage (nothing would survive anyway)."""
        if self.store is None:
            return False
        if not self._replay_complete:   # the journal was never opened for appending
            self.reject(EventKind.KEYFRAME_REJECTED, wire.ProtocolError(
                wire.ErrorCode.BUSY, f"the service stopped while map {self.name!r} was "
                "replaying its journal; put again once it is back"), id=ident)
            return False
        try:
            with self._apply_lock:
                if op is WriteOp.KEYFRAME:
                    assert payload is not None
                    decode_keyframe_put(self, ident, payload)   # refused as usual
                    self._admit(ident, len(payload))
                    self._journal_record(WriteOp.KEYFRAME, ident, payload)
                    self._unapplied.add(ident)
                else:
                    if (ident not in self.engine.map and ident not in self._unapplied
                            and not self._deferred_has(ident)):
                        raise MapError(f"cannot remove keyframe {ident}: not in map "
                                       f"{self.name!r}")
                    self._journal_record(WriteOp.DELETE, ident)
                    self._unapplied.discard(ident)
                self._journal_ahead = True
            self.publish(EventKind.KEYFRAME_ACCEPTED, id=ident, **({"removed": True}
                                                                   if op is WriteOp.DELETE
                                                                   else {}))
        except Exception as exc:
            self.reject(EventKind.KEYFRAME_REJECTED, exc, id=ident)
        return True
