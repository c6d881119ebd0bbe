"""Storage cases: a second service on the same storage, kill -9 (at rest and mid-snapshot),
damaged journal records, concurrent delete + put + train.
"""

from __future__ import annotations

import shutil
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import msgpack

from .harness import (
    MAP_NAME,
    READY_TIMEOUT_S,
    Arena,
    AttackService,
    Attempt,
    TinyScene,
    broke,
    clean,
    compare_held,
    held_ids,
    put_acknowledged,
    register,
    running,
    serve_command,
)

# -- storage -----------------------------------------------------------------------------------

@register("second-service", "storage",
          "a second reloc serve on the same storage while the first serves: refused (exit != 0) "
          "naming the holder's pid, nothing written; the first keeps every acknowledged "
          "keyframe, also after its restart")
def second_service(arena: Arena) -> list[Attempt]:
    folder = arena.case_folder("second-service")
    first = AttackService(folder / "first").start()
    try:
        with first.client() as c:
            acked = put_acknowledged(c, arena.scene, range(10))
        before = files_of(first.storage)
        second = AttackService(folder / "second", first.storage)
        with open(folder / "second.log", "wb") as log:
            proc = subprocess.run(serve_command(second.config), stdout=log,
                                  stderr=subprocess.STDOUT, timeout=READY_TIMEOUT_S)
        said = (folder / "second.log").read_text(errors="replace").strip()
        refused = (proc.returncode != 0 and f"pid {first.pid}" in said
                   and files_of(first.storage) == before)
        with first.client() as c:
            acked += put_acknowledged(c, arena.scene, range(10, 20))
        first.restart("sigterm")
        with first.client() as c:
            kept = compare_held("the first service after a restart", held_ids(c), set(acked))
    finally:
        first.stop("sigterm")
    verdict = (clean if refused and kept.clean else broke)(
        f"second service exit {proc.returncode}: {said.splitlines()[-1][:120] if said else ''}; "
        f"{kept.detail}")
    return [verdict]


def files_of(directory: Path) -> dict[str, bytes]:
    """Every file under ``directory`` (lock holder records too) by relative path."""
    return {p.relative_to(directory).as_posix(): p.read_bytes()
            for p in sorted(directory.rglob("*")) if p.is_file()}


@register("kill9-restart", "storage",
          "kill -9 right after the last acknowledgement, three times (no snapshots: the "
          "journal alone): every acknowledged keyframe is back after each restart")
def kill9_restart(arena: Arena) -> list[Attempt]:
    service = AttackService(arena.case_folder("kill9-restart")).start()
    acked: list[int] = []
    out = []
    try:
        for n in range(3):
            with service.client() as c:
                acked += put_acknowledged(c, arena.scene, range(6 * n, 6 * n + 6))
            attempt = kill9_and_compare(service, acked)
            out.append(attempt)
            if not attempt.clean:
                break
    finally:
        service.stop("sigterm")
    return out


def kill9_and_compare(service: AttackService, acked: Sequence[int]) -> Attempt:
    """kill -9 the service, start it again: clean if it holds exactly ``acked``."""
    what = f"kill -9 after {len(acked)} acknowledged"
    try:
        code = service.restart("kill9")
    except Exception as exc:  # the restart itself failed: what the attack found
        return broke(f"{what}, restart failed: {type(exc).__name__}: {exc}")
    with service.client() as c:
        return compare_held(f"{what} (exit {code})", held_ids(c), set(acked))


#: Journal records between snapshots in the mid-snapshot case: the 9th record (a camera and 8
#: keyframes) starts one, and the kill -9 follows the 8th keyframe's acknowledgement.
SNAPSHOT_EVERY = 8


@register("kill9-mid-snapshot", "storage",
          "kill -9 while a snapshot is being written (its directory without a manifest yet), "
          "the map's first and a later one: every acknowledged keyframe is back after the "
          "restart")
def kill9_mid_snapshot(arena: Arena) -> list[Attempt]:
    out = []
    for later in (False, True):
        folder = arena.case_folder(f"kill9-mid-snapshot-{'later' if later else 'first'}")
        service = AttackService(folder, snapshot_every=SNAPSHOT_EVERY).start()
        try:
            acked: list[int] = []
            if later:  # a first snapshot, complete: SIGTERM writes one before it exits
                with service.client() as c:
                    acked += put_acknowledged(c, arena.scene, range(100, 104))
                service.restart("sigterm")
            with service.client() as c:
                acked += put_acknowledged(c, arena.scene, range(SNAPSHOT_EVERY))
            partial = wait_partial_snapshot(service.storage / MAP_NAME)
            attempt = kill9_and_compare(service, acked)
            label = "a later snapshot" if later else "the first snapshot"
            out.append(Attempt(attempt.clean, f"{label} ({partial} incomplete at the kill): "
                                              f"{attempt.detail}"))
        finally:
            service.stop("sigterm")
    return out


def wait_partial_snapshot(map_dir: Path, timeout: float = 10.0) -> int:
    """Wait (polling every 5 ms) until a snapshot of ``map_dir`` is being written, so that a
    kill lands in the middle of it; the incomplete snapshots then (0 after ``timeout``)."""
    deadline = time.monotonic() + timeout
    while True:
        partial = partial_snapshots(map_dir)
        if partial or time.monotonic() > deadline:
            return partial
        time.sleep(0.005)


def partial_snapshots(map_dir: Path) -> int:
    """Snapshot directories of ``map_dir`` without their manifest (being written)."""
    snapshots = map_dir / "map" / "snapshots"
    if not snapshots.is_dir():
        return 0
    return sum(not (d / "manifest.json").exists() for d in snapshots.iterdir() if d.is_dir())


JOURNAL_IDS = range(6)


def journaled_storage(arena: Arena) -> Path:
    """A storage whose map holds camera cam0 and keyframes 0-5 in its journal only (no
    snapshot: the service was killed -9 after the acknowledgements); made once, copied by
    each attempt."""
    template = arena.folder / "journal-template"
    if not template.exists():
        service = AttackService(arena.folder / "journal-template-service", template).start()
        try:
            with service.client() as c:
                put_acknowledged(c, arena.scene, JOURNAL_IDS)
        finally:
            service.stop("kill9")
    return template


def journal_records(map_dir: Path) -> tuple[Path, bytes, list[tuple[int, int, int | None]]]:
    """The map's first journal segment, its bytes, and (payload offset, payload length,
    keyframe id or None) of each of its records."""
    from ....storage.journal import scan_segment

    [segment] = sorted((map_dir / "journal").glob("*.journal"))[:1]
    data = segment.read_bytes()
    rows, pos = [], 0
    for record in scan_segment(segment).records:
        offset = data.index(record, pos)
        op = msgpack.unpackb(record)
        rows.append((offset, len(record), op.get("id") if op.get("op") == "kf" else None))
        pos = offset + len(record)
    return segment, data, rows


#: The status counters that report damaged journal bytes (skipped or a torn tail).
DAMAGE_COUNTERS = ("restore_journal_skipped", "restore_journal_torn_bytes")


def restore_damaged(arena: Arena, name: str, damage: Callable[[Path], int | list[int]]
                    ) -> Attempt:
    """Copy the journaled storage, ``damage`` its map's journal (returns the keyframe ids it
    destroyed), start a service on it: clean if exactly those are missing and the map's status
    counters report the damage (:data:`DAMAGE_COUNTERS`)."""
    folder = arena.case_folder(name)
    storage = folder / "storage"
    shutil.copytree(journaled_storage(arena), storage)
    lost = damage(storage / MAP_NAME)
    lost = lost if isinstance(lost, list) else [lost]
    with running(folder, storage) as service, service.client() as c:
        held = held_ids(c)
        counters = c.status().counters
    verdict = compare_held(f"keyframe(s) {lost} destroyed, the rest", held, set(JOURNAL_IDS) - set(lost))
    reported = ", ".join(f"{k} = {counters.get(k, 0)}" for k in DAMAGE_COUNTERS)
    if verdict.clean and not any(counters.get(k) for k in DAMAGE_COUNTERS):
        return broke(f"{verdict.detail}, but not reported ({reported})")
    return Attempt(verdict.clean, f"{verdict.detail}; {reported}")


def flip_byte(segment: Path, offset: int) -> None:
    data = bytearray(segment.read_bytes())
    data[offset] ^= 0x10
    segment.write_bytes(bytes(data))


@register("journal-bit-flip", "storage",
          "one bit flipped in a mid-journal record's payload, then in another's length field: "
          "exactly that keyframe lost (of 6), the skip counted in status")
def journal_bit_flip(arena: Arena) -> list[Attempt]:
    from ....storage.journal import SYNC

    def in_payload(map_dir: Path) -> int:
        segment, _, rows = journal_records(map_dir)
        offset, size, kf_id = rows[3]
        flip_byte(segment, offset + size - 1)
        return int(kf_id)  # type: ignore[arg-type]

    def in_length(map_dir: Path) -> int:
        segment, data, rows = journal_records(map_dir)
        offset, _, kf_id = rows[4]
        frame = data.rindex(SYNC, 0, offset)
        flip_byte(segment, frame + len(SYNC) + 1)   # the second byte of the length field
        return int(kf_id)  # type: ignore[arg-type]

    return [restore_damaged(arena, "bit-flip-payload", in_payload),
            restore_damaged(arena, "bit-flip-length", in_length)]


@register("journal-zeroed-tail", "storage",
          "the journal's last record zeroed, then the last two: exactly those keyframes lost, "
          "the damaged bytes counted in status")
def journal_zeroed_tail(arena: Arena) -> list[Attempt]:
    from ....storage.journal import SYNC

    def zero_last(count: int) -> Callable[[Path], list[int]]:
        def damage(map_dir: Path) -> list[int]:
            segment, data, rows = journal_records(map_dir)
            first = data.rindex(SYNC, 0, rows[-count][0])
            segment.write_bytes(data[:first] + bytes(len(data) - first))
            return [int(r[2]) for r in rows[-count:] if r[2] is not None]
        return damage

    return [restore_damaged(arena, f"zeroed-tail-{n}", zero_last(n)) for n in (1, 2)]


@register("concurrent-delete-put-train", "storage",
          "deletes, puts and training of one map at once, then kill -9 and SIGTERM restarts: "
          "exactly the acknowledged changes held, training ends or is refused by name")
def concurrent_delete_put_train(arena: Arena) -> list[Attempt]:
    service = AttackService(arena.case_folder("concurrent"), snapshot_every=6).start()
    out = []
    try:
        with service.client() as c:
            put_acknowledged(c, arena.scene, range(10))
        expected = set(range(10))
        for n, kind in enumerate(("kill9", "sigterm")):
            base = 100 * (n + 1)
            problems, expected = concurrent_round(service, arena.scene, expected, base)
            with service.client() as c:
                live = compare_held("while serving", held_ids(c), expected)
            code = service.restart(kind)
            with service.client() as c:
                after = compare_held(f"after {kind} (exit {code})", held_ids(c), expected)
            ok = not problems and live.clean and after.clean
            out.append(Attempt(ok, "; ".join([*problems, live.detail, after.detail])))
    finally:
        service.stop("sigterm")
    return out


def concurrent_round(service: AttackService, scene: TinyScene, held: set[int], base: int
                     ) -> tuple[list[str], set[int]]:
    """Delete half of ``held``, put 8 new keyframes from ``base`` and train twice, in three
    threads; the problems seen and the ids that must now be held."""
    from reloc_client.client import ServiceError

    doomed = sorted(held)[: len(held) // 2]
    new = list(range(base, base + 8))
    problems: list[str] = []

    def deleter() -> None:
        with service.client() as c:
            for kf_id in doomed:
                c.remove_keyframe(kf_id, wait=True)

    def putter() -> None:
        with service.client() as c:
            put_acknowledged(c, scene, new)

    def trainer() -> None:
        with service.client() as c:
            for _ in range(2):
                try:
                    c.train(wait=True, timeout=120)
                except ServiceError as exc:   # a named refusal (e.g. BUSY) is an answer
                    if exc.code.value == "INTERNAL":
                        raise

    def guarded(fn: Callable[[], None]) -> Callable[[], None]:
        def run() -> None:
            try:
                fn()
            except Exception as exc:  # each thread's failure is a finding of the round
                problems.append(f"{fn.__name__}: {type(exc).__name__}: {exc}")
        return run

    threads = [threading.Thread(target=guarded(f)) for f in (deleter, putter, trainer)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)
    problems += [f"{t.name} hangs" for t in threads if t.is_alive()]
    return problems, (held - set(doomed)) | set(new)


