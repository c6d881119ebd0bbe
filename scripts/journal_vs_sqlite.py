"""Put throughput and restore time of the map journal against SQLite in WAL mode, on this
machine: ``python scripts/journal_vs_sqlite.py [--records 500] [--bytes 60000]``.

Both stores make every record durable before the put is acknowledged (the journal: write and
fsync; SQLite: one transaction per record, ``synchronous=FULL``), both hold the record as one
opaque blob with its sequence number, and a restore reads every record back in order (the
journal also checks each record's CRC; SQLite its page checksums are not on by default, so it
reads without an integrity check unless ``--integrity-check`` adds ``PRAGMA quick_check``)."""

from __future__ import annotations

import argparse
import os
import sqlite3
import statistics
import tempfile
import time
import uuid
from pathlib import Path

from reloc_service.storage.journal import Journal


def journal_puts(directory: Path, payloads: list[bytes]) -> float:
    j = Journal(directory)
    j.identity = uuid.uuid4()
    j.open()
    start = time.perf_counter()
    for payload in payloads:
        j.append(payload)
    elapsed = time.perf_counter() - start
    j.close()
    return elapsed


def journal_restore(directory: Path) -> tuple[float, int]:
    start = time.perf_counter()
    n = sum(1 for _ in Journal(directory).replay())
    return time.perf_counter() - start, n


def sqlite_puts(path: Path, payloads: list[bytes]) -> float:
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("PRAGMA synchronous=FULL")
    db.execute("CREATE TABLE changes (seq INTEGER PRIMARY KEY, record BLOB NOT NULL)")
    start = time.perf_counter()
    for payload in payloads:
        db.execute("BEGIN")
        db.execute("INSERT INTO changes (record) VALUES (?)", (payload,))
        db.execute("COMMIT")
    elapsed = time.perf_counter() - start
    db.close()
    return elapsed


def sqlite_restore(path: Path, integrity_check: bool) -> tuple[float, int]:
    start = time.perf_counter()
    db = sqlite3.connect(path)
    if integrity_check:
        db.execute("PRAGMA quick_check").fetchall()
    n = sum(1 for _ in db.execute("SELECT seq, record FROM changes ORDER BY seq"))
    db.close()
    return time.perf_counter() - start, n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", type=int, default=500)
    parser.add_argument("--bytes", type=int, default=60_000,
                        help="bytes per record (a keyframe put with its JPEG is 30-100 kB)")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--integrity-check", action="store_true")
    args = parser.parse_args()
    payloads = [os.urandom(args.bytes) for _ in range(args.records)]
    rows: dict[str, list[tuple[float, float]]] = {"journal": [], "sqlite-wal": []}
    for _ in range(args.runs):
        with tempfile.TemporaryDirectory(dir=".") as tmp:
            put_s = journal_puts(Path(tmp) / "journal", payloads)
            restore_s, n = journal_restore(Path(tmp) / "journal")
            assert n == args.records
            rows["journal"].append((put_s, restore_s))
            put_s = sqlite_puts(Path(tmp) / "map.db", payloads)
            restore_s, n = sqlite_restore(Path(tmp) / "map.db", args.integrity_check)
            assert n == args.records
            rows["sqlite-wal"].append((put_s, restore_s))
    print(f"{args.records} records of {args.bytes} bytes, {args.runs} runs (median), "
          f"sqlite {sqlite3.sqlite_version}")
    for name, runs in rows.items():
        put_s = statistics.median(r[0] for r in runs)
        restore_s = statistics.median(r[1] for r in runs)
        print(f"{name:11s} puts {args.records / put_s:8.0f}/s ({1000 * put_s / args.records:.2f} "
              f"ms each)  restore {1000 * restore_s:8.1f} ms")


if __name__ == "__main__":
    main()
