"""A served map's snapshots (:class:`MapSnapshots`): saved in the background, one at a time,
while the puts arriving meanwhile are journaled at once and applied after the save; the final
one when the map is closed."""

from __future__ import annotations

import logging
import threading
import time

from reloc_client.protocol import EventKind

from ..core.errors import StorageError
from .durability import ServiceMeta
from .journal_replay import JournalReplay
from .served import WriteOp

log = logging.getLogger(__name__)


class MapSnapshots(JournalReplay):
    """A map's snapshots and its close (see module docstring)."""

    # -- snapshots -------------------------------------------------------------------------------
    def start_snapshot(self, *, wait: bool = False) -> bool:
        """Save the map in the background (one at a time); with ``wait``, block until it is
        durable. False if there is no storage or a snapshot is already running."""
        if self.store is None:
            return False
        with self._job_lock:
            if self._journal_ahead or self._closed or not self._replay_complete:
                return False   # it would drop the records journaled (not applied) at shutdown
            running = self._snapshot_thread is not None and self._snapshot_thread.is_alive()
            if not running:
                self._snapshot_thread = threading.Thread(
                    target=self._snapshot, name=f"snapshot-{self.name}", daemon=True)
                self._snapshot_thread.start()
            thread = self._snapshot_thread
        if wait and thread is not None:
            thread.join()
        return not running

    def _snapshot(self) -> None:
        assert self.store is not None
        with self._maintenance:
            with self._apply_lock:   # no put between the rotation and the cameras it saves
                if self._journal_ahead:   # waited past a shutdown that journaled unapplied puts
                    return
                try:
                    segment = self.store.rotate()
                except StorageError as exc:
                    log.error("map %s: snapshot not taken: %s", self.name, exc)
                    return
                meta = ServiceMeta(cameras=dict(self._cameras),
                                   keyframe_camera_ids=dict(self._kf_camera_ids),
                                   next_segment=segment)
                self._snapshotting = True
            try:
                path = self.store.save(self.engine, meta)
                self.publish(EventKind.MAP_SAVED, map_version=self.map_state().version,
                             path=str(path))
            except Exception as exc:
                log.error("map %s: snapshot failed (the journal still has everything): %s",
                          self.name, exc)
            finally:
                self._finish_snapshot()

    def _finish_snapshot(self) -> None:
        """Apply the puts that arrived during the save, in order."""
        with self._apply_lock:
            deferred, self._deferred = self._deferred, []
            self._snapshotting = False
            for op, item in deferred:
                try:
                    self._apply(op, item)
                except Exception as exc:
                    self.reject(EventKind.KEYFRAME_REJECTED, exc,
                                id=item.kf_id if op is WriteOp.KEYFRAME else item)

    def wait_snapshot(self, timeout: float = 60.0) -> None:
        """Wait for a running snapshot (its deferred puts are applied when it ends)."""
        thread = self._snapshot_thread
        if thread is not None and thread.is_alive():
            thread.join(timeout)

    def maintenance_running(self) -> bool:
        """A snapshot or training job holds the map's files or models now."""
        thread = self._snapshot_thread
        return (thread is not None and thread.is_alive()) or self._maintenance.locked()

    # -- shutdown --------------------------------------------------------------------------------
    def close(self, *, final_snapshot: bool = True, timeout: float = 60.0) -> None:
        """Final snapshot within ``timeout`` s (when something changed since the last one and
        no record was journaled without being applied: the snapshot would drop it from the
        journal), then close the journal. A running training job is not waited for beyond
        the same ``timeout``: its models are lost, the map is not. A map closed while its
        journal replays saves what was replayed instead (:meth:`_close_mid_replay`)."""
        deadline = time.monotonic() + timeout
        if not self._replay_complete:
            self._close_mid_replay(deadline)
            return
        if (final_snapshot and self.store is not None and self.store.since_snapshot > 0
                and not self._journal_ahead):
            if self._maintenance.acquire(timeout=max(0.0, timeout)):
                self._maintenance.release()
                thread = self._start_final_snapshot()
                if thread is not None:
                    thread.join(max(0.0, deadline - time.monotonic()))
        snapshot_thread = self._snapshot_thread
        if snapshot_thread is not None:
            snapshot_thread.join(max(0.0, deadline - time.monotonic()))
        with self._job_lock:
            self._closed = True   # a training job ending later takes no snapshot
        if snapshot_thread is not None and snapshot_thread.is_alive():
            log.warning("map %s: the final snapshot did not finish within the stop budget; "
                        "the journal still holds every change", self.name)
            return   # it may still rotate the journal: leave that open (the process exits)
        if self.store is not None:
            self.store.close()

    def _start_final_snapshot(self) -> threading.Thread | None:
        self.start_snapshot()
        return self._snapshot_thread
