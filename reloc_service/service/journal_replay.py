"""A served map's restore (:class:`JournalReplay`): the cameras and losses of its storage
taken, then its journal backlog replayed after the snapshot it was loaded from while the map
is served; its progress, and what a replay stopped by the service's stop saves."""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from ..core.errors import StorageError
from .codec import WithLimits, decode_camera_put, decode_keyframe_put
from .durability import REPLAY_LIMITS, RestoreInterrupted, ServiceMeta
from .map_changes import MapChanges
from .restore_verdict import Verdict, judge, record_losses, unaccepted
from .served import WriteOp

log = logging.getLogger(__name__)


class JournalReplay(MapChanges):
    """A map's restore and journal replay (see module docstring)."""

    def _replay_progress(self) -> dict[str, int]:
        """While the journal replays: the records replayed (or skipped as not applying) and
        how many there are (status counters)."""
        if self._replay_complete or self._verdict is None:
            return {}
        report = self.restore_report
        return {"replay_records_done": report.replayed + report.not_applied,
                "replay_records_total": self._verdict.to_replay}

    def replay_note(self) -> str:
        """How far the journal replay is, as a refusal during it says it (a query refused
        while the replay ran says so even if it completed meanwhile)."""
        progress = self._replay_progress()
        if not progress:
            return f"map {self.name!r} has just replayed its journal"
        return (f"map {self.name!r} is replaying its journal "
                f"({progress['replay_records_done']} of {progress['replay_records_total']} "
                "records replayed)")

    # -- restore ---------------------------------------------------------------------------------
    def restore(self, stop: threading.Event | None = None, verdict: Verdict | None = None
                ) -> int:
        """:meth:`begin_restore`, then :meth:`replay_backlog`: the records replayed."""
        self.begin_restore(verdict)
        return self.replay_backlog(stop)

    def begin_restore(self, verdict: Verdict | None = None) -> None:
        """Take the cameras of ``service.json`` and what the restore lacks (``verdict``,
        judged on the map directory before it was loaded: :func:`.restore_verdict.judge`):
        the map can be served from the snapshot the engine was loaded from (see
        :func:`.durability.open_engine`) while :meth:`replay_backlog` applies the journal
        after it; its changes wait for that. StorageError if the verdict refuses the map
        or ``service.json`` does not read (nothing is changed)."""
        if self.store is None:
            return
        if verdict is None:
            verdict = judge(self.store.directory)
        if verdict.refusal is not None:
            raise StorageError(verdict.refusal)
        meta = self.store.read_meta()
        self._cameras.update(meta.cameras)
        self._kf_camera_ids.update(meta.keyframe_camera_ids)
        self._note_losses(verdict)
        self._verdict = verdict
        self._replay_complete = False
        self._replay_ended.clear()

    def replay_backlog(self, stop: threading.Event | None = None) -> int:
        """Replay the journal after the snapshot (each record under the apply lock, so
        queries see the map grow and replicas get the records in order), then open it for
        appending; the records replayed. What was skipped is in :attr:`restore_report` and
        the status counters. StorageError if a journal segment header does not read;
        RestoreInterrupted if ``stop`` is set meanwhile or the map was closed (the journal
        is left as it was; :meth:`close` saves what was replayed)."""
        if self._replay_complete or self._verdict is None or self.store is None:
            return 0
        with self._job_lock:
            if self._closed:
                raise RestoreInterrupted(f"map {self.name}: closed before its journal replay")
            self._replay_started = True
        report = self.restore_report
        try:
            self.store.replay(self._verdict, self._replay_locked, report, stop)
        except BaseException as exc:
            self._replay_failed = not isinstance(exc, RestoreInterrupted)
            self._replay_ended.set()
            raise
        for name, n in report.counters().items():
            if n:
                self.stats.count(name, n)
        self._replay_complete = True
        self._replay_ended.set()
        return report.replayed

    def wait_replayed(self, stop: threading.Event) -> bool:
        """Wait until the journal replay ends (the writers hold this map's changes until
        then): True once it completed, False if it did not (stopped, or failed) or ``stop``
        is set first."""
        while not self._replay_ended.wait(0.2):
            if stop.is_set():
                return False
        return self._replay_complete

    def _replay_locked(self, record: dict[str, Any]) -> None:
        with self._apply_lock:
            self._replay_record(record)

    def _note_losses(self, verdict: Verdict) -> None:
        """Record what the restore lacks (so a restart still knows it) and say so."""
        assert self.store is not None
        for note in verdict.notes:
            log.warning("map %s: %s", self.name, note)
        if not verdict.losses:
            return
        try:
            record_losses(self.store.directory, verdict.losses)
        except (OSError, StorageError) as exc:   # still served degraded; found again next time
            log.error("map %s: could not record the losses found: %s", self.name, exc)
        self._losses = list(verdict.losses)
        report = self.restore_report
        report.losses = [loss.to_dict() for loss in verdict.losses]
        report.missing_keyframe_ids = verdict.missing_keyframe_ids
        report.degraded = verdict.describe()
        log.error("map %s: served degraded: %s", self.name, report.degraded)

    def degraded(self) -> str:
        """Why the map is served degraded ("" once every loss is accepted, or if none)."""
        if not self._losses or self.store is None:
            return ""
        self._losses = unaccepted(self.store.directory, self._losses)
        return self.restore_report.degraded if self._losses else ""

    def _replay_record(self, record: dict[str, Any]) -> None:
        """Apply a journal record again (raises if it does not apply: it is skipped)."""
        op = record["op"]
        if op == WriteOp.KEYFRAME:
            kf = decode_keyframe_put(WithLimits(self, REPLAY_LIMITS), record["id"],
                                     record["payload"])
            self._apply(WriteOp.KEYFRAME, kf, replay=True)
        elif op == WriteOp.DELETE:
            if record["id"] in self.engine.map:
                self._apply(WriteOp.DELETE, record["id"], replay=True)
        elif op == WriteOp.CAMERA:
            self.apply_change(WriteOp.CAMERA, record["id"],
                              decode_camera_put(record["id"], record["payload"], REPLAY_LIMITS))
        else:
            raise ValueError(f"unknown journal op {op!r}")

    # -- a replay stopped ------------------------------------------------------------------------
    def _close_mid_replay(self, deadline: float) -> None:
        """Once the replay has stopped (at its next record: the service's stop event is
        set), save what it replayed as a snapshot within the time left, so that the next
        start resumes after it; if that does not fit, the next start replays the same
        records again (nothing is lost: the journal is untouched)."""
        with self._job_lock:
            self._closed = True
            started = self._replay_started
        if not started or self._replay_failed:
            if self.store is not None:
                self.store.close()
            return
        if not self._replay_ended.wait(max(0.0, deadline - time.monotonic())):
            log.warning("map %s: the journal replay did not stop within the stop budget; "
                        "the next start replays it again", self.name)
            return
        if self._replay_complete:   # it completed meanwhile: the journal is open
            assert self.store is not None
            self.store.close()
            return
        thread = threading.Thread(target=self._save_replayed, args=(deadline,),
                                  name=f"snapshot-{self.name}", daemon=True)
        thread.start()
        thread.join(max(0.0, deadline - time.monotonic()))
        if thread.is_alive():
            log.warning("map %s: what the stopped replay applied was not saved within the "
                        "stop budget; the next start replays those records again (nothing "
                        "is lost)", self.name)

    def _save_replayed(self, deadline: float) -> None:
        """Save the state the stopped replay reached (see :meth:`.MapStore.save_replayed`)."""
        assert self.store is not None and self._verdict is not None
        if self._verdict.map_id is None:   # a journal written before sequence numbers
            log.info("map %s: journal replay stopped; the next start replays it from the "
                     "start (it has no sequence numbers to resume by)", self.name)
            return
        if not self._maintenance.acquire(timeout=max(0.0, deadline - time.monotonic())):
            return
        try:
            meta = ServiceMeta(cameras=dict(self._cameras),
                               keyframe_camera_ids=dict(self._kf_camera_ids))
            path = self.store.save_replayed(self.engine, meta, self._verdict.map_id,
                                            self._verdict.snapshot_seq)
            report = self.restore_report
            if path is None:
                log.info("map %s: journal replay stopped before a numbered record past the "
                         "snapshot; nothing to save", self.name)
            else:
                log.info("map %s: journal replay stopped after %d of %d records; saved as "
                         "snapshot %s, the next start resumes after sequence number %s",
                         self.name, report.replayed + report.not_applied,
                         self._verdict.to_replay, path.name,
                         None if self.store.replayed_to is None else self.store.replayed_to[0])
        except Exception as exc:
            log.error("map %s: saving what the stopped replay applied failed (the next "
                      "start replays those records again): %s", self.name, exc)
        finally:
            self._maintenance.release()
