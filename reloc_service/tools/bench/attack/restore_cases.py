"""Restore completeness: storage whose snapshots or journal disagree with the map is served
as degraded naming what it lacks, or refused by name; never another map's content.
"""

from __future__ import annotations

import shutil
from pathlib import Path

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
)

# -- restore completeness --------------------------------------------------------------------------
# Storage whose snapshots disagree with the journal or with the map: the map is served as
# degraded naming what it lacks, or refused by name; never another map's content. Cases still
# to add here: a deleted or emptied journal segment.

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
    from ....service.durability import map_dirname

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


