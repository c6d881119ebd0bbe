"""Restore completeness: storage whose snapshots or journal disagree with the map is served
as degraded naming what it lacks, or refused by name; never another map's content.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .harness import (
    MAP_NAME,
    Arena,
    AttackService,
    Attempt,
    broke,
    clean,
    compare_held,
    held_ids,
    judge_code,
    put_acknowledged,
    register,
    running,
)

# -- restore completeness --------------------------------------------------------------------------
# Storage whose snapshots disagree with the journal or with the map: the map is served as
# degraded naming what it lacks, or refused by name; never another map's content.

def two_snapshot_storage(arena: Arena, name: str) -> tuple[AttackService, Path]:
    """A stopped service whose map ``lab`` has snapshot A (keyframes 0-3) and, after it,
    snapshot B (keyframes 0-7; each written by a SIGTERM), and map ``other`` (keyframes
    20-21) in a snapshot."""
    service = AttackService(arena.case_folder(name)).start()
    try:
        with service.client() as c:
            put_acknowledged(c, arena.scene, range(4))
        with service.client("other") as c:
            put_acknowledged(c, arena.scene, range(20, 22))
        service.restart("sigterm")
        with service.client() as c:
            put_acknowledged(c, arena.scene, range(4, 8))
    finally:
        service.stop("sigterm")
    return service, service.storage


def map_directory(storage: Path, name: str) -> Path:
    from ....service.map_dirs import map_dirname

    return storage / map_dirname(name)


@register("another-maps-snapshot", "storage",
          "another map's map/ directory (its snapshots) swapped into lab's: lab refused by "
          "name (STORAGE_ERROR), never served with the other map's keyframes; the other map "
          "still served")
def another_maps_snapshot(arena: Arena) -> list[Attempt]:
    from reloc_client.client import ServiceError

    service, storage = two_snapshot_storage(arena, "another-maps-snapshot")
    lab, other = map_directory(storage, MAP_NAME), map_directory(storage, "other")
    shutil.rmtree(lab / "map")
    shutil.copytree(other / "map", lab / "map")
    try:
        try:
            service.start()
            return [broke("lab answered status with another map's snapshot in place")]
        except ServiceError as exc:
            refusal = judge_code(f"lab: {exc.message[:100]}", exc.code.value,
                                 ["STORAGE_ERROR"])
        with service.client("other") as c:
            kept = compare_held("'other'", held_ids(c), {20, 21})
        return [Attempt(refusal.clean and kept.clean, f"{refusal.detail}; {kept.detail}")]
    finally:
        service.stop("sigterm")


@register("current-rolled-back", "storage",
          "map/CURRENT pointed back at the kept previous snapshot: lab served degraded, "
          "naming the keyframes the newer snapshot held (4-7) as missing")
def current_rolled_back(arena: Arena) -> list[Attempt]:
    service, storage = two_snapshot_storage(arena, "current-rolled-back")
    snapshots = map_directory(storage, MAP_NAME) / "map"
    current = (snapshots / "CURRENT").read_text().strip()
    older = sorted(p.name for p in (snapshots / "snapshots").iterdir()
                   if f"snapshots/{p.name}" != current)
    if not older:
        return [broke(f"no previous snapshot kept beside {current} (the case needs one)")]
    (snapshots / "CURRENT").write_text(f"snapshots/{older[-1]}\n")
    try:
        service.start()
        with service.client() as c:
            held = held_ids(c)
            status = c.status()
    finally:
        service.stop("sigterm")
    what = f"CURRENT {current} -> snapshots/{older[-1]}"
    missing = status.counters.get("restore_missing_keyframes")
    if held - set(range(8)):
        return [broke(f"{what}: served keyframes never put: {sorted(held - set(range(8)))}")]
    if not status.degraded or missing != len(set(range(8)) - held):
        return [broke(f"{what}: held {sorted(held)}, degraded {status.degraded!r}, "
                      f"restore_missing_keyframes = {missing}")]
    return [clean(f"{what}: held {sorted(held)}, degraded: {status.degraded[:90]}")]




#: Keyframes acknowledged (journaled) after snapshot B, killed before any other snapshot.
AFTER_SNAPSHOT = range(8, 10)


def journal_after_snapshot(arena: Arena, name: str) -> Path:
    """Storage of :func:`two_snapshot_storage` plus keyframes :data:`AFTER_SNAPSHOT`
    acknowledged in the journal after snapshot B, the service then killed (-9) so that no
    snapshot holds them; the storage is copied per attempt from the one made here."""
    service, storage = two_snapshot_storage(arena, name)
    service.start()
    try:
        with service.client() as c:
            put_acknowledged(c, arena.scene, AFTER_SNAPSHOT)
    finally:
        service.stop("kill9")
    return storage


def segment_after_snapshot(map_dir: Path) -> Path:
    """The journal segment holding the records after the snapshot (``next_segment`` of the
    map's service.json)."""
    from ....storage import journal

    first = json.loads((map_dir / "service.json").read_text())["next_segment"]
    return map_dir / "journal" / journal.segment_name(first)


def map_check(map_dir: Path) -> tuple[int, dict[str, Any]]:
    """``reloc map check --json`` of ``map_dir`` in a child process: exit code and report."""
    proc = subprocess.run([sys.executable, "-m", "reloc_service.cli.main", "map", "check",
                           "--json", str(map_dir)], capture_output=True, text=True,
                          timeout=120)
    try:
        [report] = json.loads(proc.stdout)
    except ValueError:
        report = {"stdout": proc.stdout[-300:], "stderr": proc.stderr[-300:]}
    return proc.returncode, report


def judge_segment_loss(arena: Arena, template: Path, name: str, kind: str,
                       damage: Callable[[Path], object]) -> Attempt:
    """``damage`` a copy of ``template``'s lab map: clean if ``reloc map check`` exits 1
    with loss ``kind``, and the service serves lab degraded (status names ``kind``) holding
    exactly snapshot B's keyframes 0-7, never more."""
    storage = arena.case_folder(name) / "storage"
    shutil.copytree(template, storage)
    map_dir = map_directory(storage, MAP_NAME)
    damage(map_dir)
    code, report = map_check(map_dir)
    kinds = [loss.get("kind") for loss in report.get("verdict", {}).get("losses", [])]
    with running(arena.case_folder(name), storage) as service, service.client() as c:
        held = held_ids(c)
        degraded = c.status().degraded
    what = f"{name}: map check exit {code} losses {kinds}; held {sorted(held)}"
    if held != set(range(8)):
        return broke(f"{what} (expected snapshot B's 0-7)")
    if code != 1 or kinds != [kind] or not degraded.startswith(f"degraded: {kind}"):
        return broke(f"{what}; status degraded {degraded[:80]!r} (expected {kind} in both)")
    return clean(f"{what}; status: {degraded[:80]}")


@register("journal-segment-lost", "storage",
          "the journal segment after the last snapshot (2 acknowledged keyframes) deleted, "
          "then emptied to 0 bytes: lab served degraded (missing_segment, empty_segment) with "
          "the snapshot's keyframes, reloc map check exit 1 with the same loss")
def journal_segment_lost(arena: Arena) -> list[Attempt]:
    template = journal_after_snapshot(arena, "journal-segment-lost")
    return [judge_segment_loss(arena, template, "segment-deleted", "missing_segment",
                               lambda d: segment_after_snapshot(d).unlink()),
            judge_segment_loss(arena, template, "segment-emptied", "empty_segment",
                               lambda d: segment_after_snapshot(d).write_bytes(b""))]
