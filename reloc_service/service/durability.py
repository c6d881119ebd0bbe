"""What survives a restart of one served map: its journal, engine snapshots and ``service.json``.

Per map directory ``<storage>/<map>/``::

    journal/NNNNNNNNNNNN.journal   every accepted put/delete, fsynced before it is applied
    map/                           engine snapshots (``reloc_service.storage.snapshot``: map + models)
    service.json                   the map's identity (a UUID), cameras, keyframe camera ids, the
                               snapshot, its last sequence number and keyframe ids, the
                               first journal segment to replay

A snapshot rotates the journal, saves the engine, writes ``service.json`` atomically and only
then deletes the older journal segments (:class:`MapStore`; when it runs and what happens to
puts meanwhile is the map runtime's business). Restoring loads the last snapshot
(:func:`open_engine`) and replays the journal from there (:meth:`MapStore.replay`), keeping
what it can prove: a damaged journal record is skipped (its bytes quarantined, see
:mod:`.journal`), a missing ``map/CURRENT`` is restored only to the snapshot ``service.json``
names (verified, :func:`recover_current`), and anything else that does not read is a
StorageError for this map alone. What was skipped is reported in a :class:`RestoreReport`.

Every journal record carries a sequence number (``seq``, one more than the previous record's);
each snapshot records the last one it holds and the map's identity, and each journal segment
the map's identity and the number it starts at, so that a restore proves it is complete or
says what it lacks (:mod:`.restore_verdict`).
"""

from __future__ import annotations

import json
import logging
import shutil
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import msgpack
from reloc_client import protocol as wire

from ..core.cameras import Camera, camera_from_dict
from ..core.errors import CameraError, StorageError
from ..core.fileio import atomic_write
from ..engine import Engine, EngineConf
from ..storage.journal import FIRST_SEGMENT, Journal, JournalReport, segment_name
from ..storage.snapshot import restore_current
from ..storage.snapshot_files import CURRENT_FILE, snapshot_dirs

log = logging.getLogger(__name__)

SERVICE_FILE = "service.json"
#: Limits when replaying the journal: what was accepted once is accepted again.
REPLAY_LIMITS = wire.Limits(max_payload_bytes=2**40, max_image_pixels=2**40,
                            max_features=2**40, max_hypotheses=2**20, max_list_len=2**40)


class RestoreInterrupted(Exception):
    """The service stopped while a map was being restored (nothing was written)."""


@dataclass
class RestoreReport:
    """What restoring a map found: journal records applied, records read that did not apply,
    damaged journal bytes skipped (quarantined), and a snapshot ``CURRENT`` was restored to."""

    replayed: int = 0
    not_applied: int = 0
    journal: JournalReport = field(default_factory=JournalReport)
    recovered_snapshot: str | None = None
    #: Acknowledged changes the restore could not give back (not accepted by an operator):
    #: ``Loss.to_dict()`` of each, and the keyframe ids they held where those are known.
    losses: list[dict[str, Any]] = field(default_factory=list)
    missing_keyframe_ids: list[int] = field(default_factory=list)
    #: Why the map is degraded (empty: it is not).
    degraded: str = ""

    @property
    def damaged(self) -> bool:
        return bool(self.journal.damage or self.not_applied or self.recovered_snapshot
                    or self.degraded)

    def counters(self) -> dict[str, int]:
        """Status counters (a StatusReply carries them without a protocol change)."""
        return {"restore_records_replayed": self.replayed,
                "restore_records_not_applied": self.not_applied,
                "restore_journal_skipped": len(self.journal.skipped),
                "restore_journal_torn_bytes": self.journal.torn_bytes,
                "restore_quarantine_files": len(self.journal.quarantined),
                "restore_snapshot_recovered": int(self.recovered_snapshot is not None),
                "restore_degraded": int(bool(self.degraded)),
                "restore_missing_keyframes": len(self.missing_keyframe_ids)}

    def event_fields(self) -> dict[str, Any]:
        """Fields of the ``storage_damaged`` event published when :attr:`damaged`."""
        return {"failed": False, "records_replayed": self.replayed,
                "records_not_applied": self.not_applied,
                "journal_skipped": [[d.segment, d.offset, d.size] for d in self.journal.skipped],
                "journal_torn_bytes": self.journal.torn_bytes,
                "quarantined": [str(p) for p in self.journal.quarantined],
                "recovered_snapshot": self.recovered_snapshot,
                "degraded": bool(self.degraded), "losses": self.losses,
                "missing_keyframe_ids": self.missing_keyframe_ids}


class ReplayPlan(Protocol):
    """Where a restore continues, as :class:`.restore_verdict.Verdict` says: the map's
    identity (None: to be assigned), whether it is a map written before identities, the
    last sequence number its snapshot holds, the first segment to replay, the next sequence
    number, and the lowest number a new segment may take."""

    map_id: str | None
    legacy: bool
    snapshot_seq: int
    replay_from: int
    next_seq: int
    min_segment: int


@dataclass(frozen=True)
class ServiceMeta:
    """What ``service.json`` holds besides the snapshot name: the registered cameras, the
    camera id each keyframe was put with, and the first journal segment after the snapshot."""

    cameras: dict[str, Camera] = field(default_factory=dict)
    keyframe_camera_ids: dict[int, str] = field(default_factory=dict)
    next_segment: int = 0
    #: The map's identity as recorded (None: a legacy map or a new one).
    map_id: str | None = None


class MapStore:
    """The files of one map directory (see module docstring); used from the map's writer
    thread and its snapshot thread, which the map runtime keeps from overlapping."""

    def __init__(self, name: str, directory: Path, *, fsync: bool = True,
                 snapshot_every: int = 200) -> None:
        self.name = name
        self.directory = directory
        self.journal = Journal(directory / "journal", fsync=fsync)
        self.snapshot_every = snapshot_every
        #: Records journaled since the last snapshot (replayed ones included).
        self.since_snapshot = 0
        #: The last sequence number journaled when the journal was last rotated (what the
        #: snapshot being saved holds).
        self._rotated_seq = 0
        #: Where the replay stands: (sequence number, segment) of the last record it handed
        #: on, None before the first or after a record without a sequence number (legacy).
        self.replayed_to: tuple[int, int] | None = None

    @property
    def map_id(self) -> str | None:
        """The map's identity (a UUID's hex) once restored."""
        return None if self.journal.identity is None else self.journal.identity.hex

    def append(self, record: dict[str, Any]) -> None:
        """Journal ``record`` (``op`` kf / del / cam) with the next sequence number
        (``seq``); durable when this returns."""
        self.journal.append(msgpack.packb({**record, "seq": self.journal.next_seq},
                                          use_bin_type=True))
        self.since_snapshot += 1

    def wants_snapshot(self) -> bool:
        return self.snapshot_every > 0 and self.since_snapshot >= self.snapshot_every

    # -- restore ---------------------------------------------------------------------------------
    def read_meta(self) -> ServiceMeta:
        """The cameras and journal position of ``service.json`` (empty for a new map);
        StorageError naming the file if it does not read."""
        meta = read_service_file(self.directory)
        try:
            return ServiceMeta(
                cameras={cid: camera_from_dict(d) for cid, d in meta.get("cameras", {}).items()},
                keyframe_camera_ids={int(k): str(v) for k, v in
                                     meta.get("keyframe_camera_ids", {}).items()},
                next_segment=int(meta.get("next_segment", 0)),
                map_id=None if meta.get("map_id") is None else str(meta["map_id"]))
        except (AttributeError, KeyError, TypeError, ValueError, CameraError) as exc:
            raise StorageError(f"{self.directory / SERVICE_FILE}: {exc}; expected cameras, "
                               f"keyframe_camera_ids and next_segment as written by the "
                               f"service") from exc

    def replay(self, verdict: ReplayPlan, apply: Callable[[dict[str, Any]], None],
               report: RestoreReport, stop: threading.Event | None = None) -> None:
        """Hand every journal record the snapshot does not hold (from segment
        ``verdict.replay_from``, sequence numbers above ``verdict.snapshot_seq``) to
        ``apply``, counting in ``report`` those it applied and those it raised on (skipped,
        logged); then open the journal for appending with the map's identity (assigned now
        to a legacy or new map, and recorded in ``service.json``). RestoreInterrupted if
        ``stop`` is set meanwhile (the journal is left as it was)."""
        for segment, raw in self.journal.replay_numbered(from_segment=verdict.replay_from):
            if stop is not None and stop.is_set():
                raise RestoreInterrupted(f"map {self.name}: restore interrupted after "
                                         f"{report.replayed} journal records (shutting down)")
            applied = self._replay_record(raw, apply, verdict.snapshot_seq, segment)
            if applied:
                report.replayed += 1
            elif applied is not None:
                report.not_applied += 1
        report.journal = self.journal.report
        self._open_for_appending(verdict)
        self.since_snapshot = report.replayed

    def _open_for_appending(self, verdict: ReplayPlan) -> None:
        """Open the journal numbering from ``verdict.next_seq`` under the map's identity; a
        map without one gets it now, recorded in ``service.json`` after the first segment
        that carries it exists (so a recorded identity always has a segment behind it)."""
        self.journal.identity = (uuid.UUID(verdict.map_id) if verdict.map_id is not None
                                 else uuid.uuid4())
        self.journal.next_seq = verdict.next_seq
        segment = self.journal.open(min_segment=verdict.min_segment)
        meta = read_service_file(self.directory)
        if meta.get("map_id") != self.journal.identity.hex:
            log.info("map %s: identity %s recorded%s", self.name, self.journal.identity.hex,
                     " (a map written before identities: sequence checks start now)"
                     if verdict.legacy and (meta or self.journal.segments() != [segment])
                     else "")
            # the replay position is kept: legacy segments are replayed by number
            write_service_file(self.directory, {**meta, "map_id": self.journal.identity.hex,
                                                "next_segment": meta.get("next_segment",
                                                                         verdict.replay_from)})

    def _replay_record(self, raw: bytes, apply: Callable[[dict[str, Any]], None],
                       snapshot_seq: int, segment: int) -> bool | None:
        """True if the record was applied again, False if it was skipped (logged), None if
        the snapshot already holds it (its sequence number is not above ``snapshot_seq``).
        Either way the replay has moved past it (:attr:`replayed_to`)."""
        seq = None
        try:
            record = msgpack.unpackb(raw, raw=False)
            seq = record.get("seq") if isinstance(record, dict) else None
            if isinstance(seq, int) and seq <= snapshot_seq:
                return None
            apply(record)
            return True
        except Exception as exc:  # a record that cannot be applied again is skipped, loudly
            log.error("map %s: skipping a journal record that does not replay: %s", self.name,
                      exc)
            return False
        finally:
            self.replayed_to = ((seq, segment) if isinstance(seq, int)
                                and not isinstance(seq, bool) else None)

    def adopt_identity(self, map_id: str) -> None:
        """Take ``map_id`` (a peer's identity for the same map) as this map's, for a map that
        holds nothing yet: no snapshot, no keyframe journaled (the caller checks the latter
        and puts its cameras again). Its segments are replaced by a new first segment under
        ``map_id``; a crash midway leaves either the old identity or none (a new map)."""
        new = uuid.UUID(hex=map_id)
        meta = read_service_file(self.directory)
        if meta.get("snapshot"):
            raise StorageError(f"map {self.name}: holds a snapshot; an identity is adopted only "
                               f"by a map that holds nothing yet")
        self.journal.close()
        write_service_file(self.directory, {k: v for k, v in meta.items() if k != "map_id"})
        for number in self.journal.segments():
            (self.journal.directory / segment_name(number)).unlink(missing_ok=True)
        self.journal.identity = new
        self.journal.next_seq = 1
        segment = self.journal.open()
        write_service_file(self.directory, {**meta, "map_id": new.hex, "next_segment": segment})
        self.since_snapshot = 0
        log.info("map %s: identity %s adopted from a peer", self.name, new.hex)

    # -- snapshots -------------------------------------------------------------------------------
    def rotate(self) -> int:
        """Start a new journal segment (its number): the snapshot about to be taken holds
        everything journaled before it. Call with the map's changes held."""
        segment = self.journal.rotate()
        self.since_snapshot = 0
        self._rotated_seq = self.journal.next_seq - 1
        return segment

    def save(self, engine: Engine, meta: ServiceMeta) -> Path:
        """Save ``engine``, then ``service.json`` naming the snapshot and ``meta`` (the
        cameras as of :meth:`rotate`, ``meta.next_segment`` its segment), then delete the
        segments before it; the snapshot directory."""
        return self._save(engine, meta, {"map_id": self.map_id, "last_seq": self._rotated_seq})

    def save_replayed(self, engine: Engine, meta: ServiceMeta, map_id: str,
                      snapshot_seq: int) -> Path | None:
        """For a replay stopped midway: save ``engine`` (which holds the records up to
        :attr:`replayed_to`) as a snapshot holding exactly those, so the next restore goes
        on from the record after it (skipped by sequence number) instead of the first. The
        segment holding that record stays (it is ``next_segment``); earlier ones are
        deleted. None (nothing written) when the last record replayed carries no sequence
        number (a journal written before them: the next restore replays it whole), or when
        it replayed nothing past the loaded snapshot (``snapshot_seq``)."""
        if self.replayed_to is None or self.replayed_to[0] <= snapshot_seq:
            return None
        seq, segment = self.replayed_to
        meta = ServiceMeta(meta.cameras, meta.keyframe_camera_ids, segment, map_id)
        return self._save(engine, meta, {"map_id": map_id, "last_seq": seq})

    def _save(self, engine: Engine, meta: ServiceMeta, store: dict[str, Any]) -> Path:
        path = engine.save(self.directory / "map", store=store)
        write_service_file(self.directory, {
            **store, "snapshot": path.name, "next_segment": meta.next_segment,
            "keyframe_ids": sorted(engine.map.snapshot().keyframes),
            "cameras": {cid: cam.to_dict() for cid, cam in meta.cameras.items()},
            "keyframe_camera_ids": {str(k): v for k, v in meta.keyframe_camera_ids.items()},
            "map_version": engine.map.snapshot().version, "time": time.time()})
        self.journal.delete_before(meta.next_segment)
        return path

    def close(self) -> None:
        self.journal.close()


# -- the service.json file ---------------------------------------------------------------------

def read_service_file(directory: Path) -> dict[str, Any]:
    """``service.json`` of a map directory ({} if absent); StorageError if damaged."""
    path = directory / SERVICE_FILE
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise StorageError(f"{path}: cannot read ({exc}); expected the service's map "
                           f"metadata") from exc
    if not isinstance(data, dict):
        raise StorageError(f"{path}: expected a JSON object")
    return data


def write_service_file(directory: Path, data: dict[str, Any]) -> None:
    """Write ``service.json`` atomically (temporary file, fsync, rename, fsync directory)."""
    atomic_write(directory / SERVICE_FILE, json.dumps(data, indent=1))


# -- the storage directory ----------------------------------------------------------------------

def journal_bytes(directory: Path) -> int:
    """Bytes of journal a restore of map directory ``directory`` would read (its cost)."""
    journal = directory / "journal"
    return sum(p.stat().st_size for p in journal.glob("*.journal")) if journal.is_dir() else 0


# -- opening a map directory -------------------------------------------------------------------

def open_engine(directory: Path | None, conf: EngineConf, *, pools: bool = True) -> Engine:
    """The engine of a map: loaded from its last snapshot if there is one, else empty.
    Call :func:`recover_current` first so a missing ``CURRENT`` is not taken for a new map.
    ``pools``: make the repetition check's pools at load (not where others answer queries)."""
    if directory is not None and (directory / "map" / CURRENT_FILE).is_file():
        return Engine.load(directory / "map", conf, pools=pools)
    return Engine(conf)


def committed_snapshot(directory: Path, meta: dict[str, Any]) -> str | None:
    """With ``map/CURRENT`` missing, the snapshot the journal of map directory ``directory``
    continues from: the one ``service.json`` (``meta``) names. None when it names none and
    the journal still begins with its first segment: no segment was ever deleted (that
    happens only after ``service.json`` names a snapshot), so the journal holds every change
    and the snapshot directories present are saves the process did not finish (killed while
    writing one, or before pointing ``CURRENT`` at it). StorageError when there is no telling
    which snapshot the journal continues from."""
    named = meta.get("snapshot")
    map_dir = directory / "map"
    present = [p.name for p in snapshot_dirs(map_dir)]
    if named is None and not present:
        return None
    if named is None and Journal(directory / "journal").segments()[:1] == [FIRST_SEGMENT]:
        return None
    if not isinstance(named, str) or named not in present:
        raise StorageError(
            f"{map_dir / CURRENT_FILE}: missing; snapshot(s) {present or 'none'} present, "
            f"{directory / SERVICE_FILE} names {named!r}: cannot tell which snapshot the "
            f"journal continues from, so the map is not restored (nothing was deleted); "
            f"inspect it with `reloc map check {directory}`, then point CURRENT at a snapshot "
            f"with `reloc map set-current {directory} <n>`")
    return named


def recover_current(directory: Path) -> str | None:
    """Restore a missing ``map/CURRENT`` of map directory ``directory``; the snapshot name
    if it was restored, None if nothing was missing (or no snapshot was ever committed).

    Only the snapshot ``service.json`` names is a valid target (:func:`committed_snapshot`):
    the journal continues from it (``next_segment``), so any other snapshot would silently
    lose or repeat records. It is used only if every file of it verifies against its
    manifest; otherwise StorageError (the map is failed, nothing is deleted or rewritten).
    Where none was ever committed, the unfinished saves present are removed: nothing refers
    to them and the journal holds what they would have."""
    map_dir = directory / "map"
    if (map_dir / CURRENT_FILE).is_file():
        return None
    named = committed_snapshot(directory, read_service_file(directory))
    if named is None:
        for unfinished in snapshot_dirs(map_dir):
            log.warning("map directory %s: removing %s, a snapshot never committed (no "
                        "CURRENT, not named by %s); the journal holds every change",
                        directory, unfinished, SERVICE_FILE)
            shutil.rmtree(unfinished, ignore_errors=True)
        return None
    restore_current(map_dir, named)
    log.warning("map directory %s: %s was missing; restored it to snapshots/%s, the snapshot "
                "service.json names (every file verified)", directory, CURRENT_FILE, named)
    return named


def check_storage(directory: Path) -> None:
    """Create ``directory`` (StorageError with the reason if impossible)."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StorageError(f"cannot create the storage directory {directory}: "
                           f"{exc.strerror or exc}") from exc
