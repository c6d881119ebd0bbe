"""What a map directory (or a whole storage) holds, read only: snapshots verified against their
manifests, ``CURRENT`` and ``service.json``, journal records (good, skipped, torn tail, and
intact ones a replay would refuse), quarantined bytes, and the restore verdict the service
reaches on it (:func:`.restore_verdict.judge`, then the same snapshot load). Backs
``reloc map check``; writes nothing, except :func:`accept_losses` (``--accept-loss``)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import msgpack
from reloc_client import protocol as wire

from ..core.errors import StorageError
from ..storage.journal import QUARANTINE_DIR, Journal, scan_segment, segment_name
from ..storage.snapshot import load_map, verify_snapshot
from ..storage.snapshot_files import CURRENT_FILE, current_snapshot, snapshot_dirs
from .durability import REPLAY_LIMITS, SERVICE_FILE, read_service_file
from .restore_verdict import Verdict, judge, record_losses
from .served import WriteOp


@dataclass
class SnapshotCheck:
    name: str
    files: int = 0
    problem: str | None = None
    current: bool = False
    named_by_service_file: bool = False


@dataclass
class SegmentCheck:
    number: int
    version: int = 2
    records: int = 0
    skipped: list[tuple[int, int]] = field(default_factory=list)   # (offset, bytes)
    torn_bytes: int = 0
    replayed: bool = True        # at or after the segment service.json says to replay from
    problem: str | None = None
    #: Intact records whose content a replay would refuse (e.g. a keyframe put whose pose
    #: covariance is not one): "record <i>: <why>".
    invalid: list[str] = field(default_factory=list)


@dataclass
class MapCheck:
    """Everything found in one map directory; :attr:`problems` lists what is damaged."""

    directory: str
    snapshots: list[SnapshotCheck] = field(default_factory=list)
    current: str | None = None
    next_segment: int = 0
    segments: list[SegmentCheck] = field(default_factory=list)
    quarantine: list[tuple[str, int]] = field(default_factory=list)   # (file, bytes)
    problems: list[str] = field(default_factory=list)
    #: The restore verdict (:meth:`.restore_verdict.Verdict.to_dict`).
    verdict: dict[str, Any] = field(default_factory=dict)

    @property
    def damaged(self) -> bool:
        return bool(self.problems)

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "damaged": self.damaged}


def is_map_dir(path: Path) -> bool:
    return any((path / name).exists() for name in ("journal", "map", SERVICE_FILE))


def check_path(path: str | Path) -> list[MapCheck]:
    """Check map directory ``path``, or every map directory of storage ``path``.
    StorageError if ``path`` is neither."""
    path = Path(path)
    if not path.is_dir():
        raise StorageError(f"{path}: not a directory; expected a map directory or a storage")
    if is_map_dir(path):
        return [check_map_dir(path)]
    maps = [p for p in sorted(path.iterdir()) if p.is_dir() and is_map_dir(p)]
    if not maps:
        raise StorageError(f"{path}: no map directory here (expected journal/, map/ or "
                           f"{SERVICE_FILE}, or subdirectories holding them)")
    return [check_map_dir(p) for p in maps]


def check_map_dir(directory: Path) -> MapCheck:
    """Read every file of map directory ``directory`` and report (see :class:`MapCheck`)."""
    out = MapCheck(str(directory))
    meta = _check_service_file(directory, out)
    _check_snapshots(directory, out, meta)
    _check_journal(directory, out)
    quarantine = directory / "journal" / QUARANTINE_DIR
    if quarantine.is_dir():
        out.quarantine = [(str(p), p.stat().st_size) for p in sorted(quarantine.iterdir())]
    verdict = restore_verdict(directory)
    out.verdict = verdict.to_dict()
    if verdict.refusal is not None:
        out.problems.append(f"the service refuses this map: {verdict.refusal}")
    out.problems += [f"the service serves this map degraded: {loss.describe()}"
                     for loss in verdict.losses]
    return out


def restore_verdict(directory: Path) -> Verdict:
    """The service's verdict on map directory ``directory``: :func:`.restore_verdict.judge`,
    then (unless refused) the load of its current snapshot the service would do (a manifest
    that reads but whose files do not fit its format version, ...), read only."""
    verdict = judge(directory)
    if verdict.refusal is None and (directory / "map" / CURRENT_FILE).is_file():
        try:
            load_map(directory / "map")
        except StorageError as exc:
            verdict.refusal = str(exc)
    return verdict


def accept_losses(directory: Path) -> Verdict:
    """Record that an operator accepts every loss the verdict on ``directory`` names (the
    map is then served normally); the verdict afterwards. A refused map is left as it is."""
    verdict = restore_verdict(directory)
    if verdict.refusal is None and verdict.losses:
        record_losses(directory, verdict.losses, accept=True)
        verdict = restore_verdict(directory)
    return verdict


def _check_service_file(directory: Path, out: MapCheck) -> dict[str, Any]:
    try:
        meta = read_service_file(directory)
        out.next_segment = int(meta.get("next_segment", 0))
        return meta
    except (StorageError, TypeError, ValueError) as exc:
        out.problems.append(str(exc))
        return {}


def _check_snapshots(directory: Path, out: MapCheck, meta: dict[str, Any]) -> None:
    map_dir = directory / "map"
    try:
        current = current_snapshot(map_dir).name if (map_dir / CURRENT_FILE).exists() else None
    except StorageError as exc:
        out.problems.append(str(exc))
        current = None
    out.current = current
    for path in snapshot_dirs(map_dir):
        snap = SnapshotCheck(path.name, current=path.name == current,
                             named_by_service_file=path.name == meta.get("snapshot"))
        try:
            snap.files = verify_snapshot(path)
        except StorageError as exc:
            snap.problem = str(exc)
            if snap.current:
                out.problems.append(f"the current snapshot is damaged: {exc}")
        out.snapshots.append(snap)
    # Snapshots present with neither CURRENT nor service.json naming one are unfinished
    # saves the restore removes (:func:`.durability.recover_current`): not damage.
    if current is None and not (map_dir / CURRENT_FILE).exists() and (
            meta.get("snapshot") is not None):
        out.problems.append(f"{map_dir / CURRENT_FILE}: missing although snapshot(s) "
                            f"{[s.name for s in out.snapshots]} are present and "
                            f"{SERVICE_FILE} names {meta.get('snapshot')!r}")


def _check_journal(directory: Path, out: MapCheck) -> None:
    journal = Journal(directory / "journal")
    for number in journal.segments():
        seg = SegmentCheck(number, replayed=number >= out.next_segment)
        path = journal.directory / segment_name(number)
        try:
            scan = scan_segment(path)
        except (StorageError, OSError) as exc:
            seg.problem = str(exc)
            out.problems.append(str(exc))
            out.segments.append(seg)
            continue
        seg.version, seg.records, seg.torn_bytes = scan.version, len(scan.records), \
            scan.torn_bytes
        seg.skipped = [(d.offset, d.size) for d in scan.damage if d.kind == "corrupt"]
        if seg.skipped and seg.replayed:
            out.problems.append(f"{path}: {len(seg.skipped)} damaged range(s) skipped "
                                f"({sum(n for _, n in seg.skipped)} bytes)")
        seg.invalid = [f"record {i}: {why}" for i, record in enumerate(scan.records)
                       if (why := record_problem(record)) is not None]
        if seg.invalid and seg.replayed:
            out.problems += [f"{path}: {why} (a replay skips it)" for why in seg.invalid]
        out.segments.append(seg)


def record_problem(record: bytes) -> str | None:
    """Why an intact journal record would not replay, as far as its content tells (a
    keyframe or camera put that does not decode: a pose covariance that is not one, a bad
    pose, ...); None when it would. The cameras a keyframe names are not checked here."""
    try:
        entry = msgpack.unpackb(record, raw=False)
        op = entry["op"]
        if op == WriteOp.KEYFRAME:
            put = wire.KeyframePut.decode(entry["payload"], REPLAY_LIMITS)
            if put.id != entry["id"]:
                return f"keyframe {entry['id']}: the put names keyframe {put.id}"
        elif op == WriteOp.CAMERA:
            wire.CameraPut.decode(entry["payload"], REPLAY_LIMITS)
        elif op != WriteOp.DELETE:
            return f"unknown op {op!r}"
    except wire.ProtocolError as exc:
        return f"{entry.get('op')} {entry.get('id')!r}: {exc.message}"
    except (ValueError, TypeError, KeyError, msgpack.UnpackException) as exc:
        return f"not a journal record ({type(exc).__name__}: {exc})"
    return None


def format_check(check: MapCheck) -> str:
    """A human-readable report of one map directory."""
    lines = [f"{check.directory}: {'DAMAGED' if check.damaged else 'ok'}"]
    if check.verdict:
        lines.append(f"  restore: {check.verdict['outcome']}"
                     + (f", missing keyframe ids {check.verdict['missing_keyframe_ids']}"
                        if check.verdict["missing_keyframe_ids"] else "")
                     + (f" ({len(check.verdict['accepted'])} loss(es) accepted)"
                        if check.verdict["accepted"] else ""))
        lines += [f"  note: {note}" for note in check.verdict["notes"]]
    lines.append(f"  CURRENT -> {check.current or '(missing)'}")
    for s in check.snapshots:
        marks = "".join([" [CURRENT]" if s.current else "",
                         f" [{SERVICE_FILE}]" if s.named_by_service_file else ""])
        state = f"ok, {s.files} files verified" if s.problem is None else f"DAMAGED: {s.problem}"
        lines.append(f"  snapshot {s.name}{marks}: {state}")
    lines.append(f"  journal (replayed from segment {check.next_segment}):")
    for g in check.segments:
        if g.problem is not None:
            lines.append(f"    {segment_name(g.number)}: DAMAGED: {g.problem}")
            continue
        note = "" if g.replayed else " (covered by the snapshot)"
        lines.append(f"    {segment_name(g.number)} v{g.version}: {g.records} good records, "
                     f"{len(g.skipped)} skipped, torn tail {g.torn_bytes} bytes{note}")
        lines += [f"      invalid {why}" for why in g.invalid]
    lines.append(f"  quarantine: {len(check.quarantine)} file(s)")
    lines += [f"    {name} ({size} bytes)" for name, size in check.quarantine]
    lines += [f"  problem: {p}" for p in check.problems]
    return "\n".join(lines)


def to_json(checks: list[MapCheck]) -> str:
    return json.dumps([c.to_dict() for c in checks], indent=1)
