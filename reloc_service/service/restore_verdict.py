"""Whether a map directory restores completely, is served *degraded* (what it lacks named), or
is refused (why): one verdict, read only, for the service's restore and ``reloc map check``.

What it proves with (see :mod:`.durability`): the map's identity (a UUID made when the map is
created, in ``service.json``, in the ``store`` fields of every snapshot manifest and in the
header of every third-format journal segment) and the sequence numbers every journaled change
carries (each snapshot records the last one it holds, each segment the one it starts at).

- **refused**: a snapshot or segment of another map (a different identity), a file that does
  not read (``service.json``, a manifest, a segment header), damaged bytes that could not be
  kept because the quarantine is not a writable directory, ``CURRENT`` missing with no
  snapshot to restore it to;
- **degraded**: sequence numbers that should be there and are not: ``CURRENT`` names an older
  snapshot than ``service.json`` (the keyframe ids it lacks are named, from ``service.json``),
  a missing or emptied journal segment, records skipped as damaged (a range of sequence
  numbers: which keyframes they held cannot be known);
- **complete** otherwise, or once an operator accepted every loss
  (``reloc map check --accept-loss``).

A loss found once is recorded (``losses.json`` in the map directory, by the service when it
restores the map), so the map stays degraded after a restart has moved past the evidence
(a new segment where one was missing), until the loss is accepted.

Maps written before identities and sequence numbers existed are *legacy*: no identity is
recorded anywhere, so one is assigned at their first open and sequence checks start then.
"""

from __future__ import annotations

import json
import os
import time
import uuid
from dataclasses import asdict, dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import msgpack

from ..core.errors import StorageError
from ..core.fileio import atomic_write
from ..storage.journal import QUARANTINE_DIR, Journal, SegmentScan, scan_segment, segment_name
from ..storage.snapshot import snapshot_summary
from ..storage.snapshot_files import CURRENT_FILE, current_snapshot
from .durability import SERVICE_FILE, committed_snapshot, read_service_file

LOSSES_FILE = "losses.json"


class Outcome(StrEnum):
    COMPLETE = "complete"
    DEGRADED = "degraded"
    REFUSED = "refused"


class LossKind(StrEnum):
    OLDER_SNAPSHOT = "older_snapshot"     # CURRENT names an older snapshot than service.json
    MISSING_SEGMENT = "missing_segment"   # the journal lacks the segment(s) holding them
    EMPTY_SEGMENT = "empty_segment"       # a segment shorter than its header
    SEQUENCE_GAP = "sequence_gap"         # records between two present ones (damaged bytes)


@dataclass(frozen=True)
class Loss:
    """Acknowledged changes a restore cannot give back: sequence numbers ``first_seq`` to
    ``last_seq`` (None: how many is unknown), the keyframe ids they added when those can be
    known (None: they cannot), the segment concerned, and what was found."""

    kind: LossKind
    first_seq: int
    last_seq: int | None
    keyframe_ids: tuple[int, ...] | None
    segment: int | None
    detail: str

    @property
    def key(self) -> str:
        """What identifies this loss across restarts (for recording and accepting it)."""
        return f"{self.kind.value}:{self.segment}:{self.first_seq}"

    def describe(self) -> str:
        seqs = (f"sequence numbers {self.first_seq}-{self.last_seq}" if self.last_seq is not None
                else f"sequence numbers from {self.first_seq} (how many is unknown)")
        ids = (f"keyframe ids {list(self.keyframe_ids)}" if self.keyframe_ids is not None
               else "keyframe ids unknown (only the sequence range can be known)")
        return f"{self.kind.value}: {self.detail}; lost {seqs}; {ids}"

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "kind": self.kind.value, "key": self.key,
                "keyframe_ids": None if self.keyframe_ids is None else list(self.keyframe_ids)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Loss:
        ids = d.get("keyframe_ids")
        return cls(LossKind(d["kind"]), int(d["first_seq"]),
                   None if d.get("last_seq") is None else int(d["last_seq"]),
                   None if ids is None else tuple(int(i) for i in ids),
                   None if d.get("segment") is None else int(d["segment"]), str(d["detail"]))


@dataclass
class Verdict:
    """What restoring map directory ``directory`` gives (see module docstring), and where the
    restore continues: the snapshot's last sequence number (records up to it are in the
    snapshot), the first segment to replay, the next sequence number, the lowest number a
    new segment may take (a missing segment's number is never reused)."""

    directory: str
    map_id: str | None = None
    legacy: bool = False               # no identity recorded anywhere: assigned at first open
    refusal: str | None = None
    losses: list[Loss] = field(default_factory=list)
    accepted: list[Loss] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    snapshot_seq: int = 0
    next_seq: int = 1
    replay_from: int = 0
    min_segment: int = 0
    #: Journal records a restore will read past the snapshot (its progress is counted
    #: against this; records without a sequence number all count).
    to_replay: int = 0

    @property
    def outcome(self) -> Outcome:
        if self.refusal is not None:
            return Outcome.REFUSED
        return Outcome.DEGRADED if self.losses else Outcome.COMPLETE

    @property
    def missing_keyframe_ids(self) -> list[int]:
        return sorted({i for loss in self.losses for i in loss.keyframe_ids or ()})

    def describe(self) -> str:
        """One line: the outcome and why."""
        if self.refusal is not None:
            return f"refused: {self.refusal}"
        if not self.losses:
            return "complete" + (f" ({len(self.accepted)} loss(es) accepted)"
                                 if self.accepted else "")
        return ("degraded: " + "; ".join(loss.describe() for loss in self.losses)
                + f"; accept with `reloc map check --accept-loss {self.directory}`")

    def to_dict(self) -> dict[str, Any]:
        return {"outcome": self.outcome.value, "map_id": self.map_id, "legacy": self.legacy,
                "refusal": self.refusal, "losses": [x.to_dict() for x in self.losses],
                "accepted": [x.to_dict() for x in self.accepted], "notes": self.notes,
                "missing_keyframe_ids": self.missing_keyframe_ids,
                "snapshot_seq": self.snapshot_seq, "next_seq": self.next_seq}


@dataclass(frozen=True)
class _Segment:
    """One journal segment as the verdict needs it: its scan and each record's sequence
    number (None for a record that does not carry one)."""

    scan: SegmentScan
    seqs: tuple[int | None, ...]


# -- the verdict -----------------------------------------------------------------------------------

def judge(directory: str | Path) -> Verdict:
    """The verdict on map directory ``directory`` (read only; see module docstring)."""
    directory = Path(directory)
    verdict = Verdict(str(directory))
    try:
        meta = read_service_file(directory)
        snapshot = snapshot_to_load(directory, meta)
        store, snapshot_ids = snapshot_summary(snapshot) if snapshot is not None else ({}, [])
        segments = _read_journal(directory / "journal")
        _check_identity(verdict, meta, store, snapshot, segments)
        _check_quarantine(directory / "journal", segments)
        _check_sequence(verdict, meta, store, snapshot_ids, segments)
        verdict.to_replay = _records_to_replay(verdict, segments)
        _merge_recorded(verdict, read_losses(directory))
    except StorageError as exc:
        verdict.refusal = str(exc)
    except (ValueError, TypeError, KeyError) as exc:   # a field edited to another type
        verdict.refusal = (f"{directory}: {type(exc).__name__}: {exc}; expected {SERVICE_FILE} "
                           f"and the manifests as the service writes them")
    return verdict


def snapshot_to_load(directory: Path, meta: dict[str, Any]) -> Path | None:
    """The snapshot a restore loads: the one ``CURRENT`` names, or (``CURRENT`` missing) the
    one ``service.json`` names, which a restore points ``CURRENT`` back at; None for a map
    without a committed snapshot (:func:`.durability.committed_snapshot`). StorageError
    when there is no telling which."""
    map_dir = directory / "map"
    if (map_dir / CURRENT_FILE).is_file():
        return current_snapshot(map_dir)
    named = committed_snapshot(directory, meta)
    return None if named is None else map_dir / "snapshots" / named


def _read_journal(journal: Path) -> list[_Segment]:
    """Every segment with its records' sequence numbers; StorageError for a bad header."""
    out = []
    for number in Journal(journal).segments():
        path = journal / segment_name(number)
        try:
            scan = scan_segment(path)
        except OSError as exc:
            raise StorageError(f"{path}: cannot read ({exc.strerror or exc})") from exc
        out.append(_Segment(scan, tuple(_record_seq(r) for r in scan.records)))
    return out


def _record_seq(record: bytes) -> int | None:
    try:
        entry = msgpack.unpackb(record, raw=False)
    except (ValueError, msgpack.UnpackException):
        return None
    seq = entry.get("seq") if isinstance(entry, dict) else None
    return seq if isinstance(seq, int) and not isinstance(seq, bool) else None


def _check_identity(verdict: Verdict, meta: dict[str, Any], store: dict[str, Any],
                    snapshot: Path | None, segments: list[_Segment]) -> None:
    """The map's identity (``service.json``, else the snapshot's, else the first segment's);
    StorageError naming the snapshot or segment that belongs to another map."""
    recorded = [(str(meta["map_id"]), f"{SERVICE_FILE}")] if meta.get("map_id") else []
    if store.get("map_id"):
        recorded.append((str(store["map_id"]), f"snapshot {snapshot}"))
    recorded += [(s.scan.map_id, f"journal segment {segment_name(s.scan.number)}")
                 for s in segments if s.scan.map_id is not None]
    if not recorded:
        verdict.legacy = True
        return
    map_id, source = recorded[0]
    try:
        uuid.UUID(hex=map_id)
    except (ValueError, TypeError):
        raise StorageError(f"{source}: map_id {map_id!r} is not a UUID; expected the 32 hex "
                           f"digits the service writes") from None
    for other, where in recorded[1:]:
        if other != map_id:
            raise StorageError(
                f"{where} belongs to map {other}, not to this map ({map_id}, from {source}): "
                f"another map's content is never served; put this map's own file back")
    verdict.map_id = map_id


def _check_quarantine(journal: Path, segments: list[_Segment]) -> None:
    """Damaged bytes not yet kept must be copyable to the quarantine before a restore goes
    on (it never drops bytes it has not kept): StorageError if it is not a writable
    directory."""
    quarantine = journal / QUARANTINE_DIR
    pending = [d for s in segments for d in s.scan.damage
               if not (quarantine / d.quarantine_name()).exists()]
    if not pending:
        return
    usable = (quarantine.is_dir() and os.access(quarantine, os.W_OK | os.X_OK)) or (
        not quarantine.exists() and os.access(journal, os.W_OK | os.X_OK))
    if not usable:
        d = pending[0]
        raise StorageError(f"cannot keep the damaged bytes of {journal / segment_name(d.segment)} "
                           f"({d.size} bytes at offset {d.offset}) in {quarantine}: not a "
                           f"writable directory; make it one, then restart")


def _check_sequence(verdict: Verdict, meta: dict[str, Any], store: dict[str, Any],
                    snapshot_ids: list[int], segments: list[_Segment]) -> None:
    """The losses the sequence numbers prove, and where the restore continues."""
    loaded, expected_snapshot = int(store.get("last_seq", 0)), int(meta.get("last_seq", 0))
    verdict.snapshot_seq = loaded
    next_segment = int(meta.get("next_segment", 0))
    if loaded < expected_snapshot:
        verdict.losses.append(_older_snapshot(meta, loaded, expected_snapshot, snapshot_ids))
    numbered = [s for s in segments if s.scan.version in (0, 3)] if (
        verdict.map_id is not None) else []
    expected = max(loaded, expected_snapshot) + 1
    if not numbered and verdict.map_id is not None and (
            meta.get("map_id") or store.get("map_id")):
        verdict.losses.append(Loss(
            LossKind.MISSING_SEGMENT, expected, None, None, next_segment,
            f"no journal segment is left ({SERVICE_FILE} names segment {next_segment}): the "
            f"changes since the snapshot are gone, how many is unknown"))
        verdict.min_segment = next_segment + 1
    expected = _walk_segments(verdict, numbered, expected)
    verdict.next_seq = expected
    first_numbered = numbered[0].scan.number if numbered else next_segment
    verdict.replay_from = min(next_segment, first_numbered)
    if numbered and next_segment not in {s.scan.number for s in numbered} and \
            next_segment > numbered[0].scan.number:
        verdict.notes.append(
            f"{SERVICE_FILE} names journal segment {next_segment}, which is not where the "
            f"journal continues; replayed by sequence number instead (nothing lost by it)")
    verdict.min_segment = max(verdict.min_segment, *(s.scan.number + 1 for s in numbered
                                                     if s.scan.version == 0), 0)


def _records_to_replay(verdict: Verdict, segments: list[_Segment]) -> int:
    """The records of the segments a restore replays that the snapshot does not hold."""
    return sum(1 for seg in segments if seg.scan.number >= verdict.replay_from
               for seq in seg.seqs if seq is None or seq > verdict.snapshot_seq)


def _older_snapshot(meta: dict[str, Any], loaded: int, expected: int,
                    snapshot_ids: list[int]) -> Loss:
    named = meta.get("keyframe_ids")
    ids = (tuple(sorted(set(int(i) for i in named) - set(snapshot_ids)))
           if isinstance(named, list) else None)
    return Loss(LossKind.OLDER_SNAPSHOT, loaded + 1, expected, ids, None,
                f"CURRENT names a snapshot holding changes up to sequence number {loaded}, "
                f"{SERVICE_FILE} one holding them up to {expected} (snapshot "
                f"{meta.get('snapshot')!r}; pointing CURRENT back at it restores them)")


def _walk_segments(verdict: Verdict, numbered: list[_Segment], expected: int) -> int:
    """Follow the chain of numbered segments from sequence number ``expected``: each gap
    is a loss; returns the next sequence number."""
    emptied: Loss | None = None
    for seg in numbered:
        scan = seg.scan
        if scan.version == 0:
            emptied = Loss(LossKind.EMPTY_SEGMENT, expected, None, None, scan.number,
                           f"journal segment {segment_name(scan.number)} holds "
                           f"{len(scan.damage) and scan.damage[0].size} bytes, less than its "
                           f"header: whatever it held is gone")
            verdict.losses.append(emptied)
            continue
        assert scan.first_seq is not None
        if scan.first_seq > expected:
            if emptied is not None:
                verdict.losses[verdict.losses.index(emptied)] = Loss(
                    emptied.kind, emptied.first_seq, scan.first_seq - 1, None, emptied.segment,
                    emptied.detail)
            else:
                verdict.losses.append(Loss(
                    LossKind.MISSING_SEGMENT, expected, scan.first_seq - 1, None,
                    scan.number - 1, f"journal segment {segment_name(scan.number)} starts at "
                    f"sequence number {scan.first_seq}, {expected} was expected: the "
                    f"segment(s) before it are missing"))
            expected = scan.first_seq
        emptied = None
        for seq in seg.seqs:
            if seq is None or seq < expected:
                continue        # covered by the snapshot (or not a numbered record)
            if seq > expected:
                verdict.losses.append(Loss(
                    LossKind.SEQUENCE_GAP, expected, seq - 1, None, scan.number,
                    f"journal segment {segment_name(scan.number)} jumps from sequence "
                    f"number {expected - 1} to {seq} (damaged bytes skipped)"))
            expected = seq + 1
    return expected


# -- recorded and accepted losses ------------------------------------------------------------------

def read_losses(directory: Path) -> list[tuple[Loss, bool]]:
    """The losses recorded in ``losses.json`` with whether each was accepted ([] if none);
    StorageError if the file does not read."""
    path = directory / LOSSES_FILE
    if not path.is_file():
        return []
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return [(Loss.from_dict(d), bool(d.get("accepted"))) for d in data["losses"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise StorageError(f"{path}: cannot read ({exc}); expected the losses recorded by "
                           f"the service") from exc


def _merge_recorded(verdict: Verdict, recorded: list[tuple[Loss, bool]]) -> None:
    """Add the recorded losses not found again; move the accepted ones aside."""
    found = {loss.key for loss in verdict.losses}
    verdict.losses += [loss for loss, _ in recorded if loss.key not in found]
    accepted = {loss.key for loss, ok in recorded if ok}
    verdict.accepted = [loss for loss in verdict.losses if loss.key in accepted]
    verdict.losses = [loss for loss in verdict.losses if loss.key not in accepted]


def record_losses(directory: Path, losses: list[Loss], *, accept: bool = False) -> None:
    """Add ``losses`` to ``losses.json`` (atomically); with ``accept`` mark them accepted."""
    recorded = {loss.key: (loss, ok) for loss, ok in read_losses(directory)}
    now = time.time()
    for loss in losses:
        recorded[loss.key] = (loss, accept or recorded.get(loss.key, (loss, False))[1])
    data = {"losses": [{**loss.to_dict(), "accepted": ok,
                        **({"accepted_at": now} if ok and accept else {})}
                       for loss, ok in recorded.values()]}
    atomic_write(directory / LOSSES_FILE, json.dumps(data, indent=1))


def unaccepted(directory: Path, losses: list[Loss]) -> list[Loss]:
    """Those of ``losses`` not accepted in ``losses.json`` (yet)."""
    try:
        accepted = {loss.key for loss, ok in read_losses(directory) if ok}
    except StorageError:
        return losses
    return [loss for loss in losses if loss.key not in accepted]


def new_identity() -> uuid.UUID:
    """An identity for a map created now (or a legacy map opened for the first time)."""
    return uuid.uuid4()
